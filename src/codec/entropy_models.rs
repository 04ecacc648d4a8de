//! GIFStream's conditional entropy models (spec §9.3): five small MLPs predicting a Gaussian
//! (mean, scale) per coded element, trained with the rate term and used again by the coder.
//!
//! | attribute     | model (in → hidden → out) | context |
//! |---------------|---------------------------|---------|
//! | log-scales    | C_F → 8 → 3·6             | the quantised (masked) anchor feature, detached |
//! | offsets       | C_F → 16 → 3·3K           | same; bits of gated slots do not count (ACA-GS) |
//! | factors       | C_F → 8 → 3·4             | same |
//! | features      | 24 → 12 → 24              | chunk j of 8 channels from chunks j−3..j−1 (zeros before 0); F_adapt bits count only where M = 1 (ACA-GS) |
//! | time features | 3·C_T → 12 → 3·C_T        | frame f from frames f−3..f−1 |
//!
//! Every context is in **quantisation-index units** (value / step), in training and in coding
//! alike: GIFStream trains on feature units and codes with index units (spec §18 items 11-12);
//! one convention removes that mismatch. The scale/offset/factor contexts are the same quantised
//! feature the forward pass sees (noised, later rounded), not GIFStream's always-noised one.
//!
//! Deviations: σ = max(|s|, 0.01) instead of clamp(s, 0.01, 1e10), so a scale unit that starts
//! negative still gets a gradient (a clamp would leave it dead at 0.01); the third output part
//! (GIFStream's adaptive step multiplier qs) is kept in the layer sizes but not used yet: every
//! attribute is quantised on its preset's fixed step (see `quantization`).
//!
//! The coder evaluates the MLPs on the host ([`HostMlp`], plain f32 loops in a fixed order), so
//! encoder and decoder predict bit-identical means and scale levels whatever backend trained
//! the model.

use burn::tensor::{Device, Tensor, TensorData};

use super::quantization::QuantizationSteps;
use crate::host_math::sigmoid as host_sigmoid;
use crate::model::anchors::{Column, FACTOR_COUNT, SCALE_DIMS, host_values};
use crate::model::decoders::Mlp;

/// Channels per autoregressive feature chunk.
pub const FEATURE_CHUNK: usize = 8;
/// Chunks (features) or frames (time features) of context.
pub const CONTEXT_LENGTH: usize = 3;
/// Smallest predicted scale, in steps.
pub const MIN_SCALE: f32 = 0.01;
/// Below this σ(raw time gate) an anchor's stream is not in the training rate (GIFStream's 0.2).
pub const TIME_RATE_GATE: f32 = 0.2;

/// The five models depend on the same sizes as the decoders (C_F, C_T, K).
pub type EntropyModelSizes = crate::model::decoders::DecoderSizes;

/// The five models (plain device; training takes tracked copies).
#[derive(Clone, Debug)]
pub struct EntropyModels {
    pub log_scales: Mlp,
    pub offsets: Mlp,
    pub factors: Mlp,
    pub features: Mlp,
    pub time_features: Mlp,
}

/// Chunks of the padded feature.
pub fn feature_chunks(feature_dim: usize) -> usize {
    feature_dim.div_ceil(FEATURE_CHUNK)
}

impl EntropyModels {
    /// (input, hidden, output) of each model, in [`EntropyModels::named`] order.
    pub fn layer_sizes(s: EntropyModelSizes) -> [(usize, usize, usize); 5] {
        let context = CONTEXT_LENGTH;
        [
            (s.feature_dim, 8, 3 * SCALE_DIMS),
            (s.feature_dim, 16, 3 * 3 * s.slots),
            (s.feature_dim, 8, 3 * FACTOR_COUNT),
            (context * FEATURE_CHUNK, 12, 3 * FEATURE_CHUNK),
            (context * s.time_feature_dim, 12, 3 * s.time_feature_dim),
        ]
    }

    pub fn seeded(sizes: EntropyModelSizes, seed: u64, device: &Device) -> Self {
        use rand::SeedableRng;
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed ^ 0x5EED_E27E);
        let [a, b, c, d, e] =
            Self::layer_sizes(sizes).map(|(i, h, o)| Mlp::seeded(i, h, o, &mut rng, device));
        Self {
            log_scales: a,
            offsets: b,
            factors: c,
            features: d,
            time_features: e,
        }
    }

    pub fn named(&self) -> [(&'static str, &Mlp); 5] {
        [
            ("log_scales", &self.log_scales),
            ("offsets", &self.offsets),
            ("factors", &self.factors),
            ("features", &self.features),
            ("time_features", &self.time_features),
        ]
    }

    pub fn named_mut(&mut self) -> [(&'static str, &mut Mlp); 5] {
        [
            ("log_scales", &mut self.log_scales),
            ("offsets", &mut self.offsets),
            ("factors", &mut self.factors),
            ("features", &mut self.features),
            ("time_features", &mut self.time_features),
        ]
    }

    /// A copy on the autodiff device with every parameter tracked.
    pub fn tracked(&self) -> Self {
        let t = crate::model::decoders::tracked_mlp;
        Self {
            log_scales: t(&self.log_scales),
            offsets: t(&self.offsets),
            factors: t(&self.factors),
            features: t(&self.features),
            time_features: t(&self.time_features),
        }
    }

    /// Every weight, model by model (hidden weight, hidden bias, output weight, output bias).
    pub fn weights(&self) -> Vec<f32> {
        self.named()
            .iter()
            .flat_map(|(_, m)| HostMlp::from_mlp(m).flat())
            .collect()
    }

    pub fn weight_count(sizes: EntropyModelSizes) -> usize {
        Self::layer_sizes(sizes)
            .iter()
            .map(|&(i, h, o)| i * h + h + h * o + o)
            .sum()
    }

    /// Host models from [`EntropyModels::weights`]' layout.
    pub fn host_from_weights(sizes: EntropyModelSizes, weights: &[f32]) -> HostEntropyModels {
        assert_eq!(
            weights.len(),
            Self::weight_count(sizes),
            "entropy model weights"
        );
        let mut at = 0;
        HostEntropyModels::from_array(Self::layer_sizes(sizes).map(|(i, h, o)| {
            let n = i * h + h + h * o + o;
            let m = HostMlp::from_flat(i, h, o, &weights[at..at + n]);
            at += n;
            m
        }))
    }

    pub fn host(&self) -> HostEntropyModels {
        HostEntropyModels::from_array(self.named().map(|(_, m)| HostMlp::from_mlp(m)))
    }
}

/// Per-channel (mean, standard deviation) of `values` laid out as rows × `channels`, over the
/// finite entries where `keep(row, channel)`.
fn channel_moments(
    values: &[f32],
    channels: usize,
    keep: impl Fn(usize, usize) -> bool,
) -> Vec<(f32, f32)> {
    let mut sums = vec![(0f64, 0f64, 0f64); channels];
    for (i, &v) in values.iter().enumerate() {
        let (row, c) = (i / channels, i % channels);
        // Non-finite entries mark padding.
        if keep(row, c) && v.is_finite() {
            let s = &mut sums[c];
            s.0 += 1.0;
            s.1 += v as f64;
            s.2 += (v as f64) * (v as f64);
        }
    }
    sums.iter()
        .map(|&(n, sum, sq)| {
            if n == 0.0 {
                (0.0, 1.0)
            } else {
                let mean = sum / n;
                (mean as f32, ((sq / n - mean * mean).max(0.0)).sqrt() as f32)
            }
        })
        .collect()
}

/// Starts a model at the per-channel Gaussian of its data: output bias μ ← mean, σ ← std
/// (at least ½ step), output weights × 0.1 so the context starts as a small correction.
fn start_at(mlp: &mut Mlp, moments: &[(f32, f32)]) {
    let width = moments.len();
    let mut bias = host_values(&mlp.output.bias.as_ref().expect("bias").val());
    for (c, &(mean, std)) in moments.iter().enumerate() {
        bias[c] = mean;
        bias[width + c] = std.max(0.5);
    }
    let device = mlp.output.weight.val().device();
    let weight = mlp.output.weight.val().mul_scalar(0.1);
    mlp.output.weight = burn::module::Param::from_tensor(weight);
    let n = bias.len();
    mlp.output.bias = Some(burn::module::Param::from_tensor(Tensor::<1>::from_data(
        TensorData::new(bias, [n]),
        &device,
    )));
}

impl EntropyModels {
    /// Data-dependent start, run once when the rate term switches on. Deviation: GIFStream
    /// starts from PyTorch's default initialisation; here an attribute far from zero in index
    /// units (log-scales sit at ln(s)/0.02 ≈ −250) would put every symbol in the Gaussian's
    /// float32 tail, where the bit estimate saturates at −log2(1e-5) and passes no gradient to
    /// the model, so it could never learn to predict them.
    pub fn start_from(
        &mut self,
        set: &crate::model::anchors::AnchorSet,
        steps: &QuantizationSteps,
    ) {
        let d = set.dims;
        let scaled = |v: Vec<f32>, step: f32| v.into_iter().map(|x| x / step).collect::<Vec<_>>();
        let log_scales = scaled(set.host(Column::LogScales), steps.log_scales);
        start_at(
            &mut self.log_scales,
            &channel_moments(&log_scales, SCALE_DIMS, |_, _| true),
        );
        let offsets = scaled(set.host(Column::Offsets), steps.offsets);
        let k = d.slots;
        let gates = &set.slot_gates;
        start_at(
            &mut self.offsets,
            &channel_moments(&offsets, 3 * k, |row, c| gates[row * k + c / 3]),
        );
        let gate_steps = steps.gate_steps();
        let factors: Vec<f32> = set
            .host(Column::Factors)
            .into_iter()
            .enumerate()
            .map(|(i, r)| host_sigmoid(r) / gate_steps[i % FACTOR_COUNT])
            .collect();
        start_at(
            &mut self.factors,
            &channel_moments(&factors, FACTOR_COUNT, |_, _| true),
        );
        // Chunk positions share one model: moments over all chunks at each position.
        let cf = d.feature_dim;
        let features = scaled(set.host(Column::Features), steps.features);
        let mut by_position = Vec::with_capacity(features.len());
        for row in features.chunks_exact(cf) {
            let mut padded = row.to_vec();
            padded.resize(feature_chunks(cf) * FEATURE_CHUNK, f32::NAN);
            by_position.extend(padded);
        }
        start_at(
            &mut self.features,
            &channel_moments(&by_position, FEATURE_CHUNK, |_, _| true),
        );
        let stream = scaled(set.host(Column::TimeFeatures), steps.time_features);
        start_at(
            &mut self.time_features,
            &channel_moments(&stream, d.time_feature_dim, |_, _| true),
        );
    }
}

/// An MLP evaluated on the host in a fixed order (bit-identical wherever f32 is IEEE).
#[derive(Clone, Debug, PartialEq)]
pub struct HostMlp {
    pub input: usize,
    pub hidden: usize,
    pub output: usize,
    /// [input, hidden] row-major, [hidden], [hidden, output], [output].
    pub w1: Vec<f32>,
    pub b1: Vec<f32>,
    pub w2: Vec<f32>,
    pub b2: Vec<f32>,
}

impl HostMlp {
    pub fn from_mlp(m: &Mlp) -> Self {
        let [input, hidden] = m.hidden.weight.val().dims();
        let [_, output] = m.output.weight.val().dims();
        let bias = |l: &burn::nn::Linear| host_values(&l.bias.as_ref().expect("bias").val());
        Self {
            input,
            hidden,
            output,
            w1: host_values(&m.hidden.weight.val()),
            b1: bias(&m.hidden),
            w2: host_values(&m.output.weight.val()),
            b2: bias(&m.output),
        }
    }

    pub fn from_flat(input: usize, hidden: usize, output: usize, v: &[f32]) -> Self {
        let (w1, rest) = v.split_at(input * hidden);
        let (b1, rest) = rest.split_at(hidden);
        let (w2, b2) = rest.split_at(hidden * output);
        Self {
            input,
            hidden,
            output,
            w1: w1.to_vec(),
            b1: b1.to_vec(),
            w2: w2.to_vec(),
            b2: b2.to_vec(),
        }
    }

    pub fn flat(&self) -> Vec<f32> {
        [&self.w1[..], &self.b1, &self.w2, &self.b2].concat()
    }

    pub fn forward(&self, x: &[f32]) -> Vec<f32> {
        debug_assert_eq!(x.len(), self.input);
        let h: Vec<f32> = (0..self.hidden)
            .map(|j| {
                let mut acc = self.b1[j];
                for (i, &xi) in x.iter().enumerate() {
                    acc += xi * self.w1[i * self.hidden + j];
                }
                acc.max(0.0)
            })
            .collect();
        (0..self.output)
            .map(|o| {
                let mut acc = self.b2[o];
                for (j, &hj) in h.iter().enumerate() {
                    acc += hj * self.w2[j * self.output + o];
                }
                acc
            })
            .collect()
    }

    /// (rounded mean, σ) of `width` channels from one context row.
    pub fn gaussians(&self, context: &[f32], width: usize) -> Vec<(i32, f32)> {
        let out = self.forward(context);
        (0..width)
            .map(|c| (out[c].round() as i32, out[width + c].abs().max(MIN_SCALE)))
            .collect()
    }
}

/// The five models on the host, for the coder.
#[derive(Clone, Debug, PartialEq)]
pub struct HostEntropyModels {
    pub log_scales: HostMlp,
    pub offsets: HostMlp,
    pub factors: HostMlp,
    pub features: HostMlp,
    pub time_features: HostMlp,
}

impl HostEntropyModels {
    /// From the five models in [`EntropyModels::named`] order.
    fn from_array([log_scales, offsets, factors, features, time_features]: [HostMlp; 5]) -> Self {
        Self {
            log_scales,
            offsets,
            factors,
            features,
            time_features,
        }
    }

    /// In [`EntropyModels::named`] order (the file's).
    pub fn all(&self) -> [&HostMlp; 5] {
        [
            &self.log_scales,
            &self.offsets,
            &self.factors,
            &self.features,
            &self.time_features,
        ]
    }
}
