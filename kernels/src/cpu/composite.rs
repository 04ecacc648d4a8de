//! Per-pixel alpha compositing over tiles: forward, and its backward without per-pixel lists.
//!
//! Each tile row (16 image rows) is one parallel work item: its pixels, its per-pixel state and its
//! intersections are contiguous, so threads write disjoint slices and results are deterministic.
//!
//! Inside a tile the loop runs over Gaussians (front to back, or back to front in the backward)
//! and, for each, only over the tile pixels inside its opacity-aware screen box: outside it alpha
//! is below 1/255 by construction. Every pixel still sees its Gaussians in depth order with the same
//! arithmetic, so the result equals a dense per-pixel loop bit for bit (a test checks this).

use rayon::prelude::*;

use super::bin::TileBins;
use crate::conventions::{ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_STOP};

const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;

/// What compositing needs of one Gaussian, gathered per tile for locality.
#[derive(Clone, Copy, Debug, Default)]
pub struct Splat {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub color: [f32; 3],
    /// Opacity-aware half extents of the screen box (pixels).
    pub radius: [f32; 2],
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
    /// Tile-local pixel box [x0, x1) x [y0, y1) the splat can reach.
    bounds: [usize; 4],
}

const SIGMA_CUT_MARGIN: f32 = 1e-3;

/// Pixel box of a splat clipped to a tile whose top-left pixel is (tx0, ty0) and which has
/// `w` x `h` pixels. Pixel centres within `radius` of the mean, widened by one pixel against
/// rounding at the edge.
fn tile_bounds(s: &Splat, tx0: u32, ty0: u32, w: usize, h: usize) -> [usize; 4] {
    let axis = |mean: f32, radius: f32, origin: u32, len: usize| {
        let lo = (mean - radius - 0.5).floor() - 1.0 - origin as f32;
        let hi = (mean + radius - 0.5).ceil() + 2.0 - origin as f32;
        (
            lo.clamp(0.0, len as f32) as usize,
            hi.clamp(0.0, len as f32) as usize,
        )
    };
    let (x0, x1) = axis(s.mean2d[0], s.radius[0], tx0, w);
    let (y0, y1) = axis(s.mean2d[1], s.radius[1], ty0, h);
    [x0, x1, y0, y1]
}

/// The tile at (tx, ty): its pixel origin and size.
struct TileGeometry {
    x0: u32,
    y0: u32,
    w: usize,
    h: usize,
}

impl TileGeometry {
    fn new(tx: u32, ty: u32, width: u32, height: u32) -> Self {
        let (x0, y0) = (tx * TILE_SIZE, ty * TILE_SIZE);
        Self {
            x0,
            y0,
            w: ((x0 + TILE_SIZE).min(width) - x0) as usize,
            h: ((y0 + TILE_SIZE).min(height) - y0) as usize,
        }
    }

    fn pixel_centre(&self, lx: usize, ly: usize) -> (f32, f32) {
        (
            (self.x0 as usize + lx) as f32 + 0.5,
            (self.y0 as usize + ly) as f32 + 0.5,
        )
    }
}

fn gather(splats: &[Splat], ids: &[u32], tile: &TileGeometry) -> Vec<TileSplat> {
    ids.iter()
        .map(|&g| {
            let splat = splats[g as usize];
            TileSplat {
                splat,
                sigma_cut: (splat.opacity / ALPHA_MIN).ln() + SIGMA_CUT_MARGIN,
                bounds: tile_bounds(&splat, tile.x0, tile.y0, tile.w, tile.h),
            }
        })
        .collect()
}

/// alpha of a pair and `o * exp(-sigma)` unclamped, or `None` when the pair is skipped
/// (sigma < 0 or alpha < 1/255).
#[inline(always)]
fn pair_alpha(s: &TileSplat, dx: f32, dy: f32) -> Option<(f32, f32)> {
    let sigma = s.splat.sigma(dx, dy);
    if sigma < 0.0 || sigma > s.sigma_cut {
        return None;
    }
    let raw = s.splat.opacity * (-sigma).exp();
    let alpha = raw.min(ALPHA_MAX);
    if alpha < ALPHA_MIN {
        return None;
    }
    Some((alpha, raw))
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

fn tile_range(bins: &TileBins, tile: usize) -> std::ops::Range<usize> {
    bins.tile_offsets[tile] as usize..bins.tile_offsets[tile + 1] as usize
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
            for tx in 0..bins.tiles_x {
                let tile = TileGeometry::new(tx, ty, width, height);
                let local = gather(
                    splats,
                    &bins.gaussian_from_intersection
                        [tile_range(bins, (ty * bins.tiles_x + tx) as usize)],
                    &tile,
                );
                let mut t = [1.0f32; TILE_PIXELS];
                let mut color = [[0.0f32; 3]; TILE_PIXELS];
                let mut last = [0u32; TILE_PIXELS];
                let mut done = [false; TILE_PIXELS];
                let mut remaining = tile.w * tile.h;
                for (k, s) in local.iter().enumerate() {
                    let [bx0, bx1, by0, by1] = s.bounds;
                    for ly in by0..by1 {
                        for lx in bx0..bx1 {
                            let p = ly * TILE_SIZE as usize + lx;
                            if done[p] {
                                continue;
                            }
                            let (px, py) = tile.pixel_centre(lx, ly);
                            let Some((alpha, _)) =
                                pair_alpha(s, s.splat.mean2d[0] - px, s.splat.mean2d[1] - py)
                            else {
                                continue;
                            };
                            let next_t = t[p] * (1.0 - alpha);
                            if next_t <= TRANSMITTANCE_STOP {
                                done[p] = true;
                                remaining -= 1;
                                continue;
                            }
                            let weight = alpha * t[p];
                            for c in 0..3 {
                                color[p][c] += s.splat.color[c] * weight;
                            }
                            t[p] = next_t;
                            last[p] = k as u32 + 1;
                        }
                    }
                    if remaining == 0 {
                        break; // every pixel of the tile is saturated
                    }
                }
                for ly in 0..tile.h {
                    for lx in 0..tile.w {
                        let p = ly * TILE_SIZE as usize + lx;
                        let o = ly * w + tile.x0 as usize + lx;
                        for c in 0..3 {
                            image[o * 4 + c] = color[p][c] + t[p] * background[c];
                        }
                        image[o * 4 + 3] = 1.0 - t[p];
                        transmittance[o] = t[p];
                        n_contrib[o] = last[p];
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
    let w = width as usize;
    let mut per_intersection = vec![SplatGrad::default(); bins.intersection_count()];
    // Split the intersection gradients into one contiguous slice per tile row.
    let mut rows: Vec<(u32, &mut [SplatGrad])> = Vec::with_capacity(bins.tiles_y as usize);
    let mut rest = per_intersection.as_mut_slice();
    for ty in 0..bins.tiles_y {
        let (head, tail) = rest.split_at_mut(bins.row_range(ty).len());
        rows.push((ty, head));
        rest = tail;
    }
    rows.into_par_iter().for_each(|(ty, row_grads)| {
        let row_start = bins.row_range(ty).start;
        for tx in 0..bins.tiles_x {
            let tile = TileGeometry::new(tx, ty, width, height);
            let range = tile_range(bins, (ty * bins.tiles_x + tx) as usize);
            let local = gather(
                splats,
                &bins.gaussian_from_intersection[range.clone()],
                &tile,
            );
            let grads = &mut row_grads[range.start - row_start..range.end - row_start];
            // Per-pixel state, walked back to front from the forward's final values.
            let mut t = [0.0f32; TILE_PIXELS];
            let mut n_contrib = [0usize; TILE_PIXELS];
            let mut v_color = [[0.0f32; 3]; TILE_PIXELS];
            // dLoss/dT_final's coefficient: v_alpha_out - background . v_color.
            let mut v_final = [0.0f32; TILE_PIXELS];
            let mut t_final = [0.0f32; TILE_PIXELS];
            // Colour composited behind the current Gaussian: sum over later j of c_j a_j T_j.
            let mut behind = [[0.0f32; 3]; TILE_PIXELS];
            let mut deepest = 0;
            for ly in 0..tile.h {
                for lx in 0..tile.w {
                    let p = ly * TILE_SIZE as usize + lx;
                    let o = ly * w + tile.x0 as usize + lx + tile.y0 as usize * w;
                    t[p] = forward.final_transmittance[o];
                    t_final[p] = t[p];
                    n_contrib[p] = forward.n_contrib[o] as usize;
                    deepest = deepest.max(n_contrib[p]);
                    v_color[p] = [
                        grad_image_alpha[o * 4],
                        grad_image_alpha[o * 4 + 1],
                        grad_image_alpha[o * 4 + 2],
                    ];
                    let v_background: f32 = (0..3).map(|c| background[c] * v_color[p][c]).sum();
                    v_final[p] = grad_image_alpha[o * 4 + 3] - v_background;
                }
            }
            for k in (0..deepest).rev() {
                let s = &local[k];
                let g = &mut grads[k];
                let [bx0, bx1, by0, by1] = s.bounds;
                for ly in by0..by1 {
                    for lx in bx0..bx1 {
                        let p = ly * TILE_SIZE as usize + lx;
                        if k >= n_contrib[p] {
                            continue;
                        }
                        let (px, py) = tile.pixel_centre(lx, ly);
                        let (dx, dy) = (s.splat.mean2d[0] - px, s.splat.mean2d[1] - py);
                        let Some((alpha, raw)) = pair_alpha(s, dx, dy) else {
                            continue;
                        };
                        let one_minus = 1.0 - alpha;
                        t[p] /= one_minus; // transmittance in front of Gaussian k
                        let inv_one_minus = 1.0 / one_minus;
                        let weight = alpha * t[p];
                        let mut v_a = 0.0f32;
                        for c in 0..3 {
                            g.color[c] += weight * v_color[p][c];
                            v_a += (s.splat.color[c] * t[p] - behind[p][c] * inv_one_minus)
                                * v_color[p][c];
                            behind[p][c] += s.splat.color[c] * weight;
                        }
                        v_a += t_final[p] * inv_one_minus * v_final[p];
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
