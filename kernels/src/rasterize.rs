//! The public rasterizer entry point on high-level Burn tensors (any backend, with or without
//! autodiff): callers never branch on the backend.

use burn::tensor::{Bool, Device, Gradients, Int, Tensor, TensorData};

use crate::cpu::GaussianArrays;

use crate::RasterError;
use crate::columns::slice_columns;
use crate::backend::{GaussianRasterBackend, IntersectionCapacity, RasterForward, RasterGaussians};
use crate::camera::RasterCamera;
use crate::conventions::projected_column;
use burn::backend::Dispatch;

/// The Gaussians to render, one row per Gaussian, all on one device.
#[derive(Clone, Debug)]
pub struct GaussianTensors {
    /// [N, 3] world positions.
    pub means: Tensor<2>,
    /// [N, 4] rotations (w, x, y, z), normalised inside.
    pub quats: Tensor<2>,
    /// [N, 3] activated (linear) scales.
    pub scales: Tensor<2>,
    /// [N] activated opacities.
    pub opacities: Tensor<1>,
    /// [N] 1 keeps a Gaussian, 0 removes it before binning (applied as gate * opacity; constant).
    pub gates: Tensor<1>,
    /// [N, 3] RGB.
    pub colors: Tensor<2>,
}

impl GaussianTensors {
    /// Uploads host arrays to `device`.
    pub fn from_arrays(arrays: &GaussianArrays, device: &Device) -> Self {
        let n = arrays.len();
        let t2 = |v: &[f32], w: usize| {
            Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, w]), device)
        };
        let t1 = |v: &[f32]| Tensor::<1>::from_data(TensorData::new(v.to_vec(), [n]), device);
        Self {
            means: t2(&arrays.means, 3),
            quats: t2(&arrays.quats, 4),
            scales: t2(&arrays.scales, 3),
            opacities: t1(&arrays.opacities),
            gates: t1(&arrays.gates),
            colors: t2(&arrays.colors, 3),
        }
    }

    /// Marks every differentiable input (all but the gates) as requiring a gradient.
    pub fn require_grad(self) -> Self {
        Self {
            means: self.means.require_grad(),
            quats: self.quats.require_grad(),
            scales: self.scales.require_grad(),
            opacities: self.opacities.require_grad(),
            gates: self.gates,
            colors: self.colors.require_grad(),
        }
    }

    pub fn len(&self) -> usize {
        self.opacities.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn validate(&self) -> Result<(), RasterError> {
        let n = self.len();
        let check = |name: &str, dims: &[usize], want: &[usize]| {
            if dims == want {
                Ok(())
            } else {
                Err(RasterError::Shape(format!(
                    "{name} has shape {dims:?}, expected {want:?}"
                )))
            }
        };
        check("means", &self.means.dims(), &[n, 3])?;
        check("quats", &self.quats.dims(), &[n, 4])?;
        check("scales", &self.scales.dims(), &[n, 3])?;
        check("gates", &self.gates.dims(), &[n])?;
        check("colors", &self.colors.dims(), &[n, 3])
    }
}

/// What the rasterizer returns. `image` and `alpha` are differentiable with respect to means,
/// quats, scales, opacities and colors.
#[derive(Clone, Debug)]
pub struct RasterOutput {
    /// [H, W, 3] RGB, background composited behind.
    pub image: Tensor<3>,
    /// [H, W] accumulated opacity, 1 - final transmittance.
    pub alpha: Tensor<2>,
    /// [N, 2] opacity-aware screen half extents in pixels; (0, 0) for culled or gated Gaussians.
    pub radii: Tensor<2, Int>,
    /// [N, 2] screen-space means in pixels (zero where culled); not differentiable.
    pub means2d: Tensor<2>,
    /// [N] camera-space depths (zero where culled).
    pub depths: Tensor<1>,
    /// Zeros [N, 2] that require grad under autodiff; its gradient is dLoss/d(means2d).
    means2d_probe: Option<Tensor<2>>,
    forward: RasterForward<Dispatch>,
}

impl RasterOutput {
    /// [N] whether each Gaussian survived gating and culling.
    pub fn visible(&self) -> Tensor<1, Bool> {
        let n = self.radii.dims()[0];
        self.radii.clone().sum_dim(1).reshape([n]).greater_elem(0)
    }

    /// dLoss/d(screen-space mean), [N, 2] in pixels, for densification statistics; `None` when the
    /// render was not on an autodiff device or the loss did not depend on it.
    pub fn means2d_grad(&self, grads: &Gradients) -> Option<Tensor<2>> {
        self.means2d_probe.as_ref()?.grad(grads)
    }

    /// Total number of (tile, Gaussian) intersections the render composited over, for a render
    /// with [`IntersectionCapacity::Exact`] (with buffers sized ahead: their length).
    pub fn intersection_count(&self) -> usize {
        Tensor::<1, Int>::from_dispatch(self.forward.gaussian_from_intersection.clone()).dims()[0]
    }

    /// [1] the (tile, Gaussian) intersections the Gaussians make, on the device (no read).
    pub fn intersections(&self) -> Tensor<1, Int> {
        Tensor::from_dispatch(self.forward.intersections.clone())
    }

    /// [1] f32 on the device: 1 when the intersections outnumbered the buffers sized ahead for
    /// them (the render left some out and must be redone with at least [`Self::intersections`]),
    /// else 0. Always 0 for an exact render.
    pub fn overflowed(&self) -> Tensor<1> {
        self.intersections()
            .greater_elem(self.intersection_count() as i64)
            .float()
    }
}

/// Renders gated 3D Gaussians from a camera, differentiably (see the crate docs for conventions).
///
/// Errors on an invalid camera (empty image, non-positive focal length, non-finite entries), a
/// non-finite background, or inconsistent shapes. Gaussians with a non-finite input are culled.
///
/// Panics, with the counts, when the tile intersections cannot be held: 2^32 or more on any
/// device, or more than one storage buffer of the device holds (4 bytes each; 128 MiB, i.e.
/// 33.5M intersections, on lavapipe). Only footprints far beyond a sane scene reach either.
pub fn rasterize(
    gaussians: &GaussianTensors,
    camera: &RasterCamera,
    background: [f32; 3],
) -> Result<RasterOutput, RasterError> {
    rasterize_with(gaussians, camera, background, IntersectionCapacity::Exact)
}

/// [`rasterize`] with the intersection buffers sized by `capacity`: with
/// [`IntersectionCapacity::AtMost`] a GPU render reads nothing back, and the caller checks
/// [`RasterOutput::overflowed`] (with its other values) before using the render.
pub fn rasterize_with(
    gaussians: &GaussianTensors,
    camera: &RasterCamera,
    background: [f32; 3],
    capacity: IntersectionCapacity,
) -> Result<RasterOutput, RasterError> {
    camera.validate()?;
    gaussians.validate()?;
    if background.iter().any(|v| !v.is_finite()) {
        return Err(RasterError::InvalidBackground(background));
    }
    let n = gaussians.len();
    let device = gaussians.means.device();
    let probe = gaussians
        .means
        .is_autodiff()
        .then(|| Tensor::<2>::zeros([n, 2], &device).require_grad());
    let probe_input = probe
        .clone()
        .unwrap_or_else(|| Tensor::<2>::zeros([n, 2], &device));

    let inputs = RasterGaussians {
        means: gaussians.means.clone().into_dispatch(),
        quats: gaussians.quats.clone().into_dispatch(),
        scales: gaussians.scales.clone().into_dispatch(),
        opacities: gaussians.opacities.clone().into_dispatch(),
        gates: gaussians.gates.clone().into_dispatch(),
        colors: gaussians.colors.clone().into_dispatch(),
    };
    let forward = <Dispatch as GaussianRasterBackend>::rasterize_forward(
        inputs,
        probe_input.into_dispatch(),
        *camera,
        background,
        capacity,
    );
    let (h, w) = (camera.height as usize, camera.width as usize);
    // The outputs are column ranges of two row-major tables: split with `slice_columns` (row
    // copies), not Burn's `slice`, which on ndarray copies through a dynamic-rank element
    // iterator, forward and backward (5.4 % of a CPU training step's samples, issue 21).
    let pixels = Tensor::<3>::from_dispatch(forward.image_alpha.clone()).reshape([h * w, 4]);
    let projected = Tensor::<2>::from_dispatch(forward.projected.clone());
    use projected_column as col;
    Ok(RasterOutput {
        image: slice_columns(pixels.clone(), 0..3).reshape([h, w, 3]),
        alpha: slice_columns(pixels, 3..4).reshape([h, w]),
        radii: slice_columns(projected.clone(), col::RADIUS_X..col::RADIUS_Y + 1).int(),
        means2d: slice_columns(projected.clone(), col::MEAN2D_X..col::MEAN2D_Y + 1),
        depths: slice_columns(projected, col::DEPTH..col::DEPTH + 1).reshape([n]),
        means2d_probe: probe,
        forward,
    })
}
