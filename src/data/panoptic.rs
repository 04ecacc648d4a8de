//! Panoptic Sports as released by Dynamic3DGS:
//!
//! ```text
//! <root>/train_meta.json, test_meta.json   {w, h, k[t][c], w2c[t][c], fn[t][c], cam_id[t][c]}
//! <root>/ims/<cam>/<t:06>.jpg             frames (fn gives the relative name)
//! <root>/init_pt_cld.npz                  "data": P×7 = xyz, rgb, seg
//! ```
//!
//! Cameras are static over time in the release; the loader checks that and uses timestep 0's.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::Deserialize;

use super::cameras::{camera_from_d3dgs, rescale_camera};
use super::npy::read_npz_array;
use super::scene::{DatasetLayout, LoadOptions, PointCloud, PointSource, Scene, SceneCamera};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Meta {
    w: u32,
    h: u32,
    k: Vec<Vec<[[f64; 3]; 3]>>,
    w2c: Vec<Vec<[[f64; 4]; 4]>>,
    #[serde(rename = "fn")]
    file_names: Vec<Vec<String>>,
    cam_id: Vec<Vec<i64>>,
}

fn read_meta(path: &Path) -> Result<Meta> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: missing or unreadable", path.display()))?;
    let mut de = serde_json::Deserializer::from_str(&text);
    let meta: Meta = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let field = e.path().to_string();
        anyhow::anyhow!("{}: field '{field}': {}", path.display(), e.into_inner())
    })?;
    let t = meta.file_names.len();
    if t == 0 {
        bail!("{}: no timesteps", path.display());
    }
    for (name, len) in [
        ("k", meta.k.len()),
        ("w2c", meta.w2c.len()),
        ("cam_id", meta.cam_id.len()),
    ] {
        if len != t {
            bail!(
                "{}: '{name}' has {len} timesteps but 'fn' has {t}",
                path.display()
            );
        }
    }
    for ti in 0..t {
        let c = meta.file_names[ti].len();
        if meta.k[ti].len() != c || meta.w2c[ti].len() != c || meta.cam_id[ti].len() != c {
            bail!(
                "{}: timestep {ti} lists different camera counts in k / w2c / fn / cam_id",
                path.display()
            );
        }
    }
    Ok(meta)
}

struct CameraTrack {
    k: [[f64; 3]; 3],
    w2c: [[f64; 4]; 4],
    files: Vec<String>,
}

/// Per camera id, its intrinsics/extrinsics and its file per timestep.
fn tracks(meta: &Meta, path: &Path) -> Result<BTreeMap<i64, CameraTrack>> {
    let mut out: BTreeMap<i64, CameraTrack> = BTreeMap::new();
    for t in 0..meta.file_names.len() {
        for c in 0..meta.file_names[t].len() {
            let id = meta.cam_id[t][c];
            let entry = out.entry(id).or_insert_with(|| CameraTrack {
                k: meta.k[t][c],
                w2c: meta.w2c[t][c],
                files: Vec::new(),
            });
            let moved = entry
                .k
                .iter()
                .flatten()
                .zip(meta.k[t][c].iter().flatten())
                .chain(
                    entry
                        .w2c
                        .iter()
                        .flatten()
                        .zip(meta.w2c[t][c].iter().flatten()),
                )
                .any(|(a, b)| (a - b).abs() > 1e-6 * a.abs().max(1.0));
            if moved {
                bail!(
                    "{}: camera {id} changes its intrinsics or pose at timestep {t}; moving cameras are not supported",
                    path.display()
                );
            }
            if entry.files.len() != t {
                bail!(
                    "{}: camera {id} is missing from timestep {}",
                    path.display(),
                    entry.files.len()
                );
            }
            entry.files.push(meta.file_names[t][c].clone());
        }
    }
    Ok(out)
}

pub fn load(root: &Path, options: &LoadOptions) -> Result<Scene> {
    if !root.is_dir() {
        bail!("dataset directory {} does not exist", root.display());
    }
    let train_path = root.join("train_meta.json");
    let test_path = root.join("test_meta.json");
    let train = read_meta(&train_path)?;
    let test = read_meta(&test_path)?;
    if (train.w, train.h) != (test.w, test.h) {
        bail!(
            "{} says {}x{} but {} says {}x{}",
            train_path.display(),
            train.w,
            train.h,
            test_path.display(),
            test.w,
            test.h
        );
    }
    if train.file_names.len() != test.file_names.len() {
        bail!(
            "{} has {} timesteps but {} has {}",
            train_path.display(),
            train.file_names.len(),
            test_path.display(),
            test.file_names.len()
        );
    }
    let frames_available = train.file_names.len();
    let frames = options.gop(frames_available)?;

    // Cameras sorted by id; the split comes from the meta files, not from indices.
    let train_tracks = tracks(&train, &train_path)?;
    let test_tracks = tracks(&test, &test_path)?;
    if let Some(id) = train_tracks.keys().find(|id| test_tracks.contains_key(id)) {
        bail!(
            "camera {id} is in both {} and {}",
            train_path.display(),
            test_path.display()
        );
    }
    let mut all: Vec<(i64, bool, &CameraTrack)> = train_tracks
        .iter()
        .map(|(id, t)| (*id, false, t))
        .chain(test_tracks.iter().map(|(id, t)| (*id, true, t)))
        .collect();
    all.sort_by_key(|(id, _, _)| *id);

    let (w, h) = (train.w / options.downscale, train.h / options.downscale);
    let mut cameras = Vec::new();
    let (mut train_cameras, mut test_cameras) = (Vec::new(), Vec::new());
    for (index, (id, is_test, track)) in all.iter().enumerate() {
        let camera =
            camera_from_d3dgs(&track.k, &track.w2c, train.w, train.h).with_context(|| {
                format!(
                    "{}: camera {id}",
                    if *is_test { &test_path } else { &train_path }.display()
                )
            })?;
        let frame_paths: Vec<PathBuf> = frames
            .frames()
            .map(|t| root.join("ims").join(&track.files[t]))
            .collect();
        if options.removed_cameras.contains(&index) {
            // Kept in the camera list so indices stay stable, but in neither split.
        } else if *is_test {
            test_cameras.push(index);
        } else {
            train_cameras.push(index);
        }
        cameras.push(SceneCamera {
            name: id.to_string(),
            camera: rescale_camera(&camera, w, h),
            frame_paths,
            source_size: (train.w, train.h),
        });
    }
    if options.test_cameras.is_some() {
        bail!("Panoptic's test cameras come from test_meta.json; --test-cameras does not apply");
    }

    let npz = root.join("init_pt_cld.npz");
    let data = read_npz_array(&npz, "data")?;
    let rows = data
        .expect_matrix(7, "init_pt_cld.npz 'data'")
        .with_context(|| format!("{}", npz.display()))?;
    if rows == 0 {
        bail!("{}: the point cloud is empty", npz.display());
    }
    let mut points = PointCloud::default();
    let color_scale = if (0..rows).any(|r| data.row(r)[3..6].iter().any(|v| *v > 1.0)) {
        1.0 / 255.0
    } else {
        1.0
    };
    for r in 0..rows {
        let row = data.row(r);
        if row[..6].iter().any(|v| !v.is_finite()) {
            bail!("{}: point {r} has a non-finite value", npz.display());
        }
        points
            .positions
            .push([row[0] as f32, row[1] as f32, row[2] as f32]);
        points.colors.push([
            (row[3] * color_scale) as f32,
            (row[4] * color_scale) as f32,
            (row[5] * color_scale) as f32,
        ]);
    }
    // Dynamic3DGS renders with near 1 and far 100 (metres).
    let depth_range = (1.0, 100.0);
    Ok(Scene {
        root: root.to_path_buf(),
        layout: DatasetLayout::Panoptic,
        cameras,
        frames,
        frames_available,
        train_cameras,
        test_cameras,
        points,
        point_source: PointSource::File(npz),
        depth_range,
        downscale: options.downscale,
        resample: options.resample,
    })
}
