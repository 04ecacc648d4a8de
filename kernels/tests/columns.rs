//! `slice_columns` against Burn's `slice` it replaces: the values and the gradient bit for bit on
//! ndarray (plain and autodiff) and on wgpu (lavapipe in CI; fails instead of skipping under
//! ACAGS_REQUIRE_WGPU=1), for a column range at the start, in the middle, at the end, empty and
//! whole (and the shape of an empty one), and for a table that is not contiguous (a transposed view).
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::columns::slice_columns;
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
