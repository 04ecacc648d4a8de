//! CubeCL kernels against the CPU twin on the wgpu device (lavapipe in CI).
//! Fails instead of skipping when ACAGS_REQUIRE_WGPU=1.

mod common;

use acags_kernels::cpu::{self, ProjectionCamera};
use acags_kernels::cube::project::{pack_camera, project};
use acags_kernels::random_scene::{SceneSpec, identity_camera, random_scene};
use burn::backend::ops::FloatTensorOps;
use burn::backend::read_sync;
use burn::backend::wgpu::{RuntimeOptions, WgpuDevice, graphics::AutoGraphicsApi, try_init_setup};
use burn::tensor::TensorData;
use burn_cubecl::{CubeBackend, CubeDevice};
use common::*;

fn cube_device() -> Option<CubeDevice> {
    match try_init_setup::<AutoGraphicsApi>(&WgpuDevice::default(), RuntimeOptions::default()) {
        Ok(setup) => {
            eprintln!("wgpu adapter: {}", setup.adapter.get_info().name);
            Some(CubeDevice::Wgpu(WgpuDevice::default()))
        }
        Err(e) if std::env::var("ACAGS_REQUIRE_WGPU").as_deref() == Ok("1") => {
            panic!("ACAGS_REQUIRE_WGPU=1 but no wgpu adapter: {e}")
        }
        Err(e) => {
            eprintln!("skipping: no wgpu adapter ({e})");
            None
        }
    }
}

fn upload(v: &[f32], shape: &[usize], device: &CubeDevice) -> burn_cubecl::tensor::CubeTensor {
    CubeBackend::float_from_data(TensorData::new(v.to_vec(), shape.to_vec()), device)
}

/// The projection kernel reproduces the CPU twin's rows: visibility and radii exactly, the rest
/// to float32 rounding (relative 1e-4; the kernel's operation order differs slightly).
#[test]
fn projection_kernel_matches_the_cpu_twin() {
    let Some(device) = cube_device() else { return };
    let mut scenes: Vec<(
        acags_kernels::RasterCamera,
        acags_kernels::cpu::GaussianArrays,
    )> = FIXTURE_CASES
        .iter()
        .map(|c| {
            let fx = load_fixture(c);
            (fx.camera(), fx.gaussians())
        })
        .collect();
    let camera = identity_camera(640, 360);
    let mut spec = SceneSpec::new(20_000, 12);
    spec.border = 0.5;
    spec.depth = (-1.0, 30.0); // some behind the camera and inside the near plane
    let mut big = random_scene(&camera, &spec);
    for i in (0..big.len()).step_by(7) {
        big.gates[i] = 0.0;
    }
    scenes.push((camera, big));
    for (camera, g) in scenes {
        let n = g.len();
        let gated: Vec<f32> = g
            .opacities
            .iter()
            .zip(&g.gates)
            .map(|(o, gate)| o * gate)
            .collect();
        let out = project(
            upload(&g.means, &[n, 3], &device),
            upload(&g.quats, &[n, 4], &device),
            upload(&g.scales, &[n, 3], &device),
            upload(&gated, &[n], &device),
            upload(
                &pack_camera(&camera),
                &[pack_camera(&camera).len()],
                &device,
            ),
        );
        let rows: Vec<f32> = read_sync(CubeBackend::float_into_data(out))
            .unwrap()
            .try_into_vec_as::<f32>()
            .unwrap();
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
                    let scale = if k >= 2 && k <= 4 {
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
