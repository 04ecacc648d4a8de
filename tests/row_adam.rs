//! Row-wise Adam: PyTorch's update, and state that follows grown, pruned and reset rows.
#![allow(deprecated)] // Device::ndarray

use acags::train::row_adam::{AdamConfig, RowAdam};
use burn::tensor::{Device, Tensor, TensorData};

fn t2(v: Vec<f32>, rows: usize, cols: usize) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v, [rows, cols]), &Device::ndarray())
}

fn vals(t: &Tensor<2>) -> Vec<f32> {
    t.clone().into_data().try_into_vec_as::<f32>().unwrap()
}

/// Scalar reference of torch.optim.Adam.
fn reference(p0: f64, grads: &[f64], lr: f64, c: AdamConfig) -> f64 {
    let (mut p, mut m, mut v) = (p0, 0.0, 0.0);
    for (i, g) in grads.iter().enumerate() {
        let t = (i + 1) as i32;
        m = c.beta1 * m + (1.0 - c.beta1) * g;
        v = c.beta2 * v + (1.0 - c.beta2) * g * g;
        let denom = v.sqrt() / (1.0 - c.beta2.powi(t)).sqrt() + c.eps;
        p -= lr / (1.0 - c.beta1.powi(t)) * m / denom;
    }
    p
}

#[test]
fn matches_pytorch_adam() {
    let config = AdamConfig {
        eps: 1e-8,
        ..Default::default()
    };
    let grads = [[0.5f32, -2.0], [0.1, 3.0], [-0.7, 0.01]];
    let mut p = t2(vec![1.0, -1.0], 1, 2);
    let mut adam = RowAdam::new(&p, config);
    for g in grads {
        p = adam.step(p, t2(g.to_vec(), 1, 2), 0.01);
    }
    let got = vals(&p);
    for c in 0..2 {
        let want = reference([1.0, -1.0][c], &grads.map(|g| g[c] as f64), 0.01, config);
        assert!(
            (got[c] as f64 - want).abs() < 1e-6,
            "column {c}: {} vs {want}",
            got[c]
        );
    }
    // The first step moves every coordinate by ~lr, whatever the gradient scale.
    let mut fresh = RowAdam::new(&t2(vec![0.0; 2], 1, 2), AdamConfig::default());
    let moved = vals(&fresh.step(t2(vec![0.0; 2], 1, 2), t2(vec![1e-6, 1e6], 1, 2), 0.01));
    assert!(moved.iter().all(|m| (m + 0.01).abs() < 1e-6), "{moved:?}");
}

#[test]
fn state_follows_grow_prune_and_reset() {
    let mut p = t2(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 3, 2);
    let mut adam = RowAdam::new(&p, AdamConfig::default());
    p = adam.step(p, t2(vec![1.0, 1.0, 2.0, 2.0, 3.0, 3.0], 3, 2), 0.1);
    let m_before = vals(&adam.exp_avg);
    assert_eq!(
        m_before,
        vec![0.1, 0.1, 0.2, 0.2, 0.3, 0.3]
            .iter()
            .map(|v| *v as f32)
            .collect::<Vec<_>>()
    );

    adam.grow(2);
    assert_eq!(adam.rows(), 5);
    let m = vals(&adam.exp_avg);
    assert_eq!(&m[..6], &m_before[..]);
    assert!(
        m[6..].iter().all(|v| *v == 0.0),
        "new rows start with zero state"
    );

    // Prune rows 0 and 3: rows 1, 2, 4 remain, in order.
    adam.keep_rows(&[1, 2, 4]);
    let m = vals(&adam.exp_avg);
    assert_eq!(
        m,
        vec![0.2, 0.2, 0.3, 0.3, 0.0, 0.0]
            .iter()
            .map(|v| *v as f32)
            .collect::<Vec<_>>()
    );
    let v_sq = vals(&adam.exp_avg_sq);
    assert!(v_sq[..4].iter().all(|v| *v > 0.0));

    adam.reset_rows(&[1]);
    let (m, v_sq) = (vals(&adam.exp_avg), vals(&adam.exp_avg_sq));
    assert_eq!(&m[..2], &[0.2f32, 0.2][..]);
    assert_eq!(&m[2..4], &[0.0f32, 0.0][..]);
    assert_eq!(&v_sq[2..4], &[0.0f32, 0.0][..]);
    assert_eq!(
        adam.step, 1,
        "the step count is per parameter, untouched by row edits"
    );
    let _ = p;
}

#[test]
fn works_on_three_dimensional_rows() {
    // Time features are [N, T, C]: rows are anchors.
    let device = Device::ndarray();
    let p = Tensor::<3>::ones([4, 2, 3], &device);
    let mut adam = RowAdam::new(&p, AdamConfig::default());
    let p = adam.step(p.clone(), p.ones_like(), 0.5);
    adam.reset_rows(&[0, 2]);
    adam.grow(1);
    adam.keep_rows(&[4, 1]);
    assert_eq!(adam.exp_avg.dims(), [2, 2, 3]);
    let m: Vec<f32> = adam
        .exp_avg
        .clone()
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    assert!(
        m[..6].iter().all(|v| *v == 0.0) && m[6..].iter().all(|v| (*v - 0.1).abs() < 1e-6),
        "{m:?}"
    );
    assert_eq!(p.dims(), [4, 2, 3]);
}

#[test]
fn per_column_rates_step_each_column_at_its_own_rate() {
    let config = AdamConfig {
        eps: 1e-8,
        ..Default::default()
    };
    let grads = [[0.5f32, -2.0, 0.3], [0.1, 3.0, -0.2], [-0.7, 0.01, 0.4]];
    let start = vec![1.0f32, -1.0, 0.5];
    let rates = [0.01, 0.0, 0.03];
    let mut p = t2(start.clone(), 1, 3);
    let mut adam = RowAdam::new(&p, config);
    for g in grads {
        p = adam.step_columns(p, t2(g.to_vec(), 1, 3), &rates);
    }
    let got = vals(&p);
    for c in 0..3 {
        let want = reference(
            start[c] as f64,
            &grads.map(|g| g[c] as f64),
            rates[c],
            config,
        );
        assert!(
            (got[c] as f64 - want).abs() < 1e-6,
            "column {c}: {} vs {want}",
            got[c]
        );
    }
    assert_eq!(got[1], -1.0, "a zero rate leaves its column");
    // Uniform rates are the scalar step.
    let (mut a, mut b) = (t2(start.clone(), 1, 3), t2(start, 1, 3));
    let (mut adam_a, mut adam_b) = (RowAdam::new(&a, config), RowAdam::new(&b, config));
    for g in grads {
        a = adam_a.step(a, t2(g.to_vec(), 1, 3), 0.02);
        b = adam_b.step_columns(b, t2(g.to_vec(), 1, 3), &[0.02; 3]);
    }
    let (a, b) = (vals(&a), vals(&b));
    assert!(
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-7),
        "{a:?} vs {b:?}"
    );
}
