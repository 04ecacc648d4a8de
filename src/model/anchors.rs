//! The anchor set: positions, the per-anchor columns (`anchor_columns.rs`), the AAC slot gates
//! and the neighbour lists, rows growing and shrinking together (spec §2.1, §8, §19).
//!
//! Values live on the plain (non-autodiff) device; a training step takes tracked copies
//! ([`AnchorSet::tracked`]). Everything only training needs (Adam moments, densification
//! statistics, AAC importance, birth steps) is the trainer's, row-aligned with this set
//! (`train::anchor_state`).

use crate::device_io::upload;
use burn::tensor::{Device, Gradients, Int, Tensor, TensorData};

pub use super::anchor_columns::{
    AnchorDims, Column, Columns, FACTOR_COUNT, FeatureMasking, MOTION_GATE, SCALE_DIMS,
    TrajectoryTurn,
};
use super::init::{initial_log_scales, nearest_neighbors, voxelize};
use super::slot_gates::SlotGates;
use crate::raster::gather::gather_rows;

/// The rows of new anchors (initial points, densification, a decoded file), host-side.
#[derive(Clone, Debug, Default)]
pub struct NewAnchors {
    pub positions: Vec<[f32; 3]>,
    /// Row-major values per column ([n, width]); a column left out starts at
    /// [`Column::initial_value`].
    pub columns: Columns<Vec<f32>>,
}

impl NewAnchors {
    pub fn new(positions: Vec<[f32; 3]>) -> Self {
        Self {
            positions,
            columns: Columns::default(),
        }
    }

    /// These rows with `values` ([n, width] row-major) in column `c`.
    pub fn with(mut self, c: Column, values: Vec<f32>) -> Self {
        self.columns.insert(c, values);
        self
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// One column of a forward pass in its natural rank: [N, width] for a one-dimensional row,
/// [N, a, b] for a row of shape [a, b] (offsets, the feature stream).
///
/// Not flattened: Burn's autodiff tape runs a step's backward depth by depth, so a reshape more
/// or fewer before a tensor with several consumers changes the order its gradients are summed in
/// and the last bit of the result. Tracked leaves keep the rank they had before the column table,
/// and training stays bit for bit what it was (tests/golden_trace.rs).
#[derive(Clone, Debug)]
pub enum ColumnTensor {
    Rows(Tensor<2>),
    Grid(Tensor<3>),
}

impl ColumnTensor {
    /// The [N, width] values of a column with this row shape.
    fn from_flat(values: Tensor<2>, row_shape: &[usize]) -> Self {
        match *row_shape {
            [_] => ColumnTensor::Rows(values),
            [a, b] => {
                let n = values.dims()[0];
                ColumnTensor::Grid(values.reshape([n, a, b]))
            }
            _ => unreachable!("rows are one- or two-dimensional"),
        }
    }

    pub fn rows(&self) -> usize {
        match self {
            ColumnTensor::Rows(t) => t.dims()[0],
            ColumnTensor::Grid(t) => t.dims()[0],
        }
    }

    /// [N, width] (a reshape of a grid column).
    pub fn flat(&self) -> Tensor<2> {
        match self {
            ColumnTensor::Rows(t) => t.clone(),
            ColumnTensor::Grid(t) => {
                let [n, a, b] = t.dims();
                t.clone().reshape([n, a * b])
            }
        }
    }

    /// The [N, a, b] tensor of a grid column.
    pub fn grid(&self) -> Tensor<3> {
        match self {
            ColumnTensor::Grid(t) => t.clone(),
            ColumnTensor::Rows(t) => panic!("a [N, width] column ({:?}) is not a grid", t.dims()),
        }
    }

    /// The [N, width] tensor of a one-dimensional column.
    pub fn as_rows(&self) -> Tensor<2> {
        match self {
            ColumnTensor::Rows(t) => t.clone(),
            ColumnTensor::Grid(t) => panic!("a grid column ({:?}) is not [N, width]", t.dims()),
        }
    }

    /// The gradient of this (tracked) column, as [N, width].
    pub fn grad(&self, grads: &Gradients) -> Option<Tensor<2>> {
        match self {
            ColumnTensor::Rows(t) => t.grad(grads),
            ColumnTensor::Grid(t) => {
                let [n, a, b] = t.dims();
                t.grad(grads).map(|g| g.reshape([n, a * b]))
            }
        }
    }

    /// Replaces the gradient of this (tracked) column in `grads` with `grad`, [N, width].
    pub fn replace_grad(&self, grads: &mut Gradients, grad: Tensor<2>) {
        match self {
            ColumnTensor::Rows(t) => t.grad_replace(grads, grad),
            ColumnTensor::Grid(t) => {
                let [n, a, b] = t.dims();
                t.grad_replace(grads, grad.reshape([n, a, b]))
            }
        }
    }

    /// `rows` or `grid` applied to the tensor, keeping its rank.
    pub fn map(
        self,
        rows: impl FnOnce(Tensor<2>) -> Tensor<2>,
        grid: impl FnOnce(Tensor<3>) -> Tensor<3>,
    ) -> Self {
        match self {
            ColumnTensor::Rows(t) => ColumnTensor::Rows(rows(t)),
            ColumnTensor::Grid(t) => ColumnTensor::Grid(grid(t)),
        }
    }
}

/// The per-anchor tensors of one forward pass, one per column: tracked (autodiff,
/// require-grad) copies in training, plain ones in evaluation, or what the quantisation
/// simulation made of them.
#[derive(Clone, Debug)]
pub struct AnchorTensors {
    pub dims: AnchorDims,
    pub columns: Columns<ColumnTensor>,
}

impl AnchorTensors {
    /// Column `c` as [N, width].
    pub fn get(&self, c: Column) -> Tensor<2> {
        self.columns[c].flat()
    }

    pub fn rows(&self) -> usize {
        self.columns[Column::Features].rows()
    }

    pub fn device(&self) -> Device {
        self.columns[Column::Features].as_rows().device()
    }

    /// [N, 6]
    pub fn log_scales(&self) -> Tensor<2> {
        self.columns[Column::LogScales].as_rows()
    }

    /// [N, K, 3]
    pub fn offsets(&self) -> Tensor<3> {
        self.columns[Column::Offsets].grid()
    }

    /// [N, C_F]
    pub fn features(&self) -> Tensor<2> {
        self.columns[Column::Features].as_rows()
    }

    /// [N, T, C_T]
    pub fn time_features(&self) -> Tensor<3> {
        self.columns[Column::TimeFeatures].grid()
    }

    /// [N, 4] raw gate logits.
    pub fn factors(&self) -> Tensor<2> {
        self.columns[Column::Factors].as_rows()
    }

    /// [N, 1]
    pub fn mask_logits(&self) -> Tensor<2> {
        self.columns[Column::MaskLogits].as_rows()
    }

    /// [N, knots·3], when the set has trajectories.
    pub fn trajectory(&self) -> Option<Tensor<2>> {
        self.columns.get(Column::Trajectory).map(|t| t.as_rows())
    }

    /// [N, knots·3] rotation vectors, when the trajectories turn ([`Column::Turn`]).
    pub fn turn(&self) -> Option<Tensor<2>> {
        self.columns.get(Column::Turn).map(|t| t.as_rows())
    }

    /// `f` applied to every column, in [`Column::ALL`] order.
    pub fn map(&self, mut f: impl FnMut(Column, ColumnTensor) -> ColumnTensor) -> Self {
        Self {
            dims: self.dims,
            columns: self.columns.map(|c, t| f(c, t.clone())),
        }
    }
}

#[derive(Clone, Debug)]
pub struct AnchorSet {
    pub dims: AnchorDims,
    /// World positions on the voxel grid; fixed (GIFStream lr 0).
    pub positions: Vec<[f32; 3]>,
    /// The same positions as a [N, 3] tensor.
    pub position_tensor: Tensor<2>,
    /// The optimised per-anchor values, one [N, width] tensor per column (`anchor_columns.rs`).
    /// Their optimizer state lives with the trainer (`train::anchor_state`).
    pub columns: Columns<Tensor<2>>,
    /// [N · K] AAC slot gates g: a gated slot is never rasterized. A buffer, not a parameter;
    /// with a device mirror for the decode and the rate term (`slot_gates.rs`).
    pub slot_gates: SlotGates,
    /// [N · knn] nearest other anchors, recomputed whenever the rows change.
    neighbors: Vec<u32>,
    /// [N, knn] the same on the device, so that a decode gathers its rows' neighbours there
    /// instead of uploading them each step; None while there are none (knn = 0 or no rows).
    /// Held as floats (exact below 2^24 rows) so that the fast row gather of
    /// `acags_kernels::gather` applies: Burn's `select` on ndarray costs ≈ 1 µs per index.
    neighbor_table: Option<Tensor<2>>,
}

fn tensor2(values: Vec<f32>, rows: usize, cols: usize, device: &Device) -> Tensor<2> {
    upload::<2, burn::tensor::Float>(TensorData::new(values, [rows, cols]), device)
}

/// Host copy of a tensor's values.
pub fn host_values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    crate::device_io::read_back(t.clone())
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("float tensor data")
}

/// A [rows] index tensor.
pub fn row_index(rows: &[usize], device: &Device) -> Tensor<1, Int> {
    upload::<1, Int>(
        TensorData::new(
            rows.iter().map(|&r| r as i64).collect::<Vec<_>>(),
            [rows.len()],
        ),
        device,
    )
}

impl AnchorSet {
    /// Anchors from a point cloud (spec §3): voxelised positions, log-scales from the 3 nearest
    /// anchors repeated ×6, every other column at its initial value.
    pub fn from_points(
        points: &[[f32; 3]],
        voxel_size: f32,
        dims: AnchorDims,
        device: &Device,
    ) -> Self {
        let positions = voxelize(points, voxel_size);
        let scales: Vec<f32> = initial_log_scales(&positions)
            .into_iter()
            .flat_map(|s| [s; SCALE_DIMS])
            .collect();
        Self::from_rows(
            dims,
            NewAnchors::new(positions).with(Column::LogScales, scales),
            device,
        )
    }

    /// An anchor set holding exactly these rows.
    pub fn from_rows(dims: AnchorDims, rows: NewAnchors, device: &Device) -> Self {
        let mut set = Self {
            dims,
            positions: Vec::new(),
            position_tensor: tensor2(Vec::new(), 0, 3, device),
            columns: Columns::build(&dims, |c| {
                tensor2(Vec::new(), 0, c.width(&dims).expect("present"), device)
            }),
            slot_gates: SlotGates::empty(dims.slots, device),
            neighbors: Vec::new(),
            neighbor_table: None,
        };
        set.append(rows);
        set
    }

    /// A set restored from stored parts (a checkpoint): `positions` and `position_tensor` hold
    /// the same N rows, every column and the gates N rows too; the neighbours are rebuilt.
    pub fn restored(
        dims: AnchorDims,
        positions: Vec<[f32; 3]>,
        position_tensor: Tensor<2>,
        columns: Columns<Tensor<2>>,
        slot_gates: SlotGates,
    ) -> Self {
        let n = positions.len();
        assert_eq!(position_tensor.dims(), [n, 3]);
        assert_eq!(
            (slot_gates.slots(), slot_gates.len()),
            (dims.slots, n * dims.slots)
        );
        for (c, t) in columns.iter() {
            assert_eq!(t.dims()[0], n, "rows of `{}`", c.name());
        }
        let mut set = Self {
            dims,
            positions,
            position_tensor,
            columns,
            slot_gates,
            neighbors: Vec::new(),
            neighbor_table: None,
        };
        set.rebuild_neighbors();
        set
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    pub fn device(&self) -> Device {
        self.position_tensor.device()
    }

    /// Column `c`, [N, width].
    pub fn value(&self, c: Column) -> &Tensor<2> {
        &self.columns[c]
    }

    /// Host copy of column `c`, row-major.
    pub fn host(&self, c: Column) -> Vec<f32> {
        host_values(&self.columns[c])
    }

    /// Host copy of column `c` where the set has it (trajectories, turns), None otherwise.
    pub fn host_if_present(&self, c: Column) -> Option<Vec<f32>> {
        self.columns.get(c).map(host_values)
    }

    /// Replaces column `c` with host values of the same shape, e.g. edited by relocation or
    /// post-hoc pruning (the optimizer state is the trainer's to reset).
    pub fn set_host(&mut self, c: Column, values: Vec<f32>) {
        let shape = self.columns[c].dims();
        self.columns[c] =
            upload::<2, burn::tensor::Float>(TensorData::new(values, shape), &self.device());
    }

    /// Appends rows with the first `initial_active_slots` slots active; neighbours are
    /// recomputed.
    pub fn append(&mut self, rows: NewAnchors) {
        if !rows.is_empty() {
            self.append_rows(rows);
            self.rebuild_neighbors();
        }
    }

    /// [`AnchorSet::append`] leaving the neighbour lists stale: for callers that append several
    /// times in a row (densification levels) and rebuild once.
    pub(crate) fn append_rows(&mut self, rows: NewAnchors) {
        let n = rows.len();
        if n == 0 {
            return;
        }
        let d = self.dims;
        let device = self.device();
        for (c, given) in rows.columns.iter() {
            let expected = c.width(&d).map(|w| n * w);
            assert_eq!(
                Some(given.len()),
                expected,
                "new rows of `{}` (a column this set {})",
                c.name(),
                if expected.is_some() {
                    "has"
                } else {
                    "does not have"
                }
            );
        }
        let mut new_rows = rows.columns;
        for (c, column) in self.columns.iter_mut() {
            let width = c.width(&d).expect("present");
            let values = new_rows
                .remove(c)
                .unwrap_or_else(|| vec![c.initial_value(); n * width]);
            *column = Tensor::cat(vec![column.clone(), tensor2(values, n, width, &device)], 0);
        }
        let flat: Vec<f32> = rows.positions.iter().flatten().copied().collect();
        self.position_tensor = Tensor::cat(
            vec![self.position_tensor.clone(), tensor2(flat, n, 3, &device)],
            0,
        );
        self.positions.extend_from_slice(&rows.positions);
        self.slot_gates.append_anchors(n, d.initial_active_slots);
    }

    /// Keeps the listed rows, in that order (pruning); neighbours are recomputed.
    pub fn keep(&mut self, keep: &[usize]) {
        self.keep_rows(keep);
        self.rebuild_neighbors();
    }

    /// [`AnchorSet::keep`] leaving the neighbour lists stale.
    pub(crate) fn keep_rows(&mut self, keep: &[usize]) {
        let n = self.len();
        assert!(keep.iter().all(|&r| r < n), "row out of range");
        let index = row_index(keep, &self.device());
        self.positions = keep.iter().map(|&r| self.positions[r]).collect();
        self.position_tensor = self.position_tensor.clone().select(0, index.clone());
        for (_, column) in self.columns.iter_mut() {
            *column = column.clone().select(0, index.clone());
        }
        self.slot_gates.keep_anchors(keep);
    }

    /// k nearest other anchors of every anchor (spec §4.2: recomputed whenever N changes). With
    /// fewer than k others the list is padded with the nearest found (or the anchor itself).
    pub fn rebuild_neighbors(&mut self) {
        let k = self.dims.knn;
        if k == 0 {
            self.neighbors.clear();
            self.neighbor_table = None;
            return;
        }
        let lists = nearest_neighbors(&self.positions, k);
        self.neighbors = lists
            .into_iter()
            .enumerate()
            .flat_map(|(i, list)| {
                let fill = list.first().copied().unwrap_or(i as u32);
                (0..k).map(move |j| list.get(j).copied().unwrap_or(fill))
            })
            .collect();
        assert!(self.len() < 1 << 24, "row indices held exactly as f32");
        self.neighbor_table = (!self.neighbors.is_empty()).then(|| {
            let rows: Vec<f32> = self.neighbors.iter().map(|&r| r as f32).collect();
            tensor2(rows, self.len(), k, &self.device())
        });
    }

    /// [N · knn] the knn nearest other anchors of every anchor, row-major.
    pub fn neighbors(&self) -> &[u32] {
        &self.neighbors
    }

    /// [M · knn] the neighbours of the anchors `index` [M], gathered on the device from the
    /// set's neighbour table (no upload); None when the set keeps no neighbours.
    pub fn neighbors_of(&self, index: Tensor<1, Int>) -> Option<Tensor<1, Int>> {
        let table = self.neighbor_table.as_ref()?;
        assert_eq!(
            table.dims()[0],
            self.len(),
            "neighbour table of another row count: rebuild_neighbors after changing rows"
        );
        let m = index.dims()[0];
        let k = self.dims.knn;
        Some(gather_rows(table.clone(), index).reshape([m * k]).int())
    }

    /// Tracked copies of every column, in its natural rank, on the autodiff `device`.
    pub fn tracked(&self) -> AnchorTensors {
        let d = self.dims;
        AnchorTensors {
            dims: d,
            columns: self.columns.map(|c, t| {
                match ColumnTensor::from_flat(t.clone(), &c.row_shape(&d).expect("present")) {
                    ColumnTensor::Rows(t) => ColumnTensor::Rows(t.autodiff().require_grad()),
                    ColumnTensor::Grid(t) => ColumnTensor::Grid(t.autodiff().require_grad()),
                }
            }),
        }
    }

    /// Plain (untracked) views of the columns, for evaluation.
    pub fn untracked(&self) -> AnchorTensors {
        let d = self.dims;
        AnchorTensors {
            dims: d,
            columns: self
                .columns
                .map(|c, t| ColumnTensor::from_flat(t.clone(), &c.row_shape(&d).expect("present"))),
        }
    }

    /// Active (ungated) slots over all anchors.
    pub fn active_slot_count(&self) -> usize {
        self.slot_gates.active_count()
    }

    /// Active slots of one anchor.
    pub fn cardinality(&self, anchor: usize) -> usize {
        self.slot_gates
            .of_anchor(anchor)
            .iter()
            .filter(|&&g| g)
            .count()
    }

    /// Anchors per cardinality: entry c counts the anchors with c active slots (0..=K).
    pub fn cardinality_histogram(&self) -> Vec<usize> {
        let mut histogram = vec![0; self.dims.slots + 1];
        for a in 0..self.len() {
            histogram[self.cardinality(a)] += 1;
        }
        histogram
    }

    /// Per anchor: whether F_adapt is masked off (always false when masking is off).
    pub fn adapt_masked(&self) -> Vec<bool> {
        match self.dims.feature_masking {
            FeatureMasking::Off => vec![false; self.len()],
            FeatureMasking::Adaptive { threshold, .. } => self
                .host(Column::MaskLogits)
                .into_iter()
                .map(|m| super::feature_mask::is_masked(m, threshold))
                .collect(),
        }
    }

    /// Fraction of anchors whose F_adapt is masked off, the paper's masking ratio (0 when
    /// masking is off).
    pub fn masking_ratio(&self) -> f64 {
        match self.dims.feature_masking {
            FeatureMasking::Off => 0.0,
            FeatureMasking::Adaptive { threshold, .. } => {
                super::feature_mask::masking_ratio(&self.host(Column::MaskLogits), threshold)
            }
        }
    }

    /// Feature channels each anchor uses (C_F, or F_base alone when its mask is off).
    pub fn active_feature_channels(&self) -> Vec<usize> {
        let d = self.dims;
        let base = match d.feature_masking {
            FeatureMasking::Off => d.feature_dim,
            FeatureMasking::Adaptive { base, .. } => base,
        };
        self.adapt_masked()
            .into_iter()
            .map(|masked| if masked { base } else { d.feature_dim })
            .collect()
    }

    /// Host copy of the [N, 6] log-scales.
    pub fn log_scales_host(&self) -> Vec<f32> {
        self.host(Column::LogScales)
    }

    /// Bytes of the uncompressed stored model's anchors (spec §14 A22, the same bookkeeping for
    /// every arm): float32 positions, log-scales, factors, the feature stream, the offsets of
    /// active slots only and the features without masked-off F_adapt channels, plus the bitmaps a
    /// decoder needs to know which slots and channels are stored (1 bit per slot under adaptive
    /// cardinality, 1 bit per anchor under masking). This is the post-hoc model of the paper
    /// (§13.4): gated slots and masked channels are not stored.
    pub fn stored_bytes(&self) -> usize {
        let d = self.dims;
        let n = self.len();
        // Positions, then every column: whole rows, but only active slots' offsets and kept
        // feature channels; the mask logits are the 1-bit bitmap below.
        let mut floats = n * 3;
        for c in Column::present(&d) {
            floats += match c {
                Column::Offsets => self.active_slot_count() * 3,
                Column::Features => self.active_feature_channels().iter().sum(),
                Column::MaskLogits => 0,
                Column::LogScales
                | Column::TimeFeatures
                | Column::Factors
                | Column::Trajectory
                | Column::Turn => n * c.width(&d).expect("present"),
            };
        }
        let mut bits = 0;
        // Fixed cardinality starts (and stays) with every slot active: no gate bitmap to store.
        if d.initial_active_slots < d.slots {
            bits += n * d.slots;
        }
        if matches!(d.feature_masking, FeatureMasking::Adaptive { .. }) {
            bits += n;
        }
        floats * 4 + bits.div_ceil(8)
    }
}

/// The rows `keep` of a row-major buffer of `width` values per row.
pub fn keep_row_values<T: Copy>(values: &[T], keep: &[usize], width: usize) -> Vec<T> {
    keep.iter()
        .flat_map(|&r| values[r * width..(r + 1) * width].iter().copied())
        .collect()
}
