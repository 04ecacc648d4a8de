//! Configs: `extends` (a config on top of another), the shipped ACA-GS configs differing from
//! their GIFStream baselines only in ACA-GS keys, and `acags config show`.

mod common;
use common::TempDir;

use std::path::{Path, PathBuf};
use std::process::Command;

use acags::train::config::TrainConfig;

fn configs_dir() -> PathBuf {
    common::crate_path("configs")
}

/// Every leaf key of a resolved config, as `section.key` → value.
fn leaves(config: &TrainConfig) -> Vec<(String, toml::Value)> {
    fn walk(prefix: &str, table: &toml::Table, out: &mut Vec<(String, toml::Value)>) {
        for (k, v) in table {
            let key = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match v {
                toml::Value::Table(t) => walk(&key, t, out),
                other => out.push((key, other.clone())),
            }
        }
    }
    let table: toml::Table = toml::from_str(&config.to_toml()).unwrap();
    let mut out = Vec::new();
    walk("", &table, &mut out);
    out
}

/// What an ACA-GS config may change of its baseline: K_max, the C_F split, the AAC and AAFM
/// sections and the AAFM mask's learning rate.
fn is_aca_gs_key(key: &str) -> bool {
    matches!(
        key,
        "model.slots"
            | "model.feature_dim"
            | "model.baseline_feature_dim"
            | "model.baseline_slots"
            | "lr.mask"
            | "lr.mask_final_factor"
    ) || key.starts_with("aac.")
        || key.starts_with("aafm.")
}

/// The keys (outside the ACA-GS ones) whose values differ between two resolved configs.
fn non_aca_gs_differences(baseline: &TrainConfig, aca: &TrainConfig) -> Vec<String> {
    let (a, b) = (leaves(baseline), leaves(aca));
    let mut keys: Vec<&String> = a.iter().chain(&b).map(|(k, _)| k).collect();
    keys.sort();
    keys.dedup();
    let get = |l: &[(String, toml::Value)], k: &str| {
        l.iter().find(|(x, _)| x == k).map(|(_, v)| v.clone())
    };
    keys.into_iter()
        .filter(|k| !is_aca_gs_key(k) && get(&a, k) != get(&b, k))
        .map(|k| format!("{k}: {:?} vs {:?}", get(&a, k), get(&b, k)))
        .collect()
}

#[test]
fn every_shipped_aca_gs_config_differs_from_its_baseline_only_in_aca_gs_keys() {
    let dir = configs_dir();
    let pairs = [
        ("default.toml", "aca-gs.toml"),
        ("mpeg.toml", "mpeg_aca-gs.toml"),
        ("n3dv.toml", "n3dv_aca-gs.toml"),
        ("panoptic.toml", "panoptic_aca-gs.toml"),
    ];
    // Only AAC's schedule follows the dataset's length: the rules are aca-gs.toml's everywhere,
    // so a rule changed in one file (e.g. `target_slot`) cannot miss the others.
    let reference = TrainConfig::load(Some(&dir.join("aca-gs.toml")), &[])
        .unwrap()
        .aac;
    for (base, aca) in pairs {
        let baseline = TrainConfig::load(Some(&dir.join(base)), &[]).unwrap();
        let aca_gs = TrainConfig::load(Some(&dir.join(aca)), &[]).unwrap();
        let diff = non_aca_gs_differences(&baseline, &aca_gs);
        assert!(
            diff.is_empty(),
            "{aca} vs {base} differ outside ACA-GS keys: {diff:#?}"
        );
        // And it is ACA-GS: adaptive cardinality and masking on, K_max above the baseline's K.
        assert_eq!(
            aca_gs.aac.mode,
            acags::train::config::CardinalityMode::Adaptive,
            "{aca}"
        );
        assert_ne!(
            aca_gs.aafm.mode,
            acags::train::config::FeatureMaskMode::Off,
            "{aca}"
        );
        assert!(aca_gs.model.slots > baseline.model.slots, "{aca}");
        // Its decoders are paired with the baseline's: same C_F and K at the same seed.
        assert_eq!(
            aca_gs.model.baseline_decoder_sizes(),
            acags::model::decoders::DecoderSizes {
                feature_dim: baseline.model.feature_dim,
                time_feature_dim: baseline.model.time_feature_dim,
                slots: baseline.model.slots,
            },
            "{aca}: model.baseline_* must be {base}'s C_F and K"
        );
        assert_eq!(
            baseline.model.baseline_decoder_sizes().slots,
            baseline.model.slots,
            "{base}"
        );
        // Every ACA-GS file says which baseline it extends.
        let text = std::fs::read_to_string(dir.join(aca)).unwrap();
        assert!(
            text.contains(&format!("extends = \"{base}\"")),
            "{aca} must extend {base}"
        );
        // And it is the same method on every dataset.
        let rules = acags::train::config::AacConfig {
            start: reference.start,
            stop: reference.stop,
            every: reference.every,
            ..aca_gs.aac.clone()
        };
        assert_eq!(
            rules, reference,
            "{aca}'s AAC rules differ from aca-gs.toml's"
        );
    }
    // The embedded pair (sweeps' builtin:default / builtin:aca-gs) is the shipped files.
    let embedded = |name: &str| TrainConfig::embedded(name, &[]).unwrap();
    for name in ["default.toml", "aca-gs.toml"] {
        let file = TrainConfig::load(Some(&dir.join(name)), &[]).unwrap();
        assert_eq!(embedded(name), file, "{name}");
    }
    // The check itself sees a confounded pair: the feature rate that used to differ.
    let confounded = TrainConfig::load(
        Some(&dir.join("aca-gs.toml")),
        &["lr.features=0.0075".into()],
    )
    .unwrap();
    let baseline = TrainConfig::load(Some(&dir.join("default.toml")), &[]).unwrap();
    let diff = non_aca_gs_differences(&baseline, &confounded);
    assert_eq!(diff.len(), 1, "{diff:?}");
    assert!(diff[0].starts_with("lr.features"), "{diff:?}");
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn extends_merges_section_by_section_and_names_bad_chains() {
    let tmp = TempDir::new("config-extends");
    let dir: &Path = &tmp;
    write(
        dir,
        "base.toml",
        "[train]\nmax_steps = 700\nseed = 3\n[densify]\nstart = 50\n",
    );
    write(
        dir,
        "middle.toml",
        "extends = \"base.toml\"\n[train]\nseed = 4\n",
    );
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    let child = write(
        &dir.join("sub"),
        "child.toml",
        "extends = \"../middle.toml\"\n[densify]\nstop = 90\n",
    );
    let c = TrainConfig::load(Some(&child), &["train.max_steps=800".into()]).unwrap();
    assert_eq!(c.train.max_steps, 800, "--set wins over every file");
    assert_eq!(c.train.seed, 4, "the nearer file wins");
    assert_eq!(
        (c.densify.start, c.densify.stop),
        (50, 90),
        "sections merge key by key"
    );
    // Keys no file sets are the code's defaults, as for a file without `extends`.
    let plain = write(
        dir,
        "plain.toml",
        "[train]\nmax_steps = 800\nseed = 4\n[densify]\nstart = 50\nstop = 90\n",
    );
    assert_eq!(TrainConfig::load(Some(&plain), &[]).unwrap(), c);

    let err = |text: &str| {
        let p = write(dir, "bad.toml", text);
        format!("{:#}", TrainConfig::load(Some(&p), &[]).unwrap_err())
    };
    let e = err("extends = \"missing.toml\"\n");
    assert!(e.contains("bad.toml") && e.contains("missing.toml"), "{e}");
    let e = err("extends = 3\n");
    assert!(e.contains("bad.toml") && e.contains("extends"), "{e}");
    write(dir, "loop_a.toml", "extends = \"loop_b.toml\"\n");
    write(dir, "loop_b.toml", "extends = \"loop_a.toml\"\n");
    let e = format!(
        "{:#}",
        TrainConfig::load(Some(&dir.join("loop_a.toml")), &[]).unwrap_err()
    );
    assert!(e.contains("cycle"), "{e}");
    // A typo in an extended file is still an unknown key.
    write(dir, "typo.toml", "[train]\nmax_stepz = 1\n");
    let e = err("extends = \"typo.toml\"\n");
    assert!(e.contains("max_stepz"), "{e}");
}

#[test]
fn config_show_prints_the_resolved_config() {
    let acags = || Command::new(env!("CARGO_BIN_EXE_acags"));
    let out = acags()
        .args(["config", "show", "--config"])
        .arg(configs_dir().join("aca-gs.toml"))
        .args(["--set", "train.max_steps=123"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(!text.contains("extends"), "resolved: {text}");
    let shown = TrainConfig::parse(&text, "shown.toml", &[]).unwrap();
    let want = TrainConfig::load(
        Some(&configs_dir().join("aca-gs.toml")),
        &["train.max_steps=123".into()],
    )
    .unwrap();
    assert_eq!(shown, want);
    // The baseline's feature rate reaches ACA-GS through `extends`.
    assert_eq!(
        shown.lr.features,
        TrainConfig::load(None, &[]).unwrap().lr.features
    );

    let out = acags()
        .args(["config", "show", "--config", "/nonexistent/x.toml"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/x.toml"));
}

#[test]
fn bench_train_times_dynamic_phase_steps_unless_told() {
    use acags::model::view::Phase;
    for steps in [1600, 300, 30_000] {
        let config = TrainConfig::load(None, &[format!("train.max_steps={steps}")]).unwrap();
        let warmup = acags::bench::default_train_warmup(&config);
        // Steps are numbered from 0, so `warmup` untimed steps make `warmup` the first timed one.
        assert_eq!(
            config.train.phase_at(warmup),
            Phase::Dynamic,
            "{steps} steps"
        );
        assert_eq!(
            config.train.phase_at(warmup - 3),
            Phase::Canonical,
            "{steps} steps"
        );
        assert_eq!(
            config.train.phase_at(warmup - 2),
            Phase::Dynamic,
            "{steps} steps"
        );
    }
}

#[test]
fn knot_consensus_needs_the_knot_search_and_a_positive_cell() {
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        TrainConfig::load(None, &sets).map_err(|e| format!("{e:#}"))
    };
    let on = load(&["train.knot_consensus=\"cells\""]).unwrap();
    assert_eq!(on.train.knot_consensus, acags::config::KnotConsensus::Cells);
    let e = load(&[
        "train.knot_consensus=\"cells\"",
        "train.knot_search=\"off\"",
    ])
    .unwrap_err();
    assert!(
        e.contains("knot_consensus") && e.contains("knot_search"),
        "{e}"
    );
    for radius in ["0.0", "-0.3", "nan"] {
        let e = load(&[&format!("train.knot_consensus_cell={radius}")]).unwrap_err();
        assert!(e.contains("knot_consensus_cell"), "{radius}: {e}");
    }
    let e = load(&["train.knot_consensus=\"all\""]).unwrap_err();
    assert!(e.contains("knot_consensus"), "{e}");
}

#[test]
fn rigid_fit_keys_are_validated() {
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        TrainConfig::load(None, &sets).map_err(|e| format!("{e:#}"))
    };
    let on = load(&["train.rigid_fit=\"objects\"", "train.rigid_fit_link=0.25"]).unwrap();
    assert_eq!(on.train.rigid_fit, acags::config::RigidFit::Objects);
    assert_eq!(on.train.rigid_fit_link, 0.25);
    for link in ["0.0", "-0.1", "nan", "inf"] {
        let e = load(&[&format!("train.rigid_fit_link={link}")]).unwrap_err();
        assert!(e.contains("rigid_fit_link"), "{link}: {e}");
    }
    let e = load(&["train.rigid_fit=\"affine\""]).unwrap_err();
    assert!(e.contains("rigid_fit"), "{e}");
    // The fitted knots: trained by default, held on request, and not without a fit to set them.
    assert_eq!(on.train.fitted_knots, acags::config::FittedKnots::Trained);
    let held = load(&[
        "train.rigid_fit=\"rendered\"",
        "train.fitted_knots=\"held\"",
    ])
    .unwrap();
    assert_eq!(held.train.fitted_knots, acags::config::FittedKnots::Held);
    let e = load(&["train.rigid_fit=\"off\"", "train.fitted_knots=\"held\""]).unwrap_err();
    assert!(e.contains("fitted_knots") && e.contains("rigid_fit"), "{e}");
    let e = load(&["train.fitted_knots=\"frozen\""]).unwrap_err();
    assert!(e.contains("fitted_knots"), "{e}");
    // The knot refit: off by default, at the curriculum's end on request, and refused without a
    // curriculum (it would never run).
    assert_eq!(on.train.knot_refit, acags::config::KnotRefit::Off);
    let refit = load(&["train.knot_refit=\"curriculum-end\""]).unwrap();
    assert_eq!(
        refit.train.knot_refit,
        acags::config::KnotRefit::CurriculumEnd
    );
    let e = load(&[
        "train.knot_refit=\"curriculum-end\"",
        "train.frame_curriculum=0",
    ])
    .unwrap_err();
    assert!(e.contains("knot_refit") && e.contains("frame_curriculum"), "{e}");
    let e = load(&["train.knot_refit=\"always\""]).unwrap_err();
    assert!(e.contains("knot_refit"), "{e}");
    let at = load(&["train.knot_refit=\"at-share\"", "train.knot_refit_share=0.18"]).unwrap();
    assert_eq!(at.train.knot_refit, acags::config::KnotRefit::AtShare);
    assert_eq!(at.train.knot_refit_share, 0.18);
    for share in ["0.0", "1.0", "-0.1", "nan"] {
        let e = load(&[&format!("train.knot_refit_share={share}")]).unwrap_err();
        assert!(e.contains("knot_refit_share"), "{share}: {e}");
    }
    // The refit's stream reset: kept by default, "first-frame" with a refit, refused without
    // one (it would never act) and for an unknown mode.
    use acags::config::KnotRefitStreams;
    assert_eq!(on.train.knot_refit_streams, KnotRefitStreams::Kept);
    let reset = load(&[
        "train.knot_refit=\"curriculum-end\"",
        "train.knot_refit_streams=\"first-frame\"",
    ])
    .unwrap();
    assert_eq!(reset.train.knot_refit_streams, KnotRefitStreams::FirstFrame);
    let e = load(&["train.knot_refit_streams=\"first-frame\""]).unwrap_err();
    assert!(e.contains("knot_refit_streams") && e.contains("knot_refit"), "{e}");
    let e = load(&[
        "train.knot_refit=\"curriculum-end\"",
        "train.knot_refit_streams=\"zero\"",
    ])
    .unwrap_err();
    assert!(e.contains("knot_refit_streams"), "{e}");
    // The rigid fit's grouping: by nearness by default, "kept-distances" with a rigid fit,
    // refused without one (it would never act) and for an unknown mode.
    use acags::config::RigidFitGrouping;
    assert_eq!(on.train.rigid_fit_grouping, RigidFitGrouping::Near);
    let kept = load(&["train.rigid_fit_grouping=\"kept-distances\""]).unwrap();
    assert_eq!(kept.train.rigid_fit_grouping, RigidFitGrouping::KeptDistances);
    let e = load(&[
        "train.rigid_fit=\"off\"",
        "train.rigid_fit_grouping=\"kept-distances\"",
    ])
    .unwrap_err();
    assert!(e.contains("rigid_fit_grouping") && e.contains("rigid_fit"), "{e}");
    let e = load(&["train.rigid_fit_grouping=\"far\""]).unwrap_err();
    assert!(e.contains("rigid_fit_grouping"), "{e}");
}

#[test]
fn seed_hold_modes_parse_and_bad_ones_are_named() {
    use acags::config::SeedHold;
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        TrainConfig::load(None, &sets).map_err(|e| format!("{e:#}"))
    };
    for (text, mode) in [
        ("off", SeedHold::Off),
        ("next-knot", SeedHold::NextKnot),
        ("long-intervals", SeedHold::LongIntervals),
    ] {
        let config = load(&[&format!("train.seed_hold=\"{text}\"")]).unwrap();
        assert_eq!(config.train.seed_hold, mode, "{text}");
    }
    let e = load(&["train.seed_hold=\"always\""]).unwrap_err();
    assert!(e.contains("seed_hold"), "{e}");
}

#[test]
fn motion_gate_keys_are_validated() {
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        TrainConfig::load(None, &sets).map_err(|e| format!("{e:#}"))
    };
    let on = load(&[
        "train.motion_gate_hold=\"curriculum\"",
        "train.frame_curriculum=0.4",
        "train.motion_gate_start=4",
    ])
    .unwrap();
    assert_eq!(
        on.train.motion_gate_hold,
        acags::config::MotionGateHold::Curriculum
    );
    assert_eq!(on.train.motion_gate_start, 4.0);
    let e = load(&[
        "train.motion_gate_hold=\"curriculum\"",
        "train.frame_curriculum=0",
    ])
    .unwrap_err();
    assert!(
        e.contains("motion_gate_hold") && e.contains("frame_curriculum"),
        "{e}"
    );
    for logit in ["nan", "inf"] {
        let e = load(&[&format!("train.motion_gate_start={logit}")]).unwrap_err();
        assert!(e.contains("motion_gate_start"), "{logit}: {e}");
    }
    let e = load(&["train.motion_gate_hold=\"always\""]).unwrap_err();
    assert!(e.contains("motion_gate_hold"), "{e}");
    // moving_gates rides on the knot search: turning the search off is not an error.
    let off = load(&["train.moving_gates=\"open\"", "train.knot_search=\"off\""]).unwrap();
    assert_eq!(off.train.moving_gates, acags::config::MovingGates::Open);
    // init_dynamic would reset the opened gates: refused together, fine apart.
    let e = load(&["train.init_dynamic=\"densify-statistics\""]).unwrap_err();
    assert!(
        e.contains("moving_gates") && e.contains("init_dynamic"),
        "{e}"
    );
    load(&[
        "train.init_dynamic=\"densify-statistics\"",
        "train.moving_gates=\"off\"",
    ])
    .unwrap();
    let e = load(&["train.moving_gate_logit=nan"]).unwrap_err();
    assert!(e.contains("moving_gate_logit"), "{e}");
    let e = load(&["train.moving_gates=\"closed\""]).unwrap_err();
    assert!(e.contains("moving_gates"), "{e}");
}

#[test]
fn step_overrides_replace_single_attributes_and_are_validated() {
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        TrainConfig::load(None, &sets).map_err(|e| format!("{e:#}"))
    };
    let preset = acags::codec::quantization::RatePreset::R0.steps();
    let on = load(&[
        "compression.steps.time_features=0.25",
        "compression.steps.factors=0.0078125",
    ])
    .unwrap();
    let steps = on.compression.quantization_steps();
    assert_eq!(steps.time_features, 0.25);
    assert_eq!(steps.factors, 1.0 / 128.0);
    assert_eq!(steps.features, preset.features);
    assert_eq!(steps.trajectory, preset.trajectory);
    // A coarser preset keeps the absolute override.
    let r2 = on
        .compression
        .steps_for(acags::codec::quantization::RatePreset::R2);
    assert_eq!(r2.time_features, 0.25);
    assert_eq!(r2.offsets, 0.06);
    // The override survives the run directory's config.toml.
    let again = TrainConfig::parse(&on.to_toml(), "config.toml", &[]).unwrap();
    assert_eq!(again.compression.quantization_steps(), steps);
    // Unset, the written config has no [compression.steps] keys and the preset is the grid.
    let plain = load(&[]).unwrap();
    assert_eq!(plain.compression.quantization_steps(), preset);
    for bad in ["0", "-0.5", "nan", "inf"] {
        let e = load(&[&format!("compression.steps.offsets={bad}")]).unwrap_err();
        assert!(e.contains("compression.steps.offsets"), "{bad}: {e}");
    }
    let e = load(&["compression.steps.factors=0.3"]).unwrap_err();
    assert!(e.contains("compression.steps.factors"), "{e}");
    let e = load(&["compression.steps.knots=0.1"]).unwrap_err();
    assert!(e.contains("knots"), "{e}");
}

#[test]
fn a_decoder_baseline_wider_than_the_model_is_refused_by_name() {
    let path = configs_dir().join("aca-gs.toml");
    for key in [
        "model.baseline_slots=11",
        "model.baseline_feature_dim=64",
        "model.baseline_slots=0",
    ] {
        let err = TrainConfig::load(Some(&path), &[key.into()]).unwrap_err();
        assert!(
            format!("{err:#}").contains("model.baseline_"),
            "{key}: {err:#}"
        );
    }
    // The +AAC ablation row (C_F 24, AAFM off) pairs with the same baseline.
    let aac = TrainConfig::load(
        Some(&path),
        &["aafm.mode=\"off\"".into(), "model.feature_dim=24".into()],
    )
    .unwrap();
    assert_eq!(aac.model.baseline_decoder_sizes().feature_dim, 24);
}

#[test]
fn the_feature_rate_under_baseline_step_keeps_the_baselines_update_norm_at_a_wider_width() {
    use acags::model::anchors::Column;
    use acags::train::anchor_state::ColumnRate;
    use acags::train::config::FeatureWidthRate;
    use acags::train::optimizers::StepRates;
    let dir = configs_dir();
    let load = |file: &str, width: &str| {
        let set = vec![format!("lr.feature_width=\"{width}\"")];
        TrainConfig::load(Some(&dir.join(file)), &set).unwrap()
    };
    // What the optimizer steps a column with, at a step of the dynamic phase.
    let rate = |c: &TrainConfig, column: Column| match StepRates::at(c, &dims_of(c), 700, 0).anchors
        [column]
    {
        ColumnRate::Uniform(r) => r,
        ref other => panic!("{} at {other:?}", column.name()),
    };
    let feature_rate = |c: &TrainConfig| rate(c, Column::Features);
    for width in ["per-channel", "baseline-step"] {
        let gif = load("default.toml", width);
        // GIFStream is its own baseline: the factor is exactly 1 (its trace cannot move).
        assert_eq!(feature_rate(&gif), gif.lr.features, "{width}");
        let aca = load("aca-gs.toml", width);
        assert_eq!(aca.lr.features, gif.lr.features, "one shared key");
        let parsed = if width == "per-channel" {
            FeatureWidthRate::PerChannel
        } else {
            FeatureWidthRate::BaselineStep
        };
        assert_eq!(aca.lr.feature_width, parsed);
        let want = match aca.lr.feature_width {
            FeatureWidthRate::PerChannel => aca.lr.features,
            // C_F 48 over the paired baseline's 24.
            FeatureWidthRate::BaselineStep => aca.lr.features * 0.5f64.sqrt(),
        };
        assert!((feature_rate(&aca) - want).abs() < 1e-15, "{width}");
        // The feature stream's C_T is shared: its rate never scales.
        assert_eq!(rate(&aca, Column::TimeFeatures), aca.lr.time_features);
    }
    let err = TrainConfig::load(None, &["lr.feature_width=\"per-width\"".to_string()]).unwrap_err();
    assert!(format!("{err:#}").contains("feature_width"), "{err:#}");
}

fn dims_of(c: &TrainConfig) -> acags::model::anchors::AnchorDims {
    acags::model::anchors::AnchorDims {
        slots: c.model.slots,
        initial_active_slots: c.model.slots,
        feature_masking: acags::model::anchors::FeatureMasking::Off,
        frames: 4,
        feature_dim: c.model.feature_dim,
        time_feature_dim: c.model.time_feature_dim,
        knn: 0,
        // No knots: their rates are not what this checks.
        trajectory_spacing: 0,
        trajectory_turn: acags::model::anchors::TrajectoryTurn::Off,
    }
}
