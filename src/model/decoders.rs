//! GIFStream's shared decoders (spec §4.3): four 2-layer ReLU MLPs of hidden width C_F.
//!
//! | MLP | input | output |
//! |---|---|---|
//! | opacity | [F ; T_f·tf] (C_F + C_T) | K values, Tanh |
//! | cov | same | 7K: 3 scale logits + 4 quaternion per slot, no activation |
//! | colour | same | 3K RGB, Sigmoid (no view direction: `view_adaptive` is off) |
//! | motion | [blended features ; γ(t)] (C_F + C_T + 16) | 7: translation + quaternion delta; last layer zero-initialised |
//!
//! Initialisation is PyTorch's `nn.Linear` default (Kaiming-uniform, a = √5: weights and biases
//! in ±1/√fan_in), which is also Burn's `LinearConfig` default. The appearance embedding of the
//! `neur3d_0` config is not included yet (it lands with the trainer's per-dataset configs).

use burn::module::{Module, Param};
use burn::nn::{Linear, LinearConfig};
use crate::raster::activation::{relu, sigmoid, tanh};
use burn::tensor::{Device, Tensor, TensorData};

use crate::device_io::is_host_device;
use crate::raster::linear::linear;

/// Frequencies of the sinusoidal time embedding: 2^n π for n = 0..8 (GIFStream `phi` = 2).
pub const TIME_EMBEDDING_FREQUENCIES: usize = 8;
pub const TIME_EMBEDDING_DIM: usize = 2 * TIME_EMBEDDING_FREQUENCIES;
/// Motion head output: translation (3) and a quaternion delta (4).
pub const MOTION_DIM: usize = 7;

/// One layer x·W + b. On the CPU through the fused [`linear`] op: one parallel pass forward and
/// backward, where Burn's `matmul` + broadcast `add` cost 10-15 % of a training step (issue 21;
/// `bench train`, 4 rounds: 1.10× the step). On a device, Burn's own `Linear::forward`, which
/// the fusion backend folds into its matmul; the op's device version (Burn's matmul on the inner
/// tensors, registered back as one step) would cut the fusion stream at every layer, and no GPU
/// has measured whether that costs or pays.
fn layer(linear_layer: &Linear, x: Tensor<2>) -> Tensor<2> {
    match &linear_layer.bias {
        Some(bias) if is_host_device(&x.device()) => {
            linear(x, linear_layer.weight.val(), bias.val())
        }
        _ => linear_layer.forward(x),
    }
}

/// Linear → ReLU → Linear.
#[derive(Module, Debug)]
pub struct Mlp {
    pub hidden: Linear,
    pub output: Linear,
}

/// Zero last layer of the motion head: the motion is exactly 0 at the start (GIFStream
/// L392-L393).
fn zero_output_layer(mlp: &mut Mlp) {
    mlp.output.weight = Param::from_tensor(mlp.output.weight.val().zeros_like());
    mlp.output.bias = mlp
        .output
        .bias
        .take()
        .map(|b| Param::from_tensor(b.val().zeros_like()));
}

/// Host weights of one linear layer: `weight` [input, output] row-major, `bias` [output].
struct HostLinear {
    input: usize,
    output: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl HostLinear {
    /// PyTorch's default init drawn from `rng`: weight (row-major) then bias, uniform in
    /// ±1/√fan_in.
    fn draw(input: usize, output: usize, rng: &mut impl rand::Rng) -> Self {
        let bound = 1.0 / (input as f32).sqrt();
        let mut draw = |count: usize| -> Vec<f32> {
            (0..count)
                .map(|_| rng.random_range(-bound..bound))
                .collect()
        };
        let weight = draw(input * output);
        let bias = draw(output);
        Self {
            input,
            output,
            weight,
            bias,
        }
    }

    fn into_linear(self, device: &Device) -> Linear {
        Linear {
            weight: Param::from_tensor(Tensor::<2>::from_data(
                TensorData::new(self.weight, [self.input, self.output]),
                device,
            )),
            bias: Some(Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(self.bias, [self.output]),
                device,
            ))),
        }
    }
}

/// A linear layer with PyTorch's default init drawn from `rng`: weight and bias uniform in
/// ±1/√fan_in.
fn seeded_linear(input: usize, output: usize, rng: &mut impl rand::Rng, device: &Device) -> Linear {
    HostLinear::draw(input, output, rng).into_linear(device)
}

impl Mlp {
    pub fn new(input: usize, hidden: usize, output: usize, device: &Device) -> Self {
        Self {
            hidden: LinearConfig::new(input, hidden).init(device),
            output: LinearConfig::new(hidden, output).init(device),
        }
    }

    /// Same initialisation as [`Mlp::new`], drawn from `rng` on the host: identical on every
    /// backend and independent of the device's global generator (which other threads may use).
    pub fn seeded(
        input: usize,
        hidden: usize,
        output: usize,
        rng: &mut impl rand::Rng,
        device: &Device,
    ) -> Self {
        Self {
            hidden: seeded_linear(input, hidden, rng, device),
            output: seeded_linear(hidden, output, rng, device),
        }
    }

    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        layer(&self.output, relu(layer(&self.hidden, x)))
    }
}

/// Sizes of the decoders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecoderSizes {
    /// C_F, also the hidden width.
    pub feature_dim: usize,
    /// C_T.
    pub time_feature_dim: usize,
    /// K, Neural-Gaussian slots per anchor.
    pub slots: usize,
}

/// Which weights a decoder wider than its baseline starts from (`model.decoder_init`; the
/// baseline's sizes are `model.baseline_feature_dim` / `model.baseline_slots`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DecoderInit {
    /// Where the two overlap, the baseline's weights at the same seed ([`Decoders::seeded_paired`]),
    /// so an ACA-GS run and its GIFStream baseline start from the same decoded Gaussians; the
    /// extra hidden units keep their drawn outgoing weights and start with bias 0, so on the
    /// all-zero step-0 input they output relu(0) = 0 and wake with the features at their drawn
    /// scale ([`ExtraHiddenUnits::ZeroBias`]). The default: against `paired`, +0.11 / +0.14 dB
    /// full frame and +0.18 / +0.52 dB on the moving pixels on `synthetic:fast` (seeds 42 / 43,
    /// no codec), with 0.95× / 0.97× the anchors (docs/results.md, Follow-up 37).
    #[default]
    #[serde(rename = "paired-drawn-units")]
    PairedDrawnUnits,
    /// The baseline's weights where the two overlap, and the extra hidden units silent by zero
    /// outgoing weights ([`ExtraHiddenUnits::Silent`]): they feed nothing until those weights
    /// grow from the output's gradient (acags on 2026-12-02, Follow-up 36).
    Paired,
    /// Every layer drawn row-major at its own size ([`Decoders::seeded`]; acags before
    /// 2026-12-02): a model's first slots start from weights that depend on K and C_F.
    Independent,
}

/// How [`Decoders::seeded_paired`] keeps the hidden units beyond the baseline's out of the
/// step-0 output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExtraHiddenUnits {
    /// Outgoing weights 0 (drawn biases): they feed nothing until their outgoing weights grow.
    Silent,
    /// Biases 0 (drawn outgoing weights): silent while their input is 0, i.e. at step 0, where
    /// every feature and time feature is 0.
    ZeroBias,
}

/// One of the four decoder MLPs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Head {
    Opacity,
    Cov,
    Color,
    Motion,
}

impl Head {
    /// [input, hidden, output] widths of this head for `sizes`.
    fn shape(self, sizes: DecoderSizes) -> [usize; 3] {
        let DecoderSizes {
            feature_dim: f,
            time_feature_dim: t,
            slots: k,
        } = sizes;
        let attr = f + t;
        match self {
            Head::Opacity => [attr, f, k],
            Head::Cov => [attr, f, 7 * k],
            Head::Color => [attr, f, 3 * k],
            Head::Motion => [attr + TIME_EMBEDDING_DIM, f, MOTION_DIM],
        }
    }
}

#[derive(Module, Debug)]
pub struct Decoders {
    pub opacity: Mlp,
    pub cov: Mlp,
    pub color: Mlp,
    pub motion: Mlp,
}

/// Raw decoder outputs for M anchors.
#[derive(Clone, Debug)]
pub struct DecodedAnchors {
    /// [M, K] in (−1, 1); slots with opacity ≤ 0 are not spawned.
    pub opacity: Tensor<2>,
    /// [M, 7K]
    pub cov: Tensor<2>,
    /// [M, 3K] in (0, 1)
    pub color: Tensor<2>,
    /// [M, 7]
    pub motion: Tensor<2>,
}

impl Decoders {
    pub fn new(sizes: DecoderSizes, device: &Device) -> Self {
        Self::build(sizes, |input, hidden, output| {
            Mlp::new(input, hidden, output, device)
        })
    }

    /// [`Decoders::new`] with every weight drawn from a generator seeded by `seed` (what the
    /// trainer uses, so a run's initial model depends only on its seed).
    pub fn seeded(sizes: DecoderSizes, seed: u64, device: &Device) -> Self {
        use rand::SeedableRng;
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        Self::build(sizes, |input, hidden, output| {
            Mlp::seeded(input, hidden, output, &mut rng, device)
        })
    }

    /// The initial decoders of a run (`model.decoder_init`): [`Decoders::seeded`], or
    /// [`Decoders::seeded_paired`] with `baseline`.
    pub fn initial(
        sizes: DecoderSizes,
        baseline: DecoderSizes,
        init: DecoderInit,
        seed: u64,
        device: &Device,
    ) -> Self {
        match init {
            DecoderInit::Independent => Self::seeded(sizes, seed, device),
            DecoderInit::Paired => {
                Self::seeded_paired(sizes, baseline, ExtraHiddenUnits::Silent, seed, device)
            }
            DecoderInit::PairedDrawnUnits => {
                Self::seeded_paired(sizes, baseline, ExtraHiddenUnits::ZeroBias, seed, device)
            }
        }
    }

    /// Decoders of `sizes` that start as `baseline`'s [`Decoders::seeded`] at the same seed
    /// does, where the two overlap; `sizes` is `baseline` widened by feature channels (C_F,
    /// hence hidden units) and slots (K).
    ///
    /// Why: features start at 0, so at step 0 every anchor decodes the same opacities from the
    /// biases alone, and the draw decides how many of its slots spawn for the whole set (4 of 5
    /// for GIFStream on seed 42, 1 of 5 on seed 43). `seeded` draws each layer row-major, so a
    /// slot's column, and with it that lottery, changes with K and C_F: every same-seed
    /// ACA-GS-vs-GIFStream pair compared two lotteries as well as two methods (docs/results.md,
    /// Follow-up 35). Here the baseline's weights are drawn from the seed's stream exactly as
    /// `seeded(baseline)` draws them and placed at the same feature channel, time-stream
    /// channel, hidden unit and slot; every other weight is PyTorch's default draw for the wide
    /// layer from a side stream; and the extra hidden units are kept out of the step-0 output
    /// as `extra_units` says, so at step 0 the wide model decodes exactly the baseline's
    /// Gaussians in the baseline's slots (its extra input channels see zero features). Not in
    /// GIFStream or the paper (neither compares two widths at one seed); with
    /// `sizes == baseline` this is `seeded`, bit for bit.
    pub fn seeded_paired(
        sizes: DecoderSizes,
        baseline: DecoderSizes,
        extra_units: ExtraHiddenUnits,
        seed: u64,
        device: &Device,
    ) -> Self {
        use rand::SeedableRng;
        assert!(
            baseline.feature_dim <= sizes.feature_dim
                && baseline.slots <= sizes.slots
                && baseline.time_feature_dim == sizes.time_feature_dim,
            "decoders {sizes:?} are not a widening of {baseline:?}"
        );
        let mut paired = rand::rngs::StdRng::seed_from_u64(seed);
        let mut side = rand::rngs::StdRng::seed_from_u64(seed ^ 0x51DE_D0C0_DE12_0000);
        // Inputs are [F ; stream] (and γ(t) for the motion head): the baseline's channel i sits
        // at i among the features, shifted by the extra channels after them.
        let extra_channels = sizes.feature_dim - baseline.feature_dim;
        let wide_input = |i: usize| {
            if i < baseline.feature_dim {
                i
            } else {
                i + extra_channels
            }
        };
        Self::build_heads(|head| {
            let [input_b, hidden_b, output_b] = head.shape(baseline);
            let [input, hidden, output] = head.shape(sizes);
            let base_hidden = HostLinear::draw(input_b, hidden_b, &mut paired);
            let base_output = HostLinear::draw(hidden_b, output_b, &mut paired);
            let mut wide_hidden = HostLinear::draw(input, hidden, &mut side);
            let mut wide_output = HostLinear::draw(hidden, output, &mut side);
            for i in 0..input_b {
                let row = wide_input(i) * hidden;
                wide_hidden.weight[row..row + hidden_b]
                    .copy_from_slice(&base_hidden.weight[i * hidden_b..(i + 1) * hidden_b]);
            }
            wide_hidden.bias[..hidden_b].copy_from_slice(&base_hidden.bias);
            if extra_units == ExtraHiddenUnits::ZeroBias {
                wide_hidden.bias[hidden_b..].fill(0.0);
            }
            // Outputs are slot-major (slot k's channels at k·width..), so the baseline's output
            // column j is the wide layer's column j. Under `ZeroBias` an extra unit's row keeps
            // its draw: the unit reaches the output only once its input moves off 0.
            for j in 0..hidden {
                let row = &mut wide_output.weight[j * output..(j + 1) * output];
                if j < hidden_b {
                    row[..output_b]
                        .copy_from_slice(&base_output.weight[j * output_b..(j + 1) * output_b]);
                } else if extra_units == ExtraHiddenUnits::Silent {
                    row.fill(0.0);
                }
            }
            wide_output.bias[..output_b].copy_from_slice(&base_output.bias);
            Mlp {
                hidden: wide_hidden.into_linear(device),
                output: wide_output.into_linear(device),
            }
        })
    }

    /// The four MLPs of `sizes`, made by `make(input, hidden, output)` in the order opacity,
    /// cov, colour, motion; the motion head's last layer is zeroed.
    fn build(sizes: DecoderSizes, mut make: impl FnMut(usize, usize, usize) -> Mlp) -> Self {
        Self::build_heads(|head| {
            let [input, hidden, output] = head.shape(sizes);
            make(input, hidden, output)
        })
    }

    /// The four MLPs, made by `make(head)` in the order opacity, cov, colour, motion; the
    /// motion head's last layer is zeroed.
    fn build_heads(mut make: impl FnMut(Head) -> Mlp) -> Self {
        let opacity = make(Head::Opacity);
        let cov = make(Head::Cov);
        let color = make(Head::Color);
        let mut motion = make(Head::Motion);
        zero_output_layer(&mut motion);
        Self {
            opacity,
            cov,
            color,
            motion,
        }
    }

    /// `attr` [M, C_F + C_T]; `motion_input` [M, C_F + C_T + 16].
    pub fn forward(&self, attr: Tensor<2>, motion_input: Tensor<2>) -> DecodedAnchors {
        self.forward_with_motion(attr, self.motion.forward(motion_input))
    }

    /// The attribute decoders, with the motion head's output decoded already.
    pub fn forward_with_motion(&self, attr: Tensor<2>, motion: Tensor<2>) -> DecodedAnchors {
        DecodedAnchors {
            opacity: tanh(self.opacity.forward(attr.clone())),
            cov: self.cov.forward(attr.clone()),
            color: sigmoid(self.color.forward(attr)),
            motion,
        }
    }
}

/// γ(t) = [w_n sin(2^n π t)]_{n<8} ‖ [w_n cos(2^n π t)]_{n<8}, fed only to the motion MLP.
///
/// `bands` opens the frequencies coarse to fine (Nerfies' windowed positional encoding):
/// w_n = (1 − cos(π·clamp(bands − n, 0, 1)))/2, so band n fades in as `bands` goes from n to
/// n + 1. With all [`TIME_EMBEDDING_FREQUENCIES`] bands open every w_n = 1: GIFStream's γ(t).
/// Kept on the device per frame once every band is open (the second half of the default
/// schedule, every evaluation): a frame's γ(t) is then uploaded once. While the bands open, a
/// step's γ(t) is its own and is uploaded (64 bytes).
#[track_caller]
pub fn time_embedding(t: f32, bands: f32, device: &Device) -> Tensor<1> {
    static KEPT: crate::device_io::KeptUploads<u32, 1> = crate::device_io::KeptUploads::new(1024);
    let values = || {
        TensorData::new(
            time_embedding_values(t, bands).to_vec(),
            [TIME_EMBEDDING_DIM],
        )
    };
    if bands >= TIME_EMBEDDING_FREQUENCIES as f32 {
        KEPT.get(t.to_bits(), device, values)
    } else {
        crate::device_io::upload(values(), device)
    }
}

/// The values of [`time_embedding`].
pub fn time_embedding_values(t: f32, bands: f32) -> [f32; TIME_EMBEDDING_DIM] {
    let weight = |n: usize| {
        let x = (bands as f64 - n as f64).clamp(0.0, 1.0);
        (1.0 - (std::f64::consts::PI * x).cos()) / 2.0
    };
    std::array::from_fn(|i| {
        let n = i % TIME_EMBEDDING_FREQUENCIES;
        let a = 2f64.powi(n as i32) * std::f64::consts::PI * t as f64;
        let v = if i < TIME_EMBEDDING_FREQUENCIES {
            a.sin()
        } else {
            a.cos()
        };
        (weight(n) * v) as f32
    })
}

/// Number of scalar parameters of the four MLPs.
pub fn parameter_count(decoders: &Decoders) -> usize {
    decoders.num_params()
}

/// A copy of one MLP on the autodiff device with every parameter tracked.
pub fn tracked_mlp(m: &Mlp) -> Mlp {
    let linear = |l: &Linear| Linear {
        weight: Param::from_tensor(l.weight.val().autodiff()),
        bias: l
            .bias
            .as_ref()
            .map(|b| Param::from_tensor(b.val().autodiff())),
    };
    Mlp {
        hidden: linear(&m.hidden),
        output: linear(&m.output),
    }
}

/// A copy of `plain` on the autodiff device with every parameter tracked.
pub fn tracked(plain: &Decoders) -> Decoders {
    let mlp = tracked_mlp;
    Decoders {
        opacity: mlp(&plain.opacity),
        cov: mlp(&plain.cov),
        color: mlp(&plain.color),
        motion: mlp(&plain.motion),
    }
}
