//! Neural-Gaussian spawning (spec §4.4): decoded anchor outputs → the rasterizer's per-Gaussian
//! inputs, differentiably.
//!
//! For anchor i and slot k: μ = anchor + Δxyz + R·(offset ⊙ s[0:3]) with
//! R = R(normalize(0.1·Δq + (1, 0, 0, 0))); scale = s[3:6] ⊙ sigmoid(cov[0:3]);
//! rotation = normalize(cov[3:7]) (the anchor rotation is not composed into it, as in
//! GIFStream); colour from the colour head; opacity from the Tanh head.
//!
//! Deviation in form, not in result: GIFStream drops slots with opacity ≤ 0 by boolean indexing
//! before rasterizing. Here every slot is kept and the rasterizer's gate is 0 for them: gated
//! Gaussians are removed before binning and get exactly zero gradient, so the render and the
//! gradients are the same, and shapes stay static (M·K rows).

use crate::raster::columns::slice_columns;
use burn::tensor::{Tensor, s};

use super::decoders::DecodedAnchors;
use crate::raster::GaussianTensors;

/// Per-anchor inputs of the visible anchors (M of them) at this view and time.
#[derive(Clone, Debug)]
pub struct SpawnInputs {
    /// [M, 3] world positions (canonical; anchors do not move).
    pub anchors: Tensor<2>,
    /// [M, K, 3] offsets in units of the anchor's offset scale.
    pub offsets: Tensor<3>,
    /// [M, 6] activated anchor scales: [0:3] scale the offsets, [3:6] the Gaussians (already
    /// multiplied by the pruning gate).
    pub scales: Tensor<2>,
    /// [M] motion gate mf (0 in the canonical phase).
    pub motion_gate: Tensor<1>,
}

/// Rotation matrices [M, 3, 3] of quaternions [M, 4] (w, x, y, z), normalised first.
pub fn rotation_matrices(quats: Tensor<2>) -> Tensor<3> {
    let [m, _] = quats.dims();
    let q = normalize_rows(quats);
    let col = |i: usize| slice_columns(q.clone(), i..i + 1).reshape([m]);
    let (w, x, y, z) = (col(0), col(1), col(2), col(3));
    let two = |a: Tensor<1>, b: Tensor<1>| (a * b) * 2.0;
    let entries = [
        -(two(y.clone(), y.clone()) + two(z.clone(), z.clone())) + 1.0,
        two(x.clone(), y.clone()) - two(w.clone(), z.clone()),
        two(x.clone(), z.clone()) + two(w.clone(), y.clone()),
        two(x.clone(), y.clone()) + two(w.clone(), z.clone()),
        -(two(x.clone(), x.clone()) + two(z.clone(), z.clone())) + 1.0,
        two(y.clone(), z.clone()) - two(w.clone(), x.clone()),
        two(x.clone(), z.clone()) - two(w.clone(), y.clone()),
        two(y.clone(), z.clone()) + two(w.clone(), x.clone()),
        -(two(x.clone(), x) + two(y.clone(), y)) + 1.0,
    ];
    Tensor::stack::<2>(entries.to_vec(), 1).reshape([m, 3, 3])
}

/// Rows scaled to unit length (a zero row stays zero rather than NaN).
pub fn normalize_rows(t: Tensor<2>) -> Tensor<2> {
    let norm = (t.clone() * t.clone()).sum_dim(1).sqrt().clamp_min(1e-12);
    t / norm
}

/// Spawns the M·K Gaussians of the visible anchors, row `i·K + k` for anchor i, slot k.
pub fn spawn(inputs: &SpawnInputs, decoded: &DecodedAnchors) -> GaussianTensors {
    let [m, k, _] = inputs.offsets.dims();
    let n = m * k;
    // Anchor motion, gated.
    let motion = decoded.motion.clone() * inputs.motion_gate.clone().reshape([m, 1]);
    let translation = slice_columns(motion.clone(), 0..3);
    let identity = Tensor::<2>::zeros([m, 4], &motion.device()).slice_fill(s![.., 0..1], 1.0);
    let rotation = rotation_matrices(slice_columns(motion, 3..7) * 0.1 + identity);
    // R · (offset ⊙ s[0:3]) for every slot: [M, 3, 3] x [M, 3, K].
    let offset_scale = slice_columns(inputs.scales.clone(), 0..3).reshape([m, 1, 3]);
    let local = (inputs.offsets.clone() * offset_scale).swap_dims(1, 2);
    let rotated = rotation.matmul(local).swap_dims(1, 2); // [M, K, 3]
    let centres = (inputs.anchors.clone() + translation).reshape([m, 1, 3]);
    let means = (rotated + centres).reshape([n, 3]);

    let cov = decoded.cov.clone().reshape([n, 7]);
    let base_scale = slice_columns(inputs.scales.clone(), 3..6).reshape([m, 1, 3]);
    let scales = (burn::tensor::activation::sigmoid(slice_columns(cov.clone(), 0..3))
        .reshape([m, k, 3])
        * base_scale)
        .reshape([n, 3]);
    let quats = normalize_rows(slice_columns(cov, 3..7));
    let opacities = decoded.opacity.clone().reshape([n]);
    // Slots with opacity <= 0 are not rendered (GIFStream's `selection`); constant gate.
    let gates = opacities.clone().detach().greater_elem(0.0).float();
    GaussianTensors {
        means,
        quats,
        scales,
        opacities,
        gates,
        colors: decoded.color.clone().reshape([n, 3]),
    }
}
