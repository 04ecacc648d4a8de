//! ACA-GS Adaptive Anchor Feature Masking and Conditional Regularisation (paper §3.2-§3.3, spec
//! §13): one mask logit m per anchor switches the adaptive half of its feature on or off.
//!
//! - Mask, straight-through: M = sg(1[σ(m) > γ] − σ(m)) + σ(m), γ = 0.01 (HAC's `get_mask`):
//!   forward binary, gradient σ'(m).
//! - Masked feature: F = [F_base ; M · F_adapt], what every decoder and the kNN average see.
//! - L_M = mean σ(m) (λ_M = 8e-3); L_CR = mean σ(d) · (1 − σ(m)) (λ_CR = 0.1) with d the
//!   time-feature gate logit (`factors[:, 0]`), over all anchors. `aafm.cr_gradient` chooses
//!   whether CR shapes m only (spec §13.2 / §14 A13: stop-gradient on σ(d)) or also pushes d
//!   (the paper's formula, which has none; the default, better by measurement).

use crate::raster::columns::{concat_columns, slice_columns};
use crate::raster::activation::sigmoid;
use burn::tensor::{Tensor, s};

/// γ: σ(m) above this keeps the adaptive channels.
pub const MASK_THRESHOLD: f32 = 0.01;
/// Initial logit (σ = 0.731), HAC's mask init (spec §3).
pub const INITIAL_MASK_LOGIT: f32 = 1.0;

/// The share of anchors whose time gate σ(d), d = `factors[:, 0]`, lies below `gate` (one
/// scalar read-back; 0 without anchors).
pub fn time_gate_share_below(factors: &Tensor<2>, gate: f32) -> f32 {
    if factors.dims()[0] == 0 {
        return 0.0;
    }
    let logit = crate::host_math::logit(gate);
    let share = factors
        .clone()
        .slice(s![.., 0..1])
        .lower_elem(logit)
        .float()
        .mean();
    crate::model::anchors::host_values(&share)[0]
}

/// The binary straight-through mask [N, 1] of logits [N, 1].
pub fn binary_mask(logits: Tensor<2>, threshold: f32) -> Tensor<2> {
    let soft = sigmoid(logits);
    let hard = soft.clone().greater_elem(threshold).float();
    soft.clone() + (hard - soft).detach()
}

/// [F_base ; M · F_adapt] for features [M, C_F] whose first `base` channels are never masked.
pub fn masked_features(features: Tensor<2>, mask: Tensor<2>, base: usize) -> Tensor<2> {
    let [_, channels] = features.dims();
    assert!(
        base <= channels,
        "base split {base} exceeds {channels} channels"
    );
    if base == channels {
        return features;
    }
    concat_columns(
        slice_columns(features.clone(), 0..base),
        slice_columns(features, base..channels) * mask,
    )
}

/// L_M = mean σ(m) over all anchors.
pub fn mask_loss(logits: Tensor<2>) -> Tensor<1> {
    sigmoid(logits).mean()
}

/// L_CR = mean σ(d) · (1 − σ(m)) over all anchors; `time_gate_logits` are `factors[:, 0]`.
/// With `gate_gradient` false σ(d) is a stop-gradient weight (spec §14 A13), else the gradient
/// also reaches d as in the paper's formula.
pub fn conditional_regularization(
    time_gate_logits: Tensor<2>,
    mask_logits: Tensor<2>,
    gate_gradient: bool,
) -> Tensor<1> {
    let activity = sigmoid(time_gate_logits);
    let activity = if gate_gradient {
        activity
    } else {
        activity.detach()
    };
    (activity * (-sigmoid(mask_logits) + 1.0)).mean()
}

/// Whether a mask logit switches F_adapt off: σ(m) ≤ γ (the forward of [`binary_mask`]).
pub fn is_masked(logit: f32, threshold: f32) -> bool {
    crate::host_math::sigmoid(logit) <= threshold
}

/// Fraction of anchors whose adaptive channels are masked (σ(m) ≤ γ), the paper's masking ratio.
pub fn masking_ratio(logits: &[f32], threshold: f32) -> f64 {
    if logits.is_empty() {
        return 0.0;
    }
    let masked = logits.iter().filter(|&&m| is_masked(m, threshold)).count();
    masked as f64 / logits.len() as f64
}
