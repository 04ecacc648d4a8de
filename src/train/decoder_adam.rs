//! Adam for the four decoder MLPs, one learning-rate group per MLP (spec §7.1).
//!
//! The decoders live on the plain device; each step trains a tracked copy ([`tracked`]) and the
//! update is written back into the plain module. The same [`RowAdam`] as the anchors is used so
//! the whole optimizer state is ours to checkpoint (Burn's optimizer records are keyed by
//! parameter ids that change when a module is rebuilt).

use burn::module::Param;
use burn::nn::Linear;
use burn::tensor::{Gradients, Tensor};

use super::row_adam::{AdamConfig, RowAdam};
use crate::model::decoders::{Decoders, Mlp};
pub use crate::model::decoders::{tracked, tracked_mlp};

/// Adam state of one linear layer.
#[derive(Clone, Debug)]
pub struct LinearAdam {
    pub weight: RowAdam<2>,
    pub bias: RowAdam<1>,
}

impl LinearAdam {
    fn new(layer: &Linear, config: AdamConfig) -> Self {
        Self {
            weight: RowAdam::new(&layer.weight.val(), config),
            bias: RowAdam::new(&bias(layer), config),
        }
    }
}

fn bias(layer: &Linear) -> Tensor<1> {
    layer
        .bias
        .as_ref()
        .expect("decoder layers have a bias")
        .val()
}

#[derive(Clone, Debug)]
pub struct MlpAdam {
    pub hidden: LinearAdam,
    pub output: LinearAdam,
}

impl MlpAdam {
    pub fn new(m: &Mlp, config: AdamConfig) -> Self {
        Self {
            hidden: LinearAdam::new(&m.hidden, config),
            output: LinearAdam::new(&m.output, config),
        }
    }
}

/// Adam state of the four decoders.
#[derive(Clone, Debug)]
pub struct DecoderAdam {
    pub opacity: MlpAdam,
    pub cov: MlpAdam,
    pub color: MlpAdam,
    pub motion: MlpAdam,
}

/// Learning rates of the four MLPs at one step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DecoderLearningRates {
    pub opacity: f64,
    pub cov: f64,
    pub color: f64,
    pub motion: f64,
}

/// The decoder and entropy-model optimizers: PyTorch's default eps 1e-8. A kept deviation:
/// GIFStream sets `eps=1e-15 / sqrt(BS)` like the per-anchor groups (`create_splats_with_optimizers`
/// in simple_trainer_GIFStream.py; BS = 1). acags used it from 2026-11-24 to 11-25; together with
/// the straight-through gate clamp and the simulated smoothness reference it measured
/// 0.35-1.75 dB worse decoded PSNR on three seeds of synthetic:fast (docs/results.md, Follow-up 4).
pub const DECODER_ADAM: AdamConfig = AdamConfig {
    beta1: 0.9,
    beta2: 0.999,
    eps: 1e-8,
};

impl DecoderAdam {
    pub fn new(decoders: &Decoders, config: AdamConfig) -> Self {
        let mlp = |m: &Mlp| MlpAdam {
            hidden: LinearAdam::new(&m.hidden, config),
            output: LinearAdam::new(&m.output, config),
        };
        Self {
            opacity: mlp(&decoders.opacity),
            cov: mlp(&decoders.cov),
            color: mlp(&decoders.color),
            motion: mlp(&decoders.motion),
        }
    }

    /// Updates `plain` from the gradients of its tracked copy `tracked`.
    pub fn step(
        &mut self,
        plain: &mut Decoders,
        tracked: &Decoders,
        grads: &Gradients,
        lr: DecoderLearningRates,
    ) {
        step_mlp(
            &mut plain.opacity,
            &tracked.opacity,
            &mut self.opacity,
            grads,
            lr.opacity,
        );
        step_mlp(&mut plain.cov, &tracked.cov, &mut self.cov, grads, lr.cov);
        step_mlp(
            &mut plain.color,
            &tracked.color,
            &mut self.color,
            grads,
            lr.color,
        );
        step_mlp(
            &mut plain.motion,
            &tracked.motion,
            &mut self.motion,
            grads,
            lr.motion,
        );
    }
}

pub fn step_mlp(plain: &mut Mlp, tracked: &Mlp, adam: &mut MlpAdam, grads: &Gradients, lr: f64) {
    step_linear(
        &mut plain.hidden,
        &tracked.hidden,
        &mut adam.hidden,
        grads,
        lr,
    );
    step_linear(
        &mut plain.output,
        &tracked.output,
        &mut adam.output,
        grads,
        lr,
    );
}

fn step_linear(
    plain: &mut Linear,
    tracked: &Linear,
    adam: &mut LinearAdam,
    grads: &Gradients,
    lr: f64,
) {
    let weight = plain.weight.val();
    let grad = tracked
        .weight
        .val()
        .grad(grads)
        .unwrap_or_else(|| weight.zeros_like());
    plain.weight = Param::from_tensor(adam.weight.step(weight, grad, lr).set_require_grad(false));
    let b = bias(plain);
    let grad = bias(tracked).grad(grads).unwrap_or_else(|| b.zeros_like());
    plain.bias = Some(Param::from_tensor(
        adam.bias.step(b, grad, lr).set_require_grad(false),
    ));
}
