#![allow(deprecated)] // Device::ndarray
//! Render time of a trained run's test views by the two decode paths, alternately in one
//! process (docs/benchmarks.md, "Rendering"): culling then decoding the visible anchors
//! (`cull_anchors` + `decode_view`: under deformed culling the motion of every anchor is decoded
//! for the culling and again for the visible ones) against `AnchoredModel::render`
//! (`cull_and_decode`: the culling's motion decode reused).
//!
//! `cargo run --release --example render_paths -- RUN_DIR [PASSES]`

use std::time::Instant;

use anyhow::{Context, Result};
use burn::tensor::Device;

use acags::model::anchored::{BACKGROUND, RenderedView};
use acags::eval::evaluate::evaluation_time;
use acags::model::view::{cull_anchors, decode_view};
use acags::raster::rasterize;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let dir = args.first().context("usage: render_paths RUN_DIR [PASSES]")?;
    let passes: usize = args.get(1).map_or(Ok(3), |p| p.parse())?;
    let run = acags::run::open_run(std::path::Path::new(dir), Device::ndarray())?;
    let model = &run.trained.model;
    let scene = &run.scene;
    let phase = run.trained.phase();
    let views = scene.test_views();
    let (mut twice, mut once, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for pass in 0..=passes {
        for &view in &views {
            let camera = &scene.cameras[view.camera].camera;
            let when = evaluation_time(scene, view.frame, phase);
            let started = Instant::now();
            let tensors = model.anchors.untracked();
            let visible =
                cull_anchors(&model.anchors, &tensors, &model.decoders, camera, when, model.culling);
            let decoded = decode_view(&model.anchors, &tensors, &model.decoders, visible, when);
            let raster = rasterize(&decoded.gaussians, camera, BACKGROUND)?;
            let a = RenderedView { raster, decoded }.image_host();
            let t_twice = started.elapsed().as_secs_f64();
            let started = Instant::now();
            let b = model.render(camera, when)?.image_host();
            let t_once = started.elapsed().as_secs_f64();
            let max = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            anyhow::ensure!(max < 1e-4, "the two paths differ by {max} at {view:?}");
            if pass > 0 {
                twice.push(t_twice);
                once.push(t_once);
                ratios.push(t_twice / t_once);
            }
        }
    }
    println!(
        "{} anchors, culling {:?}, {} views × {passes} passes: cull then decode {:.1} ms, \
         one decode {:.1} ms per view (median); ratio {:.2} (median of pairs)",
        model.anchors.len(),
        model.culling,
        views.len(),
        1e3 * median(twice),
        1e3 * median(once),
        median(ratios)
    );
    Ok(())
}
