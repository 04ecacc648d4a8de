//! Coding one attribute section: the grid indices of the stored elements under either
//!
//! - **factorized**: one discretised Gaussian per channel (rounded mean and the σ level of least
//!   code length, written in the section), or
//! - **conditional**: the trained entropy models of [`super::entropy_models`], evaluated on the
//!   host: scales, offsets and factors from the anchor's decoded (masked) feature; features chunk
//!   by chunk from the three chunks before; the feature stream frame by frame from the three
//!   frames before (spec §9.3, §10 item 5).
//!
//! The encoder codes both and keeps the smaller ([`ModelChoice::Smallest`]), so a poorly trained
//! entropy model never costs more than the per-channel fit; the section's first byte says which.
//!
//! Knot tables (trajectory, turn) have no conditional model; they are coded factorized either per
//! axis or per (previous knot's increment bucket, axis) (`KNOT_CONTEXT`, codec version 4 on),
//! whichever is smaller.
//!
//! Section layout: `kind: u8`, then for factorized `channels: u32` (groups, for the knot context),
//! per channel `(mean: i32, level: u8)`; then `radius: i32` and the rANS stream (u32 length +
//! words).

use anyhow::{Context, Result, bail, ensure};

use super::bitstream::QuantizedScene;
use super::entropy::{
    GaussianDecoder, GaussianTables, MAX_RADIUS, SCALE_LEVELS, encode_gaussian, level_sigma,
    normal_cdf, scale_level,
};
use super::entropy_models::{CONTEXT_LENGTH, FEATURE_CHUNK, HostEntropyModels, feature_chunks};
use super::wire::{Reader, Writer};
use crate::model::anchors::{FACTOR_COUNT, SCALE_DIMS};

/// The coded attributes, in decoding order (later ones may condition on earlier ones).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Attribute {
    Features,
    Factors,
    LogScales,
    Offsets,
    TimeFeatures,
    /// Anchor trajectories (scenes trained with them): knot-to-knot increments, per axis. There
    /// is no conditional entropy model for them, so they are always coded factorized.
    Trajectory,
    /// Trajectory turns (scenes trained with them): knot-to-knot increments of the rotation
    /// vectors, per axis; factorized like the trajectory.
    Turn,
}

impl Attribute {
    pub const ALL: [Attribute; 7] = [
        Attribute::Features,
        Attribute::Factors,
        Attribute::LogScales,
        Attribute::Offsets,
        Attribute::TimeFeatures,
        Attribute::Trajectory,
        Attribute::Turn,
    ];

    /// The attributes a scene codes (the trajectory and its turns only when it has them).
    pub fn of(scene: &QuantizedScene) -> impl Iterator<Item = Attribute> + '_ {
        let dims = scene.meta.dims();
        Self::ALL.into_iter().filter(move |&a| match a {
            Attribute::Trajectory => dims.trajectory_width() > 0,
            Attribute::Turn => dims.stored_turn_width() > 0,
            _ => true,
        })
    }

    /// Coded factorized only (no conditional entropy model exists for it).
    fn factorized_only(self) -> bool {
        matches!(self, Attribute::Trajectory | Attribute::Turn)
    }

    pub fn section(self) -> &'static str {
        match self {
            Attribute::Features => "features",
            Attribute::Factors => "factors",
            Attribute::LogScales => "log_scales",
            Attribute::Offsets => "offsets",
            Attribute::TimeFeatures => "time_features",
            Attribute::Trajectory => "trajectory",
            Attribute::Turn => "turn",
        }
    }

    /// Rows of the attribute: anchors, anchors × frames (stream) or anchors × knots.
    fn rows(self, scene: &QuantizedScene) -> usize {
        let n = scene.voxels.len();
        match self {
            Attribute::TimeFeatures => n * scene.meta.frames,
            Attribute::Trajectory | Attribute::Turn => n * scene.meta.dims().trajectory_knots(),
            _ => n,
        }
    }

    /// Channels of one row (rows: anchors, or anchors × frames for the stream).
    fn channels(self, scene: &QuantizedScene) -> usize {
        let m = &scene.meta;
        match self {
            Attribute::Features => m.feature_dim,
            Attribute::Factors => FACTOR_COUNT,
            Attribute::LogScales => SCALE_DIMS,
            Attribute::Offsets => 3 * m.slots,
            Attribute::TimeFeatures => m.time_feature_dim,
            Attribute::Trajectory | Attribute::Turn => 3,
        }
    }

    pub fn values(self, scene: &QuantizedScene) -> &Vec<i32> {
        match self {
            Attribute::Features => &scene.features,
            Attribute::Factors => &scene.factors,
            Attribute::LogScales => &scene.log_scales,
            Attribute::Offsets => &scene.offsets,
            Attribute::TimeFeatures => &scene.time_features,
            Attribute::Trajectory => &scene.trajectory,
            Attribute::Turn => &scene.turn,
        }
    }

    fn values_mut(self, scene: &mut QuantizedScene) -> &mut Vec<i32> {
        match self {
            Attribute::Features => &mut scene.features,
            Attribute::Factors => &mut scene.factors,
            Attribute::LogScales => &mut scene.log_scales,
            Attribute::Offsets => &mut scene.offsets,
            Attribute::TimeFeatures => &mut scene.time_features,
            Attribute::Trajectory => &mut scene.trajectory,
            Attribute::Turn => &mut scene.turn,
        }
    }
}

/// Which model the encoder uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelChoice {
    /// Code with both, keep the smaller (the default).
    Smallest,
    /// Without the entropy models (the knot tables still keep the smaller of their two
    /// factorized codings).
    Factorized,
    /// Requires entropy models.
    Conditional,
}

const FACTORIZED: u8 = 0;
const CONDITIONAL: u8 = 1;
/// Knot tables only (codec version 4 on): factorized per (previous knot's bucket, axis).
const KNOT_CONTEXT: u8 = 2;
const KNOT_CONTEXT_VERSION: u32 = 4;

/// Which elements are stored (the rest decode as index 0), per attribute; `None`: all.
pub type CodedMask<'a> = Option<&'a [bool]>;

fn is_coded(mask: CodedMask, i: usize) -> bool {
    mask.is_none_or(|m| m[i])
}

/// Σ over a histogram of −log2 p(y) under the level's discretised Gaussian (no tail folding).
fn histogram_bits(histogram: &std::collections::BTreeMap<i32, u64>, level: u8) -> f64 {
    let sigma = level_sigma(level);
    let cdf = |x: f64| normal_cdf(x / sigma);
    histogram
        .iter()
        .map(|(&y, &count)| {
            let p = (cdf(y as f64 + 0.5) - cdf(y as f64 - 0.5)).max(1e-12);
            -(count as f64) * p.log2()
        })
        .sum()
}

/// Rounded mean and the σ level of least code length of each of `groups` groups of the stored
/// elements, element i in group `group_of(i)`.
fn fit_groups(
    values: &[i32],
    groups: usize,
    group_of: impl Fn(usize) -> usize,
    coded: CodedMask,
) -> Vec<(i32, u8)> {
    let mut members = vec![Vec::new(); groups];
    for (i, &v) in values.iter().enumerate() {
        if is_coded(coded, i) {
            members[group_of(i)].push(v);
        }
    }
    members
        .iter()
        .map(|group| {
            let elements = group.iter().copied();
            let (sum, count) = elements
                .clone()
                .fold((0i64, 0i64), |(s, n), v| (s + v as i64, n + 1));
            if count == 0 {
                return (0, 0);
            }
            let mean = (sum as f64 / count as f64).round() as i32;
            let mut histogram = std::collections::BTreeMap::new();
            for v in elements {
                *histogram.entry(v - mean).or_insert(0u64) += 1;
            }
            let level = (0..SCALE_LEVELS as u16)
                .map(|l| (histogram_bits(&histogram, l as u8), l as u8))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .expect("levels")
                .1;
            (mean, level)
        })
        .collect()
}

/// (element, rounded mean, level) of one decoding stage under the conditional models, from the
/// scene as decoded so far. Stages: feature chunks, stream frames, or one.
fn stage_count(attribute: Attribute, scene: &QuantizedScene) -> usize {
    match attribute {
        Attribute::Features => feature_chunks(scene.meta.feature_dim),
        Attribute::TimeFeatures => scene.meta.frames,
        _ => 1,
    }
}

fn stage_params(
    attribute: Attribute,
    stage: usize,
    scene: &QuantizedScene,
    models: &HostEntropyModels,
    coded: CodedMask,
) -> Vec<(usize, i32, u8)> {
    let m = &scene.meta;
    let n = scene.voxels.len();
    let cf = m.feature_dim;
    let level = |sigma: f32| scale_level(sigma as f64);
    let mut out = Vec::new();
    match attribute {
        Attribute::Features => {
            let j = stage;
            let mut context = vec![0.0f32; CONTEXT_LENGTH * FEATURE_CHUNK];
            for a in 0..n {
                let row = &scene.features[a * cf..(a + 1) * cf];
                for (slot, d) in (1..=CONTEXT_LENGTH).rev().enumerate() {
                    for c in 0..FEATURE_CHUNK {
                        let channel =
                            (j as isize - d as isize) * FEATURE_CHUNK as isize + c as isize;
                        context[slot * FEATURE_CHUNK + c] =
                            if channel >= 0 && (channel as usize) < cf {
                                row[channel as usize] as f32
                            } else {
                                0.0
                            };
                    }
                }
                let gaussians = models.features.gaussians(&context, FEATURE_CHUNK);
                for (c, &(mu, sigma)) in gaussians.iter().enumerate() {
                    let channel = j * FEATURE_CHUNK + c;
                    let i = a * cf + channel;
                    if channel < cf && is_coded(coded, i) {
                        out.push((i, mu, level(sigma)));
                    }
                }
            }
        }
        Attribute::Factors | Attribute::LogScales | Attribute::Offsets => {
            let (model, width) = match attribute {
                Attribute::Factors => (&models.factors, FACTOR_COUNT),
                Attribute::LogScales => (&models.log_scales, SCALE_DIMS),
                _ => (&models.offsets, 3 * m.slots),
            };
            for a in 0..n {
                let context: Vec<f32> = scene.features[a * cf..(a + 1) * cf]
                    .iter()
                    .map(|&q| q as f32)
                    .collect();
                for (c, &(mu, sigma)) in model.gaussians(&context, width).iter().enumerate() {
                    let i = a * width + c;
                    if is_coded(coded, i) {
                        out.push((i, mu, level(sigma)));
                    }
                }
            }
        }
        Attribute::TimeFeatures => {
            let (t, ct) = (m.frames, m.time_feature_dim);
            let f = stage;
            let mut context = vec![0.0f32; CONTEXT_LENGTH * ct];
            for a in 0..n {
                let first = (a * t + f) * ct;
                if !is_coded(coded, first) {
                    continue; // the whole stream of this anchor is not stored
                }
                for (slot, d) in (1..=CONTEXT_LENGTH).rev().enumerate() {
                    for c in 0..ct {
                        context[slot * ct + c] = if f >= d {
                            scene.time_features[(a * t + f - d) * ct + c] as f32
                        } else {
                            0.0
                        };
                    }
                }
                for (c, &(mu, sigma)) in models
                    .time_features
                    .gaussians(&context, ct)
                    .iter()
                    .enumerate()
                {
                    out.push((first + c, mu, level(sigma)));
                }
            }
        }
        Attribute::Trajectory | Attribute::Turn => {
            unreachable!("trajectories and turns are coded factorized")
        }
    }
    out
}

fn stream_radius(symbols: &[i32]) -> Result<i32> {
    let radius = symbols
        .iter()
        .map(|y| y.unsigned_abs())
        .max()
        .unwrap_or(0)
        .max(1);
    ensure!(
        radius <= MAX_RADIUS as u32,
        "an attribute index of {radius} steps from its prediction is outside the codable range: \
         a quantisation step much too small for the values"
    );
    Ok(radius as i32)
}

fn encode_factorized(values: &[i32], channels: usize, coded: CodedMask) -> Result<Vec<u8>> {
    encode_grouped(FACTORIZED, values, channels, |i, _| i % channels, coded)
}

/// Groups of the knot-context coding: from the third knot on, the previous knot's largest
/// |increment| of the same anchor in 7 buckets (0, 1, 2-3, 4-7, 8-15, 16-31, more); the first
/// knot (an absolute value) and the second (after an absolute value, which says nothing of the
/// motion) have one each.
const KNOT_CONTEXTS: usize = 9;

/// The group of element `i` of a knot table (rows of `knots` knots × 3 axes, knot-to-knot
/// increments) under the knot-context coding: context × 3 + axis, from `values[..i]` only (what
/// the decoder already has).
fn knot_group(values: &[i32], i: usize, knots: usize) -> usize {
    let (knot, axis) = ((i / 3) % knots, i % 3);
    let context = match knot {
        0 => 7,
        1 => 8,
        _ => {
            let previous = i - axis - 3;
            let largest = values[previous..previous + 3]
                .iter()
                .map(|v| v.unsigned_abs())
                .max()
                .expect("three axes");
            (u32::BITS - largest.leading_zeros()).min(6) as usize
        }
    };
    context * 3 + axis
}

/// A knot table (trajectory or turn) coded factorized with one Gaussian per (previous knot's
/// increment bucket, axis): an anchor whose knots barely move (most of a scene's) costs far less
/// than under one Gaussian per axis, whose σ the moving objects' increments set. Kept only when
/// smaller than the plain per-axis fit (older files have only that).
fn encode_knot_context(values: &[i32], knots: usize, coded: CodedMask) -> Result<Vec<u8>> {
    encode_grouped(
        KNOT_CONTEXT,
        values,
        KNOT_CONTEXTS * 3,
        |i, v| knot_group(v, i, knots),
        coded,
    )
}

fn encode_grouped(
    kind: u8,
    values: &[i32],
    groups: usize,
    group_of: impl Fn(usize, &[i32]) -> usize,
    coded: CodedMask,
) -> Result<Vec<u8>> {
    let params = fit_groups(values, groups, |i| group_of(i, values), coded);
    let mut symbols = Vec::new();
    let mut levels = Vec::new();
    for (i, &v) in values.iter().enumerate() {
        if is_coded(coded, i) {
            let (mean, level) = params[group_of(i, values)];
            symbols.push(v - mean);
            levels.push(level);
        }
    }
    let radius = stream_radius(&symbols)?;
    let mut tables = GaussianTables::new(radius)?;
    let mut w = Writer::default();
    w.u8(kind);
    w.u32(groups as u32);
    for &(mean, level) in &params {
        w.i32(mean);
        w.u8(level);
    }
    w.i32(radius);
    w.block(&encode_gaussian(&symbols, &levels, &mut tables)?);
    Ok(w.bytes)
}

fn encode_conditional(
    attribute: Attribute,
    scene: &QuantizedScene,
    models: &HostEntropyModels,
    coded: CodedMask,
) -> Result<Vec<u8>> {
    let values = attribute.values(scene);
    let mut symbols = Vec::new();
    let mut levels = Vec::new();
    for stage in 0..stage_count(attribute, scene) {
        for (i, mu, level) in stage_params(attribute, stage, scene, models, coded) {
            symbols.push(
                values[i]
                    .checked_sub(mu)
                    .context("a prediction far outside the value range")?,
            );
            levels.push(level);
        }
    }
    let radius = stream_radius(&symbols)?;
    let mut tables = GaussianTables::new(radius)?;
    let mut w = Writer::default();
    w.u8(CONDITIONAL);
    w.i32(radius);
    w.block(&encode_gaussian(&symbols, &levels, &mut tables)?);
    Ok(w.bytes)
}

/// The section bytes of `attribute` (see [`ModelChoice`]).
pub fn encode_attribute(
    attribute: Attribute,
    scene: &QuantizedScene,
    coded: CodedMask,
    models: Option<&HostEntropyModels>,
    choice: ModelChoice,
) -> Result<Vec<u8>> {
    encode_section(attribute, scene, coded, models, choice).with_context(|| {
        format!(
            "cannot code the `{}` section (a `compression.steps` value too fine for it?)",
            attribute.section()
        )
    })
}

fn encode_section(
    attribute: Attribute,
    scene: &QuantizedScene,
    coded: CodedMask,
    models: Option<&HostEntropyModels>,
    choice: ModelChoice,
) -> Result<Vec<u8>> {
    let factorized =
        || encode_factorized(attribute.values(scene), attribute.channels(scene), coded);
    if attribute.factorized_only() {
        // Knot tables: the smaller of the per-axis fit and the knot-context fit (which scenes
        // of an older codec version cannot hold).
        let knots = scene.meta.dims().trajectory_knots();
        let a = factorized()?;
        if scene.meta.codec_version < KNOT_CONTEXT_VERSION {
            return Ok(a);
        }
        let b = encode_knot_context(attribute.values(scene), knots, coded)?;
        return Ok(if b.len() < a.len() { b } else { a });
    }
    match (choice, models) {
        (ModelChoice::Factorized, _) | (ModelChoice::Smallest, None) => factorized(),
        (ModelChoice::Conditional, None) => {
            bail!(
                "conditional coding of {} needs entropy models",
                attribute.section()
            )
        }
        (ModelChoice::Conditional, Some(m)) => encode_conditional(attribute, scene, m, coded),
        (ModelChoice::Smallest, Some(m)) => {
            let a = factorized()?;
            let b = encode_conditional(attribute, scene, m, coded)?;
            Ok(if b.len() < a.len() { b } else { a })
        }
    }
}

/// Whether a section was coded with the entropy models.
pub fn uses_models(bytes: &[u8]) -> bool {
    bytes.first() == Some(&CONDITIONAL)
}

/// How a section was coded, in words: "conditional", "factorized" or "knot-context".
pub fn section_model(bytes: &[u8]) -> &'static str {
    match bytes.first() {
        Some(&CONDITIONAL) => "conditional",
        Some(&KNOT_CONTEXT) => "knot-context",
        _ => "factorized",
    }
}

/// Decodes `attribute` into `scene` (rows × channels of it, zeros where not stored); the
/// attributes it conditions on must already be decoded.
pub fn decode_attribute(
    attribute: Attribute,
    bytes: &[u8],
    scene: &mut QuantizedScene,
    coded: CodedMask,
    models: Option<&HostEntropyModels>,
    what: &str,
) -> Result<()> {
    let channels = attribute.channels(scene);
    let total = attribute.rows(scene) * channels;
    *attribute.values_mut(scene) = vec![0; total];
    let mut r = Reader::new(bytes, what);
    let kind = r.u8("model kind")?;
    match kind {
        FACTORIZED | KNOT_CONTEXT => {
            let knots = scene.meta.dims().trajectory_knots();
            let groups = if kind == KNOT_CONTEXT {
                ensure!(
                    scene.meta.codec_version >= KNOT_CONTEXT_VERSION,
                    "{what}: knot-context coding in a version-{} scene (it came with version \
                     {KNOT_CONTEXT_VERSION})",
                    scene.meta.codec_version
                );
                ensure!(
                    attribute.factorized_only() && knots > 0,
                    "{what}: knot-context coding in the {} section, which has no knots",
                    attribute.section()
                );
                KNOT_CONTEXTS * 3
            } else {
                channels
            };
            let stored = r.u32("channel count")? as usize;
            ensure!(
                stored == groups,
                "{what}: {stored} channels, the scene needs {groups}"
            );
            let params = (0..groups)
                .map(|_| Ok((r.i32("channel mean")?, r.u8("channel scale level")?)))
                .collect::<Result<Vec<_>>>()?;
            let radius = r.i32("symbol range")?;
            let stream = r.block("coded symbols")?;
            r.finish()?;
            let mut tables = GaussianTables::new(radius).with_context(|| what.to_string())?;
            let mut decoder = GaussianDecoder::new(stream, what)?;
            let values = attribute.values_mut(scene);
            for i in 0..values.len() {
                if is_coded(coded, i) {
                    let group = if kind == KNOT_CONTEXT {
                        knot_group(values, i, knots)
                    } else {
                        i % channels
                    };
                    let (mean, level) = params[group];
                    values[i] = mean
                        .checked_add(decoder.next(level, &mut tables)?)
                        .with_context(|| format!("{what}: index overflows"))?;
                }
            }
            decoder.finish()
        }
        CONDITIONAL if attribute.factorized_only() => {
            bail!("{what}: {} has no conditional model", attribute.section())
        }
        CONDITIONAL => {
            let models = models.with_context(|| {
                format!("{what}: coded with entropy models, but the file has none")
            })?;
            let radius = r.i32("symbol range")?;
            let stream = r.block("coded symbols")?;
            r.finish()?;
            let mut tables = GaussianTables::new(radius).with_context(|| what.to_string())?;
            let mut decoder = GaussianDecoder::new(stream, what)?;
            for stage in 0..stage_count(attribute, scene) {
                let params = stage_params(attribute, stage, scene, models, coded);
                let values = attribute.values_mut(scene);
                for (i, mu, level) in params {
                    values[i] = mu
                        .checked_add(decoder.next(level, &mut tables)?)
                        .with_context(|| format!("{what}: index overflows"))?;
                }
            }
            decoder.finish()
        }
        other => bail!("{what}: unknown model kind {other}"),
    }
}
