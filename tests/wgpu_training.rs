//! A short training run on wgpu (lavapipe in CI; fails instead of skipping when
//! ACAGS_REQUIRE_WGPU=1): GIFStream steps, a checkpoint that loads on ndarray, and ACA-GS steps
//! with a relocation, the rate term in the step's graph and in its own. Its own test binary
//! because llvmpipe's worker threads and the ndarray tests' rayon pool slow each other down
//! several-fold when they share the 2 cores; one test in it, as the read-back counters are
//! process-wide.
#![allow(deprecated)] // Device::ndarray

mod common;
mod small_run;
use common::TempDir;
use small_run::{small_config, trainer};

use acags::compute_backend::{BackendKind, resolve, wgpu_adapter};
use acags::device_io::TransferCounts;
use acags::model::anchors::Column;
use burn::tensor::Device;

fn temp_dir(tag: &str) -> TempDir {
    TempDir::new(&format!("acags-test-{tag}"))
}

#[test]
fn trains_on_wgpu() {
    match wgpu_adapter() {
        Ok(adapter) => eprintln!("wgpu adapter: {} ({})", adapter.name, adapter.backend),
        Err(why) if std::env::var("ACAGS_REQUIRE_WGPU").as_deref() == Ok("1") => {
            panic!("ACAGS_REQUIRE_WGPU=1 but {why}")
        }
        Err(why) => {
            eprintln!("skipping wgpu training test: {why}");
            return;
        }
    }
    let config = small_config(&["data.downscale=8"]);
    let device = resolve(BackendKind::Wgpu).unwrap().device;
    let mut t = trainer(&config, device.clone());
    let before = t.model.anchors.host(Column::Features);
    for _ in 0..3 {
        let report = t.step().unwrap();
        assert!(report.loss.is_finite() && !report.skipped, "{report:?}");
        assert!(report.gaussians > 0);
    }
    let after = t.model.anchors.host(Column::Features);
    assert_ne!(before, after, "the optimizer moved the features");
    // A wgpu checkpoint loads on ndarray.
    let dir = temp_dir("wgpu");
    t.save_checkpoint(&dir.join("c.safetensors")).unwrap();
    let mut cpu = trainer(&config, Device::ndarray());
    cpu.load_checkpoint(&dir.join("c.safetensors")).unwrap();
    assert_eq!(cpu.model.anchors.host(Column::Features), after);

    // ACA-GS on wgpu: slot gates, masked features, L_M + CR and a relocation step at step 1.
    let config = small_config(&[
        "data.downscale=8",
        "model.slots=10",
        "model.feature_dim=48",
        "aac.mode=adaptive",
        "aac.start=1",
        "aac.every=1",
        "aafm.mode=adaptive",
    ]);
    let mut t = trainer(&config, device.clone());
    let masks = t.model.anchors.host(Column::MaskLogits);
    let mut relocated = false;
    for _ in 0..2 {
        let report = t.step().unwrap();
        assert!(report.loss.is_finite() && !report.skipped, "{report:?}");
        relocated |= report.relocation.is_some();
    }
    assert!(relocated, "an AAC step ran");
    assert_ne!(
        t.model.anchors.host(Column::MaskLogits),
        masks,
        "the mask logits are optimised"
    );
    let _ = std::fs::remove_dir_all(&dir);

    // The rate term from step 1, in the step's graph and in its own on a second thread: the
    // same losses and bits (to the rasterizer's atomics, whose order varies between runs), and
    // as many read-backs per step: on a GPU the thread's bits come back in the step's one read.
    let run = |graph: &str| {
        let key = format!("compression.rate_graph=\"{graph}\"");
        let config = small_config(&["data.downscale=8", "compression.rate_from=0", &key]);
        let mut t = trainer(&config, device.clone());
        (0..4)
            .map(|_| {
                let before = TransferCounts::now();
                let report = t.step().unwrap();
                (report, TransferCounts::now().since(before).read_backs)
            })
            .unzip::<_, _, Vec<_>, Vec<_>>()
    };
    let ((shared, shared_reads), (own, own_reads)) = (run("shared"), run("concurrent"));
    small_run::assert_same_losses_and_bits(&shared, &own, 1e-3, 0.0);
    assert_eq!(
        shared_reads, own_reads,
        "read-backs per step, shared vs own graph"
    );
}
