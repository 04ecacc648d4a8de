//! The CPU twin of the rasterizer: tile-binned forward and backward in plain Rust, parallel with
//! rayon. The CubeCL kernels must agree with it (and it with the gsplat fixtures).

pub mod bin;
pub mod composite;
pub mod project;

use rayon::prelude::*;

pub use bin::{TileBins, bin_tiles, is_visible};
pub use composite::{CompositeOutput, Splat, SplatGrad};
pub use project::{GaussianParams, Projected, ProjectionCamera};

use crate::RasterError;
use crate::camera::RasterCamera;

/// Borrowed per-Gaussian inputs, flat row-major: means [N,3], quats [N,4] (w,x,y,z, raw),
/// scales [N,3] (activated), opacities [N] (activated), gates [N] (0 removes the Gaussian),
/// colors [N,3].
#[derive(Clone, Copy, Debug)]
pub struct GaussianSlices<'a> {
    pub means: &'a [f32],
    pub quats: &'a [f32],
    pub scales: &'a [f32],
    pub opacities: &'a [f32],
    pub gates: &'a [f32],
    pub colors: &'a [f32],
}

impl GaussianSlices<'_> {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks that every array has N rows of the right width.
    pub fn validate(&self) -> Result<(), RasterError> {
        let n = self.len();
        for (name, data, width) in [
            ("means", self.means, 3),
            ("quats", self.quats, 4),
            ("scales", self.scales, 3),
            ("opacities", self.opacities, 1),
            ("gates", self.gates, 1),
            ("colors", self.colors, 3),
        ] {
            if data.len() != n * width {
                return Err(RasterError::Shape(format!(
                    "{name} has {} values, expected {n} x {width} (N = {n} from opacities)",
                    data.len()
                )));
            }
        }
        Ok(())
    }

    /// Geometry of Gaussian `i`, with the gate folded into the opacity.
    #[inline]
    pub fn params(&self, i: usize) -> GaussianParams {
        GaussianParams {
            mean: [
                self.means[3 * i],
                self.means[3 * i + 1],
                self.means[3 * i + 2],
            ],
            quat: [
                self.quats[4 * i],
                self.quats[4 * i + 1],
                self.quats[4 * i + 2],
                self.quats[4 * i + 3],
            ],
            scale: [
                self.scales[3 * i],
                self.scales[3 * i + 1],
                self.scales[3 * i + 2],
            ],
            opacity: self.gates[i] * self.opacities[i],
        }
    }

    #[inline]
    pub fn color(&self, i: usize) -> [f32; 3] {
        [
            self.colors[3 * i],
            self.colors[3 * i + 1],
            self.colors[3 * i + 2],
        ]
    }

    /// Gated Gaussians and Gaussians with a non-finite colour are removed before projection.
    #[inline]
    fn participates(&self, i: usize) -> bool {
        let gate = self.gates[i];
        gate != 0.0 && gate.is_finite() && self.color(i).iter().all(|c| c.is_finite())
    }
}

/// Owned per-Gaussian arrays in the rasterizer's layout.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianArrays {
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub scales: Vec<f32>,
    pub opacities: Vec<f32>,
    pub gates: Vec<f32>,
    pub colors: Vec<f32>,
}

impl GaussianArrays {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn slices(&self) -> GaussianSlices<'_> {
        GaussianSlices {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
            gates: &self.gates,
            colors: &self.colors,
        }
    }
}

/// Projects every Gaussian; culled (and gated) ones get the default `Projected` (radius 0).
pub fn project_all(gaussians: &GaussianSlices, camera: &ProjectionCamera) -> Vec<Projected> {
    (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            if !gaussians.participates(i) {
                return Projected::default();
            }
            project::project(&gaussians.params(i), camera).unwrap_or_default()
        })
        .collect()
}

/// Everything the backward needs from the forward, besides the inputs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ForwardState {
    pub projected: Vec<Projected>,
    pub bins: TileBins,
    pub composite: CompositeOutput,
}

fn splats(gaussians: &GaussianSlices, projected: &[Projected]) -> Vec<Splat> {
    projected
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            if !is_visible(p) {
                return Splat::default();
            }
            Splat {
                mean2d: p.mean2d,
                conic: p.conic,
                opacity: gaussians.params(i).opacity,
                color: gaussians.color(i),
                radius: [p.radius[0] as f32, p.radius[1] as f32],
            }
        })
        .collect()
}

fn validate_all(
    gaussians: &GaussianSlices,
    camera: &RasterCamera,
    background: [f32; 3],
) -> Result<(), RasterError> {
    camera.validate()?;
    gaussians.validate()?;
    if background.iter().any(|v| !v.is_finite()) {
        return Err(RasterError::InvalidBackground(background));
    }
    Ok(())
}

/// Renders the Gaussians: [H, W, 4] RGB + alpha in `state.composite.image_alpha`.
pub fn forward(
    gaussians: &GaussianSlices,
    camera: &RasterCamera,
    background: [f32; 3],
) -> Result<ForwardState, RasterError> {
    validate_all(gaussians, camera, background)?;
    let projection_camera = ProjectionCamera::new(camera);
    let projected = project_all(gaussians, &projection_camera);
    let bins = bin_tiles(&projected, camera.tiles_x(), camera.tiles_y());
    let splats = splats(gaussians, &projected);
    let composite =
        composite::composite_forward(&splats, &bins, camera.width, camera.height, background);
    Ok(ForwardState {
        projected,
        bins,
        composite,
    })
}

/// Gradients of the loss with respect to every input, flat like [`GaussianSlices`], plus the
/// screen-space mean gradient (pixels) used by densification. Culled Gaussians get exact zeros.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianGrads {
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub scales: Vec<f32>,
    pub opacities: Vec<f32>,
    pub colors: Vec<f32>,
    pub means2d: Vec<f32>,
}

/// Backward of [`forward`] given dLoss/d(image_alpha), [H, W, 4].
pub fn backward(
    gaussians: &GaussianSlices,
    camera: &RasterCamera,
    background: [f32; 3],
    state: &ForwardState,
    grad_image_alpha: &[f32],
) -> Result<GaussianGrads, RasterError> {
    validate_all(gaussians, camera, background)?;
    let expected = camera.pixel_count() * 4;
    if grad_image_alpha.len() != expected {
        return Err(RasterError::Shape(format!(
            "image gradient has {} values, expected {expected} (H x W x 4)",
            grad_image_alpha.len()
        )));
    }
    if state.projected.len() != gaussians.len() {
        return Err(RasterError::Shape(format!(
            "forward state holds {} Gaussians, inputs hold {}",
            state.projected.len(),
            gaussians.len()
        )));
    }
    let splats = splats(gaussians, &state.projected);
    let splat_grads = composite::composite_backward(
        &splats,
        &state.bins,
        camera.width,
        camera.height,
        background,
        &state.composite,
        grad_image_alpha,
    );
    let projection_camera = ProjectionCamera::new(camera);
    let n = gaussians.len();
    let per_gaussian: Vec<(project::GeometryGrad, SplatGrad, f32)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let p = &state.projected[i];
            if !is_visible(p) {
                return Default::default();
            }
            let sg = splat_grads[i];
            let geometry = project::project_backward(
                &gaussians.params(i),
                &projection_camera,
                &project::ProjectedGrad {
                    mean2d: sg.mean2d,
                    conic: sg.conic,
                },
            );
            // opacity_eff = gate * opacity; the gate is a constant.
            (geometry, sg, gaussians.gates[i] * sg.opacity)
        })
        .collect();
    let mut grads = GaussianGrads {
        means: Vec::with_capacity(3 * n),
        quats: Vec::with_capacity(4 * n),
        scales: Vec::with_capacity(3 * n),
        opacities: Vec::with_capacity(n),
        colors: Vec::with_capacity(3 * n),
        means2d: Vec::with_capacity(2 * n),
    };
    for (geometry, sg, opacity) in per_gaussian {
        grads.means.extend(geometry.mean);
        grads.quats.extend(geometry.quat);
        grads.scales.extend(geometry.scale);
        grads.opacities.push(opacity);
        grads.colors.extend(sg.color);
        grads.means2d.extend(sg.mean2d);
    }
    Ok(grads)
}
