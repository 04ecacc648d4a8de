//! The CubeCL kernels stage by stage against the CPU twin (and plain Rust) on the wgpu device
//! (lavapipe in CI): projection, prefix sum, radix sort, tile binning.
//! Fails instead of skipping when ACAGS_REQUIRE_WGPU=1.

mod common;
mod cube_common;

use acags_kernels::IntersectionCapacity;
use acags_kernels::cpu::{self, ProjectionCamera};
use acags_kernels::cube::bin::bin_tiles;
use acags_kernels::cube::project::project;
use acags_kernels::cube::radix_sort::sort_pairs;
use acags_kernels::cube::scan::exclusive_scan;
use acags_kernels::cube::{self, DeviceGaussians, camera_tensor};
use acags_kernels::raster_io::RasterGaussians;
use acags_kernels::random_scene::{GaussianArrays, SceneSpec, identity_camera, random_scene};
use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::read_sync;
use burn::tensor::TensorData;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};
use common::*;
use cube_common::cube_device;
use rand::{Rng, SeedableRng, rngs::StdRng};

fn upload(v: &[f32], shape: &[usize], device: &CubeDevice) -> CubeTensor {
    CubeBackend::float_from_data(TensorData::new(v.to_vec(), shape.to_vec()), device)
}

fn upload_u32(v: &[u32], device: &CubeDevice) -> CubeTensor {
    CubeBackend::int_from_data(TensorData::new(v.to_vec(), [v.len()]), device)
}

fn read_f32(t: CubeTensor) -> Vec<f32> {
    read_sync(CubeBackend::float_into_data(t))
        .unwrap()
        .try_into_vec_as::<f32>()
        .unwrap()
}

fn read_u32(t: CubeTensor) -> Vec<u32> {
    read_sync(CubeBackend::int_into_data(t))
        .unwrap()
        .convert::<i64>()
        .try_to_vec::<i64>()
        .unwrap()
        .into_iter()
        .map(|v| v as u32)
        .collect()
}

fn device_gaussians(g: &GaussianArrays, device: &CubeDevice) -> DeviceGaussians {
    let n = g.len();
    cube::device_gaussians(RasterGaussians {
        means: upload(&g.means, &[n, 3], device),
        quats: upload(&g.quats, &[n, 4], device),
        scales: upload(&g.scales, &[n, 3], device),
        opacities: upload(&g.opacities, &[n], device),
        gates: upload(&g.gates, &[n], device),
        colors: upload(&g.colors, &[n, 3], device),
    })
}

/// A scene with Gaussians behind the camera, inside the near plane, gated, and with
/// non-finite inputs: every culling rule is exercised.
fn culling_scene() -> (acags_kernels::RasterCamera, GaussianArrays) {
    let camera = identity_camera(640, 360);
    let mut spec = SceneSpec::new(20_000, 12);
    spec.border = 0.5;
    spec.depth = (-1.0, 30.0);
    let mut g = random_scene(&camera, &spec);
    for i in (0..g.len()).step_by(7) {
        g.gates[i] = 0.0;
    }
    for i in (3..g.len()).step_by(101) {
        g.means[3 * i] = f32::NAN;
    }
    for i in (5..g.len()).step_by(103) {
        g.colors[3 * i + 1] = f32::INFINITY;
    }
    for i in (6..g.len()).step_by(107) {
        g.quats[4 * i..4 * i + 4].fill(0.0);
    }
    (camera, g)
}

/// The projection kernel reproduces the CPU twin's rows: visibility and radii exactly, the rest
/// to float32 rounding (relative 1e-4; the kernel's operation order differs slightly).
#[test]
fn projection_kernel_matches_the_cpu_twin() {
    let Some(device) = cube_device() else { return };
    let mut scenes: Vec<(acags_kernels::RasterCamera, GaussianArrays)> = FIXTURE_CASES
        .iter()
        .map(|c| {
            let fx = load_fixture(c);
            (fx.camera(), fx.gaussians())
        })
        .collect();
    scenes.push(culling_scene());
    for (camera, g) in scenes {
        let gaussians = device_gaussians(&g, &device);
        let rows = read_f32(project(&gaussians, &camera_tensor(&camera, &gaussians.means)));
        let want = cpu::project_all(&g.slices(), &ProjectionCamera::new(&camera));
        let mut visible = 0;
        for (i, p) in want.iter().enumerate() {
            let got = &rows[i * 8..i * 8 + 8];
            assert_eq!(
                [got[6] as u32, got[7] as u32],
                p.radius,
                "Gaussian {i}: radii (row {got:?})"
            );
            if cpu::is_visible(p) {
                visible += 1;
                let expect = p.to_row();
                for (k, (a, b)) in got[..6].iter().zip(&expect[..6]).enumerate() {
                    let scale = if (2..=4).contains(&k) {
                        p.conic.iter().fold(0.0f32, |m, v| m.max(v.abs()))
                    } else {
                        b.abs().max(1.0)
                    };
                    assert!(
                        (a - b).abs() <= 1e-4 * scale,
                        "Gaussian {i} column {k}: {a} vs {b}"
                    );
                }
            } else {
                assert!(
                    got.iter().all(|v| *v == 0.0),
                    "culled Gaussian {i} has row {got:?}"
                );
            }
        }
        assert!(visible > 0);
    }
}

#[test]
fn exclusive_scan_matches_a_serial_prefix_sum() {
    let Some(device) = cube_device() else { return };
    let mut rng = StdRng::seed_from_u64(3);
    // One block, block edges, and three levels of recursion (1024² < 1.2M).
    for n in [1usize, 5, 1023, 1024, 1025, 4096 + 17, 1_200_003] {
        let values: Vec<u32> = (0..n).map(|_| rng.random_range(0..40)).collect();
        let (scan, total) = exclusive_scan(&upload_u32(&values, &device));
        let mut want = Vec::with_capacity(n);
        let mut sum = 0u32;
        for v in &values {
            want.push(sum);
            sum += v;
        }
        assert_eq!(read_u32(scan), want, "n = {n}");
        assert_eq!(read_u32(total), vec![sum], "n = {n}");
    }
}

#[test]
fn radix_sort_is_a_stable_sort_by_key() {
    let Some(device) = cube_device() else { return };
    let mut rng = StdRng::seed_from_u64(4);
    for (n, bits) in [(1usize, 32u32), (700, 4), (3000, 13), (70_001, 32), (5000, 0)] {
        // Few distinct keys: many ties, whose input order must survive.
        let max = if bits == 32 { u32::MAX } else { (1u32 << bits).max(1) - 1 };
        let keys: Vec<u32> = (0..n)
            .map(|_| {
                if bits == 0 {
                    0
                } else if rng.random_bool(0.5) {
                    rng.random_range(0..=max.min(9))
                } else {
                    rng.random_range(0..=max)
                }
            })
            .collect();
        let values: Vec<u32> = (0..n as u32).collect();
        let (sorted_keys, sorted_values) =
            sort_pairs(upload_u32(&keys, &device), upload_u32(&values, &device), bits);
        let mut want: Vec<(u32, u32)> = keys.iter().copied().zip(values).collect();
        want.sort_by_key(|&(k, _)| k); // stable
        let (want_keys, want_values): (Vec<u32>, Vec<u32>) = want.into_iter().unzip();
        assert_eq!(read_u32(sorted_keys), want_keys, "n = {n}, bits = {bits}");
        assert_eq!(read_u32(sorted_values), want_values, "n = {n}, bits = {bits}");
    }
}

/// Device binning equals the CPU twin's exactly (same rows in, same lists out), including the
/// order inside each tile: front to back, ties by index.
#[test]
fn tile_binning_matches_the_cpu_twin() {
    let Some(device) = cube_device() else { return };
    let (camera, mut g) = culling_scene();
    // Exact depth ties between distinct Gaussians.
    for i in (0..g.len()).step_by(13) {
        let j = (i + 5) % g.len();
        g.means[3 * j + 2] = g.means[3 * i + 2];
    }
    let projected = cpu::project_all(&g.slices(), &ProjectionCamera::new(&camera));
    let rows: Vec<f32> = projected.iter().flat_map(|p| p.to_row()).collect();
    let want = cpu::bin_tiles(&projected, camera.tiles_x(), camera.tiles_y());
    let rows = upload(&rows, &[projected.len(), 8], &device);
    let bin = |capacity| bin_tiles(&rows, camera.tiles_x(), camera.tiles_y(), capacity);
    let count = want.intersection_count();
    assert!(count > 10_000);
    let bins = bin(IntersectionCapacity::Exact);
    assert_eq!(read_u32(bins.intersections), vec![count as u32]);
    assert_eq!(read_u32(bins.tile_offsets), want.tile_offsets);
    assert_eq!(
        read_u32(bins.gaussian_from_intersection),
        want.gaussian_from_intersection
    );
    // Buffers sized ahead, with room to spare or exactly: the same lists, the unused slots
    // after every tile's range, the count exact.
    for capacity in [count + 777, count] {
        let bins = bin(IntersectionCapacity::AtMost(capacity));
        assert_eq!(read_u32(bins.intersections), vec![count as u32]);
        assert_eq!(read_u32(bins.tile_offsets), want.tile_offsets, "capacity {capacity}");
        let ids = read_u32(bins.gaussian_from_intersection);
        assert_eq!(ids.len(), capacity);
        assert_eq!(ids[..count], want.gaussian_from_intersection[..]);
    }
    // Too small: what fits is binned, the ranges end at the capacity, and the count says how
    // many were needed.
    let short = count / 3;
    let bins = bin(IntersectionCapacity::AtMost(short));
    assert_eq!(read_u32(bins.intersections), vec![count as u32]);
    let offsets = read_u32(bins.tile_offsets);
    assert_eq!(*offsets.last().unwrap() as usize, short);
    assert!(offsets.windows(2).all(|w| w[0] <= w[1]));
}
