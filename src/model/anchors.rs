//! The anchor set: every per-anchor tensor, its Adam state, the densification statistics and the
//! neighbour lists, in one structure whose rows grow and shrink together (spec §2.1, §8, §19).
//!
//! Values live on the plain (non-autodiff) device; a training step takes tracked copies
//! ([`AnchorSet::tracked`]) and hands the gradients back to [`AnchorSet::adam_step`].

use burn::tensor::{Device, Gradients, Int, Tensor, TensorData};

use super::feature_mask::INITIAL_MASK_LOGIT;
use super::init::{initial_log_scales, nearest_neighbors, voxelize};
use crate::train::row_adam::{AdamConfig, RowAdam};

/// Raw logit of the initial legacy quantities; factors start at 0 (sigmoid 0.5: every gate open).
const INITIAL_FACTOR_LOGIT: f32 = 0.0;
/// Gates: [time-feature d, motion, kNN blend, pruning].
pub const FACTOR_COUNT: usize = 4;
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
}

/// One optimised per-anchor tensor and its Adam state.
#[derive(Clone, Debug)]
pub struct AnchorParam<const D: usize> {
    pub value: Tensor<D>,
    pub adam: RowAdam<D>,
}

impl<const D: usize> AnchorParam<D> {
    pub fn new(value: Tensor<D>, config: AdamConfig) -> Self {
        Self {
            adam: RowAdam::new(&value, config),
            value,
        }
    }

    /// Replaces the values (same shape, same device) with host values edited in place, e.g. by
    /// relocation or post-hoc pruning; the Adam state is untouched.
    pub fn set_values(&mut self, values: Vec<f32>) {
        let shape = self.value.dims();
        self.value = Tensor::<D>::from_data(TensorData::new(values, shape), &self.value.device());
    }

    fn append(&mut self, rows: Tensor<D>) {
        let count = rows.dims()[0];
        self.value = Tensor::cat(vec![self.value.clone(), rows], 0);
        self.adam.grow(count);
    }

    fn keep(&mut self, index: &Tensor<1, Int>, keep: &[usize]) {
        self.value = self.value.clone().select(0, index.clone());
        self.adam.keep_rows(keep);
    }

    fn step(&mut self, grad: Option<Tensor<D>>, lr: f64) {
        // A parameter the loss did not reach still takes an Adam step with a zero gradient, as
        // torch does for a parameter whose .grad is a zero tensor (the moments keep decaying).
        let grad = grad.unwrap_or_else(|| self.value.zeros_like());
        self.value = self.adam.step(self.value.clone(), grad, lr);
    }
}

impl AnchorParam<2> {
    /// [`Self::step`] with a rate per column (uniform rates take the scalar path).
    fn step_columns(&mut self, grad: Option<Tensor<2>>, lr: &[f64]) {
        match lr.first() {
            Some(&first) if lr.iter().any(|&r| r != first) => {
                let grad = grad.unwrap_or_else(|| self.value.zeros_like());
                self.value = self.adam.step_columns(self.value.clone(), grad, lr);
            }
            _ => self.step(grad, lr.first().copied().unwrap_or(0.0)),
        }
    }
}

/// Per-frame densification statistics (spec §8.1), host-side, row-major.
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

/// The rows of new anchors (densification), host-side.
#[derive(Clone, Debug, Default)]
pub struct NewAnchors {
    pub positions: Vec<[f32; 3]>,
    /// [n, 6]
    pub log_scales: Vec<f32>,
    /// [n, C_F]
    pub features: Vec<f32>,
    /// [n, T, C_T]
    pub time_features: Vec<f32>,
    /// [n, 4]
    pub factors: Vec<f32>,
    /// [n] AAFM mask logits.
    pub mask_logits: Vec<f32>,
    /// Training step that creates these rows (young anchors are spared by AAC's dead test).
    pub created_at: usize,
    /// [n, knots, 3] trajectory knots (empty when the set has no trajectories).
    pub trajectory: Vec<f32>,
}

impl NewAnchors {
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }
}

/// Tracked (autodiff, require-grad) copies of the optimised tensors for one step.
#[derive(Clone, Debug)]
pub struct AnchorTensors {
    pub log_scales: Tensor<2>,
    pub offsets: Tensor<3>,
    pub features: Tensor<2>,
    pub time_features: Tensor<3>,
    pub factors: Tensor<2>,
    /// [N, 1]
    pub mask_logits: Tensor<2>,
    /// [N, knots·3] trajectory knots, when the set has them.
    pub trajectory: Option<Tensor<2>>,
}

/// Learning rates of the per-anchor groups at one step.
#[derive(Clone, Debug, PartialEq)]
pub struct AnchorLearningRates {
    pub log_scales: f64,
    pub offsets: f64,
    pub features: f64,
    pub time_features: f64,
    pub factors: f64,
    /// `None`: the mask logits are not optimised (masking off).
    pub mask_logits: Option<f64>,
    /// One rate per trajectory knot (`lr.trajectory_schedule`).
    pub trajectory: Vec<f64>,
}

#[derive(Clone, Debug)]
pub struct AnchorSet {
    pub dims: AnchorDims,
    /// World positions on the voxel grid; fixed (GIFStream lr 0).
    pub positions: Vec<[f32; 3]>,
    /// The same positions as a [N, 3] tensor.
    pub position_tensor: Tensor<2>,
    /// [N, 6] log-scales.
    pub log_scales: AnchorParam<2>,
    /// [N, K, 3] offsets in units of exp(log_scales[:, 0:3]).
    pub offsets: AnchorParam<3>,
    /// [N, C_F]
    pub features: AnchorParam<2>,
    /// [N, T, C_T] the per-frame feature stream.
    pub time_features: AnchorParam<3>,
    /// [N, 4] raw gate logits.
    pub factors: AnchorParam<2>,
    /// [N, 1] AAFM mask logits m (kept, but neither used nor optimised, when masking is off).
    pub mask_logits: AnchorParam<2>,
    /// [N, knots·3] the anchor trajectories: translations at frames 0, s, 2s, … (s =
    /// `dims.trajectory_spacing`), linearly interpolated between knots and added to the motion
    /// head's translation (deviation from GIFStream, see `view.rs`). `None` without them.
    pub trajectory: Option<AnchorParam<2>>,
    /// [N · K] AAC slot gates g: a gated slot is never rasterized. A buffer, not a parameter.
    pub slot_gates: Vec<bool>,
    /// [N · K] AAC importance I: each slot's opacity summed since the last relocation.
    pub importance: Vec<f32>,
    /// [N] training views in which each anchor was visible since the last relocation.
    pub importance_visits: Vec<f32>,
    /// [N · K] slots the last AAC step relocated: the next one reports how many of them stayed
    /// below τ (relocation churn, docs/results.md).
    pub relocated: Vec<bool>,
    /// [N] step at which each anchor was created.
    pub created_at: Vec<u32>,
    pub stats: AnchorStats,
    /// [N · knn] nearest other anchors, recomputed whenever the rows change.
    pub neighbors: Vec<u32>,
}

fn tensor2(values: Vec<f32>, rows: usize, cols: usize, device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(values, [rows, cols]), device)
}

fn tensor3(values: Vec<f32>, shape: [usize; 3], device: &Device) -> Tensor<3> {
    Tensor::<3>::from_data(TensorData::new(values, shape), device)
}

/// Host copy of a tensor's values.
pub fn host_values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.clone()
        .into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("float tensor data")
}

impl AnchorSet {
    /// Anchors from a point cloud (spec §3): voxelised positions, log-scales from the 3 nearest
    /// anchors repeated ×6, zero offsets, features, streams and factors.
    pub fn from_points(
        points: &[[f32; 3]],
        voxel_size: f32,
        dims: AnchorDims,
        adam: AdamConfig,
        device: &Device,
    ) -> Self {
        let positions = voxelize(points, voxel_size);
        let scales: Vec<f32> = initial_log_scales(&positions)
            .into_iter()
            .flat_map(|s| [s; SCALE_DIMS])
            .collect();
        let n = positions.len();
        Self::from_rows(
            dims,
            NewAnchors {
                log_scales: scales,
                features: vec![0.0; n * dims.feature_dim],
                time_features: vec![0.0; n * dims.frames * dims.time_feature_dim],
                factors: vec![INITIAL_FACTOR_LOGIT; n * FACTOR_COUNT],
                mask_logits: vec![INITIAL_MASK_LOGIT; n],
                created_at: 0,
                trajectory: vec![0.0; n * dims.trajectory_width()],
                positions,
            },
            adam,
            device,
        )
    }

    /// An anchor set holding exactly these rows, zero offsets, fresh Adam state and statistics.
    pub fn from_rows(
        dims: AnchorDims,
        rows: NewAnchors,
        adam: AdamConfig,
        device: &Device,
    ) -> Self {
        let n = rows.len();
        let empty = |shape: [usize; 3]| tensor3(Vec::new(), shape, device);
        let mut set = Self {
            dims,
            positions: Vec::new(),
            position_tensor: tensor2(Vec::new(), 0, 3, device),
            log_scales: AnchorParam::new(tensor2(Vec::new(), 0, SCALE_DIMS, device), adam),
            offsets: AnchorParam::new(empty([0, dims.slots, 3]), adam),
            features: AnchorParam::new(tensor2(Vec::new(), 0, dims.feature_dim, device), adam),
            time_features: AnchorParam::new(empty([0, dims.frames, dims.time_feature_dim]), adam),
            factors: AnchorParam::new(tensor2(Vec::new(), 0, FACTOR_COUNT, device), adam),
            mask_logits: AnchorParam::new(tensor2(Vec::new(), 0, 1, device), adam),
            trajectory: (dims.trajectory_spacing > 0).then(|| {
                AnchorParam::new(
                    tensor2(Vec::new(), 0, dims.trajectory_width(), device),
                    adam,
                )
            }),
            slot_gates: Vec::new(),
            importance: Vec::new(),
            importance_visits: Vec::new(),
            relocated: Vec::new(),
            created_at: Vec::new(),
            stats: AnchorStats::default(),
            neighbors: Vec::new(),
        };
        if n > 0 {
            set.append(rows);
        }
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

    /// Appends rows with zero offsets, zero Adam state, zero statistics and importance, and the
    /// first `initial_active_slots` slots active; neighbours are recomputed.
    pub fn append(&mut self, rows: NewAnchors) {
        if !rows.is_empty() {
            self.append_without_neighbors(rows);
            self.rebuild_neighbors();
        }
    }

    /// [`AnchorSet::append`] leaving the neighbour lists stale: for callers that append several
    /// times in a row (densification levels) and rebuild once.
    pub(crate) fn append_without_neighbors(&mut self, rows: NewAnchors) {
        let n = rows.len();
        if n == 0 {
            return;
        }
        let d = self.dims;
        assert_eq!(rows.log_scales.len(), n * SCALE_DIMS, "log_scales rows");
        assert_eq!(rows.features.len(), n * d.feature_dim, "feature rows");
        assert_eq!(
            rows.time_features.len(),
            n * d.frames * d.time_feature_dim,
            "time-feature rows"
        );
        assert_eq!(rows.factors.len(), n * FACTOR_COUNT, "factor rows");
        assert_eq!(rows.mask_logits.len(), n, "mask-logit rows");
        assert_eq!(
            rows.trajectory.len(),
            n * d.trajectory_width(),
            "trajectory rows"
        );
        let device = self.device();
        let flat: Vec<f32> = rows.positions.iter().flatten().copied().collect();
        self.position_tensor = Tensor::cat(
            vec![self.position_tensor.clone(), tensor2(flat, n, 3, &device)],
            0,
        );
        self.positions.extend_from_slice(&rows.positions);
        self.log_scales
            .append(tensor2(rows.log_scales, n, SCALE_DIMS, &device));
        self.offsets
            .append(Tensor::<3>::zeros([n, d.slots, 3], &device));
        self.features
            .append(tensor2(rows.features, n, d.feature_dim, &device));
        self.time_features.append(tensor3(
            rows.time_features,
            [n, d.frames, d.time_feature_dim],
            &device,
        ));
        self.factors
            .append(tensor2(rows.factors, n, FACTOR_COUNT, &device));
        self.mask_logits
            .append(tensor2(rows.mask_logits, n, 1, &device));
        if let Some(t) = &mut self.trajectory {
            t.append(tensor2(rows.trajectory, n, d.trajectory_width(), &device));
        }
        for _ in 0..n {
            self.slot_gates
                .extend((0..d.slots).map(|k| k < d.initial_active_slots));
        }
        self.importance
            .extend(std::iter::repeat_n(0.0, n * d.slots));
        self.importance_visits.extend(std::iter::repeat_n(0.0, n));
        self.relocated
            .extend(std::iter::repeat_n(false, n * d.slots));
        let created_at = u32::try_from(rows.created_at).expect("step fits in u32");
        self.created_at.extend(std::iter::repeat_n(created_at, n));
        let (kt, t) = (n * d.slots * d.frames, n * d.frames);
        let s = &mut self.stats;
        s.offset_grad2d.extend(std::iter::repeat_n(0.0, kt));
        s.offset_visible_count.extend(std::iter::repeat_n(0.0, kt));
        s.opacity_accum.extend(std::iter::repeat_n(0.0, t));
        s.anchor_visible_count.extend(std::iter::repeat_n(0.0, t));
    }

    /// Keeps the listed rows, in that order (pruning); neighbours are recomputed.
    pub fn keep(&mut self, keep: &[usize]) {
        let d = self.dims;
        let n = self.len();
        assert!(keep.iter().all(|&r| r < n), "row out of range");
        let index = Tensor::<1, Int>::from_data(
            TensorData::new(
                keep.iter().map(|&r| r as i64).collect::<Vec<_>>(),
                [keep.len()],
            ),
            &self.device(),
        );
        self.positions = keep.iter().map(|&r| self.positions[r]).collect();
        self.position_tensor = self.position_tensor.clone().select(0, index.clone());
        self.log_scales.keep(&index, keep);
        self.offsets.keep(&index, keep);
        self.features.keep(&index, keep);
        self.time_features.keep(&index, keep);
        self.factors.keep(&index, keep);
        self.mask_logits.keep(&index, keep);
        if let Some(t) = &mut self.trajectory {
            t.keep(&index, keep);
        }
        fn rows<T: Copy>(v: &[T], keep: &[usize], width: usize) -> Vec<T> {
            keep.iter()
                .flat_map(|&r| v[r * width..(r + 1) * width].iter().copied())
                .collect()
        }
        self.slot_gates = rows(&self.slot_gates, keep, d.slots);
        self.importance = rows(&self.importance, keep, d.slots);
        self.importance_visits = rows(&self.importance_visits, keep, 1);
        self.relocated = rows(&self.relocated, keep, d.slots);
        self.created_at = rows(&self.created_at, keep, 1);
        let rows = |v: &Vec<f32>, width: usize| rows(v, keep, width);
        let s = &self.stats;
        self.stats = AnchorStats {
            offset_grad2d: rows(&s.offset_grad2d, d.slots * d.frames),
            offset_visible_count: rows(&s.offset_visible_count, d.slots * d.frames),
            opacity_accum: rows(&s.opacity_accum, d.frames),
            anchor_visible_count: rows(&s.anchor_visible_count, d.frames),
        };
        self.rebuild_neighbors();
    }

    /// k nearest other anchors of every anchor (spec §4.2: recomputed whenever N changes). With
    /// fewer than k others the list is padded with the nearest found (or the anchor itself).
    pub fn rebuild_neighbors(&mut self) {
        let k = self.dims.knn;
        if k == 0 {
            self.neighbors.clear();
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
    }

    /// Tracked copies of the optimised tensors on the autodiff `device`.
    pub fn tracked(&self) -> AnchorTensors {
        let t2 = |t: &Tensor<2>| t.clone().autodiff().require_grad();
        let t3 = |t: &Tensor<3>| t.clone().autodiff().require_grad();
        AnchorTensors {
            log_scales: t2(&self.log_scales.value),
            offsets: t3(&self.offsets.value),
            features: t2(&self.features.value),
            time_features: t3(&self.time_features.value),
            factors: t2(&self.factors.value),
            mask_logits: t2(&self.mask_logits.value),
            trajectory: self.trajectory.as_ref().map(|t| t2(&t.value)),
        }
    }

    /// Plain (untracked) views of the optimised tensors, for evaluation.
    pub fn untracked(&self) -> AnchorTensors {
        AnchorTensors {
            log_scales: self.log_scales.value.clone(),
            offsets: self.offsets.value.clone(),
            features: self.features.value.clone(),
            time_features: self.time_features.value.clone(),
            factors: self.factors.value.clone(),
            mask_logits: self.mask_logits.value.clone(),
            trajectory: self.trajectory.as_ref().map(|t| t.value.clone()),
        }
    }

    /// One Adam step of every per-anchor group from the gradients of `tracked`.
    pub fn adam_step(
        &mut self,
        tracked: &AnchorTensors,
        grads: &Gradients,
        lr: AnchorLearningRates,
    ) {
        self.log_scales
            .step(tracked.log_scales.grad(grads), lr.log_scales);
        self.offsets.step(tracked.offsets.grad(grads), lr.offsets);
        self.features
            .step(tracked.features.grad(grads), lr.features);
        self.time_features
            .step(tracked.time_features.grad(grads), lr.time_features);
        self.factors.step(tracked.factors.grad(grads), lr.factors);
        if let Some(lr) = lr.mask_logits {
            self.mask_logits.step(tracked.mask_logits.grad(grads), lr);
        }
        if let (Some(t), Some(tracked)) = (&mut self.trajectory, &tracked.trajectory) {
            // Three columns (x, y, z) per knot.
            let columns: Vec<f64> = lr.trajectory.iter().flat_map(|&r| [r; 3]).collect();
            assert_eq!(
                columns.len(),
                self.dims.trajectory_width(),
                "one rate per knot"
            );
            t.step_columns(tracked.grad(grads), &columns);
        }
    }

    /// Active (ungated) slots over all anchors.
    pub fn active_slot_count(&self) -> usize {
        self.slot_gates.iter().filter(|&&g| g).count()
    }

    /// Active slots of one anchor.
    pub fn cardinality(&self, anchor: usize) -> usize {
        let k = self.dims.slots;
        self.slot_gates[anchor * k..(anchor + 1) * k]
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
            FeatureMasking::Adaptive { threshold, .. } => host_values(&self.mask_logits.value)
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
                super::feature_mask::masking_ratio(&host_values(&self.mask_logits.value), threshold)
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

    /// Clears the AAC importance window.
    pub fn reset_importance(&mut self) {
        self.importance.fill(0.0);
        self.importance_visits.fill(0.0);
    }

    /// Host copy of the [N, 6] log-scales.
    pub fn log_scales_host(&self) -> Vec<f32> {
        host_values(&self.log_scales.value)
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
        let per_anchor =
            3 + SCALE_DIMS + FACTOR_COUNT + d.frames * d.time_feature_dim + d.trajectory_width();
        let channels: usize = self.active_feature_channels().iter().sum();
        let floats = n * per_anchor + self.active_slot_count() * 3 + channels;
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
