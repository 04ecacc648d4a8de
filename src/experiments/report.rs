//! `acags report --sweep DIR`: `DIR/report.md` with one table per scene and the grid's charts
//! (`DIR/charts/*.png|svg`), from the cells' own `metrics.json`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::io::charts::{Chart, Series, write_chart};
use super::grid::ChartSpec;
use super::manifest::SweepManifest;
use super::results::{CellStatus, ResultRow, label, read_rows};

pub const REPORT_FILE: &str = "report.md";
pub const CHARTS_DIR: &str = "charts";

/// Table columns: metric, header, decimals.
const TABLE: &[(&str, &str, usize)] = &[
    ("psnr", "PSNR", 2),
    ("ssim", "SSIM", 3),
    ("anchors", "anchors", 0),
    ("active_slots", "Gaussians", 0),
    ("gaussians", "G/view", 0),
    ("masking_ratio", "mask", 2),
    ("uncompressed_mib", "MiB", 2),
    ("file_mib", "file MiB", 3),
    ("ratio", "ratio", 1),
    ("compressed_psnr", "decoded PSNR", 2),
    ("shipped_lpips_alex", "LPIPS-Alex", 4),
    ("shipped_lpips_vgg", "LPIPS-VGG", 4),
    ("shipped_dynamic_psnr", "dynamic PSNR", 2),
    ("shipped_static_psnr", "static PSNR", 2),
    ("max_dynamic_gap", "worst-frame gap", 2),
    ("shipped_fps", "FPS", 1),
    ("train_seconds", "train s", 0),
    ("nan_steps", "NaN steps", 0),
];

/// Charts a grid gets when it names none: quality (PSNR on the full frame and the moving pixels,
/// LPIPS-Alex) against size, speed and training time.
pub fn default_charts() -> Vec<ChartSpec> {
    let chart = |name: &str, title: &str, x: &str| ChartSpec {
        name: name.into(),
        title: title.into(),
        x: x.into(),
        y: "shipped_psnr".into(),
        log_x: false,
    };
    vec![
        chart("psnr_vs_size", "Rate-distortion: PSNR vs size", "shipped_mib"),
        ChartSpec {
            y: "shipped_dynamic_psnr".into(),
            ..chart(
                "dynamic_psnr_vs_size",
                "Rate-distortion on the moving pixels: dynamic-region PSNR vs size",
                "shipped_mib",
            )
        },
        ChartSpec {
            y: "shipped_lpips_alex".into(),
            ..chart(
                "lpips_vs_size",
                "Rate-distortion: LPIPS-Alex vs size (lower is better)",
                "shipped_mib",
            )
        },
        chart("psnr_vs_fps", "PSNR vs render speed", "shipped_fps"),
        chart("psnr_vs_train_time", "PSNR vs training time", "train_seconds"),
    ]
}

/// Every chart of the shipped PSNR also drawn for the dynamic-region PSNR (`NAME_dynamic`), unless
/// the list already has that chart: full-frame quality hides a dropped moving object.
pub fn with_dynamic_twins(specs: Vec<ChartSpec>) -> Vec<ChartSpec> {
    let mut out = specs.clone();
    for spec in specs.iter().filter(|s| s.y == "shipped_psnr") {
        let covered = specs
            .iter()
            .any(|o| o.y == "shipped_dynamic_psnr" && o.x == spec.x);
        if !covered {
            out.push(ChartSpec {
                name: format!("{}_dynamic", spec.name),
                title: format!("{} (moving pixels)", spec.title),
                y: "shipped_dynamic_psnr".into(),
                ..spec.clone()
            });
        }
    }
    out
}

/// `acags report --sweep DIR`.
pub fn report(sweep_dir: &Path) -> Result<PathBuf> {
    let manifest = SweepManifest::read(sweep_dir)?;
    let rows = read_rows(sweep_dir, &manifest)?;
    super::results::write_csv(&sweep_dir.join(super::results::RESULTS_FILE), &rows)?;
    write_report(sweep_dir, &manifest, &rows)
}

/// The chart of one spec: one series per (series, scene), finished cells only.
pub fn chart_of(spec: &ChartSpec, rows: &[ResultRow]) -> Chart {
    let scenes: Vec<&str> = unique(rows.iter().map(|r| r.cell.scene.as_str()));
    let mut series: Vec<Series> = Vec::new();
    for row in rows.iter().filter(|r| r.status == CellStatus::Done) {
        let name = if scenes.len() > 1 {
            format!("{} · {}", row.cell.series, row.cell.scene)
        } else {
            row.cell.series.clone()
        };
        let (Some(x), Some(y)) = (row.value(&spec.x), row.value(&spec.y)) else {
            continue;
        };
        match series.iter_mut().find(|s| s.name == name) {
            Some(s) => s.points.push((x, y)),
            None => series.push(Series {
                name,
                points: vec![(x, y)],
                whiskers: Vec::new(),
            }),
        }
    }
    Chart {
        title: spec.title.clone(),
        x_label: label(&spec.x),
        y_label: label(&spec.y),
        log_x: spec.log_x,
        x_categories: None,
        connect: true,
        reference: None,
        series,
    }
}

fn unique<'a>(items: impl Iterator<Item = &'a str>) -> Vec<&'a str> {
    let mut out: Vec<&str> = Vec::new();
    for i in items {
        if !out.contains(&i) {
            out.push(i);
        }
    }
    out
}

/// A metric cell of the table.
fn cell_text(row: &ResultRow, column: &str, decimals: usize) -> String {
    match row.value(column) {
        Some(v) if column == "masking_ratio" => format!("{:.0} %", 100.0 * v),
        Some(v) => format!("{v:.decimals$}"),
        None => "–".into(),
    }
}

/// The markdown table of some rows (parameters first, then the metrics).
pub fn table(rows: &[&ResultRow]) -> String {
    let params: Vec<&str> = unique(
        rows.iter()
            .flat_map(|r| r.cell.params.iter().map(|(k, _)| k.as_str())),
    );
    let mut out = String::from("| cell |");
    for p in &params {
        let _ = write!(out, " `{p}` |");
    }
    for (_, header, _) in TABLE {
        let _ = write!(out, " {header} |");
    }
    out.push_str(" status |\n|---|");
    for _ in 0..params.len() + TABLE.len() {
        out.push_str("---|");
    }
    out.push_str("---|\n");
    for row in rows {
        let _ = write!(out, "| {} |", row.cell.name);
        for p in &params {
            let v = row
                .cell
                .params
                .iter()
                .find(|(k, _)| k == p)
                .map_or("", |(_, v)| v.as_str());
            let _ = write!(out, " {v} |");
        }
        for (column, _, decimals) in TABLE {
            let _ = write!(out, " {} |", cell_text(row, column, *decimals));
        }
        let _ = writeln!(out, " {} |", row.status.name());
    }
    out
}

/// Writes `report.md` and its charts; returns the report's path.
pub fn write_report(sweep_dir: &Path, manifest: &SweepManifest, rows: &[ResultRow]) -> Result<PathBuf> {
    let mut md = String::new();
    let title = if manifest.description.is_empty() {
        manifest.grid.clone()
    } else {
        manifest.description.clone()
    };
    let _ = writeln!(md, "# {title}\n");
    let count = |s: &str| rows.iter().filter(|r| r.status.name() == s).count();
    let _ = writeln!(
        md,
        "Grid `{}`, preset `{}`{}. {} cells: {} done, {} failed, {} pending.\n",
        manifest.grid,
        manifest.preset,
        if manifest.preset_description.is_empty() {
            String::new()
        } else {
            format!(" ({})", manifest.preset_description)
        },
        rows.len(),
        count("done"),
        count("failed"),
        count("pending")
    );
    let _ = writeln!(
        md,
        "Run or resume: `{}`; this report: `acags report --sweep {}`. Every cell is a run \
         directory (`config.toml`, `metrics.json`, `train_log.csv`, `renders/`); all values are in \
         `results.csv`. PSNR/SSIM are the full-precision model's; *file MiB*, *ratio* and \
         *decoded PSNR* are its `scene.acags` (runs trained with the compression simulation); \
         *FPS* is the shipped model's (the decoded file when there is one). *Dynamic* and \
         *static PSNR* are the shipped model's on the moving and the still pixels of the test \
         images (motion mask from the ground truth: departure from the camera's temporal median, \
         dilated); *worst-frame gap* is the largest static − dynamic PSNR difference of a frame: \
         a model that drops a moving object shows it there, not in the full-frame PSNR.\n",
        manifest.command,
        sweep_dir.display()
    );
    for scene in unique(rows.iter().map(|r| r.cell.scene.as_str())) {
        let scene_rows: Vec<&ResultRow> = rows.iter().filter(|r| r.cell.scene == scene).collect();
        let _ = writeln!(md, "## Scene `{scene}`\n");
        md.push_str(&table(&scene_rows));
        md.push('\n');
    }
    let failed: Vec<&ResultRow> = rows
        .iter()
        .filter(|r| matches!(r.status, CellStatus::Failed(_)))
        .collect();
    if !failed.is_empty() {
        md.push_str("## Failed cells\n\n");
        for r in failed {
            if let CellStatus::Failed(e) = &r.status {
                let _ = writeln!(md, "- {} / {}: {}", r.cell.scene, r.cell.name, e);
            }
        }
        md.push('\n');
    }
    let specs = with_dynamic_twins(if manifest.charts.is_empty() {
        default_charts()
    } else {
        manifest.charts.clone()
    });
    md.push_str("## Charts\n\n");
    for spec in &specs {
        let chart = chart_of(spec, rows);
        write_chart(&chart, &sweep_dir.join(CHARTS_DIR).join(&spec.name))?;
        let _ = writeln!(
            md,
            "![{}]({CHARTS_DIR}/{}.png)\n\n([SVG]({CHARTS_DIR}/{}.svg))\n",
            spec.title, spec.name, spec.name
        );
    }
    let path = sweep_dir.join(REPORT_FILE);
    std::fs::write(&path, md).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}
