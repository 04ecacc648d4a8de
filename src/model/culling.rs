//! Which anchors can put a Gaussian on screen: the geometric tests [`super::view`] culls with
//! before decoding (spec §4.1).
//!
//! Two tests, one per [`super::view::AnchorCulling`] mode that culls:
//! - [`visible_anchors`], GIFStream's: the anchor as a Gaussian of its offset scale;
//! - [`anchors_reaching_view`], acags': a bound on where the anchor's Gaussians can be, so that
//!   no Gaussian the rasterizer would draw is dropped.

use rayon::prelude::*;

use super::anchors::{AnchorSet, Column};
use crate::raster::RasterCamera;
use crate::raster::conventions::{EPS2D, FAR_PLANE, MAX_EXTENT_SIGMAS, NEAR_PLANE};
use crate::raster::cpu::project::{GaussianParams, ProjectionCamera, project};

/// Anchors whose offset-scale Gaussian lands on screen (GIFStream `view_to_visible_anchors`):
/// centre = `positions[i]`, identity rotation, scale exp(log_scales[0:3]).
///
/// Deviation: the extent test is the rasterizer's opacity-aware one at opacity 1 (3.33σ) rather
/// than gsplat's 3σ, so a few more anchors at the image border count as visible; they spawn
/// Gaussians that the rasterizer culls again, so the render is unchanged.
///
/// This is a heuristic: a Gaussian at offset ≥ 3.33 offset scales, or wide itself, can reach the
/// image while its anchor's box does not, and is then dropped (the export-fidelity check found
/// one, 52/255 at an image border, docs/results.md "Export fidelity").
pub fn visible_anchors(
    positions: &[[f32; 3]],
    log_scales: &[f32],
    camera: &RasterCamera,
) -> Vec<u32> {
    let cam = ProjectionCamera::new(camera);
    positions
        .par_iter()
        .enumerate()
        .filter_map(|(i, &mean)| {
            let s = &log_scales[i * 6..i * 6 + 3];
            let g = GaussianParams {
                mean,
                quat: [1.0, 0.0, 0.0, 0.0],
                scale: [s[0].exp(), s[1].exp(), s[2].exp()],
                opacity: 1.0,
            };
            project(&g, &cam).map(|_| i as u32)
        })
        .collect()
}

/// Where each anchor's Gaussians can lie around the anchor's (deformed) centre.
///
/// A Gaussian of anchor i sits at centre + R·(offset_k ⊙ s[0:3]) with R a rotation
/// (`spawn.rs`), so within `offset_reach[i]` = max_k |offset_k ⊙ s[0:3]| of the centre, whatever
/// the motion's rotation; its scales are s[3:6] ⊙ sigmoid(·) (times a pruning gate ≤ 1), so no
/// standard deviation exceeds `gaussian_sigma[i]` = max(s[3:6]). Every slot counts, gated or
/// not (a looser bound, never a wrong one).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AnchorReach {
    pub offset_reach: Vec<f32>,
    pub gaussian_sigma: Vec<f32>,
}

impl AnchorReach {
    /// The reach of every anchor of `set`, from its plain values: computed on the set's device,
    /// one [N, 2] read-back.
    pub fn of(set: &AnchorSet) -> Self {
        if set.is_empty() {
            return Self::default();
        }
        Self::from_rows(&super::anchors::host_values(&Self::on_device(set)), 2, 0)
    }

    /// The reach read from a row-major table of `width` columns whose columns `first` and
    /// `first + 1` hold [`Self::on_device`]'s two (so that it can share a read-back).
    pub fn from_rows(values: &[f32], width: usize, first: usize) -> Self {
        assert!(first + 2 <= width && values.len() % width == 0);
        let (offset_reach, gaussian_sigma) = values
            .chunks_exact(width)
            .map(|r| (r[first], r[first + 1]))
            .unzip();
        Self {
            offset_reach,
            gaussian_sigma,
        }
    }

    /// [N, 2] (offset reach, Gaussian sigma) of every anchor of a non-empty `set`, on its device.
    pub fn on_device(set: &AnchorSet) -> burn::tensor::Tensor<2> {
        let n = set.len();
        let slots = set.dims.slots;
        let scales = set.value(Column::LogScales).clone().exp();
        let offset_scale = crate::raster::columns::slice_columns(scales.clone(), 0..3);
        let gaussian_scale = crate::raster::columns::slice_columns(scales, 3..6);
        let offsets = set.value(Column::Offsets).clone().reshape([n, slots, 3])
            * offset_scale.reshape([n, 1, 3]);
        let reach = offsets
            .powi_scalar(2)
            .sum_dim(2)
            .max_dim(1)
            .sqrt()
            .reshape([n, 1]);
        let sigma = gaussian_scale.max_dim(1);
        burn::tensor::Tensor::cat(vec![reach, sigma], 1)
    }
}

/// Anchors of which some Gaussian, anywhere within its [`AnchorReach`] of `centres[i]`, can pass
/// the rasterizer's projection test (`kernels/src/cpu/project.rs`): a superset of the anchors
/// the rasterizer draws something of, so culling with it leaves the render as decoding every
/// anchor would give it (tested).
///
/// Why it holds. The rasterizer keeps a Gaussian when its depth z is in [near, far] and its
/// screen box, mean u = fx·x/z + cx ± r, meets the image. The box half-width is
/// r = ⌈3.33·√(jᵀΣj + ε)⌉ with |j| = (fx/z)·√(1 + (x/z)²) and x/z clamped to the Jacobian's
/// limits, so r ≤ 3.33·σ·(fx/z)·k + b with k = √(1 + lim²) and b = 3.33·√ε + 1. "u + r > 0"
/// then implies fx·x + (cx + b)·z + 3.33·σ·fx·k > 0 (times z > 0), linear in the camera-space
/// point (x, z): a half-space. A ball of radius ρ around c meets it iff
/// n·c + |n|·ρ + 3.33·σ·fx·k > 0 with n = (fx, cx + b). The other three image sides are alike,
/// and the depth test needs c_z + ρ ≥ near and c_z − ρ ≤ far. Each side is tested on its own,
/// so the test is conservative at the image corners (an anchor near a corner, outside both
/// sides' half-spaces' intersection, is kept).
///
/// Deviation from GIFStream (whose [`visible_anchors`] test is a heuristic): acags' default
/// culling must not change what is drawn, only what it costs, so that a render and its export
/// see the same Gaussians. (Training culls on the plain values but draws the
/// quantisation-simulated ones, which can reach up to a quantisation step further: a sliver the
/// bound does not cover, as the box test did not.)
pub fn anchors_reaching_view(
    centres: &[[f32; 3]],
    reach: &AnchorReach,
    camera: &RasterCamera,
) -> Vec<u32> {
    assert_eq!(
        centres.len(),
        reach.offset_reach.len(),
        "one reach per anchor"
    );
    let rotation = camera.rotation();
    // The bound needs a rotation (lengths preserved): a camera matrix that scales or shears,
    // which the rasterizer accepts as given, keeps every anchor instead of culling wrongly.
    let orthonormal = (0..3).all(|i| {
        (0..3).all(|j| {
            let dot: f32 = (0..3).map(|c| rotation[i][c] * rotation[j][c]).sum();
            (dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-3
        })
    });
    if !orthonormal {
        return (0..centres.len() as u32).collect();
    }
    let translation = camera.translation();
    let [lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg] = camera.jacobian_clamp_limits();
    let k_x = (1.0 + lim_x_pos.max(lim_x_neg).powi(2)).sqrt();
    let k_y = (1.0 + lim_y_pos.max(lim_y_neg).powi(2)).sqrt();
    // The box's pixel slack beyond the Gaussian's own extent: the ε term, the ceil, and half a
    // pixel for the rounding of the float arithmetic on both sides.
    let b = MAX_EXTENT_SIGMAS * EPS2D.sqrt() + 1.5;
    let (w, h) = (camera.width as f32, camera.height as f32);
    // Per side: (focal, normal's z part, sign, Jacobian bound k, image axis, |normal|), the
    // normal's length computed once per view, not per anchor. Sign +1 tests "box right/lower
    // edge > 0", −1 tests "box left/upper edge < image size".
    let sides = [
        (camera.fx, camera.cx + b, 1.0f32, k_x, 0usize),
        (camera.fx, camera.cx - w - b, -1.0, k_x, 0),
        (camera.fy, camera.cy + b, 1.0, k_y, 1),
        (camera.fy, camera.cy - h - b, -1.0, k_y, 1),
    ]
    .map(|(focal, nz, sign, k, axis)| (focal, nz, sign, k, axis, (focal * focal + nz * nz).sqrt()));
    centres
        .par_iter()
        .enumerate()
        .filter_map(|(i, centre)| {
            let p: [f32; 3] = std::array::from_fn(|r| {
                rotation[r][0] * centre[0]
                    + rotation[r][1] * centre[1]
                    + rotation[r][2] * centre[2]
                    + translation[r]
            });
            // A little slack on the offset bound for the decode's own rounding.
            let rho = reach.offset_reach[i] * (1.0 + 1e-4) + 1e-6;
            let sigma = reach.gaussian_sigma[i];
            if !p.iter().all(|v| v.is_finite()) {
                return None;
            }
            // One non-finite slot must not hide the anchor's finite ones: no bound, kept.
            if !(rho.is_finite() && sigma.is_finite()) {
                return Some(i as u32);
            }
            if p[2] + rho < NEAR_PLANE || p[2] - rho > FAR_PLANE {
                return None;
            }
            let reaches = sides.iter().all(|&(focal, nz, sign, k, axis, norm)| {
                let along = focal * p[axis] + nz * p[2];
                sign * along + norm * rho + MAX_EXTENT_SIGMAS * sigma * focal * k > 0.0
            });
            reaches.then_some(i as u32)
        })
        .collect()
}
