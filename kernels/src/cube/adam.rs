//! The fused Adam update on the device: one unit per element reads (param, m, v, grad) once and
//! writes the three new tensors, in place of the 13 element-wise ops the plain-tensor version
//! launches. The arithmetic and its order are the CPU twin's (`fused_adam::adam_element`).

use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use cubecl::calculate_cube_count_elemwise;
use cubecl::prelude::*;

use super::buffers::fresh_f32;

/// Adam's per-step scalars, passed by value.
#[derive(CubeLaunch, CubeType, Clone, Copy)]
pub struct AdamScalars {
    beta1: f32,
    one_minus_beta1: f32,
    beta2: f32,
    one_minus_beta2: f32,
    bias2_sqrt: f32,
    eps: f32,
}

#[cube(launch)]
fn adam_kernel(
    param: &Tensor<f32>,
    exp_avg: &Tensor<f32>,
    exp_avg_sq: &Tensor<f32>,
    grad: &Tensor<f32>,
    rates: &Tensor<f32>,
    scalars: AdamScalars,
    param_out: &mut Tensor<f32>,
    exp_avg_out: &mut Tensor<f32>,
    exp_avg_sq_out: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= param.len() {
        terminate!();
    }
    let g = grad[i];
    let m = exp_avg[i] * scalars.beta1 + g * scalars.one_minus_beta1;
    let v = exp_avg_sq[i] * scalars.beta2 + g * g * scalars.one_minus_beta2;
    let denom = f32::sqrt(v) / scalars.bias2_sqrt + scalars.eps;
    let rate = rates[i % rates.len()];
    param_out[i] = param[i] - m / denom * rate;
    exp_avg_out[i] = m;
    exp_avg_sq_out[i] = v;
}

/// (param', m', v') of one Adam step; `rates` holds one rate per element of a row, cycling
/// (length 1: one rate for all).
pub fn adam_update(
    param: CubeTensor,
    exp_avg: CubeTensor,
    exp_avg_sq: CubeTensor,
    grad: CubeTensor,
    rates: CubeTensor,
    scalars: [f32; 6],
) -> (CubeTensor, CubeTensor, CubeTensor) {
    let [param, exp_avg, exp_avg_sq, grad, rates] =
        [param, exp_avg, exp_avg_sq, grad, rates].map(|t| {
            assert_eq!(
                t.dtype,
                burn::tensor::DType::F32,
                "fused Adam takes float32 tensors"
            );
            into_contiguous(t)
        });
    let shape = param.meta.shape().to_vec();
    let n: usize = shape.iter().product();
    let outputs = [0; 3].map(|_| fresh_f32(&param, shape.clone()));
    if n > 0 {
        let client = param.client.clone();
        let cube_dim = CubeDim::new_1d(256);
        let count = calculate_cube_count_elemwise(&client, n, cube_dim);
        let [
            beta1,
            one_minus_beta1,
            beta2,
            one_minus_beta2,
            bias2_sqrt,
            eps,
        ] = scalars;
        adam_kernel::launch(
            &client,
            count,
            cube_dim,
            param.into_tensor_arg(),
            exp_avg.into_tensor_arg(),
            exp_avg_sq.into_tensor_arg(),
            grad.into_tensor_arg(),
            rates.into_tensor_arg(),
            AdamScalarsLaunch::new(
                beta1,
                one_minus_beta1,
                beta2,
                one_minus_beta2,
                bias2_sqrt,
                eps,
            ),
            outputs[0].clone().into_tensor_arg(),
            outputs[1].clone().into_tensor_arg(),
            outputs[2].clone().into_tensor_arg(),
        );
    }
    let [p, m, v] = outputs;
    (p, m, v)
}
