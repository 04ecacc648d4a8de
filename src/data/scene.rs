//! The one scene type every loader produces.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::raster::RasterCamera;

/// Which on-disk layout a dataset uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DatasetLayout {
    /// GIFStream's preprocessed Neural 3D Video layout (test camera 00).
    N3dv,
    /// MPEG GSC sequences in the same layout (test cameras = sorted indices 8, 10, 12).
    Mpeg,
    /// Dynamic3DGS's Panoptic Sports release (`train_meta.json` / `test_meta.json`).
    Panoptic,
}

/// How images are resampled when downscaled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Resample {
    /// Mean over each factor×factor block (OpenCV INTER_AREA); for factor 2 this is also what
    /// OpenCV's INTER_LINEAR (GIFStream's choice) computes. Needs an integer factor.
    #[default]
    Area,
    /// OpenCV INTER_LINEAR: bilinear sample at ((x + 0.5)·f − 0.5, (y + 0.5)·f − 0.5).
    Bilinear,
}

/// The frames of one GOP: `start .. start + count` (0-based frame indices).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameRange {
    pub start: usize,
    pub count: usize,
}

impl FrameRange {
    pub fn frames(&self) -> std::ops::Range<usize> {
        self.start..self.start + self.count
    }

    /// Normalised time in [0, 1] inside the GOP: (frame − start) / (count − 1); 0 for one frame.
    pub fn time(&self, frame: usize) -> f32 {
        if self.count <= 1 {
            0.0
        } else {
            (frame - self.start) as f32 / (self.count - 1) as f32
        }
    }

    /// Frame index for a normalised time, as GIFStream does: start + int(t·(T − 1)).
    pub fn frame_at(&self, time: f32) -> usize {
        self.start + ((time.clamp(0.0, 1.0) * (self.count.saturating_sub(1)) as f32) as usize)
    }
}

/// What to load.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadOptions {
    /// First frame of the GOP (0-based).
    pub start_frame: usize,
    /// Frames in the GOP; `None` = every frame from `start_frame` on.
    pub frame_count: Option<usize>,
    /// Integer downscale factor (1 = full resolution; N3DV uses 2).
    pub downscale: u32,
    pub resample: Resample,
    /// Test cameras as indices into the sorted camera list; `None` = the layout's default.
    pub test_cameras: Option<Vec<usize>>,
    /// Cameras left out of both splits (GIFStream's coffee_martini drops index 12).
    pub removed_cameras: Vec<usize>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            start_frame: 0,
            frame_count: None,
            downscale: 1,
            resample: Resample::Area,
            test_cameras: None,
            removed_cameras: Vec::new(),
        }
    }
}

impl LoadOptions {
    /// The GOP to load when `available` frames exist.
    pub fn gop(&self, available: usize) -> anyhow::Result<FrameRange> {
        if self.downscale == 0 {
            anyhow::bail!("downscale factor must be at least 1");
        }
        if self.start_frame >= available {
            anyhow::bail!(
                "start frame {} is beyond the {available} frames every camera has",
                self.start_frame
            );
        }
        let count = self.frame_count.unwrap_or(available - self.start_frame);
        if count == 0 || self.start_frame + count > available {
            anyhow::bail!(
                "frames {}..{} requested but every camera has only {available}",
                self.start_frame,
                self.start_frame + count
            );
        }
        Ok(FrameRange {
            start: self.start_frame,
            count,
        })
    }
}

/// A camera of the rig, at the resolution the images are served at.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneCamera {
    pub name: String,
    pub camera: RasterCamera,
    /// Image file of each frame of the GOP (index = frame − start).
    pub frame_paths: Vec<PathBuf>,
    /// Size of the files on disk (before downscaling).
    pub source_size: (u32, u32),
}

/// Initial points with colours in [0, 1].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<[f32; 3]>,
    pub colors: Vec<[f32; 3]>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Axis-aligned bounds, `None` when empty.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), p| {
            (
                std::array::from_fn(|i| lo[i].min(p[i])),
                std::array::from_fn(|i| hi[i].max(p[i])),
            )
        }))
    }
}

/// Where the initial points came from.
#[derive(Clone, Debug, PartialEq)]
pub enum PointSource {
    File(PathBuf),
    /// No point file: random points inside the camera frusta (see `n3dv::random_points_in_frusta`).
    RandomInFrusta {
        seed: u64,
    },
}

/// A loaded multi-view video scene (one GOP).
#[derive(Clone, Debug)]
pub struct Scene {
    pub root: PathBuf,
    pub layout: DatasetLayout,
    /// Sorted by name; indices into this list are the camera indices used everywhere.
    pub cameras: Vec<SceneCamera>,
    pub frames: FrameRange,
    /// Total frames available on disk (before choosing the GOP).
    pub frames_available: usize,
    pub train_cameras: Vec<usize>,
    pub test_cameras: Vec<usize>,
    pub points: PointCloud,
    pub point_source: PointSource,
    /// Depth bounds of the scene (LLFF near/far, or from the points), for frustum initialisation.
    pub depth_range: (f32, f32),
    pub downscale: u32,
    pub resample: Resample,
}

/// One training or test image: a camera at a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct ViewId {
    pub camera: usize,
    pub frame: usize,
}

impl Scene {
    /// Image size served (after downscaling).
    pub fn resolution(&self) -> (u32, u32) {
        self.cameras
            .first()
            .map(|c| (c.camera.width, c.camera.height))
            .unwrap_or((0, 0))
    }

    pub fn train_views(&self) -> Vec<ViewId> {
        self.views(&self.train_cameras)
    }

    pub fn test_views(&self) -> Vec<ViewId> {
        self.views(&self.test_cameras)
    }

    fn views(&self, cameras: &[usize]) -> Vec<ViewId> {
        cameras
            .iter()
            .flat_map(|&camera| {
                self.frames
                    .frames()
                    .map(move |frame| ViewId { camera, frame })
            })
            .collect()
    }

    /// "test" or "train": the split camera `camera` belongs to (as manifests name it).
    pub fn split_name(&self, camera: usize) -> &'static str {
        if self.test_cameras.contains(&camera) {
            "test"
        } else {
            "train"
        }
    }

    /// Normalised time of a frame inside the GOP.
    pub fn time(&self, frame: usize) -> f32 {
        self.frames.time(frame)
    }

    pub fn frame_path(&self, view: ViewId) -> &std::path::Path {
        &self.cameras[view.camera].frame_paths[view.frame - self.frames.start]
    }
}

/// Splits camera indices into train and test, validating the requested indices.
pub fn split_cameras(
    count: usize,
    test: &[usize],
    removed: &[usize],
) -> anyhow::Result<(Vec<usize>, Vec<usize>)> {
    for &i in test.iter().chain(removed) {
        if i >= count {
            anyhow::bail!("camera index {i} does not exist (the rig has {count} cameras)");
        }
    }
    let train = (0..count)
        .filter(|i| !test.contains(i) && !removed.contains(i))
        .collect();
    let test = test
        .iter()
        .copied()
        .filter(|i| !removed.contains(i))
        .collect();
    Ok((train, test))
}
