//! What a sweep produced: one row per cell, read back from the cells' `metrics.json` (or
//! `failed.json`), and `results.csv`.

use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::manifest::{CellRecord, SweepManifest};
use crate::run::METRICS_FILE;

/// Written in a cell's directory when its training failed (e.g. repeated non-finite losses).
pub const FAILED_FILE: &str = "failed.json";
pub const RESULTS_FILE: &str = "results.csv";

/// How a cell ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "status", content = "error")]
pub enum CellStatus {
    Done,
    Failed(String),
    /// Not trained yet, or interrupted (its checkpoint resumes it).
    Pending,
}

impl CellStatus {
    pub fn name(&self) -> &'static str {
        match self {
            Self::Done => "done",
            Self::Failed(_) => "failed",
            Self::Pending => "pending",
        }
    }
}

/// The contents of `failed.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FailureRecord {
    pub error: String,
    /// Step the checkpoint had reached when it failed (0 when it never saved one).
    pub step: usize,
}

/// A numeric column of `results.csv` and the charts: name and axis label.
pub struct Column {
    pub name: &'static str,
    pub label: &'static str,
}

/// Every metric column, in `results.csv` order. "Shipped" is what a user gets out of the run:
/// the decoded `scene.acags` when the run wrote one, else the full-precision model.
pub const COLUMNS: &[Column] = &[
    Column { name: "step", label: "steps" },
    Column { name: "psnr", label: "PSNR (dB)" },
    Column { name: "ssim", label: "SSIM" },
    Column { name: "worst_view_psnr", label: "worst test image PSNR (dB)" },
    Column { name: "anchors", label: "anchors" },
    Column { name: "active_slots", label: "active Gaussians (slots)" },
    Column { name: "gaussians", label: "Gaussians per view" },
    Column { name: "masking_ratio", label: "masking ratio" },
    Column { name: "uncompressed_mib", label: "uncompressed size (MiB)" },
    Column { name: "file_mib", label: "scene.acags size (MiB)" },
    Column { name: "ratio", label: "compression ratio" },
    Column { name: "compressed_psnr", label: "decoded PSNR (dB)" },
    Column { name: "compressed_ssim", label: "decoded SSIM" },
    Column { name: "shipped_mib", label: "size (MiB)" },
    Column { name: "shipped_psnr", label: "PSNR (dB)" },
    Column { name: "shipped_ssim", label: "SSIM" },
    Column { name: "shipped_fps", label: "render FPS" },
    Column { name: "lpips_alex", label: "LPIPS-Alex, full precision" },
    Column { name: "lpips_vgg", label: "LPIPS-VGG, full precision" },
    Column { name: "compressed_lpips_alex", label: "decoded LPIPS-Alex" },
    Column { name: "shipped_lpips_alex", label: "LPIPS-Alex" },
    Column { name: "shipped_lpips_vgg", label: "LPIPS-VGG" },
    Column { name: "shipped_dynamic_lpips_alex", label: "dynamic-region LPIPS-Alex" },
    Column { name: "shipped_static_lpips_alex", label: "static-region LPIPS-Alex" },
    Column { name: "dynamic_psnr", label: "dynamic-region PSNR, full precision (dB)" },
    Column { name: "static_psnr", label: "static-region PSNR, full precision (dB)" },
    Column { name: "shipped_dynamic_psnr", label: "dynamic-region PSNR (dB)" },
    Column { name: "shipped_static_psnr", label: "static-region PSNR (dB)" },
    Column { name: "shipped_dynamic_ssim", label: "dynamic-region SSIM" },
    Column { name: "shipped_static_ssim", label: "static-region SSIM" },
    Column { name: "worst_frame_dynamic_psnr", label: "worst frame, dynamic-region PSNR (dB)" },
    Column { name: "max_dynamic_gap", label: "largest per-frame static − dynamic PSNR gap (dB)" },
    Column { name: "dynamic_fraction", label: "moving pixels (share of the image)" },
    Column { name: "render_fps", label: "render FPS (full precision)" },
    Column { name: "train_seconds", label: "training time (s)" },
    Column { name: "nan_steps", label: "skipped (non-finite) steps" },
];

/// The axis label of a column or parameter.
pub fn label(column: &str) -> String {
    COLUMNS
        .iter()
        .find(|c| c.name == column)
        .map_or_else(|| column.to_string(), |c| c.label.to_string())
}

/// One cell's outcome.
#[derive(Clone, Debug)]
pub struct ResultRow {
    pub cell: CellRecord,
    pub status: CellStatus,
    /// `metrics.json` of a finished cell.
    pub metrics: Option<serde_json::Value>,
}

impl ResultRow {
    /// A metric column, or a parameter of the cell parsed as a number.
    pub fn value(&self, column: &str) -> Option<f64> {
        if let Some((_, v)) = self.cell.params.iter().find(|(k, _)| k == column) {
            return v.parse().ok();
        }
        let m = self.metrics.as_ref()?;
        let num = |pointer: &str| m.pointer(pointer).and_then(serde_json::Value::as_f64);
        let compressed = m.get("compressed").filter(|c| !c.is_null()).is_some();
        // Shipped figures: the decoded file's when there is one.
        let shipped = |key: &str| {
            if compressed {
                m.pointer(&format!("/compressed/{key}"))
            } else {
                m.get(key)
            }
        };
        // `[frame, value]` pairs (worst frame, largest gap).
        let pair_value = |v: Option<&serde_json::Value>| v?.get(1)?.as_f64();
        match column {
            "shipped_dynamic_psnr" => shipped("dynamic_psnr")?.as_f64(),
            "shipped_static_psnr" => shipped("static_psnr")?.as_f64(),
            "shipped_dynamic_ssim" => shipped("dynamic_ssim")?.as_f64(),
            "shipped_static_ssim" => shipped("static_ssim")?.as_f64(),
            "shipped_lpips_alex" => shipped("lpips_alex")?.as_f64(),
            "shipped_lpips_vgg" => shipped("lpips_vgg")?.as_f64(),
            "shipped_dynamic_lpips_alex" => shipped("dynamic_lpips_alex")?.as_f64(),
            "shipped_static_lpips_alex" => shipped("static_lpips_alex")?.as_f64(),
            "compressed_lpips_alex" => num("/compressed/lpips_alex"),
            "worst_frame_dynamic_psnr" => pair_value(shipped("worst_dynamic_frame")),
            "max_dynamic_gap" => pair_value(shipped("max_dynamic_gap")),
            "worst_view_psnr" => m
                .get("views")?
                .as_array()?
                .iter()
                .filter_map(|v| v.get("psnr")?.as_f64())
                .reduce(f64::min),
            "file_mib" => num("/compressed/file_mib"),
            "ratio" => num("/compressed/ratio"),
            "compressed_psnr" => num("/compressed/psnr"),
            "compressed_ssim" => num("/compressed/ssim"),
            "shipped_mib" if compressed => num("/compressed/file_mib"),
            "shipped_mib" => num("/uncompressed_mib"),
            "shipped_psnr" if compressed => num("/compressed/psnr"),
            "shipped_psnr" => num("/psnr"),
            "shipped_ssim" if compressed => num("/compressed/ssim"),
            "shipped_ssim" => num("/ssim"),
            "shipped_fps" if compressed => num("/compressed/render_fps"),
            "shipped_fps" => num("/render_fps"),
            other => num(&format!("/{other}")),
        }
    }

    /// Per-frame mean PSNR over the test cameras (frame order) of the shipped model (the
    /// decoded file when there is one, like `shipped_psnr`), for time plots: `frames` of
    /// `metrics.json`, or for results written before it existed, the per-view values averaged.
    pub fn psnr_by_frame(&self) -> Vec<(usize, f64)> {
        let frames = self.frame_values("psnr");
        if !frames.is_empty() {
            return frames;
        }
        let metrics = self.metrics.as_ref();
        let Some(views) = metrics
            .and_then(|m| m.pointer("/compressed/views"))
            .or_else(|| metrics.and_then(|m| m.get("views")))
            .and_then(|v| v.as_array())
        else {
            return Vec::new();
        };
        let mut sums = std::collections::BTreeMap::<usize, (f64, usize)>::new();
        for v in views {
            if let (Some(f), Some(p)) = (
                v.get("frame").and_then(|x| x.as_u64()),
                v.get("psnr").and_then(|x| x.as_f64()),
            ) {
                let e = sums.entry(f as usize).or_default();
                e.0 += p;
                e.1 += 1;
            }
        }
        sums.into_iter()
            .map(|(f, (s, n))| (f, s / n as f64))
            .collect()
    }

    /// Per-frame means over the test cameras of the shipped model for `key` (`psnr`,
    /// `dynamic_psnr`, `static_psnr`, ...), from `metrics.json`'s `frames`; frames without a
    /// value (e.g. no moving pixels) are left out.
    pub fn frame_values(&self, key: &str) -> Vec<(usize, f64)> {
        let metrics = self.metrics.as_ref();
        let Some(frames) = metrics
            .and_then(|m| m.pointer("/compressed/frames"))
            .or_else(|| metrics.and_then(|m| m.get("frames")))
            .and_then(|v| v.as_array())
        else {
            return Vec::new();
        };
        frames
            .iter()
            .filter_map(|f| {
                Some((
                    f.get("frame")?.as_u64()? as usize,
                    f.get(key)?.as_f64()?,
                ))
            })
            .collect()
    }

    /// The compression preset of the shipped file, if any.
    pub fn rate(&self) -> Option<String> {
        self.metrics
            .as_ref()?
            .pointer("/compressed/rate")?
            .as_str()
            .map(str::to_string)
    }
}

/// Reads the state of one cell from its directory.
pub fn read_cell(sweep_dir: &Path, cell: &CellRecord) -> Result<ResultRow> {
    let dir = sweep_dir.join(&cell.dir);
    let metrics_path = dir.join(METRICS_FILE);
    let failed_path = dir.join(FAILED_FILE);
    let (status, metrics) = if metrics_path.exists() {
        let text = std::fs::read_to_string(&metrics_path)
            .with_context(|| format!("cannot read {}", metrics_path.display()))?;
        let value: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("{}: not valid JSON", metrics_path.display()))?;
        (CellStatus::Done, Some(value))
    } else if failed_path.exists() {
        let text = std::fs::read_to_string(&failed_path)
            .with_context(|| format!("cannot read {}", failed_path.display()))?;
        let record: FailureRecord = serde_json::from_str(&text)
            .with_context(|| format!("{}: not a failure record", failed_path.display()))?;
        (CellStatus::Failed(record.error), None)
    } else {
        (CellStatus::Pending, None)
    };
    Ok(ResultRow {
        cell: cell.clone(),
        status,
        metrics,
    })
}

/// Every cell of a sweep directory, in the manifest's order.
pub fn read_rows(sweep_dir: &Path, manifest: &SweepManifest) -> Result<Vec<ResultRow>> {
    manifest
        .cells
        .iter()
        .map(|c| read_cell(sweep_dir, c))
        .collect()
}

/// Writes `results.csv`: scene, cell, series, status, error, every parameter, every metric
/// column, the shipped file's rate preset (empty where a value does not exist).
pub fn write_csv(path: &Path, rows: &[ResultRow]) -> Result<()> {
    let mut params: Vec<String> = Vec::new();
    for row in rows {
        for (k, _) in &row.cell.params {
            if !params.contains(k) {
                params.push(k.clone());
            }
        }
    }
    let tmp = path.with_extension("csv.partial");
    {
        let mut w = csv::Writer::from_path(&tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        let mut header: Vec<String> = ["scene", "cell", "series", "status", "error"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        header.extend(params.iter().cloned());
        header.extend(COLUMNS.iter().map(|c| c.name.to_string()));
        header.push("rate".into());
        w.write_record(&header)?;
        for row in rows {
            let mut record = vec![
                row.cell.scene.clone(),
                row.cell.name.clone(),
                row.cell.series.clone(),
                row.status.name().to_string(),
                match &row.status {
                    CellStatus::Failed(e) => e.clone(),
                    _ => String::new(),
                },
            ];
            for p in &params {
                record.push(
                    row.cell
                        .params
                        .iter()
                        .find(|(k, _)| k == p)
                        .map_or(String::new(), |(_, v)| v.clone()),
                );
            }
            for c in COLUMNS {
                record.push(row.value(c.name).map_or(String::new(), |v| format!("{v}")));
            }
            record.push(row.rate().unwrap_or_default());
            w.write_record(&record)?;
        }
        w.flush()?;
    }
    std::fs::rename(&tmp, path).with_context(|| format!("cannot write {}", path.display()))
}
