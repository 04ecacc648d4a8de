//! `linear` against a host reference in f64: the values and the gradients with respect to x,
//! the weight and the bias of Σ c ⊙ linear(x, W, b) (∂x = c·Wᵀ, ∂W = xᵀ·c, ∂b = Σ_rows c), on
//! ndarray (plain and autodiff) and on wgpu (lavapipe in CI; fails instead of skipping under
//! ACAGS_REQUIRE_WGPU=1), within f32 rounding of the sums. Shapes: the decoders' (24-48
//! inputs, 5-35 outputs), a row count that is not a multiple of the CPU twin's chunk, one row,
//! and a non-contiguous input (a transposed view). Only the tracked operands get a gradient.
//! (The reference is not Burn's `x.matmul(w) + b` on wgpu: its fused matmul autotune hung on
//! lavapipe in this test, in CubeCL's tuner; the training test runs this op on wgpu.)
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::linear::linear;
use burn::tensor::{Device, DeviceKind, Tensor, TensorData};
use cube_common::{cube_device, values};

fn host_table(rows: usize, width: usize, seed: usize) -> Vec<f32> {
    (0..rows * width)
        .map(|i| (((i + seed) * 7919) % 1009) as f32 / 400.0 - 1.26)
        .collect()
}

fn table(rows: usize, width: usize, seed: usize, device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(
        TensorData::new(host_table(rows, width, seed), [rows, width]),
        device,
    )
}

/// Σ_k a[k]·b[k] in f64, and the bound on an f32 sum of those terms: n · 2⁻²⁴ of their
/// absolute sum.
fn dot(terms: impl Iterator<Item = (f32, f32)>) -> (f64, f64) {
    let (mut sum, mut size, mut n) = (0.0f64, 0.0f64, 0usize);
    for (a, b) in terms {
        let t = a as f64 * b as f64;
        sum += t;
        size += t.abs();
        n += 1;
    }
    (sum, (n as f64 + 1.0) * 6e-8 * size + 1e-9)
}

fn assert_close(got: &[f32], want: &[(f64, f64)], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (&a, &(e, bound))) in got.iter().zip(want).enumerate() {
        assert!(
            (a as f64 - e).abs() <= bound,
            "{what}: element {i}: {a} vs {e} (bound {bound})"
        );
    }
}

/// The decoders' shapes, a chunk-and-a-bit, one row.
const SHAPES: [(usize, usize, usize); 4] = [(1000, 40, 24), (1000, 24, 35), (257, 48, 5), (1, 32, 15)];

fn check(device: &Device, label: &str, shapes: &[(usize, usize, usize)]) {
    let device = device.clone().autodiff();
    for &(rows, input, output) in shapes {
        let what = format!("{label} {rows}x{input}->{output}");
        let (hx, hw, hb, hc) = (
            host_table(rows, input, 1),
            host_table(input, output, 2),
            host_table(1, output, 3),
            host_table(rows, output, 4),
        );
        let x = table(rows, input, 1, &device).require_grad();
        let w = table(input, output, 2, &device).require_grad();
        let b = table(1, output, 3, &device).reshape([output]).require_grad();
        let c = table(rows, output, 4, &device);
        let y = linear(x.clone(), w.clone(), b.clone());
        assert_eq!(y.dims(), [rows, output], "{what}");
        let want_y: Vec<(f64, f64)> = (0..rows * output)
            .map(|k| {
                let (r, o) = (k / output, k % output);
                let (s, bound) = dot(
                    (0..input)
                        .map(|i| (hx[r * input + i], hw[i * output + o]))
                        .chain([(hb[o], 1.0)]),
                );
                (s, bound)
            })
            .collect();
        assert_close(&values(&y), &want_y, &format!("{what}: values"));
        let g = (y * c).sum().backward();
        let want_dx: Vec<(f64, f64)> = (0..rows * input)
            .map(|k| {
                let (r, i) = (k / input, k % input);
                dot((0..output).map(|o| (hc[r * output + o], hw[i * output + o])))
            })
            .collect();
        let want_dw: Vec<(f64, f64)> = (0..input * output)
            .map(|k| {
                let (i, o) = (k / output, k % output);
                dot((0..rows).map(|r| (hx[r * input + i], hc[r * output + o])))
            })
            .collect();
        let want_db: Vec<(f64, f64)> = (0..output)
            .map(|o| dot((0..rows).map(|r| (hc[r * output + o], 1.0))))
            .collect();
        assert_close(&values(&x.grad(&g).unwrap()), &want_dx, &format!("{what}: ∂x"));
        assert_close(&values(&w.grad(&g).unwrap()), &want_dw, &format!("{what}: ∂weight"));
        assert_close(&values(&b.grad(&g).unwrap()), &want_db, &format!("{what}: ∂bias"));
    }

    // A transposed (non-contiguous) input that is not tracked: the parameters still get their
    // gradients.
    let hx = host_table(30, 200, 5); // [30, 200], used as its transpose [200, 30]
    let (hw, hb) = (host_table(30, 7, 6), host_table(1, 7, 7));
    let x = table(30, 200, 5, &device).transpose();
    let w = table(30, 7, 6, &device).require_grad();
    let b = table(1, 7, 7, &device).reshape([7]).require_grad();
    let y = linear(x, w.clone(), b.clone());
    let want: Vec<(f64, f64)> = (0..200 * 7)
        .map(|k| {
            let (r, o) = (k / 7, k % 7);
            dot((0..30)
                .map(|i| (hx[i * 200 + r], hw[i * 7 + o]))
                .chain([(hb[o], 1.0)]))
        })
        .collect();
    assert_close(&values(&y), &want, &format!("{label} transposed input"));
    let g = y.sum().backward();
    assert!(w.grad(&g).is_some() && b.grad(&g).is_some(), "{label}");
}

#[test]
fn linear_matches_matmul_plus_bias_on_ndarray() {
    check(&Device::ndarray(), "ndarray", &SHAPES);
}

#[test]
fn linear_matches_matmul_plus_bias_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    // Two shapes: every new shape autotunes Burn's matmul on the device (a minute on lavapipe).
    check(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu", &SHAPES[1..3]);
}

#[test]
#[should_panic(expected = "the input has 3 columns, the weight 5 rows")]
fn an_input_the_weight_does_not_fit_is_refused() {
    let device = Device::ndarray();
    let _ = linear(
        table(4, 3, 0, &device),
        table(5, 2, 0, &device),
        Tensor::<1>::zeros([2], &device),
    );
}

#[test]
#[should_panic(expected = "the bias must be [2]")]
fn a_bias_of_another_width_is_refused() {
    let device = Device::ndarray();
    let _ = linear(
        table(4, 3, 0, &device),
        table(3, 2, 0, &device),
        Tensor::<1>::zeros([3], &device),
    );
}
