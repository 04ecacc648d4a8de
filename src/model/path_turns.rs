//! Trajectory turns derived from the anchors' paths (`model.trajectory_turn = "paths"`; not in
//! GIFStream or ACA-GS, see `model/view.rs` on trajectory turns).
//!
//! Why: trained by the gradient the turns do not find an object's turn, even on its true paths
//! (docs/results.md, Follow-up 20), and the rigid fit, which sets them when a knot opens, scores
//! shorter turns than the truth (Follow-up 46). The anchors' paths do realise the turn (the
//! knot search and the gradient carry each anchor to its place: the flying cube's within 6° of
//! its true turn at most frames, Follow-up 46), yet the Gaussians keep their frame-0 layout. A
//! turn read from the paths costs no bits and no parameters: the decoder derives the same turns
//! from the decoded trajectories.
//!
//! How: anchor a's turn at knot k is the rotation (Horn's method, weighted) that best carries
//! the anchor and its `model.knn` nearest neighbours at their canonical places (with every point
//! tied with the farthest of them, so that the decoder, which orders the anchors its own way,
//! finds the same: [`neighbourhoods`]) from their places at knot 0 to their places at knot k,
//! p + g·T_k (g the motion gate, T_k the knot's displacement), each point weighted by its motion
//! gate so that static neighbours, whose paths say nothing about a turn, count little. The
//! stored value is that rotation's vector divided by the anchor's gate, since spawning turns by
//! g·r (as it translates by g·T): the rendered turn is the fitted one. Knot 0 is the identity:
//! the offsets and the cov head already lay the Gaussians out there.

use glam::{Quat, Vec3};
use rayon::prelude::*;

use super::anchor_columns::{Column, FACTOR_COUNT, MOTION_GATE, TrajectoryTurn};
use super::anchors::AnchorSet;
use super::init::neighbourhoods;
use super::rotations::{best_rotation, rotation_vector_near};
use crate::host_math::sigmoid;

/// Below this motion gate an anchor does not turn: its rendered turn g·r would need r ≫ 1 to
/// carry any rotation, and an anchor this still has no path to read one from.
const TURNING_GATE_MIN: f32 = 1e-3;

/// Replaces the [`Column::Turn`] of a set whose turns are derived from its paths by the turns
/// its trajectories and neighbour lists imply. A no-op for other sets.
pub fn derive_path_turns(set: &mut AnchorSet) {
    let d = set.dims;
    if d.trajectory_turn != TrajectoryTurn::Paths || set.is_empty() {
        return;
    }
    let (width, knots, knn) = (d.trajectory_width(), d.trajectory_knots(), d.knn);
    let trajectory = set.host(Column::Trajectory);
    let gates: Vec<f32> = set
        .host(Column::Factors)
        .chunks_exact(FACTOR_COUNT)
        .map(|f| sigmoid(f[MOTION_GATE]))
        .collect();
    let positions = &set.positions;
    let neighbourhoods = neighbourhoods(positions, knn);
    let place = |i: usize, knot: usize| {
        let t = &trajectory[i * width + knot * 3..i * width + knot * 3 + 3];
        Vec3::from(positions[i]) + Vec3::new(t[0], t[1], t[2]) * gates[i]
    };
    let turns: Vec<f32> = (0..set.len())
        .into_par_iter()
        .flat_map_iter(|a| {
            let mut row = vec![0.0f32; width];
            let gate = gates[a];
            if gate >= TURNING_GATE_MIN && knn > 0 {
                let members: Vec<usize> = std::iter::once(a)
                    .chain(neighbourhoods[a].iter().map(|&j| j as usize))
                    .collect();
                let weights: Vec<f32> = members.iter().map(|&i| gates[i]).collect();
                let from: Vec<Vec3> = members.iter().map(|&i| place(i, 0)).collect();
                let mut previous = Vec3::ZERO;
                for knot in 1..knots {
                    let to: Vec<Vec3> = members.iter().map(|&i| place(i, knot)).collect();
                    let rotation = weighted_best_rotation(&from, &to, &weights);
                    previous = rotation_vector_near(rotation, previous);
                    row[knot * 3..knot * 3 + 3].copy_from_slice(&(previous / gate).to_array());
                }
            }
            row
        })
        .collect();
    set.set_host(Column::Turn, turns);
}

/// The rotation R minimising Σ w_i |R·(a_i − ā) − (b_i − b̄)|² with ā, b̄ the weighted centroids
/// (the identity where the points do not determine it).
pub fn weighted_best_rotation(a: &[Vec3], b: &[Vec3], weights: &[f32]) -> Quat {
    let total: f32 = weights.iter().sum();
    if !(total > 0.0) {
        return Quat::IDENTITY;
    }
    let centroid = |p: &[Vec3]| p.iter().zip(weights).map(|(&x, &w)| x * w).sum::<Vec3>() / total;
    let (ca, cb) = (centroid(a), centroid(b));
    let centred = |p: &[Vec3], c: Vec3| -> Vec<Vec3> {
        p.iter()
            .zip(weights)
            .map(|(&x, &w)| (x - c) * w.max(0.0).sqrt())
            .collect()
    };
    best_rotation(&centred(a, ca), &centred(b, cb))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::rotations::angle_of;

    #[test]
    fn weighted_rotation_ignores_a_weightless_outlier() {
        let cloud = [
            Vec3::new(0.3, 0.1, -0.2),
            Vec3::new(-0.4, 0.2, 0.1),
            Vec3::new(0.1, -0.5, 0.3),
            Vec3::new(0.2, 0.4, 0.5),
            Vec3::new(-0.1, -0.2, -0.4),
        ];
        let truth = Quat::from_axis_angle(Vec3::new(0.2, 0.9, -0.4).normalize(), 0.7);
        let shift = Vec3::new(1.0, -0.5, 0.25);
        let mut a = cloud.to_vec();
        let mut b: Vec<Vec3> = cloud.iter().map(|&p| truth * p + shift).collect();
        // A point that does not move with the others, with no weight.
        a.push(Vec3::new(2.0, 0.0, 0.0));
        b.push(Vec3::new(2.0, 0.0, 0.0));
        let weights = [1.0, 0.5, 2.0, 1.0, 1.0, 0.0];
        let fitted = weighted_best_rotation(&a, &b, &weights);
        assert!(angle_of(fitted * truth.inverse()) < 1e-4);
        // Weighted in, it bends the fit.
        let bent = weighted_best_rotation(&a, &b, &[1.0; 6]);
        assert!(angle_of(bent * truth.inverse()) > 1e-2);
    }
}
