//! Dataset names as users write them: a directory, or `synthetic:<preset>`, generated once into
//! a cache directory (`$ACAGS_CACHE_DIR`, else `$XDG_CACHE_HOME/acags`, else `~/.cache/acags`).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::ValueEnum;

use super::synthetic::{GENERATOR_VERSION, SyntheticPreset, write_dataset};

/// The cache directory for generated datasets.
pub fn cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("ACAGS_CACHE_DIR") {
        return PathBuf::from(dir);
    }
    if let Some(dir) = std::env::var_os("XDG_CACHE_HOME") {
        return PathBuf::from(dir).join("acags");
    }
    std::env::var_os("HOME")
        .map(|h| PathBuf::from(h).join(".cache/acags"))
        .unwrap_or_else(|| std::env::temp_dir().join("acags-cache"))
}

/// `synthetic:fast` → its preset; anything else → `None`.
pub fn synthetic_preset(name: &str) -> Result<Option<SyntheticPreset>> {
    let Some(preset) = name.strip_prefix("synthetic:") else {
        return Ok(None);
    };
    <SyntheticPreset as clap::ValueEnum>::from_str(preset, false)
        .map(Some)
        .map_err(|_| {
            let names: Vec<String> = SyntheticPreset::value_variants()
                .iter()
                .map(|p| format!("synthetic:{}", p.name()))
                .collect();
            anyhow::anyhow!(
                "unknown synthetic preset `{preset}` (expected one of {})",
                names.join(", ")
            )
        })
}

/// The directory holding `name`, generating a synthetic scene on first use. Generation writes into
/// a private temporary directory and renames it into place, so concurrent or interrupted runs
/// never see a half-written scene.
pub fn dataset_dir(name: &str) -> Result<PathBuf> {
    let Some(preset) = synthetic_preset(name)? else {
        return Ok(PathBuf::from(name));
    };
    let cache = cache_dir();
    // Versioned: a cache written by an older generator is not silently reused.
    let dir = cache.join(format!("synthetic-{}-v{GENERATOR_VERSION}", preset.name()));
    if dir.join("poses_bounds.npy").exists() {
        return Ok(dir);
    }
    std::fs::create_dir_all(&cache)
        .with_context(|| format!("cannot create the cache directory {}", cache.display()))?;
    // Unique per call: threads of one process may generate concurrently.
    static CALLS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = cache.join(format!(
        ".synthetic-{}.partial-{}-{call}",
        preset.name(),
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).ok();
    }
    eprintln!("generating {name} into {} (once)", dir.display());
    write_dataset(preset, &tmp)?;
    if let Err(e) = std::fs::rename(&tmp, &dir) {
        // Another process may have finished first; its copy is as good as ours.
        std::fs::remove_dir_all(&tmp).ok();
        if !dir.join("poses_bounds.npy").exists() {
            return Err(e).with_context(|| format!("cannot move the scene to {}", dir.display()));
        }
    }
    Ok(dir)
}

/// True when `path` is a generated synthetic scene (it carries `synthetic.json`).
pub fn is_synthetic(path: &Path) -> bool {
    path.join("synthetic.json").exists()
}
