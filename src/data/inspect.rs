//! `acags dataset info`: load a dataset, check every frame, and report what is there and every
//! problem found.

use std::fmt::Write;
use std::path::Path;

use anyhow::{Result, bail};
use rayon::prelude::*;

use super::cameras::camera_center;
use super::frames::decode_frame;
use super::scene::{DatasetLayout, LoadOptions, PointSource, Scene};

/// Guesses the layout from the files present.
pub fn detect_layout(root: &Path) -> Result<DatasetLayout> {
    if !root.is_dir() {
        bail!("dataset directory {} does not exist", root.display());
    }
    if root.join("train_meta.json").exists() {
        Ok(DatasetLayout::Panoptic)
    } else if root.join("poses_bounds.npy").exists() || root.join("png").is_dir() {
        Ok(DatasetLayout::N3dv)
    } else {
        bail!(
            "{}: neither poses_bounds.npy (N3DV/MPEG) nor train_meta.json (Panoptic) found",
            root.display()
        )
    }
}

/// Loads a dataset of any layout.
pub fn load(root: &Path, layout: DatasetLayout, options: &LoadOptions) -> Result<Scene> {
    match layout {
        DatasetLayout::N3dv | DatasetLayout::Mpeg => super::n3dv::load(root, layout, options),
        DatasetLayout::Panoptic => super::panoptic::load(root, options),
    }
}

/// Checks every frame of the GOP: the file exists and has the camera's size; with `deep`, it
/// also decodes completely. Returns one line per problem.
pub fn check_frames(scene: &Scene, deep: bool) -> Vec<String> {
    let jobs: Vec<(usize, &std::path::PathBuf)> = scene
        .cameras
        .iter()
        .enumerate()
        .flat_map(|(c, cam)| cam.frame_paths.iter().map(move |p| (c, p)))
        .collect();
    let mut problems: Vec<String> = jobs
        .par_iter()
        .filter_map(|&(c, path)| {
            let expected = scene.cameras[c].source_size;
            if !path.is_file() {
                return Some(format!("{}: missing frame", path.display()));
            }
            if deep {
                return decode_frame(path, expected).err().map(|e| format!("{e:#}"));
            }
            match image::image_dimensions(path) {
                Err(e) => Some(format!("{}: unreadable image header ({e})", path.display())),
                Ok(size) if size != expected => Some(format!(
                    "{}: image is {}x{}, expected {}x{} like the camera's other frames",
                    path.display(),
                    size.0,
                    size.1,
                    expected.0,
                    expected.1
                )),
                Ok(_) => None,
            }
        })
        .collect();
    problems.sort();
    problems
}

/// Human-readable summary of a loaded scene.
pub fn describe(scene: &Scene) -> String {
    let mut s = String::new();
    let (w, h) = scene.resolution();
    let src = scene.cameras[0].source_size;
    let _ = writeln!(
        s,
        "dataset     {} ({:?})",
        scene.root.display(),
        scene.layout
    );
    let _ = writeln!(
        s,
        "cameras     {} ({} train, {} test: {})",
        scene.cameras.len(),
        scene.train_cameras.len(),
        scene.test_cameras.len(),
        scene
            .test_cameras
            .iter()
            .map(|&i| scene.cameras[i].name.clone())
            .collect::<Vec<_>>()
            .join(", ")
    );
    let _ = writeln!(
        s,
        "frames      {} available; GOP {}..{} ({} frames)",
        scene.frames_available,
        scene.frames.start,
        scene.frames.start + scene.frames.count,
        scene.frames.count
    );
    let _ = writeln!(
        s,
        "resolution  {w}x{h} (files {}x{}, downscale {}, {:?})",
        src.0, src.1, scene.downscale, scene.resample
    );
    let cam0 = &scene.cameras[0].camera;
    let _ = writeln!(
        s,
        "intrinsics  fx {:.2} fy {:.2} cx {:.2} cy {:.2} (camera {})",
        cam0.fx, cam0.fy, cam0.cx, cam0.cy, scene.cameras[0].name
    );
    let source = match &scene.point_source {
        PointSource::File(p) => p.display().to_string(),
        PointSource::RandomInFrusta { seed } => {
            format!("random inside the camera frusta (seed {seed})")
        }
    };
    let _ = writeln!(s, "points      {} from {source}", scene.points.len());
    if let Some((lo, hi)) = scene.points.bounds() {
        let _ = writeln!(
            s,
            "bounds      points [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}]",
            lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
        );
    }
    let centers: Vec<[f64; 3]> = scene
        .cameras
        .iter()
        .map(|c| camera_center(&c.camera))
        .collect();
    let lo: [f64; 3] =
        std::array::from_fn(|i| centers.iter().map(|c| c[i]).fold(f64::INFINITY, f64::min));
    let hi: [f64; 3] = std::array::from_fn(|i| {
        centers
            .iter()
            .map(|c| c[i])
            .fold(f64::NEG_INFINITY, f64::max)
    });
    let _ = writeln!(
        s,
        "            cameras [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}]; depth {:.3} .. {:.3}",
        lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], scene.depth_range.0, scene.depth_range.1
    );
    s
}

/// A full report: the summary (when the dataset loads) and every problem.
pub struct DatasetReport {
    pub summary: Option<String>,
    pub problems: Vec<String>,
}

pub fn inspect(
    root: &Path,
    layout: Option<DatasetLayout>,
    options: &LoadOptions,
    deep: bool,
) -> DatasetReport {
    let layout = match layout.map(Ok).unwrap_or_else(|| detect_layout(root)) {
        Ok(l) => l,
        Err(e) => {
            return DatasetReport {
                summary: None,
                problems: vec![format!("{e:#}")],
            };
        }
    };
    match load(root, layout, options) {
        Err(e) => DatasetReport {
            summary: None,
            problems: vec![format!("{e:#}")],
        },
        Ok(scene) => {
            let mut problems = check_frames(&scene, deep);
            if let PointSource::RandomInFrusta { .. } = scene.point_source {
                problems.push(format!(
                    "{}: no point cloud; training would start from random points",
                    root.display()
                ));
            }
            DatasetReport {
                summary: Some(describe(&scene)),
                problems,
            }
        }
    }
}
