//! Run directories and the `train`, `eval` and `render` commands.
//!
//! A run directory holds `config.toml` (resolved), `checkpoint.safetensors` (latest, written
//! atomically), `train_log.csv`, `metrics.json`, `renders/` (test views: ground truth | render |
//! error) and, for finished runs trained with the compression simulation, `scene.acags` with
//! `compression.json` (its size report); `metrics.json` then also holds the decoded file's
//! metrics.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use serde::Serialize;

use crate::codec::trained_model::TrainedModel;
use crate::compute_backend::{BackendKind, resolve};
use crate::config::SeedHold;
use crate::data::Scene;
use crate::data::frames::FrameCache;
use crate::eval::evaluate::{EvalSummary, LpipsSummary, Scoring, evaluate, render_view};
use crate::train::config::TrainConfig;
use crate::train::seed_hold;
use crate::train::trainer::{StepReport, Trainer, TrainingHistory, read_trained_model};

pub const CONFIG_FILE: &str = "config.toml";
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
pub const LOG_FILE: &str = "train_log.csv";
pub const METRICS_FILE: &str = "metrics.json";
/// `quality_by_frame.png|svg`: full-frame, dynamic and static PSNR per frame of the shipped model.
pub const QUALITY_CHART: &str = "quality_by_frame";
/// `psnr_by_camera.png|svg` and `lpips_by_camera.png|svg`: PSNR and LPIPS-Alex against frame, one
/// line per test camera, of the shipped model (where a dynamic scene breaks, camera by camera).
pub const CAMERA_CHARTS: [&str; 2] = ["psnr_by_camera", "lpips_by_camera"];
/// The fixed columns of `train_log.csv`; one column per objective term follows
/// ([`crate::train::objective::Term::name`], empty where the term was not computed).
const LOG_HEADER: &str = "step,loss,psnr,anchors,visible_anchors,gaussians,added,pruned,skipped,step_seconds,train_seconds,active_slots,masking_ratio,deactivated,relocated,churn_judged,churn_below,rate_bits";

fn log_header() -> String {
    let terms = crate::train::objective::Term::ALL.map(|t| t.name());
    format!("{LOG_HEADER},{}", terms.join(","))
}

/// Everything `metrics.json` records.
#[derive(Clone, Debug, Serialize)]
pub struct RunMetrics {
    pub step: usize,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(flatten)]
    pub lpips: LpipsSummary,
    #[serde(flatten)]
    pub regions: crate::eval::evaluate::RegionSummary,
    pub anchors: usize,
    /// Mean Gaussians spawned per test image.
    pub gaussians: f64,
    /// Active (ungated) slots over all anchors: the model's Gaussian count (= anchors · K
    /// under fixed cardinality).
    pub active_slots: usize,
    /// Entry c: anchors with c active slots.
    pub cardinality_histogram: Vec<usize>,
    /// Fraction of anchors whose F_adapt is masked (0 when masking is off).
    pub masking_ratio: f64,
    /// Uncompressed float32 size of the stored model (anchors and decoders), MiB: gated slots'
    /// offsets and masked channels are not stored, their bitmaps are (spec §14 A22).
    pub uncompressed_mib: f64,
    /// AAC relocation churn: relocated slots judged by the next AAC step and those that stayed
    /// below τ (absent without AAC).
    pub relocation_churn: Option<crate::train::adaptive_cardinality::RelocationChurn>,
    /// What the ACA-GS post-hoc step removed (absent for GIFStream).
    pub posthoc: Option<crate::train::posthoc::PostHocReport>,
    /// The run's `scene.acags` decoded and evaluated (finished runs trained with the compression
    /// simulation).
    pub compressed: Option<CompressedMetrics>,
    pub train_seconds: f64,
    pub render_fps: f64,
    pub nan_steps: usize,
    pub backend: String,
    pub views: Vec<crate::eval::evaluate::ViewMetrics>,
}

/// The bitstream of a run: its size and the test metrics of its decoded model.
#[derive(Clone, Debug, Serialize)]
pub struct CompressedMetrics {
    pub rate: crate::codec::quantization::RatePreset,
    pub file_bytes: usize,
    pub file_mib: f64,
    /// Uncompressed size / file size.
    pub ratio: f64,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(flatten)]
    pub lpips: LpipsSummary,
    #[serde(flatten)]
    pub regions: crate::eval::evaluate::RegionSummary,
    pub render_fps: f64,
    /// Per test view, of the decoded model (what the stability suite's worst frame reads).
    pub views: Vec<crate::eval::evaluate::ViewMetrics>,
}

impl RunMetrics {
    /// One line: step, PSNR, SSIM, anchors, Gaussians, size, FPS (and the bitstream's).
    pub fn summary(&self) -> String {
        let compressed = self.compressed.as_ref().map_or(String::new(), |c| {
            format!(
                "; compressed ({}) {:.4} MiB ({:.1}x): PSNR {:.3} dB, SSIM {:.4}{}, {}",
                c.rate.name(),
                c.file_mib,
                c.ratio,
                c.psnr,
                c.ssim,
                c.lpips.text(),
                c.regions.text()
            )
        });
        format!(
            "step {}: test PSNR {:.3} dB, SSIM {:.4}{}, {}, {} anchors, {} active slots, \
             {:.0} Gaussians/view, masking ratio {:.1} %, {:.2} MiB, {:.1} FPS{}",
            self.step,
            self.psnr,
            self.ssim,
            self.lpips.text(),
            self.regions.text(),
            self.anchors,
            self.active_slots,
            self.gaussians,
            100.0 * self.masking_ratio,
            self.uncompressed_mib,
            self.render_fps,
            compressed
        )
    }
}

fn run_metrics(
    run: &RunParts,
    eval: EvalSummary,
    backend: &str,
    posthoc: Option<crate::train::posthoc::PostHocReport>,
    compressed: Option<CompressedMetrics>,
) -> RunMetrics {
    let trained = run.trained;
    let anchors = &trained.model.anchors;
    let bytes = uncompressed_bytes(&trained.model);
    RunMetrics {
        step: trained.step,
        psnr: eval.psnr,
        ssim: eval.ssim,
        lpips: eval.lpips.clone(),
        regions: eval.regions.clone(),
        anchors: anchors.len(),
        gaussians: eval.gaussians,
        active_slots: anchors.active_slot_count(),
        cardinality_histogram: anchors.cardinality_histogram(),
        masking_ratio: anchors.masking_ratio(),
        relocation_churn: (trained.config.aac.mode
            == crate::train::config::CardinalityMode::Adaptive)
            .then_some(run.history.relocation_churn),
        uncompressed_mib: bytes as f64 / (1024.0 * 1024.0),
        posthoc,
        compressed,
        train_seconds: run.history.train_seconds,
        render_fps: eval.render_fps,
        nan_steps: run.history.nan_steps,
        backend: backend.to_string(),
        views: eval.views,
    }
}

/// Float32 bytes of the stored model: anchors (spec §14 A22) and decoders.
pub fn uncompressed_bytes(model: &crate::model::anchored::AnchoredModel) -> usize {
    model.anchors.stored_bytes() + crate::model::decoders::parameter_count(&model.decoders) * 4
}

/// Options of `acags train`.
#[derive(Clone, Debug, clap::Args)]
pub struct TrainOptions {
    /// TOML config; the embedded configs/default.toml when omitted.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override one config key, e.g. --set train.max_steps=500 (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: BackendKind,
    /// Run directory (default runs/train-<time>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Continue the run in this directory from its checkpoint, exactly.
    #[arg(long)]
    pub resume: Option<PathBuf>,
    /// Stop after this many steps (the schedule still spans train.max_steps; --resume continues).
    #[arg(long)]
    pub stop_after: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

fn default_out_dir() -> PathBuf {
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!("train-{stamp}"))
}

/// `acags train`.
pub fn train(options: TrainOptions) -> Result<RunMetrics> {
    let chosen = resolve(options.backend)?;
    eprintln!("backend: {}", chosen.description);
    let (config, dir) = match &options.resume {
        Some(dir) => {
            if options.config.is_some() {
                bail!("--resume takes the run's own config.toml; drop --config");
            }
            if options.out.as_ref().is_some_and(|o| o != dir) {
                bail!("--resume continues in the run directory; drop --out");
            }
            let path = dir.join(CONFIG_FILE);
            (
                TrainConfig::load(Some(&path), &options.overrides)?,
                dir.clone(),
            )
        }
        None => {
            let config = TrainConfig::load(options.config.as_deref(), &options.overrides)?;
            let dir = options.out.clone().unwrap_or_else(default_out_dir);
            if dir.join(CHECKPOINT_FILE).exists() {
                bail!(
                    "{} already holds a run; continue it with --resume {} or pick another --out",
                    dir.display(),
                    dir.display()
                );
            }
            (config, dir)
        }
    };
    train_run(
        config,
        &dir,
        options.resume.is_some(),
        &chosen,
        options.stop_after,
        options.quiet,
    )
}

/// Trains `config` in `dir` (a fresh run, or the run's checkpoint continued when `resume`) and
/// evaluates it: what `acags train` and every sweep cell do.
pub fn train_run(
    config: TrainConfig,
    dir: &Path,
    resume: bool,
    chosen: &crate::compute_backend::ChosenDevice,
    stop_after: Option<usize>,
    quiet: bool,
) -> Result<RunMetrics> {
    let dir = dir.to_path_buf();
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    std::fs::write(dir.join(CONFIG_FILE), config.to_toml())
        .with_context(|| format!("cannot write {}", dir.join(CONFIG_FILE).display()))?;

    let scene = config.data.load_scene()?;
    eprintln!(
        "scene: {} ({} train / {} test cameras, {} frames, {}x{})",
        scene.root.display(),
        scene.train_cameras.len(),
        scene.test_cameras.len(),
        scene.frames.count,
        scene.resolution().0,
        scene.resolution().1
    );
    let mut trainer = Trainer::new(config.clone(), scene, chosen.device.clone())?;
    if config.train.seed_hold == SeedHold::LongIntervals {
        let dims = trainer.model.anchors.dims;
        let (frames, spacing) = (dims.frames, dims.trajectory_spacing);
        eprintln!(
            "seed hold: {:?} (knots open {:.0} steps apart; held from {:.0})",
            seed_hold::resolved_mode(&config.train, frames, spacing),
            seed_hold::knot_interval_steps(&config.train, frames, spacing),
            seed_hold::LONG_INTERVAL_STEPS
        );
    }
    if resume {
        let path = dir.join(CHECKPOINT_FILE);
        trainer.load_checkpoint(&path)?;
        eprintln!("resumed {} at step {}", path.display(), trainer.step);
    } else if let Some(path) = &config.train.warm_start {
        trainer.warm_start(path, config.train.warm_start_step)?;
        eprintln!(
            "warm start from {} at step {}",
            path.display(),
            config.train.warm_start_step
        );
    }
    let mut log = open_log(&dir.join(LOG_FILE), trainer.step)?;

    let max = config.train.max_steps;
    let stop_at = stop_after.map_or(max, |n| (trainer.step + n).min(max));
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(max as u64)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {per_sec} {msg}",
        )
        .expect("valid template"),
    );
    bar.set_position(trainer.step as u64);
    // Under a script or `nohup` the bar is not drawn: a progress line every 2 % instead.
    let mut progress = (!quiet && !std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .then(|| ProgressLines::new(trainer.step, max));
    while trainer.step < stop_at {
        let report = trainer.step()?;
        if report.skipped {
            say(
                &bar,
                format!("step {}: non-finite loss, step skipped", report.step),
            );
        }
        if let Some(r) = &report.relocation {
            say(
                &bar,
                format!(
                    "step {}: AAC deactivated {} of {} active slots, relocated {}{}{}",
                    report.step,
                    r.deactivated,
                    r.active_before,
                    r.relocated,
                    if r.dropped > 0 {
                        format!(" ({} found no free slot)", r.dropped)
                    } else {
                        String::new()
                    },
                    if r.previous_relocated > 0 {
                        format!(
                            "; {} of the previous step's {} relocated slots stayed below τ",
                            r.previous_below_threshold, r.previous_relocated
                        )
                    } else {
                        String::new()
                    }
                ),
            );
        }
        // Skipped steps always get a row: the log is where a NaN event is found afterwards.
        if report.step % config.train.log_every == 0
            || trainer.step == stop_at
            || report.relocation.is_some()
            || report.skipped
        {
            // The masking ratio reads the mask logits back from the device: log rows only.
            let masking_ratio = trainer.model.anchors.masking_ratio();
            write_log_row(&mut log, &report, trainer.train_seconds, masking_ratio)?;
        }
        bar.set_message(format!(
            "loss {:.4} psnr {:.2} anchors {} gaussians {}",
            report.loss, report.psnr, report.anchors, report.gaussians
        ));
        bar.inc(1);
        if let Some(line) = progress.as_mut().and_then(|p| p.line(&report)) {
            eprintln!("{line}");
        }
        let done = trainer.step;
        let every = |n: usize| n > 0 && done % n == 0 && done < max;
        if every(config.train.checkpoint_every) {
            log.flush()?;
            trainer.save_checkpoint(&dir.join(CHECKPOINT_FILE))?;
        }
        if config.train.snapshot_steps.contains(&done) {
            trainer.save_checkpoint(&dir.join(format!("checkpoint-step{done}.safetensors")))?;
        }
        if every(config.train.eval_every) {
            let eval = evaluate(
                &trainer.model,
                &trainer.scene,
                &trainer.frames,
                trainer.phase(done),
                &config.eval,
                Scoring::PixelOnly,
                None,
            )?;
            let a = &trainer.model.anchors;
            say(
                &bar,
                format!(
                    "step {done}: test PSNR {:.3} SSIM {:.4}, {} ({} anchors, {} active slots, \
                     cardinality histogram {:?}, masking ratio {:.1} %)",
                    eval.psnr,
                    eval.ssim,
                    eval.regions.text(),
                    a.len(),
                    a.active_slot_count(),
                    a.cardinality_histogram(),
                    100.0 * a.masking_ratio()
                ),
            );
        }
    }
    bar.finish_and_clear();
    log.flush()?;
    // The ACA-GS post-hoc step once the schedule is done (idempotent, so a resumed finished run
    // is unaffected); the stored checkpoint is the pruned model.
    let posthoc = if trainer.finished() {
        trainer.finish_training()
    } else {
        None
    };
    if let Some(p) = &posthoc {
        eprintln!(
            "post-hoc: removed {} anchors without active slots, dropped F_adapt of {} anchors",
            p.removed_anchors, p.masked_anchors
        );
    }
    trainer.save_checkpoint(&dir.join(CHECKPOINT_FILE))?;
    if trainer.nan_steps > 0 {
        eprintln!(
            "warning: {} steps were skipped for a non-finite loss",
            trainer.nan_steps
        );
    }
    let trained = trainer.trained_model();
    let run = RunParts {
        trained: &trained,
        scene: &trainer.scene,
        frames: &trainer.frames,
        history: trainer.history(),
        device: &trainer.device,
    };
    let metrics = evaluate_run(&run, &dir, &chosen.description, posthoc, true)?;
    eprintln!(
        "{}, trained {:.0} s -> {}",
        metrics.summary(),
        metrics.train_seconds,
        dir.display()
    );
    Ok(metrics)
}

/// A trained model with its dataset and history: a run just trained, or one opened from its
/// directory.
struct RunParts<'a> {
    trained: &'a TrainedModel,
    scene: &'a Scene,
    frames: &'a FrameCache,
    history: TrainingHistory,
    device: &'a Device,
}

/// Evaluates a run's model on the test set, writes renders and `metrics.json`.
fn evaluate_run(
    run: &RunParts,
    dir: &Path,
    backend: &str,
    posthoc: Option<crate::train::posthoc::PostHocReport>,
    write_bitstream: bool,
) -> Result<RunMetrics> {
    let compressed = compress_and_evaluate(run, dir, write_bitstream)?;
    let eval = evaluate(
        &run.trained.model,
        run.scene,
        run.frames,
        run.trained.phase(),
        &run.trained.config.eval,
        Scoring::Full,
        Some(&dir.join("renders")),
    )?;
    let (shipped, shipped_views) = compressed
        .as_ref()
        .map_or((&eval.regions, &eval.views), |c| (&c.regions, &c.views));
    write_quality_chart(shipped, &dir.join(QUALITY_CHART))?;
    write_camera_charts(shipped_views, &CAMERA_CHARTS.map(|c| dir.join(c)))?;
    let metrics = run_metrics(run, eval, backend, posthoc, compressed);
    let path = dir.join(METRICS_FILE);
    std::fs::write(&path, serde_json::to_string_pretty(&metrics)?)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(metrics)
}

/// A finished run trained with the compression simulation gets its `scene.acags` (written when
/// `write`, else only re-read if present), decoded and evaluated like the client would.
fn compress_and_evaluate(
    run: &RunParts,
    dir: &Path,
    write: bool,
) -> Result<Option<CompressedMetrics>> {
    use crate::codec::scene_file::{SCENE_FILE, compress};
    let trained = run.trained;
    let file = dir.join(SCENE_FILE);
    let simulated =
        trained.config.compression.mode == crate::train::config::CompressionMode::Simulate;
    if write && simulated && trained.finished() {
        let report = compress(trained, None, &file, uncompressed_bytes(&trained.model))?;
        eprintln!("{}", report.table());
    }
    if !file.exists() {
        return Ok(None);
    }
    let decoded = crate::codec::scene_file::read_scene(&file, run.device)?;
    let eval = evaluate(
        &decoded.model,
        run.scene,
        run.frames,
        decoded.phase,
        &trained.config.eval,
        Scoring::Full,
        None,
    )?;
    Ok(Some(CompressedMetrics {
        regions: eval.regions.clone(),
        lpips: eval.lpips.clone(),
        rate: decoded.scene.meta.rate,
        file_bytes: decoded.file_bytes,
        file_mib: decoded.file_bytes as f64 / (1024.0 * 1024.0),
        ratio: uncompressed_bytes(&trained.model) as f64 / decoded.file_bytes as f64,
        psnr: eval.psnr,
        ssim: eval.ssim,
        render_fps: eval.render_fps,
        views: eval.views,
    }))
}

/// A run directory opened to evaluate, render, visualize or encode: its trained model, read from
/// the checkpoint without optimizer state, its dataset and what training did.
pub struct OpenedRun {
    pub trained: TrainedModel,
    pub scene: Scene,
    pub frames: FrameCache,
    pub history: TrainingHistory,
    pub device: Device,
}

impl OpenedRun {
    fn parts(&self) -> RunParts<'_> {
        RunParts {
            trained: &self.trained,
            scene: &self.scene,
            frames: &self.frames,
            history: self.history,
            device: &self.device,
        }
    }
}

/// Opens the run in `dir` (see [`OpenedRun`]).
pub fn open_run(dir: &Path, device: Device) -> Result<OpenedRun> {
    let config_path = dir.join(CONFIG_FILE);
    if !config_path.exists() {
        bail!(
            "{} is not a run directory (no {CONFIG_FILE})",
            dir.display()
        );
    }
    let config = TrainConfig::load(Some(&config_path), &[])?;
    let scene = config.data.load_scene()?;
    let (trained, history) =
        read_trained_model(&dir.join(CHECKPOINT_FILE), &config, &scene, &device)?;
    Ok(OpenedRun {
        frames: FrameCache::new(config.data.frame_cache_mib << 20),
        trained,
        scene,
        history,
        device,
    })
}

/// PSNR per frame (means over the test cameras) of the full image, its dynamic and its static
/// pixels: `stem.png` and `stem.svg`.
pub fn write_quality_chart(
    regions: &crate::eval::evaluate::RegionSummary,
    stem: &Path,
) -> Result<()> {
    use crate::io::charts::{Chart, Series, write_chart};
    let curve =
        |name: &str, f: &dyn Fn(&crate::eval::evaluate::FrameMetrics) -> Option<f64>| Series {
            name: name.into(),
            points: regions
                .frames
                .iter()
                .filter_map(|m| Some((m.frame as f64, f(m)?)))
                .collect(),
            whiskers: Vec::new(),
        };
    let chart = Chart {
        title: "Test PSNR per frame: full image, moving and static pixels".into(),
        x_label: "frame".into(),
        y_label: "PSNR (dB)".into(),
        log_x: false,
        x_categories: None,
        connect: true,
        reference: None,
        series: vec![
            curve("full frame", &|m| Some(m.psnr)),
            curve("dynamic pixels", &|m| m.dynamic_psnr),
            curve("static pixels", &|m| m.static_psnr),
        ],
    };
    write_chart(&chart, stem)?;
    Ok(())
}

/// PSNR and LPIPS-Alex against frame, one line per test camera: `stems[0]` and `stems[1]`
/// (`.png` and `.svg`). The LPIPS chart is drawn empty ("no data") when LPIPS was not computed.
pub fn write_camera_charts(
    views: &[crate::eval::evaluate::ViewMetrics],
    stems: &[PathBuf; 2],
) -> Result<()> {
    use crate::io::charts::{Chart, Series, write_chart};
    let mut cameras: Vec<usize> = views.iter().map(|v| v.camera).collect();
    cameras.sort_unstable();
    cameras.dedup();
    let lines = |f: fn(&crate::eval::evaluate::ViewMetrics) -> Option<f64>| -> Vec<Series> {
        cameras
            .iter()
            .map(|&camera| {
                let mut points: Vec<(f64, f64)> = views
                    .iter()
                    .filter(|v| v.camera == camera)
                    .filter_map(|v| Some((v.frame as f64, f(v)?)))
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                Series {
                    name: format!("camera {camera}"),
                    points,
                    whiskers: Vec::new(),
                }
            })
            .collect()
    };
    let chart = |title: &str, y_label: &str, series| Chart {
        title: title.into(),
        x_label: "frame".into(),
        y_label: y_label.into(),
        log_x: false,
        x_categories: None,
        connect: true,
        reference: None,
        series,
    };
    write_chart(
        &chart(
            "Test PSNR per frame and camera",
            "PSNR (dB)",
            lines(|v| Some(v.psnr)),
        ),
        &stems[0],
    )?;
    write_chart(
        &chart(
            "Test LPIPS-Alex per frame and camera (lower is better)",
            "LPIPS-Alex",
            lines(|v| v.lpips_alex),
        ),
        &stems[1],
    )?;
    Ok(())
}

/// `acags eval --run DIR`.
pub fn eval(dir: &Path, backend: BackendKind) -> Result<RunMetrics> {
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let run = open_run(dir, chosen.device.clone())?;
    let metrics = evaluate_run(&run.parts(), dir, &chosen.description, None, false)?;
    println!("{}: {}", dir.display(), metrics.summary());
    Ok(metrics)
}

/// `A..B` (end exclusive) or a single frame `A`.
pub fn parse_frame_range(s: &str) -> Result<std::ops::Range<usize>, String> {
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{v}` is not a frame index"))
    };
    match s.split_once("..") {
        Some((a, b)) => {
            let (a, b) = (parse(a)?, parse(b)?);
            if a >= b {
                return Err(format!("empty frame range {a}..{b}"));
            }
            Ok(a..b)
        }
        None => {
            let a = parse(s)?;
            Ok(a..a + 1)
        }
    }
}

/// A run opened on `backend` for rendering `camera` at `frames`, both checked against the rig
/// and the trained GOP.
fn open_run_for_views(
    dir: &Path,
    backend: BackendKind,
    camera: usize,
    frames: std::ops::Range<usize>,
) -> Result<OpenedRun> {
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let run = open_run(dir, chosen.device)?;
    check_views(&run.scene, camera, &frames)?;
    Ok(run)
}

/// `acags render --run DIR --camera I --frames A..B`: PNG frames, and an mp4 when ffmpeg exists.
pub fn render(
    dir: &Path,
    camera: usize,
    frames: std::ops::Range<usize>,
    out: Option<PathBuf>,
    backend: BackendKind,
) -> Result<PathBuf> {
    let run = open_run_for_views(dir, backend, camera, frames.clone())?;
    let out = out.unwrap_or_else(|| dir.join(format!("render_cam{camera:02}")));
    let trained = &run.trained;
    render_frames(
        &trained.model,
        &run.scene,
        trained.phase(),
        camera,
        frames,
        &out,
    )?;
    Ok(out)
}

/// Checks that `camera` and `frames` exist in `scene`.
fn check_views(scene: &Scene, camera: usize, frames: &std::ops::Range<usize>) -> Result<()> {
    if camera >= scene.cameras.len() {
        bail!(
            "camera {camera} does not exist (the rig has {})",
            scene.cameras.len()
        );
    }
    let gop = scene.frames.frames();
    if frames.start < gop.start || frames.end > gop.end {
        bail!("frames {frames:?} are outside the trained GOP {gop:?}");
    }
    Ok(())
}

/// `acags render --bitstream FILE --camera I --frames A..B [--data D]`.
pub fn render_bitstream(
    file: &Path,
    data: Option<&str>,
    camera: usize,
    frames: std::ops::Range<usize>,
    out: Option<PathBuf>,
    backend: BackendKind,
) -> Result<PathBuf> {
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let decoded = crate::codec::scene_file::read_scene(file, &chosen.device)?;
    let scene = crate::codec::scene_file::scene_dataset(&decoded, data)?;
    check_views(&scene, camera, &frames)?;
    let out = out.unwrap_or_else(|| sibling(file, &format!("render_cam{camera:02}")));
    render_frames(&decoded.model, &scene, decoded.phase, camera, frames, &out)?;
    Ok(out)
}

/// Where a trained scene is: a run directory, or a `scene.acags` file (and the dataset to read its
/// cameras from; default the one in its embedded config).
#[derive(Clone, Debug)]
pub enum SceneLocation {
    Run(PathBuf),
    Bitstream { file: PathBuf, data: Option<String> },
}

impl SceneLocation {
    /// `RUN/<name>` for a run, `<dir>/<stem>_<name>` beside a file.
    pub fn output_dir(&self, name: &str) -> PathBuf {
        match self {
            Self::Run(dir) => dir.join(name),
            Self::Bitstream { file, .. } => sibling(file, name),
        }
    }

    /// A path names a run when it is a directory, a bitstream otherwise.
    pub fn from_path(path: PathBuf, data: Option<String>) -> Result<Self> {
        if path.is_dir() {
            if data.is_some() {
                bail!(
                    "--data applies to a scene.acags file, not to the run {}",
                    path.display()
                );
            }
            Ok(Self::Run(path))
        } else if path.is_file() {
            Ok(Self::Bitstream { file: path, data })
        } else {
            bail!("{} is neither a run directory nor a file", path.display())
        }
    }
}

/// A trained model with the dataset it was trained on, from a run or a bitstream.
pub struct OpenedScene {
    pub model: crate::model::anchored::AnchoredModel,
    pub scene: Scene,
    pub phase: crate::model::view::Phase,
    /// What it was opened from, for messages and page titles.
    pub label: String,
    /// Size of the bitstream file, when opened from one.
    pub file_bytes: Option<usize>,
}

impl OpenedScene {
    pub fn export_source(&self) -> crate::export::ExportSource<'_> {
        crate::export::ExportSource {
            model: &self.model,
            scene: &self.scene,
            phase: self.phase,
        }
    }
}

/// Opens `location` on `device`.
pub fn open_scene(location: &SceneLocation, device: Device) -> Result<OpenedScene> {
    match location {
        SceneLocation::Run(dir) => {
            let run = open_run(dir, device)?;
            let phase = run.trained.phase();
            Ok(OpenedScene {
                model: run.trained.model,
                scene: run.scene,
                phase,
                label: dir.display().to_string(),
                file_bytes: None,
            })
        }
        SceneLocation::Bitstream { file, data } => {
            let decoded = crate::codec::scene_file::read_scene(file, &device)?;
            let scene = crate::codec::scene_file::scene_dataset(&decoded, data.as_deref())?;
            Ok(OpenedScene {
                model: decoded.model,
                scene,
                phase: decoded.phase,
                label: file.display().to_string(),
                file_bytes: Some(decoded.file_bytes),
            })
        }
    }
}

/// `acags export`: the frames of a run or a bitstream as standard 3DGS PLY files (see
/// [`crate::export`]); the frame range defaults to the whole GOP, the directory to `export`
/// beside the source.
pub fn export(
    location: &SceneLocation,
    frames: Option<std::ops::Range<usize>>,
    sh_degree: usize,
    out: Option<PathBuf>,
    fidelity: bool,
    backend: BackendKind,
) -> Result<crate::export::ExportManifest> {
    // Checked before the model is opened (again by `export::export`, for library callers).
    crate::export::check_sh_degree(sh_degree)?;
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let opened = open_scene(location, chosen.device.clone())?;
    let frames = frames.unwrap_or_else(|| opened.scene.frames.frames());
    let options = crate::export::ExportOptions {
        frames,
        sh_degree,
        out: out.unwrap_or_else(|| location.output_dir("export")),
        fidelity,
    };
    let manifest = crate::export::export(opened.export_source(), &options, &chosen.device)?;
    if manifest
        .fidelity
        .as_ref()
        .is_some_and(|f| f.views.is_empty())
    {
        eprintln!("fidelity: the dataset has no test cameras, nothing was scored");
    } else if let Some(f) = &manifest.fidelity {
        let db = |v: Option<f64>| v.map_or("identical".to_string(), |v| format!("{v:.2} dB"));
        eprintln!(
            "fidelity against acags' render ({} test views): PSNR {}, worst view {}",
            f.views.len(),
            db(f.psnr_db),
            db(f.min_psnr_db)
        );
    }
    eprintln!(
        "wrote {}",
        options.out.join(crate::export::MANIFEST_FILE).display()
    );
    Ok(manifest)
}

/// `acags view RUN|FILE`: serves the player page until interrupted (see [`crate::view`]).
pub fn view(
    location: &SceneLocation,
    options: &crate::view::ViewOptions,
    backend: BackendKind,
) -> Result<()> {
    // Checked before the model is opened (again by `view::bind`).
    crate::export::check_sh_degree(options.sh_degree)?;
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let opened = open_scene(location, chosen.device)?;
    let label = opened.label.clone();
    let server = crate::view::bind(opened, options)?;
    if !server.address().ip().is_loopback() {
        eprintln!(
            "warning: listening on {}: anyone who can reach this machine can load the scene",
            server.address()
        );
    }
    // The first line on stdout is the address (scripts and the browser test read it).
    println!("{}", server.url());
    std::io::stdout().flush().ok();
    eprintln!("playing {label} at {} (Ctrl-C to stop)", server.url());
    server.serve()
}

/// `FILE`'s directory joined with `<file stem>_<suffix>`.
fn sibling(file: &Path, suffix: &str) -> PathBuf {
    let stem = file
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    file.with_file_name(format!("{stem}_{suffix}"))
}

/// PNG frames (and an mp4 when ffmpeg exists) of `camera` over `frames` into `out`.
fn render_frames(
    model: &crate::model::anchored::AnchoredModel,
    scene: &Scene,
    phase: crate::model::view::Phase,
    camera: usize,
    frames: std::ops::Range<usize>,
    out: &Path,
) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let (w, h) = scene.resolution();
    for (i, frame) in frames.clone().enumerate() {
        let view = crate::data::ViewId { camera, frame };
        let rendered = render_view(model, scene, view, phase)?;
        let rgb: Vec<u8> = rendered
            .image_host()
            .iter()
            .map(|v| (v * 255.0).round() as u8)
            .collect();
        let path = out.join(format!("{i:05}.png"));
        image::RgbImage::from_raw(w, h, rgb)
            .expect("render size")
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    if crate::data::video::tool_available("ffmpeg") {
        let video = out.join("render.mp4");
        let status = std::process::Command::new("ffmpeg")
            .args(["-y", "-loglevel", "error", "-framerate", "30", "-i"])
            .arg(out.join("%05d.png"))
            .args([
                "-pix_fmt",
                "yuv420p",
                "-vf",
                "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            ])
            .arg(&video)
            .status()
            .context("running ffmpeg")?;
        if !status.success() {
            bail!("ffmpeg failed to encode {}", video.display());
        }
        eprintln!("wrote {}", video.display());
    } else {
        eprintln!("ffmpeg not found: wrote PNG frames only");
    }
    Ok(())
}

/// `acags compress --run DIR [--out FILE] [--rate rN]`: writes the bitstream and, beside it,
/// `compression.json`; prints the size table.
pub fn compress(
    dir: &Path,
    out: Option<PathBuf>,
    rate: Option<crate::codec::quantization::RatePreset>,
) -> Result<crate::codec::scene_file::CompressionReport> {
    use crate::codec::scene_file::{COMPRESSION_REPORT_FILE, SCENE_FILE, compress};
    // Quantisation and coding are host-side; the model is read onto the CPU backend.
    let trained = open_run(dir, resolve(BackendKind::Ndarray)?.device)?.trained;
    if !trained.finished() {
        eprintln!(
            "warning: {} stopped at step {} of {}: compressing an unfinished model",
            dir.display(),
            trained.step,
            trained.config.train.max_steps
        );
    }
    let out = out.unwrap_or_else(|| dir.join(SCENE_FILE));
    let report = compress(&trained, rate, &out, uncompressed_bytes(&trained.model))?;
    println!("{}", report.table());
    eprintln!(
        "wrote {} and {}",
        out.display(),
        out.with_file_name(COMPRESSION_REPORT_FILE).display()
    );
    Ok(report)
}

/// Test metrics of a decoded bitstream (`acags eval --bitstream`).
#[derive(Clone, Debug, Serialize)]
pub struct BitstreamMetrics {
    pub file: PathBuf,
    pub file_bytes: usize,
    pub file_mib: f64,
    pub rate: crate::codec::quantization::RatePreset,
    pub anchors: usize,
    pub psnr: f64,
    pub ssim: f64,
    #[serde(flatten)]
    pub lpips: LpipsSummary,
    #[serde(flatten)]
    pub regions: crate::eval::evaluate::RegionSummary,
    pub gaussians: f64,
    pub render_fps: f64,
    pub backend: String,
    pub views: Vec<crate::eval::evaluate::ViewMetrics>,
}

/// `acags eval --bitstream FILE [--data D]`: decodes, evaluates on the test views, writes
/// `<stem>_metrics.json` and `<stem>_renders/` beside the file.
pub fn eval_bitstream(
    file: &Path,
    data: Option<&str>,
    backend: BackendKind,
) -> Result<BitstreamMetrics> {
    let chosen = resolve(backend)?;
    eprintln!("backend: {}", chosen.description);
    let decoded = crate::codec::scene_file::read_scene(file, &chosen.device)?;
    let scene = crate::codec::scene_file::scene_dataset(&decoded, data)?;
    let frames = crate::data::frames::FrameCache::new(decoded.config.data.frame_cache_mib << 20);
    let eval = evaluate(
        &decoded.model,
        &scene,
        &frames,
        decoded.phase,
        &decoded.config.eval,
        Scoring::Full,
        Some(&sibling(file, "renders")),
    )?;
    write_quality_chart(&eval.regions, &sibling(file, QUALITY_CHART))?;
    write_camera_charts(&eval.views, &CAMERA_CHARTS.map(|c| sibling(file, c)))?;
    let metrics = BitstreamMetrics {
        file: file.to_path_buf(),
        file_bytes: decoded.file_bytes,
        file_mib: decoded.file_bytes as f64 / (1024.0 * 1024.0),
        rate: decoded.scene.meta.rate,
        anchors: decoded.scene.meta.anchors,
        psnr: eval.psnr,
        ssim: eval.ssim,
        lpips: eval.lpips.clone(),
        regions: eval.regions.clone(),
        gaussians: eval.gaussians,
        render_fps: eval.render_fps,
        backend: chosen.description.clone(),
        views: eval.views,
    };
    let path = sibling(file, "metrics.json");
    std::fs::write(&path, serde_json::to_string_pretty(&metrics)?)
        .with_context(|| format!("cannot write {}", path.display()))?;
    println!(
        "{}: test PSNR {:.3} dB, SSIM {:.4}{}, {}, {} anchors, {:.0} Gaussians/view, {:.4} MiB, {:.1} FPS",
        file.display(),
        metrics.psnr,
        metrics.ssim,
        metrics.lpips.text(),
        metrics.regions.text(),
        metrics.anchors,
        metrics.gaussians,
        metrics.file_mib,
        metrics.render_fps
    );
    Ok(metrics)
}

/// Progress as plain lines, for logs that are not a terminal: one every 2 % of the schedule.
struct ProgressLines {
    every: usize,
    max: usize,
    since: std::time::Instant,
    since_step: usize,
}

impl ProgressLines {
    fn new(step: usize, max: usize) -> Self {
        Self {
            every: (max / 50).max(1),
            max,
            since: std::time::Instant::now(),
            since_step: step,
        }
    }

    /// "step 320/1600 (20 %): loss 0.0412, PSNR 27.31 dB, 12034 anchors, 0.412 s/step, ETA 8 min 47 s"
    /// when `report` ends an interval (wall time per step over that interval).
    fn line(&mut self, report: &StepReport) -> Option<String> {
        let done = report.step + 1;
        if done % self.every != 0 && done != self.max {
            return None;
        }
        let per_step = self.since.elapsed().as_secs_f64() / (done - self.since_step).max(1) as f64;
        (self.since, self.since_step) = (std::time::Instant::now(), done);
        let eta = (per_step * (self.max - done) as f64).round() as u64;
        Some(format!(
            "step {done}/{} ({:.0} %): loss {:.4}, PSNR {:.2} dB, {} anchors, {:.3} s/step, ETA {} min {:02} s",
            self.max,
            100.0 * done as f64 / self.max as f64,
            report.loss,
            report.psnr,
            report.anchors,
            per_step,
            eta / 60,
            eta % 60
        ))
    }
}

/// A line above the progress bar, or on stderr when the bar is hidden (`--quiet`).
fn say(bar: &indicatif::ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

fn open_log(path: &Path, resume_step: usize) -> Result<std::io::BufWriter<std::fs::File>> {
    // Rows at or after the checkpoint's step are dropped: the resumed run writes them again.
    let kept: Vec<String> = match std::fs::read_to_string(path) {
        Ok(text) if resume_step > 0 => text
            .lines()
            .skip(1)
            .filter(|l| {
                l.split(',')
                    .next()
                    .and_then(|s| s.parse::<usize>().ok())
                    .is_some_and(|s| s < resume_step)
            })
            .map(str::to_string)
            .collect(),
        _ => Vec::new(),
    };
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut log = std::io::BufWriter::new(file);
    let header = log_header();
    writeln!(log, "{header}")?;
    // Rows of a build that logged fewer columns get empty ones, so every row fits the header.
    let columns = header.split(',').count();
    for line in kept {
        let missing = columns.saturating_sub(line.split(',').count());
        writeln!(log, "{line}{}", ",".repeat(missing))?;
    }
    Ok(log)
}

fn write_log_row(
    log: &mut impl Write,
    r: &StepReport,
    train_seconds: f64,
    masking_ratio: f64,
) -> Result<()> {
    write!(
        log,
        "{},{},{},{},{},{},{},{},{},{:.4},{:.2},{},{:.4},{},{},{},{},{}",
        r.step,
        r.loss,
        r.psnr,
        r.anchors,
        r.visible_anchors,
        r.gaussians,
        r.added,
        r.pruned,
        r.skipped as u8,
        r.seconds,
        train_seconds,
        r.active_slots,
        masking_ratio,
        r.relocation.map_or(0, |x| x.deactivated),
        r.relocation.map_or(0, |x| x.relocated),
        r.relocation.map_or(0, |x| x.previous_relocated),
        r.relocation.map_or(0, |x| x.previous_below_threshold),
        // Empty before the rate term starts.
        r.rate_bits.map_or(String::new(), |b| format!("{b:.4}"))
    )?;
    for term in crate::train::objective::Term::ALL {
        match r.terms.iter().find(|(t, _)| *t == term) {
            Some((_, v)) => write!(log, ",{v}")?,
            None => write!(log, ",")?,
        }
    }
    writeln!(log)?;
    // Every row reaches the file at once: `tail -f train_log.csv` follows a run.
    log.flush()?;
    Ok(())
}

/// `acags visualize --run DIR --camera I --frame F`: the render and the capacity heatmaps of
/// [`crate::eval::capacity_maps`] (anchors per pixel, cardinality, feature channels) as PNGs.
pub fn visualize(
    dir: &Path,
    camera: usize,
    frame: usize,
    out: Option<PathBuf>,
    backend: BackendKind,
) -> Result<Vec<PathBuf>> {
    use crate::eval::capacity_maps::{
        anchor_count_color, capacity_maps, cardinality_color, channel_color, overlay,
    };
    let run = open_run_for_views(dir, backend, camera, frame..frame + 1)?;
    let (scene, trained) = (&run.scene, &run.trained);
    let out = out.unwrap_or_else(|| dir.join("visualize"));
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let view = crate::data::ViewId { camera, frame };
    let rendered = render_view(&trained.model, scene, view, trained.phase())?;
    let image = rendered.image_host();
    let raster_camera = &scene.cameras[camera].camera;
    let maps = capacity_maps(&trained.model.anchors, &rendered.decoded, raster_camera);
    let (w, h) = (maps.width, maps.height);
    let stem = format!("cam{camera:02}_frame{frame:04}");
    let layers: [(&str, Vec<u8>); 4] = [
        (
            "render",
            image.iter().map(|v| (v * 255.0).round() as u8).collect(),
        ),
        (
            "anchors",
            overlay(&image, &maps, |i| anchor_count_color(maps.anchor_count[i])),
        ),
        (
            "cardinality",
            overlay(&image, &maps, |i| cardinality_color(maps.cardinality[i])),
        ),
        (
            "channels",
            overlay(&image, &maps, |i| channel_color(maps.channel_fraction[i])),
        ),
    ];
    let mut written = Vec::new();
    for (name, rgb) in layers {
        let path = out.join(format!("{stem}_{name}.png"));
        image::RgbImage::from_raw(w, h, rgb)
            .expect("map size")
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))?;
        written.push(path);
    }
    let covered: Vec<usize> = (0..maps.alpha.len())
        .filter(|&i| maps.alpha[i] >= 0.05)
        .collect();
    let mean = |v: &dyn Fn(usize) -> f32| {
        covered.iter().map(|&i| v(i) as f64).sum::<f64>() / covered.len().max(1) as f64
    };
    eprintln!(
        "{} covered pixels: {:.2} anchors per pixel, mean cardinality {:.2}, mean active channels {:.0} %",
        covered.len(),
        mean(&|i| maps.anchor_count[i] as f32),
        mean(&|i| maps.cardinality[i]),
        100.0 * mean(&|i| maps.channel_fraction[i])
    );
    Ok(written)
}
