//! ACA-GS Adaptive Anchor Cardinality (AAC; paper §3.1, spec §12): every anchor decodes K_max
//! slots, a per-slot gate g decides which are rasterized, and every `aac.every` steps the slots
//! that stayed (nearly) transparent are switched off and up to ρ of the active population is
//! re-born next to the most important Gaussians.
//!
//! The relocation step, in the spec's order (§12.3, resolutions §14 A1-A9):
//! 1. dead = active slots of anchors older than T_R with importance < τ;
//! 2. all dead slots are deactivated (A2), the budget is min(|dead|, ⌊ρ·P⌋) with P the active
//!    population before deactivation;
//! 3. each relocation draws a parent among the alive slots ∝ importance, whose anchor has a free
//!    slot (resampling up to `resample_tries` times when the anchor filled up during this step);
//! 4. the lowest free slot of the parent's anchor (or, with `aac.target_slot = "most-opaque-free"`,
//!    the free slot with the largest importance; with "above-threshold-free", the most important
//!    free slot whose importance reached τ, and only anchors with one can be parents) gets
//!    offset o_p + |o_p| ⊙ ε, ε ~ N(0, δ²), g = 1, zero Adam moments and zero densification
//!    statistics;
//! 5. the importance window restarts.
//!
//! Each step also reports the churn of the previous one: how many of the slots it relocated
//! ended this window below τ (switched on but never seen).

use rand::Rng;
use rand::distr::Distribution;
use rand::distr::weighted::WeightedIndex;
use rand_distr::Normal;

use super::anchor_state::AnchorState;
use super::config::{AacConfig, ImportanceTest, RelocationSlot};
use crate::model::anchors::{AnchorDims, AnchorSet, Column};

/// What one relocation step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct RelocationReport {
    /// Active slots before the step (P).
    pub active_before: usize,
    /// Slots deactivated as dead.
    pub deactivated: usize,
    /// Slots re-activated next to a parent.
    pub relocated: usize,
    /// Relocations within the budget that found no parent with a free slot.
    pub dropped: usize,
    /// Slots the previous relocation step placed that are still active and were judged now.
    pub previous_relocated: usize,
    /// Of those, the ones whose importance over this window stayed below τ (churn).
    pub previous_below_threshold: usize,
}

/// Relocation churn over a run: slots relocated by one AAC step that the next one judged, and
/// how many of them stayed below τ over that window.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct RelocationChurn {
    pub judged: usize,
    pub below_threshold: usize,
}

impl RelocationChurn {
    pub fn add(&mut self, report: &RelocationReport) {
        self.judged += report.previous_relocated;
        self.below_threshold += report.previous_below_threshold;
    }

    /// Share of the judged relocations that stayed below τ (None before any was judged).
    pub fn share(&self) -> Option<f64> {
        (self.judged > 0).then(|| self.below_threshold as f64 / self.judged as f64)
    }
}

/// Adds one training view's opacities to the importance window (spec §12.2): `opacity` is the
/// [M, K] decoded opacity of the `visible` anchors before the slot gates (as the spec asks),
/// clamped at 0 (α = max(0, tanh · pf)). Active slots are judged and sampled by it; free slots
/// gather what they would show, which `RelocationSlot::MostOpaqueFree` ranks them by.
pub fn accumulate_importance(
    state: &mut AnchorState,
    dims: &AnchorDims,
    visible: &[u32],
    opacity: &[f32],
) {
    let k = dims.slots;
    assert_eq!(opacity.len(), visible.len() * k, "opacity is [M, K]");
    for (i, &a) in visible.iter().enumerate() {
        let a = a as usize;
        for slot in 0..k {
            state.importance[a * k + slot] += opacity[i * k + slot].max(0.0);
        }
        state.importance_visits[a] += 1.0;
    }
}

/// The importance a slot is judged by: the window's sum, or its mean per visible view.
fn judged_importance(state: &AnchorState, k: usize, slot: usize, test: ImportanceTest) -> f32 {
    let sum = state.importance[slot];
    match test {
        ImportanceTest::Sum => sum,
        ImportanceTest::MeanPerVisit => sum / state.importance_visits[slot / k].max(1.0),
    }
}

/// One AAC relocation step at training step `step` (see the module documentation).
pub fn relocate(
    set: &mut AnchorSet,
    state: &mut AnchorState,
    config: &AacConfig,
    step: usize,
    rng: &mut impl Rng,
) -> RelocationReport {
    assert!(
        state.is_settled(),
        "statistics still on the device: settle them first"
    );
    let d = set.dims;
    let (k, t, n) = (d.slots, d.frames, set.len());
    let young = |a: usize| step.saturating_sub(state.created_at[a] as usize) < config.every;

    // The gates are edited here and handed back to the set once (which mirrors them on the
    // device).
    let mut gates = set.slot_gates.flags().to_vec();
    let active: Vec<usize> = (0..n * k).filter(|&j| gates[j]).collect();
    let population = active.len();
    // Churn of the previous step: its relocated slots, judged over the window they had.
    let judged: Vec<usize> = active
        .iter()
        .copied()
        .filter(|&j| state.relocated[j])
        .collect();
    let below = judged
        .iter()
        .filter(|&&j| judged_importance(state, k, j, config.importance) < config.dead_threshold)
        .count();
    state.relocated.fill(false);
    let mut dead: Vec<usize> = active
        .iter()
        .copied()
        .filter(|&j| {
            !young(j / k)
                && judged_importance(state, k, j, config.importance) < config.dead_threshold
        })
        .collect();
    // Ranked, lowest importance first (spec §12.3 step 4); ties by slot index for determinism.
    dead.sort_by(|&x, &y| {
        judged_importance(state, k, x, config.importance)
            .total_cmp(&judged_importance(state, k, y, config.importance))
            .then(x.cmp(&y))
    });
    let budget = dead
        .len()
        .min((config.relocate_fraction as f64 * population as f64).floor() as usize);
    for &j in &dead {
        gates[j] = false;
    }

    // A free slot a relocation may take: any free one, or under `AboveThresholdFree` one that
    // would have passed this step's test (which also excludes every slot it just switched off).
    let eligible = |gates: &[bool], state: &AnchorState, j: usize| {
        !gates[j]
            && (config.target_slot != RelocationSlot::AboveThresholdFree
                || judged_importance(state, k, j, config.importance) >= config.dead_threshold)
    };
    // Parents: alive slots ∝ importance, zero weight where the anchor has no eligible free slot.
    let has_free: Vec<bool> = (0..n)
        .map(|a| (a * k..(a + 1) * k).any(|j| eligible(&gates, state, j)))
        .collect();
    let weights: Vec<f64> = (0..n * k)
        .map(|j| {
            if gates[j] && has_free[j / k] {
                state.importance[j].max(0.0) as f64
            } else {
                0.0
            }
        })
        .collect();
    let mut report = RelocationReport {
        active_before: population,
        deactivated: dead.len(),
        previous_relocated: judged.len(),
        previous_below_threshold: below,
        ..Default::default()
    };
    let parents = WeightedIndex::new(&weights).ok();
    let mut placed: Vec<(usize, usize)> = Vec::new();
    if budget > 0 {
        let mut offsets = set.host(Column::Offsets);
        let noise = Normal::new(0.0f32, config.perturbation).expect("δ ≥ 0 is validated");
        for _ in 0..budget {
            let Some(parents) = &parents else {
                report.dropped += 1;
                continue;
            };
            let mut target = None;
            for _ in 0..config.resample_tries.max(1) {
                let parent = parents.sample(rng);
                let a = parent / k;
                let free = (0..k).filter(|&s| eligible(&gates, state, a * k + s));
                let chosen = match config.target_slot {
                    RelocationSlot::LowestFree => free.min(),
                    // Ties (e.g. all zero) go to the lowest slot.
                    RelocationSlot::MostOpaqueFree | RelocationSlot::AboveThresholdFree => free
                        .min_by(|&x, &y| {
                            let (ix, iy) =
                                (state.importance[a * k + x], state.importance[a * k + y]);
                            iy.total_cmp(&ix).then(x.cmp(&y))
                        }),
                };
                if let Some(free) = chosen {
                    target = Some((parent, a * k + free));
                    break;
                }
            }
            let Some((parent, slot)) = target else {
                report.dropped += 1;
                continue;
            };
            for c in 0..3 {
                let o = offsets[parent * 3 + c];
                offsets[slot * 3 + c] = o + o.abs() * noise.sample(rng);
            }
            gates[slot] = true;
            state.relocated[slot] = true;
            state.stats.offset_grad2d[slot * t..(slot + 1) * t].fill(0.0);
            state.stats.offset_visible_count[slot * t..(slot + 1) * t].fill(0.0);
            placed.push((slot / k, slot % k));
            report.relocated += 1;
        }
        if !placed.is_empty() {
            set.set_host(Column::Offsets, offsets);
            let mut zero = vec![false; n * k * 3];
            for &(a, s) in &placed {
                zero[(a * k + s) * 3..(a * k + s + 1) * 3].fill(true);
            }
            state.reset_adam_elements(Column::Offsets, &zero);
        }
    }
    set.slot_gates.edit(|flags| flags.copy_from_slice(&gates));
    state.reset_importance();
    report
}
