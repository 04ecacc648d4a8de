//! Image quality metrics as GIFStream reports them (spec §11), computed in f64 on the host.
//!
//! - PSNR with data range 1, per image (the mean over images is the caller's).
//! - SSIM as torchmetrics' `StructuralSimilarityIndexMeasure(data_range=1)`: 11×11 Gaussian
//!   window with σ = 1.5, k1 = 0.01, k2 = 0.03, per channel, averaged over channels and over the
//!   **valid** region (torchmetrics reflect-pads, filters, then crops the padded border before the
//!   mean, which leaves exactly the valid region). Images smaller than 11×11 are an error.

use anyhow::{Result, bail};

pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;

/// Normalised 1D Gaussian taps of the SSIM window.
pub fn gaussian_taps() -> [f64; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let mut taps: [f64; SSIM_WINDOW] = std::array::from_fn(|i| {
        let x = i as f64 - half;
        (-(x * x) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
    });
    let sum: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= sum);
    taps
}

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
    check(render, target, width, height)?;
    if width < SSIM_WINDOW || height < SSIM_WINDOW {
        bail!("SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {width}x{height}");
    }
    let taps = gaussian_taps();
    let mut total = 0.0;
    let mut count = 0usize;
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
            total += num / den;
            count += 1;
        }
    }
    Ok(total / count as f64)
}
