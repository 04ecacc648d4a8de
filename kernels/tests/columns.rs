//! `slice_columns` against Burn's `slice` it replaces: the values and the gradient bit for bit on
//! ndarray (plain and autodiff) and on wgpu (lavapipe in CI; fails instead of skipping under
//! ACAGS_REQUIRE_WGPU=1), for a column range at the start, in the middle, at the end, empty and
//! whole (and the shape of an empty one), and for a table that is not contiguous (a transposed view);
//! `concat_columns` against Burn's `cat` along columns the same way, including one tensor on both
//! sides (its two gradients summed) and an empty side.
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::columns::{concat_columns, slice_columns};
use burn::tensor::{Device, DeviceKind, Tensor, TensorData, s};
use cube_common::{cube_device, values};

fn table(rows: usize, width: usize, device: &Device) -> Tensor<2> {
    let v: Vec<f32> = (0..rows * width)
        .map(|i| ((i * 7919) % 1009) as f32 / 37.0 - 13.0)
        .collect();
    Tensor::<2>::from_data(TensorData::new(v, [rows, width]), device)
}

/// Forward values and the gradient of Σ w ⊙ slice against Burn's slice, on `device`.
fn check(device: &Device, label: &str) {
    let device = device.clone().autodiff();
    for (rows, width, range) in [
        (1000usize, 7usize, 0..3usize),
        (1000, 7, 3..7),
        (333, 10, 4..5),
        (5, 4, 0..4),
        (1, 30, 27..30),
    ] {
        let a = table(rows, width, &device).require_grad();
        let b = table(rows, width, &device).require_grad();
        let ours = slice_columns(a.clone(), range.clone());
        let theirs = b.clone().slice(s![.., range.clone()]);
        assert_eq!(
            ours.dims(),
            theirs.dims(),
            "{label} {rows}x{width} {range:?}"
        );
        assert_eq!(
            values(&ours),
            values(&theirs),
            "{label} {rows}x{width} {range:?}"
        );
        let w = range.len();
        let weights: Vec<f32> = (0..rows * w).map(|i| (i % 5) as f32 - 2.0).collect();
        let weights = Tensor::<2>::from_data(TensorData::new(weights, [rows, w]), &device);
        let ga = a.grad(&(ours * weights.clone()).sum().backward()).unwrap();
        let gb = b.grad(&(theirs * weights).sum().backward()).unwrap();
        assert_eq!(
            values(&ga),
            values(&gb),
            "{label} gradient {rows}x{width} {range:?}"
        );
    }
    // An empty range (forward only: a sum over nothing has no graph to run backward on).
    let t = table(6, 3, &device);
    assert_eq!(
        slice_columns(t.clone(), 2..2).dims(),
        [6, 0],
        "{label} empty"
    );
    // Not contiguous: columns of a transposed table.
    let t = table(9, 40, &device).transpose(); // [40, 9]
    assert_eq!(
        values(&slice_columns(t.clone(), 2..6)),
        values(&t.slice(s![.., 2..6])),
        "{label} transposed"
    );
}

#[test]
fn slice_columns_equals_burn_slice_on_ndarray() {
    check(&Device::ndarray(), "ndarray");
}

#[test]
fn slice_columns_equals_burn_slice_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    check(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu");
}

#[test]
#[should_panic(expected = "outside")]
fn a_range_past_the_width_is_refused() {
    let _ = slice_columns(table(4, 3, &Device::ndarray()), 1..4);
}

/// Forward values and the gradients of Σ w ⊙ concat against Burn's `cat` along columns.
fn check_concat(device: &Device, label: &str) {
    let device = device.clone().autodiff();
    for (rows, a_width, b_width) in [
        (1000usize, 48usize, 8usize),
        (333, 3, 4),
        (7, 1, 1),
        (5, 0, 3),
    ] {
        let (a1, b1) = (
            table(rows, a_width, &device),
            table(rows, b_width, &device).mul_scalar(0.5),
        );
        let (a1, b1) = (a1.require_grad(), b1.require_grad());
        let (a2, b2) = (
            a1.clone().detach().require_grad(),
            b1.clone().detach().require_grad(),
        );
        // Through a product, so the gradients depend on where each column went.
        let ours = concat_columns(a1.clone() * 1.5, b1.clone());
        let theirs = Tensor::cat(vec![a2.clone() * 1.5, b2.clone()], 1);
        let what = format!("{label} {rows}x({a_width}+{b_width})");
        assert_eq!(ours.dims(), [rows, a_width + b_width], "{what}");
        assert_eq!(values(&ours), values(&theirs), "{what}");
        let width = a_width + b_width;
        let weights: Vec<f32> = (0..rows * width).map(|i| (i % 7) as f32 - 3.25).collect();
        let weights = Tensor::<2>::from_data(TensorData::new(weights, [rows, width]), &device);
        let g1 = (ours * weights.clone()).sum().backward();
        let g2 = (theirs * weights).sum().backward();
        if a_width > 0 {
            assert_eq!(
                values(&a1.grad(&g1).unwrap()),
                values(&a2.grad(&g2).unwrap()),
                "{what} left"
            );
        }
        assert_eq!(
            values(&b1.grad(&g1).unwrap()),
            values(&b2.grad(&g2).unwrap()),
            "{what} right"
        );
    }
    // One tensor on both sides: its gradient is the sum of the two halves'.
    let a1 = table(300, 5, &device).require_grad();
    let a2 = a1.clone().detach().require_grad();
    let weights = Tensor::<2>::from_data(
        TensorData::new(
            (0..3000)
                .map(|i| (i % 11) as f32 * 0.3 - 1.0)
                .collect::<Vec<f32>>(),
            [300, 10],
        ),
        &device,
    );
    let g1 = (concat_columns(a1.clone(), a1.clone() * 2.0) * weights.clone())
        .sum()
        .backward();
    let g2 = (Tensor::cat(vec![a2.clone(), a2.clone() * 2.0], 1) * weights)
        .sum()
        .backward();
    assert_eq!(
        values(&a1.grad(&g1).unwrap()),
        values(&a2.grad(&g2).unwrap()),
        "{label} both sides"
    );
    // Not contiguous: a transposed table on the left.
    let t = table(9, 40, &device).transpose(); // [40, 9]
    let r = table(40, 2, &device);
    assert_eq!(
        values(&concat_columns(t.clone(), r.clone())),
        values(&Tensor::cat(vec![t, r], 1)),
        "{label} transposed"
    );
}

#[test]
fn concat_columns_equals_burn_cat_on_ndarray() {
    check_concat(&Device::ndarray(), "ndarray");
}

#[test]
fn concat_columns_equals_burn_cat_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    check_concat(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu");
}

#[test]
#[should_panic(expected = "rows on the left")]
fn concat_of_different_row_counts_is_refused() {
    let device = Device::ndarray();
    let _ = concat_columns(table(4, 3, &device), table(5, 3, &device));
}
