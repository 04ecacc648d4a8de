//! Image quality metrics as GIFStream reports them (spec §11), computed in f64 on the host.
//!
//! - PSNR with data range 1, per image (the mean over images is the caller's).
//! - SSIM as torchmetrics' `StructuralSimilarityIndexMeasure(data_range=1)`: 11×11 Gaussian
//!   window with σ = 1.5, k1 = 0.01, k2 = 0.03, per channel, averaged over channels and over the
//!   **valid** region (torchmetrics reflect-pads, filters, then crops the padded border before the
//!   mean, which leaves exactly the valid region). Images smaller than 11×11 are an error.

use anyhow::{Result, bail};

// The SSIM window and constants are shared with the training loss's fused SSIM (kernels crate).
pub use crate::raster::fused_ssim::{SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, gaussian_taps};

fn check(a: &[f32], b: &[f32], width: usize, height: usize) -> Result<()> {
    if a.len() != width * height * 3 || b.len() != a.len() {
        bail!(
            "images must both be {width}x{height}x3 (got {} and {} values)",
            a.len(),
            b.len()
        );
    }
    Ok(())
}

/// PSNR in dB of `render` against `target`, both [H, W, 3] in [0, 1]; infinite when identical.
pub fn psnr(render: &[f32], target: &[f32], width: usize, height: usize) -> Result<f64> {
    check(render, target, width, height)?;
    let mse = render
        .iter()
        .zip(target)
        .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
        .sum::<f64>()
        / render.len() as f64;
    Ok(-10.0 * mse.log10())
}

/// Valid-region separable Gaussian filter of one channel.
fn filter_valid(plane: &[f64], width: usize, height: usize, taps: &[f64; SSIM_WINDOW]) -> Vec<f64> {
    let (ow, oh) = (width - SSIM_WINDOW + 1, height - SSIM_WINDOW + 1);
    let mut horizontal = vec![0.0; ow * height];
    for y in 0..height {
        for x in 0..ow {
            horizontal[y * ow + x] = (0..SSIM_WINDOW)
                .map(|k| taps[k] * plane[y * width + x + k])
                .sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = (0..SSIM_WINDOW)
                .map(|k| taps[k] * horizontal[(y + k) * ow + x])
                .sum();
        }
    }
    out
}

/// SSIM of `render` against `target`, both [H, W, 3] in [0, 1].
pub fn ssim(render: &[f32], target: &[f32], width: usize, height: usize) -> Result<f64> {
    let map = ssim_map(render, target, width, height)?;
    Ok(map.values.iter().sum::<f64>() / map.values.len() as f64)
}

/// The SSIM map over the valid region: entry (y, x) is the SSIM (mean over the channels) of the
/// 11×11 window centred on pixel (y + 5, x + 5).
pub struct SsimMap {
    /// [(H − 10)·(W − 10)], row-major.
    pub values: Vec<f64>,
    pub width: usize,
    pub height: usize,
}

/// The per-window SSIM of `render` against `target` (see [`SsimMap`]).
pub fn ssim_map(render: &[f32], target: &[f32], width: usize, height: usize) -> Result<SsimMap> {
    check(render, target, width, height)?;
    if width < SSIM_WINDOW || height < SSIM_WINDOW {
        bail!("SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {width}x{height}");
    }
    let taps = gaussian_taps();
    let (ow, oh) = (width - SSIM_WINDOW + 1, height - SSIM_WINDOW + 1);
    let mut values = vec![0.0; ow * oh];
    for c in 0..3 {
        let x: Vec<f64> = render
            .iter()
            .skip(c)
            .step_by(3)
            .map(|&v| v as f64)
            .collect();
        let y: Vec<f64> = target
            .iter()
            .skip(c)
            .step_by(3)
            .map(|&v| v as f64)
            .collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a * b).collect();
        let [mx, my, mxx, myy, mxy] =
            [&x, &y, &xx, &yy, &xy].map(|p| filter_valid(p, width, height, &taps));
        for i in 0..mx.len() {
            let (vx, vy, cov) = (
                mxx[i] - mx[i] * mx[i],
                myy[i] - my[i] * my[i],
                mxy[i] - mx[i] * my[i],
            );
            let num = (2.0 * mx[i] * my[i] + SSIM_C1) * (2.0 * cov + SSIM_C2);
            let den = (mx[i] * mx[i] + my[i] * my[i] + SSIM_C1) * (vx + vy + SSIM_C2);
            values[i] += num / den / 3.0;
        }
    }
    Ok(SsimMap {
        values,
        width: ow,
        height: oh,
    })
}

/// PSNR and SSIM restricted to a region of the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RegionQuality {
    /// PSNR of the MSE over the region's pixels (all three channels).
    pub psnr: f64,
    /// Mean of the SSIM map over the windows whose centre pixel lies in the region; `None` when
    /// no window centre does (the region lies within 5 px of the border).
    pub ssim: Option<f64>,
    /// Pixels in the region.
    pub pixels: usize,
}

/// PSNR and SSIM of `render` against `target` on the pixels where `region` is true ([H·W]);
/// `None` for an empty region. `ssim_map` is [`ssim_map`] of the same pair (shared by the
/// regions of one image).
pub fn region_quality(
    render: &[f32],
    target: &[f32],
    region: &[bool],
    ssim_map: &SsimMap,
    width: usize,
    height: usize,
) -> Result<Option<RegionQuality>> {
    check(render, target, width, height)?;
    if region.len() != width * height {
        bail!(
            "region mask has {} entries for a {width}x{height} image",
            region.len()
        );
    }
    let pixels = region.iter().filter(|&&r| r).count();
    if pixels == 0 {
        return Ok(None);
    }
    let sum: f64 = region
        .iter()
        .enumerate()
        .filter(|&(_, &r)| r)
        .flat_map(|(p, _)| 3 * p..3 * p + 3)
        .map(|i| (render[i] as f64 - target[i] as f64).powi(2))
        .sum();
    let mse = sum / (3 * pixels) as f64;
    let half = SSIM_WINDOW / 2;
    let (mut total, mut windows) = (0.0, 0usize);
    for y in 0..ssim_map.height {
        for x in 0..ssim_map.width {
            if region[(y + half) * width + x + half] {
                total += ssim_map.values[y * ssim_map.width + x];
                windows += 1;
            }
        }
    }
    Ok(Some(RegionQuality {
        psnr: -10.0 * mse.log10(),
        ssim: (windows > 0).then(|| total / windows as f64),
        pixels,
    }))
}
