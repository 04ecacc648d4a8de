//! Sweep grids (`configs/sweeps/*.toml`): which configs to train over which scenes, expanded
//! into cells, each one fully resolved `TrainConfig` in its own run directory.
//!
//! A grid names a base config and overrides, a list of `[[cells]]` (rows of a paper table), a
//! cartesian `[axes]` table, a one-at-a-time `[vary]` table (sensitivity rows around the base),
//! the scenes, presets (overrides that shorten training: `--preset ci|reduced`; `full` is the
//! grid as written) and the charts its report draws. Overrides apply in this order, later ones
//! winning: base config, grid `set`, cell `set`, axis/vary values, preset, scene (a scene's own
//! overrides define it, e.g. a long GOP's frame count, so no preset shortens them away).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::train::config::TrainConfig;

/// The preset that trains the grid as written.
pub const FULL_PRESET: &str = "full";
/// Presets shared by the grids of one directory live in this file beside them.
pub const SHARED_PRESETS_FILE: &str = "presets.toml";

/// A grid file as written.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct GridFile {
    /// One line for the report's title.
    #[serde(default)]
    pub description: String,
    /// Datasets, or tables with a label and overrides; `synthetic:fast` when empty.
    #[serde(default)]
    pub scenes: Vec<SceneEntry>,
    /// Base config: a path relative to the grid file, or `builtin:default` / `builtin:aca-gs`;
    /// the embedded default when absent.
    pub config: Option<String>,
    #[serde(default)]
    pub set: Vec<String>,
    #[serde(default)]
    pub cells: Vec<CellEntry>,
    /// Cartesian product over every cell: key → values.
    #[serde(default)]
    pub axes: BTreeMap<String, Vec<toml::Value>>,
    /// One at a time around every cell: key → values (the cell itself is kept once).
    #[serde(default)]
    pub vary: BTreeMap<String, Vec<toml::Value>>,
    #[serde(default)]
    pub presets: BTreeMap<String, Preset>,
    #[serde(default)]
    pub charts: Vec<ChartSpec>,
    /// Stability suites: a shipped model below this PSNR has collapsed.
    pub collapse_floor_db: Option<f64>,
    /// Stability suites: a shipped model whose moving pixels trail its static pixels by more than
    /// this in some frame (mean over the test cameras) has dropped the moving object: collapsed.
    pub dynamic_gap_limit_db: Option<f64>,
}

/// A scene of a grid: a dataset name, or a labelled dataset with overrides.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(untagged)]
pub enum SceneEntry {
    Dataset(String),
    Labelled {
        name: String,
        dataset: String,
        #[serde(default)]
        set: Vec<String>,
    },
}

/// One row of a paper table.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CellEntry {
    pub name: String,
    /// Chart series (method) this cell belongs to; its name when absent.
    pub series: Option<String>,
    /// Base config of this cell (same forms as the grid's); the grid's when absent.
    pub config: Option<String>,
    #[serde(default)]
    pub set: Vec<String>,
}

/// Overrides that shorten or cheapen every cell.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Preset {
    #[serde(default)]
    pub description: String,
    #[serde(default)]
    pub set: Vec<String>,
    /// Overrides the grid's collapse floor (short schedules reach less).
    pub collapse_floor_db: Option<f64>,
    /// Overrides the grid's dynamic-gap limit.
    pub dynamic_gap_limit_db: Option<f64>,
}

/// One chart of a report: a column against a column, one line per series and scene.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ChartSpec {
    /// File stem under `charts/`.
    pub name: String,
    pub title: String,
    pub x: String,
    pub y: String,
    #[serde(default)]
    pub log_x: bool,
}

/// A grid read from disk, with where it came from.
#[derive(Clone, Debug)]
pub struct Grid {
    pub file: GridFile,
    /// The grid file (or a label for an embedded one), for messages.
    pub origin: String,
    /// Directory relative config paths are resolved against.
    pub base_dir: PathBuf,
    /// The grid's text, kept in the sweep directory.
    pub text: String,
}

/// One training run of a sweep.
#[derive(Clone, Debug)]
pub struct Cell {
    /// Scene label (directory name component).
    pub scene: String,
    /// Cell label: the row name plus its axis values.
    pub name: String,
    pub series: String,
    /// Axis / vary values of this cell: key → value as written.
    pub params: Vec<(String, String)>,
    /// `scene/name`, sanitised: the run directory under the sweep directory.
    pub dir: PathBuf,
    pub config: TrainConfig,
}

impl Grid {
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read sweep grid {}", path.display()))?;
        let base_dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
        Self::parse(&text, &path.display().to_string(), base_dir)
    }

    pub fn parse(text: &str, origin: &str, base_dir: PathBuf) -> Result<Self> {
        let file: GridFile = toml::from_str(text)
            .map_err(|e| anyhow::anyhow!("{origin}: not a sweep grid: {e}"))?;
        for (what, table) in [("axes", &file.axes), ("vary", &file.vary)] {
            if let Some((key, _)) = table.iter().find(|(_, v)| v.is_empty()) {
                bail!("{origin}: [{what}] `{key}` has no values");
            }
        }
        let mut names = std::collections::HashSet::new();
        if let Some(c) = file.cells.iter().find(|c| !names.insert(&c.name)) {
            bail!("{origin}: two [[cells]] are named `{}`", c.name);
        }
        Ok(Self {
            file,
            origin: origin.to_string(),
            base_dir,
            text: text.to_string(),
        })
    }

    /// The preset's overrides (`full`: none), from the grid or the shared presets file.
    pub fn preset(&self, name: &str) -> Result<Preset> {
        if name == FULL_PRESET {
            return Ok(Preset::default());
        }
        if let Some(p) = self.file.presets.get(name) {
            return Ok(p.clone());
        }
        let shared = self.base_dir.join(SHARED_PRESETS_FILE);
        let mut known: Vec<String> = vec![FULL_PRESET.into()];
        known.extend(self.file.presets.keys().cloned());
        if shared.exists() {
            let text = std::fs::read_to_string(&shared)
                .with_context(|| format!("cannot read {}", shared.display()))?;
            let presets: BTreeMap<String, Preset> = toml::from_str(&text)
                .map_err(|e| anyhow::anyhow!("{}: not a presets file: {e}", shared.display()))?;
            if let Some(p) = presets.get(name) {
                return Ok(p.clone());
            }
            known.extend(presets.keys().cloned());
        }
        bail!(
            "{}: no preset `{name}` (known: {})",
            self.origin,
            known.join(", ")
        )
    }

    /// The collapse floor under a preset (stability suites), if the grid has one.
    pub fn collapse_floor(&self, preset: &Preset) -> Option<f64> {
        preset.collapse_floor_db.or(self.file.collapse_floor_db)
    }

    /// The dynamic-gap limit under a preset (stability suites), if the grid has one.
    pub fn dynamic_gap_limit(&self, preset: &Preset) -> Option<f64> {
        preset.dynamic_gap_limit_db.or(self.file.dynamic_gap_limit_db)
    }

    /// Every cell, scenes outermost, each config resolved and validated (errors name the grid
    /// and the cell before anything trains).
    pub fn cells(&self, preset: &Preset) -> Result<Vec<Cell>> {
        let scenes = if self.file.scenes.is_empty() {
            vec![SceneEntry::Dataset("synthetic:fast".into())]
        } else {
            self.file.scenes.clone()
        };
        let rows = if self.file.cells.is_empty() {
            vec![CellEntry {
                name: "base".into(),
                series: None,
                config: None,
                set: Vec::new(),
            }]
        } else {
            self.file.cells.clone()
        };
        let variants = self.variants();
        let mut cells = Vec::new();
        let mut dirs = std::collections::HashSet::new();
        for scene in &scenes {
            let (scene_label, dataset, scene_set) = match scene {
                SceneEntry::Dataset(d) => (scene_label(d), d.clone(), Vec::new()),
                SceneEntry::Labelled { name, dataset, set } => {
                    (name.clone(), dataset.clone(), set.clone())
                }
            };
            for row in &rows {
                for params in &variants {
                    let mut name = row.name.clone();
                    for (key, value) in params {
                        name.push_str(&format!(" {}={}", short_key(key), display_value(value)));
                    }
                    let mut overrides = self.file.set.clone();
                    overrides.extend(row.set.iter().cloned());
                    overrides.extend(params.iter().map(|(k, v)| format!("{k}={v}")));
                    overrides.extend(preset.set.iter().cloned());
                    overrides.push(format!("data.dataset={}", toml::Value::String(dataset.clone())));
                    overrides.extend(scene_set.iter().cloned());
                    let config_name = row.config.as_ref().or(self.file.config.as_ref());
                    let config = self.load_config(config_name, &overrides).with_context(|| {
                        format!("{}: cell `{name}` on scene `{scene_label}`", self.origin)
                    })?;
                    let dir = PathBuf::from(sanitise(&scene_label)).join(sanitise(&name));
                    if !dirs.insert(dir.clone()) {
                        bail!(
                            "{}: two cells share the directory {} (rename a cell)",
                            self.origin,
                            dir.display()
                        );
                    }
                    cells.push(Cell {
                        scene: scene_label.clone(),
                        name,
                        series: row.series.clone().unwrap_or_else(|| row.name.clone()),
                        params: params
                            .iter()
                            .map(|(k, v)| (k.clone(), display_value(v)))
                            .collect(),
                        dir,
                        config,
                    });
                }
            }
        }
        Ok(cells)
    }

    /// Axis/vary assignments: the cartesian product of `axes`, each also varied one key at a
    /// time by `vary` (the unvaried assignment first).
    fn variants(&self) -> Vec<Vec<(String, toml::Value)>> {
        let mut product: Vec<Vec<(String, toml::Value)>> = vec![Vec::new()];
        for (key, values) in &self.file.axes {
            product = product
                .into_iter()
                .flat_map(|prefix| {
                    values.iter().map(move |v| {
                        let mut p = prefix.clone();
                        p.push((key.clone(), v.clone()));
                        p
                    })
                })
                .collect();
        }
        let mut out = Vec::new();
        for p in product {
            out.push(p.clone());
            for (key, values) in &self.file.vary {
                for v in values {
                    let mut q = p.clone();
                    q.push((key.clone(), v.clone()));
                    out.push(q);
                }
            }
        }
        out
    }

    fn load_config(&self, name: Option<&String>, overrides: &[String]) -> Result<TrainConfig> {
        match name.map(String::as_str) {
            None | Some("builtin:default") => {
                TrainConfig::embedded("default.toml", overrides)
            }
            Some("builtin:aca-gs") => {
                TrainConfig::embedded("aca-gs.toml", overrides)
            }
            Some(other) if other.starts_with("builtin:") => {
                bail!("unknown config `{other}` (builtin:default or builtin:aca-gs)")
            }
            Some(path) => TrainConfig::load(Some(&self.base_dir.join(path)), overrides),
        }
    }
}

/// A value as labels show it: strings bare, the rest as TOML writes them.
fn display_value(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// `synthetic:fast` → `fast`; a path → its last component.
fn scene_label(dataset: &str) -> String {
    if let Some(p) = dataset.strip_prefix("synthetic:") {
        return p.to_string();
    }
    Path::new(dataset)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| dataset.to_string())
}

/// `aafm.mask_weight` → `mask_weight` (labels stay readable; the full key is in the params).
fn short_key(key: &str) -> &str {
    key.rsplit('.').next().unwrap_or(key)
}

/// A label as a directory name: letters, digits, `.`, `-`, `_`, `=` kept, the rest `_`.
fn sanitise(label: &str) -> String {
    label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_' | '=') {
                c
            } else {
                '_'
            }
        })
        .collect()
}
