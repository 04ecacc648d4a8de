//! Test-set evaluation (spec §11): every test camera at every frame of the GOP, render clamped
//! to [0, 1], PSNR and SSIM per image then averaged, FPS = 1 / mean seconds of anchor decoding +
//! rasterization per image. Optionally writes ground truth | render | error side by side.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::metrics::{psnr, ssim};
use crate::data::frames::FrameCache;
use crate::data::{Scene, ViewId};
use crate::model::anchored::AnchoredModel;
use crate::model::view::{Phase, ViewTime};

/// Metrics of one test image.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewMetrics {
    pub camera: usize,
    pub frame: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub seconds: f64,
    pub gaussians: usize,
}

/// Averages over the test set.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalSummary {
    pub psnr: f64,
    pub ssim: f64,
    pub render_fps: f64,
    /// Mean Gaussians spawned (opacity > 0) per test image.
    pub gaussians: f64,
    pub views: Vec<ViewMetrics>,
}

/// Renders every test view; with `render_dir`, writes `cam{C}_frame{F}.png` there (ground truth,
/// render, and the absolute error ×4, side by side).
pub fn evaluate(
    model: &AnchoredModel,
    scene: &Scene,
    frames: &FrameCache,
    phase: Phase,
    render_dir: Option<&Path>,
) -> Result<EvalSummary> {
    let views = scene.test_views();
    anyhow::ensure!(!views.is_empty(), "{}: no test views", scene.root.display());
    if let Some(dir) = render_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    // One warm-up render so the timing excludes first-use allocation and kernel setup.
    render_view(model, scene, views[0], phase)?;
    let mut metrics = Vec::with_capacity(views.len());
    for &view in &views {
        let started = Instant::now();
        let rendered = render_view(model, scene, view, phase)?;
        let image = rendered.image_host();
        let seconds = started.elapsed().as_secs_f64();
        let target = frames.get(scene, view)?;
        let (w, h) = (target.width as usize, target.height as usize);
        let p = psnr(&image, &target.rgb, w, h)?;
        let s = ssim(&image, &target.rgb, w, h)?;
        if let Some(dir) = render_dir {
            let path = dir.join(format!("cam{:02}_frame{:04}.png", view.camera, view.frame));
            write_comparison(&path, &target.rgb, &image, w, h)?;
        }
        metrics.push(ViewMetrics {
            camera: view.camera,
            frame: view.frame,
            psnr: p,
            ssim: s,
            seconds,
            gaussians: AnchoredModel::spawned(&rendered.decoded),
        });
    }
    let count = metrics.len() as f64;
    let mean = |f: fn(&ViewMetrics) -> f64| metrics.iter().map(f).sum::<f64>() / count;
    Ok(EvalSummary {
        psnr: mean(|m| m.psnr),
        ssim: mean(|m| m.ssim),
        render_fps: 1.0 / mean(|m| m.seconds),
        gaussians: mean(|m| m.gaussians as f64),
        views: metrics,
    })
}

/// Decodes and rasterizes one view at evaluation settings (no time window).
pub fn render_view(
    model: &AnchoredModel,
    scene: &Scene,
    view: ViewId,
    phase: Phase,
) -> Result<crate::model::anchored::RenderedView> {
    let camera = &scene.cameras[view.camera].camera;
    model.render(
        camera,
        ViewTime {
            frame: view.frame - scene.frames.start,
            time: scene.time(view.frame),
            window_gap: 0,
            phase,
        },
    )
}

/// RGB float [H, W, 3] in [0, 1] → 8-bit.
fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Ground truth | render | |error| × 4, one PNG.
pub fn write_comparison(
    path: &Path,
    truth: &[f32],
    render: &[f32],
    w: usize,
    h: usize,
) -> Result<()> {
    let mut out = image::RgbImage::new(3 * w as u32, h as u32);
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) * 3;
            let px = |v: &[f32]| image::Rgb([to_u8(v[i]), to_u8(v[i + 1]), to_u8(v[i + 2])]);
            out.put_pixel(x as u32, y as u32, px(truth));
            out.put_pixel((w + x) as u32, y as u32, px(render));
            let err: Vec<f32> = (0..3)
                .map(|c| (truth[i + c] - render[i + c]).abs() * 4.0)
                .collect();
            out.put_pixel(
                (2 * w + x) as u32,
                y as u32,
                image::Rgb([to_u8(err[0]), to_u8(err[1]), to_u8(err[2])]),
            );
        }
    }
    out.save(path)
        .with_context(|| format!("cannot write {}", path.display()))
}
