//! The GIFStream training loop for one GOP (spec §4-§8): per step one training view, decode,
//! rasterize, 0.8·L1 + 0.2·D-SSIM plus the scale, gate and smoothness regularisers, Adam with the
//! per-group schedules, then the densification statistics and the refine steps.
//!
//! Reproducibility: every random choice of a step comes from a generator seeded by
//! (seed, step, purpose), and the view order from a sampler restorable from (seed, epoch,
//! position), so a run resumed from a checkpoint continues exactly as an uninterrupted one.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor, TensorData, s};
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::adaptive_cardinality::{RelocationChurn, RelocationReport, accumulate_importance};
use super::anchor_state::{AnchorState, AnchorStats};
use super::checkpoint::{NamedTensors, read_checkpoint, write_checkpoint};
use super::coherence::{motion_peers, trajectory_coherence};
use super::config::{
    CardinalityMode, CrGradient, FeatureMaskMode, InitDynamic, KnotExtrapolation, SmoothMotion,
    TrainConfig, knots_reached,
};
use super::decoder_adam::{DECODER_ADAM, DecoderAdam, LinearAdam, MlpAdam, tracked};
use super::densify::update_stats;
use super::knots::start_new_knots;
use super::losses::photometric_loss;
use super::objective::{Objective, Term};
use super::optimizers::{Optimizers, StepRates, TrackedParameters};
use super::posthoc::PostHocReport;
use super::refine::{RefineContext, Refinement, refiners};
use super::row_adam::{AdamConfig, RowAdam};
use super::streams::{Stream, step_rng};
use crate::codec::entropy_models::{EntropyModels, RateInputs, rate, sample_rows};
use crate::codec::quantization::simulate;
use crate::data::frames::FrameCache;
use crate::data::sampler::{SamplerState, ViewSampler};
use crate::data::{Scene, ViewId};
use crate::host_math::sigmoid;
use crate::model::anchored::{AnchoredModel, ForwardValues, RenderedView};
use crate::model::anchors::{
    AnchorDims, AnchorSet, AnchorTensors, Column, Columns, FACTOR_COUNT, FeatureMasking,
    host_values,
};
use crate::model::decoders::{DecodedAnchors, DecoderSizes, Decoders, Mlp};
use crate::model::feature_mask::{
    binary_mask, conditional_regularization, mask_loss, time_gate_share_below,
};
use crate::model::inputs::time_window_gap;
use crate::model::view::{Phase, ViewTime, decode_view};
use crate::raster::RasterCamera;
use burn::tensor::Gradients;

/// Per-anchor Adam (GIFStream: eps 1e-15 at batch size 1).
pub const ANCHOR_ADAM: AdamConfig = AdamConfig {
    beta1: 0.9,
    beta2: 0.999,
    eps: 1e-15,
};

/// Consecutive non-finite losses after which training stops with an error.
pub const MAX_CONSECUTIVE_NAN_STEPS: usize = 5;

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
}

/// Trainer state that is not a tensor, stored in the checkpoint's metadata.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct TrainerMeta {
    format: String,
    version: u32,
    /// Steps completed.
    step: usize,
    sampler: SamplerState,
    train_seconds: f64,
    nan_steps: usize,
    #[serde(default)]
    schedule_origin: usize,
    #[serde(default)]
    relocation_churn: RelocationChurn,
    #[serde(default)]
    cr_started_at: Option<usize>,
    adam_steps: std::collections::BTreeMap<String, u64>,
    config: String,
}

const CHECKPOINT_FORMAT: &str = "acags-train-checkpoint";
/// v2: ACA-GS buffers (slot gates, importance, birth steps) and the AAFM mask logits.
/// v3: the conditional entropy models and their Adam state (a v2 checkpoint loads with fresh
/// entropy models).
const CHECKPOINT_VERSION: u32 = 3;

/// The forward pass of one training step.
struct TrainingPass {
    when: ViewTime,
    camera: RasterCamera,
    /// [H, W, 3] the view's image.
    target: Tensor<3>,
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
        let anchors = AnchorSet::from_points(
            &scene.points.positions,
            config.model.voxel_size,
            dims,
            &device,
        );
        if anchors.is_empty() {
            bail!("{}: no finite initial points", scene.root.display());
        }
        let decoders = Decoders::seeded(decoder_sizes(&config), config.train.seed, &device);
        let entropy = EntropyModels::seeded(decoder_sizes(&config), config.train.seed, &device);
        let optimizers = Optimizers::new(&decoders, &entropy);
        let sampler = ViewSampler::new(scene.train_views(), config.train.seed);
        let frames = FrameCache::new(config.data.frame_cache_mib << 20);
        let culling = config.model.culling;
        let anchor_state = AnchorState::new(&anchors, 0, ANCHOR_ADAM);
        Ok(Self {
            config,
            scene,
            frames,
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

    pub fn finished(&self) -> bool {
        self.step >= self.config.train.max_steps
    }

    pub fn phase(&self, step: usize) -> Phase {
        if step <= self.config.train.canonical_until() {
            Phase::Canonical
        } else {
            Phase::Dynamic
        }
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
    fn extend_trajectories(&mut self, step: usize) {
        let cfg = &self.config.train;
        let set = &mut self.model.anchors;
        let d = set.dims;
        if set.columns.get(Column::Trajectory).is_none() {
            return;
        }
        if cfg.frame_curriculum <= 0.0 || set.positions.is_empty() {
            return;
        }
        let reached = |open: usize| knots_reached(open, d.trajectory_spacing);
        let before = if step == 0 {
            0
        } else {
            cfg.open_frames(step - 1, d.frames)
        };
        let (from, to) = (
            reached(before).max(1),
            reached(cfg.open_frames(step, d.frames)).min(d.trajectory_knots()),
        );
        if to <= from {
            return;
        }
        let mut values = set.host(Column::Trajectory);
        // The motion gates, only where the rule needs them (the gate scales the knots).
        let gates: Vec<f32> = match cfg.knot_extrapolation {
            KnotExtrapolation::MovingVelocity => set
                .host(Column::Factors)
                .chunks_exact(FACTOR_COUNT)
                .map(|f| sigmoid(f[1]))
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
        Ok(Tensor::<3>::from_data(
            TensorData::new(
                frame.rgb.clone(),
                [frame.height as usize, frame.width as usize, 3],
            ),
            device,
        ))
    }

    /// One training step: refiners due before the forward pass, the forward pass, the objective
    /// (one read-back), the backward pass and the optimizers, the statistics, then the refiners
    /// due after the update.
    pub fn step(&mut self) -> Result<StepReport> {
        let started = Instant::now();
        let step = self.step;
        let refiners = refiners(&self.config);
        for refiner in &refiners {
            refiner.before_forward(&mut self.refine_context(step));
        }
        self.extend_trajectories(step);
        let cr_on = self.conditional_regularization_on(step);
        let pass = self.forward_pass(step)?;
        let StepObjective {
            loss,
            objective,
            also,
            entropy,
        } = self.objective(step, &pass, cr_on);
        // One read-back: the loss, every term, the MSE and the rate term's bits.
        let values = objective.read(&loss, &also);
        let mut loss_value = values.total;
        if self.config.train.inject_nonfinite.contains(&step) {
            loss_value = f32::NAN;
        }
        let mut report = StepReport {
            step,
            loss: loss_value,
            psnr: -10.0 * values.also[0].max(1e-12).log10(),
            visible_anchors: pass.rendered.decoded.visible.len(),
            rate_bits: values.also.get(1).copied(),
            terms: values.terms,
            ..Default::default()
        };
        if loss_value.is_finite() {
            self.consecutive_nan = 0;
            let grads = loss.backward();
            let rates = StepRates::at(
                &self.config,
                &self.model.anchors.dims,
                step,
                self.schedule_origin,
            );
            let tracked = TrackedParameters {
                anchors: &pass.tensors,
                decoders: &pass.decoders,
                entropy: entropy.as_ref(),
            };
            let (model, state) = (&mut self.model, &mut self.anchor_state);
            self.optimizers
                .step(model, state, &mut self.entropy, tracked, &grads, &rates);
            report.gaussians = self.gather_statistics(step, &pass, &grads);
            for refiner in &refiners {
                let done = refiner.after_step(&mut self.refine_context(step));
                self.record_refinement(done, &mut report);
            }
        } else {
            self.skip_nonfinite(step)?;
            report.skipped = true;
        }
        self.step += 1;
        report.anchors = self.model.anchors.len();
        report.active_slots = self.model.anchors.active_slot_count();
        report.seconds = started.elapsed().as_secs_f64();
        self.train_seconds += report.seconds;
        Ok(report)
    }

    fn refine_context(&mut self, step: usize) -> RefineContext<'_> {
        RefineContext {
            anchors: &mut self.model.anchors,
            state: &mut self.anchor_state,
            step,
            seed: self.config.train.seed,
        }
    }

    /// Adds what a refiner did to the step's report.
    fn record_refinement(&mut self, done: Option<Refinement>, report: &mut StepReport) {
        match done {
            None => {}
            Some(Refinement::Rows(d)) => {
                report.added = d.added;
                report.pruned = d.pruned;
                if d.added + d.pruned > 0 {
                    self.motion_peers = None;
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

    /// The forward pass of `step` on tracked copies of the anchors (quantisation simulated,
    /// spec §9.2; Adam updates the leaves) and decoders.
    fn forward_pass(&mut self, step: usize) -> Result<TrainingPass> {
        let view = self.next_view(step);
        let when = self.view_time(step, view);
        let camera = self.scene.cameras[view.camera].camera.clone();
        let target = self.target(view, &self.device.clone().autodiff())?;
        let tensors = self.model.anchors.tracked();
        let cfg = &self.config;
        let forward_tensors = match cfg.compression.phase_at(step, cfg.train.max_steps) {
            Some(q) => {
                let mut rng = step_rng(cfg.train.seed, step, Stream::Quantization);
                simulate(&tensors, &cfg.compression.rate.steps(), q, &mut rng)
            }
            None => tensors.clone(),
        };
        let decoders = tracked(&self.model.decoders);
        let values = ForwardValues::Tracked {
            anchors: &forward_tensors,
            decoders: &decoders,
        };
        let rendered = self.model.forward(&camera, when, values)?;
        Ok(TrainingPass {
            when,
            camera,
            target,
            tensors,
            forward_tensors,
            decoders,
            rendered,
        })
    }

    /// The step's objective (spec §6, §9.3, §13): the photometric term and every regulariser
    /// that is on; with the tracked entropy models when the rate term is.
    fn objective(&mut self, step: usize, pass: &TrainingPass, cr_on: bool) -> StepObjective {
        let cfg = &self.config;
        let raster = &pass.rendered.raster;
        let photometric = photometric_loss(
            raster.image.clone(),
            pass.target.clone(),
            cfg.loss.ssim_lambda,
        );
        let mut objective = Objective::new(photometric.loss);
        self.regularizers(step, pass, cr_on, &mut objective);
        let mut also = vec![photometric.mse];
        let entropy = self
            .rate_term(step, pass, &mut objective)
            .map(|(models, bits)| {
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
        let visible_count = decoded.visible.len();
        // Scale regulariser: mean over spawned Gaussians of the product of their scales.
        let g = &decoded.gaussians;
        let n = g.len();
        if cfg.loss.scale_reg > 0.0 && n > 0 {
            let volume = g
                .scales
                .clone()
                .slice(s![.., 0..1])
                .mul(g.scales.clone().slice(s![.., 1..2]))
                .mul(g.scales.clone().slice(s![.., 2..3]))
                .reshape([n]);
            let spawned = g.gates.clone().sum().clamp_min(1.0);
            objective.add(
                Term::Volume,
                (volume * g.gates.clone()).sum() / spawned * cfg.loss.scale_reg,
            );
        }
        // Gate regulariser, after (gate + 0.1)·max_steps (spec §6).
        if cfg.loss.factor_reg > 0.0 && step > cfg.train.factor_reg_after() && visible_count > 0 {
            let gates = decoded.gates.clone();
            let reg =
                gates.clone().slice(s![.., 0..3]).mean() + gates.slice(s![.., 3..4]).mean() * 0.1;
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
            let peers = self.motion_peers.get_or_insert_with(|| {
                motion_peers(&self.model.anchors.positions, cfg.loss.coherence_cell)
            });
            objective.add(
                Term::Coherence,
                trajectory_coherence(trajectory, tensors.factors(), peers)
                    * cfg.loss.trajectory_coherence,
            );
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
            && !decoded.visible.is_empty()
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
        let reference = decode_view(
            &self.model.anchors,
            &self.model.anchors.untracked(),
            &self.model.decoders,
            decoded.visible.clone(),
            other_when,
        );
        let motion_gates = match cfg.loss.smooth_motion {
            SmoothMotion::Raw => None,
            SmoothMotion::Gated => Some((
                decoded.gates.clone().slice(s![.., 1..2]),
                reference.gates.clone().slice(s![.., 1..2]),
            )),
        };
        Some(smoothness(&decoded.decoded, &reference.decoded, motion_gates) * cfg.loss.smooth_reg)
    }

    /// The rate term (spec §9.3, §13.3): offset bits masked by the slot gates, F_adapt bits by
    /// M. Returns the tracked entropy models (their gradients are in the loss) and the bits,
    /// when it is on.
    fn rate_term(
        &mut self,
        step: usize,
        pass: &TrainingPass,
        objective: &mut Objective,
    ) -> Option<(EntropyModels, Tensor<1>)> {
        let cfg = &self.config;
        let on =
            cfg.compression.rate_at(step, cfg.train.max_steps) && !self.model.anchors.is_empty();
        if !on {
            return None;
        }
        if step == 0 || !cfg.compression.rate_at(step - 1, cfg.train.max_steps) {
            self.entropy
                .start_from(&self.model.anchors, &cfg.compression.rate.steps());
        }
        let cfg = &self.config;
        let models = self.entropy.tracked();
        let anchors = &self.model.anchors;
        let tensors = &pass.tensors;
        let (base_channels, adapt_kept) = match anchors.dims.feature_masking {
            FeatureMasking::Off => (anchors.dims.feature_dim, None),
            FeatureMasking::Adaptive { base, threshold } => (
                base,
                Some(binary_mask(tensors.mask_logits(), threshold).detach()),
            ),
        };
        let steps = cfg.compression.rate.steps();
        let mut rng = step_rng(cfg.train.seed, step, Stream::Rate);
        let n = anchors.len();
        let sample = ((cfg.compression.rate_sample * n as f64).ceil() as usize).clamp(1, n);
        // All anchors (GIFStream), or a fresh random subset (`compression.rate_sample`).
        let (sim, raw, kept, gates) = if sample < n {
            let mut rows: Vec<u32> = rand::seq::index::sample(&mut rng, n, sample)
                .into_iter()
                .map(|r| r as u32)
                .collect();
            rows.sort_unstable();
            sample_rows(
                &pass.forward_tensors,
                tensors,
                adapt_kept.as_ref(),
                &anchors.slot_gates,
                &rows,
            )
        } else {
            (
                pass.forward_tensors.clone(),
                tensors.clone(),
                adapt_kept,
                anchors.slot_gates.clone(),
            )
        };
        let inputs = RateInputs {
            steps: &steps,
            base_channels,
            adapt_kept: kept,
            slot_gates: &gates,
            frame: pass.when.frame,
            raw: &raw,
            bit_estimate: cfg.compression.bit_estimate,
        };
        let total = rate(&models, &sim, &inputs, &mut rng).total();
        objective.add(Term::Rate, total.clone() * cfg.compression.rate.rd_lambda());
        Some((models, total))
    }

    /// Densification statistics (spec §8.1) and AAC importance (spec §12.2) of the step, after
    /// the optimizer as in gsplat's trainer; returns the number of spawned Gaussians.
    fn gather_statistics(&mut self, step: usize, pass: &TrainingPass, grads: &Gradients) -> usize {
        let cfg = &self.config;
        let dc = &cfg.densify;
        let (decoded, raster, frame) = (
            &pass.rendered.decoded,
            &pass.rendered.raster,
            pass.when.frame,
        );
        let visible_count = decoded.visible.len();
        // init_dynamic reads these statistics: with `canonical-statistics` they also
        // accumulate over the second half of the canonical phase.
        let canonical_until = cfg.train.canonical_until();
        let for_init_dynamic = cfg.train.init_dynamic == InitDynamic::CanonicalStatistics
            && pass.when.phase == Phase::Canonical
            && step >= canonical_until / 2;
        let in_densify_window = (step > dc.start && step < dc.stop) || for_init_dynamic;
        let aac_window = cfg.aac.accumulates_at(step);
        // AAC's importance gathers the opacity before the slot gates (spec §12.2), so free
        // slots carry a signal for choosing where a relocation lands; the gated opacity the
        // densification statistics need follows from it on the host (one read-back).
        let slot_opacity = if visible_count > 0 && aac_window {
            host_values(&decoded.slot_opacity)
        } else {
            Vec::new()
        };
        let anchors = &self.model.anchors;
        let opacity = if visible_count == 0 || !in_densify_window {
            Vec::new()
        } else if aac_window {
            let (k, gates) = (anchors.dims.slots, &anchors.slot_gates);
            let visible = &decoded.visible;
            (slot_opacity.iter().enumerate())
                .map(|(i, &o)| {
                    let a = visible[i / k] as usize;
                    if gates[a * k + i % k] { o } else { 0.0 }
                })
                .collect()
        } else {
            host_values(&decoded.decoded.opacity)
        };
        let dims = anchors.dims;
        if aac_window && visible_count > 0 {
            accumulate_importance(
                &mut self.anchor_state,
                &dims,
                &decoded.visible,
                &slot_opacity,
            );
        }
        let n = decoded.gaussians.len();
        if in_densify_window && visible_count > 0 {
            let gates = host_values(&decoded.gaussians.gates);
            let radii: Vec<i64> = raster
                .radii
                .clone()
                .into_data()
                .convert::<i64>()
                .try_into_vec::<i64>()
                .expect("int radii");
            let grad2d = raster
                .means2d_grad(grads)
                .map(|g| host_values(&g))
                .unwrap_or_else(|| vec![0.0; n * 2]);
            let camera = &pass.camera;
            let (w, h) = (camera.width as f32 / 2.0, camera.height as f32 / 2.0);
            let norms: Vec<f32> = (0..n)
                .map(|i| ((grad2d[2 * i] * w).powi(2) + (grad2d[2 * i + 1] * h).powi(2)).sqrt())
                .collect();
            let counted: Vec<bool> = (0..n)
                .map(|i| gates[i] > 0.0 && (radii[2 * i] > 0 || radii[2 * i + 1] > 0))
                .collect();
            update_stats(
                &mut self.anchor_state,
                &dims,
                &decoded.visible,
                &opacity,
                &norms,
                &counted,
                frame,
            );
        }
        host_values(&decoded.gaussians.gates.clone().sum().reshape([1]))[0] as usize
    }

    /// The ACA-GS post-hoc step after the last training step (gated slots, anchors without
    /// active slots and masked channels removed); nothing to do for GIFStream.
    pub fn prune_capacity(&mut self) -> Option<PostHocReport> {
        self.motion_peers = None;
        let step = self.step;
        let mut report = None;
        for refiner in refiners(&self.config) {
            report = report.or(refiner.after_training(&mut self.refine_context(step)));
        }
        report
    }

    /// Writes a checkpoint of everything needed to continue exactly.
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut tensors = NamedTensors::default();
        let mut adam_steps = std::collections::BTreeMap::new();
        let a = &self.model.anchors;
        let d = a.dims;
        let n = a.len();
        tensors.insert(
            "anchors.positions",
            vec![n, 3],
            a.positions.iter().flatten().copied().collect(),
        );
        let state = &self.anchor_state;
        for (c, value) in a.columns.iter() {
            let key = column_key(c);
            let shape = column_shape(c, &d, n);
            tensors.insert(key.clone(), shape.clone(), host_values(value));
            put_adam_shaped(&mut tensors, &mut adam_steps, &key, &state.adam[c], shape);
        }
        let flag = |b: &bool| if *b { 1.0 } else { 0.0 };
        tensors.insert(
            "aac.slot_gates",
            vec![n, d.slots],
            a.slot_gates.iter().map(flag).collect(),
        );
        tensors.insert("aac.importance", vec![n, d.slots], state.importance.clone());
        tensors.insert(
            "aac.relocated",
            vec![n, d.slots],
            state.relocated.iter().map(flag).collect(),
        );
        tensors.insert(
            "aac.importance_visits",
            vec![n],
            state.importance_visits.clone(),
        );
        // Birth steps as float32: exact below 2^24 steps.
        tensors.insert(
            "aac.created_at",
            vec![n],
            state.created_at.iter().map(|&s| s as f32).collect(),
        );
        let st = &state.stats;
        tensors.insert(
            "stats.offset_grad2d",
            vec![n * d.slots, d.frames],
            st.offset_grad2d.clone(),
        );
        tensors.insert(
            "stats.offset_visible_count",
            vec![n * d.slots, d.frames],
            st.offset_visible_count.clone(),
        );
        tensors.insert(
            "stats.opacity_accum",
            vec![n, d.frames],
            st.opacity_accum.clone(),
        );
        tensors.insert(
            "stats.anchor_visible_count",
            vec![n, d.frames],
            st.anchor_visible_count.clone(),
        );
        let dec = &self.model.decoders;
        let adam = &self.optimizers.decoders;
        for (name, mlp, state) in [
            ("opacity", &dec.opacity, &adam.opacity),
            ("cov", &dec.cov, &adam.cov),
            ("color", &dec.color, &adam.color),
            ("motion", &dec.motion, &adam.motion),
        ] {
            put_mlp(
                &mut tensors,
                &mut adam_steps,
                &format!("decoders.{name}"),
                mlp,
                state,
            );
        }
        for ((name, mlp), state) in self
            .entropy
            .named()
            .into_iter()
            .zip(&self.optimizers.entropy)
        {
            put_mlp(
                &mut tensors,
                &mut adam_steps,
                &format!("entropy.{name}"),
                mlp,
                state,
            );
        }
        let meta = TrainerMeta {
            format: CHECKPOINT_FORMAT.into(),
            version: CHECKPOINT_VERSION,
            step: self.step,
            sampler: self.sampler.state(),
            train_seconds: self.train_seconds,
            nan_steps: self.nan_steps,
            relocation_churn: self.relocation_churn,
            cr_started_at: self.cr_started_at,
            schedule_origin: self.schedule_origin,
            adam_steps,
            config: self.config.to_toml(),
        };
        write_checkpoint(path, &tensors, &serde_json::to_value(&meta)?)
    }

    /// Restores a checkpoint written by [`Trainer::save_checkpoint`] for the same scene and
    /// model sizes.
    pub fn load_checkpoint(&mut self, path: &Path) -> Result<()> {
        let (mut tensors, meta) = read_checkpoint(path)?;
        let meta: TrainerMeta = serde_json::from_value(meta)
            .with_context(|| format!("{}: unreadable trainer state", path.display()))?;
        if meta.format != CHECKPOINT_FORMAT || !(2..=CHECKPOINT_VERSION).contains(&meta.version) {
            bail!(
                "{}: checkpoint format {} v{} is not {CHECKPOINT_FORMAT} v2..v{CHECKPOINT_VERSION}",
                path.display(),
                meta.format,
                meta.version
            );
        }
        let d = self.model.anchors.dims;
        let (shape, positions) = tensors.take("anchors.positions", &[None, Some(3)], path)?;
        let n = shape[0];
        let device = self.device.clone();
        let steps = &meta.adam_steps;
        let mut columns = Columns::default();
        let mut adam = Columns::default();
        for c in Column::present(&d) {
            let (key, shape) = (column_key(c), column_shape(c, &d, n));
            columns.insert(c, take_rows(&mut tensors, &key, &shape, path, &device)?);
            adam.insert(
                c,
                take_row_adam(&mut tensors, steps, &key, &shape, path, &device)?,
            );
        }
        let mut set = AnchorSet {
            dims: d,
            positions: positions
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            position_tensor: Tensor::<2>::from_data(TensorData::new(positions, [n, 3]), &device),
            columns,
            slot_gates: Vec::new(),
            neighbors: Vec::new(),
        };
        let gates = tensors
            .take("aac.slot_gates", &[Some(n), Some(d.slots)], path)?
            .1;
        if let Some(bad) = gates.iter().find(|&&g| g != 0.0 && g != 1.0) {
            bail!("{}: slot gate {bad} is neither 0 nor 1", path.display());
        }
        set.slot_gates = gates.iter().map(|&g| g == 1.0).collect();
        let importance = tensors
            .take("aac.importance", &[Some(n), Some(d.slots)], path)?
            .1;
        let importance_visits = tensors.take("aac.importance_visits", &[Some(n)], path)?.1;
        // Added within v3 for the churn report only: older checkpoints have no relocations pending.
        let relocated = if tensors.entries.contains_key("aac.relocated") {
            let flags = tensors
                .take("aac.relocated", &[Some(n), Some(d.slots)], path)?
                .1;
            if let Some(bad) = flags.iter().find(|&&g| g != 0.0 && g != 1.0) {
                bail!(
                    "{}: relocation flag {bad} is neither 0 nor 1",
                    path.display()
                );
            }
            flags.iter().map(|&g| g == 1.0).collect()
        } else {
            vec![false; n * d.slots]
        };
        let born = tensors.take("aac.created_at", &[Some(n)], path)?.1;
        if let Some(bad) = born
            .iter()
            .find(|&&s| !(s >= 0.0 && s.fract() == 0.0 && s < 16_777_216.0))
        {
            bail!("{}: birth step {bad} is not a step number", path.display());
        }
        let created_at = born.iter().map(|&s| s as u32).collect();
        // The visibility counts were `*_demon` before 2026-11-26 (GIFStream's name).
        let mut stat = |name: &str, former: Option<&str>, rows: usize| -> Result<Vec<f32>> {
            let expected = [Some(rows), Some(d.frames)];
            Ok(match former {
                Some(former) => tensors.take_renamed(name, former, &expected, path)?.1,
                None => tensors.take(name, &expected, path)?.1,
            })
        };
        let stats = AnchorStats {
            offset_grad2d: stat("stats.offset_grad2d", None, n * d.slots)?,
            offset_visible_count: stat(
                "stats.offset_visible_count",
                Some("stats.offset_demon"),
                n * d.slots,
            )?,
            opacity_accum: stat("stats.opacity_accum", None, n)?,
            anchor_visible_count: stat(
                "stats.anchor_visible_count",
                Some("stats.anchor_demon"),
                n,
            )?,
        };
        set.rebuild_neighbors();
        let anchor_state = AnchorState {
            adam,
            stats,
            importance,
            importance_visits,
            relocated,
            created_at,
        };

        let mut decoders = self.model.decoders.clone();
        let mut decoder_adam = self.optimizers.decoders.clone();
        for (name, mlp, state) in [
            ("opacity", &mut decoders.opacity, &mut decoder_adam.opacity),
            ("cov", &mut decoders.cov, &mut decoder_adam.cov),
            ("color", &mut decoders.color, &mut decoder_adam.color),
            ("motion", &mut decoders.motion, &mut decoder_adam.motion),
        ] {
            take_mlp(
                &mut tensors,
                steps,
                &format!("decoders.{name}"),
                mlp,
                state,
                path,
                &device,
            )?;
        }
        let mut entropy = self.entropy.clone();
        let mut entropy_adam = self.optimizers.entropy.clone();
        if meta.version >= 3 {
            for ((name, mlp), state) in entropy.named_mut().into_iter().zip(&mut entropy_adam) {
                take_mlp(
                    &mut tensors,
                    steps,
                    &format!("entropy.{name}"),
                    mlp,
                    state,
                    path,
                    &device,
                )?;
            }
        }
        if let Some(extra) = tensors.entries.keys().next() {
            bail!(
                "{}: unexpected tensor `{extra}` (written by another version?)",
                path.display()
            );
        }
        self.model = AnchoredModel {
            anchors: set,
            decoders,
            culling: self.config.model.culling,
        };
        self.anchor_state = anchor_state;
        self.optimizers.decoders = decoder_adam;
        self.entropy = entropy;
        self.optimizers.entropy = entropy_adam;
        self.sampler.restore(meta.sampler);
        self.step = meta.step;
        self.train_seconds = meta.train_seconds;
        self.nan_steps = meta.nan_steps;
        self.relocation_churn = meta.relocation_churn;
        self.cr_started_at = meta.cr_started_at;
        self.schedule_origin = meta.schedule_origin;
        self.consecutive_nan = 0;
        self.motion_peers = None;
        Ok(())
    }
}

/// Σ over {α, colour, cov, motion} of mean |x(t) − x(t')| (spec §4.5); `reference` is untracked.
/// With `motion_gates` (the [M, 1] motion gates of the current decode, tracked, and of the
/// reference) the applied motions mf·Δ are compared, as GIFStream's `decoding_features` returns
/// them (T L764-L768, L842-L857).
fn smoothness(
    current: &DecodedAnchors,
    reference: &DecodedAnchors,
    motion_gates: Option<(Tensor<2>, Tensor<2>)>,
) -> Tensor<1> {
    let term = |a: &Tensor<2>, b: &Tensor<2>| (a.clone() - b.clone()).abs().mean();
    let motion = match motion_gates {
        None => term(&current.motion, &reference.motion),
        Some((g, g_ref)) => term(
            &(current.motion.clone() * g),
            &(reference.motion.clone() * g_ref),
        ),
    };
    term(&current.opacity, &reference.opacity)
        + term(&current.color, &reference.color)
        + term(&current.cov, &reference.cov)
        + motion
}

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
    }
}

pub fn decoder_sizes(config: &TrainConfig) -> DecoderSizes {
    DecoderSizes {
        feature_dim: config.model.feature_dim,
        time_feature_dim: config.model.time_feature_dim,
        slots: config.model.slots,
    }
}

fn put_adam<const D: usize>(
    tensors: &mut NamedTensors,
    steps: &mut std::collections::BTreeMap<String, u64>,
    key: &str,
    adam: &RowAdam<D>,
) {
    let shape = adam.exp_avg.dims().to_vec();
    tensors.insert(
        format!("adam.{key}.exp_avg"),
        shape.clone(),
        host_values(&adam.exp_avg),
    );
    tensors.insert(
        format!("adam.{key}.exp_avg_sq"),
        shape,
        host_values(&adam.exp_avg_sq),
    );
    steps.insert(key.to_string(), adam.step);
}

/// A column's checkpoint key, `anchors.<name>`.
fn column_key(c: Column) -> String {
    format!("anchors.{}", c.name())
}

/// A column's checkpoint shape: [N, row shape…] (offsets [N, K, 3]), the layout checkpoints had
/// before the columns were stored flat.
fn column_shape(c: Column, d: &AnchorDims, n: usize) -> Vec<usize> {
    let mut shape = vec![n];
    shape.extend(c.row_shape(d).expect("a present column"));
    shape
}

/// [`put_adam`] of a flat [N, width] state under the column's checkpoint shape.
fn put_adam_shaped(
    tensors: &mut NamedTensors,
    steps: &mut std::collections::BTreeMap<String, u64>,
    key: &str,
    adam: &RowAdam<2>,
    shape: Vec<usize>,
) {
    tensors.insert(
        format!("adam.{key}.exp_avg"),
        shape.clone(),
        host_values(&adam.exp_avg),
    );
    tensors.insert(
        format!("adam.{key}.exp_avg_sq"),
        shape,
        host_values(&adam.exp_avg_sq),
    );
    steps.insert(key.to_string(), adam.step);
}

fn put_linear(
    tensors: &mut NamedTensors,
    steps: &mut std::collections::BTreeMap<String, u64>,
    key: &str,
    linear: &burn::nn::Linear,
    adam: &LinearAdam,
) {
    let w = linear.weight.val();
    let b = linear.bias.as_ref().expect("bias").val();
    tensors.insert(format!("{key}.weight"), w.dims().to_vec(), host_values(&w));
    tensors.insert(format!("{key}.bias"), b.dims().to_vec(), host_values(&b));
    put_adam(tensors, steps, &format!("{key}.weight"), &adam.weight);
    put_adam(tensors, steps, &format!("{key}.bias"), &adam.bias);
}

/// Both layers of an MLP and their Adam state under `key.hidden` / `key.output` (read back by
/// [`take_mlp`]).
fn put_mlp(
    tensors: &mut NamedTensors,
    steps: &mut std::collections::BTreeMap<String, u64>,
    key: &str,
    mlp: &Mlp,
    adam: &MlpAdam,
) {
    for (layer, linear, la) in [
        ("hidden", &mlp.hidden, &adam.hidden),
        ("output", &mlp.output, &adam.output),
    ] {
        put_linear(tensors, steps, &format!("{key}.{layer}"), linear, la);
    }
}

fn take_tensor<const D: usize>(
    tensors: &mut NamedTensors,
    key: &str,
    shape: [usize; D],
    path: &Path,
    device: &Device,
) -> Result<Tensor<D>> {
    let expected: Vec<Option<usize>> = shape.iter().map(|&s| Some(s)).collect();
    let (_, values) = tensors.take(key, &expected, path)?;
    Ok(Tensor::<D>::from_data(
        TensorData::new(values, shape),
        device,
    ))
}

fn take_adam<const D: usize>(
    tensors: &mut NamedTensors,
    steps: &std::collections::BTreeMap<String, u64>,
    key: &str,
    shape: [usize; D],
    config: AdamConfig,
    path: &Path,
    device: &Device,
) -> Result<RowAdam<D>> {
    Ok(RowAdam {
        config,
        exp_avg: take_tensor(tensors, &format!("adam.{key}.exp_avg"), shape, path, device)?,
        exp_avg_sq: take_tensor(
            tensors,
            &format!("adam.{key}.exp_avg_sq"),
            shape,
            path,
            device,
        )?,
        step: *steps
            .get(key)
            .with_context(|| format!("{}: no Adam step count for `{key}`", path.display()))?,
    })
}

/// A tensor of checkpoint shape [N, …] as the flat [N, width] a column is stored as.
fn take_rows(
    tensors: &mut NamedTensors,
    key: &str,
    shape: &[usize],
    path: &Path,
    device: &Device,
) -> Result<Tensor<2>> {
    let expected: Vec<Option<usize>> = shape.iter().map(|&s| Some(s)).collect();
    let (_, values) = tensors.take(key, &expected, path)?;
    let width = shape[1..].iter().product();
    Ok(Tensor::<2>::from_data(
        TensorData::new(values, [shape[0], width]),
        device,
    ))
}

fn take_row_adam(
    tensors: &mut NamedTensors,
    steps: &std::collections::BTreeMap<String, u64>,
    key: &str,
    shape: &[usize],
    path: &Path,
    device: &Device,
) -> Result<RowAdam<2>> {
    Ok(RowAdam {
        config: ANCHOR_ADAM,
        exp_avg: take_rows(tensors, &format!("adam.{key}.exp_avg"), shape, path, device)?,
        exp_avg_sq: take_rows(
            tensors,
            &format!("adam.{key}.exp_avg_sq"),
            shape,
            path,
            device,
        )?,
        step: *steps
            .get(key)
            .with_context(|| format!("{}: no Adam step count for `{key}`", path.display()))?,
    })
}

fn take_mlp(
    tensors: &mut NamedTensors,
    steps: &std::collections::BTreeMap<String, u64>,
    key: &str,
    mlp: &mut Mlp,
    adam: &mut super::decoder_adam::MlpAdam,
    path: &Path,
    device: &Device,
) -> Result<()> {
    for (layer, linear, state) in [
        ("hidden", &mut mlp.hidden, &mut adam.hidden),
        ("output", &mut mlp.output, &mut adam.output),
    ] {
        let k = format!("{key}.{layer}");
        let [i, o] = linear.weight.val().dims();
        let w: Tensor<2> = take_tensor(tensors, &format!("{k}.weight"), [i, o], path, device)?;
        let b: Tensor<1> = take_tensor(tensors, &format!("{k}.bias"), [o], path, device)?;
        state.weight = take_adam(
            tensors,
            steps,
            &format!("{k}.weight"),
            [i, o],
            DECODER_ADAM,
            path,
            device,
        )?;
        state.bias = take_adam(
            tensors,
            steps,
            &format!("{k}.bias"),
            [o],
            DECODER_ADAM,
            path,
            device,
        )?;
        linear.weight = burn::module::Param::from_tensor(w);
        linear.bias = Some(burn::module::Param::from_tensor(b));
    }
    Ok(())
}
