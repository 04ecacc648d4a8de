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
    match probe() {
        Ok((name, _)) => {
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

/// The default adapter's name and whether it is a CPU device (lavapipe), probed once per process
/// (the runtime is registered once).
fn probe() -> &'static Result<(String, bool), String> {
    static PROBE: std::sync::OnceLock<Result<(String, bool), String>> = std::sync::OnceLock::new();
    PROBE.get_or_init(|| {
        try_init_setup::<AutoGraphicsApi>(&WgpuDevice::default(), RuntimeOptions::default())
            .map(|setup| {
                let info = setup.adapter.get_info();
                (info.name, info.device_type == burn::backend::wgpu::wgpu::DeviceType::Cpu)
            })
            .map_err(|e| e.to_string())
    })
}

/// Whether the wgpu adapter is a CPU device (lavapipe, what CI has): its float functions round
/// like the CPU twin's far more often than a GPU's, so some tests hold it to tighter bounds.
pub fn cpu_adapter() -> bool {
    matches!(probe(), Ok((_, true)))
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
