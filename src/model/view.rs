//! Decoding the anchors for one view and frame (spec §4.1-§4.4): cull anchors against the camera,
//! assemble the decoder inputs (time-feature window, gates, canonical phase, kNN blend, γ(t)),
//! decode, and spawn the Neural Gaussians the rasterizer takes.

use crate::device_io::upload;
use crate::raster::columns::{concat_columns, slice_columns};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};

use super::anchors::{AnchorSet, AnchorTensors, Column, FeatureMasking};
use super::culling::{
    AnchorReach, FirstDrawnFrames, anchors_reaching_view, anchors_reaching_view_mask,
    visible_anchors,
};
use super::decoders::{DecodedAnchors, Decoders, TIME_EMBEDDING_DIM, time_embedding};
use super::feature_mask::{binary_mask, masked_features};
use super::inputs::{activate_continuous_gate, activate_gates, frame_window_mean};
use super::spawn::{SpawnInputs, spawn};
use crate::raster::gather::gather_rows;
use crate::raster::{GaussianTensors, RasterCamera};

/// Whether the time-dependent inputs are on (spec §4.2, "canonical phase").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Until step = max_steps · deformation_gate: time-feature gate 0, motion gate 0, kNN blend ½.
    Canonical,
    Dynamic,
}

/// Where and when to decode.
#[derive(Clone, Copy, Debug)]
pub struct ViewTime {
    /// Frame index inside the GOP, 0..T.
    pub frame: usize,
    /// Normalised time in [0, 1].
    pub time: f32,
    /// Half-width of the time-feature window (0 at evaluation).
    pub window_gap: usize,
    pub phase: Phase,
    /// Frequency bands of γ(t) the motion head sees ([`time_embedding`]'s coarse-to-fine
    /// window; [`ALL_TIME_BANDS`] at evaluation and in GIFStream).
    pub time_bands: f32,
}

/// Every band of γ(t): no coarse-to-fine window.
pub const ALL_TIME_BANDS: f32 = crate::model::decoders::TIME_EMBEDDING_FREQUENCIES as f32;

/// How anchors are culled against the camera before decoding.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum AnchorCulling {
    /// At the canonical (frame-0) position, ignoring motion, the anchor tested as a Gaussian of
    /// its offset scale (GIFStream, [`visible_anchors`]): an anchor that moved into view is
    /// culled, one that moved out is still decoded, and a Gaussian reaching beyond its anchor's
    /// box can be dropped.
    Canonical,
    /// At the position the motion gives for the frame (anchor + mf·Δxyz, decoded for every
    /// anchor without gradient first), with a bound on where the anchor's Gaussians can be
    /// ([`anchors_reaching_view`]): drops only anchors none of whose Gaussians the rasterizer
    /// would draw, so the render equals [`AnchorCulling::Off`]'s.
    Deformed,
    /// Every anchor is decoded (exact and slowest; the rasterizer still culls Gaussians): the
    /// reference the other modes are measured against.
    Off,
}

/// Where a training step culls its anchors (`train.step_culling`).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum StepCulling {
    /// Cull on the host, decode the visible rows ([`cull_anchors`], [`VisibleRows::Listed`]):
    /// one read-back of the motion and one upload of the row index per step.
    Host,
    /// Decode every row, mask the culled ones on the device ([`decode_all_masked`]): nothing
    /// read back or uploaded, shapes fixed between refinements. The default on every backend:
    /// on the CPU as fast as `Host` (`bench train`, docs/benchmarks.md, stop 61: the motion is
    /// decoded once instead of twice, the ~9 % culled rows are decoded in vain).
    Device,
}

impl StepCulling {
    /// Whether a step culls on the device under `culling` (the canonical box test has no device
    /// form).
    pub fn on_device(self, culling: AnchorCulling) -> bool {
        self == Self::Device && culling != AnchorCulling::Canonical
    }
}

/// The anchors' raw motion [M, 7] with their trajectory translation at the frame added to the
/// first three columns (the motion gate scales both, in [`spawn`]).
///
/// Deviation from GIFStream (docs/results.md, "Moving objects"): its only motion is the shared
/// motion head, a 2-layer MLP of the anchor feature and γ(t). On a 1600-step schedule it does not
/// learn an object's large displacement (a sphere crossing 4 units moved 0.0 units; with the
/// temporal curriculum, boosted rates or no time features still < 0.15), because one small MLP,
/// with time entering additively, must separate that object's anchors from all others before
/// any of them can move, while per-Gaussian parameters smear the object first. A per-anchor
/// trajectory gets its gradient directly, so each anchor follows its own object (default run on
/// synthetic:fast: moving pixels 16.6 → 24.3 dB decoded, the sphere present in every frame).
fn with_trajectory(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    index: Tensor<1, Int>,
    frame: usize,
    motion: Tensor<2>,
) -> Tensor<2> {
    let Some(table) = tensors.trajectory() else {
        return motion;
    };
    let along = at_frame(table, set.dims.trajectory_spacing, index, frame);
    concat_columns(
        slice_columns(motion.clone(), 0..3) + along,
        slice_columns(motion, 3..7),
    )
}

/// Rows `index` of a knot table ([N, knots·3], a knot every `spacing` frames) at `frame`: linear
/// between knot ⌊f/s⌋ and the next, weight w = (f mod s)/s on the next, as two column slices of
/// the gathered rows (no host-built interpolation matrix, no matmul). [M, 3].
fn at_frame(table: Tensor<2>, spacing: usize, index: Tensor<1, Int>, frame: usize) -> Tensor<2> {
    let (knot, w) = (frame / spacing, (frame % spacing) as f32 / spacing as f32);
    let rows = gather_rows(table, index);
    let along = slice_columns(rows.clone(), knot * 3..knot * 3 + 3);
    if w > 0.0 {
        along * (1.0 - w) + slice_columns(rows, (knot + 1) * 3..(knot + 2) * 3) * w
    } else {
        along
    }
}

/// The anchors' trajectory turn at the frame, [M, 3] rotation vectors before the motion gate
/// (which [`spawn`] applies, as to the translation), when the trajectories turn.
///
/// Deviation from GIFStream (docs/results.md, "Moving objects", Follow-up 20): its only rotation
/// is the motion head's, R(normalize(0.1·Δq + (1, 0, 0, 0))), which turns the offsets but not the
/// Gaussians, and which one shared MLP must learn per object. On `synthetic:crossing` (a cube
/// turning 180°) it turned the cube's slots by a constant 5° while the knots carried the anchors
/// along the cube's centre: the faces' Gaussians kept their frame-0 layout. With the cube's true
/// paths and turns imposed (`examples/oracle_motion.rs`) the turns are worth +1.2 dB on its
/// pixels; trained by the gradient, even on the true paths, they do not find its turn (+0.1 dB,
/// file +20 %), so `model.trajectory_turn` is off by default until the turns are fitted.
fn turn_at(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    index: Tensor<1, Int>,
    frame: usize,
) -> Option<Tensor<2>> {
    let table = tensors.turn()?;
    Some(at_frame(table, set.dims.trajectory_spacing, index, frame))
}

/// Which anchors a decode's M rows are and which of them are visible.
#[derive(Clone, Debug)]
pub enum VisibleRows {
    /// The rows are these anchors (ascending), culled on the host: all visible.
    Listed(Vec<u32>),
    /// Every anchor is a row, in order, and [N] holds 1.0 where the anchor can reach the view,
    /// 0.0 where it cannot (culled on the device: the decode's shapes do not wait for a
    /// read-back). A culled row's opacity is 0, so it spawns nothing.
    Masked(Tensor<1>),
}

impl VisibleRows {
    /// The number of decoded rows M.
    pub fn rows(&self) -> usize {
        match self {
            Self::Listed(visible) => visible.len(),
            Self::Masked(mask) => mask.dims()[0],
        }
    }

    /// The anchor decoded in row `row`.
    pub fn anchor_of_row(&self, row: usize) -> u32 {
        match self {
            Self::Listed(visible) => visible[row],
            Self::Masked(_) => row as u32,
        }
    }

    /// The visible rows' count, on the device ([1]).
    pub fn count(&self, device: &Device) -> Tensor<1> {
        match self {
            Self::Listed(visible) => Tensor::full([1], visible.len() as f32, device),
            Self::Masked(mask) => mask.clone().sum(),
        }
    }

    /// [M] 1.0 per visible row and 0.0 per culled one, on `device`.
    pub fn weights(&self, device: &Device) -> Tensor<1> {
        match self {
            Self::Listed(visible) => Tensor::ones([visible.len()], device),
            Self::Masked(mask) => mask.clone(),
        }
    }

    /// The mean of `values` [M, C] over the visible rows' elements (the plain mean when every
    /// row is visible; 0 when none is). A culled row's values do not enter, not even as 0·NaN.
    pub fn mean(&self, values: Tensor<2>) -> Tensor<1> {
        match self {
            Self::Listed(_) => values.mean(),
            Self::Masked(mask) => {
                let c = values.dims()[1];
                let count = mask.clone().sum().clamp_min(1.0).mul_scalar(c as f32);
                values.mask_fill(culled_rows(mask, c), 0.0).sum() / count
            }
        }
    }

    /// The mean of `values` [M, K·`width`] (K slots of `width` columns each, slot-major) over
    /// the visible rows' *active* slots: `slot_gates` [M, K] holds 1.0 where a slot is on and
    /// 0.0 where AAC switched it off. The mean is 0 when no visible row has an active slot; with
    /// every gate 1.0 it is [`Self::mean`].
    pub fn mean_over_slots(
        &self,
        values: Tensor<2>,
        slot_gates: Tensor<2>,
        width: usize,
    ) -> Tensor<1> {
        let [m, k] = slot_gates.dims();
        assert_eq!(values.dims(), [m, k * width], "values are [M, K·width]");
        let (values, gates) = match self {
            Self::Listed(_) => (values, slot_gates),
            Self::Masked(mask) => (
                values.mask_fill(culled_rows(mask, k * width), 0.0),
                slot_gates * mask.clone().reshape([m, 1]).expand([m, k]),
            ),
        };
        let weights = gates
            .clone()
            .reshape([m, k, 1])
            .expand([m, k, width])
            .reshape([m, k * width]);
        (values * weights).sum() / gates.sum().clamp_min(1.0).mul_scalar(width as f32)
    }

    /// The same rows with the mask outside any autodiff context (for a plain decode).
    pub fn inner(&self) -> Self {
        match self {
            Self::Listed(visible) => Self::Listed(visible.clone()),
            Self::Masked(mask) => Self::Masked(mask.clone().inner()),
        }
    }
}

/// [M, columns] true on the rows a [`VisibleRows::Masked`] mask culls: filled (not multiplied by
/// 0) so that a culled row's non-finite value, which the host culling never decoded, stays out.
fn culled_rows(mask: &Tensor<1>, columns: usize) -> Tensor<2, Bool> {
    let m = mask.dims()[0];
    mask.clone()
        .lower_elem(0.5)
        .reshape([m, 1])
        .expand([m, columns])
}

/// What one decode produced.
#[derive(Clone, Debug)]
pub struct DecodedView {
    /// Which anchors the M rows are (Gaussian row i·K + k belongs to anchor
    /// `visible.anchor_of_row(i)`) and which are visible.
    pub visible: VisibleRows,
    /// [M] the decode's row index on the device (the listed anchors, or every anchor).
    pub visible_index: Tensor<1, Int>,
    /// Decoder outputs; `opacity` already multiplied by the pruning gate and the AAC slot gates
    /// (and 0 on a masked decode's culled rows, as `slot_opacity`).
    pub decoded: DecodedAnchors,
    /// [M, K] the opacity before the slot gates (equal to `decoded.opacity` on active slots):
    /// what a free slot would show if it were switched on, which AAC's importance gathers.
    pub slot_opacity: Tensor<2>,
    /// [M, 4] activated gates of the decoded anchors (before the canonical override).
    pub gates: Tensor<2>,
    pub gaussians: GaussianTensors,
}

fn index_tensor(indices: &[u32], device: &Device) -> Tensor<1, Int> {
    upload::<1, Int>(
        TensorData::new(
            indices.iter().map(|&i| i as i64).collect::<Vec<_>>(),
            [indices.len()],
        ),
        device,
    )
}

/// The decoder inputs of some anchors (rows `index` of the set) at one view time.
struct DecoderInputs {
    /// [M, C_F + C_T] the attribute decoders' input.
    attr: Tensor<2>,
    /// [M, C_F + C_T + 16] the motion head's input.
    motion_input: Tensor<2>,
    /// [M, 4] activated gates (before the canonical override).
    gates: Tensor<2>,
    /// [M, 1] the motion gate after the canonical override.
    motion_gate: Tensor<2>,
}

/// The masked feature table (AAFM) every decoder and the kNN average see.
fn feature_table(set: &AnchorSet, tensors: &AnchorTensors) -> Tensor<2> {
    match set.dims.feature_masking {
        FeatureMasking::Off => tensors.features(),
        FeatureMasking::Adaptive { base, threshold } => masked_features(
            tensors.features(),
            binary_mask(tensors.mask_logits(), threshold),
            base,
        ),
    }
}

fn decoder_inputs(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    index: Tensor<1, Int>,
    when: ViewTime,
) -> DecoderInputs {
    let d = set.dims;
    let device = tensors.device();
    let m = index.dims()[0];
    let feature_table = feature_table(set, tensors);
    let features = gather_rows(feature_table.clone(), index.clone());
    let (lo, hi) = (
        when.frame.saturating_sub(when.window_gap),
        (when.frame + when.window_gap + 1).min(d.frames),
    );
    // The window's columns of the stream, [N, (hi − lo)·C_T], sliced once for both the anchors'
    // own window and the neighbours' frame: the forward then reads only those frames, and the
    // backward is a single zero-padding back to [N, T·C_T] (it was a product with a
    // [T·C_T, C_T] averaging matrix over every frame, forward and backward, of every row).
    let c_t = d.time_feature_dim;
    let stream_table = tensors.get(Column::TimeFeatures); // [N, T·C_T]
    let window_table = slice_columns(stream_table, lo * c_t..hi * c_t);
    // Mean of the window (GIFStream L647-L653); one frame (gap 0, 80 % of training and every
    // evaluation) is the frame itself.
    let stream = frame_window_mean(gather_rows(window_table.clone(), index.clone()), c_t);
    let gates = activate_gates(gather_rows(tensors.factors(), index.clone()));
    let column = |c: usize| slice_columns(gates.clone(), c..c + 1); // [M, 1]
    let (time_gate, motion_gate, knn_blend) = match when.phase {
        Phase::Canonical => (
            Tensor::<2>::zeros([m, 1], &device),
            Tensor::<2>::zeros([m, 1], &device),
            Tensor::<2>::full([m, 1], 0.5, &device),
        ),
        Phase::Dynamic => (column(0), column(1), column(2)),
    };
    let attr = concat_columns(features.clone(), stream * time_gate);

    let blended = if d.knn > 0 {
        let k = d.knn;
        // The rows' neighbours, gathered on the device from the set's table.
        let nindex = match set.neighbors_of(index.clone()) {
            Some(nindex) => nindex,
            None => {
                assert_eq!(m, 0, "the neighbour lists were never built");
                index.clone()
            }
        };
        let knn_features = gather_rows(feature_table, nindex.clone())
            .reshape([m, k, d.feature_dim])
            .mean_dim(1)
            .reshape([m, d.feature_dim]);
        let knn_stream = match when.phase {
            // The neighbours' stream is multiplied by 0 in the canonical phase.
            Phase::Canonical => Tensor::zeros([m, d.time_feature_dim], &device),
            // Neighbours' frame-f feature (no window) times their own time gate.
            Phase::Dynamic => {
                let at_frame = (when.frame - lo) * c_t;
                let frame_features = slice_columns(window_table, at_frame..at_frame + c_t);
                let neighbor_gate = activate_continuous_gate(slice_columns(
                    gather_rows(tensors.factors(), nindex.clone()),
                    0..1,
                ));
                (gather_rows(frame_features, nindex) * neighbor_gate)
                    .reshape([m, k, d.time_feature_dim])
                    .mean_dim(1)
                    .reshape([m, d.time_feature_dim])
            }
        };
        let knn = concat_columns(knn_features, knn_stream);
        attr.clone() * knn_blend.clone() + knn * (-knn_blend + 1.0)
    } else {
        attr.clone()
    };
    let gamma = time_embedding(when.time, when.time_bands, &device)
        .reshape([1, TIME_EMBEDDING_DIM])
        .expand([m, TIME_EMBEDDING_DIM]);
    DecoderInputs {
        attr,
        motion_input: concat_columns(blended, gamma),
        gates,
        motion_gate,
    }
}

/// Where every anchor is at `when`: its canonical position plus its gated translation
/// mf·Δxyz (the canonical position itself in the canonical phase). Decoded without gradient
/// from `tensors` (the set's plain values), for motion-aware culling.
pub fn deformed_positions(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    when: ViewTime,
) -> Vec<[f32; 3]> {
    if !anchors_move(set, when) {
        return set.positions.clone();
    }
    let translation = all_anchor_motion(set, tensors, decoders, when).translation;
    moved_by(set, &super::anchors::host_values(&translation), 3)
}

/// Whether `set` has anchors that the motion head moves at `when` (the dynamic phase).
fn anchors_move(set: &AnchorSet, when: ViewTime) -> bool {
    when.phase == Phase::Dynamic && !set.is_empty()
}

/// `set`'s canonical positions moved by the translations in columns 0..3 of a row-major host
/// table of `width` columns.
fn moved_by(set: &AnchorSet, table: &[f32], width: usize) -> Vec<[f32; 3]> {
    set.positions
        .iter()
        .zip(table.chunks_exact(width))
        .map(|(p, t)| [p[0] + t[0], p[1] + t[1], p[2] + t[2]])
        .collect()
}

/// Where every anchor is at `when` and how far its Gaussians reach, for
/// [`AnchorCulling::Deformed`] culling: with `translation` (the [N, 3] gated translations of a
/// dynamic-phase decode) both come back in ONE read-back of an [N, 5] table (a
/// synchronisation per step fewer on a GPU than reading them apart).
fn placed_with_reach(
    set: &AnchorSet,
    translation: Option<Tensor<2>>,
) -> (Vec<[f32; 3]>, AnchorReach) {
    match translation {
        Some(translation) if !set.is_empty() => {
            let table = concat_columns(translation, AnchorReach::on_device(set));
            let table = super::anchors::host_values(&table);
            (
                moved_by(set, &table, 5),
                AnchorReach::from_rows(&table, 5, 3),
            )
        }
        _ => (set.positions.clone(), AnchorReach::of(set)),
    }
}

/// The decoder inputs and the motion of every anchor at `when`, and the translation it applies.
struct AllAnchorMotion {
    inputs: DecoderInputs,
    /// [N, 7] raw motion with the trajectory added.
    motion: Tensor<2>,
    /// [N, 3] gated translation mf·Δxyz.
    translation: Tensor<2>,
}

fn all_anchor_motion(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    when: ViewTime,
) -> AllAnchorMotion {
    // Every row, in order: made by the backend (on a GPU on the device), not uploaded.
    let index = Tensor::<1, Int>::arange(0..set.len() as i64, &tensors.device());
    let inputs = decoder_inputs(set, tensors, index.clone(), when);
    let motion = with_trajectory(
        set,
        tensors,
        index,
        when.frame,
        decoders.motion.forward(inputs.motion_input.clone()),
    );
    let translation = slice_columns(motion.clone(), 0..3) * inputs.motion_gate.clone();
    AllAnchorMotion {
        inputs,
        motion,
        translation,
    }
}

/// The anchors to decode for `camera` at `when` under `culling` (their indices, ascending).
pub fn cull_anchors(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    camera: &RasterCamera,
    when: ViewTime,
    culling: AnchorCulling,
) -> Vec<u32> {
    match culling {
        AnchorCulling::Canonical => visible_anchors(&set.positions, &set.log_scales_host(), camera),
        AnchorCulling::Deformed => {
            let translation = anchors_move(set, when)
                .then(|| all_anchor_motion(set, tensors, decoders, when).translation);
            let (centres, reach) = placed_with_reach(set, translation);
            anchors_reaching_view(&centres, &reach, camera)
        }
        AnchorCulling::Off => (0..set.len() as u32).collect(),
    }
}

/// Culls and decodes without a second motion decode: under [`AnchorCulling::Deformed`] the
/// motion of every anchor, which the culling needs, is decoded once and its visible rows reused
/// (culling then [`decode_view`] decodes it for all anchors and again for the visible ones: on
/// the default synthetic:fast run that path is 1.23× slower per view, docs/benchmarks.md).
/// For plain tensors (evaluation, `render`); a training step decodes tracked, quantised values
/// with [`decode_all_masked`] (or, culling on the host, [`cull_anchors`] on the plain values +
/// [`decode_view`]).
pub fn cull_and_decode(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    camera: &RasterCamera,
    when: ViewTime,
    culling: AnchorCulling,
) -> DecodedView {
    if culling != AnchorCulling::Deformed || !anchors_move(set, when) {
        let visible = cull_anchors(set, tensors, decoders, camera, when, culling);
        return decode_view(set, tensors, decoders, visible, when);
    }
    let all = all_anchor_motion(set, tensors, decoders, when);
    let (centres, reach) = placed_with_reach(set, Some(all.translation));
    let visible = anchors_reaching_view(&centres, &reach, camera);
    let index = index_tensor(&visible, &tensors.device());
    let rows = RowInputs::decoded(all.inputs, all.motion, |t| gather_rows(t, index.clone()));
    let visible = VisibleRows::Listed(visible);
    decode_rows(set, tensors, decoders, visible, index, rows, when)
}

/// Decodes the `visible` anchors at `when`. `tensors` are the set's tensors, tracked for training
/// or plain for evaluation; `decoders` must live on the same kind of device.
pub fn decode_view(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    visible: Vec<u32>,
    when: ViewTime,
) -> DecodedView {
    let index = index_tensor(&visible, &tensors.device());
    decode_view_rows(
        set,
        tensors,
        decoders,
        VisibleRows::Listed(visible),
        index,
        when,
    )
}

/// Decodes every anchor of `set` at `when` and marks on the device which of them `culling`
/// keeps for `camera` ([`VisibleRows::Masked`]): nothing is read back and nothing uploaded,
/// and the shapes change only when the anchor set does, where culling on the host first
/// ([`cull_anchors`]) waits for a read-back of the motion and uploads the list.
///
/// The motion is decoded once, for the decode and the culling both, and the reach test
/// ([`anchors_reaching_view_mask`]) sees the values the rasterizer draws (`tensors`, in training
/// the quantisation-simulated ones; the host path culls on the plain values). Under
/// [`AnchorCulling::Deformed`] culling changes no pixel, so masking instead of dropping leaves
/// the render as it was; what the visible set still decides is which rows the regularisers
/// average over and which anchors the statistics count as seen.
///
/// [`AnchorCulling::Canonical`] (GIFStream's box test) has no device form: it stays on the host.
///
/// `first_frames` masks too the anchors held back from `when`'s frame (they draw nothing).
pub fn decode_all_masked(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    camera: &RasterCamera,
    when: ViewTime,
    culling: AnchorCulling,
    first_frames: Option<&FirstDrawnFrames>,
) -> DecodedView {
    assert_ne!(
        culling,
        AnchorCulling::Canonical,
        "the canonical box test culls on the host"
    );
    assert!(!set.is_empty(), "an empty set has no rows to mask");
    let all = all_anchor_motion(set, tensors, decoders, when);
    let n = set.len();
    let index = Tensor::<1, Int>::arange(0..n as i64, &tensors.device());
    let mask = match culling {
        AnchorCulling::Off => Tensor::ones([n], &tensors.device()),
        _ => {
            let centres = set.position_tensor.clone() + all.translation.clone().detach();
            let reach = AnchorReach::of_columns(
                tensors.log_scales().detach(),
                tensors.get(Column::Offsets).detach(),
                set.dims.slots,
            );
            anchors_reaching_view_mask(centres, reach, camera)
        }
    };
    let mask = match first_frames {
        Some(first) => {
            assert_eq!(first.len(), n, "one first frame per anchor");
            mask * first.mask(when.frame)
        }
        None => mask,
    };
    let rows = RowInputs::decoded(all.inputs, all.motion, |t| t);
    decode_rows(
        set,
        tensors,
        decoders,
        VisibleRows::Masked(mask),
        index,
        rows,
        when,
    )
}

/// [`decode_view`] with `visible` already on the device as `index` (e.g. another frame of a
/// decode's rows, [`DecodedView::visible_index`]): nothing uploaded.
pub fn decode_view_rows(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    visible: VisibleRows,
    index: Tensor<1, Int>,
    when: ViewTime,
) -> DecodedView {
    assert_eq!(index.dims(), [visible.rows()], "one index per decoded row");
    let inputs = decoder_inputs(set, tensors, index.clone(), when);
    let rows = RowInputs {
        attr: inputs.attr,
        gates: inputs.gates,
        motion_gate: inputs.motion_gate,
        motion: RowMotion::Decode(inputs.motion_input),
    };
    decode_rows(set, tensors, decoders, visible, index, rows, when)
}

/// The motion of the rows being decoded.
enum RowMotion {
    /// To decode: the motion head's [M, C_F + C_T + 16] input.
    Decode(Tensor<2>),
    /// Decoded already ([M, 7], trajectory added).
    Decoded(Tensor<2>),
}

/// What [`decode_rows`] takes (see [`DecoderInputs`]).
struct RowInputs {
    attr: Tensor<2>,
    gates: Tensor<2>,
    motion_gate: Tensor<2>,
    motion: RowMotion,
}

impl RowInputs {
    /// The rows `take` selects (a gather, or every row as it is) of inputs and a motion decoded
    /// for all anchors.
    fn decoded(
        inputs: DecoderInputs,
        motion: Tensor<2>,
        take: impl Fn(Tensor<2>) -> Tensor<2>,
    ) -> Self {
        Self {
            attr: take(inputs.attr),
            gates: take(inputs.gates),
            motion_gate: take(inputs.motion_gate),
            motion: RowMotion::Decoded(take(motion)),
        }
    }
}

/// The decode of rows `visible` (`index` on the device) from their inputs.
fn decode_rows(
    set: &AnchorSet,
    tensors: &AnchorTensors,
    decoders: &Decoders,
    visible: VisibleRows,
    index: Tensor<1, Int>,
    rows: RowInputs,
    when: ViewTime,
) -> DecodedView {
    let d = set.dims;
    let m = visible.rows();
    let RowInputs {
        attr,
        gates,
        motion_gate,
        motion,
    } = rows;
    let prune_gate = slice_columns(gates.clone(), 3..4);

    let mut decoded = match motion {
        RowMotion::Decoded(motion) => decoders.forward_with_motion(attr, motion),
        RowMotion::Decode(motion_input) => {
            let mut decoded = decoders.forward(attr, motion_input);
            decoded.motion =
                with_trajectory(set, tensors, index.clone(), when.frame, decoded.motion);
            decoded
        }
    };
    // α ← α · pf (spec §4.4 step 1): the pruning gate removes whole anchors.
    decoded.opacity = decoded.opacity * prune_gate.clone();
    // A masked decode's culled rows: opacity 0, so they spawn nothing, gather no importance and
    // count as unseen (what dropping them from the decode did).
    if let VisibleRows::Masked(mask) = &visible {
        decoded.opacity = decoded.opacity.mask_fill(culled_rows(mask, d.slots), 0.0);
    }
    let slot_opacity = decoded.opacity.clone();
    // α' = g · α (ACA-GS AAC, spec §12.1): a gated slot has opacity exactly 0, so spawn never
    // hands it to the rasterizer and no gradient reaches its offset or its decoder outputs.
    // The rows' gates come from the set's device mirror (none while every slot is active).
    if let Some(all_gates) = set.slot_gates.mirror() {
        decoded.opacity = decoded.opacity * gather_rows(all_gates.clone(), index.clone());
    }

    let scales = gather_rows(tensors.log_scales(), index.clone()).exp();
    // s[3:6] ← s[3:6] · pf (GIFStream L714).
    let scales = concat_columns(
        slice_columns(scales.clone(), 0..3),
        slice_columns(scales, 3..6) * prune_gate,
    );
    let inputs = SpawnInputs {
        turn: turn_at(set, tensors, index.clone(), when.frame),
        anchors: gather_rows(set.position_tensor.clone(), index.clone()),
        offsets: gather_rows(tensors.get(Column::Offsets), index.clone()).reshape([m, d.slots, 3]),
        scales,
        motion_gate: motion_gate.reshape([m]),
    };
    let gaussians = spawn(&inputs, &decoded);
    DecodedView {
        visible,
        visible_index: index,
        decoded,
        slot_opacity,
        gates,
        gaussians,
    }
}
