//! Capacity heatmaps of one rendered view, like the paper's Fig. 7 (ACA-GS): where the model
//! spends anchors, Neural Gaussians and feature channels.
//!
//! The Gaussians the rasterizer draws are composited again on the host, front to back with the
//! rasterizer's rules (α = min(0.99, o·exp(−σ)), α < 1/255 skipped, stop at T < 1e-4), and each
//! pixel records
//! - how many distinct anchors contribute at least [`CONTRIBUTION_THRESHOLD`] of its blend
//!   weight (Fig. 7a: 0-1 blue, 2-4 green, ≥ 5 red);
//! - the blend-weighted mean cardinality (active slots) of the anchors behind it (Fig. 7b:
//!   1-3 blue, 4-6 green, 7-10 red);
//! - the blend-weighted mean fraction of feature channels those anchors use (Fig. 7c: blue = 50 %,
//!   red = 100 %).

use crate::model::anchors::{AnchorSet, host_values};
use crate::model::view::DecodedView;
use crate::raster::RasterCamera;
use crate::raster::cpu::project::{GaussianParams, ProjectionCamera, project};

/// An anchor counts for a pixel when its Gaussians carry at least this share of the pixel's
/// blend weight (T·α summed over the anchor's Gaussians): the anchors that shape the pixel, at
/// most 10 (with 2 % nearly every pixel of a trained scene shows ≥ 5 anchors and the map says
/// little).
pub const CONTRIBUTION_THRESHOLD: f32 = 0.1;
const MIN_ALPHA: f32 = 1.0 / 255.0;
const MAX_ALPHA: f32 = 0.99;
const MIN_TRANSMITTANCE: f32 = 1e-4;

/// Per-pixel maps, row-major [H, W].
#[derive(Clone, Debug)]
pub struct CapacityMaps {
    pub width: u32,
    pub height: u32,
    /// Distinct anchors contributing ≥ [`CONTRIBUTION_THRESHOLD`] of the blend weight.
    pub anchor_count: Vec<u32>,
    /// Blend-weighted mean cardinality; NaN where nothing was drawn.
    pub cardinality: Vec<f32>,
    /// Blend-weighted mean fraction of active feature channels; NaN where nothing was drawn.
    pub channel_fraction: Vec<f32>,
    /// Σ of blend weights (the render's alpha).
    pub alpha: Vec<f32>,
}

/// A Gaussian to composite and the anchor it belongs to.
#[derive(Clone, Copy, Debug)]
pub struct AnchoredGaussian {
    pub params: GaussianParams,
    pub anchor: u32,
}

/// Composites `gaussians` and measures the per-anchor `cardinality` and `channel_fraction`
/// (indexed by `AnchoredGaussian::anchor`) per pixel.
pub fn composite_capacity(
    gaussians: &[AnchoredGaussian],
    cardinality: &[f32],
    channel_fraction: &[f32],
    camera: &RasterCamera,
) -> CapacityMaps {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let cam = ProjectionCamera::new(camera);
    let mut projected: Vec<_> = gaussians
        .iter()
        .filter_map(|g| project(&g.params, &cam).map(|p| (p, g)))
        .collect();
    projected.sort_by(|a, b| a.0.depth.total_cmp(&b.0.depth));

    let mut transmittance = vec![1.0f32; w * h];
    let mut alpha_sum = vec![0.0f32; w * h];
    let mut card_sum = vec![0.0f32; w * h];
    let mut channel_sum = vec![0.0f32; w * h];
    // Per pixel: (anchor, weight so far) of the anchors seen.
    let mut contributions: Vec<Vec<(u32, f32)>> = vec![Vec::new(); w * h];
    for (p, g) in &projected {
        let [cx, cy] = p.mean2d;
        let x0 = (cx - p.radius[0] as f32).floor().max(0.0) as usize;
        let x1 = ((cx + p.radius[0] as f32).ceil() as i64).clamp(0, w as i64) as usize;
        let y0 = (cy - p.radius[1] as f32).floor().max(0.0) as usize;
        let y1 = ((cy + p.radius[1] as f32).ceil() as i64).clamp(0, h as i64) as usize;
        let [a, b, c] = p.conic;
        let anchor = g.anchor as usize;
        for y in y0..y1 {
            for x in x0..x1 {
                let i = y * w + x;
                if transmittance[i] < MIN_TRANSMITTANCE {
                    continue;
                }
                let (dx, dy) = (x as f32 + 0.5 - cx, y as f32 + 0.5 - cy);
                let sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
                if sigma < 0.0 {
                    continue;
                }
                let alpha = (g.params.opacity * (-sigma).exp()).min(MAX_ALPHA);
                if alpha < MIN_ALPHA {
                    continue;
                }
                let weight = transmittance[i] * alpha;
                transmittance[i] *= 1.0 - alpha;
                alpha_sum[i] += weight;
                card_sum[i] += weight * cardinality[anchor];
                channel_sum[i] += weight * channel_fraction[anchor];
                let list = &mut contributions[i];
                match list.iter_mut().find(|(id, _)| *id == g.anchor) {
                    Some(entry) => entry.1 += weight,
                    None => list.push((g.anchor, weight)),
                }
            }
        }
    }
    let mean = |sum: &[f32]| -> Vec<f32> {
        sum.iter()
            .zip(&alpha_sum)
            .map(|(&s, &a)| if a > 0.0 { s / a } else { f32::NAN })
            .collect()
    };
    CapacityMaps {
        width: camera.width,
        height: camera.height,
        anchor_count: contributions
            .iter()
            .zip(&alpha_sum)
            .map(|(list, &total)| {
                list.iter()
                    .filter(|(_, weight)| *weight >= CONTRIBUTION_THRESHOLD * total.max(1e-12))
                    .count() as u32
            })
            .collect(),
        cardinality: mean(&card_sum),
        channel_fraction: mean(&channel_sum),
        alpha: alpha_sum,
    }
}

/// The maps of a decoded view of `set`.
pub fn capacity_maps(set: &AnchorSet, view: &DecodedView, camera: &RasterCamera) -> CapacityMaps {
    let g = &view.gaussians;
    let means = host_values(&g.means);
    let quats = host_values(&g.quats);
    let scales = host_values(&g.scales);
    let opacities = host_values(&g.opacities);
    let gates = host_values(&g.gates);
    let k = set.dims.slots;
    let gaussians: Vec<AnchoredGaussian> = (0..gates.len())
        .filter(|&i| gates[i] > 0.0)
        .map(|i| AnchoredGaussian {
            params: GaussianParams {
                mean: [means[3 * i], means[3 * i + 1], means[3 * i + 2]],
                quat: [
                    quats[4 * i],
                    quats[4 * i + 1],
                    quats[4 * i + 2],
                    quats[4 * i + 3],
                ],
                scale: [scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]],
                opacity: opacities[i] * gates[i],
            },
            anchor: view.visible.anchor_of_row(i / k),
        })
        .collect();
    let cardinality: Vec<f32> = (0..set.len()).map(|a| set.cardinality(a) as f32).collect();
    let channels: Vec<f32> = set
        .active_feature_channels()
        .into_iter()
        .map(|c| c as f32 / set.dims.feature_dim as f32)
        .collect();
    composite_capacity(&gaussians, &cardinality, &channels, camera)
}

const BLUE: [f32; 3] = [0.15, 0.35, 1.0];
const GREEN: [f32; 3] = [0.1, 0.85, 0.2];
const RED: [f32; 3] = [1.0, 0.15, 0.1];

/// Fig. 7a buckets.
pub fn anchor_count_color(count: u32) -> [f32; 3] {
    match count {
        0..=1 => BLUE,
        2..=4 => GREEN,
        _ => RED,
    }
}

/// Fig. 7b buckets of the (rounded) mean cardinality.
pub fn cardinality_color(cardinality: f32) -> [f32; 3] {
    match cardinality.round() as i64 {
        i64::MIN..=3 => BLUE,
        4..=6 => GREEN,
        _ => RED,
    }
}

/// Fig. 7c ramp: 50 % of the channels blue, 100 % red.
pub fn channel_color(fraction: f32) -> [f32; 3] {
    let t = ((fraction - 0.5) / 0.5).clamp(0.0, 1.0);
    std::array::from_fn(|c| BLUE[c] + t * (RED[c] - BLUE[c]))
}

/// 8-bit RGB of a heat layer over the render's luminance; pixels the model does not cover
/// (alpha < 0.05) show the dimmed render.
pub fn overlay(
    render: &[f32],
    maps: &CapacityMaps,
    color_of: impl Fn(usize) -> [f32; 3],
) -> Vec<u8> {
    let pixels = (maps.width * maps.height) as usize;
    let mut out = Vec::with_capacity(pixels * 3);
    for i in 0..pixels {
        let rgb = &render[3 * i..3 * i + 3];
        let luma = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2];
        let pixel: [f32; 3] = if maps.alpha[i] < 0.05 {
            [0.3 * luma; 3]
        } else {
            let heat = color_of(i);
            std::array::from_fn(|c| 0.65 * heat[c] + 0.35 * luma)
        };
        out.extend(pixel.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8));
    }
    out
}
