//! Runs to files and back: `acags compress --run DIR` writes `scene.acags` with a size report;
//! `acags eval --bitstream` / `render --bitstream` decode one into a model and its dataset.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use serde::Serialize;

use super::attributes::{Attribute, ModelChoice, section_model};
use super::bitstream::QuantizedScene;
use super::container::Container;
use super::quantization::RatePreset;
use super::trained_model::TrainedModel;
use crate::config::{CompressionMode, TrainConfig};
use crate::data::Scene;
use crate::model::anchored::AnchoredModel;
use crate::model::view::Phase;

pub const SCENE_FILE: &str = "scene.acags";
pub const COMPRESSION_REPORT_FILE: &str = "compression.json";

/// One section's share of the file.
#[derive(Clone, Debug, Serialize)]
pub struct SectionSize {
    pub name: String,
    pub bytes: usize,
    /// For attributes: which entropy model coded it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<&'static str>,
}

/// What `acags compress` reports (and writes beside the file as JSON).
#[derive(Clone, Debug, Serialize)]
pub struct CompressionReport {
    pub file: PathBuf,
    pub rate: RatePreset,
    /// Whether training simulated this grid (false: a full-precision model rounded afterwards).
    pub trained_on_grid: bool,
    pub anchors_in: usize,
    pub anchors_stored: usize,
    /// The file, container framing included.
    pub file_bytes: usize,
    /// The uncompressed float32 model (`metrics.json`'s `uncompressed_mib`, in bytes).
    pub uncompressed_bytes: usize,
    pub ratio: f64,
    pub sections: Vec<SectionSize>,
}

impl CompressionReport {
    /// The size table `acags compress` prints.
    pub fn table(&self) -> String {
        let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
        let mut out = format!(
            "{:<14} {:>12} {:>10} {:>7}  model\n",
            "section", "bytes", "MiB", "share"
        );
        for s in &self.sections {
            out += &format!(
                "{:<14} {:>12} {:>10.4} {:>6.1}%  {}\n",
                s.name,
                s.bytes,
                mib(s.bytes),
                100.0 * s.bytes as f64 / self.file_bytes as f64,
                s.model.unwrap_or("")
            );
        }
        out += &format!(
            "{:<14} {:>12} {:>10.4}\n{} anchors of {} stored; uncompressed {:.2} MiB -> {:.4} MiB, {:.1}x",
            "total (file)",
            self.file_bytes,
            mib(self.file_bytes),
            self.anchors_stored,
            self.anchors_in,
            mib(self.uncompressed_bytes),
            mib(self.file_bytes),
            self.ratio
        );
        out
    }
}

/// The quantised scene of a trained model on `rate`'s grid, with the config's step overrides.
pub fn quantize(trained: &TrainedModel, rate: RatePreset) -> Result<QuantizedScene> {
    QuantizedScene::from_model(
        &trained.model,
        rate,
        trained.config.compression.steps_for(rate),
        trained.phase(),
        trained.gop,
        trained.config.model.voxel_size,
        trained.config.to_toml(),
    )
}

/// Encodes a trained model into `out` and writes its size report beside it
/// ([`COMPRESSION_REPORT_FILE`]); `uncompressed_bytes` is the run's reference size.
pub fn compress(
    trained: &TrainedModel,
    rate: Option<RatePreset>,
    out: &Path,
    uncompressed_bytes: usize,
) -> Result<CompressionReport> {
    let cfg = &trained.config.compression;
    let rate = rate.unwrap_or(cfg.rate);
    let trained_on_grid = cfg.mode == CompressionMode::Simulate && rate == cfg.rate;
    if !trained_on_grid {
        eprintln!(
            "warning: the run was not trained on the {} grid; rounding a model that never saw it \
             costs quality",
            rate.name()
        );
    }
    let scene = quantize(trained, rate)?;
    let models = trained.entropy.host();
    let container = scene.encode(Some(&models), ModelChoice::Smallest)?;
    container.write(out)?;
    let file_bytes = std::fs::metadata(out)
        .with_context(|| format!("cannot stat {}", out.display()))?
        .len() as usize;
    let report = CompressionReport {
        file: out.to_path_buf(),
        rate,
        trained_on_grid,
        anchors_in: trained.model.anchors.len(),
        anchors_stored: scene.meta.anchors,
        file_bytes,
        uncompressed_bytes,
        ratio: uncompressed_bytes as f64 / file_bytes as f64,
        sections: container
            .sections
            .iter()
            .map(|s| SectionSize {
                name: s.name.clone(),
                bytes: s.data.len(),
                model: Attribute::ALL
                    .iter()
                    .find(|a| a.section() == s.name)
                    .map(|_| section_model(&s.data)),
            })
            .collect(),
    };
    let json = out.with_file_name(COMPRESSION_REPORT_FILE);
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    Ok(report)
}

/// A decoded file: the model, the config it was trained with and how to decode it.
pub struct DecodedScene {
    pub scene: QuantizedScene,
    pub model: AnchoredModel,
    pub config: TrainConfig,
    pub phase: Phase,
    pub file_bytes: usize,
}

/// Reads and decodes `path` onto `device`.
pub fn read_scene(path: &Path, device: &Device) -> Result<DecodedScene> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let origin = path.display().to_string();
    let container = Container::from_bytes(&bytes, &origin)?;
    let (scene, _) = QuantizedScene::decode(&container, &origin)?;
    let config = TrainConfig::parse(
        &scene.meta.config,
        &format!("{origin}: embedded config"),
        &[],
    )?;
    let model = scene
        .to_model(device)
        .with_context(|| format!("{origin}: cannot rebuild the model"))?;
    Ok(DecodedScene {
        phase: scene.meta.phase(),
        model,
        config,
        file_bytes: bytes.len(),
        scene,
    })
}

/// The dataset to evaluate a decoded scene on: the embedded config's, or `data` instead; its GOP
/// must be the trained one.
pub fn scene_dataset(decoded: &DecodedScene, data: Option<&str>) -> Result<Scene> {
    let mut config = decoded.config.clone();
    if let Some(d) = data {
        config.data.dataset = d.to_string();
    }
    let scene = config.data.load_scene()?;
    let meta = &decoded.scene.meta;
    if scene.frames.start != meta.gop_start || scene.frames.count != meta.gop_frames {
        bail!(
            "dataset {} has frames {:?}, the scene was trained on {:?}",
            config.data.dataset,
            scene.frames.frames(),
            meta.gop_start..meta.gop_start + meta.gop_frames
        );
    }
    Ok(scene)
}
