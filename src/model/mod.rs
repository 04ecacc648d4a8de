//! The anchored dynamic model: the anchor set, the shared decoders, per-view decoding and
//! spawning, and initialisation from a point cloud.

pub mod anchor_columns;
pub mod anchored;
pub mod anchors;
pub mod culling;
pub mod decoders;
pub mod feature_mask;
pub mod init;
pub mod inputs;
pub mod object_clusters;
pub mod path_turns;
pub mod rotations;
pub mod slot_gates;
pub mod spawn;
pub mod view;
