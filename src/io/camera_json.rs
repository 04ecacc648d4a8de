//! Camera files for `render-ply`: `{width, height, fx, fy, cx, cy, world_to_camera}` with a
//! row-major 4x4 world-to-camera matrix in OpenCV axes.

use std::path::Path;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::raster::RasterCamera;

/// A camera as `render-ply` reads it (and the player's manifest lists it).
#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    width: u32,
    height: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    world_to_camera: [[f32; 4]; 4],
}

pub fn parse_camera(text: &str) -> Result<RasterCamera> {
    let mut de = serde_json::Deserializer::from_str(text);
    let f: CameraFile = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        anyhow::anyhow!("field '{path}': {}", e.into_inner())
    })?;
    let camera = RasterCamera {
        width: f.width,
        height: f.height,
        fx: f.fx,
        fy: f.fy,
        cx: f.cx,
        cy: f.cy,
        world_to_camera: f.world_to_camera,
    };
    camera.validate()?;
    let last = f.world_to_camera[3];
    if last != [0.0, 0.0, 0.0, 1.0] {
        bail!("world_to_camera's last row is {last:?}, expected [0, 0, 0, 1]");
    }
    Ok(camera)
}

impl From<&RasterCamera> for CameraFile {
    fn from(c: &RasterCamera) -> Self {
        Self {
            width: c.width,
            height: c.height,
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            world_to_camera: c.world_to_camera,
        }
    }
}

/// `camera` in the format [`read_camera`] reads (pretty JSON).
pub fn camera_json(camera: &RasterCamera) -> String {
    serde_json::to_string_pretty(&CameraFile::from(camera)).expect("a camera serialises")
}

pub fn write_camera(path: &Path, camera: &RasterCamera) -> Result<()> {
    std::fs::write(path, camera_json(camera))
        .with_context(|| format!("cannot write camera file {}", path.display()))
}

pub fn read_camera(path: &Path) -> Result<RasterCamera> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read camera file {}", path.display()))?;
    parse_camera(&text).with_context(|| format!("invalid camera file {}", path.display()))
}
