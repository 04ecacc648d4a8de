//! What the trainer keeps per anchor besides the model's values, row-aligned with the model's
//! [`AnchorSet`]: the Adam moments of every column (keyed by [`Column`], as gsplat's
//! `strategy/ops.py` edits a parameter and its optimizer state together), the densification
//! statistics, the AAC importance window, each anchor's birth step and the frame whose colours
//! the knot search re-finds it by, and the knots the rigid fit set that training holds.
//!
//! Rows change only through [`AnchorState::edit`], which applies one [`RowEdit`] to the set and
//! to this state together, so the two cannot drift apart.

use std::borrow::Cow;

use burn::tensor::{Bool, Gradients, Int, Tensor};

use crate::device_io::upload;
use crate::raster::columns::slice_columns;

use super::config::KnotStep;
use super::row_adam::{AdamConfig, RowAdam};
use super::statistics::{DensifyView, DeviceStatistics};
use crate::model::anchors::{
    AnchorDims, AnchorSet, AnchorTensors, Column, Columns, MOTION_GATE, NewAnchors, keep_row_values,
};

/// Per-frame densification statistics (spec §8.1), host-side, row-major: the host copy of what
/// [`AnchorState`] gathers on the device, current after [`AnchorState::settle`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AnchorStats {
    /// [N·K, T] Σ ‖∂L/∂μ2D‖ (gsplat-normalised) of spawned, on-screen slots.
    pub offset_grad2d: Vec<f32>,
    /// [N·K, T] how often each slot was spawned and on screen.
    pub offset_visible_count: Vec<f32>,
    /// [N, T] Σ_k max(α, 0) of visible anchors.
    pub opacity_accum: Vec<f32>,
    /// [N, T] how often each anchor was visible.
    pub anchor_visible_count: Vec<f32>,
}

impl AnchorStats {
    /// Zero statistics for `n` anchors of K slots and T frames.
    pub fn zeros(n: usize, slots: usize, frames: usize) -> Self {
        Self {
            offset_grad2d: vec![0.0; n * slots * frames],
            offset_visible_count: vec![0.0; n * slots * frames],
            opacity_accum: vec![0.0; n * frames],
            anchor_visible_count: vec![0.0; n * frames],
        }
    }
}

/// A change of the anchor rows.
#[derive(Clone, Debug)]
pub enum RowEdit<'a> {
    /// New rows at the end, born at training step `created_at`, each re-found by the knot search
    /// by its colours at GOP frame `reference_frames[i]` ([`AnchorState::reference_frame`]):
    /// zero Adam moments, statistics and importance.
    Append {
        rows: NewAnchors,
        created_at: usize,
        reference_frames: Vec<u32>,
    },
    /// Keep these rows, in this order (pruning).
    Keep(&'a [usize]),
}

/// The rate of one column's Adam step.
#[derive(Clone, Debug, PartialEq)]
pub enum ColumnRate {
    /// Not optimised this step (its moments and step count stay as they are).
    Frozen,
    Uniform(f64),
    /// One rate per element of a row (the trajectory knots' per-knot schedule).
    PerElement(Vec<f64>),
}

/// The trainer-owned per-anchor state.
#[derive(Clone, Debug)]
pub struct AnchorState {
    /// Adam state of each column, [N, width] like the column.
    pub adam: Columns<RowAdam<2>>,
    /// The statistics, current after [`Self::settle`] (while a window of gathering on the device
    /// is open they are empty: see `statistics.rs`).
    pub stats: AnchorStats,
    /// [N · K] AAC importance I: each slot's opacity summed since the last relocation (current
    /// after [`Self::settle`], as `stats`).
    pub importance: Vec<f32>,
    /// [N] training views in which each anchor was visible since the last relocation (as
    /// `importance`).
    pub importance_visits: Vec<f32>,
    /// What training steps gathered on the device since the last [`Self::settle`].
    on_device: DeviceStatistics,
    /// [N · K] slots the last AAC step relocated: the next one reports how many of them stayed
    /// below τ (relocation churn, docs/results.md).
    pub relocated: Vec<bool>,
    /// [N] step at which each anchor was created.
    pub created_at: Vec<u32>,
    /// [N] the GOP frame whose training images the knot search takes an anchor's reference
    /// colour from (`train/knot_search.rs`): 0, or the frame an anchor was seeded at by
    /// `train.appearance_seeding`.
    pub reference_frame: Vec<u32>,
    /// [N · knots] row-major: the trajectory knots (and their turns) that training holds where
    /// the rigid fit set them (`train.fitted_knots = "held"`, `train/rigid_fit.rs`).
    held_knots: Vec<bool>,
    /// [N, knots · 3] true where `held_knots` holds an element (`Some(None)`: none held): built
    /// on the first Adam step after `held_knots` or the rows change (`None`), so a step uploads
    /// and scans nothing.
    held_mask: Option<Option<Tensor<2, Bool>>>,
}

fn step_u32(step: usize) -> u32 {
    u32::try_from(step).expect("step fits in u32")
}

impl AnchorState {
    /// Fresh state for every row of `set`, all born at `created_at`.
    pub fn new(set: &AnchorSet, created_at: usize, config: AdamConfig) -> Self {
        let d = set.dims;
        let n = set.len();
        Self {
            adam: set.columns.map(|_, value| RowAdam::new(value, config)),
            stats: AnchorStats::zeros(n, d.slots, d.frames),
            importance: vec![0.0; n * d.slots],
            importance_visits: vec![0.0; n],
            relocated: vec![false; n * d.slots],
            created_at: vec![step_u32(created_at); n],
            reference_frame: vec![0; n],
            held_knots: vec![false; n * d.trajectory_knots()],
            held_mask: None,
            on_device: DeviceStatistics::default(),
        }
    }

    /// State from checkpointed values, nothing pending on the device.
    #[allow(clippy::too_many_arguments)]
    pub fn from_parts(
        adam: Columns<RowAdam<2>>,
        stats: AnchorStats,
        importance: Vec<f32>,
        importance_visits: Vec<f32>,
        relocated: Vec<bool>,
        created_at: Vec<u32>,
        reference_frame: Vec<u32>,
        held_knots: Vec<bool>,
    ) -> Self {
        assert_eq!(
            held_knots.len() % created_at.len().max(1),
            0,
            "held knots cover whole rows"
        );
        Self {
            adam,
            stats,
            importance,
            importance_visits,
            relocated,
            created_at,
            reference_frame,
            held_knots,
            held_mask: None,
            on_device: DeviceStatistics::default(),
        }
    }

    /// Adds one training view's densification statistics, on the device (nothing is read back;
    /// [`Self::settle`] brings `stats` up to date).
    pub fn gather_densify(&mut self, dims: &AnchorDims, view: DensifyView) {
        let n = self.len();
        self.on_device
            .gather_densify(&mut self.stats, dims, n, view);
    }

    /// Adds one training view's slot opacities before the slot gates ([M, K] for the `visible`
    /// rows) to AAC's importance window, on the device (as `gather_densify`).
    pub fn gather_importance(
        &mut self,
        dims: &AnchorDims,
        visible: Tensor<1, Int>,
        seen: Tensor<1>,
        slot_opacity: Tensor<2>,
    ) {
        let n = self.len();
        self.on_device.gather_importance(
            &mut self.importance,
            &mut self.importance_visits,
            dims,
            n,
            visible,
            seen,
            slot_opacity,
        );
    }

    /// Whether `stats`, `importance` and `importance_visits` are current (nothing gathered on
    /// the device since the last [`Self::settle`]).
    pub fn is_settled(&self) -> bool {
        self.on_device.is_settled()
    }

    /// Brings `stats`, `importance` and `importance_visits` up to date with what was gathered on
    /// the device (one read-back; nothing when nothing is pending).
    pub fn settle(&mut self) {
        self.on_device.settle(
            &mut self.stats,
            &mut self.importance,
            &mut self.importance_visits,
        );
    }

    /// This state with its statistics current: itself when nothing is pending, else a settled
    /// copy (for readers that hold it shared, such as a checkpoint).
    pub fn settled(&self) -> Cow<'_, Self> {
        if self.is_settled() {
            Cow::Borrowed(self)
        } else {
            let mut copy = self.clone();
            copy.settle();
            Cow::Owned(copy)
        }
    }

    pub fn len(&self) -> usize {
        self.created_at.len()
    }

    pub fn is_empty(&self) -> bool {
        self.created_at.is_empty()
    }

    /// Applies `edit` to `set` and to this state. The set's neighbour lists are left stale: call
    /// `set.rebuild_neighbors()` once after a batch of edits.
    pub fn edit(&mut self, set: &mut AnchorSet, edit: RowEdit) {
        // The statistics gathered on the device are row-aligned with the rows before the edit.
        self.settle();
        assert_eq!(
            set.len(),
            self.len(),
            "anchor state out of step with the set"
        );
        let d = set.dims;
        let (k, t) = (d.slots, d.frames);
        match edit {
            RowEdit::Append {
                rows,
                created_at,
                reference_frames,
            } => {
                let n = rows.len();
                set.append_rows(rows);
                for (_, adam) in self.adam.iter_mut() {
                    adam.grow(n);
                }
                let s = &mut self.stats;
                s.offset_grad2d
                    .resize(s.offset_grad2d.len() + n * k * t, 0.0);
                s.offset_visible_count
                    .resize(s.offset_visible_count.len() + n * k * t, 0.0);
                s.opacity_accum.resize(s.opacity_accum.len() + n * t, 0.0);
                s.anchor_visible_count
                    .resize(s.anchor_visible_count.len() + n * t, 0.0);
                self.importance.resize(self.importance.len() + n * k, 0.0);
                self.importance_visits
                    .resize(self.importance_visits.len() + n, 0.0);
                self.relocated.resize(self.relocated.len() + n * k, false);
                self.created_at
                    .resize(self.created_at.len() + n, step_u32(created_at));
                assert_eq!(reference_frames.len(), n, "one reference frame per new row");
                self.reference_frame.extend(reference_frames);
                // New rows (growth copies its parents' knots, a seed offsets its neighbour's)
                // train theirs.
                self.held_knots
                    .resize(self.held_knots.len() + n * d.trajectory_knots(), false);
            }
            RowEdit::Keep(keep) => {
                set.keep_rows(keep);
                for (_, adam) in self.adam.iter_mut() {
                    adam.keep_rows(keep);
                }
                let s = &self.stats;
                self.stats = AnchorStats {
                    offset_grad2d: keep_row_values(&s.offset_grad2d, keep, k * t),
                    offset_visible_count: keep_row_values(&s.offset_visible_count, keep, k * t),
                    opacity_accum: keep_row_values(&s.opacity_accum, keep, t),
                    anchor_visible_count: keep_row_values(&s.anchor_visible_count, keep, t),
                };
                self.importance = keep_row_values(&self.importance, keep, k);
                self.importance_visits = keep_row_values(&self.importance_visits, keep, 1);
                self.relocated = keep_row_values(&self.relocated, keep, k);
                self.created_at = keep_row_values(&self.created_at, keep, 1);
                self.reference_frame = keep_row_values(&self.reference_frame, keep, 1);
                self.held_knots = keep_row_values(&self.held_knots, keep, d.trajectory_knots());
            }
        }
        self.held_mask = None;
    }

    /// [N · knots] row-major: whether training holds each anchor's knot where the rigid fit set
    /// it.
    pub fn held_knots(&self) -> &[bool] {
        &self.held_knots
    }

    /// Holds knot `knot` of each of `anchors` (trajectory and turn) where it is now: no later
    /// Adam step changes it, whatever its gradient (the image loss's, the rate term's) or its
    /// moments (they go on as every element's; nothing reads them while it is held).
    pub fn hold_fitted_knots(&mut self, dims: &AnchorDims, knot: usize, anchors: &[usize]) {
        let knots = dims.trajectory_knots();
        assert!(knot < knots, "knot {knot} of {knots}");
        if anchors.is_empty() {
            return;
        }
        for &a in anchors {
            self.held_knots[a * knots + knot] = true;
        }
        self.held_mask = None;
    }

    /// Releases every held knot (a checkpoint written under `train.fitted_knots = "held"`
    /// resumed under `"trained"`).
    pub fn release_held_knots(&mut self) {
        self.held_knots.fill(false);
        self.held_mask = None;
    }

    /// [N, knots · 3] true on the held knots' elements, `None` when none is held.
    fn held_mask(
        &mut self,
        dims: &AnchorDims,
        device: &burn::tensor::Device,
    ) -> Option<Tensor<2, Bool>> {
        let (n, width) = (self.len(), dims.trajectory_width());
        let held_knots = &self.held_knots;
        self.held_mask
            .get_or_insert_with(|| {
                held_knots.contains(&true).then(|| {
                    let values: Vec<bool> = held_knots.iter().flat_map(|&h| [h; 3]).collect();
                    upload::<2, Bool>(burn::tensor::TensorData::new(values, [n, width]), device)
                })
            })
            .clone()
    }

    /// Clears the AAC importance window.
    pub fn reset_importance(&mut self) {
        // What the device gathered is replaced by zeros: nothing to read back.
        self.on_device.drop_importance();
        self.importance = vec![0.0; self.relocated.len()];
        self.importance_visits = vec![0.0; self.len()];
    }

    /// Fresh Adam state, statistics and importance for the same rows (a warm-started GOP); the
    /// birth steps stay. Reference frames restart at 0: they index the previous GOP's frames.
    pub fn restart(&mut self, set: &AnchorSet, config: AdamConfig) {
        let created_at = std::mem::take(&mut self.created_at);
        *self = Self::new(set, 0, config);
        self.created_at = created_at;
    }

    /// One Adam step of every column from the gradients of `tracked` (`set.tracked()` of this
    /// step).
    pub fn adam_step(
        &mut self,
        set: &mut AnchorSet,
        tracked: &AnchorTensors,
        grads: &Gradients,
        rates: &Columns<ColumnRate>,
        knot_step: KnotStep,
    ) {
        let held = match set.columns.get(Column::Trajectory) {
            Some(knots) => self.held_mask(&set.dims, &knots.device()),
            None => None,
        };
        // [N, 1] motion gates of the values before the step (detached plain values).
        let gates = (knot_step == KnotStep::Rendered && !set.is_empty()).then(|| {
            let factors = set.columns[Column::Factors].clone();
            crate::raster::activation::sigmoid(slice_columns(factors, MOTION_GATE..MOTION_GATE + 1))
        });
        for (c, adam) in self.adam.iter_mut() {
            let rate = rates.get(c).unwrap_or(&ColumnRate::Frozen);
            if *rate == ColumnRate::Frozen {
                continue;
            }
            let value = set.columns[c].clone();
            let old = value.clone();
            // A column the loss did not reach still takes an Adam step with a zero gradient, as
            // torch does for a parameter whose .grad is a zero tensor (the moments keep decaying).
            let grad: Tensor<2> = tracked.columns[c]
                .grad(grads)
                .unwrap_or_else(|| value.zeros_like());
            set.columns[c] = match rate {
                ColumnRate::Frozen => unreachable!(),
                ColumnRate::Uniform(lr) => adam.step(value, grad, *lr),
                ColumnRate::PerElement(lr) => {
                    assert_eq!(
                        Some(lr.len()),
                        c.width(&set.dims),
                        "one rate per element of a `{}` row",
                        c.name()
                    );
                    match lr.first() {
                        Some(&first) if lr.iter().any(|&r| r != first) => {
                            adam.step_columns(value, grad, lr)
                        }
                        // Uniform rates take the scalar path.
                        _ => adam.step(value, grad, lr.first().copied().unwrap_or(0.0)),
                    }
                }
            };
            // Knots stepped in rendered units: the update scaled by the anchor's motion gate.
            if let (Some(gates), Column::Trajectory | Column::Turn) = (&gates, c) {
                let new = set.columns[c].clone();
                set.columns[c] = old.clone() + (new - old.clone()) * gates.clone();
            }
            // Held knots keep their values exactly (a selection, not a blend: bit for bit, and
            // a non-finite step does not reach them).
            if let (Some(held), Column::Trajectory | Column::Turn) = (&held, c) {
                let new = set.columns[c].clone();
                set.columns[c] = new.mask_where(held.clone(), old);
            }
        }
    }

    /// Zeroes column `c`'s Adam moments where `zero` is set (row-major over [N, width]): a
    /// relocated slot's offsets start afresh.
    pub fn reset_adam_elements(&mut self, c: Column, zero: &[bool]) {
        self.adam[c].reset_elements(zero);
    }
}
