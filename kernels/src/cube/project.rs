//! Projection + culling kernel: one unit per Gaussian, the same arithmetic as
//! `cpu::project::project` (f32), writing the [N, 8] projection rows of
//! `backend::projected_column` (zeros for culled Gaussians).

use burn::backend::cubecl::dtype_to_storage_type;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::empty_device_dtype;
use burn_cubecl::tensor::CubeTensor;
use cubecl::{CubeDim, calculate_cube_count_elemwise, prelude::*};

use crate::conventions::{ALPHA_MIN, EPS2D, FAR_PLANE, MAX_EXTENT_SIGMAS, NEAR_PLANE};

/// Camera packed for the kernel: R (row-major 9), t (3), fx, fy, cx, cy, width, height,
/// lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg.
pub const CAMERA_FLOATS: usize = 22;

pub fn pack_camera(camera: &crate::RasterCamera) -> Vec<f32> {
    let r = camera.rotation();
    let t = camera.translation();
    let (w, h) = (camera.width as f32, camera.height as f32);
    let mut v: Vec<f32> = r.iter().flatten().copied().collect();
    v.extend(t);
    v.extend([camera.fx, camera.fy, camera.cx, camera.cy, w, h]);
    v.extend(camera.jacobian_clamp_limits());
    v
}

#[cube(launch)]
fn project_kernel<F: Float>(
    means: &Tensor<F>,
    quats: &Tensor<F>,
    scales: &Tensor<F>,
    opacities: &Tensor<F>,
    camera: &Tensor<F>,
    out: &mut Tensor<F>,
    #[define(F)] _dtype: ElemType,
) {
    let i = ABSOLUTE_POS;
    if i >= opacities.len() {
        terminate!();
    }
    let zero = F::new(0.0);
    for k in 0..8usize {
        out[i * 8 + k] = zero;
    }
    let (mx, my, mz) = (means[i * 3], means[i * 3 + 1], means[i * 3 + 2]);
    let opacity = opacities[i];
    // Camera-space position.
    let px = camera[0] * mx + camera[1] * my + camera[2] * mz + camera[9];
    let py = camera[3] * mx + camera[4] * my + camera[5] * mz + camera[10];
    let pz = camera[6] * mx + camera[7] * my + camera[8] * mz + camera[11];
    let (qw, qx, qy, qz) = (
        quats[i * 4],
        quats[i * 4 + 1],
        quats[i * 4 + 2],
        quats[i * 4 + 3],
    );
    let qnorm = F::sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    // Written so NaN fails every test (culled), like the CPU twin.
    let finite_ok = opacity >= F::new(ALPHA_MIN)
        && pz >= F::new(NEAR_PLANE)
        && pz <= F::new(FAR_PLANE)
        && qnorm > zero;
    if finite_ok {
        let (w, x, y, z) = (qw / qnorm, qx / qnorm, qy / qnorm, qz / qnorm);
        let two = F::new(2.0);
        let one = F::new(1.0);
        // R_q (row-major) times diag(s): M.
        let (s0, s1, s2) = (scales[i * 3], scales[i * 3 + 1], scales[i * 3 + 2]);
        let m00 = (one - two * (y * y + z * z)) * s0;
        let m01 = two * (x * y - w * z) * s1;
        let m02 = two * (x * z + w * y) * s2;
        let m10 = two * (x * y + w * z) * s0;
        let m11 = (one - two * (x * x + z * z)) * s1;
        let m12 = two * (y * z - w * x) * s2;
        let m20 = two * (x * z - w * y) * s0;
        let m21 = two * (y * z + w * x) * s1;
        let m22 = (one - two * (x * x + y * y)) * s2;
        // cov = M M^T (symmetric).
        let c00 = m00 * m00 + m01 * m01 + m02 * m02;
        let c01 = m00 * m10 + m01 * m11 + m02 * m12;
        let c02 = m00 * m20 + m01 * m21 + m02 * m22;
        let c11 = m10 * m10 + m11 * m11 + m12 * m12;
        let c12 = m10 * m20 + m11 * m21 + m12 * m22;
        let c22 = m20 * m20 + m21 * m21 + m22 * m22;
        // cov_cam = R cov R^T: first A = R cov.
        let (r00, r01, r02) = (camera[0], camera[1], camera[2]);
        let (r10, r11, r12) = (camera[3], camera[4], camera[5]);
        let (r20, r21, r22) = (camera[6], camera[7], camera[8]);
        let a00 = r00 * c00 + r01 * c01 + r02 * c02;
        let a01 = r00 * c01 + r01 * c11 + r02 * c12;
        let a02 = r00 * c02 + r01 * c12 + r02 * c22;
        let a10 = r10 * c00 + r11 * c01 + r12 * c02;
        let a11 = r10 * c01 + r11 * c11 + r12 * c12;
        let a12 = r10 * c02 + r11 * c12 + r12 * c22;
        let a20 = r20 * c00 + r21 * c01 + r22 * c02;
        let a21 = r20 * c01 + r21 * c11 + r22 * c12;
        let a22 = r20 * c02 + r21 * c12 + r22 * c22;
        let k00 = a00 * r00 + a01 * r01 + a02 * r02;
        let k01 = a00 * r10 + a01 * r11 + a02 * r12;
        let k02 = a00 * r20 + a01 * r21 + a02 * r22;
        let k11 = a10 * r10 + a11 * r11 + a12 * r12;
        let k12 = a10 * r20 + a11 * r21 + a12 * r22;
        let k22 = a20 * r20 + a21 * r21 + a22 * r22;
        // Jacobian with x/z, y/z clamped to 1.3x the field of view.
        let (fx, fy, cx, cy) = (camera[12], camera[13], camera[14], camera[15]);
        let tx = pz * F::clamp(px / pz, zero - camera[19], camera[18]);
        let ty = pz * F::clamp(py / pz, zero - camera[21], camera[20]);
        let j00 = fx / pz;
        let j02 = zero - fx * tx / (pz * pz);
        let j11 = fy / pz;
        let j12 = zero - fy * ty / (pz * pz);
        // cov2d = J cov_cam J^T + eps I, with J rows (j00, 0, j02) and (0, j11, j12).
        let sxx = j00 * (k00 * j00 + k02 * j02) + j02 * (k02 * j00 + k22 * j02) + F::new(EPS2D);
        let sxy = j00 * (k01 * j11 + k02 * j12) + j02 * (k12 * j11 + k22 * j12);
        let syy = j11 * (k11 * j11 + k12 * j12) + j12 * (k12 * j11 + k22 * j12) + F::new(EPS2D);
        let det = sxx * syy - sxy * sxy;
        if det > zero {
            let mean_x = fx * px / pz + cx;
            let mean_y = fy * py / pz + cy;
            let extent = F::min(
                F::new(MAX_EXTENT_SIGMAS),
                F::sqrt(two * F::ln(opacity / F::new(ALPHA_MIN))),
            );
            let rx = F::ceil(extent * F::sqrt(sxx));
            let ry = F::ceil(extent * F::sqrt(syy));
            let (width, height) = (camera[16], camera[17]);
            let on_screen = mean_x + rx > zero
                && mean_x - rx < width
                && mean_y + ry > zero
                && mean_y - ry < height;
            if on_screen && (rx > zero || ry > zero) {
                out[i * 8] = mean_x;
                out[i * 8 + 1] = mean_y;
                out[i * 8 + 2] = syy / det;
                out[i * 8 + 3] = zero - sxy / det;
                out[i * 8 + 4] = sxx / det;
                out[i * 8 + 5] = pz;
                out[i * 8 + 6] = rx;
                out[i * 8 + 7] = ry;
            }
        }
    }
}

/// Projects N Gaussians (opacities already gated) on the device: [N, 8] rows.
pub fn project(
    means: CubeTensor,
    quats: CubeTensor,
    scales: CubeTensor,
    opacities: CubeTensor,
    camera: CubeTensor,
) -> CubeTensor {
    let n = opacities.meta.shape()[0];
    let [means, quats, scales, opacities, camera] =
        [means, quats, scales, opacities, camera].map(into_contiguous);
    let out = empty_device_dtype(
        means.client.clone(),
        means.device.clone(),
        [n, 8].into(),
        means.dtype,
    );
    if n == 0 {
        return out;
    }
    let cube_dim = CubeDim::new_1d(256);
    let cube_count = calculate_cube_count_elemwise(&means.client, n, cube_dim);
    let dtype = dtype_to_storage_type(means.dtype);
    let client = means.client.clone();
    project_kernel::launch(
        &client,
        cube_count,
        cube_dim,
        means.into_tensor_arg(),
        quats.into_tensor_arg(),
        scales.into_tensor_arg(),
        opacities.into_tensor_arg(),
        camera.into_tensor_arg(),
        out.clone().into_tensor_arg(),
        dtype,
    );
    out
}
