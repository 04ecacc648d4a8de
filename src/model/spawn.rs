//! Neural-Gaussian spawning (spec §4.4): decoded anchor outputs → the rasterizer's per-Gaussian
//! inputs, differentiably.
//!
//! For anchor i and slot k: μ = anchor + Δxyz + R·(offset ⊙ s[0:3]) with
//! R = R(normalize(0.1·Δq + (1, 0, 0, 0))); scale = s[3:6] ⊙ sigmoid(cov[0:3]);
//! rotation = normalize(cov[3:7]) (the anchor rotation is not composed into it, as in
//! GIFStream); colour from the colour head; opacity from the Tanh head.
//!
//! With trajectory turns (`model.trajectory_turn`, not in GIFStream, see `view.rs`), the anchor's
//! gated turn Q = q(mf·r) also acts: μ = anchor + Δxyz + R(Q)·R·(offset ⊙ s[0:3]) and
//! rotation = Q ⊗ normalize(cov[3:7]), so a turning object's Gaussians keep their place and
//! orientation on its surface.
//!
//! Deviation in form, not in result: GIFStream drops slots with opacity ≤ 0 by boolean indexing
//! before rasterizing. Here every slot is kept and the rasterizer's gate is 0 for them: gated
//! Gaussians are removed before binning and get exactly zero gradient, so the render and the
//! gradients are the same, and shapes stay static (M·K rows).

use crate::raster::columns::{concat_columns, slice_columns};
use crate::raster::spawn_means::spawn_means;
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
    /// [M, 3] the trajectory's rotation vector at this frame before the motion gate, when the
    /// trajectories turn.
    pub turn: Option<Tensor<2>>,
}

/// Unit quaternions [M, 4] (w, x, y, z) of rotation vectors [M, 3] (axis × angle):
/// (cos θ/2, sin(θ/2)/θ · r). θ is taken as √(|r|² + 1e-12), so the zero vector gives the
/// identity with a finite gradient (sin(θ/2)/θ → ½).
pub fn rotation_vector_quaternions(r: Tensor<2>) -> Tensor<2> {
    let theta = ((r.clone() * r.clone()).sum_dim(1) + 1e-12).sqrt(); // [M, 1]
    let half = theta.clone() * 0.5;
    let imaginary = r * (half.clone().sin() / theta);
    concat_columns(half.cos(), imaginary)
}

/// Hamilton products a ⊗ b of quaternion rows [n, 4] (w, x, y, z): the rotation b, then a.
pub fn quaternion_products(a: Tensor<2>, b: Tensor<2>) -> Tensor<2> {
    let [n, _] = a.dims();
    let col = |t: &Tensor<2>, i: usize| slice_columns(t.clone(), i..i + 1).reshape([n]);
    let (w1, x1, y1, z1) = (col(&a, 0), col(&a, 1), col(&a, 2), col(&a, 3));
    let (w2, x2, y2, z2) = (col(&b, 0), col(&b, 1), col(&b, 2), col(&b, 3));
    let entries = vec![
        w1.clone() * w2.clone()
            - x1.clone() * x2.clone()
            - y1.clone() * y2.clone()
            - z1.clone() * z2.clone(),
        w1.clone() * x2.clone() + x1.clone() * w2.clone() + y1.clone() * z2.clone()
            - z1.clone() * y2.clone(),
        w1.clone() * y2.clone() - x1.clone() * z2.clone()
            + y1.clone() * w2.clone()
            + z1.clone() * x2.clone(),
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ];
    Tensor::stack::<2>(entries, 1)
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

/// The centres with the trajectory's turn `turn` [M, 4] composed into the motion's rotation, as
/// tensor ops (turns are off by default; `spawn_means` covers the default path).
fn turned_means(inputs: &SpawnInputs, decoded: &DecodedAnchors, turn: Tensor<2>) -> Tensor<2> {
    let [m, k, _] = inputs.offsets.dims();
    let motion = decoded.motion.clone() * inputs.motion_gate.clone().reshape([m, 1]);
    let translation = slice_columns(motion.clone(), 0..3);
    let identity = Tensor::<2>::zeros([m, 4], &motion.device()).slice_fill(s![.., 0..1], 1.0);
    let rotation = rotation_matrices(slice_columns(motion, 3..7) * 0.1 + identity);
    let rotation = rotation_matrices(turn).matmul(rotation);
    // R · (offset ⊙ s[0:3]) for every slot: [M, 3, 3] x [M, 3, K].
    let offset_scale = slice_columns(inputs.scales.clone(), 0..3).reshape([m, 1, 3]);
    let local = (inputs.offsets.clone() * offset_scale).swap_dims(1, 2);
    let rotated = rotation.matmul(local).swap_dims(1, 2); // [M, K, 3]
    let centres = (inputs.anchors.clone() + translation).reshape([m, 1, 3]);
    (rotated + centres).reshape([m * k, 3])
}

/// Spawns the M·K Gaussians of the visible anchors, row `i·K + k` for anchor i, slot k.
pub fn spawn(inputs: &SpawnInputs, decoded: &DecodedAnchors) -> GaussianTensors {
    let [m, k, _] = inputs.offsets.dims();
    let n = m * k;
    // The trajectory's turn, gated like its translation.
    let turn = inputs.turn.as_ref().map(|r| {
        rotation_vector_quaternions(r.clone() * inputs.motion_gate.clone().reshape([m, 1]))
    });
    let means = match &turn {
        // One op each way (issue 21: as tensor ops, the form `turned_means` keeps, this was ~40
        // small ops and a batched 3×3 matmul, 4-6 % of a CPU step); equal to them within
        // rounding (kernels/tests/spawn_means.rs).
        None => spawn_means(
            inputs.anchors.clone(),
            inputs.offsets.clone(),
            inputs.scales.clone(),
            decoded.motion.clone(),
            inputs.motion_gate.clone(),
        ),
        Some(q) => turned_means(inputs, decoded, q.clone()),
    };

    let cov = decoded.cov.clone().reshape([n, 7]);
    let base_scale = slice_columns(inputs.scales.clone(), 3..6).reshape([m, 1, 3]);
    let scales = (crate::raster::activation::sigmoid(slice_columns(cov.clone(), 0..3))
        .reshape([m, k, 3])
        * base_scale)
        .reshape([n, 3]);
    let quats = normalize_rows(slice_columns(cov, 3..7));
    let quats = match turn {
        Some(q) => {
            let per_slot = q.reshape([m, 1, 4]).expand([m, k, 4]).reshape([n, 4]);
            quaternion_products(per_slot, quats)
        }
        None => quats,
    };
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
