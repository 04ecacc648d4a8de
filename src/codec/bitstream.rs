//! The `scene.acags` bitstream (spec §10, §12.4, §13.1): a trained model is quantised onto its
//! rate preset's grid ([`QuantizedScene::from_model`]), coded section by section into the
//! container, and decoded back to exactly the same quantised scene, which renders like any model
//! ([`QuantizedScene::to_model`]).
//!
//! Sections, in file order (the decoder needs earlier ones to parse later ones):
//!
//! | name             | content |
//! |------------------|---------|
//! | `meta`           | JSON: sizes, voxel size, rate preset and steps, phase, GOP, the training config |
//! | `decoders`       | the four MLPs, float32 (weights then bias, layer by layer) |
//! | `entropy_models` | the five conditional entropy models, float32 (only when an attribute uses them) |
//! | `positions`      | voxel integers: origin, then Morton codes sorted and delta-coded as varints |
//! | `slot_gates`     | N×K gate bitmap, one Bernoulli context per slot index (ACA-GS AAC) |
//! | `feature_mask`   | N bits M_i (ACA-GS AAFM; only when masking is on) |
//! | `features`       | F_base always, F_adapt only where M_i = 1 |
//! | `factors`        | gate values on the 1/16 grid |
//! | `log_scales`     | |
//! | `offsets`        | only the offsets of active slots (the decoder knows the gates) |
//! | `time_features`  | the whole stream of anchors whose time gate is open (GIFStream's dynamic subset) |
//! | `trajectory`     | knot-to-knot increments of the trajectories of anchors whose motion gate is open (only in scenes trained with trajectories) |
//! | `turn`           | knot-to-knot increments of those anchors' trajectory turns, rotation vectors (only in scenes trained with stored turns, `knots`; `paths` turns are derived by the decoder) |
//!
//! Attributes are coded by [`super::attributes`]: under the trained conditional entropy models
//! or a per-channel Gaussian fit, whichever is smaller.
//!
//! What the encoder drops, as GIFStream's end-to-end compression does: anchors whose pruning gate
//! is closed (they spawn nothing) and, under AAC, anchors without an active slot. What it zeroes
//! because no decode reads it: gated slots' offsets, masked F_adapt channels and the feature
//! stream of anchors whose time gate is closed and the trajectory of anchors whose motion gate
//! is closed. Anchors are stored in Morton order and the
//! decoder recomputes the kNN lists (spec §10 item 8); [`QuantizedScene::from_model`] does the
//! same, so the scene the encoder describes is the scene the decoder rebuilds.

use anyhow::{Context, Result, bail, ensure};
use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::attributes::{Attribute, ModelChoice, decode_attribute, encode_attribute, uses_models};
use super::container::Container;
use super::entropy::BitModels;
use super::entropy_models::{EntropyModels, HostEntropyModels, HostMlp};
use super::quantization::{
    QuantizationSteps, RatePreset, dequantize, factor_index, factor_logit, quantize_index,
};
use super::wire::{Reader, Writer};
use crate::model::anchored::AnchoredModel;
use crate::model::anchors::{
    AnchorDims, AnchorSet, Column, FACTOR_COUNT, FeatureMasking, MOTION_GATE, NewAnchors,
    SCALE_DIMS, TrajectoryTurn,
};
use crate::model::decoders::{DecoderSizes, Decoders, parameter_count};
use crate::model::inputs::GATE_THRESHOLD;
use crate::model::path_turns::derive_path_turns;
use crate::model::slot_gates::SlotGates;
use crate::model::view::{AnchorCulling, Phase};

pub const SCENE_FORMAT: &str = "acags-scene";
/// Version of the section contents (the container has its own). v2 adds the anchor trajectories
/// and the culling mode, v3 the trajectory turns, v4 the knot-context coding of the knot
/// sections (`attributes.rs`), v5 the motion gate's own quantisation step; older files
/// (without them) still decode.
pub const CODEC_VERSION: u32 = 5;
/// The first version whose meta may carry `steps.motion_gate`.
const MOTION_GATE_STEP_VERSION: u32 = 5;
/// Mask logits the decoder gives kept / masked F_adapt (σ = 0.73 / 1e-13 against γ ≪ 1).
const KEPT_MASK_LOGIT: f32 = 1.0;
const MASKED_MASK_LOGIT: f32 = -30.0;
/// Positions must lie on the voxel grid within this fraction of a voxel.
const GRID_TOLERANCE: f32 = 1e-3;
/// Most attribute values a file may declare (1 GiB of indices).
const MAX_ELEMENTS: usize = 1 << 28;
/// Bits per axis of a Morton code.
const MORTON_BITS: u32 = 21;

/// Everything the decoder needs besides the coded attributes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneMeta {
    pub format: String,
    pub codec_version: u32,
    pub anchors: usize,
    pub slots: usize,
    pub initial_active_slots: usize,
    pub frames: usize,
    pub feature_dim: usize,
    pub time_feature_dim: usize,
    pub knn: usize,
    /// F_base channels when AAFM is on.
    pub mask_base_channels: Option<usize>,
    pub mask_threshold: Option<f32>,
    pub voxel_size: f32,
    pub rate: RatePreset,
    pub steps: QuantizationSteps,
    /// Decode in the canonical phase (a run stopped before its dynamic phase).
    pub canonical: bool,
    /// The trained GOP: first dataset frame and frame count.
    pub gop_start: usize,
    pub gop_frames: usize,
    /// The training config (TOML): dataset, test cameras, every hyper-parameter.
    pub config: String,
    /// How the decoder culls anchors (files written before motion-aware culling: canonical).
    #[serde(default = "canonical_culling")]
    pub culling: AnchorCulling,
    /// Frames between trajectory knots (0: no trajectories, as every v1 file).
    #[serde(default)]
    pub trajectory_spacing: usize,
    /// Whether the trajectory knots also turn the anchors (off in every v1 and v2 file).
    #[serde(default)]
    pub trajectory_turn: TrajectoryTurn,
}

fn canonical_culling() -> AnchorCulling {
    AnchorCulling::Canonical
}

impl SceneMeta {
    pub fn dims(&self) -> AnchorDims {
        AnchorDims {
            slots: self.slots,
            initial_active_slots: self.initial_active_slots,
            feature_masking: match (self.mask_base_channels, self.mask_threshold) {
                (Some(base), Some(threshold)) => FeatureMasking::Adaptive { base, threshold },
                _ => FeatureMasking::Off,
            },
            frames: self.frames,
            feature_dim: self.feature_dim,
            time_feature_dim: self.time_feature_dim,
            knn: self.knn,
            trajectory_spacing: self.trajectory_spacing,
            trajectory_turn: self.trajectory_turn,
        }
    }

    pub fn decoder_sizes(&self) -> DecoderSizes {
        DecoderSizes {
            feature_dim: self.feature_dim,
            time_feature_dim: self.time_feature_dim,
            slots: self.slots,
        }
    }

    pub fn phase(&self) -> Phase {
        if self.canonical {
            Phase::Canonical
        } else {
            Phase::Dynamic
        }
    }

    fn validate(&self) -> Result<()> {
        ensure!(
            self.format == SCENE_FORMAT,
            "not an acags scene (format `{}`)",
            self.format
        );
        ensure!(
            (1..=CODEC_VERSION).contains(&self.codec_version),
            "codec version {} is not supported (this build reads versions 1 to {CODEC_VERSION})",
            self.codec_version
        );
        ensure!(
            self.trajectory_spacing == 0 || self.codec_version >= 2,
            "a version-1 scene cannot hold trajectories"
        );
        ensure!(
            self.trajectory_spacing <= self.frames.max(1),
            "trajectory knot spacing {} exceeds the {} frames",
            self.trajectory_spacing,
            self.frames
        );
        if self.trajectory_turn != TrajectoryTurn::Off {
            ensure!(
                self.codec_version >= 3,
                "a version-{} scene cannot hold trajectory turns",
                self.codec_version
            );
            ensure!(
                self.trajectory_spacing > 0,
                "trajectory turns in a scene without trajectories"
            );
            ensure!(
                self.steps.turn > 0.0 && self.steps.turn.is_finite(),
                "quantisation step of turn is {}",
                self.steps.turn
            );
        }
        if self.trajectory_spacing > 0 {
            ensure!(
                self.steps.trajectory > 0.0 && self.steps.trajectory.is_finite(),
                "quantisation step of trajectory is {}",
                self.steps.trajectory
            );
        }
        ensure!(
            self.slots > 0 && self.slots <= 64,
            "implausible slot count {}",
            self.slots
        );
        ensure!(
            self.initial_active_slots <= self.slots,
            "initial_active_slots {} > slots {}",
            self.initial_active_slots,
            self.slots
        );
        ensure!(
            (1..=4096).contains(&self.frames) && self.frames == self.gop_frames,
            "implausible frame count {}",
            self.frames
        );
        ensure!(
            (1..=1024).contains(&self.feature_dim) && (1..=1024).contains(&self.time_feature_dim),
            "implausible feature sizes {} / {}",
            self.feature_dim,
            self.time_feature_dim
        );
        ensure!(self.knn <= 64, "implausible kNN count {}", self.knn);
        if let Some(base) = self.mask_base_channels {
            ensure!(
                base < self.feature_dim,
                "mask base channels {base} >= feature_dim"
            );
        }
        ensure!(
            self.voxel_size > 0.0 && self.voxel_size.is_finite(),
            "voxel size {} is not positive",
            self.voxel_size
        );
        ensure!(
            self.anchors <= 1 << 26,
            "implausible anchor count {}",
            self.anchors
        );
        let s = &self.steps;
        for (name, v) in [
            ("log_scales", s.log_scales),
            ("offsets", s.offsets),
            ("features", s.features),
            ("time_features", s.time_features),
            ("factors", s.factors),
            ("motion_gate", s.motion_gate_step()),
        ] {
            ensure!(
                v > 0.0 && v.is_finite(),
                "quantisation step of {name} is {v}"
            );
        }
        ensure!(
            s.motion_gate.is_none() || self.codec_version >= MOTION_GATE_STEP_VERSION,
            "a version-{} scene cannot hold a motion-gate step",
            self.codec_version
        );
        for (name, v) in [
            ("factors", s.factors),
            ("motion_gate", s.motion_gate_step()),
        ] {
            ensure!(
                1.0 / v <= 65536.0,
                "quantisation step of {name} is {v}: more than 65536 gate levels"
            );
        }
        Ok(())
    }
}

/// A model on the quantisation grid: what the bitstream holds, element for element.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantizedScene {
    pub meta: SceneMeta,
    /// Decoder weights, float32, in [`decoder_layers`] order.
    pub decoders: Vec<f32>,
    /// [N] voxel coordinates, Morton-sorted.
    pub voxels: Vec<[i32; 3]>,
    /// [N·K]
    pub slot_gates: Vec<bool>,
    /// [N] M_i (all true when masking is off).
    pub adapt_kept: Vec<bool>,
    /// Grid indices: [N, 4] on the factor grid, [N, 6], [N, K, 3], [N, C_F], [N, T, C_T].
    pub factors: Vec<i32>,
    pub log_scales: Vec<i32>,
    pub offsets: Vec<i32>,
    pub features: Vec<i32>,
    pub time_features: Vec<i32>,
    /// [N, knots, 3]: per axis, knot 0's index, then each knot's index minus the previous one
    /// (empty without trajectories).
    pub trajectory: Vec<i32>,
    /// [N, knots, 3]: the turns' rotation vectors, coded like `trajectory` (empty without turns).
    pub turn: Vec<i32>,
}

/// Decoder weights in storage order: opacity, cov, colour, motion, each hidden weight, hidden
/// bias, output weight, output bias (the entropy models' layout).
fn decoder_weights(decoders: &Decoders) -> Vec<f32> {
    [
        &decoders.opacity,
        &decoders.cov,
        &decoders.color,
        &decoders.motion,
    ]
    .into_iter()
    .flat_map(|mlp| HostMlp::from_mlp(mlp).flat())
    .collect()
}

fn decoder_weight_count(sizes: DecoderSizes) -> usize {
    // On the CPU: the default device would probe the GPU just to count weights.
    parameter_count(&Decoders::new(
        sizes,
        &crate::compute_backend::host_device(),
    ))
}

fn gate_open(q: i32, step: f32) -> bool {
    dequantize(q, step) >= GATE_THRESHOLD
}

fn morton(v: [u32; 3]) -> u64 {
    let spread = |x: u32| -> u64 {
        let mut x = x as u64 & ((1 << MORTON_BITS) - 1);
        x = (x | x << 32) & 0x1f00000000ffff;
        x = (x | x << 16) & 0x1f0000ff0000ff;
        x = (x | x << 8) & 0x100f00f00f00f00f;
        x = (x | x << 4) & 0x10c30c30c30c30c3;
        x = (x | x << 2) & 0x1249249249249249;
        x
    };
    spread(v[0]) | spread(v[1]) << 1 | spread(v[2]) << 2
}

fn unmorton(code: u64) -> [u32; 3] {
    let compact = |mut x: u64| -> u32 {
        x &= 0x1249249249249249;
        x = (x ^ (x >> 2)) & 0x10c30c30c30c30c3;
        x = (x ^ (x >> 4)) & 0x100f00f00f00f00f;
        x = (x ^ (x >> 8)) & 0x1f0000ff0000ff;
        x = (x ^ (x >> 16)) & 0x1f00000000ffff;
        x = (x ^ (x >> 32)) & 0x1fffff;
        x as u32
    };
    [compact(code), compact(code >> 1), compact(code >> 2)]
}

impl QuantizedScene {
    /// Quantises a trained model on `steps` (`rate`'s, or the config's overrides of them; see
    /// the module docs for what is dropped and zeroed). `config_toml` and the GOP are carried
    /// for evaluation.
    pub fn from_model(
        model: &AnchoredModel,
        rate: RatePreset,
        steps: QuantizationSteps,
        phase: Phase,
        gop: (usize, usize),
        voxel_size: f32,
        config_toml: String,
    ) -> Result<Self> {
        let set = &model.anchors;
        let d = set.dims;
        let n = set.len();
        let (k, cf, t, ct) = (d.slots, d.feature_dim, d.frames, d.time_feature_dim);
        let factors_raw = set.host(Column::Factors);
        let gate_steps = steps.gate_steps();
        let factors: Vec<i32> = factors_raw
            .iter()
            .enumerate()
            .map(|(i, &r)| factor_index(r, gate_steps[i % FACTOR_COUNT]))
            .collect();
        let adapt_kept: Vec<bool> = set.adapt_masked().iter().map(|m| !m).collect();
        let (base, masking) = match d.feature_masking {
            FeatureMasking::Off => (cf, false),
            FeatureMasking::Adaptive { base, .. } => (base, true),
        };
        let keep: Vec<usize> = (0..n)
            .filter(|&a| {
                gate_open(factors[a * FACTOR_COUNT + 3], steps.factors)
                    && set.slot_gates[a * k..(a + 1) * k].iter().any(|&g| g)
            })
            .collect();
        // Voxel integers and the Morton order.
        let mut voxels = Vec::with_capacity(keep.len());
        for &a in &keep {
            let p = set.positions[a];
            let v = p.map(|x| (x / voxel_size).round());
            let off_grid =
                (0..3).any(|i| (v[i] * voxel_size - p[i]).abs() > GRID_TOLERANCE * voxel_size);
            if off_grid || v.iter().any(|x| x.abs() > (1 << 30) as f32) {
                bail!(
                    "anchor {a} at {p:?} is not on the {voxel_size} voxel grid: the model's voxel \
                     size does not match its positions"
                );
            }
            voxels.push(v.map(|x| x as i32));
        }
        let lo = voxels.iter().fold([i32::MAX; 3], |m, v| {
            [m[0].min(v[0]), m[1].min(v[1]), m[2].min(v[2])]
        });
        let mut codes = Vec::with_capacity(voxels.len());
        for v in &voxels {
            let shifted = [0, 1, 2].map(|i| (v[i] as i64 - lo[i] as i64) as u64);
            ensure!(
                shifted.iter().all(|&s| s < 1 << MORTON_BITS),
                "the anchors span more than 2^{MORTON_BITS} voxels along an axis"
            );
            codes.push(morton(shifted.map(|s| s as u32)));
        }
        let mut order: Vec<usize> = (0..keep.len()).collect();
        order.sort_by_key(|&i| codes[i]);

        let log_scales = set.host(Column::LogScales);
        let offsets = set.host(Column::Offsets);
        let features = set.host(Column::Features);
        let time_features = set.host(Column::TimeFeatures);
        let trajectory = set.host_if_present(Column::Trajectory);
        // Turns derived from the paths are not stored: the decoder derives them.
        let turn = set
            .host_if_present(Column::Turn)
            .filter(|_| d.stored_turn_width() > 0);
        let (knots, width) = (d.trajectory_knots(), d.trajectory_width());
        let mut scene = QuantizedScene {
            meta: SceneMeta {
                format: SCENE_FORMAT.into(),
                codec_version: CODEC_VERSION,
                anchors: keep.len(),
                slots: k,
                initial_active_slots: d.initial_active_slots,
                frames: t,
                feature_dim: cf,
                time_feature_dim: ct,
                knn: d.knn,
                mask_base_channels: masking.then_some(base),
                mask_threshold: match d.feature_masking {
                    FeatureMasking::Adaptive { threshold, .. } => Some(threshold),
                    FeatureMasking::Off => None,
                },
                voxel_size,
                rate,
                steps,
                canonical: phase == Phase::Canonical,
                gop_start: gop.0,
                gop_frames: gop.1,
                config: config_toml,
                culling: model.culling,
                trajectory_spacing: d.trajectory_spacing,
                trajectory_turn: d.trajectory_turn,
            },
            decoders: decoder_weights(&model.decoders),
            voxels: Vec::new(),
            slot_gates: Vec::new(),
            adapt_kept: Vec::new(),
            factors: Vec::new(),
            log_scales: Vec::new(),
            offsets: Vec::new(),
            features: Vec::new(),
            time_features: Vec::new(),
            trajectory: Vec::new(),
            turn: Vec::new(),
        };
        let q = |x: f32, step: f32| quantize_index(x, step);
        for &i in &order {
            let a = keep[i];
            scene.voxels.push(voxels[i]);
            let gates = &set.slot_gates[a * k..(a + 1) * k];
            scene.slot_gates.extend_from_slice(gates);
            let kept = adapt_kept[a];
            scene.adapt_kept.push(kept);
            let f = &factors[a * FACTOR_COUNT..(a + 1) * FACTOR_COUNT];
            scene.factors.extend_from_slice(f);
            scene.log_scales.extend(
                log_scales[a * SCALE_DIMS..(a + 1) * SCALE_DIMS]
                    .iter()
                    .map(|&x| q(x, steps.log_scales)),
            );
            for (slot, &g) in gates.iter().enumerate() {
                let o = &offsets[(a * k + slot) * 3..(a * k + slot + 1) * 3];
                scene
                    .offsets
                    .extend(o.iter().map(|&x| if g { q(x, steps.offsets) } else { 0 }));
            }
            scene
                .features
                .extend(
                    features[a * cf..(a + 1) * cf]
                        .iter()
                        .enumerate()
                        .map(|(c, &x)| {
                            if c < base || kept {
                                q(x, steps.features)
                            } else {
                                0
                            }
                        }),
                );
            let dynamic = gate_open(f[0], steps.factors);
            scene
                .time_features
                .extend(
                    time_features[a * t * ct..(a + 1) * t * ct]
                        .iter()
                        .map(|&x| {
                            if dynamic {
                                q(x, steps.time_features)
                            } else {
                                0
                            }
                        }),
                );
            // Knot-to-knot increments, zero where the motion gate is closed (no decode reads
            // the knots then).
            let moving = gate_open(f[MOTION_GATE], steps.motion_gate_step());
            for (values, step, out) in [
                (&trajectory, steps.trajectory, &mut scene.trajectory),
                (&turn, steps.turn, &mut scene.turn),
            ] {
                let Some(values) = values else { continue };
                let row = &values[a * width..(a + 1) * width];
                let mut previous = [0i32; 3];
                for j in 0..knots {
                    for c in 0..3 {
                        let index = if moving { q(row[j * 3 + c], step) } else { 0 };
                        out.push(index - previous[c]);
                        previous[c] = index;
                    }
                }
            }
        }
        Ok(scene)
    }

    /// The renderable model (recomputes the kNN lists, as the decoder must).
    pub fn to_model(&self, device: &Device) -> Result<AnchoredModel> {
        let m = &self.meta;
        let dims = m.dims();
        let s = &m.steps;
        let deq = |v: &[i32], step: f32| v.iter().map(|&q| dequantize(q, step)).collect::<Vec<_>>();
        let positions = self
            .voxels
            .iter()
            .map(|v| v.map(|x| x as f32 * m.voxel_size))
            .collect();
        let mask_logits = self
            .adapt_kept
            .iter()
            .map(|&kept| {
                if kept {
                    KEPT_MASK_LOGIT
                } else {
                    MASKED_MASK_LOGIT
                }
            })
            .collect();
        let gate_steps = s.gate_steps();
        let factors = self
            .factors
            .iter()
            .enumerate()
            .map(|(i, &q)| factor_logit(q, gate_steps[i % FACTOR_COUNT]))
            .collect();
        let mut rows = NewAnchors::new(positions)
            .with(Column::LogScales, deq(&self.log_scales, s.log_scales))
            .with(Column::Offsets, deq(&self.offsets, s.offsets))
            .with(Column::Features, deq(&self.features, s.features))
            .with(
                Column::TimeFeatures,
                deq(&self.time_features, s.time_features),
            )
            .with(Column::Factors, factors)
            .with(Column::MaskLogits, mask_logits);
        if dims.trajectory_width() > 0 {
            rows = rows.with(
                Column::Trajectory,
                self.knot_values(&self.trajectory, m.steps.trajectory, "trajectory")?,
            );
        }
        if dims.stored_turn_width() > 0 {
            rows = rows.with(
                Column::Turn,
                self.knot_values(&self.turn, m.steps.turn, "turn")?,
            );
        } else if dims.turn_width() > 0 {
            // Derived below, once the set has its neighbour lists.
            rows = rows.with(Column::Turn, vec![0.0; m.anchors * dims.turn_width()]);
        }
        let mut anchors = AnchorSet::from_rows(dims, rows, device);
        derive_path_turns(&mut anchors);
        ensure!(
            self.slot_gates.len() == anchors.len() * dims.slots,
            "{} slot gates for {} anchors of {} slots",
            self.slot_gates.len(),
            anchors.len(),
            dims.slots
        );
        anchors.slot_gates = SlotGates::from_flags(self.slot_gates.clone(), dims.slots, device);
        let mut decoders = Decoders::new(m.decoder_sizes(), device);
        let expected = decoder_weight_count(m.decoder_sizes());
        ensure!(
            self.decoders.len() == expected,
            "decoders hold {} weights, the sizes need {expected}",
            self.decoders.len()
        );
        let mut at = 0;
        for linear in [
            &mut decoders.opacity,
            &mut decoders.cov,
            &mut decoders.color,
            &mut decoders.motion,
        ]
        .into_iter()
        .flat_map(|mlp| [&mut mlp.hidden, &mut mlp.output])
        {
            let [i, o] = linear.weight.val().dims();
            let w = self.decoders[at..at + i * o].to_vec();
            at += i * o;
            let b = self.decoders[at..at + o].to_vec();
            at += o;
            linear.weight =
                Param::from_tensor(Tensor::<2>::from_data(TensorData::new(w, [i, o]), device));
            linear.bias = Some(Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(b, [o]),
                device,
            )));
        }
        Ok(AnchoredModel {
            anchors,
            decoders,
            culling: m.culling,
        })
    }

    /// Knot values (the trajectory in world units, the turns in radians) from their stored
    /// increments (cumulative sums); `name` names them in errors.
    fn knot_values(&self, increments: &[i32], step: f32, name: &str) -> Result<Vec<f32>> {
        let width = self.meta.dims().trajectory_width();
        if width == 0 {
            return Ok(Vec::new());
        }
        ensure!(
            increments.len() == self.voxels.len() * width,
            "{name} holds {} values, the anchors need {}",
            increments.len(),
            self.voxels.len() * width
        );
        let mut values = Vec::with_capacity(increments.len());
        for row in increments.chunks_exact(width) {
            let mut index = [0i32; 3];
            for knot in row.chunks_exact(3) {
                for c in 0..3 {
                    index[c] = index[c]
                        .checked_add(knot[c])
                        .with_context(|| format!("a {name} index overflows"))?;
                    values.push(dequantize(index[c], step));
                }
            }
        }
        Ok(values)
    }

    fn base_channels(&self) -> usize {
        self.meta
            .mask_base_channels
            .unwrap_or(self.meta.feature_dim)
    }

    /// Which elements of each attribute are stored (the rest decode as index 0).
    fn coded_masks(&self) -> CodedMasks {
        let m = &self.meta;
        let (k, cf, t, ct) = (m.slots, m.feature_dim, m.frames, m.time_feature_dim);
        let base = self.base_channels();
        let n = self.voxels.len();
        let mut masks = CodedMasks::default();
        for a in 0..n {
            for slot in 0..k {
                masks.offsets.extend([self.slot_gates[a * k + slot]; 3]);
            }
            masks
                .features
                .extend((0..cf).map(|c| c < base || self.adapt_kept[a]));
            // Before the factors are decoded the stream's mask is not needed (nor known).
            let dynamic = self
                .factors
                .get(a * FACTOR_COUNT)
                .is_some_and(|&q| gate_open(q, m.steps.factors));
            masks
                .time_features
                .extend(std::iter::repeat_n(dynamic, t * ct));
            let moving = self
                .factors
                .get(a * FACTOR_COUNT + MOTION_GATE)
                .is_some_and(|&q| gate_open(q, m.steps.motion_gate_step()));
            masks
                .trajectory
                .extend(std::iter::repeat_n(moving, m.dims().trajectory_width()));
            masks
                .turn
                .extend(std::iter::repeat_n(moving, m.dims().stored_turn_width()));
        }
        masks
    }

    /// The `scene.acags` container: attributes under the entropy models when given and
    /// `choice` allows (the smaller of the two codings per attribute by default).
    pub fn encode(
        &self,
        models: Option<&HostEntropyModels>,
        choice: ModelChoice,
    ) -> Result<Container> {
        let m = &self.meta;
        let n = self.voxels.len();
        ensure!(
            n == m.anchors,
            "scene holds {n} anchors, its meta says {}",
            m.anchors
        );
        let masks = self.coded_masks();
        let mut attributes = Vec::new();
        for attribute in Attribute::of(self) {
            let bytes = encode_attribute(attribute, self, masks.get(attribute), models, choice)?;
            attributes.push((attribute.section(), bytes));
        }
        let mut c = Container::default();
        c.push("meta", serde_json::to_vec(m)?)?;
        let mut w = Writer::default();
        w.f32s(&self.decoders);
        c.push("decoders", w.bytes)?;
        // Entropy-model weights only when an attribute was coded with them.
        if attributes.iter().any(|(_, b)| uses_models(b)) {
            let models = models.expect("conditional coding had models");
            let mut w = Writer::default();
            for mlp in models.all() {
                w.f32s(&mlp.flat());
            }
            c.push("entropy_models", w.bytes)?;
        }
        c.push("positions", encode_positions(&self.voxels)?)?;
        let k = m.slots;
        let slot_context: Vec<usize> = (0..n * k).map(|i| i % k).collect();
        c.push(
            "slot_gates",
            encode_bits(&self.slot_gates, &slot_context, k)?,
        )?;
        if m.mask_base_channels.is_some() {
            c.push(
                "feature_mask",
                encode_bits(&self.adapt_kept, &vec![0; n], 1)?,
            )?;
        }
        for (name, bytes) in attributes {
            c.push(name, bytes)?;
        }
        Ok(c)
    }

    /// Parses a container written by [`QuantizedScene::encode`]; `origin` names it in errors.
    /// Returns the entropy models the file carries, if any (re-encoding with them reproduces the
    /// file byte for byte).
    pub fn decode(
        container: &Container,
        origin: &str,
    ) -> Result<(Self, Option<HostEntropyModels>)> {
        let section = |name: &str| -> Result<&[u8]> {
            container
                .get(name)
                .with_context(|| format!("{origin}: no `{name}` section"))
        };
        let meta: SceneMeta = serde_json::from_slice(section("meta")?)
            .with_context(|| format!("{origin}: section `meta` is not valid scene metadata"))?;
        meta.validate()
            .with_context(|| format!("{origin}: section `meta`"))?;
        let n = meta.anchors;
        let k = meta.slots;
        // Bounds what a crafted header could make the decoder allocate.
        let elements = n
            .checked_mul(
                meta.frames * meta.time_feature_dim
                    + meta.feature_dim
                    + k * 3
                    + meta.dims().trajectory_width()
                    + meta.dims().stored_turn_width(),
            )
            .filter(|&e| e <= MAX_ELEMENTS);
        ensure!(
            elements.is_some(),
            "{origin}: {n} anchors of this size exceed the decoder's limit of {MAX_ELEMENTS} values"
        );
        let what = |name: &str| format!("{origin}: section `{name}`");
        if let Some(extra) = container
            .sections
            .iter()
            .find(|s| !SECTION_ORDER.contains(&s.name.as_str()))
        {
            bail!("{origin}: unknown section `{}`", extra.name);
        }

        let count = decoder_weight_count(meta.decoder_sizes());
        let mut r = Reader::new(section("decoders")?, what("decoders"));
        let decoders = r.f32s(count, "decoder weights")?;
        r.finish()?;
        ensure!(
            decoders.iter().all(|v| v.is_finite()),
            "{}: non-finite decoder weight",
            what("decoders")
        );
        let models = match container.get("entropy_models") {
            None => None,
            Some(bytes) => {
                let sizes = meta.decoder_sizes();
                let mut r = Reader::new(bytes, what("entropy_models"));
                let weights =
                    r.f32s(EntropyModels::weight_count(sizes), "entropy model weights")?;
                r.finish()?;
                ensure!(
                    weights.iter().all(|v| v.is_finite()),
                    "{}: non-finite weight",
                    what("entropy_models")
                );
                Some(EntropyModels::host_from_weights(sizes, &weights))
            }
        };
        let voxels = decode_positions(section("positions")?, n, &what("positions"))?;
        let slot_context: Vec<usize> = (0..n * k).map(|i| i % k).collect();
        let slot_gates = decode_bits(
            section("slot_gates")?,
            &slot_context,
            k,
            &what("slot_gates"),
        )?;
        let adapt_kept = if meta.mask_base_channels.is_some() {
            decode_bits(
                section("feature_mask")?,
                &vec![0; n],
                1,
                &what("feature_mask"),
            )?
        } else {
            ensure!(
                container.get("feature_mask").is_none(),
                "{origin}: a `feature_mask` section in a scene without feature masking"
            );
            vec![true; n]
        };
        let mut scene = QuantizedScene {
            meta,
            decoders,
            voxels,
            slot_gates,
            adapt_kept,
            factors: Vec::new(),
            log_scales: Vec::new(),
            offsets: Vec::new(),
            features: Vec::new(),
            time_features: Vec::new(),
            trajectory: Vec::new(),
            turn: Vec::new(),
        };
        if scene.meta.dims().stored_turn_width() == 0 {
            ensure!(
                container.get("turn").is_none(),
                "{origin}: a `turn` section in a scene without stored trajectory turns"
            );
        }
        if scene.meta.trajectory_spacing == 0 {
            ensure!(
                container.get("trajectory").is_none(),
                "{origin}: a `trajectory` section in a scene without trajectories"
            );
        }
        let factor_levels = scene
            .meta
            .steps
            .gate_steps()
            .map(|s| (1.0 / s).round() as i32);
        let attributes: Vec<Attribute> = Attribute::of(&scene).collect();
        for attribute in attributes {
            // Masks depend on earlier attributes (the stream on the decoded time gate).
            let masks = scene.coded_masks();
            let name = attribute.section();
            decode_attribute(
                attribute,
                section(name)?,
                &mut scene,
                masks.get(attribute),
                models.as_ref(),
                &what(name),
            )?;
            if attribute == Attribute::Factors {
                ensure!(
                    scene
                        .factors
                        .iter()
                        .enumerate()
                        .all(|(i, &q)| (0..=factor_levels[i % FACTOR_COUNT]).contains(&q)),
                    "{}: a gate value outside [0, 1]",
                    what("factors")
                );
            }
        }
        if models.is_some()
            && !Attribute::ALL
                .iter()
                .any(|a| uses_models(section(a.section()).unwrap_or(&[])))
        {
            bail!("{origin}: entropy models stored but no attribute uses them");
        }
        Ok((scene, models))
    }
}

/// Section names in file order (every one optional to the parser, which decides what is
/// required).
pub const SECTION_ORDER: [&str; 13] = [
    "meta",
    "decoders",
    "entropy_models",
    "positions",
    "slot_gates",
    "feature_mask",
    "features",
    "factors",
    "log_scales",
    "offsets",
    "time_features",
    "trajectory",
    "turn",
];

/// A container from `u32 length + bytes` records assigned to [`SECTION_ORDER`] in turn (an empty
/// record skips a section): how the fuzz target and the damage tests reach the section parsers
/// behind valid checksums.
pub fn container_from_records(mut data: &[u8]) -> Container {
    let mut container = Container::default();
    for name in SECTION_ORDER {
        if data.len() < 4 {
            break;
        }
        let len = u32::from_le_bytes(data[..4].try_into().unwrap()) as usize;
        data = &data[4..];
        let take = len.min(data.len());
        if take > 0 {
            container
                .push(name, data[..take].to_vec())
                .expect("known section names are valid");
        }
        data = &data[take..];
    }
    container
}

/// The records [`container_from_records`] reads back into `container` (fuzz corpus seeds).
pub fn records_from_container(container: &Container) -> Vec<u8> {
    let mut out = Vec::new();
    for name in SECTION_ORDER {
        let data = container.get(name).unwrap_or(&[]);
        out.extend((data.len() as u32).to_le_bytes());
        out.extend(data);
    }
    out
}

#[derive(Default)]
struct CodedMasks {
    offsets: Vec<bool>,
    features: Vec<bool>,
    time_features: Vec<bool>,
    trajectory: Vec<bool>,
    turn: Vec<bool>,
}

impl CodedMasks {
    fn get(&self, attribute: Attribute) -> Option<&[bool]> {
        match attribute {
            Attribute::Offsets => Some(&self.offsets),
            Attribute::Features => Some(&self.features),
            Attribute::TimeFeatures => Some(&self.time_features),
            Attribute::Trajectory => Some(&self.trajectory),
            Attribute::Turn => Some(&self.turn),
            Attribute::Factors | Attribute::LogScales => None,
        }
    }
}

fn encode_positions(voxels: &[[i32; 3]]) -> Result<Vec<u8>> {
    let mut w = Writer::default();
    let lo = voxels.iter().fold([i32::MAX; 3], |m, v| {
        [m[0].min(v[0]), m[1].min(v[1]), m[2].min(v[2])]
    });
    let lo = if voxels.is_empty() { [0; 3] } else { lo };
    for x in lo {
        w.i32(x);
    }
    let mut previous = 0u64;
    for (i, v) in voxels.iter().enumerate() {
        let code = morton([0, 1, 2].map(|a| (v[a] - lo[a]) as u32));
        ensure!(
            i == 0 || code >= previous,
            "positions are not in Morton order (the scene was not built by from_model)"
        );
        w.varint(code - previous);
        previous = code;
    }
    Ok(w.bytes)
}

fn decode_positions(bytes: &[u8], n: usize, what: &str) -> Result<Vec<[i32; 3]>> {
    let mut r = Reader::new(bytes, what);
    let lo = [r.i32("origin")?, r.i32("origin")?, r.i32("origin")?];
    let mut code = 0u64;
    let mut out = Vec::with_capacity(n.min(bytes.len()));
    for _ in 0..n {
        let delta = r.varint("Morton delta")?;
        code = code
            .checked_add(delta)
            .filter(|&c| c < 1 << (3 * MORTON_BITS))
            .with_context(|| format!("{what}: Morton code out of range"))?;
        let v = unmorton(code);
        let mut p = [0i32; 3];
        for a in 0..3 {
            p[a] = lo[a]
                .checked_add(v[a] as i32)
                .with_context(|| format!("{what}: voxel coordinate overflows"))?;
        }
        out.push(p);
    }
    r.finish()?;
    Ok(out)
}

fn encode_bits(bits: &[bool], contexts: &[usize], context_count: usize) -> Result<Vec<u8>> {
    let (ones, totals) = BitModels::count(bits, contexts, context_count);
    let models = BitModels::new(&ones, &totals)?;
    let mut w = Writer::default();
    for &o in &ones {
        w.u32(o);
    }
    w.block(&models.encode(bits, contexts)?);
    Ok(w.bytes)
}

fn decode_bits(
    bytes: &[u8],
    contexts: &[usize],
    context_count: usize,
    what: &str,
) -> Result<Vec<bool>> {
    let mut r = Reader::new(bytes, what);
    let mut totals = vec![0u32; context_count];
    for &c in contexts {
        totals[c] += 1;
    }
    let ones = (0..context_count)
        .map(|_| r.u32("count of set bits"))
        .collect::<Result<Vec<_>>>()?;
    let models = BitModels::new(&ones, &totals).with_context(|| what.to_string())?;
    let stream = r.block("bit stream")?;
    r.finish()?;
    models.decode(stream, contexts, what)
}
