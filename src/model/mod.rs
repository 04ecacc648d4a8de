//! The anchored dynamic model (the decoders and anchor set land with the trainer); for now its
//! initialisation from a point cloud and the anchor neighbourhoods.

pub mod decoders;
pub mod init;
pub mod inputs;
pub mod spawn;
