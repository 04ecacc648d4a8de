//! CubeCL kernels of the rasterizer (the GPU twin of `cpu/`), launched on `CubeBackend` tensors.
//!
//! Work in progress (issue "CubeCL kernels on wgpu"): the projection stage is here and tested
//! against the CPU twin on lavapipe; binning, compositing and the backward still run on the host
//! (`backend.rs`, host round trip) until their kernels land.

pub mod project;
