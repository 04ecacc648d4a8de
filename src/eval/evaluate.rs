//! Test-set evaluation (spec §11): every test camera at every frame of the GOP, render clamped
//! to [0, 1], PSNR and SSIM per image then averaged, FPS = 1 / mean seconds of anchor decoding +
//! rasterization per image. Optionally writes ground truth | render | error side by side.
//!
//! Beside the full-frame figures, every image is also scored on its *dynamic* pixels (the
//! motion mask of [`super::motion_mask`], from the ground truth alone) and on its *static*
//! pixels: a model that drops a moving object keeps a fine full-frame PSNR, because the object
//! covers a small part of the image. Region means are over the images whose region is not
//! empty; per-frame figures are means over the test cameras.
//!
//! LPIPS ([`super::lpips`]): AlexNet always, VGG when its weights are present (`[eval]
//! lpips_vgg`), with the `[eval] lpips_input` convention; on regions, the mean of the spatial
//! LPIPS map over the region's pixels.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::config::{EvalConfig, VggLpips};
use super::lpips::{Lpips, LpipsInput, LpipsNet, region_mean, vgg_weights_path};
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
    /// LPIPS (absent when not computed: VGG without weights, an image too small for the net).
    #[serde(default)]
    pub lpips_alex: Option<f64>,
    #[serde(default)]
    pub lpips_vgg: Option<f64>,
    /// Mean of the spatial LPIPS map over the moving / the static pixels.
    #[serde(default)]
    pub dynamic_lpips_alex: Option<f64>,
    #[serde(default)]
    pub static_lpips_alex: Option<f64>,
    #[serde(default)]
    pub dynamic_lpips_vgg: Option<f64>,
    #[serde(default)]
    pub static_lpips_vgg: Option<f64>,
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
    #[serde(default)]
    pub lpips_alex: Option<f64>,
    #[serde(default)]
    pub lpips_vgg: Option<f64>,
    #[serde(default)]
    pub dynamic_lpips_alex: Option<f64>,
    #[serde(default)]
    pub static_lpips_alex: Option<f64>,
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

/// LPIPS means over the test set (each over the images where it was computed).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LpipsSummary {
    /// The input convention of every LPIPS figure here; absent when none was computed.
    pub lpips_input: Option<LpipsInput>,
    pub lpips_alex: Option<f64>,
    pub lpips_vgg: Option<f64>,
    pub dynamic_lpips_alex: Option<f64>,
    pub static_lpips_alex: Option<f64>,
    pub dynamic_lpips_vgg: Option<f64>,
    pub static_lpips_vgg: Option<f64>,
}

impl LpipsSummary {
    /// ", LPIPS-Alex 0.1234 (dynamic 0.3010 / static 0.0800), LPIPS-VGG 0.2000", or "".
    pub fn text(&self) -> String {
        let one = |name: &str, all: Option<f64>, dynamic: Option<f64>, stat: Option<f64>| {
            all.map_or(String::new(), |v| {
                let split = match (dynamic, stat) {
                    (Some(d), Some(s)) => format!(" (dynamic {d:.4} / static {s:.4})"),
                    _ => String::new(),
                };
                format!(", {name} {v:.4}{split}")
            })
        };
        let unscaled = if self.lpips_input == Some(LpipsInput::Unscaled) {
            " [unscaled inputs, GIFStream's convention]"
        } else {
            ""
        };
        let text = one("LPIPS-Alex", self.lpips_alex, self.dynamic_lpips_alex, self.static_lpips_alex)
            + &one("LPIPS-VGG", self.lpips_vgg, self.dynamic_lpips_vgg, self.static_lpips_vgg);
        if text.is_empty() { text } else { text + unscaled }
    }
}

/// Averages over the test set.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalSummary {
    pub psnr: f64,
    pub ssim: f64,
    #[serde(flatten)]
    pub lpips: LpipsSummary,
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
    /// The summary of per-image metrics (means, per-frame means, worst frames); `lpips_input`
    /// is the convention of the views' LPIPS figures.
    pub fn from_views(views: Vec<ViewMetrics>, lpips_input: LpipsInput) -> Self {
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
                    lpips_alex: region(|v| v.lpips_alex),
                    lpips_vgg: region(|v| v.lpips_vgg),
                    dynamic_lpips_alex: region(|v| v.dynamic_lpips_alex),
                    static_lpips_alex: region(|v| v.static_lpips_alex),
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
        let lpips_alex = some(|v| v.lpips_alex);
        let lpips_vgg = some(|v| v.lpips_vgg);
        Self {
            psnr: all(|v| v.psnr),
            ssim: all(|v| v.ssim),
            lpips: LpipsSummary {
                lpips_input: (lpips_alex.is_some() || lpips_vgg.is_some()).then_some(lpips_input),
                lpips_alex,
                lpips_vgg,
                dynamic_lpips_alex: some(|v| v.dynamic_lpips_alex),
                static_lpips_alex: some(|v| v.static_lpips_alex),
                dynamic_lpips_vgg: some(|v| v.dynamic_lpips_vgg),
                static_lpips_vgg: some(|v| v.static_lpips_vgg),
            },
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

/// Which metrics an evaluation computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scoring {
    /// PSNR, SSIM and LPIPS (final evaluations, `eval`, the stability suite).
    Full,
    /// PSNR and SSIM only: progress evaluations during training, where LPIPS would cost more
    /// than the figures are worth.
    PixelOnly,
}

/// The LPIPS networks of an evaluation and their input convention.
pub struct Perceptual {
    nets: Vec<Lpips>,
    input: LpipsInput,
}

impl Perceptual {
    /// No LPIPS.
    pub fn none() -> Self {
        Self {
            nets: Vec::new(),
            input: LpipsInput::default(),
        }
    }

    /// LPIPS-Alex, and LPIPS-VGG as `[eval] lpips_vgg` says (`auto`: when its weights exist,
    /// with a note once per process when they do not).
    pub fn load(config: &EvalConfig, device: &burn::tensor::Device) -> Result<Self> {
        let mut nets = vec![Lpips::alex(device)?];
        match config.lpips_vgg {
            VggLpips::Off => {}
            VggLpips::On => nets.push(Lpips::vgg(device)?),
            VggLpips::Auto if vgg_weights_path().exists() => nets.push(Lpips::vgg(device)?),
            VggLpips::Auto => {
                static NOTE: std::sync::Once = std::sync::Once::new();
                NOTE.call_once(|| {
                    eprintln!(
                        "note: LPIPS-VGG not computed: no weights at {} (`{}` fetches them)",
                        vgg_weights_path().display(),
                        super::lpips::FETCH_VGG_COMMAND
                    )
                });
            }
        }
        Ok(Self {
            nets,
            input: config.lpips_input,
        })
    }

    pub fn input(&self) -> LpipsInput {
        self.input
    }

    pub fn nets(&self) -> &[Lpips] {
        &self.nets
    }
}

/// Renders every test view; with `render_dir`, writes `cam{C}_frame{F}.png` there (ground truth,
/// render, and the absolute error ×4, side by side).
pub fn evaluate(
    model: &AnchoredModel,
    scene: &Scene,
    frames: &FrameCache,
    phase: Phase,
    config: &EvalConfig,
    scoring: Scoring,
    render_dir: Option<&Path>,
) -> Result<EvalSummary> {
    let views = scene.test_views();
    anyhow::ensure!(!views.is_empty(), "{}: no test views", scene.root.display());
    if let Some(dir) = render_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let perceptual = match scoring {
        Scoring::Full => Perceptual::load(config, &model.anchors.device())?,
        Scoring::PixelOnly => Perceptual::none(),
    };
    let masks = test_motion_masks(scene, frames, &config.motion_mask())?;
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
        let mut scored = score_view(&image, &target, motion, view, seconds, AnchoredModel::spawned(&rendered.decoded))?;
        score_lpips(&mut scored, &perceptual, &image, &target, motion)?;
        metrics.push(scored);
    }
    Ok(EvalSummary::from_views(metrics, perceptual.input))
}

/// Adds LPIPS (whole image, moving and static pixels) of every network in `perceptual` to
/// `metrics`; a network the image is too small for is left out, with a note once.
pub fn score_lpips(
    metrics: &mut ViewMetrics,
    perceptual: &Perceptual,
    image: &[f32],
    target: &crate::data::frames::Frame,
    motion: &[bool],
) -> Result<()> {
    let (w, h) = (target.width as usize, target.height as usize);
    let still: Vec<bool> = motion.iter().map(|&m| !m).collect();
    for net in &perceptual.nets {
        if !net.net().accepts(w, h) {
            static NOTE: std::sync::Once = std::sync::Once::new();
            NOTE.call_once(|| {
                eprintln!(
                    "note: {} not computed: {w}x{h} test images are smaller than its {min}x{min} minimum",
                    net.net().name(),
                    min = net.net().min_size()
                )
            });
            continue;
        }
        // LPIPS is symmetric; the render goes first like `lpips(render, gt)` in the papers' code.
        let maps = net.maps(image, &target.rgb, w, h, perceptual.input)?;
        let spatial = maps.spatial();
        let (all, dynamic, stat) = (
            Some(maps.value()),
            region_mean(&spatial, motion),
            region_mean(&spatial, &still),
        );
        match net.net() {
            LpipsNet::Alex => {
                (metrics.lpips_alex, metrics.dynamic_lpips_alex, metrics.static_lpips_alex) = (all, dynamic, stat)
            }
            LpipsNet::Vgg => {
                (metrics.lpips_vgg, metrics.dynamic_lpips_vgg, metrics.static_lpips_vgg) = (all, dynamic, stat)
            }
        }
    }
    Ok(())
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

/// Full-frame, dynamic and static PSNR and SSIM of one rendered test image (LPIPS: [`score_lpips`]).
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
        lpips_alex: None,
        lpips_vgg: None,
        dynamic_lpips_alex: None,
        static_lpips_alex: None,
        dynamic_lpips_vgg: None,
        static_lpips_vgg: None,
        seconds,
        gaussians,
    })
}

/// The evaluation settings of the scene's frame `frame` (absolute): no time window, every
/// γ(t) band.
pub fn evaluation_time(scene: &Scene, frame: usize, phase: Phase) -> ViewTime {
    ViewTime {
        frame: frame - scene.frames.start,
        time: scene.time(frame),
        window_gap: 0,
        phase,
        time_bands: ALL_TIME_BANDS,
    }
}

/// Decodes and rasterizes one view at evaluation settings ([`evaluation_time`]).
pub fn render_view(
    model: &AnchoredModel,
    scene: &Scene,
    view: ViewId,
    phase: Phase,
) -> Result<crate::model::anchored::RenderedView> {
    let camera = &scene.cameras[view.camera].camera;
    model.render(camera, evaluation_time(scene, view.frame, phase))
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
