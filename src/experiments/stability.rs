//! `acags stability`: GIFStream and ACA-GS on scenes built to break methods (the embedded grid
//! `configs/sweeps/stability.toml`): fast large motion, motion leaving the initial point cloud,
//! four training cameras, a strong lighting change, a long GOP, and injected non-finite losses.
//! Per run: quality, worst frame, non-finite steps, and a verdict against the collapse floor;
//! `stability.md` and a chart beside the sweep's own report.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Serialize;

use crate::io::charts::{Chart, Series, write_chart};
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
    /// `full` (the default 3200-step schedule), `reduced` or `ci`.
    #[arg(long, default_value = "reduced")]
    pub preset: String,
    #[command(flatten)]
    pub run: GridRunOptions,
}

/// How one run fared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Above the floor on the full image and on the moving pixels, the moving pixels within the
    /// gap limit of the static ones in every frame, no non-finite step.
    Stable,
    /// Non-finite steps were skipped and the run still ended stable.
    Recovered,
    /// Finished below the floor (full image or moving pixels), dropped the moving object in some
    /// frame (gap above the limit), or non-finite metrics.
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
    /// PSNR on the moving and on the static pixels (shipped model).
    pub dynamic_psnr: Option<f64>,
    pub static_psnr: Option<f64>,
    /// LPIPS-Alex of the shipped model, whole image and moving pixels.
    pub lpips_alex: Option<f64>,
    pub dynamic_lpips_alex: Option<f64>,
    /// Lowest per-frame PSNR (mean over test cameras) and the frame.
    pub worst_frame: Option<(usize, f64)>,
    pub best_frame: Option<(usize, f64)>,
    /// Lowest per-frame dynamic-region PSNR and the frame.
    pub worst_dynamic_frame: Option<(usize, f64)>,
    /// Largest per-frame static − dynamic PSNR gap and the frame.
    pub max_dynamic_gap: Option<(usize, f64)>,
    /// Why a finished run is not stable.
    pub reason: Option<String>,
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
    pub gap_limit_db: f64,
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
    let gap_limit = outcome
        .manifest
        .dynamic_gap_limit_db
        .context("the stability grid names no dynamic_gap_limit_db")?;
    let report = assess(&outcome.dir, &options.preset, floor, gap_limit, &outcome.rows);
    write_stability_report(&report)?;
    Ok(report)
}

/// Why a finished run with these figures is not stable, or `None` when it is: the full-image
/// and the dynamic-region PSNR must reach `floor_db`, and no frame's dynamic region may trail its
/// static region by more than `gap_limit_db` (a dropped moving object costs little full-frame
/// PSNR, so the full image alone would call it stable).
pub fn collapse_reason(
    psnr: Option<f64>,
    dynamic_psnr: Option<f64>,
    max_gap: Option<(usize, f64)>,
    floor_db: f64,
    gap_limit_db: f64,
) -> Option<String> {
    match psnr {
        Some(p) if p.is_finite() && p >= floor_db => {}
        Some(p) => return Some(format!("PSNR {p:.2} dB below the {floor_db:.1} dB floor")),
        None => return Some("no PSNR".into()),
    }
    if let Some(d) = dynamic_psnr
        && !(d.is_finite() && d >= floor_db)
    {
        return Some(format!(
            "dynamic-region PSNR {d:.2} dB below the {floor_db:.1} dB floor"
        ));
    }
    if let Some((frame, gap)) = max_gap
        && !(gap <= gap_limit_db)
    {
        return Some(format!(
            "moving pixels {gap:.2} dB below the static ones at frame {frame} (limit {gap_limit_db:.1} dB)"
        ));
    }
    None
}

/// The verdict of every row against `floor_db` and `gap_limit_db`.
pub fn assess(
    dir: &Path,
    preset: &str,
    floor_db: f64,
    gap_limit_db: f64,
    rows: &[ResultRow],
) -> StabilityReport {
    let rows = rows
        .iter()
        .map(|r| {
            let frames = r.psnr_by_frame();
            let worst = frames.iter().copied().min_by(|a, b| a.1.total_cmp(&b.1));
            let best = frames.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1));
            let dynamic_frames = r.frame_values("dynamic_psnr");
            let static_frames = r.frame_values("static_psnr");
            let worst_dynamic = dynamic_frames
                .iter()
                .copied()
                .min_by(|a, b| a.1.total_cmp(&b.1));
            let max_gap = dynamic_frames
                .iter()
                .filter_map(|&(f, d)| Some((f, static_frames.iter().find(|s| s.0 == f)?.1 - d)))
                .max_by(|a, b| a.1.total_cmp(&b.1));
            let psnr = r.value("shipped_psnr");
            let dynamic_psnr = r.value("shipped_dynamic_psnr");
            let nan_steps = r.value("nan_steps").map(|v| v as usize);
            let reason = match r.status {
                CellStatus::Done => collapse_reason(psnr, dynamic_psnr, max_gap, floor_db, gap_limit_db),
                _ => None,
            };
            let verdict = match &r.status {
                CellStatus::Pending => Verdict::Pending,
                CellStatus::Failed(_) => Verdict::Failed,
                CellStatus::Done if reason.is_some() => Verdict::Collapsed,
                CellStatus::Done if nan_steps.unwrap_or(0) > 0 => Verdict::Recovered,
                CellStatus::Done => Verdict::Stable,
            };
            StabilityRow {
                scene: r.cell.scene.clone(),
                method: r.cell.series.clone(),
                verdict,
                psnr,
                ssim: r.value("shipped_ssim"),
                dynamic_psnr,
                static_psnr: r.value("shipped_static_psnr"),
                lpips_alex: r.value("shipped_lpips_alex"),
                dynamic_lpips_alex: r.value("shipped_dynamic_lpips_alex"),
                worst_frame: worst,
                best_frame: best,
                worst_dynamic_frame: worst_dynamic,
                max_dynamic_gap: max_gap,
                reason,
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
        gap_limit_db,
        rows,
    }
}

fn opt(v: Option<f64>, decimals: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.decimals$}"))
}

/// Writes `stability.md`, `stability.json` and `charts/stability_psnr.png|svg`.
pub fn write_stability_report(report: &StabilityReport) -> Result<PathBuf> {
    let unique = |f: fn(&StabilityRow) -> &String| -> Vec<String> {
        report.rows.iter().fold(Vec::new(), |mut v, r| {
            if !v.contains(f(r)) {
                v.push(f(r).clone());
            }
            v
        })
    };
    let scenes = unique(|r| &r.scene);
    let methods = unique(|r| &r.method);
    // Per scene: the mean (point) and the worst..best frame (whisker) of one figure.
    let per_scene = |value: fn(&StabilityRow) -> Option<f64>,
                     range: fn(&StabilityRow) -> Option<(f64, f64)>| {
        methods
            .iter()
            .map(|m| {
                let mut s = Series {
                    name: m.clone(),
                    ..Default::default()
                };
                for r in report.rows.iter().filter(|r| &r.method == m) {
                    let x = scenes.iter().position(|s| s == &r.scene).unwrap_or(0) as f64;
                    if let Some(p) = value(r) {
                        s.points.push((x, p));
                    }
                    if let Some((lo, hi)) = range(r) {
                        s.whiskers.push((x, lo, hi));
                    }
                }
                s
            })
            .collect::<Vec<_>>()
    };
    let floor = Some((report.floor_db, format!("collapse floor {:.0} dB", report.floor_db)));
    let chart = Chart {
        title: format!("Stability ({} preset): PSNR, whiskers = worst..best frame", report.preset),
        x_label: "scene".into(),
        y_label: "PSNR (dB)".into(),
        log_x: false,
        x_categories: Some(scenes.clone()),
        connect: false,
        reference: floor.clone(),
        series: per_scene(|r| r.psnr, |r| Some((r.worst_frame?.1, r.best_frame?.1))),
    };
    write_chart(&chart, &report.dir.join(CHARTS_DIR).join("stability_psnr"))?;
    let chart = Chart {
        title: format!(
            "Stability ({} preset): moving pixels, whiskers down to the worst frame",
            report.preset
        ),
        y_label: "dynamic-region PSNR (dB)".into(),
        series: per_scene(|r| r.dynamic_psnr, |r| {
            Some((r.worst_dynamic_frame?.1, r.dynamic_psnr?))
        }),
        ..chart
    };
    write_chart(&chart, &report.dir.join(CHARTS_DIR).join("stability_dynamic_psnr"))?;

    let mut md = String::new();
    let _ = writeln!(md, "# Stability suite (preset `{}`)\n", report.preset);
    let _ = writeln!(
        md,
        "GIFStream and ACA-GS on scenes built to break methods. *Collapsed*: the shipped model \
         (decoded `scene.acags`) ends below {:.1} dB on the full image or on the moving pixels, \
         or in some frame its moving pixels trail its static pixels by more than {:.1} dB (the \
         moving object was dropped: the full-frame PSNR hardly shows it); *recovered*: \
         non-finite steps were skipped and training still ended stable; *failed*: training \
         stopped with an error. Moving pixels: the ground truth departs from its camera's \
         temporal median (dilated; `eval.motion_threshold`, `eval.motion_dilation`). Frames: \
         means over the test cameras. Details per run: [report.md](report.md); each run's \
         `quality_by_frame.png` plots its frames.\n",
        report.floor_db, report.gap_limit_db
    );
    md.push_str(
        "| scene | method | verdict | PSNR | SSIM | LPIPS-Alex | dynamic PSNR | static PSNR | dynamic LPIPS-Alex | worst frame | worst dynamic frame | largest gap | non-finite steps | size MiB |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let frame = |f: Option<(usize, f64)>| f.map_or("–".into(), |(i, p)| format!("{p:.2} (#{i})"));
    for r in &report.rows {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r.scene,
            r.method,
            serde_json::to_value(r.verdict)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default(),
            opt(r.psnr, 2),
            opt(r.ssim, 3),
            opt(r.lpips_alex, 4),
            opt(r.dynamic_psnr, 2),
            opt(r.static_psnr, 2),
            opt(r.dynamic_lpips_alex, 4),
            frame(r.worst_frame),
            frame(r.worst_dynamic_frame),
            frame(r.max_dynamic_gap),
            r.nan_steps.map_or("–".into(), |n| n.to_string()),
            opt(r.size_mib, 3),
        );
    }
    let broken = report.broken();
    if !broken.is_empty() {
        md.push_str("\n## Not stable\n\n");
        for r in broken {
            let why = r.error.as_ref().or(r.reason.as_ref());
            let _ = writeln!(
                md,
                "- {} / {}: {:?}{}",
                r.scene,
                r.method,
                r.verdict,
                why.map_or(String::new(), |e| format!(": {e}"))
            );
        }
    }
    let _ = writeln!(
        md,
        "\n![stability]({CHARTS_DIR}/stability_psnr.png)\n\n([SVG]({CHARTS_DIR}/stability_psnr.svg))\n\n\
         ![moving pixels]({CHARTS_DIR}/stability_dynamic_psnr.png)\n\n([SVG]({CHARTS_DIR}/stability_dynamic_psnr.svg))"
    );
    let path = report.dir.join(STABILITY_REPORT_FILE);
    std::fs::write(&path, md).with_context(|| format!("cannot write {}", path.display()))?;
    let json = report.dir.join(STABILITY_JSON_FILE);
    std::fs::write(&json, serde_json::to_string_pretty(report)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    Ok(path)
}
