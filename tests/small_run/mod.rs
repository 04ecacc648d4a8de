#![allow(dead_code)] // each test binary uses some of these
//! The tiny training schedule shared by `train_run.rs` and `wgpu_training.rs`.

use std::path::PathBuf;

use acags::train::config::TrainConfig;
use acags::train::trainer::Trainer;
use burn::tensor::Device;

/// One generated scene shared by every test of these binaries (generation is atomic).
pub fn cache_dir() -> PathBuf {
    std::env::temp_dir().join("acags-test-cache")
}

/// A tiny schedule on synthetic:fast at 80×60: densification, the end of the canonical phase,
/// init_dynamic, smoothness and factor regularisation all happen within 16 steps.
pub const SMALL: &[&str] = &[
    "data.downscale=4",
    "train.max_steps=40",
    "train.deformation_gate=0.05",
    "train.checkpoint_every=0",
    "train.eval_every=0",
    "train.log_every=1",
    "densify.start=3",
    "densify.every=4",
    "densify.stop=30",
    "densify.check_interval=4",
    "densify.grad_threshold=0.00005",
];

pub fn small_config(extra: &[&str]) -> TrainConfig {
    unsafe { std::env::set_var("ACAGS_CACHE_DIR", cache_dir()) };
    let overrides: Vec<String> = SMALL.iter().chain(extra).map(|s| s.to_string()).collect();
    TrainConfig::load(None, &overrides).unwrap()
}

pub fn trainer(config: &TrainConfig, device: Device) -> Trainer {
    let scene = config.data.load_scene().unwrap();
    Trainer::new(config.clone(), scene, device).unwrap()
}

/// The rate term in the step's graph (`shared`) and in its own (`own`) train alike: per step the
/// same loss (within `tolerance` · max(|loss|, `loss_floor`)) and rate bits (within `tolerance`
/// relative), the rate term on from step 1.
pub fn assert_same_losses_and_bits(
    shared: &[acags::train::trainer::StepReport],
    own: &[acags::train::trainer::StepReport],
    tolerance: f64,
    loss_floor: f64,
) {
    assert_eq!(shared.len(), own.len());
    for (a, b) in shared.iter().zip(own) {
        let step = a.step;
        assert!(!a.skipped && !b.skipped, "step {step} skipped");
        let (la, lb) = (a.loss as f64, b.loss as f64);
        assert!(
            (la - lb).abs() <= tolerance * la.abs().max(loss_floor),
            "step {step}: loss {la} (shared) vs {lb} (own graph)"
        );
        match (a.rate_bits, b.rate_bits) {
            (None, None) => assert_eq!(step, 0, "the rate term is on from step 1"),
            (Some(x), Some(y)) => {
                let (x, y) = (x as f64, y as f64);
                assert!(
                    (x - y).abs() <= tolerance * x.abs(),
                    "step {step}: {x} vs {y}"
                )
            }
            other => panic!("step {step}: rate bits {other:?}"),
        }
    }
}
