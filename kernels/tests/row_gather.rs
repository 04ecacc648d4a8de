//! The row ops of `gather.rs` against the Burn ops they replace: `gather_rows` against `select`
//! (values, and the scatter-add gradient against autodiff's own `select` backward), and
//! `add_rows_at` against `select_assign(.., Add)` (repeated indices included, so the order of the
//! additions shows): bit for bit on ndarray and its autodiff device, within f32 rounding on wgpu,
//! whose kernel adds with atomics (lavapipe in CI; fails instead of skipping under
//! ACAGS_REQUIRE_WGPU=1); the wgpu run also checks the compare-and-swap fallback. `add_rows_at` adds in place on ndarray
//! when nothing else holds the table: a table that is shared must come out unchanged.
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::cube::atomics::force_compare_and_swap;
use acags_kernels::gather::{add_rows_at, gather_rows};
use burn::tensor::{Device, DeviceKind, IndexingUpdateOp, Int, Tensor, TensorData};
use cube_common::{cube_device, values};
use rand::{Rng, SeedableRng, rngs::StdRng};

fn table(rows: usize, width: usize, rng: &mut StdRng, device: &Device) -> Tensor<2> {
    let v: Vec<f32> = (0..rows * width)
        .map(|_| rng.random_range(-3.0f32..3.0))
        .collect();
    Tensor::<2>::from_data(TensorData::new(v, [rows, width]), device)
}

/// `m` indices below `rows`, a quarter of them repeats of earlier ones.
fn indices(m: usize, rows: usize, rng: &mut StdRng, device: &Device) -> Tensor<1, Int> {
    let mut v: Vec<i64> = Vec::with_capacity(m);
    for i in 0..m {
        let j = if i > 0 && rng.random_bool(0.25) {
            v[rng.random_range(0..i)]
        } else {
            rng.random_range(0..rows as i64)
        };
        v.push(j);
    }
    Tensor::<1, Int>::from_data(TensorData::new(v, [m]), device)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Equal bit for bit (`exact`: the CPU twin adds in index order), or within f32 rounding of a
/// different order of additions (the GPU's atomics).
fn assert_same(got: &[f32], want: &[f32], exact: bool, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    if exact {
        assert_eq!(bits(got), bits(want), "{what}");
        return;
    }
    for (i, (a, b)) in got.iter().zip(want).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
            "{what}: element {i}: {a} vs {b}"
        );
    }
}

fn check_add_rows_at(device: &Device, label: &str, exact: bool) {
    let mut rng = StdRng::seed_from_u64(7);
    for (rows, width, m) in [(1000usize, 1usize, 5000usize), (300, 4, 900), (17, 3, 0)] {
        let into = table(rows, width, &mut rng, device);
        let index = indices(m, rows, &mut rng, device);
        let add = table(m, width, &mut rng, device);
        let expected = values(&into.clone().select_assign(
            0,
            index.clone(),
            add.clone(),
            IndexingUpdateOp::Add,
        ));
        let before = values(&into);
        // Shared: `into` is still held here, so the op must not write into its buffer.
        let shared = add_rows_at(into.clone(), index.clone(), add.clone());
        assert_same(
            &values(&shared),
            &expected,
            exact,
            &format!("{label}: {rows}x{width}, {m} indices, shared table"),
        );
        assert_eq!(
            bits(&values(&into)),
            bits(&before),
            "{label}: {rows}x{width}: the shared table was changed"
        );
        // Unique: the table's own buffer is reused, the result the same.
        let unique = add_rows_at(into, index, add);
        assert_same(
            &values(&unique),
            &expected,
            exact,
            &format!("{label}: {rows}x{width}, {m} indices, unique table"),
        );
    }
    // Accumulating over several calls, as the trainer's statistics do.
    let mut acc = Tensor::<2>::zeros([50, 1], device);
    let mut reference = acc.clone();
    for _ in 0..6 {
        let index = indices(200, 50, &mut rng, device);
        let add = table(200, 1, &mut rng, device);
        reference = reference.select_assign(0, index.clone(), add.clone(), IndexingUpdateOp::Add);
        acc = add_rows_at(acc, index, add);
    }
    assert_same(
        &values(&acc),
        &values(&reference),
        exact,
        &format!("{label}: accumulated"),
    );
}

fn check_gather_rows(device: &Device, label: &str) {
    let device = device.clone().autodiff();
    let mut rng = StdRng::seed_from_u64(11);
    let source = table(400, 6, &mut rng, &device);
    let index = indices(1500, 400, &mut rng, &device);
    let weight = table(1500, 6, &mut rng, &device);

    let ours = source.clone().require_grad();
    let out = gather_rows(ours.clone(), index.clone());
    let grads = (out.clone() * weight.clone()).sum().backward();
    let ours_grad = values(&ours.grad(&grads).unwrap());

    let theirs = source.require_grad();
    let reference = theirs.clone().select(0, index);
    let grads = (reference.clone() * weight).sum().backward();
    let theirs_grad = values(&theirs.grad(&grads).unwrap());

    assert_eq!(
        bits(&values(&out)),
        bits(&values(&reference)),
        "{label}: gathered rows"
    );
    // Both scatter-add the same products; the order of a GPU's atomics may differ.
    for (i, (a, b)) in ours_grad.iter().zip(&theirs_grad).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5 * (1.0 + b.abs()),
            "{label}: gradient {i}: {a} vs {b}"
        );
    }
}

#[test]
fn add_rows_at_equals_select_assign_add_on_ndarray() {
    check_add_rows_at(&Device::ndarray(), "ndarray", true);
    check_add_rows_at(&Device::ndarray().autodiff(), "ndarray+autodiff", true);
}

#[test]
fn add_rows_at_equals_select_assign_add_on_wgpu() {
    if cube_device().is_none() {
        return;
    }
    let device = Device::wgpu(DeviceKind::DefaultDevice);
    check_add_rows_at(&device, "wgpu", false);
    check_add_rows_at(&device.clone().autodiff(), "wgpu+autodiff", false);
    force_compare_and_swap(true);
    check_add_rows_at(&device, "wgpu, compare-and-swap", false);
    force_compare_and_swap(false);
}

#[test]
fn gather_rows_equals_select_in_values_and_gradient() {
    check_gather_rows(&Device::ndarray(), "ndarray");
    if cube_device().is_some() {
        check_gather_rows(&Device::wgpu(DeviceKind::DefaultDevice), "wgpu");
    }
}

#[test]
#[should_panic(expected = "out of range")]
fn add_rows_at_refuses_an_index_past_the_table() {
    let device = Device::ndarray();
    let into = Tensor::<2>::zeros([4, 1], &device);
    let index = Tensor::<1, Int>::from_data(TensorData::new(vec![1i64, 4], [2]), &device);
    let _ = add_rows_at(into, index, Tensor::<2>::ones([2, 1], &device));
}
