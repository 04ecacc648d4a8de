//! Time-feature window and gate activation (spec §2.1, §4.2).
#![allow(deprecated)] // Device::ndarray

use acags::model::inputs::{activate_gates, time_window_gap, windowed_time_feature};
use burn::tensor::{Device, Tensor, TensorData};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

#[test]
fn window_shrinks_from_t_over_5_to_zero_at_20_percent() {
    assert_eq!(time_window_gap(0, 30_000, 60), 12);
    // 12 · (1 − 5·3000/29999) = 5.9998, truncated like Python's int().
    assert_eq!(time_window_gap(3_000, 30_000, 60), 5);
    assert_eq!(time_window_gap(2_999, 30_000, 60), 6);
    assert_eq!(time_window_gap(6_000, 30_000, 60), 0);
    assert_eq!(time_window_gap(29_999, 30_000, 60), 0);
    assert_eq!(time_window_gap(0, 30_000, 65), 13);
}

#[test]
fn windowed_feature_is_the_clipped_mean() {
    let device = Device::ndarray();
    // One anchor, 6 frames, 2 channels: frame f holds (f, 10 f).
    let data: Vec<f32> = (0..6).flat_map(|f| [f as f32, 10.0 * f as f32]).collect();
    let tf = Tensor::<3>::from_data(TensorData::new(data, [1, 6, 2]), &device);
    assert_eq!(
        values(windowed_time_feature(tf.clone(), 3, 0)),
        vec![3.0, 30.0]
    );
    assert_eq!(
        values(windowed_time_feature(tf.clone(), 3, 1)),
        vec![3.0, 30.0]
    ); // mean of 2, 3, 4
    assert_eq!(
        values(windowed_time_feature(tf.clone(), 0, 2)),
        vec![1.0, 10.0]
    ); // frames 0..=2
    assert_eq!(values(windowed_time_feature(tf, 5, 3)), vec![3.5, 35.0]); // frames 2..=5
}

#[test]
fn gates_threshold_in_forward_and_pass_sigmoid_gradient_back() {
    let device = Device::ndarray().autodiff();
    // sigmoid(-3) = 0.047 < 0.1 -> off; sigmoid(0) = 0.5; sigmoid(2) = 0.88.
    let raw = Tensor::<2>::from_data(
        TensorData::new(vec![-3.0f32, 0.0, 2.0, 0.0, 0.0, -3.0, -3.0, -3.0], [2, 4]),
        &device,
    )
    .require_grad();
    let gates = activate_gates(raw.clone());
    let got = values(gates.clone());
    let sig = |x: f32| 1.0 / (1.0 + (-x).exp());
    let want = [0.0, 0.5, sig(2.0), 1.0, 0.5, 0.0, 0.0, 0.0];
    assert!(
        got.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{got:?}"
    );
    let grads = gates.sum().backward();
    let g = values(raw.grad(&grads).unwrap());
    let raws = [-3.0f32, 0.0, 2.0, 0.0, 0.0, -3.0, -3.0, -3.0];
    for (i, r) in raws.iter().enumerate() {
        let d = sig(*r) * (1.0 - sig(*r));
        assert!(
            (g[i] - d).abs() < 1e-6,
            "entry {i}: {} vs sigmoid' {d}",
            g[i]
        );
    }
}
