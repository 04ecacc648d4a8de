//! Choosing where tensors live: `--backend ndarray|wgpu|cuda|auto`.
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
    /// CUDA, natively on NVIDIA GPUs: the same CubeCL kernels. Needs a build with
    /// `--features cuda` (which builds without a CUDA toolkit) and an NVIDIA driver to run.
    Cuda,
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

/// Probes CUDA device 0 once per process: `Err` says why it is unusable (no driver, no GPU).
#[cfg(feature = "cuda")]
pub fn cuda_probe() -> Result<(), String> {
    static PROBE: OnceLock<Result<(), String>> = OnceLock::new();
    PROBE
        .get_or_init(|| {
            // CubeCL's CUDA runtime panics when the driver library cannot be loaded: turn that
            // into an error (and keep the panic message off the terminal).
            let hook = std::panic::take_hook();
            std::panic::set_hook(Box::new(|_| {}));
            let probe = std::panic::catch_unwind(|| {
                burn::tensor::Tensor::<1>::zeros([1], &Device::cuda(0)).into_data()
            });
            std::panic::set_hook(hook);
            probe.map(|_| ()).map_err(|e| {
                let why = crate::panics::panic_message(&*e)
                    .unwrap_or_else(|| "unknown error".into());
                format!("no usable CUDA device: {why}")
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

/// The CPU device, for bookkeeping that must not touch a GPU (e.g. counting parameters): Burn's
/// `Default` device is the wgpu one, whose first use probes Vulkan.
pub fn host_device() -> Device {
    Device::ndarray()
}

/// Whether an adapter is a real GPU (not a CPU implementation such as lavapipe/llvmpipe).
fn is_gpu(adapter: &WgpuAdapter) -> bool {
    matches!(
        adapter.device_type.as_str(),
        "DiscreteGpu" | "IntegratedGpu" | "VirtualGpu"
    )
}

/// Resolves a backend choice to a device.
///
/// `auto` takes wgpu when its adapter is a real GPU and ndarray otherwise: on a CPU Vulkan
/// driver (lavapipe) the CubeCL kernels run far slower than the CPU twin.
pub fn resolve(kind: BackendKind) -> Result<ChosenDevice> {
    match kind {
        BackendKind::Ndarray => Ok(ChosenDevice {
            device: host_device(),
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
                    "wgpu on {} ({}, {}); rasterizer: CubeCL kernels",
                    adapter.name, adapter.backend, adapter.device_type
                ),
            })
        }
        BackendKind::Cuda => resolve_cuda(),
        #[cfg(feature = "cuda")]
        BackendKind::Auto if cuda_probe().is_ok() => {
            let mut chosen = resolve_cuda()?;
            chosen.description = format!("auto: {}", chosen.description);
            Ok(chosen)
        }
        BackendKind::Auto => match wgpu_adapter() {
            Ok(adapter) if is_gpu(&adapter) => {
                let mut chosen = resolve(BackendKind::Wgpu)?;
                chosen.description = format!("auto: {}", chosen.description);
                Ok(chosen)
            }
            found => {
                let why = match found {
                    Ok(adapter) => format!(
                        "the wgpu adapter {} is a {} device, not a GPU",
                        adapter.name, adapter.device_type
                    ),
                    Err(e) => e,
                };
                let mut chosen = resolve(BackendKind::Ndarray)?;
                chosen.description = format!("auto: ndarray (CPU twin), since {why}");
                Ok(chosen)
            }
        },
    }
}

#[cfg(feature = "cuda")]
fn resolve_cuda() -> Result<ChosenDevice> {
    cuda_probe().map_err(|e| anyhow!("--backend cuda: {e}"))?;
    Ok(ChosenDevice {
        device: Device::cuda(0),
        kind: BackendKind::Cuda,
        description: "cuda device 0; rasterizer: CubeCL kernels".into(),
    })
}

#[cfg(not(feature = "cuda"))]
fn resolve_cuda() -> Result<ChosenDevice> {
    Err(anyhow!(
        "--backend cuda: this acags was built without CUDA support; rebuild with \
         `cargo build --release --features cuda` (no CUDA toolkit needed to build, an NVIDIA \
         driver to run), or use --backend wgpu, which runs the same kernels through Vulkan"
    ))
}
