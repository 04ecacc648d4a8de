//! Refiners: what edits the anchor rows or re-initialises their values between optimizer steps,
//! behind one trait and composed from the config ([`refiners`]), so a method is a list of
//! refiners rather than branches in the step. GIFStream is densification, pruning by the pruning
//! gate and `init_dynamic`; ACA-GS adds AAC relocation and the post-hoc step.
//!
//! Refiners read the statistics the trainer gathers after the backward pass
//! ([`AnchorState`]; gathered on the device and read back only when a refiner takes them through
//! [`RefineContext::parts`]); they hold no state of their own (everything they change is in the
//! set or the state, so checkpoints need nothing from them).

use super::adaptive_cardinality::{RelocationReport, relocate};
use super::anchor_state::AnchorState;
use super::config::{
    AacConfig, CardinalityMode, DensifyConfig, FeatureMaskMode, InitDynamic, TrainConfig,
};
use super::densify::{DensifyReport, grow_and_prune, init_dynamic, prune_by_pruning_gate};
use super::posthoc::{PostHocReport, prune_capacity};
use super::streams::{Stream, step_rng};
use crate::model::anchors::AnchorSet;

/// The anchors a refiner works on at one step.
pub struct RefineContext<'a> {
    anchors: &'a mut AnchorSet,
    state: &'a mut AnchorState,
    /// The training step (after its optimizer update, for [`Refiner::after_step`]).
    pub step: usize,
    /// `train.seed`: refiners that draw take the step's stream of their own.
    pub seed: u64,
}

impl<'a> RefineContext<'a> {
    pub fn new(
        anchors: &'a mut AnchorSet,
        state: &'a mut AnchorState,
        step: usize,
        seed: u64,
    ) -> Self {
        Self {
            anchors,
            state,
            step,
            seed,
        }
    }

    /// The anchors and their state with its statistics current: what the steps gathered on the
    /// device is read back here, so a refiner that does not act this step costs no
    /// synchronisation.
    pub fn parts(&mut self) -> (&mut AnchorSet, &mut AnchorState) {
        self.state.settle();
        (self.anchors, self.state)
    }
}

/// What a refiner did after a step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Refinement {
    /// Rows added and removed.
    Rows(DensifyReport),
    /// An AAC relocation (slots switched off and on, no rows changed).
    Relocation(RelocationReport),
}

pub trait Refiner {
    /// Before the forward pass of the step.
    fn before_forward(&self, _ctx: &mut RefineContext) {}

    /// After the optimizer update of the step (and the statistics it gathered).
    fn after_step(&self, _ctx: &mut RefineContext) -> Option<Refinement> {
        None
    }

    /// Once, after the last training step.
    fn after_training(&self, _ctx: &mut RefineContext) -> Option<PostHocReport> {
        None
    }
}

/// The refiners of a config, in the order they run: GIFStream's (init_dynamic, densification,
/// pruning by the pruning gate), then ACA-GS's (AAC relocation after densification on shared
/// steps, spec §14 A9; the post-hoc step).
pub fn refiners(config: &TrainConfig) -> Vec<Box<dyn Refiner>> {
    let mut out: Vec<Box<dyn Refiner>> = Vec::new();
    if config.train.init_dynamic != InitDynamic::Off {
        out.push(Box::new(InitDynamicAtPhaseEnd {
            step: config.train.canonical_until(),
        }));
    }
    out.push(Box::new(Densification {
        config: config.densify.clone(),
        voxel_size: config.model.voxel_size,
    }));
    out.push(Box::new(PruningGate {
        every: 5 * config.densify.every,
        from: config.densify.stop,
        until: config.train.max_steps as f64 * 2.0 / 3.0,
    }));
    if config.aac.mode == CardinalityMode::Adaptive {
        out.push(Box::new(Relocation {
            config: config.aac.clone(),
        }));
    }
    if config.aac.mode == CardinalityMode::Adaptive || config.aafm.mode == FeatureMaskMode::Adaptive
    {
        out.push(Box::new(PostHoc));
    }
    out
}

/// `init_dynamic` at the end of the canonical phase (spec §7.3).
struct InitDynamicAtPhaseEnd {
    step: usize,
}

impl Refiner for InitDynamicAtPhaseEnd {
    fn before_forward(&self, ctx: &mut RefineContext) {
        if ctx.step == self.step && ctx.step > 0 {
            let (anchors, state) = ctx.parts();
            init_dynamic(anchors, state);
        }
    }
}

/// GIFStream's grow + prune every `every` steps in (start, stop) (spec §8.2).
struct Densification {
    config: DensifyConfig,
    voxel_size: f32,
}

impl Refiner for Densification {
    fn after_step(&self, ctx: &mut RefineContext) -> Option<Refinement> {
        let (c, step) = (&self.config, ctx.step);
        if !(step > c.start && step % c.every == 0 && step < c.stop) {
            return None;
        }
        let mut rng = step_rng(ctx.seed, step, Stream::Densify);
        let (anchors, state) = ctx.parts();
        Some(Refinement::Rows(grow_and_prune(
            anchors,
            state,
            c,
            self.voxel_size,
            step,
            &mut rng,
        )))
    }
}

/// After densification, pruning by the pruning gate every 5·`densify.every` steps while
/// step < 2/3·max_steps (spec §8.3).
struct PruningGate {
    every: usize,
    from: usize,
    until: f64,
}

impl Refiner for PruningGate {
    fn after_step(&self, ctx: &mut RefineContext) -> Option<Refinement> {
        let step = ctx.step;
        (step >= self.from && step % self.every == 0 && (step as f64) < self.until).then(|| {
            let (anchors, state) = ctx.parts();
            Refinement::Rows(DensifyReport {
                added: 0,
                pruned: prune_by_pruning_gate(anchors, state),
            })
        })
    }
}

/// ACA-GS's AAC relocation (paper §3.1, spec §12).
struct Relocation {
    config: AacConfig,
}

impl Refiner for Relocation {
    fn after_step(&self, ctx: &mut RefineContext) -> Option<Refinement> {
        if !self.config.relocates_at(ctx.step) {
            return None;
        }
        let mut rng = step_rng(ctx.seed, ctx.step, Stream::Relocate);
        let step = ctx.step;
        let (anchors, state) = ctx.parts();
        Some(Refinement::Relocation(relocate(
            anchors,
            state,
            &self.config,
            step,
            &mut rng,
        )))
    }
}

/// ACA-GS's post-hoc step (spec §13.4).
struct PostHoc;

impl Refiner for PostHoc {
    fn after_training(&self, ctx: &mut RefineContext) -> Option<PostHocReport> {
        let (anchors, state) = ctx.parts();
        Some(prune_capacity(anchors, state))
    }
}
