//! Adam as one fused op, a Burn backend extension (CPU twin + CubeCL kernel).
//!
//! The plain-tensor update (`acags::train::row_adam`) is 13 element-wise ops per tensor, each a
//! full pass with its own allocation (and, on a GPU, its own launch), over ~42 tensors a step.
//! Here one pass reads (param, m, v, grad) and writes (param', m', v'). The arithmetic is the
//! plain version's, op for op and in the same order, in f32 with no fused multiply-add:
//!
//! m' = m·β1 + g·(1 − β1), v' = v·β2 + (g·g)·(1 − β2),
//! param' = param − m' / (√v' / √(1 − β2^t) + ε) · rate,
//!
//! with every scalar rounded to f32 as Burn rounds a scalar operand, so on the CPU the result
//! equals the plain version bit for bit (a test checks it; the training golden trace relies on
//! it). `rate` is lr / (1 − β1^t), one per element of a row (the trajectory knots' per-knot
//! schedule) or one for all.

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend.

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::backend::HostIo;

/// Adam's hyper-parameters and bias corrections for one step, as the f32 scalars the update uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamStep {
    pub beta1: f32,
    pub one_minus_beta1: f32,
    pub beta2: f32,
    pub one_minus_beta2: f32,
    /// √(1 − β2^t).
    pub bias2_sqrt: f32,
    pub eps: f32,
}

impl AdamStep {
    /// Step `t` (1-based) of Adam with (β1, β2, ε), each scalar computed in f64 and rounded to
    /// f32 as Burn rounds a scalar operand of an f32 tensor op.
    pub fn new(beta1: f64, beta2: f64, eps: f64, t: i32) -> Self {
        Self {
            beta1: beta1 as f32,
            one_minus_beta1: (1.0 - beta1) as f32,
            beta2: beta2 as f32,
            one_minus_beta2: (1.0 - beta2) as f32,
            bias2_sqrt: (1.0 - beta2.powi(t)).sqrt() as f32,
            eps: eps as f32,
        }
    }

    fn to_array(self) -> [f32; 6] {
        [
            self.beta1,
            self.one_minus_beta1,
            self.beta2,
            self.one_minus_beta2,
            self.bias2_sqrt,
            self.eps,
        ]
    }

    fn from_array(
        [
            beta1,
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            bias2_sqrt,
            eps,
        ]: [f32; 6],
    ) -> Self {
        Self {
            beta1,
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            bias2_sqrt,
            eps,
        }
    }
}

/// One rate for all, or one per element of a row (the last dimension).
fn check_rates(rates: usize, dims: &[usize]) {
    let width = dims.last().copied().unwrap_or(1);
    assert!(
        rates == 1 || rates == width,
        "fused Adam: {rates} rates for rows of {width} (one rate, or one per element of a row)"
    );
}

/// One element's update: (param', m', v'). The kernel (`cube::adam`) writes the same expression.
#[inline(always)]
pub fn adam_element(p: f32, m: f32, v: f32, g: f32, rate: f32, s: &AdamStep) -> (f32, f32, f32) {
    let m = m * s.beta1 + g * s.one_minus_beta1;
    let v = v * s.beta2 + g * g * s.one_minus_beta2;
    let denom = v.sqrt() / s.bias2_sqrt + s.eps;
    (p - m / denom * rate, m, v)
}

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait FusedAdamBackend: Backend {
    /// (param', exp_avg', exp_avg_sq') of one Adam step. All four inputs share one shape;
    /// `rates` [R] is one rate (R = 1) or one per element of a row (R = the last dimension):
    /// element i of the flattened tensor takes `rates[i % R]`. `scalars` is [`AdamStep`] as an array.
    fn adam_update(
        param: FloatTensor<Self>,
        exp_avg: FloatTensor<Self>,
        exp_avg_sq: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        rates: FloatTensor<Self>,
        beta1: f32,
        one_minus_beta1: f32,
        beta2: f32,
        one_minus_beta2: f32,
        bias2_sqrt: f32,
        eps: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

/// The CPU twin: one parallel pass. The moments are updated in place when their storage is not
/// shared (the optimizer's own state), so a step allocates only the new parameter.
impl FusedAdamBackend for NdArray {
    fn adam_update(
        param: FloatTensor<Self>,
        exp_avg: FloatTensor<Self>,
        exp_avg_sq: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        rates: FloatTensor<Self>,
        beta1: f32,
        one_minus_beta1: f32,
        beta2: f32,
        one_minus_beta2: f32,
        bias2_sqrt: f32,
        eps: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let s = AdamStep::from_array([
            beta1,
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            bias2_sqrt,
            eps,
        ]);
        let shape = param.shape();
        for (name, t) in [
            ("exp_avg", &exp_avg),
            ("exp_avg_sq", &exp_avg_sq),
            ("grad", &grad),
        ] {
            assert_eq!(
                t.shape(),
                shape,
                "fused Adam: {name} is shaped unlike the parameter"
            );
        }
        let dims: Vec<usize> = (0..shape.num_dims()).map(|d| shape[d]).collect();
        let device = param.device();
        let rates = <NdArray as HostIo>::read_floats(rates);
        assert!(!rates.is_empty(), "fused Adam: no rate");
        check_rates(rates.len(), &dims);
        let grad = <NdArray as HostIo>::read_floats(grad);
        let mut p = <NdArray as HostIo>::read_floats(param);
        let mut m = owned_floats(exp_avg);
        let mut v = owned_floats(exp_avg_sq);
        const CHUNK: usize = 4096;
        let r = rates.len();
        p.par_chunks_mut(CHUNK)
            .zip(m.par_chunks_mut(CHUNK))
            .zip(v.par_chunks_mut(CHUNK))
            .zip(grad.par_chunks(CHUNK))
            .enumerate()
            .for_each(|(chunk, (((p, m), v), g))| {
                let start = chunk * CHUNK;
                for j in 0..p.len() {
                    let rate = if r == 1 {
                        rates[0]
                    } else {
                        rates[(start + j) % r]
                    };
                    (p[j], m[j], v[j]) = adam_element(p[j], m[j], v[j], g[j], rate, &s);
                }
            });
        let tensor = |values: Vec<f32>| {
            NdArray::float_from_data(TensorData::new(values, dims.clone()), &device)
        };
        (tensor(p), tensor(m), tensor(v))
    }
}

/// The values of a float tensor as an owned vector (moved out without a copy where possible).
fn owned_floats(t: FloatTensor<NdArray>) -> Vec<f32> {
    use burn::backend::ndarray::NdArrayTensor;
    if let NdArrayTensor::F32(storage) = t {
        let array = storage.into_owned().into_owned();
        let n = array.len();
        if array.is_standard_layout() {
            let (values, offset) = array.into_raw_vec_and_offset();
            if values.len() == n && offset.unwrap_or(0) == 0 {
                return values;
            }
            // A view into a larger buffer: its elements are the first n after the offset.
            let start = offset.unwrap_or(0);
            return values[start..start + n].to_vec();
        }
        return array.iter().copied().collect();
    }
    <NdArray as HostIo>::read_floats(t)
}

impl FusedAdamBackend for burn::backend::Cube {
    fn adam_update(
        param: FloatTensor<Self>,
        exp_avg: FloatTensor<Self>,
        exp_avg_sq: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        rates: FloatTensor<Self>,
        beta1: f32,
        one_minus_beta1: f32,
        beta2: f32,
        one_minus_beta2: f32,
        bias2_sqrt: f32,
        eps: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        use crate::backend::fused::{inner_float, register};
        let shape = param.shape();
        let dims: Vec<usize> = (0..shape.num_dims()).map(|d| shape[d]).collect();
        check_rates(rates.shape().num_elements(), &dims);
        for t in [&exp_avg, &exp_avg_sq, &grad] {
            assert_eq!(
                t.shape(),
                shape,
                "fused Adam: a state or gradient is shaped unlike the parameter"
            );
        }
        // Like the rasterizer, one opaque step of the fusion stream: inputs resolved, the kernel
        // on the inner tensors, outputs registered back.
        let client = param.client.clone();
        let (p, m, v) = crate::cube::adam::adam_update(
            inner_float(param),
            inner_float(exp_avg),
            inner_float(exp_avg_sq),
            inner_float(grad),
            inner_float(rates),
            [
                beta1,
                one_minus_beta1,
                beta2,
                one_minus_beta2,
                bias2_sqrt,
                eps,
            ],
        );
        (
            register(&client, p),
            register(&client, m),
            register(&client, v),
        )
    }
}

/// An optimizer step is not differentiated: the autodiff backend runs the inner one.
impl<B: FusedAdamBackend, C: CheckpointStrategy> FusedAdamBackend for Autodiff<B, C> {
    fn adam_update(
        param: FloatTensor<Self>,
        exp_avg: FloatTensor<Self>,
        exp_avg_sq: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        rates: FloatTensor<Self>,
        beta1: f32,
        one_minus_beta1: f32,
        beta2: f32,
        one_minus_beta2: f32,
        bias2_sqrt: f32,
        eps: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (p, m, v) = B::adam_update(
            Self::inner(param),
            Self::inner(exp_avg),
            Self::inner(exp_avg_sq),
            Self::inner(grad),
            Self::inner(rates),
            beta1,
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            bias2_sqrt,
            eps,
        );
        (
            Self::from_inner(p),
            Self::from_inner(m),
            Self::from_inner(v),
        )
    }
}

/// One fused Adam step on any backend: (param', exp_avg', exp_avg_sq').
pub fn adam_update<const D: usize>(
    param: Tensor<D>,
    exp_avg: Tensor<D>,
    exp_avg_sq: Tensor<D>,
    grad: Tensor<D>,
    rates: Tensor<1>,
    step: AdamStep,
) -> (Tensor<D>, Tensor<D>, Tensor<D>) {
    let [
        beta1,
        one_minus_beta1,
        beta2,
        one_minus_beta2,
        bias2_sqrt,
        eps,
    ] = step.to_array();
    let (p, m, v) = <Dispatch as FusedAdamBackend>::adam_update(
        param.into_dispatch(),
        exp_avg.into_dispatch(),
        exp_avg_sq.into_dispatch(),
        grad.into_dispatch(),
        rates.into_dispatch(),
        beta1,
        one_minus_beta1,
        beta2,
        one_minus_beta2,
        bias2_sqrt,
        eps,
    );
    (
        Tensor::from_dispatch(p),
        Tensor::from_dispatch(m),
        Tensor::from_dispatch(v),
    )
}
