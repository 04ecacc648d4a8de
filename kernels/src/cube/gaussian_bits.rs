//! The rate term's bit estimate on the device, forward and backward: one unit per element, the
//! CPU twin's formulas (`gaussian_bits.rs`) in f32: CubeCL's `Erf` polyfill is the
//! Abramowitz & Stegun formula the twin evaluates, exp is the device's.

use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use cubecl::calculate_cube_count_elemwise;
use cubecl::prelude::*;

use super::buffers::fresh_f32;

/// (a, b, σ, ∂σ/∂scale) of element i.
#[cube]
fn bin_arguments(
    x: f32,
    mean: f32,
    scale: f32,
    noise: f32,
    min_scale: f32,
) -> (f32, f32, f32, f32) {
    // round half to even, as Burn's round.
    let floor = f32::floor(mean);
    let fraction = mean - floor;
    let mut rounded = f32::round(mean);
    if fraction == 0.5f32 {
        rounded = f32::round(mean * 0.5f32) * 2.0f32;
    }
    let rounded_mean = mean + (rounded - mean);
    let magnitude = f32::abs(scale);
    let mut sigma = magnitude;
    let mut dsigma = 0.0f32;
    if magnitude < min_scale {
        sigma = min_scale;
    } else if scale > 0.0f32 {
        dsigma = 1.0f32;
    } else if scale < 0.0f32 {
        dsigma = -1.0f32;
    }
    let y = x - rounded_mean + noise;
    let z = 0.70710677f32;
    (
        (y + 0.5f32) / sigma * z,
        (y - 0.5f32) / sigma * z,
        sigma,
        dsigma,
    )
}

#[cube(launch)]
fn bits_kernel(
    x: &Tensor<f32>,
    mean: &Tensor<f32>,
    scale: &Tensor<f32>,
    noise: &Tensor<f32>,
    min_scale: f32,
    out: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= out.len() {
        terminate!();
    }
    let (a, b, _sigma, _dsigma) = bin_arguments(x[i], mean[i], scale[i], noise[i], min_scale);
    let p = (Erf::erf(a) - Erf::erf(b)) * 0.5f32;
    out[i] = f32::ln(p + 1e-5f32) * -1.442695f32;
}

#[cube(launch)]
fn bits_backward_kernel(
    x: &Tensor<f32>,
    mean: &Tensor<f32>,
    scale: &Tensor<f32>,
    noise: &Tensor<f32>,
    grad: &Tensor<f32>,
    min_scale: f32,
    dx: &mut Tensor<f32>,
    dmean: &mut Tensor<f32>,
    dscale: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= dx.len() {
        terminate!();
    }
    let (a, b, sigma, dsigma) = bin_arguments(x[i], mean[i], scale[i], noise[i], min_scale);
    let p = (Erf::erf(a) - Erf::erf(b)) * 0.5f32;
    let ea = f32::exp(-a * a);
    let eb = f32::exp(-b * b);
    // −log2(e) · (2/√π) · ½
    let common = grad[i] * -1.442695f32 / (p + 1e-5f32) * 0.5641896f32;
    let dy = common * (ea - eb) * 0.70710677f32 / sigma;
    dx[i] = dy;
    dmean[i] = -dy;
    dscale[i] = common * (b * eb - a * ea) / sigma * dsigma;
}

fn launch_dims(like: &CubeTensor) -> (usize, CubeCount, CubeDim) {
    let n = like.meta.num_elements();
    let cube_dim = CubeDim::new_1d(256);
    (
        n,
        calculate_cube_count_elemwise(&like.client, n.max(1), cube_dim),
        cube_dim,
    )
}

pub fn forward(
    x: CubeTensor,
    mean: CubeTensor,
    scale: CubeTensor,
    noise: CubeTensor,
    min_scale: f32,
) -> CubeTensor {
    let [x, mean, scale, noise] = [x, mean, scale, noise].map(into_contiguous);
    let out = fresh_f32(&x, x.meta.shape().to_vec());
    let (n, count, dim) = launch_dims(&x);
    if n > 0 {
        bits_kernel::launch(
            &x.client.clone(),
            count,
            dim,
            x.into_tensor_arg(),
            mean.into_tensor_arg(),
            scale.into_tensor_arg(),
            noise.into_tensor_arg(),
            min_scale,
            out.clone().into_tensor_arg(),
        );
    }
    out
}

pub fn backward(
    x: CubeTensor,
    mean: CubeTensor,
    scale: CubeTensor,
    noise: CubeTensor,
    grad: CubeTensor,
    min_scale: f32,
) -> (CubeTensor, CubeTensor, CubeTensor) {
    let [x, mean, scale, noise, grad] = [x, mean, scale, noise, grad].map(into_contiguous);
    let shape = x.meta.shape().to_vec();
    let [dx, dmean, dscale] = [0; 3].map(|_| fresh_f32(&x, shape.clone()));
    let (n, count, dim) = launch_dims(&x);
    if n > 0 {
        bits_backward_kernel::launch(
            &x.client.clone(),
            count,
            dim,
            x.into_tensor_arg(),
            mean.into_tensor_arg(),
            scale.into_tensor_arg(),
            noise.into_tensor_arg(),
            grad.into_tensor_arg(),
            min_scale,
            dx.clone().into_tensor_arg(),
            dmean.clone().into_tensor_arg(),
            dscale.clone().into_tensor_arg(),
        );
    }
    (dx, dmean, dscale)
}
