//! The pinhole camera every rasterizer call takes.

use serde::{Deserialize, Serialize};

use crate::RasterError;

/// A pinhole camera with OpenCV axes (x right, y down, z forward).
///
/// `world_to_camera` is row-major: `p_cam = R * p_world + t` with `R = m[0..3][0..3]` and
/// `t = m[0..3][3]`. It is used exactly as given (not re-orthonormalised), as gsplat does.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RasterCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub world_to_camera: [[f32; 4]; 4],
}

impl RasterCamera {
    /// Rejects cameras the rasterizer cannot render: empty images, non-finite or non-positive
    /// focal lengths, non-finite matrices.
    pub fn validate(&self) -> Result<(), RasterError> {
        let bad = |what: String| Err(RasterError::InvalidCamera(what));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        // Pixel indices ×4 (the RGBA output) stay inside u32 and pixel centres are exact in f32
        // (< 2^24); the pixel bound is also what one GPU storage buffer of the [H, W, 4] output
        // holds (1 GiB).
        const MAX_SIDE: u32 = 1 << 20;
        const MAX_PIXELS: u64 = 1 << 26;
        if self.width > MAX_SIDE || self.height > MAX_SIDE {
            return bad(format!(
                "image size {}x{} exceeds the supported {MAX_SIDE} pixels per side",
                self.width, self.height
            ));
        }
        if self.width as u64 * self.height as u64 > MAX_PIXELS {
            return bad(format!(
                "image size {}x{} exceeds the supported {MAX_PIXELS} pixels (8192 x 8192)",
                self.width, self.height
            ));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} = {v} must be finite and positive"));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return bad(format!("{name} = {v} must be finite"));
            }
        }
        if self
            .world_to_camera
            .iter()
            .flatten()
            .any(|v| !v.is_finite())
        {
            return bad("world_to_camera has a non-finite entry".into());
        }
        Ok(())
    }

    /// Rotation rows of the world-to-camera transform.
    pub fn rotation(&self) -> [[f32; 3]; 3] {
        let m = &self.world_to_camera;
        [
            [m[0][0], m[0][1], m[0][2]],
            [m[1][0], m[1][1], m[1][2]],
            [m[2][0], m[2][1], m[2][2]],
        ]
    }

    /// Translation of the world-to-camera transform.
    pub fn translation(&self) -> [f32; 3] {
        let m = &self.world_to_camera;
        [m[0][3], m[1][3], m[2][3]]
    }

    /// The camera centre in world space, −Rᵀt.
    pub fn center(&self) -> [f32; 3] {
        let (r, t) = (self.rotation(), self.translation());
        std::array::from_fn(|j| -(0..3).map(|i| r[i][j] * t[i]).sum::<f32>())
    }

    /// Bounds on x/z and y/z used inside the projection Jacobian, gsplat's "1.3x field of view":
    /// (+x, −x, +y, −y) = each side's image half-extent plus 0.15 of the full extent, in
    /// normalised coordinates.
    pub fn jacobian_clamp_limits(&self) -> [f32; 4] {
        use crate::conventions::FOV_CLAMP_MARGIN;
        let (w, h) = (self.width as f32, self.height as f32);
        [
            (w - self.cx) / self.fx + FOV_CLAMP_MARGIN * w / self.fx,
            self.cx / self.fx + FOV_CLAMP_MARGIN * w / self.fx,
            (h - self.cy) / self.fy + FOV_CLAMP_MARGIN * h / self.fy,
            self.cy / self.fy + FOV_CLAMP_MARGIN * h / self.fy,
        ]
    }

    pub fn tiles_x(&self) -> u32 {
        crate::conventions::tiles_along(self.width)
    }

    pub fn tiles_y(&self) -> u32 {
        crate::conventions::tiles_along(self.height)
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}
