//! The trainer's photometric searches when a trajectory knot opens: re-finding anchors whose
//! moving object left them (`train.knot_search`, `train/knot_search.rs`) and seeding anchors on
//! objects no anchor covers (`train.appearance_seeding`, `train/appearance_seeding.rs`). Both read
//! the training images of one frame and the evaluation's motion mask; neither renders.

use std::collections::{BTreeSet, HashSet};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::{Device, Float, Tensor, TensorData};

use super::super::anchor_state::RowEdit;
use super::super::appearance_seeding::{SeedParams, SeedReport, seed_positions};
use super::super::knot_search::{
    ConsensusReport, FrameViews, Placement, SearchGrouping, SearchParams, SearchReport,
    place_by_consensus, search_placements,
};
use super::super::losses::moving_pixel_weights;
use super::Trainer;
use crate::config::{KnotConsensus, KnotSearch, MovingGates};
use crate::data::ViewId;
use crate::data::frames::Frame;
use crate::device_io::upload;
use crate::eval::motion_mask::{median, motion_mask, temporal_median};
use crate::host_math::sigmoid;
use crate::model::anchors::{AnchorSet, Column, FACTOR_COUNT, MOTION_GATE, NewAnchors, SCALE_DIMS};
use crate::model::init::nearest_neighbors;
use crate::model::inputs::GATE_THRESHOLD;
use crate::model::view::{Phase, ViewTime, deformed_positions};
use crate::raster::RasterCamera;

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
        let seeded_at_previous = |r: u32| knot >= 2 && r as usize == (knot - 1) * spacing;
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
        for (a, &r) in self.anchor_state.reference_frame.iter().enumerate() {
            if !seeded_at_previous(r) {
                continue;
            }
            let b = knot - 1;
            let row = &mut values[a * width..(a + 1) * width];
            for c in 0..3 {
                let velocity = row[knot * 3 + c] - row[b * 3 + c];
                for i in 0..b {
                    row[i * 3 + c] = row[b * 3 + c] - (b - i) as f32 * velocity;
                }
            }
        }
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
        self.motion_peers = None;
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
