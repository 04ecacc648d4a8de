//! Shared test support: the gsplat fixtures and tolerance checks.
#![allow(dead_code)]

use std::path::PathBuf;

use acags_kernels::RasterCamera;
use acags_kernels::random_scene::GaussianArrays;
use serde::Deserialize;

pub const FIXTURE_CASES: [&str; 6] = [
    "single",
    "random_small",
    "occlusion_saturation",
    "border_and_large",
    "near_plane_and_behind",
    "anisotropic_rotated",
];

/// `../shared/fixtures/gsplat` beside the checkout, or `$ACAGS_FIXTURES`.
pub fn fixture_dir() -> PathBuf {
    if let Ok(dir) = std::env::var("ACAGS_FIXTURES") {
        return dir.into();
    }
    // Tests run from either crate of the workspace: look beside each ancestor directory.
    // The manifest directory cargo gives the running test first: a test binary built from
    // another checkout sharing the target directory (and not rebuilt, its sources unchanged)
    // still carries that checkout's path in `env!`.
    let manifest = PathBuf::from(
        std::env::var("CARGO_MANIFEST_DIR").unwrap_or_else(|_| env!("CARGO_MANIFEST_DIR").into()),
    );
    manifest
        .ancestors()
        .filter_map(|dir| Some(dir.parent()?.join("shared/fixtures/gsplat")))
        .find(|candidate| candidate.is_dir())
        .unwrap_or_else(|| manifest.join("../../shared/fixtures/gsplat"))
}

#[derive(Deserialize)]
pub struct Fixture {
    pub case: String,
    pub width: u32,
    pub height: u32,
    pub viewmat: [[f32; 4]; 4],
    #[serde(rename = "K")]
    pub k: [[f32; 3]; 3],
    pub background: [f32; 3],
    pub means: Vec<[f32; 3]>,
    pub quats: Vec<[f32; 4]>,
    pub scales: Vec<[f32; 3]>,
    pub opacities: Vec<f32>,
    pub colors: Vec<[f32; 3]>,
    pub upstream_image: Vec<Vec<[f32; 3]>>,
    pub upstream_alpha: Vec<Vec<f32>>,
    pub image: Vec<Vec<[f32; 3]>>,
    pub alpha: Vec<Vec<f32>>,
    pub visible: Vec<bool>,
    pub grad_means: Vec<[f32; 3]>,
    pub grad_quats: Vec<[f32; 4]>,
    pub grad_scales: Vec<[f32; 3]>,
    pub grad_opacities: Vec<f32>,
    pub grad_colors: Vec<[f32; 3]>,
    pub grad_means2d: Vec<[f32; 2]>,
    pub radii: Vec<[u32; 2]>,
    pub means2d: Vec<[f32; 2]>,
    pub conics: Vec<[f32; 3]>,
    pub depths: Vec<f32>,
    pub loss: f64,
}

pub fn load_fixture(case: &str) -> Fixture {
    let path = fixture_dir().join(format!("{case}.json"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| {
        panic!(
            "cannot read gsplat fixture {} ({e}); shared/ must sit beside the checkout",
            path.display()
        )
    });
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

impl Fixture {
    pub fn camera(&self) -> RasterCamera {
        RasterCamera {
            width: self.width,
            height: self.height,
            fx: self.k[0][0],
            fy: self.k[1][1],
            cx: self.k[0][2],
            cy: self.k[1][2],
            world_to_camera: self.viewmat,
        }
    }

    pub fn gaussians(&self) -> GaussianArrays {
        GaussianArrays {
            means: self.means.concat(),
            quats: self.quats.concat(),
            scales: self.scales.concat(),
            opacities: self.opacities.clone(),
            gates: vec![1.0; self.opacities.len()],
            colors: self.colors.concat(),
        }
    }

    /// dLoss/d(image_alpha) packed [H, W, 4].
    pub fn upstream_packed(&self) -> Vec<f32> {
        let mut out = Vec::new();
        for (row_img, row_a) in self.upstream_image.iter().zip(&self.upstream_alpha) {
            for (p, a) in row_img.iter().zip(row_a) {
                out.extend_from_slice(p);
                out.push(*a);
            }
        }
        out
    }

    pub fn image_flat(&self) -> Vec<f32> {
        self.image.iter().flatten().flatten().copied().collect()
    }

    pub fn alpha_flat(&self) -> Vec<f32> {
        self.alpha.iter().flatten().copied().collect()
    }
}

/// The fixture's scalar loss on a render: sum(image * upstream_image) + sum(alpha * upstream_alpha).
pub fn fixture_loss(fx: &Fixture, out: &acags_kernels::RasterOutput) -> burn::tensor::Tensor<1> {
    use burn::tensor::{Tensor, TensorData};
    let (h, w) = (fx.height as usize, fx.width as usize);
    let device = out.image.device();
    let up_image: Vec<f32> = fx
        .upstream_image
        .iter()
        .flatten()
        .flatten()
        .copied()
        .collect();
    let up_image = Tensor::<3>::from_data(TensorData::new(up_image, [h, w, 3]), &device);
    let up_alpha =
        Tensor::<2>::from_data(TensorData::new(fx.upstream_alpha.concat(), [h, w]), &device);
    (out.image.clone() * up_image).sum() + (out.alpha.clone() * up_alpha).sum()
}

/// Largest |got - want|.
pub fn max_abs_diff(got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len(), "length mismatch");
    got.iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max)
}

/// The fixture README's gradient tolerance: |got - want| <= rtol |want| + atol_rel max|want|.
/// Panics naming the worst entry.
pub fn assert_grad_close(label: &str, got: &[f32], want: &[f32], rtol: f32, atol_rel: f32) {
    assert_eq!(got.len(), want.len(), "{label}: length mismatch");
    let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let mut worst = (0.0f32, 0usize);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(g.is_finite(), "{label}[{i}] is {g}");
        let budget = rtol * w.abs() + atol_rel * scale;
        let used = if budget > 0.0 {
            (g - w).abs() / budget
        } else if g == w {
            0.0
        } else {
            f32::INFINITY
        };
        if used > worst.0 {
            worst = (used, i);
        }
    }
    assert!(
        worst.0 <= 1.0,
        "{label}: entry {} got {} want {} (uses {:.2}x the tolerance; max|want| = {scale})",
        worst.1,
        got[worst.1],
        want[worst.1],
        worst.0
    );
}
