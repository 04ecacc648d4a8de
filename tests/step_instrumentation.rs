//! `bench train`'s instruments: the per-stage clock covers the whole step, and the host↔device
//! crossings of a step are counted (the target frame goes up, the loss comes back), with their
//! bytes; the densification statistics and AAC's importance are gathered without a read-back.
//! One test in its own binary: the crossing counters are process-wide.
#![allow(deprecated)] // Device::ndarray

mod small_run;

use acags::device_io::TransferCounts;
use acags::train::stage_clock::Stage;
use burn::tensor::Device;
use small_run::{small_config, trainer};

#[test]
fn stage_times_cover_the_step_and_crossings_are_counted() {
    let config = small_config(&[]);
    let mut t = trainer(&config, Device::ndarray());
    t.step().unwrap();
    let frame_bytes = {
        let (w, h) = config.data.load_scene().unwrap().resolution();
        (w * h * 3 * 4) as u64
    };
    for _ in 0..6 {
        let before = TransferCounts::now();
        let r = t.step().unwrap();
        let crossed = TransferCounts::now().since(before);
        let total = r.stages.total();
        assert!(
            total <= r.seconds + 1e-9 && total >= 0.9 * r.seconds - 1e-3,
            "stages {total} s of a {} s step",
            r.seconds
        );
        for stage in [
            Stage::Quantization,
            Stage::Forward,
            Stage::Objective,
            Stage::Backward,
            Stage::Optimizer,
        ] {
            assert!(r.stages.get(stage) > 0.0, "{} took no time", stage.name());
        }
        // At least the target frame goes up and the loss with its terms comes back.
        assert!(
            crossed.uploads >= 1 && crossed.upload_bytes >= frame_bytes,
            "{crossed:?}"
        );
        assert!(
            crossed.read_backs >= 1 && crossed.read_back_bytes >= 4 * crossed.read_backs,
            "{crossed:?}"
        );
    }
    // The benchmark reports the same instruments.
    let report = acags::bench::bench_train(&Device::ndarray(), "ndarray", &config, 1, 3).unwrap();
    assert_eq!(report.median_stage_seconds.len(), Stage::ALL.len());
    let staged: f64 = report.median_stage_seconds.values().sum();
    assert!(staged > 0.3 * report.median_seconds_per_step, "{report:?}");
    assert!(report.transfers_per_step.read_backs >= 1.0, "{report:?}");
    if cfg!(unix) {
        let busy = report.average_cores_busy.expect("getrusage on unix");
        assert!(
            busy > 0.1 && busy <= rayon::current_num_threads() as f64 + 1.5,
            "cores busy {busy}"
        );
    }

    // Statistics stay on the device (`train/statistics.rs`): a step that gathers the
    // densification statistics and AAC's importance reads back exactly as often as the same
    // step of a run that gathers nothing. The two runs differ only in their gathering windows,
    // no refiner reads the statistics before step 36 and no row changes, so they train alike.
    let aac = [
        "model.slots=6",
        "aac.mode=\"adaptive\"",
        "aac.initial_active=4",
        "train.init_dynamic=\"off\"",
        // No temporal curriculum, hence no knot openings: their knot search and appearance
        // seeding read back (and the seeding's row edits bring the statistics back) by design.
        "train.frame_curriculum=0",
    ];
    let gathering = small_config(
        &[
            &aac[..],
            &[
                "densify.every=100",
                "aac.start=36",
                "aac.every=36",
                "aac.stop=40",
            ],
        ]
        .concat(),
    );
    let idle = small_config(
        &[
            &aac[..],
            &[
                "densify.every=100",
                "densify.start=40",
                "aac.start=200",
                "aac.every=100",
                "aac.stop=300",
            ],
        ]
        .concat(),
    );
    assert!(gathering.aac.accumulates_at(10) && !idle.aac.accumulates_at(10));
    let (mut a, mut b) = (
        trainer(&gathering, Device::ndarray()),
        trainer(&idle, Device::ndarray()),
    );
    let counted_step = |t: &mut acags::train::trainer::Trainer| {
        let before = TransferCounts::now();
        let loss = t.step().unwrap().loss;
        (loss, TransferCounts::now().since(before).read_backs)
    };
    for step in 0..36 {
        let (loss_a, reads_a) = counted_step(&mut a);
        let (loss_b, reads_b) = counted_step(&mut b);
        assert_eq!(
            loss_a, loss_b,
            "step {step}: the gathering changed training"
        );
        assert_eq!(
            reads_a,
            reads_b,
            "step {step}: gathering the statistics read back {} more times",
            reads_a as i64 - reads_b as i64
        );
    }
    assert!(
        !a.anchor_state.is_settled(),
        "statistics pending on the device"
    );
    a.anchor_state.settle();
    assert!(
        a.anchor_state
            .stats
            .anchor_visible_count
            .iter()
            .sum::<f32>()
            > 0.0
            && a.anchor_state.importance_visits.iter().sum::<f32>() > 0.0,
        "the gathering run gathered"
    );

    // Uploads a step may make: the frame, the visible rows, the knots' learning rates, the time
    // embedding and the stream window's averaging matrix at their first use (both are kept on
    // the device), and a little room.
    const MAX_UPLOADS: u64 = 10;
    // A plain step (dynamic phase, no refinement, no rate term) reads back once under
    // motion-aware culling (issue 21's target): the objective's values; the culling runs on the
    // device (`train.step_culling = "device"`, the default) and its visible count comes back
    // with them. GIFStream's canonical box test (no device form), as culling on the host,
    // reads the per-anchor table too: twice.
    // Its uploads: the target frame and a few scalars (learning rates, the time embedding);
    // culled on the host also the visible anchors' row index (≤ 8 bytes per anchor). No
    // per-anchor table built on the host (the neighbours' rows and the slot gates are gathered
    // from device mirrors).
    for (culling, side, plain_reads) in [("canonical", "device", 2), ("deformed", "device", 1)] {
        let config = small_config(&[
            &format!("model.culling=\"{culling}\""),
            &format!("train.step_culling=\"{side}\""),
            "compression.rate_from=1.0",
        ]);
        let mut t = trainer(&config, Device::ndarray());
        let plain_from = config.densify.stop + 1;
        while t.step < plain_from {
            t.step().unwrap();
        }
        assert_eq!(t.phase(t.step), acags::model::view::Phase::Dynamic);
        // On the CPU the host frame cache is the device's memory: no second copy is kept, and
        // every step's target counts as an upload (a copy in the same memory).
        assert_eq!(t.device_targets.budget_bytes(), 0);
        let mut checked = 0;
        while checked < 4 {
            // Closed anchors are pruned every `densify.every` steps after densification (a
            // refine step: it reads the gates back).
            if t.step % config.densify.every == 0 {
                t.step().unwrap();
                continue;
            }
            checked += 1;
            let step = t.step;
            let before = TransferCounts::now();
            let report = t.step().unwrap();
            let crossed = TransferCounts::now().since(before);
            let reads = crossed.read_backs;
            assert!(report.rate_bits.is_none() && report.added + report.pruned == 0);
            assert_eq!(
                reads, plain_reads,
                "culling {culling} on the {side}, step {step}: {reads} read-backs"
            );
            let anchors = t.model.anchors.len() as u64;
            let row_index = if plain_reads == 1 { 0 } else { 8 * anchors };
            assert!(
                crossed.upload_bytes <= frame_bytes + row_index + 4096,
                "culling {culling}, step {step}: {crossed:?} for {anchors} anchors \
                 and a {frame_bytes}-byte frame"
            );
            // A handful of uploads, not one per parameter tensor: a single learning rate is
            // filled on the device (it was 22 uploads of one rate each).
            assert!(
                crossed.uploads <= MAX_UPLOADS,
                "culling {culling}, step {step}: {crossed:?}"
            );
        }
    }
    // A rate-term step uploads no more: the offsets' mask comes from the slot gates' mirror
    // (it was an [N, 3K] table built on the host and uploaded every rate step).
    let config = small_config(&["compression.rate_from=0.0"]);
    let mut t = trainer(&config, Device::ndarray());
    while t.step <= config.densify.stop {
        t.step().unwrap();
    }
    for _ in 0..3 {
        let before = TransferCounts::now();
        let report = t.step().unwrap();
        let crossed = TransferCounts::now().since(before);
        assert!(report.rate_bits.is_some() && report.added + report.pruned == 0);
        let anchors = t.model.anchors.len() as u64;
        assert!(
            crossed.upload_bytes <= frame_bytes + 8 * anchors + 4096,
            "rate step {}: {crossed:?} for {anchors} anchors",
            report.step
        );
        // The entropy models' Adam steps add no upload either (they were 20 more).
        assert!(
            crossed.uploads <= MAX_UPLOADS,
            "rate step {}: {crossed:?}",
            report.step
        );
    }
}
