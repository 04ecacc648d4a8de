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
use crate::host_simd::{Lanes, avx2_twin};

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

avx2_twin! {
    /// [`adam_element`] over a chunk with one rate.
    pub(crate) fn adam_one_rate(
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        g: &[f32],
        rate: f32,
        s: AdamStep,
    ) {
        for (((p, m), v), &g) in p.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(g) {
            (*p, *m, *v) = adam_element(*p, *m, *v, g, rate, &s);
        }
    }
}

avx2_twin! {
    /// [`adam_element`] over a chunk of whole rows, element j of a row at `rates[j]`.
    pub(crate) fn adam_row_rates(
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        g: &[f32],
        rates: &[f32],
        s: AdamStep,
    ) {
        let r = rates.len();
        let rows = p
            .chunks_exact_mut(r)
            .zip(m.chunks_exact_mut(r))
            .zip(v.chunks_exact_mut(r))
            .zip(g.chunks_exact(r));
        for (((p, m), v), g) in rows {
            let row = p.iter_mut().zip(m.iter_mut()).zip(v.iter_mut()).zip(g).zip(rates);
            for ((((p, m), v), &g), &rate) in row {
                (*p, *m, *v) = adam_element(*p, *m, *v, g, rate, &s);
            }
        }
    }
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
        // Chunks of whole rows, so element j of a chunk takes rates[j % R] and a row's rates
        // zip with its elements (no division per element; check_rates: R divides the length).
        let r = rates.len();
        let chunk = (4096 / r).max(1) * r;
        p.par_chunks_mut(chunk)
            .zip(m.par_chunks_mut(chunk))
            .zip(v.par_chunks_mut(chunk))
            .zip(grad.par_chunks(chunk))
            .for_each(|(((p, m), v), g)| {
                if r == 1 {
                    adam_one_rate(Lanes::Widest, p, m, v, g, rates[0], s);
                } else {
                    adam_row_rates(Lanes::Widest, p, m, v, g, &rates, s);
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

#[cfg(test)]
mod twin_tests {
    use super::*;

    /// Both copies of both loops equal the element formula to the bit.
    #[test]
    fn both_copies_of_the_update_loops_give_the_element_formula_to_the_bit() {
        let n = 30 * 347;
        let wave = |k: usize, f: f32| (k as f32 * f).sin() * 0.1;
        let g: Vec<f32> = (0..n).map(|k| wave(k, 0.37)).collect();
        let p0: Vec<f32> = (0..n).map(|k| wave(k, 0.11)).collect();
        let m0: Vec<f32> = (0..n).map(|k| wave(k, 0.53) * 0.1).collect();
        let v0: Vec<f32> = (0..n).map(|k| wave(k, 0.29).abs() * 0.01).collect();
        let s = AdamStep::new(0.9, 0.999, 1e-15, 17);
        let row_rates: Vec<f32> = (0..30).map(|j| 1e-3 * (1.0 + j as f32)).collect();
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        for rates in [vec![2e-3f32], row_rates] {
            let r = rates.len();
            let mut want = (p0.clone(), m0.clone(), v0.clone());
            for k in 0..n {
                (want.0[k], want.1[k], want.2[k]) =
                    adam_element(p0[k], m0[k], v0[k], g[k], rates[k % r], &s);
            }
            for lanes in [Lanes::Widest, Lanes::Portable] {
                let (mut p, mut m, mut v) = (p0.clone(), m0.clone(), v0.clone());
                if r == 1 {
                    adam_one_rate(lanes, &mut p, &mut m, &mut v, &g, rates[0], s);
                } else {
                    adam_row_rates(lanes, &mut p, &mut m, &mut v, &g, &rates, s);
                }
                assert_eq!(bits(&p), bits(&want.0), "{lanes:?}, {r} rates: param");
                assert_eq!(bits(&m), bits(&want.1), "{lanes:?}, {r} rates: exp_avg");
                assert_eq!(bits(&v), bits(&want.2), "{lanes:?}, {r} rates: exp_avg_sq");
            }
        }
    }
}
