//! `sweep.json`: what a sweep directory holds (grid, preset, cells), written before the first
//! cell trains so `acags report` and a re-run read the same cell list.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::grid::{Cell, ChartSpec};

pub const MANIFEST_FILE: &str = "sweep.json";
/// The grid's text as it was run.
pub const GRID_COPY_FILE: &str = "grid.toml";

/// A cell as the sweep directory records it (its config is in `DIR/config.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellRecord {
    pub scene: String,
    pub name: String,
    pub series: String,
    pub params: Vec<(String, String)>,
    /// Relative to the sweep directory.
    pub dir: PathBuf,
}

impl From<&Cell> for CellRecord {
    fn from(c: &Cell) -> Self {
        Self {
            scene: c.scene.clone(),
            name: c.name.clone(),
            series: c.series.clone(),
            params: c.params.clone(),
            dir: c.dir.clone(),
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SweepManifest {
    pub description: String,
    /// The grid file the sweep ran.
    pub grid: String,
    pub preset: String,
    pub preset_description: String,
    /// The command that runs (or resumes) this sweep.
    pub command: String,
    /// Stability suites: the PSNR below which a shipped model counts as collapsed.
    pub collapse_floor_db: Option<f64>,
    /// Stability suites: the largest per-frame static − dynamic PSNR gap of a stable run.
    #[serde(default)]
    pub dynamic_gap_limit_db: Option<f64>,
    pub charts: Vec<ChartSpec>,
    pub cells: Vec<CellRecord>,
}

impl SweepManifest {
    pub fn read(sweep_dir: &Path) -> Result<Self> {
        let path = sweep_dir.join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&path).with_context(|| {
            format!(
                "cannot read {} (is {} a sweep directory?)",
                path.display(),
                sweep_dir.display()
            )
        })?;
        serde_json::from_str(&text).with_context(|| format!("{}: not a sweep manifest", path.display()))
    }

    pub fn write(&self, sweep_dir: &Path) -> Result<()> {
        let path = sweep_dir.join(MANIFEST_FILE);
        std::fs::write(&path, serde_json::to_string_pretty(self)?)
            .with_context(|| format!("cannot write {}", path.display()))
    }
}
