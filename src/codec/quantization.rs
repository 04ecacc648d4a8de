//! Quantisation (spec §9.1-§9.2): the rate presets' step sizes, the simulation that training runs
//! before every forward pass (faint noise → uniform noise of one step → straight-through
//! rounding), and the host-side rounding the encoder applies to the same grid.
//!
//! One grid for both sides: an attribute value x is coded as the integer index q = round(x/step)
//! and decoded as q·step, exactly what the rounding phase of training computes, so the model the
//! encoder sees is the model training ended with.
//!
//! Deviation (spec §9.3): GIFStream's conditional entropy models also predict a per-element step
//! multiplier `qs` for scales, offsets and factors; the codec here quantises every attribute on
//! its preset's fixed step (qs ≡ 1). The conditional entropy models come next in this issue and
//! will bring `qs` with them.

use acags_kernels::counter_noise::uniform_noise_like;
pub use acags_kernels::counter_noise::{NoiseKey, NoiseStream};
use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::host_math::{logit, sigmoid};
use crate::model::anchor_columns::{FACTOR_COUNT, MOTION_GATE};
use crate::model::anchors::{AnchorTensors, Column, ColumnTensor};

impl QuantizationSteps {
    /// The step of each gate column (time, motion, kNN blend, pruning).
    pub fn gate_steps(&self) -> [f32; FACTOR_COUNT] {
        let mut steps = [self.factors; FACTOR_COUNT];
        steps[MOTION_GATE] = self.motion_gate_step();
        steps
    }

    pub fn motion_gate_step(&self) -> f32 {
        self.motion_gate.unwrap_or(self.factors)
    }
}

/// GIFStream's `--rate` index: step sizes and the rate-distortion weight (spec §9.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum RatePreset {
    R0,
    R1,
    R2,
    R3,
}

/// Quantisation step of every coded attribute.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct QuantizationSteps {
    /// Log-scales (both halves).
    pub log_scales: f32,
    pub offsets: f32,
    pub features: f32,
    pub time_features: f32,
    /// Gate values after the sigmoid, in [0, 1] (every gate but the motion gate, when that has
    /// its own step).
    pub factors: f32,
    /// The motion gate's own step (None: `factors`'; files before codec version 5). Not
    /// GIFStream's (one step for all four gates): there the motion gate scales the motion
    /// head's few-centimetre output; here it also scales the trajectory, metres across the
    /// scene, so the factor grid's half step (1/32) moves a fast object by 3 % of its path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_gate: Option<f32>,
    /// Anchor trajectory knots, in world units (files without trajectories: 0).
    #[serde(default)]
    pub trajectory: f32,
    /// Trajectory turns, radians of rotation vector (read only where the scene has turns; files
    /// written before turns existed lack it: 0).
    #[serde(default)]
    pub turn: f32,
}

impl RatePreset {
    pub fn steps(self) -> QuantizationSteps {
        let (geometry, features) = match self {
            RatePreset::R0 => (0.02, 1.0),
            RatePreset::R1 => (0.04, 1.0),
            RatePreset::R2 => (0.06, 1.5),
            RatePreset::R3 => (0.08, 2.0),
        };
        QuantizationSteps {
            log_scales: geometry,
            offsets: geometry,
            features,
            time_features: features,
            factors: 1.0 / 16.0,
            // 1/1024 in every preset: under the factor grid's half step (1/32) a trajectory
            // of 2 m jitters by 6 cm, ~5 px at 320×240, and the noise phase teaches the model
            // to blur a fast object; at 1/1024 the jitter is 1 mm, under the knots' own half
            // step. `synthetic:fast`, seeds 42 / 43, decoded: moving pixels +0.91 / +0.61 dB,
            // static 0.00 / +0.23, file +1.6 % / −0.2 % (docs/results.md, Follow-up 32).
            motion_gate: Some(1.0 / 1024.0),
            // A quarter of the offset step in world units: half a GIFStream voxel (0.01) at r0,
            // about 0.4 px at the synthetic scenes' 320×240 (offsets are in units of the
            // anchor's offset scale; a trajectory spans the scene, so its step is absolute).
            trajectory: geometry / 4.0,
            // Radians: 0.29° at r0. A slot a few offset scales from its anchor moves by less
            // than a quarter of the offset step under a half-step error.
            turn: geometry / 4.0,
        }
    }

    /// λ of the rate term (GIFStream's scripts).
    pub fn rd_lambda(self) -> f32 {
        match self {
            RatePreset::R0 => 5e-4,
            RatePreset::R1 => 1e-3,
            RatePreset::R2 => 2e-3,
            RatePreset::R3 => 4e-3,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            RatePreset::R0 => "r0",
            RatePreset::R1 => "r1",
            RatePreset::R2 => "r2",
            RatePreset::R3 => "r3",
        }
    }
}

/// What the simulation does at a step (spec §9.2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QuantizationPhase {
    /// Uniform noise of 0.001 step: GIFStream's "effectively off" start.
    Faint,
    /// x + U(−½, ½)·step.
    Noise,
    /// round(x/step)·step forward, identity backward.
    Round,
}

/// Uniform noise amplitude of the faint phase, in steps.
const FAINT_NOISE: f32 = 0.001;

/// Gate values are mapped back to logits through v·(1 − 2ε) + ε so that a value quantised to
/// exactly 0 or 1 keeps a finite logit (sigmoid of it is within 1e-6 of the value).
const LOGIT_EPSILON: f32 = 1e-6;

/// Index of `x` on the grid of `step` (round half away from zero, as training's rounding).
pub fn quantize_index(x: f32, step: f32) -> i32 {
    (x / step).round() as i32
}

/// The value of grid index `q`.
pub fn dequantize(q: i32, step: f32) -> f32 {
    q as f32 * step
}

/// Grid index of a raw gate logit's value σ(raw) on the factor grid.
pub fn factor_index(raw: f32, step: f32) -> i32 {
    quantize_index(sigmoid(raw), step)
}

/// The raw logit that reproduces gate value `q·step` (see [`LOGIT_EPSILON`]).
pub fn factor_logit(q: i32, step: f32) -> f32 {
    let v = dequantize(q, step) * (1.0 - 2.0 * LOGIT_EPSILON) + LOGIT_EPSILON;
    logit(v)
}

/// Host-side rounding of every element onto the grid (the encoder's view of a tensor).
pub fn round_to_grid(values: &[f32], step: f32) -> Vec<f32> {
    values
        .iter()
        .map(|&x| dequantize(quantize_index(x, step), step))
        .collect()
}

/// x quantised for a forward pass. The noise is drawn on the tensor's device from `noise`, a
/// counter-based key (`acags_kernels::counter_noise`: a resumed run draws the same noise, the
/// host draws and uploads nothing); rounding passes the gradient straight through.
pub fn fake_quantize<const D: usize>(
    x: Tensor<D>,
    step: f32,
    phase: QuantizationPhase,
    noise: NoiseKey,
) -> Tensor<D> {
    match phase {
        QuantizationPhase::Faint | QuantizationPhase::Noise => {
            let amplitude = if phase == QuantizationPhase::Faint {
                step * FAINT_NOISE
            } else {
                step
            };
            let noise = uniform_noise_like(&x, noise, amplitude);
            x + noise
        }
        QuantizationPhase::Round => {
            let rounded = x.clone().div_scalar(step).round().mul_scalar(step);
            x.clone() + (rounded - x).detach()
        }
    }
}

/// [`fake_quantize`] of a [N, C] tensor with column c on the grid of `steps[c]`: the same unit
/// noise draw scaled per column, or rounding per column.
fn fake_quantize_columns(
    x: Tensor<2>,
    steps: &[f32],
    phase: QuantizationPhase,
    noise: NoiseKey,
) -> Tensor<2> {
    let [_, c] = x.dims();
    assert_eq!(c, steps.len(), "one step per column");
    let row = Tensor::<2>::from_data(
        burn::tensor::TensorData::new(steps.to_vec(), [1, c]),
        &x.device(),
    );
    match phase {
        QuantizationPhase::Faint | QuantizationPhase::Noise => {
            let amplitude = if phase == QuantizationPhase::Faint {
                FAINT_NOISE
            } else {
                1.0
            };
            let unit = uniform_noise_like(&x, noise, amplitude);
            x + unit * row
        }
        QuantizationPhase::Round => {
            let rounded = (x.clone() / row.clone()).round() * row;
            x.clone() + (rounded - x).detach()
        }
    }
}

/// Gate logits whose sigmoid is quantised on the factor grid (GIFStream's `fake_quantize_factors`
/// quantises the activated value); the gradient reaches the raw logit through σ, the quantiser
/// (noise or straight-through) and the logit, whose derivatives cancel up to the ε map.
///
/// `steps` holds one step per column; where they are all equal this is one scalar step (the
/// same ops, hence the same bits, as before the motion gate had its own).
pub fn fake_quantize_gate_logits(
    raw: Tensor<2>,
    steps: &[f32],
    phase: QuantizationPhase,
    noise: NoiseKey,
) -> Tensor<2> {
    let v = crate::raster::activation::sigmoid(raw);
    let v = if steps.iter().all(|&s| s == steps[0]) {
        fake_quantize(v, steps[0], phase, noise)
    } else {
        fake_quantize_columns(v, steps, phase, noise)
    };
    let v = v
        .mul_scalar(1.0 - 2.0 * LOGIT_EPSILON)
        .add_scalar(LOGIT_EPSILON);
    // Noise can push v outside (0, 1), where the logit is undefined, so it is clamped there. A
    // kept deviation: GIFStream has no logit and no clamp (it uses v itself, so its gradient
    // passes whatever the noise drew); the plain clamp gives no gradient to a gate the noise
    // pushed past it. Together with the decoder eps and the smoothness reference, GIFStream's
    // choices measured 0.35-1.75 dB worse decoded PSNR on three seeds (docs/results.md, Follow-up 4).
    let v = v.clamp(LOGIT_EPSILON, 1.0 - LOGIT_EPSILON);
    (v.clone() / (v.neg() + 1.0)).log()
}

/// The anchor tensors a forward pass sees under the simulation: quantised log-scales, offsets,
/// features, feature streams and gate values; the AAFM mask logits are not coded as values (one
/// bit per anchor) and pass through.
pub fn simulate(
    tensors: &AnchorTensors,
    steps: &QuantizationSteps,
    phase: QuantizationPhase,
    noise: NoiseStream,
) -> AnchorTensors {
    // One noise tensor per column, its draw number the column's place in Column::ALL.
    let stored_turns = tensors.dims.stored_turn_width() > 0;
    tensors.map(|c, t| {
        let key = noise.key(Column::ALL.iter().position(|&a| a == c).expect("a column") as u32);
        let step = match c {
            Column::Factors => {
                return ColumnTensor::Rows(fake_quantize_gate_logits(
                    t.as_rows(),
                    &steps.gate_steps(),
                    phase,
                    key,
                ));
            }
            Column::MaskLogits => return t,
            // Turns derived from the paths are not coded: the decoder derives them.
            Column::Turn if !stored_turns => return t,
            Column::LogScales => steps.log_scales,
            Column::Offsets => steps.offsets,
            Column::Features => steps.features,
            Column::TimeFeatures => steps.time_features,
            Column::Trajectory => steps.trajectory,
            Column::Turn => steps.turn,
        };
        match t {
            ColumnTensor::Rows(x) => ColumnTensor::Rows(fake_quantize(x, step, phase, key)),
            ColumnTensor::Grid(x) => ColumnTensor::Grid(fake_quantize(x, step, phase, key)),
        }
    })
}
