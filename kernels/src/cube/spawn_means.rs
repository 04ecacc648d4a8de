//! The spawned Gaussians' centres on the device, forward and backward: one unit per anchor, the
//! CPU twin's formulas (`spawn_means.rs`), looping over the anchor's K slots (an anchor owns its
//! slots, so the backward sums them without atomics). The rotation and its backward are the
//! projection's (`mat3`); the backward recomputes R(q) from the motion rather than keeping the
//! forward's [M, 9] (nine flops per anchor against a buffer written and read).

use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use cubecl::calculate_cube_count_elemwise;
use cubecl::prelude::*;

use super::buffers::fresh_f32;
use super::mat3::{M3, col0, col1, col2, dot, mul_vec, rotation_from_quat, unit_quat_backward, v3};

/// The unit quaternion (w, x, y, z) of anchor i and the norm it was divided by.
#[cube]
fn unit_quaternion(motion: &Tensor<f32>, gate: f32, i: usize) -> (f32, f32, f32, f32, f32) {
    let q0 = motion[i * 7 + 3] * gate * 0.1f32 + 1.0f32;
    let q1 = motion[i * 7 + 4] * gate * 0.1f32;
    let q2 = motion[i * 7 + 5] * gate * 0.1f32;
    let q3 = motion[i * 7 + 6] * gate * 0.1f32;
    let norm = f32::max(f32::sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12f32);
    (q0 / norm, q1 / norm, q2 / norm, q3 / norm, norm)
}

#[cube(launch)]
fn means_kernel(
    anchors: &Tensor<f32>,
    offsets: &Tensor<f32>,
    scales: &Tensor<f32>,
    motion: &Tensor<f32>,
    gate: &Tensor<f32>,
    slots: u32,
    out: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= gate.len() {
        terminate!();
    }
    let g = gate[i];
    let (w, x, y, z, _norm) = unit_quaternion(motion, g, i);
    let r = rotation_from_quat(w, x, y, z);
    let c0 = anchors[i * 3] + motion[i * 7] * g;
    let c1 = anchors[i * 3 + 1] + motion[i * 7 + 1] * g;
    let c2 = anchors[i * 3 + 2] + motion[i * 7 + 2] * g;
    let s0 = scales[i * 6];
    let s1 = scales[i * 6 + 1];
    let s2 = scales[i * 6 + 2];
    let k_count = slots as usize;
    for k in 0..k_count {
        let o = (i * k_count + k) * 3;
        let l = v3(offsets[o] * s0, offsets[o + 1] * s1, offsets[o + 2] * s2);
        let turned = mul_vec(&r, &l);
        out[o] = c0 + turned.x;
        out[o + 1] = c1 + turned.y;
        out[o + 2] = c2 + turned.z;
    }
}

#[cube(launch)]
fn means_backward_kernel(
    offsets: &Tensor<f32>,
    scales: &Tensor<f32>,
    motion: &Tensor<f32>,
    gate: &Tensor<f32>,
    grad: &Tensor<f32>,
    slots: u32,
    d_anchors: &mut Tensor<f32>,
    d_offsets: &mut Tensor<f32>,
    d_scales: &mut Tensor<f32>,
    d_motion: &mut Tensor<f32>,
    d_gate: &mut Tensor<f32>,
) {
    let i = ABSOLUTE_POS;
    if i >= gate.len() {
        terminate!();
    }
    let g = gate[i];
    let (w, x, y, z, norm) = unit_quaternion(motion, g, i);
    let r = rotation_from_quat(w, x, y, z);
    let s0 = scales[i * 6];
    let s1 = scales[i * 6 + 1];
    let s2 = scales[i * 6 + 2];
    let mut sum0 = 0.0f32;
    let mut sum1 = 0.0f32;
    let mut sum2 = 0.0f32;
    let mut d00 = 0.0f32;
    let mut d01 = 0.0f32;
    let mut d02 = 0.0f32;
    let mut d10 = 0.0f32;
    let mut d11 = 0.0f32;
    let mut d12 = 0.0f32;
    let mut d20 = 0.0f32;
    let mut d21 = 0.0f32;
    let mut d22 = 0.0f32;
    let mut ds0 = 0.0f32;
    let mut ds1 = 0.0f32;
    let mut ds2 = 0.0f32;
    let k_count = slots as usize;
    for k in 0..k_count {
        let o = (i * k_count + k) * 3;
        let o0 = offsets[o];
        let o1 = offsets[o + 1];
        let o2 = offsets[o + 2];
        let l0 = o0 * s0;
        let l1 = o1 * s1;
        let l2 = o2 * s2;
        let g0 = grad[o];
        let g1 = grad[o + 1];
        let g2 = grad[o + 2];
        sum0 += g0;
        sum1 += g1;
        sum2 += g2;
        d00 += g0 * l0;
        d01 += g0 * l1;
        d02 += g0 * l2;
        d10 += g1 * l0;
        d11 += g1 * l1;
        d12 += g1 * l2;
        d20 += g2 * l0;
        d21 += g2 * l1;
        d22 += g2 * l2;
        // Rᵀ g, column by column.
        let gv = v3(g0, g1, g2);
        let dl0 = dot(&col0(&r), &gv);
        let dl1 = dot(&col1(&r), &gv);
        let dl2 = dot(&col2(&r), &gv);
        d_offsets[o] = dl0 * s0;
        d_offsets[o + 1] = dl1 * s1;
        d_offsets[o + 2] = dl2 * s2;
        ds0 += dl0 * o0;
        ds1 += dl1 * o1;
        ds2 += dl2 * o2;
    }
    d_anchors[i * 3] = sum0;
    d_anchors[i * 3 + 1] = sum1;
    d_anchors[i * 3 + 2] = sum2;
    d_scales[i * 6] = ds0;
    d_scales[i * 6 + 1] = ds1;
    d_scales[i * 6 + 2] = ds2;
    d_scales[i * 6 + 3] = 0.0f32;
    d_scales[i * 6 + 4] = 0.0f32;
    d_scales[i * 6 + 5] = 0.0f32;
    let d_rotation = M3 {
        r0: v3(d00, d01, d02),
        r1: v3(d10, d11, d12),
        r2: v3(d20, d21, d22),
    };
    let (dw, dx, dy, dz) = unit_quat_backward(w, x, y, z, &d_rotation);
    // Through q/|q|; where the norm was clamped it is a constant.
    let mut along = w * dw + x * dx + y * dy + z * dz;
    if norm <= 1e-12f32 {
        along = 0.0f32;
    }
    let dq0 = (dw - w * along) / norm * 0.1f32;
    let dq1 = (dx - x * along) / norm * 0.1f32;
    let dq2 = (dy - y * along) / norm * 0.1f32;
    let dq3 = (dz - z * along) / norm * 0.1f32;
    d_motion[i * 7] = sum0 * g;
    d_motion[i * 7 + 1] = sum1 * g;
    d_motion[i * 7 + 2] = sum2 * g;
    d_motion[i * 7 + 3] = dq0 * g;
    d_motion[i * 7 + 4] = dq1 * g;
    d_motion[i * 7 + 5] = dq2 * g;
    d_motion[i * 7 + 6] = dq3 * g;
    d_gate[i] = sum0 * motion[i * 7]
        + sum1 * motion[i * 7 + 1]
        + sum2 * motion[i * 7 + 2]
        + dq0 * motion[i * 7 + 3]
        + dq1 * motion[i * 7 + 4]
        + dq2 * motion[i * 7 + 5]
        + dq3 * motion[i * 7 + 6];
}

/// (M, K) of the offsets [M, K, 3].
fn anchors_and_slots(offsets: &CubeTensor) -> (usize, usize) {
    let shape = offsets.meta.shape().to_vec();
    (shape[0], shape[1])
}

fn launch_dims(client_of: &CubeTensor, m: usize) -> (CubeCount, CubeDim) {
    let cube_dim = CubeDim::new_1d(64);
    (
        calculate_cube_count_elemwise(&client_of.client, m.max(1), cube_dim),
        cube_dim,
    )
}

pub fn forward(
    anchors: CubeTensor,
    offsets: CubeTensor,
    scales: CubeTensor,
    motion: CubeTensor,
    gate: CubeTensor,
) -> CubeTensor {
    let [anchors, offsets, scales, motion, gate] =
        [anchors, offsets, scales, motion, gate].map(into_contiguous);
    let (m, k) = anchors_and_slots(&offsets);
    let out = fresh_f32(&offsets, vec![m * k, 3]);
    if m > 0 && k > 0 {
        let (count, dim) = launch_dims(&offsets, m);
        means_kernel::launch(
            &offsets.client.clone(),
            count,
            dim,
            anchors.into_tensor_arg(),
            offsets.into_tensor_arg(),
            scales.into_tensor_arg(),
            motion.into_tensor_arg(),
            gate.into_tensor_arg(),
            k as u32,
            out.clone().into_tensor_arg(),
        );
    }
    out
}

/// Gradients of (anchors, offsets, scales, motion, gate).
pub fn backward(
    offsets: CubeTensor,
    scales: CubeTensor,
    motion: CubeTensor,
    gate: CubeTensor,
    grad: CubeTensor,
) -> [CubeTensor; 5] {
    let [offsets, scales, motion, gate, grad] =
        [offsets, scales, motion, gate, grad].map(into_contiguous);
    let (m, k) = anchors_and_slots(&offsets);
    let out = [vec![m, 3], vec![m, k, 3], vec![m, 6], vec![m, 7], vec![m]]
        .map(|shape| fresh_f32(&offsets, shape));
    if m > 0 {
        if k == 0 {
            // No slots: every gradient is zero (the kernel would write only the per-anchor ones).
            for t in &out {
                super::buffers::fill_words(t, 0);
            }
        } else {
            let (count, dim) = launch_dims(&offsets, m);
            let [d_anchors, d_offsets, d_scales, d_motion, d_gate] = out.clone();
            means_backward_kernel::launch(
                &offsets.client.clone(),
                count,
                dim,
                offsets.into_tensor_arg(),
                scales.into_tensor_arg(),
                motion.into_tensor_arg(),
                gate.into_tensor_arg(),
                grad.into_tensor_arg(),
                k as u32,
                d_anchors.into_tensor_arg(),
                d_offsets.into_tensor_arg(),
                d_scales.into_tensor_arg(),
                d_motion.into_tensor_arg(),
                d_gate.into_tensor_arg(),
            );
        }
    }
    out
}
