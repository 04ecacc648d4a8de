//! Trajectory turns derived from the anchors' paths (`model.trajectory_turn = "paths"` or
//! `"objects"`; not in GIFStream or ACA-GS, see `model/view.rs` on trajectory turns).
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
//!
//! `"paths"` measured worse (docs/results.md, Follow-up 47): seven anchors' noisy paths do not
//! determine a rotation, and static anchors turned by their noise. `model.trajectory_turn =
//! "objects"` therefore derives one turn per moving object ([`object_turns`]): the anchors whose
//! paths stay together are grouped, each group turns by the one rotation that carries all its
//! members, and anchors on nothing that moves do not turn.

use glam::{Quat, Vec3};
use rayon::prelude::*;

use super::anchor_columns::{Column, FACTOR_COUNT, MOTION_GATE, TrajectoryTurn};
use super::anchors::AnchorSet;
use super::init::neighbourhoods;
use super::inputs::GATE_THRESHOLD;
use super::object_clusters::object_clusters_linked;
use super::rotations::{best_rotation, rotation_vector_near};
use crate::host_math::sigmoid;

/// Below this motion gate an anchor does not turn: its rendered turn g·r would need r ≫ 1 to
/// carry any rotation, and an anchor this still has no path to read one from.
const TURNING_GATE_MIN: f32 = 1e-3;

/// `"objects"`: two anchors are linked when their places at knot 0 lie within this of each other
/// (world units; single linkage), `train.rigid_fit_link`'s default, with which the rigid fit
/// groups the anchors at one knot's frame.
pub const OBJECT_LINK: f32 = 0.15;

/// `"objects"`: ... and stay within this of each other at every knot, so that two objects that
/// touch at knot 0 (an object and the floor it rests on, two that cross later) part. Measured on
/// `crossing`'s paths (`examples/object_groups.rs`, Follow-up 49): with 0.15 (the link itself)
/// the paths' own noise (a tenth to a third of a unit, Follow-up 19) broke the flying cube into
/// fragments of 20-30 anchors; with 0.3 it is one group of 287 anchors whose rotation is within
/// 1-6° of the cube's true turn at every knot; with 0.5 it merges with its neighbours (730
/// anchors, whose rotation explains 0.12 and reaches 106° of 180°).
pub const OBJECT_PART: f32 = 0.3;

/// `"objects"`: fewest anchors whose common turn is derived; a smaller group keeps no turn (its
/// paths do not pin a rotation, Follow-up 47's neighbourhoods of seven).
pub const MIN_OBJECT_ANCHORS: usize = 16;

/// `"objects"`: an anchor whose path leaves its knot-0 place by less than this (world units) at
/// every knot is not on anything moving and does not turn.
pub const OBJECT_TRAVEL_MIN: f32 = 0.05;

/// `"objects"`: a group turns only if its rotation explains at least this share of what its
/// paths leave unexplained by a translation alone (summed over the knots, weighted by the
/// gates). The room's anchors drift by the gradient's noise and chain into groups of hundreds
/// whose best rotation, a few degrees of noise (explained share 0.00-0.05 on `crossing`), would
/// move their Gaussians by their offsets; the objects that do turn explain 0.45 (the slow cube,
/// 48° of its 60°) and 0.73 (the flying cube) (Follow-up 49).
pub const OBJECT_TURN_EXPLAINS: f32 = 0.4;

/// Replaces the [`Column::Turn`] of a set whose turns are derived from its paths
/// ([`TrajectoryTurn::is_derived`]) by the turns its trajectories (and, for `"paths"`, its
/// neighbour lists) imply. A no-op for other sets. Returns, under `"objects"`, the groups found,
/// largest first.
pub fn derive_path_turns(set: &mut AnchorSet) -> Vec<ObjectTurn> {
    let d = set.dims;
    if !d.trajectory_turn.is_derived() || set.is_empty() {
        return Vec::new();
    }
    let paths = Paths::read(set);
    let (turns, objects) = match d.trajectory_turn {
        TrajectoryTurn::Objects => object_turns(&paths, OBJECT_PART),
        _ => (
            neighbourhood_turns(&paths, &neighbourhoods(&set.positions, d.knn)),
            Vec::new(),
        ),
    };
    set.set_host(Column::Turn, turns);
    objects
}

/// The groups `"objects"` finds on `set`'s paths (whatever its own `trajectory_turn`) with
/// `part` as the parting distance ([`OBJECT_PART`] in training), largest first; for
/// `examples/object_groups.rs`.
pub fn object_groups(set: &AnchorSet, part: f32) -> Vec<ObjectTurn> {
    if set.is_empty() || set.dims.trajectory_knots() == 0 {
        return Vec::new();
    }
    object_turns(&Paths::read(set), part).1
}

/// One group of anchors `"objects"` found, whether it turns or not.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectTurn {
    pub anchors: usize,
    /// Its anchors' centre at the first and at the last knot.
    pub centres: [[f32; 3]; 2],
    /// The share of its paths' residual after a translation that its rotation explains.
    pub explained: f32,
    /// Whether it turns ([`OBJECT_TURN_EXPLAINS`]).
    pub turns: bool,
    /// Its rotation's angle at each knot, degrees.
    pub degrees: Vec<f32>,
}

impl std::fmt::Display for ObjectTurn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let degrees: Vec<String> = self.degrees.iter().map(|d| format!("{d:.0}")).collect();
        let [a, b] = self.centres;
        write!(
            f,
            "{} anchors at ({:.2}, {:.2}, {:.2}) -> ({:.2}, {:.2}, {:.2}), {} (explains {:.2}): {} \
             deg",
            self.anchors,
            a[0],
            a[1],
            a[2],
            b[0],
            b[1],
            b[2],
            if self.turns { "turns" } else { "still" },
            self.explained,
            degrees.join(" ")
        )
    }
}

/// The anchors' places along their knots, p + g·T_k, and their motion gates g.
struct Paths {
    knots: usize,
    gates: Vec<f32>,
    /// [anchor][knot] place.
    places: Vec<Vec<Vec3>>,
}

impl Paths {
    fn read(set: &AnchorSet) -> Self {
        let d = set.dims;
        let (width, knots) = (d.trajectory_width(), d.trajectory_knots());
        let trajectory = set.host(Column::Trajectory);
        let gates: Vec<f32> = set
            .host(Column::Factors)
            .chunks_exact(FACTOR_COUNT)
            .map(|f| sigmoid(f[MOTION_GATE]))
            .collect();
        let places = (0..set.len())
            .map(|a| {
                let p = Vec3::from(set.positions[a]);
                trajectory[a * width..(a + 1) * width]
                    .chunks_exact(3)
                    .map(|t| p + Vec3::new(t[0], t[1], t[2]) * gates[a])
                    .collect()
            })
            .collect();
        Paths {
            knots,
            gates,
            places,
        }
    }

    fn len(&self) -> usize {
        self.gates.len()
    }

    fn width(&self) -> usize {
        3 * self.knots
    }

    /// The rotation vectors, knot by knot (knot 0 the identity), of the weighted rotation that
    /// best carries `members` from their places at knot 0 to those at each knot, each continuous
    /// with the previous knot's.
    fn rotations_of(&self, members: &[usize]) -> Vec<Vec3> {
        self.rigid_motion_of(members).0
    }

    /// [`Self::rotations_of`], and the share of the weighted squared residual that a translation
    /// alone leaves (summed over the knots) which the rotations explain (1: the paths are that
    /// rigid motion; 0: turning does not help; 0 where the paths are a translation).
    fn rigid_motion_of(&self, members: &[usize]) -> (Vec<Vec3>, f32) {
        let weights: Vec<f32> = members.iter().map(|&i| self.gates[i]).collect();
        let centred_at = |knot: usize| {
            let places: Vec<Vec3> = members.iter().map(|&i| self.places[i][knot]).collect();
            weighted_centred(&places, &weights)
        };
        let mut rotations = vec![Vec3::ZERO; self.knots];
        // Weightless members determine no rotation.
        let Some(from) = centred_at(0) else {
            return (rotations, 0.0);
        };
        let mut previous = Vec3::ZERO;
        let (mut translated, mut turned) = (0.0f64, 0.0f64);
        for (knot, rotation) in rotations.iter_mut().enumerate().skip(1) {
            let to = centred_at(knot).expect("the same weights at every knot");
            let fitted = centred_best_rotation(&from, &to, &weights);
            for ((b, a), &w) in to.iter().zip(&from).zip(&weights) {
                translated += f64::from(w * (*b - *a).length_squared());
                turned += f64::from(w * (*b - fitted * *a).length_squared());
            }
            previous = rotation_vector_near(fitted, previous);
            *rotation = previous;
        }
        let explained = if translated > 0.0 {
            (1.0 - turned / translated) as f32
        } else {
            0.0
        };
        (rotations, explained)
    }
}

/// `"paths"`: each anchor's turn is the rotation of itself and its neighbours.
fn neighbourhood_turns(paths: &Paths, neighbourhoods: &[Vec<u32>]) -> Vec<f32> {
    let width = paths.width();
    (0..paths.len())
        .into_par_iter()
        .flat_map_iter(|a| {
            let mut row = vec![0.0f32; width];
            let gate = paths.gates[a];
            if gate >= TURNING_GATE_MIN && !neighbourhoods[a].is_empty() {
                let members: Vec<usize> = std::iter::once(a)
                    .chain(neighbourhoods[a].iter().map(|&j| j as usize))
                    .collect();
                for (knot, r) in paths.rotations_of(&members).iter().enumerate() {
                    row[knot * 3..knot * 3 + 3].copy_from_slice(&(*r / gate).to_array());
                }
            }
            row
        })
        .collect()
}

/// `"objects"`: the anchors that travel ([`OBJECT_TRAVEL_MIN`]) with an open enough gate are
/// grouped by their paths ([`OBJECT_LINK`] at knot 0, [`OBJECT_PART`] at every knot); each group
/// of at least [`MIN_OBJECT_ANCHORS`] whose rotation explains its paths
/// ([`OBJECT_TURN_EXPLAINS`]) turns by that one rotation, the others not at all. Why per object:
/// a neighbourhood of seven anchors about a voxel apart, each path a tenth of a unit off, does
/// not determine a rotation (the noise is as large as the lever arm), and static anchors turned
/// by their noise (Follow-up 47); hundreds of anchors over a whole object do.
fn object_turns(paths: &Paths, part: f32) -> (Vec<f32>, Vec<ObjectTurn>) {
    let (n, width) = (paths.len(), paths.width());
    let candidate: Vec<bool> = (0..n)
        .map(|a| {
            let start = paths.places[a][0];
            paths.gates[a] >= GATE_THRESHOLD
                && paths.places[a]
                    .iter()
                    .any(|&p| p.distance(start) >= OBJECT_TRAVEL_MIN)
        })
        .collect();
    let starts: Vec<[f32; 3]> = paths.places.iter().map(|p| p[0].to_array()).collect();
    let part2 = part * part;
    let together = |a: usize, b: usize| {
        paths.places[a]
            .iter()
            .zip(&paths.places[b])
            .all(|(p, q)| p.distance_squared(*q) <= part2)
    };
    let objects = object_clusters_linked(
        &starts,
        &candidate,
        OBJECT_LINK,
        MIN_OBJECT_ANCHORS,
        together,
    );
    let mut turns = vec![0.0f32; n * width];
    let motions: Vec<(Vec<Vec3>, f32)> = objects
        .par_iter()
        .map(|m| paths.rigid_motion_of(m))
        .collect();
    let mut report = Vec::with_capacity(objects.len());
    for (members, (rotations, explained)) in objects.iter().zip(&motions) {
        let turning = *explained >= OBJECT_TURN_EXPLAINS;
        let centre = |knot: usize| {
            (members.iter().map(|&a| paths.places[a][knot]).sum::<Vec3>() / members.len() as f32)
                .to_array()
        };
        report.push(ObjectTurn {
            anchors: members.len(),
            centres: [centre(0), centre(paths.knots - 1)],
            explained: *explained,
            turns: turning,
            degrees: rotations.iter().map(|r| r.length().to_degrees()).collect(),
        });
        if !turning {
            continue;
        }
        for &a in members {
            let gate = paths.gates[a];
            for (knot, r) in rotations.iter().enumerate() {
                turns[a * width + knot * 3..a * width + knot * 3 + 3]
                    .copy_from_slice(&(*r / gate).to_array());
            }
        }
    }
    report.sort_by_key(|o| std::cmp::Reverse(o.anchors));
    (turns, report)
}

/// The rotation R minimising Σ w_i |R·(a_i − ā) − (b_i − b̄)|² with ā, b̄ the weighted centroids
/// (the identity where the points do not determine it).
pub fn weighted_best_rotation(a: &[Vec3], b: &[Vec3], weights: &[f32]) -> Quat {
    match (weighted_centred(a, weights), weighted_centred(b, weights)) {
        (Some(a), Some(b)) => centred_best_rotation(&a, &b, weights),
        _ => Quat::IDENTITY,
    }
}

/// `p` less its `weights`-weighted centroid (`None` where the weights have no positive sum).
fn weighted_centred(p: &[Vec3], weights: &[f32]) -> Option<Vec<Vec3>> {
    let total: f32 = weights.iter().sum();
    if !(total > 0.0) {
        return None;
    }
    let centroid = p.iter().zip(weights).map(|(&x, &w)| x * w).sum::<Vec3>() / total;
    Some(p.iter().map(|&x| x - centroid).collect())
}

/// [`weighted_best_rotation`] of points already centred ([`weighted_centred`]).
fn centred_best_rotation(a: &[Vec3], b: &[Vec3], weights: &[f32]) -> Quat {
    let scaled = |p: &[Vec3]| -> Vec<Vec3> {
        p.iter()
            .zip(weights)
            .map(|(&x, &w)| x * w.max(0.0).sqrt())
            .collect()
    };
    best_rotation(&scaled(a), &scaled(b))
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
