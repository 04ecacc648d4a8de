//! `train.knot_refit`: the moving objects' knot intervals refined again against the trained
//! model's rendering, and every anchor's later knots linked on from there (the why and the
//! linking: `train/knot_refit.rs`).

use std::time::Instant;

use anyhow::Result;
use glam::{Quat, Vec3};

use super::super::super::knot_refit::{
    IntervalRefit, KnotChain, ObjectRefit, knots_through, relinked,
};
use super::super::super::rigid_fit::RigidMotion;
use super::{
    FrameImages, MovingObjects, RENDERED_MIN_ANCHORS, RenderedInputs, RenderedRefinement, Trainer,
    claim_enclosed, refine_rendered,
};
use crate::config::KnotRefitStreams;
use crate::data::frames::Frame;
use crate::model::anchors::Column;
use crate::model::rotations::{angle_of, rotation_vector_near};

/// Each knot's frame and interpolation weight, and every anchor's place at it.
struct KnotPlaces {
    frames: Vec<(usize, f32)>,
    places: Vec<Vec<[f32; 3]>>,
}

/// What [`Trainer::relink_from`] changed: anchors whose knots it linked again, and of them
/// those whose feature streams it reset.
#[derive(Default)]
struct Relinked {
    anchors: usize,
    streams_reset: usize,
}

/// What [`Trainer::refit_knots`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct KnotRefitReport {
    /// Per object refined: its interval, anchors and motions.
    pub objects: Vec<ObjectRefit>,
    /// Anchors whose knots changed.
    pub anchors: usize,
    /// Anchors whose feature streams `train.knot_refit_streams = "first-frame"` reset.
    pub streams_reset: usize,
}

impl Trainer {
    /// `train.knot_refit`: each knot interval's moving objects (found at its first frame as the
    /// rigid fit finds them, with the anchors they enclose; [`RENDERED_MIN_ANCHORS`] members or
    /// more) get the motion their anchors' places make over it refined against the model as
    /// trained now: the object drawn at the interval's first frame, moved, composited with the
    /// rest of the model at its last frame, scored against that frame's training images (the
    /// rendered fit's score and bounds). Then every anchor of a refined object has its places
    /// and turns at the knots' frames linked again from knot 0 ([`relinked`]) and its knots set
    /// to draw them. All intervals are measured on the model as it stands before any change.
    pub fn refit_knots(&mut self, step: usize) -> Result<KnotRefitReport> {
        let started = Instant::now();
        let mut report = KnotRefitReport::default();
        let set = &self.model.anchors;
        if set.columns.get(Column::Trajectory).is_none() || set.is_empty() {
            return Ok(report);
        }
        let dims = set.dims;
        let knots = dims.trajectory_knots();
        let at_knots = self.knot_places(step)?;
        let (frames, places) = (&at_knots.frames, &at_knots.places);
        let gates = self.applied_motion_gates();
        let n = gates.len();
        let rig = self.search_rig();
        let tolerance = self.config.train.knot_search_tolerance;
        let translation_step = self.config.train.knot_search_radius / 8.0;
        let v = |p: [f32; 3]| Vec3::from_array(p);
        // The intervals of the knots the curriculum has opened (the others are set when they
        // open, from where this leaves the objects).
        let opened = self
            .config
            .train
            .knots_reached_at(step, dims.trajectory_spacing, dims.frames)
            .min(knots);
        let mut refits = Vec::new();
        for k in 1..opened {
            let ((previous, _), (frame, w)) = (frames[k - 1], frames[k]);
            if w <= 0.0 || previous >= frame {
                continue;
            }
            let movable = self.movable_anchors(&gates, w, previous);
            if !movable.contains(&true) {
                continue;
            }
            let (before, after) = (&places[k - 1], &places[k]);
            let before_images = self.frame_images(previous)?;
            let before_refs = before_images.refs();
            let earlier = k.checked_sub(2).map(|i| places[i].as_slice());
            let MovingObjects { seen, objects, .. } = self.moving_objects(
                &movable,
                before,
                earlier,
                &before_images.views(&rig, &before_refs),
            );
            if !objects.iter().any(|m| m.len() >= RENDERED_MIN_ANCHORS) {
                continue;
            }
            let target_images: FrameImages = self.frame_images(frame)?;
            let target_refs: Vec<&Frame> = target_images.refs();
            let (at_previous, per_anchor) = self.gaussians_at(step, previous);
            let (at_frame, _) = self.gaussians_at(step, frame);
            let per_anchor = per_anchor.max(1);
            let mut claimed = vec![false; n];
            for &a in objects.iter().flatten() {
                claimed[a] = true;
            }
            for members in objects.iter().filter(|m| m.len() >= RENDERED_MIN_ANCHORS) {
                let enclosed =
                    claim_enclosed(members, before, &movable, &seen, tolerance, &mut claimed);
                let object: Vec<usize> = members.iter().chain(&enclosed).copied().collect();
                let from: Vec<Vec3> = object.iter().map(|&a| v(before[a])).collect();
                let to: Vec<Vec3> = object.iter().map(|&a| v(after[a])).collect();
                let centre = from.iter().copied().sum::<Vec3>() / from.len() as f32;
                let Some(current) = RigidMotion::fit(&from, &to).map(|m| m.about(centre)) else {
                    continue;
                };
                let mut in_template = vec![false; n];
                for &a in &object {
                    in_template[a] = true;
                }
                let Some(RenderedRefinement {
                    score,
                    refined,
                    before: before_score,
                    after: after_score,
                }) = refine_rendered(
                    RenderedInputs {
                        at_previous: &at_previous,
                        at_frame: &at_frame,
                        per_anchor,
                        in_template: &in_template,
                        rig: &rig,
                        targets: &target_refs,
                    },
                    current,
                    centre,
                    translation_step,
                )
                else {
                    continue;
                };
                let (turn, refined_turn) = (
                    angle_of(current.rotation).to_degrees(),
                    angle_of(refined.rotation).to_degrees(),
                );
                eprintln!(
                    "  knot {k} (frames {previous}-{frame}) refit: object of {} + {} enclosed \
                     anchors: turn {turn:.1} -> {refined_turn:.1} deg ({:.1} deg apart), shift \
                     {:.3} -> {:.3}, score {before_score:.4} -> {after_score:.4} in {} cameras",
                    members.len(),
                    enclosed.len(),
                    angle_of(refined.rotation * current.rotation.inverse()).to_degrees(),
                    current.translation.length(),
                    refined.translation.length(),
                    score.cameras(),
                );
                refits.push(ObjectRefit {
                    knot: k,
                    anchors: object,
                    refit: IntervalRefit { current, refined },
                });
            }
        }
        let relinked = self.relink_from(&at_knots, &gates, &refits)?;
        (report.anchors, report.streams_reset) = (relinked.anchors, relinked.streams_reset);
        report.objects = refits;
        let mut intervals: Vec<usize> = report.objects.iter().map(|o| o.knot).collect();
        intervals.dedup();
        eprintln!(
            "step {step}: knot refit: {} objects over {} intervals refined, {} anchors' knots \
             linked again, {} anchors' feature streams reset ({:.2} s)",
            report.objects.len(),
            intervals.len(),
            report.anchors,
            report.streams_reset,
            started.elapsed().as_secs_f64()
        );
        Ok(report)
    }

    /// Every anchor of `refits`' objects gets its places and turns at the knots' frames linked
    /// again from knot 0 ([`relinked`]; each (anchor, knot) in at most one refit, the last one
    /// listed otherwise) and its knots set to draw them through its motion gate and the
    /// interpolation weights ([`knots_through`]; knot 0 keeps its values). Anchors whose gate
    /// the decoder does not apply (below the threshold) cannot be moved and are left. Under
    /// `train.knot_refit_streams = "first-frame"` the moved anchors' feature streams are reset
    /// ([`Self::reset_refitted_streams`]). Returns the anchors changed.
    pub fn relink_knots(&mut self, step: usize, refits: &[ObjectRefit]) -> Result<usize> {
        let set = &self.model.anchors;
        if set.columns.get(Column::Trajectory).is_none() || set.is_empty() || refits.is_empty() {
            return Ok(0);
        }
        let at_knots = self.knot_places(step)?;
        let gates = self.applied_motion_gates();
        Ok(self.relink_from(&at_knots, &gates, refits)?.anchors)
    }

    /// Each knot's frame and interpolation weight, and every anchor's place there (a decode of
    /// the model per knot: [`Self::refit_knots`] measures and relinks from one).
    fn knot_places(&self, step: usize) -> Result<KnotPlaces> {
        let frames: Vec<(usize, f32)> = (0..self.model.anchors.dims.trajectory_knots())
            .map(|k| self.knot_frame(k))
            .collect::<Result<_>>()?;
        let places = frames
            .iter()
            .map(|&(f, _)| self.positions_at(step, f))
            .collect();
        Ok(KnotPlaces { frames, places })
    }

    /// `train.knot_refit_streams = "first-frame"`: each anchor [`Self::relink_from`] moved,
    /// listed with the first frame of its earliest refitted interval, has its per-frame feature
    /// stream at every later frame set to its value at that frame, and the Adam moments of the
    /// entries set zeroed. Returns the anchors reset.
    fn reset_refitted_streams(&mut self, moved: &[(usize, usize)]) -> usize {
        let set = &self.model.anchors;
        let (t, c) = (set.dims.frames, set.dims.time_feature_dim);
        if t < 2 || c == 0 || moved.is_empty() {
            return 0;
        }
        let width = t * c;
        let mut stream = set.host(Column::TimeFeatures);
        let mut zero = vec![false; stream.len()];
        let mut reset = 0;
        for &(a, first) in moved {
            if first + 1 >= t {
                continue;
            }
            let row = &mut stream[a * width..(a + 1) * width];
            let kept: Vec<f32> = row[first * c..(first + 1) * c].to_vec();
            for f in first + 1..t {
                row[f * c..(f + 1) * c].copy_from_slice(&kept);
            }
            zero[a * width + (first + 1) * c..(a + 1) * width].fill(true);
            reset += 1;
        }
        self.model.anchors.set_host(Column::TimeFeatures, stream);
        self.anchor_state
            .reset_adam_elements(Column::TimeFeatures, &zero);
        reset
    }

    /// [`Self::relink_knots`] from the model's places at the knots and its applied motion
    /// `gates`, both as they stand.
    fn relink_from(
        &mut self,
        at_knots: &KnotPlaces,
        gates: &[f32],
        refits: &[ObjectRefit],
    ) -> Result<Relinked> {
        let set = &self.model.anchors;
        if set.columns.get(Column::Trajectory).is_none() || set.is_empty() || refits.is_empty() {
            return Ok(Relinked::default());
        }
        let knots = set.dims.trajectory_knots();
        let (frames, places) = (&at_knots.frames, &at_knots.places);
        let n = gates.len();
        // Per (anchor, knot): its object's refit over the interval ending at the knot.
        let mut refit_of: Vec<Option<IntervalRefit>> = vec![None; n * knots];
        for object in refits {
            if object.knot == 0 || object.knot >= knots {
                anyhow::bail!("knot {}: no interval ends there", object.knot);
            }
            for &a in &object.anchors {
                if a >= n {
                    anyhow::bail!("anchor {a}: the model has {n} anchors");
                }
                refit_of[a * knots + object.knot] = Some(object.refit);
            }
        }
        let v = |p: [f32; 3]| Vec3::from_array(p);
        // Per anchor linked again: the first frame of its earliest refitted interval.
        let mut moved: Vec<(usize, usize)> = Vec::new();
        let weights: Vec<f32> = frames.iter().map(|&(_, w)| w).collect();
        let width = set.dims.trajectory_width();
        let set = &mut self.model.anchors;
        let mut values = set.host(Column::Trajectory);
        let mut turn_values = set.host_if_present(Column::Turn);
        for a in 0..n {
            let refits = &refit_of[a * knots..(a + 1) * knots];
            let g = gates[a];
            if refits.iter().all(Option::is_none) || g <= 0.0 {
                continue;
            }
            // The rendered turn at each knot's frame: gate × the knots' interpolation there.
            let turn_vectors: Vec<Vec3> = match &turn_values {
                Some(turn) => {
                    let row = &turn[a * width..(a + 1) * width];
                    let knot = |k: usize| v(std::array::from_fn(|c| row[k * 3 + c]));
                    (0..knots)
                        .map(|k| match k {
                            0 => knot(0) * g,
                            _ => ((1.0 - weights[k]) * knot(k - 1) + weights[k] * knot(k)) * g,
                        })
                        .collect()
                }
                None => vec![Vec3::ZERO; knots],
            };
            let chain = KnotChain {
                places: (0..knots).map(|k| v(places[k][a])).collect(),
                turns: turn_vectors.iter().map(|&t| Quat::from_scaled_axis(t)).collect(),
            };
            let linked = relinked(&chain, refits);
            let changes: Vec<Vec3> = (0..knots)
                .map(|k| (linked.places[k] - chain.places[k]) / g)
                .collect();
            for (k, delta) in knots_through(&changes, &weights).into_iter().enumerate() {
                for c in 0..3 {
                    values[a * width + k * 3 + c] += delta[c];
                }
            }
            if let Some(turn) = turn_values.as_mut() {
                let targets: Vec<Vec3> = (0..knots)
                    .map(|k| rotation_vector_near(linked.turns[k], turn_vectors[k]) / g)
                    .collect();
                let row = &mut turn[a * width..(a + 1) * width];
                // Knot 0 is never refitted: it keeps its value exactly.
                for (k, knot) in knots_through(&targets, &weights)
                    .into_iter()
                    .enumerate()
                    .skip(1)
                {
                    row[k * 3..k * 3 + 3].copy_from_slice(&knot.to_array());
                }
            }
            let earliest = refits.iter().position(Option::is_some).expect("a refit");
            moved.push((a, frames[earliest - 1].0));
        }
        set.set_host(Column::Trajectory, values);
        if let Some(turn) = turn_values {
            set.set_host(Column::Turn, turn);
        }
        let streams_reset = match self.config.train.knot_refit_streams {
            KnotRefitStreams::Kept => 0,
            KnotRefitStreams::FirstFrame => self.reset_refitted_streams(&moved),
        };
        Ok(Relinked {
            anchors: moved.len(),
            streams_reset,
        })
    }
}
