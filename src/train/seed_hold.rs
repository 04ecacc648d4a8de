//! `train.seed_hold`: which anchors a training step holds back from the frames before the one
//! they were found at (not in GIFStream, whose anchors all come from frame 0's points).
//!
//! `train.appearance_seeding` places an anchor on an object at knot k's frame r when that knot
//! opens, while the temporal curriculum has opened only the frames up to the previous knot's
//! (and one past it). Its knots are all offset alike, so at every earlier frame it waits at its
//! seed, where its object is not yet: until the next knot's searches set its earlier knots
//! (`continue_backwards` in `trainer/motion_search.rs`), every view of an earlier frame
//! pushes it away or fades it. On `large-motion` at 12,800 steps those are 525 steps (4× the
//! 3,200-step run's), and the sphere seeded at frame 8 was gone from it 143 steps after
//! seeding (25 Gaussians inside it against 598 at 3,200 steps; docs/results.md, Follow-up 47).
//! Held, the anchor is drawn only from frame r on (it trains when frame r opens) until frame
//! r + 1 opens: that step opens knot k + 1, whose searches, run before the step draws, set its
//! path before r; from then on, and once every frame is open, it is drawn everywhere.
//!
//! While held, its knots (and turns) get no gradient ([`hold_knots_still`]): it stays where the
//! cameras agreed at seeding, its appearance trains at frame r. Trained there alone, its knots
//! drift (frame 8 seen alone fits many placements): on `large-motion` at 12,800 steps, 264
//! anchors inside the sphere at frame 8 when it opened, 145 when knot 3 did, and knot 3's search
//! and rigid fit no longer saw the sphere's anchors on it; held still, 389 were inside and the fit
//! moved 331 of them with the sphere (docs/results.md, Follow-up 48).
//!
//! Derived from the step and the reference frames alone, so a resumed run holds the same
//! anchors. Evaluation and the decoder draw every anchor at every frame.

use crate::config::{ScheduleConfig, SeedHold};
use crate::model::anchors::{AnchorTensors, Column, ColumnTensor};
use crate::model::culling::FirstDrawnFrames;

/// Under `train.seed_hold = "long-intervals"`: the fewest training steps between two knot
/// openings of the temporal curriculum at which seeded anchors are held. Measured, decoded: at
/// 131 steps (the default 3,200-step schedule, knots every 4 of 40 frames) the hold is within a
/// seed's spread and mixed (`large-motion` moving +0.10 / +0.23, seeds 42 / 43, `crossing`
/// −0.14 / −0.16, `fast` static −0.17 / −0.07); at 525 (12,800 steps) `large-motion` stops
/// collapsing (gap 8.80 → 5.48) and `crossing` gains on the moving pixels (+0.30 / +0.12, seeds
/// 42 / 43; gaps 6.01 → 5.41, 5.81 → 5.78; docs/results.md, Follow-ups 48-51). The threshold
/// lies between the two, at their geometric mean.
pub const LONG_INTERVAL_STEPS: f64 = 262.0;

/// The hold `config` asks for on a clip of `frames` frames with knots every `spacing` frames:
/// `long-intervals` resolved by how many steps apart the curriculum opens knots.
pub fn resolved_mode(config: &ScheduleConfig, frames: usize, spacing: usize) -> SeedHold {
    match config.seed_hold {
        SeedHold::LongIntervals => {
            if knot_interval_steps(config, frames, spacing) >= LONG_INTERVAL_STEPS {
                SeedHold::NextKnot
            } else {
                SeedHold::Off
            }
        }
        mode => mode,
    }
}

/// Training steps between two knot openings of the temporal curriculum (frames open evenly
/// over `frame_curriculum` of the steps); 0 without the curriculum or knots.
pub fn knot_interval_steps(config: &ScheduleConfig, frames: usize, spacing: usize) -> f64 {
    if config.frame_curriculum <= 0.0 || frames <= 1 || spacing == 0 {
        return 0.0;
    }
    config.frame_curriculum * config.max_steps as f64 * spacing as f64 / (frames - 1) as f64
}

/// Per anchor, the first GOP frame a training step draws it at when `open` of `frames` GOP
/// frames are open (the first `open`), from each anchor's reference frame: `None` when no
/// anchor is held (every anchor drawn at every frame).
pub fn first_drawn_frames(
    mode: SeedHold,
    reference_frame: &[u32],
    open: usize,
    frames: usize,
) -> Option<Vec<u32>> {
    assert_ne!(
        mode,
        SeedHold::LongIntervals,
        "resolve `long-intervals` first (`resolved_mode`)"
    );
    if mode == SeedHold::Off || open >= frames {
        return None;
    }
    // Held while frame r + 1 is not open: `open` frames are 0..open.
    let held = |r: u32| r > 0 && open <= r as usize + 1;
    if !reference_frame.iter().any(|&r| held(r)) {
        return None;
    }
    Some(
        reference_frame
            .iter()
            .map(|&r| if held(r) { r } else { 0 })
            .collect(),
    )
}

/// `tensors` (a step's tracked values) with the knots and turns of the anchors `first` holds
/// back detached: the step's gradient does not move them (their values are unchanged).
pub fn hold_knots_still(mut tensors: AnchorTensors, first: &FirstDrawnFrames) -> AnchorTensors {
    for c in [Column::Trajectory, Column::Turn] {
        let Some(column) = tensors.columns.get(c) else {
            continue;
        };
        let flat = column.flat();
        let [n, width] = flat.dims();
        assert_eq!(first.len(), n, "one first frame per anchor");
        let held = first.held().reshape([n, 1]).expand([n, width]);
        let kept = held.clone().neg().add_scalar(1.0);
        let still = flat.clone() * kept + flat.detach() * held;
        let still = match column {
            ColumnTensor::Rows(_) => ColumnTensor::Rows(still),
            ColumnTensor::Grid(grid) => ColumnTensor::Grid(still.reshape(grid.dims())),
        };
        tensors.columns[c] = still;
    }
    tensors
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_anchor_seeded_at_a_knot_frame_is_held_until_the_frame_after_it_opens() {
        // Frame-0 anchors, one seeded at frame 8 and one at 4, 40 frames (`open` frames are
        // 0..open).
        let references = [0, 8, 0, 4];
        let at = |open| first_drawn_frames(SeedHold::NextKnot, &references, open, 40);
        // Frames 0..=4 open: the frame-4 seed is drawn at frame 4 only.
        assert_eq!(at(5), Some(vec![0, 8, 0, 4]));
        // Frame 5 opens knot 2 (whose searches set the frame-4 seed's path): it is released;
        // the frame-8 seed (seeded at this opening) is held.
        assert_eq!(at(6), Some(vec![0, 8, 0, 0]));
        // Frame 8 open, frame 9 not yet: still held, drawn at frame 8 only.
        assert_eq!(at(9), Some(vec![0, 8, 0, 0]));
        // Frame 9 opens knot 3: nothing is held.
        assert_eq!(at(10), None);
    }

    #[test]
    fn nothing_is_held_once_every_frame_is_open_or_with_the_hold_off() {
        // The clip's last frame (a last knot past the clip searches it): released when it opens,
        // the curriculum's end.
        let references = [0, 39];
        assert_eq!(
            first_drawn_frames(SeedHold::NextKnot, &references, 39, 40),
            Some(vec![0, 39])
        );
        assert_eq!(
            first_drawn_frames(SeedHold::NextKnot, &references, 40, 40),
            None
        );
        assert_eq!(first_drawn_frames(SeedHold::Off, &references, 20, 40), None);
        assert_eq!(first_drawn_frames(SeedHold::NextKnot, &[0, 0], 3, 40), None);
    }

    /// `long-intervals` holds at 12,800 steps (knots 525 steps apart on 40 frames, every 4) and
    /// not at the default 3,200 (131 apart), nor without the curriculum; the explicit modes
    /// stay what they say.
    #[test]
    fn long_intervals_hold_only_where_knots_open_far_apart() {
        let config = |mode, steps, curriculum| ScheduleConfig {
            seed_hold: mode,
            max_steps: steps,
            frame_curriculum: curriculum,
            ..ScheduleConfig::default()
        };
        let long = config(SeedHold::LongIntervals, 12_800, 0.4);
        assert!((knot_interval_steps(&long, 40, 4) - 525.1).abs() < 0.1);
        assert_eq!(resolved_mode(&long, 40, 4), SeedHold::NextKnot);
        let default = config(SeedHold::LongIntervals, 3_200, 0.4);
        assert!((knot_interval_steps(&default, 40, 4) - 131.3).abs() < 0.1);
        assert_eq!(resolved_mode(&default, 40, 4), SeedHold::Off);
        // Twice the default is 263 steps apart: held.
        assert_eq!(
            resolved_mode(&config(SeedHold::LongIntervals, 6_400, 0.4), 40, 4),
            SeedHold::NextKnot
        );
        assert_eq!(
            resolved_mode(&config(SeedHold::LongIntervals, 12_800, 0.0), 40, 4),
            SeedHold::Off
        );
        for mode in [SeedHold::Off, SeedHold::NextKnot] {
            assert_eq!(resolved_mode(&config(mode, 3_200, 0.4), 40, 4), mode);
            assert_eq!(resolved_mode(&config(mode, 12_800, 0.4), 40, 4), mode);
        }
    }
}
