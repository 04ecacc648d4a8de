//! The tensor bundles that cross the rasterizer op (`backend::GaussianRasterBackend`): its
//! inputs, its forward state and its gradients, generic in the backend. The CubeCL kernels work
//! on the `CubeBackend` instances (`cube::DeviceGaussians` …), the CPU twin on host copies, and
//! the decorators (fusion, autodiff) convert a bundle with one `map` instead of field by field.

use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, ExtensionType, TensorMetadata};

use crate::cpu::GaussianArrays;

/// The six per-Gaussian inputs: means [N,3], quats [N,4] (w,x,y,z raw), scales [N,3],
/// opacities [N], gates [N] (constants: 1 keeps a Gaussian, 0 removes it), colors [N,3].
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterGaussians<B: Backend> {
    pub means: FloatTensor<B>,
    pub quats: FloatTensor<B>,
    pub scales: FloatTensor<B>,
    pub opacities: FloatTensor<B>,
    pub gates: FloatTensor<B>,
    pub colors: FloatTensor<B>,
}

impl<B: Backend> RasterGaussians<B> {
    /// The same bundle with `f` applied to each tensor (e.g. to the inner backend's tensors).
    pub fn map<C: Backend>(
        self,
        mut f: impl FnMut(FloatTensor<B>) -> FloatTensor<C>,
    ) -> RasterGaussians<C> {
        RasterGaussians {
            means: f(self.means),
            quats: f(self.quats),
            scales: f(self.scales),
            opacities: f(self.opacities),
            gates: f(self.gates),
            colors: f(self.colors),
        }
    }

    /// Host copies of every input, read with `read`.
    pub fn to_host(self, mut read: impl FnMut(FloatTensor<B>) -> Vec<f32>) -> GaussianArrays {
        GaussianArrays {
            means: read(self.means),
            quats: read(self.quats),
            scales: read(self.scales),
            opacities: read(self.opacities),
            gates: read(self.gates),
            colors: read(self.colors),
        }
    }

    pub fn len(&self) -> usize {
        self.opacities.shape()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Forward outputs. `image_alpha` is the only differentiable one; the rest is the backward's
/// state and per-Gaussian diagnostics.
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterForward<B: Backend> {
    /// [H, W, 4]: RGB with the background composited, then alpha = 1 - T_final.
    pub image_alpha: FloatTensor<B>,
    /// [N, 8], see [`crate::conventions::projected_column`]. Culled Gaussians have zero radii
    /// (and zero elsewhere).
    pub projected: FloatTensor<B>,
    /// [tiles + 1] start of each tile's range in `gaussian_from_intersection`.
    pub tile_offsets: IntTensor<B>,
    /// [intersections] Gaussian index per (tile, depth)-sorted intersection.
    pub gaussian_from_intersection: IntTensor<B>,
    /// [H, W] transmittance after the last composited Gaussian.
    pub final_transmittance: FloatTensor<B>,
    /// [H, W] tile-list entries processed up to the last composited Gaussian.
    pub n_contrib: IntTensor<B>,
    /// [1] the tile intersections the Gaussians make. With buffers sized ahead
    /// ([`IntersectionCapacity::AtMost`]) it can exceed what `gaussian_from_intersection`
    /// holds: the render then left intersections out and must be redone with more room.
    pub intersections: IntTensor<B>,
}

/// How the rasterizer sizes its intersection buffers (tile keys, Gaussian ids, the sort's
/// copies), whose length only the device knows after binning.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum IntersectionCapacity {
    /// Read the count back and allocate exactly: one synchronisation per render on a GPU.
    #[default]
    Exact,
    /// Allocate this many (at least 1) without reading anything back. Intersections beyond it
    /// are dropped, the render is then incomplete, and [`RasterForward::intersections`] says
    /// how many were needed (the caller reads it later, with its other values, and renders
    /// again). The CPU twin, where reading is free, always counts exactly.
    AtMost(usize),
}

impl<B: Backend> RasterForward<B> {
    /// The same state with `float` applied to its float tensors and `int` to its int tensors.
    pub fn map<C: Backend>(
        self,
        mut float: impl FnMut(FloatTensor<B>) -> FloatTensor<C>,
        mut int: impl FnMut(IntTensor<B>) -> IntTensor<C>,
    ) -> RasterForward<C> {
        RasterForward {
            image_alpha: float(self.image_alpha),
            projected: float(self.projected),
            tile_offsets: int(self.tile_offsets),
            gaussian_from_intersection: int(self.gaussian_from_intersection),
            final_transmittance: float(self.final_transmittance),
            n_contrib: int(self.n_contrib),
            intersections: int(self.intersections),
        }
    }
}

/// Gradients of the loss with respect to each differentiable input, shaped like the inputs.
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterGrads<B: Backend> {
    pub means: FloatTensor<B>,
    pub quats: FloatTensor<B>,
    pub scales: FloatTensor<B>,
    pub opacities: FloatTensor<B>,
    pub colors: FloatTensor<B>,
    /// [N, 2] dLoss/d(screen mean) in pixels, what densification accumulates.
    pub means2d: FloatTensor<B>,
}

impl<B: Backend> RasterGrads<B> {
    /// The same gradients with `f` applied to each tensor.
    pub fn map<C: Backend>(
        self,
        mut f: impl FnMut(FloatTensor<B>) -> FloatTensor<C>,
    ) -> RasterGrads<C> {
        RasterGrads {
            means: f(self.means),
            quats: f(self.quats),
            scales: f(self.scales),
            opacities: f(self.opacities),
            colors: f(self.colors),
            means2d: f(self.means2d),
        }
    }
}
