//! Projection + culling (one unit per Gaussian) and its backward, the arithmetic of
//! `cpu::project` in f32: projection rows of `conventions::projected_column` (zeros when culled), and
//! from the screen-space gradients the gradients of means, quaternions and scales.
//!
//! Non-finite inputs are tested on the bits, not by comparisons: WGSL lets compilers assume
//! floats are finite, so `x != x` may fold away.

use burn_cubecl::tensor::CubeTensor;
use cubecl::{CubeDim, calculate_cube_count_elemwise, prelude::*};

use super::buffers::fresh_f32;
use super::mat3::{
    M3, V3, add, col0, col1, col2, dot, madd, mul, mul_vec, outer_scaled, rotation_from_quat,
    scaled, transpose, unit_quat_backward, v3,
};
use super::{DeviceGaussians, DeviceGrads};
use crate::conventions::{
    ALPHA_MIN, EPS2D, FAR_PLANE, MAX_EXTENT_SIGMAS, NEAR_PLANE, PROJECTED_COLUMNS,
    projected_column as col,
};

/// Camera packed for the kernels: R (row-major 9), t (3), fx, fy, cx, cy, width, height,
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
    debug_assert_eq!(v.len(), CAMERA_FLOATS);
    v
}

/// Splat gradient columns (per Gaussian, what compositing accumulates): mean2d x, y, conic a, b,
/// c, opacity (effective, gate included), colour r, g, b.
pub const SPLAT_GRAD_COLUMNS: usize = 9;

/// Whether `x` is finite, from its bits.
#[cube]
pub(crate) fn finite(x: f32) -> bool {
    (u32::reinterpret(x) & 0x7FFF_FFFFu32) < 0x7F80_0000u32
}

#[cube]
fn camera_rotation(camera: &Tensor<f32>) -> M3 {
    M3 {
        r0: v3(camera[0], camera[1], camera[2]),
        r1: v3(camera[3], camera[4], camera[5]),
        r2: v3(camera[6], camera[7], camera[8]),
    }
}

/// What the forward computes before the screen quantities (`cpu::project::Intermediates`).
#[derive(CubeType, Clone, Copy)]
struct Intermediates {
    p_cam: V3,
    /// Unit quaternion and the raw one's norm.
    qw: f32,
    qx: f32,
    qy: f32,
    qz: f32,
    quat_norm: f32,
    rot_q: M3,
    m: M3,
    cov_cam: M3,
    j0: V3,
    j1: V3,
    x_clamped: bool,
    y_clamped: bool,
    sxx: f32,
    sxy: f32,
    syy: f32,
    /// False when the Gaussian is culled before the 2D covariance (depth, quaternion).
    valid: bool,
}

#[cube]
fn intermediates(
    means: &Tensor<f32>,
    quats: &Tensor<f32>,
    scales: &Tensor<f32>,
    camera: &Tensor<f32>,
    i: usize,
) -> Intermediates {
    let r = camera_rotation(camera);
    let mean = v3(means[i * 3], means[i * 3 + 1], means[i * 3 + 2]);
    let p_cam = add(&mul_vec(&r, &mean), &v3(camera[9], camera[10], camera[11]));
    let z = p_cam.z;
    let (qw0, qx0, qy0, qz0) = (
        quats[i * 4],
        quats[i * 4 + 1],
        quats[i * 4 + 2],
        quats[i * 4 + 3],
    );
    let quat_norm = f32::sqrt(qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0);
    let valid =
        finite(z) && z >= NEAR_PLANE && z <= FAR_PLANE && finite(quat_norm) && quat_norm > 0.0;
    // Keep the arithmetic finite for culled Gaussians (their results are discarded).
    let norm = select(valid, quat_norm, 1.0);
    let (qw, qx, qy, qz) = (qw0 / norm, qx0 / norm, qy0 / norm, qz0 / norm);
    let rot_q = rotation_from_quat(qw, qx, qy, qz);
    let (s0, s1, s2) = (scales[i * 3], scales[i * 3 + 1], scales[i * 3 + 2]);
    let m = M3 {
        r0: v3(rot_q.r0.x * s0, rot_q.r0.y * s1, rot_q.r0.z * s2),
        r1: v3(rot_q.r1.x * s0, rot_q.r1.y * s1, rot_q.r1.z * s2),
        r2: v3(rot_q.r2.x * s0, rot_q.r2.y * s1, rot_q.r2.z * s2),
    };
    let cov_world = mul(&m, &transpose(&m));
    let cov_cam = mul(&mul(&r, &cov_world), &transpose(&r));

    let zs = select(valid, z, 1.0);
    let (x_over_z, y_over_z) = (p_cam.x / zs, p_cam.y / zs);
    let (lim_x_pos, lim_x_neg) = (camera[18], camera[19]);
    let (lim_y_pos, lim_y_neg) = (camera[20], camera[21]);
    let x_clamped = !(x_over_z >= -lim_x_neg && x_over_z <= lim_x_pos);
    let y_clamped = !(y_over_z >= -lim_y_neg && y_over_z <= lim_y_pos);
    let tx = zs * f32::clamp(x_over_z, -lim_x_neg, lim_x_pos);
    let ty = zs * f32::clamp(y_over_z, -lim_y_neg, lim_y_pos);
    let (fx, fy) = (camera[12], camera[13]);
    let j0 = v3(fx / zs, 0.0, -fx * tx / (zs * zs));
    let j1 = v3(0.0, fy / zs, -fy * ty / (zs * zs));
    let cj0 = mul_vec(&cov_cam, &j0);
    let cj1 = mul_vec(&cov_cam, &j1);
    let sxx = dot(&j0, &cj0) + EPS2D;
    let sxy = dot(&j0, &cj1);
    let syy = dot(&j1, &cj1) + EPS2D;
    Intermediates {
        p_cam,
        qw,
        qx,
        qy,
        qz,
        quat_norm,
        rot_q,
        m,
        cov_cam,
        j0,
        j1,
        x_clamped,
        y_clamped,
        sxx,
        sxy,
        syy,
        valid,
    }
}

/// The CPU twin's `participates` and `all_finite`: gated, or any non-finite input, culls.
#[cube]
fn inputs_usable(
    means: &Tensor<f32>,
    quats: &Tensor<f32>,
    scales: &Tensor<f32>,
    opacity: f32,
    gate: f32,
    colors: &Tensor<f32>,
    i: usize,
) -> bool {
    let mut ok = gate != 0.0 && finite(gate) && finite(opacity);
    #[unroll]
    for k in 0..3usize {
        ok = ok
            && finite(means[i * 3 + k])
            && finite(scales[i * 3 + k])
            && finite(colors[i * 3 + k]);
    }
    #[unroll]
    for k in 0..4usize {
        ok = ok && finite(quats[i * 4 + k]);
    }
    ok
}

#[cube(launch)]
fn project_kernel(
    means: &Tensor<f32>,
    quats: &Tensor<f32>,
    scales: &Tensor<f32>,
    opacities: &Tensor<f32>,
    gates: &Tensor<f32>,
    colors: &Tensor<f32>,
    camera: &Tensor<f32>,
    out: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= opacities.len() {
        terminate!();
    }
    #[unroll]
    for k in 0..PROJECTED_COLUMNS {
        out[i * PROJECTED_COLUMNS + k] = 0.0;
    }
    let opacity = gates[i] * opacities[i];
    if inputs_usable(means, quats, scales, opacity, gates[i], colors, i) && opacity >= ALPHA_MIN {
        let it = intermediates(means, quats, scales, camera, i);
        let det = it.sxx * it.syy - it.sxy * it.sxy;
        if it.valid && finite(det) && det > 0.0 {
            let (fx, fy, cx, cy) = (camera[12], camera[13], camera[14], camera[15]);
            let mean_x = fx * it.p_cam.x / it.p_cam.z + cx;
            let mean_y = fy * it.p_cam.y / it.p_cam.z + cy;
            // Opacity-aware extent: alpha < 1/255 outside the box.
            let extent = f32::min(
                MAX_EXTENT_SIGMAS,
                f32::sqrt(2.0 * f32::ln(opacity / ALPHA_MIN)),
            );
            let rx = f32::ceil(extent * f32::sqrt(it.sxx));
            let ry = f32::ceil(extent * f32::sqrt(it.syy));
            let (width, height) = (camera[16], camera[17]);
            let all_finite = finite(rx) && finite(ry) && finite(mean_x) && finite(mean_y);
            let on_screen = mean_x + rx > 0.0
                && mean_x - rx < width
                && mean_y + ry > 0.0
                && mean_y - ry < height;
            if all_finite && on_screen && (rx > 0.0 || ry > 0.0) {
                let row = i * PROJECTED_COLUMNS;
                out[row + col::MEAN2D_X] = mean_x;
                out[row + col::MEAN2D_Y] = mean_y;
                out[row + col::CONIC_A] = it.syy / det;
                out[row + col::CONIC_B] = -it.sxy / det;
                out[row + col::CONIC_C] = it.sxx / det;
                out[row + col::DEPTH] = it.p_cam.z;
                out[row + col::RADIUS_X] = rx;
                out[row + col::RADIUS_Y] = ry;
            }
        }
    }
}

/// Gradient with respect to the raw quaternion from the gradient `g` (row-major) with respect to
/// the rotation matrix of its normalisation (`cpu::project::quat_backward`).
#[cube]
fn quat_backward(it: &Intermediates, g: &M3) -> (f32, f32, f32, f32) {
    let w = it.qw;
    let x = it.qx;
    let y = it.qy;
    let z = it.qz;
    let (dw, dx, dy, dz) = unit_quat_backward(w, x, y, z, g);
    let d = w * dw + x * dx + y * dy + z * dz;
    let n = it.quat_norm;
    (
        (dw - w * d) / n,
        (dx - x * d) / n,
        (dy - y * d) / n,
        (dz - z * d) / n,
    )
}

/// Per Gaussian: the input gradients from the accumulated splat gradients [N, 9]. Culled
/// Gaussians (zero radii) get exact zeros.
#[cube(launch)]
fn project_backward_kernel(
    means: &Tensor<f32>,
    quats: &Tensor<f32>,
    scales: &Tensor<f32>,
    gates: &Tensor<f32>,
    camera: &Tensor<f32>,
    projected: &Tensor<f32>,
    splat_grads: &Tensor<f32>,
    grad_means: &mut Tensor<f32>,
    grad_quats: &mut Tensor<f32>,
    grad_scales: &mut Tensor<f32>,
    grad_opacities: &mut Tensor<f32>,
    grad_colors: &mut Tensor<f32>,
    grad_means2d: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= gates.len() {
        terminate!();
    }
    let visible = projected[i * PROJECTED_COLUMNS + col::RADIUS_X] != 0.0
        || projected[i * PROJECTED_COLUMNS + col::RADIUS_Y] != 0.0;
    if !visible {
        #[unroll]
        for k in 0..3usize {
            grad_means[i * 3 + k] = 0.0;
            grad_scales[i * 3 + k] = 0.0;
            grad_colors[i * 3 + k] = 0.0;
        }
        #[unroll]
        for k in 0..4usize {
            grad_quats[i * 4 + k] = 0.0;
        }
        grad_opacities[i] = 0.0;
        grad_means2d[i * 2] = 0.0;
        grad_means2d[i * 2 + 1] = 0.0;
        terminate!();
    }
    let s = i * SPLAT_GRAD_COLUMNS;
    let vmx = splat_grads[s];
    let vmy = splat_grads[s + 1];
    let va = splat_grads[s + 2];
    let vb = splat_grads[s + 3];
    let vc = splat_grads[s + 4];
    grad_means2d[i * 2] = vmx;
    grad_means2d[i * 2 + 1] = vmy;
    // opacity_eff = gate · opacity; the gate is a constant.
    grad_opacities[i] = gates[i] * splat_grads[s + 5];
    #[unroll]
    for k in 0..3usize {
        grad_colors[i * 3 + k] = splat_grads[s + 6 + k];
    }

    let it = intermediates(means, quats, scales, camera, i);
    let det = it.sxx * it.syy - it.sxy * it.sxy;
    let a = it.syy / det;
    let b = -it.sxy / det;
    let c = it.sxx / det;
    // conic = cov2d⁻¹: d cov2d = −S⁻¹ G S⁻¹, G symmetric with half of the b gradient off the
    // diagonal (b appears twice in the quadratic form).
    let g00 = va;
    let g01 = 0.5 * vb;
    let g11 = vc;
    let p00 = a * g00 + b * g01;
    let p01 = a * g01 + b * g11;
    let p10 = b * g00 + c * g01;
    let p11 = b * g01 + c * g11;
    let gc00 = -(p00 * a + p01 * b);
    let gc01 = -(p00 * b + p01 * c);
    let gc10 = -(p10 * a + p11 * b);
    let gc11 = -(p10 * b + p11 * c);
    // cov2d = J cov_cam Jᵀ: d cov_cam = Jᵀ G J, d J = (G + Gᵀ) J cov_cam.
    let g_cov_cam = madd(
        &madd(
            &outer_scaled(&it.j0, &it.j0, gc00),
            &outer_scaled(&it.j0, &it.j1, gc01),
        ),
        &madd(
            &outer_scaled(&it.j1, &it.j0, gc10),
            &outer_scaled(&it.j1, &it.j1, gc11),
        ),
    );
    let cj0 = mul_vec(&it.cov_cam, &it.j0);
    let cj1 = mul_vec(&it.cov_cam, &it.j1);
    let g_j0 = add(&scaled(&cj0, gc00 + gc00), &scaled(&cj1, gc01 + gc10));
    let g_j1 = add(&scaled(&cj0, gc10 + gc01), &scaled(&cj1, gc11 + gc11));
    // cov_cam = R cov Rᵀ; cov = M Mᵀ; M = R_q diag(s).
    let r = camera_rotation(camera);
    let r_t = transpose(&r);
    let g_cov = mul(&mul(&r_t, &g_cov_cam), &r);
    let g_m = mul(&madd(&g_cov, &transpose(&g_cov)), &it.m);
    grad_scales[i * 3] = dot(&col0(&g_m), &col0(&it.rot_q));
    grad_scales[i * 3 + 1] = dot(&col1(&g_m), &col1(&it.rot_q));
    grad_scales[i * 3 + 2] = dot(&col2(&g_m), &col2(&it.rot_q));
    let s0 = scales[i * 3];
    let s1 = scales[i * 3 + 1];
    let s2 = scales[i * 3 + 2];
    let g_rot = M3 {
        r0: v3(g_m.r0.x * s0, g_m.r0.y * s1, g_m.r0.z * s2),
        r1: v3(g_m.r1.x * s0, g_m.r1.y * s1, g_m.r1.z * s2),
        r2: v3(g_m.r2.x * s0, g_m.r2.y * s1, g_m.r2.z * s2),
    };
    let (dw, dx, dy, dz) = quat_backward(&it, &g_rot);
    grad_quats[i * 4] = dw;
    grad_quats[i * 4 + 1] = dx;
    grad_quats[i * 4 + 2] = dy;
    grad_quats[i * 4 + 3] = dz;

    // Screen mean (unclamped x/z) and the Jacobian (clamped inside) as functions of p_cam.
    let x = it.p_cam.x;
    let y = it.p_cam.y;
    let z = it.p_cam.z;
    let fx = camera[12];
    let fy = camera[13];
    let mut gx = vmx * fx / z;
    let mut gy = vmy * fy / z;
    let mut gz = -(vmx * fx * x + vmy * fy * y) / (z * z);
    gz += -g_j0.x * fx / (z * z) - g_j1.y * fy / (z * z);
    if it.x_clamped {
        let tx = -it.j0.z * z * z / fx;
        gz += g_j0.z * fx * tx / (z * z * z);
    } else {
        gx += -g_j0.z * fx / (z * z);
        gz += g_j0.z * 2.0 * fx * x / (z * z * z);
    }
    if it.y_clamped {
        let ty = -it.j1.z * z * z / fy;
        gz += g_j1.z * fy * ty / (z * z * z);
    } else {
        gy += -g_j1.z * fy / (z * z);
        gz += g_j1.z * 2.0 * fy * y / (z * z * z);
    }
    let g_mean = mul_vec(&r_t, &v3(gx, gy, gz));
    grad_means[i * 3] = g_mean.x;
    grad_means[i * 3 + 1] = g_mean.y;
    grad_means[i * 3 + 2] = g_mean.z;
}

fn elemwise(client: &cubecl::client::Client, n: usize) -> (CubeCount, CubeDim) {
    let cube_dim = CubeDim::new_1d(256);
    (calculate_cube_count_elemwise(client, n, cube_dim), cube_dim)
}

/// Projects every Gaussian: [N, 8] rows (zeros where culled).
pub fn project(gaussians: &DeviceGaussians, camera: &CubeTensor) -> CubeTensor {
    let n = gaussians.len();
    let out = fresh_f32(&gaussians.means, vec![n, PROJECTED_COLUMNS]);
    if n == 0 {
        return out;
    }
    let client = gaussians.means.client.clone();
    let (count, dim) = elemwise(&client, n);
    project_kernel::launch(
        &client,
        count,
        dim,
        gaussians.means.clone().into_tensor_arg(),
        gaussians.quats.clone().into_tensor_arg(),
        gaussians.scales.clone().into_tensor_arg(),
        gaussians.opacities.clone().into_tensor_arg(),
        gaussians.gates.clone().into_tensor_arg(),
        gaussians.colors.clone().into_tensor_arg(),
        camera.clone().into_tensor_arg(),
        out.clone().into_tensor_arg(),
    );
    out
}

/// The projection backward: from the per-Gaussian splat gradients [N, 9] to input gradients.
pub fn project_backward(
    gaussians: &DeviceGaussians,
    camera: &CubeTensor,
    projected: &CubeTensor,
    splat_grads: &CubeTensor,
) -> DeviceGrads {
    let n = gaussians.len();
    let like = &gaussians.means;
    let grads = DeviceGrads {
        means: fresh_f32(like, vec![n, 3]),
        quats: fresh_f32(like, vec![n, 4]),
        scales: fresh_f32(like, vec![n, 3]),
        opacities: fresh_f32(like, vec![n]),
        colors: fresh_f32(like, vec![n, 3]),
        means2d: fresh_f32(like, vec![n, 2]),
    };
    if n == 0 {
        return grads;
    }
    let client = like.client.clone();
    let (count, dim) = elemwise(&client, n);
    project_backward_kernel::launch(
        &client,
        count,
        dim,
        gaussians.means.clone().into_tensor_arg(),
        gaussians.quats.clone().into_tensor_arg(),
        gaussians.scales.clone().into_tensor_arg(),
        gaussians.gates.clone().into_tensor_arg(),
        camera.clone().into_tensor_arg(),
        projected.clone().into_tensor_arg(),
        splat_grads.clone().into_tensor_arg(),
        grads.means.clone().into_tensor_arg(),
        grads.quats.clone().into_tensor_arg(),
        grads.scales.clone().into_tensor_arg(),
        grads.opacities.clone().into_tensor_arg(),
        grads.colors.clone().into_tensor_arg(),
        grads.means2d.clone().into_tensor_arg(),
    );
    grads
}
