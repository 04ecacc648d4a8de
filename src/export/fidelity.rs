//! What an export loses: each exported PLY, read back from disk and drawn by `render-ply`'s
//! renderer, against acags' own render of the same test camera and frame (both float, clamped to
//! [0, 1], black background).
//!
//! Both sides use the same rasterizer, so the difference is the export's alone: the SH fit,
//! the PLY's logit/log round trip, the dropped slots, and acags' anchor culling (its render
//! decodes only the anchors that pass the camera test, the export decodes all of them).

use std::path::Path;

use anyhow::{Context, Result};
use serde::Serialize;

use super::{ExportSource, ExportedFrame};
use crate::data::ViewId;
use crate::eval::evaluate::render_view;
use crate::io::splat_ply::{read_splat_ply, render_splat};
use crate::model::anchored::BACKGROUND;
use crate::model::anchors::host_values;

#[derive(Clone, Debug, Serialize)]
pub struct ViewFidelity {
    pub camera: usize,
    pub frame: usize,
    /// PSNR of the exported frame's render against acags' render; `None` when they are equal.
    pub psnr_db: Option<f64>,
    /// Largest absolute difference of one channel of one pixel.
    pub max_abs_diff: f32,
}

#[derive(Clone, Debug, Serialize)]
pub struct FidelityReport {
    pub views: Vec<ViewFidelity>,
    /// PSNR of the mean squared error over all views (`None`: every view identical).
    pub psnr_db: Option<f64>,
    /// The worst view's PSNR (`None`: every view identical).
    pub min_psnr_db: Option<f64>,
}

/// Scores every frame of `frames` (already written under `dir`) on the test cameras.
pub fn score_export(
    source: ExportSource,
    dir: &Path,
    frames: &[ExportedFrame],
    device: &burn::tensor::Device,
) -> Result<FidelityReport> {
    let scene = source.scene;
    let mut views = Vec::new();
    let mut squared_error = 0.0f64;
    let mut values = 0usize;
    for exported in frames {
        let splats = read_splat_ply(&dir.join(&exported.file))?;
        for &camera in &scene.test_cameras {
            let view = ViewId {
                camera,
                frame: exported.frame,
            };
            let own = render_view(source.model, scene, view, source.phase)
                .with_context(|| format!("rendering camera {camera} at frame {}", exported.frame))?
                .image_host();
            let cam = &scene.cameras[camera].camera;
            let drawn = render_splat(&splats, cam, BACKGROUND, device)?;
            let drawn = host_values(&drawn.image.clamp(0.0, 1.0));
            let max_abs_diff = own
                .iter()
                .zip(&drawn)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            let view_error = own
                .iter()
                .zip(&drawn)
                .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
                .sum::<f64>();
            squared_error += view_error;
            values += own.len();
            views.push(ViewFidelity {
                camera,
                frame: exported.frame,
                psnr_db: psnr_of(view_error / own.len() as f64),
                max_abs_diff,
            });
        }
    }
    let mse = squared_error / values.max(1) as f64;
    let min_psnr_db = views
        .iter()
        .filter_map(|v| v.psnr_db)
        .min_by(f64::total_cmp);
    Ok(FidelityReport {
        psnr_db: psnr_of(mse),
        min_psnr_db,
        views,
    })
}

/// PSNR (peak 1) of a mean squared error; `None` when the images are equal.
fn psnr_of(mse: f64) -> Option<f64> {
    (mse > 0.0).then(|| -10.0 * mse.log10())
}
