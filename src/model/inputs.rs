//! Per-frame decoder inputs (spec §2.1, §4.2): the coarse-to-fine time-feature window and the
//! anchor gates.

use crate::raster::columns::{concat_columns, slice_columns};
use burn::tensor::{Device, Tensor, TensorData, s};

use crate::device_io::KeptUploads;

/// Half-width of the training window over the feature stream:
/// gap = int((T // 5) · (1 − min(1, 5·step / (max_steps − 1)))) — 12 frames at the start for
/// T = 60, shrinking to 0 at 20 % of training (GIFStream L647-L653). Evaluation uses gap 0.
pub fn time_window_gap(step: usize, max_steps: usize, frames: usize) -> usize {
    let progress = (5.0 * step as f64 / (max_steps.max(2) - 1) as f64).min(1.0);
    ((frames / 5) as f64 * (1.0 - progress)) as usize
}

/// Mean of `time_features[:, f − gap ..= f + gap]` (clipped to the stream) for frame index `f`
/// inside the GOP: [M, T, C] → [M, C].
pub fn windowed_time_feature(time_features: Tensor<3>, frame: usize, gap: usize) -> Tensor<2> {
    let [m, t, c] = time_features.dims();
    assert!(frame < t, "frame {frame} outside the {t}-frame stream");
    let (lo, hi) = (frame.saturating_sub(gap), (frame + gap + 1).min(t));
    time_features
        .slice(s![.., lo..hi, ..])
        .mean_dim(1)
        .reshape([m, c])
}

/// Mean over the frames of each row of a frame-major window of the stream, [M, F·C] → [M, C]:
/// [`windowed_time_feature`] for rows whose window columns were sliced out of the [N, T·C] stream
/// table. One frame is returned as it is; more as one product with an [F·C, C] averaging matrix
/// (a strided mean over frames costs more on ndarray).
pub fn frame_window_mean(window: Tensor<2>, channels: usize) -> Tensor<2> {
    let [_, width] = window.dims();
    assert!(
        channels > 0 && width % channels == 0,
        "a window of {width} columns is not whole frames of {channels} channels"
    );
    if width == channels {
        return window;
    }
    let average = averaging_matrix(width / channels, channels, &window.device());
    window.matmul(average)
}

/// The [F·C, C] matrix whose product with a frame-major row of F frames is the frames' mean,
/// uploaded once per (F, C, device) and kept (issue 21: a step uploads no table it sent before).
/// At most a few dozen exist in a run (F ranges over the window widths the schedule passes).
fn averaging_matrix(frames: usize, channels: usize, device: &Device) -> Tensor<2> {
    static KEPT: KeptUploads<(usize, usize), 2> = KeptUploads::new(256);
    KEPT.get((frames, channels), device, || {
        let width = frames * channels;
        let weight = 1.0 / frames as f32;
        let mut average = vec![0.0f32; width * channels];
        for f in 0..frames {
            for c in 0..channels {
                average[(f * channels + c) * channels + c] = weight;
            }
        }
        TensorData::new(average, [width, channels])
    })
}

/// Below this sigmoid value a gate is exactly 0.
pub const GATE_THRESHOLD: f32 = 0.1;

/// GIFStream's `fake_quantize_factors` without the quantisation step (that comes with the
/// compression simulation): v = sigmoid(raw) for the four per-anchor gates
/// [time-feature d, motion, kNN blend, pruning]; columns 0-2 are v, or 0 where v < 0.1;
/// column 3 is 0 where v < 0.1 and 1 elsewhere. Straight-through: the gradient is that of v.
pub fn activate_gates(raw: Tensor<2>) -> Tensor<2> {
    let v = crate::raster::activation::sigmoid(raw);
    // The hard values carry no gradient, so they are made from a detached copy: nothing below
    // enters the autodiff graph, and the columns are split with `slice_columns` (row copies)
    // instead of Burn's `slice` of a bool tensor, which ndarray copies element by element
    // through a dynamic-rank iterator (2.7 % of a CPU training step's samples, issue 21).
    // Same values, NaN included (a NaN gate is not below the threshold: kept, binary 1).
    let plain = v.clone().detach();
    let continuous = zero_below_threshold(slice_columns(plain.clone(), 0..3));
    let binary = slice_columns(plain.clone(), 3..4)
        .lower_elem(GATE_THRESHOLD)
        .bool_not()
        .float();
    let hard = concat_columns(continuous, binary);
    // Straight-through estimator: forward = hard, backward = identity on v.
    v + (hard - plain)
}

/// Column 0 of [`activate_gates`] (the time-feature gate d) alone, from the raw column [M, 1]:
/// v = sigmoid(raw), 0 where v < 0.1, with v's gradient (straight-through). For the neighbours'
/// gates, where only d is used: a quarter of the work of activating all four and slicing.
pub fn activate_continuous_gate(raw: Tensor<2>) -> Tensor<2> {
    let v = crate::raster::activation::sigmoid(raw);
    let plain = v.clone().detach();
    v + (zero_below_threshold(plain.clone()) - plain)
}

/// The hard value of a continuous gate: v, or 0 where v < [`GATE_THRESHOLD`] (NaN kept).
fn zero_below_threshold(v: Tensor<2>) -> Tensor<2> {
    v.clone().mask_fill(v.lower_elem(GATE_THRESHOLD), 0.0)
}
