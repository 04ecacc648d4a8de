//! Which anchors can put a Gaussian on screen: the geometric tests [`super::view`] culls with
//! before decoding (spec §4.1).
//!
//! Two tests, one per [`super::view::AnchorCulling`] mode that culls:
//! - [`visible_anchors`], GIFStream's: the anchor as a Gaussian of its offset scale;
//! - [`anchors_reaching_view`], acags': a bound on where the anchor's Gaussians can be, so that
//!   no Gaussian the rasterizer would draw is dropped.
//!
//! And one test in time: [`FirstDrawnFrames`], the frames before which a training step does not
//! draw an anchor.

use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use super::anchors::{AnchorSet, Column};
use crate::raster::RasterCamera;
use crate::raster::columns::{concat_columns, slice_columns};
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
    pub fn on_device(set: &AnchorSet) -> Tensor<2> {
        Self::of_columns(
            set.value(Column::LogScales).clone(),
            set.value(Column::Offsets).clone(),
            set.dims.slots,
        )
    }

    /// [`Self::on_device`] from the log-scale [N, 6] and offset [N, K·3] columns themselves (e.g.
    /// a training step's quantisation-simulated values, detached).
    pub fn of_columns(log_scales: Tensor<2>, offsets: Tensor<2>, slots: usize) -> Tensor<2> {
        let n = log_scales.dims()[0];
        let scales = log_scales.exp();
        let offset_scale = slice_columns(scales.clone(), 0..3);
        let gaussian_scale = slice_columns(scales, 3..6);
        let offsets = offsets.reshape([n, slots, 3]) * offset_scale.reshape([n, 1, 3]);
        let reach = offsets
            .powi_scalar(2)
            .sum_dim(2)
            .max_dim(1)
            .sqrt()
            .reshape([n, 1]);
        let sigma = gaussian_scale.max_dim(1);
        concat_columns(reach, sigma)
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
/// see the same Gaussians. (A training step culls on the quantisation-simulated values it draws,
/// [`anchors_reaching_view_mask`]; with `train.step_culling = "host"` it culls on the plain
/// values, and the simulated ones can reach up to a quantisation step further: a sliver the
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
    let Some(test) = ReachTest::of(camera) else {
        return (0..centres.len() as u32).collect();
    };
    let (rotation, translation) = (test.rotation, test.translation);
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
            let rho = reach.offset_reach[i] * RHO_SCALE + RHO_SLACK;
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
            let reaches = test.sides.iter().all(|side| {
                let along = side.focal * p[side.axis] + side.normal_z * p[2];
                side.sign * along
                    + side.normal_length * rho
                    + MAX_EXTENT_SIGMAS * sigma * side.focal * side.jacobian_bound
                    > 0.0
            });
            reaches.then_some(i as u32)
        })
        .collect()
}

/// [`anchors_reaching_view`] on the device: [N] 1.0 where anchor i is kept, 0.0 where it is
/// culled, from `centres` [N, 3] and `reach` [N, 2] (the columns of [`AnchorReach::on_device`]).
/// Nothing is read back, so a training step can decode every row and mask the culled ones
/// instead of waiting for the list (`train.step_culling = "device"`). The same f32 operations in
/// the same order as the host test, element by element, so both keep the same anchors on the
/// CPU backend (tested).
pub fn anchors_reaching_view_mask(
    centres: Tensor<2>,
    reach: Tensor<2>,
    camera: &RasterCamera,
) -> Tensor<1> {
    let n = centres.dims()[0];
    assert_eq!(reach.dims(), [n, 2], "one (reach, sigma) row per anchor");
    let device = centres.device();
    let Some(test) = ReachTest::of(camera) else {
        return Tensor::ones([n], &device);
    };
    let column = |t: &Tensor<2>, c: usize| slice_columns(t.clone(), c..c + 1).reshape([n]);
    let c = [
        column(&centres, 0),
        column(&centres, 1),
        column(&centres, 2),
    ];
    let p: [Tensor<1>; 3] = std::array::from_fn(|r| {
        let rot = test.rotation[r];
        (c[0].clone().mul_scalar(rot[0])
            + c[1].clone().mul_scalar(rot[1])
            + c[2].clone().mul_scalar(rot[2]))
        .add_scalar(test.translation[r])
    });
    let rho = column(&reach, 0)
        .mul_scalar(RHO_SCALE)
        .add_scalar(RHO_SLACK);
    let sigma = column(&reach, 1);
    let finite_p = p[0]
        .clone()
        .is_finite()
        .bool_and(p[1].clone().is_finite())
        .bool_and(p[2].clone().is_finite());
    let unbounded = rho
        .clone()
        .is_finite()
        .bool_and(sigma.clone().is_finite())
        .bool_not();
    let in_depth = (p[2].clone() + rho.clone())
        .lower_elem(NEAR_PLANE)
        .bool_or((p[2].clone() - rho.clone()).greater_elem(FAR_PLANE))
        .bool_not();
    let reaches = test.sides.iter().fold(in_depth, |kept, side| {
        let along =
            p[side.axis].clone().mul_scalar(side.focal) + p[2].clone().mul_scalar(side.normal_z);
        let margin = along.mul_scalar(side.sign)
            + rho.clone().mul_scalar(side.normal_length)
            + sigma
                .clone()
                .mul_scalar(MAX_EXTENT_SIGMAS)
                .mul_scalar(side.focal)
                .mul_scalar(side.jacobian_bound);
        kept.bool_and(margin.greater_elem(0.0))
    });
    finite_p.bool_and(unbounded.bool_or(reaches)).float()
}

/// The offset bound's relative and absolute slack for the decode's own rounding.
const RHO_SCALE: f32 = 1.0 + 1e-4;
const RHO_SLACK: f32 = 1e-6;

/// One side of the image as a half-space in camera space (see [`anchors_reaching_view`]):
/// sign · (focal·p[axis] + normal_z·p_z) + |normal|·ρ + 3.33·σ·focal·k > 0.
struct ImageSide {
    focal: f32,
    normal_z: f32,
    /// +1 tests "box right/lower edge > 0", −1 "box left/upper edge < image size".
    sign: f32,
    /// k: the bound on the Jacobian's norm per unit of focal/z.
    jacobian_bound: f32,
    /// 0 for x, 1 for y.
    axis: usize,
    /// |(focal, normal_z)|, computed once per view, not per anchor.
    normal_length: f32,
}

/// Per anchor, the first GOP frame a training step draws it at (0: every frame), on the host and
/// on the device. The trainer holds an anchor found at a later frame back from the frames
/// before it until its path there is set (`train.seed_hold`, `train/seed_hold.rs`); evaluation
/// and the decoder draw every anchor at every frame.
#[derive(Clone, Debug)]
pub struct FirstDrawnFrames {
    host: Vec<u32>,
    /// [N] the same frames as f32 (exact up to 2^24).
    device: Tensor<1>,
}

impl FirstDrawnFrames {
    pub fn new(first: Vec<u32>, device: &Device) -> Self {
        let values: Vec<f32> = first.iter().map(|&f| f as f32).collect();
        let n = values.len();
        let device = crate::device_io::upload(TensorData::new(values, [n]), device);
        Self {
            host: first,
            device,
        }
    }

    /// The anchors (rows) covered.
    pub fn len(&self) -> usize {
        self.host.len()
    }

    pub fn is_empty(&self) -> bool {
        self.host.is_empty()
    }

    /// Whether `anchor` is drawn at GOP frame `frame`.
    pub fn draws(&self, anchor: u32, frame: usize) -> bool {
        self.host[anchor as usize] as usize <= frame
    }

    /// [N] 1.0 where the anchor is held back from some frame (its first drawn frame is not 0).
    pub fn held(&self) -> Tensor<1> {
        self.device.clone().greater_elem(0.0).float()
    }

    /// [N] 1.0 where the anchor is drawn at GOP frame `frame`, 0.0 where it is held back (a
    /// [`super::view::VisibleRows::Masked`] mask's form; nothing uploaded).
    pub fn mask(&self, frame: usize) -> Tensor<1> {
        self.device.clone().lower_equal_elem(frame as f32).float()
    }
}

/// The per-view constants of the reach test, shared by the host and the device forms.
struct ReachTest {
    rotation: [[f32; 3]; 3],
    translation: [f32; 3],
    sides: [ImageSide; 4],
}

impl ReachTest {
    /// `None` for a camera whose matrix scales or shears: the bound needs a rotation (lengths
    /// preserved), and such a camera, which the rasterizer accepts as given, keeps every anchor
    /// instead of culling wrongly.
    fn of(camera: &RasterCamera) -> Option<Self> {
        let rotation = camera.rotation();
        let orthonormal = (0..3).all(|i| {
            (0..3).all(|j| {
                let dot: f32 = (0..3).map(|c| rotation[i][c] * rotation[j][c]).sum();
                (dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-3
            })
        });
        if !orthonormal {
            return None;
        }
        let [lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg] = camera.jacobian_clamp_limits();
        let k_x = (1.0 + lim_x_pos.max(lim_x_neg).powi(2)).sqrt();
        let k_y = (1.0 + lim_y_pos.max(lim_y_neg).powi(2)).sqrt();
        // The box's pixel slack beyond the Gaussian's own extent: the ε term, the ceil, and half
        // a pixel for the rounding of the float arithmetic on both sides.
        let b = MAX_EXTENT_SIGMAS * EPS2D.sqrt() + 1.5;
        let (w, h) = (camera.width as f32, camera.height as f32);
        let side =
            |focal: f32, normal_z: f32, sign: f32, jacobian_bound: f32, axis: usize| ImageSide {
                focal,
                normal_z,
                sign,
                jacobian_bound,
                axis,
                normal_length: (focal * focal + normal_z * normal_z).sqrt(),
            };
        Some(Self {
            rotation,
            translation: camera.translation(),
            sides: [
                side(camera.fx, camera.cx + b, 1.0, k_x, 0),
                side(camera.fx, camera.cx - w - b, -1.0, k_x, 0),
                side(camera.fy, camera.cy + b, 1.0, k_y, 1),
                side(camera.fy, camera.cy - h - b, -1.0, k_y, 1),
            ],
        })
    }
}
