//! The CPU twin against gsplat 1.5.3's own outputs and gradients (../shared/fixtures/gsplat).

mod common;

use acags_kernels::cpu;
use common::*;

/// Tolerances from the fixture README ("Suggested tolerances").
const IMAGE_ATOL: f32 = 1e-4;
const GRAD_RTOL: f32 = 1e-3;
const GRAD_ATOL_REL: f32 = 3e-5;

fn check_case(case: &str) {
    let fx = load_fixture(case);
    let camera = fx.camera();
    let g = fx.gaussians();
    let state = cpu::forward(&g.slices(), &camera, fx.background).unwrap();

    // Projection diagnostics.
    for (i, p) in state.projected.iter().enumerate() {
        assert_eq!(cpu::is_visible(p), fx.visible[i], "{case}: visible[{i}]");
        assert_eq!(p.radius, fx.radii[i], "{case}: radii[{i}]");
        if fx.visible[i] {
            for a in 0..2 {
                assert!(
                    (p.mean2d[a] - fx.means2d[i][a]).abs() <= 1e-3,
                    "{case}: means2d[{i}]"
                );
            }
            assert!(
                ((p.depth - fx.depths[i]) / fx.depths[i]).abs() <= 1e-5,
                "{case}: depth[{i}]"
            );
        }
    }
    let conics: Vec<f32> = state.projected.iter().flat_map(|p| p.conic).collect();
    let want_conics: Vec<f32> = fx.conics.concat();
    assert_grad_close(&format!("{case} conics"), &conics, &want_conics, 1e-3, 1e-6);

    let image: Vec<f32> = state
        .composite
        .image_alpha
        .chunks(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let alpha: Vec<f32> = state
        .composite
        .image_alpha
        .chunks(4)
        .map(|p| p[3])
        .collect();
    let image_err = max_abs_diff(&image, &fx.image_flat());
    let alpha_err = max_abs_diff(&alpha, &fx.alpha_flat());
    assert!(
        image_err <= IMAGE_ATOL,
        "{case}: image max abs error {image_err}"
    );
    assert!(
        alpha_err <= IMAGE_ATOL,
        "{case}: alpha max abs error {alpha_err}"
    );

    let upstream = fx.upstream_packed();
    let loss: f64 = state
        .composite
        .image_alpha
        .iter()
        .zip(&upstream)
        .map(|(a, b)| *a as f64 * *b as f64)
        .sum();
    assert!(
        ((loss - fx.loss) / fx.loss).abs() <= 1e-5,
        "{case}: loss {loss} vs {}",
        fx.loss
    );

    let grads = cpu::backward(&g.slices(), &camera, fx.background, &state, &upstream).unwrap();
    let check = |name: &str, got: &[f32], want: Vec<f32>| {
        assert_grad_close(
            &format!("{case} grad_{name}"),
            got,
            &want,
            GRAD_RTOL,
            GRAD_ATOL_REL,
        )
    };
    check("means", &grads.means, fx.grad_means.concat());
    check("quats", &grads.quats, fx.grad_quats.concat());
    check("scales", &grads.scales, fx.grad_scales.concat());
    check("opacities", &grads.opacities, fx.grad_opacities.clone());
    check("colors", &grads.colors, fx.grad_colors.concat());
    check("means2d", &grads.means2d, fx.grad_means2d.concat());

    // Culled Gaussians get exactly zero gradient.
    for (i, visible) in fx.visible.iter().enumerate() {
        if !visible {
            assert!(
                grads.means[3 * i..3 * i + 3].iter().all(|v| *v == 0.0),
                "{case}: culled {i} has a gradient"
            );
            assert_eq!(grads.opacities[i], 0.0);
            assert!(grads.means2d[2 * i..2 * i + 2].iter().all(|v| *v == 0.0));
        }
    }
}

#[test]
fn single() {
    check_case("single");
}

#[test]
fn random_small() {
    check_case("random_small");
}

#[test]
fn occlusion_saturation() {
    check_case("occlusion_saturation");
}

#[test]
fn border_and_large() {
    check_case("border_and_large");
}

#[test]
fn near_plane_and_behind() {
    check_case("near_plane_and_behind");
}

#[test]
fn anisotropic_rotated() {
    check_case("anisotropic_rotated");
}
