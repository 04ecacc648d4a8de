//! The fused host SSIM equals the convolution SSIM, and its hand-written backward equals autodiff
//! through the convolution version.
#![allow(deprecated)] // Device::ndarray

use acags::raster::fused_ssim::{fused_ssim, ssim_backward_host, ssim_host};
use acags::device_io::is_host_device;
use acags::train::losses::ssim;
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};

fn images(w: usize, h: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let target: Vec<f32> = (0..w * h * 3).map(|_| rng.random::<f32>()).collect();
    // A render correlated with the target, so SSIM is far from 0 and from 1.
    let render = target
        .iter()
        .map(|t| (0.7 * t + 0.3 * rng.random::<f32>()).clamp(0.0, 1.0))
        .collect();
    (render, target)
}

fn t3(v: &[f32], h: usize, w: usize, d: &Device) -> Tensor<3> {
    Tensor::<3>::from_data(TensorData::new(v.to_vec(), [h, w, 3]), d)
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap()
}

#[test]
fn fused_ssim_matches_the_convolution_version_and_its_gradient() {
    let device = Device::ndarray().autodiff();
    assert!(is_host_device(&device));
    for (w, h, seed) in [(11, 11, 1), (37, 23, 2), (64, 48, 3)] {
        let (render, target) = images(w, h, seed);
        let conv_render = t3(&render, h, w, &device).require_grad();
        let conv = ssim(conv_render.clone(), t3(&target, h, w, &device));
        let conv_value = values(conv.clone())[0];
        let host_value = ssim_host(&render, &target, w, h);
        assert!(
            (conv_value - host_value).abs() < 1e-5,
            "{w}x{h}: fused {host_value} vs conv {conv_value}"
        );
        let want = values(conv_render.grad(&(conv * 2.5).backward()).unwrap());
        let got = ssim_backward_host(&render, &target, w, h, 2.5);
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        for (i, (g, e)) in got.iter().zip(&want).enumerate() {
            assert!(
                (g - e).abs() <= 1e-3 * scale + 1e-7,
                "{w}x{h} element {i}: fused grad {g} vs autodiff {e}"
            );
        }
        // Through Burn autodiff: the extension op registers the same gradient.
        let fused_render = t3(&render, h, w, &device).require_grad();
        let fused = fused_ssim(fused_render.clone(), t3(&target, h, w, &device));
        assert!((values(fused.clone())[0] - host_value).abs() < 1e-6);
        let through = values(fused_render.grad(&(fused * 2.5).backward()).unwrap());
        assert_eq!(through, got);
    }
}

#[test]
fn fused_ssim_gradient_matches_finite_differences() {
    let (w, h) = (16, 13);
    let (render, target) = images(w, h, 7);
    let grad = ssim_backward_host(&render, &target, w, h, 1.0);
    let eps = 1e-2f32;
    for i in [0usize, 5, 100, 311, w * h * 3 - 1] {
        let mut plus = render.clone();
        plus[i] += eps;
        let mut minus = render.clone();
        minus[i] -= eps;
        let fd = (ssim_host(&plus, &target, w, h) as f64 - ssim_host(&minus, &target, w, h) as f64)
            / (2.0 * eps as f64);
        assert!(
            (fd - grad[i] as f64).abs() < 2e-4,
            "element {i}: finite difference {fd} vs {}",
            grad[i]
        );
    }
}

#[test]
fn identical_images_have_ssim_one_and_zero_gradient() {
    let (w, h) = (20, 15);
    let (_, target) = images(w, h, 9);
    assert!((ssim_host(&target, &target, w, h) - 1.0).abs() < 1e-5);
    let grad = ssim_backward_host(&target, &target, w, h, 1.0);
    assert!(
        grad.iter().all(|g| g.abs() < 1e-4),
        "SSIM is maximal: gradient must vanish"
    );
}
