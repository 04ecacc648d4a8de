//! Per-Gaussian projection (EWA splatting with gsplat's conventions) and its hand-written backward.
//!
//! Forward: world mean, raw quaternion, activated scales and gated opacity -> screen mean, conic
//! (inverse 2D covariance), depth and the opacity-aware screen radius; or `None` when culled.
//! Backward: the vector-Jacobian product of the same map, recomputing the forward intermediates
//! (cheaper than storing ~40 floats per Gaussian).

use glam::{Mat3, Vec3};

use crate::camera::RasterCamera;
use crate::conventions::projected_column::{self as col};
use crate::conventions::{
    ALPHA_MIN, EPS2D, FAR_PLANE, MAX_EXTENT_SIGMAS, NEAR_PLANE, PROJECTED_COLUMNS,
};

/// Camera quantities shared by every Gaussian of one projection.
#[derive(Clone, Copy, Debug)]
pub struct ProjectionCamera {
    rotation: Mat3,
    translation: Vec3,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: f32,
    height: f32,
    /// Bounds on x/z and y/z used inside the Jacobian (1.3x the field of view).
    lim_x_pos: f32,
    lim_x_neg: f32,
    lim_y_pos: f32,
    lim_y_neg: f32,
}

impl ProjectionCamera {
    pub fn new(camera: &RasterCamera) -> Self {
        let (w, h) = (camera.width as f32, camera.height as f32);
        let [lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg] = camera.jacobian_clamp_limits();
        Self {
            rotation: mat3_from_rows(camera.rotation()),
            translation: Vec3::from(camera.translation()),
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            width: w,
            height: h,
            lim_x_pos,
            lim_x_neg,
            lim_y_pos,
            lim_y_neg,
        }
    }
}

/// One Gaussian's inputs, as the rasterizer receives them.
#[derive(Clone, Copy, Debug)]
pub struct GaussianParams {
    pub mean: [f32; 3],
    /// Raw (w, x, y, z); normalised here.
    pub quat: [f32; 4],
    /// Activated (linear) scales.
    pub scale: [f32; 3],
    /// Activated opacity, already multiplied by the gate.
    pub opacity: f32,
}

/// A Gaussian that survived culling, as the compositing stage sees it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Projected {
    /// Screen-space mean in pixels (pixel centres at +0.5).
    pub mean2d: [f32; 2],
    /// (a, b, c) of the inverse 2D covariance: sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2.
    pub conic: [f32; 3],
    /// Camera-space z, the compositing order.
    pub depth: f32,
    /// Opacity-aware half extents of the screen box, in whole pixels.
    pub radius: [u32; 2],
}

impl Projected {
    /// One row of the projection tensor ([`crate::conventions::projected_column`] layout).
    pub fn to_row(&self) -> [f32; PROJECTED_COLUMNS] {
        let mut row = [0.0; PROJECTED_COLUMNS];
        row[col::MEAN2D_X] = self.mean2d[0];
        row[col::MEAN2D_Y] = self.mean2d[1];
        row[col::CONIC_A] = self.conic[0];
        row[col::CONIC_B] = self.conic[1];
        row[col::CONIC_C] = self.conic[2];
        row[col::DEPTH] = self.depth;
        row[col::RADIUS_X] = self.radius[0] as f32;
        row[col::RADIUS_Y] = self.radius[1] as f32;
        row
    }

    pub fn from_row(r: &[f32]) -> Self {
        Self {
            mean2d: [r[col::MEAN2D_X], r[col::MEAN2D_Y]],
            conic: [r[col::CONIC_A], r[col::CONIC_B], r[col::CONIC_C]],
            depth: r[col::DEPTH],
            radius: [r[col::RADIUS_X] as u32, r[col::RADIUS_Y] as u32],
        }
    }
}

/// Gradients of the loss with respect to one Gaussian's projected quantities.
#[derive(Clone, Copy, Debug, Default)]
pub struct ProjectedGrad {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
}

/// Gradients with respect to one Gaussian's geometric inputs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GeometryGrad {
    pub mean: [f32; 3],
    pub quat: [f32; 4],
    pub scale: [f32; 3],
}

/// Forward intermediates, shared by the forward and the backward.
struct Intermediates {
    p_cam: Vec3,
    quat_unit: [f32; 4],
    quat_norm: f32,
    rot_q: Mat3,
    m: Mat3,
    cov_cam: Mat3,
    /// Rows of the 2x3 Jacobian.
    j0: Vec3,
    j1: Vec3,
    x_clamped: bool,
    y_clamped: bool,
    cov2d: [f32; 3],
}

fn mat3_from_rows(rows: [[f32; 3]; 3]) -> Mat3 {
    Mat3::from_cols_array_2d(&rows).transpose()
}

/// Entry (row, col) of a glam (column-major) matrix.
#[inline]
pub(crate) fn at(m: &Mat3, row: usize, col: usize) -> f32 {
    m.col(col)[row]
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
pub(crate) fn rotation_from_quat([w, x, y, z]: [f32; 4]) -> Mat3 {
    mat3_from_rows([
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ])
}

fn intermediates(g: &GaussianParams, cam: &ProjectionCamera) -> Option<Intermediates> {
    let mean = Vec3::from(g.mean);
    let p_cam = cam.rotation * mean + cam.translation;
    let z = p_cam.z;
    // Written so that NaN fails the test: NaN depths are culled.
    if !(z >= NEAR_PLANE && z <= FAR_PLANE) {
        return None;
    }
    let [qw, qx, qy, qz] = g.quat;
    let quat_norm = (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
    if !(quat_norm > 0.0 && quat_norm.is_finite()) {
        return None;
    }
    let quat_unit = [
        qw / quat_norm,
        qx / quat_norm,
        qy / quat_norm,
        qz / quat_norm,
    ];
    let rot_q = rotation_from_quat(quat_unit);
    let m = rot_q * Mat3::from_diagonal(Vec3::from(g.scale));
    let cov_world = m * m.transpose();
    let cov_cam = cam.rotation * cov_world * cam.rotation.transpose();

    let (x, y) = (p_cam.x, p_cam.y);
    let (x_over_z, y_over_z) = (x / z, y / z);
    let x_clamped = !(x_over_z >= -cam.lim_x_neg && x_over_z <= cam.lim_x_pos);
    let y_clamped = !(y_over_z >= -cam.lim_y_neg && y_over_z <= cam.lim_y_pos);
    let tx = z * x_over_z.clamp(-cam.lim_x_neg, cam.lim_x_pos);
    let ty = z * y_over_z.clamp(-cam.lim_y_neg, cam.lim_y_pos);
    let j0 = Vec3::new(cam.fx / z, 0.0, -cam.fx * tx / (z * z));
    let j1 = Vec3::new(0.0, cam.fy / z, -cam.fy * ty / (z * z));
    let cov2d = [
        j0.dot(cov_cam * j0) + EPS2D,
        j0.dot(cov_cam * j1),
        j1.dot(cov_cam * j1) + EPS2D,
    ];
    Some(Intermediates {
        p_cam,
        quat_unit,
        quat_norm,
        rot_q,
        m,
        cov_cam,
        j0,
        j1,
        x_clamped,
        y_clamped,
        cov2d,
    })
}

fn all_finite(g: &GaussianParams) -> bool {
    g.mean
        .iter()
        .chain(&g.quat)
        .chain(&g.scale)
        .all(|v| v.is_finite())
        && g.opacity.is_finite()
}

/// Projects one Gaussian; `None` when it is culled (behind or too near the camera, degenerate,
/// below the alpha threshold everywhere, off-screen, or with a non-finite input).
pub fn project(g: &GaussianParams, cam: &ProjectionCamera) -> Option<Projected> {
    if !all_finite(g) || g.opacity < ALPHA_MIN {
        return None;
    }
    let it = intermediates(g, cam)?;
    let [sxx, sxy, syy] = it.cov2d;
    let det = sxx * syy - sxy * sxy;
    if !(det > 0.0) {
        return None;
    }
    let conic = [syy / det, -sxy / det, sxx / det];
    let mean2d = [
        cam.fx * it.p_cam.x / it.p_cam.z + cam.cx,
        cam.fy * it.p_cam.y / it.p_cam.z + cam.cy,
    ];
    // Opacity-aware extent: the box holds exactly the region where alpha >= 1/255.
    let extent = MAX_EXTENT_SIGMAS.min((2.0 * (g.opacity / ALPHA_MIN).ln()).sqrt());
    let rx = (extent * sxx.sqrt()).ceil();
    let ry = (extent * syy.sqrt()).ceil();
    if !(rx.is_finite() && ry.is_finite() && mean2d.iter().all(|v| v.is_finite())) {
        return None;
    }
    if rx <= 0.0 && ry <= 0.0 {
        return None;
    }
    let [mx, my] = mean2d;
    if mx + rx <= 0.0 || mx - rx >= cam.width || my + ry <= 0.0 || my - ry >= cam.height {
        return None;
    }
    // Radii beyond u32 cannot come from a finite image-overlapping box; saturate defensively.
    Some(Projected {
        mean2d,
        conic,
        depth: it.p_cam.z,
        radius: [rx as u32, ry as u32],
    })
}

/// Vector-Jacobian product of [`project`] for a Gaussian it did not cull.
pub fn project_backward(
    g: &GaussianParams,
    cam: &ProjectionCamera,
    grad: &ProjectedGrad,
) -> GeometryGrad {
    let Some(it) = intermediates(g, cam) else {
        return GeometryGrad::default();
    };
    let [sxx, sxy, syy] = it.cov2d;
    let det = sxx * syy - sxy * sxy;
    let (a, b, c) = (syy / det, -sxy / det, sxx / det);

    // conic = inverse(cov2d): d cov2d = -S^-1 G S^-1, with G the symmetric matrix whose
    // off-diagonal entries each carry half of the b gradient (b appears twice in the quadratic form).
    let [va, vb, vc] = grad.conic;
    let (g00, g01, g11) = (va, 0.5 * vb, vc);
    let p00 = a * g00 + b * g01;
    let p01 = a * g01 + b * g11;
    let p10 = b * g00 + c * g01;
    let p11 = b * g01 + c * g11;
    let gc = [
        [-(p00 * a + p01 * b), -(p00 * b + p01 * c)],
        [-(p10 * a + p11 * b), -(p10 * b + p11 * c)],
    ];

    // cov2d = J cov_cam J^T (+ eps): d cov_cam = J^T G J, d J = (G + G^T) J cov_cam.
    let rows = [it.j0, it.j1];
    let mut g_cov_cam = Mat3::ZERO;
    for r in 0..2 {
        for s in 0..2 {
            g_cov_cam += gc[r][s] * outer(rows[r], rows[s]);
        }
    }
    let cj = [it.cov_cam * it.j0, it.cov_cam * it.j1];
    let g_j0 = (gc[0][0] + gc[0][0]) * cj[0] + (gc[0][1] + gc[1][0]) * cj[1];
    let g_j1 = (gc[1][0] + gc[0][1]) * cj[0] + (gc[1][1] + gc[1][1]) * cj[1];

    // cov_cam = R cov R^T; cov = M M^T; M = R_q diag(s).
    let r = cam.rotation;
    let g_cov = r.transpose() * g_cov_cam * r;
    let g_m = (g_cov + g_cov.transpose()) * it.m;
    let mut scale = [0.0f32; 3];
    let mut g_rot = [[0.0f32; 3]; 3];
    for (j, s) in scale.iter_mut().enumerate() {
        for (i, row) in g_rot.iter_mut().enumerate() {
            *s += at(&g_m, i, j) * at(&it.rot_q, i, j);
            row[j] = at(&g_m, i, j) * g.scale[j];
        }
    }
    let quat = quat_backward(it.quat_unit, it.quat_norm, &g_rot);

    // Screen mean (unclamped x/z) and the Jacobian (clamped inside) as functions of p_cam.
    let Vec3 { x, y, z } = it.p_cam;
    let (fx, fy) = (cam.fx, cam.fy);
    let [vmx, vmy] = grad.mean2d;
    let mut gp = Vec3::new(
        vmx * fx / z,
        vmy * fy / z,
        -(vmx * fx * x + vmy * fy * y) / (z * z),
    );
    gp.z += -g_j0.x * fx / (z * z) - g_j1.y * fy / (z * z);
    if it.x_clamped {
        // J02 = -fx * lim / z with tx = z * lim.
        let tx = -it.j0.z * z * z / fx;
        gp.z += g_j0.z * fx * tx / (z * z * z);
    } else {
        gp.x += -g_j0.z * fx / (z * z);
        gp.z += g_j0.z * 2.0 * fx * x / (z * z * z);
    }
    if it.y_clamped {
        let ty = -it.j1.z * z * z / fy;
        gp.z += g_j1.z * fy * ty / (z * z * z);
    } else {
        gp.y += -g_j1.z * fy / (z * z);
        gp.z += g_j1.z * 2.0 * fy * y / (z * z * z);
    }
    let mean = r.transpose() * gp;
    GeometryGrad {
        mean: mean.into(),
        quat,
        scale,
    }
}

fn outer(u: Vec3, v: Vec3) -> Mat3 {
    Mat3::from_cols(u * v.x, u * v.y, u * v.z)
}

/// Gradient with respect to the raw quaternion, given the gradient `g` (row-major) with respect
/// to the rotation matrix of its normalisation.
fn quat_backward(unit: [f32; 4], norm: f32, g: &[[f32; 3]; 3]) -> [f32; 4] {
    let [dw, dx, dy, dz] = unit_quat_backward(unit, g);
    let [w, x, y, z] = unit;
    // Through q / |q|: (I - q_hat q_hat^T) / |q|.
    let dot = w * dw + x * dx + y * dy + z * dz;
    [
        (dw - w * dot) / norm,
        (dx - x * dot) / norm,
        (dy - y * dot) / norm,
        (dz - z * dot) / norm,
    ]
}

/// Gradient with respect to a unit quaternion (w, x, y, z) from the gradient `g` (row-major) with
/// respect to its rotation matrix ([`rotation_from_quat`]), before any normalisation.
pub(crate) fn unit_quat_backward([w, x, y, z]: [f32; 4], g: &[[f32; 3]; 3]) -> [f32; 4] {
    let dw =
        2.0 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let dx = 2.0
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - 2.0 * x * g[2][2]);
    let dy = 2.0
        * (-2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
            - w * g[2][0]
            + z * g[2][1]
            - 2.0 * y * g[2][2]);
    let dz = 2.0
        * (-2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    [dw, dx, dy, dz]
}
