//! The codec (issue "End-to-end compression"): so far the `scene.acags` container format; the
//! quantisation, entropy models and attribute coding come next.

pub mod container;
