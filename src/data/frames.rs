//! Decoding frames (PNG/JPEG → RGB f32 in [0, 1]), downscaling, and a lazy cache bounded by a
//! memory budget (least recently used frames are dropped first).

use std::path::Path;
use std::sync::{Arc, Mutex};

use anyhow::{Context, Result, bail};

use super::scene::{Resample, Scene, ViewId};
use crate::byte_budget::ByteBudgetLru;

/// An RGB image, row-major [H, W, 3], values in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
}

impl Frame {
    pub fn bytes(&self) -> usize {
        self.rgb.len() * std::mem::size_of::<f32>()
    }
}

/// Decodes an image file and checks its size.
pub fn decode_frame(path: &Path, expected: (u32, u32)) -> Result<Frame> {
    let image =
        image::open(path).with_context(|| format!("{}: cannot decode image", path.display()))?;
    let (w, h) = (image.width(), image.height());
    if (w, h) != expected {
        bail!(
            "{}: image is {w}x{h}, expected {}x{} like the camera's other frames",
            path.display(),
            expected.0,
            expected.1
        );
    }
    Ok(Frame {
        width: w,
        height: h,
        rgb: image.into_rgb32f().into_raw(),
    })
}

/// Downscales by an integer factor to (W / f, H / f) (floor), as GIFStream does.
pub fn downscale(frame: &Frame, factor: u32, resample: Resample) -> Frame {
    if factor == 1 {
        return frame.clone();
    }
    let (w, h) = (frame.width / factor, frame.height / factor);
    let src = |x: usize, y: usize, c: usize| frame.rgb[(y * frame.width as usize + x) * 3 + c];
    let mut rgb = Vec::with_capacity((w * h * 3) as usize);
    let f = factor as usize;
    for y in 0..h as usize {
        for x in 0..w as usize {
            for c in 0..3 {
                let v = match resample {
                    Resample::Area => {
                        let mut sum = 0.0f32;
                        for dy in 0..f {
                            for dx in 0..f {
                                sum += src(x * f + dx, y * f + dy, c);
                            }
                        }
                        sum / (f * f) as f32
                    }
                    Resample::Bilinear => {
                        let sample = |o: usize, len: u32| {
                            let s = ((o as f32 + 0.5) * factor as f32 - 0.5)
                                .clamp(0.0, (len - 1) as f32);
                            let i0 = s.floor() as usize;
                            let i1 = (i0 + 1).min(len as usize - 1);
                            (i0, i1, s - i0 as f32)
                        };
                        let (x0, x1, fx) = sample(x, frame.width);
                        let (y0, y1, fy) = sample(y, frame.height);
                        let top = src(x0, y0, c) * (1.0 - fx) + src(x1, y0, c) * fx;
                        let bottom = src(x0, y1, c) * (1.0 - fx) + src(x1, y1, c) * fx;
                        top * (1.0 - fy) + bottom * fy
                    }
                };
                rgb.push(v);
            }
        }
    }
    Frame {
        width: w,
        height: h,
        rgb,
    }
}

/// Decoded, downscaled frames of a scene, loaded on first use and kept within a byte budget.
pub struct FrameCache {
    frames: Mutex<ByteBudgetLru<ViewId, Arc<Frame>>>,
}

impl FrameCache {
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            frames: Mutex::new(ByteBudgetLru::new(budget_bytes)),
        }
    }

    /// The frame of `view`, decoded now unless cached. A frame larger than the whole budget is
    /// returned but not kept.
    pub fn get(&self, scene: &Scene, view: ViewId) -> Result<Arc<Frame>> {
        if let Some(frame) = self.frames.lock().unwrap().get(&view) {
            return Ok(frame.clone());
        }
        let camera = &scene.cameras[view.camera];
        let decoded = decode_frame(scene.frame_path(view), camera.source_size)?;
        let frame = Arc::new(downscale(&decoded, scene.downscale, scene.resample));
        let bytes = frame.bytes();
        self.frames.lock().unwrap().insert(view, frame.clone(), bytes);
        Ok(frame)
    }

    /// Bytes held and frames held.
    pub fn usage(&self) -> (usize, usize) {
        let frames = self.frames.lock().unwrap();
        (frames.bytes(), frames.len())
    }

    pub fn budget_bytes(&self) -> usize {
        self.frames.lock().unwrap().budget_bytes()
    }
}
