//! ACA-GS feature masking (AAFM) and conditional regularisation (CR) as building blocks: the STE
//! mask is binary forward with gradient σ'(m), masking touches only the adaptive channels, CR sends
//! no gradient into the time gate d.
#![allow(deprecated)] // Device::ndarray

use acags::model::feature_mask::{
    MASK_THRESHOLD, binary_mask, conditional_regularization, mask_loss, masked_features,
    masking_ratio, time_gate_share_below,
};
use acags::train::config::{AafmConfig, CR_TRIGGER_CHECK_EVERY, CrTrigger};
use burn::tensor::{Device, Tensor, TensorData};

fn t2(v: &[f32], rows: usize, cols: usize, d: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v.to_vec(), [rows, cols]), d)
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap()
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

#[test]
fn ste_mask_is_binary_forward_with_the_sigmoid_gradient() {
    let device = Device::ndarray().autodiff();
    // σ(−5) = 0.0067 ≤ γ → 0; σ(−4) = 0.018 > γ → 1; σ(1) → 1.
    let logits_host = [-5.0f32, -4.0, 1.0, -8.0];
    let logits = t2(&logits_host, 4, 1, &device).require_grad();
    let mask = binary_mask(logits.clone(), MASK_THRESHOLD);
    assert_eq!(values(mask.clone()), vec![0.0, 1.0, 1.0, 0.0]);
    let weights = t2(&[1.0, 2.0, 3.0, 4.0], 4, 1, &device);
    let grad = values(logits.grad(&(mask * weights).sum().backward()).unwrap());
    for (i, m) in logits_host.iter().enumerate() {
        let s = sigmoid(*m);
        let want = (i + 1) as f32 * s * (1.0 - s);
        assert!(
            (grad[i] - want).abs() < 1e-6,
            "logit {m}: {} vs σ' = {want}",
            grad[i]
        );
    }
}

#[test]
fn masking_zeroes_only_the_adaptive_channels() {
    let device = Device::ndarray();
    let features = t2(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0], 2, 4, &device);
    let mask = t2(&[0.0, 1.0], 2, 1, &device);
    assert_eq!(
        values(masked_features(features.clone(), mask.clone(), 2)),
        vec![1.0, 2.0, 0.0, 0.0, 5.0, 6.0, 7.0, 8.0]
    );
    // No adaptive part: unchanged.
    assert_eq!(
        values(masked_features(features.clone(), mask, 4)),
        values(features)
    );
}

#[test]
fn conditional_regularization_shapes_m_and_reaches_d_only_when_asked() {
    let device = Device::ndarray().autodiff();
    let (d_host, m_host) = ([2.0f32, -1.0, 0.5], [0.3f32, -2.0, 1.5]);
    let d = t2(&d_host, 3, 1, &device).require_grad();
    let m = t2(&m_host, 3, 1, &device).require_grad();
    let loss = conditional_regularization(d.clone(), m.clone(), false);
    let want: f32 = d_host
        .iter()
        .zip(&m_host)
        .map(|(d, m)| sigmoid(*d) * (1.0 - sigmoid(*m)))
        .sum::<f32>()
        / 3.0;
    assert!((values(loss.clone())[0] - want).abs() < 1e-6);
    let grads = loss.backward();
    let gd = d.grad(&grads).map(values).unwrap_or_else(|| vec![0.0; 3]);
    assert!(
        gd.iter().all(|g| *g == 0.0),
        "CR must not push gradient into d: {gd:?}"
    );
    let gm = values(m.grad(&grads).unwrap());
    for i in 0..3 {
        let s = sigmoid(m_host[i]);
        let want = -sigmoid(d_host[i]) * s * (1.0 - s) / 3.0;
        assert!((gm[i] - want).abs() < 1e-6, "m[{i}]: {} vs {want}", gm[i]);
    }
    // The paper's formula (no stop-gradient): the same value and m-gradient, and
    // ∂L/∂d = σ'(d)·(1 − σ(m))/N, which closes the time gate of a masked anchor (σ(m) → 0).
    let d = t2(&d_host, 3, 1, &device).require_grad();
    let m = t2(&m_host, 3, 1, &device).require_grad();
    let loss = conditional_regularization(d.clone(), m.clone(), true);
    assert!((values(loss.clone())[0] - want).abs() < 1e-6);
    let grads = loss.backward();
    let (gd, gm2) = (
        values(d.grad(&grads).unwrap()),
        values(m.grad(&grads).unwrap()),
    );
    for i in 0..3 {
        let sd = sigmoid(d_host[i]);
        let want = sd * (1.0 - sd) * (1.0 - sigmoid(m_host[i])) / 3.0;
        assert!((gd[i] - want).abs() < 1e-6, "d[{i}]: {} vs {want}", gd[i]);
        assert!(gd[i] > 0.0, "descent lowers d");
        assert!((gm2[i] - gm[i]).abs() < 1e-7);
    }
    // L_M is the mean σ(m).
    let lm = values(mask_loss(t2(&m_host, 3, 1, &Device::ndarray())))[0];
    assert!((lm - m_host.iter().map(|m| sigmoid(*m)).sum::<f32>() / 3.0).abs() < 1e-6);
}

#[test]
fn masking_ratio_counts_anchors_at_or_below_the_threshold() {
    assert_eq!(masking_ratio(&[], MASK_THRESHOLD), 0.0);
    assert_eq!(masking_ratio(&[-5.0, -4.0, 1.0, -8.0], MASK_THRESHOLD), 0.5);
}

#[test]
fn the_gate_share_trigger_starts_cr_once_enough_time_gates_favour_masking() {
    let device = Device::ndarray();
    // Time-gate logits d (column 0) of five anchors; the other factor columns must not count.
    // σ(−4) = 0.018, σ(−2.6) = 0.069, σ(−2.3) = 0.091, σ(0) = 0.5, σ(3) = 0.95.
    let d = [-4.0f32, -2.6, -2.3, 0.0, 3.0];
    let factors: Vec<f32> = d.iter().flat_map(|&x| [x, -9.0, -9.0, -9.0]).collect();
    let factors = t2(&factors, 5, 4, &device);
    let config = AafmConfig {
        cr_trigger: CrTrigger::GateShare,
        cr_gate_share: 0.5,
        cr_start: 100,
        ..AafmConfig::default()
    };
    // λ_M / λ_CR = 8e-3 / 0.1: CR's pull on a mask is weaker than L_M's push below σ(d) = 0.08.
    assert!((config.cr_neutral_gate() - 0.08).abs() < 1e-7);
    let share = time_gate_share_below(&factors, config.cr_neutral_gate());
    assert!((share - 0.4).abs() < 1e-6, "2 of 5 below 0.08, got {share}");
    let wider = time_gate_share_below(&factors, 0.1);
    assert!((wider - 0.6).abs() < 1e-6, "3 of 5 below 0.1, got {wider}");
    assert_eq!(time_gate_share_below(&t2(&[], 0, 4, &device), 0.08), 0.0);

    // Not before cr_start, whatever the gates; then only at a check with share ≥ 0.5.
    assert!(!config.cr_starts_at(99, Some(1.0)));
    assert!(!config.cr_starts_at(100, Some(0.4)));
    assert!(!config.cr_starts_at(100, None), "no measurement, no start");
    assert!(config.cr_starts_at(100, Some(0.5)));
    assert!(
        config.cr_checks_gates_at(100) && config.cr_checks_gates_at(100 + CR_TRIGGER_CHECK_EVERY)
    );
    assert!(!config.cr_checks_gates_at(101) && !config.cr_checks_gates_at(90));
    // The step trigger (the paper) ignores the gates and never measures them.
    let step = AafmConfig {
        cr_trigger: CrTrigger::Step,
        ..config.clone()
    };
    assert!(step.cr_starts_at(100, None) && !step.cr_starts_at(99, None));
    assert!(!step.cr_checks_gates_at(100));
    // λ_CR = 0 switches CR off under either trigger.
    let off = AafmConfig {
        cr_weight: 0.0,
        ..config
    };
    assert!(!off.cr_starts_at(100, Some(1.0)) && !off.cr_checks_gates_at(100));
}
