//! Trajectory curvature (not in GIFStream; docs/results.md, Follow-up 43): each anchor's path is
//! straight unless the images insist.
//!
//! A knot every 4 frames is too many for a smooth flight (`synthetic:crossing` gained 0.63 dB of
//! mean gap with a knot every 8 frames) and too few to be dropped where an object turns sharply
//! (`large-motion`'s bounce lost 1.5 dB at 8; Follow-up 42). The term is ℓ1 trend filtering
//! (Kim, Koh, Boyd and Gorinevsky, 2009) on the knots: the L1 norm of each anchor's second
//! differences K_{j−1} − 2·K_j + K_{j+1}, whose minimisers are piecewise linear with few
//! bends, so a steady path behaves like one with fewer knots and a bounce keeps its turn.
//!
//! Measured (Follow-up 43, seed 42, decoded) it does neither, so `loss.trajectory_curvature` is
//! 0 by default: at 30 and 100 `large-motion`'s mean gap rose 1.6-1.8 dB (the bounce's turns
//! are penalised as much as any noise), and `crossing`'s rose 0.19-0.44 dB, all in the clip's
//! second half. Translation is not all of an anchor's path: on a turning object every anchor
//! moves on an arc, which bends at every knot (crossing's cube turns 18.5° per knot: a bend of
//! 2r(1 − cos 18.5°) ≈ 0.04 units at r = 0.4), so "straight unless the images insist" is the
//! wrong prior for rotation at that strength. At 3 `crossing` gains 0.61 dB and `large-motion`
//! loses 0.42: the knots' spacing's split again, so no λ measured helps both.

use burn::tensor::{Tensor, s};

use super::coherence::gated_trajectory;

/// Mean over anchors and interior knot coordinates of |mf·(K_{j−1} − 2·K_j + K_{j+1})| over the
/// first `reached` knots (those the open frames use: a knot the curriculum has not reached is
/// set when it opens, so it must not bend the opened path towards its placeholder). The
/// divisor counts every interior knot, open or not, so a coordinate's gradient (λ·mf / (N·3·
/// (knots − 2)) per unit of sign) does not change as the curriculum opens knots. mf·K is the
/// coherence term's [`gated_trajectory`] (gates held constant). `None` while fewer than three
/// knots are open.
pub fn trajectory_curvature(
    trajectory: Tensor<2>,
    factors: Tensor<2>,
    reached: usize,
) -> Option<Tensor<1>> {
    let [n, width] = trajectory.dims();
    let knots = width / 3;
    let reached = reached.min(knots);
    if n == 0 || reached < 3 {
        return None;
    }
    let applied = gated_trajectory(trajectory.slice(s![.., 0..3 * reached]), factors);
    let before = applied.clone().slice(s![.., 0..3 * (reached - 2)]);
    let at = applied.clone().slice(s![.., 3..3 * (reached - 1)]);
    let after = applied.slice(s![.., 6..3 * reached]);
    let bends = before - at * 2.0 + after;
    Some(bends.abs().sum() / (n * 3 * (knots - 2)) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device_io::upload;
    use crate::model::anchors::host_values;
    use burn::tensor::{Device, TensorData};

    fn tensor(values: Vec<f32>, shape: [usize; 2]) -> Tensor<2> {
        #[allow(deprecated)] // Device::ndarray
        let device = Device::ndarray();
        upload(TensorData::new(values, shape), &device)
    }

    /// Factors whose motion gate (column 1) is σ(raw).
    fn factors(raw_motion: &[f32]) -> Tensor<2> {
        let n = raw_motion.len();
        let values = raw_motion
            .iter()
            .flat_map(|&m| [0.0, m, 0.0, 0.0])
            .collect();
        tensor(values, [n, 4])
    }

    #[test]
    fn straight_paths_cost_nothing_and_a_bend_costs_its_turn() {
        // Anchor 0 flies straight (knots x = 0, 1, 2, 3, 4); anchor 1 rises and falls
        // (y = 0, 1, 2, 1, 0): one bend of −2 at knot 2 in y.
        let straight: Vec<f32> = (0..5).flat_map(|j| [j as f32, 0.5, -0.25]).collect();
        let bounce: Vec<f32> = [0.0, 1.0, 2.0, 1.0, 0.0]
            .iter()
            .flat_map(|&y| [0.0, y, 0.0])
            .collect();
        let big = 30.0; // σ(30) = 1 in f32
        let all = tensor([straight.clone(), bounce.clone()].concat(), [2, 15]);
        let value = host_values(&trajectory_curvature(all, factors(&[big, big]), 5).unwrap())[0];
        // |−2| over 2 anchors × 3 coordinates × 3 interior knots.
        assert!((value - 2.0 / 18.0).abs() < 1e-6, "{value}");
        let only_straight = tensor(straight, [1, 15]);
        let value =
            host_values(&trajectory_curvature(only_straight, factors(&[big]), 5).unwrap())[0];
        assert!(value.abs() < 1e-6, "{value}");
        // The motion gate scales the path: σ(0) = 0.5.
        let half = tensor(bounce.clone(), [1, 15]);
        let value = host_values(&trajectory_curvature(half, factors(&[0.0]), 5).unwrap())[0];
        assert!((value - 0.5 * 2.0 / 9.0).abs() < 1e-6, "{value}");
        // Only the opened knots: with 3 of 5 reached the path 0, 1, 2 is straight, and the
        // divisor still counts the 3 interior knots of the whole path.
        let first = tensor(bounce.clone(), [1, 15]);
        let value = host_values(&trajectory_curvature(first, factors(&[big]), 3).unwrap())[0];
        assert!(value.abs() < 1e-6, "{value}");
        let four = tensor(bounce, [1, 15]);
        let value = host_values(&trajectory_curvature(four, factors(&[big]), 4).unwrap())[0];
        assert!((value - 2.0 / 9.0).abs() < 1e-6, "{value}");
        let two = tensor(vec![0.0; 15], [1, 15]);
        assert!(trajectory_curvature(two, factors(&[big]), 2).is_none());
    }

    #[test]
    fn the_gradient_straightens_the_bend_and_spares_the_gate() {
        // One anchor, y = 0, 1, 2, 1, 0: the bend at knot 2 is −2, so L = |−2|·g / (3·3) and
        // ∂L/∂y = g/9 · (−1, 2, −1) at knots 1, 2, 3: the gradient step lowers knot 2 and raises
        // its neighbours, towards a straight path. Nothing flows into the gate logit.
        #[allow(deprecated)] // Device::ndarray
        let device = Device::ndarray().autodiff();
        let bounce: Vec<f32> = [0.0, 1.0, 2.0, 1.0, 0.0]
            .iter()
            .flat_map(|&y| [0.0, y, 0.0])
            .collect();
        let knots: Tensor<2> = upload(TensorData::new(bounce, [1, 15]), &device).require_grad();
        let raw: Tensor<2> = upload(
            TensorData::new(vec![0.0f32, 0.0, 0.0, 0.0], [1, 4]),
            &device,
        )
        .require_grad();
        let loss = trajectory_curvature(knots.clone(), raw.clone(), 5).unwrap();
        let grads = loss.backward();
        let g = host_values(&knots.grad(&grads).unwrap());
        let unit = 0.5 / 9.0;
        let mut expected = vec![0.0f32; 15];
        expected[3 + 1] = -unit;
        expected[6 + 1] = 2.0 * unit;
        expected[9 + 1] = -unit;
        for (i, (a, b)) in g.iter().zip(&expected).enumerate() {
            assert!((a - b).abs() < 1e-6, "coordinate {i}: {a} against {b}");
        }
        let gate = raw.grad(&grads).map(|t| host_values(&t));
        assert!(
            gate.as_ref().is_none_or(|v| v.iter().all(|&x| x == 0.0)),
            "{gate:?}"
        );
    }
}
