//! Experiments: ablation sweeps over config grids (`acags sweep`), their reports and charts
//! (`acags report`), and the stability suite (`acags stability`).

pub mod grid;
pub mod manifest;
pub mod report;
pub mod results;
pub mod stability;
pub mod sweep;
