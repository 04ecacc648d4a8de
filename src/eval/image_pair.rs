//! `acags metrics A B`: PSNR, SSIM and LPIPS of one pair of 8-bit images, with the same code
//! (and conventions) as the test-set evaluation.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use super::config::EvalConfig;
use super::evaluate::Perceptual;
use super::lpips::{LpipsInput, LpipsNet};
use super::metrics::{psnr, ssim};

/// The metrics of one image pair.
#[derive(Clone, Debug, Serialize)]
pub struct PairMetrics {
    pub a: PathBuf,
    pub b: PathBuf,
    pub width: usize,
    pub height: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_alex: Option<f64>,
    pub lpips_vgg: Option<f64>,
    pub lpips_input: LpipsInput,
}

impl PairMetrics {
    pub fn text(&self) -> String {
        let lpips = |name: &str, v: Option<f64>| v.map_or(String::new(), |v| format!(", {name} {v:.4}"));
        format!(
            "{} vs {} ({}x{}): PSNR {:.3} dB, SSIM {:.4}{}{} (LPIPS inputs {})",
            self.a.display(),
            self.b.display(),
            self.width,
            self.height,
            self.psnr,
            self.ssim,
            lpips("LPIPS-Alex", self.lpips_alex),
            lpips("LPIPS-VGG", self.lpips_vgg),
            match self.lpips_input {
                LpipsInput::Normalized => "mapped to [-1, 1]",
                LpipsInput::Unscaled => "unscaled [0, 1], GIFStream's convention",
            }
        )
    }
}

/// An 8-bit RGB image as [H, W, 3] floats in [0, 1]; RGBA is accepted only when fully opaque
/// (a transparent pixel has no single colour to compare).
pub fn read_rgb8(path: &Path) -> Result<(Vec<f32>, usize, usize)> {
    let image = image::ImageReader::open(path)
        .with_context(|| format!("cannot open {}", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("cannot read {}", path.display()))?
        .decode()
        .with_context(|| format!("{}: not a readable PNG or JPEG image", path.display()))?;
    let (width, height) = (image.width() as usize, image.height() as usize);
    let rgb = match image {
        image::DynamicImage::ImageRgb8(rgb) => rgb,
        image::DynamicImage::ImageRgba8(rgba) => {
            if let Some((x, y, _)) = rgba.enumerate_pixels().find(|(_, _, p)| p[3] != 255) {
                bail!(
                    "{}: pixel ({x}, {y}) is not opaque; acags metrics compares opaque RGB images \
                     (composite it over a background first)",
                    path.display()
                );
            }
            image::DynamicImage::ImageRgba8(rgba).to_rgb8()
        }
        other => bail!(
            "{}: {:?} pixels; acags metrics compares 8-bit RGB images",
            path.display(),
            other.color()
        ),
    };
    Ok((rgb.into_raw().into_iter().map(|v| v as f32 / 255.0).collect(), width, height))
}

/// PSNR, SSIM, LPIPS-Alex and (per `config.lpips_vgg`) LPIPS-VGG of `a` against `b`.
pub fn pair_metrics(a: &Path, b: &Path, config: &EvalConfig, device: &burn::tensor::Device) -> Result<PairMetrics> {
    let (ia, wa, ha) = read_rgb8(a)?;
    let (ib, wb, hb) = read_rgb8(b)?;
    if (wa, ha) != (wb, hb) {
        bail!(
            "{} is {wa}x{ha} but {} is {wb}x{hb}: the images must have the same size",
            a.display(),
            b.display()
        );
    }
    let perceptual = Perceptual::load(config, device)?;
    let mut lpips = [None, None];
    for net in perceptual.nets() {
        let slot = match net.net() {
            LpipsNet::Alex => 0,
            LpipsNet::Vgg => 1,
        };
        lpips[slot] = Some(
            net.distance(&ia, &ib, wa, ha, perceptual.input())
                .with_context(|| format!("{} vs {}", a.display(), b.display()))?,
        );
    }
    Ok(PairMetrics {
        a: a.to_path_buf(),
        b: b.to_path_buf(),
        width: wa,
        height: ha,
        psnr: psnr(&ia, &ib, wa, ha)?,
        ssim: ssim(&ia, &ib, wa, ha).with_context(|| format!("{}", a.display()))?,
        lpips_alex: lpips[0],
        lpips_vgg: lpips[1],
        lpips_input: perceptual.input(),
    })
}
