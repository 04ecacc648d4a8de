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
//! ([`object_clusters`]: anchors closer than a link distance belong together). Each object gets
//! the rigid motion (a rotation about its centre and a translation) from the previous knot's
//! frame to the new knot's that the training images confirm best: each of its anchors, moved by
//! the motion, is probed camera by camera against what the same camera saw at its place in the
//! previous frame (`knot_search::SameViewProbe`) and, for half the score, at its place in the
//! object's origin (its anchors' oldest reference frame, where their places are the cameras'
//! own, so one interval's error is not inherited by the next; Follow-up 23), and the object's
//! score is the mean over its anchors of that disagreement, capped (`Trainer::fit_rigid_knot` in
//! `train/trainer/motion_search.rs`). Only anchors on a surface the cameras see (their colours
//! agree) and, among those, the object's oldest are scored: a point hidden behind a face, or one
//! seeded off the surface, is seen through as the point in front of it, which a translation keeps
//! in front and a turn does not, so such points pull the fit towards a translation. Not a
//! trimmed mean: a turn that is off moves only the anchors near the pattern's edges onto another
//! colour, the minority a trimmed mean drops (docs/results.md, Follow-up 21). The motion is
//! found by a pattern search ([`fit_motion`]) from a few starts: the previous interval's motion
//! continued, the best rigid fit of where the search left the anchors ([`best_rotation`], Horn's
//! method), and that translation alone, each also turned ±[`START_TURN`] about the three axes.

use glam::{Quat, Vec3};
use rayon::prelude::*;
use std::collections::HashMap;

/// A rigid motion: p ↦ rotation·(p − centre) + centre + translation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidMotion {
    pub rotation: Quat,
    pub centre: Vec3,
    pub translation: Vec3,
}

impl RigidMotion {
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

/// The rotation R minimising Σ |R·a_i − b_i|² for centred point sets (Horn 1987: the unit
/// quaternion is the eigenvector of the largest eigenvalue of a symmetric 4×4 matrix built from
/// the cross-covariance). The identity where the points do not determine it.
pub fn best_rotation(a: &[Vec3], b: &[Vec3]) -> Quat {
    let mut s = [[0.0f64; 3]; 3];
    for (p, q) in a.iter().zip(b) {
        let (p, q) = (p.as_dvec3(), q.as_dvec3());
        let (p, q) = (p.to_array(), q.to_array());
        for (i, row) in s.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += p[i] * q[j];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = symmetric_eigen4(n);
    let best = (0..4)
        .max_by(|&i, &j| values[i].total_cmp(&values[j]))
        .expect("four eigenvalues");
    let [w, x, y, z] = std::array::from_fn(|r| vectors[r][best]);
    let q = Quat::from_xyzw(x as f32, y as f32, z as f32, w as f32);
    if q.length_squared().is_finite() && q.length_squared() > 0.5 {
        q.normalize()
    } else {
        Quat::IDENTITY
    }
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 4×4 matrix, by cyclic Jacobi
/// rotations.
fn symmetric_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..50 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let scale: f64 = (0..4).map(|i| a[i][i] * a[i][i]).sum::<f64>() + off;
        if off <= 1e-24 * scale.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                // A ← Jᵀ A J with J the rotation in the (p, q) plane.
                for k in 0..4 {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    (std::array::from_fn(|i| a[i][i]), v)
}

/// Groups the anchors with `candidate[a]` into objects: two belong together when their
/// `positions` lie within `link` of each other (single linkage); groups of fewer than
/// `min_members` are dropped. Members in ascending order, groups by their first member.
pub fn object_clusters(
    positions: &[[f32; 3]],
    candidate: &[bool],
    link: f32,
    min_members: usize,
) -> Vec<Vec<usize>> {
    assert_eq!(positions.len(), candidate.len());
    assert!(link > 0.0, "the link distance must be positive");
    let key = |p: &[f32; 3]| p.map(|v| (v / link).floor() as i64);
    let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for (a, p) in positions.iter().enumerate() {
        if candidate[a] {
            cells.entry(key(p)).or_default().push(a);
        }
    }
    let mut parent: Vec<usize> = (0..positions.len()).collect();
    fn root(parent: &mut [usize], mut a: usize) -> usize {
        while parent[a] != a {
            parent[a] = parent[parent[a]];
            a = parent[a];
        }
        a
    }
    let link2 = link * link;
    for (a, p) in positions.iter().enumerate() {
        if !candidate[a] {
            continue;
        }
        let k = key(p);
        for o in 0..27 {
            let off = [o % 3 - 1, (o / 3) % 3 - 1, o / 9 - 1];
            let Some(others) = cells.get(&[k[0] + off[0], k[1] + off[1], k[2] + off[2]]) else {
                continue;
            };
            for &b in others {
                if b <= a {
                    continue;
                }
                let q = positions[b];
                let d2: f32 = (0..3).map(|i| (p[i] - q[i]).powi(2)).sum();
                if d2 <= link2 {
                    let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
                    if ra != rb {
                        parent[ra.max(rb)] = ra.min(rb);
                    }
                }
            }
        }
    }
    let mut groups: HashMap<usize, Vec<usize>> = HashMap::new();
    for a in (0..positions.len()).filter(|&a| candidate[a]) {
        let r = root(&mut parent, a);
        groups.entry(r).or_default().push(a);
    }
    let mut groups: Vec<Vec<usize>> = groups
        .into_values()
        .filter(|g| g.len() >= min_members)
        .collect();
    groups.sort_by_key(|g| g[0]);
    groups
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
    let turned = |m: &RigidMotion, axis: Vec3, angle: f32| RigidMotion {
        rotation: (Quat::from_axis_angle(axis, angle) * m.rotation).normalize(),
        ..*m
    };
    let mut all = Vec::new();
    for m in starts {
        all.push(*m);
        for axis in [Vec3::X, Vec3::Y, Vec3::Z] {
            for sign in [-1.0, 1.0] {
                all.push(turned(m, axis, sign * START_TURN));
            }
        }
    }
    all.par_iter()
        .filter_map(|&start| {
            let mut best = (start, score(&start)?);
            let (mut turn, mut shift) = (FIRST_TURN_STEP, translation_step);
            while turn >= LAST_TURN_STEP {
                let m = best.0;
                let neighbours = [Vec3::X, Vec3::Y, Vec3::Z].into_iter().flat_map(|axis| {
                    [-1.0f32, 1.0].into_iter().flat_map(move |sign| {
                        [
                            turned(&m, axis, sign * turn),
                            RigidMotion {
                                translation: m.translation + axis * (sign * shift),
                                ..m
                            },
                        ]
                    })
                });
                let improved = neighbours
                    .filter_map(|n| Some((n, score(&n)?)))
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
        })
        .min_by(|x, y| x.1.total_cmp(&y.1))
}

/// The rotation vector (axis × angle) of `q` nearest `near` among its representatives
/// (axis × (angle + 2πk)), so that knots interpolated linearly turn the short way from the
/// previous knot's turn, also past a half turn.
pub fn rotation_vector_near(q: Quat, near: Vec3) -> Vec3 {
    let (axis, angle) = q.normalize().to_axis_angle();
    if !angle.is_finite() || angle.abs() < 1e-9 {
        // Identity: the representative 2πk·axis nearest `near`, along its own axis.
        let length = near.length();
        if length < std::f32::consts::PI {
            return Vec3::ZERO;
        }
        let k = (length / std::f32::consts::TAU).round();
        return near / length * (k * std::f32::consts::TAU);
    }
    // Every representative is axis × (angle + 2πk); −axis × (2π − angle) is k = −1.
    (-2..=2)
        .map(|k| axis * (angle + k as f32 * std::f32::consts::TAU))
        .min_by(|x, y| (*x - near).length().total_cmp(&(*y - near).length()))
        .expect("five representatives")
}

/// The angle (radians) of a rotation.
pub fn angle_of(q: Quat) -> f32 {
    // atan2, not acos(w): accurate near the identity in f32.
    2.0 * q.xyz().length().atan2(q.w.abs())
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn clusters_join_anchors_within_the_link_and_drop_small_groups() {
        // Two lines of anchors 0.1 apart, 1.0 from each other, and a pair.
        let mut positions = Vec::new();
        for i in 0..10 {
            positions.push([i as f32 * 0.1, 0.0, 0.0]);
        }
        for i in 0..6 {
            positions.push([i as f32 * 0.1, 1.0, 0.0]);
        }
        positions.push([5.0, 5.0, 5.0]);
        positions.push([5.05, 5.0, 5.0]);
        let mut candidate = vec![true; positions.len()];
        let groups = object_clusters(&positions, &candidate, 0.15, 3);
        assert_eq!(
            groups,
            vec![(0..10).collect::<Vec<_>>(), (10..16).collect()]
        );
        // A non-candidate breaks a chain.
        candidate[5] = false;
        let groups = object_clusters(&positions, &candidate, 0.15, 3);
        assert_eq!(
            groups,
            vec![vec![0, 1, 2, 3, 4], vec![6, 7, 8, 9], (10..16).collect()]
        );
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

    #[test]
    fn rotation_vectors_continue_past_a_half_turn() {
        let axis = Vec3::new(0.0, 0.6, 0.8);
        // A turn of 3.3 rad is stored by the quaternion as −(2π − 3.3) about the axis; near the
        // previous knot's 2.9 rad it reads back as 3.3 about the axis.
        let q = Quat::from_axis_angle(axis, 3.3);
        let v = rotation_vector_near(q, axis * 2.9);
        assert!((v - axis * 3.3).length() < 1e-4, "{v}");
        assert!(angle_of(Quat::from_scaled_axis(v) * q.inverse()) < 1e-4);
        // Near zero: the short way.
        let v = rotation_vector_near(Quat::from_axis_angle(axis, 0.2), Vec3::ZERO);
        assert!((v - axis * 0.2).length() < 1e-5);
        let v = rotation_vector_near(Quat::from_axis_angle(axis, -0.2), Vec3::ZERO);
        assert!((v + axis * 0.2).length() < 1e-5);
        // The identity near a full turn stays a full turn.
        let v = rotation_vector_near(Quat::IDENTITY, axis * 6.0);
        assert!((v - axis * std::f32::consts::TAU).length() < 1e-4, "{v}");
    }
}
