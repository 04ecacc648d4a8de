//! Choosing where tensors live: `--backend ndarray|wgpu|auto`.
#![allow(deprecated)] // Burn 0.22 deprecates NdArray, still the CPU backend the rasterizer twin targets.

use std::sync::OnceLock;

use anyhow::{Result, anyhow};
use burn::backend::wgpu::{RuntimeOptions, WgpuDevice, graphics::AutoGraphicsApi, try_init_setup};
use burn::tensor::{Device, DeviceKind};

/// Which Burn backend computes.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// Pure-Rust CPU tensors; the rasterizer runs its CPU twin.
    Ndarray,
    /// wgpu (Vulkan/Metal/DX12/GL; lavapipe on machines without a GPU).
    Wgpu,
    /// The fastest available rasterizer (see [`resolve`]).
    Auto,
}

/// The wgpu adapter, probed once per process (registering it with CubeCL).
#[derive(Clone, Debug)]
pub struct WgpuAdapter {
    pub name: String,
    pub backend: String,
    pub device_type: String,
}

/// Probes the default wgpu adapter without panicking; `Err` says why none is usable.
pub fn wgpu_adapter() -> Result<WgpuAdapter, String> {
    static PROBE: OnceLock<Result<WgpuAdapter, String>> = OnceLock::new();
    PROBE
        .get_or_init(|| {
            let setup = try_init_setup::<AutoGraphicsApi>(
                &WgpuDevice::default(),
                RuntimeOptions::default(),
            )
            .map_err(|e| format!("no usable wgpu adapter: {e}"))?;
            let info = setup.adapter.get_info();
            Ok(WgpuAdapter {
                name: info.name,
                backend: format!("{:?}", info.backend),
                device_type: format!("{:?}", info.device_type),
            })
        })
        .clone()
}

/// A device ready to compute, and a line saying what was chosen.
pub struct ChosenDevice {
    pub device: Device,
    pub kind: BackendKind,
    pub description: String,
}

/// Resolves a backend choice to a device.
///
/// `auto` picks ndarray for now: until the CubeCL rasterizer kernels land, the wgpu device runs the
/// rasterizer through a host round trip, so the CPU twin on ndarray is the faster path everywhere.
pub fn resolve(kind: BackendKind) -> Result<ChosenDevice> {
    match kind {
        BackendKind::Ndarray => Ok(ChosenDevice {
            device: Device::ndarray(),
            kind,
            description: "ndarray (CPU)".into(),
        }),
        BackendKind::Wgpu => {
            let adapter = wgpu_adapter().map_err(|e| {
                anyhow!("--backend wgpu: {e} (on Linux without a GPU, install mesa-vulkan-drivers for lavapipe)")
            })?;
            Ok(ChosenDevice {
                device: Device::wgpu(DeviceKind::DefaultDevice),
                kind,
                description: format!(
                    "wgpu on {} ({}, {}); rasterizer via host round trip until the CubeCL kernels land",
                    adapter.name, adapter.backend, adapter.device_type
                ),
            })
        }
        BackendKind::Auto => {
            let mut chosen = resolve(BackendKind::Ndarray)?;
            chosen.description =
                "ndarray (CPU): auto picks the CPU twin until the CubeCL rasterizer lands".into();
            Ok(chosen)
        }
    }
}
