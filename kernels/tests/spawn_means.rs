//! `spawn_means` against the plain-tensor composition it replaces (spec §4.4's
//! μ = a + g·m[0:3] + R(normalize(0.1·g·m[3:7] + (1, 0, 0, 0)))·(o ⊙ s[0:3]) with Burn's matmul):
//! values and the gradients of all five inputs within float rounding, on ndarray and on wgpu
//! (lavapipe in CI; fails instead of skipping under ACAGS_REQUIRE_WGPU=1), for K = 1, 5 and 10,
//! closed gates, large turns and a transposed input; and a finite-difference check of the
//! gradients on a few anchors, independent of both.
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::spawn_means::spawn_means;
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use cube_common::{cube_device, values};

/// A deterministic spread of values in [lo, hi).
fn spread(n: usize, seed: usize, lo: f32, hi: f32) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let h = (i.wrapping_mul(2_654_435_761) ^ seed.wrapping_mul(40_503)) % 10_007;
            lo + (hi - lo) * h as f32 / 10_007.0
        })
        .collect()
}

struct Inputs {
    anchors: Vec<f32>,
    offsets: Vec<f32>,
    scales: Vec<f32>,
    motion: Vec<f32>,
    gate: Vec<f32>,
}

fn inputs(m: usize, k: usize) -> Inputs {
    let mut gate = spread(m, 5, 0.0, 1.0);
    // Closed and fully open gates.
    for i in (0..m).step_by(7) {
        gate[i] = 0.0;
    }
    for i in (3..m).step_by(11) {
        gate[i] = 1.0;
    }
    Inputs {
        anchors: spread(m * 3, 1, -3.0, 3.0),
        offsets: spread(m * k * 3, 2, -1.5, 1.5),
        scales: spread(m * 6, 3, 0.01, 0.8),
        // Quaternion deltas up to ±8 (0.1·8 = 0.8 against the identity's 1: turns of ~80°).
        motion: spread(m * 7, 4, -8.0, 8.0),
        gate,
    }
}

/// The plain-tensor version (the spawn of acags before the op).
fn reference(
    anchors: Tensor<2>,
    offsets: Tensor<3>,
    scales: Tensor<2>,
    motion: Tensor<2>,
    gate: Tensor<1>,
) -> Tensor<2> {
    let [m, k, _] = offsets.dims();
    let motion = motion * gate.reshape([m, 1]);
    let translation = motion.clone().slice([0..m, 0..3]);
    let q = motion.slice([0..m, 3..7]) * 0.1;
    let q = Tensor::cat(
        vec![q.clone().slice([0..m, 0..1]) + 1.0, q.slice([0..m, 1..4])],
        1,
    );
    let norm = (q.clone() * q.clone()).sum_dim(1).sqrt().clamp_min(1e-12);
    let q = q / norm;
    let c = |i: usize| q.clone().slice([0..m, i..i + 1]).reshape([m]);
    let (w, x, y, z) = (c(0), c(1), c(2), c(3));
    let two = |a: Tensor<1>, b: Tensor<1>| a * b * 2.0;
    let r = Tensor::stack::<2>(
        vec![
            -(two(y.clone(), y.clone()) + two(z.clone(), z.clone())) + 1.0,
            two(x.clone(), y.clone()) - two(w.clone(), z.clone()),
            two(x.clone(), z.clone()) + two(w.clone(), y.clone()),
            two(x.clone(), y.clone()) + two(w.clone(), z.clone()),
            -(two(x.clone(), x.clone()) + two(z.clone(), z.clone())) + 1.0,
            two(y.clone(), z.clone()) - two(w.clone(), x.clone()),
            two(x.clone(), z.clone()) - two(w.clone(), y.clone()),
            two(y.clone(), z.clone()) + two(w.clone(), x.clone()),
            -(two(x.clone(), x) + two(y.clone(), y)) + 1.0,
        ],
        1,
    )
    .reshape([m, 3, 3]);
    let local = (offsets * scales.slice([0..m, 0..3]).reshape([m, 1, 3])).swap_dims(1, 2);
    let rotated = r.matmul(local).swap_dims(1, 2);
    (rotated + (anchors + translation).reshape([m, 1, 3])).reshape([m * k, 3])
}

fn assert_close(ours: &[f32], theirs: &[f32], tolerance: f32, what: &str) {
    assert_eq!(ours.len(), theirs.len(), "{what}: lengths");
    for (i, (a, b)) in ours.iter().zip(theirs).enumerate() {
        assert!(
            a.is_finite() && (a - b).abs() <= tolerance * (1.0 + b.abs()),
            "{what}: element {i}: {a} against the tensor version's {b}"
        );
    }
}

/// Values and the gradients of Σ w ⊙ μ (plus the inputs' other use in the loss) against the
/// tensor version on `device`.
fn check(device: &Device, label: &str) {
    let device = device.clone().autodiff();
    for (m, k) in [(300usize, 5usize), (97, 10), (64, 1), (1, 5)] {
        let what = format!("{label} M={m} K={k}");
        let inp = inputs(m, k);
        let make = || {
            (
                Tensor::<2>::from_data(TensorData::new(inp.anchors.clone(), [m, 3]), &device)
                    .require_grad(),
                Tensor::<3>::from_data(TensorData::new(inp.offsets.clone(), [m, k, 3]), &device)
                    .require_grad(),
                Tensor::<2>::from_data(TensorData::new(inp.scales.clone(), [m, 6]), &device)
                    .require_grad(),
                Tensor::<2>::from_data(TensorData::new(inp.motion.clone(), [m, 7]), &device)
                    .require_grad(),
                Tensor::<1>::from_data(TensorData::new(inp.gate.clone(), [m]), &device)
                    .require_grad(),
            )
        };
        let w = Tensor::<2>::from_data(
            TensorData::new(spread(m * k * 3, 9, -1.0, 1.0), [m * k, 3]),
            &device,
        );
        let mut grads = Vec::new();
        let mut outs = Vec::new();
        for fused in [true, false] {
            let (a, o, s, mo, g) = make();
            let means = if fused {
                spawn_means(a.clone(), o.clone(), s.clone(), mo.clone(), g.clone())
            } else {
                reference(a.clone(), o.clone(), s.clone(), mo.clone(), g.clone())
            };
            assert_eq!(means.dims(), [m * k, 3], "{what}: shape");
            outs.push(values(&means));
            // The scales also feed the loss through their Gaussian half: the op's zero gradient
            // there must add to it, not replace it.
            let loss = (means * w.clone()).sum() + s.clone().slice([0..m, 3..6]).sum() * 0.25;
            let gr = loss.backward();
            grads.push([
                values(&a.grad(&gr).unwrap()),
                values(&o.grad(&gr).unwrap()),
                values(&s.grad(&gr).unwrap()),
                values(&mo.grad(&gr).unwrap()),
                values(&g.grad(&gr).unwrap()),
            ]);
        }
        assert_close(&outs[0], &outs[1], 2e-6, &what);
        for (j, name) in ["anchors", "offsets", "scales", "motion", "gate"]
            .into_iter()
            .enumerate()
        {
            // Sums over K slots of products: a few more roundings than the values.
            assert_close(
                &grads[0][j],
                &grads[1][j],
                2e-5,
                &format!("{what}: gradient of {name}"),
            );
        }
    }
    // A transposed (not contiguous) anchor input.
    let inp = inputs(40, 5);
    let anchors_t =
        Tensor::<2>::from_data(TensorData::new(inp.anchors.clone(), [3, 40]), &device).transpose();
    let t = |v: &Vec<f32>, s: [usize; 2]| {
        Tensor::<2>::from_data(TensorData::new(v.clone(), s), &device)
    };
    let offsets = Tensor::<3>::from_data(TensorData::new(inp.offsets.clone(), [40, 5, 3]), &device);
    let gate = Tensor::<1>::from_data(TensorData::new(inp.gate.clone(), [40]), &device);
    assert_close(
        &values(&spawn_means(
            anchors_t.clone(),
            offsets.clone(),
            t(&inp.scales, [40, 6]),
            t(&inp.motion, [40, 7]),
            gate.clone(),
        )),
        &values(&reference(
            anchors_t,
            offsets,
            t(&inp.scales, [40, 6]),
            t(&inp.motion, [40, 7]),
            gate,
        )),
        2e-6,
        &format!("{label} transposed anchors"),
    );
}

#[test]
fn spawn_means_equals_the_tensor_version_on_ndarray() {
    check(&Device::ndarray(), "ndarray");
    // Without autodiff, and with no anchors.
    let device = Device::ndarray();
    let inp = inputs(10, 5);
    let means = spawn_means(
        Tensor::<2>::from_data(TensorData::new(inp.anchors, [10, 3]), &device),
        Tensor::<3>::from_data(TensorData::new(inp.offsets, [10, 5, 3]), &device),
        Tensor::<2>::from_data(TensorData::new(inp.scales, [10, 6]), &device),
        Tensor::<2>::from_data(TensorData::new(inp.motion, [10, 7]), &device),
        Tensor::<1>::from_data(TensorData::new(inp.gate, [10]), &device),
    );
    assert_eq!(means.dims(), [50, 3]);
    let empty =
        |s: Vec<usize>| Tensor::<2>::from_data(TensorData::new(Vec::<f32>::new(), s), &device);
    let none = spawn_means(
        empty(vec![0, 3]),
        Tensor::<3>::from_data(TensorData::new(Vec::<f32>::new(), [0, 5, 3]), &device),
        empty(vec![0, 6]),
        empty(vec![0, 7]),
        Tensor::<1>::from_data(TensorData::new(Vec::<f32>::new(), [0]), &device),
    );
    assert_eq!(none.dims(), [0, 3]);
}

#[test]
fn spawn_means_equals_the_tensor_version_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    check(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu");
}

/// Central differences in f64 of the op's own forward (through the same formula written out
/// here), against its analytic gradients: independent of Burn's autodiff.
#[test]
fn spawn_means_gradients_match_finite_differences() {
    let (m, k) = (6usize, 4usize);
    let inp = inputs(m, k);
    let w = spread(m * k * 3, 9, -1.0, 1.0);
    // The loss Σ w ⊙ μ in f64.
    let loss = |a: &[f32], o: &[f32], s: &[f32], mo: &[f32], g: &[f32]| -> f64 {
        let mut total = 0.0f64;
        for i in 0..m {
            let gi = g[i] as f64;
            let q: Vec<f64> = (0..4)
                .map(|j| mo[i * 7 + 3 + j] as f64 * gi * 0.1 + if j == 0 { 1.0 } else { 0.0 })
                .collect();
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            let (qw, x, y, z) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
            let r = [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - qw * z),
                2.0 * (x * z + qw * y),
                2.0 * (x * y + qw * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - qw * x),
                2.0 * (x * z - qw * y),
                2.0 * (y * z + qw * x),
                1.0 - 2.0 * (x * x + y * y),
            ];
            for kk in 0..k {
                let l: Vec<f64> = (0..3)
                    .map(|c| o[(i * k + kk) * 3 + c] as f64 * s[i * 6 + c] as f64)
                    .collect();
                for row in 0..3 {
                    let mu = a[i * 3 + row] as f64
                        + mo[i * 7 + row] as f64 * gi
                        + r[row * 3] * l[0]
                        + r[row * 3 + 1] * l[1]
                        + r[row * 3 + 2] * l[2];
                    total += w[(i * k + kk) * 3 + row] as f64 * mu;
                }
            }
        }
        total
    };
    let device = Device::ndarray().autodiff();
    let tensor2 = |v: &Vec<f32>, s: [usize; 2]| {
        Tensor::<2>::from_data(TensorData::new(v.clone(), s), &device).require_grad()
    };
    let (a, s, mo) = (
        tensor2(&inp.anchors, [m, 3]),
        tensor2(&inp.scales, [m, 6]),
        tensor2(&inp.motion, [m, 7]),
    );
    let o = Tensor::<3>::from_data(TensorData::new(inp.offsets.clone(), [m, k, 3]), &device)
        .require_grad();
    let g = Tensor::<1>::from_data(TensorData::new(inp.gate.clone(), [m]), &device).require_grad();
    let wt = Tensor::<2>::from_data(TensorData::new(w.clone(), [m * k, 3]), &device);
    let gr = (spawn_means(a.clone(), o.clone(), s.clone(), mo.clone(), g.clone()) * wt)
        .sum()
        .backward();
    let analytic = [
        values(&a.grad(&gr).unwrap()),
        values(&o.grad(&gr).unwrap()),
        values(&s.grad(&gr).unwrap()),
        values(&mo.grad(&gr).unwrap()),
        values(&g.grad(&gr).unwrap()),
    ];
    let base = [
        inp.anchors.clone(),
        inp.offsets.clone(),
        inp.scales.clone(),
        inp.motion.clone(),
        inp.gate.clone(),
    ];
    let h = 1e-3f32;
    for (which, name) in ["anchors", "offsets", "scales", "motion", "gate"]
        .into_iter()
        .enumerate()
    {
        for e in 0..base[which].len() {
            let eval = |delta: f32| {
                let mut v = base.clone();
                v[which][e] += delta;
                loss(&v[0], &v[1], &v[2], &v[3], &v[4])
            };
            let numeric = (eval(h) - eval(-h)) / (2.0 * h as f64);
            let got = analytic[which][e] as f64;
            assert!(
                (got - numeric).abs() <= 2e-3 * (1.0 + numeric.abs()),
                "{name}[{e}]: analytic {got} against central difference {numeric}"
            );
        }
    }
}
