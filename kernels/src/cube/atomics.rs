//! Which float accumulation the backward uses: native f32 atomic add where the device offers it
//! (Vulkan with VK_EXT_shader_atomic_float, CUDA, Metal), a compare-and-swap loop otherwise.

use std::cell::Cell;

use cubecl::ir::features::AtomicUsage;
use cubecl::ir::{ElemType, FloatKind, Type};

thread_local! {
    static FORCE_COMPARE_AND_SWAP: Cell<bool> = const { Cell::new(false) };
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
