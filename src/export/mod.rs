//! Leaving acags: a trained model's frames as standard 3DGS PLY files (the Inria layout every
//! common viewer reads), with colour distilled into spherical harmonics ([`distill`]), the rig's
//! cameras as `render-ply` camera files, and a manifest. [`fidelity`] measures what the export
//! loses against acags' own render.
//!
//! acags' decoders take no view direction (`view_adaptive` is off, as in GIFStream's defaults),
//! so a neural Gaussian's colour and opacity are the same from every viewpoint and the SH fit
//! reproduces them exactly at any degree (its DC term is unpenalised). The fit still samples the
//! training cameras, so a view-dependent decoder would be distilled by the same code: only
//! [`viewpoint_colours`] would decode per camera.

pub mod decode;
pub mod distill;
pub mod fidelity;

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crate::data::Scene;
use crate::eval::evaluate::evaluation_time;
use crate::io::camera_json::write_camera;
use crate::io::splat_ply::{SplatScene, splat_ply_bytes};
use crate::model::anchored::AnchoredModel;
use crate::model::view::Phase;
use decode::{FrameGaussians, decode_frame};
use distill::{ColourSamples, fit_sh};

/// The manifest's name in an export directory.
pub const MANIFEST_FILE: &str = "export.json";

/// Playback rate written to the manifest: datasets do not record their capture rate (N3DV and
/// our synthetic scenes are 30 fps), and `render` encodes its videos at 30 too.
pub const PLAYBACK_FPS: f32 = 30.0;

/// A trained model and the dataset it was trained on.
#[derive(Clone, Copy)]
pub struct ExportSource<'a> {
    pub model: &'a AnchoredModel,
    pub scene: &'a Scene,
    pub phase: Phase,
}

/// Checks an SH degree given on the command line.
pub fn check_sh_degree(degree: usize) -> Result<()> {
    if degree > 3 {
        bail!("SH degree {degree} is outside 0-3");
    }
    Ok(())
}

/// Checks that `frames` is a non-empty range inside the trained GOP.
pub fn check_frames(scene: &Scene, frames: &Range<usize>) -> Result<()> {
    let gop = scene.frames.frames();
    if frames.is_empty() {
        bail!("the frame range {frames:?} is empty");
    }
    if frames.start < gop.start || frames.end > gop.end {
        bail!("frames {frames:?} are outside the trained GOP {gop:?}");
    }
    Ok(())
}

/// The colour every Gaussian shows from each training camera (see the module note: one shared
/// set while the decoders are view-independent).
fn viewpoint_colours<'a>(scene: &Scene, gaussians: &'a FrameGaussians) -> Vec<&'a [f32]> {
    vec![gaussians.colours.as_slice(); scene.train_cameras.len()]
}

/// Frame `frame` (a dataset frame index inside the GOP) as a standard 3DGS scene with SH of
/// `sh_degree`, and how many decoded slots were dropped.
pub fn frame_splats(
    source: ExportSource,
    frame: usize,
    sh_degree: usize,
) -> Result<(SplatScene, usize)> {
    check_sh_degree(sh_degree)?;
    check_frames(source.scene, &(frame..frame + 1))?;
    let when = evaluation_time(source.scene, frame, source.phase);
    let gaussians = decode_frame(source.model, when);
    let viewpoints: Vec<[f32; 3]> = source
        .scene
        .train_cameras
        .iter()
        .map(|&c| source.scene.cameras[c].camera.center())
        .collect();
    let sh = fit_sh(
        &ColourSamples {
            means: &gaussians.means,
            viewpoints: &viewpoints,
            colours: viewpoint_colours(source.scene, &gaussians),
        },
        sh_degree,
    )
    .with_context(|| format!("distilling the colours of frame {frame}"))?;
    let dropped = gaussians.slots - gaussians.len();
    let FrameGaussians {
        means,
        quats,
        scales,
        opacities,
        ..
    } = gaussians;
    Ok((
        SplatScene {
            means,
            quats,
            scales,
            opacities,
            sh,
            sh_degree,
        },
        dropped,
    ))
}

/// What `acags export` writes.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    /// Dataset frame indices, inside the trained GOP.
    pub frames: Range<usize>,
    pub sh_degree: usize,
    pub out: PathBuf,
    /// Render every exported frame from the test cameras and compare with acags' own render.
    pub fidelity: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct ExportedFrame {
    pub frame: usize,
    /// File name inside the export directory.
    pub file: String,
    pub gaussians: usize,
    /// Decoded slots not written (gated, opacity < 1/255 or non-finite).
    pub dropped_slots: usize,
    pub bytes: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct ExportedCamera {
    pub index: usize,
    pub name: String,
    pub file: String,
    pub split: &'static str,
}

/// The manifest (`export.json`).
#[derive(Clone, Debug, Serialize)]
pub struct ExportManifest {
    pub format: &'static str,
    pub version: u32,
    pub sh_degree: usize,
    pub width: u32,
    pub height: u32,
    pub fps: f32,
    pub gop: Range<usize>,
    pub frames: Vec<ExportedFrame>,
    pub cameras: Vec<ExportedCamera>,
    pub fidelity: Option<fidelity::FidelityReport>,
}

/// File name of frame `frame` in an export.
pub fn frame_file(frame: usize) -> String {
    format!("frame_{frame:05}.ply")
}

/// Writes `options.frames` of `source` as PLY files, the rig's cameras and the manifest into
/// `options.out`; with `options.fidelity`, reads every file back and scores it.
pub fn export(
    source: ExportSource,
    options: &ExportOptions,
    device: &burn::tensor::Device,
) -> Result<ExportManifest> {
    check_sh_degree(options.sh_degree)?;
    check_frames(source.scene, &options.frames)?;
    let out = &options.out;
    let cameras_dir = out.join("cameras");
    std::fs::create_dir_all(&cameras_dir)
        .with_context(|| format!("cannot create {}", cameras_dir.display()))?;
    let scene = source.scene;
    let mut cameras = Vec::new();
    for (index, cam) in scene.cameras.iter().enumerate() {
        let file = format!("cameras/cam{index:02}.json");
        write_camera(&out.join(&file), &cam.camera)?;
        cameras.push(ExportedCamera {
            index,
            name: cam.name.clone(),
            file,
            split: scene.split_name(index),
        });
    }
    let mut frames = Vec::new();
    for frame in options.frames.clone() {
        let (splats, dropped_slots) = frame_splats(source, frame, options.sh_degree)?;
        let file = frame_file(frame);
        let bytes = splat_ply_bytes(&splats);
        write_file(&out.join(&file), &bytes)?;
        eprintln!(
            "frame {frame}: {} Gaussians ({dropped_slots} slots dropped), {:.2} MiB -> {}",
            splats.len(),
            bytes.len() as f64 / (1 << 20) as f64,
            out.join(&file).display()
        );
        frames.push(ExportedFrame {
            frame,
            file,
            gaussians: splats.len(),
            dropped_slots,
            bytes: bytes.len(),
        });
    }
    let fidelity = if options.fidelity {
        Some(fidelity::score_export(source, out, &frames, device)?)
    } else {
        None
    };
    let (width, height) = scene.resolution();
    let manifest = ExportManifest {
        format: "acags-export",
        version: 1,
        sh_degree: options.sh_degree,
        width,
        height,
        fps: PLAYBACK_FPS,
        gop: scene.frames.frames(),
        frames,
        cameras,
        fidelity,
    };
    let json = serde_json::to_string_pretty(&manifest).expect("the manifest serialises");
    write_file(&out.join(MANIFEST_FILE), json.as_bytes())?;
    Ok(manifest)
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}
