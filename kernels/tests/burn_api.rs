//! The rasterizer through the Burn API on the ndarray and ndarray+autodiff devices: gsplat
//! fixtures, the means2d probe, gates, edge cases and determinism.
#![allow(deprecated)] // Device::ndarray

mod common;

use acags_kernels::random_scene::{GaussianArrays, SceneSpec, identity_camera, random_scene};
use acags_kernels::{GaussianTensors, RasterCamera, RasterError, rasterize};
use burn::tensor::{Device, Tensor};
use common::*;

fn to_tensors(g: &GaussianArrays, device: &Device, track: bool) -> GaussianTensors {
    let t = GaussianTensors::from_arrays(g, device);
    if track { t.require_grad() } else { t }
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .unwrap()
}

#[test]
fn fixtures_through_autodiff() {
    let device = Device::ndarray().autodiff();
    for case in FIXTURE_CASES {
        let fx = load_fixture(case);
        let g = to_tensors(&fx.gaussians(), &device, true);
        let out = rasterize(&g, &fx.camera(), fx.background).unwrap();
        assert!(
            max_abs_diff(&values(out.image.clone()), &fx.image_flat()) <= 1e-4,
            "{case}: image"
        );
        assert!(
            max_abs_diff(&values(out.alpha.clone()), &fx.alpha_flat()) <= 1e-4,
            "{case}: alpha"
        );
        let visible: Vec<bool> = out.visible().into_data().to_vec::<bool>().unwrap();
        assert_eq!(visible, fx.visible, "{case}: visible");

        let grads = fixture_loss(&fx, &out).backward();
        let check = |name: &str, got: Option<Vec<f32>>, want: Vec<f32>| {
            let got = got.unwrap_or_else(|| panic!("{case}: no gradient for {name}"));
            assert_grad_close(&format!("{case} {name}"), &got, &want, 1e-3, 3e-5);
        };
        check(
            "means",
            g.means.grad(&grads).map(values),
            fx.grad_means.concat(),
        );
        check(
            "quats",
            g.quats.grad(&grads).map(values),
            fx.grad_quats.concat(),
        );
        check(
            "scales",
            g.scales.grad(&grads).map(values),
            fx.grad_scales.concat(),
        );
        check(
            "opacities",
            g.opacities.grad(&grads).map(values),
            fx.grad_opacities.clone(),
        );
        check(
            "colors",
            g.colors.grad(&grads).map(values),
            fx.grad_colors.concat(),
        );
        check(
            "means2d",
            out.means2d_grad(&grads).map(values),
            fx.grad_means2d.concat(),
        );
    }
}

#[test]
fn forward_on_plain_ndarray_matches_autodiff_device() {
    let fx = load_fixture("random_small");
    let plain = rasterize(
        &to_tensors(&fx.gaussians(), &Device::ndarray(), false),
        &fx.camera(),
        fx.background,
    )
    .unwrap();
    let tracked = rasterize(
        &to_tensors(&fx.gaussians(), &Device::ndarray().autodiff(), true),
        &fx.camera(),
        fx.background,
    )
    .unwrap();
    assert_eq!(values(plain.image.clone()), values(tracked.image));
    assert_eq!(values(plain.means2d), values(tracked.means2d));
    // Without autodiff there is no probe to read a means2d gradient from.
    assert!(plain.image.is_autodiff() == false);
}

/// Gate 0 renders exactly as if the Gaussian were absent, and gets zero gradient.
#[test]
fn gated_gaussian_is_absent_and_gets_no_gradient() {
    let camera = identity_camera(80, 56);
    let scene = random_scene(&camera, &SceneSpec::new(60, 3));
    let device = Device::ndarray().autodiff();
    let gated_ids = [3usize, 17, 40];
    let mut gated = scene.clone();
    for &i in &gated_ids {
        gated.gates[i] = 0.0;
    }
    let mut removed = GaussianArrays::default();
    for i in (0..scene.len()).filter(|i| !gated_ids.contains(i)) {
        removed
            .means
            .extend_from_slice(&scene.means[3 * i..3 * i + 3]);
        removed
            .quats
            .extend_from_slice(&scene.quats[4 * i..4 * i + 4]);
        removed
            .scales
            .extend_from_slice(&scene.scales[3 * i..3 * i + 3]);
        removed.opacities.push(scene.opacities[i]);
        removed.gates.push(1.0);
        removed
            .colors
            .extend_from_slice(&scene.colors[3 * i..3 * i + 3]);
    }
    let bg = [0.2, 0.3, 0.4];
    let weights = Tensor::<3>::random(
        [56, 80, 3],
        burn::tensor::Distribution::Normal(0.0, 1.0),
        &device,
    );
    let run = |g: &GaussianArrays| {
        let t = to_tensors(g, &device, true);
        let out = rasterize(&t, &camera, bg).unwrap();
        let loss = (out.image.clone() * weights.clone()).sum() + out.alpha.clone().sum();
        let grads = loss.backward();
        (
            values(out.image.clone()),
            values(t.means.grad(&grads).unwrap()),
            values(out.means2d_grad(&grads).unwrap()),
        )
    };
    let (img_gated, gm_gated, g2d_gated) = run(&gated);
    let (img_removed, gm_removed, _) = run(&removed);
    assert_eq!(img_gated, img_removed, "a gated Gaussian changed the image");
    let kept: Vec<usize> = (0..scene.len())
        .filter(|i| !gated_ids.contains(i))
        .collect();
    for (j, &i) in kept.iter().enumerate() {
        assert_eq!(
            &gm_gated[3 * i..3 * i + 3],
            &gm_removed[3 * j..3 * j + 3],
            "gradient of Gaussian {i} changed"
        );
    }
    for &i in &gated_ids {
        assert!(gm_gated[3 * i..3 * i + 3].iter().all(|v| *v == 0.0));
        assert!(g2d_gated[2 * i..2 * i + 2].iter().all(|v| *v == 0.0));
    }
    // The scene is not trivially empty: the gated Gaussians were visible when ungated.
    let ungated = rasterize(&to_tensors(&scene, &device, false), &camera, bg).unwrap();
    let visible: Vec<bool> = ungated.visible().into_data().to_vec().unwrap();
    assert!(gated_ids.iter().all(|&i| visible[i]));
}

#[test]
fn empty_scene_renders_background() {
    let camera = identity_camera(37, 23);
    let device = Device::ndarray().autodiff();
    let out = rasterize(
        &to_tensors(&GaussianArrays::default(), &device, true),
        &camera,
        [0.1, 0.5, 0.9],
    )
    .unwrap();
    let image = values(out.image.clone());
    assert_eq!(image.len(), 37 * 23 * 3);
    assert!(image.chunks(3).all(|p| p == [0.1, 0.5, 0.9]));
    assert!(values(out.alpha.clone()).iter().all(|a| *a == 0.0));
    let grads = out.image.clone().sum().backward();
    assert_eq!(out.means2d_grad(&grads).map(|g| g.dims()), Some([0, 2]));
}

#[test]
fn all_culled_scene_renders_background_with_zero_gradients() {
    let camera = identity_camera(48, 32);
    let mut scene = random_scene(&camera, &SceneSpec::new(20, 5));
    for i in 0..scene.len() {
        scene.means[3 * i + 2] = -scene.means[3 * i + 2]; // behind the camera
    }
    let device = Device::ndarray().autodiff();
    let t = to_tensors(&scene, &device, true);
    let out = rasterize(&t, &camera, [0.3, 0.3, 0.3]).unwrap();
    assert!(values(out.image.clone()).iter().all(|v| *v == 0.3));
    assert_eq!(out.intersection_count(), 0);
    let grads = (out.image.sum() + out.alpha.sum()).backward();
    for grad in [
        t.means.grad(&grads),
        t.scales.grad(&grads),
        t.colors.grad(&grads),
    ] {
        assert!(values(grad.unwrap()).iter().all(|v| *v == 0.0));
    }
}

/// A 1x1 image with one Gaussian centred on the pixel: sigma = 0 there, so alpha = opacity and
/// the pixel is o*c + (1 - o)*bg, with d(pixel)/d(color) = o and d(alpha)/d(opacity) = 1.
#[test]
fn one_pixel_image_has_the_analytic_value() {
    let camera = RasterCamera {
        cx: 0.5,
        cy: 0.5,
        ..identity_camera(1, 1)
    };
    let g = GaussianArrays {
        means: vec![0.0, 0.0, 2.0],
        quats: vec![1.0, 0.0, 0.0, 0.0],
        scales: vec![0.01, 0.02, 0.01],
        opacities: vec![0.6],
        gates: vec![1.0],
        colors: vec![1.0, 0.5, 0.0],
    };
    let bg = [0.0, 0.0, 1.0];
    let device = Device::ndarray().autodiff();
    let t = to_tensors(&g, &device, true);
    let out = rasterize(&t, &camera, bg).unwrap();
    let image = values(out.image.clone());
    let want = [0.6, 0.3, 0.4];
    assert!(max_abs_diff(&image, &want) <= 1e-6, "{image:?}");
    assert!((values(out.alpha.clone())[0] - 0.6).abs() <= 1e-6);
    let grads = (out.image.clone().sum() + out.alpha.clone().sum()).backward();
    let color_grad = values(t.colors.grad(&grads).unwrap());
    assert!(
        max_abs_diff(&color_grad, &[0.6, 0.6, 0.6]) <= 1e-6,
        "{color_grad:?}"
    );
    // d/do [o (c_r + c_g + c_b) + (1 - o) (bg sum) + o] = 1.5 - 1 + 1.
    let opacity_grad = values(t.opacities.grad(&grads).unwrap());
    assert!((opacity_grad[0] - 1.5).abs() <= 1e-5, "{opacity_grad:?}");
    // At the centre the screen-mean gradient vanishes (sigma is stationary there).
    let g2d = values(out.means2d_grad(&grads).unwrap());
    assert!(g2d.iter().all(|v| v.abs() <= 1e-6), "{g2d:?}");
}

#[test]
fn non_finite_inputs_are_culled_never_nan() {
    let camera = identity_camera(64, 48);
    let scene = random_scene(&camera, &SceneSpec::new(30, 11));
    let device = Device::ndarray().autodiff();
    let clean = rasterize(&to_tensors(&scene, &device, false), &camera, [0.0; 3]).unwrap();
    let clean_visible: Vec<bool> = clean.visible().into_data().to_vec().unwrap();
    let mut poisoned = scene.clone();
    let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
    // One non-finite value in a different input of different Gaussians.
    poisoned.means[3 * 2] = bad[0];
    poisoned.quats[4 * 5 + 1] = bad[1];
    poisoned.scales[3 * 7 + 2] = bad[2];
    poisoned.opacities[9] = bad[0];
    poisoned.colors[3 * 11] = bad[1];
    poisoned.gates[13] = bad[0];
    poisoned.quats[4 * 15..4 * 15 + 4].copy_from_slice(&[0.0; 4]); // zero quaternion
    let t = to_tensors(&poisoned, &device, true);
    let out = rasterize(&t, &camera, [0.0; 3]).unwrap();
    let visible: Vec<bool> = out.visible().into_data().to_vec().unwrap();
    for i in [2, 5, 7, 9, 11, 13, 15] {
        assert!(
            !visible[i],
            "Gaussian {i} with a non-finite input was not culled"
        );
    }
    for i in (0..scene.len()).filter(|i| ![2, 5, 7, 9, 11, 13, 15].contains(i)) {
        assert_eq!(visible[i], clean_visible[i]);
    }
    assert!(values(out.image.clone()).iter().all(|v| v.is_finite()));
    let grads = (out.image.sum() + out.alpha.sum()).backward();
    for grad in [
        t.means.grad(&grads),
        t.quats.grad(&grads),
        t.scales.grad(&grads),
        t.colors.grad(&grads),
    ] {
        assert!(values(grad.unwrap()).iter().all(|v| v.is_finite()));
    }
}

#[test]
fn invalid_calls_are_clear_errors() {
    let camera = identity_camera(16, 16);
    let device = Device::ndarray();
    let scene = random_scene(&camera, &SceneSpec::new(4, 1));
    let g = to_tensors(&scene, &device, false);
    let err = |c: RasterCamera| rasterize(&g, &c, [0.0; 3]).unwrap_err();
    assert!(matches!(
        err(RasterCamera { width: 0, ..camera }),
        RasterError::InvalidCamera(_)
    ));
    assert!(matches!(
        err(RasterCamera { fx: -1.0, ..camera }),
        RasterError::InvalidCamera(_)
    ));
    assert!(matches!(
        err(RasterCamera {
            cy: f32::NAN,
            ..camera
        }),
        RasterError::InvalidCamera(_)
    ));
    let mut m = camera;
    m.world_to_camera[1][3] = f32::INFINITY;
    assert!(matches!(err(m), RasterError::InvalidCamera(_)));
    // Too large: a side beyond 2^20, or more than 2^26 pixels (8192²).
    for (width, height) in [((1 << 20) + 1, 1), (8193, 8192)] {
        let e = err(RasterCamera { width, height, ..camera });
        assert!(
            matches!(&e, RasterError::InvalidCamera(m) if m.contains("exceeds")),
            "{e}"
        );
    }
    assert!(matches!(
        rasterize(&g, &camera, [0.0, f32::NAN, 0.0]),
        Err(RasterError::InvalidBackground(_))
    ));
    let mut bad = g.clone();
    bad.colors = Tensor::<2>::zeros([3, 3], &device);
    let e = rasterize(&bad, &camera, [0.0; 3]).unwrap_err();
    assert!(e.to_string().contains("colors"), "{e}");
}

#[test]
fn two_runs_are_bitwise_identical() {
    let camera = identity_camera(200, 120);
    let scene = random_scene(&camera, &SceneSpec::new(3000, 21));
    let device = Device::ndarray().autodiff();
    let run = || {
        let t = to_tensors(&scene, &device, true);
        let out = rasterize(&t, &camera, [0.1, 0.1, 0.1]).unwrap();
        let image = values(out.image.clone());
        let grads = (out.image.clone() * out.image.clone()).sum().backward();
        (
            image,
            values(t.means.grad(&grads).unwrap()),
            values(t.quats.grad(&grads).unwrap()),
        )
    };
    assert!(run() == run());
}
