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

    // Targets stay on the device: two training views (one camera, two frames), so of three
    // steps at least one finds its target cached and uploads no frame.
    // Canonical-phase steps before densification: nothing but the step itself uploads.
    // Motion-aware culling, which a step does on the device (`train.step_culling = "device"`).
    let cached = small_config(&[
        "data.downscale=8",
        "data.frames=2",
        "data.removed_cameras=[2, 3, 4, 5, 6, 7, 8, 9, 10, 11]",
        "train.deformation_gate=0.5",
        "densify.start=10",
        "model.culling=\"deformed\"",
    ]);
    let mut c = trainer(&cached, device.clone());
    assert_eq!(
        c.scene.train_views().len(),
        2,
        "one training camera, two frames"
    );
    let frame_bytes = {
        let (w, h) = c.scene.resolution();
        (w * h * 3 * 4) as u64
    };
    let mut cached_reports = Vec::new();
    let mut reads = Vec::new();
    for _ in 0..3 {
        let (_, _, hits, misses) = c.device_targets.usage();
        let before = TransferCounts::now();
        let report = c.step().unwrap();
        let crossed = TransferCounts::now().since(before);
        assert!(report.loss.is_finite() && !report.skipped, "{report:?}");
        let (_, _, hits_after, misses_after) = c.device_targets.usage();
        // Besides the frame a step uploads a few scalars: culled on the device, no row index.
        let besides_frame = 4096;
        assert!(
            frame_bytes > besides_frame,
            "a frame larger than the scalars' room"
        );
        assert!(report.visible_anchors > 0, "{report:?}");
        if hits_after > hits {
            assert!(
                crossed.upload_bytes <= besides_frame,
                "a cached target's step uploaded {crossed:?} (frame {frame_bytes} bytes)"
            );
        } else {
            assert_eq!(misses_after, misses + 1);
            assert!(crossed.upload_bytes >= frame_bytes, "{crossed:?}");
        }
        assert!(!report.rerendered, "{report:?}");
        cached_reports.push(report);
        reads.push(crossed.read_backs);
    }
    // From the second step on the rasterizer's intersection buffers are sized from the count
    // the previous step read with its loss: a step reads back once fewer. (Steps 0-2 run no
    // refiner and no evaluation render; one added there would change these counts.)
    // Culled on the device, a plain step reads back once: its loss (issue 21's target); the
    // first also reads the exact intersection count.
    eprintln!("read-backs per step on wgpu, the first counting intersections exactly: {reads:?}");
    assert_eq!(reads, [2, 1, 1], "read-backs per step");
    // The same steps with every target uploaded give the same losses (to the rasterizer's
    // atomics' order): a cache serving another view's target would not.
    let uploaded = small_config(&[
        "data.downscale=8",
        "data.frames=2",
        "data.removed_cameras=[2, 3, 4, 5, 6, 7, 8, 9, 10, 11]",
        "train.deformation_gate=0.5",
        "densify.start=10",
        "model.culling=\"deformed\"",
        "data.device_frame_cache_mib=0",
    ]);
    let mut u = trainer(&uploaded, device.clone());
    for report in &cached_reports {
        // Buffers sized far too small for the second step: it renders again, counting exactly,
        // and trains as the cached run's step did.
        if report.step == 1 {
            u.intersection_capacity = Some(1);
        }
        let other = u.step().unwrap();
        assert_eq!(other.rerendered, report.step == 1, "{other:?}");
        let (a, b) = (report.loss as f64, other.loss as f64);
        assert!(
            (a - b).abs() <= 1e-3 * a.abs(),
            "step {}: {a} cached, {b} uploaded",
            report.step
        );
    }
    assert_eq!(u.device_targets.usage().1, 0);
    let (bytes, entries, hits, misses) = c.device_targets.usage();
    assert_eq!(hits + misses, 3);
    assert!(hits >= 1 && misses <= 2, "hits {hits}, misses {misses}");
    assert_eq!(entries as u64, misses);
    assert_eq!(bytes as u64, misses * frame_bytes);
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
