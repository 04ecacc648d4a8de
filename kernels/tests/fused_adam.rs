//! The fused Adam op against the plain-tensor update it replaces (13 Burn element-wise ops, as
//! `acags::train::row_adam` wrote it before): bit for bit on ndarray (CPU twin), within f32
//! rounding on the wgpu kernel (lavapipe in CI; fails instead of skipping under
//! ACAGS_REQUIRE_WGPU=1). Also on the autodiff device, with per-column rates, shared state
//! storage, and after several steps.
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::fused_adam::{AdamStep, adam_update};
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use cube_common::{cube_device, values};
use rand::{Rng, SeedableRng, rngs::StdRng};

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;

fn tensor2(v: Vec<f32>, shape: [usize; 2], device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v, shape), device)
}

/// The reference: Adam as separate tensor ops, in the order `row_adam` issued them.
fn plain_step(
    param: Tensor<2>,
    m: Tensor<2>,
    v: Tensor<2>,
    grad: Tensor<2>,
    lr: &[f64],
    eps: f64,
    t: i32,
) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
    let m = m * BETA1 + grad.clone() * (1.0 - BETA1);
    let v = v * BETA2 + grad.clone() * grad * (1.0 - BETA2);
    let bias1 = 1.0 - BETA1.powi(t);
    let bias2 = 1.0 - BETA2.powi(t);
    let denom = v.clone().sqrt() / bias2.sqrt() + eps;
    let direction = m.clone() / denom;
    let param = if lr.len() == 1 {
        param - direction * (lr[0] / bias1)
    } else {
        let rates: Vec<f32> = lr.iter().map(|&r| (r / bias1) as f32).collect();
        let columns = rates.len();
        param - direction * tensor2(rates, [1, columns], &m.device())
    };
    (param, m, v)
}

fn fused_step(
    param: Tensor<2>,
    m: Tensor<2>,
    v: Tensor<2>,
    grad: Tensor<2>,
    lr: &[f64],
    eps: f64,
    t: i32,
) -> (Tensor<2>, Tensor<2>, Tensor<2>) {
    let bias1 = 1.0 - BETA1.powi(t);
    let rates: Vec<f32> = lr.iter().map(|&r| (r / bias1) as f32).collect();
    let rates = Tensor::<1>::from_data(TensorData::new(rates, [lr.len()]), &param.device());
    adam_update(
        param,
        m,
        v,
        grad,
        rates,
        AdamStep::new(BETA1, BETA2, eps, t),
    )
}

/// Random values spanning many magnitudes (and exact zeros), so rounding differences show.
fn random_values(rng: &mut StdRng, n: usize) -> Vec<f32> {
    (0..n)
        .map(|_| match rng.random_range(0..10) {
            0 => 0.0,
            1 => rng.random_range(-1e-6f32..1e-6),
            2 => rng.random_range(-100f32..100.0),
            _ => rng.random_range(-1f32..1.0),
        })
        .collect()
}

/// Five steps of both versions from the same start; returns (plain, fused) after each step.
fn run_both(device: &Device, shape: [usize; 2], lr: &[f64], eps: f64) -> Vec<[[Vec<f32>; 3]; 2]> {
    let mut rng = StdRng::seed_from_u64(7);
    let n = shape[0] * shape[1];
    let param = tensor2(random_values(&mut rng, n), shape, device);
    let zeros = Tensor::<2>::zeros(shape, device);
    let (mut plain, mut fused) = (
        (param.clone(), zeros.clone(), zeros.clone()),
        (param, zeros.clone(), zeros),
    );
    let mut out = Vec::new();
    for t in 1..=5 {
        let grad = tensor2(random_values(&mut rng, n), shape, device);
        plain = plain_step(plain.0, plain.1, plain.2, grad.clone(), lr, eps, t);
        // The fused op may update its state in place: hand it copies the plain side never sees.
        fused = fused_step(fused.0, fused.1, fused.2, grad, lr, eps, t);
        out.push([
            [values(&plain.0), values(&plain.1), values(&plain.2)],
            [values(&fused.0), values(&fused.1), values(&fused.2)],
        ]);
    }
    out
}

fn assert_bitwise(label: &str, runs: &[[[Vec<f32>; 3]; 2]]) {
    for (t, [plain, fused]) in runs.iter().enumerate() {
        for (name, (a, b)) in ["param", "exp_avg", "exp_avg_sq"]
            .iter()
            .zip(plain.iter().zip(fused))
        {
            assert_eq!(a.len(), b.len());
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(
                    x.to_bits() == y.to_bits(),
                    "{label}: {name}[{i}] after step {}: plain {x:e}, fused {y:e}",
                    t + 1
                );
            }
        }
    }
}

#[test]
fn fused_adam_equals_the_plain_update_bit_for_bit_on_ndarray() {
    for device in [Device::ndarray(), Device::ndarray().autodiff()] {
        // One rate (every anchor column, the decoders), eps of the anchors and of the decoders.
        assert_bitwise(
            "one rate, eps 1e-15",
            &run_both(&device, [300, 37], &[7.5e-3], 1e-15),
        );
        assert_bitwise(
            "one rate, eps 1e-8",
            &run_both(&device, [64, 5], &[0.0016], 1e-8),
        );
        // One rate per column (the trajectory knots' schedule).
        let lr: Vec<f64> = (0..6).map(|k| 1e-3 * (k + 1) as f64).collect();
        assert_bitwise("per column", &run_both(&device, [129, 6], &lr, 1e-15));
    }
}

#[test]
fn fused_adam_leaves_shared_inputs_untouched() {
    // The CPU twin updates the moments in place when it owns them; when another handle shares
    // their storage, that handle must still see the old values.
    let device = Device::ndarray();
    let mut rng = StdRng::seed_from_u64(3);
    let shape = [50, 4];
    let [p, m, v, g] = [0; 4].map(|_| tensor2(random_values(&mut rng, 200), shape, &device));
    let v = v.abs();
    let before: Vec<Vec<f32>> = [&p, &m, &v, &g].iter().map(|t| values(t)).collect();
    let (p2, m2, v2) = fused_step(
        p.clone(),
        m.clone(),
        v.clone(),
        g.clone(),
        &[0.01],
        1e-15,
        3,
    );
    let after: Vec<Vec<f32>> = [&p, &m, &v, &g].iter().map(|t| values(t)).collect();
    assert_eq!(before, after, "an input shared with the caller changed");
    let (p3, m3, v3) = plain_step(p, m, v, g, &[0.01], 1e-15, 3);
    assert_eq!(values(&p2), values(&p3));
    assert_eq!(values(&m2), values(&m3));
    assert_eq!(values(&v2), values(&v3));
}

#[test]
fn fused_adam_rejects_rates_that_do_not_tile_the_row() {
    let device = Device::ndarray();
    let z = Tensor::<2>::zeros([4, 3], &device);
    let result = std::panic::catch_unwind(|| {
        fused_step(
            z.clone(),
            z.clone(),
            z.clone(),
            z.clone(),
            &[0.1, 0.2],
            1e-15,
            1,
        )
    });
    let message = result
        .err()
        .and_then(|e| e.downcast_ref::<String>().cloned())
        .unwrap_or_default();
    assert!(message.contains("2 rates for rows of 3"), "{message}");
}

#[test]
fn fused_adam_kernel_matches_the_plain_update_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    let device = Device::wgpu(DeviceKind::DefaultDevice);
    for (label, shape, lr, eps) in [
        ("one rate", [1000, 37], vec![7.5e-3], 1e-15),
        (
            "per column",
            [513, 6],
            (0..6).map(|k| 1e-3 * (k + 1) as f64).collect(),
            1e-15,
        ),
        ("decoder eps", [64, 5], vec![0.0016], 1e-8),
    ] {
        for (t, [plain, fused]) in run_both(&device, shape, &lr, eps).iter().enumerate() {
            for (name, (a, b)) in ["param", "exp_avg", "exp_avg_sq"]
                .iter()
                .zip(plain.iter().zip(fused))
            {
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    // Element-wise f32 ops; a GPU may contract a multiply-add or round sqrt and
                    // division differently by an ulp or two.
                    let tolerance = 8.0 * f32::EPSILON * x.abs().max(y.abs()) + 1e-6;
                    assert!(
                        (x - y).abs() <= tolerance,
                        "{label}: {name}[{i}] after step {}: plain {x:e}, kernel {y:e}",
                        t + 1
                    );
                }
            }
        }
    }
}
