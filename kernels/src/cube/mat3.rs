//! 3-vectors and row-major 3×3 matrices in CubeCL, and the rotation of a unit quaternion with
//! its backward: shared by the projection (`project`) and the spawned centres (`spawn_means`),
//! the formulas of `cpu::project`.

use cubecl::prelude::*;

#[derive(CubeType, Clone, Copy)]
pub(crate) struct V3 {
    pub(crate) x: f32,
    pub(crate) y: f32,
    pub(crate) z: f32,
}

/// Row-major 3×3.
#[derive(CubeType, Clone, Copy)]
pub(crate) struct M3 {
    pub(crate) r0: V3,
    pub(crate) r1: V3,
    pub(crate) r2: V3,
}

#[cube]
pub(crate) fn v3(x: f32, y: f32, z: f32) -> V3 {
    V3 { x, y, z }
}

#[cube]
pub(crate) fn dot(a: &V3, b: &V3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

#[cube]
pub(crate) fn add(a: &V3, b: &V3) -> V3 {
    v3(a.x + b.x, a.y + b.y, a.z + b.z)
}

#[cube]
pub(crate) fn scaled(a: &V3, s: f32) -> V3 {
    v3(a.x * s, a.y * s, a.z * s)
}

#[cube]
pub(crate) fn col0(m: &M3) -> V3 {
    v3(m.r0.x, m.r1.x, m.r2.x)
}

#[cube]
pub(crate) fn col1(m: &M3) -> V3 {
    v3(m.r0.y, m.r1.y, m.r2.y)
}

#[cube]
pub(crate) fn col2(m: &M3) -> V3 {
    v3(m.r0.z, m.r1.z, m.r2.z)
}

#[cube]
pub(crate) fn transpose(m: &M3) -> M3 {
    M3 {
        r0: col0(m),
        r1: col1(m),
        r2: col2(m),
    }
}

#[cube]
pub(crate) fn mul_vec(m: &M3, v: &V3) -> V3 {
    v3(dot(&m.r0, v), dot(&m.r1, v), dot(&m.r2, v))
}

#[cube]
pub(crate) fn mul(a: &M3, b: &M3) -> M3 {
    let c0 = col0(b);
    let c1 = col1(b);
    let c2 = col2(b);
    M3 {
        r0: v3(dot(&a.r0, &c0), dot(&a.r0, &c1), dot(&a.r0, &c2)),
        r1: v3(dot(&a.r1, &c0), dot(&a.r1, &c1), dot(&a.r1, &c2)),
        r2: v3(dot(&a.r2, &c0), dot(&a.r2, &c1), dot(&a.r2, &c2)),
    }
}

#[cube]
pub(crate) fn madd(a: &M3, b: &M3) -> M3 {
    M3 {
        r0: add(&a.r0, &b.r0),
        r1: add(&a.r1, &b.r1),
        r2: add(&a.r2, &b.r2),
    }
}

/// s · u vᵀ.
#[cube]
pub(crate) fn outer_scaled(u: &V3, v: &V3, s: f32) -> M3 {
    M3 {
        r0: scaled(v, u.x * s),
        r1: scaled(v, u.y * s),
        r2: scaled(v, u.z * s),
    }
}

/// Rotation of a unit quaternion (w, x, y, z).
#[cube]
pub(crate) fn rotation_from_quat(w: f32, x: f32, y: f32, z: f32) -> M3 {
    M3 {
        r0: v3(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ),
        r1: v3(
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ),
        r2: v3(
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ),
    }
}

/// Gradient with respect to the unit quaternion (w, x, y, z) from the gradient `g` (row-major)
/// with respect to its rotation matrix (`cpu::project::unit_quat_backward`); the normalisation's
/// backward is the caller's.
#[cube]
pub(crate) fn unit_quat_backward(w: f32, x: f32, y: f32, z: f32, g: &M3) -> (f32, f32, f32, f32) {
    let dw =
        2.0f32 * (-z * g.r0.y + y * g.r0.z + z * g.r1.x - x * g.r1.z - y * g.r2.x + x * g.r2.y);
    let dx = 2.0f32
        * (y * g.r0.y + z * g.r0.z + y * g.r1.x - 2.0f32 * x * g.r1.y - w * g.r1.z
            + z * g.r2.x
            + w * g.r2.y
            - 2.0f32 * x * g.r2.z);
    let dy = 2.0f32
        * (-2.0f32 * y * g.r0.x + x * g.r0.y + w * g.r0.z + x * g.r1.x + z * g.r1.z - w * g.r2.x
            + z * g.r2.y
            - 2.0f32 * y * g.r2.z);
    let dz = 2.0f32
        * (-2.0f32 * z * g.r0.x - w * g.r0.y + x * g.r0.z + w * g.r1.x - 2.0f32 * z * g.r1.y
            + y * g.r1.z
            + x * g.r2.x
            + y * g.r2.y);
    (dw, dx, dy, dz)
}
