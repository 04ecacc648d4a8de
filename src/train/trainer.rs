//! The GIFStream training loop for one GOP (spec §4-§8): per step one training view, decode,
//! rasterize, 0.8·L1 + 0.2·D-SSIM plus the scale, gate and smoothness regularisers, Adam with the
//! per-group schedules, then the densification statistics and the refine steps.
//!
//! Reproducibility: every random choice of a step comes from a generator seeded by
//! (seed, step, purpose), and the view order from a sampler restorable from (seed, epoch,
//! position), so a run resumed from a checkpoint continues exactly as an uninterrupted one.

mod checkpoint_io;
mod motion_search;

pub use checkpoint_io::{TrainingHistory, read_trained_model};
pub use motion_search::{KnotRefitReport, KnotSearchOutcome, RigidFitReport};

use crate::device_io::{is_host_device, upload};
use crate::raster::columns::slice_columns;
use crate::raster::gather::gather_rows;
use std::path::Path;
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::{Device, Tensor, TensorData, s};
use rand::Rng;
use serde::Serialize;

use super::adaptive_cardinality::{RelocationChurn, RelocationReport};
use super::anchor_state::AnchorState;
use super::background::{Background, StartOn};
use super::coherence::{
    SPACE_TIME_REGROUP_EVERY, motion_peers, space_time_frames, trajectory_coherence,
};
use super::config::{
    AppearanceSeeding, CardinalityMode, CoherenceGroups, CrGradient, FeatureMaskMode, InitDynamic,
    KnotExtrapolation, KnotRefit, KnotSearch, RigidFit, SmoothMotion, SmoothSlots, TrainConfig,
};
use super::curvature::trajectory_curvature;
use super::decoder_adam::{DECODER_ADAM, DecoderAdam, tracked};
use super::device_targets::{
    DEFAULT_DEVICE_FRAME_CACHE_MIB, DeviceTarget, DeviceTargets, PixelWeighting,
};
use super::knots::start_new_knots;
use super::losses::photometric_loss;
use super::objective::{Objective, Term};
use super::optimizers::{Optimizers, StepRates, TrackedParameters};
use super::posthoc::PostHocReport;
use super::refine::{RefineContext, Refinement, refiners};
use super::row_adam::AdamConfig;
use super::seed_hold::{first_drawn_frames, hold_knots_still, resolved_mode};
use super::stage_clock::{Stage, StageClock, StageTimes};
use super::statistics::DensifyView;
use super::streams::{Stream, step_noise, step_rng};
use crate::codec::entropy_models::EntropyModels;
use crate::codec::quantization::simulate;
use crate::codec::rate::{RateInputs, rate, sample_rows};
use crate::codec::trained_model::TrainedModel;
use crate::config::{RateGraph, StepThread};
use crate::data::frames::FrameCache;
use crate::data::sampler::ViewSampler;
use crate::data::{Scene, ViewId};
use crate::host_math::sigmoid;
use crate::model::anchored::{AnchoredModel, BACKGROUND, ForwardValues, RenderedView};
use crate::model::anchors::{
    AnchorDims, AnchorSet, AnchorTensors, Column, FACTOR_COUNT, FeatureMasking, MOTION_GATE,
};
use crate::model::culling::FirstDrawnFrames;
use crate::model::decoders::{DecodedAnchors, DecoderSizes, Decoders};
use crate::model::feature_mask::{
    binary_mask, conditional_regularization, mask_loss, time_gate_share_below,
};
use crate::model::inputs::time_window_gap;
use crate::model::path_turns::derive_path_turns;
use crate::model::view::{Phase, ViewTime, VisibleRows, decode_view_rows};
use crate::raster::{IntersectionCapacity, RasterCamera, rasterize_with};
use burn::tensor::Gradients;

/// Per-anchor Adam (GIFStream: eps 1e-15 at batch size 1).
pub const ANCHOR_ADAM: AdamConfig = AdamConfig {
    beta1: 0.9,
    beta2: 0.999,
    eps: 1e-15,
};

/// Consecutive non-finite losses after which training stops with an error.
pub const MAX_CONSECUTIVE_NAN_STEPS: usize = 5;

/// Steps between two derivations of the turns from the paths (`model.trajectory_turn =
/// "paths"`) besides the steps that open knots or change rows: the gradient moves the knots a
/// little every step, and a derivation reads every anchor's trajectory back (host work).
const PATH_TURNS_EVERY: usize = 50;

/// What one step did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct StepReport {
    pub step: usize,
    pub loss: f32,
    /// PSNR of the training view.
    pub psnr: f32,
    pub anchors: usize,
    pub visible_anchors: usize,
    /// Gaussians spawned with opacity > 0.
    pub gaussians: usize,
    pub seconds: f64,
    /// The loss was not finite: no parameter was updated.
    pub skipped: bool,
    pub added: usize,
    pub pruned: usize,
    /// Active (ungated) slots over all anchors after the step.
    pub active_slots: usize,
    /// The AAC relocation of this step, if one ran.
    pub relocation: Option<RelocationReport>,
    /// Σ_attr mean bits of the rate term, when it is on.
    pub rate_bits: Option<f32>,
    /// The objective's terms computed this step, weighted (their sum is `loss`).
    pub terms: Vec<(Term, f32)>,
    /// Wall time per stage of the step (`bench train`).
    pub stages: StageTimes,
    /// The rasterizer's intersection buffers, sized ahead from the previous step, were too
    /// small: the view was rendered again, counting exactly.
    pub rerendered: bool,
    /// The step ran on a worker of rayon's pool (`train.step_thread`).
    pub ran_on_pool: bool,
}

/// The forward pass of one training step.
struct TrainingPass {
    when: ViewTime,
    camera: RasterCamera,
    /// [H, W, 3] the view's image.
    target: Tensor<3>,
    /// [H, W, 1] the L1 weights of its pixels (`loss.moving_weight`; `None` at weight 1).
    pixel_weights: Option<Tensor<3>>,
    /// Tracked copies of the anchor columns: the leaves Adam updates.
    tensors: AnchorTensors,
    /// What the decoders saw: `tensors` under the quantisation simulation.
    forward_tensors: AnchorTensors,
    /// Tracked copies of the decoders.
    decoders: Decoders,
    rendered: RenderedView,
}

/// The objective of one step and what is read back with it.
struct StepObjective {
    loss: Tensor<1>,
    objective: Objective,
    /// The MSE, then the rate term's bits when it is on.
    also: Vec<Tensor<1>>,
    /// The tracked entropy models, when the rate term is on.
    entropy: Option<EntropyModels>,
}

pub struct Trainer {
    pub config: TrainConfig,
    pub scene: Scene,
    pub frames: FrameCache,
    /// The training views' targets on the device (`data.device_frame_cache_mib`; none kept on
    /// the CPU backend, whose device memory is the host frame cache's).
    pub device_targets: DeviceTargets,
    /// The plain device the model lives on (training uses its autodiff twin).
    pub device: Device,
    pub model: AnchoredModel,
    /// Adam moments, statistics and AAC importance of the anchors, row-aligned with
    /// `model.anchors` (edited together through [`AnchorState::edit`]).
    pub anchor_state: AnchorState,
    /// The conditional entropy models (spec §9.3), trained by the rate term, used by the coder.
    pub entropy: EntropyModels,
    /// Adam state of the decoders and the entropy models.
    optimizers: Optimizers,
    sampler: ViewSampler,
    /// Steps completed; the next step has this index (GIFStream counts from 0).
    pub step: usize,
    /// Seconds spent in steps (evaluation and checkpoints excluded).
    pub train_seconds: f64,
    /// Relocated slots judged by the following AAC step, and those that stayed below τ.
    pub relocation_churn: RelocationChurn,
    /// The step the CR term started at (`aafm.cr_trigger`), once it has.
    pub cr_started_at: Option<usize>,
    /// Steps skipped because the loss was not finite.
    pub nan_steps: usize,
    consecutive_nan: usize,
    /// Step at which the learning-rate schedules started: 0, or the warm-start step of a later
    /// GOP (GIFStream re-creates its schedulers there, spec §5).
    pub schedule_origin: usize,
    /// The anchors' motion peers for the coherence term, rebuilt when the rows change.
    motion_peers: Option<Vec<u32>>,
    /// `train.seed_hold`'s first drawn frames and the open frame count they were built at,
    /// rebuilt when the rows change too.
    first_drawn: Option<(usize, Option<FirstDrawnFrames>)>,
    /// Room for the next step's tile intersections on a GPU, from this step's count (read with
    /// the loss): the rasterizer then reads nothing back; `None` counts exactly (the first step,
    /// and on the CPU, where reading is free).
    pub intersection_capacity: Option<usize>,
    /// The room `intersection_capacity` rounds up ([`Self::size_intersections_ahead`]).
    intersection_room: f64,
    /// Per training camera, the temporal median of its images (for `train.knot_search`'s
    /// moving pixels and `loss.moving_weight`), computed from the ground truth at the first use
    /// (so a resumed run recomputes the same).
    temporal_medians: Option<Vec<Vec<f32>>>,
}

impl Trainer {
    /// A fresh model for `scene` (anchors from its point cloud).
    pub fn new(config: TrainConfig, scene: Scene, device: Device) -> Result<Self> {
        if scene.points.is_empty() {
            bail!(
                "{}: the dataset has no initial points",
                scene.root.display()
            );
        }
        if scene.train_cameras.is_empty() {
            bail!("{}: no training cameras", scene.root.display());
        }
        let dims = anchor_dims(&config, &scene);
        let mut anchors = AnchorSet::from_points(
            &scene.points.positions,
            config.model.voxel_size,
            dims,
            &device,
        );
        if anchors.is_empty() {
            bail!("{}: no finite initial points", scene.root.display());
        }
        let start = config.train.motion_gate_start;
        if start != 0.0 {
            // Not in GIFStream (its gates start at logit 0): see `train.motion_gate_start`.
            let mut factors = anchors.host(Column::Factors);
            for row in factors.chunks_exact_mut(FACTOR_COUNT) {
                row[MOTION_GATE] = start;
            }
            anchors.set_host(Column::Factors, factors);
        }
        let decoders = initial_decoders(&config, &device);
        let entropy = EntropyModels::seeded(decoder_sizes(&config), config.train.seed, &device);
        let optimizers = Optimizers::new(&decoders, &entropy);
        let sampler = ViewSampler::new(scene.train_views(), config.train.seed);
        let frames = FrameCache::new(config.data.frame_cache_mib << 20);
        let device_targets = DeviceTargets::new(match config.data.device_frame_cache_mib {
            Some(mib) => mib.saturating_mul(1 << 20),
            None if is_host_device(&device) => 0,
            None => DEFAULT_DEVICE_FRAME_CACHE_MIB << 20,
        });
        let culling = config.model.culling;
        let anchor_state = AnchorState::new(&anchors, 0, ANCHOR_ADAM);
        Ok(Self {
            config,
            scene,
            frames,
            device_targets,
            device,
            model: AnchoredModel {
                anchors,
                decoders,
                culling,
            },
            anchor_state,
            entropy,
            optimizers,
            sampler,
            step: 0,
            train_seconds: 0.0,
            nan_steps: 0,
            relocation_churn: RelocationChurn::default(),
            cr_started_at: None,
            consecutive_nan: 0,
            schedule_origin: 0,
            motion_peers: None,
            first_drawn: None,
            intersection_capacity: None,
            intersection_room: 0.0,
            temporal_medians: None,
        })
    }

    /// Warm start of a later GOP (spec §5): the anchors (time features included) and decoders of
    /// another run's checkpoint, fresh optimizer state and densification statistics, training
    /// continuing at `init_step` with the learning-rate schedules restarted there. The canonical
    /// phase and `init_dynamic` are skipped when `init_step` is past them, as in GIFStream.
    pub fn warm_start(&mut self, path: &Path, init_step: usize) -> Result<()> {
        if init_step >= self.config.train.max_steps {
            bail!(
                "warm start at step {init_step} leaves nothing to train (train.max_steps = {})",
                self.config.train.max_steps
            );
        }
        self.load_checkpoint(path)?;
        self.anchor_state.restart(&self.model.anchors, ANCHOR_ADAM);
        // Reference frames restart at 0.
        self.rows_changed();
        // The entropy models and their Adam state carry over (noted in docs/results.md).
        self.optimizers.decoders = DecoderAdam::new(&self.model.decoders, DECODER_ADAM);
        self.step = init_step;
        self.schedule_origin = init_step;
        self.train_seconds = 0.0;
        self.nan_steps = 0;
        self.relocation_churn = RelocationChurn::default();
        self.cr_started_at = None;
        // A fresh view order for this GOP.
        self.sampler = ViewSampler::new(self.scene.train_views(), self.config.train.seed);
        Ok(())
    }

    /// The trained model as it stands (a copy: the trainer keeps training).
    pub fn trained_model(&self) -> TrainedModel {
        let frames = &self.scene.frames;
        TrainedModel {
            model: self.model.clone(),
            entropy: self.entropy.clone(),
            config: self.config.clone(),
            step: self.step,
            gop: (frames.start, frames.count),
        }
    }

    /// What training did so far, besides the model.
    pub fn history(&self) -> TrainingHistory {
        TrainingHistory {
            train_seconds: self.train_seconds,
            nan_steps: self.nan_steps,
            relocation_churn: self.relocation_churn,
        }
    }

    pub fn finished(&self) -> bool {
        self.step >= self.config.train.max_steps
    }

    pub fn phase(&self, step: usize) -> Phase {
        self.config.train.phase_at(step)
    }

    /// The training view of `step`: the sampler's next view, or, while the temporal curriculum
    /// is opening frames, a view drawn uniformly from the open frames (seeded by the step, so a
    /// resumed run draws the same; the sampler's epoch order starts when every frame is open).
    fn next_view(&mut self, step: usize) -> ViewId {
        let frames = &self.scene.frames;
        let open = self.config.train.open_frames(step, frames.count);
        if open >= frames.count {
            return self.sampler.next_view();
        }
        let mut rng = step_rng(self.config.train.seed, step, Stream::Curriculum);
        let cameras = &self.scene.train_cameras;
        let camera = cameras[rng.random_range(0..cameras.len())];
        let frontier = (frames.count / 10).max(1).min(open);
        let first = if rng.random::<f64>() < self.config.train.frontier_share {
            open - frontier
        } else {
            0
        };
        ViewId {
            camera,
            frame: frames.start + rng.random_range(first..open),
        }
    }

    /// Under the temporal curriculum, the trajectory knots that this step's newly opened frames
    /// reach for the first time start where each anchor is heading: K_j = 2·K_{j−1} − K_{j−2}
    /// (K_{j−1} for j = 1), so a frame opens with its object close to where it is and the local
    /// gradient can finish the job. Decided by the step alone: resume stays exact.
    /// Whether knots opened.
    fn extend_trajectories(&mut self, step: usize) -> Result<bool> {
        let cfg = &self.config.train;
        let set = &mut self.model.anchors;
        let d = set.dims;
        if set.columns.get(Column::Trajectory).is_none() {
            return Ok(false);
        }
        let opened = cfg.knots_opened(step, d.trajectory_spacing, d.frames, d.trajectory_knots());
        if opened.is_empty() || set.positions.is_empty() {
            return Ok(false);
        }
        let (from, to) = (opened.start, opened.end);
        let mut values = set.host(Column::Trajectory);
        // The motion gates, only where the rule needs them (the gate scales the knots).
        let gates: Vec<f32> = match cfg.knot_extrapolation {
            KnotExtrapolation::MovingVelocity => set
                .host(Column::Factors)
                .chunks_exact(FACTOR_COUNT)
                .map(|f| sigmoid(f[MOTION_GATE]))
                .collect(),
            _ => Vec::new(),
        };
        start_new_knots(
            &mut values,
            d.trajectory_width(),
            from..to,
            cfg.knot_extrapolation,
            &gates,
            cfg.knot_moving_voxels * self.config.model.voxel_size,
        );
        set.set_host(Column::Trajectory, values);
        // The turns start alike; under `moving-velocity` an anchor whose last segment turned it
        // (gate × angle) more than TURNING_MIN_RADIANS keeps turning.
        if let Some(mut turns) = set.host_if_present(Column::Turn) {
            start_new_knots(
                &mut turns,
                d.turn_width(),
                from..to,
                cfg.knot_extrapolation,
                &gates,
                TURNING_MIN_RADIANS,
            );
            set.set_host(Column::Turn, turns);
        }
        let (search, seeding, rigid) = (cfg.knot_search, cfg.appearance_seeding, cfg.rigid_fit);
        for knot in from..to {
            // Lost anchors first, so the seeding sees the objects they re-found as explained;
            // the objects' rigid motions start from where the search put their anchors.
            if search != KnotSearch::Off {
                self.search_knot(step, knot)?;
            }
            if rigid != RigidFit::Off {
                self.fit_rigid_knot(step, knot)?;
            }
            if seeding == AppearanceSeeding::Photometric {
                self.seed_appearances(step, knot)?;
            }
        }
        Ok(true)
    }

    /// Whether `train.knot_refit` refits the knots at `step`: under `"curriculum-end"`, the
    /// step at which the temporal curriculum opens the last frame; under `"at-share"`,
    /// ⌈`knot_refit_share` × `max_steps`⌉ (decided by the step alone: a resumed run refits
    /// exactly when an uninterrupted one does).
    fn knot_refit_at(&self, step: usize) -> bool {
        let cfg = &self.config.train;
        let frames = self.scene.frames.count;
        match cfg.knot_refit {
            KnotRefit::Off => false,
            KnotRefit::CurriculumEnd => {
                step > 0
                    && cfg.curriculum_opening(step - 1, frames)
                    && !cfg.curriculum_opening(step, frames)
            }
            KnotRefit::AtShare => {
                step == (cfg.knot_refit_share * cfg.max_steps as f64).ceil() as usize
            }
        }
    }

    /// Whether the CR term acts at `step`: from `aafm.cr_start`, and under
    /// `CrTrigger::GateShare` once enough time gates favour masking; the start is latched.
    fn conditional_regularization_on(&mut self, step: usize) -> bool {
        let aafm = &self.config.aafm;
        // The weight test also covers a resume that switched CR off after it had started.
        if aafm.mode != FeatureMaskMode::Adaptive || aafm.cr_weight <= 0.0 {
            return false;
        }
        if self.cr_started_at.is_some_and(|start| start <= step) {
            return true;
        }
        let anchors = &self.model.anchors;
        let share = (aafm.cr_checks_gates_at(step) && !anchors.is_empty())
            .then(|| time_gate_share_below(anchors.value(Column::Factors), aafm.cr_neutral_gate()));
        let on = aafm.cr_starts_at(step, share);
        if on {
            self.cr_started_at = Some(step);
            if let Some(share) = share {
                eprintln!(
                    "step {step}: CR starts ({:.1} % of anchors have sigma(d) < {:.3})",
                    100.0 * share,
                    aafm.cr_neutral_gate()
                );
            }
        }
        on
    }

    /// The target image of a view, [H, W, 3] on `device`.
    pub fn target(&self, view: ViewId, device: &Device) -> Result<Tensor<3>> {
        let frame = self.frames.get(&self.scene, view)?;
        Ok(upload::<3, burn::tensor::Float>(
            TensorData::new(
                frame.rgb.clone(),
                [frame.height as usize, frame.width as usize, 3],
            ),
            device,
        ))
    }

    /// What the step of `view` compares its render with, on the autodiff device: from the
    /// device cache, or uploaded (and kept when it fits the cache).
    fn step_target(&mut self, view: ViewId) -> Result<DeviceTarget> {
        let weighting = PixelWeighting {
            moving_weight: self.config.loss.moving_weight,
            mask: self.config.eval.motion_mask(),
        };
        if let Some(target) = self.device_targets.get(view, weighting) {
            return Ok(target);
        }
        let device = self.device.clone().autodiff();
        let target = DeviceTarget {
            rgb: self.target(view, &device)?,
            pixel_weights: self.moving_pixel_weights(view, &device)?,
            weighted_by: weighting,
        };
        self.device_targets.insert(view, target.clone());
        Ok(target)
    }

    /// The room for the next step's tile intersections (on a GPU), from this step's count:
    /// its count and a quarter more (another view, densification), or the room kept so far
    /// shrunk by [`INTERSECTION_ROOM_DECAY`], whichever is larger; twice the kept room after a
    /// step that overflowed it.
    fn size_intersections_ahead(&mut self, needed: f32, overflowed: bool) {
        let wanted = needed as f64 * 1.25;
        let kept = match overflowed {
            true => self.intersection_room * 2.0,
            false => self.intersection_room * INTERSECTION_ROOM_DECAY,
        };
        self.intersection_room = wanted.max(kept);
        self.intersection_capacity = Some(intersection_bucket(self.intersection_room));
    }

    /// One training step: refiners due before the forward pass, the forward pass, the objective
    /// (one read-back; a second for a concurrent rate term's bits on the CPU, where reading is
    /// free), the backward pass and the optimizers, the statistics, then the refiners
    /// due after the update. On the CPU backend it runs on a worker of rayon's pool
    /// (`train.step_thread`).
    pub fn step(&mut self) -> Result<StepReport> {
        match self.background_on() {
            // Called from outside the pool, `rayon::scope` runs the closure on a worker and
            // blocks the caller until it returns (a panic comes back to the caller).
            StartOn::Pool => rayon::scope(|_| self.step_on_this_thread()),
            StartOn::Thread => self.step_on_this_thread(),
        }
    }

    /// Where the step's background work (the rate term's own graph) runs: a pool job when
    /// the step runs on the pool, a thread of its own otherwise. A CPU step called from a
    /// worker of the pool already (a caller's own parallel loop) is on the pool whatever
    /// `train.step_thread` says: there a thread of its own, joined by the blocked worker, could
    /// wait for a free worker forever. On a GPU the rate graph's thread only queues device work.
    fn background_on(&self) -> StartOn {
        if !is_host_device(&self.device) {
            return StartOn::Thread;
        }
        match self.config.train.step_thread {
            StepThread::Pool => StartOn::Pool,
            StepThread::Caller if rayon::current_thread_index().is_some() => StartOn::Pool,
            StepThread::Caller => StartOn::Thread,
        }
    }

    fn step_on_this_thread(&mut self) -> Result<StepReport> {
        let started = Instant::now();
        let mut clock = StageClock::start();
        let step = self.step;
        let refiners = refiners(&self.config);
        for refiner in &refiners {
            refiner.before_forward(&mut self.refine_context(step));
        }
        let knots_opened = self.extend_trajectories(step)?;
        if self.knot_refit_at(step) {
            self.refit_knots(step)?;
        }
        if knots_opened || step % PATH_TURNS_EVERY == 0 {
            let objects = derive_path_turns(&mut self.model.anchors);
            if knots_opened && !objects.is_empty() {
                let turning: Vec<String> = objects
                    .iter()
                    .filter(|o| o.turns)
                    .map(ToString::to_string)
                    .collect();
                eprintln!(
                    "step {step}: object turns: {} of {} groups turn{}{}",
                    turning.len(),
                    objects.len(),
                    if turning.is_empty() { "" } else { ": " },
                    turning.join("; ")
                );
            }
        }
        let cr_on = self.conditional_regularization_on(step);
        let view = self.next_view(step);
        let own_rate = self.spawn_rate_graph(step, self.view_time(step, view).frame);
        clock.lap(Stage::RefineBefore);
        let mut pass = self.forward_pass(step, view, &mut clock)?;
        let StepObjective {
            mut loss,
            mut objective,
            mut also,
            mut entropy,
        } = self.objective(step, &pass, cr_on, own_rate.is_none());
        // With the rate term in its own graph: on a device whose read-backs synchronise (a
        // GPU), its thread is joined before the step's read so that its bits come back in it
        // (the thread only queued work there); on the CPU, where reading is free, the step's
        // backward overlaps the thread, joined after it.
        let join_first = !is_host_device(&self.device);
        let mut own_rate = own_rate;
        let joined = match own_rate.take_if(|_| join_first) {
            Some(thread) => Some(join_rate_graph(thread, step)?),
            None => None,
        };
        if let Some(rate) = &joined {
            rate.read_bits_with(&mut also);
        }
        // (Waiting for a joined rate graph counts as the objective's time.)
        clock.lap(Stage::Objective);
        // One read-back: the loss, every term, the MSE, the rasterizer's intersection count and
        // (in the step's graph, or joined before it) the rate term's bits.
        let mut values = objective.read(&loss, &also);
        let mut rerendered = false;
        if values.also[ALSO_OVERFLOWED] > 0.0 {
            // The intersection buffers sized ahead were too small (a view or a densification
            // that made many more): render the decoded Gaussians again, counting exactly.
            rerendered = true;
            clock.lap(Stage::ReadBack);
            // The incomplete render's graph goes before the new one is built.
            drop((loss, objective, also, entropy));
            pass.rendered.raster = rasterize_with(
                &pass.rendered.decoded.gaussians,
                &pass.camera,
                BACKGROUND,
                IntersectionCapacity::Exact,
            )?;
            StepObjective {
                loss,
                objective,
                also,
                entropy,
            } = self.objective(step, &pass, cr_on, own_rate.is_none() && joined.is_none());
            if let Some(rate) = &joined {
                rate.read_bits_with(&mut also);
            }
            clock.lap(Stage::Forward);
            values = objective.read(&loss, &also);
        }
        self.size_intersections_ahead(values.also[ALSO_INTERSECTIONS], rerendered);
        clock.lap(Stage::ReadBack);
        let mut loss_value = values.total;
        let mut terms = values.terms;
        let mut rate_bits = values.also.get(ALSO_RATE_BITS).copied();
        let mut grads = None;
        let own_rate = match (joined, own_rate) {
            (Some(rate), _) => Some(rate),
            (None, Some(thread)) => {
                if loss_value.is_finite() {
                    grads = Some(loss.backward());
                }
                let rate = join_rate_graph(thread, step)?;
                rate_bits = Some(crate::model::anchors::host_values(&rate.bits)[0]);
                Some(rate)
            }
            (None, None) => None,
        };
        // The loss is judged with the rate added.
        if let (Some(_), Some(bits)) = (&own_rate, rate_bits) {
            let weighted = bits * self.config.compression.rate.rd_lambda();
            loss_value += weighted;
            terms.push((Term::Rate, weighted));
        }
        if self.config.train.inject_nonfinite.contains(&step) {
            loss_value = f32::NAN;
        }
        let mut report = StepReport {
            step,
            loss: loss_value,
            psnr: -10.0 * values.also[ALSO_MSE].max(1e-12).log10(),
            visible_anchors: values.also[ALSO_VISIBLE] as usize,
            rate_bits,
            terms,
            rerendered,
            ran_on_pool: rayon::current_thread_index().is_some(),
            ..Default::default()
        };
        if loss_value.is_finite() {
            self.consecutive_nan = 0;
            let mut grads = grads.unwrap_or_else(|| loss.backward());
            if let Some(rate) = &own_rate {
                merge_rate_gradients(&pass.tensors, rate, &mut grads);
            }
            clock.lap(Stage::Backward);
            let rates = StepRates::at(
                &self.config,
                &self.model.anchors.dims,
                step,
                self.schedule_origin,
            );
            let tracked = TrackedParameters {
                anchors: &pass.tensors,
                decoders: &pass.decoders,
                entropy: match (&own_rate, &entropy) {
                    (Some(rate), _) => Some((&rate.models, &rate.grads)),
                    (None, Some(models)) => Some((models, &grads)),
                    (None, None) => None,
                },
            };
            let (model, state) = (&mut self.model, &mut self.anchor_state);
            self.optimizers
                .step(model, state, &mut self.entropy, tracked, &grads, &rates);
            clock.lap(Stage::Optimizer);
            self.gather_statistics(step, &pass, &grads);
            report.gaussians = values.also[ALSO_GAUSSIANS] as usize;
            clock.lap(Stage::Statistics);
            for refiner in &refiners {
                let done = refiner.after_step(&mut self.refine_context(step));
                self.record_refinement(done, &mut report);
            }
            // New rows and neighbour lists: their turns at once.
            if report.added + report.pruned > 0 {
                derive_path_turns(&mut self.model.anchors);
            }
        } else {
            self.skip_nonfinite(step)?;
            report.skipped = true;
        }
        self.step += 1;
        report.anchors = self.model.anchors.len();
        report.active_slots = self.model.anchors.active_slot_count();
        clock.lap(Stage::RefineAfter);
        report.stages = clock.times();
        report.seconds = started.elapsed().as_secs_f64();
        self.train_seconds += report.seconds;
        Ok(report)
    }

    fn refine_context(&mut self, step: usize) -> RefineContext<'_> {
        RefineContext::new(
            &mut self.model.anchors,
            &mut self.anchor_state,
            step,
            self.config.train.seed,
        )
    }

    /// Adds what a refiner did to the step's report.
    fn record_refinement(&mut self, done: Option<Refinement>, report: &mut StepReport) {
        match done {
            None => {}
            Some(Refinement::Rows(d)) => {
                report.added += d.added;
                report.pruned += d.pruned;
                if d.added + d.pruned > 0 {
                    self.rows_changed();
                }
            }
            Some(Refinement::Relocation(relocation)) => {
                self.relocation_churn.add(&relocation);
                report.relocation = Some(relocation);
            }
        }
    }

    /// A step whose loss was not finite updates nothing; too many in a row stop training.
    fn skip_nonfinite(&mut self, step: usize) -> Result<()> {
        self.nan_steps += 1;
        self.consecutive_nan += 1;
        if self.consecutive_nan >= MAX_CONSECUTIVE_NAN_STEPS {
            bail!(
                "the loss was not finite for {} consecutive steps (last at step {step}); \
                 stopping rather than training on garbage. Lower the learning rates or \
                 resume from an earlier checkpoint.",
                self.consecutive_nan
            );
        }
        Ok(())
    }

    /// The view, frame and time of `step`.
    fn view_time(&self, step: usize, view: ViewId) -> ViewTime {
        let train = &self.config.train;
        let frames = self.model.anchors.dims.frames;
        ViewTime {
            frame: view.frame - self.scene.frames.start,
            time: self.scene.time(view.frame),
            window_gap: time_window_gap(step, train.max_steps, frames),
            phase: self.phase(step),
            time_bands: train.time_bands(step),
        }
    }

    /// The caches of row-aligned values (the coherence term's motion peers, the held anchors'
    /// first drawn frames) are stale: the rows or their reference frames changed.
    fn rows_changed(&mut self) {
        self.motion_peers = None;
        self.first_drawn = None;
    }

    /// `train.seed_hold`: the frames before which `step` does not draw each anchor (`None`: all
    /// drawn everywhere), rebuilt only when the open frames or the rows change.
    fn first_drawn_frames(&mut self, step: usize) -> Option<FirstDrawnFrames> {
        let frames = self.model.anchors.dims.frames;
        let open = self.config.train.open_frames(step, frames);
        match &self.first_drawn {
            Some((o, first)) if *o == open => first.clone(),
            _ => {
                let mode = resolved_mode(
                    &self.config.train,
                    frames,
                    self.model.anchors.dims.trajectory_spacing,
                );
                let first = first_drawn_frames(
                    mode,
                    &self.anchor_state.reference_frame,
                    open,
                    frames,
                )
                .map(|first| FirstDrawnFrames::new(first, &self.device));
                self.first_drawn = Some((open, first.clone()));
                first
            }
        }
    }

    /// The forward pass of `step` on tracked copies of the anchors (quantisation simulated,
    /// spec §9.2; Adam updates the leaves) and decoders.
    fn forward_pass(
        &mut self,
        step: usize,
        view: ViewId,
        clock: &mut StageClock,
    ) -> Result<TrainingPass> {
        let when = self.view_time(step, view);
        let camera = self.scene.cameras[view.camera].camera.clone();
        let DeviceTarget {
            rgb: target,
            pixel_weights,
            ..
        } = self.step_target(view)?;
        let tensors = self.model.anchors.tracked();
        let cfg = &self.config;
        let forward_tensors = simulated_at_step(
            &cfg.compression,
            cfg.train.seed,
            cfg.train.max_steps,
            step,
            &tensors,
        );
        let decoders = tracked(&self.model.decoders);
        clock.lap(Stage::Quantization);
        let first_frames = self.first_drawn_frames(step);
        let forward_tensors = match &first_frames {
            Some(first) => hold_knots_still(forward_tensors, first),
            None => forward_tensors,
        };
        let cfg = &self.config;
        let values = ForwardValues::Tracked {
            anchors: &forward_tensors,
            decoders: &decoders,
            culling: cfg.train.step_culling,
            first_frames: first_frames.as_ref(),
        };
        let capacity = match self.intersection_capacity {
            Some(slots) if !is_host_device(&self.device) => IntersectionCapacity::AtMost(slots),
            _ => IntersectionCapacity::Exact,
        };
        let rendered = self.model.forward_with(&camera, when, values, capacity)?;
        clock.lap(Stage::Forward);
        Ok(TrainingPass {
            when,
            camera,
            target,
            pixel_weights,
            tensors,
            forward_tensors,
            decoders,
            rendered,
        })
    }

    /// The step's objective (spec §6, §9.3, §13): the photometric term and every regulariser
    /// that is on; with the tracked entropy models when the rate term is.
    /// `shared_rate`: whether the rate term (when on) is in this graph (`compression.rate_graph
    /// = "shared"`).
    fn objective(
        &mut self,
        step: usize,
        pass: &TrainingPass,
        cr_on: bool,
        shared_rate: bool,
    ) -> StepObjective {
        let cfg = &self.config;
        let raster = &pass.rendered.raster;
        let photometric = photometric_loss(
            raster.image.clone(),
            pass.target.clone(),
            cfg.loss.ssim_lambda,
            pass.pixel_weights.clone(),
        );
        let mut objective = Objective::new(photometric.loss);
        self.regularizers(step, pass, cr_on, &mut objective);
        // Read back with the loss: the MSE, the count of spawned Gaussians (gates > 0), the
        // rasterizer's intersection count and whether its buffers overflowed and, when on, the
        // rate term's bits — one synchronisation for all of them.
        let decoded = &pass.rendered.decoded;
        let gaussians = decoded.gaussians.gates.clone().sum();
        let visible = decoded.visible.count(&gaussians.device());
        let mut also = vec![
            photometric.mse,
            gaussians,
            raster.intersections().float(),
            raster.overflowed(),
            visible,
        ];
        let rate = shared_rate
            .then(|| self.rate_term(step, pass, &mut objective))
            .flatten();
        let entropy = rate.map(|(models, bits)| {
            assert_eq!(also.len(), ALSO_RATE_BITS);
            also.push(bits);
            models
        });
        StepObjective {
            loss: objective.total(),
            objective,
            also,
            entropy,
        }
    }

    /// Volume, gate, temporal smoothness, trajectory coherence, AAFM mask rate and CR.
    fn regularizers(
        &mut self,
        step: usize,
        pass: &TrainingPass,
        cr_on: bool,
        objective: &mut Objective,
    ) {
        let cfg = &self.config;
        let decoded = &pass.rendered.decoded;
        let rows = decoded.visible.rows();
        // Scale regulariser: mean over spawned Gaussians of the product of their scales.
        let g = &decoded.gaussians;
        let n = g.len();
        if cfg.loss.scale_reg > 0.0 && n > 0 {
            let volume = slice_columns(g.scales.clone(), 0..1)
                .mul(slice_columns(g.scales.clone(), 1..2))
                .mul(slice_columns(g.scales.clone(), 2..3))
                .reshape([n]);
            let spawned = g.gates.clone().sum().clamp_min(1.0);
            objective.add(
                Term::Volume,
                (volume * g.gates.clone()).sum() / spawned * cfg.loss.scale_reg,
            );
        }
        // Gate regulariser, after (gate + 0.1)·max_steps (spec §6).
        // Over the visible anchors' gates.
        if cfg.loss.factor_reg > 0.0 && step > cfg.train.factor_reg_after() && rows > 0 {
            let (gates, visible) = (decoded.gates.clone(), &decoded.visible);
            let reg = visible.mean(slice_columns(gates.clone(), 0..3))
                + visible.mean(slice_columns(gates, 3..4)) * 0.1;
            objective.add(Term::Gate, reg * cfg.loss.factor_reg);
        }
        if let Some(term) = self.smoothness_term(step, pass) {
            objective.add(Term::Smoothness, term);
        }
        let cfg = &self.config;
        let tensors = &pass.tensors;
        // Trajectory coherence (not in GIFStream, `coherence.rs`).
        if cfg.loss.trajectory_coherence > 0.0
            && let Some(trajectory) = tensors.trajectory()
            && pass.when.phase == Phase::Dynamic
        {
            let weight = cfg.loss.trajectory_coherence;
            let peers = self.motion_peers_at(step);
            objective.add(
                Term::Coherence,
                trajectory_coherence(trajectory, tensors.factors(), peers) * weight,
            );
        }
        // Trajectory curvature (not in GIFStream, `curvature.rs`), over the knots the open
        // frames use.
        let cfg = &self.config;
        if cfg.loss.trajectory_curvature > 0.0
            && let Some(trajectory) = tensors.trajectory()
            && pass.when.phase == Phase::Dynamic
        {
            let frames = self.scene.frames.count;
            let spacing = self.model.anchors.dims.trajectory_spacing;
            let reached = cfg.train.knots_reached_at(step, spacing, frames);
            if let Some(term) = trajectory_curvature(trajectory, tensors.factors(), reached) {
                objective.add(Term::Curvature, term * cfg.loss.trajectory_curvature);
            }
        }
        // AAFM mask rate and conditional regularisation (spec §13.1-§13.2), over all anchors.
        if cfg.aafm.mode == FeatureMaskMode::Adaptive && !self.model.anchors.is_empty() {
            let m = tensors.mask_logits();
            objective.add(Term::MaskRate, mask_loss(m.clone()) * cfg.aafm.mask_weight);
            if cr_on {
                let d = tensors.factors().slice(s![.., 0..1]);
                let gate_gradient = cfg.aafm.cr_gradient == CrGradient::MaskAndGate;
                objective.add(
                    Term::ConditionalRegularization,
                    conditional_regularization(d, m, gate_gradient) * cfg.aafm.cr_weight,
                );
            }
        }
    }

    /// The trajectory coherence term's motion peers (`coherence.rs`), rebuilt after the anchor
    /// set changed and, when grouped in space-time, every `SPACE_TIME_REGROUP_EVERY` steps.
    fn motion_peers_at(&mut self, step: usize) -> &[u32] {
        let cell = self.config.loss.coherence_cell;
        let groups = self.config.loss.coherence_groups;
        if groups == CoherenceGroups::SpaceTime && step % SPACE_TIME_REGROUP_EVERY == 0 {
            self.motion_peers = None;
        }
        if self.motion_peers.is_none() {
            let peers = match groups {
                CoherenceGroups::Canonical => motion_peers(&[&self.model.anchors.positions], cell),
                CoherenceGroups::SpaceTime => {
                    let tracks: Vec<Vec<[f32; 3]>> =
                        space_time_frames(self.model.anchors.dims.frames)
                            .into_iter()
                            .map(|frame| self.positions_at(step, frame))
                            .collect();
                    let tracks: Vec<&[[f32; 3]]> = tracks.iter().map(Vec::as_slice).collect();
                    motion_peers(&tracks, cell)
                }
            };
            self.motion_peers = Some(peers);
        }
        self.motion_peers.as_deref().expect("built above")
    }

    /// Temporal smoothness against a no-gradient decode 1-2 frames away (spec §4.5), on the
    /// steps it runs.
    fn smoothness_term(&self, step: usize, pass: &TrainingPass) -> Option<Tensor<1>> {
        let cfg = &self.config;
        let (decoded, when) = (&pass.rendered.decoded, pass.when);
        let t_frames = self.model.anchors.dims.frames;
        let due = cfg.loss.smooth_reg > 0.0
            && cfg.train.smooth_every > 0
            && step % cfg.train.smooth_every == 0
            && when.phase == Phase::Dynamic
            && decoded.visible.rows() > 0
            && t_frames > 1;
        if !due {
            return None;
        }
        let mut rng = step_rng(cfg.train.seed, step, Stream::Smoothness);
        let delta = [-2i64, -1, 1, 2][rng.random_range(0..4)];
        let other = (when.frame as i64 + delta).clamp(0, t_frames as i64 - 1) as usize;
        let other_when = ViewTime {
            frame: other,
            time: other as f32 / (t_frames - 1) as f32,
            ..when
        };
        // From the unquantised attributes. A kept deviation: GIFStream decodes both frames from
        // the simulated ones; with the decoder eps and the gate clamp, its choices measured
        // 0.35-1.75 dB worse decoded PSNR on three seeds (docs/results.md, Follow-up 4).
        let reference = decode_view_rows(
            &self.model.anchors,
            &self.model.anchors.untracked(),
            &self.model.decoders,
            // Without the step's autodiff context: a plain decode.
            decoded.visible.inner(),
            decoded.visible_index.clone().inner(),
            other_when,
        );
        let motion_gates = match cfg.loss.smooth_motion {
            SmoothMotion::Raw => None,
            SmoothMotion::Gated => Some((
                decoded.gates.clone().slice(s![.., 1..2]),
                reference.gates.clone().slice(s![.., 1..2]),
            )),
        };
        // The rows' slot gates (none while every slot is on, as under GIFStream).
        let slot_gates = match cfg.loss.smooth_slots {
            SmoothSlots::All => None,
            SmoothSlots::Active => self
                .model
                .anchors
                .slot_gates
                .mirror()
                .map(|gates| gather_rows(gates.clone(), decoded.visible_index.clone())),
        };
        Some(
            smoothness(
                &decoded.visible,
                &decoded.decoded,
                &reference.decoded,
                motion_gates,
                slot_gates,
            ) * cfg.loss.smooth_reg,
        )
    }

    /// Whether the rate term is on at `step`.
    fn rate_on(&self, step: usize) -> bool {
        let cfg = &self.config;
        cfg.compression.rate_at(step, cfg.train.max_steps) && !self.model.anchors.is_empty()
    }

    /// The entropy models start from the anchors' statistics at the rate term's first step.
    fn start_entropy_models(&mut self, step: usize) {
        let cfg = &self.config;
        if step == 0 || !cfg.compression.rate_at(step - 1, cfg.train.max_steps) {
            self.entropy
                .start_from(&self.model.anchors, &cfg.compression.quantization_steps());
        }
    }

    /// The rate term in the step's graph (`compression.rate_graph = "shared"`). Returns the
    /// tracked entropy models (their gradients are in the loss) and the bits, when it is on.
    fn rate_term(
        &mut self,
        step: usize,
        pass: &TrainingPass,
        objective: &mut Objective,
    ) -> Option<(EntropyModels, Tensor<1>)> {
        if !self.rate_on(step) {
            return None;
        }
        self.start_entropy_models(step);
        let cfg = &self.config;
        let models = self.entropy.tracked();
        let anchors = &self.model.anchors;
        let total = rate_bits(
            &RateContext {
                compression: &cfg.compression,
                seed: cfg.train.seed,
                step,
                frame: pass.when.frame,
                dims: &anchors.dims,
                slot_gates: anchors.slot_gates.mirror().cloned(),
            },
            &models,
            &pass.forward_tensors,
            &pass.tensors,
        );
        objective.add(Term::Rate, total.clone() * cfg.compression.rate.rd_lambda());
        Some((models, total))
    }

    /// The rate term in a graph of its own beside the step (`compression.rate_graph =
    /// "concurrent"`; a pool job or a thread, [`Self::background_on`]), when it is on: fresh
    /// tracked copies of the anchors (the same values the step's pass tracks), quantisation
    /// simulated with the step's own noise key (so the priced values equal the pass's), and the
    /// tracked entropy models; the job runs the backward of the weighted rate.
    /// [`merge_rate_gradients`] adds its gradients to the step's.
    fn spawn_rate_graph(&mut self, step: usize, frame: usize) -> Option<Background<OwnRateGraph>> {
        if self.config.compression.rate_graph != RateGraph::Concurrent || !self.rate_on(step) {
            return None;
        }
        self.start_entropy_models(step);
        let anchors = &self.model.anchors;
        let leaves = anchors.tracked();
        let models = self.entropy.tracked();
        let compression = self.config.compression.clone();
        let (seed, max_steps) = (self.config.train.seed, self.config.train.max_steps);
        let dims = anchors.dims;
        let slot_gates = anchors.slot_gates.mirror().cloned();
        Some(Background::start(self.background_on(), move || {
            let sim = simulated_at_step(&compression, seed, max_steps, step, &leaves);
            let context = RateContext {
                compression: &compression,
                seed,
                step,
                frame,
                dims: &dims,
                slot_gates,
            };
            let bits = rate_bits(&context, &models, &sim, &leaves);
            let grads = (bits.clone() * compression.rate.rd_lambda()).backward();
            OwnRateGraph {
                bits: bits.detach(),
                leaves,
                models,
                grads,
            }
        }))
    }

    /// Densification statistics (spec §8.1) and AAC importance (spec §12.2) of the step, after
    /// the optimizer as in gsplat's trainer.
    fn gather_statistics(&mut self, step: usize, pass: &TrainingPass, grads: &Gradients) {
        let cfg = &self.config;
        let dc = &cfg.densify;
        let (decoded, raster) = (&pass.rendered.decoded, &pass.rendered.raster);
        if decoded.visible.rows() == 0 {
            return;
        }
        // init_dynamic reads these statistics: with `canonical-statistics` they also
        // accumulate over the second half of the canonical phase.
        let canonical_until = cfg.train.canonical_until();
        let for_init_dynamic = cfg.train.init_dynamic == InitDynamic::CanonicalStatistics
            && pass.when.phase == Phase::Canonical
            && step >= canonical_until / 2;
        let in_densify_window = (step > dc.start && step < dc.stop) || for_init_dynamic;
        let dims = self.model.anchors.dims;
        // Both on the device (`statistics.rs`): nothing is read back here.
        // AAC's importance gathers the opacity before the slot gates (spec §12.2), so free
        // slots carry a signal for choosing where a relocation lands.
        if cfg.aac.accumulates_at(step) {
            self.anchor_state.gather_importance(
                &dims,
                decoded.visible_index.clone(),
                decoded.visible.weights(&decoded.visible_index.device()),
                decoded.slot_opacity.clone(),
            );
        }
        if in_densify_window {
            let camera = &pass.camera;
            self.anchor_state.gather_densify(
                &dims,
                DensifyView {
                    visible: decoded.visible_index.clone(),
                    seen: decoded.visible.weights(&decoded.visible_index.device()),
                    frame: pass.when.frame,
                    opacity: decoded.decoded.opacity.clone(),
                    gates: decoded.gaussians.gates.clone(),
                    radii: raster.radii.clone(),
                    grad2d: raster.means2d_grad(grads),
                    half_size: [camera.width as f32 / 2.0, camera.height as f32 / 2.0],
                },
            );
        }
    }

    /// After the last training step: the ACA-GS post-hoc step (gated slots, anchors without
    /// active slots and masked channels removed; nothing to do for GIFStream), then turns
    /// derived from the paths of the model as stored, which the decoder derives alike.
    pub fn finish_training(&mut self) -> Option<PostHocReport> {
        let step = self.step;
        let mut report = None;
        for refiner in refiners(&self.config) {
            report = report.or(refiner.after_training(&mut self.refine_context(step)));
        }
        self.rows_changed();
        derive_path_turns(&mut self.model.anchors);
        report
    }
}

/// The anchor tensors a step's pass decodes: `tensors` with the quantisation simulated in the
/// phase `step` is in, drawn with the step's own noise key (so the step's pass and the rate
/// term's own graph see the same values); `tensors` themselves when the codec is off.
fn simulated_at_step(
    compression: &crate::config::CompressionConfig,
    seed: u64,
    max_steps: usize,
    step: usize,
    tensors: &AnchorTensors,
) -> AnchorTensors {
    match compression.phase_at(step, max_steps) {
        Some(q) => {
            let noise = step_noise(seed, step, Stream::Quantization);
            simulate(tensors, &compression.quantization_steps(), q, noise)
        }
        None => tensors.clone(),
    }
}

/// What the rate term reads besides the models and the anchor tensors.
struct RateContext<'a> {
    compression: &'a crate::config::CompressionConfig,
    seed: u64,
    step: usize,
    /// The training frame (index inside the GOP).
    frame: usize,
    dims: &'a AnchorDims,
    /// [N, K] slot gates on the device (None: every slot active).
    slot_gates: Option<Tensor<2>>,
}

/// The rate term (spec §9.3, §13.3) of one step, unweighted: offset bits masked by the slot
/// gates, F_adapt bits by M. `sim` are the simulated anchor tensors the pass decodes, `raw` the
/// tracked ones they came from.
fn rate_bits(
    context: &RateContext,
    models: &EntropyModels,
    sim: &AnchorTensors,
    raw: &AnchorTensors,
) -> Tensor<1> {
    let cfg = context.compression;
    let (base_channels, adapt_kept) = match context.dims.feature_masking {
        FeatureMasking::Off => (context.dims.feature_dim, None),
        FeatureMasking::Adaptive { base, threshold } => (
            base,
            Some(binary_mask(raw.mask_logits(), threshold).detach()),
        ),
    };
    let steps = cfg.quantization_steps();
    let mut rng = step_rng(context.seed, context.step, Stream::Rate);
    let n = raw.rows();
    let sample = ((cfg.rate_sample * n as f64).ceil() as usize).clamp(1, n);
    // All anchors (GIFStream), or a fresh random subset (`compression.rate_sample`).
    let (sim, raw, kept, gates) = if sample < n {
        let mut rows: Vec<u32> = rand::seq::index::sample(&mut rng, n, sample)
            .into_iter()
            .map(|r| r as u32)
            .collect();
        rows.sort_unstable();
        sample_rows(
            sim,
            raw,
            adapt_kept.as_ref(),
            context.slot_gates.as_ref(),
            &rows,
        )
    } else {
        (
            sim.clone(),
            raw.clone(),
            adapt_kept,
            context.slot_gates.clone(),
        )
    };
    let inputs = RateInputs {
        steps: &steps,
        base_channels,
        adapt_kept: kept,
        slot_gates: gates,
        frame: context.frame,
        raw: &raw,
        bit_estimate: cfg.bit_estimate,
        trajectory: cfg.trajectory_rate,
    };
    let noise = step_noise(context.seed, context.step, Stream::Rate);
    rate(models, &sim, &inputs, noise).total()
}

/// Where each value read back with the loss sits among them: the MSE, the count of spawned
/// Gaussians, the rasterizer's intersection count and overflow flag, the count of visible
/// anchors (a device-culled step knows it only there), then the rate term's bits when they are
/// read with it.
const ALSO_MSE: usize = 0;
const ALSO_GAUSSIANS: usize = 1;
const ALSO_INTERSECTIONS: usize = 2;
const ALSO_OVERFLOWED: usize = 3;
const ALSO_VISIBLE: usize = 4;
const ALSO_RATE_BITS: usize = 5;

/// `want` rounded up to a sixteenth of an octave, so that the intersection buffers' sizes repeat
/// and the device allocator reuses them.
fn intersection_bucket(want: f64) -> usize {
    let want = want.ceil().max(4096.0) as usize;
    let bucket = (want.next_power_of_two() / 16).max(1);
    want.div_ceil(bucket) * bucket
}

/// Per step, the room kept for the next step's intersections shrinks by this factor at most: a
/// view that makes many more than the last one would cost a second render (two read-backs), so
/// the room follows the largest recent count rather than the last.
const INTERSECTION_ROOM_DECAY: f64 = 0.97;

/// The rate term's own graph, differentiated beside the step ([`Trainer::spawn_rate_graph`]).
struct OwnRateGraph {
    /// [1] the bits, unweighted, untracked (read with the step's values or after its backward).
    bits: Tensor<1>,
    /// The anchor leaves the rate was computed from, and the entropy models.
    leaves: AnchorTensors,
    models: EntropyModels,
    grads: Gradients,
}

impl OwnRateGraph {
    /// Puts the bits among the values read with the loss, at [`ALSO_RATE_BITS`].
    fn read_bits_with(&self, also: &mut Vec<Tensor<1>>) {
        assert_eq!(also.len(), ALSO_RATE_BITS);
        also.push(self.bits.clone());
    }
}

fn join_rate_graph(work: Background<OwnRateGraph>, step: usize) -> Result<OwnRateGraph> {
    work.join()
        .map_err(|_| anyhow::anyhow!("the rate term's own graph panicked at step {step}"))
}

/// Adds the rate graph's anchor gradients to the step's: each column of `tracked` (the pass's
/// leaves) gets its own gradient plus the rate's for the same column of `rate.leaves`.
fn merge_rate_gradients(tracked: &AnchorTensors, rate: &OwnRateGraph, grads: &mut Gradients) {
    for (c, column) in tracked.columns.iter() {
        let Some(from_rate) = rate.leaves.columns[c].grad(&rate.grads) else {
            continue;
        };
        let sum = match column.grad(grads) {
            Some(own) => own + from_rate,
            None => from_rate,
        };
        column.replace_grad(grads, sum);
    }
}

/// Σ over {α, colour, cov, motion} of mean |x(t) − x(t')| (spec §4.5); `reference` is untracked.
/// With `motion_gates` (the [M, 1] motion gates of the current decode, tracked, and of the
/// reference) the applied motions mf·Δ are compared, as GIFStream's `decoding_features` returns
/// them (T L764-L768, L842-L857). With `slot_gates` ([M, K], 1 on an active slot) α, colour
/// and covariance are averaged over the active slots only (`loss.smooth_slots = "active"`).
fn smoothness(
    visible: &VisibleRows,
    current: &DecodedAnchors,
    reference: &DecodedAnchors,
    motion_gates: Option<(Tensor<2>, Tensor<2>)>,
    slot_gates: Option<Tensor<2>>,
) -> Tensor<1> {
    // Over the visible anchors' rows.
    let term = |a: &Tensor<2>, b: &Tensor<2>| visible.mean((a.clone() - b.clone()).abs());
    // Per-slot attributes ([M, K·width]), over the active slots when they are given.
    let slot_term = |a: &Tensor<2>, b: &Tensor<2>| match &slot_gates {
        None => term(a, b),
        Some(gates) => {
            let width = a.dims()[1] / gates.dims()[1];
            visible.mean_over_slots((a.clone() - b.clone()).abs(), gates.clone(), width)
        }
    };
    let motion = match motion_gates {
        None => term(&current.motion, &reference.motion),
        Some((g, g_ref)) => term(
            &(current.motion.clone() * g),
            &(reference.motion.clone() * g_ref),
        ),
    };
    slot_term(&current.opacity, &reference.opacity)
        + slot_term(&current.color, &reference.color)
        + slot_term(&current.cov, &reference.cov)
        + motion
}

/// Under `train.knot_extrapolation = "moving-velocity"`, the gated turn of an anchor's last knot
/// segment above which its new turn knot continues it (2°: well above what Adam's noise turns a
/// still anchor by, well below the 18° per knot interval of `synthetic:crossing`'s cube).
const TURNING_MIN_RADIANS: f32 = 0.035;

pub fn anchor_dims(config: &TrainConfig, scene: &Scene) -> AnchorDims {
    AnchorDims {
        slots: config.model.slots,
        initial_active_slots: match config.aac.mode {
            CardinalityMode::Fixed => config.model.slots,
            CardinalityMode::Adaptive => config.aac.initial_active,
        },
        feature_masking: match config.aafm.mode {
            FeatureMaskMode::Off => FeatureMasking::Off,
            FeatureMaskMode::Adaptive => FeatureMasking::Adaptive {
                base: config.aafm.base_channels,
                threshold: config.aafm.threshold,
            },
        },
        frames: scene.frames.count,
        feature_dim: config.model.feature_dim,
        time_feature_dim: config.model.time_feature_dim,
        knn: config.model.knn,
        trajectory_spacing: config.model.trajectory_spacing,
        trajectory_turn: config.model.trajectory_turn,
    }
}

/// A new run's decoders: drawn from `train.seed`, paired with the baseline's where
/// `model.decoder_init` pairs them ([`Decoders::initial`]).
pub fn initial_decoders(config: &TrainConfig, device: &Device) -> Decoders {
    Decoders::initial(
        decoder_sizes(config),
        config.model.baseline_decoder_sizes(),
        config.model.decoder_init,
        config.train.seed,
        device,
    )
}

pub fn decoder_sizes(config: &TrainConfig) -> DecoderSizes {
    DecoderSizes {
        feature_dim: config.model.feature_dim,
        time_feature_dim: config.model.time_feature_dim,
        slots: config.model.slots,
    }
}
