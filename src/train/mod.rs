//! Training: configuration, the trainer loop, optimizers, densification, losses, checkpoints.

pub mod adaptive_cardinality;
pub mod anchor_state;
pub mod appearance_seeding;
pub mod background;
pub mod checkpoint;
pub mod coherence;
pub mod curvature;
pub use crate::config;
pub mod decoder_adam;
pub mod device_targets;
pub mod densify;
pub mod knot_search;
pub mod knots;
pub mod losses;
pub mod objective;
pub mod optimizers;
pub mod posthoc;
pub mod refine;
pub mod rendered_fit;
pub mod rigid_fit;
pub mod row_adam;
pub mod seed_hold;
pub mod stage_clock;
pub mod statistics;
pub mod streams;
pub mod trainer;
