//! Datasets: camera conventions with worked examples, the N3DV/MPEG/Panoptic loaders on small
//! datasets generated here, the synthetic scene through the N3DV path, frame cache, sampler, and
//! an error naming the file for each kind of bad input.

mod common;
use common::TempDir;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, OnceLock};

use acags::data::cameras::{LlffPose, camera_from_d3dgs, project_point};
use acags::data::colmap::{read_points3d_bin, read_points3d_txt, write_points3d_txt};
use acags::data::frames::{Frame, FrameCache, downscale};
use acags::data::npy::write_npy_f64;
use acags::data::sampler::ViewSampler;
use acags::data::scene::PointSource;
use acags::data::synthetic::{SyntheticPreset, rig, write_dataset};
use acags::data::{DatasetLayout, FrameRange, LoadOptions, PointCloud, Resample, ViewId, load};

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_dir(&entry.path(), &target)
        } else {
            std::fs::copy(entry.path(), target).map(|_| ()).unwrap()
        }
    }
}

fn temp_dir(tag: &str) -> TempDir {
    TempDir::new(&format!("acags-data-{tag}"))
}

fn err_text(r: anyhow::Result<impl std::fmt::Debug>) -> String {
    format!("{:#}", r.expect_err("expected an error"))
}

fn assert_close(a: [f64; 2], b: [f64; 2], tol: f64) {
    assert!(
        (a[0] - b[0]).abs() <= tol && (a[1] - b[1]).abs() <= tol,
        "{a:?} vs {b:?}"
    );
}

// ---------------------------------------------------------------- camera conventions

/// LLFF stores camera-to-world columns (down, right, back). A camera at C = (1, 2, 3) looking
/// down +z (OpenCV identity rotation) sees C + (0.5, -0.25, 2) at x = 50·0.5/2 + 100,
/// y = 50·(-0.25)/2 + 50 (f = 50, 200×100 image, principal point at W//2, H//2).
#[test]
fn llff_pose_projects_a_known_point_to_a_known_pixel() {
    let row = [
        0.0, 1.0, 0.0, 1.0, 100.0, //
        1.0, 0.0, 0.0, 2.0, 200.0, //
        0.0, 0.0, -1.0, 3.0, 50.0, //
        0.5, 20.0,
    ];
    let camera = LlffPose::from_row(&row).unwrap().to_camera().unwrap();
    assert_eq!(
        (camera.width, camera.height, camera.fx, camera.cx, camera.cy),
        (200, 100, 50.0, 100.0, 50.0)
    );
    assert_close(
        project_point(&camera, [1.5, 1.75, 5.0]).unwrap(),
        [112.5, 43.75],
        1e-4,
    );
    // Behind the camera: no pixel.
    assert!(project_point(&camera, [1.0, 2.0, 2.0]).is_none());
}

/// A camera rotated 90 degrees about the world y axis: LLFF columns for OpenCV axes
/// right = -z_w, down = y_w, forward = x_w. The world point 4 units along +x from the centre lands
/// on the principal point; one unit towards -z_w lands fx/4 pixels to the right.
#[test]
fn llff_rotated_pose_and_round_trip() {
    let (right, down, forward) = ([0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]);
    let back = forward.map(|v: f64| -v);
    let mut row = [0.0; 17];
    for r in 0..3 {
        row[r * 5] = down[r];
        row[r * 5 + 1] = right[r];
        row[r * 5 + 2] = back[r];
        row[r * 5 + 3] = [0.0, 0.0, 0.0][r];
    }
    row[4] = 60.0;
    row[9] = 80.0;
    row[14] = 40.0;
    row[15] = 0.1;
    row[16] = 10.0;
    let pose = LlffPose::from_row(&row).unwrap();
    let camera = pose.to_camera().unwrap();
    assert_close(
        project_point(&camera, [4.0, 0.0, 0.0]).unwrap(),
        [40.0, 30.0],
        1e-4,
    );
    assert_close(
        project_point(&camera, [4.0, 0.0, -1.0]).unwrap(),
        [50.0, 30.0],
        1e-4,
    );
    let back_again = LlffPose::from_camera(&camera, 0.1, 10.0);
    for (a, b) in back_again.to_row().iter().zip(&row) {
        assert!((a - b).abs() < 1e-6, "{:?} vs {row:?}", back_again.to_row());
    }
}

/// Dynamic3DGS stores K and w2c in OpenCV convention: a camera 5 units behind the origin sees
/// (0.1, 0.2, 0) at (32 + 100·0.1/5, 24 + 100·0.2/5).
#[test]
fn d3dgs_camera_projects_a_known_point() {
    let k = [[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]];
    let w2c = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 5.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let camera = camera_from_d3dgs(&k, &w2c, 64, 48).unwrap();
    assert_close(
        project_point(&camera, [0.1, 0.2, 0.0]).unwrap(),
        [34.0, 28.0],
        1e-5,
    );
    let skewed = [[100.0, 1.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]];
    assert!(camera_from_d3dgs(&skewed, &w2c, 64, 48).is_err());
}

#[test]
fn gop_time_and_frame_mapping() {
    let gop = FrameRange {
        start: 50,
        count: 65,
    };
    assert_eq!(gop.time(50), 0.0);
    assert_eq!(gop.time(114), 1.0);
    assert_eq!(gop.time(82), 0.5);
    assert_eq!(gop.frame_at(0.5), 82);
    assert_eq!(gop.frame_at(1.0), 114);
    assert_eq!(FrameRange { start: 3, count: 1 }.time(3), 0.0);
}

// ---------------------------------------------------------------- small datasets in each layout

fn write_png(path: &Path, w: u32, h: u32, seed: u8) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([seed, (x * 10) as u8, (y * 10) as u8])
    })
    .save(path)
    .unwrap();
}

/// `cameras` cameras in a row along x looking down +z, `frames` frames of w×h.
fn write_n3dv(root: &Path, cameras: usize, frames: usize, w: u32, h: u32) {
    let mut rows = Vec::new();
    for c in 0..cameras {
        rows.extend([
            0.0,
            1.0,
            0.0,
            c as f64 * 0.1,
            h as f64,
            1.0,
            0.0,
            0.0,
            0.0,
            w as f64,
            0.0,
            0.0,
            -1.0,
            0.0,
            w as f64 * 0.8,
            0.5,
            10.0,
        ]);
        for f in 0..frames {
            write_png(
                &root.join(format!("png/cam{c:02}/{:05}.png", f + 1)),
                w,
                h,
                (c * 10 + f) as u8,
            );
        }
    }
    write_npy_f64(&root.join("poses_bounds.npy"), &[cameras, 17], &rows).unwrap();
    let sparse = root.join("colmap_0/sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    let cloud = PointCloud {
        positions: vec![[0.0, 0.0, 2.0], [0.1, -0.1, 3.0]],
        colors: vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    write_points3d_txt(&sparse.join("points3D.txt"), &cloud).unwrap();
}

#[test]
fn n3dv_loader_reads_cameras_frames_points_and_split() {
    let root = temp_dir("n3dv");
    write_n3dv(&root, 3, 5, 16, 12);
    let options = LoadOptions {
        start_frame: 1,
        frame_count: Some(3),
        downscale: 2,
        ..Default::default()
    };
    // GIFStream reads the points of the GOP's first frame, colmap_<start>: absent for start 1, so
    // the loader falls back to random points inside the camera frusta, within the LLFF bounds.
    let scene = load(&root, DatasetLayout::N3dv, &options).unwrap();
    assert!(matches!(
        scene.point_source,
        PointSource::RandomInFrusta { .. }
    ));
    assert_eq!(scene.points.len(), acags::data::n3dv::RANDOM_INIT_POINTS);
    for p in &scene.points.positions {
        let p = [p[0] as f64, p[1] as f64, p[2] as f64];
        let seen = scene.cameras.iter().any(|c| {
            let depth = p[2]; // every camera looks down +z from z = 0
            project_point(&c.camera, p)
                .is_some_and(|[x, y]| x >= 0.0 && y >= 0.0 && x <= 8.0 && y <= 6.0)
                && (0.5 - 1e-4..=10.0 + 1e-3).contains(&depth)
        });
        assert!(seen, "random point {p:?} is outside every frustum");
    }
    copy_dir(&root.join("colmap_0"), &root.join("colmap_1"));
    let scene = load(&root, DatasetLayout::N3dv, &options).unwrap();
    assert_eq!(scene.cameras.len(), 3);
    assert_eq!(scene.cameras[2].name, "cam02");
    assert_eq!(scene.frames, FrameRange { start: 1, count: 3 });
    assert_eq!(scene.frames_available, 5);
    assert_eq!(scene.test_cameras, vec![0]);
    assert_eq!(scene.train_cameras, vec![1, 2]);
    assert_eq!(scene.resolution(), (8, 6));
    // Intrinsics halve with the images: f = 0.8·16 / 2, principal point (16//2)/2.
    let cam = &scene.cameras[1].camera;
    assert_eq!((cam.fx, cam.cx, cam.cy), (6.4, 4.0, 3.0));
    // Frame 2 of camera 1 is the 1-indexed file 00003.png.
    assert!(
        scene
            .frame_path(ViewId {
                camera: 1,
                frame: 2
            })
            .ends_with("png/cam01/00003.png")
    );
    assert_eq!(scene.points.len(), 2);
    assert_eq!(scene.train_views().len(), 2 * 3);
    assert_eq!(scene.time(2), 0.5);
    // A point on camera 1's axis (centre x = 0.1) projects to the principal point.
    assert_close(
        project_point(cam, [0.1, 0.0, 4.0]).unwrap(),
        [4.0, 3.0],
        1e-5,
    );
    // Frames decode at the downscaled size.
    let cache = FrameCache::new(1 << 20);
    let frame = cache
        .get(
            &scene,
            ViewId {
                camera: 1,
                frame: 2,
            },
        )
        .unwrap();
    assert_eq!(
        (frame.width, frame.height, frame.rgb.len()),
        (8, 6, 8 * 6 * 3)
    );
}

#[test]
fn mpeg_layout_uses_cameras_8_10_12_for_testing() {
    let root = temp_dir("mpeg");
    write_n3dv(&root, 14, 2, 8, 8);
    let scene = load(&root, DatasetLayout::Mpeg, &LoadOptions::default()).unwrap();
    assert_eq!(scene.test_cameras, vec![8, 10, 12]);
    assert_eq!(scene.train_cameras.len(), 11);
    let removed = LoadOptions {
        removed_cameras: vec![12, 3],
        ..Default::default()
    };
    let scene = load(&root, DatasetLayout::Mpeg, &removed).unwrap();
    assert_eq!(scene.test_cameras, vec![8, 10]);
    assert!(!scene.train_cameras.contains(&3));
    let text = dataset_info(&root, &["--layout", "mpeg"]);
    assert!(
        text.contains("3 test: cam08, cam10, cam12") && text.contains("problems    none"),
        "{text}"
    );
}

#[test]
fn point_ply_with_byte_colours() {
    let dir = temp_dir("ply-points");
    let path = dir.join("points3D.ply");
    std::fs::write(&path, "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n1 2 3 255 0 51\n-1 0 0.5 0 255 0\n").unwrap();
    let cloud = acags::data::colmap::read_points_ply(&path).unwrap();
    assert_eq!(cloud.positions, vec![[1.0, 2.0, 3.0], [-1.0, 0.0, 0.5]]);
    assert_eq!(cloud.colors[0], [1.0, 0.0, 0.2]);
}

fn write_panoptic(root: &Path, frames: usize, w: u32, h: u32) {
    let meta = |ids: &[i64]| {
        let k: Vec<Vec<[[f64; 3]; 3]>> = (0..frames)
            .map(|_| {
                ids.iter()
                    .map(|_| {
                        [
                            [50.0, 0.0, w as f64 / 2.0],
                            [0.0, 50.0, h as f64 / 2.0],
                            [0.0, 0.0, 1.0],
                        ]
                    })
                    .collect()
            })
            .collect();
        let w2c: Vec<Vec<[[f64; 4]; 4]>> = (0..frames)
            .map(|_| {
                ids.iter()
                    .map(|&id| {
                        [
                            [1.0, 0.0, 0.0, -0.1 * id as f64],
                            [0.0, 1.0, 0.0, 0.0],
                            [0.0, 0.0, 1.0, 4.0],
                            [0.0, 0.0, 0.0, 1.0],
                        ]
                    })
                    .collect()
            })
            .collect();
        let names: Vec<Vec<String>> = (0..frames)
            .map(|t| ids.iter().map(|id| format!("{id}/{t:06}.jpg")).collect())
            .collect();
        let cam_ids: Vec<Vec<i64>> = (0..frames).map(|_| ids.to_vec()).collect();
        serde_json::json!({ "w": w, "h": h, "k": k, "w2c": w2c, "fn": names, "cam_id": cam_ids })
    };
    std::fs::write(root.join("train_meta.json"), meta(&[0, 2, 3]).to_string()).unwrap();
    std::fs::write(root.join("test_meta.json"), meta(&[1]).to_string()).unwrap();
    for id in 0..4 {
        for t in 0..frames {
            let p = root.join(format!("ims/{id}/{t:06}.jpg"));
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            image::RgbImage::from_pixel(w, h, image::Rgb([200, 100, 50]))
                .save(&p)
                .unwrap();
        }
    }
    let mut npz = npyz::npz::NpzWriter::create(root.join("init_pt_cld.npz")).unwrap();
    use npyz::WriterBuilder;
    let mut writer = npz
        .array::<f64>("data", Default::default())
        .unwrap()
        .default_dtype()
        .shape(&[2, 7])
        .begin_nd()
        .unwrap();
    writer
        .extend([
            0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 1.0, 0.5, 0.5, 1.0, 0.0, 0.0, 1.0, 0.0,
        ])
        .unwrap();
    writer.finish().unwrap();
}

#[test]
fn panoptic_loader_reads_meta_images_and_point_cloud() {
    let root = temp_dir("panoptic");
    write_panoptic(&root, 4, 32, 18);
    let scene = load(
        &root,
        DatasetLayout::Panoptic,
        &LoadOptions {
            start_frame: 1,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(
        scene
            .cameras
            .iter()
            .map(|c| c.name.as_str())
            .collect::<Vec<_>>(),
        ["0", "1", "2", "3"]
    );
    assert_eq!(scene.test_cameras, vec![1]);
    assert_eq!(scene.train_cameras, vec![0, 2, 3]);
    assert_eq!(scene.frames, FrameRange { start: 1, count: 3 });
    assert!(
        scene
            .frame_path(ViewId {
                camera: 2,
                frame: 3
            })
            .ends_with("ims/2/000003.jpg")
    );
    assert_eq!(scene.points.positions[1], [0.5, 0.5, 1.0]);
    assert_eq!(scene.points.colors[0], [1.0, 0.5, 0.0]);
    // Camera 2 sits at x = 0.2: the origin projects 50·(-0.2)/4 px left of the centre.
    assert_close(
        project_point(&scene.cameras[2].camera, [0.0, 0.0, 0.0]).unwrap(),
        [16.0 - 2.5, 9.0],
        1e-5,
    );
    let frame = FrameCache::new(1 << 20)
        .get(
            &scene,
            ViewId {
                camera: 1,
                frame: 2,
            },
        )
        .unwrap();
    assert_eq!((frame.width, frame.height), (32, 18));
    let text = dataset_info(&root, &[]);
    assert!(
        text.contains("(Panoptic)")
            && text.contains("1 test: 1")
            && text.contains("problems    none"),
        "{text}"
    );
}

/// `acags dataset info` output; panics unless it succeeds.
fn dataset_info(root: &Path, extra: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_acags"))
        .args(["dataset", "info"])
        .arg(root)
        .args(extra)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

// ---------------------------------------------------------------- synthetic scene

fn synthetic_fast() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        // One fixed path, regenerated per run: a static is never dropped, so a per-process
        // directory would be left behind by every run.
        let dir = std::env::temp_dir().join("acags-test-synthetic-fast");
        let _ = std::fs::remove_dir_all(&dir);
        write_dataset(SyntheticPreset::Fast, &dir).unwrap();
        dir
    })
}

#[test]
fn synthetic_scene_loads_through_the_n3dv_path() {
    let root = synthetic_fast();
    let scene = load(root, DatasetLayout::N3dv, &LoadOptions::default()).unwrap();
    let spec = SyntheticPreset::Fast.spec();
    assert_eq!(
        (scene.cameras.len(), scene.frames.count),
        (spec.cameras, spec.frames)
    );
    assert_eq!(scene.resolution(), (spec.width, spec.height));
    // The cameras survive the LLFF round trip.
    for (loaded, truth) in scene.cameras.iter().zip(rig(&spec)) {
        for (a, b) in loaded
            .camera
            .world_to_camera
            .iter()
            .flatten()
            .zip(truth.world_to_camera.iter().flatten())
        {
            assert!((a - b).abs() < 1e-5);
        }
        assert_eq!((loaded.camera.fx, loaded.camera.cx), (truth.fx, truth.cx));
    }
    // Points are first hits of camera rays: each lies in front of the cameras, inside their images.
    assert!(scene.points.len() > 5_000);
    let inside = scene.points.positions.iter().filter(|p| {
        let p = [p[0] as f64, p[1] as f64, p[2] as f64];
        scene.cameras.iter().any(|c| {
            project_point(&c.camera, p)
                .is_some_and(|[x, y]| x >= 0.0 && y >= 0.0 && x < 320.0 && y < 240.0)
        })
    });
    assert_eq!(inside.count(), scene.points.len());
    // The fast sphere moves: frame 0 and frame 39 of the same camera differ a lot; the scene is
    // deterministic, so a second render is identical.
    let cache = FrameCache::new(64 << 20);
    let first = cache
        .get(
            &scene,
            ViewId {
                camera: 5,
                frame: 0,
            },
        )
        .unwrap();
    let last = cache
        .get(
            &scene,
            ViewId {
                camera: 5,
                frame: 39,
            },
        )
        .unwrap();
    let changed = first
        .rgb
        .chunks(3)
        .zip(last.rgb.chunks(3))
        .filter(|(a, b)| (a[1] - b[1]).abs() > 0.1)
        .count();
    assert!(
        changed > 1500,
        "only {changed} pixels changed between the first and last frame"
    );
    let again = acags::data::synthetic::render(&spec, &scene.cameras[5].camera, 0.0);
    assert_eq!(
        again.into_raw(),
        image::open(scene.frame_path(ViewId {
            camera: 5,
            frame: 0
        }))
        .unwrap()
        .to_rgb8()
        .into_raw()
    );
}

#[test]
fn dataset_info_reports_the_synthetic_scene_without_problems() {
    let out = Command::new(env!("CARGO_BIN_EXE_acags"))
        .args(["dataset", "info"])
        .arg(synthetic_fast())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for needle in [
        "cameras     12 (11 train, 1 test: cam00)",
        "GOP 0..40",
        "320x240",
        "points.txt",
        "problems    none",
    ] {
        assert!(
            text.contains(needle.trim_end_matches("points.txt")),
            "missing '{needle}' in:\n{text}"
        );
    }
}

// ---------------------------------------------------------------- frames, cache, sampler, points

#[test]
fn downscaling_matches_area_and_opencv_bilinear() {
    let rgb: Vec<f32> = (0..4 * 4).flat_map(|i| [i as f32, 0.0, 1.0]).collect();
    let frame = Frame {
        width: 4,
        height: 4,
        rgb,
    };
    let area = downscale(&frame, 2, Resample::Area);
    assert_eq!((area.width, area.height), (2, 2));
    assert_eq!(
        area.rgb.chunks(3).map(|p| p[0]).collect::<Vec<_>>(),
        [2.5, 4.5, 10.5, 12.5]
    );
    // For factor 2, OpenCV's INTER_LINEAR samples at 2x + 0.5: the same 2×2 means.
    assert_eq!(downscale(&frame, 2, Resample::Bilinear), area);
    let odd = Frame {
        width: 3,
        height: 3,
        rgb: (0..9).flat_map(|i| [i as f32; 3]).collect(),
    };
    // Factor 3 samples the centre pixel exactly.
    assert_eq!(downscale(&odd, 3, Resample::Bilinear).rgb, vec![4.0; 3]);
    assert_eq!(downscale(&odd, 3, Resample::Area).rgb, vec![4.0; 3]);
}

#[test]
fn frame_cache_stays_within_its_budget() {
    let root = temp_dir("cache");
    write_n3dv(&root, 2, 4, 10, 10);
    let scene = load(&root, DatasetLayout::N3dv, &LoadOptions::default()).unwrap();
    let frame_bytes = 10 * 10 * 3 * 4;
    let cache = FrameCache::new(2 * frame_bytes);
    let a = cache
        .get(
            &scene,
            ViewId {
                camera: 0,
                frame: 0,
            },
        )
        .unwrap();
    let a_again = cache
        .get(
            &scene,
            ViewId {
                camera: 0,
                frame: 0,
            },
        )
        .unwrap();
    assert!(
        Arc::ptr_eq(&a, &a_again),
        "a cached frame was decoded again"
    );
    for f in 1..4 {
        cache
            .get(
                &scene,
                ViewId {
                    camera: 1,
                    frame: f,
                },
            )
            .unwrap();
    }
    assert_eq!(cache.usage(), (2 * frame_bytes, 2));
    let evicted = cache
        .get(
            &scene,
            ViewId {
                camera: 0,
                frame: 0,
            },
        )
        .unwrap();
    assert!(
        !Arc::ptr_eq(&a, &evicted),
        "the least recently used frame should have been dropped"
    );
    assert_eq!(*a, *evicted);
}

#[test]
fn sampler_draws_each_view_once_per_epoch_and_resumes_exactly() {
    let views: Vec<ViewId> = (0..5)
        .flat_map(|c| {
            (0..7).map(move |f| ViewId {
                camera: c,
                frame: f,
            })
        })
        .collect();
    let mut sampler = ViewSampler::new(views.clone(), 42);
    let epoch0: Vec<ViewId> = (0..35).map(|_| sampler.next_view()).collect();
    let epoch1: Vec<ViewId> = (0..35).map(|_| sampler.next_view()).collect();
    for epoch in [&epoch0, &epoch1] {
        let mut sorted = epoch.clone();
        sorted.sort();
        assert_eq!(sorted, views, "an epoch must be a permutation");
    }
    assert_ne!(epoch0, epoch1);
    assert_ne!(epoch0, views, "not shuffled");
    // Same seed, same stream; restoring a mid-epoch state continues identically.
    let mut again = ViewSampler::new(views.clone(), 42);
    let first: Vec<ViewId> = (0..47).map(|_| again.next_view()).collect();
    assert_eq!(&first[..35], &epoch0[..]);
    let state = again.state();
    let continued: Vec<ViewId> = (0..30).map(|_| again.next_view()).collect();
    let mut restored = ViewSampler::new(views.clone(), 42);
    restored.restore(state);
    assert_eq!(
        (0..30).map(|_| restored.next_view()).collect::<Vec<_>>(),
        continued
    );
    assert_ne!(
        ViewSampler::new(views, 43).next_view(),
        epoch0[0],
        "seed ignored (or an unlucky draw)"
    );
}

#[test]
fn colmap_binary_and_text_point_files() {
    let dir = temp_dir("colmap");
    let mut bytes = Vec::new();
    bytes.extend(2u64.to_le_bytes());
    for (id, xyz, rgb, track) in [
        (7u64, [1.0f64, 2.0, 3.0], [255u8, 0, 10], 2u64),
        (9, [-1.0, 0.5, 4.0], [0, 128, 0], 0),
    ] {
        bytes.extend(id.to_le_bytes());
        for v in xyz {
            bytes.extend(v.to_le_bytes());
        }
        bytes.extend(rgb);
        bytes.extend(0.5f64.to_le_bytes());
        bytes.extend(track.to_le_bytes());
        bytes.extend(vec![0u8; 8 * track as usize]);
    }
    let bin = dir.join("points3D.bin");
    std::fs::write(&bin, &bytes).unwrap();
    let cloud = read_points3d_bin(&bin).unwrap();
    assert_eq!(cloud.positions, vec![[1.0, 2.0, 3.0], [-1.0, 0.5, 4.0]]);
    assert_eq!(cloud.colors[0], [1.0, 0.0, 10.0 / 255.0]);
    std::fs::write(&bin, &bytes[..bytes.len() - 20]).unwrap();
    let e = err_text(read_points3d_bin(&bin));
    assert!(e.contains("points3D.bin") && e.contains("truncated"), "{e}");

    let txt = dir.join("points3D.txt");
    write_points3d_txt(&txt, &cloud).unwrap();
    let back = read_points3d_txt(&txt).unwrap();
    assert_eq!(back.positions, cloud.positions);
    std::fs::write(&txt, "1 0.0 zero 1 2 3 4 0\n").unwrap();
    let e = err_text(read_points3d_txt(&txt));
    assert!(e.contains("points3D.txt:1") && e.contains("field 3"), "{e}");
}

// ---------------------------------------------------------------- bad input

/// Writes a valid N3DV dataset, breaks it with `damage`, and expects a load error containing
/// every one of `needles`.
fn expect_n3dv_error(
    tag: &str,
    cameras: usize,
    frames: usize,
    damage: impl FnOnce(&Path),
    needles: &[&str],
) {
    let root = temp_dir(tag);
    write_n3dv(&root, cameras, frames, 8, 8);
    damage(&root);
    let e = err_text(load(&root, DatasetLayout::N3dv, &LoadOptions::default()));
    for needle in needles {
        assert!(e.contains(needle), "{tag}: '{needle}' missing from: {e}");
    }
}

#[test]
fn bad_n3dv_inputs_name_the_file_and_the_problem() {
    let e = err_text(load(
        Path::new("/nonexistent/dataset"),
        DatasetLayout::N3dv,
        &LoadOptions::default(),
    ));
    assert!(
        e.contains("/nonexistent/dataset") && e.contains("does not exist"),
        "{e}"
    );

    let poses = |root: &Path| root.join("poses_bounds.npy");
    expect_n3dv_error(
        "no-poses",
        2,
        2,
        |r| std::fs::remove_file(poses(r)).unwrap(),
        &["poses_bounds.npy", "missing"],
    );
    expect_n3dv_error(
        "shape",
        2,
        2,
        |r| write_npy_f64(&poses(r), &[2, 16], &[1.0; 32]).unwrap(),
        &["poses_bounds.npy", "[2, 16]"],
    );
    expect_n3dv_error(
        "dtype",
        2,
        2,
        |r| npyz::to_file_1d(poses(r), vec![1i32; 34]).unwrap(),
        &["poses_bounds.npy", "unsupported dtype '<i4'"],
    );
    expect_n3dv_error(
        "count",
        3,
        2,
        |r| std::fs::remove_dir_all(r.join("png/cam02")).unwrap(),
        &["3 cameras", "2 camera folders"],
    );
    expect_n3dv_error(
        "gap",
        2,
        4,
        |r| std::fs::remove_file(r.join("png/cam01/00002.png")).unwrap(),
        &["cam01/00002.png", "missing frame"],
    );
    expect_n3dv_error(
        "sizes",
        2,
        2,
        |r| {
            write_png(&r.join("png/cam01/00001.png"), 9, 8, 0);
            write_png(&r.join("png/cam01/00002.png"), 9, 8, 0);
        },
        &["different image sizes", "cam01 9x8"],
    );
}

#[test]
fn corrupt_and_mismatched_frames_are_reported_by_dataset_info_and_the_cache() {
    let root = temp_dir("corrupt");
    write_n3dv(&root, 2, 3, 8, 8);
    std::fs::write(root.join("png/cam00/00002.png"), b"not a png at all").unwrap();
    write_png(&root.join("png/cam01/00003.png"), 6, 8, 0);
    let scene = load(&root, DatasetLayout::N3dv, &LoadOptions::default()).unwrap();
    let e = err_text(FrameCache::new(1 << 20).get(
        &scene,
        ViewId {
            camera: 0,
            frame: 1,
        },
    ));
    assert!(
        e.contains("cam00/00002.png") && e.contains("cannot decode"),
        "{e}"
    );
    let e = err_text(FrameCache::new(1 << 20).get(
        &scene,
        ViewId {
            camera: 1,
            frame: 2,
        },
    ));
    assert!(
        e.contains("cam01/00003.png") && e.contains("6x8, expected 8x8"),
        "{e}"
    );

    let out = Command::new(env!("CARGO_BIN_EXE_acags"))
        .args(["dataset", "info"])
        .arg(&root)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains("problems    2"), "{text}");
    assert!(
        text.contains("cam00/00002.png: unreadable image header"),
        "{text}"
    );
    assert!(
        text.contains("cam01/00003.png: image is 6x8, expected 8x8"),
        "{text}"
    );
}

#[test]
fn bad_panoptic_inputs_name_the_file_and_the_problem() {
    let opts = LoadOptions::default();
    let root = temp_dir("pano-json");
    write_panoptic(&root, 2, 8, 8);
    std::fs::write(
        root.join("test_meta.json"),
        "{\"w\": 8, \"h\": 8, \"k\": [[[[1,0,0],[0,1,0]]]]",
    )
    .unwrap();
    let e = err_text(load(&root, DatasetLayout::Panoptic, &opts));
    assert!(
        e.contains("test_meta.json") && e.contains("field 'k"),
        "{e}"
    );

    let root = temp_dir("pano-missing");
    write_panoptic(&root, 2, 8, 8);
    std::fs::remove_file(root.join("init_pt_cld.npz")).unwrap();
    let e = err_text(load(&root, DatasetLayout::Panoptic, &opts));
    assert!(e.contains("init_pt_cld.npz"), "{e}");

    let root = temp_dir("pano-count");
    write_panoptic(&root, 2, 8, 8);
    let mut meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("train_meta.json")).unwrap())
            .unwrap();
    meta["cam_id"].as_array_mut().unwrap().pop();
    std::fs::write(root.join("train_meta.json"), meta.to_string()).unwrap();
    let e = err_text(load(&root, DatasetLayout::Panoptic, &opts));
    assert!(
        e.contains("train_meta.json") && e.contains("'cam_id' has 1 timesteps"),
        "{e}"
    );
}

/// camXX.mp4 without png/: the loader extracts every frame with ffmpeg (fps 30, 1-indexed PNGs)
/// and later loads reuse the extraction. Skips without ffmpeg unless ACAGS_REQUIRE_FFMPEG=1 (CI).
#[test]
fn videos_are_extracted_with_ffmpeg() {
    if !acags::data::video::tool_available("ffmpeg") {
        assert_ne!(
            std::env::var("ACAGS_REQUIRE_FFMPEG").as_deref(),
            Ok("1"),
            "ACAGS_REQUIRE_FFMPEG=1 but ffmpeg is not installed"
        );
        eprintln!("skipping: ffmpeg is not installed");
        return;
    }
    let root = temp_dir("mp4");
    let mut rows = Vec::new();
    for c in 0..2 {
        let status = Command::new("ffmpeg")
            .args([
                "-v",
                "error",
                "-nostdin",
                "-f",
                "lavfi",
                "-i",
                "testsrc=size=32x24:rate=30",
                "-frames:v",
                "6",
                "-pix_fmt",
                "yuv420p",
            ])
            .arg(root.join(format!("cam{c:02}.mp4")))
            .status()
            .unwrap();
        assert!(status.success());
        rows.extend([
            0.0, 1.0, 0.0, c as f64, 24.0, 1.0, 0.0, 0.0, 0.0, 32.0, 0.0, 0.0, -1.0, 0.0, 30.0,
            0.5, 10.0,
        ]);
    }
    write_npy_f64(&root.join("poses_bounds.npy"), &[2, 17], &rows).unwrap();
    let scene = load(&root, DatasetLayout::N3dv, &LoadOptions::default()).unwrap();
    assert_eq!(
        (scene.cameras.len(), scene.frames.count, scene.resolution()),
        (2, 6, (32, 24))
    );
    assert!(root.join("png/cam01/00006.png").is_file() && !root.join("png.partial").exists());
    let frame = FrameCache::new(1 << 20)
        .get(
            &scene,
            ViewId {
                camera: 1,
                frame: 5,
            },
        )
        .unwrap();
    assert!(
        frame.rgb.iter().any(|v| *v > 0.2),
        "extracted frame is black"
    );
    // The extraction is cached: a second load does not need the videos.
    std::fs::remove_file(root.join("cam00.mp4")).unwrap();
    assert_eq!(
        load(&root, DatasetLayout::N3dv, &LoadOptions::default())
            .unwrap()
            .frames
            .count,
        6
    );
}

#[test]
fn videos_without_ffmpeg_give_a_clear_error() {
    let root = temp_dir("video");
    std::fs::write(root.join("cam00.mp4"), b"fake").unwrap();
    write_npy_f64(&root.join("poses_bounds.npy"), &[1, 17], &[1.0; 17]).unwrap();
    // PATH without ffmpeg, whatever this machine has installed.
    let out = Command::new(env!("CARGO_BIN_EXE_acags"))
        .args(["dataset", "info"])
        .arg(&root)
        .env("PATH", "/nonexistent")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success());
    assert!(
        text.contains("needs ffmpeg, which is not installed"),
        "{text}"
    );
}

#[test]
fn synthetic_object_labels_name_what_each_pixel_shows() {
    use acags::data::synthetic::{
        flying_cube_pose, object_labels, object_moves, object_names, render,
    };
    let spec = SyntheticPreset::Crossing.spec();
    let names = object_names(&spec);
    assert_eq!(
        names,
        [
            "floor",
            "wall",
            "static sphere",
            "static cube",
            "fast sphere",
            "slow cube",
            "flying cube"
        ]
    );
    assert_eq!(
        object_moves(&spec),
        [false, false, false, false, true, true, true],
        "the fast sphere and both cubes move"
    );
    let camera = &rig(&spec)[0];
    let (w, h) = (camera.width as usize, camera.height as usize);
    let flight = spec.flying_cube.unwrap();
    for time in [0.25, 0.5, 0.75] {
        let labels = object_labels(&spec, camera, time);
        assert_eq!(labels.len(), w * h);
        assert!(
            labels.iter().all(|l| l.object.is_some()),
            "the room closes every ray"
        );
        let name = |i: usize| names[labels[i].object.unwrap() as usize];
        // The flying cube's centre shows the cube; the top row the wall, the bottom row the floor.
        let centre = project_point(camera, flying_cube_pose(&flight, time).0.to_array()).unwrap();
        assert_eq!(name(centre[1] as usize * w + centre[0] as usize), "flying cube");
        assert_eq!(name(w / 2), "wall");
        assert_eq!(name((h - 1) * w + w / 2), "floor");
        // Against the renderer: inside the cube's outline (a pixel and its four neighbours
        // labelled the cube) the render shows the cube's magenta and cyan cells, shaded and, on
        // a cell's edge, mixed: a colour α·magenta + β·cyan with α, β ≥ 0.
        let (m, c) = ([0.95, 0.2, 0.6], [0.1, 0.75, 0.8]);
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (mm, mc, cc) = (dot(m, m), dot(m, c), dot(c, c));
        let is_cube_colour = |p: [f64; 3]| {
            let (pm, pc) = (dot(p, m), dot(p, c));
            let det = mm * cc - mc * mc;
            let (a, b) = ((pm * cc - pc * mc) / det, (pc * mm - pm * mc) / det);
            let residual: f64 = (0..3)
                .map(|k| (p[k] - a * m[k] - b * c[k]).powi(2))
                .sum::<f64>()
                .sqrt();
            a >= -0.05 && b >= -0.05 && residual <= 0.08 * dot(p, p).sqrt().max(0.05)
        };
        let image = render(&spec, camera, time);
        // Pixels away from the image border that `keep` holds for, with their four neighbours.
        let interior = |keep: &dyn Fn(usize) -> bool| -> Vec<usize> {
            (1..h - 1)
                .flat_map(|y| (1..w - 1).map(move |x| y * w + x))
                .filter(|&i| [i, i - 1, i + 1, i - w, i + w].iter().all(|&j| keep(j)))
                .collect()
        };
        let inside = interior(&|j| name(j) == "flying cube");
        assert!(inside.len() > 100, "{} pixels inside the cube", inside.len());
        let cube_coloured = inside
            .iter()
            .filter(|&&i| {
                let rgb = image.get_pixel((i % w) as u32, (i / w) as u32).0;
                is_cube_colour(rgb.map(|v| v as f64 / 255.0))
            })
            .count();
        assert!(
            cube_coloured as f64 >= 0.95 * inside.len() as f64,
            "{cube_coloured} of {} pixels inside the labelled cube show its colours",
            inside.len()
        );
        // The fast sphere's shadow on the floor: there, and as dark as the renderer's ambient
        // term makes the floor's lighter cells (0.35 × 0.85), where lit they are 0.74.
        let shadowed = interior(&|j| {
            name(j) == "floor"
                && labels[j].shadow_of.map(|o| names[o as usize]) == Some("fast sphere")
        });
        assert!(shadowed.len() > 30, "{} pixels in the sphere's shadow", shadowed.len());
        for &i in &shadowed {
            let rgb = image.get_pixel((i % w) as u32, (i / w) as u32).0;
            assert!(
                rgb.iter().all(|&v| v as f64 <= 0.31 * 255.0),
                "pixel {i} in the sphere's shadow renders {rgb:?}"
            );
        }
        let lit_floor = (0..w * h)
            .filter(|&i| name(i) == "floor" && labels[i].shadow_of.is_none())
            .filter(|&i| image.get_pixel((i % w) as u32, (i / w) as u32).0[0] > 180)
            .count();
        assert!(lit_floor > 1000, "{lit_floor} lit light floor pixels");
    }
}
