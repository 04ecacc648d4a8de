//! The trainer end to end on a downscaled synthetic scene: resume ≡ uninterrupted, checkpoints,
//! the `train` / `eval` / `render` / `compress` commands and their outputs (bitstream included)
//! and config errors. Training on wgpu is in `wgpu_training.rs`.
#![allow(deprecated)] // Device::ndarray

mod common;
mod small_run;
use common::{TempDir, assert_success, read_json};
use small_run::{SMALL, cache_dir, small_config, trainer};
use std::process::Command;

use acags::codec::quantization::RatePreset;
use acags::model::anchors::{Column, host_values};
use acags::train::checkpoint::{read_checkpoint, write_checkpoint};
use acags::train::config::TrainConfig;
use acags::train::trainer::{Trainer, read_trained_model};
use burn::tensor::Device;

fn acags() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_acags"));
    c.env("ACAGS_CACHE_DIR", cache_dir());
    c
}

fn temp_dir(tag: &str) -> TempDir {
    TempDir::new(&format!("acags-test-{tag}"))
}

/// Trains `total` steps straight, and `at` steps + checkpoint + a fresh trainer resuming to
/// `total`; the losses and the final model must agree. Returns both trainers.
fn assert_resume_is_exact(
    config: &TrainConfig,
    tag: &str,
    at: usize,
    total: usize,
) -> (Trainer, Trainer) {
    let dir = temp_dir(tag);
    let mut straight = trainer(config, Device::ndarray());
    let losses: Vec<f32> = (0..total).map(|_| straight.step().unwrap().loss).collect();
    assert!(losses.iter().all(|l| l.is_finite()));

    let mut first = trainer(config, Device::ndarray());
    for (step, want) in losses.iter().enumerate().take(at) {
        assert_eq!(
            first.step().unwrap().loss,
            *want,
            "step {step} differs before the checkpoint"
        );
    }
    let path = dir.join("checkpoint.safetensors");
    first.save_checkpoint(&path).unwrap();
    drop(first);

    let mut resumed = trainer(config, Device::ndarray());
    resumed.load_checkpoint(&path).unwrap();
    assert_eq!(resumed.step, at);
    for (step, want) in losses.iter().enumerate().skip(at) {
        let got = resumed.step().unwrap().loss;
        assert!(
            (got - want).abs() <= 1e-5,
            "step {step}: resumed loss {got} vs uninterrupted {want}"
        );
    }
    let (a, b) = (&straight.model.anchors, &resumed.model.anchors);
    assert_eq!(a.len(), b.len());
    let close = |x: Vec<f32>, y: Vec<f32>| {
        x.len() == y.len() && x.iter().zip(&y).all(|(x, y)| (x - y).abs() <= 1e-5)
    };
    assert!(close(a.host(Column::Features), b.host(Column::Features)));
    assert!(close(
        a.host(Column::MaskLogits),
        b.host(Column::MaskLogits)
    ));
    assert_eq!(a.slot_gates, b.slot_gates);
    let (sa, sb) = (
        straight.anchor_state.settled(),
        resumed.anchor_state.settled(),
    );
    assert_eq!(sa.created_at, sb.created_at);
    assert_eq!(sa.reference_frame, sb.reference_frame);
    assert_eq!(sa.held_knots(), sb.held_knots());
    assert!(close(
        a.host(Column::Trajectory),
        b.host(Column::Trajectory)
    ));
    assert!(close(sa.importance.clone(), sb.importance.clone()));
    assert_eq!(sa.relocated, sb.relocated);
    assert_eq!(straight.relocation_churn, resumed.relocation_churn);
    assert!(close(straight.entropy.weights(), resumed.entropy.weights()));
    let _ = std::fs::remove_dir_all(&dir);
    (straight, resumed)
}

/// A checkpoint opens as a trained model without its trainer: the anchor columns, slot gates,
/// decoders and entropy models are the trainer's, and both render a view bit for bit alike.
#[test]
fn a_checkpoint_opens_as_a_trained_model_without_a_trainer() {
    let config = small_config(&[
        "model.slots=6",
        "aac.mode=\"adaptive\"",
        "aac.initial_active=4",
    ]);
    let dir = temp_dir("trained-model");
    let mut t = trainer(&config, Device::ndarray());
    for _ in 0..6 {
        t.step().unwrap();
    }
    let path = dir.join("checkpoint.safetensors");
    t.save_checkpoint(&path).unwrap();
    let (opened, history) =
        read_trained_model(&path, &config, &t.scene, &Device::ndarray()).unwrap();
    let want = t.trained_model();
    assert_eq!(opened.step, 6);
    assert_eq!(opened.gop, want.gop);
    assert!((history.train_seconds - t.train_seconds).abs() < 1e-9);
    let (a, b) = (&want.model.anchors, &opened.model.anchors);
    assert_eq!(a.positions, b.positions);
    assert_eq!(a.slot_gates, b.slot_gates);
    assert!(a.slot_gates.iter().any(|&g| !g), "some slots are gated");
    for (c, values) in a.columns.iter() {
        assert_eq!(host_values(values), b.host(c), "{c:?}");
    }
    assert_eq!(a.neighbors(), b.neighbors());
    assert_eq!(want.entropy.weights(), opened.entropy.weights());
    let view = t.scene.test_views()[0];
    let render = |m: &acags::model::anchored::AnchoredModel| {
        acags::eval::evaluate::render_view(m, &t.scene, view, want.phase())
            .unwrap()
            .image_host()
    };
    assert_eq!(render(&want.model), render(&opened.model));

    // A tensor that is neither the model's nor training state (a column of another build) is
    // named, not silently dropped.
    let (mut tensors, metadata) = read_checkpoint(&path).unwrap();
    let n = want.model.anchors.len();
    tensors
        .entries
        .insert("anchors.color_bias".into(), (vec![n, 3], vec![0.0; n * 3]));
    let other = dir.join("other.safetensors");
    write_checkpoint(&other, &tensors, &metadata).unwrap();
    let err = format!(
        "{:#}",
        read_trained_model(&other, &config, &t.scene, &Device::ndarray()).unwrap_err()
    );
    assert!(err.contains("anchors.color_bias"), "{err}");
}

#[test]
fn resuming_from_a_checkpoint_continues_exactly() {
    let config = small_config(&[]);
    // Checkpoint at 15 of 40: quantisation noise is on (from 8) and the rate term has trained
    // the entropy models for one step (from 14), so their weights and Adam state must resume.
    assert!(config.compression.rate_at(14, 40) && !config.compression.rate_at(13, 40));
    let (straight, _) = assert_resume_is_exact(&config, "resume", 15, 19);
    // The default appearance seeding placed anchors on later frames before the checkpoint (the
    // curriculum opens every knot within the first 16 steps), so their reference frames resumed.
    assert!(
        straight.anchor_state.reference_frame.iter().any(|&f| f > 0),
        "no anchor was seeded after frame 0"
    );
    // Densification ran (anchors were added or removed) within these steps.
    let initial = trainer(&config, Device::ndarray()).model.anchors.len();
    assert_ne!(
        initial,
        straight.model.anchors.len(),
        "densification never changed the set"
    );
}

/// With the rigid fit's knots held (`train.fitted_knots = "held"`), the held flags resume with
/// the checkpoint: the resumed run holds the same knots and trains to the same model.
#[test]
fn resuming_with_held_fitted_knots_continues_exactly() {
    let config = small_config(&["train.fitted_knots=\"held\""]);
    // The curriculum opens every knot within the first 16 steps, and knots are held only when
    // one opens: what the uninterrupted run holds at the end was held before the checkpoint.
    let (straight, _) = assert_resume_is_exact(&config, "resume-held", 17, 21);
    assert!(
        straight.anchor_state.held_knots().contains(&true),
        "the rigid fit held no knot"
    );
    // Resumed under "trained", the same checkpoint holds nothing.
    let dir = temp_dir("resume-held-released");
    let mut held = trainer(&config, Device::ndarray());
    for _ in 0..17 {
        held.step().unwrap();
    }
    assert!(held.anchor_state.held_knots().contains(&true));
    let path = dir.join("checkpoint.safetensors");
    held.save_checkpoint(&path).unwrap();
    let trained = small_config(&["train.fitted_knots=\"trained\""]);
    let mut released = trainer(&trained, Device::ndarray());
    released.load_checkpoint(&path).unwrap();
    assert!(!released.anchor_state.held_knots().contains(&true));
}

/// ACA-GS's slot gates and masks with the rate term on from step 1.
const ACA_GS_RATE_TERM: &[&str] = &[
    "compression.rate_from=0",
    "model.slots=6",
    "aac.mode=\"adaptive\"",
    "aac.initial_active=4",
    "model.feature_dim=48",
    "aafm.mode=\"adaptive\"",
];

/// `compression.rate_graph = "concurrent"` differentiates the rate term in a graph of its own
/// beside the step and adds its gradients to the step's: the losses, the rate's bits, the
/// anchors and the entropy models follow the shared graph's, up to the order in which the two
/// gradient parts are summed. ACA-GS's masks and slot gates are on, so every priced column
/// (F_adapt under M, offsets under the gates) takes part.
#[test]
fn the_rate_term_in_its_own_graph_trains_as_in_the_steps_graph() {
    let keys = ACA_GS_RATE_TERM;
    let run = |graph: &str| {
        let key = format!("compression.rate_graph=\"{graph}\"");
        let config = small_config(&[&keys[..], &[key.as_str()]].concat());
        let mut t = trainer(&config, Device::ndarray());
        let reports: Vec<_> = (0..8).map(|_| t.step().unwrap()).collect();
        (t, reports)
    };
    let (shared, shared_reports) = run("shared");
    let (own, own_reports) = run("concurrent");
    small_run::assert_same_losses_and_bits(&shared_reports, &own_reports, 1e-5, 1.0);
    // (Without the merge the losses part at step 2.) The anchors compared elementwise, allowing
    // the rare element whose gradient is a near-cancellation: Adam (ε = 1e-15) steps it by ±lr
    // whichever sign the rounding left, and the sum's order differs (measured: 0.18 % of the
    // features, 0.01 % of the streams and offsets off by more than 1e-4; entropy weights 1.4e-6).
    let agree = |x: Vec<f32>, y: Vec<f32>, what: &str| {
        assert_eq!(x.len(), y.len(), "{what}");
        let off = x
            .iter()
            .zip(&y)
            .filter(|(x, y)| (*x - *y).abs() > 1e-4)
            .count();
        assert!(
            off * 200 <= x.len(),
            "{what}: {off} of {} elements differ",
            x.len()
        );
    };
    let (a, b) = (&shared.model.anchors, &own.model.anchors);
    for column in [
        Column::Features,
        Column::Offsets,
        Column::LogScales,
        Column::TimeFeatures,
    ] {
        agree(a.host(column), b.host(column), &format!("{column:?}"));
    }
    agree(
        shared.entropy.weights(),
        own.entropy.weights(),
        "entropy models",
    );
    // And the entropy models did train (from their start at step 1).
    let fresh = {
        let config = small_config(&keys);
        let mut t = trainer(&config, Device::ndarray());
        t.step().unwrap();
        t.step().unwrap();
        t.entropy.weights()
    };
    assert!(
        fresh
            .iter()
            .zip(own.entropy.weights())
            .any(|(x, y)| (x - y).abs() > 1e-4),
        "the entropy models did not move after step 2"
    );
}

/// `train.step_thread = "pool"` (the default) runs a CPU step on a worker of rayon's pool and
/// its rate term's own graph as a pool job: the same operations in the same order as on the
/// caller's thread, so the same losses, bits and anchors to the bit. And two such trainings at
/// once in one process (as the golden traces and the sweeps run them) both finish: with the rate
/// graph on an OS thread joined by a blocked worker, they deadlocked (docs/benchmarks.md, "The
/// step on the pool"; the deadlock needed every worker of the global pool blocked, so the
/// concurrent part can catch a return of it on a machine of two cores, as CI's).
#[test]
fn a_step_on_the_pool_trains_as_on_the_callers_thread_and_two_run_at_once() {
    let config_on = |thread: &str| {
        let key = format!("train.step_thread=\"{thread}\"");
        let graph = "compression.rate_graph=\"concurrent\"";
        small_config(&[ACA_GS_RATE_TERM, &[graph, key.as_str()]].concat())
    };
    let run = |config: TrainConfig| {
        let mut t = trainer(&config, Device::ndarray());
        let reports: Vec<_> = (0..6).map(|_| t.step().unwrap()).collect();
        let features = t.model.anchors.host(Column::Features);
        (reports, features, t.entropy.weights())
    };
    let caller = run(config_on("caller"));
    let pool = run(config_on("pool"));
    assert!(
        caller.0.iter().all(|r| !r.ran_on_pool),
        "a caller step ran on the pool"
    );
    assert!(
        pool.0.iter().all(|r| r.ran_on_pool),
        "a pool step ran off the pool"
    );
    for (a, b) in caller.0.iter().zip(&pool.0) {
        assert_eq!(a.loss.to_bits(), b.loss.to_bits(), "step {}: loss", a.step);
        assert_eq!(a.rate_bits, b.rate_bits, "step {}: rate bits", a.step);
        // (The rate term is on from step 1: `step > rate_from · max_steps`.)
        assert!(
            a.step == 0 || a.rate_bits.is_some(),
            "step {}: no rate term",
            a.step
        );
    }
    assert_eq!(caller.1, pool.1, "anchor features after 6 steps");
    assert_eq!(caller.2, pool.2, "entropy models after 6 steps");

    let (sender, receiver) = std::sync::mpsc::channel();
    for _ in 0..2 {
        let (sender, config) = (sender.clone(), config_on("pool"));
        std::thread::spawn(move || sender.send(run(config).0).unwrap());
    }
    for _ in 0..2 {
        let reports = receiver
            .recv_timeout(std::time::Duration::from_secs(600))
            .expect("two trainings on the pool at once did not finish within 10 minutes");
        for (a, b) in caller.0.iter().zip(&reports) {
            assert_eq!(
                a.loss.to_bits(),
                b.loss.to_bits(),
                "step {}: loss (concurrent)",
                a.step
            );
        }
    }
}

/// ACA-GS: the slot gates, the importance window (checkpointed mid-window), birth steps, mask
/// logits and relocation flags survive a checkpoint, and relocations after the resume draw the
/// same parents.
/// Targets kept on the device train exactly as targets uploaded every step: the cache turned on
/// for the CPU (where it is off unless set) on a scene of two training views, so that most of
/// the steps find their target cached; then the moving-pixel weights turned on mid-run, which
/// must not be served from entries made without them.
#[test]
fn cached_targets_train_as_uploaded_ones() {
    let keys = [
        "data.frames=2",
        "data.removed_cameras=[2, 3, 4, 5, 6, 7, 8, 9, 10, 11]",
    ];
    let run = |mib: &str| {
        let budget = format!("data.device_frame_cache_mib={mib}");
        let config = small_config(&[keys[0], keys[1], &budget]);
        let mut t = trainer(&config, Device::ndarray());
        assert_eq!(t.scene.train_views().len(), 2);
        let mut losses: Vec<f32> = (0..6).map(|_| t.step().unwrap().loss).collect();
        t.config.loss.moving_weight = 4.0;
        losses.extend((0..3).map(|_| t.step().unwrap().loss));
        (losses, t.device_targets.usage())
    };
    let (cached, (bytes, entries, hits, misses)) = run("64");
    let (uploaded, (_, kept, ..)) = run("0");
    assert_eq!(
        cached, uploaded,
        "per-step losses, cached vs uploaded targets"
    );
    assert_eq!(kept, 0, "a zero budget keeps nothing");
    assert_eq!(hits + misses, 9);
    assert!(hits >= 5, "{hits} hits of 9 steps over at most two views");
    // A miss for each view's first step, and again once the weights changed: the weighted
    // steps' entries replaced the unweighted ones.
    assert!(
        misses >= 2 && entries <= 2,
        "{misses} misses, {entries} entries"
    );
    assert!(bytes > 0);
}

/// `train.step_culling = "device"` decodes every anchor and masks the culled ones on the device
/// instead of reading the visible list back: under motion-aware culling (which drops no drawn
/// Gaussian either way) the same anchors count as visible, and the steps train alike, up to
/// the order of sums over more rows and the culling's view of the quantised values (the host
/// culls on the plain ones). ACA-GS's slot gates and masks on, densification, the dynamic phase,
/// smoothness and the gate regulariser within the steps.
#[test]
fn device_culling_trains_as_host_culling() {
    let run = |side: &str| {
        let config = small_config(&[
            "model.culling=\"deformed\"",
            "model.slots=6",
            "aac.mode=\"adaptive\"",
            "aac.initial_active=4",
            "model.feature_dim=48",
            "aafm.mode=\"adaptive\"",
            &format!("train.step_culling=\"{side}\""),
        ]);
        let mut t = trainer(&config, Device::ndarray());
        let reports: Vec<_> = (0..10).map(|_| t.step().unwrap()).collect();
        t.anchor_state.settle();
        (t, reports)
    };
    let (host, host_reports) = run("host");
    let (device, device_reports) = run("device");
    let mut culled = false;
    for (a, b) in host_reports.iter().zip(&device_reports) {
        let step = a.step;
        assert!(!a.skipped && !b.skipped, "step {step} skipped");
        assert_eq!(a.anchors, b.anchors, "step {step}: anchors");
        culled |= a.visible_anchors < a.anchors;
        // The few anchors at the bound's margin may go either way (quantised vs plain values).
        let (va, vb) = (a.visible_anchors as f64, b.visible_anchors as f64);
        assert!(
            (va - vb).abs() <= 0.01 * va,
            "step {step}: {va} visible on the host, {vb} on the device"
        );
        let (la, lb) = (a.loss as f64, b.loss as f64);
        assert!(
            (la - lb).abs() <= 2e-3 * la.abs(),
            "step {step}: loss {la} (host) vs {lb} (device)"
        );
        let (ga, gb) = (a.gaussians as f64, b.gaussians as f64);
        assert!(
            (ga - gb).abs() <= 0.01 * ga,
            "step {step}: {ga} vs {gb} Gaussians"
        );
    }
    assert!(
        culled,
        "no step culled an anchor: the comparison proves nothing"
    );
    // The statistics count the same views of the same anchors.
    let (h, d) = (&host.anchor_state, &device.anchor_state);
    assert_eq!(
        h.stats.anchor_visible_count.len(),
        d.stats.anchor_visible_count.len()
    );
    let seen = |v: &[f32]| v.iter().sum::<f32>();
    let (sh, sd) = (
        seen(&h.stats.anchor_visible_count),
        seen(&d.stats.anchor_visible_count),
    );
    assert!(
        sh > 0.0 && (sh - sd).abs() <= 0.01 * sh,
        "views counted: {sh} vs {sd}"
    );
    assert_eq!(
        seen(&h.importance_visits) > 0.0,
        seen(&d.importance_visits) > 0.0
    );
}

#[test]
fn resuming_aca_gs_continues_exactly() {
    let config = small_config(&[
        "model.slots=10",
        "model.feature_dim=48",
        "aac.mode=\"adaptive\"",
        "aac.start=8",
        "aac.every=4",
        "aac.stop=30",
        "aafm.mode=\"adaptive\"",
        // The non-default choices of issue 19 and 17 resume exactly too.
        "aac.target_slot=\"most-opaque-free\"",
        "aafm.cr_gradient=\"mask-only\"",
        "lr.trajectory_schedule=\"per-knot\"",
        // CR by the gate share: λ_CR = 0.01 puts the neutral gate at 0.8, above every σ(d) = 0.5,
        // so it starts at the check of step 5; the checkpoint at 10 must carry that start (the
        // next check is at 15).
        "aafm.cr_trigger=\"gate-share\"",
        "aafm.cr_weight=0.01",
        "aafm.cr_start=5",
    ]);
    let (straight, _) = assert_resume_is_exact(&config, "resume-aca", 10, 17);
    assert_eq!(straight.cr_started_at, Some(5));
    // Relocations at 8 and 12 were judged at 12 and 16.
    assert!(
        straight.relocation_churn.judged > 0,
        "no relocation was judged"
    );
    let a = &straight.model.anchors;
    // Relocations at steps 8, 12 and 16 switched slots off and on: not every anchor has the
    // initial first five.
    let initial: Vec<bool> = (0..10).map(|k| k < 5).collect();
    assert!(
        (0..a.len()).any(|i| a.slot_gates[i * 10..(i + 1) * 10] != initial[..]),
        "no relocation changed a gate"
    );
}

#[test]
fn warm_start_loads_the_model_and_restarts_optimizers_and_schedules() {
    let config = small_config(&[]);
    let dir = temp_dir("warm");
    let mut gop0 = trainer(&config, Device::ndarray());
    for _ in 0..6 {
        gop0.step().unwrap();
    }
    let path = dir.join("gop0.safetensors");
    gop0.save_checkpoint(&path).unwrap();
    // The next GOP: frames 20..40 of the same rig would be a new scene; the model shapes match
    // (same T), which is what a warm start needs.
    let mut next = trainer(&config, Device::ndarray());
    next.warm_start(&path, 21).unwrap();
    assert_eq!(next.step, 21);
    assert_eq!(next.schedule_origin, 21);
    assert_eq!(next.model.anchors.len(), gop0.model.anchors.len());
    assert_eq!(
        next.model.anchors.host(Column::TimeFeatures),
        gop0.model.anchors.host(Column::TimeFeatures)
    );
    let a = &next.anchor_state;
    for (c, adam) in a.adam.iter() {
        assert_eq!(adam.step, 0, "fresh optimizer state of {c:?}");
        assert!(host_values(&adam.exp_avg).iter().all(|v| *v == 0.0));
    }
    assert!(
        a.stats.anchor_visible_count.iter().all(|v| *v == 0.0),
        "fresh statistics"
    );
    assert_eq!(
        a.created_at, gop0.anchor_state.created_at,
        "birth steps kept"
    );
    let report = next.step().unwrap();
    assert_eq!(report.step, 21);
    assert!(report.loss.is_finite());
    let err = format!(
        "{:#}",
        trainer(&config, Device::ndarray())
            .warm_start(&path, 40)
            .unwrap_err()
    );
    assert!(err.contains("nothing to train"), "{err}");
}

#[test]
fn checkpoints_are_atomic_and_bad_files_are_named() {
    let config = small_config(&[]);
    let dir = temp_dir("ckpt");
    let mut t = trainer(&config, Device::ndarray());
    t.step().unwrap();
    let path = dir.join("checkpoint.safetensors");
    t.save_checkpoint(&path).unwrap();
    let good = std::fs::read(&path).unwrap();
    // A writer killed mid-write leaves only its temporary file behind; the checkpoint is intact.
    std::fs::write(
        dir.join(".checkpoint.safetensors.tmp-999"),
        &good[..good.len() / 2],
    )
    .unwrap();
    let mut other = trainer(&config, Device::ndarray());
    other.load_checkpoint(&path).unwrap();
    assert_eq!(other.step, 1);
    // A truncated checkpoint is an error naming the file, not a panic.
    let broken = dir.join("broken.safetensors");
    std::fs::write(&broken, &good[..good.len() / 2]).unwrap();
    let err = format!("{:#}", other.load_checkpoint(&broken).unwrap_err());
    assert!(err.contains("broken.safetensors"), "{err}");
    // A checkpoint of another model size is rejected with the tensor named.
    let wide = small_config(&["model.feature_dim=16"]);
    let err = format!(
        "{:#}",
        trainer(&wide, Device::ndarray())
            .load_checkpoint(&path)
            .unwrap_err()
    );
    assert!(err.contains("anchors.features"), "{err}");

    // A checkpoint written before the visibility counts were renamed (`*_demon`) still loads.
    // (Past `densify.start`, so the counts are not all zero.)
    for _ in 0..5 {
        t.step().unwrap();
    }
    let counted = dir.join("counted.safetensors");
    t.save_checkpoint(&counted).unwrap();
    let mut current = trainer(&config, Device::ndarray());
    current.load_checkpoint(&counted).unwrap();
    let (mut tensors, metadata) = read_checkpoint(&counted).unwrap();
    for (name, former) in [
        ("stats.offset_visible_count", "stats.offset_demon"),
        ("stats.anchor_visible_count", "stats.anchor_demon"),
    ] {
        let entry = tensors
            .entries
            .remove(name)
            .expect("written under its new name");
        tensors.entries.insert(former.to_string(), entry);
    }
    let older = dir.join("older.safetensors");
    write_checkpoint(&older, &tensors, &metadata).unwrap();
    let mut from_older = trainer(&config, Device::ndarray());
    from_older.load_checkpoint(&older).unwrap();
    assert!(
        from_older.anchor_state.stats == current.anchor_state.stats
            && current
                .anchor_state
                .stats
                .anchor_visible_count
                .iter()
                .any(|&v| v > 0.0),
        "the counts load from their former names"
    );
}

#[test]
fn config_errors_name_the_key_and_the_file() {
    let err = format!(
        "{:#}",
        TrainConfig::load(None, &["train.max_stepz=5".into()]).unwrap_err()
    );
    assert!(err.contains("max_stepz"), "{err}");
    let err = format!(
        "{:#}",
        TrainConfig::load(None, &["train.max_steps=abc".into()]).unwrap_err()
    );
    assert!(err.contains("train.max_steps"), "{err}");
    let dir = temp_dir("config");
    let path = dir.join("bad.toml");
    std::fs::write(&path, "[model\nslots = 3").unwrap();
    let err = format!("{:#}", TrainConfig::load(Some(&path), &[]).unwrap_err());
    assert!(err.contains("bad.toml"), "{err}");
    // Every shipped config parses.
    for entry in std::fs::read_dir(common::crate_path("configs")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            TrainConfig::load(Some(&path), &[])
                .unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        }
    }
}

/// `--backend cuda` in a default build stops before any work with how to get CUDA support.
#[cfg(not(feature = "cuda"))]
#[test]
fn cuda_backend_without_the_feature_says_how_to_build_it() {
    let dir = temp_dir("cuda");
    let out = acags()
        .args(["train", "--backend", "cuda", "--out"])
        .arg(dir.join("run"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--features cuda"), "{stderr}");
    assert!(!dir.join("run").exists(), "nothing was written");
}

#[test]
fn train_eval_render_commands_write_their_outputs() {
    let dir = temp_dir("cli");
    let run = dir.join("run");
    let mut train = acags();
    train
        .args([
            "train",
            "--backend",
            "ndarray",
            "--quiet",
            "--stop-after",
            "6",
            "--out",
        ])
        .arg(&run);
    for s in SMALL {
        train.args(["--set", s]);
    }
    train.args(["--set", "train.max_steps=10"]);
    // Off by default; on here so the log shows the term joins the objective once knots open.
    train.args(["--set", "loss.trajectory_curvature=100"]);
    let out = train.output().unwrap();
    assert_success(&out);
    // Rows written by a build before the objective's `loss_*` columns had 18 fields: make the
    // first rows such rows; the resume must pad them to the header.
    let log_path = run.join("train_log.csv");
    let text = std::fs::read_to_string(&log_path).unwrap();
    let older: Vec<String> = (text.lines().enumerate())
        .map(|(i, line)| {
            let fields: Vec<&str> = line.split(',').collect();
            match fields[0].parse::<usize>() {
                Ok(step) if i > 0 && step < 2 => fields[..18].join(","),
                _ => line.to_string(),
            }
        })
        .collect();
    std::fs::write(&log_path, older.join("\n") + "\n").unwrap();
    // Stopped at 6 of 10: continue with --resume (without --quiet: stderr is a pipe here, so
    // progress comes as plain lines).
    let out = acags()
        .args(["train", "--backend", "ndarray", "--resume"])
        .arg(&run)
        .output()
        .unwrap();
    assert_success(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("at step 6"), "{stderr}");
    assert!(
        stderr.contains("step 8/10 (80 %): loss") && stderr.contains("step 10/10 (100 %)"),
        "{stderr}"
    );
    assert!(stderr.contains("s/step, ETA"), "{stderr}");

    let metrics = read_json(&run.join("metrics.json"));
    assert_eq!(metrics["step"], 10);
    let psnr = metrics["psnr"].as_f64().unwrap();
    assert!(psnr.is_finite() && psnr > 5.0, "psnr {psnr}");
    for key in [
        "ssim",
        "anchors",
        "gaussians",
        "uncompressed_mib",
        "train_seconds",
        "render_fps",
    ] {
        assert!(metrics[key].as_f64().is_some(), "metrics.json lacks {key}");
    }
    // LPIPS-Alex (weights built in) on the whole image and, per view, on its regions; VGG is
    // absent here (no weights in the test cache) and that is recorded as null, not 0.
    let lpips = metrics["lpips_alex"]
        .as_f64()
        .expect("metrics.json has lpips_alex");
    assert!(lpips > 0.0 && lpips < 1.0, "lpips_alex {lpips}");
    assert_eq!(metrics["lpips_input"], "normalized");
    assert!(metrics["lpips_vgg"].is_null());
    assert!(metrics["compressed"]["lpips_alex"].as_f64().is_some());
    assert!(metrics["views"][0]["lpips_alex"].as_f64().is_some());
    assert!(metrics["frames"][0]["lpips_alex"].as_f64().is_some());
    for chart in ["psnr_by_camera", "lpips_by_camera", "quality_by_frame"] {
        for ext in ["png", "svg"] {
            assert!(
                run.join(format!("{chart}.{ext}")).is_file(),
                "no {chart}.{ext}"
            );
        }
    }
    // A finished run trained with the compression simulation ships its bitstream, decoded and
    // evaluated in metrics.json.
    assert!(run.join("scene.acags").is_file() && run.join("compression.json").is_file());
    let compressed = &metrics["compressed"];
    for key in ["file_bytes", "ratio", "psnr", "ssim"] {
        assert!(
            compressed[key].as_f64().is_some(),
            "metrics.json compressed lacks {key}"
        );
    }
    assert_eq!(compressed["rate"], "r0");
    // GIFStream: every anchor has all K = 5 slots, nothing is masked.
    let histogram: Vec<u64> = metrics["cardinality_histogram"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    let anchors = metrics["anchors"].as_u64().unwrap();
    assert_eq!(histogram, vec![0, 0, 0, 0, 0, anchors]);
    assert_eq!(metrics["active_slots"].as_u64().unwrap(), 5 * anchors);
    assert_eq!(metrics["masking_ratio"].as_f64().unwrap(), 0.0);
    let log = std::fs::read_to_string(run.join("train_log.csv")).unwrap();
    // The rate term (from step 4 of 10) is logged; before it the column is empty. Every row's
    // objective terms add up to its loss.
    let header: Vec<&str> = log.lines().next().unwrap().split(',').collect();
    let column = |name: &str| header.iter().position(|&h| h == name).unwrap();
    let (bits_at, rate_at, loss_at) = (column("rate_bits"), column("loss_rate"), column("loss"));
    let term_columns: Vec<usize> = (0..header.len())
        .filter(|&i| header[i].starts_with("loss_"))
        .collect();
    assert_eq!(term_columns.len(), 9, "{header:?}");
    let curvature_at = column("loss_curvature");
    for line in log.lines().skip(1) {
        let fields: Vec<&str> = line.split(',').collect();
        assert_eq!(fields.len(), header.len(), "{line}");
        let step: usize = fields[0].parse().unwrap();
        let (bits, rate) = (fields[bits_at], fields[rate_at]);
        if step >= 4 {
            let b: f32 = bits.parse().unwrap();
            assert!(b.is_finite() && b > 0.0, "step {step}: rate {b}");
            assert!(rate.parse::<f32>().unwrap() > 0.0, "step {step}: {rate}");
        } else {
            assert!(
                bits.is_empty() && rate.is_empty(),
                "step {step}: {bits} {rate}"
            );
        }
        if step < 2 {
            // The padded rows of the older build: no term was logged.
            assert!(term_columns.iter().all(|&i| fields[i].is_empty()), "{line}");
            continue;
        }
        // Every knot is open from step 4 of 10 (the curriculum's 40 %): the trajectory
        // curvature term is computed.
        if step >= 4 {
            let c: f64 = fields[curvature_at].parse().unwrap();
            assert!(c.is_finite() && c >= 0.0, "step {step}: curvature {c}");
        }
        let loss: f64 = fields[loss_at].parse().unwrap();
        let sum: f64 = (term_columns.iter())
            .filter(|&&i| !fields[i].is_empty())
            .map(|&i| fields[i].parse::<f64>().unwrap())
            .sum();
        assert!(
            (sum - loss).abs() <= 1e-5 * loss.abs().max(1e-3),
            "step {step}: {sum} vs {loss}"
        );
    }
    let steps: Vec<usize> = log
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(
        steps,
        (0..10).collect::<Vec<_>>(),
        "one row per step, none duplicated by the resume"
    );
    let config = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(config.contains("max_steps = 10"));
    let renders = std::fs::read_dir(run.join("renders")).unwrap().count();
    assert_eq!(
        renders, 40,
        "one comparison image per test view (1 camera x 40 frames)"
    );
    let img = image::open(run.join("renders/cam00_frame0000.png")).unwrap();
    assert_eq!(
        (img.width(), img.height()),
        (3 * 80, 60),
        "truth | render | error"
    );

    let out = acags()
        .args(["eval", "--backend", "ndarray", "--run"])
        .arg(&run)
        .output()
        .unwrap();
    assert_success(&out);
    let again = read_json(&run.join("metrics.json"))["psnr"]
        .as_f64()
        .unwrap();
    assert!(
        (again - psnr).abs() < 1e-9,
        "eval recomputes the same PSNR: {again} vs {psnr}"
    );

    let frames = dir.join("frames");
    let out = acags()
        .args([
            "render",
            "--backend",
            "ndarray",
            "--camera",
            "3",
            "--frames",
            "2..5",
            "--run",
        ])
        .arg(&run)
        .arg("--out")
        .arg(&frames)
        .output()
        .unwrap();
    assert_success(&out);
    let pngs = std::fs::read_dir(&frames)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "png")
        })
        .count();
    assert_eq!(pngs, 3);
    if std::env::var("ACAGS_REQUIRE_FFMPEG").as_deref() == Ok("1")
        || acags::data::video::tool_available("ffmpeg")
    {
        assert!(
            frames.join("render.mp4").is_file(),
            "ffmpeg present: an mp4 is written"
        );
    }

    // Capacity heatmaps: the render and three maps at the run's resolution.
    let vis = dir.join("vis");
    let out = acags()
        .args([
            "visualize",
            "--backend",
            "ndarray",
            "--camera",
            "3",
            "--frame",
            "2",
            "--run",
        ])
        .arg(&run)
        .arg("--out")
        .arg(&vis)
        .output()
        .unwrap();
    assert_success(&out);
    for layer in ["render", "anchors", "cardinality", "channels"] {
        let img = image::open(vis.join(format!("cam03_frame0002_{layer}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (80, 60), "{layer}");
    }
    assert!(String::from_utf8_lossy(&out.stderr).contains("anchors per pixel"));
    let out = acags()
        .args(["visualize", "--camera", "0", "--frame", "99", "--run"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("outside the trained GOP"));

    // The codec: compress → size report; eval --bitstream equals the quantised model's own
    // evaluation (decode → render == quantised model before encoding, ≤ 0.01 dB per image).
    let out = acags()
        .args(["compress", "--run"])
        .arg(&run)
        .output()
        .unwrap();
    assert_success(&out);
    let table = String::from_utf8_lossy(&out.stdout);
    for name in [
        "meta",
        "decoders",
        "positions",
        "offsets",
        "time_features",
        "total (file)",
    ] {
        assert!(table.contains(name), "size table lacks {name}: {table}");
    }
    let file = run.join("scene.acags");
    let report = read_json(&run.join("compression.json"));
    let file_bytes = std::fs::metadata(&file).unwrap().len();
    assert_eq!(report["file_bytes"].as_u64().unwrap(), file_bytes);
    let sections: u64 = report["sections"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["bytes"].as_u64().unwrap())
        .sum();
    let count = report["sections"].as_array().unwrap().len() as u64;
    // Container framing: magic, version, count, one 36-byte table entry per section, table CRC.
    assert_eq!(file_bytes, sections + 12 + 36 * count + 4);
    assert!(report["ratio"].as_f64().unwrap() > 5.0, "{report}");
    let out = acags()
        .args(["eval", "--backend", "ndarray", "--bitstream"])
        .arg(&file)
        .output()
        .unwrap();
    assert_success(&out);
    let decoded = read_json(&run.join("scene_metrics.json"));
    let opened = acags::run::open_run(&run, Device::ndarray()).unwrap();
    let reference = acags::codec::scene_file::quantize(&opened.trained, RatePreset::R0)
        .unwrap()
        .to_model(&Device::ndarray())
        .unwrap();
    let expected = acags::eval::evaluate::evaluate(
        &reference,
        &opened.scene,
        &opened.frames,
        opened.trained.phase(),
        &opened.trained.config.eval,
        acags::eval::evaluate::Scoring::Full,
        None,
    )
    .unwrap();
    let views = decoded["views"].as_array().unwrap();
    assert_eq!(views.len(), expected.views.len());
    for (got, want) in views.iter().zip(&expected.views) {
        let p = got["psnr"].as_f64().unwrap();
        assert!((p - want.psnr).abs() <= 0.01, "{p} vs {}", want.psnr);
    }
    let frames_b = dir.join("frames_bitstream");
    let out = acags()
        .args([
            "render",
            "--backend",
            "ndarray",
            "--camera",
            "3",
            "--frames",
            "2..4",
        ])
        .arg("--bitstream")
        .arg(&file)
        .arg("--out")
        .arg(&frames_b)
        .output()
        .unwrap();
    assert_success(&out);
    assert!(frames_b.join("00001.png").is_file());
    // A damaged file is refused with its name and the problem.
    let mut bytes = std::fs::read(&file).unwrap();
    let at = bytes.len() / 2;
    bytes[at] ^= 0x10;
    let damaged = dir.join("damaged.acags");
    std::fs::write(&damaged, &bytes).unwrap();
    let out = acags()
        .args(["eval", "--bitstream"])
        .arg(&damaged)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("damaged.acags") && stderr.contains("checksum"),
        "{stderr}"
    );

    // Clear errors: an existing run without --resume, a frame range outside the GOP.
    let out = acags()
        .args(["train", "--quiet", "--out"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--resume"));
    let out = acags()
        .args(["render", "--camera", "0", "--frames", "30..50", "--run"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("outside the trained GOP"));
}
