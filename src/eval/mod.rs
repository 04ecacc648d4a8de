//! Evaluation: image metrics (and, with the trainer, test renders and timing).

pub mod capacity_maps;
pub mod evaluate;
pub mod metrics;
pub mod motion_mask;
