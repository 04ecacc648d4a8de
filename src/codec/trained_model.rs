//! A trained scene without its trainer: the model, its entropy models, the config it was trained
//! with, how far it trained and which GOP it covers. It is what a finished run hands on, what
//! opening a run directory returns (`run::open_run`, read from the checkpoint without any
//! optimizer state) and what the codec encodes ([`crate::codec::scene_file::compress`]).

use crate::codec::entropy_models::EntropyModels;
use crate::config::TrainConfig;
use crate::model::anchored::AnchoredModel;
use crate::model::view::Phase;

#[derive(Clone, Debug)]
pub struct TrainedModel {
    pub model: AnchoredModel,
    /// The conditional entropy models the rate term trained (untrained when it never ran).
    pub entropy: EntropyModels,
    pub config: TrainConfig,
    /// Steps trained.
    pub step: usize,
    /// First frame and frame count of the GOP it was trained on.
    pub gop: (usize, usize),
}

impl TrainedModel {
    /// The phase of its last training step: a model stopped in the canonical phase decodes
    /// without time inputs.
    pub fn phase(&self) -> Phase {
        self.config.train.phase_at(self.step.saturating_sub(1))
    }

    /// Whether it trained its whole schedule.
    pub fn finished(&self) -> bool {
        self.step >= self.config.train.max_steps
    }
}
