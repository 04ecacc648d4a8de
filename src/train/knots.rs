//! Where new trajectory knots start when the temporal curriculum first opens the frames that use
//! them (`train.knot_extrapolation`; anchor trajectories are not in GIFStream, see
//! `model/view.rs`).

use super::config::KnotExtrapolation;

/// Sets knots `knots` (each ≥ 1) of every trajectory row in `values` ([N, width], 3 floats per
/// knot) from the knots before them, under `rule`. `gates` are the anchors' motion gates
/// (σ of the raw factor; read only by [`KnotExtrapolation::MovingVelocity`]) and `moving_min`
/// the world-space length of a last segment (gate × knot difference) above which an anchor
/// counts as moving.
pub fn start_new_knots(
    values: &mut [f32],
    width: usize,
    knots: std::ops::Range<usize>,
    rule: KnotExtrapolation,
    gates: &[f32],
    moving_min: f32,
) {
    assert!(knots.start >= 1, "knot 0 has no knot before it");
    if width == 0 {
        return;
    }
    for (a, row) in values.chunks_exact_mut(width).enumerate() {
        for j in knots.clone() {
            let last: [f32; 3] = std::array::from_fn(|c| {
                if j >= 2 {
                    row[(j - 1) * 3 + c] - row[(j - 2) * 3 + c]
                } else {
                    0.0
                }
            });
            let extrapolate = match rule {
                KnotExtrapolation::Hold => false,
                KnotExtrapolation::Velocity => true,
                KnotExtrapolation::MovingVelocity => {
                    let length = last.iter().map(|v| v * v).sum::<f32>().sqrt();
                    gates[a] * length > moving_min
                }
            };
            for c in 0..3 {
                let velocity = if extrapolate { last[c] } else { 0.0 };
                row[j * 3 + c] = row[(j - 1) * 3 + c] + velocity;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two anchors, three knots: anchor 0 moved 1.0 along x over its first segment, anchor 1
    /// drifted 0.01; the third knot is new.
    fn rows() -> Vec<f32> {
        vec![
            0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 9.0, 9.0, 9.0, //
            0.5, 0.0, 0.0, 0.51, 0.0, 0.0, 9.0, 9.0, 9.0,
        ]
    }

    #[test]
    fn new_knots_hold_extrapolate_or_extrapolate_only_what_moves() {
        let mut hold = rows();
        start_new_knots(&mut hold, 9, 2..3, KnotExtrapolation::Hold, &[], 0.0);
        assert_eq!(&hold[6..9], &[1.0, 0.0, 0.0]);
        assert_eq!(&hold[15..18], &[0.51, 0.0, 0.0]);

        let mut velocity = rows();
        start_new_knots(&mut velocity, 9, 2..3, KnotExtrapolation::Velocity, &[], 0.0);
        assert_eq!(&velocity[6..9], &[2.0, 0.0, 0.0]);
        assert!((velocity[15] - 0.52).abs() < 1e-6);

        // Gate 0.5: anchor 0 moved 0.5 in world space (> 0.1), anchor 1 moved 0.005 (held).
        let mut moving = rows();
        let rule = KnotExtrapolation::MovingVelocity;
        start_new_knots(&mut moving, 9, 2..3, rule, &[0.5, 0.5], 0.1);
        assert_eq!(&moving[6..9], &[2.0, 0.0, 0.0]);
        assert_eq!(&moving[15..18], &[0.51, 0.0, 0.0]);
        // A closed gate means the knots do not move the anchor: held.
        let mut closed = rows();
        start_new_knots(&mut closed, 9, 2..3, rule, &[0.05, 0.5], 0.1);
        assert_eq!(&closed[6..9], &[1.0, 0.0, 0.0]);

        // Knot 1 has no segment before it: every rule holds; several new knots chain.
        let mut chain = rows();
        start_new_knots(&mut chain, 9, 1..3, KnotExtrapolation::Velocity, &[], 0.0);
        assert_eq!(&chain[0..9], &[0.0; 9]);
    }
}
