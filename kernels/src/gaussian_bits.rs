//! The rate term's bit estimate as one op with an analytic backward, a Burn backend extension
//! (CPU twin + CubeCL kernels).
//!
//! bits = −log2(P + 1e-5), P = ½ [erf((y + ½) / (σ√2)) − erf((y − ½) / (σ√2))], the probability of
//! the unit bin around y = x − round(μ) + noise under N(0, σ²), σ = max(|scale|, min_scale).
//! round(μ) passes the gradient straight through (∂/∂μ = −∂/∂y); the noise gets none.
//!
//! As plain tensor ops this is ~20 passes (and as many again in the backward) over every
//! priced element, with erf in f64, one thread. Both twins evaluate erf in f32 as
//! Abramowitz & Stegun 7.1.26 (|error| ≤ 1.5e-7 in exact arithmetic, ≤ 6e-7 evaluated in f32),
//! the formula of CubeCL's `Erf` polyfill, so the CPU twin and the GPU kernel compute the same
//! function; the e^{−x²} it needs is shared with the backward. Against the f64 erf this moves a
//! bit count by at most log2(e)·6e-7/(P + 1e-5) (≤ 0.09 bits at the floor, < 0.05 measured;
//! ~9e-6 at P = 0.1; a test checks the bound); f64 erf and exp were 4 % of a default run's CPU
//! profile. On the CPU, e^x and ln are [`crate::host_simd`]'s call-free polynomials (≤ 1.2e-7
//! from the exact values; libm's calls kept the loops scalar, ~4x slower than the AVX2 copy).
//! One parallel pass forward; the backward is the derivative
//! written out (with erf's exact derivative, as the GPU kernel):
//! ∂bits/∂y = −log2(e)/(P + 1e-5) · (1/√π) · (e^{−a²} − e^{−b²}) / (σ√2),
//! ∂bits/∂σ = −log2(e)/(P + 1e-5) · (1/√π) · (−a e^{−a²} + b e^{−b²}) / σ,
//! a, b = (y ± ½)/(σ√2); ∂σ/∂scale = sign(scale) where |scale| ≥ min_scale, else 0 (Burn's clamp).

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend.

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
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::backend::HostIo;
use crate::host_simd::{Lanes, avx2_twin, exp_f32, ln_f32};

/// The floor of P: bins of vanishing probability cost at most −log2(1e-5) ≈ 16.6 bits.
pub const BIN_PROBABILITY_FLOOR: f32 = 1e-5;

/// erf(x) as Abramowitz & Stegun 7.1.26 given `gaussian` = e^{−x²}: 1 − t·poly(t)·e^{−x²},
/// t = 1/(1 + p|x|), odd in x. The constants and the order of operations are those of CubeCL's
/// `Erf` polyfill (cubecl-core `frontend/polyfills.rs`), which the GPU kernel calls.
#[inline(always)]
pub fn erf_given_gaussian(x: f32, gaussian: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.3275911 * x.abs());
    let poly = ((((1.0614054 * t + -1.453152) * t) + 1.4214137) * t + -0.28449674) * t + 0.2548296;
    let positive = 1.0 - poly * t * gaussian;
    if x < 0.0 { -positive } else { positive }
}

/// erf(x) in f32 ([`erf_given_gaussian`], e^{−x²} by [`exp_f32`]).
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    erf_given_gaussian(x, exp_f32(-x * x))
}

/// The forward of one element.
#[inline(always)]
pub fn bits_element(x: f32, mean: f32, scale: f32, noise: f32, min_scale: f32) -> f32 {
    let (a, b, _, _) = bin_arguments(x, mean, scale, noise, min_scale);
    let p = (erf(a) - erf(b)) * 0.5;
    ln_f32(p + BIN_PROBABILITY_FLOOR) * -std::f32::consts::LOG2_E
}

/// (a, b, σ, ∂σ/∂scale) of one element.
#[inline(always)]
fn bin_arguments(
    x: f32,
    mean: f32,
    scale: f32,
    noise: f32,
    min_scale: f32,
) -> (f32, f32, f32, f32) {
    // mean + (round(mean) − mean): the straight-through rounding as the plain version writes it.
    // (Rounding in f32 gives the f64 rounding's bits: an f32's nearest integer is an f32.)
    let rounded_mean = mean + (mean.round_ties_even() - mean);
    let magnitude = scale.abs();
    let (sigma, dsigma) = if magnitude < min_scale {
        (min_scale, 0.0)
    } else {
        (magnitude, sign(scale))
    };
    let y = x - rounded_mean + noise;
    let z = std::f32::consts::FRAC_1_SQRT_2;
    ((y + 0.5) / sigma * z, (y - 0.5) / sigma * z, sigma, dsigma)
}

fn sign(v: f32) -> f32 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// (∂bits/∂x, ∂bits/∂mean, ∂bits/∂scale) of one element times the upstream gradient `g`.
#[inline(always)]
pub fn bits_element_backward(
    x: f32,
    mean: f32,
    scale: f32,
    noise: f32,
    min_scale: f32,
    g: f32,
) -> (f32, f32, f32) {
    let (a, b, sigma, dsigma) = bin_arguments(x, mean, scale, noise, min_scale);
    let (ea, eb) = (exp_f32(-a * a), exp_f32(-b * b));
    // P as the forward computed it: the gradient is that of the function the forward evaluates
    // (with erf's exact derivative 2/√π·e^{−x²}).
    let p = (erf_given_gaussian(a, ea) - erf_given_gaussian(b, eb)) * 0.5;
    // −log2(e) · (2/√π) · ½
    let common = g * -std::f32::consts::LOG2_E / (p + BIN_PROBABILITY_FLOOR)
        * std::f32::consts::FRAC_2_SQRT_PI
        * 0.5;
    let dy = common * (ea - eb) * std::f32::consts::FRAC_1_SQRT_2 / sigma;
    let dsigma_value = common * (b * eb - a * ea) / sigma;
    (dy, -dy, dsigma_value * dsigma)
}

avx2_twin! {
    /// [`bits_element`] over a chunk; `inputs` are (x, mean, scale, noise).
    pub(crate) fn bits_forward(bits: &mut [f32], inputs: [&[f32]; 4], min_scale: f32) {
        let [x, mean, scale, noise] = inputs;
        let elements = bits.iter_mut().zip(x).zip(mean).zip(scale).zip(noise);
        for ((((bits, &x), &mean), &scale), &noise) in elements {
            *bits = bits_element(x, mean, scale, noise, min_scale);
        }
    }
}

avx2_twin! {
    /// [`bits_element_backward`] over a chunk into (∂x, ∂mean, ∂scale).
    pub(crate) fn bits_backward(
        out: [&mut [f32]; 3],
        inputs: [&[f32]; 4],
        grad: &[f32],
        min_scale: f32,
    ) {
        let [dx, dmean, dscale] = out;
        let [x, mean, scale, noise] = inputs;
        let outputs = dx.iter_mut().zip(dmean.iter_mut()).zip(dscale.iter_mut());
        let elements = outputs.zip(x).zip(mean).zip(scale).zip(noise).zip(grad);
        for (((((((dx, dmean), dscale), &x), &mean), &scale), &noise), &g) in elements {
            (*dx, *dmean, *dscale) = bits_element_backward(x, mean, scale, noise, min_scale, g);
        }
    }
}

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait GaussianBitsBackend: Backend {
    /// Bits of each element; `x`, `mean`, `scale`, `noise` share one shape.
    fn gaussian_bits(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        min_scale: f32,
    ) -> FloatTensor<Self>;

    /// (∂/∂x, ∂/∂mean, ∂/∂scale) of Σ grad · bits.
    fn gaussian_bits_backward(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        min_scale: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

fn dims_of<T: TensorMetadata>(t: &T) -> Vec<usize> {
    let shape = t.shape();
    (0..shape.num_dims()).map(|d| shape[d]).collect()
}

fn check_shapes<T: TensorMetadata>(op: &str, tensors: &[(&str, &T)]) -> Vec<usize> {
    let dims = dims_of(tensors[0].1);
    for (name, t) in &tensors[1..] {
        assert_eq!(
            dims_of(*t),
            dims,
            "{op}: `{name}` is shaped unlike `{}`",
            tensors[0].0
        );
    }
    dims
}

const CHUNK: usize = 4096;

impl GaussianBitsBackend for NdArray {
    fn gaussian_bits(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        min_scale: f32,
    ) -> FloatTensor<Self> {
        let dims = check_shapes(
            "gaussian_bits",
            &[
                ("x", &x),
                ("mean", &mean),
                ("scale", &scale),
                ("noise", &noise),
            ],
        );
        let device = x.device();
        let [x, mean, scale, noise] = [x, mean, scale, noise].map(<NdArray as HostIo>::read_floats);
        let mut out = vec![0.0f32; x.len()];
        out.par_chunks_mut(CHUNK).enumerate().for_each(|(c, bits)| {
            let r = c * CHUNK..c * CHUNK + bits.len();
            let inputs = [&x, &mean, &scale, &noise].map(|v| &v[r.clone()]);
            bits_forward(Lanes::Widest, bits, inputs, min_scale);
        });
        NdArray::float_from_data(TensorData::new(out, dims), &device)
    }

    fn gaussian_bits_backward(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        min_scale: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let dims = check_shapes(
            "gaussian_bits_backward",
            &[
                ("x", &x),
                ("mean", &mean),
                ("scale", &scale),
                ("noise", &noise),
                ("grad", &grad),
            ],
        );
        let device = x.device();
        let [x, mean, scale, noise, grad] =
            [x, mean, scale, noise, grad].map(<NdArray as HostIo>::read_floats);
        let n = x.len();
        let (mut dx, mut dmean, mut dscale) = (vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]);
        dx.par_chunks_mut(CHUNK)
            .zip(dmean.par_chunks_mut(CHUNK))
            .zip(dscale.par_chunks_mut(CHUNK))
            .enumerate()
            .for_each(|(c, ((dx, dmean), dscale))| {
                let r = c * CHUNK..c * CHUNK + dx.len();
                let inputs = [&x, &mean, &scale, &noise].map(|v| &v[r.clone()]);
                bits_backward(
                    Lanes::Widest,
                    [dx, dmean, dscale],
                    inputs,
                    &grad[r],
                    min_scale,
                );
            });
        let tensor =
            |v: Vec<f32>| NdArray::float_from_data(TensorData::new(v, dims.clone()), &device);
        (tensor(dx), tensor(dmean), tensor(dscale))
    }
}

impl GaussianBitsBackend for burn::backend::Cube {
    fn gaussian_bits(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        min_scale: f32,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, register};
        check_shapes(
            "gaussian_bits",
            &[
                ("x", &x),
                ("mean", &mean),
                ("scale", &scale),
                ("noise", &noise),
            ],
        );
        let client = x.client.clone();
        let [x, mean, scale, noise] = [x, mean, scale, noise].map(inner_float);
        register(
            &client,
            crate::cube::gaussian_bits::forward(x, mean, scale, noise, min_scale),
        )
    }

    fn gaussian_bits_backward(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        min_scale: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        use crate::backend::fused::{inner_float, register};
        let client = x.client.clone();
        let [x, mean, scale, noise, grad] = [x, mean, scale, noise, grad].map(inner_float);
        let (dx, dmean, dscale) =
            crate::cube::gaussian_bits::backward(x, mean, scale, noise, grad, min_scale);
        (
            register(&client, dx),
            register(&client, dmean),
            register(&client, dscale),
        )
    }
}

#[derive(Debug)]
struct GaussianBitsBackward;

impl<B: GaussianBitsBackend> Backward<B, 3> for GaussianBitsBackward {
    /// (x, mean, scale, noise, min_scale)
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        f32,
    );

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (x, mean, scale, noise, min_scale) = ops.state;
        let (dx, dmean, dscale) = B::gaussian_bits_backward(x, mean, scale, noise, grad, min_scale);
        let [px, pmean, pscale] = ops.parents;
        for (parent, g) in [(px, dx), (pmean, dmean), (pscale, dscale)] {
            if let Some(node) = parent {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

impl<B: GaussianBitsBackend, C: CheckpointStrategy> GaussianBitsBackend for Autodiff<B, C> {
    fn gaussian_bits(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        min_scale: f32,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (mean, mean_node) = mean.into_parts();
        let (scale, scale_node) = scale.into_parts();
        // The noise is a constant of the estimate: no gradient.
        let noise = Self::inner(noise);
        match GaussianBitsBackward
            .prepare::<C>([x_node, mean_node, scale_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::gaussian_bits(
                    x.clone(),
                    mean.clone(),
                    scale.clone(),
                    noise.clone(),
                    min_scale,
                );
                prep.finish((x, mean, scale, noise, min_scale), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::gaussian_bits(x, mean, scale, noise, min_scale))
            }
        }
    }

    fn gaussian_bits_backward(
        x: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        noise: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        min_scale: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        // Only used as a backward: not differentiable itself.
        let (dx, dmean, dscale) = B::gaussian_bits_backward(
            Self::inner(x),
            Self::inner(mean),
            Self::inner(scale),
            Self::inner(noise),
            Self::inner(grad),
            min_scale,
        );
        (
            Self::from_inner(dx),
            Self::from_inner(dmean),
            Self::from_inner(dscale),
        )
    }
}

/// Bits of each element of x under N(round(mean), max(|scale|, min_scale)²) with `noise` added
/// to x (see the module), differentiable in x, mean and scale, on any backend.
pub fn gaussian_bits<const D: usize>(
    x: Tensor<D>,
    mean: Tensor<D>,
    scale: Tensor<D>,
    noise: Tensor<D>,
    min_scale: f32,
) -> Tensor<D> {
    Tensor::from_dispatch(<Dispatch as GaussianBitsBackend>::gaussian_bits(
        x.into_dispatch(),
        mean.into_dispatch(),
        scale.into_dispatch(),
        noise.into_dispatch(),
        min_scale,
    ))
}

#[cfg(test)]
mod twin_tests {
    use super::*;

    /// Both copies of both loops equal the element formulas to the bit, on arguments that
    /// reach the clamp of σ, the probability floor and e^{−x²}'s underflow.
    #[test]
    fn both_copies_of_the_bit_loops_give_the_element_formulas_to_the_bit() {
        let n = 9_001;
        let wave = |k: usize, f: f32, a: f32| (k as f32 * f).sin() * a;
        let x: Vec<f32> = (0..n).map(|k| wave(k, 0.37, 40.0)).collect();
        let mean: Vec<f32> = (0..n).map(|k| wave(k, 0.11, 3.0)).collect();
        let scale: Vec<f32> = (0..n).map(|k| wave(k, 0.53, 2.0)).collect();
        let noise: Vec<f32> = (0..n).map(|k| wave(k, 0.29, 0.5)).collect();
        let grad: Vec<f32> = (0..n).map(|k| wave(k, 0.17, 1.0)).collect();
        let inputs = [&x[..], &mean[..], &scale[..], &noise[..]];
        let min_scale = 0.11;
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        let want: Vec<f32> = (0..n)
            .map(|k| bits_element(x[k], mean[k], scale[k], noise[k], min_scale))
            .collect();
        let want_back: Vec<(f32, f32, f32)> = (0..n)
            .map(|k| bits_element_backward(x[k], mean[k], scale[k], noise[k], min_scale, grad[k]))
            .collect();
        assert!(
            want.iter().any(|&b| b > 16.0),
            "no argument reaches the floor"
        );
        for lanes in [Lanes::Widest, Lanes::Portable] {
            let mut out = vec![0.0; n];
            bits_forward(lanes, &mut out, inputs, min_scale);
            assert_eq!(bits(&out), bits(&want), "{lanes:?} forward");
            let (mut dx, mut dmean, mut dscale) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            bits_backward(
                lanes,
                [&mut dx, &mut dmean, &mut dscale],
                inputs,
                &grad,
                min_scale,
            );
            for k in 0..n {
                let got = (dx[k].to_bits(), dmean[k].to_bits(), dscale[k].to_bits());
                let (a, b, c) = want_back[k];
                assert_eq!(
                    got,
                    (a.to_bits(), b.to_bits(), c.to_bits()),
                    "{lanes:?} element {k}"
                );
            }
        }
    }
}
