//! Where a training step's time goes: wall time per stage of `Trainer::step`, for `bench train`'s
//! per-stage breakdown.
//!
//! On the CPU backend every tensor op runs when it is issued, so a stage's time is its work. On a
//! GPU backend ops are queued: a stage's time is the host's time to issue them, and the device's
//! work shows up in the next stage that waits for it (the read-back of the loss, the statistics'
//! read-backs). The breakdown then says where the host waits, which is what the step-cost work
//! needs to know there too.

use std::time::Instant;

use serde::Serialize;

/// A stage of one training step, in the order the step runs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Refiners before the forward pass (dynamic initialisation, knots, CR trigger).
    RefineBefore,
    /// Target frame, tracked leaves and the quantisation simulation.
    Quantization,
    /// Culling, decoding, spawning and rasterizing the view.
    Forward,
    /// Photometric loss, regularisers and the rate term (graph building).
    Objective,
    /// The one read-back of the loss and its terms.
    ReadBack,
    Backward,
    /// Adam over anchors, decoders and entropy models.
    Optimizer,
    /// Densification statistics and AAC importance.
    Statistics,
    /// Refiners after the update (densify, prune, relocate) and the step's counters.
    RefineAfter,
}

impl Stage {
    pub const ALL: [Stage; 9] = [
        Stage::RefineBefore,
        Stage::Quantization,
        Stage::Forward,
        Stage::Objective,
        Stage::ReadBack,
        Stage::Backward,
        Stage::Optimizer,
        Stage::Statistics,
        Stage::RefineAfter,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Stage::RefineBefore => "refine_before",
            Stage::Quantization => "quantization",
            Stage::Forward => "forward",
            Stage::Objective => "objective",
            Stage::ReadBack => "read_back",
            Stage::Backward => "backward",
            Stage::Optimizer => "optimizer",
            Stage::Statistics => "statistics",
            Stage::RefineAfter => "refine_after",
        }
    }

    fn index(self) -> usize {
        Stage::ALL
            .iter()
            .position(|&s| s == self)
            .expect("every stage is in ALL")
    }
}

/// Seconds spent in each stage of one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes([f64; Stage::ALL.len()]);

impl StageTimes {
    pub fn get(&self, stage: Stage) -> f64 {
        self.0[stage.index()]
    }

    pub fn total(&self) -> f64 {
        self.0.iter().sum()
    }
}

impl Serialize for StageTimes {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut map = serializer.serialize_map(Some(Stage::ALL.len()))?;
        for stage in Stage::ALL {
            map.serialize_entry(stage.name(), &self.get(stage))?;
        }
        map.end()
    }
}

/// Laps of a running step: `lap(stage)` charges the time since the previous lap to `stage`
/// (adding, so a stage may be charged more than once).
pub struct StageClock {
    last: Instant,
    times: StageTimes,
}

impl StageClock {
    pub fn start() -> Self {
        Self {
            last: Instant::now(),
            times: StageTimes::default(),
        }
    }

    pub fn lap(&mut self, stage: Stage) {
        let now = Instant::now();
        self.times.0[stage.index()] += (now - self.last).as_secs_f64();
        self.last = now;
    }

    pub fn times(&self) -> StageTimes {
        self.times
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laps_are_charged_to_their_stage_and_add_up() {
        let mut clock = StageClock::start();
        std::thread::sleep(std::time::Duration::from_millis(20));
        clock.lap(Stage::Forward);
        clock.lap(Stage::Backward);
        std::thread::sleep(std::time::Duration::from_millis(10));
        clock.lap(Stage::Forward);
        let times = clock.times();
        assert!(times.get(Stage::Forward) >= 0.030, "{times:?}");
        assert!(times.get(Stage::Backward) < 0.010, "{times:?}");
        assert_eq!(times.get(Stage::Optimizer), 0.0);
        assert!(
            (times.total() - Stage::ALL.iter().map(|&s| times.get(s)).sum::<f64>()).abs() < 1e-12
        );
        let json = serde_json::to_value(times).unwrap();
        assert_eq!(json.as_object().unwrap().len(), Stage::ALL.len());
        assert!(json["forward"].as_f64().unwrap() >= 0.030);
    }
}
