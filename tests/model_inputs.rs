//! Time-feature window and gate activation (spec §2.1, §4.2).
#![allow(deprecated)] // Device::ndarray

use acags::model::inputs::{
    activate_gates, frame_window_mean, time_window_gap, windowed_time_feature,
};
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

#[test]
fn the_decoders_window_of_sliced_columns_equals_the_reference_window_in_values_and_gradients() {
    // view.rs slices the window's columns out of the [N, T·C] stream table, gathers rows and
    // averages (`frame_window_mean`); the reference reshapes every row to [T, C] and takes
    // `windowed_time_feature`. Same values, and the same gradient on the table (zero outside the
    // window and the gathered rows), for windows at both ends, inside, of one frame and of all.
    use acags::raster::columns::slice_columns;
    use acags::raster::gather::gather_rows;
    use burn::tensor::Int;
    let device = Device::ndarray().autodiff();
    let (n, t, c) = (5, 7, 3);
    let table: Vec<f32> = (0..n * t * c)
        .map(|v| ((v * 37 % 101) as f32 - 50.0) / 7.0)
        .collect();
    let rows = [3i64, 0, 3, 4];
    let upstream: Vec<f32> = (0..rows.len() * c).map(|v| 1.0 + v as f32 * 0.25).collect();
    for (frame, gap) in [
        (0usize, 0usize),
        (6, 0),
        (3, 0),
        (0, 2),
        (6, 2),
        (3, 1),
        (3, 9),
    ] {
        let run = |windowed: &dyn Fn(Tensor<2>, Tensor<1, Int>) -> Tensor<2>| {
            let table = Tensor::<2>::from_data(TensorData::new(table.clone(), [n, t * c]), &device)
                .require_grad();
            let index = Tensor::<1, Int>::from_data(TensorData::new(rows.to_vec(), [4]), &device);
            let out = windowed(table.clone(), index);
            let weights =
                Tensor::<2>::from_data(TensorData::new(upstream.clone(), [4, c]), &device);
            let grads = (out.clone() * weights).sum().backward();
            (values(out), values(table.grad(&grads).unwrap()))
        };
        let (lo, hi) = (frame.saturating_sub(gap), (frame + gap + 1).min(t));
        let sliced = run(&|table, index| {
            frame_window_mean(gather_rows(slice_columns(table, lo * c..hi * c), index), c)
        });
        let reference = run(&|table, index| {
            windowed_time_feature(gather_rows(table, index).reshape([4, t, c]), frame, gap)
        });
        for (got, want) in [(&sliced.0, &reference.0), (&sliced.1, &reference.1)] {
            assert_eq!(got.len(), want.len());
            for (a, b) in got.iter().zip(want.iter()) {
                assert!(
                    (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
                    "frame {frame} gap {gap}: {a} vs {b}"
                );
            }
        }
        // The gradient lands only inside the window's columns.
        let outside = sliced.1.chunks(c).enumerate().any(|(i, g)| {
            let f = i % t;
            !(lo..hi).contains(&f) && g.iter().any(|&v| v != 0.0)
        });
        assert!(
            !outside,
            "frame {frame} gap {gap}: gradient outside the window"
        );
    }
    // Half a frame is a caller's bug.
    let bad = std::panic::catch_unwind(|| {
        frame_window_mean(Tensor::<2>::zeros([2, 4], &Device::ndarray()), 3)
    });
    assert!(bad.is_err());
}
