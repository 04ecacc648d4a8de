//! The trainer's photometric searches when a trajectory knot opens: re-finding anchors whose
//! moving object left them (`train.knot_search`, `train/knot_search.rs`) and seeding anchors on
//! objects no anchor covers (`train.appearance_seeding`, `train/appearance_seeding.rs`). Both read
//! the training images of one frame and the evaluation's motion mask; neither renders. The rigid
//! fit of moving objects (`train.rigid_fit`, `train/rigid_fit.rs`) probes them too, and under
//! `"rendered"` draws the model on the rasterizer's CPU twin (`train/rendered_fit.rs`).

mod knot_refit;

pub use knot_refit::KnotRefitReport;

use std::collections::{BTreeSet, HashSet};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::{Device, Float, Tensor, TensorData};
use glam::{Quat, Vec3};
use rayon::prelude::*;

use super::super::anchor_state::RowEdit;
use super::super::appearance_seeding::{SeedParams, SeedReport, seed_positions};
use super::super::knot_search::{
    ConsensusReport, FrameViews, Placement, SameViewProbe, SearchGrouping, SearchParams,
    SearchReport, median_shift, place_by_consensus, search_placements, seen_at,
};
use super::super::losses::moving_pixel_weights;
use super::super::rendered_fit::{RenderedScore, select};
use super::super::rigid_fit::{RigidMotion, fit_motion, refine_motion};
use super::Trainer;
use crate::config::{
    FittedKnots, KnotConsensus, KnotSearch, MovingGates, RigidFit, RigidFitGrouping,
};
use crate::data::ViewId;
use crate::data::frames::Frame;
use crate::device_io::upload;
use crate::eval::motion_mask::{median, motion_mask, temporal_median};
use crate::host_math::sigmoid;
use crate::model::anchors::{
    AnchorSet, Column, FACTOR_COUNT, MOTION_GATE, NewAnchors, SCALE_DIMS, host_values,
};
use crate::model::init::nearest_neighbors;
use crate::model::inputs::GATE_THRESHOLD;
use crate::model::object_clusters::{clusters_moved_as_one, object_clusters};
use crate::model::rotations::{angle_of, rotation_vector_near};
use crate::model::view::{Phase, ViewTime, decode_view, deformed_positions};
use crate::raster::RasterCamera;
use crate::raster::cpu::GaussianArrays;

/// What [`Trainer::search_knot`] did.
#[derive(Clone, Debug)]
pub struct KnotSearchOutcome {
    /// The frame whose images were searched (the knot's own, or the clip's last).
    pub frame: usize,
    /// Per anchor, the displacement at `frame` the knot change applied.
    pub applied: Vec<Option<[f32; 3]>>,
    /// `moved` counts the applied displacements (the consensus's included).
    pub report: SearchReport,
    /// What `train.knot_consensus` changed.
    pub consensus: ConsensusReport,
}

/// What [`Trainer::fit_rigid_knot`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RigidFitReport {
    /// Objects fitted, and their anchors.
    pub objects: usize,
    pub anchors: usize,
    /// Anchors moved by their object's motion (an object's anchor its cameras confirm where it
    /// stands, and not there, stays).
    pub moved: usize,
    /// The fitted motions' median turn over the knot interval.
    pub median_turn_degrees: f32,
}

/// Fewest anchors that `train.rigid_fit` fits a motion to: fewer are a fragment (a few anchors
/// of a shadow or an outline), whose motion the images do not pin.
const MIN_OBJECT_ANCHORS: usize = 16;

/// Most anchors of an object its motion is scored by (spread evenly over its members): enough to
/// pin six parameters, few enough that a knot's fit costs about a second.
const MAX_SCORED_ANCHORS: usize = 128;

/// What a turn of one radian adds to an object's score (a mean colour disagreement) under
/// `train.rigid_fit`: a tie-break, not a prior. The cube of `crossing` turns 0.31 rad per knot
/// interval, and the true turn scores 0.03-0.1 better than none, 10-30 times this cost.
const TURN_TIE: f32 = 0.01;

/// Under `train.rigid_fit = "rendered"`: the refinement's first rotation step (radians, 2.9°;
/// the probe fit leaves the flying cube of `crossing` 6-9° short per interval, Follow-up 50) and
/// its first translation step, as a share of the probe fit's.
const RENDERED_FIRST_TURN: f32 = 0.05;
const RENDERED_SHIFT_SHARE: f32 = 0.5;

/// Under `train.rigid_fit = "rendered"`: the refinement stays within this turn (radians, 17°)
/// and this shift (a share of the probe fit's translation step) of the probe fit's motion. On
/// `crossing` the unbounded search turned a fragment of 16 anchors 48° and shifted one of 24
/// anchors by 0.98: a motion that carries a poorly drawn fragment out of its crops scores better
/// than any that keeps it there.
const RENDERED_MAX_TURN: f32 = 0.3;
const RENDERED_MAX_SHIFT_SHARE: f32 = 1.0;

/// Under `train.rigid_fit = "rendered"`: fewest members of an object whose motion is refined.
/// Fragments of 16-32 anchors (a shadow's, an outline's) cover too few pixels to pin a turn:
/// their rendered scores changed by 1-2 % over turns of 10-48°.
const RENDERED_MIN_ANCHORS: usize = 128;

/// What the rendered refinement of one object's motion is drawn from: the model's Gaussians at
/// the interval's first and last frames (`per_anchor` rows per anchor), which anchors make the
/// object (the template), and the training cameras with the last frame's images.
struct RenderedInputs<'a> {
    at_previous: &'a GaussianArrays,
    at_frame: &'a GaussianArrays,
    per_anchor: usize,
    in_template: &'a [bool],
    rig: &'a [RasterCamera],
    targets: &'a [&'a Frame],
}

/// An object's motion refined against the rendered model, and its scores before and after.
struct RenderedRefinement {
    /// The score it was refined by (for the turn profile in the log).
    score: RenderedScore,
    refined: RigidMotion,
    before: f32,
    after: f32,
}

/// The rendered fit's refinement of `start`, bounded to [`RENDERED_MAX_TURN`] and
/// [`RENDERED_MAX_SHIFT_SHARE`] of `translation_step` from it (the turn and the shift of
/// `centre`): shared by the rigid fit when a knot opens and by `train.knot_refit`. `None` when no
/// camera sees the object or no motion within the bounds scores.
fn refine_rendered(
    inputs: RenderedInputs,
    start: RigidMotion,
    centre: Vec3,
    translation_step: f32,
) -> Option<RenderedRefinement> {
    let k = inputs.per_anchor.max(1);
    let score = RenderedScore::new(
        select(inputs.at_previous, |i| inputs.in_template[i / k]),
        &select(inputs.at_frame, |i| !inputs.in_template[i / k]),
        inputs.rig,
        inputs.targets,
        &start,
    );
    let before = score.score(&start)?;
    let max_shift = RENDERED_MAX_SHIFT_SHARE * translation_step;
    let within = |m: &RigidMotion| {
        angle_of(m.rotation * start.rotation.inverse()) <= RENDERED_MAX_TURN
            && (m.apply(centre) - start.apply(centre)).length() <= max_shift
    };
    let (refined, after) = refine_motion(
        |m| within(m).then(|| score.score(m)).flatten(),
        &[start],
        RENDERED_FIRST_TURN,
        RENDERED_SHIFT_SHARE * translation_step,
    )?;
    Some(RenderedRefinement {
        score,
        refined,
        before,
        after,
    })
}

/// Extra turns (degrees) about the refined turn's axis at which the rendered fit logs its score
/// (7 renders per object and knot, against a few hundred for the refinement).
const PROFILE_EXTRA_TURNS_DEGREES: [f32; 7] = [-4.0, -2.0, 2.0, 4.0, 6.0, 8.0, 10.0];

/// Smallest motion gate × interpolation weight through which `train.knot_search` moves an
/// anchor (a displacement Δ needs a knot change Δ / scale; below this it would be 20× Δ).
const MIN_SEARCH_SCALE: f32 = 0.05;

/// Motion gate of a seeded anchor at least (logit 0: σ = 1/2): it sits on a moving object, and
/// its knots move it by Δ / gate.
const SEEDED_MOTION_GATE_LOGIT: f32 = 0.0;

/// Pruning gate of a seeded anchor at least (logit 0, the gates' initial value: σ = 1/2).
const SEEDED_PRUNING_GATE_LOGIT: f32 = 0.0;

/// One frame's training images, in `scene.train_cameras` order, and their moving pixels.
struct FrameImages {
    images: Vec<Arc<Frame>>,
    moving: Vec<Vec<bool>>,
}

impl FrameImages {
    fn views<'a>(&'a self, cameras: &'a [RasterCamera], refs: &'a [&'a Frame]) -> FrameViews<'a> {
        FrameViews {
            cameras,
            images: refs,
            moving: &self.moving,
        }
    }

    fn refs(&self) -> Vec<&Frame> {
        self.images.iter().map(|f| &**f).collect()
    }
}

impl Trainer {
    /// The training cameras, as the searches see them.
    fn search_rig(&self) -> Vec<RasterCamera> {
        self.scene
            .train_cameras
            .iter()
            .map(|&c| self.scene.cameras[c].camera.clone())
            .collect()
    }

    /// GOP frame `frame`'s training images and moving pixels (`eval::motion_mask` against each
    /// camera's temporal median, computed at the first call).
    fn frame_images(&mut self, frame: usize) -> Result<FrameImages> {
        self.ensure_temporal_medians()?;
        let cameras = self.scene.train_cameras.clone();
        let images = cameras
            .iter()
            .map(|&camera| {
                self.frames.get(
                    &self.scene,
                    ViewId {
                        camera,
                        frame: self.scene.frames.start + frame,
                    },
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let config = self.config.eval.motion_mask();
        let medians = self.temporal_medians.as_deref().unwrap_or_default();
        let moving = images
            .iter()
            .zip(medians)
            .map(|(image, median)| {
                let (w, h) = (image.width as usize, image.height as usize);
                motion_mask(&image.rgb, median, w, h, &config)
            })
            .collect();
        Ok(FrameImages { images, moving })
    }

    /// Every anchor's position at GOP frame `frame` as the knot searches see it.
    pub(super) fn positions_at(&self, step: usize, frame: usize) -> Vec<[f32; 3]> {
        let plain = self.model.anchors.untracked();
        deformed_positions(
            &self.model.anchors,
            &plain,
            &self.model.decoders,
            self.knot_search_time(step, frame),
        )
    }

    /// The motion gate of every anchor as the decoder applies it in the dynamic phase (0 below
    /// the gate threshold).
    fn applied_motion_gates(&self) -> Vec<f32> {
        self.model
            .anchors
            .host(Column::Factors)
            .chunks_exact(FACTOR_COUNT)
            .map(|f| sigmoid(f[MOTION_GATE]))
            .map(|g| if g < GATE_THRESHOLD { 0.0 } else { g })
            .collect()
    }

    /// Every anchor decoded at `frame` as the searches see it, as the rasterizer's host arrays
    /// (Gaussian row a·K + k is anchor a's slot k), and K.
    fn gaussians_at(&self, step: usize, frame: usize) -> (GaussianArrays, usize) {
        let set = &self.model.anchors;
        let all: Vec<u32> = (0..set.len() as u32).collect();
        let view = decode_view(
            set,
            &set.untracked(),
            &self.model.decoders,
            all,
            self.knot_search_time(step, frame),
        );
        let g = &view.gaussians;
        let arrays = GaussianArrays {
            means: host_values(&g.means),
            quats: host_values(&g.quats),
            scales: host_values(&g.scales),
            opacities: host_values(&g.opacities),
            gates: host_values(&g.gates),
            colors: host_values(&g.colors),
        };
        let k = arrays.len() / set.len().max(1);
        (arrays, k)
    }

    /// The frame knot `knot` is searched at: its own, or the last where the last knot lies past
    /// the clip; and the knot's interpolation weight there (`with_trajectory` in model/view.rs).
    fn knot_frame(&self, knot: usize) -> Result<(usize, f32)> {
        let dims = self.model.anchors.dims;
        if self.model.anchors.columns.get(Column::Trajectory).is_none()
            || dims.trajectory_spacing == 0
            || knot >= dims.trajectory_knots()
        {
            bail!("knot {knot}: the model has no such trajectory knot to search for");
        }
        let spacing = dims.trajectory_spacing;
        let frame = (knot * spacing).min(dims.frames - 1);
        let w = 1.0 - (knot * spacing - frame) as f32 / spacing as f32;
        Ok((frame, w))
    }

    /// As the knot search: the anchors whose knot (weight `w` at its frame) can move them
    /// (`gates` × `w` at least [`MIN_SEARCH_SCALE`]), placed by a frame up to `previous`.
    fn movable_anchors(&self, gates: &[f32], w: f32, previous: usize) -> Vec<bool> {
        gates
            .iter()
            .zip(&self.anchor_state.reference_frame)
            .map(|(g, &r)| g * w >= MIN_SEARCH_SCALE && r as usize <= previous)
            .collect()
    }

    /// The moving objects at a frame whose training images are `views` and where the anchors
    /// stand at `places`: the `movable` anchors on something moving there, grouped
    /// ([`object_clusters`], `train.rigid_fit_link`), as the rigid fit finds them. Under
    /// `train.rigid_fit_grouping = "kept-distances"`, anchors that moved as one body from
    /// `earlier` (their places at the knot before, where there is one) are grouped too.
    fn moving_objects(
        &self,
        movable: &[bool],
        places: &[[f32; 3]],
        earlier: Option<&[[f32; 3]]>,
        views: &FrameViews,
    ) -> MovingObjects {
        // Per anchor: on something moving there, and whether its cameras agree on its colour
        // (it is on a surface they see).
        let seen: Vec<Option<(bool, f32)>> = (0..movable.len())
            .into_par_iter()
            .map(|a| movable[a].then(|| seen_at(views, places[a])).flatten())
            .collect();
        let candidate: Vec<bool> = seen.iter().map(|s| s.is_some_and(|(m, _)| m)).collect();
        let link = self.config.train.rigid_fit_link;
        let objects = match (self.config.train.rigid_fit_grouping, earlier) {
            (RigidFitGrouping::KeptDistances, Some(earlier)) => {
                clusters_moved_as_one(places, earlier, &candidate, link, MIN_OBJECT_ANCHORS)
            }
            _ => object_clusters(places, &candidate, link, MIN_OBJECT_ANCHORS),
        };
        MovingObjects {
            seen,
            candidate,
            objects,
        }
    }

    /// `train.knot_search`: moves the anchors whose moving object left them to where knot
    /// `knot`'s frame shows them (see `train/knot_search.rs`), by changing that knot alone.
    /// Each anchor is re-found by its colours at its reference frame (frame 0, or the frame
    /// `train.appearance_seeding` seeded it at: at the next knot, such an anchor's earlier knots
    /// are set along its segment to that knot, backwards, so before it appeared it comes from
    /// where its object came from). Returns the frame searched and, per anchor, the displacement applied there
    /// (none for an anchor left alone). Called by the step when the curriculum opens the knot.
    pub fn search_knot(&mut self, step: usize, knot: usize) -> Result<KnotSearchOutcome> {
        let started = Instant::now();
        let (frame, w) = self.knot_frame(knot)?;
        let mut outcome = KnotSearchOutcome {
            frame,
            applied: vec![None; self.model.anchors.len()],
            report: SearchReport::default(),
            consensus: ConsensusReport::default(),
        };
        // The knot change is sized for the gate of now: if the gate drifts later, the
        // displacement scales with it (the photometric loss corrects both).
        let mut gates = self.applied_motion_gates();
        // A displacement Δ needs a knot change Δ / (gate · w): only anchors whose knot can move
        // them are searched, and only by a reference frame before this one.
        let references = &self.anchor_state.reference_frame;
        let movable: Vec<bool> = gates
            .iter()
            .zip(references)
            .map(|(g, &r)| g * w >= MIN_SEARCH_SCALE && (r as usize) < frame)
            .collect();
        // Anchors seeded at the previous knot's frame get their earlier knots set below.
        let spacing = self.model.anchors.dims.trajectory_spacing;
        let seeded_at_previous = |r: u32| seeded_at_knot_before(r, knot, spacing);
        if w <= 0.0
            || !(movable.contains(&true) || references.iter().any(|&r| seeded_at_previous(r)))
        {
            return Ok(outcome);
        }
        let groups: BTreeSet<u32> = references
            .iter()
            .zip(&movable)
            .filter(|(_, m)| **m)
            .map(|(&r, _)| r)
            .collect();
        let rig = self.search_rig();
        let target = self.frame_images(frame)?;
        let target_refs = target.refs();
        let predicted = self.positions_at(step, frame);
        let params = SearchParams {
            radius: self.config.train.knot_search_radius,
            tolerance: self.config.train.knot_search_tolerance,
            grouping: match self.config.train.knot_search {
                KnotSearch::Patches => SearchGrouping::Patches {
                    side: self.config.train.knot_search_patch,
                },
                KnotSearch::Off | KnotSearch::Photometric => SearchGrouping::PerAnchor,
            },
        };
        let mut moves = vec![None; self.model.anchors.len()];
        let mut report = SearchReport::default();
        // `train.moving_gates`: the anchors on moving pixels at a reference frame before this
        // knot and not before the previous one (each anchor once, at its first search).
        let mut to_open = Vec::new();
        let first_search = |r: u32| {
            let r = r as usize;
            (knot - 1) * spacing <= r && r < knot * spacing
        };
        for r in groups {
            let reference = self.frame_images(r as usize)?;
            let reference_refs = reference.refs();
            let in_group: Vec<bool> = movable
                .iter()
                .zip(&self.anchor_state.reference_frame)
                .map(|(&m, &g)| m && g == r)
                .collect();
            let reference_views = reference.views(&rig, &reference_refs);
            let target_views = target.views(&rig, &target_refs);
            let reference_positions = self.positions_at(step, r as usize);
            let (placements, group_report) = search_placements(
                &reference_views,
                &reference_positions,
                &target_views,
                &predicted,
                &in_group,
                params,
            );
            if self.config.train.moving_gates == MovingGates::Open && first_search(r) {
                to_open.extend(
                    (0..placements.len())
                        .filter(|&a| in_group[a] && placements[a] != Placement::Untracked),
                );
            }
            let found: Vec<Option<[f32; 3]>> = match self.config.train.knot_consensus {
                KnotConsensus::Off => placements
                    .iter()
                    .map(|p| match p {
                        Placement::Moved(d) => Some(*d),
                        _ => None,
                    })
                    .collect(),
                KnotConsensus::Cells => {
                    let (found, consensus) = place_by_consensus(
                        &reference_views,
                        &reference_positions,
                        &target_views,
                        &predicted,
                        &placements,
                        self.config.train.knot_consensus_cell,
                        params,
                    );
                    outcome.consensus.adopted += consensus.adopted;
                    outcome.consensus.corrected += consensus.corrected;
                    found
                }
            };
            for (a, delta) in found.into_iter().enumerate() {
                if delta.is_some() {
                    moves[a] = delta;
                }
            }
            report.reliable += group_report.reliable;
            report.inconsistent += group_report.inconsistent;
        }
        let set = &mut self.model.anchors;
        let width = set.dims.trajectory_width();
        let mut values = set.host(Column::Trajectory);
        let opened = open_moving_gates(
            set,
            &mut values,
            &mut gates,
            &to_open,
            self.config.train.moving_gate_logit,
        );
        let mut moved = 0;
        for (a, delta) in moves.iter().enumerate() {
            let Some(delta) = delta else { continue };
            // The knot's displacement reaches the position scaled by the motion gate and the
            // interpolation weight (the motion head's term does not depend on the knots).
            let scale = gates[a] * w;
            for c in 0..3 {
                values[a * width + knot * 3 + c] += delta[c] / scale;
            }
            outcome.applied[a] = Some(*delta);
            moved += 1;
        }
        // Anchors seeded at knot b = knot − 1 waited at their seed in the frames before it: their
        // knots before b now continue the segment b → knot backwards (linear in the knots, so in
        // the position), so before it appeared each comes from where its object came from (held
        // still where the search did not move it: a zero velocity changes nothing).
        let seeded: Vec<usize> = (0..values.len() / width.max(1))
            .filter(|&a| seeded_at_previous(self.anchor_state.reference_frame[a]))
            .collect();
        continue_backwards(&mut values, width, knot, &seeded);
        set.set_host(Column::Trajectory, values);
        eprintln!(
            "step {step}: knot {knot} (frame {frame}) search: {} anchors on moving objects, {} lost, \
             {moved} moved ({} adopted, {} corrected by their neighbours; {opened} motion gates \
             opened; {:.2} s)",
            report.reliable,
            report.inconsistent,
            outcome.consensus.adopted,
            outcome.consensus.corrected,
            started.elapsed().as_secs_f64()
        );
        outcome.report = SearchReport { moved, ..report };
        Ok(outcome)
    }

    /// `train.rigid_fit = "objects"`: moves each moving object's anchors from knot − 1's frame
    /// to knot `knot`'s by the one rigid motion their cameras confirm (see `train/rigid_fit.rs`),
    /// by changing knot `knot` alone; under `model.trajectory_turn = "knots"` their turn at that
    /// knot becomes the motion's rotation composed with their turn at knot − 1. Called by the
    /// step when the curriculum opens the knot, after the knot search (whose placements are one
    /// of the fit's starts).
    pub fn fit_rigid_knot(&mut self, step: usize, knot: usize) -> Result<RigidFitReport> {
        let started = Instant::now();
        let mut report = RigidFitReport::default();
        if knot == 0 || self.model.anchors.is_empty() {
            return Ok(report);
        }
        let (frame, w) = self.knot_frame(knot)?;
        let (previous, _) = self.knot_frame(knot - 1)?;
        if w <= 0.0 || previous >= frame {
            return Ok(report);
        }
        let gates = self.applied_motion_gates();
        let n = gates.len();
        let movable = self.movable_anchors(&gates, w, previous);
        if !movable.contains(&true) {
            return Ok(report);
        }
        let rig = self.search_rig();
        let before_images = self.frame_images(previous)?;
        let target_images = self.frame_images(frame)?;
        let (before_refs, target_refs) = (before_images.refs(), target_images.refs());
        let before_views = before_images.views(&rig, &before_refs);
        let target_views = target_images.views(&rig, &target_refs);
        let before = self.positions_at(step, previous);
        let predicted = self.positions_at(step, frame);
        let earlier = match knot {
            0 | 1 => None,
            _ => Some(self.positions_at(step, self.knot_frame(knot - 2)?.0)),
        };
        let MovingObjects {
            seen,
            candidate,
            objects,
        } = self.moving_objects(&movable, &before, earlier.as_deref(), &before_views);
        let tolerance = self.config.train.knot_search_tolerance;
        let visible = |a: usize| seen[a].is_some_and(|(_, spread)| spread <= tolerance);
        let probe = SameViewProbe::new(&before_views, &before, &target_views, |a| candidate[a]);
        // Under "rendered": the model at both frames (decoded only when some object is large
        // enough to be refined), and which anchors are some object's.
        let refined_any = objects.iter().any(|m| m.len() >= RENDERED_MIN_ANCHORS);
        let rendered =
            (self.config.train.rigid_fit == RigidFit::Rendered && refined_any).then(|| {
                (
                    self.gaussians_at(step, previous),
                    self.gaussians_at(step, frame),
                )
            });
        let mut claimed = vec![false; n];
        for &a in objects.iter().flatten() {
            claimed[a] = true;
        }
        // Each object is also scored against its oldest reference frame (its origin), where its
        // oldest anchors' places are the most trusted (placed by the cameras' agreement there,
        // not carried by fits since): one interval's error is then not inherited by the next.
        // With the cube's true paths on `crossing` (`examples/oracle_motion.rs`) the fitted
        // turns at knots 1-9 were 18, 16, 17, 8, 16, 13, 17, 15, 15° (the cube's: 18 each)
        // against 18, 16, 18, 8, 10, 12, 15, 16° against the previous frame alone; trained on
        // `fast`, moving +0.21 dB and static +0.20 dB (docs/results.md, Follow-up 22).
        let mut origin_frames: Vec<usize> = objects
            .iter()
            .map(|members| oldest_reference(members, &self.anchor_state.reference_frame))
            .filter(|&f| f < previous)
            .collect();
        origin_frames.sort_unstable();
        origin_frames.dedup();
        let origin_images = origin_frames
            .iter()
            .map(|&f| self.frame_images(f))
            .collect::<Result<Vec<_>>>()?;
        let origin_refs: Vec<Vec<&Frame>> = origin_images.iter().map(FrameImages::refs).collect();
        let origin_probes: Vec<SameViewProbe> = origin_frames
            .iter()
            .zip(&origin_images)
            .zip(&origin_refs)
            .map(|((&f, images), refs)| {
                let views = images.views(&rig, refs);
                let at_origin = self.positions_at(step, f);
                SameViewProbe::new(&views, &at_origin, &target_views, |a| candidate[a])
            })
            .collect();
        let references = &self.anchor_state.reference_frame;
        // Disagreement beyond which an anchor counts as simply not matching (twice the search's
        // tolerance).
        let cap = 2.0 * tolerance;
        let translation_step = self.config.train.knot_search_radius / 8.0;
        let v = |p: [f32; 3]| Vec3::from_array(p);
        // Per moved anchor: its place at `frame` and the object's rotation.
        let mut moves: Vec<(usize, Vec3, Quat)> = Vec::new();
        let mut turns = Vec::new();
        for members in &objects {
            let from: Vec<Vec3> = members.iter().map(|&a| v(before[a])).collect();
            let centre = from.iter().copied().sum::<Vec3>() / from.len() as f32;
            // Scored by the anchors on a surface the cameras see at the previous frame: a point
            // hidden behind a face is seen by each camera as the point of the face in front of
            // it, which a translation keeps in front and a turn does not, so such points pull
            // the fit towards a translation (with the true paths on `crossing` they made the
            // fit prefer 11° to the cube's true 18°, once its turn had hidden frame 0's
            // anchors). All of them where too few are seen.
            // And by the object's oldest anchors (those of its earliest reference frame): an
            // anchor seeded on it later was placed by where two cameras agree, often off its
            // surface on a pattern (the cameras agree at several depths), and a point before
            // or behind the surface pulls as a hidden one does (with the true paths of frame
            // 0's anchors, the seeded ones made the fit prefer 8-9° to the cube's 18°).
            let oldest = oldest_reference(members, references);
            let surface: Vec<usize> = members.iter().copied().filter(|&a| visible(a)).collect();
            let settled: Vec<usize> = surface
                .iter()
                .copied()
                .filter(|&a| references[a] as usize == oldest)
                .collect();
            let pool = [&settled, &surface, members]
                .into_iter()
                .find(|p| p.len() >= MIN_OBJECT_ANCHORS)
                .unwrap_or(members);
            let origin = origin_frames
                .binary_search(&oldest)
                .ok()
                .map(|i| &origin_probes[i]);
            let stride = pool.len().div_ceil(MAX_SCORED_ANCHORS);
            let scored: Vec<usize> = pool.iter().copied().step_by(stride).collect();
            let score = |m: &RigidMotion| -> Option<f32> {
                let mut values = Vec::with_capacity(scored.len());
                let mut moving = 0;
                // The same anchors at the origin, where it sees them: (sum, count).
                let (mut far, mut far_seen) = (0.0f32, 0usize);
                for &a in &scored {
                    let there = m.apply(v(before[a])).to_array();
                    let probed = probe.at(a, there);
                    if let Some(s) = probed.agreement {
                        values.push(s.min(cap));
                        moving += usize::from(probed.moving);
                    }
                    if let Some(s) = origin.and_then(|o| o.at(a, there).agreement) {
                        far += s.min(cap);
                        far_seen += 1;
                    }
                }
                // As the knot search: an object is where something moves, seen by most.
                if values.is_empty()
                    || 2 * values.len() < scored.len()
                    || 2 * moving <= values.len()
                {
                    return None;
                }
                // The mean of the capped disagreements, not a trimmed mean: a turn that is off
                // moves only the anchors near the pattern's edges onto another colour, a
                // minority that a trimmed mean drops (it scored a turn of 8° like the true 18°
                // on `crossing` with the true paths). The cap keeps an anchor that the turn
                // hides (its camera sees another face) from preferring whatever motion shows it
                // a similar colour: it costs the same wherever it lands.
                // A turn the images do not ask for (a ball's bands are the same under any turn
                // about its axis) costs a little: TURN_TIE per radian.
                let mut mean = values.iter().sum::<f32>() / values.len() as f32;
                // Half the score from the origin, where it sees any of the object.
                if far_seen > 0 {
                    mean = 0.5 * (mean + far / far_seen as f32);
                }
                Some(mean + TURN_TIE * angle_of(m.rotation))
            };
            // Starts: where the search left the anchors (its best rigid fit, and its median
            // translation alone), and the previous interval's motion continued.
            let to: Vec<Vec3> = members.iter().map(|&a| v(predicted[a])).collect();
            let mut starts = Vec::new();
            if let Some(m) = RigidMotion::fit(&from, &to) {
                starts.push(m.about(centre));
            }
            starts.push(RigidMotion {
                translation: v(median_shift(members, &before, &predicted)),
                ..RigidMotion::identity(centre)
            });
            if let Some(earlier) = &earlier {
                // By the anchors the score trusts (a seeded one's knots before its seeding are
                // a guess).
                let back: Vec<Vec3> = pool.iter().map(|&a| v(earlier[a])).collect();
                let now: Vec<Vec3> = pool.iter().map(|&a| v(before[a])).collect();
                if let Some(m) = RigidMotion::fit(&back, &now) {
                    // The same turn and shift again, from where the pool is now.
                    let here = now.iter().copied().sum::<Vec3>() / now.len() as f32;
                    let continued = RigidMotion { centre: here, ..m };
                    starts.push(continued.about(centre));
                }
            }
            let Some((motion, fitted)) = fit_motion(&score, &starts, translation_step) else {
                continue;
            };
            let at_starts: Vec<String> = starts
                .iter()
                .map(|m| match score(m) {
                    Some(s) => format!("{s:.3} at {:.1} deg", angle_of(m.rotation).to_degrees()),
                    None => "-".into(),
                })
                .collect();
            // "rendered": the motion refined against the model drawn at `frame`, and the
            // anchors it moves are the members and those they enclose.
            let refined_here = rendered
                .as_ref()
                .filter(|_| members.len() >= RENDERED_MIN_ANCHORS);
            let (motion, moving) = match refined_here {
                None => (motion, members.clone()),
                Some(((at_previous, k), (at_frame, _))) => {
                    let rendered_started = Instant::now();
                    let enclosed =
                        claim_enclosed(members, &before, &movable, &seen, tolerance, &mut claimed);
                    let mut in_template = vec![false; n];
                    for &a in members.iter().chain(&enclosed) {
                        in_template[a] = true;
                    }
                    let refinement = refine_rendered(
                        RenderedInputs {
                            at_previous,
                            at_frame,
                            per_anchor: *k,
                            in_template: &in_template,
                            rig: &rig,
                            targets: &target_refs,
                        },
                        motion,
                        centre,
                        translation_step,
                    );
                    let moving: Vec<usize> = members.iter().chain(&enclosed).copied().collect();
                    match refinement {
                        Some(RenderedRefinement {
                            score,
                            refined,
                            before: before_score,
                            after,
                        }) => {
                            if let Some(profile) =
                                score.turn_profile(&refined, after, &PROFILE_EXTRA_TURNS_DEGREES)
                            {
                                eprintln!(
                                    "  rendered: score turned further about its axis, against \
                                     the refined (deg: difference): {profile}"
                                );
                            }
                            eprintln!(
                                "  rendered: turn {:.1} -> {:.1} deg ({:.1} deg apart), shift \
                                 {:.3} -> {:.3}, score {before_score:.4} -> {after:.4} in {} \
                                 cameras, {} + {} enclosed anchors ({:.2} s)",
                                angle_of(motion.rotation).to_degrees(),
                                angle_of(refined.rotation).to_degrees(),
                                angle_of(refined.rotation * motion.rotation.inverse()).to_degrees(),
                                motion.translation.length(),
                                refined.translation.length(),
                                score.cameras(),
                                members.len(),
                                enclosed.len(),
                                rendered_started.elapsed().as_secs_f64()
                            );
                            (refined, moving)
                        }
                        _ => (motion, moving),
                    }
                }
            };
            report.objects += 1;
            report.anchors += moving.len();
            turns.push(angle_of(motion.rotation).to_degrees());
            eprintln!(
                "  object of {} anchors at ({:.2}, {:.2}, {:.2}): turn {:.1} deg, shift {:.3}, \
                 agreement {fitted:.3} (starts: {})",
                members.len(),
                centre.x,
                centre.y,
                centre.z,
                angle_of(motion.rotation).to_degrees(),
                motion.translation.length(),
                at_starts.join(", ")
            );
            for &a in &moving {
                let there = motion.apply(v(before[a]));
                // An anchor its cameras confirm where it stands, and clearly not at the object's
                // motion (by a tolerance: colour noise never keeps one), stays: a point of
                // something else that the object's anchors reach. (Only the candidates are
                // probed; an enclosed anchor the cameras do not confirm anywhere moves.)
                let stays = candidate[a] && {
                    let here = probe.at(a, predicted[a]).agreement;
                    let moved = probe.at(a, there.to_array()).agreement;
                    here.is_some_and(|h| h <= tolerance && moved.is_none_or(|t| t > h + tolerance))
                };
                if !stays {
                    moves.push((a, there, motion.rotation));
                }
            }
        }
        let set = &mut self.model.anchors;
        let width = set.dims.trajectory_width();
        let mut values = set.host(Column::Trajectory);
        let mut turn_values = set.host_if_present(Column::Turn);
        for &(a, there, rotation) in &moves {
            // The knot's displacement reaches the position scaled by the gate and the weight.
            let scale = gates[a] * w;
            for c in 0..3 {
                values[a * width + knot * 3 + c] += (there[c] - predicted[a][c]) / scale;
            }
            if let Some(turn) = turn_values.as_mut() {
                // The rendered turn at the previous knot (gate × knot − 1's turn; its frame is
                // that knot's own), turned further by the object's rotation; the knot gets what
                // makes the rendered turn at `frame` that, through the gate and the weight.
                let row = &mut turn[a * width..(a + 1) * width];
                let before_turn = v(std::array::from_fn(|c| row[(knot - 1) * 3 + c])) * gates[a];
                let after = rotation * Quat::from_scaled_axis(before_turn);
                let rendered = rotation_vector_near(after, before_turn);
                let knot_turn = (rendered / gates[a] - (1.0 - w) * before_turn / gates[a]) / w;
                row[knot * 3..knot * 3 + 3].copy_from_slice(&knot_turn.to_array());
            }
        }
        report.moved = moves.len();
        // Anchors seeded at the previous knot's frame continue backwards along their new segment.
        let spacing = set.dims.trajectory_spacing;
        let seeded: Vec<usize> = moves
            .iter()
            .map(|&(a, _, _)| a)
            .filter(|&a| seeded_at_knot_before(self.anchor_state.reference_frame[a], knot, spacing))
            .collect();
        continue_backwards(&mut values, width, knot, &seeded);
        set.set_host(Column::Trajectory, values);
        if let Some(turn) = turn_values {
            set.set_host(Column::Turn, turn);
        }
        if self.config.train.fitted_knots == FittedKnots::Held {
            let moved: Vec<usize> = moves.iter().map(|&(a, _, _)| a).collect();
            self.anchor_state
                .hold_fitted_knots(&self.model.anchors.dims, knot, &moved);
        }
        report.median_turn_degrees = if turns.is_empty() {
            0.0
        } else {
            median(&mut turns)
        };
        eprintln!(
            "step {step}: knot {knot} (frame {frame}) rigid fit: {} objects of {} anchors, {} \
             moved, median turn {:.1} deg ({:.2} s)",
            report.objects,
            report.anchors,
            report.moved,
            report.median_turn_degrees,
            started.elapsed().as_secs_f64()
        );
        Ok(report)
    }

    /// `train.appearance_seeding`: new anchors on what knot `knot`'s frame shows moving that no
    /// anchor occupies there (see `train/appearance_seeding.rs`), placed at that frame: each
    /// copies its features, feature stream and gates from the anchor nearest it at that frame
    /// (as growth copies its parents'; the motion gate raised to at least 1/2), its knots all
    /// offset so that it sits where it was found at that frame, and its reference frame is that
    /// frame, so the knot search follows it from there. Knot 0 is not seeded (frame 0's objects
    /// have their points). Returns what the sweep found.
    pub fn seed_appearances(&mut self, step: usize, knot: usize) -> Result<SeedReport> {
        let started = Instant::now();
        let (frame, _) = self.knot_frame(knot)?;
        if knot == 0 || self.model.anchors.is_empty() {
            return Ok(SeedReport::default());
        }
        let rig = self.search_rig();
        let target = self.frame_images(frame)?;
        let target_refs = target.refs();
        let at_frame = self.positions_at(step, frame);
        let cell = typical_spacing(&self.model.anchors.positions, self.config.model.voxel_size);
        let (seeds, mut report) = seed_positions(
            &target.views(&rig, &target_refs),
            &at_frame,
            SeedParams {
                tolerance: self.config.train.knot_search_tolerance,
                cell,
            },
        );
        if !seeds.is_empty() {
            report.seeded = self.append_seeds(step, frame, &seeds, &at_frame, cell);
        }
        eprintln!(
            "step {step}: knot {knot} (frame {frame}) seeding: {} moving pixels swept, {} \
             consistent, {} cells, {} seeded ({:.2} s)",
            report.rays,
            report.consistent,
            report.cells,
            report.seeded,
            started.elapsed().as_secs_f64()
        );
        Ok(report)
    }

    /// Appends anchors at `seeds` (positions at GOP frame `frame`; `at_frame` the existing
    /// anchors' positions there) and returns how many.
    fn append_seeds(
        &mut self,
        step: usize,
        frame: usize,
        seeds: &[[f32; 3]],
        at_frame: &[[f32; 3]],
        cell: f32,
    ) -> usize {
        // Canonical positions on the voxel grid (the bitstream codes voxel integers), one anchor
        // per voxel: the seed's own, or the next free one along x (the knot offset below carries
        // each anchor from its canonical position to its seed, wherever that is).
        let voxel = self.config.model.voxel_size;
        let to_voxel = |p: &[f32; 3]| p.map(|v| (v / voxel).round() as i64);
        let mut taken: HashSet<[i64; 3]> =
            self.model.anchors.positions.iter().map(to_voxel).collect();
        let canonical: Vec<[f32; 3]> = seeds
            .iter()
            .map(|p| {
                let mut v = to_voxel(p);
                while !taken.insert(v) {
                    v[0] += 1;
                }
                v.map(|i| i as f32 * voxel)
            })
            .collect();
        let set = &self.model.anchors;
        let d = set.dims;
        let donor = |p: &[f32; 3]| {
            let distance = |q: &[f32; 3]| (0..3).map(|c| (p[c] - q[c]).powi(2)).sum::<f32>();
            (0..at_frame.len())
                .min_by(|&a, &b| distance(&at_frame[a]).total_cmp(&distance(&at_frame[b])))
                .expect("some anchors")
        };
        let donors: Vec<usize> = seeds.iter().map(donor).collect();
        let copy = |c: Column, width: usize| -> Vec<f32> {
            let values = set.host(c);
            donors
                .iter()
                .flat_map(|&a| values[a * width..(a + 1) * width].iter().copied())
                .collect()
        };
        let mut factors = copy(Column::Factors, FACTOR_COUNT);
        let donor_gates: Vec<f32> = factors
            .chunks_exact(FACTOR_COUNT)
            .map(|f| sigmoid(f[MOTION_GATE]))
            .collect();
        // The motion gate raised as above; the pruning gate opened (a donor whose gate is shut
        // would give a seed that is born invisible and pruned).
        for f in factors.chunks_exact_mut(FACTOR_COUNT) {
            f[MOTION_GATE] = f[MOTION_GATE].max(SEEDED_MOTION_GATE_LOGIT);
            f[3] = f[3].max(SEEDED_PRUNING_GATE_LOGIT);
        }
        let n = seeds.len();
        if n == 0 {
            return 0;
        }
        let width = d.trajectory_width();
        let mut rows = NewAnchors::new(canonical)
            .with(Column::LogScales, vec![cell.ln(); n * SCALE_DIMS])
            .with(Column::Features, copy(Column::Features, d.feature_dim))
            .with(
                Column::TimeFeatures,
                copy(Column::TimeFeatures, d.frames * d.time_feature_dim),
            )
            .with(Column::Factors, factors.clone())
            .with(Column::MaskLogits, copy(Column::MaskLogits, 1))
            .with(Column::Trajectory, vec![0.0; n * width]);
        // A seed copies its donor's features, so its Gaussians are laid out as the donor's before
        // the donor's turn: it takes the donor's rendered turn (gate × turn), in its own gate's
        // units (knot 0 stays the identity).
        if d.turn_width() > 0 {
            let turns = copy(Column::Turn, width);
            let seeded: Vec<f32> = turns
                .chunks_exact(width)
                .enumerate()
                .flat_map(|(i, row)| {
                    let scale = donor_gates[i] / sigmoid(factors[i * FACTOR_COUNT + MOTION_GATE]);
                    row.iter().map(move |r| r * scale)
                })
                .collect();
            rows = rows.with(Column::Turn, seeded);
        }
        let first = set.len();
        self.anchor_state.edit(
            &mut self.model.anchors,
            RowEdit::Append {
                rows,
                created_at: step,
                reference_frames: vec![u32::try_from(frame).expect("frame fits in u32"); n],
            },
        );
        self.model.anchors.rebuild_neighbors();
        self.rows_changed();
        // The motion head moves a new anchor too (by gate × its output for the copied feature):
        // offset every knot by what remains, so it sits at its seed at `frame` (the knots'
        // interpolation weights sum to 1).
        let now = self.positions_at(step, frame);
        let mut values = self.model.anchors.host(Column::Trajectory);
        for (i, seed) in seeds.iter().enumerate() {
            let a = first + i;
            let gate = sigmoid(factors[i * FACTOR_COUNT + MOTION_GATE]);
            for k in 0..d.trajectory_knots() {
                for c in 0..3 {
                    values[a * width + k * 3 + c] += (seed[c] - now[a][c]) / gate;
                }
            }
        }
        self.model.anchors.set_host(Column::Trajectory, values);
        n
    }

    /// The decode time at which the knot searches see the anchors at GOP frame index `frame`
    /// at `step`: where they will be once the motion acts, also while the canonical phase holds
    /// them still (the first knots open then).
    pub fn knot_search_time(&self, step: usize, frame: usize) -> ViewTime {
        let view = ViewId {
            camera: self.scene.train_cameras[0],
            frame: self.scene.frames.start + frame,
        };
        ViewTime {
            phase: Phase::Dynamic,
            ..self.view_time(step, view)
        }
    }

    /// `loss.moving_weight`: the L1 weights [H, W, 1] of `view`'s pixels on `device` (its moving
    /// pixels against its camera's temporal median weigh `moving_weight` times the static ones,
    /// mean 1; `losses::moving_pixel_weights`), or `None` at weight 1.
    pub(super) fn moving_pixel_weights(
        &mut self,
        view: ViewId,
        device: &Device,
    ) -> Result<Option<Tensor<3>>> {
        let weight = self.config.loss.moving_weight;
        if weight == 1.0 {
            return Ok(None);
        }
        self.ensure_temporal_medians()?;
        let cameras = &self.scene.train_cameras;
        let Some(index) = cameras.iter().position(|&c| c == view.camera) else {
            bail!(
                "moving-pixel weights of camera {}, which is not a training camera",
                view.camera
            );
        };
        let frame = self.frames.get(&self.scene, view)?;
        let (w, h) = (frame.width as usize, frame.height as usize);
        let medians = self.temporal_medians.as_deref().unwrap_or_default();
        let moving = motion_mask(
            &frame.rgb,
            &medians[index],
            w,
            h,
            &self.config.eval.motion_mask(),
        );
        Ok(Some(upload::<3, Float>(
            TensorData::new(moving_pixel_weights(&moving, weight), [h, w, 1]),
            device,
        )))
    }

    /// Computes `temporal_medians` (each training camera's, in `scene.train_cameras` order) at
    /// the first call, from the ground truth, so a resumed run gets the same.
    fn ensure_temporal_medians(&mut self) -> Result<()> {
        if self.temporal_medians.is_none() {
            let cameras = self.scene.train_cameras.clone();
            self.temporal_medians = Some(self.compute_temporal_medians(&cameras)?);
        }
        Ok(())
    }

    /// The temporal median of each camera of `cameras` over the GOP (the evaluation's motion
    /// mask compares a frame with it).
    fn compute_temporal_medians(&self, cameras: &[usize]) -> Result<Vec<Vec<f32>>> {
        cameras
            .iter()
            .map(|&camera| {
                let images = self
                    .scene
                    .frames
                    .frames()
                    .map(|frame| self.frames.get(&self.scene, ViewId { camera, frame }))
                    .collect::<Result<Vec<_>>>()?;
                let planes: Vec<&[f32]> = images.iter().map(|f| f.rgb.as_slice()).collect();
                Ok(temporal_median(&planes))
            })
            .collect()
    }
}

/// The anchors' typical spacing: the median distance to the nearest other anchor (`fallback`
/// where no two anchors are apart).
fn typical_spacing(positions: &[[f32; 3]], fallback: f32) -> f32 {
    let nearest = nearest_neighbors(positions, 1);
    let mut distances: Vec<f32> = positions
        .iter()
        .zip(&nearest)
        .filter_map(|(p, nn)| {
            let q = positions[*nn.first()? as usize];
            Some((0..3).map(|c| (p[c] - q[c]).powi(2)).sum::<f32>().sqrt())
        })
        .filter(|&d| d > 0.0)
        .collect();
    if distances.is_empty() {
        return fallback;
    }
    median(&mut distances)
}

/// The moving objects at a frame ([`Trainer::moving_objects`]).
struct MovingObjects {
    /// Per anchor (movable ones only): on something moving, and its cameras' colour spread.
    seen: Vec<Option<(bool, f32)>>,
    /// Movable and on something moving.
    candidate: Vec<bool>,
    /// The candidates grouped, each of [`MIN_OBJECT_ANCHORS`] or more.
    objects: Vec<Vec<usize>>,
}

/// The anchors an object's `members` enclose ([`enclosed_anchors`]) that are movable, no
/// object's yet (`claimed`, which they then are), and not confirmed on something static (seen,
/// not moving, within `tolerance`).
fn claim_enclosed(
    members: &[usize],
    places: &[[f32; 3]],
    movable: &[bool],
    seen: &[Option<(bool, f32)>],
    tolerance: f32,
    claimed: &mut [bool],
) -> Vec<usize> {
    let enclosed = enclosed_anchors(members, places, |a| {
        movable[a] && !claimed[a] && !seen[a].is_some_and(|(m, spread)| !m && spread <= tolerance)
    });
    for &a in &enclosed {
        claimed[a] = true;
    }
    enclosed
}

/// The anchors that `eligible` admits whose place lies inside the bounding box of the
/// `members`' places: the object's anchors that were not grouped with it (hidden inside it, or
/// not confirmed by the cameras; about half the flying cube's on `crossing`, Follow-up 50).
fn enclosed_anchors(
    members: &[usize],
    places: &[[f32; 3]],
    eligible: impl Fn(usize) -> bool + Sync,
) -> Vec<usize> {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for &a in members {
        lo = lo.min(Vec3::from_array(places[a]));
        hi = hi.max(Vec3::from_array(places[a]));
    }
    let is_member: HashSet<usize> = members.iter().copied().collect();
    (0..places.len())
        .into_par_iter()
        .filter(|&a| {
            let p = Vec3::from_array(places[a]);
            !is_member.contains(&a) && p.cmpge(lo).all() && p.cmple(hi).all() && eligible(a)
        })
        .collect()
}

/// Whether an anchor of reference frame `reference` was seeded at knot − 1's frame (knot ≥ 2;
/// knot 0 is never seeded): its earlier knots continue the segment to `knot` backwards
/// ([`continue_backwards`]) once `knot` is placed.
fn seeded_at_knot_before(reference: u32, knot: usize, spacing: usize) -> bool {
    knot >= 2 && reference as usize == (knot - 1) * spacing
}

/// Sets knots 0..knot − 1 of each of `anchors` (rows of `values`, `width` floats each, 3 per
/// knot) along its segment from knot − 1 to `knot`, backwards: anchors seeded at knot − 1's
/// frame waited at their seed before it; so before it appeared each comes from where its object
/// came from (linear in the knots, so in the position).
fn continue_backwards(values: &mut [f32], width: usize, knot: usize, anchors: &[usize]) {
    if knot < 2 {
        return;
    }
    let b = knot - 1;
    for &a in anchors {
        let row = &mut values[a * width..(a + 1) * width];
        for c in 0..3 {
            let velocity = row[knot * 3 + c] - row[b * 3 + c];
            for i in 0..b {
                row[i * 3 + c] = row[b * 3 + c] - (b - i) as f32 * velocity;
            }
        }
    }
}

/// `train.moving_gates = "open"`: raises the motion gate logit of each anchor in `anchors` to
/// `logit` where it is below, dividing its knots (`trajectory`, the host copy the search edits)
/// by the new gate over the old so that their displacement stays (the motion head's term, which
/// the gate scales too, grows with it), and so its turns (the set's `turn` column, when the
/// trajectories turn), and updates `gates` (the applied gates the search sizes its knot changes
/// by). Returns how many gates it opened.
///
/// Not in GIFStream, where every motion gate starts at σ(0) = 1/2 (or from `init_dynamic`'s
/// statistics) and trains from there. Held at σ(4) on the `fast` sphere's anchors while frames
/// open (`examples/oracle_motion.rs --gate-only`), the moving pixels gained +2.6 dB decoded
/// (docs/results.md, Follow-up 18): at 1/2, where σ is steepest, every Adam step on the logit
/// rescales the anchor's whole path, and the knots move it at half their rate.
fn open_moving_gates(
    set: &mut AnchorSet,
    trajectory: &mut [f32],
    gates: &mut [f32],
    anchors: &[usize],
    logit: f32,
) -> usize {
    if anchors.is_empty() {
        return 0;
    }
    let width = set.dims.trajectory_width();
    let mut factors = set.host(Column::Factors);
    let mut turns = set.host_if_present(Column::Turn);
    let open = sigmoid(logit);
    let mut opened = 0;
    for &a in anchors {
        let raw = &mut factors[a * FACTOR_COUNT + MOTION_GATE];
        if *raw >= logit {
            continue;
        }
        let ratio = sigmoid(*raw) / open;
        for k in &mut trajectory[a * width..(a + 1) * width] {
            *k *= ratio;
        }
        if let Some(turns) = turns.as_mut() {
            for r in &mut turns[a * width..(a + 1) * width] {
                *r *= ratio;
            }
        }
        *raw = logit;
        gates[a] = open;
        opened += 1;
    }
    set.set_host(Column::Factors, factors);
    if let Some(turns) = turns {
        set.set_host(Column::Turn, turns);
    }
    opened
}

/// The earliest reference frame among `members` (the frame the oldest of them was placed at).
fn oldest_reference(members: &[usize], reference_frame: &[u32]) -> usize {
    members
        .iter()
        .map(|&a| reference_frame[a] as usize)
        .min()
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The enclosed anchors are those inside the members' bounding box that `eligible` admits,
    /// the members themselves excluded.
    #[test]
    fn enclosed_anchors_are_inside_the_members_box_and_eligible() {
        let places = [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
            [0.5, 0.5, 0.5], // inside
            [0.5, 0.5, 1.5], // outside (z)
            [0.2, 0.9, 0.1], // inside, not eligible
            [1.0, 0.0, 1.0], // on the box's face: inside
        ];
        let found = enclosed_anchors(&[0, 1], &places, |a| a != 4);
        assert_eq!(found, vec![2, 5]);
        assert!(enclosed_anchors(&[0], &places, |_| true).is_empty());
    }
}
