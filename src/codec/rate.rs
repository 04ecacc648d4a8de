//! The rate term of training (spec §9.3, §12.4, §13.1): the mean bits per attribute that the
//! conditional entropy models ([`super::entropy_models`]) predict for the quantised attributes
//! of one step, differentiable in both. The file format does not use this module; the coder
//! evaluates the same models on the host (`entropy_models::HostEntropyModels`).

use crate::device_io::upload;
use crate::raster::columns::slice_columns;
use acags_kernels::counter_noise::uniform_noise_like;
use crate::raster::activation::sigmoid;
use burn::tensor::{Tensor, TensorData, s};

use super::entropy::SCALE_MIN;
use super::entropy_models::{
    CONTEXT_LENGTH, EntropyModels, FEATURE_CHUNK, MIN_SCALE, TIME_RATE_GATE, feature_chunks,
};
use super::quantization::{NoiseKey, NoiseStream, QuantizationSteps};
use crate::config::TrajectoryRate;
use crate::model::anchors::{AnchorTensors, Column, FACTOR_COUNT, MOTION_GATE, SCALE_DIMS};
use crate::model::inputs::GATE_THRESHOLD;

/// Per-attribute mean bits of one training step.
#[derive(Clone, Debug)]
pub struct RateTerms {
    pub log_scales: Tensor<1>,
    pub offsets: Tensor<1>,
    pub factors: Tensor<1>,
    pub features: Tensor<1>,
    pub time_features: Tensor<1>,
    /// The trajectory knots' increments, when the set has trajectories and they are priced
    /// ([`RateInputs::trajectory`]).
    pub trajectory: Option<Tensor<1>>,
}

impl RateTerms {
    /// Σ_attr mean bits (GIFStream sums the per-attribute means, spec §18 item 8).
    pub fn total(&self) -> Tensor<1> {
        let total = self.log_scales.clone()
            + self.offsets.clone()
            + self.factors.clone()
            + self.features.clone()
            + self.time_features.clone();
        match &self.trajectory {
            Some(trajectory) => total + trajectory.clone(),
            None => total,
        }
    }
}

/// The values whose bits the training rate estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BitEstimate {
    /// The unquantised value / step plus one U(±½) draw: GIFStream's estimate.
    Unquantised,
    /// The simulated value (already noised or rounded) / step plus one more U(±½) draw (a
    /// triangular density in the noise phase, rounded then noised after). The default, a kept
    /// deviation: it prices values higher and measured a 15 % smaller file at no loss.
    Simulated,
}

/// What the rate needs besides the simulated attributes (the entropy models' contexts).
pub struct RateInputs<'a> {
    pub steps: &'a QuantizationSteps,
    /// F_base channels (C_F without feature masking).
    pub base_channels: usize,
    /// [N, 1] binary M (detached); None without masking.
    pub adapt_kept: Option<Tensor<2>>,
    /// [N, K] slot gates, 1.0 on active slots and 0.0 on gated ones (the anchor set's device
    /// mirror, `model::slot_gates`); None: every slot is active.
    pub slot_gates: Option<Tensor<2>>,
    /// Training frame (index inside the GOP).
    pub frame: usize,
    /// The unquantised attributes; their raw gate logits choose the time-feature subset.
    pub raw: &'a AnchorTensors,
    /// Whether the raw (GIFStream) or the simulated values are priced.
    pub bit_estimate: BitEstimate,
    /// Whether the trajectory knots are priced.
    pub trajectory: TrajectoryRate,
}

/// U(±½) shaped like `x`, drawn on its device (`acags_kernels::counter_noise`).
fn unit_noise(x: &Tensor<2>, key: NoiseKey) -> Tensor<2> {
    uniform_noise_like(x, key, 1.0)
}

/// −log2 of the probability of the unit bin around x under N(round(μ), σ²), with uniform noise
/// on x (GIFStream always noises inside the bit estimate): [rows, cols] bits.
pub fn gaussian_bits(
    x: Tensor<2>,
    mean: Tensor<2>,
    scale: Tensor<2>,
    noise: Tensor<2>,
) -> Tensor<2> {
    // One fused op (`acags_kernels::gaussian_bits`): the forward of
    // y = x − (μ + sg(round(μ) − μ)) + noise, σ = max(|scale|, MIN_SCALE),
    // −log2(½[erf((y + ½)/(σ√2)) − erf((y − ½)/(σ√2))] + 1e-5), with an analytic backward.
    acags_kernels::gaussian_bits::gaussian_bits(x, mean, scale, noise, MIN_SCALE)
}

fn weighted_mean(bits: Tensor<2>, weight: Tensor<2>) -> Tensor<1> {
    (bits * weight.clone()).sum() / weight.sum().clamp_min(1.0)
}

/// The rows `rows` of everything the rate reads: an unbiased estimate of the mean bits from a
/// random subset of anchors (`compression.rate_sample`; HAC estimates on 5 %, GIFStream on all).
pub fn sample_rows(
    sim: &AnchorTensors,
    raw: &AnchorTensors,
    adapt_kept: Option<&Tensor<2>>,
    slot_gates: Option<&Tensor<2>>,
    rows: &[u32],
) -> (
    AnchorTensors,
    AnchorTensors,
    Option<Tensor<2>>,
    Option<Tensor<2>>,
) {
    use crate::raster::gather::gather_rows;
    let device = sim.device();
    let index = upload::<1, burn::tensor::Int>(
        TensorData::new(
            rows.iter().map(|&r| r as i64).collect::<Vec<_>>(),
            [rows.len()],
        ),
        &device,
    );
    let m = rows.len();
    let take = |t: &Tensor<2>| gather_rows(t.clone(), index.clone());
    let take3 = |t: &Tensor<3>| {
        let [n, a, b] = t.dims();
        gather_rows(t.clone().reshape([n, a * b]), index.clone()).reshape([m, a, b])
    };
    let rows_of = |t: &AnchorTensors| t.map(|_, column| column.map(|x| take(&x), |x| take3(&x)));
    (
        rows_of(sim),
        rows_of(raw),
        adapt_kept.map(take),
        slot_gates.map(take),
    )
}

/// The rate of one training step over all anchors (spec §9.3, §12.4, §13.1). The entropy models'
/// contexts are the simulated attributes `sim` (what the decoder sees; the autoregressive ones not
/// detached); the priced values plus one uniform draw are chosen by `inputs.bit_estimate`: the
/// simulated `sim` (default) or the unquantised `inputs.raw` (GIFStream).
pub fn rate(
    models: &EntropyModels,
    sim: &AnchorTensors,
    inputs: &RateInputs,
    noise: NoiseStream,
) -> RateTerms {
    let device = sim.device();
    let [n, cf] = sim.features().dims();
    let [_, t, ct] = sim.time_features().dims();
    let [_, k, _] = sim.offsets().dims();
    let st = inputs.steps;
    let base = inputs.base_channels;
    let raw = inputs.raw;
    // The priced values: one U(±½) draw is added to them below.
    let coded_values = match inputs.bit_estimate {
        BitEstimate::Unquantised => raw,
        BitEstimate::Simulated => sim,
    };
    // A masked feature in index units.
    let masked_index = |f: &Tensor<2>| {
        let f_idx = f.clone() / st.features;
        match &inputs.adapt_kept {
            Some(m) => Tensor::cat(
                vec![
                    slice_columns(f_idx.clone(), 0..base),
                    slice_columns(f_idx, base..cf) * m.clone(),
                ],
                1,
            ),
            None => f_idx,
        }
    };
    let features = masked_index(&sim.features());
    let context = features.clone().detach();
    let split = |out: Tensor<2>, width: usize| {
        (
            slice_columns(out.clone(), 0..width),
            slice_columns(out, width..2 * width),
        )
    };

    let (mu, sigma) = split(models.log_scales.forward(context.clone()), SCALE_DIMS);
    // One noise tensor per attribute, drawn 0..=5 in this order.
    let x = coded_values.log_scales() / st.log_scales;
    let draw = unit_noise(&x, noise.key(0));
    let log_scales = gaussian_bits(x, mu, sigma, draw).mean();

    let (mu, sigma) = split(models.offsets.forward(context.clone()), 3 * k);
    let x = coded_values.get(Column::Offsets) / st.offsets;
    // A gated slot's offset is not coded: each slot's gate repeated over its 3 values, made
    // on the device (all ones while every slot is active).
    let gates = match &inputs.slot_gates {
        Some(g) => g
            .clone()
            .reshape([n, k, 1])
            .expand([n, k, 3])
            .reshape([n, 3 * k]),
        None => Tensor::ones([n, 3 * k], &device),
    };
    let draw = unit_noise(&x, noise.key(1));
    let offsets = weighted_mean(gaussian_bits(x, mu, sigma, draw), gates);

    let (mu, sigma) = split(models.factors.forward(context), FACTOR_COUNT);
    let x = match st.motion_gate {
        Some(g) if g != st.factors => sigmoid(coded_values.factors()) / gate_step_row(st, &device),
        _ => sigmoid(coded_values.factors()) / st.factors,
    };
    let draw = unit_noise(&x, noise.key(2));
    let factors = gaussian_bits(x, mu, sigma, draw).mean();

    // Channel-autoregressive features: chunk j from chunks j−3..j−1 (not detached).
    let chunks = feature_chunks(cf);
    let padded_width = chunks * FEATURE_CHUNK;
    let pad = |f: Tensor<2>| {
        if padded_width > cf {
            Tensor::cat(vec![f, Tensor::zeros([n, padded_width - cf], &device)], 1)
        } else {
            f
        }
    };
    let padded = pad(features);
    // The simulated estimate prices the context itself: no second mask and pad.
    let coded = match inputs.bit_estimate {
        BitEstimate::Simulated => padded.clone(),
        BitEstimate::Unquantised => pad(masked_index(&raw.features())),
    };
    let grid = Tensor::cat(
        vec![
            Tensor::<3>::zeros([n, CONTEXT_LENGTH, FEATURE_CHUNK], &device),
            padded.clone().reshape([n, chunks, FEATURE_CHUNK]),
        ],
        1,
    );
    let ar_context = Tensor::cat(
        (0..CONTEXT_LENGTH)
            .map(|d| grid.clone().slice(s![.., d..d + chunks, ..]))
            .collect(),
        2,
    )
    .reshape([n * chunks, CONTEXT_LENGTH * FEATURE_CHUNK]);
    let (mu, sigma) = split(models.features.forward(ar_context), FEATURE_CHUNK);
    let mu = mu.reshape([n, padded_width]);
    let sigma = sigma.reshape([n, padded_width]);
    let mut weight = vec![Tensor::<2>::ones([n, base.min(cf)], &device)];
    if cf > base {
        weight.push(match &inputs.adapt_kept {
            Some(m) => m.clone().expand([n, cf - base]),
            None => Tensor::ones([n, cf - base], &device),
        });
    }
    if padded_width > cf {
        weight.push(Tensor::zeros([n, padded_width - cf], &device));
    }
    let draw = unit_noise(&coded, noise.key(3));
    let features = weighted_mean(
        gaussian_bits(coded, mu, sigma, draw),
        Tensor::cat(weight, 1),
    );

    // Temporal-autoregressive stream: the training frame from the three before it. One column
    // slice of the [N, T·C_T] stream takes frames f−3..=f (those inside the stream), so the
    // backward pads one window into the stream instead of one [N, T, C_T] zero tensor per frame.
    let f = inputs.frame;
    assert!(f < t, "training frame {f} outside the {t}-frame stream");
    let first = f.saturating_sub(CONTEXT_LENGTH);
    let window = |values: &AnchorTensors, frames: std::ops::Range<usize>| {
        slice_columns(
            values.get(Column::TimeFeatures),
            frames.start * ct..frames.end * ct,
        ) / st.time_features
    };
    let sim_window = window(sim, first..f + 1);
    // Frames before the stream's first are zeros.
    let missing = CONTEXT_LENGTH - (f - first);
    let mut context = Vec::with_capacity(2);
    if missing > 0 {
        context.push(Tensor::<2>::zeros([n, missing * ct], &device));
    }
    if f > first {
        context.push(slice_columns(sim_window.clone(), 0..(f - first) * ct));
    }
    let context = Tensor::cat(context, 1);
    let (mu, sigma) = split(models.time_features.forward(context), ct);
    // The anchors whose time-feature gate is open (σ(raw) ≥ 0.2), decided on the device.
    let subset = sigmoid(slice_columns(raw.factors().detach(), 0..1))
        .greater_equal_elem(TIME_RATE_GATE)
        .float();
    let coded_frame = match inputs.bit_estimate {
        BitEstimate::Simulated => slice_columns(sim_window, (f - first) * ct..(f - first + 1) * ct),
        BitEstimate::Unquantised => window(raw, f..f + 1),
    };
    let draw = unit_noise(&coded_frame, noise.key(4));
    let time_features = weighted_mean(
        gaussian_bits(coded_frame, mu, sigma, draw),
        subset.expand([n, ct]),
    );

    let trajectory = match (inputs.trajectory, coded_values.trajectory()) {
        (TrajectoryRate::Factorized, Some(knots)) => Some(trajectory_bits(
            knots / st.trajectory,
            raw.factors().detach(),
            noise.key(5),
        )),
        _ => None,
    };

    RateTerms {
        log_scales,
        offsets,
        factors,
        features,
        time_features,
        trajectory,
    }
}

/// Mean bits of the trajectory knots `knots` ([N, knots·3], in steps) as the file's per-axis
/// coding prices them (`codec::attributes`, factorized): knot-to-knot increments (the first from
/// zero), under one zero-mean Gaussian per axis whose σ is the increments' RMS (detached: the
/// encoder fits it to the data, nothing learns it), over the anchors whose motion gate
/// σ(`raw_factors`) is open (the others' knots are not stored), plus one U(±½) draw keyed by
/// `key`. The file may code them cheaper still (the knot context, when smaller); the turns are
/// not priced (off by default).
///
/// Not in GIFStream (it has no trajectories): without it nothing prices the knots, which were
/// 29-37 % of the default runs' files, mostly still surfaces' anchors whose knots wander under
/// the photometric gradient's noise (docs/results.md, Follow-up 26).
fn trajectory_bits(knots: Tensor<2>, raw_factors: Tensor<2>, key: NoiseKey) -> Tensor<1> {
    let device = knots.device();
    let [n, width] = knots.dims();
    let increments = if width == 3 {
        knots
    } else {
        let previous = Tensor::cat(
            vec![
                Tensor::<2>::zeros([n, 3], &device),
                slice_columns(knots.clone(), 0..width - 3),
            ],
            1,
        );
        knots - previous
    };
    let moving = sigmoid(slice_columns(raw_factors, MOTION_GATE..MOTION_GATE + 1))
        .greater_equal_elem(GATE_THRESHOLD)
        .float();
    let weight = moving.clone().expand([n, width]);
    // σ per axis over the stored increments: [1, 3], repeated over the knots.
    let squares = (increments.clone().detach().powi_scalar(2) * weight.clone())
        .reshape([n * width / 3, 3])
        .sum_dim(0);
    let count = moving.sum().mul_scalar((width / 3) as f32).clamp_min(1.0);
    // No narrower than the coder's narrowest table.
    let sigma = (squares / count.unsqueeze_dim(1))
        .sqrt()
        .clamp_min(SCALE_MIN as f32);
    let sigma = sigma.repeat_dim(1, width / 3).expand([n, width]);
    let draw = unit_noise(&increments, key);
    weighted_mean(
        gaussian_bits(increments, Tensor::zeros([n, width], &device), sigma, draw),
        weight,
    )
}

/// The gate columns' steps as a [1, 4] row (divides [N, 4] gate values into grid units).
fn gate_step_row(steps: &QuantizationSteps, device: &burn::tensor::Device) -> Tensor<2> {
    Tensor::from_data(
        TensorData::new(steps.gate_steps().to_vec(), [1, FACTOR_COUNT]),
        device,
    )
}
