//! Per-pixel alpha compositing over tiles: forward, and its backward without per-pixel lists.
//!
//! Each tile row (16 image rows) is one parallel work item: its pixels, its per-pixel state and its
//! intersections are contiguous, so threads write disjoint slices and results are deterministic.

use rayon::prelude::*;

use super::bin::TileBins;
use crate::conventions::{ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_STOP};

/// What compositing needs of one Gaussian, gathered per tile for locality.
#[derive(Clone, Copy, Debug, Default)]
pub struct Splat {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub color: [f32; 3],
}

impl Splat {
    /// sigma at offset (dx, dy) = mean2d - pixel centre.
    #[inline(always)]
    fn sigma(&self, dx: f32, dy: f32) -> f32 {
        let [a, b, c] = self.conic;
        0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    }
}

/// A splat plus `ln(255 * opacity)`: sigma above it means alpha < 1/255, which lets most far pairs
/// skip the `exp`. A margin keeps the shortcut from deciding a pair the exact test would keep.
#[derive(Clone, Copy)]
struct TileSplat {
    splat: Splat,
    sigma_cut: f32,
}

const SIGMA_CUT_MARGIN: f32 = 1e-3;

fn gather(splats: &[Splat], ids: &[u32]) -> Vec<TileSplat> {
    ids.iter()
        .map(|&g| {
            let splat = splats[g as usize];
            TileSplat {
                splat,
                sigma_cut: (splat.opacity / ALPHA_MIN).ln() + SIGMA_CUT_MARGIN,
            }
        })
        .collect()
}

/// alpha of a pair, or `None` when the pair is skipped (sigma < 0 or alpha < 1/255).
/// Also returns whether alpha hit the 0.999 clamp and `o * exp(-sigma)` unclamped.
#[inline(always)]
fn pair_alpha(s: &TileSplat, dx: f32, dy: f32) -> Option<(f32, f32, f32)> {
    let sigma = s.splat.sigma(dx, dy);
    if sigma < 0.0 || sigma > s.sigma_cut {
        return None;
    }
    let raw = s.splat.opacity * (-sigma).exp();
    let alpha = raw.min(ALPHA_MAX);
    if alpha < ALPHA_MIN {
        return None;
    }
    Some((alpha, raw, sigma))
}

/// Per-pixel results of the forward pass, kept for the backward.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CompositeOutput {
    /// [H, W, 4]: RGB (background included) and alpha = 1 - T_final.
    pub image_alpha: Vec<f32>,
    /// [H, W] transmittance after the last composited Gaussian.
    pub final_transmittance: Vec<f32>,
    /// [H, W] number of entries of the pixel's tile list up to and including the last composited.
    pub n_contrib: Vec<u32>,
}

fn row_pixel_range(ty: u32, height: u32) -> (u32, u32) {
    let y0 = ty * TILE_SIZE;
    (y0, (y0 + TILE_SIZE).min(height))
}

pub fn composite_forward(
    splats: &[Splat],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [f32; 3],
) -> CompositeOutput {
    let (w, h) = (width as usize, height as usize);
    let band = TILE_SIZE as usize * w;
    let mut out = CompositeOutput {
        image_alpha: vec![0.0; h * w * 4],
        final_transmittance: vec![0.0; h * w],
        n_contrib: vec![0; h * w],
    };
    out.image_alpha
        .par_chunks_mut(band * 4)
        .zip(out.final_transmittance.par_chunks_mut(band))
        .zip(out.n_contrib.par_chunks_mut(band))
        .enumerate()
        .for_each(|(ty, ((image, transmittance), n_contrib))| {
            let ty = ty as u32;
            let (y0, y1) = row_pixel_range(ty, height);
            for tx in 0..bins.tiles_x {
                let tile = (ty * bins.tiles_x + tx) as usize;
                let range = bins.tile_offsets[tile] as usize..bins.tile_offsets[tile + 1] as usize;
                let local = gather(splats, &bins.gaussian_from_intersection[range]);
                let x0 = tx * TILE_SIZE;
                let x1 = (x0 + TILE_SIZE).min(width);
                for y in y0..y1 {
                    for x in x0..x1 {
                        let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                        let mut t = 1.0f32;
                        let mut color = [0.0f32; 3];
                        let mut last = 0u32;
                        for (k, s) in local.iter().enumerate() {
                            let Some((alpha, _, _)) =
                                pair_alpha(s, s.splat.mean2d[0] - px, s.splat.mean2d[1] - py)
                            else {
                                continue;
                            };
                            let next_t = t * (1.0 - alpha);
                            if next_t <= TRANSMITTANCE_STOP {
                                break;
                            }
                            let weight = alpha * t;
                            for c in 0..3 {
                                color[c] += s.splat.color[c] * weight;
                            }
                            t = next_t;
                            last = k as u32 + 1;
                        }
                        let p = ((y - y0) * width + x) as usize;
                        for c in 0..3 {
                            image[p * 4 + c] = color[c] + t * background[c];
                        }
                        image[p * 4 + 3] = 1.0 - t;
                        transmittance[p] = t;
                        n_contrib[p] = last;
                    }
                }
            }
        });
    out
}

/// Gradient of the loss with respect to one intersection's (or one Gaussian's) splat.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SplatGrad {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub color: [f32; 3],
}

impl SplatGrad {
    pub fn add(&mut self, o: &SplatGrad) {
        for i in 0..2 {
            self.mean2d[i] += o.mean2d[i];
        }
        for i in 0..3 {
            self.conic[i] += o.conic[i];
            self.color[i] += o.color[i];
        }
        self.opacity += o.opacity;
    }
}

/// Backward of [`composite_forward`]: per-intersection gradients (aligned with
/// `bins.gaussian_from_intersection`), then summed per Gaussian in intersection order, so the
/// result is deterministic and needs no atomics.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    splats: &[Splat],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [f32; 3],
    forward: &CompositeOutput,
    grad_image_alpha: &[f32],
) -> Vec<SplatGrad> {
    let mut per_intersection = vec![SplatGrad::default(); bins.intersection_count()];
    // Split the intersection gradients into one contiguous slice per tile row.
    let mut rows: Vec<(u32, &mut [SplatGrad])> = Vec::with_capacity(bins.tiles_y as usize);
    let mut rest = per_intersection.as_mut_slice();
    for ty in 0..bins.tiles_y {
        let len = bins.row_range(ty).len();
        let (head, tail) = rest.split_at_mut(len);
        rows.push((ty, head));
        rest = tail;
    }
    rows.into_par_iter().for_each(|(ty, row_grads)| {
        let (y0, y1) = row_pixel_range(ty, height);
        let row_start = bins.row_range(ty).start;
        for tx in 0..bins.tiles_x {
            let tile = (ty * bins.tiles_x + tx) as usize;
            let range = bins.tile_offsets[tile] as usize..bins.tile_offsets[tile + 1] as usize;
            let local = gather(splats, &bins.gaussian_from_intersection[range.clone()]);
            let grads = &mut row_grads[range.start - row_start..range.end - row_start];
            let x0 = tx * TILE_SIZE;
            let x1 = (x0 + TILE_SIZE).min(width);
            for y in y0..y1 {
                for x in x0..x1 {
                    let p = (y * width + x) as usize;
                    let v_color = [
                        grad_image_alpha[p * 4],
                        grad_image_alpha[p * 4 + 1],
                        grad_image_alpha[p * 4 + 2],
                    ];
                    let v_alpha_out = grad_image_alpha[p * 4 + 3];
                    let t_final = forward.final_transmittance[p];
                    let v_background: f32 = (0..3).map(|c| background[c] * v_color[c]).sum();
                    let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                    // Colour composited behind the current Gaussian: sum over later j of c_j a_j T_j.
                    let mut behind = [0.0f32; 3];
                    let mut t = t_final;
                    for k in (0..forward.n_contrib[p] as usize).rev() {
                        let s = &local[k];
                        let (dx, dy) = (s.splat.mean2d[0] - px, s.splat.mean2d[1] - py);
                        let Some((alpha, raw, _)) = pair_alpha(s, dx, dy) else {
                            continue;
                        };
                        let one_minus = 1.0 - alpha;
                        t /= one_minus; // transmittance in front of Gaussian k
                        let inv_one_minus = 1.0 / one_minus;
                        let weight = alpha * t;
                        let g = &mut grads[k];
                        let mut v_a = 0.0f32;
                        for c in 0..3 {
                            g.color[c] += weight * v_color[c];
                            v_a += (s.splat.color[c] * t - behind[c] * inv_one_minus) * v_color[c];
                            behind[c] += s.splat.color[c] * weight;
                        }
                        v_a += t_final * inv_one_minus * (v_alpha_out - v_background);
                        // The 0.999 clamp is a constant: no gradient to opacity or sigma there.
                        if raw <= ALPHA_MAX {
                            let [a, b, c] = s.splat.conic;
                            let v_sigma = -raw * v_a;
                            g.opacity += raw / s.splat.opacity * v_a;
                            g.conic[0] += 0.5 * dx * dx * v_sigma;
                            g.conic[1] += dx * dy * v_sigma;
                            g.conic[2] += 0.5 * dy * dy * v_sigma;
                            g.mean2d[0] += v_sigma * (a * dx + b * dy);
                            g.mean2d[1] += v_sigma * (b * dx + c * dy);
                        }
                    }
                }
            }
        }
    });

    let mut per_gaussian = vec![SplatGrad::default(); splats.len()];
    for (g, grad) in bins
        .gaussian_from_intersection
        .iter()
        .zip(&per_intersection)
    {
        per_gaussian[*g as usize].add(grad);
    }
    per_gaussian
}
