//! The gated differentiable Gaussian rasterizer of acags.
//!
//! - [`cpu`]: the CPU twin (plain Rust + rayon), the reference every other implementation matches.
//! - [`backend`]: the Burn backend extension (`GaussianRasterBackend`) with implementations for
//!   NdArray, the Cube backend and Autodiff (hand-written backward).
//! - [`fused_ssim`]: the training loss's SSIM as a backend extension (host twin, hand-written
//!   backward), beside the rasterizer's.
//! - [`raster_io`]: the tensor bundles crossing that op (inputs, forward state, gradients).
//! - [`rasterize`]: the one public entry point on high-level Burn tensors.

pub mod backend;
pub mod camera;
pub mod conventions;
pub mod cpu;
pub mod cube;
pub mod fused_ssim;
pub mod gather;
pub mod random_scene;
pub mod raster_io;
mod rasterize;

pub use camera::RasterCamera;
pub use rasterize::{GaussianTensors, RasterOutput, rasterize};

/// Why a rasterizer call was refused.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum RasterError {
    #[error("invalid camera: {0}")]
    InvalidCamera(String),
    #[error("invalid background {0:?}: every component must be finite")]
    InvalidBackground([f32; 3]),
    #[error("inconsistent input shapes: {0}")]
    Shape(String),
}
