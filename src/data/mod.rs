//! Multi-view video datasets: one scene type, loaders for the N3DV/MPEG (GIFStream) and Panoptic
//! Sports (Dynamic3DGS) layouts, the embedded synthetic scenes, lazy frame loading and sampling.
//!
//! Spec: `../shared/spec/baseline_spec.md` §3 and §15.

pub mod cameras;
pub mod colmap;
pub mod frames;
pub mod inspect;
pub mod n3dv;
pub mod npy;
pub mod panoptic;
pub mod resolve;
pub mod sampler;
pub mod scene;
pub mod synthetic;
pub mod video;

pub use inspect::{detect_layout, load};
pub use scene::{
    DatasetLayout, FrameRange, LoadOptions, PointCloud, Resample, Scene, SceneCamera, ViewId,
};
