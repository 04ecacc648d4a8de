//! Checkpoints of a trainer: everything needed to continue exactly (the model, the trainer's
//! per-anchor state, every optimizer, the sampler and counters), written atomically as one
//! safetensors file whose metadata holds the non-tensor state. The per-anchor columns are
//! written generically, under `anchors.<name>` in their row shape (the layout predates the
//! column table, so older checkpoints load).

use std::path::Path;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::super::adaptive_cardinality::RelocationChurn;
use super::super::anchor_state::{AnchorState, AnchorStats};
use super::super::checkpoint::{NamedTensors, read_checkpoint, write_checkpoint};
use super::super::decoder_adam::{DECODER_ADAM, DecoderAdam, LinearAdam, MlpAdam};
use super::super::row_adam::{AdamConfig, RowAdam};
use super::{ANCHOR_ADAM, Trainer, anchor_dims, decoder_sizes};
use crate::codec::entropy_models::EntropyModels;
use crate::codec::trained_model::TrainedModel;
use crate::config::{FittedKnots, TrainConfig};
use crate::data::Scene;
use crate::data::sampler::SamplerState;
use crate::model::anchored::AnchoredModel;
use crate::model::anchors::{AnchorDims, AnchorSet, Column, Columns, host_values};
use crate::model::decoders::{Decoders, Mlp};
use crate::model::slot_gates::SlotGates;

/// Adam step counts by parameter key (in the metadata: one count per tensor, as PyTorch).
type AdamSteps = std::collections::BTreeMap<String, u64>;

/// Trainer state that is not a tensor, stored in the checkpoint's metadata.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct TrainerMeta {
    format: String,
    version: u32,
    /// Steps completed.
    step: usize,
    sampler: SamplerState,
    train_seconds: f64,
    nan_steps: usize,
    #[serde(default)]
    schedule_origin: usize,
    #[serde(default)]
    relocation_churn: RelocationChurn,
    #[serde(default)]
    cr_started_at: Option<usize>,
    adam_steps: AdamSteps,
    config: String,
}

const CHECKPOINT_FORMAT: &str = "acags-train-checkpoint";
/// v2: ACA-GS buffers (slot gates, importance, birth steps) and the AAFM mask logits.
/// v3: the conditional entropy models and their Adam state (a v2 checkpoint loads with fresh
/// entropy models).
const CHECKPOINT_VERSION: u32 = 3;

impl Trainer {
    /// Writes a checkpoint of everything needed to continue exactly.
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let mut tensors = NamedTensors::default();
        let mut adam_steps = AdamSteps::new();
        self.put_anchors(&mut tensors, &mut adam_steps);
        self.put_models(&mut tensors, &mut adam_steps);
        let meta = TrainerMeta {
            format: CHECKPOINT_FORMAT.into(),
            version: CHECKPOINT_VERSION,
            step: self.step,
            sampler: self.sampler.state(),
            train_seconds: self.train_seconds,
            nan_steps: self.nan_steps,
            relocation_churn: self.relocation_churn,
            cr_started_at: self.cr_started_at,
            schedule_origin: self.schedule_origin,
            adam_steps,
            config: self.config.to_toml(),
        };
        write_checkpoint(path, &tensors, &serde_json::to_value(&meta)?)
    }

    /// Positions, every column with its Adam state, the AAC buffers and the statistics.
    fn put_anchors(&self, tensors: &mut NamedTensors, adam_steps: &mut AdamSteps) {
        let a = &self.model.anchors;
        let d = a.dims;
        let n = a.len();
        tensors.insert(
            "anchors.positions",
            vec![n, 3],
            a.positions.iter().flatten().copied().collect(),
        );
        // What the steps gathered on the device since the last refine step, read back here.
        let state = self.anchor_state.settled();
        for (c, value) in a.columns.iter() {
            let key = column_key(c);
            let shape = column_shape(c, &d, n);
            tensors.insert(key.clone(), shape.clone(), host_values(value));
            put_adam_shaped(tensors, adam_steps, &key, &state.adam[c], shape);
        }
        let flag = |b: &bool| if *b { 1.0 } else { 0.0 };
        tensors.insert(
            "aac.slot_gates",
            vec![n, d.slots],
            a.slot_gates.iter().map(flag).collect(),
        );
        tensors.insert("aac.importance", vec![n, d.slots], state.importance.clone());
        tensors.insert(
            "aac.relocated",
            vec![n, d.slots],
            state.relocated.iter().map(flag).collect(),
        );
        tensors.insert(
            "aac.importance_visits",
            vec![n],
            state.importance_visits.clone(),
        );
        // Birth steps as float32: exact below 2^24 steps.
        tensors.insert(
            "aac.created_at",
            vec![n],
            state.created_at.iter().map(|&s| s as f32).collect(),
        );
        // Frame indices as float32: exact below 2^24.
        tensors.insert(
            "motion.reference_frame",
            vec![n],
            state.reference_frame.iter().map(|&f| f as f32).collect(),
        );
        // Only where some knot is held: a checkpoint without fitted knots held opens in builds
        // from before `train.fitted_knots`.
        if state.held_knots().contains(&true) {
            tensors.insert(
                "motion.held_knots",
                vec![n, d.trajectory_knots()],
                state.held_knots().iter().map(flag).collect(),
            );
        }
        let st = &state.stats;
        tensors.insert(
            "stats.offset_grad2d",
            vec![n * d.slots, d.frames],
            st.offset_grad2d.clone(),
        );
        tensors.insert(
            "stats.offset_visible_count",
            vec![n * d.slots, d.frames],
            st.offset_visible_count.clone(),
        );
        tensors.insert(
            "stats.opacity_accum",
            vec![n, d.frames],
            st.opacity_accum.clone(),
        );
        tensors.insert(
            "stats.anchor_visible_count",
            vec![n, d.frames],
            st.anchor_visible_count.clone(),
        );
    }

    /// The decoders and the entropy models with their Adam state.
    fn put_models(&self, tensors: &mut NamedTensors, adam_steps: &mut AdamSteps) {
        let dec = &self.model.decoders;
        let adam = &self.optimizers.decoders;
        for (name, mlp, state) in [
            ("opacity", &dec.opacity, &adam.opacity),
            ("cov", &dec.cov, &adam.cov),
            ("color", &dec.color, &adam.color),
            ("motion", &dec.motion, &adam.motion),
        ] {
            put_mlp(tensors, adam_steps, &format!("decoders.{name}"), mlp, state);
        }
        for ((name, mlp), state) in self
            .entropy
            .named()
            .into_iter()
            .zip(&self.optimizers.entropy)
        {
            put_mlp(tensors, adam_steps, &format!("entropy.{name}"), mlp, state);
        }
    }

    /// Restores a checkpoint written by [`Trainer::save_checkpoint`] for the same scene and
    /// model sizes.
    pub fn load_checkpoint(&mut self, path: &Path) -> Result<()> {
        let (mut tensors, meta) = read_checkpoint(path)?;
        let meta = checked_meta(meta, path)?;
        let device = self.device.clone();
        let steps = &meta.adam_steps;
        let (set, anchor_state) =
            take_anchors(&mut tensors, steps, self.model.anchors.dims, path, &device)?;
        let (decoders, decoder_adam, entropy, entropy_adam) =
            self.take_models(&mut tensors, steps, meta.version, path, &device)?;
        if let Some(extra) = tensors.entries.keys().next() {
            bail!(
                "{}: unexpected tensor `{extra}` (written by another version?)",
                path.display()
            );
        }
        self.model = AnchoredModel {
            anchors: set,
            decoders,
            culling: self.config.model.culling,
        };
        self.anchor_state = anchor_state;
        // Knots held by a run under `train.fitted_knots = "held"` train when it resumes under
        // "trained".
        if self.config.train.fitted_knots == FittedKnots::Trained {
            self.anchor_state.release_held_knots();
        }
        self.optimizers.decoders = decoder_adam;
        self.entropy = entropy;
        self.optimizers.entropy = entropy_adam;
        self.sampler.restore(meta.sampler);
        self.step = meta.step;
        self.train_seconds = meta.train_seconds;
        self.nan_steps = meta.nan_steps;
        self.relocation_churn = meta.relocation_churn;
        self.cr_started_at = meta.cr_started_at;
        self.schedule_origin = meta.schedule_origin;
        self.consecutive_nan = 0;
        self.rows_changed();
        Ok(())
    }

    /// The decoders and (from v3) the entropy models with their Adam state.
    #[allow(clippy::type_complexity)]
    fn take_models(
        &self,
        tensors: &mut NamedTensors,
        steps: &AdamSteps,
        version: u32,
        path: &Path,
        device: &Device,
    ) -> Result<(Decoders, DecoderAdam, EntropyModels, Vec<MlpAdam>)> {
        let mut decoders = self.model.decoders.clone();
        let mut decoder_adam = self.optimizers.decoders.clone();
        for (name, mlp, state) in [
            ("opacity", &mut decoders.opacity, &mut decoder_adam.opacity),
            ("cov", &mut decoders.cov, &mut decoder_adam.cov),
            ("color", &mut decoders.color, &mut decoder_adam.color),
            ("motion", &mut decoders.motion, &mut decoder_adam.motion),
        ] {
            let key = format!("decoders.{name}");
            take_mlp(tensors, steps, &key, mlp, state, path, device)?;
        }
        let mut entropy = self.entropy.clone();
        let mut entropy_adam = self.optimizers.entropy.clone();
        if version >= 3 {
            for ((name, mlp), state) in entropy.named_mut().into_iter().zip(&mut entropy_adam) {
                let key = format!("entropy.{name}");
                take_mlp(tensors, steps, &key, mlp, state, path, device)?;
            }
        }
        Ok((decoders, decoder_adam, entropy, entropy_adam))
    }
}

/// The anchor rows of a checkpoint and the trainer's state for them.
fn take_anchors(
    tensors: &mut NamedTensors,
    steps: &AdamSteps,
    d: AnchorDims,
    path: &Path,
    device: &Device,
) -> Result<(AnchorSet, AnchorState)> {
    let set = take_anchor_values(tensors, d, path, device)?;
    let n = set.len();
    let mut adam = Columns::default();
    for c in Column::present(&d) {
        let (key, shape) = (column_key(c), column_shape(c, &d, n));
        adam.insert(
            c,
            take_row_adam(tensors, steps, &key, &shape, path, device)?,
        );
    }
    let (importance, importance_visits, relocated, created_at) =
        take_aac_state(tensors, n, d.slots, path)?;
    let stats = take_stats(tensors, n, &d, path)?;
    let reference_frame = take_reference_frames(tensors, n, d.frames, path)?;
    let held_knots = take_held_knots(tensors, n, d.trajectory_knots(), path)?;
    let state = AnchorState::from_parts(
        adam,
        stats,
        importance,
        importance_visits,
        relocated,
        created_at,
        reference_frame,
        held_knots,
    );
    Ok((set, state))
}

/// The model's part of the anchor rows: positions, columns and slot gates.
fn take_anchor_values(
    tensors: &mut NamedTensors,
    d: AnchorDims,
    path: &Path,
    device: &Device,
) -> Result<AnchorSet> {
    let (shape, positions) = tensors.take("anchors.positions", &[None, Some(3)], path)?;
    let n = shape[0];
    let mut columns = Columns::default();
    for c in Column::present(&d) {
        let (key, shape) = (column_key(c), column_shape(c, &d, n));
        columns.insert(c, take_rows(tensors, &key, &shape, path, device)?);
    }
    let slot_gates = take_flags(tensors, "aac.slot_gates", n, d.slots, path)?;
    Ok(AnchorSet::restored(
        d,
        positions
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        Tensor::<2>::from_data(TensorData::new(positions, [n, 3]), device),
        columns,
        SlotGates::from_flags(slot_gates, d.slots, device),
    ))
}

/// [n, width] 0/1 flags.
fn take_flags(
    tensors: &mut NamedTensors,
    key: &str,
    n: usize,
    width: usize,
    path: &Path,
) -> Result<Vec<bool>> {
    let flags = tensors.take(key, &[Some(n), Some(width)], path)?.1;
    if let Some(bad) = flags.iter().find(|&&g| g != 0.0 && g != 1.0) {
        bail!("{}: `{key}` holds {bad}, neither 0 nor 1", path.display());
    }
    Ok(flags.iter().map(|&g| g == 1.0).collect())
}

/// AAC importance, visits, relocation flags and birth steps.
#[allow(clippy::type_complexity)]
fn take_aac_state(
    tensors: &mut NamedTensors,
    n: usize,
    slots: usize,
    path: &Path,
) -> Result<(Vec<f32>, Vec<f32>, Vec<bool>, Vec<u32>)> {
    let importance = tensors
        .take("aac.importance", &[Some(n), Some(slots)], path)?
        .1;
    let importance_visits = tensors.take("aac.importance_visits", &[Some(n)], path)?.1;
    // Added within v3 for the churn report only: older checkpoints have no relocations pending.
    let relocated = if tensors.entries.contains_key("aac.relocated") {
        take_flags(tensors, "aac.relocated", n, slots, path)?
    } else {
        vec![false; n * slots]
    };
    let born = tensors.take("aac.created_at", &[Some(n)], path)?.1;
    if let Some(bad) = born
        .iter()
        .find(|&&s| !(s >= 0.0 && s.fract() == 0.0 && s < 16_777_216.0))
    {
        bail!("{}: birth step {bad} is not a step number", path.display());
    }
    let created_at = born.iter().map(|&s| s as u32).collect();
    Ok((importance, importance_visits, relocated, created_at))
}

/// The knot search's reference frames; checkpoints written before appearance seeding have none
/// (every anchor then came from frame 0's points or from growth: reference frame 0).
fn take_reference_frames(
    tensors: &mut NamedTensors,
    n: usize,
    frames: usize,
    path: &Path,
) -> Result<Vec<u32>> {
    if !tensors.entries.contains_key("motion.reference_frame") {
        return Ok(vec![0; n]);
    }
    let values = tensors.take("motion.reference_frame", &[Some(n)], path)?.1;
    if let Some(bad) = values
        .iter()
        .find(|&&f| !(f >= 0.0 && f.fract() == 0.0 && (f as usize) < frames.max(1)))
    {
        bail!(
            "{}: `motion.reference_frame` holds {bad}, not a frame of this {frames}-frame GOP",
            path.display()
        );
    }
    Ok(values.iter().map(|&f| f as u32).collect())
}

/// The knots training holds where the rigid fit set them; checkpoints written before
/// `train.fitted_knots` have none (nothing held).
fn take_held_knots(
    tensors: &mut NamedTensors,
    n: usize,
    knots: usize,
    path: &Path,
) -> Result<Vec<bool>> {
    if knots == 0 || !tensors.entries.contains_key("motion.held_knots") {
        return Ok(vec![false; n * knots]);
    }
    let values = tensors
        .take("motion.held_knots", &[Some(n), Some(knots)], path)?
        .1;
    if let Some(bad) = values.iter().find(|&&v| v != 0.0 && v != 1.0) {
        bail!(
            "{}: `motion.held_knots` holds {bad}, not a flag (0 or 1)",
            path.display()
        );
    }
    Ok(values.iter().map(|&v| v == 1.0).collect())
}

/// The densification statistics.
fn take_stats(
    tensors: &mut NamedTensors,
    n: usize,
    d: &AnchorDims,
    path: &Path,
) -> Result<AnchorStats> {
    // The visibility counts were `*_demon` before 2026-11-26 (GIFStream's name).
    let mut stat = |name: &str, former: Option<&str>, rows: usize| -> Result<Vec<f32>> {
        let expected = [Some(rows), Some(d.frames)];
        Ok(match former {
            Some(former) => tensors.take_renamed(name, former, &expected, path)?.1,
            None => tensors.take(name, &expected, path)?.1,
        })
    };
    Ok(AnchorStats {
        offset_grad2d: stat("stats.offset_grad2d", None, n * d.slots)?,
        offset_visible_count: stat(
            "stats.offset_visible_count",
            Some("stats.offset_demon"),
            n * d.slots,
        )?,
        opacity_accum: stat("stats.opacity_accum", None, n)?,
        anchor_visible_count: stat("stats.anchor_visible_count", Some("stats.anchor_demon"), n)?,
    })
}

/// The Adam state of `key` under its own shape.
fn put_adam<const D: usize>(
    tensors: &mut NamedTensors,
    steps: &mut AdamSteps,
    key: &str,
    adam: &RowAdam<D>,
) {
    put_adam_shaped(tensors, steps, key, adam, adam.exp_avg.dims().to_vec());
}

/// A column's checkpoint key, `anchors.<name>`.
fn column_key(c: Column) -> String {
    format!("anchors.{}", c.name())
}

/// A column's checkpoint shape: [N, row shape…] (offsets [N, K, 3]), the layout checkpoints had
/// before the columns were stored flat.
fn column_shape(c: Column, d: &AnchorDims, n: usize) -> Vec<usize> {
    let mut shape = vec![n];
    shape.extend(c.row_shape(d).expect("a present column"));
    shape
}

/// The Adam state of `key` under `shape` (a column's flat [N, width] state is written in the
/// column's checkpoint shape).
fn put_adam_shaped<const D: usize>(
    tensors: &mut NamedTensors,
    steps: &mut AdamSteps,
    key: &str,
    adam: &RowAdam<D>,
    shape: Vec<usize>,
) {
    tensors.insert(
        format!("adam.{key}.exp_avg"),
        shape.clone(),
        host_values(&adam.exp_avg),
    );
    tensors.insert(
        format!("adam.{key}.exp_avg_sq"),
        shape,
        host_values(&adam.exp_avg_sq),
    );
    steps.insert(key.to_string(), adam.step);
}

fn put_linear(
    tensors: &mut NamedTensors,
    steps: &mut AdamSteps,
    key: &str,
    linear: &burn::nn::Linear,
    adam: &LinearAdam,
) {
    let w = linear.weight.val();
    let b = linear.bias.as_ref().expect("bias").val();
    tensors.insert(format!("{key}.weight"), w.dims().to_vec(), host_values(&w));
    tensors.insert(format!("{key}.bias"), b.dims().to_vec(), host_values(&b));
    put_adam(tensors, steps, &format!("{key}.weight"), &adam.weight);
    put_adam(tensors, steps, &format!("{key}.bias"), &adam.bias);
}

/// Both layers of an MLP and their Adam state under `key.hidden` / `key.output` (read back by
/// [`take_mlp`]).
fn put_mlp(
    tensors: &mut NamedTensors,
    steps: &mut AdamSteps,
    key: &str,
    mlp: &Mlp,
    adam: &MlpAdam,
) {
    for (layer, linear, la) in [
        ("hidden", &mlp.hidden, &adam.hidden),
        ("output", &mlp.output, &adam.output),
    ] {
        put_linear(tensors, steps, &format!("{key}.{layer}"), linear, la);
    }
}

fn take_tensor<const D: usize>(
    tensors: &mut NamedTensors,
    key: &str,
    shape: [usize; D],
    path: &Path,
    device: &Device,
) -> Result<Tensor<D>> {
    let expected: Vec<Option<usize>> = shape.iter().map(|&s| Some(s)).collect();
    let (_, values) = tensors.take(key, &expected, path)?;
    Ok(Tensor::<D>::from_data(
        TensorData::new(values, shape),
        device,
    ))
}

fn take_adam<const D: usize>(
    tensors: &mut NamedTensors,
    steps: &AdamSteps,
    key: &str,
    shape: [usize; D],
    config: AdamConfig,
    path: &Path,
    device: &Device,
) -> Result<RowAdam<D>> {
    Ok(RowAdam {
        config,
        exp_avg: take_tensor(tensors, &format!("adam.{key}.exp_avg"), shape, path, device)?,
        exp_avg_sq: take_tensor(
            tensors,
            &format!("adam.{key}.exp_avg_sq"),
            shape,
            path,
            device,
        )?,
        step: adam_step_count(steps, key, path)?,
    })
}

/// The Adam step count of `key` from the checkpoint's metadata.
fn adam_step_count(steps: &AdamSteps, key: &str, path: &Path) -> Result<u64> {
    steps
        .get(key)
        .copied()
        .with_context(|| format!("{}: no Adam step count for `{key}`", path.display()))
}

/// A tensor of checkpoint shape [N, …] as the flat [N, width] a column is stored as.
fn take_rows(
    tensors: &mut NamedTensors,
    key: &str,
    shape: &[usize],
    path: &Path,
    device: &Device,
) -> Result<Tensor<2>> {
    let expected: Vec<Option<usize>> = shape.iter().map(|&s| Some(s)).collect();
    let (_, values) = tensors.take(key, &expected, path)?;
    let width = shape[1..].iter().product();
    Ok(Tensor::<2>::from_data(
        TensorData::new(values, [shape[0], width]),
        device,
    ))
}

fn take_row_adam(
    tensors: &mut NamedTensors,
    steps: &AdamSteps,
    key: &str,
    shape: &[usize],
    path: &Path,
    device: &Device,
) -> Result<RowAdam<2>> {
    Ok(RowAdam {
        config: ANCHOR_ADAM,
        exp_avg: take_rows(tensors, &format!("adam.{key}.exp_avg"), shape, path, device)?,
        exp_avg_sq: take_rows(
            tensors,
            &format!("adam.{key}.exp_avg_sq"),
            shape,
            path,
            device,
        )?,
        step: adam_step_count(steps, key, path)?,
    })
}

fn take_mlp(
    tensors: &mut NamedTensors,
    steps: &AdamSteps,
    key: &str,
    mlp: &mut Mlp,
    adam: &mut MlpAdam,
    path: &Path,
    device: &Device,
) -> Result<()> {
    take_mlp_weights(tensors, key, mlp, path, device)?;
    for (layer, linear, state) in [
        ("hidden", &mlp.hidden, &mut adam.hidden),
        ("output", &mlp.output, &mut adam.output),
    ] {
        let k = format!("{key}.{layer}");
        let [i, o] = linear.weight.val().dims();
        state.weight = take_adam(
            tensors,
            steps,
            &format!("{k}.weight"),
            [i, o],
            DECODER_ADAM,
            path,
            device,
        )?;
        state.bias = take_adam(
            tensors,
            steps,
            &format!("{k}.bias"),
            [o],
            DECODER_ADAM,
            path,
            device,
        )?;
    }
    Ok(())
}

/// Both layers' weights of an MLP written by `put_mlp` (no optimizer state).
fn take_mlp_weights(
    tensors: &mut NamedTensors,
    key: &str,
    mlp: &mut Mlp,
    path: &Path,
    device: &Device,
) -> Result<()> {
    for (layer, linear) in [("hidden", &mut mlp.hidden), ("output", &mut mlp.output)] {
        let k = format!("{key}.{layer}");
        let [i, o] = linear.weight.val().dims();
        let w: Tensor<2> = take_tensor(tensors, &format!("{k}.weight"), [i, o], path, device)?;
        let b: Tensor<1> = take_tensor(tensors, &format!("{k}.bias"), [o], path, device)?;
        linear.weight = burn::module::Param::from_tensor(w);
        linear.bias = Some(burn::module::Param::from_tensor(b));
    }
    Ok(())
}

/// What a run's training did, besides the model (from the checkpoint's metadata).
#[derive(Clone, Copy, Debug, Default)]
pub struct TrainingHistory {
    pub train_seconds: f64,
    pub nan_steps: usize,
    pub relocation_churn: RelocationChurn,
}

/// The trained model of a checkpoint written by [`Trainer::save_checkpoint`] for `config` and
/// `scene`, without its optimizer state, statistics or sampler (which are not read).
pub fn read_trained_model(
    path: &Path,
    config: &TrainConfig,
    scene: &Scene,
    device: &Device,
) -> Result<(TrainedModel, TrainingHistory)> {
    let (mut tensors, meta) = read_checkpoint(path)?;
    let meta = checked_meta(meta, path)?;
    let anchors = take_anchor_values(&mut tensors, anchor_dims(config, scene), path, device)?;
    // Seeded (not drawn from the device's generator); every weight is overwritten below.
    let mut decoders = Decoders::seeded(decoder_sizes(config), config.train.seed, device);
    for (name, mlp) in [
        ("opacity", &mut decoders.opacity),
        ("cov", &mut decoders.cov),
        ("color", &mut decoders.color),
        ("motion", &mut decoders.motion),
    ] {
        take_mlp_weights(&mut tensors, &format!("decoders.{name}"), mlp, path, device)?;
    }
    // A v2 checkpoint has none: the models stay as a fresh trainer would start them.
    let mut entropy = EntropyModels::seeded(decoder_sizes(config), config.train.seed, device);
    if meta.version >= 3 {
        for (name, mlp) in entropy.named_mut() {
            take_mlp_weights(&mut tensors, &format!("entropy.{name}"), mlp, path, device)?;
        }
    }
    // What is left is training state (not read); anything else was written by another build.
    let training_state = |key: &str| {
        key.starts_with("adam.")
            || key.starts_with("stats.")
            || [
                "aac.importance",
                "aac.importance_visits",
                "aac.relocated",
                "aac.created_at",
                "motion.reference_frame",
                "motion.held_knots",
            ]
            .contains(&key)
    };
    if let Some(extra) = tensors.entries.keys().find(|k| !training_state(k)) {
        bail!(
            "{}: unexpected tensor `{extra}` (written by another version, or for another config?)",
            path.display()
        );
    }
    let trained = TrainedModel {
        model: AnchoredModel {
            anchors,
            decoders,
            culling: config.model.culling,
        },
        entropy,
        config: config.clone(),
        step: meta.step,
        gop: (scene.frames.start, scene.frames.count),
    };
    let history = TrainingHistory {
        train_seconds: meta.train_seconds,
        nan_steps: meta.nan_steps,
        relocation_churn: meta.relocation_churn,
    };
    Ok((trained, history))
}

/// The metadata of a checkpoint, checked to be this trainer's format.
fn checked_meta(meta: serde_json::Value, path: &Path) -> Result<TrainerMeta> {
    let meta: TrainerMeta = serde_json::from_value(meta)
        .with_context(|| format!("{}: unreadable trainer state", path.display()))?;
    if meta.format != CHECKPOINT_FORMAT || !(2..=CHECKPOINT_VERSION).contains(&meta.version) {
        bail!(
            "{}: checkpoint format {} v{} is not {CHECKPOINT_FORMAT} v2..v{CHECKPOINT_VERSION}",
            path.display(),
            meta.format,
            meta.version
        );
    }
    Ok(meta)
}
