//! `activate` (ReLU, sigmoid, tanh) against Burn's own activations it replaces: values and the
//! gradient of Σ w ⊙ act(x), bit for bit on ndarray (plain and autodiff; also the input's other
//! uses, a transposed view, a rank-3 tensor, and saturating inputs where e^−x overflows), and on
//! wgpu (lavapipe in CI; fails instead of skipping under ACAGS_REQUIRE_WGPU=1) within float
//! rounding, since the device compiles Burn's ops its own way.
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::activation::{Activation, activate};
use burn::tensor::{Device, DeviceKind, Tensor, TensorData, activation};
use cube_common::{cube_device, values};

const ALL: [Activation; 3] = [Activation::Relu, Activation::Sigmoid, Activation::Tanh];

fn burn_activation<const D: usize>(x: Tensor<D>, which: Activation) -> Tensor<D> {
    match which {
        Activation::Relu => activation::relu(x),
        Activation::Sigmoid => activation::sigmoid(x),
        Activation::Tanh => activation::tanh(x),
    }
}

/// Inputs spread over ±12 with exact zeros, plus values where e^−x overflows or underflows.
fn inputs(n: usize) -> Vec<f32> {
    let mut v: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 2003) as f32 / 83.0 - 12.0)
        .collect();
    for (i, extreme) in [0.0f32, -100.0, 100.0, -89.0, 89.0, 1e-30, -1e-30]
        .into_iter()
        .enumerate()
    {
        if i * 3 < n {
            v[i * 3] = extreme;
        }
    }
    v
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn assert_close(ours: &[f32], theirs: &[f32], what: &str) {
    assert_eq!(ours.len(), theirs.len(), "{what}");
    for (i, (a, b)) in ours.iter().zip(theirs).enumerate() {
        assert!(
            (a - b).abs() <= 2e-6 * (1.0 + b.abs()),
            "{what}: element {i}: {a} against Burn's {b}"
        );
    }
}

/// Values and gradients against Burn's, on `device`; `exact` compares bits.
fn check(device: &Device, label: &str, exact: bool) {
    let device = device.clone().autodiff();
    let compare = |ours: &[f32], theirs: &[f32], what: &str| {
        if exact {
            assert_eq!(bits(ours), bits(theirs), "{what}");
        } else {
            assert_close(ours, theirs, what);
        }
    };
    for which in ALL {
        for (rows, width) in [(1000usize, 24usize), (333, 7), (1, 5), (9000, 3)] {
            let what = format!("{label} {which:?} {rows}x{width}");
            let x = TensorData::new(inputs(rows * width), [rows, width]);
            let a = Tensor::<2>::from_data(x.clone(), &device).require_grad();
            let b = Tensor::<2>::from_data(x, &device).require_grad();
            // The input also feeds the loss directly, so the gradients add up in the parent.
            let ours = activate(a.clone(), which);
            let theirs = burn_activation(b.clone(), which);
            compare(&values(&ours), &values(&theirs), &what);
            let w: Vec<f32> = (0..rows * width).map(|i| (i % 9) as f32 * 0.37 - 1.3).collect();
            let w = Tensor::<2>::from_data(TensorData::new(w, [rows, width]), &device);
            let ga = a
                .grad(&((ours * w.clone()).sum() + a.clone().sum() * 0.5).backward())
                .unwrap();
            let gb = b
                .grad(&((theirs * w).sum() + b.clone().sum() * 0.5).backward())
                .unwrap();
            compare(&values(&ga), &values(&gb), &format!("{what} gradient"));
        }
        // A transposed (not contiguous) input and a rank-3 one.
        let t = Tensor::<2>::from_data(TensorData::new(inputs(40 * 9), [9, 40]), &device)
            .transpose();
        compare(
            &values(&activate(t.clone(), which)),
            &values(&burn_activation(t, which)),
            &format!("{label} {which:?} transposed"),
        );
        let t = Tensor::<3>::from_data(TensorData::new(inputs(4 * 5 * 6), [4, 5, 6]), &device);
        let ours = activate(t.clone(), which);
        assert_eq!(ours.dims(), [4, 5, 6], "{label} {which:?} rank 3");
        compare(
            &values(&ours),
            &values(&burn_activation(t, which)),
            &format!("{label} {which:?} rank 3"),
        );
    }
}

#[test]
fn activations_equal_burns_on_ndarray_to_the_bit() {
    check(&Device::ndarray(), "ndarray", true);
    // Without autodiff too.
    let device = Device::ndarray();
    for which in ALL {
        let x = Tensor::<2>::from_data(TensorData::new(inputs(600), [200, 3]), &device);
        assert_eq!(
            bits(&values(&activate(x.clone(), which))),
            bits(&values(&burn_activation(x, which))),
            "ndarray {which:?} plain"
        );
    }
}

#[test]
fn activations_equal_burns_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    check(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu", false);
}

/// The formulas themselves, against f64 references (Burn's could change under us).
#[test]
fn the_element_formulas_are_the_activations_and_their_derivatives() {
    for x in [-30.0f32, -3.0, -0.5, 0.0, 0.25, 2.0, 30.0] {
        let s = 1.0 / (1.0 + (-(x as f64)).exp());
        let y = Activation::Sigmoid.value(x);
        assert!((y as f64 - s).abs() < 1e-6, "sigmoid({x})");
        let d = Activation::Sigmoid.gradient(y, 2.0) as f64;
        assert!((d - 2.0 * s * (1.0 - s)).abs() < 1e-6, "sigmoid'({x})");
        let t = (x as f64).tanh();
        let y = Activation::Tanh.value(x);
        assert!((y as f64 - t).abs() < 1e-6, "tanh({x})");
        let d = Activation::Tanh.gradient(y, 2.0) as f64;
        assert!((d - 2.0 * (1.0 - t * t)).abs() < 1e-6, "tanh'({x})");
        let y = Activation::Relu.value(x);
        assert_eq!(y, x.max(0.0), "relu({x})");
        let d = Activation::Relu.gradient(y, 2.0);
        assert_eq!(d, if x > 0.0 { 2.0 } else { 0.0 }, "relu'({x})");
    }
}

/// Signed zeros, infinities, NaN and a subnormal: the same values and gradients as Burn's (a NaN
/// compared as NaN, its sign bit aside); an empty tensor keeps its shape.
#[test]
fn special_values_and_empty_tensors_behave_like_burns() {
    let device = Device::ndarray().autodiff();
    let special = vec![-0.0f32, 0.0, f32::INFINITY, f32::NEG_INFINITY, f32::NAN, 1e-45, -1e-45, 88.7, -88.7, 104.0];
    let n = special.len();
    let same = |a: &[f32], b: &[f32], what: &str| {
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x.is_nan() && y.is_nan()) || x.to_bits() == y.to_bits(),
                "{what}: element {i} (input {}): {x} against Burn's {y}",
                special[i]
            );
        }
    };
    for which in ALL {
        let a = Tensor::<1>::from_data(TensorData::new(special.clone(), [n]), &device).require_grad();
        let b = Tensor::<1>::from_data(TensorData::new(special.clone(), [n]), &device).require_grad();
        let ours = activate(a.clone(), which);
        let theirs = burn_activation(b.clone(), which);
        same(&values(&ours), &values(&theirs), &format!("{which:?}"));
        let ga = a.grad(&ours.sum().backward()).unwrap();
        let gb = b.grad(&theirs.sum().backward()).unwrap();
        same(&values(&ga), &values(&gb), &format!("{which:?} gradient"));
        let empty = Tensor::<2>::from_data(TensorData::new(Vec::<f32>::new(), [0, 3]), &device);
        assert_eq!(activate(empty, which).dims(), [0, 3], "{which:?} empty");
    }
}
