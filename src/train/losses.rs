//! Differentiable image losses on Burn tensors (any backend, with autodiff).
//!
//! GIFStream's photometric loss is (1 − λ)·L1 + λ·(1 − SSIM), λ = `loss.ssim_lambda` = 0.2, with
//! fused-ssim's "valid" padding (spec §6): the same SSIM as [`crate::eval::metrics::ssim`] (11×11 Gaussian window, σ 1.5,
//! C1 = 0.01², C2 = 0.03², mean over the valid region and the channels), here as separable
//! depthwise convolutions so autodiff differentiates it.

use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use crate::device_io::is_host_device;
use crate::eval::metrics::{SSIM_C1, SSIM_C2, SSIM_WINDOW, gaussian_taps};

/// Depthwise separable Gaussian kernels for 3 channels: [3, 1, 1, 11] and [3, 1, 11, 1].
fn ssim_kernels(device: &Device) -> (Tensor<4>, Tensor<4>) {
    let taps: Vec<f32> = gaussian_taps().iter().map(|&t| t as f32).collect();
    let three: Vec<f32> = (0..3).flat_map(|_| taps.iter().copied()).collect();
    let horizontal = Tensor::<4>::from_data(
        TensorData::new(three.clone(), [3, 1, 1, SSIM_WINDOW]),
        device,
    );
    let vertical = Tensor::<4>::from_data(TensorData::new(three, [3, 1, SSIM_WINDOW, 1]), device);
    (horizontal, vertical)
}

fn blur(x: Tensor<4>, kernels: &(Tensor<4>, Tensor<4>)) -> Tensor<4> {
    let options = || ConvOptions::new([1, 1], [0, 0], [1, 1], 3);
    let x = conv2d(x, kernels.0.clone(), None, options());
    conv2d(x, kernels.1.clone(), None, options())
}

/// SSIM of two [H, W, 3] images (valid region, mean over channels and pixels); H, W ≥ 11.
pub fn ssim(render: Tensor<3>, target: Tensor<3>) -> Tensor<1> {
    let [h, w, c] = render.dims();
    assert_eq!(c, 3, "ssim expects [H, W, 3] images");
    assert!(
        h >= SSIM_WINDOW && w >= SSIM_WINDOW,
        "ssim needs images of at least 11x11, got {w}x{h}"
    );
    let kernels = ssim_kernels(&render.device());
    let to_nchw = |t: Tensor<3>| t.permute([2, 0, 1]).reshape([1, 3, h, w]);
    let (x, y) = (to_nchw(render), to_nchw(target));
    let mx = blur(x.clone(), &kernels);
    let my = blur(y.clone(), &kernels);
    let mxx = blur(x.clone() * x.clone(), &kernels);
    let myy = blur(y.clone() * y.clone(), &kernels);
    let mxy = blur(x * y, &kernels);
    let (mx2, my2, mxmy) = (mx.clone() * mx.clone(), my.clone() * my.clone(), mx * my);
    let (vx, vy, cov) = (mxx - mx2.clone(), myy - my2.clone(), mxy - mxmy.clone());
    let num = (mxmy * 2.0 + SSIM_C1 as f32) * (cov * 2.0 + SSIM_C2 as f32);
    let den = (mx2 + my2 + SSIM_C1 as f32) * (vx + vy + SSIM_C2 as f32);
    (num / den).mean()
}

/// SSIM for the training loss: the fused host version on ndarray, the convolution version
/// elsewhere (same value; both differentiable with respect to `render`).
pub fn training_ssim(render: Tensor<3>, target: Tensor<3>) -> Tensor<1> {
    if is_host_device(&render.device()) {
        crate::raster::fused_ssim::fused_ssim(render, target)
    } else {
        ssim(render, target)
    }
}

/// The photometric term of the training objective and the MSE the log reports with it.
pub struct Photometric {
    /// [1] (1 − λ)·mean|render − target| + λ·(1 − SSIM).
    pub loss: Tensor<1>,
    /// [1] mean (render − target)².
    pub mse: Tensor<1>,
}

/// Per-pixel L1 weights [H·W] for one view: `weight` on its moving pixels (`moving`, the
/// evaluation's motion mask of the view against its camera's temporal median), 1 elsewhere,
/// scaled to mean 1 so the loss keeps its scale against the regularisers and only the share of
/// the gradient between moving and static pixels changes (`loss.moving_weight`).
pub fn moving_pixel_weights(moving: &[bool], weight: f32) -> Vec<f32> {
    assert!(!moving.is_empty(), "moving_pixel_weights of an empty image");
    let count = moving.iter().filter(|&&m| m).count() as f64;
    let mean = (count * weight as f64 + (moving.len() as f64 - count)) / moving.len() as f64;
    let (on, off) = ((weight as f64 / mean) as f32, (1.0 / mean) as f32);
    moving.iter().map(|&m| if m { on } else { off }).collect()
}

/// GIFStream's photometric loss with SSIM weight `ssim_lambda` (λ = 0 skips the SSIM).
///
/// `pixel_weights` ([H, W, 1], mean 1, from [`moving_pixel_weights`]) weight the L1 term per
/// pixel: mean(w·|render − target|), which is the expectation of the plain L1 over pixels drawn
/// with probability ∝ w — DyNeRF's importance sampling of rays by their departure from the
/// temporal median (ISG, Li et al. 2022) for a renderer that draws whole images. The SSIM term
/// stays unweighted (a windowed statistic), as does the reported MSE.
pub fn photometric_loss(
    render: Tensor<3>,
    target: Tensor<3>,
    ssim_lambda: f32,
    pixel_weights: Option<Tensor<3>>,
) -> Photometric {
    let diff = render.clone() - target.clone();
    let mse = (diff.clone() * diff.clone()).mean();
    let l1 = match pixel_weights {
        Some(weights) => (diff.abs() * weights).mean(),
        None => diff.abs().mean(),
    };
    let mut loss = l1 * (1.0 - ssim_lambda);
    if ssim_lambda > 0.0 {
        loss = loss + (-training_ssim(render, target) + 1.0) * ssim_lambda;
    }
    Photometric { loss, mse }
}
