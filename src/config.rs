//! Training configuration: one TOML file (`configs/*.toml`), overridable key by key with
//! `--set section.key=value`, saved resolved into every run directory.
//!
//! Defaults are GIFStream's 30k-step values (spec §2.2, §6-§8); `configs/default.toml` shortens
//! the schedule for the embedded synthetic scene. Unknown keys are errors, so a typo in a sweep
//! never silently trains the default.

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::codec::quantization::{QuantizationPhase, QuantizationSteps, RatePreset};
use crate::codec::rate::BitEstimate;
use crate::data::DatasetLayout;
use crate::eval::config::EvalConfig;
use crate::model::anchor_columns::TrajectoryTurn;
use crate::model::decoders::{DecoderInit, DecoderSizes};
use crate::model::view::{AnchorCulling, StepCulling};

/// The configuration `acags train` uses when given none (embedded so it works from anywhere).
pub const DEFAULT_CONFIG: &str = include_str!("../configs/default.toml");
/// ACA-GS on the same scene and schedule (embedded for sweeps that run from anywhere, e.g.
/// `acags stability`).
pub const ACA_GS_CONFIG: &str = include_str!("../configs/aca-gs.toml");

/// The configs compiled into the binary, by file name (what an embedded config's `extends` may
/// name).
const EMBEDDED_CONFIGS: [(&str, &str); 2] = [
    ("default.toml", DEFAULT_CONFIG),
    ("aca-gs.toml", ACA_GS_CONFIG),
];

/// The embedded config named `name` (a path's last component counts): (file name, text).
fn embedded_config(name: &str) -> Option<(&'static str, &'static str)> {
    let name = name.rsplit('/').next().unwrap_or(name);
    EMBEDDED_CONFIGS.iter().copied().find(|(n, _)| *n == name)
}

/// The key naming a config's base: `extends = "default.toml"` takes every key of that file
/// (a path relative to this one) and lets this file override them. An ACA-GS config extends
/// the GIFStream config it is compared with, so the two differ only in what it sets.
pub const EXTENDS_KEY: &str = "extends";
/// Longest chain of `extends`.
const MAX_EXTENDS_DEPTH: usize = 8;

/// Where a config's text came from.
#[derive(Clone, Debug, PartialEq)]
enum ConfigSource {
    File(std::path::PathBuf),
    /// An embedded config, by file name.
    Embedded(String),
}

impl std::fmt::Display for ConfigSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConfigSource::File(p) => write!(f, "{}", p.display()),
            ConfigSource::Embedded(name) => write!(f, "configs/{name} (embedded)"),
        }
    }
}

/// The table of `text` with its `extends` chain merged in (this file's keys win, section by
/// section), without the `extends` key.
fn resolve_extends(
    text: &str,
    source: &ConfigSource,
    chain: &mut Vec<ConfigSource>,
) -> Result<toml::Table> {
    let mut table: toml::Table =
        toml::from_str(text).with_context(|| format!("{source}: invalid TOML"))?;
    let Some(base) = table.remove(EXTENDS_KEY) else {
        return Ok(table);
    };
    let base = base.as_str().with_context(|| {
        format!("{source}: `{EXTENDS_KEY}` must be a file name or path, got {base}")
    })?;
    if chain.contains(source) {
        bail!("{source}: `{EXTENDS_KEY}` forms a cycle");
    }
    if chain.len() >= MAX_EXTENDS_DEPTH {
        bail!("{source}: more than {MAX_EXTENDS_DEPTH} levels of `{EXTENDS_KEY}`");
    }
    chain.push(source.clone());
    let (base_source, base_text) = match source {
        ConfigSource::File(path) => {
            let base_path = path.parent().unwrap_or(Path::new(".")).join(base);
            let text = std::fs::read_to_string(&base_path).with_context(|| {
                format!(
                    "{source}: cannot read the config it extends, {}",
                    base_path.display()
                )
            })?;
            (ConfigSource::File(base_path), text)
        }
        ConfigSource::Embedded(_) => {
            let (name, text) = embedded_config(base).with_context(|| {
                format!("{source}: extends `{base}`, which is not an embedded config")
            })?;
            (ConfigSource::Embedded(name.to_string()), text.to_string())
        }
    };
    let mut merged = resolve_extends(&base_text, &base_source, chain)?;
    chain.pop();
    merge_tables(&mut merged, table);
    Ok(merged)
}

/// `over`'s keys into `base`: sections merge key by key, any other value replaces.
fn merge_tables(base: &mut toml::Table, over: toml::Table) {
    for (key, value) in over {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge_tables(b, o),
            (_, value) => {
                base.insert(key, value);
            }
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    pub data: DataConfig,
    pub model: ModelConfig,
    pub train: ScheduleConfig,
    pub loss: LossConfig,
    pub lr: LearningRates,
    pub densify: DensifyConfig,
    /// ACA-GS Adaptive Anchor Cardinality (off: GIFStream's fixed K).
    pub aac: AacConfig,
    /// ACA-GS Adaptive Anchor Feature Masking and Conditional Regularisation (off: GIFStream).
    pub aafm: AafmConfig,
    /// Quantisation simulation and rate preset (spec §9).
    pub compression: CompressionConfig,
    /// Evaluation: the motion mask that splits test images into dynamic and static pixels, and
    /// the LPIPS conventions.
    pub eval: EvalConfig,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            data: DataConfig::default(),
            model: ModelConfig::default(),
            train: ScheduleConfig::default(),
            loss: LossConfig::default(),
            lr: LearningRates::default(),
            densify: DensifyConfig::default(),
            aac: AacConfig::default(),
            aafm: AafmConfig::default(),
            compression: CompressionConfig::default(),
            eval: EvalConfig::default(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DataConfig {
    /// A dataset directory, or `synthetic:fast` / `synthetic:slow` (generated into a cache
    /// directory on first use).
    pub dataset: String,
    /// Layout; detected from the files when absent.
    pub layout: Option<DatasetLayout>,
    pub start_frame: usize,
    /// Frames in the GOP (T); every frame from `start_frame` when absent.
    pub frames: Option<usize>,
    pub downscale: u32,
    /// Test cameras (indices into the sorted camera list); the layout's default when absent.
    pub test_cameras: Option<Vec<usize>>,
    pub removed_cameras: Vec<usize>,
    /// Decoded training frames kept in memory, in MiB.
    pub frame_cache_mib: usize,
    /// Training targets kept on the device, in MiB (uploaded at first use, least recently
    /// used dropped first; `train::device_targets`). Unset: 1024 on a GPU, 0 on the CPU
    /// backend, whose device memory is the host frame cache's. 0 uploads every step's target.
    pub device_frame_cache_mib: Option<usize>,
}

impl DataConfig {
    /// Loads the dataset this table names (`data::load_dataset`).
    pub fn load_scene(&self) -> Result<crate::data::Scene> {
        let options = crate::data::LoadOptions {
            start_frame: self.start_frame,
            frame_count: self.frames,
            downscale: self.downscale,
            test_cameras: self.test_cameras.clone(),
            removed_cameras: self.removed_cameras.clone(),
            ..Default::default()
        };
        crate::data::load_dataset(&self.dataset, self.layout, &options)
    }
}

impl Default for DataConfig {
    fn default() -> Self {
        Self {
            dataset: "synthetic:fast".into(),
            layout: None,
            start_frame: 0,
            frames: None,
            downscale: 1,
            test_cameras: None,
            removed_cameras: Vec::new(),
            frame_cache_mib: 2048,
            device_frame_cache_mib: None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// C_F, also the decoders' hidden width.
    pub feature_dim: usize,
    /// C_T, channels of the per-frame feature stream.
    pub time_feature_dim: usize,
    /// K, Neural Gaussians per anchor.
    pub slots: usize,
    /// Anchor grid in scene units (GIFStream: 0.01, not configurable there).
    pub voxel_size: f32,
    /// Neighbours blended into the motion input; 0 turns the kNN blend off.
    pub knn: usize,
    /// Where anchors are culled against the camera: at their canonical position (GIFStream) or
    /// where the motion head puts them at the frame.
    pub culling: AnchorCulling,
    /// Per-anchor trajectories: a knot (a translation) every this many frames, interpolated
    /// linearly and added to the motion head's translation (0: none, GIFStream).
    pub trajectory_spacing: usize,
    /// Whether each knot also holds a rotation that turns the anchor's Gaussians (`"knots"`,
    /// optimised and stored; `"paths"`, derived from the anchors' paths and their kNN
    /// neighbours, neither optimised nor stored; `"objects"`, derived likewise, one turn per
    /// group of anchors whose paths stay together; all need trajectories) or the knots only
    /// translate (`"off"`, the only rotation then being the motion head's, as in GIFStream).
    pub trajectory_turn: TrajectoryTurn,
    /// Where a model is wider than its baseline (more slots or feature channels), whether its
    /// decoders start from the baseline's weights at the same seed (`"paired-drawn-units"`, the
    /// default, or `"paired"` with the extra hidden units silenced by zero outgoing weights) or
    /// from their own row-major draw (`"independent"`); see [`DecoderInit`].
    pub decoder_init: DecoderInit,
    /// C_F of the baseline the decoders are paired with (unset: this model's own, no pairing).
    /// An ACA-GS config sets the C_F of the config it extends; tests/config.rs checks it.
    pub baseline_feature_dim: Option<usize>,
    /// K of the baseline the decoders are paired with (unset: this model's own).
    pub baseline_slots: Option<usize>,
}

impl ModelConfig {
    /// The decoder sizes `model.decoder_init = "paired*"` pairs this model's decoders with.
    pub fn baseline_decoder_sizes(&self) -> DecoderSizes {
        DecoderSizes {
            feature_dim: self.baseline_feature_dim.unwrap_or(self.feature_dim),
            time_feature_dim: self.time_feature_dim,
            slots: self.baseline_slots.unwrap_or(self.slots),
        }
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            feature_dim: 24,
            time_feature_dim: 8,
            slots: 5,
            voxel_size: 0.01,
            knn: 6,
            culling: AnchorCulling::Canonical,
            trajectory_spacing: 0,
            trajectory_turn: TrajectoryTurn::Off,
            decoder_init: DecoderInit::PairedDrawnUnits,
            baseline_feature_dim: None,
            baseline_slots: None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScheduleConfig {
    pub max_steps: usize,
    pub seed: u64,
    /// Canonical phase (no time features, no motion) while step ≤ max_steps · deformation_gate;
    /// `init_dynamic` runs at its end; factor regularisation starts at (gate + 0.1) · max_steps.
    pub deformation_gate: f64,
    /// Temporal smoothness pass on steps divisible by this (0 = off).
    pub smooth_every: usize,
    /// Where a training step culls its anchors: `"device"` (every row decoded, the culled ones
    /// masked on the device: no read-back, shapes fixed between refinements; the default) or
    /// `"host"` (the visible list read back, only the visible rows decoded). The render is the
    /// same either way under `model.culling = "deformed"` or `"off"`; `"canonical"` always culls
    /// on the host.
    pub step_culling: StepCulling,
    /// Which thread runs a training step on the CPU backend (GPU backends always use the
    /// caller's: there the host only queues work, and the Cube runtime's buffers are per
    /// thread).
    pub step_thread: StepThread,
    /// Test-set evaluation every this many steps (0 = only at the end).
    pub eval_every: usize,
    /// Checkpoint every this many steps (0 = only at the end).
    pub checkpoint_every: usize,
    /// Rows of `train_log.csv`: one every this many steps.
    pub log_every: usize,
    /// Also keep `checkpoint-step{N}.safetensors` after these many steps (e.g. 7000: the model
    /// later GOPs warm-start from, spec §5).
    pub snapshot_steps: Vec<usize>,
    /// Warm start (spec §5): the anchors and decoders of this checkpoint, training from
    /// `warm_start_step` with fresh optimizers and restarted schedules. GIFStream: GOP 0's
    /// checkpoint after 7000 steps, continuing at 7001.
    pub warm_start: Option<std::path::PathBuf>,
    pub warm_start_step: usize,
    /// Fault injection: these steps' losses are replaced by NaN, to exercise the non-finite
    /// guard (skip, log, stop after repeats); the stability suite's `nan-injection` scene.
    pub inject_nonfinite: Vec<usize>,
    /// Temporal curriculum: the training frames open one after another from the GOP's first
    /// frame, all of them open at this fraction of max_steps (0: every frame from the start,
    /// GIFStream). While frames are opening, views are drawn uniformly from the open frames.
    pub frame_curriculum: f64,
    /// Coarse-to-fine γ(t): the motion head's time bands open from 1 to all 8 between the end of
    /// the canonical phase and this fraction of max_steps (0: all bands from the start,
    /// GIFStream).
    pub time_band_schedule: f64,
    /// How the motion gates are initialised at the end of the canonical phase (spec §7.3).
    pub init_dynamic: InitDynamic,
    /// While the curriculum opens frames, this share of the training views is drawn from the
    /// frontier (the newest tenth of the GOP's frames that are open) and the rest from all open
    /// frames: the newest frames are where motion is being tracked, and without it they end the
    /// curriculum with a fraction of the early frames' training.
    pub frontier_share: f64,
    /// Where a trajectory knot starts when the curriculum first opens a frame that uses it.
    pub knot_extrapolation: KnotExtrapolation,
    /// Under `knot_extrapolation = "moving-velocity"`: an anchor whose last segment moved it
    /// (motion gate × segment length) more than this many voxels (`model.voxel_size`) starts its
    /// new knot along that velocity; the others hold.
    pub knot_moving_voxels: f32,
    /// Whether an anchor that lost its moving object is searched for when a knot opens
    /// (`train/knot_search.rs`). Acts only with trajectories (`model.trajectory_spacing` > 0) and
    /// the temporal curriculum (`frame_curriculum` > 0), which open the knots; its first search
    /// takes each training camera's temporal median, holding one camera's GOP in memory at a time.
    pub knot_search: KnotSearch,
    /// Half-width of the search region around the predicted position, world units.
    pub knot_search_radius: f32,
    /// Colour agreement (mean-channel L1 distance, colours in [0, 1], averaged over the best
    /// three quarters of the cameras) below which the images count as showing an anchor's
    /// reference colour.
    pub knot_search_tolerance: f32,
    /// Side of the cubes (world units, at the anchors' predicted positions) whose lost anchors
    /// are searched for together under `knot_search = "patches"`.
    pub knot_search_patch: f32,
    /// Whether, after the knot search, the anchors it could not place (no colour of their own,
    /// or none found), and those it placed by a colour that may alias, move with their
    /// neighbours, by one motion per cell that their cameras confirm together
    /// (`train/knot_search.rs`, `place_by_consensus`). Acts only with `knot_search` on.
    pub knot_consensus: KnotConsensus,
    /// Side (world units, at the anchors' reference positions) of the cells whose anchors share
    /// one motion under `knot_consensus = "cells"`.
    pub knot_consensus_cell: f32,
    /// Whether anchors are seeded on objects that appear after frame 0 when a knot opens
    /// (`train/appearance_seeding.rs`; agreement within `knot_search_tolerance`). Acts, as the
    /// knot search, only with trajectories and the temporal curriculum; the knot search then
    /// follows the seeded anchors by their colours at the frame they were seeded at.
    pub appearance_seeding: AppearanceSeeding,
    /// Whether an anchor found at a later frame (seeded there, or grown from such anchors) is
    /// drawn at the open frames before it while the temporal curriculum opens frames
    /// (`train/seed_hold.rs`).
    pub seed_hold: SeedHold,
    /// The motion gate's starting logit on the initial anchors (0: σ = 0.5; `init_dynamic`, when
    /// on, overwrites it at the end of the canonical phase). Anchors grown later take their
    /// parents' gates, as before.
    pub motion_gate_start: f32,
    /// Whether the motion gates are trained while the temporal curriculum opens frames.
    pub motion_gate_hold: MotionGateHold,
    /// Whether the anchors the knot search finds on a moving object get their motion gates
    /// opened (`train/trainer/motion_search.rs`). Acts only with `knot_search` on (which finds
    /// them), so turning the search off turns this off too; refused with `init_dynamic`, which
    /// would reset the opened gates and leave their knots divided.
    pub moving_gates: MovingGates,
    /// The logit those gates are opened to (4: σ = 0.982).
    pub moving_gate_logit: f32,
    /// Whether, when a knot opens, each moving object's anchors move by one rigid motion (a
    /// turn and a translation) that the training images confirm, and turn their trajectory
    /// turns with it (`train/rigid_fit.rs`). Acts, as the knot search, only with trajectories
    /// and the temporal curriculum.
    pub rigid_fit: RigidFit,
    /// Under `rigid_fit = "objects"`: anchors on something moving closer than this (world
    /// units, at the previous knot's frame) belong to one object.
    pub rigid_fit_link: f32,
    /// Under `rigid_fit`: which anchors on something moving make one object besides those
    /// within `rigid_fit_link` of each other.
    pub rigid_fit_grouping: RigidFitGrouping,
    /// What training does with the knots (and turns) the rigid fit sets when a knot opens.
    pub fitted_knots: FittedKnots,
    /// Whether (and when) the moving objects' knot intervals opened so far are fitted again,
    /// against the model's rendering as trained by then (`train/knot_refit.rs`).
    pub knot_refit: KnotRefit,
    /// Under `knot_refit = "at-share"`: the refit's step as a share of `max_steps`.
    pub knot_refit_share: f64,
    /// What the knot refit does with the refitted anchors' per-frame feature streams.
    pub knot_refit_streams: KnotRefitStreams,
}

/// What `train.knot_refit` does with the per-frame feature streams of the anchors whose knots
/// it links again (`train.knot_refit_streams`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KnotRefitStreams {
    /// Kept as trained: the decoded Gaussians keep whatever they learned to draw on the
    /// anchors' old places.
    Kept,
    /// Each refitted anchor's stream, from the first frame of its first refitted interval on,
    /// set to its value at that frame (and its Adam moments there zeroed): the object is drawn
    /// as it was there, carried by the refitted motion, and the decoder's make-up for the old
    /// places (Follow-up 54) is dropped and learned again on the new ones. Measured worse
    /// (docs/results.md, Follow-up 55): the mean gap +0.27-0.31 dB on `crossing` and +0.21 on
    /// `large-motion` against the refit alone, so opt-in.
    FirstFrame,
}

/// When the moving objects' knot intervals are fitted again (`train.knot_refit`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KnotRefit {
    /// Never: each interval keeps the motion fitted when its knot opened.
    Off,
    /// Once, at the step the temporal curriculum opens the last frame: each interval's objects
    /// are refined against the model as trained by then, and every later knot follows.
    CurriculumEnd,
    /// Once, at `knot_refit_share` × `max_steps`: the intervals of the knots opened by then,
    /// the later ones fitted when they open from where the refit left the objects.
    AtShare,
}

/// What training does with the knots the rigid fit sets (`train.fitted_knots`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FittedKnots {
    /// Trained on from where the fit set them, as every other knot.
    Trained,
    /// Held where the fit set them: no later step moves them (the knots of anchors the fit did
    /// not move, and the fitted anchors' other knots, train).
    Held,
}

/// Whether a moving object's anchors get one rigid motion per knot.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RigidFit {
    /// Each anchor moves by its own translation (the knot search's, the gradient's).
    Off,
    /// The anchors on something moving at the previous knot's frame are grouped into objects
    /// (`rigid_fit_link`); each object's anchors move, from that frame to the new knot's, by the
    /// rigid motion under which their cameras see what they saw there, and their turns (under
    /// `model.trajectory_turn = "knots"`) compose its rotation.
    Objects,
    /// As `Objects`, then each object's motion refined against the model drawn at the new
    /// frame (its Gaussians at the previous knot's frame moved by the motion, every pixel of
    /// the training images around it compared; `train/rendered_fit.rs`), and it moves with the
    /// anchors its members enclose that no camera sees on something static.
    Rendered,
}

/// Which anchors on something moving the rigid fit groups into one object
/// (`train.rigid_fit_grouping`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RigidFitGrouping {
    /// Those within `rigid_fit_link` of each other at the previous knot's frame (single
    /// linkage).
    Near,
    /// Also those within twice that which both travelled at least `rigid_fit_link` over the
    /// interval before and kept their distance to within half of it: they moved as one body
    /// ([`crate::model::object_clusters::clusters_moved_as_one`]). Acts from knot 2 on (knot 1
    /// has no interval before it). Built to fit an object split into pieces
    /// as one; on `crossing` the second fast object beside the flying cube turned out to be its
    /// shadow on the floor, and a longer link alone (0.3) joined the cube to the slow objects.
    /// Decoded mean gap against "near": crossing 5.86 -> 5.90 / 6.26 -> 6.56 (seeds 42 / 43),
    /// large-motion 7.43 -> 7.36 (docs/results.md, Follow-up 56), so opt-in.
    KeptDistances,
}

/// Whether the knot search opens the motion gates of the anchors it finds on moving objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MovingGates {
    /// The gates train from where they start (GIFStream).
    Off,
    /// At the first knot searched after an anchor's reference frame, an anchor on moving
    /// pixels there whose motion gate is below `moving_gate_logit` gets it, its knots divided so
    /// that their displacement stays (the motion head's term, scaled by the gate too, grows with
    /// it; it is zero at the first knots, before the dynamic phase); the gate trains from there
    /// (held while frames open under `motion_gate_hold`). An anchor the search cannot move at
    /// that knot (gate × interpolation weight below 0.05) is not opened later.
    Open,
}

/// Whether the motion gates are held at their values while the temporal curriculum opens frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MotionGateHold {
    /// Trained from the first step, like every gate (GIFStream).
    Off,
    /// Not optimised until every frame is open (their Adam moments still follow the gradient);
    /// trained after.
    Curriculum,
}

/// The trajectory knots that frames 0..open touch, knots every `spacing` frames:
/// 0..=⌈(open − 1)/spacing⌉ (none for no open frame).
pub fn knots_reached(open: usize, spacing: usize) -> usize {
    match open {
        0 => 0,
        open => (open - 1).div_ceil(spacing.max(1)) + 1,
    }
}

/// Where a trajectory knot starts when the temporal curriculum first reaches it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KnotExtrapolation {
    /// At the previous knot: the anchor holds still until the new frames pull it.
    Hold,
    /// Along the last segment's velocity (2·K_{j−1} − K_{j−2}).
    Velocity,
    /// Along the last segment's velocity for anchors that moved (`train.knot_moving_voxels`),
    /// held for the rest: an object that moves more than its size per knot interval leaves the
    /// held knot's footprint and the photometric loss no longer pulls it, while extrapolating
    /// every anchor dragged the static room along (docs/results.md, "Moving objects").
    #[serde(rename = "moving-velocity")]
    MovingVelocity,
}

/// Whether lost moving anchors are searched for when a trajectory knot opens.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KnotSearch {
    /// New knots start by `knot_extrapolation` only.
    Off,
    /// Anchors on a moving object whose predicted position no longer shows their colour at their
    /// reference frame (frame 0, or the frame `appearance_seeding` placed them at)
    /// move to where the knot's frame's training images show it (multi-view photo-consistency
    /// on a grid within `knot_search_radius`), each anchor alone by its own colour.
    Photometric,
    /// As `Photometric`, but the lost anchors of each cube of side `knot_search_patch` share one
    /// displacement, the one under which their colours agree best together (each then refines
    /// it alone within a coarse grid step): on a patterned object a single colour matches many
    /// places, a patch of the pattern one (`train/knot_search.rs`, `SearchGrouping`).
    Patches,
}

/// Whether the knot search's placements are made consistent across an object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KnotConsensus {
    /// Each anchor where the search put it, or at its prediction.
    Off,
    /// The anchors on something moving in each cube of side `knot_consensus_cell` get the one
    /// motion (reference frame to the knot's) under which their cameras, each against itself,
    /// see what they saw at the reference frame; an anchor the search placed takes its own or a
    /// neighbour cube's motion wherever its cameras confirm it within `knot_search_tolerance`,
    /// one the search did not place only where its cameras agree better there than at its
    /// prediction.
    Cells,
}

/// Whether objects that no anchor covers when a knot's frame opens get anchors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AppearanceSeeding {
    /// Anchors come from frame 0's points and from growth only (GIFStream).
    Off,
    /// Moving pixels of the knot's frame are swept along their rays (multi-view
    /// photo-consistency); surfaces two cameras agree on that no anchor occupies get anchors.
    Photometric,
}

/// Whether a training step draws an anchor at the frames before the one it was found at
/// (`train.seed_hold`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SeedHold {
    /// At every open frame: before the next knot's searches set its path there, a seeded anchor
    /// waits at its seed in the earlier frames, where its object is not.
    Off,
    /// Only from its reference frame on, its knots held still (its appearance trains there),
    /// until the frame after it opens (the next knot's searches then set its path before it,
    /// `continue_backwards`); at every frame from then on, and once every frame is open.
    NextKnot,
    /// `NextKnot` where the temporal curriculum opens knots at least
    /// `seed_hold::LONG_INTERVAL_STEPS` steps apart, `Off` where closer (`train/seed_hold.rs`).
    LongIntervals,
}

/// Which thread runs a CPU training step (the same operations in the same order either way).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StepThread {
    /// A worker of rayon's pool: the step's parallel regions split their work with the other
    /// workers instead of being handed to the pool from outside (a futex wake and wait per
    /// region), and the rate term's own graph is a pool job (docs/benchmarks.md, "The step on
    /// the pool").
    Pool,
    /// The thread that calls `Trainer::step`; the rate term's graph on a thread of its own.
    Caller,
}

/// `init_dynamic` (spec §7.3): the motion gate from how hard each anchor's slots were pulled on
/// screen over time.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InitDynamic {
    /// GIFStream's code: at the end of the canonical phase, from the densification statistics,
    /// which accumulate only after `densify.start` (on a short schedule that is after the
    /// canonical phase, so every gate gets the floor 0.15).
    DensifyStatistics,
    /// The statistics also accumulate over the second half of the canonical phase (GIFStream's
    /// 30k schedule: statistics from 501, init at 900), so the gates are driven by data on any
    /// schedule.
    CanonicalStatistics,
    /// No initialisation: every motion gate keeps its initial value (σ(0) = 0.5).
    Off,
}

impl Default for ScheduleConfig {
    fn default() -> Self {
        Self {
            max_steps: 30_000,
            seed: 42,
            deformation_gate: 0.03,
            smooth_every: 4,
            step_culling: StepCulling::Device,
            step_thread: StepThread::Pool,
            eval_every: 7_000,
            checkpoint_every: 7_000,
            log_every: 10,
            snapshot_steps: Vec::new(),
            warm_start: None,
            warm_start_step: 7001,
            inject_nonfinite: Vec::new(),
            frame_curriculum: 0.0,
            time_band_schedule: 0.0,
            init_dynamic: InitDynamic::DensifyStatistics,
            frontier_share: 0.0,
            knot_extrapolation: KnotExtrapolation::Hold,
            knot_moving_voxels: 10.0,
            knot_search: KnotSearch::Off,
            knot_search_radius: 1.0,
            knot_search_tolerance: 0.08,
            knot_search_patch: 0.5,
            knot_consensus: KnotConsensus::Off,
            knot_consensus_cell: 0.3,
            appearance_seeding: AppearanceSeeding::Off,
            seed_hold: SeedHold::Off,
            motion_gate_start: 0.0,
            motion_gate_hold: MotionGateHold::Off,
            moving_gates: MovingGates::Off,
            moving_gate_logit: 4.0,
            rigid_fit: RigidFit::Off,
            rigid_fit_link: 0.15,
            rigid_fit_grouping: RigidFitGrouping::Near,
            fitted_knots: FittedKnots::Trained,
            knot_refit: KnotRefit::Off,
            knot_refit_share: 0.4,
            knot_refit_streams: KnotRefitStreams::Kept,
        }
    }
}

impl ScheduleConfig {
    /// Last step of the canonical phase (900 at 30k).
    pub fn canonical_until(&self) -> usize {
        (self.max_steps as f64 * self.deformation_gate) as usize
    }

    /// The phase `step` trains in: canonical up to [`Self::canonical_until`], dynamic after.
    pub fn phase_at(&self, step: usize) -> crate::model::view::Phase {
        if step <= self.canonical_until() {
            crate::model::view::Phase::Canonical
        } else {
            crate::model::view::Phase::Dynamic
        }
    }

    /// First step of the factor regulariser is the one after this (3900 at 30k).
    pub fn factor_reg_after(&self) -> usize {
        (self.max_steps as f64 * (self.deformation_gate + 0.1)) as usize
    }

    /// Frames open for training at `step` under the temporal curriculum: the first
    /// 1 + (T − 1)·step/(curriculum·max_steps) frames of the GOP, all of them without one.
    pub fn open_frames(&self, step: usize, frames: usize) -> usize {
        if self.frame_curriculum <= 0.0 || frames <= 1 {
            return frames;
        }
        let end = self.frame_curriculum * self.max_steps as f64;
        let progress = (step as f64 / end).min(1.0);
        (1 + ((frames - 1) as f64 * progress).floor() as usize).min(frames)
    }

    /// Whether the temporal curriculum is still opening frames at `step` (of `frames`).
    pub fn curriculum_opening(&self, step: usize, frames: usize) -> bool {
        self.open_frames(step, frames) < frames
    }

    /// How many trajectory knots (from knot 0) the frames open at `step` use, knots every
    /// `spacing` frames over `frames` frames.
    pub fn knots_reached_at(&self, step: usize, spacing: usize, frames: usize) -> usize {
        knots_reached(self.open_frames(step, frames), spacing)
    }

    /// The trajectory knots (after knot 0) that step `step`'s newly opened frames reach for the
    /// first time, knots every `spacing` frames over `frames` frames and `knots` knots in all;
    /// empty without the curriculum (every knot is open from the start).
    pub fn knots_opened(
        &self,
        step: usize,
        spacing: usize,
        frames: usize,
        knots: usize,
    ) -> std::ops::Range<usize> {
        if self.frame_curriculum <= 0.0 {
            return 0..0;
        }
        let before = match step {
            0 => 0,
            _ => self.knots_reached_at(step - 1, spacing, frames),
        };
        let from = before.max(1);
        let to = self.knots_reached_at(step, spacing, frames).min(knots);
        from..to.max(from)
    }

    /// The first step at which the curriculum opens a frame that trajectory knot `knot` shapes
    /// (knots every `spacing` frames over `frames` frames; 0 for knot 0 and without a curriculum).
    pub fn knot_opening_step(&self, knot: usize, spacing: usize, frames: usize) -> usize {
        let reaches = |step: usize| self.knots_reached_at(step, spacing, frames) > knot;
        // open_frames grows with the step: bisect for the first step that reaches the knot.
        let (mut low, mut high) = (0, self.max_steps);
        if reaches(low) {
            return 0;
        }
        if !reaches(high) {
            return high;
        }
        while high - low > 1 {
            let mid = (low + high) / 2;
            if reaches(mid) {
                high = mid;
            } else {
                low = mid;
            }
        }
        high
    }

    /// γ(t) bands open at `step` (coarse to fine from the end of the canonical phase).
    pub fn time_bands(&self, step: usize) -> f32 {
        let all = crate::model::view::ALL_TIME_BANDS;
        if self.time_band_schedule <= 0.0 {
            return all;
        }
        let start = self.canonical_until() as f64;
        let end = self.time_band_schedule * self.max_steps as f64;
        if end <= start {
            return all;
        }
        let progress = ((step as f64 - start) / (end - start)).clamp(0.0, 1.0);
        (1.0 + (all as f64 - 1.0) * progress) as f32
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossConfig {
    /// Weight of D-SSIM; L1 gets 1 − this.
    pub ssim_lambda: f32,
    pub scale_reg: f32,
    pub factor_reg: f32,
    pub smooth_reg: f32,
    /// What the smoothness term compares of the motion head.
    pub smooth_motion: SmoothMotion,
    /// Which slots the smoothness term's opacity, colour and covariance means run over.
    pub smooth_slots: SmoothSlots,
    /// Weight of the trajectory coherence term (`coherence.rs`): mean over anchors and knots of
    /// |mf·K − mean of mf·K over the anchor's motion peers| (L1, so objects may separate).
    pub trajectory_coherence: f32,
    /// Weight of the trajectory curvature term (`curvature.rs`): mean over anchors and interior
    /// knot coordinates of |mf·(K_{j−1} − 2·K_j + K_{j+1})| over the opened knots (L1, so a
    /// path bends only where the images insist). 0 = off, the default: at 30 and 100 it cost
    /// `large-motion` 1.6-1.8 dB of mean gap (the bounce's turns) and did not help `crossing`
    /// (+0.19 / +0.44; its turning cube's anchors move on arcs, bent at every knot); at 3
    /// `crossing` gained 0.61 dB and `large-motion` lost 0.42: no λ helps both (seed 42,
    /// docs/results.md Follow-up 43).
    pub trajectory_curvature: f32,
    /// Side of the cells whose anchors are each other's motion peers.
    pub coherence_cell: f32,
    /// Where the motion peers' cells are taken: canonical space alone, or the positions at
    /// several frames (`coherence.rs`).
    pub coherence_groups: CoherenceGroups,
    /// L1 weight of a training view's moving pixels relative to its static ones (the
    /// evaluation's motion mask against the camera's temporal median, `[eval]`'s threshold and
    /// dilation), the weights scaled to mean 1 per view; 1 = GIFStream's plain L1. Not in
    /// GIFStream: DyNeRF's importance sampling by departure from the temporal median (ISG) as a
    /// weight, since a splatting renderer draws whole images.
    pub moving_weight: f32,
}

/// How the trajectory coherence term groups anchors into motion peers (`loss.coherence_groups`;
/// not in GIFStream, `train/coherence.rs`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoherenceGroups {
    /// Anchors of one cell of the canonical (frame-0) space. An object's outline shares cells
    /// with what lies behind it at frame 0, so static peers hold the outline back (docs/results.md,
    /// Follow-up 14).
    Canonical,
    /// Anchors in one cell at each of a few frames spread over the clip (regrouped as the
    /// trajectories change): peers are anchors that move together, so a moving object's anchors
    /// are pulled towards the object's motion and the room's towards the room's.
    SpaceTime,
}

/// The motion term of the temporal smoothness loss (spec §4.5).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SmoothMotion {
    /// The raw head output Δ(t) − Δ(t′) (acags before 2026-11, a misreading of the spec): every
    /// visible anchor's time dependence is penalised, static ones included, hardest where the
    /// motion gate is small.
    Raw,
    /// The applied motion mf·Δ(t) − mf′·Δ(t′), as GIFStream's code compares it (its
    /// `decoding_features` returns the gated motion): only motion that reaches the render.
    Gated,
}

/// Which Neural Gaussians of an anchor the temporal smoothness term averages over (the same
/// under GIFStream, whose slots are all active; they differ only under ACA-GS's AAC).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SmoothSlots {
    /// All K_max decoded slots, switched off or not: GIFStream's mean over every decoded slot
    /// (spec §4.5; under AAC "All 10 slots are still decoded densely", §4.4). With K_max = 10
    /// and at least half the slots off, the active slots' weight is halved or less, and the free
    /// slots' colour and covariance, which no render uses, enter the term.
    All,
    /// Only the slots AAC has on, as the rate term masks gated offsets (spec §14 A10). Measured
    /// against `all` on `synthetic:fast` (docs/results.md): unpaired, six same-seed pairs were
    /// neutral (Follow-up 35); paired (Follow-up 38), +AAC gains +0.41 / +0.57 dB on the moving
    /// pixels without the codec on two seeds, ACA-GS with the `paired` init +0.15 / +0.58 dB;
    /// the shipped ACA-GS (`paired-drawn-units`, decoded) is level (−0.06 / −0.03 dB moving at
    /// 1.00× / 0.96× the file), so the default stays `all`.
    Active,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            ssim_lambda: 0.2,
            scale_reg: 0.01,
            factor_reg: 0.005,
            smooth_reg: 0.005,
            smooth_motion: SmoothMotion::Gated,
            smooth_slots: SmoothSlots::All,
            trajectory_coherence: 0.0,
            trajectory_curvature: 0.0,
            coherence_cell: 0.3,
            coherence_groups: CoherenceGroups::Canonical,
            moving_weight: 1.0,
        }
    }
}

/// Initial learning rates and their exponential decay to `lr · final_factor` at max_steps
/// (spec §7.1; a final factor of 1 is a constant rate).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearningRates {
    pub offsets: f64,
    pub offsets_final_factor: f64,
    pub scales: f64,
    pub features: f64,
    pub time_features: f64,
    pub factors: f64,
    pub mlp_opacity: f64,
    pub mlp_opacity_final_factor: f64,
    pub mlp_cov: f64,
    pub mlp_cov_final_factor: f64,
    pub mlp_color: f64,
    pub mlp_color_final_factor: f64,
    pub mlp_motion: f64,
    pub mlp_motion_final_factor: f64,
    /// AAFM mask logits m (HAC: 1e-2 → 1e-4, spec §14 A11).
    pub mask: f64,
    pub mask_final_factor: f64,
    /// The conditional entropy models (spec §7.1: 1e-4, constant).
    pub entropy: f64,
    /// Anchor trajectory knots (world units per Adam step; not in GIFStream), decaying like
    /// the offsets.
    pub trajectory: f64,
    pub trajectory_final_factor: f64,
    /// Whose clock the knots' decay follows (`per-knot`: each knot's from the step the
    /// temporal curriculum opens it).
    pub trajectory_schedule: TrajectorySchedule,
    /// Trajectory turns (`model.trajectory_turn`; radians of rotation vector per Adam step),
    /// on the knots' schedule (`trajectory_final_factor`, `trajectory_schedule`).
    pub turn: f64,
    /// In which units a knot's Adam step is taken.
    pub knot_step: KnotStep,
    /// How the anchor features' rate follows the feature width C_F.
    pub feature_width: FeatureWidthRate,
}

impl LearningRates {
    /// The anchor features' rate for `model` (`lr.features`, scaled by `lr.feature_width`).
    pub fn features_for(&self, model: &ModelConfig) -> f64 {
        match self.feature_width {
            FeatureWidthRate::PerChannel => self.features,
            FeatureWidthRate::BaselineStep => {
                let base = model.baseline_decoder_sizes().feature_dim as f64;
                self.features * (base / model.feature_dim as f64).sqrt()
            }
        }
    }
}

/// How the anchor features' Adam rate follows the feature width C_F (`lr.feature_width`).
///
/// Adam moves every feature channel by about its rate, and each decoder's hidden unit sums its
/// C_F inputs, so at one rate a wider feature moves the decoded Gaussians further per step
/// (ACA-GS's C_F = 48 against GIFStream's 24: 1.25× for updates of random sign through the
/// paired weights, up to 1.76× for updates aligned with them). On the short schedule, whose
/// feature rate is 5× the spec's (for the codec's rounding, default.toml), the wide model
/// prunes more anchors at the first pruning step; `baseline-step` brings that back to the
/// narrow model's. On `fast` without the codec it gains +0.14 / +0.36 dB full frame and
/// +0.41 / +0.47 dB on the moving pixels with `paired-drawn-units` (1.06× / 1.01× the anchors),
/// +0.10 / +0.52 dB full frame with `paired` (docs/results.md, Follow-up 38); decoded, one key
/// apart, it buys quality with a larger file (1.11-1.12× at one threshold) and is level at
/// equal size (one seed), so the default stays per channel (Follow-up 39).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FeatureWidthRate {
    /// Every channel at `lr.features`, whatever C_F (GIFStream and the spec).
    #[default]
    PerChannel,
    /// `lr.features · √(C_F,base / C_F)`, the baseline's C_F being `model.baseline_feature_dim`
    /// (unset: the model's own, a factor of 1): the feature update's norm is the baseline's.
    /// Not in the paper or GIFStream, which train one width each.
    BaselineStep,
}

/// In which units an Adam step moves a trajectory knot (and its turn).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KnotStep {
    /// Knot units, as every parameter: Adam moves a knot by about its rate whatever the
    /// gradient's size, so under a small motion gate (a still anchor, whose knots barely change
    /// the render and get a weak, noisy gradient) the knots wander as far as a moving anchor's.
    Knot,
    /// Rendered units: each anchor's knot update times its motion gate σ(factor), so a step
    /// moves what renders (gate × knot) by about the rate, whatever the gate.
    Rendered,
}

/// Whose clock a trajectory knot's learning-rate decay follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrajectorySchedule {
    /// The run's, like every other rate: under the temporal curriculum the last frames' knots
    /// open at 40 % of the run with a quarter of the starting rate (0.03^0.4), so a knot can
    /// follow a quarter of the distance per frame late in the video that it could early on.
    Run,
    /// Each knot's own: from `lr.trajectory` at the step the curriculum first opens a frame that
    /// uses the knot down to `lr.trajectory · trajectory_final_factor` at max_steps, so every
    /// knot starts to track at the same speed (docs/results.md, "Knot rate"). Without the
    /// curriculum every knot opens at step 0 and this equals `run`.
    PerKnot,
}

impl TrajectorySchedule {
    /// The rate of each of `knots` knots at `step` (counted from the schedule's origin), where
    /// `opened(j)` is the step the curriculum opens knot j.
    pub fn knot_rates(
        self,
        lr: f64,
        final_factor: f64,
        step: usize,
        max_steps: usize,
        knots: usize,
        opened: impl Fn(usize) -> usize,
    ) -> Vec<f64> {
        (0..knots)
            .map(|j| match self {
                Self::Run => exponential_lr(lr, final_factor, step, max_steps),
                Self::PerKnot => {
                    let open = opened(j).min(max_steps.saturating_sub(1));
                    exponential_lr(
                        lr,
                        final_factor,
                        step.saturating_sub(open),
                        max_steps - open,
                    )
                }
            })
            .collect()
    }
}

impl Default for LearningRates {
    fn default() -> Self {
        Self {
            offsets: 1e-2,
            offsets_final_factor: 0.03,
            scales: 7e-3,
            features: 7.5e-3,
            time_features: 7.5e-3,
            factors: 1e-3,
            mlp_opacity: 2e-3,
            mlp_opacity_final_factor: 0.01,
            mlp_cov: 4e-3,
            mlp_cov_final_factor: 1.0,
            mlp_color: 8e-3,
            mlp_color_final_factor: 0.01,
            mlp_motion: 8e-3,
            mlp_motion_final_factor: 0.01,
            mask: 1e-2,
            mask_final_factor: 0.01,
            entropy: 1e-4,
            trajectory: 0.01,
            trajectory_final_factor: 0.03,
            trajectory_schedule: TrajectorySchedule::Run,
            knot_step: KnotStep::Knot,
            turn: 0.01,
            feature_width: FeatureWidthRate::PerChannel,
        }
    }
}

/// lr · final_factor^(step / max_steps): torch's ExponentialLR with γ = final_factor^(1/max_steps).
pub fn exponential_lr(lr: f64, final_factor: f64, step: usize, max_steps: usize) -> f64 {
    lr * final_factor.powf(step as f64 / max_steps.max(1) as f64)
}

/// GIFStream's densification strategy (spec §8).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DensifyConfig {
    /// Gradient threshold of level 0 (GIFStream class default 9e-5; configs 2e-4 to 6e-4).
    pub grad_threshold: f32,
    /// Statistics accumulate after this step; grow/prune on steps after it.
    pub start: usize,
    /// Grow/prune before this step; mask pruning from it on.
    pub stop: usize,
    pub every: usize,
    pub check_interval: f32,
    pub success_threshold: f32,
    pub prune_opacity: f32,
    pub update_depth: usize,
    pub update_init_factor: usize,
    pub update_hierarchy_factor: usize,
    /// Weight of the per-frame peak against the temporal mean in the statistics.
    pub peak_ratio: f32,
    /// When anchors whose pruning gate has closed leave training (`train::refine`).
    pub closed_pruning: ClosedPruning,
}

/// When closed anchors (pruning gate σ < 0.1, or no active slot) are removed in training.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClosedPruning {
    /// Every `densify.every` steps from `densify.stop` on, and at the last step (Follow-up 45).
    Periodic,
    /// Only at the last step: the stored model is the file's, but a gate that closes for a
    /// while after densification can reopen (its σ keeps the straight-through gradient).
    LastStep,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        Self {
            grad_threshold: 9e-5,
            start: 500,
            stop: 15_000,
            every: 100,
            check_interval: 100.0,
            success_threshold: 0.8,
            prune_opacity: 0.005,
            update_depth: 3,
            update_init_factor: 16,
            update_hierarchy_factor: 4,
            peak_ratio: 0.1,
            closed_pruning: ClosedPruning::Periodic,
        }
    }
}

/// How many Neural Gaussians an anchor may have.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CardinalityMode {
    /// GIFStream: every anchor spawns `model.slots` Gaussians.
    Fixed,
    /// ACA-GS AAC: `model.slots` (K_max) slots decoded, a per-slot gate, dead slots deactivated
    /// and relocated to important anchors.
    Adaptive,
}

/// What "dead" measures (spec §14 A3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImportanceTest {
    /// The paper's Eq. 1: Σ of the slot's opacity over the relocation window.
    Sum,
    /// The sum divided by the iterations the anchor was visible (GIFStream `prune_opa` style).
    MeanPerVisit,
}

/// ACA-GS Adaptive Anchor Cardinality (paper §3.1, spec §12). Defaults are the paper's
/// 30k-step values; `configs/aca-gs.toml` scales the schedule for the short synthetic runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AacConfig {
    pub mode: CardinalityMode,
    /// Slots 0..initial_active of every new anchor start active (spec §14 A1: 5 of 10).
    pub initial_active: usize,
    /// First relocation step (3000).
    pub start: usize,
    /// No relocation after this step (15000, spec §14 A5).
    pub stop: usize,
    /// Relocation interval, also the importance window T_R and the young-anchor age (500).
    pub every: usize,
    /// τ: active slots with importance below this are dead (0.005).
    pub dead_threshold: f32,
    pub importance: ImportanceTest,
    /// ρ: at most this fraction of the active population is relocated per step (0.2).
    pub relocate_fraction: f32,
    /// δ: offset = parent + |parent| ⊙ N(0, δ²) (0.05).
    pub perturbation: f32,
    /// Draws of a parent before a relocation is dropped (spec §14 A6: 3).
    pub resample_tries: usize,
    /// Which free slot of the parent's anchor a relocated Gaussian takes.
    pub target_slot: RelocationSlot,
}

/// Which free slot of the parent's anchor a relocated Gaussian takes. A slot's opacity, colour
/// and covariance are decoded from its anchor's feature and its slot index, never from its
/// offset, so the slot decides whether the relocated Gaussian can be seen at all.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RelocationSlot {
    /// The lowest free slot (spec §12.3 step 4) — often one this same step just switched off
    /// because it decoded no opacity, so it stays dead (churn, docs/results.md).
    LowestFree,
    /// The free slot with the largest importance over the window (its opacity before the slot
    /// gates, summed), so the Gaussian lands in a slot its anchor's decoder makes visible.
    /// When every free slot decoded α ≤ 0 it still picks one, and that Gaussian never renders
    /// (α = max(0, ·) passes no gradient): measured churn 80 % (docs/results.md).
    MostOpaqueFree,
    /// The most opaque free slot among those whose importance over the window reached τ, i.e.
    /// that would have passed this step's test had they been on; parents are drawn only among
    /// anchors that have such a slot, and the budget left over when none has is not spent. The
    /// relocated Gaussian is visible from the first step, so it is judged on what it shows.
    AboveThresholdFree,
}

impl Default for AacConfig {
    fn default() -> Self {
        Self {
            mode: CardinalityMode::Fixed,
            initial_active: 5,
            start: 3000,
            stop: 15_000,
            every: 500,
            dead_threshold: 0.005,
            importance: ImportanceTest::Sum,
            relocate_fraction: 0.2,
            perturbation: 0.05,
            resample_tries: 3,
            target_slot: RelocationSlot::LowestFree,
        }
    }
}

impl AacConfig {
    /// Whether `step` adds to the importance window: the T_R = `every` steps before each
    /// relocation (spec §12.2).
    pub fn accumulates_at(&self, step: usize) -> bool {
        self.mode == CardinalityMode::Adaptive
            && step > self.start.saturating_sub(self.every)
            && step <= self.stop
    }

    /// Whether `step` (0-based, after its optimizer update) is a relocation step.
    pub fn relocates_at(&self, step: usize) -> bool {
        self.mode == CardinalityMode::Adaptive
            && step >= self.start
            && step <= self.stop
            && step % self.every == 0
    }
}

/// Whether anchors carry a learned mask over the adaptive half of their feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FeatureMaskMode {
    Off,
    Adaptive,
}

/// ACA-GS AAFM + CR (paper §3.2-§3.3, spec §13).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AafmConfig {
    pub mode: FeatureMaskMode,
    /// F_base: the first channels, never masked; the remaining `model.feature_dim − base` are
    /// F_adapt (24 | 24 in the paper).
    pub base_channels: usize,
    /// γ: σ(m) above this keeps F_adapt (0.01).
    pub threshold: f32,
    /// λ_M on mean σ(m) (8e-3).
    pub mask_weight: f32,
    /// λ_CR on mean σ(d)·(1 − σ(m)) (0.1).
    pub cr_weight: f32,
    /// First step of the CR term (paper: 0). Until the factor regulariser has separated static
    /// from dynamic anchors every σ(d) is ≈ 0.5 and CR pushes every mask open; a later start
    /// lets L_M act first (docs/results.md).
    pub cr_start: usize,
    /// What else, besides `cr_start`, decides when CR starts.
    pub cr_trigger: CrTrigger,
    /// `CrTrigger::GateShare`: the share of anchors whose time gate σ(d) must lie below
    /// λ_M / λ_CR (where CR lets a mask close) before CR starts.
    pub cr_gate_share: f32,
    /// Which of CR's two factors its gradient reaches.
    pub cr_gradient: CrGradient,
}

/// When the CR term starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CrTrigger {
    /// At `aafm.cr_start` (the paper: step 0).
    Step,
    /// At the first step from `aafm.cr_start` on at which at least `aafm.cr_gate_share` of the
    /// anchors have σ(d) < λ_M / λ_CR, checked every `CR_TRIGGER_CHECK_EVERY` steps; once on,
    /// it stays on (the step is checkpointed). CR's net pull on a mask logit is
    /// (λ_M − λ_CR·σ(d))·σ'(m): started while the time gates are uninformed (σ(d) ≈ 0.5) it
    /// drives every mask open into saturation, where the decayed mask rate cannot bring it back
    /// on a short schedule (docs/results.md, Follow-up 4). Not in the paper, which trains 30k
    /// steps. Measured worse than `Step` on the default build (seeds 42, 43: −0.65 / −0.34 dB
    /// decoded at 0.99 / 0.90× the file; docs/results.md, Follow-up 5).
    GateShare,
}

/// Steps between two checks of `CrTrigger::GateShare` (one scalar read-back each).
pub const CR_TRIGGER_CHECK_EVERY: usize = 10;

impl AafmConfig {
    /// σ(d) below which CR's pull on a mask (λ_CR·σ(d)) is weaker than L_M's push (λ_M).
    pub fn cr_neutral_gate(&self) -> f32 {
        self.mask_weight / self.cr_weight
    }

    /// Whether CR starts at `step` given the share of anchors with σ(d) below
    /// [`Self::cr_neutral_gate`] (`None`: not measured at this step).
    pub fn cr_starts_at(&self, step: usize, gate_share: Option<f32>) -> bool {
        if !self.cr_may_start_at(step) {
            return false;
        }
        match self.cr_trigger {
            CrTrigger::Step => true,
            CrTrigger::GateShare => gate_share.is_some_and(|s| s >= self.cr_gate_share),
        }
    }

    /// Whether `step` is one at which `CrTrigger::GateShare` measures the gates.
    pub fn cr_checks_gates_at(&self, step: usize) -> bool {
        self.cr_trigger == CrTrigger::GateShare
            && self.cr_may_start_at(step)
            && (step - self.cr_start) % CR_TRIGGER_CHECK_EVERY == 0
    }

    /// CR is on (weight > 0) and `aafm.cr_start` has passed: the trigger decides from here.
    fn cr_may_start_at(&self, step: usize) -> bool {
        self.cr_weight > 0.0 && step >= self.cr_start
    }
}

/// Which factors of L_CR = mean σ(d)·(1 − σ(m)) receive its gradient.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CrGradient {
    /// The mask logits m only: σ(d) is a stop-gradient weight (spec §14 A13's resolution), so CR
    /// never closes a time gate. Measured worse than `MaskAndGate` (docs/results.md).
    MaskOnly,
    /// Both, as the paper writes it (no stop-gradient): CR also pushes the time gate d of an
    /// anchor whose adaptive channels are masked towards closed (paper §3.3's stated purpose).
    /// The default: the paper wins over the spec's resolution by measurement.
    MaskAndGate,
}

impl Default for AafmConfig {
    fn default() -> Self {
        Self {
            mode: FeatureMaskMode::Off,
            base_channels: 24,
            threshold: 0.01,
            mask_weight: 8e-3,
            cr_weight: 0.1,
            cr_start: 0,
            cr_trigger: CrTrigger::Step,
            cr_gate_share: 0.5,
            // The paper's form, not spec §14 A13's stop-gradient: on synthetic:fast, two seeds,
            // it gave +1.17 / +0.62 dB decoded PSNR at −12 % / −11 % size (docs/results.md).
            cr_gradient: CrGradient::MaskAndGate,
        }
    }
}

/// Whether training simulates the codec's quantisation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CompressionMode {
    /// Full-precision training (the "w/o compression" ablation rows); `acags compress` still
    /// works but rounds a model that never saw the grid.
    Off,
    /// GIFStream's schedule: faint noise, then uniform noise, then straight-through rounding.
    Simulate,
}

/// Compression simulation (spec §9). The phase boundaries are fractions of `train.max_steps`
/// so shortened schedules keep GIFStream's proportions (6k and 20k of 30k).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CompressionConfig {
    pub mode: CompressionMode,
    /// Step sizes and rate weight: r0 (finest) … r3.
    pub rate: RatePreset,
    /// Uniform noise of one step from this fraction of training (0.2).
    pub noise_from: f64,
    /// Straight-through rounding from this fraction (2/3).
    pub round_from: f64,
    /// The rate term (entropy models) from this fraction (1/3: GIFStream's step 10k of 30k).
    pub rate_from: f64,
    /// Fraction of anchors (drawn anew every step) whose bits estimate the rate: 1 is
    /// GIFStream (all anchors); smaller is an unbiased, cheaper estimate (HAC uses 0.05).
    pub rate_sample: f64,
    /// Which values the rate's bit estimate prices (the contexts are the simulated ones in both).
    pub bit_estimate: BitEstimate,
    /// Where the rate term's forward and backward run: in the step's graph, or in a graph of
    /// its own on a second thread, overlapping the render's forward and backward.
    pub rate_graph: RateGraph,
    /// Whether the rate term prices the anchor trajectories' knots (`codec::rate`).
    pub trajectory_rate: TrajectoryRate,
    /// Per-attribute steps that replace the preset's (`compression.steps.time_features = 0.25`);
    /// training simulates and the encoder codes on the same grid, and the file records it.
    pub steps: StepOverrides,
}

/// Quantisation steps that replace `compression.rate`'s for single attributes (unset: the
/// preset's). Absolute, so they hold whatever preset `acags compress --rate` names.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StepOverrides {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log_scales: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub offsets: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub features: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_features: Option<f32>,
    /// Gate values in [0, 1]; 1/step must be a whole number of levels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub factors: Option<f32>,
    /// The motion gate alone (default: the factors' step); 1/step a whole number.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motion_gate: Option<f32>,
    /// World units.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<f32>,
    /// Radians of rotation vector.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub turn: Option<f32>,
}

impl StepOverrides {
    /// `preset` with the set fields replaced.
    pub fn apply(&self, preset: QuantizationSteps) -> QuantizationSteps {
        QuantizationSteps {
            log_scales: self.log_scales.unwrap_or(preset.log_scales),
            offsets: self.offsets.unwrap_or(preset.offsets),
            features: self.features.unwrap_or(preset.features),
            time_features: self.time_features.unwrap_or(preset.time_features),
            factors: self.factors.unwrap_or(preset.factors),
            motion_gate: self.motion_gate.or(preset.motion_gate),
            trajectory: self.trajectory.unwrap_or(preset.trajectory),
            turn: self.turn.unwrap_or(preset.turn),
        }
    }

    fn validate(&self) -> Result<()> {
        let named = [
            ("log_scales", self.log_scales),
            ("offsets", self.offsets),
            ("features", self.features),
            ("time_features", self.time_features),
            ("factors", self.factors),
            ("motion_gate", self.motion_gate),
            ("trajectory", self.trajectory),
            ("turn", self.turn),
        ];
        for (name, step) in named {
            if let Some(s) = step
                && !(s > 0.0 && s.is_finite())
            {
                bail!("compression.steps.{name} must be positive and finite, got {s}");
            }
        }
        for (name, step) in [("factors", self.factors), ("motion_gate", self.motion_gate)] {
            if let Some(s) = step {
                let levels = 1.0 / s;
                if !(levels <= 65536.0 && (levels - levels.round()).abs() < 1e-3) {
                    bail!(
                        "compression.steps.{name} must be 1/n for a whole n <= 65536 (the \
                         gate's levels), got {s}"
                    );
                }
            }
        }
        Ok(())
    }
}

/// Whether the training rate term prices the trajectory knots, which GIFStream does not have.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TrajectoryRate {
    /// Not priced: the knots move only by the photometric loss (and the fits).
    Unpriced,
    /// Priced as the file's per-axis coding prices them: knot-to-knot increments under one
    /// Gaussian per axis fitted to them, over the anchors whose motion gate is open.
    Factorized,
}

/// Where the training step evaluates the rate term (the same values and gradients either way,
/// up to the order in which two gradient parts are summed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RateGraph {
    /// One autodiff graph for the whole objective (GIFStream).
    Shared,
    /// Its own graph, built and differentiated on another thread while the step renders,
    /// its gradients added to the step's before the optimizers. On the CPU backend most of the
    /// step's tensor ops run on one thread, so the rate term then uses a core that idles.
    Concurrent,
}

impl Default for CompressionConfig {
    fn default() -> Self {
        Self {
            mode: CompressionMode::Simulate,
            rate: RatePreset::R0,
            noise_from: 0.2,
            round_from: 2.0 / 3.0,
            rate_from: 1.0 / 3.0,
            rate_sample: 1.0,
            // Not GIFStream's estimate: on synthetic:fast, seeds 42/43, pricing the simulated
            // values gave a 15 % smaller file at +0.06/+0.22 dB decoded PSNR (docs/results.md,
            // Follow-up 3).
            bit_estimate: BitEstimate::Simulated,
            // Not GIFStream's single graph: the same values up to the order of one sum
            // (tests/train_run.rs), the rate-term steps 1.13x faster on 2 cores. Quality alone,
            // five seeds: decoded +0.06 dB mean (−0.11 to +0.51), moving pixels +0.02, within
            // the ±0.4-0.5 dB that any parting of two runs gives (docs/benchmarks.md, "The
            // rate-term changes, one at a time ...").
            rate_graph: RateGraph::Concurrent,
            trajectory_rate: TrajectoryRate::Unpriced,
            steps: StepOverrides::default(),
        }
    }
}

impl CompressionConfig {
    /// The grid training simulates and the encoder codes on: the preset's steps with the
    /// overrides applied.
    pub fn quantization_steps(&self) -> QuantizationSteps {
        self.steps_for(self.rate)
    }

    /// The grid of `rate` (e.g. `acags compress --rate`) with this config's overrides.
    pub fn steps_for(&self, rate: RatePreset) -> QuantizationSteps {
        self.steps.apply(rate.steps())
    }

    /// Whether the rate term is on at `step` (GIFStream: step > 10000 of 30000).
    pub fn rate_at(&self, step: usize, max_steps: usize) -> bool {
        self.mode == CompressionMode::Simulate && step as f64 > self.rate_from * max_steps as f64
    }

    /// The simulation's phase at `step` of `max_steps` (None when off).
    pub fn phase_at(&self, step: usize, max_steps: usize) -> Option<QuantizationPhase> {
        if self.mode == CompressionMode::Off {
            return None;
        }
        let progress = step as f64 / max_steps as f64;
        Some(if progress < self.noise_from {
            QuantizationPhase::Faint
        } else if progress < self.round_from {
            QuantizationPhase::Noise
        } else {
            QuantizationPhase::Round
        })
    }
}

impl TrainConfig {
    /// A config from its TOML text, as if it were the file `origin` (named in errors; an
    /// `extends` in it is looked for beside it), with `key=value` overrides applied.
    pub fn parse(text: &str, origin: &str, overrides: &[String]) -> Result<Self> {
        Self::from_source(text, &ConfigSource::File(origin.into()), overrides)
    }

    /// An embedded config by file name (`default.toml`, `aca-gs.toml`).
    pub fn embedded(name: &str, overrides: &[String]) -> Result<Self> {
        let (name, text) =
            embedded_config(name).with_context(|| format!("`{name}` is not an embedded config"))?;
        Self::from_source(text, &ConfigSource::Embedded(name.to_string()), overrides)
    }

    fn from_source(text: &str, source: &ConfigSource, overrides: &[String]) -> Result<Self> {
        let mut table = resolve_extends(text, source, &mut Vec::new())?;
        for o in overrides {
            apply_override(&mut table, o)?;
        }
        let config: Self = serde_path_to_error::deserialize(toml::Value::Table(table))
            .map_err(|e| anyhow::anyhow!("{source}: {} at `{}`", e.inner(), e.path()))?;
        config.validate().with_context(|| format!("{source}"))?;
        Ok(config)
    }

    /// Reads a config file, or the embedded default when `path` is `None`.
    pub fn load(path: Option<&Path>, overrides: &[String]) -> Result<Self> {
        match path {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("cannot read config {}", p.display()))?;
                Self::parse(&text, &p.display().to_string(), overrides)
            }
            None => Self::embedded("default.toml", overrides),
        }
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("a config serialises")
    }

    pub fn validate(&self) -> Result<()> {
        let m = &self.model;
        if m.feature_dim == 0 || m.time_feature_dim == 0 || m.slots == 0 {
            bail!("model.feature_dim, time_feature_dim and slots must be positive");
        }
        if !(m.voxel_size > 0.0 && m.voxel_size.is_finite()) {
            bail!("model.voxel_size must be positive, got {}", m.voxel_size);
        }
        if self.train.max_steps == 0 {
            bail!("train.max_steps must be positive");
        }
        if !(0.0..1.0).contains(&self.train.deformation_gate) {
            bail!("train.deformation_gate must be in [0, 1)");
        }
        if self.densify.every == 0 || self.train.log_every == 0 {
            bail!("densify.every and train.log_every must be positive");
        }
        if self.data.downscale == 0 {
            bail!("data.downscale must be at least 1");
        }
        let baseline = m.baseline_decoder_sizes();
        if baseline.feature_dim == 0
            || baseline.feature_dim > m.feature_dim
            || baseline.slots == 0
            || baseline.slots > m.slots
        {
            bail!(
                "model.baseline_feature_dim = {} and model.baseline_slots = {} must be in \
                 1..=model.feature_dim ({}) and 1..=model.slots ({}): the baseline the decoders \
                 are paired with is a narrower model",
                baseline.feature_dim,
                baseline.slots,
                m.feature_dim,
                m.slots
            );
        }
        let aac = &self.aac;
        if aac.mode == CardinalityMode::Adaptive {
            if aac.initial_active == 0 || aac.initial_active >= m.slots {
                bail!(
                    "aac.initial_active = {} must be in 1..model.slots ({}): relocation needs free slots \
                     (the paper: 5 of 10)",
                    aac.initial_active,
                    m.slots
                );
            }
            if aac.every == 0 {
                bail!("aac.every must be positive");
            }
            if !(0.0..=1.0).contains(&aac.relocate_fraction) {
                bail!("aac.relocate_fraction must be in [0, 1]");
            }
            if !(aac.dead_threshold >= 0.0 && aac.perturbation >= 0.0) {
                bail!("aac.dead_threshold and aac.perturbation must be non-negative");
            }
        }
        let c = &self.compression;
        c.steps.validate()?;
        if !(c.rate_sample > 0.0 && c.rate_sample <= 1.0) {
            bail!(
                "compression.rate_sample must be in (0, 1], got {}",
                c.rate_sample
            );
        }
        if !(0.0..=1.0).contains(&c.rate_from) {
            bail!(
                "compression.rate_from must be in [0, 1], got {}",
                c.rate_from
            );
        }
        if !(0.0 <= c.noise_from && c.noise_from <= c.round_from && c.round_from <= 1.0) {
            bail!(
                "compression: need 0 <= noise_from ({}) <= round_from ({}) <= 1",
                c.noise_from,
                c.round_from
            );
        }
        let aafm = &self.aafm;
        if aafm.mode == FeatureMaskMode::Adaptive {
            if aafm.base_channels >= m.feature_dim {
                bail!(
                    "aafm.base_channels = {} leaves no adaptive channels of model.feature_dim = {}",
                    aafm.base_channels,
                    m.feature_dim
                );
            }
            if !(aafm.threshold > 0.0 && aafm.threshold < 1.0) {
                bail!("aafm.threshold must be in (0, 1)");
            }
            if !(aafm.cr_gate_share > 0.0 && aafm.cr_gate_share <= 1.0) {
                bail!(
                    "aafm.cr_gate_share must be in (0, 1], got {}",
                    aafm.cr_gate_share
                );
            }
        }
        let t = &self.train;
        if !(self.loss.moving_weight > 0.0 && self.loss.moving_weight.is_finite()) {
            bail!(
                "loss.moving_weight must be a positive weight (1 = off), got {}",
                self.loss.moving_weight
            );
        }
        if !(self.loss.coherence_cell > 0.0 && self.loss.coherence_cell.is_finite()) {
            bail!(
                "loss.coherence_cell must be a positive length, got {}",
                self.loss.coherence_cell
            );
        }
        if !(t.knot_moving_voxels.is_finite() && t.knot_moving_voxels >= 0.0) {
            bail!(
                "train.knot_moving_voxels must be a length in voxels ≥ 0, got {}",
                t.knot_moving_voxels
            );
        }
        if !(t.knot_search_radius.is_finite() && t.knot_search_radius > 0.0) {
            bail!(
                "train.knot_search_radius must be a positive length, got {}",
                t.knot_search_radius
            );
        }
        if t.knot_consensus != KnotConsensus::Off && t.knot_search == KnotSearch::Off {
            bail!(
                "train.knot_consensus places what the knot search tracked: it needs \
                 train.knot_search on (\"photometric\" or \"patches\")"
            );
        }
        if self.model.trajectory_turn != TrajectoryTurn::Off && self.model.trajectory_spacing == 0 {
            bail!(
                "model.trajectory_turn = \"{}\" turns the trajectory knots: it needs \
                 model.trajectory_spacing > 0",
                self.model.trajectory_turn.name()
            );
        }
        if self.model.trajectory_turn == TrajectoryTurn::Paths && self.model.knn == 0 {
            bail!(
                "model.trajectory_turn = \"paths\" reads each anchor's turn from its kNN \
                 neighbours' paths: it needs model.knn > 0"
            );
        }
        if !t.motion_gate_start.is_finite() {
            bail!(
                "train.motion_gate_start must be a finite logit, got {}",
                t.motion_gate_start
            );
        }
        if t.moving_gates != MovingGates::Off
            && t.knot_search != KnotSearch::Off
            && t.init_dynamic != InitDynamic::Off
        {
            bail!(
                "train.moving_gates = \"open\" opens gates that train.init_dynamic = {:?} would \
                 reset at the end of the canonical phase (leaving their knots divided): set \
                 train.moving_gates = \"off\" with init_dynamic, or init_dynamic = \"off\"",
                t.init_dynamic
            );
        }
        if !t.moving_gate_logit.is_finite() {
            bail!(
                "train.moving_gate_logit must be a finite logit, got {}",
                t.moving_gate_logit
            );
        }
        if t.motion_gate_hold != MotionGateHold::Off && t.frame_curriculum <= 0.0 {
            bail!(
                "train.motion_gate_hold = \"curriculum\" holds the gates while frames open: it \
                 needs train.frame_curriculum > 0"
            );
        }
        if t.fitted_knots == FittedKnots::Held && t.rigid_fit == RigidFit::Off {
            bail!(
                "train.fitted_knots = \"held\" holds the knots the rigid fit sets: it needs \
                 train.rigid_fit = \"objects\" or \"rendered\""
            );
        }
        if t.knot_refit != KnotRefit::Off && t.frame_curriculum <= 0.0 {
            bail!(
                "train.knot_refit refits the knots the temporal curriculum has opened: it needs \
                 train.frame_curriculum > 0"
            );
        }
        if t.knot_refit_streams != KnotRefitStreams::Kept && t.knot_refit == KnotRefit::Off {
            bail!(
                "train.knot_refit_streams resets the streams of the anchors the knot refit moves: \
                 it needs train.knot_refit = \"curriculum-end\" or \"at-share\""
            );
        }
        if !(t.knot_refit_share > 0.0 && t.knot_refit_share < 1.0) {
            bail!(
                "train.knot_refit_share must be a share of the steps in (0, 1), got {}",
                t.knot_refit_share
            );
        }
        if !(t.rigid_fit_link.is_finite() && t.rigid_fit_link > 0.0) {
            bail!(
                "train.rigid_fit_link must be a positive length, got {}",
                t.rigid_fit_link
            );
        }
        if t.rigid_fit_grouping != RigidFitGrouping::Near && t.rigid_fit == RigidFit::Off {
            bail!(
                "train.rigid_fit_grouping groups the anchors the rigid fit moves: it needs \
                 train.rigid_fit \"objects\" or \"rendered\""
            );
        }
        if !(t.knot_consensus_cell.is_finite() && t.knot_consensus_cell > 0.0) {
            bail!(
                "train.knot_consensus_cell must be a positive length, got {}",
                t.knot_consensus_cell
            );
        }
        if !(t.knot_search_patch.is_finite() && t.knot_search_patch > 0.0) {
            bail!(
                "train.knot_search_patch must be a positive length, got {}",
                t.knot_search_patch
            );
        }
        if !(t.knot_search_tolerance.is_finite() && t.knot_search_tolerance > 0.0) {
            bail!(
                "train.knot_search_tolerance must be a positive colour distance, got {}",
                t.knot_search_tolerance
            );
        }
        if !(0.0..=1.0).contains(&t.frontier_share) {
            bail!(
                "train.frontier_share must be in [0, 1], got {}",
                t.frontier_share
            );
        }
        if !(0.0..=1.0).contains(&t.frame_curriculum)
            || !(0.0..=1.0).contains(&t.time_band_schedule)
        {
            bail!(
                "train.frame_curriculum ({}) and train.time_band_schedule ({}) are fractions of \
                 max_steps in [0, 1]",
                t.frame_curriculum,
                t.time_band_schedule
            );
        }
        let e = &self.eval;
        if !(e.motion_threshold >= 0.0 && e.motion_threshold < 255.0) {
            bail!(
                "eval.motion_threshold must be in [0, 255) 8-bit levels, got {}",
                e.motion_threshold
            );
        }
        Ok(())
    }
}

/// `a.b.c=value`: value is parsed as a TOML value (number, bool, array, quoted string) and falls
/// back to a bare string, so `--set data.dataset=/data/x` works without quotes.
fn apply_override(table: &mut toml::Table, assignment: &str) -> Result<()> {
    let (key, raw) = assignment
        .split_once('=')
        .with_context(|| format!("--set {assignment}: expected key=value"))?;
    let value = match toml::from_str::<toml::Table>(&format!("v = {raw}")) {
        Ok(mut t) => t.remove("v").expect("parsed key"),
        Err(_) => toml::Value::String(raw.to_string()),
    };
    let parts: Vec<&str> = key.trim().split('.').collect();
    if parts.iter().any(|p| p.is_empty()) {
        bail!("--set {assignment}: empty key segment");
    }
    let mut node = table;
    for part in &parts[..parts.len() - 1] {
        node = node
            .entry(part.to_string())
            .or_insert_with(|| toml::Value::Table(Default::default()))
            .as_table_mut()
            .with_context(|| format!("--set {assignment}: `{part}` is not a section"))?;
    }
    node.insert(parts[parts.len() - 1].to_string(), value);
    Ok(())
}
