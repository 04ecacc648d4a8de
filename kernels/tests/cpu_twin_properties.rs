//! Properties of the CPU twin: tile binning loses nothing (equal to a dense per-pixel reference at
//! awkward image sizes), finite differences for every input, determinism.

mod common;

use acags_kernels::RasterCamera;
use acags_kernels::conventions::{ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_STOP};
use acags_kernels::cpu::composite::exp_f32;
use acags_kernels::cpu::{self, ProjectionCamera};
use acags_kernels::random_scene::{GaussianArrays, SceneSpec, identity_camera, random_scene};
use rand::{Rng, SeedableRng, rngs::StdRng};

/// Every visible Gaussian against every pixel, in depth order: no tiles at all.
fn dense_reference(g: &GaussianArrays, camera: &RasterCamera, bg: [f32; 3]) -> Vec<f32> {
    let projected = cpu::project_all(&g.slices(), &ProjectionCamera::new(camera));
    let mut order: Vec<usize> = (0..g.len())
        .filter(|&i| cpu::is_visible(&projected[i]))
        .collect();
    order.sort_by(|&a, &b| projected[a].depth.total_cmp(&projected[b].depth));
    let mut out = Vec::new();
    for y in 0..camera.height {
        for x in 0..camera.width {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let mut t = 1.0f32;
            let mut c = [0.0f32; 3];
            for &i in &order {
                let p = &projected[i];
                let (dx, dy) = (p.mean2d[0] - px, p.mean2d[1] - py);
                let [a, b, cc] = p.conic;
                let sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
                if sigma < 0.0 {
                    continue;
                }
                let alpha = (g.gates[i] * g.opacities[i] * exp_f32(-sigma)).min(ALPHA_MAX);
                if alpha < ALPHA_MIN {
                    continue;
                }
                let next = t * (1.0 - alpha);
                if next <= TRANSMITTANCE_STOP {
                    break;
                }
                let weight = alpha * t; // same rounding order as the tiled path
                for k in 0..3 {
                    c[k] += g.colors[3 * i + k] * weight;
                }
                t = next;
            }
            out.extend([
                c[0] + t * bg[0],
                c[1] + t * bg[1],
                c[2] + t * bg[2],
                1.0 - t,
            ]);
        }
    }
    out
}

#[test]
fn tiled_forward_equals_dense_reference_at_awkward_sizes() {
    for (k, (w, h)) in [
        (37u32, 23u32),
        (100, 17),
        (16, 17),
        (17, 16),
        (1, 1),
        (5, 64),
    ]
    .into_iter()
    .enumerate()
    {
        let camera = identity_camera(w, h);
        let mut spec = SceneSpec::new(150, 100 + k as u64);
        spec.pixel_std = (0.3, 6.0);
        spec.border = 0.3;
        let scene = random_scene(&camera, &spec);
        let state = cpu::forward(&scene.slices(), &camera, [0.2, 0.1, 0.7]).unwrap();
        let dense = dense_reference(&scene, &camera, [0.2, 0.1, 0.7]);
        // Same operations in the same order per pixel: bitwise equal unless binning lost a pair.
        assert_eq!(state.composite.image_alpha, dense, "{w}x{h}");
    }
}

#[test]
fn saturated_pixels_stop_early_and_match_dense_reference() {
    let camera = identity_camera(64, 48);
    let mut spec = SceneSpec::new(400, 77);
    spec.opacity = (0.9, 0.9999);
    spec.pixel_std = (2.0, 6.0);
    let scene = random_scene(&camera, &spec);
    let state = cpu::forward(&scene.slices(), &camera, [0.0; 3]).unwrap();
    assert_eq!(
        state.composite.image_alpha,
        dense_reference(&scene, &camera, [0.0; 3])
    );
    let stopped = state
        .composite
        .final_transmittance
        .iter()
        .filter(|t| **t < 1e-3)
        .count();
    assert!(
        stopped > 100,
        "only {stopped} saturated pixels: the case does not exercise early stopping"
    );
}

fn loss(g: &GaussianArrays, camera: &RasterCamera, bg: [f32; 3], weights: &[f32]) -> f64 {
    let state = cpu::forward(&g.slices(), camera, bg).unwrap();
    state
        .composite
        .image_alpha
        .iter()
        .zip(weights)
        .map(|(a, w)| *a as f64 * *w as f64)
        .sum()
}

/// Zeroes the loss weight of every pixel where some Gaussian's alpha is within `margin` (in ln
/// units) of the 1/255 cut-off: there a small perturbation can switch the pair on or off, a jump
/// that no gradient describes. Elsewhere the loss is smooth and finite differences are exact.
fn mask_threshold_pixels(
    g: &GaussianArrays,
    camera: &RasterCamera,
    weights: &mut [f32],
    margin: f32,
) -> usize {
    let projected = cpu::project_all(&g.slices(), &ProjectionCamera::new(camera));
    let mut masked = 0;
    for y in 0..camera.height {
        for x in 0..camera.width {
            let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
            let near_cut = (0..g.len())
                .filter(|&i| cpu::is_visible(&projected[i]))
                .any(|i| {
                    let p = &projected[i];
                    let (dx, dy) = (p.mean2d[0] - px, p.mean2d[1] - py);
                    let sigma =
                        0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) + p.conic[1] * dx * dy;
                    (sigma - (255.0 * g.opacities[i]).ln()).abs() < margin
                });
            if near_cut {
                let p = (y * camera.width + x) as usize;
                weights[4 * p..4 * p + 4].fill(0.0);
                masked += 1;
            }
        }
    }
    masked
}

/// Central differences for every element of every input, on a loss made smooth by masking the
/// pixels next to the alpha cut-off (opacities stay below the 0.999 clamp and T above 1e-4).
#[test]
fn gradients_match_finite_differences() {
    let camera = RasterCamera {
        world_to_camera: [
            [0.98, -0.17, 0.0, 0.1],
            [0.17, 0.98, 0.0, -0.05],
            [0.0, 0.0, 1.0, 0.2],
            [0.0, 0.0, 0.0, 1.0],
        ],
        ..identity_camera(48, 40)
    };
    let mut spec = SceneSpec::new(10, 4);
    spec.pixel_std = (2.0, 7.0);
    spec.depth = (2.0, 5.0);
    spec.opacity = (0.1, 0.6);
    let scene = random_scene(&identity_camera(48, 40), &spec);
    let bg = [0.3, 0.2, 0.1];
    let mut rng = StdRng::seed_from_u64(1);
    let mut weights: Vec<f32> = (0..48 * 40 * 4)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let masked = mask_threshold_pixels(&scene, &camera, &mut weights, 0.3);
    assert!(
        masked < 48 * 40 / 3,
        "{masked} pixels masked: too few left to test"
    );
    let state = cpu::forward(&scene.slices(), &camera, bg).unwrap();
    let visible = state
        .projected
        .iter()
        .filter(|p| cpu::is_visible(p))
        .count();
    assert!(visible >= 8, "only {visible} visible Gaussians");
    assert!(
        state
            .composite
            .final_transmittance
            .iter()
            .all(|t| *t > 1e-3)
    );
    let grads = cpu::backward(&scene.slices(), &camera, bg, &state, &weights).unwrap();

    type Field = fn(&mut GaussianArrays) -> &mut Vec<f32>;
    let fields: [(&str, Field, &Vec<f32>); 5] = [
        ("means", |g| &mut g.means, &grads.means),
        ("quats", |g| &mut g.quats, &grads.quats),
        ("scales", |g| &mut g.scales, &grads.scales),
        ("opacities", |g| &mut g.opacities, &grads.opacities),
        ("colors", |g| &mut g.colors, &grads.colors),
    ];
    let mut checked = 0;
    for (name, field, analytic) in fields {
        let scale = analytic.iter().fold(0.0f32, |m, v| m.max(v.abs())) as f64;
        for i in 0..analytic.len() {
            let x = field(&mut scene.clone())[i];
            let h = 2e-4 * (x.abs() as f64).max(0.05);
            let eval = |delta: f64| {
                let mut p = scene.clone();
                field(&mut p)[i] = (x as f64 + delta) as f32;
                let actual = field(&mut p)[i] as f64 - x as f64; // the step f32 can represent
                (loss(&p, &camera, bg, &weights), actual)
            };
            let ((plus, hp), (minus, hm)) = (eval(h), eval(-h));
            let central = (plus - minus) / (hp - hm);
            let a = analytic[i] as f64;
            let tol = 1e-2 * a.abs() + 2e-3 * scale + 1e-4;
            assert!(
                (central - a).abs() <= tol,
                "{name}[{i}]: analytic {a}, finite difference {central}"
            );
            checked += 1;
        }
    }
    assert_eq!(checked, 10 * (3 + 4 + 3 + 1 + 3));
}

#[test]
fn two_runs_are_bitwise_identical() {
    let camera = identity_camera(333, 211);
    let scene = random_scene(&camera, &SceneSpec::new(20_000, 5));
    let mut rng = StdRng::seed_from_u64(2);
    let weights: Vec<f32> = (0..333 * 211 * 4)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let run = || {
        let state = cpu::forward(&scene.slices(), &camera, [0.5; 3]).unwrap();
        let grads = cpu::backward(&scene.slices(), &camera, [0.5; 3], &state, &weights).unwrap();
        (state, grads)
    };
    assert!(run() == run());
}

/// The vector path (AVX2 where the CPU has it) and the portable lane code do the same IEEE
/// operations in the same order: forward and gradients agree bit for bit. On a CPU without AVX2
/// both runs take the portable path and the test checks determinism only.
#[test]
fn vector_and_portable_lanes_are_bitwise_identical() {
    let camera = identity_camera(203, 149);
    let scene = random_scene(&camera, &SceneSpec::new(15_000, 8));
    let mut rng = StdRng::seed_from_u64(3);
    let weights: Vec<f32> = (0..203 * 149 * 4)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let run = || {
        let state = cpu::forward(&scene.slices(), &camera, [0.3, 0.2, 0.1]).unwrap();
        let grads =
            cpu::backward(&scene.slices(), &camera, [0.3, 0.2, 0.1], &state, &weights).unwrap();
        (state, grads)
    };
    let vector = run();
    cpu::composite::force_portable_lanes(true);
    let portable = run();
    cpu::composite::force_portable_lanes(false);
    assert!(vector.0 == portable.0, "forward differs between lane paths");
    assert!(
        vector.1 == portable.1,
        "gradients differ between lane paths"
    );
}

/// `exp_f32` (the compositing exponential) against f64 `exp`: within 2 ulp over the range it
/// serves (e^-sigma, sigma in [0, 6]) and within 3 ulp over its whole clamp range.
#[test]
fn exp_f32_is_accurate() {
    let ulp_error = |x: f32| {
        let got = exp_f32(x) as f64;
        let want = (x as f64).exp();
        let ulp = (want as f32).next_up() as f64 - want as f32 as f64;
        (got - want).abs() / ulp
    };
    let mut worst_served = 0.0f64;
    for i in 0..=1_000_000 {
        let x = -6.0 * i as f32 / 1_000_000.0;
        worst_served = worst_served.max(ulp_error(x));
    }
    let mut worst_all = 0.0f64;
    for i in 0..=1_000_000 {
        let x = -87.0 + 175.0 * i as f32 / 1_000_000.0;
        worst_all = worst_all.max(ulp_error(x));
    }
    assert!(
        worst_served <= 2.0,
        "worst error on [-6, 0]: {worst_served} ulp"
    );
    assert!(
        worst_all <= 3.0,
        "worst error on [-87, 88]: {worst_all} ulp"
    );
    assert_eq!(exp_f32(0.0), 1.0);
    assert_eq!(exp_f32(-1e9), exp_f32(-87.0), "clamped below");
    assert!(exp_f32(1e9).is_finite(), "clamped above");
}
