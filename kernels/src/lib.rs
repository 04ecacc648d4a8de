//! The gated differentiable Gaussian rasterizer of acags.
//!
//! - [`cpu`]: the CPU twin (plain Rust + rayon), the reference every other implementation matches.
//! - [`activation`]: ReLU, sigmoid and tanh as one op each way (one parallel pass on the CPU,
//!   Burn's values to the bit; Burn's own ops on a device).
//! - [`backend`]: the Burn backend extension (`GaussianRasterBackend`) with implementations for
//!   NdArray, the Cube backend and Autodiff (hand-written backward).
//! - [`columns`]: a column range of a [R, W] tensor with a zero-padding backward (row copies on
//!   the CPU instead of Burn's element-wise slice).
//! - [`fused_ssim`]: the training loss's SSIM as a backend extension (host twin, hand-written
//!   backward), beside the rasterizer's.
//! - [`counter_noise`]: uniform noise hashed from (key, element) on the device (the quantisation
//!   simulation's and the rate term's noise; no host draws, no uploads).
//! - [`fused_adam`]: the optimizer's Adam update as one op (CPU twin bit-identical to the
//!   plain-tensor update, CubeCL kernel).
//! - [`gaussian_bits`]: the rate term's bit estimate as one op with an analytic backward.
//! - [`host_simd`]: the CPU twins' element-wise loops compiled for AVX2 and portably (same bits),
//!   and call-free e^x and ln.
//! - [`linear`]: a linear layer x·W + b with its backward as one op (the decoders' and entropy
//!   models' layers; row chunks on rayon's pool on the CPU).
//! - [`spawn_means`]: the spawned Gaussians' centres (anchor + gated motion + rotated, scaled
//!   offsets) as one op with its backward, one unit per anchor.
//! - [`raster_io`]: the tensor bundles crossing that op (inputs, forward state, gradients).
//! - [`transfers`]: counts of host↔device uploads and read-backs (`bench train`).
//! - [`rasterize`]: the one public entry point on high-level Burn tensors.

pub mod activation;
pub mod backend;
pub mod camera;
pub mod columns;
pub mod conventions;
pub mod counter_noise;
pub mod cpu;
pub mod cube;
pub mod fused_adam;
pub mod fused_ssim;
pub mod gather;
pub mod gaussian_bits;
pub mod host_simd;
pub mod linear;
pub mod random_scene;
pub mod spawn_means;
pub mod raster_io;
mod rasterize;
pub mod transfers;

pub use camera::RasterCamera;
pub use raster_io::IntersectionCapacity;
pub use rasterize::{GaussianTensors, RasterOutput, rasterize, rasterize_with};

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
