//! Rigid motions of moving objects when a trajectory knot opens (`train.rigid_fit`; not in
//! GIFStream or ACA-GS, see `model/view.rs` on anchor trajectories and turns).
//!
//! Why: the knot search (`train/knot_search.rs`) and the gradient move each anchor by a
//! translation, and the trajectory turns, trained by the gradient, do not find an object's turn
//! even when the anchors sit on its true paths (docs/results.md, Follow-up 20). On
//! `synthetic:crossing` the cube's anchors therefore translate with its centre while it turns
//! 180°: their path error is what a pure translation leaves, and the faces' Gaussians keep their
//! frame-0 layout (Follow-up 19). Given the cube's true paths and turns the moving pixels gain
//! 3.9 dB (Follow-up 20). An object is rigid far more often than its anchors are independent,
//! and a rigid motion has six parameters where its anchors have hundreds, so the images pin it.
//!
//! How: the anchors on something moving at the previous knot's frame are grouped into objects
//! ([`crate::model::object_clusters`]: anchors closer than a link distance belong together). Each
//! object gets the rigid motion (a rotation about its centre and a translation) from the previous
//! knot's frame to the new knot's that the training images confirm best: each of its anchors, moved
//! by the motion, is probed camera by camera against what the same camera saw at its place in the
//! previous frame (`knot_search::SameViewProbe`) and, for half the score, at its place in the
//! object's origin (its anchors' oldest reference frame, where their places are the cameras' own,
//! so one interval's error is not inherited by the next; Follow-up 23), and the object's score is
//! the mean over its anchors of that disagreement, capped (`Trainer::fit_rigid_knot` in
//! `train/trainer/motion_search.rs`). Only anchors on a surface the cameras see (their colours
//! agree) and, among those, the object's oldest are scored: a point hidden behind a face, or one
//! seeded off the surface, is seen through as the point in front of it, which a translation keeps
//! in front and a turn does not, so such points pull the fit towards a translation. Not a trimmed
//! mean: a turn that is off moves only the anchors near the pattern's edges onto another colour,
//! the minority a trimmed mean drops (docs/results.md, Follow-up 21). The motion is found by a
//! pattern search ([`fit_motion`]) from a few starts: the previous interval's motion continued, the
//! best rigid fit of where the search left the anchors ([`best_rotation`], Horn's method), and that
//! translation alone, each also turned ±[`START_TURN`] about the three axes.

use crate::model::rotations::best_rotation;
use glam::{Quat, Vec3};
use rayon::prelude::*;

/// A rigid motion: p ↦ rotation·(p − centre) + centre + translation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidMotion {
    pub rotation: Quat,
    pub centre: Vec3,
    pub translation: Vec3,
}

impl RigidMotion {
    /// This motion turned further by `angle` (radians) about `axis` through its centre.
    pub fn turned(&self, axis: Vec3, angle: f32) -> Self {
        Self {
            rotation: (Quat::from_axis_angle(axis, angle) * self.rotation).normalize(),
            ..*self
        }
    }

    pub fn identity(centre: Vec3) -> Self {
        Self {
            rotation: Quat::IDENTITY,
            centre,
            translation: Vec3::ZERO,
        }
    }

    pub fn apply(&self, p: Vec3) -> Vec3 {
        self.rotation * (p - self.centre) + self.centre + self.translation
    }

    /// The least-squares rigid motion carrying `from[i]` to `to[i]` (rotation about `from`'s
    /// centroid), `None` for fewer than three points.
    pub fn fit(from: &[Vec3], to: &[Vec3]) -> Option<Self> {
        assert_eq!(from.len(), to.len());
        if from.len() < 3 {
            return None;
        }
        let n = from.len() as f32;
        let (cf, ct) = (
            from.iter().copied().sum::<Vec3>() / n,
            to.iter().copied().sum::<Vec3>() / n,
        );
        let a: Vec<Vec3> = from.iter().map(|p| *p - cf).collect();
        let b: Vec<Vec3> = to.iter().map(|p| *p - ct).collect();
        Some(Self {
            rotation: best_rotation(&a, &b),
            centre: cf,
            translation: ct - cf,
        })
    }

    /// The same motion (as a map) expressed about another centre.
    pub fn about(&self, centre: Vec3) -> Self {
        Self {
            rotation: self.rotation,
            centre,
            translation: self.apply(centre) - centre,
        }
    }
}

/// Each start is also turned by ± this angle (radians) about each axis: a knot interval's turn
/// that the starts miss by up to about this much is still reached.
pub const START_TURN: f32 = 0.3;

/// The pattern search's steps: the rotation's first (radians) and last; the translation's first
/// is the caller's and halves with the rotation's.
const FIRST_TURN_STEP: f32 = 0.1;
const LAST_TURN_STEP: f32 = 0.004;

/// The motion with the least `score` (lower is better; `None`: not scorable, never chosen) found
/// from each of `starts` and its turned copies ([`START_TURN`]) by a pattern search: the
/// motion moves by one step along each of the six axes (a turn about x, y, z at its centre, a
/// translation along x, y, z) to the best improving neighbour, and both steps halve when none
/// improves, down to [`LAST_TURN_STEP`]. Returns the motion and its score, `None` where no start
/// is scorable.
pub fn fit_motion(
    score: impl Fn(&RigidMotion) -> Option<f32> + Sync,
    starts: &[RigidMotion],
    translation_step: f32,
) -> Option<(RigidMotion, f32)> {
    let mut all = Vec::new();
    for m in starts {
        all.push(*m);
        for axis in [Vec3::X, Vec3::Y, Vec3::Z] {
            for sign in [-1.0, 1.0] {
                all.push(m.turned(axis, sign * START_TURN));
            }
        }
    }
    all.par_iter()
        .filter_map(|&start| descend(&score, start, FIRST_TURN_STEP, translation_step))
        .min_by(|x, y| x.1.total_cmp(&y.1))
}

/// The pattern search of [`fit_motion`] from each of `starts` alone (no turned copies), its
/// first rotation step `first_turn` (radians), the six neighbours of each step scored in
/// parallel: for a score that is costly and whose starts are already near (the rendered
/// refinement, `train/rendered_fit.rs`). Returns the best motion and its score.
pub fn refine_motion(
    score: impl Fn(&RigidMotion) -> Option<f32> + Sync,
    starts: &[RigidMotion],
    first_turn: f32,
    translation_step: f32,
) -> Option<(RigidMotion, f32)> {
    starts
        .iter()
        .filter_map(|&start| descend(&score, start, first_turn, translation_step))
        .min_by(|x, y| x.1.total_cmp(&y.1))
}

/// One pattern search from `start`: a step along each of the six axes (a turn about x, y, z at
/// the centre, a translation along x, y, z) to the best improving neighbour; both steps halve
/// when none improves, down to [`LAST_TURN_STEP`].
fn descend(
    score: &(impl Fn(&RigidMotion) -> Option<f32> + Sync),
    start: RigidMotion,
    first_turn: f32,
    translation_step: f32,
) -> Option<(RigidMotion, f32)> {
    let mut best = (start, score(&start)?);
    let (mut turn, mut shift) = (first_turn, translation_step);
    while turn >= LAST_TURN_STEP {
        let m = best.0;
        let neighbours: Vec<RigidMotion> = [Vec3::X, Vec3::Y, Vec3::Z]
            .into_iter()
            .flat_map(|axis| {
                [-1.0f32, 1.0].into_iter().flat_map(move |sign| {
                    [
                        m.turned(axis, sign * turn),
                        RigidMotion {
                            translation: m.translation + axis * (sign * shift),
                            ..m
                        },
                    ]
                })
            })
            .collect();
        // Scored in parallel, chosen in order (the first of equals, as a sequential search).
        let scores: Vec<Option<f32>> = neighbours.par_iter().map(|n| score(n)).collect();
        let improved = neighbours
            .into_iter()
            .zip(scores)
            .filter_map(|(n, s)| Some((n, s?)))
            .filter(|(_, s)| *s < best.1)
            .min_by(|x, y| x.1.total_cmp(&y.1));
        match improved {
            Some(better) => best = better,
            None => {
                turn *= 0.5;
                shift *= 0.5;
            }
        }
    }
    Some(best)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::rotations::angle_of;

    fn cloud() -> Vec<Vec3> {
        // An irregular cloud, so every rotation is determined.
        (0..40)
            .map(|i| {
                let f = i as f32;
                Vec3::new(
                    (f * 1.7).sin() * 0.4,
                    (f * 0.9).cos() * 0.3 + 0.1 * f / 40.0,
                    (f * 2.3).sin() * 0.2,
                ) + Vec3::new(1.0, -0.5, 3.0)
            })
            .collect()
    }

    #[test]
    fn horns_rotation_recovers_a_known_motion_also_near_a_half_turn() {
        let from = cloud();
        for (axis, angle) in [
            (Vec3::new(0.0, 0.87, -0.5), 0.3),
            (Vec3::new(1.0, 2.0, 3.0), 2.0),
            (Vec3::new(-0.2, 0.1, 1.0), 3.1),
            (Vec3::X, 0.0),
        ] {
            let truth = RigidMotion {
                rotation: Quat::from_axis_angle(axis.normalize(), angle),
                centre: Vec3::new(0.9, -0.4, 3.1),
                translation: Vec3::new(0.4, -0.2, 0.05),
            };
            let to: Vec<Vec3> = from.iter().map(|p| truth.apply(*p)).collect();
            let fitted = RigidMotion::fit(&from, &to).unwrap();
            let error = angle_of(fitted.rotation * truth.rotation.inverse());
            assert!(error < 1e-3, "axis {axis} angle {angle}: error {error}");
            for (p, q) in from.iter().zip(&to) {
                assert!(fitted.apply(*p).distance(*q) < 1e-4);
            }
        }
        // Too few points: none.
        assert!(RigidMotion::fit(&from[..2], &from[..2]).is_none());
    }

    #[test]
    fn a_motion_is_the_same_map_about_another_centre() {
        let m = RigidMotion {
            rotation: Quat::from_axis_angle(Vec3::Y, 0.7),
            centre: Vec3::new(1.0, 0.0, 0.0),
            translation: Vec3::new(0.0, 0.5, 0.0),
        };
        let other = m.about(Vec3::new(-2.0, 1.0, 4.0));
        for p in cloud() {
            assert!(m.apply(p).distance(other.apply(p)) < 1e-5);
        }
    }

    #[test]
    fn the_pattern_search_finds_a_turn_and_shift_its_starts_miss() {
        let from = cloud();
        let centre = from.iter().copied().sum::<Vec3>() / from.len() as f32;
        let truth = RigidMotion {
            rotation: Quat::from_axis_angle(Vec3::new(0.0, 0.87, -0.5).normalize(), 0.35),
            centre,
            translation: Vec3::new(0.3, -0.1, 0.05),
        };
        // Scored as the images would: how far each point lands from the truth, with a plateau
        // beyond 0.5 (a colour that no longer matches).
        let score = |m: &RigidMotion| {
            let d = from
                .iter()
                .map(|p| m.apply(*p).distance(truth.apply(*p)).min(0.5));
            Some(d.sum::<f32>() / from.len() as f32)
        };
        // The start: the translation alone (what a search by translations finds).
        let start = RigidMotion {
            rotation: Quat::IDENTITY,
            centre,
            translation: truth.translation,
        };
        let (fitted, s) = fit_motion(score, &[start], 0.1).unwrap();
        let error = angle_of(fitted.rotation * truth.rotation.inverse());
        assert!(error < 0.02, "turn error {error} rad (score {s})");
        assert!(fitted.translation.distance(truth.translation) < 0.02);
        // Nothing scorable: none.
        assert!(fit_motion(|_| None, &[start], 0.1).is_none());
    }
}
