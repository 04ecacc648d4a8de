//! The rasterizer as a Burn backend extension.
//!
//! `GaussianRasterBackend` has one forward and one backward op. Backends implement both;
//! `Autodiff<B>` implements the forward by calling `B`'s and registering a hand-written `Backward`
//! node that calls `B`'s backward op: no autodiff graph is built through per-pixel operations.
//!
//! The forward returns the backward's state as tensors (projection, tile bins, per-pixel final
//! transmittance and contributor counts), so a GPU implementation keeps it on the device. The
//! tensor bundles crossing the op live in [`crate::raster_io`].
#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend we target.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{
    AutodiffBackend, Backend, NdArray, TensorMetadata, backend_extension, read_sync,
};
use burn::tensor::TensorData;

use burn_cubecl::CubeBackend;

use crate::camera::RasterCamera;
use crate::conventions::PROJECTED_COLUMNS;
use crate::cpu;
use crate::cube;
pub use crate::raster_io::{IntersectionCapacity, RasterForward, RasterGaussians, RasterGrads};

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait GaussianRasterBackend: Backend {
    /// Renders N gated Gaussians (shapes in [`RasterGaussians`]); `means2d_probe` [N,2] must be
    /// zeros: it only carries the screen-mean gradient back to the caller under autodiff.
    ///
    /// Callers validate camera, background and shapes first ([`crate::rasterize`] does).
    /// `capacity` sizes the intersection buffers (the CPU twin counts exactly whatever it says).
    fn rasterize_forward(
        #[extension_type] gaussians: RasterGaussians<Self>,
        means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
        capacity: IntersectionCapacity,
    ) -> RasterForward<Self>;

    /// Vector-Jacobian product of [`Self::rasterize_forward`] for dLoss/d(image_alpha).
    fn rasterize_backward(
        #[extension_type] gaussians: RasterGaussians<Self>,
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

/// The CPU twins compute in f32, as every acags tensor is: another float type would come back
/// as f32 where Burn keeps it, so it is refused.
pub(crate) fn assert_f32(t: &FloatTensor<NdArray>, what: &str) {
    assert_eq!(
        t.dtype(),
        burn::tensor::DType::F32,
        "{what}: the CPU twin takes f32 tensors"
    );
}

/// Runs `f` on an ndarray float tensor's values: straight out of its storage when that is
/// contiguous (a shared parameter table read in part, without copying all of it first), else on
/// a copy.
pub fn with_floats<R>(t: FloatTensor<NdArray>, f: impl FnOnce(&[f32]) -> R) -> R {
    if let burn::backend::ndarray::NdArrayTensor::F32(storage) = &t
        && let Some(values) = storage.view().as_slice()
    {
        return f(values);
    }
    f(&<NdArray as HostIo>::read_floats(t))
}

/// NdArray: a tensor nothing else holds gives its buffer up without a copy; a shared one is
/// copied straight out of contiguous f32 storage (its generic `into_data` walks the array
/// element by element, ~25x slower).
impl HostIo for NdArray {
    fn read_floats(t: FloatTensor<Self>) -> Vec<f32> {
        use burn::backend::ndarray::NdArrayTensor;
        if let NdArrayTensor::F32(storage) = &t
            && storage.is_unique()
            && storage.view().is_standard_layout()
            && let NdArrayTensor::F32(storage) = t
        {
            let array = storage.into_owned();
            let len = array.len();
            // Unique: `into_owned` unwraps the Arc instead of cloning the elements.
            let (mut values, offset) = array.into_owned().into_raw_vec_and_offset();
            let offset = offset.unwrap_or(0);
            if offset == 0 {
                values.truncate(len);
                return values;
            }
            return values[offset..offset + len].to_vec();
        }
        if let NdArrayTensor::F32(storage) = &t
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

fn projected_rows(projected: &[cpu::Projected]) -> Vec<f32> {
    projected.iter().flat_map(cpu::Projected::to_row).collect()
}

fn projected_from_rows(rows: &[f32]) -> Vec<cpu::Projected> {
    rows.chunks_exact(PROJECTED_COLUMNS)
        .map(cpu::Projected::from_row)
        .collect()
}

fn host_forward<B: HostIo>(
    gaussians: RasterGaussians<B>,
    camera: RasterCamera,
    background: [f32; 3],
) -> RasterForward<B> {
    let device = gaussians.means.device();
    let inputs = gaussians.to_host(B::read_floats);
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
        intersections: upload_indices::<B>(&[state.bins.intersection_count() as u32], &device),
    }
}

fn host_backward<B: HostIo>(
    gaussians: RasterGaussians<B>,
    forward: RasterForward<B>,
    grad_image_alpha: FloatTensor<B>,
    camera: RasterCamera,
    background: [f32; 3],
) -> RasterGrads<B> {
    let device = gaussians.means.device();
    let inputs = gaussians.to_host(B::read_floats);
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

// NdArray: the CPU twin itself (the copies in and out are O(N + pixels), negligible next to
// compositing).
impl GaussianRasterBackend for NdArray {
    fn rasterize_forward(
        gaussians: RasterGaussians<Self>,
        _means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
        _capacity: IntersectionCapacity,
    ) -> RasterForward<Self> {
        host_forward::<Self>(gaussians, camera, background)
    }

    fn rasterize_backward(
        gaussians: RasterGaussians<Self>,
        forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self> {
        host_backward::<Self>(gaussians, forward, grad_image_alpha, camera, background)
    }
}

// ---------------------------------------------------------------------------------------------
// Cube (wgpu, CUDA): the CubeCL kernels (`crate::cube`), whose device types are these bundles.

impl GaussianRasterBackend for CubeBackend {
    fn rasterize_forward(
        gaussians: RasterGaussians<Self>,
        _means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
        capacity: IntersectionCapacity,
    ) -> RasterForward<Self> {
        cube::forward(&cube::device_gaussians(gaussians), &camera, background, capacity)
    }

    fn rasterize_backward(
        gaussians: RasterGaussians<Self>,
        forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self> {
        let gaussians = cube::device_gaussians(gaussians);
        cube::backward(&gaussians, &forward, grad_image_alpha, &camera, background)
    }
}

/// The fused wgpu device (`burn::backend::Cube` = `Fusion<CubeBackend>`): the rasterizer is one
/// opaque step of the stream. Its inputs are resolved (the queued work that produces them runs),
/// the kernels run on the inner tensors, and the outputs are registered back as fresh tensors.
/// Not a `#[fusion]` custom op: the intersection buffers are sized by a count only the device
/// knows, and custom ops need their output shapes up front.
pub(crate) mod fused {
    use super::*;
    use burn::backend::fusion::{Client, Fusion, FusionBackend, NoOp, stream::StreamId};
    use burn::backend::ir::{BackendIr, InitOperationIr, OperationIr, OperationOutput};

    pub(crate) type Runtime = <CubeBackend as FusionBackend>::FusionRuntime;

    pub(crate) fn inner_float(t: FloatTensor<Fusion<CubeBackend>>) -> FloatTensor<CubeBackend> {
        t.client.clone().resolve_tensor_float::<CubeBackend>(t)
    }

    pub(crate) fn inner_int(t: IntTensor<Fusion<CubeBackend>>) -> IntTensor<CubeBackend> {
        t.client.clone().resolve_tensor_int::<CubeBackend>(t)
    }

    pub(crate) fn register(
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

    impl GaussianRasterBackend for Fusion<CubeBackend> {
        fn rasterize_forward(
            gaussians: RasterGaussians<Self>,
            means2d_probe: FloatTensor<Self>,
            camera: RasterCamera,
            background: [f32; 3],
            capacity: IntersectionCapacity,
        ) -> RasterForward<Self> {
            let client = gaussians.means.client.clone();
            let f = CubeBackend::rasterize_forward(
                gaussians.map(inner_float),
                inner_float(means2d_probe),
                camera,
                background,
                capacity,
            );
            // Int tensors are registered through the same float-handle path (a handle is bytes).
            f.map(|t| register(&client, t), |t| register(&client, t))
        }

        fn rasterize_backward(
            gaussians: RasterGaussians<Self>,
            forward: RasterForward<Self>,
            grad_image_alpha: FloatTensor<Self>,
            camera: RasterCamera,
            background: [f32; 3],
        ) -> RasterGrads<Self> {
            let client = gaussians.means.client.clone();
            let g = CubeBackend::rasterize_backward(
                gaussians.map(inner_float),
                forward.map(inner_float, inner_int),
                inner_float(grad_image_alpha),
                camera,
                background,
            );
            g.map(|t| register(&client, t))
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
    gaussians: RasterGaussians<B>,
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
            tape.gaussians,
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
        gaussians: RasterGaussians<Self>,
        means2d_probe: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
        capacity: IntersectionCapacity,
    ) -> RasterForward<Self> {
        let (means, means_node) = gaussians.means.into_parts();
        let (quats, quats_node) = gaussians.quats.into_parts();
        let (scales, scales_node) = gaussians.scales.into_parts();
        let (opacities, opacities_node) = gaussians.opacities.into_parts();
        let (colors, colors_node) = gaussians.colors.into_parts();
        let (probe, probe_node) = means2d_probe.into_parts();
        // Gates are constants (binary masks decided outside the rasterizer): no gradient.
        let gates = gaussians.gates.into_primitive();
        let nodes = [
            means_node,
            quats_node,
            scales_node,
            opacities_node,
            colors_node,
            probe_node,
        ];
        let inner = RasterGaussians {
            means,
            quats,
            scales,
            opacities,
            gates,
            colors,
        };

        let forward = B::rasterize_forward(inner.clone(), probe, camera, background, capacity);
        let image_alpha = match RasterizeBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let tape = RasterTape {
                    gaussians: inner,
                    forward: forward.clone(),
                    camera,
                    background,
                };
                prep.finish(tape, forward.image_alpha.clone())
            }
            OpsKind::UnTracked(prep) => prep.finish(forward.image_alpha.clone()),
        };
        // Only the image is tracked; the rest of the state is passed through.
        RasterForward {
            image_alpha,
            ..forward.map(Self::from_inner, |t| t)
        }
    }

    fn rasterize_backward(
        gaussians: RasterGaussians<Self>,
        forward: RasterForward<Self>,
        grad_image_alpha: FloatTensor<Self>,
        camera: RasterCamera,
        background: [f32; 3],
    ) -> RasterGrads<Self> {
        // Not differentiable itself (no double backward): run on the inner backend.
        B::rasterize_backward(
            gaussians.map(Self::inner),
            forward.map(Self::inner, |t| t),
            Self::inner(grad_image_alpha),
            camera,
            background,
        )
        .map(Self::from_inner)
    }
}
