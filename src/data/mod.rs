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

/// Loads the dataset `name` (a directory, or a name `resolve` knows), detecting its layout
/// unless `layout` is given. `config::DataConfig::load_scene` calls it with a config's `[data]`.
pub fn load_dataset(
    name: &str,
    layout: Option<DatasetLayout>,
    options: &LoadOptions,
) -> anyhow::Result<Scene> {
    use anyhow::Context;
    let root = resolve::dataset_dir(name)?;
    let layout = match layout {
        Some(l) => l,
        None => detect_layout(&root)?,
    };
    load(&root, layout, options).with_context(|| format!("loading dataset {}", root.display()))
}
