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

/// Loads the dataset a config's `[data]` table names (its layout detected unless given).
pub fn load_scene(data: &crate::config::DataConfig) -> anyhow::Result<Scene> {
    use anyhow::Context;
    let root = resolve::dataset_dir(&data.dataset)?;
    let layout = match data.layout {
        Some(l) => l,
        None => detect_layout(&root)?,
    };
    let options = LoadOptions {
        start_frame: data.start_frame,
        frame_count: data.frames,
        downscale: data.downscale,
        test_cameras: data.test_cameras.clone(),
        removed_cameras: data.removed_cameras.clone(),
        ..Default::default()
    };
    load(&root, layout, &options).with_context(|| format!("loading dataset {}", root.display()))
}
