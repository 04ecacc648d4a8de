//! Image metrics (PSNR, torchmetrics-style SSIM, their dynamic / static split) and the
//! differentiable photometric loss.
#![allow(deprecated)] // Device::ndarray

use acags::data::ViewId;
use acags::data::frames::Frame;
use acags::eval::evaluate::{EvalSummary, score_view};
use acags::eval::metrics::{SSIM_C1, gaussian_taps, psnr, region_quality, ssim, ssim_map};
use acags::eval::motion_mask::{MotionMaskConfig, camera_motion_masks};
use acags::train::losses::{moving_pixel_weights, photometric_loss, ssim as ssim_tensor};
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};

fn random_image(w: usize, h: usize, seed: u64) -> Vec<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    // Smooth structure plus noise, like a photo.
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .flat_map(|(x, y)| {
            [
                0.5 + 0.4 * ((x as f32) * 0.3).sin(),
                0.5 + 0.4 * ((y as f32) * 0.2).cos(),
                0.3,
            ]
        })
        .map(|v| (v + rng.random_range(-0.1..0.1)).clamp(0.0, 1.0))
        .collect()
}

#[test]
fn gaussian_window_is_normalised_and_symmetric() {
    let taps = gaussian_taps();
    assert!((taps.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    for i in 0..5 {
        assert_eq!(taps[i], taps[10 - i]);
    }
    // Ratio of neighbouring taps of a sigma = 1.5 Gaussian: exp(-1 / (2 * 2.25)).
    assert!((taps[6] / taps[5] - (-1.0f64 / 4.5).exp()).abs() < 1e-12);
}

#[test]
fn psnr_known_values() {
    let a = vec![0.5f32; 4 * 4 * 3];
    let b: Vec<f32> = a.iter().map(|v| v + 0.1).collect();
    assert!(
        (psnr(&a, &b, 4, 4).unwrap() - 20.0).abs() < 1e-4,
        "MSE 0.01 is 20 dB"
    );
    assert!(psnr(&a, &a, 4, 4).unwrap().is_infinite());
    assert!(psnr(&a, &b[..10], 4, 4).is_err());
}

#[test]
fn ssim_analytic_cases() {
    let (w, h) = (20, 16);
    let x = random_image(w, h, 1);
    assert!((ssim(&x, &x, w, h).unwrap() - 1.0).abs() < 1e-12);
    // Constant images: variances vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    let (a, b) = (0.3f32, 0.6f32);
    let want =
        (2.0 * a as f64 * b as f64 + SSIM_C1) / ((a as f64).powi(2) + (b as f64).powi(2) + SSIM_C1);
    let got = ssim(&vec![a; w * h * 3], &vec![b; w * h * 3], w, h).unwrap();
    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
    // Symmetric, and lower with more noise.
    let mut rng = StdRng::seed_from_u64(2);
    let noisy = |amount: f32, rng: &mut StdRng| -> Vec<f32> {
        x.iter()
            .map(|v| v + rng.random_range(-amount..amount))
            .collect()
    };
    let (y1, y2) = (noisy(0.05, &mut rng), noisy(0.2, &mut rng));
    assert_eq!(ssim(&x, &y1, w, h).unwrap(), ssim(&y1, &x, w, h).unwrap());
    assert!(ssim(&x, &y1, w, h).unwrap() > ssim(&x, &y2, w, h).unwrap());
    assert!(
        ssim(&x[..10 * 10 * 3], &x[..10 * 10 * 3], 10, 10).is_err(),
        "needs 11x11"
    );
}

fn tensor(v: &[f32], w: usize, h: usize, device: &Device) -> Tensor<3> {
    Tensor::<3>::from_data(TensorData::new(v.to_vec(), [h, w, 3]), device)
}

#[test]
fn burn_ssim_matches_the_host_metric() {
    let (w, h) = (40, 32);
    let (x, y) = (random_image(w, h, 3), random_image(w, h, 4));
    let device = Device::ndarray();
    let got: f32 = ssim_tensor(tensor(&x, w, h, &device), tensor(&y, w, h, &device)).into_scalar();
    let want = ssim(&x, &y, w, h).unwrap();
    assert!((got as f64 - want).abs() < 1e-5, "{got} vs {want}");
}

/// Autodiff gradient of the photometric loss against central differences of the f64 host
/// metrics, at pixels where render and target differ (away from the kink of |.|).
#[test]
fn photometric_loss_gradient_matches_finite_differences() {
    check_photometric_gradient(None);
}

/// The same with per-pixel L1 weights (`loss.moving_weight`): the host reference weights each
/// pixel's |difference| itself, so a weight applied to the wrong pixel or channel, or not
/// normalised as the loss assumes, fails.
#[test]
fn weighted_photometric_loss_gradient_matches_finite_differences() {
    let (w, h) = (16, 14);
    // A moving block in the middle and one stray pixel: 4 of the 7 rows, 6 of the 16 columns.
    let moving: Vec<bool> = (0..w * h)
        .map(|i| ((5..11).contains(&(i % w)) && (4..8).contains(&(i / w))) || i == 3)
        .collect();
    check_photometric_gradient(Some(moving_pixel_weights(&moving, 5.0)));
}

fn check_photometric_gradient(weights: Option<Vec<f32>>) {
    let (w, h) = (16, 14);
    let (x, y) = (random_image(w, h, 5), random_image(w, h, 6));
    let device = Device::ndarray().autodiff();
    let render = tensor(&x, w, h, &device).require_grad();
    let weight_tensor = weights.as_ref().map(|weights| {
        Tensor::<3>::from_data(TensorData::new(weights.clone(), [h, w, 1]), &device)
    });
    let loss = photometric_loss(
        render.clone(),
        tensor(&y, w, h, &device),
        0.2,
        weight_tensor,
    )
    .loss;
    let grads = loss.backward();
    let analytic: Vec<f32> = render
        .grad(&grads)
        .unwrap()
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    let pixel_weight = |i: usize| {
        weights
            .as_ref()
            .map_or(1.0, |weights| weights[i / 3] as f64)
    };
    let host_loss = |img: &[f32]| {
        let l1 = img
            .iter()
            .zip(&y)
            .enumerate()
            .map(|(i, (a, b))| pixel_weight(i) * (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / img.len() as f64;
        0.8 * l1 + 0.2 * (1.0 - ssim(img, &y, w, h).unwrap())
    };
    let mut checked = 0;
    for i in (0..x.len()).step_by(7) {
        if (x[i] - y[i]).abs() < 0.02 {
            continue;
        }
        let h_step = 1e-3f32;
        let (mut plus, mut minus) = (x.clone(), x.clone());
        plus[i] += h_step;
        minus[i] -= h_step;
        let fd = (host_loss(&plus) - host_loss(&minus)) / (plus[i] as f64 - minus[i] as f64);
        let a = analytic[i] as f64;
        assert!(
            (fd - a).abs() <= 1e-3 * a.abs().max(1e-2) + 2e-6,
            "pixel value {i}: autodiff {a}, finite difference {fd}"
        );
        checked += 1;
    }
    assert!(checked > 50, "only {checked} entries checked");
}

/// Moving-pixel weights: `weight` times the static pixels' weight, mean 1 (the loss keeps its
/// scale), all ones where nothing moves or the weight is 1.
#[test]
fn moving_pixel_weights_keep_the_ratio_and_a_mean_of_one() {
    let moving: Vec<bool> = (0..1000).map(|i| i % 7 == 0).collect();
    let weights = moving_pixel_weights(&moving, 4.0);
    let mean = weights.iter().map(|&v| v as f64).sum::<f64>() / weights.len() as f64;
    assert!((mean - 1.0).abs() < 1e-6, "mean {mean}");
    let (on, off) = (weights[0], weights[1]);
    assert!((on / off - 4.0).abs() < 1e-5, "ratio {}", on / off);
    assert!(
        moving
            .iter()
            .zip(&weights)
            .all(|(&m, &v)| v == if m { on } else { off })
    );
    // 143 moving pixels of 1000 at weight 4: the static ones get 1 / (1 + 3·0.143).
    assert!(
        (off as f64 - 1.0 / (1.0 + 3.0 * 0.143)).abs() < 1e-6,
        "static weight {off}"
    );
    assert!(
        moving_pixel_weights(&[false; 50], 4.0)
            .iter()
            .all(|&v| v == 1.0)
    );
    assert!(
        moving_pixel_weights(&moving, 1.0)
            .iter()
            .all(|&v| (v - 1.0).abs() < 1e-7)
    );
}

/// A 40×30 background with a 6×6 magenta square at `(x, y)`.
fn frame_with_square(x: usize, y: usize) -> Vec<f32> {
    let (w, h) = (40, 30);
    let mut img = random_image(w, h, 9);
    for yy in y..y + 6 {
        for xx in x..x + 6 {
            let i = (yy * w + xx) * 3;
            img[i] = 1.0;
            img[i + 1] = 0.1;
            img[i + 2] = 1.0;
        }
    }
    img
}

#[test]
fn region_metrics_split_a_moving_square_from_its_background() {
    let (w, h) = (40, 30);
    // Ground truth: a square crossing the view over 5 frames; its mask at frame 2 is the square
    // dilated by 2 px, and nothing moves elsewhere.
    let truth: Vec<Vec<f32>> = (0..5).map(|f| frame_with_square(4 + 7 * f, 12)).collect();
    let planes: Vec<&[f32]> = truth.iter().map(|t| t.as_slice()).collect();
    let masks = camera_motion_masks(&planes, w, h, &MotionMaskConfig::default());
    let mask = &masks[2];
    for y in 0..h {
        for x in 0..w {
            let inside = (16..=25).contains(&x) && (10..=19).contains(&y);
            assert_eq!(mask[y * w + x], inside, "({x}, {y})");
        }
    }
    // A render that drops the square (background only) and is off by 0.02 everywhere else.
    let background = random_image(w, h, 9);
    let render: Vec<f32> = background
        .iter()
        .map(|v| (v + 0.02).min(1.0))
        .collect();
    let target = &truth[2];
    let map = ssim_map(&render, target, w, h).unwrap();
    let still: Vec<bool> = mask.iter().map(|&m| !m).collect();
    let dynamic = region_quality(&render, target, mask, &map, w, h).unwrap().unwrap();
    let stat = region_quality(&render, target, &still, &map, w, h).unwrap().unwrap();
    // Independent computation of each region's MSE.
    let mse_of = |keep: &dyn Fn(usize) -> bool| {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for p in (0..w * h).filter(|&p| keep(p)) {
            for c in 0..3 {
                sum += (render[3 * p + c] as f64 - target[3 * p + c] as f64).powi(2);
            }
            n += 3;
        }
        sum / n as f64
    };
    let dyn_mse = mse_of(&|p| mask[p]);
    let stat_mse = mse_of(&|p| !mask[p]);
    assert!((dynamic.psnr + 10.0 * dyn_mse.log10()).abs() < 1e-9);
    assert!((stat.psnr + 10.0 * stat_mse.log10()).abs() < 1e-9);
    assert_eq!(dynamic.pixels + stat.pixels, w * h);
    assert_eq!(dynamic.pixels, 100);
    // The full-frame MSE is the pixel-weighted mean of the two regions'.
    let full = psnr(&render, target, w, h).unwrap();
    let pooled = (dyn_mse * 100.0 + stat_mse * (w * h - 100) as f64) / (w * h) as f64;
    assert!((full + 10.0 * pooled.log10()).abs() < 1e-9);
    // The dropped square: the full frame hides it, the dynamic region does not.
    assert!(full > 20.0 && dynamic.psnr < 12.0, "full {full}, dynamic {}", dynamic.psnr);
    assert!(stat.psnr > 33.0);
    assert!(dynamic.ssim.unwrap() < stat.ssim.unwrap());
    // Over the whole image the region SSIM is the SSIM.
    let everything = vec![true; w * h];
    let whole = region_quality(&render, target, &everything, &map, w, h).unwrap().unwrap();
    assert!((whole.ssim.unwrap() - ssim(&render, target, w, h).unwrap()).abs() < 1e-12);
    assert!((whole.psnr - full).abs() < 1e-9);
    // Empty regions have no figures; a region within 5 px of the border has no SSIM window.
    assert!(region_quality(&render, target, &vec![false; w * h], &map, w, h).unwrap().is_none());
    let mut corner = vec![false; w * h];
    corner[0] = true;
    let c = region_quality(&render, target, &corner, &map, w, h).unwrap().unwrap();
    assert!(c.ssim.is_none() && c.pixels == 1);
    assert!(region_quality(&render, target, &corner[1..], &map, w, h).is_err());

    // Per view and per frame: two cameras, one that drops the square and one that renders it.
    let frame = Frame {
        width: w as u32,
        height: h as u32,
        rgb: target.clone(),
    };
    let view = |camera| ViewId { camera, frame: 2 };
    let dropped = score_view(&render, &frame, mask, view(0), 0.1, 10).unwrap();
    let perfect = score_view(target, &frame, mask, view(1), 0.1, 10).unwrap();
    assert_eq!(dropped.dynamic_psnr, Some(dynamic.psnr));
    assert!(perfect.dynamic_psnr.unwrap().is_infinite());
    assert!((dropped.dynamic_fraction - 100.0 / (w * h) as f64).abs() < 1e-12);
    let still_frame = score_view(&render, &frame, &vec![false; w * h], ViewId { camera: 0, frame: 3 }, 0.1, 10)
        .unwrap();
    assert_eq!(still_frame.dynamic_psnr, None);
    let summary = EvalSummary::from_views(vec![dropped.clone(), still_frame.clone()], Default::default());
    let r = &summary.regions;
    assert_eq!(r.dynamic_psnr, dropped.dynamic_psnr, "means skip images without motion");
    assert_eq!(r.frames.len(), 2);
    assert_eq!(r.worst_dynamic_frame, Some((2, dynamic.psnr)));
    let gap = r.max_dynamic_gap.unwrap();
    assert_eq!(gap.0, 2);
    assert!((gap.1 - (stat.psnr - dynamic.psnr)).abs() < 1e-9);
    assert!(r.text().contains("worst dynamic frame #2"), "{}", r.text());
}
