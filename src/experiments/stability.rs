//! `acags stability`: GIFStream and ACA-GS on scenes built to break methods (the embedded grid
//! `configs/sweeps/stability.toml`): fast large motion, motion leaving the initial point cloud,
//! four training cameras, a strong lighting change, a long GOP, and injected non-finite losses.
//! Per run: quality, worst frame, non-finite steps, and a verdict against the collapse floor;
//! `stability.md` and a chart beside the sweep's own report.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Serialize;

use super::charts::{Chart, Series, write_chart};
use super::grid::Grid;
use super::report::CHARTS_DIR;
use super::results::{CellStatus, ResultRow};
use super::sweep::{GridRunOptions, run_grid};

/// The suite's grid, embedded so `acags stability` runs from anywhere.
pub const STABILITY_GRID: &str = include_str!("../../configs/sweeps/stability.toml");
pub const STABILITY_REPORT_FILE: &str = "stability.md";
pub const STABILITY_JSON_FILE: &str = "stability.json";

/// Options of `acags stability`.
#[derive(Clone, Debug, clap::Args)]
pub struct StabilityOptions {
    /// Output directory (default runs/stability-PRESET).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// `full` (the 1600-step schedule), `reduced` or `ci`.
    #[arg(long, default_value = "reduced")]
    pub preset: String,
    #[command(flatten)]
    pub run: GridRunOptions,
}

/// How one run fared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Above the floor, no non-finite step.
    Stable,
    /// Non-finite steps were skipped and the run still ended above the floor.
    Recovered,
    /// Finished below the floor (or with non-finite metrics).
    Collapsed,
    /// Training stopped with an error (e.g. repeated non-finite losses).
    Failed,
    /// Not trained (yet).
    Pending,
}

/// One row of the stability table.
#[derive(Clone, Debug, Serialize)]
pub struct StabilityRow {
    pub scene: String,
    pub method: String,
    pub verdict: Verdict,
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// Lowest per-frame PSNR (mean over test cameras) and the frame.
    pub worst_frame: Option<(usize, f64)>,
    pub best_frame: Option<(usize, f64)>,
    pub nan_steps: Option<usize>,
    pub size_mib: Option<f64>,
    pub error: Option<String>,
}

/// The suite's result.
#[derive(Clone, Debug, Serialize)]
pub struct StabilityReport {
    pub dir: PathBuf,
    pub preset: String,
    pub floor_db: f64,
    pub rows: Vec<StabilityRow>,
}

impl StabilityReport {
    /// Runs that did not end stable or recovered.
    pub fn broken(&self) -> Vec<&StabilityRow> {
        self.rows
            .iter()
            .filter(|r| !matches!(r.verdict, Verdict::Stable | Verdict::Recovered))
            .collect()
    }
}

pub fn stability_grid() -> Result<Grid> {
    Grid::parse(
        STABILITY_GRID,
        "configs/sweeps/stability.toml (embedded)",
        PathBuf::from("configs/sweeps"),
    )
}

/// `acags stability`.
pub fn stability(options: &StabilityOptions) -> Result<StabilityReport> {
    let grid = stability_grid()?;
    let out = options
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs").join(format!("stability-{}", options.preset)));
    let command = format!(
        "acags stability --preset {} --out {}",
        options.preset,
        out.display()
    );
    let outcome = run_grid(&grid, &options.preset, &out, &options.run, command)?;
    let floor = outcome
        .manifest
        .collapse_floor_db
        .context("the stability grid names no collapse_floor_db")?;
    let report = assess(&outcome.dir, &options.preset, floor, &outcome.rows);
    write_stability_report(&report)?;
    Ok(report)
}

/// The verdict of every row against `floor_db`.
pub fn assess(dir: &Path, preset: &str, floor_db: f64, rows: &[ResultRow]) -> StabilityReport {
    let rows = rows
        .iter()
        .map(|r| {
            let frames = r.psnr_by_frame();
            let worst = frames.iter().copied().min_by(|a, b| a.1.total_cmp(&b.1));
            let best = frames.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1));
            let psnr = r.value("shipped_psnr");
            let nan_steps = r.value("nan_steps").map(|v| v as usize);
            let verdict = match &r.status {
                CellStatus::Pending => Verdict::Pending,
                CellStatus::Failed(_) => Verdict::Failed,
                CellStatus::Done => match psnr {
                    Some(p) if p.is_finite() && p >= floor_db => {
                        if nan_steps.unwrap_or(0) > 0 {
                            Verdict::Recovered
                        } else {
                            Verdict::Stable
                        }
                    }
                    _ => Verdict::Collapsed,
                },
            };
            StabilityRow {
                scene: r.cell.scene.clone(),
                method: r.cell.series.clone(),
                verdict,
                psnr,
                ssim: r.value("shipped_ssim"),
                worst_frame: worst,
                best_frame: best,
                nan_steps,
                size_mib: r.value("shipped_mib"),
                error: match &r.status {
                    CellStatus::Failed(e) => Some(e.clone()),
                    _ => None,
                },
            }
        })
        .collect();
    StabilityReport {
        dir: dir.to_path_buf(),
        preset: preset.to_string(),
        floor_db,
        rows,
    }
}

fn opt(v: Option<f64>, decimals: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.decimals$}"))
}

/// Writes `stability.md`, `stability.json` and `charts/stability_psnr.png|svg`.
pub fn write_stability_report(report: &StabilityReport) -> Result<PathBuf> {
    let scenes: Vec<String> = report.rows.iter().fold(Vec::new(), |mut v, r| {
        if !v.contains(&r.scene) {
            v.push(r.scene.clone());
        }
        v
    });
    let methods: Vec<String> = report.rows.iter().fold(Vec::new(), |mut v, r| {
        if !v.contains(&r.method) {
            v.push(r.method.clone());
        }
        v
    });
    let series = methods
        .iter()
        .map(|m| {
            let mut s = Series {
                name: m.clone(),
                ..Default::default()
            };
            for r in report.rows.iter().filter(|r| &r.method == m) {
                let x = scenes.iter().position(|s| s == &r.scene).unwrap_or(0) as f64;
                if let Some(p) = r.psnr {
                    s.points.push((x, p));
                }
                if let (Some(w), Some(b)) = (r.worst_frame, r.best_frame) {
                    s.whiskers.push((x, w.1, b.1));
                }
            }
            s
        })
        .collect();
    let chart = Chart {
        title: format!("Stability ({} preset): PSNR, whiskers = worst..best frame", report.preset),
        x_label: "scene".into(),
        y_label: "PSNR (dB)".into(),
        log_x: false,
        x_categories: Some(scenes.clone()),
        connect: false,
        reference: Some((report.floor_db, format!("collapse floor {:.0} dB", report.floor_db))),
        series,
    };
    write_chart(&chart, &report.dir.join(CHARTS_DIR).join("stability_psnr"))?;

    let mut md = String::new();
    let _ = writeln!(md, "# Stability suite (preset `{}`)\n", report.preset);
    let _ = writeln!(
        md,
        "GIFStream and ACA-GS on scenes built to break methods. *Collapsed*: the shipped model \
         (decoded `scene.acags`) ends below {:.1} dB; *recovered*: non-finite steps were skipped \
         and training still ended above it; *failed*: training stopped with an error. Worst / \
         best frame: mean PSNR over the test cameras of the frame. Details per run: \
         [report.md](report.md).\n",
        report.floor_db
    );
    md.push_str(
        "| scene | method | verdict | PSNR | SSIM | worst frame | best frame | non-finite steps | size MiB |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for r in &report.rows {
        let frame = |f: Option<(usize, f64)>| f.map_or("–".into(), |(i, p)| format!("{p:.2} (#{i})"));
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r.scene,
            r.method,
            serde_json::to_value(r.verdict)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default(),
            opt(r.psnr, 2),
            opt(r.ssim, 3),
            frame(r.worst_frame),
            frame(r.best_frame),
            r.nan_steps.map_or("–".into(), |n| n.to_string()),
            opt(r.size_mib, 3),
        );
    }
    let broken = report.broken();
    if !broken.is_empty() {
        md.push_str("\n## Not stable\n\n");
        for r in broken {
            let _ = writeln!(
                md,
                "- {} / {}: {:?}{}",
                r.scene,
                r.method,
                r.verdict,
                r.error.as_ref().map_or(String::new(), |e| format!(": {e}"))
            );
        }
    }
    let _ = writeln!(
        md,
        "\n![stability]({CHARTS_DIR}/stability_psnr.png)\n\n([SVG]({CHARTS_DIR}/stability_psnr.svg))"
    );
    let path = report.dir.join(STABILITY_REPORT_FILE);
    std::fs::write(&path, md).with_context(|| format!("cannot write {}", path.display()))?;
    let json = report.dir.join(STABILITY_JSON_FILE);
    std::fs::write(&json, serde_json::to_string_pretty(report)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    Ok(path)
}
