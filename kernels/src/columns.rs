//! A column range of a [R, W] tensor, with a zero-padding backward, and two tables side by side,
//! with a column-split backward, as Burn backend extensions.
//!
//! The decode and spawn split their tensors by columns at every step (the covariance output into
//! scales and rotation, the motion into translation and rotation, the gates, the scales). On
//! ndarray Burn's `slice` copies a column range through a dynamic-rank element iterator, and its
//! backward assigns into a zero tensor the same way: measured at ~7.6 % of a CPU training step's
//! samples (`perf`, default config, dynamic phase). Here the ndarray implementation copies row
//! segments; the Cube (wgpu) implementation is Burn's own `slice` / `slice_assign`, already
//! device kernels. The values are copies either way, so results are the same to the bit.
//!
//! `concat_columns` replaces `Tensor::cat(vec![a, b], 1)` of the decode's inputs, gates and
//! scales for the same reason on the way back: Burn's `cat` backward cuts the gradient with that
//! same element-iterator `slice`, on the step's thread (~3 % of an ACA-GS step's samples, `perf`,
//! issue 21).

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use std::ops::Range;

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Slice, Tensor, TensorData};
use rayon::prelude::*;

use crate::backend::HostIo;

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait ColumnSliceBackend: Backend {
    /// Columns `start..end` of `table` [R, W] → [R, end − start]. Needs start ≤ end ≤ W.
    fn slice_columns(table: FloatTensor<Self>, start: usize, end: usize) -> FloatTensor<Self>;

    /// The VJP of [`Self::slice_columns`]: `values` [R, w] placed at columns `start..start + w`
    /// of a [R, width] zero tensor.
    fn pad_columns(values: FloatTensor<Self>, width: usize, start: usize) -> FloatTensor<Self>;

    /// `left` [R, a] and `right` [R, b] side by side → [R, a + b].
    fn concat_columns(left: FloatTensor<Self>, right: FloatTensor<Self>) -> FloatTensor<Self>;
}

fn dims2(shape: &burn::tensor::Shape, what: &str) -> (usize, usize) {
    assert_eq!(shape.num_dims(), 2, "{what} expects a [R, W] tensor");
    (shape[0], shape[1])
}

/// Row by row, `width` values from column `from` of `src` (rows of `sw`) to column `to` of `dst`
/// (rows of `dw`); both hold the same number of rows, `dw` and `sw` are > 0.
fn copy_segments(
    src: &[f32],
    sw: usize,
    from: usize,
    dst: &mut [f32],
    dw: usize,
    to: usize,
    width: usize,
) {
    dst.par_chunks_mut(dw)
        .zip(src.par_chunks(sw))
        .with_min_len(256)
        .for_each(|(d, s)| d[to..to + width].copy_from_slice(&s[from..from + width]));
}

impl ColumnSliceBackend for NdArray {
    fn slice_columns(table: FloatTensor<Self>, start: usize, end: usize) -> FloatTensor<Self> {
        let (rows, w) = dims2(&table.shape(), "slice_columns");
        assert!(
            start <= end && end <= w,
            "slice_columns: columns {start}..{end} outside 0..{w}"
        );
        let device = table.device();
        let out_w = end - start;
        let mut out = vec![0.0f32; rows * out_w];
        if out_w > 0 && rows > 0 {
            // Straight out of the storage when it is contiguous (the usual case): no copy of
            // the whole table first.
            crate::backend::with_floats(table, |values| {
                copy_segments(values, w, start, &mut out, out_w, 0, out_w)
            });
        }
        NdArray::float_from_data(TensorData::new(out, [rows, out_w]), &device)
    }

    fn pad_columns(values: FloatTensor<Self>, width: usize, start: usize) -> FloatTensor<Self> {
        let (rows, w) = dims2(&values.shape(), "pad_columns");
        assert!(
            start + w <= width,
            "pad_columns: {w} columns at {start} do not fit in {width}"
        );
        let device = values.device();
        let mut out = vec![0.0f32; rows * width];
        if w > 0 && rows > 0 {
            let values = <NdArray as HostIo>::read_floats(values);
            copy_segments(&values, w, 0, &mut out, width, start, w);
        }
        NdArray::float_from_data(TensorData::new(out, [rows, width]), &device)
    }

    fn concat_columns(left: FloatTensor<Self>, right: FloatTensor<Self>) -> FloatTensor<Self> {
        let (rows, a) = dims2(&left.shape(), "concat_columns");
        let (right_rows, b) = dims2(&right.shape(), "concat_columns");
        assert_eq!(
            rows, right_rows,
            "concat_columns: {rows} rows on the left, {right_rows} on the right"
        );
        let device = left.device();
        let width = a + b;
        let mut out = vec![0.0f32; rows * width];
        if rows > 0 && width > 0 {
            for (part, w, at) in [(left, a, 0), (right, b, a)] {
                if w > 0 {
                    crate::backend::with_floats(part, |values| {
                        copy_segments(values, w, 0, &mut out, width, at, w)
                    });
                }
            }
        }
        NdArray::float_from_data(TensorData::new(out, [rows, width]), &device)
    }
}

impl ColumnSliceBackend for burn::backend::Cube {
    fn slice_columns(table: FloatTensor<Self>, start: usize, end: usize) -> FloatTensor<Self> {
        let (rows, _) = dims2(&table.shape(), "slice_columns");
        Self::float_slice(table, &[Slice::from(0..rows), Slice::from(start..end)])
    }

    fn pad_columns(values: FloatTensor<Self>, width: usize, start: usize) -> FloatTensor<Self> {
        let (rows, w) = dims2(&values.shape(), "pad_columns");
        let device = values.device();
        let zeros = Self::float_zeros([rows, width].into(), &device, burn::tensor::FloatDType::F32);
        Self::float_slice_assign(
            zeros,
            &[Slice::from(0..rows), Slice::from(start..start + w)],
            values,
        )
    }

    fn concat_columns(left: FloatTensor<Self>, right: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::float_cat(vec![left, right], 1)
    }
}

#[derive(Debug)]
struct SliceColumnsBackward;

impl<B: ColumnSliceBackend> Backward<B, 1> for SliceColumnsBackward {
    /// (the table's width, the first column).
    type State = (usize, usize);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (width, start) = ops.state;
        let [parent] = ops.parents;
        if let Some(node) = parent {
            grads.register::<B>(node.id, B::pad_columns(grad, width, start));
        }
    }
}

#[derive(Debug)]
struct ConcatColumnsBackward;

impl<B: ColumnSliceBackend> Backward<B, 2> for ConcatColumnsBackward {
    /// (the left table's width, the right table's).
    type State = (usize, usize);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (a, b) = ops.state;
        let [left, right] = ops.parents;
        // In parent order, as Burn's `cat` registers them (the same sums where a tensor is both).
        if let Some(node) = left {
            grads.register::<B>(node.id, B::slice_columns(grad.clone(), 0, a));
        }
        if let Some(node) = right {
            grads.register::<B>(node.id, B::slice_columns(grad, a, a + b));
        }
    }
}

impl<B: ColumnSliceBackend, C: CheckpointStrategy> ColumnSliceBackend for Autodiff<B, C> {
    fn slice_columns(table: FloatTensor<Self>, start: usize, end: usize) -> FloatTensor<Self> {
        let (table, node) = table.into_parts();
        let width = table.shape()[1];
        let out = B::slice_columns(table, start, end);
        match SliceColumnsBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((width, start), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn pad_columns(values: FloatTensor<Self>, width: usize, start: usize) -> FloatTensor<Self> {
        // Only used as a backward: not differentiable itself.
        Self::from_inner(B::pad_columns(Self::inner(values), width, start))
    }

    fn concat_columns(left: FloatTensor<Self>, right: FloatTensor<Self>) -> FloatTensor<Self> {
        let (left, left_node) = left.into_parts();
        let (right, right_node) = right.into_parts();
        let widths = (left.shape()[1], right.shape()[1]);
        let out = B::concat_columns(left, right);
        match ConcatColumnsBackward
            .prepare::<C>([left_node, right_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(widths, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

/// Columns `range` of a [R, W] tensor, differentiable with respect to it (any backend, with or
/// without autodiff); equal to `t.slice(s![.., range])`.
pub fn slice_columns(t: Tensor<2>, range: Range<usize>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as ColumnSliceBackend>::slice_columns(
        t.into_dispatch(),
        range.start,
        range.end,
    ))
}

/// `left` [R, a] and `right` [R, b] side by side → [R, a + b], differentiable in both (any
/// backend, with or without autodiff); equal to `Tensor::cat(vec![left, right], 1)`, values and
/// gradients to the bit.
pub fn concat_columns(left: Tensor<2>, right: Tensor<2>) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as ColumnSliceBackend>::concat_columns(
        left.into_dispatch(),
        right.into_dispatch(),
    ))
}
