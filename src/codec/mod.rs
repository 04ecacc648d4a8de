//! The codec (issue "End-to-end compression"): the `scene.acags` container, the quantisation
//! grid shared by training and coding, the entropy coder and the bitstream.

pub mod attributes;
pub mod bitstream;
pub mod container;
pub mod entropy;
pub mod entropy_models;
pub mod quantization;
pub mod scene_file;
pub mod trained_model;
pub mod wire;
