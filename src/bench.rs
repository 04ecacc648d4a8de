//! `acags bench raster`: forward and forward+backward timings of the rasterizer through the Burn
//! API on the chosen backend, written as JSON.

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
        let sync = |d: &Device| d.sync().map_err(|e| anyhow::anyhow!("device sync failed: {e:?}"));
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
    /// Mean Gaussians spawned per timed step.
    pub gaussians: f64,
}

/// Times `steps` training steps after `warmup` untimed ones, from a fresh model of `config`.
pub fn bench_train(
    device: &Device,
    backend: &str,
    config: &crate::train::config::TrainConfig,
    warmup: usize,
    steps: usize,
) -> Result<TrainBenchReport> {
    anyhow::ensure!(steps > 0, "bench train needs at least one timed step");
    let scene = crate::run::load_scene(config)?;
    let resolution = scene.resolution();
    let mut trainer = crate::train::trainer::Trainer::new(config.clone(), scene, device.clone())?;
    for _ in 0..warmup {
        trainer.step()?;
    }
    let mut seconds = Vec::with_capacity(steps);
    let mut gaussians = 0usize;
    for _ in 0..steps {
        let report = trainer.step()?;
        seconds.push(report.seconds);
        gaussians += report.gaussians;
    }
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
        gaussians: gaussians as f64 / steps as f64,
    })
}
