//! Rotations fitted and expressed on the host: Horn's best rotation between point sets and the
//! rotation vectors that trajectory turns interpolate (shared by the rigid fit in training and
//! the turns derived from anchor paths, which the decoder recomputes).

use glam::{Quat, Vec3};

/// The rotation R minimising Σ |R·a_i − b_i|² for centred point sets (Horn 1987: the unit
/// quaternion is the eigenvector of the largest eigenvalue of a symmetric 4×4 matrix built from
/// the cross-covariance). The identity where the points do not determine it.
pub fn best_rotation(a: &[Vec3], b: &[Vec3]) -> Quat {
    let mut s = [[0.0f64; 3]; 3];
    for (p, q) in a.iter().zip(b) {
        let (p, q) = (p.as_dvec3(), q.as_dvec3());
        let (p, q) = (p.to_array(), q.to_array());
        for (i, row) in s.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v += p[i] * q[j];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = symmetric_eigen4(n);
    let best = (0..4)
        .max_by(|&i, &j| values[i].total_cmp(&values[j]))
        .expect("four eigenvalues");
    let [w, x, y, z] = std::array::from_fn(|r| vectors[r][best]);
    let q = Quat::from_xyzw(x as f32, y as f32, z as f32, w as f32);
    if q.length_squared().is_finite() && q.length_squared() > 0.5 {
        q.normalize()
    } else {
        Quat::IDENTITY
    }
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 4×4 matrix, by cyclic Jacobi
/// rotations.
fn symmetric_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..50 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let scale: f64 = (0..4).map(|i| a[i][i] * a[i][i]).sum::<f64>() + off;
        if off <= 1e-24 * scale.max(f64::MIN_POSITIVE) {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                // A ← Jᵀ A J with J the rotation in the (p, q) plane.
                for k in 0..4 {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    (std::array::from_fn(|i| a[i][i]), v)
}

/// The rotation vector (axis × angle) of `q` nearest `near` among its representatives
/// (axis × (angle + 2πk)), so that knots interpolated linearly turn the short way from the
/// previous knot's turn, also past a half turn.
pub fn rotation_vector_near(q: Quat, near: Vec3) -> Vec3 {
    let (axis, angle) = q.normalize().to_axis_angle();
    if !angle.is_finite() || angle.abs() < 1e-9 {
        // Identity: the representative 2πk·axis nearest `near`, along its own axis.
        let length = near.length();
        if length < std::f32::consts::PI {
            return Vec3::ZERO;
        }
        let k = (length / std::f32::consts::TAU).round();
        return near / length * (k * std::f32::consts::TAU);
    }
    // Every representative is axis × (angle + 2πk); −axis × (2π − angle) is k = −1.
    (-2..=2)
        .map(|k| axis * (angle + k as f32 * std::f32::consts::TAU))
        .min_by(|x, y| (*x - near).length().total_cmp(&(*y - near).length()))
        .expect("five representatives")
}

/// The angle (radians) of a rotation.
pub fn angle_of(q: Quat) -> f32 {
    // atan2, not acos(w): accurate near the identity in f32.
    2.0 * q.xyz().length().atan2(q.w.abs())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_vectors_continue_past_a_half_turn() {
        let axis = Vec3::new(0.0, 0.6, 0.8);
        // A turn of 3.3 rad is stored by the quaternion as −(2π − 3.3) about the axis; near the
        // previous knot's 2.9 rad it reads back as 3.3 about the axis.
        let q = Quat::from_axis_angle(axis, 3.3);
        let v = rotation_vector_near(q, axis * 2.9);
        assert!((v - axis * 3.3).length() < 1e-4, "{v}");
        assert!(angle_of(Quat::from_scaled_axis(v) * q.inverse()) < 1e-4);
        // Near zero: the short way.
        let v = rotation_vector_near(Quat::from_axis_angle(axis, 0.2), Vec3::ZERO);
        assert!((v - axis * 0.2).length() < 1e-5);
        let v = rotation_vector_near(Quat::from_axis_angle(axis, -0.2), Vec3::ZERO);
        assert!((v + axis * 0.2).length() < 1e-5);
        // The identity near a full turn stays a full turn.
        let v = rotation_vector_near(Quat::IDENTITY, axis * 6.0);
        assert!((v - axis * std::f32::consts::TAU).length() < 1e-4, "{v}");
    }
}
