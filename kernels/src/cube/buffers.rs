//! Device buffers of the kernels. Fresh buffers come uninitialised from the allocator (often a
//! reused allocation): no kernel may assume they hold zeros. Tests check that by asking for every
//! fresh buffer to be filled with garbage first ([`poison_fresh_buffers`]) and comparing results.

use std::cell::Cell;

use burn::tensor::DType;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

thread_local! {
    static POISON: Cell<bool> = const { Cell::new(false) };
}

/// The bit pattern poisoned buffers hold: a NaN as f32, a huge count or index as u32.
pub const POISON_BITS: u32 = 0xFFBA_DBAD;

/// Test hook: when on, every buffer the rasterizer kernels allocate is filled with
/// [`POISON_BITS`] before use, so a kernel that reads memory it did not write shows up as a
/// changed result. Per thread (kernels launch from the thread that calls the rasterizer, so
/// parallel tests do not see each other's setting); off by default (it costs a fill per buffer).
pub fn poison_fresh_buffers(on: bool) {
    POISON.set(on);
}

#[cube(launch)]
fn fill_kernel(buffer: &mut Tensor<u32>, value: u32) {
    let i = ABSOLUTE_POS;
    if i < buffer.len() {
        buffer[i] = value;
    }
}

/// Writes `bits` into every 32-bit word of `tensor` (f32 or u32 storage).
pub(crate) fn fill_words(tensor: &CubeTensor, bits: u32) {
    let n = tensor.meta.num_elements();
    if n == 0 {
        return;
    }
    debug_assert_eq!(tensor.dtype.size(), 4);
    let cube_dim = CubeDim::new_1d(256);
    fill_kernel::launch(
        &tensor.client,
        cubecl::calculate_cube_count_elemwise(&tensor.client, n, cube_dim),
        cube_dim,
        tensor.clone().into_tensor_arg(),
        bits,
    );
}

fn fresh(like: &CubeTensor, shape: Vec<usize>, dtype: DType) -> CubeTensor {
    let t = empty_device_dtype(like.client.clone(), like.device.clone(), shape.into(), dtype);
    if POISON.get() {
        fill_words(&t, POISON_BITS);
    }
    t
}

/// An uninitialised u32 tensor of `shape` on `like`'s device.
pub(crate) fn fresh_u32(like: &CubeTensor, shape: &[usize]) -> CubeTensor {
    fresh(like, shape.to_vec(), DType::U32)
}

/// An uninitialised f32 tensor of `shape` on `like`'s device.
pub(crate) fn fresh_f32(like: &CubeTensor, shape: Vec<usize>) -> CubeTensor {
    fresh(like, shape, DType::F32)
}

/// A zero-filled f32 tensor of `shape` (accumulators).
pub(crate) fn zeros_f32(like: &CubeTensor, shape: Vec<usize>) -> CubeTensor {
    let t = fresh_f32(like, shape);
    fill_words(&t, 0);
    t
}
