//! The fused Gaussian-bits op against the plain-tensor estimate it replaces (as
//! `acags::codec::rate::gaussian_bits` wrote it before, erf in f64): the forward within the
//! bound the f32 erf's error allows, the f32 erf against libm's f64 one, the gradients (x, mean,
//! scale; none for the noise) close to autodiff's through the plain ops and to central finite
//! differences, and the wgpu kernels close to the CPU twin (lavapipe in CI;
//! fails instead of skipping under ACAGS_REQUIRE_WGPU=1).
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::gaussian_bits::{erf, gaussian_bits};
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use cube_common::{cube_device, values};
use rand::{Rng, SeedableRng, rngs::StdRng};

const MIN_SCALE: f32 = 0.01;

fn plain_bits(x: Tensor<2>, mean: Tensor<2>, scale: Tensor<2>, noise: Tensor<2>) -> Tensor<2> {
    let rounded_mean = mean.clone() + (mean.clone().round() - mean).detach();
    let sigma = scale.abs().clamp_min(MIN_SCALE);
    let y = x - rounded_mean + noise;
    let z = std::f32::consts::FRAC_1_SQRT_2;
    let upper = ((y.clone() + 0.5) / sigma.clone() * z).erf();
    let lower = ((y - 0.5) / sigma * z).erf();
    let p = (upper - lower) * 0.5;
    (p + 1e-5).log() * (-std::f32::consts::LOG2_E)
}

struct Inputs {
    x: Vec<f32>,
    mean: Vec<f32>,
    scale: Vec<f32>,
    noise: Vec<f32>,
    shape: [usize; 2],
}

/// Index-unit values as the rate sees them: x and μ a few steps apart, σ from below the floor
/// (and negative, and zero) to wide, half-integer means (the rounding tie).
fn inputs(seed: u64, shape: [usize; 2]) -> Inputs {
    let mut rng = StdRng::seed_from_u64(seed);
    let n = shape[0] * shape[1];
    let mut draw =
        |f: &mut dyn FnMut(&mut StdRng) -> f32| (0..n).map(|_| f(&mut rng)).collect::<Vec<_>>();
    let x = draw(&mut |r| r.random_range(-20f32..20.0));
    let mean = draw(&mut |r| match r.random_range(0..6) {
        0 => r.random_range(-10i32..10) as f32 + 0.5,
        _ => r.random_range(-20f32..20.0),
    });
    let scale = draw(&mut |r| match r.random_range(0..8) {
        0 => 0.0,
        1 => r.random_range(-0.02f32..0.02),
        2 => -r.random_range(0.01f32..5.0),
        _ => r.random_range(0.01f32..8.0),
    });
    let noise = draw(&mut |r| r.random::<f32>() - 0.5);
    Inputs {
        x,
        mean,
        scale,
        noise,
        shape,
    }
}

fn tensors(i: &Inputs, device: &Device, track: bool) -> [Tensor<2>; 4] {
    let t = |v: &Vec<f32>| Tensor::<2>::from_data(TensorData::new(v.clone(), i.shape), device);
    let [x, mean, scale, noise] = [&i.x, &i.mean, &i.scale, &i.noise].map(t);
    if track {
        [
            x.require_grad(),
            mean.require_grad(),
            scale.require_grad(),
            noise,
        ]
    } else {
        [x, mean, scale, noise]
    }
}

/// Gradients of Σ w·bits with respect to x, mean and scale, and the bits.
fn with_gradients(
    i: &Inputs,
    device: &Device,
    weights: &[f32],
    bits: fn(Tensor<2>, Tensor<2>, Tensor<2>, Tensor<2>) -> Tensor<2>,
) -> [Vec<f32>; 4] {
    let [x, mean, scale, noise] = tensors(i, device, true);
    let out = bits(x.clone(), mean.clone(), scale.clone(), noise);
    let w = Tensor::<2>::from_data(TensorData::new(weights.to_vec(), i.shape), device);
    let grads = (out.clone() * w).sum().backward();
    let grad = |t: &Tensor<2>| values(&t.grad(&grads).expect("a gradient"));
    [values(&out), grad(&x), grad(&mean), grad(&scale)]
}

fn fused(x: Tensor<2>, mean: Tensor<2>, scale: Tensor<2>, noise: Tensor<2>) -> Tensor<2> {
    gaussian_bits(x, mean, scale, noise, MIN_SCALE)
}

fn assert_close(label: &str, got: &[f32], want: &[f32], rtol: f32, atol: f32) {
    let mut worst = (0.0f32, 0usize);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let excess = (g - w).abs() - (atol + rtol * w.abs());
        if excess > worst.0 {
            worst = (excess, i);
        }
    }
    let i = worst.1;
    assert!(
        worst.0 <= 0.0,
        "{label}[{i}]: got {}, want {}",
        got[i],
        want[i]
    );
}

#[test]
fn forward_and_gradients_agree_with_the_plain_estimate() {
    let i = inputs(1, [200, 33]);
    let n = i.x.len();
    let mut rng = StdRng::seed_from_u64(2);
    let weights: Vec<f32> = (0..n).map(|_| rng.random_range(0.1f32..2.0)).collect();
    let device = Device::ndarray().autodiff();
    let [bits_p, gx_p, gm_p, gs_p] = with_gradients(&i, &device, &weights, plain_bits);
    let [bits_f, gx_f, gm_f, gs_f] = with_gradients(&i, &device, &weights, fused);
    // erf to 6e-7 (see the erf test): P moves by ≤ 6e-7 and −log2(P + 1e-5) by
    // ≤ log2(e)·6e-7/(P + 1e-5), with P + 1e-5 = 2^−bits.
    let mut worst_at_floor = 0.0f32;
    for (k, (a, b)) in bits_f.iter().zip(&bits_p).enumerate() {
        let allowed = std::f32::consts::LOG2_E * 6e-7 * b.exp2() + 2e-6 * (1.0 + b.abs());
        assert!(
            (a - b).abs() <= allowed,
            "bits[{k}]: fused {a}, plain {b} (allowed {allowed})"
        );
        if *b > 16.0 {
            worst_at_floor = worst_at_floor.max((a - b).abs());
        }
    }
    assert!(worst_at_floor < 0.05, "{worst_at_floor} bits at the floor");
    // The plain backward runs in f32 through ~20 ops from the f64 erf; both gradients scale
    // with 1/(P + 1e-5), which the f32 erf moves by a relative 6e-7/(P + 1e-5) = 6e-7·2^bits.
    for (label, got, want) in [
        ("d/dx", &gx_f, &gx_p),
        ("d/dmean", &gm_f, &gm_p),
        ("d/dscale", &gs_f, &gs_p),
    ] {
        for k in 0..n {
            let rtol = 2e-3 + 6e-7 * bits_p[k].exp2();
            assert!(
                (got[k] - want[k]).abs() <= 1e-4 + rtol * want[k].abs(),
                "{label}[{k}]: fused {}, plain {} (bits {})",
                got[k],
                want[k],
                bits_p[k]
            );
        }
    }
    // Clamped scales (|scale| < MIN_SCALE) get no gradient; the straight-through mean gets −d/dx.
    for k in 0..n {
        if i.scale[k].abs() < MIN_SCALE {
            assert_eq!(gs_f[k], 0.0, "scale[{k}] = {} is clamped", i.scale[k]);
        }
        assert_eq!(gm_f[k], -gx_f[k]);
    }
    // Without autodiff the same forward.
    let [x, mean, scale, noise] = tensors(&i, &Device::ndarray(), false);
    assert_eq!(values(&fused(x, mean, scale, noise)), bits_f);
}

#[test]
fn the_f32_erf_is_within_its_bound_of_the_f64_one() {
    // Abramowitz & Stegun 7.1.26: |error| ≤ 1.5e-7 in exact arithmetic; in f32, 1 − t·poly·e^{−x²}
    // cancels near 0 (5.8e-7 measured at x = 0.035, where erf ≈ 0.04).
    let mut worst = 0.0f64;
    for k in -80_000..=80_000 {
        let x = k as f32 * 1e-4;
        let got = erf(x) as f64;
        let want = libm::erf(x as f64);
        worst = worst.max((got - want).abs());
        assert!((got - want).abs() <= 6e-7, "erf({x}): {got} vs {want}");
        // Odd, except at ±0 (both take the positive branch, erf(0) ≈ 1e-7 there).
        if k != 0 {
            assert_eq!(erf(-x), -erf(x));
        }
    }
    // The bound is not loose by orders of magnitude: this is the formula, not a better one.
    assert!(worst > 1.5e-7, "worst error {worst}");
    assert_eq!(erf(f32::INFINITY), 1.0);
}

#[test]
fn gradients_match_finite_differences() {
    // Away from the clamp and the rounding ties, where the estimate is smooth.
    let mut i = inputs(3, [16, 8]);
    // x within two σ of the mean: in the far tails the f32 forward is flat (P rounds to 0)
    // while its derivative is not.
    let mut rng = StdRng::seed_from_u64(5);
    for k in 0..i.x.len() {
        i.mean[k] = i.mean[k].round();
        i.scale[k] = i.scale[k].abs().max(0.3);
        i.x[k] = i.mean[k] + rng.random_range(-2.0f32..2.0) * i.scale[k];
    }
    let n = i.x.len();
    let device = Device::ndarray().autodiff();
    let ones = vec![1.0f32; n];
    let [_, gx, _, gs] = with_gradients(&i, &device, &ones, fused);
    let bits_at = |i: &Inputs| {
        let [x, mean, scale, noise] = tensors(i, &Device::ndarray(), false);
        values(&fused(x, mean, scale, noise))
    };
    let h = 1e-2f32;
    for k in 0..n {
        for (name, analytic, field) in [("x", gx[k], 0), ("scale", gs[k], 1)] {
            let shifted = |d: f32| {
                let mut j = Inputs {
                    x: i.x.clone(),
                    mean: i.mean.clone(),
                    scale: i.scale.clone(),
                    noise: i.noise.clone(),
                    shape: i.shape,
                };
                if field == 0 {
                    j.x[k] += d
                } else {
                    j.scale[k] += d
                }
                bits_at(&j)[k] as f64
            };
            let numeric = ((shifted(h) - shifted(-h)) / (2.0 * h as f64)) as f32;
            assert!(
                (numeric - analytic).abs() <= 2e-2 * numeric.abs().max(1.0),
                "d bits[{k}] / d {name}: analytic {analytic}, finite difference {numeric}"
            );
        }
    }
}

#[test]
fn the_wgpu_kernels_match_the_cpu_twin() {
    if cube_device().is_none() {
        return;
    }
    let i = inputs(4, [513, 19]);
    let weights: Vec<f32> = (0..i.x.len())
        .map(|k| 0.5 + (k % 7) as f32 * 0.25)
        .collect();
    let cpu = with_gradients(&i, &Device::ndarray().autodiff(), &weights, fused);
    let gpu = with_gradients(
        &i,
        &Device::wgpu(DeviceKind::DefaultDevice).autodiff(),
        &weights,
        fused,
    );
    // The same erf formula on both; the device's exp differs from the host's by ulps.
    assert_close("bits", &gpu[0], &cpu[0], 1e-4, 1e-4);
    for (label, k) in [("d/dx", 1), ("d/dmean", 2), ("d/dscale", 3)] {
        assert_close(label, &gpu[k], &cpu[k], 1e-2, 1e-3);
    }
}
