//! Row scatter-add on the device: `into[index[m], c] += values[m, c]`, one unit per (m, c), with
//! float atomics (or the compare-and-swap fallback, `atomics::accumulate`).
//!
//! Burn's `select_assign(.., Add)` on CubeCL runs one unit per element of the *other*
//! dimensions, each walking all M indices in order: for a [N] table that is a single unit doing
//! M dependent read-modify-writes (80k per densification statistic and step), for the [N, W]
//! gradient of a row gather W units. Here all M·W additions run at once; repeated indices meet in
//! the atomics, so the order of their additions (and the last bits of a sum) is the GPU's, not
//! the index order the CPU twin keeps.

use burn::tensor::DType;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use cubecl::calculate_cube_count_elemwise;
use cubecl::prelude::*;

use super::atomics::{accumulate, native_float_add};
use super::buffers::fresh_f32;

#[cube(launch)]
fn add_rows_kernel(
    values: &Tensor<f32>,
    index: &Tensor<i32>,
    width: u32,
    rows: u32,
    native: &mut Tensor<Atomic<f32>>,
    bits: &mut Tensor<Atomic<u32>>,
    #[comptime] native_float_atomics: bool,
) {
    let i = ABSOLUTE_POS;
    if i >= values.len() {
        terminate!();
    }
    let w = width as usize;
    let row = index[i / w];
    // Indices come from the trainer's own tables; the CPU twin asserts the range, a kernel
    // cannot, so one outside it is skipped rather than written out of bounds.
    if row >= 0 && (row as u32) < rows {
        accumulate(
            native,
            bits,
            row as usize * w + i % w,
            values[i],
            native_float_atomics,
        );
    }
}

/// `into` [N, W] with `values` [M, W] added at rows `index` [M] (an int tensor of any width).
/// Writes into `into`'s buffer when nothing else holds it, else into a copy.
pub fn add_rows_at(into: CubeTensor, index: CubeTensor, values: CubeTensor) -> CubeTensor {
    for t in [&into, &values] {
        assert_eq!(t.dtype, DType::F32, "add_rows_at takes float32 tensors");
    }
    let shape = into.meta.shape().to_vec();
    assert_eq!(shape.len(), 2, "add_rows_at expects an [N, W] table");
    let (n, w) = (shape[0], shape[1]);
    let m = index.meta.num_elements();
    assert_eq!(
        values.meta.shape().to_vec(),
        vec![m, w],
        "add_rows_at: values are not [M, W] for M indices and the table's W"
    );
    let index = if index.dtype == DType::I32 {
        index
    } else {
        burn_cubecl::kernel::cast(index, DType::I32)
    };
    let index = into_contiguous(index);
    let values = into_contiguous(values);
    let into = into_contiguous(into);
    let out = if into.can_mut() { into } else { into.copy() };
    if m == 0 || w == 0 {
        return out;
    }
    let client = out.client.clone();
    let native = native_float_add(&client);
    // The accumulator is bound once, as f32 or as u32 bits; the other binding gets a stand-in.
    let stand_in = fresh_f32(&out, vec![1]);
    let (as_float, as_bits) = if native {
        (out.clone(), stand_in)
    } else {
        (stand_in, out.clone())
    };
    let cube_dim = CubeDim::new_1d(256);
    let count = calculate_cube_count_elemwise(&client, m * w, cube_dim);
    add_rows_kernel::launch(
        &client,
        count,
        cube_dim,
        values.into_tensor_arg(),
        index.into_tensor_arg(),
        w as u32,
        n as u32,
        as_float.into_tensor_arg(),
        as_bits.into_tensor_arg(),
        native,
    );
    out
}
