//! Fused SSIM for the training loss: forward and hand-written backward in one host pass, as a
//! Burn backend extension (the role `fused_ssim` plays for GIFStream, spec §6, §19).
//!
//! Same definition as acags' `train::losses::ssim` and `eval::metrics::ssim` (11-tap Gaussian, σ 1.5, valid region,
//! mean over pixels and channels), differentiable with respect to the render only. On ndarray
//! Burn's `conv_transpose2d` made the SSIM backward ~40 % of a training step; here both passes
//! are separable 11-tap filters, O(11·pixels). The Cube (wgpu) implementation is a host round
//! trip: GPU callers use the convolution version instead (acags' `train::losses` picks).
//!
//! With blurred moments μx, μy, m2x = G∗x², m2y, mxy = G∗xy and
//! A1 = 2μxμy + C1, A2 = 2(mxy − μxμy) + C2, B1 = μx² + μy² + C1, B2 = m2x − μx² + m2y − μy² + C2,
//! S = A1·A2 / (B1·B2) and
//! ∂S/∂μx = S(2μy/A1 − 2μy/A2 − 2μx/B1 + 2μx/B2), ∂S/∂m2x = −S/B2, ∂S/∂mxy = 2S/A2, so
//! ∂L/∂x = Gᵀ(∂S/∂μx) + 2x·Gᵀ(∂S/∂m2x) + y·Gᵀ(∂S/∂mxy), Gᵀ the transposed valid filter.

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend.

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::backend::HostIo;

pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;

/// Normalised 1D Gaussian taps of the SSIM window.
pub fn gaussian_taps() -> [f64; SSIM_WINDOW] {
    let half = (SSIM_WINDOW / 2) as f64;
    let mut taps: [f64; SSIM_WINDOW] = std::array::from_fn(|i| {
        let x = i as f64 - half;
        (-(x * x) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp()
    });
    let sum: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= sum);
    taps
}

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait FusedSsimBackend: Backend {
    /// Mean SSIM [1] of two [H, W, 3] images, H, W ≥ 11.
    fn fused_ssim(render: FloatTensor<Self>, target: FloatTensor<Self>) -> FloatTensor<Self>;

    /// ∂(grad · SSIM)/∂render, [H, W, 3]; `grad` is [1].
    fn fused_ssim_backward(
        render: FloatTensor<Self>,
        target: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

fn taps() -> [f32; SSIM_WINDOW] {
    gaussian_taps().map(|t| t as f32)
}

/// Valid separable filter of a [h, w] plane → [h − 10, w − 10].
///
/// Both passes run a whole row per tap (`out[x] += t_k · row[x + k]` for k = 0..11), which LLVM
/// vectorises; per pixel the products are added in the same order as the scalar dot product
/// `Σ_k t_k · row[x + k]` (starting from −0.0, as `Iterator::sum` does), so the result is the same
/// to the bit: a per-pixel dot product was ~7 % of a CPU training step's samples.
fn blur_valid(plane: &[f32], w: usize, h: usize, taps: &[f32; SSIM_WINDOW]) -> Vec<f32> {
    let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut horizontal = vec![-0.0f32; ow * h];
    for (out, row) in horizontal.chunks_exact_mut(ow).zip(plane.chunks_exact(w)) {
        for (k, &t) in taps.iter().enumerate() {
            for (o, &v) in out.iter_mut().zip(&row[k..k + ow]) {
                *o += t * v;
            }
        }
    }
    let mut out = vec![0.0f32; ow * oh];
    for (y, dst) in out.chunks_exact_mut(ow).enumerate() {
        for (k, &t) in taps.iter().enumerate() {
            let src = &horizontal[(y + k) * ow..(y + k + 1) * ow];
            for (o, &s) in dst.iter_mut().zip(src) {
                *o += t * s;
            }
        }
    }
    out
}

/// Transpose of [`blur_valid`]: [h − 10, w − 10] → [h, w].
///
/// The horizontal scatter runs the taps from the last to the first, a whole row each: output
/// pixel j then receives t_k · src[j − k] in increasing source order, the order of the scalar
/// scatter `for x { for k { dst[x + k] += t_k · src[x] } }`, so the result is the same to the bit.
fn blur_valid_transpose(map: &[f32], w: usize, h: usize, taps: &[f32; SSIM_WINDOW]) -> Vec<f32> {
    let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut vertical = vec![0.0f32; ow * h];
    for (y, src) in map.chunks_exact(ow).take(oh).enumerate() {
        for (k, &t) in taps.iter().enumerate() {
            for (o, &s) in vertical[(y + k) * ow..(y + k + 1) * ow].iter_mut().zip(src) {
                *o += t * s;
            }
        }
    }
    let mut out = vec![0.0f32; w * h];
    for (dst, src) in out.chunks_exact_mut(w).zip(vertical.chunks_exact(ow)) {
        for (k, &t) in taps.iter().enumerate().rev() {
            for (o, &s) in dst[k..k + ow].iter_mut().zip(src) {
                *o += t * s;
            }
        }
    }
    out
}

/// Per-channel blurred moments and the SSIM map.
struct ChannelMoments {
    mx: Vec<f32>,
    my: Vec<f32>,
    mxx: Vec<f32>,
    myy: Vec<f32>,
    mxy: Vec<f32>,
}

fn channel(image: &[f32], c: usize) -> Vec<f32> {
    image.iter().skip(c).step_by(3).copied().collect()
}

fn moments(x: &[f32], y: &[f32], w: usize, h: usize, taps: &[f32; SSIM_WINDOW]) -> ChannelMoments {
    let xx: Vec<f32> = x.iter().map(|v| v * v).collect();
    let yy: Vec<f32> = y.iter().map(|v| v * v).collect();
    let xy: Vec<f32> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    // Fifteen blurs over three channels: spread over the threads one by one (by channel alone,
    // two cores took two rounds for three channels).
    let planes: [&[f32]; 5] = [x, y, &xx, &yy, &xy];
    let mut blurred: Vec<Vec<f32>> = planes
        .par_iter()
        .map(|plane| blur_valid(plane, w, h, taps))
        .collect();
    let mut next = || blurred.remove(0);
    ChannelMoments {
        mx: next(),
        my: next(),
        mxx: next(),
        myy: next(),
        mxy: next(),
    }
}

/// (A1, A2, B1, B2) at one valid pixel.
fn terms(m: &ChannelMoments, i: usize) -> (f32, f32, f32, f32) {
    let (c1, c2) = (SSIM_C1 as f32, SSIM_C2 as f32);
    let (mx, my) = (m.mx[i], m.my[i]);
    (
        2.0 * mx * my + c1,
        2.0 * (m.mxy[i] - mx * my) + c2,
        mx * mx + my * my + c1,
        (m.mxx[i] - mx * mx) + (m.myy[i] - my * my) + c2,
    )
}

fn check_size(w: usize, h: usize, len: usize) {
    assert!(
        w >= SSIM_WINDOW && h >= SSIM_WINDOW,
        "fused SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {w}x{h}"
    );
    assert_eq!(len, w * h * 3, "fused SSIM expects [H, W, 3] images");
}

/// Mean SSIM of two interleaved [h, w, 3] images.
pub fn ssim_host(render: &[f32], target: &[f32], w: usize, h: usize) -> f32 {
    check_size(w, h, render.len());
    let taps = taps();
    let sums: Vec<f64> = (0..3)
        .into_par_iter()
        .map(|c| {
            let m = moments(&channel(render, c), &channel(target, c), w, h, &taps);
            (0..m.mx.len())
                .map(|i| {
                    let (a1, a2, b1, b2) = terms(&m, i);
                    (a1 * a2 / (b1 * b2)) as f64
                })
                .sum()
        })
        .collect();
    let count = 3 * (w + 1 - SSIM_WINDOW) * (h + 1 - SSIM_WINDOW);
    (sums.iter().sum::<f64>() / count as f64) as f32
}

/// ∂(grad · mean SSIM)/∂render, interleaved [h, w, 3].
pub fn ssim_backward_host(
    render: &[f32],
    target: &[f32],
    w: usize,
    h: usize,
    grad: f32,
) -> Vec<f32> {
    check_size(w, h, render.len());
    let taps = taps();
    let count = 3 * (w + 1 - SSIM_WINDOW) * (h + 1 - SSIM_WINDOW);
    let scale = grad / count as f32;
    let planes: Vec<Vec<f32>> = (0..3)
        .into_par_iter()
        .map(|c| {
            let (x, y) = (channel(render, c), channel(target, c));
            let m = moments(&x, &y, w, h, &taps);
            let n = m.mx.len();
            let (mut d_mu, mut d_m2, mut d_mxy) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            for i in 0..n {
                let (a1, a2, b1, b2) = terms(&m, i);
                let s = a1 * a2 / (b1 * b2);
                let (mx, my) = (m.mx[i], m.my[i]);
                d_mu[i] =
                    scale * s * (2.0 * my / a1 - 2.0 * my / a2 - 2.0 * mx / b1 + 2.0 * mx / b2);
                d_m2[i] = -scale * s / b2;
                d_mxy[i] = scale * 2.0 * s / a2;
            }
            let mut transposed: Vec<Vec<f32>> = [&d_mu, &d_m2, &d_mxy]
                .par_iter()
                .map(|d| blur_valid_transpose(d, w, h, &taps))
                .collect();
            let (g_mxy, g_m2, g_mu) = (
                transposed.pop().expect("three maps"),
                transposed.pop().expect("three maps"),
                transposed.pop().expect("three maps"),
            );
            (0..w * h)
                .map(|p| g_mu[p] + 2.0 * x[p] * g_m2[p] + y[p] * g_mxy[p])
                .collect()
        })
        .collect();
    let mut out = vec![0.0f32; w * h * 3];
    for (c, plane) in planes.iter().enumerate() {
        for (p, &v) in plane.iter().enumerate() {
            out[p * 3 + c] = v;
        }
    }
    out
}

fn image_size<B: Backend>(t: &FloatTensor<B>) -> (usize, usize) {
    let shape = t.shape();
    assert!(
        shape.num_dims() == 3 && shape[2] == 3,
        "fused SSIM expects [H, W, 3] images"
    );
    (shape[1], shape[0])
}

macro_rules! host_ssim_backend {
    ($backend:ty) => {
        impl FusedSsimBackend for $backend {
            fn fused_ssim(
                render: FloatTensor<Self>,
                target: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                let (w, h) = image_size::<Self>(&render);
                let device = render.device();
                let value = ssim_host(
                    &<Self as HostIo>::read_floats(render),
                    &<Self as HostIo>::read_floats(target),
                    w,
                    h,
                );
                Self::float_from_data(TensorData::new(vec![value], [1]), &device)
            }

            fn fused_ssim_backward(
                render: FloatTensor<Self>,
                target: FloatTensor<Self>,
                grad: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                let (w, h) = image_size::<Self>(&render);
                let device = render.device();
                let g = <Self as HostIo>::read_floats(grad)[0];
                let out = ssim_backward_host(
                    &<Self as HostIo>::read_floats(render),
                    &<Self as HostIo>::read_floats(target),
                    w,
                    h,
                    g,
                );
                Self::float_from_data(TensorData::new(out, [h, w, 3]), &device)
            }
        }
    };
}

host_ssim_backend!(NdArray);
host_ssim_backend!(burn::backend::Cube);

#[derive(Debug)]
struct FusedSsimBackward;

impl<B: FusedSsimBackend> Backward<B, 1> for FusedSsimBackward {
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let (render, target) = ops.state;
        let [parent] = ops.parents;
        if let Some(node) = parent {
            grads.register::<B>(node.id, B::fused_ssim_backward(render, target, grad));
        }
    }
}

impl<B: FusedSsimBackend, C: CheckpointStrategy> FusedSsimBackend for Autodiff<B, C> {
    fn fused_ssim(render: FloatTensor<Self>, target: FloatTensor<Self>) -> FloatTensor<Self> {
        let (render, node) = render.into_parts();
        // The target is a constant (ground truth): no gradient flows to it.
        let target = Self::inner(target);
        let out = B::fused_ssim(render.clone(), target.clone());
        match FusedSsimBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((render, target), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }

    fn fused_ssim_backward(
        render: FloatTensor<Self>,
        target: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        Self::from_inner(B::fused_ssim_backward(
            Self::inner(render),
            Self::inner(target),
            Self::inner(grad),
        ))
    }
}

/// Mean SSIM [1] of two [H, W, 3] images, differentiable with respect to `render`.
pub fn fused_ssim(render: Tensor<3>, target: Tensor<3>) -> Tensor<1> {
    Tensor::<1>::from_dispatch(<Dispatch as FusedSsimBackend>::fused_ssim(
        render.into_dispatch(),
        target.into_dispatch(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The filters as first written: a scalar dot product per output pixel and a scalar scatter.
    fn blur_valid_scalar(plane: &[f32], w: usize, h: usize, taps: &[f32; SSIM_WINDOW]) -> Vec<f32> {
        let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
        let mut horizontal = vec![0.0f32; ow * h];
        for y in 0..h {
            let row = &plane[y * w..(y + 1) * w];
            for x in 0..ow {
                horizontal[y * ow + x] = (0..SSIM_WINDOW).map(|k| taps[k] * row[x + k]).sum();
            }
        }
        let mut out = vec![0.0f32; ow * oh];
        for y in 0..oh {
            for k in 0..SSIM_WINDOW {
                for x in 0..ow {
                    out[y * ow + x] += taps[k] * horizontal[(y + k) * ow + x];
                }
            }
        }
        out
    }

    fn blur_valid_transpose_scalar(
        map: &[f32],
        w: usize,
        h: usize,
        taps: &[f32; SSIM_WINDOW],
    ) -> Vec<f32> {
        let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
        let mut vertical = vec![0.0f32; ow * h];
        for y in 0..oh {
            for k in 0..SSIM_WINDOW {
                for x in 0..ow {
                    vertical[(y + k) * ow + x] += taps[k] * map[y * ow + x];
                }
            }
        }
        let mut out = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..ow {
                for k in 0..SSIM_WINDOW {
                    out[y * w + x + k] += taps[k] * vertical[y * ow + x];
                }
            }
        }
        out
    }

    /// Values with every sign and a wide range of exponents, so any change in the order of the
    /// additions would show in the low bits.
    fn plane(len: usize, seed: u32) -> Vec<f32> {
        (0..len as u32)
            .map(|i| {
                let r =
                    (i ^ seed).wrapping_mul(2_654_435_761).rotate_left(13) as f32 / u32::MAX as f32;
                (r - 0.37) * 10f32.powi((i % 7) as i32 - 3)
            })
            .collect()
    }

    #[test]
    fn row_vectorised_filters_equal_the_scalar_ones_bit_for_bit() {
        let taps = taps();
        for (w, h) in [(11, 11), (12, 19), (37, 23), (64, 48)] {
            let x = plane(w * h, (w * 31 + h) as u32);
            let fast = blur_valid(&x, w, h, &taps);
            let slow = blur_valid_scalar(&x, w, h, &taps);
            let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&slow), "blur_valid at {w}x{h}");
            let m = plane((w + 1 - SSIM_WINDOW) * (h + 1 - SSIM_WINDOW), 7 + w as u32);
            let fast = blur_valid_transpose(&m, w, h, &taps);
            let slow = blur_valid_transpose_scalar(&m, w, h, &taps);
            assert_eq!(bits(&fast), bits(&slow), "blur_valid_transpose at {w}x{h}");
        }
    }
}
