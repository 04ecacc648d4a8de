//! The groups `model.trajectory_turn = "objects"` finds on a run's paths, and what each would
//! turn, with the shipped parting distance and others (docs/results.md, Follow-up 49).
//!
//! ```bash
//! cargo run --release --example object_groups -- RUN_DIR [PART...]   # default: 0.15 0.3 0.5
//! ```
//!
//! For each parting distance: the number of groups and their anchors, then the largest eight,
//! each with its centre at the first and last knot, whether it turns (the share of its
//! translation-only residual its rotation explains) and its rotation's angle at each knot. The
//! run's own `model.trajectory_turn` does not matter: the groups are read from its trajectories.

use acags::model::path_turns::{OBJECT_PART, object_groups};
use anyhow::{Context, Result, ensure};
use burn::tensor::Device;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = args
        .first()
        .context("usage: object_groups RUN_DIR [PART...]")?;
    let mut parts: Vec<f32> = args[1..]
        .iter()
        .map(|a| a.parse().context("parting distances are numbers"))
        .collect::<Result<_>>()?;
    if parts.is_empty() {
        parts = vec![0.15, OBJECT_PART, 0.5];
    }
    #[allow(deprecated)]
    let device = Device::ndarray();
    let run = acags::run::open_run(std::path::Path::new(dir), device)?;
    let set = &run.trained.model.anchors;
    ensure!(
        set.dims.trajectory_knots() > 1,
        "{dir}: the model has no trajectory knots"
    );
    for part in parts {
        let groups = object_groups(set, part);
        let covered: usize = groups.iter().map(|g| g.anchors).sum();
        let turning = groups.iter().filter(|g| g.turns).count();
        println!(
            "part {part}: {} groups of {covered} anchors, {turning} turn",
            groups.len()
        );
        for group in groups.iter().take(8) {
            println!("  {group}");
        }
    }
    Ok(())
}
