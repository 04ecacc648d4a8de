//! The codec (issue "End-to-end compression"): the `scene.acags` container, the quantisation
//! grid shared by training and coding, the entropy coder and the bitstream.
//!
//! Training-time only: `rate.rs` (the rate term) and `quantization::simulate`. The file format
//! (`bitstream.rs`, `attributes.rs`, `container.rs`, `entropy.rs`, `wire.rs`, `scene_file.rs`,
//! `trained_model.rs`) imports nothing from `train` or `run`.

pub mod attributes;
pub mod bitstream;
pub mod container;
pub mod entropy;
pub mod entropy_models;
pub mod quantization;
pub mod rate;
pub mod scene_file;
pub mod trained_model;
pub mod wire;
