//! The `acags render-ply` command end to end, its PLY/camera readers, and their error messages.

mod common;
use common::TempDir;
use std::path::{Path, PathBuf};
use std::process::Command;

use acags::io::camera_json::parse_camera;
use acags::io::splat_ply::{SplatScene, read_splat_ply, sh_basis, write_splat_ply};

fn acags() -> Command {
    Command::new(env!("CARGO_BIN_EXE_acags"))
}

fn example(name: &str) -> PathBuf {
    common::crate_path("assets/example").join(name)
}

fn temp_dir(tag: &str) -> TempDir {
    TempDir::new(&format!("acags-test-{tag}"))
}

fn read_npy(path: &Path) -> (Vec<u64>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    let npy = npyz::NpyFile::new(&bytes[..]).unwrap();
    let shape = npy.shape().to_vec();
    (shape, npy.into_vec::<f32>().unwrap())
}

#[test]
fn renders_the_shipped_example_to_png_and_npy() {
    let dir = temp_dir("render");
    let png = dir.join("example.png");
    let npy = dir.join("example.npy");
    for out in [&png, &npy] {
        let status = acags()
            .args([
                "render-ply",
                "--backend",
                "ndarray",
                "--background",
                "0.1,0.2,0.3",
            ])
            .arg("--ply")
            .arg(example("scene.ply"))
            .arg("--camera")
            .arg(example("camera.json"))
            .arg("--out")
            .arg(out)
            .status()
            .unwrap();
        assert!(status.success());
    }
    let img = image::open(&png).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (640, 400));
    let (shape, rgba) = read_npy(&npy);
    assert_eq!(shape, vec![400, 640, 4]);
    // The PNG is the npy's RGB quantised.
    for (i, p) in img.pixels().enumerate() {
        for c in 0..3 {
            let want = (rgba[i * 4 + c].clamp(0.0, 1.0) * 255.0).round() as u8;
            assert_eq!(p[c], want);
        }
    }
    // Something was drawn, and the background shows where nothing was.
    let covered = rgba.chunks(4).filter(|p| p[3] > 0.5).count();
    assert!(covered > 640 * 400 / 10, "only {covered} covered pixels");
    let empty = rgba
        .chunks(4)
        .find(|p| p[3] == 0.0)
        .expect("some background pixel");
    assert_eq!(&empty[..3], &[0.1, 0.2, 0.3]);
}

#[test]
fn ply_round_trip_keeps_every_value() {
    let scene = SplatScene {
        means: vec![0.1, -0.2, 3.0, 1.0, 2.0, 5.0],
        quats: vec![1.0, 0.0, 0.0, 0.0, 0.3, 0.4, -0.5, 0.6],
        scales: vec![0.01, 0.02, 0.5, 1.0, 2.0, 0.3],
        opacities: vec![0.25, 0.9],
        sh: (0..2 * 4 * 3).map(|i| i as f32 * 0.1 - 1.0).collect(),
        sh_degree: 1,
    };
    let dir = temp_dir("ply");
    let path = dir.join("s.ply");
    write_splat_ply(&path, &scene).unwrap();
    let back = read_splat_ply(&path).unwrap();
    assert_eq!(back.sh_degree, 1);
    assert_eq!(back.means, scene.means);
    assert_eq!(back.quats, scene.quats);
    assert_eq!(back.sh, scene.sh);
    for (a, b) in back
        .scales
        .iter()
        .chain(&back.opacities)
        .zip(scene.scales.iter().chain(&scene.opacities))
    {
        assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{a} vs {b}");
    }
}

#[test]
fn sh_colors_follow_the_inria_convention() {
    // Degree 0: colour = C0 * dc + 0.5, clamped at 0.
    let mut scene = SplatScene {
        means: vec![0.0, 0.0, 2.0],
        quats: vec![1.0, 0.0, 0.0, 0.0],
        scales: vec![1.0; 3],
        opacities: vec![0.5],
        sh: vec![1.0, -1.0, -3.0],
        sh_degree: 0,
    };
    let c = scene.colors_from([0.0; 3]);
    let c0 = 0.282_094_79f32;
    assert!((c[0] - (c0 + 0.5)).abs() < 1e-6 && (c[1] - (0.5 - c0)).abs() < 1e-6 && c[2] == 0.0);
    // Degree 1 seen along +z: basis = (C0, -C1 y, C1 z, -C1 x) = (C0, 0, C1, 0).
    scene.sh_degree = 1;
    scene.sh = vec![0.0, 0.0, 0.0, 5.0, 5.0, 5.0, 1.0, 2.0, 3.0, 5.0, 5.0, 5.0];
    let c = scene.colors_from([0.0; 3]);
    let c1 = 0.488_602_5f32;
    for k in 0..3 {
        assert!((c[k] - (0.5 + c1 * (k as f32 + 1.0))).abs() < 1e-5);
    }
    let b = sh_basis(3, [0.0, 0.0, 1.0]);
    assert!(
        (b[12] - 0.373_176_33 * 2.0).abs() < 1e-6,
        "z(2zz - 3xx - 3yy) term"
    );
}

fn run_expect_error(args: &[&str]) -> String {
    let out = acags().args(args).output().unwrap();
    assert!(!out.status.success(), "expected failure for {args:?}");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn malformed_inputs_give_errors_naming_file_and_field() {
    let dir = temp_dir("bad");
    let camera = example("camera.json");
    let cam = camera.to_str().unwrap();
    let out = dir.join("o.png");
    let out = out.to_str().unwrap();

    // PLY without an opacity property.
    let no_opacity = dir.join("no_opacity.ply");
    std::fs::write(
        &no_opacity,
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 1\n",
    )
    .unwrap();
    let err = run_expect_error(&[
        "render-ply",
        "--ply",
        no_opacity.to_str().unwrap(),
        "--camera",
        cam,
        "--out",
        out,
    ]);
    assert!(
        err.contains("no_opacity.ply") && err.contains("f_dc_0"),
        "{err}"
    );

    // Truncated binary payload.
    let bytes = std::fs::read(example("scene.ply")).unwrap();
    let truncated = dir.join("truncated.ply");
    std::fs::write(&truncated, &bytes[..bytes.len() - 100]).unwrap();
    let err = run_expect_error(&[
        "render-ply",
        "--ply",
        truncated.to_str().unwrap(),
        "--camera",
        cam,
        "--out",
        out,
    ]);
    assert!(
        err.contains("truncated.ply") && err.contains("payload"),
        "{err}"
    );

    // Not a PLY at all; a missing file.
    let junk = dir.join("junk.ply");
    std::fs::write(&junk, "hello").unwrap();
    let err = run_expect_error(&[
        "render-ply",
        "--ply",
        junk.to_str().unwrap(),
        "--camera",
        cam,
        "--out",
        out,
    ]);
    assert!(err.contains("junk.ply") && err.contains("header"), "{err}");
    let err = run_expect_error(&[
        "render-ply",
        "--ply",
        "/nonexistent/x.ply",
        "--camera",
        cam,
        "--out",
        out,
    ]);
    assert!(err.contains("/nonexistent/x.ply"), "{err}");

    // Camera JSON with a missing field, a wrong type, a bad matrix; unknown output type.
    let ply = example("scene.ply");
    let ply = ply.to_str().unwrap();
    for (name, text, needle) in [
        (
            "missing.json",
            r#"{"width": 4, "height": 4, "fx": 1, "fy": 1, "cx": 2, "cy": 2}"#,
            "world_to_camera",
        ),
        (
            "type.json",
            r#"{"width": "4", "height": 4, "fx": 1, "fy": 1, "cx": 2, "cy": 2, "world_to_camera": []}"#,
            "width",
        ),
        (
            "focal.json",
            r#"{"width": 4, "height": 4, "fx": 0, "fy": 1, "cx": 2, "cy": 2, "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#,
            "fx",
        ),
    ] {
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        let err = run_expect_error(&[
            "render-ply",
            "--ply",
            ply,
            "--camera",
            path.to_str().unwrap(),
            "--out",
            out,
        ]);
        assert!(err.contains(name) && err.contains(needle), "{name}: {err}");
    }
    let err = run_expect_error(&[
        "render-ply",
        "--ply",
        ply,
        "--camera",
        cam,
        "--out",
        "x.jpg",
    ]);
    assert!(err.contains(".png or .npy"), "{err}");
}

#[test]
fn camera_json_rejects_a_non_affine_last_row() {
    let text = r#"{"width": 4, "height": 4, "fx": 1, "fy": 1, "cx": 2, "cy": 2,
        "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,1,1]]}"#;
    let err = parse_camera(text).unwrap_err().to_string();
    assert!(err.contains("last row"), "{err}");
}
