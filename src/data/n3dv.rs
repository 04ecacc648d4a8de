//! GIFStream's preprocessed N3DV layout, also used for MPEG sequences:
//!
//! ```text
//! <root>/poses_bounds.npy               N×17 LLFF poses + near/far, one row per camera (sorted)
//! <root>/png/camXX/NNNNN.png            frames, 1-indexed: frame f is {f+1:05}.png
//! <root>/colmap_<start>/sparse/0/points3D.{bin,txt}   initial points (or <root>/points3D.ply)
//! <root>/camXX.mp4                      raw videos, extracted to png/ with ffmpeg when png/ is absent
//! ```

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rand::{Rng, SeedableRng, rngs::StdRng};

use super::cameras::{LlffPose, camera_to_c2w, rescale_camera};
use super::colmap::{read_points_ply, read_points3d_bin, read_points3d_txt};
use super::npy::read_npy;
use super::scene::{
    DatasetLayout, LoadOptions, PointCloud, PointSource, Scene, SceneCamera, split_cameras,
};
use super::video;
use crate::raster::RasterCamera;

/// Points drawn by the random initialisation when no point file exists.
pub const RANDOM_INIT_POINTS: usize = 20_000;

/// Default test cameras (indices into the sorted camera list).
pub fn default_test_cameras(layout: DatasetLayout) -> Vec<usize> {
    match layout {
        DatasetLayout::Mpeg => vec![8, 10, 12],
        _ => vec![0],
    }
}

/// 1-indexed frame file name of 0-based frame `f`.
pub fn frame_file_name(f: usize) -> String {
    format!("{:05}.png", f + 1)
}

fn sorted_dirs(dir: &Path, prefix: &str) -> Result<Vec<PathBuf>> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_dir()
                && p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with(prefix))
        })
        .collect();
    dirs.sort();
    Ok(dirs)
}

/// Frames present in a camera folder: the count of consecutive `00001.png, 00002.png, ...`.
fn count_frames(dir: &Path) -> Result<usize> {
    let mut present = std::collections::BTreeSet::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let name = entry?.file_name();
        let Some(name) = name.to_str() else { continue };
        if let Some(stem) = name.strip_suffix(".png")
            && let Ok(n) = stem.parse::<usize>()
            && n >= 1
        {
            present.insert(n - 1);
        }
    }
    let contiguous = present
        .iter()
        .enumerate()
        .take_while(|(i, f)| i == *f)
        .count();
    if contiguous != present.len() {
        bail!(
            "{}: missing frame {} ({} present after it)",
            dir.display(),
            dir.join(frame_file_name(contiguous)).display(),
            present.len() - contiguous
        );
    }
    Ok(contiguous)
}

fn load_points(root: &Path, start: usize) -> Result<Option<(PointCloud, PathBuf)>> {
    let sparse = root.join(format!("colmap_{start}/sparse/0"));
    for (path, reader) in [
        (
            sparse.join("points3D.bin"),
            read_points3d_bin as fn(&Path) -> Result<PointCloud>,
        ),
        (sparse.join("points3D.txt"), read_points3d_txt),
        (root.join("points3D.ply"), read_points_ply),
    ] {
        if path.is_file() {
            let cloud = reader(&path)?;
            if cloud.is_empty() {
                bail!("{}: the point cloud is empty", path.display());
            }
            return Ok(Some((cloud, path)));
        }
    }
    Ok(None)
}

/// Uniform random points inside the camera frusta: a random camera, a random pixel and a depth
/// uniform in inverse depth between near and far (denser close to the cameras, like SfM points),
/// grey colour. Used, with a warning, when a dataset has no point cloud.
pub fn random_points_in_frusta(
    cameras: &[RasterCamera],
    depth_range: (f32, f32),
    count: usize,
    seed: u64,
) -> PointCloud {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut cloud = PointCloud::default();
    let (near, far) = (
        depth_range.0.max(1e-3) as f64,
        depth_range.1.max(depth_range.0 * 1.01) as f64,
    );
    for _ in 0..count {
        let cam = &cameras[rng.random_range(0..cameras.len())];
        let (c2w, center) = camera_to_c2w(cam);
        let u = rng.random_range(0.0..cam.width as f64);
        let v = rng.random_range(0.0..cam.height as f64);
        let inv = rng.random_range(1.0 / far..1.0 / near);
        let z = 1.0 / inv;
        let dir_cam = glam::DVec3::new(
            (u - cam.cx as f64) / cam.fx as f64,
            (v - cam.cy as f64) / cam.fy as f64,
            1.0,
        );
        let p = center + c2w * (dir_cam * z);
        cloud.positions.push(p.as_vec3().to_array());
        cloud.colors.push([0.5; 3]);
    }
    cloud
}

/// Loads an N3DV- or MPEG-layout dataset.
pub fn load(root: &Path, layout: DatasetLayout, options: &LoadOptions) -> Result<Scene> {
    if !root.is_dir() {
        bail!("dataset directory {} does not exist", root.display());
    }
    let poses_path = root.join("poses_bounds.npy");
    if !poses_path.is_file() {
        bail!(
            "{}: missing (LLFF poses and bounds, N×17)",
            poses_path.display()
        );
    }
    let poses = read_npy(&poses_path)?;
    let n_poses = poses
        .expect_matrix(17, "poses_bounds.npy")
        .with_context(|| format!("{}", poses_path.display()))?;

    let png = root.join("png");
    if !png.is_dir() {
        video::extract_n3dv_videos(root)?;
    }
    let camera_dirs = sorted_dirs(&png, "cam")?;
    if camera_dirs.len() != n_poses {
        bail!(
            "{} has {n_poses} cameras but {} has {} camera folders (cam*)",
            poses_path.display(),
            png.display(),
            camera_dirs.len()
        );
    }
    if camera_dirs.is_empty() {
        bail!("{}: no cameras", png.display());
    }

    let mut frames_available = usize::MAX;
    for dir in &camera_dirs {
        let n = count_frames(dir)?;
        if n == 0 {
            bail!(
                "{}: no frames (expected 00001.png, 00002.png, ...)",
                dir.display()
            );
        }
        frames_available = frames_available.min(n);
    }
    let frames = options.gop(frames_available)?;

    let mut cameras = Vec::with_capacity(n_poses);
    let mut depth_range = (f32::INFINITY, 0.0f32);
    for (i, dir) in camera_dirs.iter().enumerate() {
        let pose = LlffPose::from_row(poses.row(i))?;
        let llff_camera = pose
            .to_camera()
            .with_context(|| format!("{}: row {i}", poses_path.display()))?;
        if !(pose.near > 0.0 && pose.far > pose.near) {
            bail!(
                "{}: row {i} has bounds near {} far {}",
                poses_path.display(),
                pose.near,
                pose.far
            );
        }
        depth_range = (
            depth_range.0.min(pose.near as f32),
            depth_range.1.max(pose.far as f32),
        );
        let frame_paths: Vec<PathBuf> = frames
            .frames()
            .map(|f| dir.join(frame_file_name(f)))
            .collect();
        let first = &frame_paths[0];
        let source_size = image::image_dimensions(first)
            .with_context(|| format!("{}: cannot read image header", first.display()))?;
        // GIFStream rescales K to the actual image size, then to the downscaled size.
        let camera = rescale_camera(&llff_camera, source_size.0, source_size.1);
        let (w, h) = (
            source_size.0 / options.downscale,
            source_size.1 / options.downscale,
        );
        if w == 0 || h == 0 {
            bail!(
                "{}: {}x{} images cannot be downscaled by {}",
                first.display(),
                source_size.0,
                source_size.1,
                options.downscale
            );
        }
        let name = dir.file_name().unwrap().to_string_lossy().into_owned();
        cameras.push(SceneCamera {
            name,
            camera: rescale_camera(&camera, w, h),
            frame_paths,
            source_size,
        });
    }
    let sizes: std::collections::BTreeSet<(u32, u32)> =
        cameras.iter().map(|c| c.source_size).collect();
    if sizes.len() > 1 {
        let detail: Vec<String> = cameras
            .iter()
            .map(|c| format!("{} {}x{}", c.name, c.source_size.0, c.source_size.1))
            .collect();
        bail!(
            "{}: cameras have different image sizes: {}",
            png.display(),
            detail.join(", ")
        );
    }

    let test = options
        .test_cameras
        .clone()
        .unwrap_or_else(|| default_test_cameras(layout));
    let (train_cameras, test_cameras) =
        split_cameras(cameras.len(), &test, &options.removed_cameras)?;

    let (points, point_source) = match load_points(root, options.start_frame)? {
        Some((cloud, path)) => (cloud, PointSource::File(path)),
        None => {
            let seed = 0;
            eprintln!(
                "warning: {} has no colmap_{}/sparse/0/points3D.{{bin,txt}} nor points3D.ply; initialising {RANDOM_INIT_POINTS} random points inside the camera frusta",
                root.display(),
                options.start_frame
            );
            let raw: Vec<RasterCamera> = cameras.iter().map(|c| c.camera).collect();
            (
                random_points_in_frusta(&raw, depth_range, RANDOM_INIT_POINTS, seed),
                PointSource::RandomInFrusta { seed },
            )
        }
    };

    Ok(Scene {
        root: root.to_path_buf(),
        layout,
        cameras,
        frames,
        frames_available,
        train_cameras,
        test_cameras,
        points,
        point_source,
        depth_range,
        downscale: options.downscale,
        resample: options.resample,
    })
}
