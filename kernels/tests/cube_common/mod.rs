//! The wgpu device of the kernel tests (not in `common`: the acags crate's tests share that
//! module and do not depend on burn-cubecl).
#![allow(dead_code)]

use burn::backend::wgpu::{RuntimeOptions, WgpuDevice, graphics::AutoGraphicsApi, try_init_setup};
use burn_cubecl::CubeDevice;
use burn::tensor::Tensor;

/// Whether a missing adapter must fail the test (CI) rather than skip it.
pub fn wgpu_required() -> bool {
    std::env::var("ACAGS_REQUIRE_WGPU").as_deref() == Ok("1")
}

/// The default wgpu adapter as a CubeCL device, or `None` (with a printed reason) when there is
/// none and ACAGS_REQUIRE_WGPU is not 1.
/// The runtime is registered once per process, so the probe runs once and is remembered.
pub fn cube_device() -> Option<CubeDevice> {
    static PROBE: std::sync::OnceLock<Result<String, String>> = std::sync::OnceLock::new();
    let probe = PROBE.get_or_init(|| {
        try_init_setup::<AutoGraphicsApi>(&WgpuDevice::default(), RuntimeOptions::default())
            .map(|setup| setup.adapter.get_info().name)
            .map_err(|e| e.to_string())
    });
    match probe {
        Ok(name) => {
            eprintln!("wgpu adapter: {name}");
            Some(CubeDevice::Wgpu(WgpuDevice::default()))
        }
        Err(e) if wgpu_required() => panic!("ACAGS_REQUIRE_WGPU=1 but no wgpu adapter: {e}"),
        Err(e) => {
            eprintln!("skipping: no wgpu adapter ({e})");
            None
        }
    }
}

/// A tensor's values as f32, on any device and dtype (the kernel tests compare these).
#[allow(deprecated)] // TensorData::to_vec, as the tests have always read values
pub fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.clone()
        .into_data()
        .convert::<f32>()
        .to_vec::<f32>()
        .unwrap()
}
