//! Experiments: sweep grids expand into the right cells with overrides in the documented order;
//! `acags sweep` runs a grid end to end, writes results.csv / report.md / charts from the cells'
//! metrics, resumes after a kill, skips finished cells, records failed ones and carries on;
//! the non-finite guard skips, logs and stops; the stability scenes are what they claim; and
//! the stability suite passes on its CI preset.

mod common;
use common::TempDir;
use std::path::{Path, PathBuf};
use std::process::Command;

use acags::data::synthetic::{
    FAST_SPHERE_RADIUS, SyntheticPreset, fast_sphere_center, points, render, rig,
};
use acags::io::charts::format_number;
use acags::experiments::grid::{Grid, Preset};
use acags::experiments::manifest::SweepManifest;
use acags::experiments::results::{COLUMNS, read_rows};
use acags::train::config::{CardinalityMode, CompressionMode};

fn acags() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_acags"));
    c.env("ACAGS_CACHE_DIR", cache_dir());
    c
}

/// One generated scene set shared by every test of this binary (generation is atomic).
fn cache_dir() -> PathBuf {
    std::env::temp_dir().join("acags-test-cache")
}

fn temp_dir(tag: &str) -> TempDir {
    TempDir::new(&format!("acags-test-{tag}"))
}

fn grid(text: &str) -> Grid {
    Grid::parse(text, "test.toml", PathBuf::from("configs/sweeps")).unwrap()
}

#[test]
fn grids_expand_cells_axes_and_one_at_a_time_variations() {
    let g = grid(
        r#"
        scenes = ["synthetic:fast", { name = "four", dataset = "synthetic:slow", set = ["data.frames=7"] }]
        config = "../aca-gs.toml"
        set = ["train.max_steps=900"]
        [[cells]]
        name = "base"
        [[cells]]
        name = "fixed"
        series = "Fixed"
        set = ["aac.mode=fixed", "train.max_steps=800"]
        [axes]
        "compression.mode" = ["off", "simulate"]
        [vary]
        "aafm.threshold" = [0.1]
        [presets.short]
        set = ["train.max_steps=50", "data.frames=3"]
        "#,
    );
    let cells = g.cells(&g.preset("full").unwrap()).unwrap();
    // 2 scenes × 2 cells × (2 axis values × (1 + 1 variation)).
    assert_eq!(cells.len(), 16);
    let c = &cells[0];
    assert_eq!((c.scene.as_str(), c.name.as_str()), ("fast", "base mode=off"));
    assert_eq!(c.dir, Path::new("fast").join("base_mode=off"));
    assert_eq!(c.series, "base");
    assert_eq!(c.config.compression.mode, CompressionMode::Off);
    assert_eq!(c.config.train.max_steps, 900);
    assert_eq!(c.config.aac.mode, CardinalityMode::Adaptive, "the base is aca-gs.toml");
    let v = &cells[1];
    assert_eq!(v.name, "base mode=off threshold=0.1");
    assert_eq!(
        v.params,
        vec![
            ("compression.mode".to_string(), "off".to_string()),
            ("aafm.threshold".to_string(), "0.1".to_string())
        ]
    );
    assert_eq!(v.config.aafm.threshold, 0.1);
    assert_eq!(cells[2].config.compression.mode, CompressionMode::Simulate);
    // Cell overrides come after the grid's.
    let fixed = cells.iter().find(|c| c.name == "fixed mode=off").unwrap();
    assert_eq!(fixed.series, "Fixed");
    assert_eq!(fixed.config.aac.mode, CardinalityMode::Fixed);
    assert_eq!(fixed.config.train.max_steps, 800);
    // The scene's overrides and dataset.
    let four = cells.iter().find(|c| c.scene == "four").unwrap();
    assert_eq!(four.config.data.dataset, "synthetic:slow");
    assert_eq!(four.config.data.frames, Some(7));
    // A preset overrides cells, but not the scene's own overrides.
    let short = g.cells(&g.preset("short").unwrap()).unwrap();
    assert!(short.iter().all(|c| c.config.train.max_steps == 50));
    assert_eq!(short[0].config.data.frames, Some(3));
    let four = short.iter().find(|c| c.scene == "four").unwrap();
    assert_eq!(four.config.data.frames, Some(7));
}

#[test]
fn grid_errors_name_the_grid_the_cell_and_the_problem() {
    let err = |text: &str| -> String {
        match Grid::parse(text, "bad.toml", PathBuf::from("configs/sweeps"))
            .and_then(|g| g.cells(&Preset::default()))
        {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => format!("{e:#}"),
        }
    };
    let e = err("[[cells]]\nname = \"a\"\nset = [\"aafm.no_such_key=1\"]");
    assert!(e.contains("bad.toml") && e.contains("cell `a`") && e.contains("no_such_key"), "{e}");
    let e = err("[[cells]]\nname = \"a\"\n[[cells]]\nname = \"a\"");
    assert!(e.contains("two [[cells]] are named `a`"), "{e}");
    let e = err("[[cells]]\nname = \"a b\"\n[[cells]]\nname = \"a_b\"");
    assert!(e.contains("share the directory"), "{e}");
    let e = err("[axes]\n\"model.slots\" = []");
    assert!(e.contains("`model.slots` has no values"), "{e}");
    let e = err("bogus = 1");
    assert!(e.contains("bad.toml") && e.contains("bogus"), "{e}");
    let e = err("config = \"no/such.toml\"");
    assert!(e.contains("no/such.toml"), "{e}");
    let e = err("config = \"builtin:nope\"");
    assert!(e.contains("builtin:nope"), "{e}");
    let g = grid("[presets.mine]\nset = []");
    let e = format!("{:#}", g.preset("nope").unwrap_err());
    assert!(e.contains("no preset `nope`") && e.contains("mine") && e.contains("reduced"), "{e}");
}

#[test]
fn every_shipped_grid_resolves_under_every_preset() {
    let dir = common::crate_path("configs/sweeps");
    let mut grids = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if name == "presets.toml" {
            continue;
        }
        let g = Grid::read(&path).unwrap();
        for preset in ["full", "reduced", "ci"] {
            let cells = g
                .cells(&g.preset(preset).unwrap())
                .unwrap_or_else(|e| panic!("{name} / {preset}: {e:#}"));
            assert!(!cells.is_empty(), "{name}");
            if preset == "ci" {
                assert!(cells.iter().all(|c| c.config.train.max_steps <= 80), "{name}");
            }
        }
        grids += 1;
    }
    assert_eq!(grids, 7, "module ablation, λ_M, cardinality, feature split, sensitivity, RD, stability");
    // The paper's rows: Table 3 is 3 methods × with/without compression, Table 6 brackets 8e-3.
    let t3 = Grid::read(&dir.join("module_ablation.toml")).unwrap();
    let cells = t3.cells(&Preset::default()).unwrap();
    assert_eq!(cells.len(), 6);
    assert_eq!(
        cells.iter().filter(|c| c.config.compression.mode == CompressionMode::Off).count(),
        3
    );
    let t6 = Grid::read(&dir.join("mask_weight.toml")).unwrap();
    let weights: Vec<f32> = t6
        .cells(&Preset::default())
        .unwrap()
        .iter()
        .map(|c| c.config.aafm.mask_weight)
        .collect();
    assert!(weights.contains(&0.003) && weights.contains(&0.008) && weights.contains(&0.03));
    // The embedded stability grid is the file.
    let embedded = acags::experiments::stability::stability_grid().unwrap();
    assert_eq!(embedded.text, std::fs::read_to_string(dir.join("stability.toml")).unwrap());
}

#[test]
fn tick_labels_are_short() {
    assert_eq!(format_number(0.0), "0");
    assert_eq!(format_number(27.194), "27.2");
    assert_eq!(format_number(0.5), "0.5");
    assert_eq!(format_number(0.008), "8e-3");
    assert_eq!(format_number(1500.0), "1500");
}

#[test]
fn stability_scenes_are_what_they_claim() {
    // Leaving: at the end the sphere is far from every point of frame 0's cloud (nothing
    // there to grow anchors from); in `fast` it rolls along the floor it started on.
    let spec = SyntheticPreset::Leaving.spec();
    let cloud = points(&spec, &rig(&spec));
    let end = fast_sphere_center(&spec, 1.0);
    let nearest = cloud
        .positions
        .iter()
        .map(|p| (glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) - end).length())
        .fold(f64::INFINITY, f64::min);
    assert!(nearest > FAST_SPHERE_RADIUS + 0.5, "nearest cloud point {nearest}");
    assert!(
        (end - fast_sphere_center(&spec, 0.0)).y < -2.0,
        "flies up (y is down)"
    );
    // Large motion: more than the sphere's radius per frame on average.
    let spec = SyntheticPreset::LargeMotion.spec();
    let travel = (fast_sphere_center(&spec, 1.0) - fast_sphere_center(&spec, 0.0)).length();
    assert!(travel / (spec.frames - 1) as f64 > FAST_SPHERE_RADIUS / 2.0);
    let fast = SyntheticPreset::Fast.spec();
    assert!(travel > 1.5 * (fast_sphere_center(&fast, 1.0) - fast_sphere_center(&fast, 0.0)).length());
    // Long GOP: 3× the frames of `fast`, same motion.
    let long = SyntheticPreset::LongGop.spec();
    assert_eq!(long.frames, 3 * fast.frames);
    assert_eq!(fast_sphere_center(&long, 0.7), fast_sphere_center(&fast, 0.7));
    // Lighting: the last frame is much darker than the first (dimmed to 40 %, ambient too, and the
    // swing shades more of the view: measured 0.32); `fast` keeps its brightness.
    let mean = |spec: &acags::data::synthetic::SyntheticSpec, t: f64| {
        let camera = rig(spec)[1].clone();
        let img = render(spec, &camera, t);
        img.pixels().map(|p| p.0.iter().map(|&v| v as f64).sum::<f64>()).sum::<f64>()
            / (img.width() * img.height() * 3) as f64
    };
    let light = SyntheticPreset::Lighting.spec();
    let ratio = mean(&light, 1.0) / mean(&light, 0.0);
    assert!((0.2..0.45).contains(&ratio), "brightness ratio {ratio}");
    let ratio = mean(&fast, 1.0) / mean(&fast, 0.0);
    assert!((0.9..1.1).contains(&ratio), "fast brightness ratio {ratio}");
    // The everyday presets are unchanged by the new knobs (cached scenes stay valid).
    assert_eq!(fast.light_dimming, 0.0);
    assert_eq!(fast.light_swing_degrees, 0.0);
}

#[test]
fn a_run_that_drops_the_moving_object_is_collapsed() {
    use acags::experiments::stability::collapse_reason;
    let (floor, limit) = (22.0, 10.0);
    // The case that was called stable: fine full frame, the object gone at frame 21.
    let dropped = collapse_reason(Some(27.2), Some(23.0), Some((21, 20.5)), floor, limit);
    assert!(dropped.unwrap().contains("frame 21"));
    assert_eq!(collapse_reason(Some(27.2), Some(25.0), Some((3, 9.0)), floor, limit), None);
    // The moving pixels below the floor, or the full image.
    assert!(collapse_reason(Some(27.2), Some(15.7), Some((3, 9.0)), floor, limit)
        .unwrap()
        .contains("dynamic-region"));
    assert!(collapse_reason(Some(20.0), Some(25.0), None, floor, limit).is_some());
    assert!(collapse_reason(Some(f64::NAN), None, None, floor, limit).is_some());
    // A scene without moving pixels is judged on the full image alone.
    assert_eq!(collapse_reason(Some(25.0), None, None, floor, limit), None);
}

fn assert_success(out: &std::process::Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A grid of two tiny cells on synthetic:fast at 80×60 and 4 frames.
const TINY_GRID: &str = r#"
description = "tiny"
scenes = ["synthetic:fast"]
set = [
    "data.downscale=4", "data.frames=4", "train.max_steps=60", "train.checkpoint_every=5",
    "train.log_every=1", "densify.start=6", "densify.every=6", "densify.stop=40",
    "densify.grad_threshold=0.00005",
]
[[cells]]
name = "baseline"
series = "GIFStream"
[[cells]]
name = "other seed"
series = "GIFStream seed 7"
set = ["train.seed=7", "train.max_steps=12", "train.checkpoint_every=0"]
[axes]
"compression.mode" = ["off"]
[[charts]]
name = "psnr_vs_size"
title = "PSNR vs size"
x = "shipped_mib"
y = "shipped_psnr"
"#;

fn sweep_cmd(grid: &Path, out: &Path) -> Command {
    let mut c = acags();
    c.args(["sweep", "--backend", "ndarray", "--quiet", "--grid"])
        .arg(grid)
        .arg("--out")
        .arg(out);
    c
}

fn log_steps(path: &Path) -> Vec<usize> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect()
}

#[test]
fn sweeps_run_end_to_end_resume_after_a_kill_and_skip_finished_cells() {
    let dir = temp_dir("sweep");
    let grid_path = dir.join("tiny.toml");
    std::fs::write(&grid_path, TINY_GRID).unwrap();
    let out = dir.join("sweep");
    let first_cell = out.join("fast").join("baseline_mode=off");

    // Kill the sweep once the first cell has a checkpoint mid-training.
    let mut child = sweep_cmd(&grid_path, &out)
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    while !first_cell.join("checkpoint.safetensors").exists() {
        assert!(started.elapsed().as_secs() < 600, "no checkpoint appeared");
        assert!(child.try_wait().unwrap().is_none(), "sweep ended before it could be killed");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!first_cell.join("metrics.json").exists(), "killed before the cell finished");

    let run = sweep_cmd(&grid_path, &out).output().unwrap();
    assert_success(&run);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("resumed"), "{stderr}");
    // Every step logged exactly once across the kill.
    assert_eq!(log_steps(&first_cell.join("train_log.csv")), (0..60).collect::<Vec<_>>());

    // results.csv: one row per cell, values from the cells' metrics.json.
    let manifest = SweepManifest::read(&out).unwrap();
    assert_eq!(manifest.cells.len(), 2);
    let rows = read_rows(&out, &manifest).unwrap();
    let mut csv = csv::Reader::from_path(out.join("results.csv")).unwrap();
    let header: Vec<String> = csv.headers().unwrap().iter().map(str::to_string).collect();
    for c in COLUMNS {
        assert!(header.contains(&c.name.to_string()), "{}", c.name);
    }
    assert!(header.contains(&"compression.mode".to_string()));
    let records: Vec<csv::StringRecord> = csv.records().map(Result::unwrap).collect();
    assert_eq!(records.len(), 2);
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    for (record, row) in records.iter().zip(&rows) {
        let metrics: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.join(&row.cell.dir).join("metrics.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(&record[col("status")], "done");
        assert_eq!(&record[col("compression.mode")], "off");
        let psnr: f64 = record[col("psnr")].parse().unwrap();
        assert_eq!(psnr, metrics["psnr"].as_f64().unwrap());
        let anchors: f64 = record[col("anchors")].parse().unwrap();
        assert_eq!(anchors, metrics["anchors"].as_f64().unwrap());
        // Uncompressed runs ship the float32 model.
        let shipped: f64 = record[col("shipped_mib")].parse().unwrap();
        assert_eq!(shipped, metrics["uncompressed_mib"].as_f64().unwrap());
        assert_eq!(&record[col("file_mib")], "");
    }
    assert_eq!(&records[1][col("step")], "12");
    // The report: a table row per cell, the chart as PNG and SVG.
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("| baseline mode=off |") && report.contains("| other seed mode=off |"));
    assert!(report.contains("charts/psnr_vs_size.png"));
    let png = image::open(out.join("charts/psnr_vs_size.png")).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (880, 560));
    let coloured = png.pixels().filter(|p| {
        let [r, g, b] = p.0;
        r.max(g).max(b) as i32 - r.min(g).min(b) as i32 > 60
    });
    assert!(coloured.count() > 50, "the series are drawn in colour");
    let svg = std::fs::read_to_string(out.join("charts/psnr_vs_size.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("GIFStream seed 7"));

    // A re-run trains nothing.
    let before = std::fs::metadata(first_cell.join("metrics.json")).unwrap().modified().unwrap();
    let again = sweep_cmd(&grid_path, &out).output().unwrap();
    assert_success(&again);
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert_eq!(stderr.matches("done before, skipped").count(), 2, "{stderr}");
    let after = std::fs::metadata(first_cell.join("metrics.json")).unwrap().modified().unwrap();
    assert_eq!(before, after);
    // `report` rewrites the report from the cells.
    std::fs::remove_file(out.join("report.md")).unwrap();
    let r = acags().args(["report", "--sweep"]).arg(&out).output().unwrap();
    assert_success(&r);
    assert!(out.join("report.md").exists());

    // The same directory with an edited grid is refused before anything trains.
    std::fs::write(&grid_path, TINY_GRID.replace("train.seed=7", "train.seed=8")).unwrap();
    let edited = sweep_cmd(&grid_path, &out).output().unwrap();
    assert!(!edited.status.success());
    let stderr = String::from_utf8_lossy(&edited.stderr);
    assert!(stderr.contains("other seed") && stderr.contains("config.toml"), "{stderr}");
}

#[test]
fn a_failed_cell_is_recorded_and_the_sweep_goes_on() {
    let dir = temp_dir("sweep-fail");
    let grid_path = dir.join("fail.toml");
    std::fs::write(
        &grid_path,
        r#"
        scenes = ["synthetic:fast"]
        set = ["data.downscale=4", "data.frames=4", "train.max_steps=10",
               "train.checkpoint_every=0", "compression.mode=off"]
        [[cells]]
        name = "diverges"
        set = ["train.inject_nonfinite=[2, 3, 4, 5, 6]"]
        [[cells]]
        name = "fine"
        "#,
    )
    .unwrap();
    let out = dir.join("sweep");
    let run = sweep_cmd(&grid_path, &out).output().unwrap();
    assert!(!run.status.success(), "a failed cell fails the sweep");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("1 of 2 cells failed"), "{stderr}");
    assert!(out.join("fast/fine/metrics.json").exists(), "the next cell still trained");
    let failed: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("fast/diverges/failed.json")).unwrap(),
    )
    .unwrap();
    let error = failed["error"].as_str().unwrap();
    assert!(error.contains("not finite for 5 consecutive steps (last at step 6)"), "{error}");
    let results = std::fs::read_to_string(out.join("results.csv")).unwrap();
    assert!(results.contains("diverges,diverges,failed,"), "{results}");
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("## Failed cells") && report.contains("consecutive"));
    // Failed cells are skipped on a re-run unless asked.
    let again = sweep_cmd(&grid_path, &out).output().unwrap();
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(stderr.contains("failed before"), "{stderr}");
}

#[test]
fn non_finite_steps_are_skipped_logged_and_counted() {
    let dir = temp_dir("nan-guard");
    let run = dir.join("run");
    let out = acags()
        .args(["train", "--backend", "ndarray", "--quiet", "--out"])
        .arg(&run)
        .args([
            "--set",
            "data.downscale=4",
            "--set",
            "data.frames=4",
            "--set",
            "train.max_steps=12",
            "--set",
            "train.log_every=5",
            "--set",
            "compression.mode=off",
            "--set",
            "train.inject_nonfinite=[3, 7, 8]",
        ])
        .output()
        .unwrap();
    assert_success(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("step 3: non-finite loss, step skipped"), "{stderr}");
    assert!(stderr.contains("3 steps were skipped"), "{stderr}");
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["nan_steps"], 3);
    assert!(metrics["psnr"].as_f64().unwrap().is_finite());
    // Skipped steps get log rows even between log_every rows, flagged in `skipped`.
    let log = std::fs::read_to_string(run.join("train_log.csv")).unwrap();
    let skipped: Vec<usize> = log
        .lines()
        .skip(1)
        .filter(|l| l.split(',').nth(8) == Some("1"))
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(skipped, vec![3, 7, 8]);
}

#[test]
fn the_stability_suite_passes_on_its_ci_preset() {
    let dir = temp_dir("stability");
    let out = dir.join("stability");
    let run = acags()
        .args(["stability", "--preset", "ci", "--backend", "ndarray", "--quiet", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert_success(&run);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stability.json")).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 14, "7 scenes × GIFStream, ACA-GS");
    let floor = report["floor_db"].as_f64().unwrap();
    for r in rows {
        let verdict = r["verdict"].as_str().unwrap();
        let psnr = r["psnr"].as_f64().unwrap();
        assert!(psnr >= floor, "{r}");
        // Worst and best frame are of the same (shipped) model as the PSNR: every frame has the
        // same test cameras, so the mean lies between them.
        let worst = r["worst_frame"][1].as_f64().unwrap();
        let best = r["best_frame"][1].as_f64().unwrap();
        assert!(worst <= psnr + 1e-9 && psnr <= best + 1e-9, "{r}");
        if r["scene"] == "nan-injection" {
            assert_eq!(verdict, "recovered", "{r}");
            assert_eq!(r["nan_steps"], 4, "{r}");
        } else {
            assert_eq!(verdict, "stable", "{r}");
            assert_eq!(r["nan_steps"], 0, "{r}");
        }
        // Every run shipped a decoded scene.acags (both configs train with compression).
        assert!(r["size_mib"].as_f64().unwrap() < 5.0, "{r}");
    }
    let md = std::fs::read_to_string(out.join("stability.md")).unwrap();
    assert!(md.contains("| long-gop | ACA-GS | stable |"), "{md}");
    // Every scene has moving pixels, and the verdict saw them.
    for r in rows {
        let dynamic = r["dynamic_psnr"].as_f64().unwrap();
        assert!(dynamic >= floor, "{r}");
        assert!(r["max_dynamic_gap"][1].as_f64().unwrap() <= report["gap_limit_db"].as_f64().unwrap(), "{r}");
    }
    assert!(md.contains("| crossing | GIFStream | stable |"), "{md}");
    let png = image::open(out.join("charts/stability_psnr.png")).unwrap();
    assert_eq!(png.width(), 880);
}

/// The acceptance run of the paper's grids: module ablation (Table 3) and λ_M (Table 6) end to
/// end with the `ci` preset, results and charts included.
#[test]
fn the_shipped_ablation_and_mask_weight_grids_run_on_the_ci_preset() {
    let dir = temp_dir("shipped-grids");
    let grids = common::crate_path("configs/sweeps");
    let run = |grid: &str| -> (PathBuf, Vec<acags::experiments::results::ResultRow>) {
        let out = dir.join(grid);
        let mut c = sweep_cmd(&grids.join(format!("{grid}.toml")), &out);
        assert_success(&c.args(["--preset", "ci"]).output().unwrap());
        let manifest = SweepManifest::read(&out).unwrap();
        let rows = read_rows(&out, &manifest).unwrap();
        for r in &rows {
            assert_eq!(r.status.name(), "done", "{}", r.cell.name);
            assert!(r.value("shipped_psnr").unwrap() > 14.0, "{}", r.cell.name);
        }
        assert!(out.join("report.md").exists() && out.join("results.csv").exists());
        (out, rows)
    };

    let (out, rows) = run("module_ablation");
    assert_eq!(rows.len(), 6);
    for chart in ["psnr_vs_size", "psnr_vs_fps", "psnr_vs_train_time"] {
        assert!(out.join("charts").join(format!("{chart}.png")).exists(), "{chart}");
        assert!(out.join("charts").join(format!("{chart}.svg")).exists(), "{chart}");
    }
    // Every method ships a scene.acags far smaller than its float32 model when compressed.
    for series in ["GIFStream", "+AAC", "+AAC+AAFM (ACA-GS)"] {
        let size = |mode: &str| {
            rows.iter()
                .find(|r| r.cell.series == series && r.cell.name.ends_with(&format!("mode={mode}")))
                .and_then(|r| r.value("shipped_mib"))
                .unwrap()
        };
        assert!(size("simulate") * 5.0 < size("off"), "{series}");
    }

    let (out, rows) = run("mask_weight");
    assert_eq!(rows.len(), 5);
    assert!(out.join("charts/mask_ratio_vs_lambda.png").exists());
    // More mask pressure never masks fewer channels.
    let mut ratios: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| (r.value("aafm.mask_weight").unwrap(), r.value("masking_ratio").unwrap()))
        .collect();
    ratios.sort_by(|a, b| a.0.total_cmp(&b.0));
    assert!(ratios.windows(2).all(|w| w[0].1 <= w[1].1 + 1e-9), "{ratios:?}");
}
