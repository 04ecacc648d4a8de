//! The spawned Gaussians' centres as one op, forward and backward (a Burn backend extension: CPU
//! twin + CubeCL kernel).
//!
//! For anchor i with gated motion g·m (m = the motion head's 7 outputs, g the motion gate) and
//! slot k: μ_ik = a_i + g·m[0:3] + R(q)·(o_ik ⊙ s_i[0:3]), q = normalize(0.1·g·m[3:7] + (1, 0, 0, 0))
//! (spec §4.4, GIFStream's spawn). As Burn tensor ops this was ~40 ops each way on [M]-sized
//! columns (the quaternion's slices, the nine matrix entries and their stack), a batched 3×3
//! `matmul` over [M, 3, K] and two `swap_dims` copies around it, all on the step's one thread:
//! ~4-6 % of a CPU step (`perf`, issue 21). Here each anchor is one unit of work that writes its
//! K slots forward and sums their gradients backward (no atomics: an anchor owns its slots).
//!
//! Not the same bits as the tensor version (the matmul's sums were matrixmultiply's FMA order);
//! the tests compare values and gradients with the tensor version within rounding.

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

use crate::backend::{HostIo, assert_f32};
use crate::cpu::project::{at, rotation_from_quat, unit_quat_backward};

/// Columns of the motion head's output: translation (3), then the rotation quaternion's delta (4).
pub const MOTION_COLUMNS: usize = 7;
/// Columns of an anchor's activated scales: [0:3] scale the offsets, [3:6] the Gaussians.
pub const SCALE_COLUMNS: usize = 6;

/// The rotation of one anchor: its matrix (row-major), the unit quaternion (w, x, y, z) and the
/// norm it was divided by.
#[derive(Clone, Copy, Debug)]
struct AnchorRotation {
    r: [f32; 9],
    unit: [f32; 4],
    norm: f32,
}

/// R(normalize(0.1·g·m[3:7] + (1, 0, 0, 0))), the norm clamped at 1e-12 as `normalize_rows`.
#[inline(always)]
fn anchor_rotation(motion: &[f32], gate: f32) -> AnchorRotation {
    let q = [
        motion[3] * gate * 0.1 + 1.0,
        motion[4] * gate * 0.1,
        motion[5] * gate * 0.1,
        motion[6] * gate * 0.1,
    ];
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        .sqrt()
        .max(1e-12);
    let unit = q.map(|v| v / norm);
    let matrix = rotation_from_quat(unit);
    let r = std::array::from_fn(|e| at(&matrix, e / 3, e % 3));
    AnchorRotation { r, unit, norm }
}

/// One anchor's K centres into `out` [K·3].
#[inline(always)]
fn anchor_means(
    anchor: &[f32],
    offsets: &[f32],
    scales: &[f32],
    motion: &[f32],
    gate: f32,
    out: &mut [f32],
) {
    let rot = anchor_rotation(motion, gate);
    let r = rot.r;
    let centre = [0, 1, 2].map(|c| anchor[c] + motion[c] * gate);
    for (o, mean) in offsets.chunks_exact(3).zip(out.chunks_exact_mut(3)) {
        let l = [o[0] * scales[0], o[1] * scales[1], o[2] * scales[2]];
        for row in 0..3 {
            mean[row] =
                centre[row] + (r[row * 3] * l[0] + r[row * 3 + 1] * l[1] + r[row * 3 + 2] * l[2]);
        }
    }
}

/// One anchor's gradients from its slots' centre gradients `grad` [K·3]: into `d_anchor` [3],
/// `d_offsets` [K·3], `d_scales` [6] ([3:6] zero), `d_motion` [7]; returns ∂/∂gate.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn anchor_means_backward(
    offsets: &[f32],
    scales: &[f32],
    motion: &[f32],
    gate: f32,
    grad: &[f32],
    d_anchor: &mut [f32],
    d_offsets: &mut [f32],
    d_scales: &mut [f32],
    d_motion: &mut [f32],
) -> f32 {
    let rot = anchor_rotation(motion, gate);
    let r = rot.r;
    let mut sum = [0.0f32; 3];
    let mut d_r = [[0.0f32; 3]; 3];
    let mut d_s = [0.0f32; 3];
    for ((o, g), d_o) in offsets
        .chunks_exact(3)
        .zip(grad.chunks_exact(3))
        .zip(d_offsets.chunks_exact_mut(3))
    {
        let l = [o[0] * scales[0], o[1] * scales[1], o[2] * scales[2]];
        for row in 0..3 {
            sum[row] += g[row];
            for col in 0..3 {
                d_r[row][col] += g[row] * l[col];
            }
        }
        for col in 0..3 {
            // (Rᵀ g)[col]
            let d_l = r[col] * g[0] + r[3 + col] * g[1] + r[6 + col] * g[2];
            d_o[col] = d_l * scales[col];
            d_s[col] += d_l * o[col];
        }
    }
    d_anchor.copy_from_slice(&sum);
    d_scales[..3].copy_from_slice(&d_s);
    d_scales[3..].fill(0.0);
    let d_unit = unit_quat_backward(rot.unit, &d_r);
    // Through the normalisation (q/|q|); where the norm was clamped it is a constant.
    let [w, x, y, z] = rot.unit;
    let along = w * d_unit[0] + x * d_unit[1] + y * d_unit[2] + z * d_unit[3];
    let clamped = rot.norm <= 1e-12;
    let d_q = [0, 1, 2, 3].map(|j| {
        if clamped {
            d_unit[j] / rot.norm
        } else {
            (d_unit[j] - rot.unit[j] * along) / rot.norm
        }
    });
    // The gated motion g·m: translation `sum`, quaternion delta 0.1·d_q.
    let d_gated = [
        sum[0],
        sum[1],
        sum[2],
        d_q[0] * 0.1,
        d_q[1] * 0.1,
        d_q[2] * 0.1,
        d_q[3] * 0.1,
    ];
    let mut d_gate = 0.0;
    for c in 0..MOTION_COLUMNS {
        d_motion[c] = d_gated[c] * gate;
        d_gate += d_gated[c] * motion[c];
    }
    d_gate
}

/// Anchors per parallel task.
const ANCHOR_CHUNK: usize = 256;

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait SpawnMeansBackend: Backend {
    /// The [M·K, 3] centres, row i·K + k, of anchors [M, 3], offsets [M, K, 3], activated scales
    /// [M, 6], motion [M, 7] and motion gates [M].
    fn spawn_means(
        anchors: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// The VJP of [`Self::spawn_means`] for `grad` [M·K, 3]: the gradients of (anchors, offsets,
    /// scales, motion, gate), in that order, each shaped as its input (the anchors' positions
    /// do not enter them).
    fn spawn_means_backward(
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );
}

/// (M, K) of the inputs, after checking every shape against them.
fn check_shapes<T: TensorMetadata>(
    anchors: &T,
    offsets: &T,
    scales: &T,
    motion: &T,
    gate: &T,
) -> (usize, usize) {
    let dims = |t: &T| {
        let s = t.shape();
        (0..s.num_dims()).map(|d| s[d]).collect::<Vec<_>>()
    };
    let o = dims(offsets);
    assert!(
        o.len() == 3 && o[2] == 3,
        "spawn_means: offsets must be [M, K, 3], got {o:?}"
    );
    let (m, k) = (o[0], o[1]);
    for (name, t, want) in [
        ("anchors", anchors, vec![m, 3]),
        ("scales", scales, vec![m, SCALE_COLUMNS]),
        ("motion", motion, vec![m, MOTION_COLUMNS]),
        ("gate", gate, vec![m]),
    ] {
        assert_eq!(
            dims(t),
            want,
            "spawn_means: `{name}` does not fit offsets {o:?}"
        );
    }
    (m, k)
}

impl SpawnMeansBackend for NdArray {
    fn spawn_means(
        anchors: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (m, k) = check_shapes(&anchors, &offsets, &scales, &motion, &gate);
        assert_f32(&offsets, "spawn_means");
        let device = offsets.device();
        let [anchors, offsets, scales, motion, gate] =
            [anchors, offsets, scales, motion, gate].map(<NdArray as HostIo>::read_floats);
        let mut out = vec![0.0f32; m * k * 3];
        if k > 0 {
            out.par_chunks_mut(ANCHOR_CHUNK * k * 3)
                .enumerate()
                .for_each(|(c, chunk)| {
                    let first = c * ANCHOR_CHUNK;
                    for (j, means) in chunk.chunks_exact_mut(k * 3).enumerate() {
                        let i = first + j;
                        anchor_means(
                            &anchors[i * 3..i * 3 + 3],
                            &offsets[i * k * 3..(i + 1) * k * 3],
                            &scales[i * SCALE_COLUMNS..(i + 1) * SCALE_COLUMNS],
                            &motion[i * MOTION_COLUMNS..(i + 1) * MOTION_COLUMNS],
                            gate[i],
                            means,
                        );
                    }
                });
        }
        NdArray::float_from_data(TensorData::new(out, [m * k, 3]), &device)
    }

    fn spawn_means_backward(
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        assert_f32(&grad, "spawn_means_backward");
        let o = offsets.shape();
        let (m, k) = (o[0], o[1]);
        assert_eq!(
            grad.shape().num_elements(),
            m * k * 3,
            "spawn_means_backward: the gradient is not [M·K, 3]"
        );
        let device = offsets.device();
        let [offsets, scales, motion, gate, grad] =
            [offsets, scales, motion, gate, grad].map(<NdArray as HostIo>::read_floats);
        let mut d_anchors = vec![0.0f32; m * 3];
        let mut d_offsets = vec![0.0f32; m * k * 3];
        let mut d_scales = vec![0.0f32; m * SCALE_COLUMNS];
        let mut d_motion = vec![0.0f32; m * MOTION_COLUMNS];
        let mut d_gate = vec![0.0f32; m];
        if k > 0 {
            d_anchors
                .par_chunks_mut(ANCHOR_CHUNK * 3)
                .zip(d_offsets.par_chunks_mut(ANCHOR_CHUNK * k * 3))
                .zip(d_scales.par_chunks_mut(ANCHOR_CHUNK * SCALE_COLUMNS))
                .zip(d_motion.par_chunks_mut(ANCHOR_CHUNK * MOTION_COLUMNS))
                .zip(d_gate.par_chunks_mut(ANCHOR_CHUNK))
                .enumerate()
                .for_each(|(c, ((((d_a, d_o), d_s), d_m), d_g))| {
                    for (j, d_g) in d_g.iter_mut().enumerate() {
                        let i = c * ANCHOR_CHUNK + j;
                        *d_g = anchor_means_backward(
                            &offsets[i * k * 3..(i + 1) * k * 3],
                            &scales[i * SCALE_COLUMNS..(i + 1) * SCALE_COLUMNS],
                            &motion[i * MOTION_COLUMNS..(i + 1) * MOTION_COLUMNS],
                            gate[i],
                            &grad[i * k * 3..(i + 1) * k * 3],
                            &mut d_a[j * 3..j * 3 + 3],
                            &mut d_o[j * k * 3..(j + 1) * k * 3],
                            &mut d_s[j * SCALE_COLUMNS..(j + 1) * SCALE_COLUMNS],
                            &mut d_m[j * MOTION_COLUMNS..(j + 1) * MOTION_COLUMNS],
                        );
                    }
                });
        }
        let tensor = |v: Vec<f32>, shape: Vec<usize>| {
            NdArray::float_from_data(TensorData::new(v, shape), &device)
        };
        (
            tensor(d_anchors, vec![m, 3]),
            tensor(d_offsets, vec![m, k, 3]),
            tensor(d_scales, vec![m, SCALE_COLUMNS]),
            tensor(d_motion, vec![m, MOTION_COLUMNS]),
            tensor(d_gate, vec![m]),
        )
    }
}

impl SpawnMeansBackend for burn::backend::Cube {
    fn spawn_means(
        anchors: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, register};
        check_shapes(&anchors, &offsets, &scales, &motion, &gate);
        let client = offsets.client.clone();
        let [anchors, offsets, scales, motion, gate] =
            [anchors, offsets, scales, motion, gate].map(inner_float);
        register(
            &client,
            crate::cube::spawn_means::forward(anchors, offsets, scales, motion, gate),
        )
    }

    fn spawn_means_backward(
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        use crate::backend::fused::{inner_float, register};
        let client = offsets.client.clone();
        let [offsets, scales, motion, gate, grad] =
            [offsets, scales, motion, gate, grad].map(inner_float);
        let [anchors, offsets, scales, motion, gate] =
            crate::cube::spawn_means::backward(offsets, scales, motion, gate, grad)
                .map(|t| register(&client, t));
        (anchors, offsets, scales, motion, gate)
    }
}

#[derive(Debug)]
struct SpawnMeansBackward;

impl<B: SpawnMeansBackend> Backward<B, 5> for SpawnMeansBackward {
    /// (offsets, scales, motion, gate): the anchors' positions do not enter the gradients.
    type State = (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
    );

    fn backward(self, ops: Ops<Self::State, 5>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (offsets, scales, motion, gate) = ops.state;
        let (da, d_o, ds, dm, dg) = B::spawn_means_backward(offsets, scales, motion, gate, grad);
        let [pa, po, ps, pm, pg] = ops.parents;
        for (parent, g) in [(pa, da), (po, d_o), (ps, ds), (pm, dm), (pg, dg)] {
            if let Some(node) = parent {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

impl<B: SpawnMeansBackend, C: CheckpointStrategy> SpawnMeansBackend for Autodiff<B, C> {
    fn spawn_means(
        anchors: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let (anchors, a_node) = anchors.into_parts();
        let (offsets, o_node) = offsets.into_parts();
        let (scales, s_node) = scales.into_parts();
        let (motion, m_node) = motion.into_parts();
        let (gate, g_node) = gate.into_parts();
        match SpawnMeansBackward
            .prepare::<C>([a_node, o_node, s_node, m_node, g_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::spawn_means(
                    anchors,
                    offsets.clone(),
                    scales.clone(),
                    motion.clone(),
                    gate.clone(),
                );
                prep.finish((offsets, scales, motion, gate), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::spawn_means(anchors, offsets, scales, motion, gate))
            }
        }
    }

    fn spawn_means_backward(
        offsets: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        motion: FloatTensor<Self>,
        gate: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        // Only used as a backward: not differentiable itself.
        let (da, d_o, ds, dm, dg) = B::spawn_means_backward(
            Self::inner(offsets),
            Self::inner(scales),
            Self::inner(motion),
            Self::inner(gate),
            Self::inner(grad),
        );
        (
            Self::from_inner(da),
            Self::from_inner(d_o),
            Self::from_inner(ds),
            Self::from_inner(dm),
            Self::from_inner(dg),
        )
    }
}

/// The [M·K, 3] centres of the spawned Gaussians, row i·K + k for anchor i and slot k:
/// a_i + g_i·m_i[0:3] + R(normalize(0.1·g_i·m_i[3:7] + (1, 0, 0, 0)))·(o_ik ⊙ s_i[0:3]),
/// differentiable in every input (any backend, with or without autodiff).
///
/// `anchors` [M, 3], `offsets` [M, K, 3], `scales` [M, 6] (only [0:3] enter), `motion` [M, 7],
/// `gate` [M].
pub fn spawn_means(
    anchors: Tensor<2>,
    offsets: Tensor<3>,
    scales: Tensor<2>,
    motion: Tensor<2>,
    gate: Tensor<1>,
) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as SpawnMeansBackend>::spawn_means(
        anchors.into_dispatch(),
        offsets.into_dispatch(),
        scales.into_dispatch(),
        motion.into_dispatch(),
        gate.into_dispatch(),
    ))
}
