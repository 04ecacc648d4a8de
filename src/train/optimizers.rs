//! The optimizers of a training step and their learning rates: Adam for every anchor column (its
//! state is the trainer's [`AnchorState`], row-aligned with the anchors), for the four decoders
//! and for the entropy models, each with GIFStream's schedule (spec §5, §7.1).

use burn::tensor::Gradients;

use super::anchor_state::{AnchorState, ColumnRate};
use super::config::{FeatureMaskMode, KnotStep, MotionGateHold, TrainConfig, exponential_lr};
use super::decoder_adam::{DECODER_ADAM, DecoderAdam, DecoderLearningRates, MlpAdam, step_mlp};
use crate::codec::entropy_models::EntropyModels;
use crate::model::anchored::AnchoredModel;
use crate::model::anchors::{
    AnchorDims, AnchorTensors, Column, Columns, FACTOR_COUNT, MOTION_GATE,
};
use crate::model::decoders::Decoders;

/// The learning rate of every parameter group at one step.
#[derive(Clone, Debug, PartialEq)]
pub struct StepRates {
    pub anchors: Columns<ColumnRate>,
    /// The units of the knots' steps (`lr.knot_step`).
    pub knot_step: KnotStep,
    pub decoders: DecoderLearningRates,
    pub entropy: f64,
}

impl StepRates {
    /// The rates at `step` of a schedule that started at `origin` (0, or a warm start's step).
    pub fn at(config: &TrainConfig, dims: &AnchorDims, step: usize, origin: usize) -> Self {
        let (lr, train) = (&config.lr, &config.train);
        let since = step - origin;
        let progress = |lr: f64, factor: f64| exponential_lr(lr, factor, since, train.max_steps);
        let masking = config.aafm.mode == FeatureMaskMode::Adaptive;
        let anchors = Columns::build(dims, |c| match c {
            Column::LogScales => ColumnRate::Uniform(lr.scales),
            Column::Offsets => ColumnRate::Uniform(progress(lr.offsets, lr.offsets_final_factor)),
            Column::Features => ColumnRate::Uniform(lr.features_for(&config.model)),
            Column::TimeFeatures => ColumnRate::Uniform(lr.time_features),
            // The motion gate held while frames open (`train.motion_gate_hold`).
            Column::Factors
                if train.motion_gate_hold == MotionGateHold::Curriculum
                    && train.curriculum_opening(step, dims.frames) =>
            {
                let mut rates = vec![lr.factors; FACTOR_COUNT];
                rates[MOTION_GATE] = 0.0;
                ColumnRate::PerElement(rates)
            }
            Column::Factors => ColumnRate::Uniform(lr.factors),
            // Not optimised without masking: the logits stay at their initial value.
            Column::MaskLogits if !masking => ColumnRate::Frozen,
            Column::MaskLogits => ColumnRate::Uniform(progress(lr.mask, lr.mask_final_factor)),
            // Each knot its own (`lr.trajectory_schedule`), for its three elements x, y, z.
            Column::Trajectory => ColumnRate::PerElement(
                knot_rates(config, dims, since, lr.trajectory)
                    .iter()
                    .flat_map(|&r| [r; 3])
                    .collect(),
            ),
            // Derived from the paths (`model/path_turns.rs`), not optimised.
            Column::Turn if dims.trajectory_turn.is_derived() => ColumnRate::Frozen,
            // The knots' schedule, from `lr.turn` (radians) instead of `lr.trajectory`. Knot 0's
            // turn is held at the identity: at frame 0 it only re-expresses what the offsets and
            // the cov head already place (a free gauge that costs bits; trained free it drifted
            // by a median 20° on `crossing`).
            Column::Turn => ColumnRate::PerElement(
                knot_rates(config, dims, since, lr.turn)
                    .iter()
                    .enumerate()
                    .flat_map(|(j, &r)| [if j == 0 { 0.0 } else { r }; 3])
                    .collect(),
            ),
        });
        Self {
            anchors,
            knot_step: lr.knot_step,
            decoders: DecoderLearningRates {
                opacity: progress(lr.mlp_opacity, lr.mlp_opacity_final_factor),
                cov: progress(lr.mlp_cov, lr.mlp_cov_final_factor),
                color: progress(lr.mlp_color, lr.mlp_color_final_factor),
                motion: progress(lr.mlp_motion, lr.mlp_motion_final_factor),
            },
            entropy: lr.entropy,
        }
    }
}

/// The learning rate of each trajectory knot `since` steps after the schedule's origin under
/// `lr.trajectory_schedule`, starting from `base` (`lr.trajectory` for the translations,
/// `lr.turn` for the turns); empty without trajectories.
pub fn knot_rates(config: &TrainConfig, d: &AnchorDims, since: usize, base: f64) -> Vec<f64> {
    let (lr, train) = (&config.lr, &config.train);
    if d.trajectory_spacing == 0 {
        return Vec::new();
    }
    lr.trajectory_schedule.knot_rates(
        base,
        lr.trajectory_final_factor,
        since,
        train.max_steps,
        d.trajectory_knots(),
        |knot| train.knot_opening_step(knot, d.trajectory_spacing, d.frames),
    )
}

/// Adam state of the decoders and the entropy models (the anchors' is in [`AnchorState`]).
#[derive(Clone, Debug)]
pub struct Optimizers {
    pub decoders: DecoderAdam,
    /// In [`EntropyModels::named`] order.
    pub entropy: Vec<MlpAdam>,
}

/// The tracked copies one step's gradients belong to.
pub struct TrackedParameters<'a> {
    pub anchors: &'a AnchorTensors,
    pub decoders: &'a Decoders,
    /// The entropy models, when the rate term was on, and the gradients that hold theirs
    /// (the step's, or the rate term's own graph's under `compression.rate_graph =
    /// "concurrent"`).
    pub entropy: Option<(&'a EntropyModels, &'a Gradients)>,
}

impl Optimizers {
    /// Fresh state for these decoders and entropy models.
    pub fn new(decoders: &Decoders, entropy: &EntropyModels) -> Self {
        Self {
            decoders: DecoderAdam::new(decoders, DECODER_ADAM),
            entropy: entropy
                .named()
                .iter()
                .map(|(_, m)| MlpAdam::new(m, DECODER_ADAM))
                .collect(),
        }
    }

    /// One Adam step of every group from the gradients of `tracked`.
    pub fn step(
        &mut self,
        model: &mut AnchoredModel,
        anchor_state: &mut AnchorState,
        entropy: &mut EntropyModels,
        tracked: TrackedParameters,
        grads: &Gradients,
        rates: &StepRates,
    ) {
        anchor_state.adam_step(
            &mut model.anchors,
            tracked.anchors,
            grads,
            &rates.anchors,
            rates.knot_step,
        );
        self.decoders
            .step(&mut model.decoders, tracked.decoders, grads, rates.decoders);
        if let Some((models, entropy_grads)) = tracked.entropy {
            for (((_, plain), (_, tracked)), adam) in entropy
                .named_mut()
                .into_iter()
                .zip(models.named())
                .zip(&mut self.entropy)
            {
                step_mlp(plain, tracked, adam, entropy_grads, rates.entropy);
            }
        }
    }
}
