//! The per-anchor columns: every optimised per-anchor attribute is declared here, once, with the
//! sizes every row shares ([`AnchorDims`]).
//!
//! A column is stored as a row-aligned [N, width] tensor (a row's values flattened, e.g. an
//! anchor's K offsets as 3·K floats); a forward pass sees it in its natural rank
//! (`anchors::ColumnTensor`). [`Column`] names each one and [`Column::row_shape`] gives the shape
//! of one row; appending, keeping and gathering rows, taking tracked copies, the Adam state
//! (`train::anchor_state`, keyed by the same columns) and checkpoints all iterate
//! [`Column::ALL`], so adding an attribute is one variant here plus its arm in each `match`
//! below. The compiler then names the three other decisions a column needs, as exhaustive
//! matches: its learning rate (`train::optimizers::StepRates::at`), its quantisation
//! (`codec::quantization::simulate`) and its share of the stored size
//! (`AnchorSet::stored_bytes`); using it in the decoders is the rest (docs/architecture.md walks
//! through an example).

use std::ops::{Index, IndexMut};

use super::feature_mask::INITIAL_MASK_LOGIT;

/// Gates: [time-feature d, motion, kNN blend, pruning].
pub const FACTOR_COUNT: usize = 4;
/// The motion gate's place in a row of [`Column::Factors`].
pub const MOTION_GATE: usize = 1;
/// Log-scales: [0:3] scale the offsets, [3:6] are the Gaussians' base scale.
pub const SCALE_DIMS: usize = 6;

/// Whether the decoders see a masked feature (ACA-GS AAFM).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FeatureMasking {
    Off,
    /// F = [F[0..base] ; M · F[base..]], M = 1[σ(m) > threshold] (straight-through).
    Adaptive {
        base: usize,
        threshold: f32,
    },
}

/// Sizes shared by every row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnchorDims {
    /// K (K_max under adaptive cardinality).
    pub slots: usize,
    /// Slots 0..this of a new anchor start active; `slots` under fixed cardinality.
    pub initial_active_slots: usize,
    pub feature_masking: FeatureMasking,
    /// T, frames of the GOP.
    pub frames: usize,
    /// C_F
    pub feature_dim: usize,
    /// C_T
    pub time_feature_dim: usize,
    /// Neighbours per anchor for the motion input's kNN blend (0 = off).
    pub knn: usize,
    /// Frames between two knots of the anchor trajectories (0: no trajectories, GIFStream).
    pub trajectory_spacing: usize,
    /// Whether the trajectories also turn each anchor's Gaussians ([`Column::Turn`]; only with
    /// trajectories).
    pub trajectory_turn: TrajectoryTurn,
}

/// Whether an anchor trajectory carries a rotation besides its translation (`model.trajectory_turn`;
/// not in GIFStream, see `model/view.rs`).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum TrajectoryTurn {
    /// Knots translate the anchor only; its slots turn by the motion head's rotation alone
    /// (GIFStream's only rotation), so an object that spins keeps its Gaussians' frame-0 layout.
    #[default]
    Off,
    /// Each knot also holds a rotation vector (axis × angle, radians), interpolated linearly
    /// like the translation; gated by the motion gate, it turns the anchor's offsets about the
    /// anchor and composes into its Gaussians' orientations.
    Knots,
    /// The same turns, not optimised and not stored: derived from the anchors' paths, each
    /// anchor's the rotation carrying it and its kNN neighbours from knot 0 to the knot
    /// (`model/path_turns.rs`); the decoder derives them from the decoded trajectories.
    Paths,
    /// Derived likewise, but one turn per moving object: the anchors whose paths stay together
    /// are grouped, and each group's anchors all turn by the rotation that best carries the
    /// whole group from knot 0 to the knot; the rest do not turn (`model/path_turns.rs`).
    Objects,
}

impl TrajectoryTurn {
    /// The config's spelling.
    pub fn name(self) -> &'static str {
        match self {
            TrajectoryTurn::Off => "off",
            TrajectoryTurn::Knots => "knots",
            TrajectoryTurn::Paths => "paths",
            TrajectoryTurn::Objects => "objects",
        }
    }

    /// Whether the turns are derived from the paths (neither optimised nor stored).
    pub fn is_derived(self) -> bool {
        matches!(self, TrajectoryTurn::Paths | TrajectoryTurn::Objects)
    }
}

impl AnchorDims {
    /// Knots of an anchor trajectory: one every `trajectory_spacing` frames from frame 0, the
    /// last at or after frame T − 1 (0 without trajectories).
    pub fn trajectory_knots(&self) -> usize {
        match self.trajectory_spacing {
            0 => 0,
            s => self.frames.saturating_sub(1).div_ceil(s) + 1,
        }
    }

    /// Floats per anchor of its trajectory: 3 per knot.
    pub fn trajectory_width(&self) -> usize {
        3 * self.trajectory_knots()
    }

    /// Floats per anchor of its turn ([`Column::Turn`]): 3 per knot, 0 without turns.
    pub fn turn_width(&self) -> usize {
        match self.trajectory_turn {
            TrajectoryTurn::Off => 0,
            TrajectoryTurn::Knots | TrajectoryTurn::Paths | TrajectoryTurn::Objects => {
                self.trajectory_width()
            }
        }
    }

    /// Floats per anchor of its turn in a scene file: derived turns are not stored.
    pub fn stored_turn_width(&self) -> usize {
        match self.trajectory_turn {
            TrajectoryTurn::Off | TrajectoryTurn::Paths | TrajectoryTurn::Objects => 0,
            TrajectoryTurn::Knots => self.trajectory_width(),
        }
    }
}

/// An optimised per-anchor attribute.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Column {
    /// [6] log-scales: [0:3] scale the offsets, [3:6] are the Gaussians' base scale.
    LogScales,
    /// [K, 3] offsets in units of exp(log_scales[0:3]).
    Offsets,
    /// [C_F] the anchor feature.
    Features,
    /// [T, C_T] the per-frame feature stream.
    TimeFeatures,
    /// [4] raw gate logits: time-feature d, motion, kNN blend, pruning.
    Factors,
    /// [1] the AAFM mask logit m (kept, but neither used nor optimised, when masking is off).
    MaskLogits,
    /// [3·knots] trajectory knots, x y z per knot (only with `model.trajectory_spacing` > 0; see
    /// `view.rs`).
    Trajectory,
    /// [3·knots] rotation vector per trajectory knot (axis × angle, radians; only with
    /// trajectories and `model.trajectory_turn = "knots"`).
    Turn,
}

impl Column {
    pub const COUNT: usize = 8;
    /// Every column, in the order steps that draw random numbers visit them (the quantisation
    /// noise), which is part of the exact-resume contract: append new columns at the end.
    pub const ALL: [Column; Column::COUNT] = [
        Column::LogScales,
        Column::Offsets,
        Column::Features,
        Column::TimeFeatures,
        Column::Factors,
        Column::MaskLogits,
        Column::Trajectory,
        Column::Turn,
    ];

    /// The name in checkpoints (`anchors.<name>`) and messages.
    pub fn name(self) -> &'static str {
        match self {
            Column::LogScales => "log_scales",
            Column::Offsets => "offsets",
            Column::Features => "features",
            Column::TimeFeatures => "time_features",
            Column::Factors => "factors",
            Column::MaskLogits => "mask_logits",
            Column::Trajectory => "trajectory",
            Column::Turn => "turn",
        }
    }

    /// The shape of one row, or None where a set of these sizes has no such column.
    pub fn row_shape(self, d: &AnchorDims) -> Option<Vec<usize>> {
        Some(match self {
            Column::LogScales => vec![SCALE_DIMS],
            Column::Offsets => vec![d.slots, 3],
            Column::Features => vec![d.feature_dim],
            Column::TimeFeatures => vec![d.frames, d.time_feature_dim],
            Column::Factors => vec![FACTOR_COUNT],
            Column::MaskLogits => vec![1],
            Column::Trajectory if d.trajectory_spacing == 0 => return None,
            Column::Trajectory => vec![d.trajectory_width()],
            Column::Turn if d.turn_width() == 0 => return None,
            Column::Turn => vec![d.turn_width()],
        })
    }

    /// Floats per row (None where the set has no such column).
    pub fn width(self, d: &AnchorDims) -> Option<usize> {
        self.row_shape(d).map(|s| s.iter().product())
    }

    /// The value of every element of a row created without one (initial anchors, and rows
    /// appended without this column): zero, except the mask logit (masks start open) and the
    /// log-scales, which a caller always supplies.
    pub fn initial_value(self) -> f32 {
        match self {
            Column::MaskLogits => INITIAL_MASK_LOGIT,
            // Raw gate logit 0: sigmoid 0.5, every gate half open.
            Column::Factors => 0.0,
            Column::LogScales
            | Column::Offsets
            | Column::Features
            | Column::TimeFeatures
            | Column::Trajectory
            // The identity turn.
            | Column::Turn => 0.0,
        }
    }

    /// The columns a set of these sizes has.
    pub fn present(d: &AnchorDims) -> impl Iterator<Item = Column> + '_ {
        Column::ALL
            .into_iter()
            .filter(move |c| c.row_shape(d).is_some())
    }
}

/// One value per column (absent columns hold None): the anchor values, their tracked copies,
/// Adam states, learning rates, new rows.
#[derive(Clone, Debug, PartialEq)]
pub struct Columns<T>([Option<T>; Column::COUNT]);

impl<T> Default for Columns<T> {
    fn default() -> Self {
        Self(std::array::from_fn(|_| None))
    }
}

impl<T> Columns<T> {
    /// `value(c)` for every column a set of these sizes has.
    pub fn build(d: &AnchorDims, mut value: impl FnMut(Column) -> T) -> Self {
        let mut out = Self::default();
        for c in Column::present(d) {
            out.0[c as usize] = Some(value(c));
        }
        out
    }

    pub fn get(&self, c: Column) -> Option<&T> {
        self.0[c as usize].as_ref()
    }

    pub fn get_mut(&mut self, c: Column) -> Option<&mut T> {
        self.0[c as usize].as_mut()
    }

    pub fn insert(&mut self, c: Column, value: T) {
        self.0[c as usize] = Some(value);
    }

    pub fn remove(&mut self, c: Column) -> Option<T> {
        self.0[c as usize].take()
    }

    /// The present columns in [`Column::ALL`] order.
    pub fn iter(&self) -> impl Iterator<Item = (Column, &T)> {
        Column::ALL
            .into_iter()
            .filter_map(|c| self.get(c).map(|v| (c, v)))
    }

    pub fn iter_mut(&mut self) -> impl Iterator<Item = (Column, &mut T)> {
        Column::ALL
            .into_iter()
            .zip(self.0.iter_mut())
            .filter_map(|(c, v)| v.as_mut().map(|v| (c, v)))
    }

    /// A value per present column, computed in [`Column::ALL`] order.
    pub fn map<U>(&self, mut f: impl FnMut(Column, &T) -> U) -> Columns<U> {
        let mut out = Columns::default();
        for (c, v) in self.iter() {
            out.0[c as usize] = Some(f(c, v));
        }
        out
    }
}

impl<T> Index<Column> for Columns<T> {
    type Output = T;

    fn index(&self, c: Column) -> &T {
        self.get(c)
            .unwrap_or_else(|| panic!("this anchor set has no `{}` column", c.name()))
    }
}

impl<T> IndexMut<Column> for Columns<T> {
    fn index_mut(&mut self, c: Column) -> &mut T {
        self.get_mut(c)
            .unwrap_or_else(|| panic!("this anchor set has no `{}` column", c.name()))
    }
}
