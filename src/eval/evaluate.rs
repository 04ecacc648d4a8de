//! Test-set evaluation (spec §11): every test camera at every frame of the GOP, render clamped
//! to [0, 1], PSNR and SSIM per image then averaged, FPS = 1 / mean seconds of anchor decoding +
//! rasterization per image. Optionally writes ground truth | render | error side by side.
//!
//! Beside the full-frame figures, every image is also scored on its *dynamic* pixels (the
//! motion mask of [`super::motion_mask`], from the ground truth alone) and on its *static*
//! pixels: a model that drops a moving object keeps a fine full-frame PSNR, because the object
//! covers a small part of the image. Region means are over the images whose region is not
//! empty; per-frame figures are means over the test cameras.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::metrics::{RegionQuality, psnr, region_quality, ssim_map};
use super::motion_mask::{MotionMaskConfig, camera_motion_masks};
use crate::data::frames::FrameCache;
use crate::data::{Scene, ViewId};
use crate::model::anchored::AnchoredModel;
use crate::model::view::{ALL_TIME_BANDS, Phase, ViewTime};

/// Metrics of one test image.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewMetrics {
    pub camera: usize,
    pub frame: usize,
    pub psnr: f64,
    pub ssim: f64,
    /// On the moving pixels (absent when the frame has none).
    #[serde(default)]
    pub dynamic_psnr: Option<f64>,
    #[serde(default)]
    pub dynamic_ssim: Option<f64>,
    /// On the other pixels (absent when every pixel moves).
    #[serde(default)]
    pub static_psnr: Option<f64>,
    #[serde(default)]
    pub static_ssim: Option<f64>,
    /// Share of the image's pixels in the motion mask.
    #[serde(default)]
    pub dynamic_fraction: f64,
    pub seconds: f64,
    pub gaussians: usize,
}

/// Means over the test cameras of one frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameMetrics {
    pub frame: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub dynamic_psnr: Option<f64>,
    pub static_psnr: Option<f64>,
    pub dynamic_ssim: Option<f64>,
    pub static_ssim: Option<f64>,
}

impl FrameMetrics {
    /// Static minus dynamic PSNR: how far the moving pixels trail (absent unless both exist).
    pub fn dynamic_gap(&self) -> Option<f64> {
        Some(self.static_psnr? - self.dynamic_psnr?)
    }
}

/// The dynamic / static split of a test-set evaluation.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RegionSummary {
    /// Mean over the images with moving pixels; absent when no test image has any.
    pub dynamic_psnr: Option<f64>,
    pub dynamic_ssim: Option<f64>,
    /// Mean over the images with static pixels.
    pub static_psnr: Option<f64>,
    pub static_ssim: Option<f64>,
    /// Mean share of moving pixels per test image.
    pub dynamic_fraction: f64,
    /// The frame whose dynamic PSNR (mean over test cameras) is lowest, and that PSNR.
    pub worst_dynamic_frame: Option<(usize, f64)>,
    /// The largest per-frame static − dynamic PSNR gap and its frame.
    pub max_dynamic_gap: Option<(usize, f64)>,
    /// Per frame, means over the test cameras.
    pub frames: Vec<FrameMetrics>,
}

impl RegionSummary {
    /// "dynamic 18.61 dB / static 34.70 dB (14.2 % moving; worst dynamic frame #21 12.60 dB,
    /// largest gap #21 21.30 dB)", or "no moving pixels".
    pub fn text(&self) -> String {
        match self.dynamic_psnr {
            Some(d) => format!(
                "dynamic {d:.2} dB / static {} ({:.1} % moving; worst dynamic frame {}, largest gap {})",
                self.static_psnr.map_or("–".into(), |s| format!("{s:.2} dB")),
                100.0 * self.dynamic_fraction,
                self.worst_dynamic_frame
                    .map_or("–".into(), |(f, p)| format!("#{f} {p:.2} dB")),
                self.max_dynamic_gap
                    .map_or("–".into(), |(f, g)| format!("#{f} {g:.2} dB")),
            ),
            None => "no moving pixels".into(),
        }
    }
}

/// Averages over the test set.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalSummary {
    pub psnr: f64,
    pub ssim: f64,
    #[serde(flatten)]
    pub regions: RegionSummary,
    pub render_fps: f64,
    /// Mean Gaussians spawned (opacity > 0) per test image.
    pub gaussians: f64,
    pub views: Vec<ViewMetrics>,
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

impl EvalSummary {
    /// The summary of per-image metrics (means, per-frame means, worst frames).
    pub fn from_views(views: Vec<ViewMetrics>) -> Self {
        let all = |f: fn(&ViewMetrics) -> f64| mean(views.iter().map(f)).unwrap_or(f64::NAN);
        let some = |f: fn(&ViewMetrics) -> Option<f64>| mean(views.iter().filter_map(f));
        let mut frame_ids: Vec<usize> = views.iter().map(|v| v.frame).collect();
        frame_ids.sort_unstable();
        frame_ids.dedup();
        let frames: Vec<FrameMetrics> = frame_ids
            .into_iter()
            .map(|frame| {
                let of_frame = || views.iter().filter(move |v| v.frame == frame);
                let region = |f: fn(&ViewMetrics) -> Option<f64>| mean(of_frame().filter_map(f));
                FrameMetrics {
                    frame,
                    psnr: mean(of_frame().map(|v| v.psnr)).unwrap_or(f64::NAN),
                    ssim: mean(of_frame().map(|v| v.ssim)).unwrap_or(f64::NAN),
                    dynamic_psnr: region(|v| v.dynamic_psnr),
                    static_psnr: region(|v| v.static_psnr),
                    dynamic_ssim: region(|v| v.dynamic_ssim),
                    static_ssim: region(|v| v.static_ssim),
                }
            })
            .collect();
        let worst_dynamic_frame = frames
            .iter()
            .filter_map(|f| Some((f.frame, f.dynamic_psnr?)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let max_dynamic_gap = frames
            .iter()
            .filter_map(|f| Some((f.frame, f.dynamic_gap()?)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        Self {
            psnr: all(|v| v.psnr),
            ssim: all(|v| v.ssim),
            regions: RegionSummary {
                dynamic_psnr: some(|v| v.dynamic_psnr),
                dynamic_ssim: some(|v| v.dynamic_ssim),
                static_psnr: some(|v| v.static_psnr),
                static_ssim: some(|v| v.static_ssim),
                dynamic_fraction: all(|v| v.dynamic_fraction),
                worst_dynamic_frame,
                max_dynamic_gap,
                frames,
            },
            render_fps: 1.0 / all(|v| v.seconds),
            gaussians: all(|v| v.gaussians as f64),
            views,
        }
    }
}

/// Renders every test view; with `render_dir`, writes `cam{C}_frame{F}.png` there (ground truth,
/// render, and the absolute error ×4, side by side).
pub fn evaluate(
    model: &AnchoredModel,
    scene: &Scene,
    frames: &FrameCache,
    phase: Phase,
    mask: &MotionMaskConfig,
    render_dir: Option<&Path>,
) -> Result<EvalSummary> {
    let views = scene.test_views();
    anyhow::ensure!(!views.is_empty(), "{}: no test views", scene.root.display());
    if let Some(dir) = render_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let masks = test_motion_masks(scene, frames, mask)?;
    // One warm-up render so the timing excludes first-use allocation and kernel setup.
    render_view(model, scene, views[0], phase)?;
    let mut metrics = Vec::with_capacity(views.len());
    for &view in &views {
        let started = Instant::now();
        let rendered = render_view(model, scene, view, phase)?;
        let image = rendered.image_host();
        let seconds = started.elapsed().as_secs_f64();
        let target = frames.get(scene, view)?;
        let motion = &masks[&view];
        if let Some(dir) = render_dir {
            let path = dir.join(format!("cam{:02}_frame{:04}.png", view.camera, view.frame));
            write_comparison(&path, &target.rgb, &image, target.width as usize, target.height as usize)?;
        }
        metrics.push(score_view(&image, &target, motion, view, seconds, AnchoredModel::spawned(&rendered.decoded))?);
    }
    Ok(EvalSummary::from_views(metrics))
}

/// The motion masks of every test view (each camera against its own temporal median).
pub fn test_motion_masks(
    scene: &Scene,
    frames: &FrameCache,
    config: &MotionMaskConfig,
) -> Result<std::collections::HashMap<ViewId, Vec<bool>>> {
    let mut out = std::collections::HashMap::new();
    for &camera in &scene.test_cameras {
        let views: Vec<ViewId> = scene
            .frames
            .frames()
            .map(|frame| ViewId { camera, frame })
            .collect();
        let images = views
            .iter()
            .map(|&v| frames.get(scene, v))
            .collect::<Result<Vec<_>>>()?;
        let (w, h) = (images[0].width as usize, images[0].height as usize);
        let planes: Vec<&[f32]> = images.iter().map(|f| f.rgb.as_slice()).collect();
        for (view, mask) in views.into_iter().zip(camera_motion_masks(&planes, w, h, config)) {
            out.insert(view, mask);
        }
    }
    Ok(out)
}

/// Full-frame, dynamic and static metrics of one rendered test image.
pub fn score_view(
    image: &[f32],
    target: &crate::data::frames::Frame,
    motion: &[bool],
    view: ViewId,
    seconds: f64,
    gaussians: usize,
) -> Result<ViewMetrics> {
    let (w, h) = (target.width as usize, target.height as usize);
    let map = ssim_map(image, &target.rgb, w, h)?;
    let still: Vec<bool> = motion.iter().map(|&m| !m).collect();
    let dynamic = region_quality(image, &target.rgb, motion, &map, w, h)?;
    let stat = region_quality(image, &target.rgb, &still, &map, w, h)?;
    let psnr_of = |r: &Option<RegionQuality>| r.map(|r| r.psnr);
    let ssim_of = |r: &Option<RegionQuality>| r.and_then(|r| r.ssim);
    Ok(ViewMetrics {
        camera: view.camera,
        frame: view.frame,
        psnr: psnr(image, &target.rgb, w, h)?,
        ssim: map.values.iter().sum::<f64>() / map.values.len() as f64,
        dynamic_psnr: psnr_of(&dynamic),
        dynamic_ssim: ssim_of(&dynamic),
        static_psnr: psnr_of(&stat),
        static_ssim: ssim_of(&stat),
        dynamic_fraction: dynamic.map_or(0, |r| r.pixels) as f64 / (w * h) as f64,
        seconds,
        gaussians,
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
            time_bands: ALL_TIME_BANDS,
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
