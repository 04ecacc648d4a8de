//! Evaluation: image metrics (and, with the trainer, test renders and timing).

pub mod evaluate;
pub mod metrics;
