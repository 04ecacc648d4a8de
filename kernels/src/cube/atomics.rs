//! Which float accumulation the backward (and the row scatter, `scatter.rs`) uses: native f32
//! atomic add where the device offers it (Vulkan with VK_EXT_shader_atomic_float, CUDA, Metal),
//! a compare-and-swap loop otherwise; and whether the compositing backward first sums each
//! Gaussian's gradient over a subgroup.

use std::cell::Cell;

use cubecl::ir::features::{AtomicUsage, Plane};
use cubecl::ir::{ElemType, FloatKind, Type};
use cubecl::prelude::*;

thread_local! {
    static FORCE_COMPARE_AND_SWAP: Cell<bool> = const { Cell::new(false) };
    static FORCE_PER_PIXEL_ATOMICS: Cell<bool> = const { Cell::new(false) };
}

/// Test hook: accumulate with the compare-and-swap fallback even where float atomics exist, so
/// both paths are tested on one device. Per thread, like `buffers::poison_fresh_buffers`.
pub fn force_compare_and_swap(on: bool) {
    FORCE_COMPARE_AND_SWAP.set(on);
}

/// Whether the backward accumulates with native float atomic adds on this client.
pub fn native_float_add(client: &cubecl::client::Client) -> bool {
    !FORCE_COMPARE_AND_SWAP.get()
        && client
            .properties()
            .atomic_type_usage(Type::atomic(ElemType::Float(FloatKind::F32)))
            .contains(AtomicUsage::Add)
}

/// How the compositing backward adds a (pixel, Gaussian) pair's gradient to the Gaussian's
/// splat gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GradientAccumulation {
    /// One atomic per pair and column: 256 pixels of a tile hitting the same Gaussian's 9
    /// entries at once serialise on them (18.5 of the 24.8 ms of a 1M @ 1080p forward+backward
    /// on an H100, docs/benchmarks.md).
    PerPixel,
    /// Each column summed over the subgroup (32 pixels on NVIDIA) first, then one atomic per
    /// subgroup, as gsplat's and Brush's backwards do. Needs subgroup arithmetic, which CubeCL's
    /// wgpu runtime offers on GPU adapters but not on CPU ones (lavapipe, what CI has).
    SubgroupSum,
}

/// Test hook: `PerPixel` accumulation even where subgroup sums exist, so both paths run on one
/// device. Per thread, like `force_compare_and_swap`.
pub fn force_per_pixel_atomics(on: bool) {
    FORCE_PER_PIXEL_ATOMICS.set(on);
}

/// The accumulation the compositing backward uses on this client. `ACAGS_SUBGROUP_SUMS=0` turns
/// the subgroup sums off for the process, so one binary times both (scripts/gpu_bench.sh).
pub fn gradient_accumulation(client: &cubecl::client::Client) -> GradientAccumulation {
    let switched_off = std::env::var("ACAGS_SUBGROUP_SUMS").as_deref() == Ok("0");
    if !FORCE_PER_PIXEL_ATOMICS.get()
        && !switched_off
        && client.properties().features.plane.contains(Plane::Ops)
    {
        GradientAccumulation::SubgroupSum
    } else {
        GradientAccumulation::PerPixel
    }
}

/// Adds `value` to entry `index` of an f32 buffer: a native float atomic add, or a
/// compare-and-swap loop on the bits (the same buffer bound as u32; the other binding is a
/// stand-in, since one buffer may not be bound twice for writing).
#[cube]
pub(crate) fn accumulate(
    native: &mut Tensor<Atomic<f32>>,
    bits: &mut Tensor<Atomic<u32>>,
    index: usize,
    value: f32,
    #[comptime] native_float_atomics: bool,
) {
    if native_float_atomics {
        native[index].fetch_add(value);
    } else {
        let mut old = bits[index].load();
        loop {
            let new = u32::reinterpret(f32::reinterpret(old) + value);
            // Vulkan's and CUDA's compare-exchange are strong: an unchanged value means it swapped.
            let seen = bits[index].compare_exchange_weak(old, new);
            if seen == old {
                break;
            }
            old = seen;
        }
    }
}
