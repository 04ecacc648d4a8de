//! Row gather with a scatter-add backward, and an accumulating scatter-add, as a Burn backend
//! extension.
//!
//! The trainer gathers the rows of the visible anchors (and of their k nearest neighbours) from
//! every per-anchor tensor at every step: tens of thousands of indices. Burn's `select` on the
//! ndarray backend copies and scatters row by row through dynamic-rank views (≈ 1 µs per index),
//! which made those gathers the most expensive part of a CPU training step. Here the ndarray
//! implementation copies contiguous rows directly; the Cube (wgpu) implementation gathers with
//! Burn's own `select` and scatters with the atomic kernel of `cube/scatter.rs` (Burn's
//! `select_assign` walks the indices serially on the device). The trainer's statistics on the
//! device (densification, AAC importance) add each step's contributions into large tables
//! ([N·K·T] rows) with [`add_rows_at`], which on ndarray adds in place into the table's buffer
//! instead of walking the index through a view per element as `select_assign` does.

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::FloatTensorOps;

use crate::backend::HostIo;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Int, Tensor, TensorData};
use rayon::prelude::*;

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait RowGatherBackend: Backend {
    /// Rows `index` [M] of `table` [N, W] → [M, W]. Indices must be < N.
    fn gather_rows(table: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self>;

    /// The VJP of [`Self::gather_rows`]: a [rows, W] zero tensor with `values` [M, W] added at
    /// rows `index` (repeated indices accumulate).
    fn scatter_add_rows(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self>;

    /// `into` [N, W] with `values` [M, W] added at rows `index` [M] (repeated indices
    /// accumulate). On the CPU in index order: the same f32 additions in the same order as
    /// `select_assign(0, index, values, Add)`. On CubeCL in the order the atomics meet, so a
    /// repeated index's sum may differ in its last bits from run to run. Not differentiable (for
    /// gathered statistics).
    fn add_rows_at(
        into: FloatTensor<Self>,
        index: IntTensor<Self>,
        values: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

impl RowGatherBackend for NdArray {
    fn gather_rows(table: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        let shape = table.shape();
        assert_eq!(shape.num_dims(), 2, "gather_rows expects a [N, W] table");
        let (n, w) = (shape[0], shape[1]);
        let device = table.device();
        let index = <NdArray as HostIo>::read_indices(index);
        let mut out = vec![0.0f32; index.len() * w];
        // Rows straight out of the table's storage: the tables are the model's parameters,
        // shared, so reading them out first copied the whole table (the [N, T·C_T] time
        // features: ~18 MB per gather at 14k anchors) to use a fraction of it.
        if w > 0 {
            crate::backend::with_floats(table, |values| {
                out.par_chunks_mut(w).zip(&index).for_each(|(row, &i)| {
                    let i = i as usize;
                    assert!(i < n, "gather_rows: index {i} out of range for {n} rows");
                    row.copy_from_slice(&values[i * w..(i + 1) * w]);
                })
            });
        }
        NdArray::float_from_data(TensorData::new(out, [index.len(), w]), &device)
    }

    fn scatter_add_rows(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        let shape = values.shape();
        assert_eq!(
            shape.num_dims(),
            2,
            "scatter_add_rows expects [M, W] values"
        );
        let w = shape[1];
        let zeros = NdArray::float_from_data(
            TensorData::new(vec![0.0f32; rows * w], [rows, w]),
            &values.device(),
        );
        // Into zeros in index order: repeated indices accumulate deterministically.
        Self::add_rows_at(zeros, index, values)
    }

    fn add_rows_at(
        into: FloatTensor<Self>,
        index: IntTensor<Self>,
        values: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = into.shape();
        assert_eq!(shape.num_dims(), 2, "add_rows_at expects an [N, W] table");
        let (n, w) = (shape[0], shape[1]);
        let index = <NdArray as HostIo>::read_indices(index);
        let values_shape = values.shape();
        assert!(
            values_shape.num_dims() == 2 && values_shape[0] == index.len() && values_shape[1] == w,
            "add_rows_at: values are not [M, W] for M indices and the table's W"
        );
        let device = into.device();
        // The table's own buffer when nothing else holds it (the statistics are owned by the
        // trainer alone), so the step touches M rows instead of copying N.
        let mut out = <NdArray as HostIo>::read_floats(into);
        crate::backend::with_floats(values, |values| {
            // Sequential in index order: the order of `select_assign`'s additions.
            for (m, &i) in index.iter().enumerate() {
                let i = i as usize;
                assert!(i < n, "add_rows_at: index {i} out of range for {n} rows");
                for (o, &v) in out[i * w..(i + 1) * w]
                    .iter_mut()
                    .zip(&values[m * w..(m + 1) * w])
                {
                    *o += v;
                }
            }
        });
        NdArray::float_from_data(TensorData::new(out, [n, w]), &device)
    }
}

impl RowGatherBackend for burn::backend::Cube {
    fn gather_rows(table: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        Self::float_select(table, 0, index)
    }

    // Not Burn's `select_assign(Add)`: on CubeCL it walks the indices serially in one unit per
    // column (`cube/scatter.rs`); this runs one unit per added element.
    fn scatter_add_rows(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, inner_int, register};
        let client = values.client.clone();
        let values = inner_float(values);
        let w = values.meta.shape()[1];
        let zeros = crate::cube::buffers::zeros_f32(&values, vec![rows, w]);
        let out = crate::cube::scatter::add_rows_at(zeros, inner_int(index), values);
        register(&client, out)
    }

    fn add_rows_at(
        into: FloatTensor<Self>,
        index: IntTensor<Self>,
        values: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, inner_int, register};
        let client = into.client.clone();
        let out = crate::cube::scatter::add_rows_at(
            inner_float(into),
            inner_int(index),
            inner_float(values),
        );
        register(&client, out)
    }
}

#[derive(Debug)]
struct GatherRowsBackward;

impl<B: RowGatherBackend> Backward<B, 1> for GatherRowsBackward {
    type State = (IntTensor<B>, usize);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (index, rows) = ops.state;
        let [parent] = ops.parents;
        if let Some(node) = parent {
            grads.register::<B>(node.id, B::scatter_add_rows(grad, index, rows));
        }
    }
}

impl<B: RowGatherBackend, C: CheckpointStrategy> RowGatherBackend for Autodiff<B, C> {
    fn gather_rows(table: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        let (table, node) = table.into_parts();
        let rows = table.shape()[0];
        let out = B::gather_rows(table, index.clone());
        match GatherRowsBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((index, rows), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn scatter_add_rows(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        // Only used as a backward: not differentiable itself.
        Self::from_inner(B::scatter_add_rows(Self::inner(values), index, rows))
    }

    fn add_rows_at(
        into: FloatTensor<Self>,
        index: IntTensor<Self>,
        values: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        // Statistics, not differentiable: the result leaves the graph.
        Self::from_inner(B::add_rows_at(
            Self::inner(into),
            index,
            Self::inner(values),
        ))
    }
}

/// `table[index]` along the first dimension for a [N, W] tensor, differentiable with respect to
/// `table` (any backend, with or without autodiff).
pub fn gather_rows(table: Tensor<2>, index: Tensor<1, Int>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as RowGatherBackend>::gather_rows(
        table.into_dispatch(),
        index.into_dispatch(),
    ))
}

/// `into` [N, W] with `values` [M, W] added at rows `index` [M] (repeated indices accumulate: in
/// index order on the CPU, in the atomics' order on a GPU); not differentiable: the result is a
/// constant of any autodiff graph.
pub fn add_rows_at(into: Tensor<2>, index: Tensor<1, Int>, values: Tensor<2>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as RowGatherBackend>::add_rows_at(
        into.into_dispatch(),
        index.into_dispatch(),
        values.into_dispatch(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::ops::IntTensorOps;

    fn address(t: &FloatTensor<NdArray>) -> usize {
        crate::backend::with_floats(t.clone(), |v| v.as_ptr() as usize)
    }

    /// The trainer's statistics rely on it: a table nothing else holds is added to in its own
    /// buffer (no copy of all N rows per call), a shared one is not touched.
    #[test]
    fn add_rows_at_adds_into_a_unique_tables_own_buffer_on_ndarray() {
        let device = Default::default();
        let table = || NdArray::float_from_data(TensorData::new(vec![1.0f32; 12], [6, 2]), &device);
        let index = || NdArray::int_from_data(TensorData::new(vec![1i64, 4, 1], [3]), &device);
        let values = || {
            let v = vec![0.5f32, 0.25, 2.0, 3.0, 0.5, 0.25];
            NdArray::float_from_data(TensorData::new(v, [3, 2]), &device)
        };
        let expected = [1.0, 1.0, 2.0, 1.5, 1.0, 1.0, 1.0, 1.0, 3.0, 4.0, 1.0, 1.0];

        let unique = table();
        let before = address(&unique);
        let out = NdArray::add_rows_at(unique, index(), values());
        assert_eq!(address(&out), before, "a unique table is added to in place");
        assert_eq!(crate::backend::with_floats(out, |v| v.to_vec()), expected);

        let shared = table();
        let out = NdArray::add_rows_at(shared.clone(), index(), values());
        assert_ne!(address(&out), address(&shared), "a shared table is copied");
        assert_eq!(
            crate::backend::with_floats(shared, |v| v.to_vec()),
            [1.0; 12]
        );
        assert_eq!(crate::backend::with_floats(out, |v| v.to_vec()), expected);
    }
}
