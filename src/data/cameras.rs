//! Camera conventions: LLFF `poses_bounds.npy` rows and Dynamic3DGS `w2c`/`k` to the one camera
//! type of the project, [`RasterCamera`] (OpenCV axes: x right, y down, z forward; world→camera).

use anyhow::{Result, bail};
use glam::{DMat3, DVec3};

use crate::raster::RasterCamera;

/// One LLFF row: a 3×5 camera-to-world matrix (columns: down, right, backwards, centre, [h, w, f])
/// followed by the near and far depth bounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LlffPose {
    pub rows: [[f64; 5]; 3],
    pub near: f64,
    pub far: f64,
}

impl LlffPose {
    pub fn from_row(row: &[f64]) -> Result<Self> {
        if row.len() != 17 {
            bail!("an LLFF pose row has 17 values, got {}", row.len());
        }
        let rows = std::array::from_fn(|r| std::array::from_fn(|c| row[r * 5 + c]));
        Ok(Self {
            rows,
            near: row[15],
            far: row[16],
        })
    }

    pub fn to_row(&self) -> [f64; 17] {
        let mut out = [0.0; 17];
        for r in 0..3 {
            out[r * 5..r * 5 + 5].copy_from_slice(&self.rows[r]);
        }
        out[15] = self.near;
        out[16] = self.far;
        out
    }

    /// Image height, width and focal length stored in the fifth column.
    pub fn hwf(&self) -> (f64, f64, f64) {
        (self.rows[0][4], self.rows[1][4], self.rows[2][4])
    }

    /// OpenCV camera: LLFF axes (down, right, back) become (right, down, forward) by taking the
    /// columns in the order [1, 0, -2] (GIFStream's "[y, x, -z]"), then inverting. The principal
    /// point is (W // 2, H // 2) as GIFStream's COLMAP database sets it (integer division).
    pub fn to_camera(&self) -> Result<RasterCamera> {
        let (h, w, f) = self.hwf();
        if !(h >= 1.0 && w >= 1.0 && h.fract() == 0.0 && w.fract() == 0.0 && f > 0.0) {
            bail!("invalid [h, w, f] column ({h}, {w}, {f})");
        }
        let col = |c: usize| DVec3::new(self.rows[0][c], self.rows[1][c], self.rows[2][c]);
        let rotation_c2w = DMat3::from_cols(col(1), col(0), -col(2));
        let center = col(3);
        let camera = camera_from_c2w(
            rotation_c2w,
            center,
            w as u32,
            h as u32,
            f,
            f,
            (w / 2.0).floor(),
            (h / 2.0).floor(),
        );
        camera.validate()?;
        Ok(camera)
    }

    /// The LLFF row for an OpenCV camera (inverse of [`Self::to_camera`] up to the principal point).
    pub fn from_camera(camera: &RasterCamera, near: f64, far: f64) -> Self {
        let (rotation_c2w, center) = camera_to_c2w(camera);
        let cols = [
            rotation_c2w.y_axis,
            rotation_c2w.x_axis,
            -rotation_c2w.z_axis,
            center,
        ];
        let hwf = [camera.height as f64, camera.width as f64, camera.fx as f64];
        let rows = std::array::from_fn(|r| {
            std::array::from_fn(|c| if c < 4 { cols[c][r] } else { hwf[r] })
        });
        Self { rows, near, far }
    }
}

/// World→camera from a camera-to-world rotation and the camera centre.
#[allow(clippy::too_many_arguments)]
pub fn camera_from_c2w(
    rotation_c2w: DMat3,
    center: DVec3,
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
) -> RasterCamera {
    let r = rotation_c2w.transpose();
    let t = -(r * center);
    let m = [
        [r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x],
        [r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y],
        [r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z],
        [0.0, 0.0, 0.0, 1.0],
    ];
    RasterCamera {
        width,
        height,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
        world_to_camera: m.map(|row| row.map(|v| v as f32)),
    }
}

/// Camera-to-world rotation and centre of a camera.
pub fn camera_to_c2w(camera: &RasterCamera) -> (DMat3, DVec3) {
    let m = camera.world_to_camera.map(|row| row.map(|v| v as f64));
    let r = DMat3::from_cols(
        DVec3::new(m[0][0], m[1][0], m[2][0]),
        DVec3::new(m[0][1], m[1][1], m[2][1]),
        DVec3::new(m[0][2], m[1][2], m[2][2]),
    );
    let t = DVec3::new(m[0][3], m[1][3], m[2][3]);
    let c2w = r.transpose();
    (c2w, -(c2w * t))
}

/// Camera centre in world coordinates.
pub fn camera_center(camera: &RasterCamera) -> [f64; 3] {
    camera_to_c2w(camera).1.to_array()
}

/// Dynamic3DGS (Panoptic) camera: `k` 3×3 intrinsics and `w2c` 4×4 world→camera, both already
/// OpenCV/COLMAP convention, so only validation is needed.
pub fn camera_from_d3dgs(
    k: &[[f64; 3]; 3],
    w2c: &[[f64; 4]; 4],
    width: u32,
    height: u32,
) -> Result<RasterCamera> {
    if k[0][1] != 0.0 || k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        bail!("intrinsics {k:?} are not a pinhole K (skew or last row)");
    }
    if w2c[3] != [0.0, 0.0, 0.0, 1.0] {
        bail!("w2c last row is {:?}, expected [0, 0, 0, 1]", w2c[3]);
    }
    let camera = RasterCamera {
        width,
        height,
        fx: k[0][0] as f32,
        fy: k[1][1] as f32,
        cx: k[0][2] as f32,
        cy: k[1][2] as f32,
        world_to_camera: w2c.map(|row| row.map(|v| v as f32)),
    };
    camera.validate()?;
    Ok(camera)
}

/// Pixel coordinates (x, y), pixel centres at +0.5, of a world point; `None` behind the camera.
pub fn project_point(camera: &RasterCamera, p: [f64; 3]) -> Option<[f64; 2]> {
    let m = camera.world_to_camera.map(|row| row.map(|v| v as f64));
    let c: [f64; 3] =
        std::array::from_fn(|i| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3]);
    (c[2] > 0.0).then(|| {
        [
            camera.fx as f64 * c[0] / c[2] + camera.cx as f64,
            camera.fy as f64 * c[1] / c[2] + camera.cy as f64,
        ]
    })
}

/// The camera for images downscaled to `width`×`height`: intrinsics scaled by the size ratio per
/// axis (GIFStream divides K by the factor and rescales it to the actual image size).
pub fn rescale_camera(camera: &RasterCamera, width: u32, height: u32) -> RasterCamera {
    let sx = width as f32 / camera.width as f32;
    let sy = height as f32 / camera.height as f32;
    RasterCamera {
        width,
        height,
        fx: camera.fx * sx,
        fy: camera.fy * sy,
        cx: camera.cx * sx,
        cy: camera.cy * sy,
        ..*camera
    }
}
