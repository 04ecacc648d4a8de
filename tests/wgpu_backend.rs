//! The rasterizer on the wgpu device (lavapipe in CI) through the same public function.
//! Fails instead of skipping when ACAGS_REQUIRE_WGPU=1.

#[path = "../kernels/tests/common/mod.rs"]
mod common;

use acags::compute_backend::{BackendKind, resolve, wgpu_adapter};
use acags::raster::{GaussianTensors, rasterize};
use burn::tensor::{Device, Tensor};
use common::*;

fn wgpu_device() -> Option<Device> {
    match wgpu_adapter() {
        Ok(adapter) => {
            eprintln!(
                "wgpu adapter: {} ({}, {})",
                adapter.name, adapter.backend, adapter.device_type
            );
            Some(resolve(BackendKind::Wgpu).unwrap().device)
        }
        Err(why) if std::env::var("ACAGS_REQUIRE_WGPU").as_deref() == Ok("1") => {
            panic!("ACAGS_REQUIRE_WGPU=1 but {why}")
        }
        Err(why) => {
            eprintln!("skipping wgpu test: {why}");
            None
        }
    }
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap()
}

#[test]
fn fixtures_on_wgpu_with_autodiff() {
    let Some(device) = wgpu_device() else { return };
    let device = device.autodiff();
    for case in [
        "random_small",
        "occlusion_saturation",
        "near_plane_and_behind",
    ] {
        let fx = load_fixture(case);
        let gt = GaussianTensors::from_arrays(&fx.gaussians(), &device).require_grad();
        let out = rasterize(&gt, &fx.camera(), fx.background).unwrap();
        assert!(
            max_abs_diff(&values(out.image.clone()), &fx.image_flat()) <= 1e-4,
            "{case}: image"
        );
        let grads = fixture_loss(&fx, &out).backward();
        assert_grad_close(
            case,
            &values(gt.means.grad(&grads).unwrap()),
            &fx.grad_means.concat(),
            1e-3,
            3e-5,
        );
        assert_grad_close(
            case,
            &values(gt.quats.grad(&grads).unwrap()),
            &fx.grad_quats.concat(),
            1e-3,
            3e-5,
        );
        assert_grad_close(
            case,
            &values(out.means2d_grad(&grads).unwrap()),
            &fx.grad_means2d.concat(),
            1e-3,
            3e-5,
        );
    }
}
