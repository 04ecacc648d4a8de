//! The rasterizer as a Burn backend extension.
//!
//! `GaussianRasterBackend` has one forward and one backward op. Backends implement both;
//! `Autodiff<B>` implements the forward by calling `B`'s and registering a hand-written `Backward`
//! node that calls `B`'s backward op: no autodiff graph is built through per-pixel operations.
//!
//! The forward returns the backward's state as tensors (projection, tile bins, per-pixel final
//! transmittance and contributor counts), so a GPU implementation keeps it on the device.
#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{
    AutodiffBackend, Backend, ExtensionType, NdArray, TensorMetadata, backend_extension, read_sync,
};
use burn::tensor::TensorData;

use burn_cubecl::CubeBackend;

use crate::camera::RasterCamera;
use crate::cpu;
use crate::cube::{self, DeviceGaussians};

/// Columns of the per-Gaussian projection tensor [N, PROJECTED_COLUMNS].
pub mod projected_column {
    pub const MEAN2D_X: usize = 0;
    pub const MEAN2D_Y: usize = 1;
    pub const CONIC_A: usize = 2;
    pub const CONIC_B: usize = 3;
    pub const CONIC_C: usize = 4;
    pub const DEPTH: usize = 5;
    pub const RADIUS_X: usize = 6;
    pub const RADIUS_Y: usize = 7;
}
pub const PROJECTED_COLUMNS: usize = 8;

/// Forward outputs. `image_alpha` is the only differentiable one; the rest is the backward's
/// state and per-Gaussian diagnostics.
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterForward<B: Backend> {
    /// [H, W, 4]: RGB with the background composited, then alpha = 1 - T_final.
    pub image_alpha: FloatTensor<B>,
    /// [N, 8], see [`projected_column`]. Culled Gaussians have zero radii (and zero elsewhere).
    pub projected: FloatTensor<B>,
    /// [tiles + 1] start of each tile's range in `gaussian_from_intersection`.
    pub tile_offsets: IntTensor<B>,
    /// [intersections] Gaussian index per (tile, depth)-sorted intersection.
    pub gaussian_from_intersection: IntTensor<B>,
    /// [H, W] transmittance after the last composited Gaussian.
    pub final_transmittance: FloatTensor<B>,
    /// [H, W] tile-list entries processed up to the last composited Gaussian.
    pub n_contrib: IntTensor<B>,
}

/// Gradients of the loss with respect to each input, shaped like the inputs.
#[derive(ExtensionType, Clone, Debug)]
pub struct RasterGrads<B: Backend> {
    pub means: FloatTensor<B>,
    pub quats: FloatTensor<B>,
    pub scales: FloatTensor<B>,
    pub opacities: FloatTensor<B>,
    pub colors: FloatTensor<B>,
    /// [N, 2] dLoss/d(screen mean) in pixels, what densification accumulates.
    pub means2d: FloatTensor<B>,
}

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait GaussianRasterBackend: Backend {
    /// Renders N gated Gaussians. Shapes: means [N,3], quats [N,4] (w,x,y,z raw), scales [N,3],
    /// opacities [N], gates [N], colors [N,3]; `means2d_probe` [N,2] must be zeros: it only
    /// carries the screen-mean gradient back to the caller under autodiff.
    ///
    /// Callers validate camera, background and shapes first ([`crate::rasterize`] does).
    #[allow(clippy::too_many_arguments)]
    fn rasterize_forward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterForward<Self>;

    /// Vector-Jacobian product of [`Self::rasterize_forward`] for dLoss/d(image_alpha).
    #[allow(clippy::too_many_arguments)]
    fn rasterize_backward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        #[extension_type] forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self>;
}

// ---------------------------------------------------------------------------------------------
// Host implementation: read the tensors, run the CPU twin, upload the results.

/// Moving tensors between a backend and the host for the CPU twins (rasterizer, row gather,
/// fused SSIM); zero-copy for contiguous ndarray storage.
pub trait HostIo: Backend {
    fn read_floats(t: FloatTensor<Self>) -> Vec<f32> {
        read_floats_via_data::<Self>(t)
    }

    fn read_indices(t: IntTensor<Self>) -> Vec<u32> {
        read_indices_via_data::<Self>(t)
    }
}

fn read_floats_via_data<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    read_sync(B::float_into_data(t))
        .expect("rasterizer: reading a float tensor back from the device failed")
        .try_into_vec_as::<f32>()
        .expect("float tensor converts to f32")
}

/// NdArray: copy straight out of contiguous f32 storage (its generic `into_data` walks the array
/// element by element, ~25x slower).
impl HostIo for NdArray {
    fn read_floats(t: FloatTensor<Self>) -> Vec<f32> {
        if let burn::backend::ndarray::NdArrayTensor::F32(storage) = &t
            && let Some(slice) = storage.view().as_slice()
        {
            return slice.to_vec();
        }
        read_floats_via_data::<Self>(t)
    }

    fn read_indices(t: IntTensor<Self>) -> Vec<u32> {
        use burn::backend::ndarray::NdArrayTensor;
        fn narrow<T: Copy + TryInto<u32>>(values: &[T]) -> Vec<u32> {
            values
                .iter()
                .map(|&v| v.try_into().unwrap_or(u32::MAX))
                .collect()
        }
        let copied = match &t {
            NdArrayTensor::I32(s) => s.view().as_slice().map(narrow),
            NdArrayTensor::I64(s) => s.view().as_slice().map(narrow),
            _ => None,
        };
        copied.unwrap_or_else(|| read_indices_via_data::<Self>(t))
    }
}

impl HostIo for burn::backend::Cube {}

fn read_indices_via_data<B: Backend>(t: IntTensor<B>) -> Vec<u32> {
    read_sync(B::int_into_data(t))
        .expect("rasterizer: reading an int tensor back from the device failed")
        .convert::<i64>()
        .try_into_vec::<i64>()
        .expect("int tensor converts to i64")
        .into_iter()
        .map(|v| v as u32)
        .collect()
}

fn upload_floats<B: Backend>(
    data: Vec<f32>,
    shape: Vec<usize>,
    device: &B::Device,
) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(data, shape), device)
}

fn upload_indices<B: Backend>(data: &[u32], device: &B::Device) -> IntTensor<B> {
    let data: Vec<i32> = data.iter().map(|&v| v as i32).collect();
    let len = data.len();
    B::int_from_data(TensorData::new(data, [len]), device)
}

fn read_gaussians<B: HostIo>(
    means: FloatTensor<B>,
    quats: FloatTensor<B>,
    scales: FloatTensor<B>,
    opacities: FloatTensor<B>,
    gates: FloatTensor<B>,
    colors: FloatTensor<B>,
) -> cpu::GaussianArrays {
    cpu::GaussianArrays {
        means: B::read_floats(means),
        quats: B::read_floats(quats),
        scales: B::read_floats(scales),
        opacities: B::read_floats(opacities),
        gates: B::read_floats(gates),
        colors: B::read_floats(colors),
    }
}

fn projected_rows(projected: &[cpu::Projected]) -> Vec<f32> {
    projected.iter().flat_map(cpu::Projected::to_row).collect()
}

fn projected_from_rows(rows: &[f32]) -> Vec<cpu::Projected> {
    rows.chunks_exact(PROJECTED_COLUMNS)
        .map(cpu::Projected::from_row)
        .collect()
}

#[allow(clippy::too_many_arguments)]
fn host_forward<B: HostIo>(
    means: FloatTensor<B>,
    quats: FloatTensor<B>,
    scales: FloatTensor<B>,
    opacities: FloatTensor<B>,
    gates: FloatTensor<B>,
    colors: FloatTensor<B>,
    camera: RasterCamera,
    background: [f32; 3],
) -> RasterForward<B> {
    let device = means.device();
    let inputs = read_gaussians::<B>(means, quats, scales, opacities, gates, colors);
    let state = cpu::forward(&inputs.slices(), &camera, background)
        .unwrap_or_else(|e| panic!("rasterize_forward called with unvalidated input: {e}"));
    let (h, w) = (camera.height as usize, camera.width as usize);
    let n = inputs.opacities.len();
    RasterForward {
        image_alpha: upload_floats::<B>(state.composite.image_alpha, vec![h, w, 4], &device),
        projected: upload_floats::<B>(
            projected_rows(&state.projected),
            vec![n, PROJECTED_COLUMNS],
            &device,
        ),
        tile_offsets: upload_indices::<B>(&state.bins.tile_offsets, &device),
        gaussian_from_intersection: upload_indices::<B>(
            &state.bins.gaussian_from_intersection,
            &device,
        ),
        final_transmittance: upload_floats::<B>(
            state.composite.final_transmittance,
            vec![h, w],
            &device,
        ),
        n_contrib: {
            let t = upload_indices::<B>(&state.composite.n_contrib, &device);
            B::int_reshape(t, [h, w].into())
        },
    }
}

#[allow(clippy::too_many_arguments)]
fn host_backward<B: HostIo>(
    means: FloatTensor<B>,
    quats: FloatTensor<B>,
    scales: FloatTensor<B>,
    opacities: FloatTensor<B>,
    gates: FloatTensor<B>,
    colors: FloatTensor<B>,
    forward: RasterForward<B>,
    grad_image_alpha: FloatTensor<B>,
    camera: RasterCamera,
    background: [f32; 3],
) -> RasterGrads<B> {
    let device = means.device();
    let inputs = read_gaussians::<B>(means, quats, scales, opacities, gates, colors);
    let n = inputs.opacities.len();
    let tile_offsets = B::read_indices(forward.tile_offsets);
    let state = cpu::ForwardState {
        projected: projected_from_rows(&B::read_floats(forward.projected)),
        bins: cpu::TileBins {
            tiles_x: camera.tiles_x(),
            tiles_y: camera.tiles_y(),
            tile_offsets,
            gaussian_from_intersection: B::read_indices(forward.gaussian_from_intersection),
        },
        composite: cpu::CompositeOutput {
            // The backward never reads the forward image.
            image_alpha: Vec::new(),
            final_transmittance: B::read_floats(forward.final_transmittance),
            n_contrib: B::read_indices(forward.n_contrib),
        },
    };
    let grad = B::read_floats(grad_image_alpha);
    let grads = cpu::backward(&inputs.slices(), &camera, background, &state, &grad)
        .unwrap_or_else(|e| panic!("rasterize_backward called with unvalidated input: {e}"));
    RasterGrads {
        means: upload_floats::<B>(grads.means, vec![n, 3], &device),
        quats: upload_floats::<B>(grads.quats, vec![n, 4], &device),
        scales: upload_floats::<B>(grads.scales, vec![n, 3], &device),
        opacities: upload_floats::<B>(grads.opacities, vec![n], &device),
        colors: upload_floats::<B>(grads.colors, vec![n, 3], &device),
        means2d: upload_floats::<B>(grads.means2d, vec![n, 2], &device),
    }
}

/// Implements the trait for a backend by running the CPU twin on the host.
macro_rules! host_raster_backend {
    ($backend:ty) => {
        impl GaussianRasterBackend for $backend {
            fn rasterize_forward(
                means: FloatTensor<Self>,
                quats: FloatTensor<Self>,
                scales: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                gates: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                _means2d_probe: FloatTensor<Self>,
                camera: RasterCamera,
                background: [f32; 3],
            ) -> RasterForward<Self> {
                host_forward::<Self>(
                    means, quats, scales, opacities, gates, colors, camera, background,
                )
            }

            fn rasterize_backward(
                means: FloatTensor<Self>,
                quats: FloatTensor<Self>,
                scales: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                gates: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                forward: RasterForward<Self>,
                grad_image_alpha: FloatTensor<Self>,
                camera: RasterCamera,
                background: [f32; 3],
            ) -> RasterGrads<Self> {
                host_backward::<Self>(
                    means,
                    quats,
                    scales,
                    opacities,
                    gates,
                    colors,
                    forward,
                    grad_image_alpha,
                    camera,
                    background,
                )
            }
        }
    };
}

// NdArray: the CPU twin itself (the copies in and out are O(N + pixels), negligible next to
// compositing).
host_raster_backend!(NdArray);

// ---------------------------------------------------------------------------------------------
// Cube (wgpu, CUDA): the CubeCL kernels (`crate::cube`).

impl GaussianRasterBackend for CubeBackend {
    fn rasterize_forward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        _means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterForward<Self> {
        let gaussians = DeviceGaussians::new(means, quats, scales, opacities, gates, colors);
        let f = cube::forward(&gaussians, &camera, background);
        RasterForward {
            image_alpha: f.image_alpha,
            projected: f.projected,
            tile_offsets: f.tile_offsets,
            gaussian_from_intersection: f.gaussian_from_intersection,
            final_transmittance: f.final_transmittance,
            n_contrib: f.n_contrib,
        }
    }

    fn rasterize_backward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self> {
        let gaussians = DeviceGaussians::new(means, quats, scales, opacities, gates, colors);
        let forward = cube::DeviceForward {
            image_alpha: forward.image_alpha,
            projected: forward.projected,
            tile_offsets: forward.tile_offsets,
            gaussian_from_intersection: forward.gaussian_from_intersection,
            final_transmittance: forward.final_transmittance,
            n_contrib: forward.n_contrib,
        };
        let g = cube::backward(&gaussians, &forward, grad_image_alpha, &camera, background);
        RasterGrads {
            means: g.means,
            quats: g.quats,
            scales: g.scales,
            opacities: g.opacities,
            colors: g.colors,
            means2d: g.means2d,
        }
    }
}

/// The fused wgpu device (`burn::backend::Cube` = `Fusion<CubeBackend>`): the rasterizer is one
/// opaque step of the stream. Its inputs are resolved (the queued work that produces them runs),
/// the kernels run on the inner tensors, and the outputs are registered back as fresh tensors.
/// Not a `#[fusion]` custom op: the intersection buffers are sized by a count only the device
/// knows, and custom ops need their output shapes up front.
mod fused {
    use super::*;
    use burn::backend::fusion::{Client, Fusion, FusionBackend, NoOp, stream::StreamId};
    use burn::backend::ir::{BackendIr, InitOperationIr, OperationIr, OperationOutput};

    type Runtime = <CubeBackend as FusionBackend>::FusionRuntime;

    fn inner_float(t: FloatTensor<Fusion<CubeBackend>>) -> FloatTensor<CubeBackend> {
        t.client.clone().resolve_tensor_float::<CubeBackend>(t)
    }

    fn inner_int(t: IntTensor<Fusion<CubeBackend>>) -> IntTensor<CubeBackend> {
        t.client.clone().resolve_tensor_int::<CubeBackend>(t)
    }

    fn register(
        client: &Client<Runtime>,
        t: FloatTensor<CubeBackend>,
    ) -> FloatTensor<Fusion<CubeBackend>> {
        let shape = t.shape();
        let dtype = t.dtype;
        let handle = CubeBackend::float_tensor_handle(t);
        let desc = InitOperationIr::create(shape, dtype, || client.register_tensor_handle(handle));
        client
            .register(
                StreamId::current(),
                OperationIr::Init(desc),
                NoOp::<CubeBackend>::new(),
            )
            .output()
    }

    fn outer_forward(
        client: &Client<Runtime>,
        f: RasterForward<CubeBackend>,
    ) -> RasterForward<Fusion<CubeBackend>> {
        RasterForward {
            image_alpha: register(client, f.image_alpha),
            projected: register(client, f.projected),
            tile_offsets: register(client, f.tile_offsets),
            gaussian_from_intersection: register(client, f.gaussian_from_intersection),
            final_transmittance: register(client, f.final_transmittance),
            n_contrib: register(client, f.n_contrib),
        }
    }

    impl GaussianRasterBackend for Fusion<CubeBackend> {
        fn rasterize_forward(
            means: FloatTensor<Self>,
            quats: FloatTensor<Self>,
            scales: FloatTensor<Self>,
            opacities: FloatTensor<Self>,
            gates: FloatTensor<Self>,
            colors: FloatTensor<Self>,
            means2d_probe: FloatTensor<Self>,
            camera: RasterCamera,
            background: [f32; 3],
        ) -> RasterForward<Self> {
            let client = means.client.clone();
            let f = CubeBackend::rasterize_forward(
                inner_float(means),
                inner_float(quats),
                inner_float(scales),
                inner_float(opacities),
                inner_float(gates),
                inner_float(colors),
                inner_float(means2d_probe),
                camera,
                background,
            );
            outer_forward(&client, f)
        }

        fn rasterize_backward(
            means: FloatTensor<Self>,
            quats: FloatTensor<Self>,
            scales: FloatTensor<Self>,
            opacities: FloatTensor<Self>,
            gates: FloatTensor<Self>,
            colors: FloatTensor<Self>,
            forward: RasterForward<Self>,
            grad_image_alpha: FloatTensor<Self>,
            camera: RasterCamera,
            background: [f32; 3],
        ) -> RasterGrads<Self> {
            let client = means.client.clone();
            let forward = RasterForward {
                image_alpha: inner_float(forward.image_alpha),
                projected: inner_float(forward.projected),
                tile_offsets: inner_int(forward.tile_offsets),
                gaussian_from_intersection: inner_int(forward.gaussian_from_intersection),
                final_transmittance: inner_float(forward.final_transmittance),
                n_contrib: inner_int(forward.n_contrib),
            };
            let g = CubeBackend::rasterize_backward(
                inner_float(means),
                inner_float(quats),
                inner_float(scales),
                inner_float(opacities),
                inner_float(gates),
                inner_float(colors),
                forward,
                inner_float(grad_image_alpha),
                camera,
                background,
            );
            RasterGrads {
                means: register(&client, g.means),
                quats: register(&client, g.quats),
                scales: register(&client, g.scales),
                opacities: register(&client, g.opacities),
                colors: register(&client, g.colors),
                means2d: register(&client, g.means2d),
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Autodiff: hand-written backward.

/// Float parents of the rasterize node, in this order.
const PARENTS: usize = 6; // means, quats, scales, opacities, colors, means2d_probe

#[derive(Debug)]
struct RasterizeBackward;

#[derive(Clone, Debug)]
struct RasterTape<B: Backend> {
    means: FloatTensor<B>,
    quats: FloatTensor<B>,
    scales: FloatTensor<B>,
    opacities: FloatTensor<B>,
    gates: FloatTensor<B>,
    colors: FloatTensor<B>,
    forward: RasterForward<B>,
    camera: RasterCamera,
    background: [f32; 3],
}

impl<B: GaussianRasterBackend> Backward<B, PARENTS> for RasterizeBackward {
    type State = RasterTape<B>;

    fn backward(
        self,
        ops: Ops<Self::State, PARENTS>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad_image_alpha = grads.consume::<B>(&ops.node);
        let tape = ops.state;
        let g = B::rasterize_backward(
            tape.means,
            tape.quats,
            tape.scales,
            tape.opacities,
            tape.gates,
            tape.colors,
            tape.forward,
            grad_image_alpha,
            tape.camera,
            tape.background,
        );
        let [means, quats, scales, opacities, colors, probe] = ops.parents;
        for (parent, grad) in [
            (means, g.means),
            (quats, g.quats),
            (scales, g.scales),
            (opacities, g.opacities),
            (colors, g.colors),
            (probe, g.means2d),
        ] {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: GaussianRasterBackend, C: CheckpointStrategy> GaussianRasterBackend for Autodiff<B, C> {
    fn rasterize_forward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterForward<Self> {
        let (means, means_node) = means.into_parts();
        let (quats, quats_node) = quats.into_parts();
        let (scales, scales_node) = scales.into_parts();
        let (opacities, opacities_node) = opacities.into_parts();
        let (colors, colors_node) = colors.into_parts();
        let (probe, probe_node) = means2d_probe.into_parts();
        // Gates are constants (binary masks decided outside the rasterizer): no gradient.
        let gates = gates.into_primitive();
        let nodes = [
            means_node,
            quats_node,
            scales_node,
            opacities_node,
            colors_node,
            probe_node,
        ];

        let forward = B::rasterize_forward(
            means.clone(),
            quats.clone(),
            scales.clone(),
            opacities.clone(),
            gates.clone(),
            colors.clone(),
            probe,
            camera,
            background,
        );
        let image_alpha = match RasterizeBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let tape = RasterTape {
                    means,
                    quats,
                    scales,
                    opacities,
                    gates,
                    colors,
                    forward: forward.clone(),
                    camera,
                    background,
                };
                prep.finish(tape, forward.image_alpha.clone())
            }
            OpsKind::UnTracked(prep) => prep.finish(forward.image_alpha.clone()),
        };
        RasterForward {
            image_alpha,
            projected: Self::from_inner(forward.projected),
            tile_offsets: forward.tile_offsets,
            gaussian_from_intersection: forward.gaussian_from_intersection,
            final_transmittance: Self::from_inner(forward.final_transmittance),
            n_contrib: forward.n_contrib,
        }
    }

    fn rasterize_backward(
        means: FloatTensor<Self>,
        quats: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        gates: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self> {
        // Not differentiable itself (no double backward): run on the inner backend.
        let inner_forward = RasterForward {
            image_alpha: Self::inner(forward.image_alpha),
            projected: Self::inner(forward.projected),
            tile_offsets: forward.tile_offsets,
            gaussian_from_intersection: forward.gaussian_from_intersection,
            final_transmittance: Self::inner(forward.final_transmittance),
            n_contrib: forward.n_contrib,
        };
        let g = B::rasterize_backward(
            Self::inner(means),
            Self::inner(quats),
            Self::inner(scales),
            Self::inner(opacities),
            Self::inner(gates),
            Self::inner(colors),
            inner_forward,
            Self::inner(grad_image_alpha),
            camera,
            background,
        );
        RasterGrads {
            means: Self::from_inner(g.means),
            quats: Self::from_inner(g.quats),
            scales: Self::from_inner(g.scales),
            opacities: Self::from_inner(g.opacities),
            colors: Self::from_inner(g.colors),
            means2d: Self::from_inner(g.means2d),
        }
    }
}
