//! CubeCL kernels of the rasterizer, the GPU twin of `cpu/`, on `CubeBackend` tensors (wgpu,
//! and CUDA with the `cuda` feature). Every stage runs on the device:
//!
//! - `project`: projection + culling, and the projection backward;
//! - `bin`: tile counts, prefix sum (`scan`), intersection emission, sort by (tile, depth)
//!   (`radix_sort`), tile ranges;
//! - `composite`: per-tile forward compositing with early exit, and the backward with float
//!   atomics or a compare-and-swap fallback (`atomics`).
//!
//! `scatter` adds rows at indices with atomics (the row gather's backward, the trainer's
//! statistics). `buffers` allocates (and, for tests, poisons) the intermediate buffers. `backend.rs` registers
//! [`forward`] and [`backward`] as the `Cube` implementation of `GaussianRasterBackend`.

pub mod adam;
pub mod atomics;
pub mod bin;
pub mod buffers;
pub mod composite;
pub mod gaussian_bits;
pub(crate) mod mat3;
pub mod noise;
pub mod project;
pub mod radix_sort;
pub mod scan;
pub mod scatter;
pub mod spawn_means;

use burn::backend::ops::FloatTensorOps;
use burn::tensor::TensorData;
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;

use crate::camera::RasterCamera;
use crate::raster_io::{IntersectionCapacity, RasterForward, RasterGaussians, RasterGrads};
use buffers::{fill_words, fresh_f32, fresh_u32};

/// The rasterizer's inputs on the device: contiguous f32 (the kernels index them flat), made
/// by [`device_gaussians`].
pub type DeviceGaussians = RasterGaussians<CubeBackend>;
/// Everything the forward produces on the device: [H, W, 4] f32 image, [N, 8] f32 projection
/// rows, [tiles + 1] u32 tile offsets, [intersections] u32 Gaussian indices, [H, W] f32 final
/// transmittance, [H, W] u32 contributor counts.
pub type DeviceForward = RasterForward<CubeBackend>;
/// Input gradients on the device, shaped like the inputs; `means2d` [N, 2].
pub type DeviceGrads = RasterGrads<CubeBackend>;

/// The kernels' view of the inputs: each made contiguous, float32 asserted.
pub fn device_gaussians(gaussians: RasterGaussians<CubeBackend>) -> DeviceGaussians {
    gaussians.map(|t| {
        assert_eq!(
            t.dtype,
            burn::tensor::DType::F32,
            "the rasterizer kernels take float32 tensors"
        );
        into_contiguous(t)
    })
}

/// With `ACAGS_KERNEL_TIMING=1`, waits for the device after each stage and prints its time
/// (stderr): a profile of the pipeline at the cost of the overlap between stages.
struct StageTimer {
    enabled: bool,
    start: std::time::Instant,
}

impl StageTimer {
    fn new() -> Self {
        Self {
            enabled: std::env::var("ACAGS_KERNEL_TIMING").as_deref() == Ok("1"),
            start: std::time::Instant::now(),
        }
    }

    fn stage(&mut self, name: &str, like: &CubeTensor) {
        if !self.enabled {
            return;
        }
        use burn::backend::Backend;
        let _ = CubeBackend::sync(&like.device);
        eprintln!(
            "rasterizer stage {name}: {:.1} ms",
            self.start.elapsed().as_secs_f64() * 1e3
        );
        self.start = std::time::Instant::now();
    }
}

/// The packed camera of the projection kernels, on `like`'s device.
pub fn camera_tensor(camera: &RasterCamera, like: &CubeTensor) -> CubeTensor {
    let packed = project::pack_camera(camera);
    let len = packed.len();
    CubeBackend::float_from_data(TensorData::new(packed, [len]), &like.device)
}

/// Kernels bind one-row stand-ins where there are no Gaussians (empty bindings are invalid).
fn with_rows(gaussians: &DeviceGaussians) -> DeviceGaussians {
    if !gaussians.is_empty() {
        return gaussians.clone();
    }
    let one = |width: usize| {
        let t = fresh_f32(&gaussians.means, vec![1, width]);
        fill_words(&t, 0);
        t
    };
    DeviceGaussians {
        means: one(3),
        quats: one(4),
        scales: one(3),
        opacities: one(1),
        gates: one(1),
        colors: one(3),
    }
}

/// Renders on the device. Inputs are validated by the caller (`crate::rasterize`).
pub fn forward(
    gaussians: &DeviceGaussians,
    camera: &RasterCamera,
    background: [f32; 3],
    capacity: IntersectionCapacity,
) -> DeviceForward {
    let mut timer = StageTimer::new();
    timer.stage("(queued before)", &gaussians.means);
    let camera_t = camera_tensor(camera, &gaussians.means);
    let projected = project::project(gaussians, &camera_t);
    timer.stage("project", &projected);
    let (tiles_x, tiles_y) = (camera.tiles_x(), camera.tiles_y());
    let bins = if gaussians.is_empty() {
        let tile_offsets = fresh_u32(&projected, &[(tiles_x * tiles_y) as usize + 1]);
        fill_words(&tile_offsets, 0);
        let intersections = fresh_u32(&projected, &[1]);
        fill_words(&intersections, 0);
        bin::DeviceTileBins {
            tile_offsets,
            gaussian_from_intersection: fresh_u32(&projected, &[0]),
            intersections,
        }
    } else {
        bin::bin_tiles(&projected, tiles_x, tiles_y, capacity)
    };
    timer.stage("bin", &projected);
    let bound = with_rows(gaussians);
    let bound_projected = if gaussians.is_empty() {
        let t = fresh_f32(&projected, vec![1, crate::conventions::PROJECTED_COLUMNS]);
        fill_words(&t, 0);
        t
    } else {
        projected.clone()
    };
    let composite = composite::composite_forward(
        &bound,
        &bound_projected,
        &bins.tile_offsets,
        &bins.gaussian_from_intersection,
        camera,
        background,
    );
    timer.stage("composite", &projected);
    DeviceForward {
        image_alpha: composite.image_alpha,
        projected,
        tile_offsets: bins.tile_offsets,
        gaussian_from_intersection: bins.gaussian_from_intersection,
        final_transmittance: composite.final_transmittance,
        n_contrib: composite.n_contrib,
        intersections: bins.intersections,
    }
}

/// Gradients of every input for dLoss/d(image_alpha) ([H, W, 4]).
pub fn backward(
    gaussians: &DeviceGaussians,
    forward: &DeviceForward,
    grad_image_alpha: CubeTensor,
    camera: &RasterCamera,
    background: [f32; 3],
) -> DeviceGrads {
    if gaussians.is_empty() {
        return project::project_backward(
            gaussians,
            &camera_tensor(camera, &gaussians.means),
            &forward.projected,
            &forward.projected,
        );
    }
    let mut timer = StageTimer::new();
    timer.stage("(queued before backward)", &gaussians.means);
    let grad_image_alpha = into_contiguous(grad_image_alpha);
    let splat_grads = composite::composite_backward(
        gaussians,
        &forward.projected,
        &forward.tile_offsets,
        &forward.gaussian_from_intersection,
        &forward.final_transmittance,
        &forward.n_contrib,
        &grad_image_alpha,
        camera,
        background,
    );
    timer.stage("composite backward", &gaussians.means);
    let camera_t = camera_tensor(camera, &gaussians.means);
    let grads = project::project_backward(gaussians, &camera_t, &forward.projected, &splat_grads);
    timer.stage("project backward", &gaussians.means);
    grads
}
