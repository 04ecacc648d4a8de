//! Raw N3DV videos (`camXX.mp4`) to the `png/camXX/NNNNN.png` frames the loader reads, with ffmpeg
//! (`-vf fps=30`, as GIFStream's preprocessing). Frames are written to `png.partial/` and renamed
//! to `png/` when every video is done, so an interrupted extraction is redone, never half-used.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

fn videos(root: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(root)
        .with_context(|| format!("cannot list {}", root.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.starts_with("cam") && name.ends_with(".mp4")
        })
        .collect();
    v.sort();
    Ok(v)
}

/// Whether `program -version` runs.
pub fn tool_available(program: &str) -> bool {
    Command::new(program)
        .arg("-version")
        .output()
        .is_ok_and(|o| o.status.success())
}

pub fn extract_n3dv_videos(root: &Path) -> Result<()> {
    let videos = videos(root)?;
    if videos.is_empty() {
        bail!(
            "{}: no png/ frame folders and no camXX.mp4 videos",
            root.display()
        );
    }
    if !tool_available("ffmpeg") {
        bail!(
            "{}: png/ is missing and extracting its {} camXX.mp4 videos needs ffmpeg, which is not installed (e.g. apt-get install ffmpeg)",
            root.display(),
            videos.len()
        );
    }
    let partial = root.join("png.partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial)
            .with_context(|| format!("cannot clear {}", partial.display()))?;
    }
    for video in &videos {
        let stem = video.file_stem().unwrap().to_string_lossy().into_owned();
        let out = partial.join(&stem);
        std::fs::create_dir_all(&out)
            .with_context(|| format!("cannot create {}", out.display()))?;
        eprintln!("extracting {} ...", video.display());
        let status = Command::new("ffmpeg")
            .args(["-v", "error", "-nostdin", "-i"])
            .arg(video)
            .args(["-vf", "fps=30", "-start_number", "1"])
            .arg(out.join("%05d.png"))
            .status()
            .context("running ffmpeg")?;
        if !status.success() {
            bail!("{}: ffmpeg failed ({status})", video.display());
        }
    }
    std::fs::rename(&partial, root.join("png"))
        .with_context(|| format!("cannot move {} to png/", partial.display()))
}
