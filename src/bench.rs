//! Benchmarks written as JSON: `acags bench raster` (forward and forward+backward timings of the
//! rasterizer through the Burn API), `bench train` (seconds per step), `bench lpips` (one LPIPS
//! evaluation and peak memory), `bench render` (seconds per rendered view of a trained run).

use std::collections::BTreeMap;
use std::time::Instant;

use anyhow::Result;
use burn::tensor::{Device, Tensor};
use serde::Serialize;

use crate::raster::random_scene::{GaussianArrays, SceneSpec, identity_camera, random_scene};
use crate::raster::{GaussianTensors, RasterCamera, rasterize};

/// One benchmark case: a fixed random scene at a resolution.
#[derive(Clone, Copy, Debug)]
pub struct RasterCase {
    pub name: &'static str,
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    pub repeats: usize,
}

pub const RASTER_CASES: [RasterCase; 2] = [
    RasterCase {
        name: "100k@512x512",
        gaussians: 100_000,
        width: 512,
        height: 512,
        repeats: 5,
    },
    RasterCase {
        name: "1M@1920x1080",
        gaussians: 1_000_000,
        width: 1920,
        height: 1080,
        repeats: 3,
    },
];

#[derive(Clone, Debug, Serialize)]
pub struct RasterCaseResult {
    pub name: String,
    pub gaussians: usize,
    pub width: u32,
    pub height: u32,
    pub visible: usize,
    pub intersections: usize,
    /// Sum over tiles of (pixels in tile x Gaussians binned to it): the (pixel, Gaussian) pairs a
    /// tile rasterizer considers before early termination.
    pub tile_pair_evaluations: u64,
    pub forward_ms: f64,
    pub forward_backward_ms: f64,
    /// tile_pair_evaluations / forward time.
    pub forward_pairs_per_second: f64,
    pub forward_backward_pairs_per_second: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct RasterBenchReport {
    pub backend: String,
    pub threads: usize,
    pub cases: Vec<RasterCaseResult>,
}

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn tile_pairs(camera: &RasterCamera, gaussians: &GaussianArrays) -> (usize, usize, u64) {
    let state = crate::raster::cpu::forward(&gaussians.slices(), camera, [0.0; 3])
        .expect("valid bench scene");
    let visible = state
        .projected
        .iter()
        .filter(|p| crate::raster::cpu::is_visible(p))
        .count();
    let bins = &state.bins;
    let mut pairs = 0u64;
    for ty in 0..bins.tiles_y {
        for tx in 0..bins.tiles_x {
            let t = (ty * bins.tiles_x + tx) as usize;
            let len = (bins.tile_offsets[t + 1] - bins.tile_offsets[t]) as u64;
            let pw = (camera.width - tx * 16).min(16) as u64;
            let ph = (camera.height - ty * 16).min(16) as u64;
            pairs += len * pw * ph;
        }
    }
    (visible, bins.intersection_count(), pairs)
}

/// Runs the cases on `device` (an autodiff version is derived for the backward).
pub fn bench_raster(
    device: &Device,
    backend: &str,
    cases: &[RasterCase],
) -> Result<RasterBenchReport> {
    let mut results = Vec::new();
    for case in cases {
        let camera = identity_camera(case.width, case.height);
        let scene = random_scene(&camera, &SceneSpec::new(case.gaussians, 7));
        let (visible, intersections, pairs) = tile_pairs(&camera, &scene);
        let plain = GaussianTensors::from_arrays(&scene, device);
        let autodiff_device = device.clone().autodiff();
        let tracked = GaussianTensors::from_arrays(&scene, &autodiff_device).require_grad();
        let weights = Tensor::<3>::random(
            [case.height as usize, case.width as usize, 3],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &autodiff_device,
        );
        let mut forward = Vec::new();
        let mut forward_backward = Vec::new();
        // One warm-up round (allocations, kernel compilation), then timed repeats.
        // Reading one result back is not enough to time a queueing device (CubeCL's wgpu and
        // CUDA streams): work the read does not depend on may still run. Every timed span
        // therefore starts and ends with a full device sync.
        let sync = |d: &Device| {
            d.sync()
                .map_err(|e| anyhow::anyhow!("device sync failed: {e:?}"))
        };
        for round in 0..=case.repeats {
            sync(device)?;
            let start = Instant::now();
            let out = rasterize(&plain, &camera, [0.0; 3])?;
            let _ = out.alpha.sum().into_data();
            sync(device)?;
            let fwd = start.elapsed().as_secs_f64() * 1e3;

            sync(&autodiff_device)?;
            let start = Instant::now();
            let out = rasterize(&tracked, &camera, [0.0; 3])?;
            let loss = (out.image * weights.clone()).sum() + out.alpha.sum();
            let grads = loss.backward();
            let _ = tracked.means.grad(&grads).map(|g| g.sum().into_data());
            sync(&autodiff_device)?;
            let fwd_bwd = start.elapsed().as_secs_f64() * 1e3;
            if round > 0 {
                forward.push(fwd);
                forward_backward.push(fwd_bwd);
            }
        }
        let (f, fb) = (median_ms(forward), median_ms(forward_backward));
        results.push(RasterCaseResult {
            name: case.name.into(),
            gaussians: case.gaussians,
            width: case.width,
            height: case.height,
            visible,
            intersections,
            tile_pair_evaluations: pairs,
            forward_ms: f,
            forward_backward_ms: fb,
            forward_pairs_per_second: pairs as f64 / (f / 1e3),
            forward_backward_pairs_per_second: pairs as f64 / (fb / 1e3),
        });
    }
    Ok(RasterBenchReport {
        backend: backend.into(),
        threads: rayon::current_num_threads(),
        cases: results,
    })
}

/// `acags bench train`: seconds per training step on one backend.
#[derive(Clone, Debug, Serialize)]
pub struct TrainBenchReport {
    pub backend: String,
    pub threads: usize,
    pub dataset: String,
    pub resolution: (u32, u32),
    pub anchors: usize,
    pub warmup_steps: usize,
    pub timed_steps: usize,
    pub mean_seconds_per_step: f64,
    pub median_seconds_per_step: f64,
    /// Median seconds per stage of a step (`train::stage_clock`; on a GPU backend a stage's
    /// time is the host's, and queued device work lands where the host next waits).
    pub median_stage_seconds: BTreeMap<&'static str, f64>,
    /// The process's CPU time over the timed steps' wall time: how many cores the step keeps
    /// busy on average (None where the OS does not report it).
    pub average_cores_busy: Option<f64>,
    /// Host↔device crossings per timed step (`device_io`; a read-back is a synchronisation).
    pub transfers_per_step: TransfersPerStep,
    /// Mean Gaussians spawned per timed step.
    pub gaussians: f64,
}

/// Mean uploads and read-backs (counts and bytes) per step.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct TransfersPerStep {
    pub uploads: f64,
    pub upload_bytes: f64,
    pub read_backs: f64,
    pub read_back_bytes: f64,
}

impl TransfersPerStep {
    fn over(counts: crate::device_io::TransferCounts, steps: usize) -> Self {
        let per = |v: u64| v as f64 / steps as f64;
        Self {
            uploads: per(counts.uploads),
            upload_bytes: per(counts.upload_bytes),
            read_backs: per(counts.read_backs),
            read_back_bytes: per(counts.read_back_bytes),
        }
    }
}

/// `bench train`'s untimed steps unless told: through the canonical phase and 2 steps into the
/// dynamic one. Timing from step 3, as it did, measured only canonical-phase steps (no stream,
/// neighbour stream or motion decoded): 3 % of a default run, and the cheapest.
pub fn default_train_warmup(config: &crate::train::config::TrainConfig) -> usize {
    config.train.canonical_until() + 3
}

/// Times `steps` training steps after `warmup` untimed ones, from a fresh model of `config`.
pub fn bench_train(
    device: &Device,
    backend: &str,
    config: &crate::train::config::TrainConfig,
    warmup: usize,
    steps: usize,
) -> Result<TrainBenchReport> {
    use crate::train::stage_clock::Stage;
    anyhow::ensure!(steps > 0, "bench train needs at least one timed step");
    let scene = config.data.load_scene()?;
    let resolution = scene.resolution();
    let mut trainer = crate::train::trainer::Trainer::new(config.clone(), scene, device.clone())?;
    for _ in 0..warmup {
        trainer.step()?;
    }
    let mut seconds = Vec::with_capacity(steps);
    let mut stages = Vec::with_capacity(steps);
    let mut gaussians = 0usize;
    let (cpu_before, wall_before) = (process_cpu_seconds(), std::time::Instant::now());
    let transfers_before = crate::device_io::TransferCounts::now();
    for _ in 0..steps {
        let report = trainer.step()?;
        seconds.push(report.seconds);
        stages.push(report.stages);
        gaussians += report.gaussians;
    }
    let wall = wall_before.elapsed().as_secs_f64();
    let transfers = crate::device_io::TransferCounts::now().since(transfers_before);
    let average_cores_busy = match (cpu_before, process_cpu_seconds()) {
        (Some(before), Some(after)) if wall > 0.0 => Some((after - before) / wall),
        _ => None,
    };
    let median_stage_seconds = Stage::ALL
        .iter()
        .map(|&stage| {
            (
                stage.name(),
                median_ms(stages.iter().map(|t| t.get(stage)).collect()),
            )
        })
        .collect();
    Ok(TrainBenchReport {
        backend: backend.to_string(),
        threads: rayon::current_num_threads(),
        dataset: config.data.dataset.clone(),
        resolution,
        anchors: trainer.model.anchors.len(),
        warmup_steps: warmup,
        timed_steps: steps,
        mean_seconds_per_step: seconds.iter().sum::<f64>() / steps as f64,
        median_seconds_per_step: median_ms(seconds),
        median_stage_seconds,
        average_cores_busy,
        transfers_per_step: TransfersPerStep::over(transfers, steps),
        gaussians: gaussians as f64 / steps as f64,
    })
}

/// User + system CPU seconds of this process so far (all threads).
#[cfg(unix)]
pub fn process_cpu_seconds() -> Option<f64> {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a rusage into the pointer it is given.
    let usage = unsafe {
        if libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) != 0 {
            return None;
        }
        usage.assume_init()
    };
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    Some(seconds(usage.ru_utime) + seconds(usage.ru_stime))
}

#[cfg(not(unix))]
pub fn process_cpu_seconds() -> Option<f64> {
    None
}

/// `acags bench lpips`: seconds per LPIPS evaluation of one image pair, and the process's peak
/// resident memory.
#[derive(Clone, Debug, Serialize)]
pub struct LpipsBenchReport {
    pub backend: String,
    pub net: crate::eval::lpips::LpipsNet,
    pub width: usize,
    pub height: usize,
    /// Loading the weights onto the device.
    pub load_seconds: f64,
    /// The first evaluation (kernel compilation / autotuning on GPU backends).
    pub first_seconds: f64,
    /// Median of the timed evaluations after the first.
    pub median_seconds: f64,
    pub repeats: usize,
    /// Peak resident set size of the process (Linux `VmHWM`), MiB; on a GPU the device memory
    /// is not in it.
    pub peak_rss_mib: Option<f64>,
}

/// Peak resident memory of this process in MiB (Linux only).
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Times LPIPS of a fixed pseudo-random image pair (smooth gradients plus noise, seeded) of
/// `width`×`height`.
pub fn bench_lpips(
    device: &Device,
    backend: &str,
    net: crate::eval::lpips::LpipsNet,
    width: usize,
    height: usize,
    repeats: usize,
) -> Result<LpipsBenchReport> {
    use crate::eval::lpips::{Lpips, LpipsInput, LpipsNet};
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(18);
    let mut image = |phase: f32| -> Vec<f32> {
        (0..width * height * 3)
            .map(|i| {
                let (p, c) = (i / 3, i % 3);
                let (x, y) = (
                    (p % width) as f32 / width as f32,
                    (p / width) as f32 / height as f32,
                );
                let smooth = 0.5 + 0.4 * (6.0 * x + 4.0 * y + phase + c as f32).sin();
                (smooth + rng.random_range(-0.05..0.05)).clamp(0.0, 1.0)
            })
            .collect()
    };
    let (a, b) = (image(0.0), image(0.3));
    let started = Instant::now();
    let lpips = match net {
        LpipsNet::Alex => Lpips::alex(device)?,
        LpipsNet::Vgg => Lpips::vgg(device)?,
    };
    let load_seconds = started.elapsed().as_secs_f64();
    let time = || -> Result<f64> {
        let started = Instant::now();
        lpips.distance(&a, &b, width, height, LpipsInput::Normalized)?;
        Ok(started.elapsed().as_secs_f64())
    };
    let first_seconds = time()?;
    let mut times = (0..repeats.max(1))
        .map(|_| time())
        .collect::<Result<Vec<_>>>()?;
    times.sort_by(f64::total_cmp);
    Ok(LpipsBenchReport {
        backend: backend.to_string(),
        net,
        width,
        height,
        load_seconds,
        first_seconds,
        median_seconds: times[times.len() / 2],
        repeats: times.len(),
        peak_rss_mib: peak_rss_mib(),
    })
}

/// `acags bench render`: seconds per rendered test view of a trained run (anchor culling,
/// decoding, rasterizing and reading the image back: what evaluation's FPS counts).
#[derive(Clone, Debug, Serialize)]
pub struct RenderBenchReport {
    pub backend: String,
    pub threads: usize,
    pub run: String,
    pub culling: crate::model::view::AnchorCulling,
    pub resolution: (u32, u32),
    pub anchors: usize,
    pub views: usize,
    pub repeats: usize,
    /// Median over every timed render.
    pub median_seconds_per_view: f64,
    pub fps: f64,
    /// Mean anchors decoded per view (those the culling kept).
    pub decoded_anchors: f64,
}

/// Renders every test view of the run in `dir` `repeats` times after one untimed render,
/// culling anchors as the run does or as `culling` says.
pub fn bench_render(
    device: &Device,
    backend: &str,
    dir: &std::path::Path,
    culling: Option<crate::model::view::AnchorCulling>,
    repeats: usize,
) -> Result<RenderBenchReport> {
    anyhow::ensure!(repeats > 0, "bench render needs at least one repeat");
    let run = crate::run::open_run(dir, device.clone())?;
    let mut model = run.trained.model.clone();
    if let Some(c) = culling {
        model.culling = c;
    }
    let scene = &run.scene;
    let phase = run.trained.phase();
    let views = scene.test_views();
    anyhow::ensure!(!views.is_empty(), "{}: no test views", scene.root.display());
    crate::eval::evaluate::render_view(&model, scene, views[0], phase)?;
    let mut seconds = Vec::with_capacity(views.len() * repeats);
    let mut decoded = 0usize;
    for _ in 0..repeats {
        for &view in &views {
            let started = Instant::now();
            let rendered = crate::eval::evaluate::render_view(&model, scene, view, phase)?;
            rendered.image_host();
            seconds.push(started.elapsed().as_secs_f64());
            decoded += rendered.decoded.visible.rows();
        }
    }
    let median = median_ms(seconds.clone());
    Ok(RenderBenchReport {
        backend: backend.to_string(),
        threads: rayon::current_num_threads(),
        run: dir.display().to_string(),
        culling: model.culling,
        resolution: scene.resolution(),
        anchors: model.anchors.len(),
        views: views.len(),
        repeats,
        median_seconds_per_view: median,
        fps: 1.0 / median,
        decoded_anchors: decoded as f64 / seconds.len() as f64,
    })
}
