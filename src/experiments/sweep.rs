//! `acags sweep`: trains every cell of a grid, one after another, each in its own run
//! directory under the sweep directory; a re-run skips finished cells and resumes interrupted
//! ones from their checkpoints, so a killed sweep continues where it stopped.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use super::grid::{Cell, FULL_PRESET, Grid};
use super::manifest::{CellRecord, GRID_COPY_FILE, SweepManifest};
use super::results::{
    CellStatus, FAILED_FILE, FailureRecord, RESULTS_FILE, ResultRow, read_cell, write_csv,
};
use crate::compute_backend::{BackendKind, ChosenDevice, resolve};
use crate::panics::panic_message;
use crate::run::{CHECKPOINT_FILE, CONFIG_FILE, train_run};
use crate::train::config::TrainConfig;

/// Options of `acags sweep`.
#[derive(Clone, Debug, clap::Args)]
pub struct SweepOptions {
    /// The grid: configs/sweeps/NAME.toml.
    #[arg(long)]
    pub grid: PathBuf,
    /// Sweep directory (default runs/sweep-NAME-PRESET).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// `full` trains the grid as written; `reduced` and `ci` shorten it
    /// (configs/sweeps/presets.toml).
    #[arg(long, default_value = FULL_PRESET)]
    pub preset: String,
    #[command(flatten)]
    pub run: GridRunOptions,
}

/// How the cells of a grid are trained: shared by `acags sweep` and `acags stability`.
#[derive(Clone, Copy, Debug, clap::Args)]
pub struct GridRunOptions {
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: BackendKind,
    /// Train cells that failed before again (they are skipped otherwise).
    #[arg(long)]
    pub retry_failed: bool,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
}

/// What a sweep ended with.
pub struct SweepOutcome {
    pub dir: PathBuf,
    pub manifest: SweepManifest,
    pub rows: Vec<ResultRow>,
}

impl SweepOutcome {
    pub fn failed(&self) -> usize {
        self.rows
            .iter()
            .filter(|r| matches!(r.status, CellStatus::Failed(_)))
            .count()
    }
}

/// The default sweep directory of a grid and preset.
pub fn default_sweep_dir(grid: &Path, preset: &str) -> PathBuf {
    let stem = grid
        .file_stem()
        .map_or_else(|| "grid".into(), |s| s.to_string_lossy().into_owned());
    PathBuf::from("runs").join(format!("sweep-{stem}-{preset}"))
}

/// `acags sweep`.
pub fn sweep(options: &SweepOptions) -> Result<SweepOutcome> {
    let grid = Grid::read(&options.grid)?;
    let out = options
        .out
        .clone()
        .unwrap_or_else(|| default_sweep_dir(&options.grid, &options.preset));
    let command = format!(
        "acags sweep --grid {} --preset {} --out {}",
        options.grid.display(),
        options.preset,
        out.display()
    );
    run_grid(&grid, &options.preset, &out, &options.run, command)
}

/// Runs every cell of `grid` under `preset` in `out` (shared by `sweep` and `stability`).
pub fn run_grid(
    grid: &Grid,
    preset_name: &str,
    out: &Path,
    run: &GridRunOptions,
    command: String,
) -> Result<SweepOutcome> {
    let GridRunOptions {
        backend,
        retry_failed,
        quiet,
    } = *run;
    let preset = grid.preset(preset_name)?;
    let cells = grid.cells(&preset)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    // Refuse before training anything when a cell directory holds another config.
    for cell in &cells {
        check_cell_config(out, cell)?;
    }
    let manifest = SweepManifest {
        description: grid.file.description.clone(),
        grid: grid.origin.clone(),
        preset: preset_name.to_string(),
        preset_description: preset.description.clone(),
        command,
        collapse_floor_db: grid.collapse_floor(&preset),
        dynamic_gap_limit_db: grid.dynamic_gap_limit(&preset),
        charts: grid.file.charts.clone(),
        cells: cells.iter().map(CellRecord::from).collect(),
    };
    manifest.write(out)?;
    std::fs::write(out.join(GRID_COPY_FILE), &grid.text)
        .with_context(|| format!("cannot write {}", out.join(GRID_COPY_FILE).display()))?;

    let chosen = resolve(backend)?;
    eprintln!(
        "sweep {} ({} cells, preset {preset_name}) -> {} on {}",
        grid.origin,
        cells.len(),
        out.display(),
        chosen.description
    );
    for (i, cell) in cells.iter().enumerate() {
        let record = CellRecord::from(cell);
        let state = read_cell(out, &record)?;
        let label = format!("[{}/{}] {} / {}", i + 1, cells.len(), cell.scene, cell.name);
        match &state.status {
            CellStatus::Done => {
                eprintln!("{label}: done before, skipped");
                continue;
            }
            CellStatus::Failed(e) if !retry_failed => {
                eprintln!("{label}: failed before ({e}), skipped (--retry-failed trains it again)");
                continue;
            }
            _ => {}
        }
        eprintln!("{label}");
        // A panic in one cell (e.g. the rasterizer refusing a diverged model's footprints) is
        // that cell's failure: it is recorded and the sweep goes on.
        match panic_as_error(|| train_cell(out, cell, &chosen, quiet)) {
            Ok(()) => {}
            Err(e) => {
                let dir = out.join(&cell.dir);
                let error = format!("{e:#}");
                eprintln!("{label}: FAILED: {error}");
                let record = FailureRecord {
                    error,
                    step: checkpoint_step(&dir).unwrap_or(0),
                };
                let path = dir.join(FAILED_FILE);
                std::fs::create_dir_all(&dir)?;
                std::fs::write(&path, serde_json::to_string_pretty(&record)?)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
        }
        // After every cell, so a killed sweep still leaves a current table.
        let rows = super::results::read_rows(out, &manifest)?;
        write_csv(&out.join(RESULTS_FILE), &rows)?;
    }
    let rows = super::results::read_rows(out, &manifest)?;
    write_csv(&out.join(RESULTS_FILE), &rows)?;
    let outcome = SweepOutcome {
        dir: out.to_path_buf(),
        manifest,
        rows,
    };
    let report = super::report::write_report(&outcome.dir, &outcome.manifest, &outcome.rows)?;
    eprintln!(
        "{} cells done, {} failed -> {} and {}",
        outcome
            .rows
            .iter()
            .filter(|r| r.status == CellStatus::Done)
            .count(),
        outcome.failed(),
        out.join(RESULTS_FILE).display(),
        report.display()
    );
    Ok(outcome)
}

/// Runs `f`, turning a panic into an error carrying the panic's message.
pub fn panic_as_error<T>(f: impl FnOnce() -> Result<T>) -> Result<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(result) => result,
        Err(payload) => {
            let message = panic_message(&*payload).unwrap_or_else(|| "(no message)".into());
            bail!("panicked: {message}")
        }
    }
}

/// Trains (or resumes) one cell and evaluates it.
fn train_cell(out: &Path, cell: &Cell, chosen: &ChosenDevice, quiet: bool) -> Result<()> {
    let dir = out.join(&cell.dir);
    let resume = dir.join(CHECKPOINT_FILE).exists();
    // A retried cell's old failure is no longer its state.
    let failed = dir.join(FAILED_FILE);
    if failed.exists() {
        std::fs::remove_file(&failed)
            .with_context(|| format!("cannot remove {}", failed.display()))?;
    }
    train_run(cell.config.clone(), &dir, resume, chosen, None, quiet)?;
    Ok(())
}

/// A cell directory that already holds a run must hold this cell's config: a sweep re-run with
/// another preset or an edited grid would otherwise mix results.
fn check_cell_config(out: &Path, cell: &Cell) -> Result<()> {
    let path = out.join(&cell.dir).join(CONFIG_FILE);
    if !path.exists() {
        return Ok(());
    }
    let existing = TrainConfig::load(Some(&path), &[])?;
    if existing != cell.config {
        bail!(
            "{} was trained with another config than cell `{}` of this grid and preset now \
             resolves to (grid or preset changed?); pick another --out or remove that directory",
            path.display(),
            cell.name
        );
    }
    Ok(())
}

/// The step of a cell's checkpoint, read from its log (cheap; no model load).
fn checkpoint_step(dir: &Path) -> Option<usize> {
    let log = std::fs::read_to_string(dir.join(crate::run::LOG_FILE)).ok()?;
    log.lines()
        .last()?
        .split(',')
        .next()?
        .parse()
        .ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panicking_cell_becomes_an_error_with_its_message() {
        let formatted = panic_as_error::<()>(|| panic!("rasterizer: {} intersections", 7));
        assert_eq!(formatted.unwrap_err().to_string(), "panicked: rasterizer: 7 intersections");
        let literal = panic_as_error::<()>(|| panic!("literal"));
        assert_eq!(literal.unwrap_err().to_string(), "panicked: literal");
        let failed = panic_as_error::<()>(|| bail!("plain error"));
        assert_eq!(failed.unwrap_err().to_string(), "plain error");
        assert_eq!(panic_as_error(|| Ok(3)).unwrap(), 3);
    }
}
