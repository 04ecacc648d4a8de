//! Row gather with a scatter-add backward, as a Burn backend extension.
//!
//! The trainer gathers the rows of the visible anchors (and of their k nearest neighbours) from
//! every per-anchor tensor at every step: tens of thousands of indices. Burn's `select` on the
//! ndarray backend copies and scatters row by row through dynamic-rank views (≈ 1 µs per index),
//! which made those gathers the most expensive part of a CPU training step. Here the ndarray
//! implementation copies contiguous rows directly; the Cube (wgpu) implementation is Burn's own
//! `select` / `select_assign(Add)`, already device kernels.

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
        let device = values.device();
        let values = <NdArray as HostIo>::read_floats(values);
        let index = <NdArray as HostIo>::read_indices(index);
        let mut out = vec![0.0f32; rows * w];
        // Sequential in index order: repeated indices accumulate deterministically.
        for (m, &i) in index.iter().enumerate() {
            let i = i as usize;
            assert!(
                i < rows,
                "scatter_add_rows: index {i} out of range for {rows} rows"
            );
            for (o, &v) in out[i * w..(i + 1) * w]
                .iter_mut()
                .zip(&values[m * w..(m + 1) * w])
            {
                *o += v;
            }
        }
        NdArray::float_from_data(TensorData::new(out, [rows, w]), &device)
    }
}

impl RowGatherBackend for burn::backend::Cube {
    fn gather_rows(table: FloatTensor<Self>, index: IntTensor<Self>) -> FloatTensor<Self> {
        Self::float_select(table, 0, index)
    }

    fn scatter_add_rows(
        values: FloatTensor<Self>,
        index: IntTensor<Self>,
        rows: usize,
    ) -> FloatTensor<Self> {
        let w = values.shape()[1];
        let device = values.device();
        let zeros = Self::float_zeros([rows, w].into(), &device, burn::tensor::FloatDType::F32);
        Self::float_select_assign(zeros, 0, index, values, burn::tensor::IndexingUpdateOp::Add)
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
}

/// `table[index]` along the first dimension for a [N, W] tensor, differentiable with respect to
/// `table` (any backend, with or without autodiff).
pub fn gather_rows(table: Tensor<2>, index: Tensor<1, Int>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as RowGatherBackend>::gather_rows(
        table.into_dispatch(),
        index.into_dispatch(),
    ))
}
