//! Files in and out: 3DGS PLY scenes, camera JSON, rendered images.

pub mod camera_json;
pub mod charts;
pub mod image_out;
pub mod splat_ply;
