//! The codec: rate presets and the quantisation schedule (spec §9.1-§9.2), the training-time
//! quantiser (grid forward, straight-through backward, bounded noise), the rANS glue (exact
//! round trips, code length at the model's entropy), and the `scene.acags` bitstream (decode ==
//! the quantised scene, re-encode byte-identical, decoded renders equal the quantised model's,
//! nothing a decode reads is dropped, damaged payloads are errors and never panics).
#![allow(deprecated)] // Device::ndarray

use acags::codec::attributes::ModelChoice;
use acags::codec::bitstream::{CODEC_VERSION, QuantizedScene};
use acags::codec::container::Container;
use acags::codec::entropy::{
    BitModels, GaussianTables, SCALE_LEVELS, decode_gaussian, encode_gaussian, level_sigma,
    scale_level,
};
use acags::codec::entropy_models::{EntropyModelSizes, EntropyModels, HostEntropyModels};
use acags::codec::quantization::{
    NoiseKey, NoiseStream, QuantizationPhase, QuantizationSteps, RatePreset, fake_quantize,
    fake_quantize_gate_logits, round_to_grid,
};
use acags::codec::rate::{BitEstimate, RateInputs, gaussian_bits, rate};
use acags::model::anchored::AnchoredModel;
use acags::model::anchors::{
    AnchorDims, AnchorSet, Column, ColumnTensor, FeatureMasking, NewAnchors, TrajectoryTurn,
    host_values,
};
use acags::model::decoders::{DecoderSizes, Decoders};
use acags::model::view::{ALL_TIME_BANDS, Phase, ViewTime};
use acags::raster::random_scene::identity_camera;
use acags::train::anchor_state::AnchorState;
use acags::train::config::{CompressionConfig, CompressionMode, TrajectoryRate};
use acags::train::densify::prune_closed_anchors;
use acags::train::row_adam::AdamConfig;
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};

#[test]
fn rate_presets_are_the_spec_table() {
    // spec §9.1: (scales/offsets, features/time features, factors, rd_lambda) per preset.
    let expected = [
        (RatePreset::R0, 0.02, 1.0, 5e-4),
        (RatePreset::R1, 0.04, 1.0, 1e-3),
        (RatePreset::R2, 0.06, 1.5, 2e-3),
        (RatePreset::R3, 0.08, 2.0, 4e-3),
    ];
    for (rate, geometry, features, lambda) in expected {
        let s = rate.steps();
        assert_eq!((s.log_scales, s.offsets), (geometry, geometry), "{rate:?}");
        assert_eq!(
            (s.features, s.time_features),
            (features, features),
            "{rate:?}"
        );
        assert_eq!(s.factors, 1.0 / 16.0);
        assert_eq!(s.motion_gate, Some(1.0 / 1024.0));
        assert_eq!(rate.rd_lambda(), lambda);
    }
}

#[test]
fn the_schedule_switches_at_a_fifth_and_two_thirds_of_training() {
    let c = CompressionConfig::default();
    // GIFStream at 30k: faint noise until 6000, uniform noise until 20000, rounding after.
    assert_eq!(c.phase_at(5999, 30000), Some(QuantizationPhase::Faint));
    assert_eq!(c.phase_at(6000, 30000), Some(QuantizationPhase::Noise));
    assert_eq!(c.phase_at(19999, 30000), Some(QuantizationPhase::Noise));
    assert_eq!(c.phase_at(20000, 30000), Some(QuantizationPhase::Round));
    let off = CompressionConfig {
        mode: CompressionMode::Off,
        ..c
    };
    assert_eq!(off.phase_at(25000, 30000), None);
}

#[test]
fn rounding_is_the_grid_forward_and_the_identity_backward() {
    let device = Device::ndarray().autodiff();
    let mut rng = StdRng::seed_from_u64(1);
    let values: Vec<f32> = (0..200)
        .map(|_| (rng.random::<f32>() - 0.5) * 7.0)
        .collect();
    let step = 0.37;
    let x =
        Tensor::<2>::from_data(TensorData::new(values.clone(), [20, 10]), &device).require_grad();
    let q = fake_quantize(
        x.clone(),
        step,
        QuantizationPhase::Round,
        NoiseKey::new(1, 0, 0, 0),
    );
    let expected = round_to_grid(&values, step);
    for (a, b) in host_values(&q).iter().zip(&expected) {
        assert!((a - b).abs() <= 1e-6, "{a} vs {b}");
    }
    let weights: Vec<f32> = (0..200).map(|i| i as f32 * 0.01 - 1.0).collect();
    let w = Tensor::<2>::from_data(TensorData::new(weights.clone(), [20, 10]), &device);
    let grads = (q * w).sum().backward();
    assert_eq!(host_values(&x.grad(&grads).unwrap()), weights);
}

#[test]
fn noise_is_uniform_over_one_step_and_faint_noise_over_a_thousandth() {
    let device = Device::ndarray();
    let n = 40_000;
    let step = 0.5;
    let x = Tensor::<1>::from_data(TensorData::new(vec![1.25f32; n], [n]), &device);
    let noisy = host_values(&fake_quantize(
        x.clone(),
        step,
        QuantizationPhase::Noise,
        NoiseKey::new(2, 0, 0, 0),
    ));
    let e: Vec<f64> = noisy.iter().map(|&v| (v - 1.25) as f64).collect();
    assert!(e.iter().all(|v| v.abs() <= 0.5 * step as f64 + 1e-6));
    let mean = e.iter().sum::<f64>() / n as f64;
    let var = e.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
    // U(−step/2, step/2): mean 0 (± 4 standard errors), variance step²/12 (± 3 %).
    let sd = step as f64 / 12f64.sqrt();
    assert!(mean.abs() < 4.0 * sd / (n as f64).sqrt(), "mean {mean}");
    assert!(
        (var / (sd * sd) - 1.0).abs() < 0.03,
        "variance ratio {}",
        var / (sd * sd)
    );
    let faint = host_values(&fake_quantize(
        x,
        step,
        QuantizationPhase::Faint,
        NoiseKey::new(2, 0, 0, 1),
    ));
    assert!(
        faint
            .iter()
            .all(|&v| (v - 1.25).abs() <= 0.0005 * step + 1e-6)
    );
    assert!(faint.iter().any(|&v| v != 1.25));
}

#[test]
fn noise_past_the_gate_range_is_clamped_without_gradient() {
    // Gates near 0 and 1: the noise phase's U(±step/2) pushes many of them outside (0, 1), where
    // the logit is clamped. The clamp is plain (a kept deviation, measured; GIFStream has none):
    // a gate it holds gets no gradient, every other one σ'(r).
    let device = Device::ndarray().autodiff();
    let raw: Vec<f32> = (0..64)
        .map(|i| {
            let r = 4.0 + (i % 32) as f32 * 0.15;
            if i < 32 { -r } else { r }
        })
        .collect();
    let x = Tensor::<2>::from_data(TensorData::new(raw.clone(), [16, 4]), &device).require_grad();
    let logits = fake_quantize_gate_logits(
        x.clone(),
        &[1.0 / 16.0; 4],
        QuantizationPhase::Noise,
        NoiseKey::new(5, 0, 0, 0),
    );
    let v = burn::tensor::activation::sigmoid(logits);
    let values = host_values(&v);
    let held = |v: f32| v < 2e-6 || v > 1.0 - 2e-6;
    let clamped = values.iter().filter(|&&v| held(v)).count();
    assert!(
        (16..64).contains(&clamped),
        "{clamped} of 64 gates reached the clamp"
    );
    let grads = v.sum().backward();
    let sig = |r: f32| 1.0 / (1.0 + (-r).exp());
    let gradients = host_values(&x.grad(&grads).unwrap());
    for ((&g, &r), &value) in gradients.iter().zip(&raw).zip(&values) {
        let expected = if held(value) {
            0.0
        } else {
            sig(r) * (1.0 - sig(r))
        };
        // Float32's 1 − v near 1 loses a few per cent (see the test below).
        assert!(
            (g - expected).abs() <= 0.1 * expected + 1e-9,
            "r {r}, gate {value}: gradient {g}, expected {expected}"
        );
    }
}

#[test]
fn the_motion_gate_can_have_its_own_grid() {
    // Column 1 (the motion gate) on a 1/1024 grid, the others on 1/16: rounding lands each
    // column on its own grid, the noise phase moves each by at most half its own step.
    let device = Device::ndarray().autodiff();
    let raw: Vec<f32> = (0..256).map(|i| (i as f32 - 128.0) * 0.037).collect();
    let x = Tensor::<2>::from_data(TensorData::new(raw.clone(), [64, 4]), &device).require_grad();
    let steps = QuantizationSteps {
        motion_gate: Some(1.0 / 1024.0),
        ..RatePreset::R0.steps()
    };
    assert_eq!(
        steps.gate_steps(),
        [1.0 / 16.0, 1.0 / 1024.0, 1.0 / 16.0, 1.0 / 16.0]
    );
    let sig = |r: f32| 1.0 / (1.0 + (-r).exp());
    let rounded = fake_quantize_gate_logits(
        x.clone(),
        &steps.gate_steps(),
        QuantizationPhase::Round,
        NoiseKey::new(3, 0, 0, 0),
    );
    for (i, &got) in host_values(&burn::tensor::activation::sigmoid(rounded))
        .iter()
        .enumerate()
    {
        let step = steps.gate_steps()[i % 4];
        let expected = (sig(raw[i]) / step).round() * step;
        assert!(
            (got - expected).abs() < 2e-6,
            "element {i}: {got} vs {expected}"
        );
    }
    let noised = fake_quantize_gate_logits(
        x.clone(),
        &steps.gate_steps(),
        QuantizationPhase::Noise,
        NoiseKey::new(4, 0, 0, 0),
    );
    let mut largest = [0.0f32; 4];
    for (i, &got) in host_values(&burn::tensor::activation::sigmoid(noised))
        .iter()
        .enumerate()
    {
        let moved = (got - sig(raw[i])).abs();
        // The clamp at ε can only shorten a move.
        assert!(
            moved <= 0.5 * steps.gate_steps()[i % 4] + 2e-6,
            "element {i}: {moved}"
        );
        largest[i % 4] = largest[i % 4].max(moved);
    }
    // The noise spans each column's own step (not the finest one).
    assert!(largest[0] > 0.02 && largest[1] < 1e-3, "{largest:?}");
    // The per-column path draws the scalar path's noise: nearly equal steps, nearly equal gates.
    let one = fake_quantize_gate_logits(
        x.clone(),
        &[1.0 / 16.0; 4],
        QuantizationPhase::Noise,
        NoiseKey::new(4, 0, 0, 0),
    );
    let columns = fake_quantize_gate_logits(
        x.clone(),
        &[1.0 / 16.0, 1.0 / 16.0 + 1e-7, 1.0 / 16.0, 1.0 / 16.0],
        QuantizationPhase::Noise,
        NoiseKey::new(4, 0, 0, 0),
    );
    let gate = |t: Tensor<2>| host_values(&burn::tensor::activation::sigmoid(t));
    for (a, b) in gate(one).iter().zip(gate(columns)) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn gate_values_are_quantised_after_the_sigmoid_with_the_sigmoids_gradient() {
    let device = Device::ndarray().autodiff();
    let raw: Vec<f32> = (0..64).map(|i| (i as f32 - 32.0) * 0.23).collect();
    let x = Tensor::<2>::from_data(TensorData::new(raw.clone(), [16, 4]), &device).require_grad();
    let logits = fake_quantize_gate_logits(
        x.clone(),
        &[1.0 / 16.0; 4],
        QuantizationPhase::Round,
        NoiseKey::new(3, 0, 0, 0),
    );
    let v = burn::tensor::activation::sigmoid(logits);
    let sig = |r: f32| 1.0 / (1.0 + (-r).exp());
    for (&got, &r) in host_values(&v).iter().zip(&raw) {
        let expected = (sig(r) * 16.0).round() / 16.0;
        assert!(
            (got - expected).abs() < 2e-6,
            "σ({r}) → {got}, grid value {expected}"
        );
    }
    let grads = v.sum().backward();
    for (&g, &r) in host_values(&x.grad(&grads).unwrap()).iter().zip(&raw) {
        let s = sig(r);
        // Straight through the grid: d σ(logit(q(σ(r))))/dr = σ'(r) up to the ε map. Where the
        // grid value is exactly 0 or 1 the logit sits at ±13.8 and float32's 1 − σ loses a
        // few per cent; inside the grid the identity holds to 1e-3.
        let expected = s * (1.0 - s);
        let grid = (s * 16.0).round();
        let tolerance = if grid == 0.0 || grid == 16.0 {
            0.1
        } else {
            1e-3
        };
        assert!(
            (g - expected).abs() <= tolerance * expected.max(1e-3),
            "r {r}: {g} vs {expected}"
        );
    }
}

#[test]
fn scale_levels_bracket_sigma_and_clamp_at_the_ends() {
    for i in 0..2000 {
        let sigma = 0.11 * (64.0f64 / 0.11).powf(i as f64 / 1999.0) * 0.9999;
        let l = scale_level(sigma);
        if sigma >= 0.11 {
            assert!(
                level_sigma(l) <= sigma * (1.0 + 1e-12),
                "σ {sigma} level {l}"
            );
        }
        if (l as usize) < SCALE_LEVELS - 1 {
            assert!(sigma < level_sigma(l + 1), "σ {sigma} level {l}");
        }
    }
    assert_eq!(scale_level(0.01), 0);
    assert_eq!(scale_level(f64::NAN), 0);
    assert_eq!(scale_level(1e9), 255);
    assert!((level_sigma(0) - 0.11).abs() < 1e-12 && (level_sigma(255) - 64.0).abs() < 1e-9);
}

/// Σ −log2 p(y) under the discretised Gaussian of σ (tails ignored).
fn ideal_bits(symbols: &[i32], sigma: f64) -> f64 {
    let cdf = |x: f64| 0.5 * (1.0 + libm::erf(x / (sigma * std::f64::consts::SQRT_2)));
    symbols
        .iter()
        .map(|&y| -(cdf(y as f64 + 0.5) - cdf(y as f64 - 0.5)).log2())
        .sum()
}

#[test]
fn gaussian_coding_round_trips_at_the_models_entropy() {
    let mut rng = StdRng::seed_from_u64(4);
    let normal = rand_distr::Normal::new(0.0f64, 1.0).unwrap();
    for &sigma_level in &[0u8, 60, 128, 200, 255] {
        let sigma = level_sigma(sigma_level);
        let symbols: Vec<i32> = (0..20_000)
            .map(|_| (rng.sample(normal) * sigma).round() as i32)
            .collect();
        let radius = symbols.iter().map(|y| y.abs()).max().unwrap().max(1);
        let mut tables = GaussianTables::new(radius).unwrap();
        let levels = vec![sigma_level; symbols.len()];
        let bytes = encode_gaussian(&symbols, &levels, &mut tables).unwrap();
        let back = decode_gaussian(&bytes, &levels, &mut tables, "test").unwrap();
        assert_eq!(back, symbols);
        let ideal = ideal_bits(&symbols, sigma);
        let actual = bytes.len() as f64 * 8.0;
        // rANS overhead: the final state (64 bits) plus < 0.5 % for 24-bit probabilities.
        assert!(
            actual <= ideal * 1.005 + 96.0,
            "level {sigma_level}: {actual} bits for an ideal {ideal:.0}"
        );
    }
    // Mixed levels, extremes of the range.
    let radius = 300;
    let mut tables = GaussianTables::new(radius).unwrap();
    let symbols: Vec<i32> = (0..5000)
        .map(|i| [-radius, radius, 0, 7, -1][i % 5])
        .collect();
    let levels: Vec<u8> = (0..5000).map(|i| (i * 37 % 256) as u8).collect();
    let bytes = encode_gaussian(&symbols, &levels, &mut tables).unwrap();
    assert_eq!(
        decode_gaussian(&bytes, &levels, &mut tables, "test").unwrap(),
        symbols
    );
    // Out of range is refused at encode time.
    assert!(encode_gaussian(&[radius + 1], &[3], &mut tables).is_err());
    // A stream decoded with fewer symbols than it holds is reported, not accepted.
    let err = decode_gaussian(&bytes, &levels[..4000], &mut tables, "test").unwrap_err();
    assert!(err.to_string().contains("data left"), "{err}");
}

#[test]
fn bitmaps_round_trip_at_their_entropy_and_constant_contexts_are_free() {
    let mut rng = StdRng::seed_from_u64(5);
    let n = 30_000;
    // Context 0: p = 0.1, context 1: all ones, context 2: p = 0.5.
    let contexts: Vec<usize> = (0..n).map(|i| i % 3).collect();
    let bits: Vec<bool> = contexts
        .iter()
        .map(|&c| match c {
            0 => rng.random::<f64>() < 0.1,
            1 => true,
            _ => rng.random::<bool>(),
        })
        .collect();
    let (ones, totals) = BitModels::count(&bits, &contexts, 3);
    assert_eq!(ones[1], totals[1]);
    let models = BitModels::new(&ones, &totals).unwrap();
    let bytes = models.encode(&bits, &contexts).unwrap();
    assert_eq!(models.decode(&bytes, &contexts, "test").unwrap(), bits);
    let h = |p: f64| -(p * p.log2() + (1.0 - p) * (1.0 - p).log2());
    let p0 = ones[0] as f64 / totals[0] as f64;
    let ideal = totals[0] as f64 * h(p0) + totals[2] as f64 * h(ones[2] as f64 / totals[2] as f64);
    let actual = bytes.len() as f64 * 8.0;
    assert!(
        actual <= ideal * 1.005 + 96.0 && actual >= ideal * 0.99,
        "{actual} vs {ideal}"
    );
}

fn dims(masking: FeatureMasking, knn: usize, trajectory_spacing: usize) -> AnchorDims {
    AnchorDims {
        slots: 4,
        initial_active_slots: 2,
        feature_masking: masking,
        frames: 3,
        feature_dim: 8,
        time_feature_dim: 2,
        knn,
        trajectory_spacing,
        trajectory_turn: TrajectoryTurn::Off,
    }
}

/// Every column of `m`'s anchors, as rows at `positions` (one per anchor).
fn copied_rows(m: &AnchoredModel, positions: Vec<[f32; 3]>) -> NewAnchors {
    assert_eq!(positions.len(), m.anchors.len());
    Column::present(&m.anchors.dims).fold(NewAnchors::new(positions), |rows, c| {
        rows.with(c, m.anchors.host(c))
    })
}

/// [`model_with`] (a knot every 2 frames) whose knots also turn: every column copied, turns of
/// up to ±`angle` radians drawn on the r0 grid.
fn turned_model(seed: u64, angle: f32) -> AnchoredModel {
    let m = model_with(FeatureMasking::Off, 0, true, seed, 2);
    let d = AnchorDims {
        trajectory_turn: TrajectoryTurn::Knots,
        ..m.anchors.dims
    };
    let rows = copied_rows(&m, m.anchors.positions.clone());
    let step = RatePreset::R0.steps().turn;
    let mut rng = StdRng::seed_from_u64(seed + 1000);
    let turns: Vec<f32> = (0..m.anchors.len() * d.turn_width())
        .map(|_| ((rng.random::<f32>() - 0.5) * 2.0 * angle / step).round() * step)
        .collect();
    let mut anchors = AnchorSet::from_rows(d, rows.with(Column::Turn, turns), &Device::ndarray());
    anchors.slot_gates = m.anchors.slot_gates.clone();
    AnchoredModel { anchors, ..m }
}

const VOXEL: f32 = 0.01;

/// A model with anchors on the voxel grid in front of the identity camera, random attributes
/// (optionally already on the r0 grid), a third of the slots gated, some masks off, some time
/// gates and one pruning gate closed.
fn model(masking: FeatureMasking, knn: usize, on_grid: bool, seed: u64) -> AnchoredModel {
    model_with(masking, knn, on_grid, seed, 0)
}

/// [`model`] with anchor trajectories (a knot every `trajectory_spacing` frames; the motion gate
/// of every fourth anchor closed, so its trajectory is not stored).
fn model_with(
    masking: FeatureMasking,
    knn: usize,
    on_grid: bool,
    seed: u64,
    trajectory_spacing: usize,
) -> AnchoredModel {
    let d = dims(masking, knn, trajectory_spacing);
    let device = Device::ndarray();
    let mut rng = StdRng::seed_from_u64(seed);
    let n = 60;
    let steps = RatePreset::R0.steps();
    let mut draw = |count: usize, scale: f32, step: f32| -> Vec<f32> {
        let v: Vec<f32> = (0..count)
            .map(|_| (rng.random::<f32>() - 0.5) * 2.0 * scale)
            .collect();
        if on_grid { round_to_grid(&v, step) } else { v }
    };
    let positions: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            [
                ((i % 10) as f32 - 4.5) * 30.0 * VOXEL,
                ((i / 10) as f32 - 2.5) * 30.0 * VOXEL + (i % 3) as f32 * VOXEL,
                (300 + 7 * (i % 4)) as f32 * VOXEL,
            ]
        })
        .collect();
    let log_scales: Vec<f32> = draw(n * 6, 0.3, steps.log_scales)
        .iter()
        .map(|v| v + round_to_grid(&[0.2f32.ln()], steps.log_scales)[0])
        .collect();
    // Gate logits whose sigmoid is on the 1/16 grid when `on_grid`.
    let factor_values: Vec<i32> = (0..n * 4)
        .map(|i| match (i / 4, i % 4) {
            (a, 0) if a % 5 == 0 => 1, // time gate closed: stream not stored
            (a, 1) if a % 4 == 0 => 1, // motion gate closed: trajectory not stored
            (7, 3) => 0,               // pruning gate closed: anchor dropped
            (_, 3) => 16,
            _ => 3 + (i * 7 % 13) as i32,
        })
        .collect();
    let factors: Vec<f32> = factor_values
        .iter()
        .map(|&q| acags::codec::quantization::factor_logit(q, steps.factors))
        .collect();
    let mut rows = NewAnchors::new(positions)
        .with(Column::LogScales, log_scales)
        .with(
            Column::Features,
            draw(n * d.feature_dim, 6.0, steps.features),
        )
        .with(
            Column::TimeFeatures,
            draw(n * d.frames * d.time_feature_dim, 4.0, steps.time_features),
        )
        .with(Column::Factors, factors)
        .with(
            Column::MaskLogits,
            (0..n)
                .map(|a| if a % 3 == 0 { -9.0 } else { 1.0 })
                .collect(),
        );
    if d.trajectory_width() > 0 {
        rows = rows.with(
            Column::Trajectory,
            draw(n * d.trajectory_width(), 0.2, steps.trajectory),
        );
    }
    let mut anchors = AnchorSet::from_rows(d, rows, &device);
    anchors.set_host(Column::Offsets, draw(n * d.slots * 3, 1.5, steps.offsets));
    anchors.slot_gates.edit(|flags| {
        for (i, g) in flags.iter_mut().enumerate() {
            *g = i % 3 != 1;
        }
    });
    let decoders = Decoders::seeded(
        DecoderSizes {
            feature_dim: d.feature_dim,
            time_feature_dim: d.time_feature_dim,
            slots: d.slots,
        },
        seed,
        &device,
    );
    AnchoredModel {
        anchors,
        decoders,
        culling: acags::model::view::AnchorCulling::Canonical,
    }
}

fn quantize(model: &AnchoredModel) -> QuantizedScene {
    QuantizedScene::from_model(
        model,
        RatePreset::R0,
        RatePreset::R0.steps(),
        Phase::Dynamic,
        (0, 3),
        VOXEL,
        "[data]\ndataset = \"synthetic:fast\"\n".into(),
    )
    .unwrap()
}

fn render(model: &AnchoredModel, frame: usize) -> Vec<f32> {
    let camera = identity_camera(96, 64);
    let when = ViewTime {
        frame,
        time: frame as f32 / 2.0,
        window_gap: 0,
        phase: Phase::Dynamic,
        time_bands: ALL_TIME_BANDS,
    };
    model.render(&camera, when).unwrap().image_host()
}

/// Every frame of `b` renders like `a` within 1e-4 per channel.
fn assert_renders_alike(a: &AnchoredModel, b: &AnchoredModel, frames: usize) {
    for frame in 0..frames {
        let (x, y) = (render(a, frame), render(b, frame));
        let max = x
            .iter()
            .zip(&y)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0f32, f32::max);
        assert!(max <= 1e-4, "frame {frame}: max difference {max}");
    }
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.max(1e-20).log10()
}

#[test]
fn decode_is_the_quantised_scene_and_reencoding_is_byte_identical() {
    for masking in [
        FeatureMasking::Off,
        FeatureMasking::Adaptive {
            base: 5,
            threshold: 0.01,
        },
    ] {
        let m = model(masking, 6, false, 11);
        let scene = quantize(&m);
        assert_eq!(
            scene.meta.anchors, 59,
            "the anchor with a closed pruning gate is dropped"
        );
        let bytes = scene
            .encode(None, ModelChoice::Smallest)
            .unwrap()
            .to_bytes();
        let (decoded, models) =
            QuantizedScene::decode(&Container::from_bytes(&bytes, "mem").unwrap(), "mem").unwrap();
        assert!(models.is_none(), "no entropy models were given");
        assert_eq!(decoded, scene);
        assert_eq!(
            decoded
                .encode(None, ModelChoice::Smallest)
                .unwrap()
                .to_bytes(),
            bytes,
            "re-encode"
        );
        // Decode → render equals the quantised model's render (spec acceptance: ≤ 0.01 dB;
        // here exactly, both are the same scene rebuilt the same way).
        let device = Device::ndarray();
        let reference = scene.to_model(&device).unwrap();
        let rebuilt = decoded.to_model(&device).unwrap();
        for frame in 0..3 {
            let (a, b) = (render(&reference, frame), render(&rebuilt, frame));
            assert!(a.iter().any(|&v| v > 0.0), "the scene draws something");
            assert_eq!(a, b, "frame {frame}");
        }
        // Anchors are stored in Morton order with the kNN lists recomputed.
        assert_eq!(rebuilt.anchors.neighbors().len(), 59 * 6);
    }
}

#[test]
fn nothing_a_decode_reads_is_dropped() {
    // Attributes already on the grid, no kNN (whose lists change when an anchor is dropped):
    // quantising, coding and decoding must reproduce the model's renders although gated
    // offsets, masked F_adapt, closed-time-gate streams and the pruned anchor are not stored.
    let masking = FeatureMasking::Adaptive {
        base: 5,
        threshold: 0.01,
    };
    let m = model(masking, 0, true, 12);
    let scene = quantize(&m);
    let decoded = decode(&scene.encode(None, ModelChoice::Smallest).unwrap()).unwrap();
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    assert_renders_alike(&m, &rebuilt, 3);
    // ...and what is not stored is zero in the decoded scene.
    let (k, cf, t, ct) = (4, 8, 3, 2);
    for a in 0..decoded.meta.anchors {
        for s in 0..k {
            if !decoded.slot_gates[a * k + s] {
                assert_eq!(
                    &decoded.offsets[(a * k + s) * 3..(a * k + s + 1) * 3],
                    &[0; 3]
                );
            }
        }
        if !decoded.adapt_kept[a] {
            assert!(
                decoded.features[a * cf + 5..(a + 1) * cf]
                    .iter()
                    .all(|&q| q == 0)
            );
        }
        if decoded.factors[a * 4] < 2 {
            assert!(
                decoded.time_features[a * t * ct..(a + 1) * t * ct]
                    .iter()
                    .all(|&q| q == 0)
            );
        }
    }
}

/// Largest per-channel difference between `a`'s and `b`'s renders over `frames`.
fn render_difference(a: &AnchoredModel, b: &AnchoredModel, frames: usize) -> f32 {
    (0..frames)
        .flat_map(|f| {
            let (x, y) = (render(a, f), render(b, f));
            x.iter()
                .zip(&y)
                .map(|(p, q)| (p - q).abs())
                .collect::<Vec<_>>()
        })
        .fold(0.0, f32::max)
}

#[test]
fn with_knn_a_model_pruned_of_closed_anchors_decodes_to_its_own_renders() {
    // The file leaves out closed anchors (pruning gate shut, or every AAC slot gated) and the
    // decoder rebuilds the kNN lists over the anchors it keeps. A model whose neighbours' blend
    // still reads closed anchors therefore decodes to other renders; pruned by the training's
    // rule (`prune_closed_anchors`, run to the last step), it decodes to its own (attributes on
    // the grid, so nothing else differs).
    let m = model(FeatureMasking::Off, 6, true, 14);
    // Anchors at distinct random voxels: `model`'s regular grid ties distances, and the decoded
    // set (Morton order) would break the ties otherwise than the model's rows.
    let mut rng = StdRng::seed_from_u64(14);
    let positions: Vec<[f32; 3]> = (0..m.anchors.len())
        .map(|_| {
            let mut voxel = |lo: i32, hi: i32| rng.random_range(lo..hi) as f32 * VOXEL;
            [voxel(-150, 150), voxel(-100, 100), voxel(290, 340)]
        })
        .collect();
    let rows = copied_rows(&m, positions);
    let mut anchors = AnchorSet::from_rows(m.anchors.dims, rows, &Device::ndarray());
    anchors.slot_gates = m.anchors.slot_gates.clone();
    let mut m = AnchoredModel { anchors, ..m };
    // Anchor 7's pruning gate is closed (`model`); close every slot of anchor 12 as well.
    m.anchors
        .slot_gates
        .edit(|flags| flags[12 * 4..13 * 4].fill(false));
    // A motion head that moves anchors (its last layer starts at zero), so the blended motion
    // input reaches the image.
    let output = &mut m.decoders.motion.output;
    let shape = output.weight.val().dims();
    let weights: Vec<f32> = (0..shape[0] * shape[1])
        .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.02)
        .collect();
    output.weight = burn::module::Param::from_tensor(Tensor::from_data(
        TensorData::new(weights, shape),
        &Device::ndarray(),
    ));
    let decoded = |m: &AnchoredModel| {
        decode(&quantize(m).encode(None, ModelChoice::Smallest).unwrap())
            .unwrap()
            .to_model(&Device::ndarray())
            .unwrap()
    };
    let stale = decoded(&m);
    assert_eq!(
        stale.anchors.len(),
        58,
        "the file leaves out both closed anchors"
    );
    let moved = render_difference(&m, &stale, 3);
    assert!(
        moved > 1e-3,
        "the dropped anchors' neighbours render alike: {moved}"
    );

    let mut state = AnchorState::new(&m.anchors, 0, AdamConfig::default());
    assert_eq!(prune_closed_anchors(&mut m.anchors, &mut state), 2);
    let rebuilt = decoded(&m);
    assert_eq!(
        rebuilt.anchors.len(),
        m.anchors.len(),
        "the file keeps every anchor left"
    );
    assert_renders_alike(&m, &rebuilt, 3);
}

#[test]
fn the_quantised_model_stays_close_to_the_full_precision_one() {
    // Off-grid attributes: the r0 grid moves a render by a bounded amount (a property of the
    // grid's fineness, not of the coder): PSNR between the two stays high.
    let m = model(FeatureMasking::Off, 0, false, 13);
    let rebuilt = quantize(&m).to_model(&Device::ndarray()).unwrap();
    let p = psnr(&render(&m, 1), &render(&rebuilt, 1));
    assert!(p > 25.0, "{p} dB");
}

/// The row of `m` whose anchor a decoded anchor at `p` came from (anchors are stored in Morton
/// order; decoded positions are the voxel grid's, within float rounding of the model's).
fn source_row(m: &AnchoredModel, p: [f32; 3]) -> usize {
    let distance = |q: &[f32; 3]| (0..3).map(|c| (q[c] - p[c]).powi(2)).sum::<f32>();
    let source = (0..m.anchors.len())
        .min_by(|&i, &j| {
            distance(&m.anchors.positions[i]).total_cmp(&distance(&m.anchors.positions[j]))
        })
        .expect("a model with anchors");
    assert!(
        distance(&m.anchors.positions[source]) < (0.01 * VOXEL).powi(2),
        "no anchor of the model at {p:?}"
    );
    source
}

#[test]
fn step_overrides_are_the_grid_the_file_codes_and_records() {
    // `compression.steps` replaces single attributes' steps: the encoder codes on that grid
    // (each decoded feature within half a step of the original), the file records it, and a
    // finer grid renders closer to the full-precision model than the preset's.
    let m = model(FeatureMasking::Off, 0, false, 13);
    let config = CompressionConfig {
        steps: acags::config::StepOverrides {
            features: Some(0.125),
            time_features: Some(0.125),
            log_scales: Some(0.005),
            offsets: Some(0.005),
            motion_gate: Some(1.0 / 1024.0),
            ..Default::default()
        },
        ..Default::default()
    };
    let steps = config.quantization_steps();
    assert_eq!(steps.features, 0.125);
    assert_eq!(steps.factors, RatePreset::R0.steps().factors);
    let scene = QuantizedScene::from_model(
        &m,
        RatePreset::R0,
        steps,
        Phase::Dynamic,
        (0, 3),
        VOXEL,
        String::new(),
    )
    .unwrap();
    let decoded = decode(&scene.encode(None, ModelChoice::Smallest).unwrap()).unwrap();
    assert_eq!(decoded.meta.steps, steps);
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    let cf = m.anchors.dims.feature_dim;
    let original = m.anchors.host(Column::Features);
    let coded = rebuilt.anchors.host(Column::Features);
    let (gates_in, gates_out) = (
        m.anchors.host(Column::Factors),
        rebuilt.anchors.host(Column::Factors),
    );
    let sig = |r: f32| 1.0 / (1.0 + (-r).exp());
    for a in 0..rebuilt.anchors.len() {
        let source = source_row(&m, rebuilt.anchors.positions[a]);
        for c in 0..cf {
            let (x, y) = (coded[a * cf + c], original[source * cf + c]);
            assert!(
                (x - y).abs() <= 0.5 * 0.125 + 1e-5,
                "anchor {a} channel {c}: {x} vs {y}"
            );
        }
        // Each gate on its own grid: the motion gate on 1/1024, the others on 1/16.
        for (g, step) in steps.gate_steps().into_iter().enumerate() {
            let (x, y) = (sig(gates_out[a * 4 + g]), sig(gates_in[source * 4 + g]));
            assert!(
                (x - y).abs() <= 0.5 * step + 1e-5,
                "anchor {a} gate {g}: {x} vs {y} (step {step})"
            );
        }
    }
    let preset = quantize(&m).to_model(&Device::ndarray()).unwrap();
    let reference = render(&m, 1);
    let (fine, coarse) = (
        psnr(&reference, &render(&rebuilt, 1)),
        psnr(&reference, &render(&preset, 1)),
    );
    assert!(
        fine > coarse + 3.0,
        "finer grid {fine} dB, preset {coarse} dB"
    );
    // A step so fine that the indices leave the coder's range is refused by section name.
    let too_fine = QuantizedScene::from_model(
        &m,
        RatePreset::R0,
        acags::codec::quantization::QuantizationSteps {
            offsets: 1e-7,
            ..steps
        },
        Phase::Dynamic,
        (0, 3),
        VOXEL,
        String::new(),
    )
    .unwrap();
    let e = format!(
        "{:#}",
        too_fine.encode(None, ModelChoice::Smallest).unwrap_err()
    );
    assert!(
        e.contains("`offsets`") && e.contains("codable range"),
        "{e}"
    );
}

fn encoded() -> (QuantizedScene, Container) {
    let scene = quantize(&model(
        FeatureMasking::Adaptive {
            base: 5,
            threshold: 0.01,
        },
        6,
        false,
        14,
    ));
    // Conditional coding, so the entropy-model section and the autoregressive decoders are
    // exercised by the damage tests too.
    let models = entropy_models(&scene);
    let container = scene
        .encode(Some(&models), ModelChoice::Conditional)
        .unwrap();
    (scene, container)
}

fn decode(container: &Container) -> anyhow::Result<QuantizedScene> {
    // Through bytes, as a file would be read.
    let bytes = container.to_bytes();
    Ok(QuantizedScene::decode(&Container::from_bytes(&bytes, "mem")?, "mem")?.0)
}

fn entropy_models(scene: &QuantizedScene) -> HostEntropyModels {
    EntropyModels::seeded(scene.meta.decoder_sizes(), 5, &Device::ndarray()).host()
}

#[test]
fn damaged_sections_are_errors_never_panics() {
    // The container's checksums catch damage in a file; these payloads carry valid checksums
    // (as a buggy or malicious writer would produce), so every section parser and the rANS glue
    // see garbage directly.
    let (scene, container) = encoded();
    let mut rng = StdRng::seed_from_u64(15);
    let mut errors = 0;
    let mut cases = 0;
    for (index, section) in container.sections.iter().enumerate() {
        let len = section.data.len();
        let mut variants: Vec<Vec<u8>> = Vec::new();
        // Truncations at every length (all of them for short sections).
        let cut_step = (len / 64).max(1);
        variants.extend(
            (0..len)
                .step_by(cut_step)
                .map(|n| section.data[..n].to_vec()),
        );
        // Single bit flips, byte overwrites, and appended bytes.
        for _ in 0..60 {
            let mut d = section.data.clone();
            if !d.is_empty() {
                let at = rng.random_range(0..d.len());
                d[at] ^= 1 << rng.random_range(0..8);
            }
            variants.push(d);
            let mut d = section.data.clone();
            if !d.is_empty() {
                let at = rng.random_range(0..d.len());
                d[at] = rng.random();
            }
            variants.push(d);
        }
        variants.push([section.data.clone(), vec![0, 1, 2, 3]].concat());
        for data in variants {
            let mut damaged = container.clone();
            damaged.sections[index].data = data;
            cases += 1;
            let result = decode(&damaged);
            match result {
                Err(e) => {
                    errors += 1;
                    let message = format!("{e:#}");
                    assert!(
                        message.starts_with("mem"),
                        "error names the file: {message}"
                    );
                }
                // Some damage decodes to another valid scene (e.g. a flipped mantissa bit of a
                // decoder weight); it must then still re-encode and rebuild.
                Ok(other) => {
                    if other != scene {
                        other.encode(None, ModelChoice::Factorized).unwrap();
                    }
                }
            }
        }
    }
    assert!(cases > 1500, "{cases} damaged inputs");
    assert!(errors > cases / 2, "only {errors} of {cases} were rejected");
}

#[test]
fn wrong_versions_missing_and_unknown_sections_are_named() {
    let (_, container) = encoded();
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta["codec_version"] = serde_json::json!(CODEC_VERSION + 1);
    let mut c = container.clone();
    c.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("codec version"), "{err}");

    // A motion-gate step in a version-4 header (whose readers would decode the gate on the
    // factors' grid) is refused.
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta["codec_version"] = serde_json::json!(4);
    meta["steps"]["motion_gate"] = serde_json::json!(1.0 / 1024.0);
    let mut c = container.clone();
    c.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("motion-gate step"), "{err}");

    let mut c = container.clone();
    c.sections.retain(|s| s.name != "offsets");
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("no `offsets` section"), "{err}");

    let mut c = container.clone();
    c.push("surprise", vec![1, 2, 3]).unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("unknown section `surprise`"), "{err}");

    // A header claiming an absurd model is refused before anything is allocated.
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta["anchors"] = serde_json::json!(1u64 << 40);
    let mut c = container.clone();
    c.sections[0].data = serde_json::to_vec(&meta).unwrap();
    assert!(decode(&c).is_err());
}

#[test]
fn off_grid_positions_are_refused_with_the_reason() {
    let mut m = model(FeatureMasking::Off, 0, false, 16);
    m.anchors.positions[3][1] += 0.3 * VOXEL;
    let err = QuantizedScene::from_model(
        &m,
        RatePreset::R0,
        RatePreset::R0.steps(),
        Phase::Dynamic,
        (0, 3),
        VOXEL,
        String::new(),
    )
    .unwrap_err();
    assert!(err.to_string().contains("voxel grid"), "{err}");
}

#[test]
fn conditional_coding_round_trips_and_the_smallest_choice_never_loses() {
    let scene = quantize(&model(
        FeatureMasking::Adaptive {
            base: 5,
            threshold: 0.01,
        },
        6,
        false,
        17,
    ));
    let models = entropy_models(&scene);
    let sizes = |c: &Container| {
        c.sections
            .iter()
            .map(|s| (s.name.clone(), s.data.len()))
            .collect::<Vec<_>>()
    };
    let mut per_choice = Vec::new();
    for choice in [
        ModelChoice::Conditional,
        ModelChoice::Factorized,
        ModelChoice::Smallest,
    ] {
        let container = scene.encode(Some(&models), choice).unwrap();
        let bytes = container.to_bytes();
        let (decoded, carried) =
            QuantizedScene::decode(&Container::from_bytes(&bytes, "mem").unwrap(), "mem").unwrap();
        assert_eq!(decoded, scene, "{choice:?}");
        let reencoded = decoded.encode(carried.as_ref(), choice).unwrap().to_bytes();
        assert_eq!(reencoded, bytes, "{choice:?}: re-encode is byte-identical");
        per_choice.push(sizes(&container));
    }
    // The conditional file carries the models; the factorized one does not.
    assert!(per_choice[0].iter().any(|(n, _)| n == "entropy_models"));
    assert!(!per_choice[1].iter().any(|(n, _)| n == "entropy_models"));
    // Smallest takes, per attribute, the smaller of the two codings.
    for (name, bytes) in &per_choice[2] {
        let find = |v: &Vec<(String, usize)>| v.iter().find(|(n, _)| n == name).map(|x| x.1);
        if let (Some(a), Some(b)) = (find(&per_choice[0]), find(&per_choice[1])) {
            if name != "entropy_models" {
                assert_eq!(*bytes, a.min(b), "{name}");
            }
        }
    }
    // Conditional coding without models is refused.
    assert!(scene.encode(None, ModelChoice::Conditional).is_err());
}

#[test]
fn the_coder_predicts_what_the_trained_models_predict() {
    // Host evaluation (the coder's, fixed-order f32 loops) against Burn's forward pass of the
    // same weights: the means and scales that decide the code agree to float rounding.
    let sizes = EntropyModelSizes {
        feature_dim: 24,
        time_feature_dim: 8,
        slots: 10,
    };
    let device = Device::ndarray();
    let models = EntropyModels::seeded(sizes, 9, &device);
    let host = models.host();
    let weights = models.weights();
    assert_eq!(weights.len(), EntropyModels::weight_count(sizes));
    assert_eq!(EntropyModels::host_from_weights(sizes, &weights), host);
    let mut rng = StdRng::seed_from_u64(6);
    for ((_, mlp), host_mlp) in models.named().iter().zip(host.all()) {
        let rows = 32;
        let x: Vec<f32> = (0..rows * host_mlp.input)
            .map(|_| (rng.random::<f32>() - 0.5) * 8.0)
            .collect();
        let burn_out = host_values(&mlp.forward(Tensor::<2>::from_data(
            TensorData::new(x.clone(), [rows, host_mlp.input]),
            &device,
        )));
        for r in 0..rows {
            let out = host_mlp.forward(&x[r * host_mlp.input..(r + 1) * host_mlp.input]);
            for (o, &v) in out.iter().enumerate() {
                let b = burn_out[r * host_mlp.output + o];
                assert!((v - b).abs() <= 1e-4 * (1.0 + b.abs()), "{v} vs {b}");
            }
        }
    }
}

#[test]
fn bits_are_the_gaussian_bin_probability() {
    let device = Device::ndarray();
    let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v.clone(), [1, v.len()]), &device);
    // x = 2, μ = 0.4 (rounds to 0), σ = 1.5, no noise: −log2(Φ(2.5/1.5) − Φ(1.5/1.5)).
    let bits = host_values(&gaussian_bits(
        t(vec![2.0]),
        t(vec![0.4]),
        t(vec![1.5]),
        t(vec![0.0]),
    ))[0];
    let cdf = |x: f64| 0.5 * (1.0 + libm::erf(x / std::f64::consts::SQRT_2));
    let expected = -((cdf(2.5 / 1.5) - cdf(1.5 / 1.5)) + 1e-5).log2();
    assert!(
        (bits as f64 - expected).abs() < 1e-4,
        "{bits} vs {expected}"
    );
    // A negative scale output acts as its magnitude; tiny scales floor at 0.01.
    let neg = host_values(&gaussian_bits(
        t(vec![2.0]),
        t(vec![0.4]),
        t(vec![-1.5]),
        t(vec![0.0]),
    ))[0];
    assert_eq!(neg, bits);
    let sharp = host_values(&gaussian_bits(
        t(vec![0.0]),
        t(vec![0.0]),
        t(vec![1e-6]),
        t(vec![0.0]),
    ))[0];
    assert!(
        sharp.abs() < 1e-3,
        "a certain symbol costs ~0 bits: {sharp}"
    );
}

/// A masked model (F_base = 5 channels, no kNN) and entropy models started at its data, as
/// training starts them when the rate switches on: every attribute then lies within the predicted
/// Gaussians and passes gradients.
fn masked_model_with_started_entropy_models(seed: u64) -> (AnchoredModel, EntropyModels) {
    let m = model(
        FeatureMasking::Adaptive {
            base: 5,
            threshold: 0.01,
        },
        0,
        false,
        seed,
    );
    let models = started_entropy_models(&m);
    (m, models)
}

/// Entropy models sized for `m` and started at its data (r0 steps).
fn started_entropy_models(m: &AnchoredModel) -> EntropyModels {
    let d = m.anchors.dims;
    let sizes = EntropyModelSizes {
        feature_dim: d.feature_dim,
        time_feature_dim: d.time_feature_dim,
        slots: d.slots,
    };
    let mut models = EntropyModels::seeded(sizes, 4, &Device::ndarray());
    models.start_from(&m.anchors, &RatePreset::R0.steps());
    models
}

#[test]
fn the_rate_ignores_gated_offsets_and_masked_channels_and_trains_the_models() {
    let (m, models) = masked_model_with_started_entropy_models(18);
    let set = &m.anchors;
    let steps = RatePreset::R0.steps();
    let rate_of = |set: &AnchorSet| {
        let tracked_models = models.tracked();
        let tensors = set.tracked();
        let kept = acags::model::feature_mask::binary_mask(tensors.mask_logits(), 0.01).detach();
        let terms = rate(
            &tracked_models,
            &tensors,
            &RateInputs {
                steps: &steps,
                base_channels: 5,
                adapt_kept: Some(kept),
                slot_gates: set.slot_gates.mirror().cloned(),
                frame: 1,
                raw: &tensors,
                bit_estimate: BitEstimate::Unquantised,
                trajectory: TrajectoryRate::Unpriced,
            },
            NoiseStream {
                seed: 7,
                step: 0,
                stream: 0,
            },
        );
        (terms, tracked_models, tensors)
    };
    let (terms, tracked_models, tensors) = rate_of(set);
    let value = |t: &Tensor<1>| host_values(&t.clone().reshape([1]))[0];
    let base = [value(&terms.offsets), value(&terms.features)];
    // Moving a gated offset, or a masked anchor's adaptive channel, changes no bit.
    let mut moved = set.clone();
    let mut offsets = moved.host(Column::Offsets);
    let gated = moved.slot_gates.iter().position(|&g| !g).unwrap();
    offsets[gated * 3] += 3.0;
    moved.set_host(Column::Offsets, offsets);
    let mut features = moved.host(Column::Features);
    let masked = moved.adapt_masked().iter().position(|&m| m).unwrap();
    features[masked * 8 + 6] += 5.0;
    moved.set_host(Column::Features, features);
    let (moved_terms, _, _) = rate_of(&moved);
    assert_eq!(value(&moved_terms.offsets), base[0]);
    // The AR context of a masked anchor is its masked feature: nothing changes either.
    assert_eq!(value(&moved_terms.features), base[1]);
    // ...while an active slot's offset does count.
    let mut active = set.clone();
    let mut offsets = active.host(Column::Offsets);
    let live = active.slot_gates.iter().position(|&g| g).unwrap();
    offsets[live * 3] += 0.5;
    active.set_host(Column::Offsets, offsets);
    assert_ne!(value(&rate_of(&active).0.offsets), base[0]);
    // Gradients reach every entropy model and the coded attributes.
    let grads = terms.total().backward();
    for (name, mlp) in tracked_models.named() {
        let g = host_values(&mlp.output.weight.val().grad(&grads).unwrap());
        assert!(g.iter().any(|&v| v != 0.0), "{name} gets no gradient");
    }
    assert!(
        host_values(&tensors.columns[Column::Features].grad(&grads).unwrap())
            .iter()
            .any(|&v| v != 0.0)
    );
}

#[test]
fn the_bits_are_estimated_on_the_unquantised_values_and_the_contexts_on_the_simulated_ones() {
    // GIFStream's bit estimate codes value / step + one U(±½) draw and conditions on what the
    // decoder sees: rounding the simulated scales, offsets and gates (no context of anything)
    // changes no term, while rounding the simulated features (every model's context) does.
    let (m, models) = masked_model_with_started_entropy_models(20);
    let set = &m.anchors;
    let steps = RatePreset::R0.steps();
    let raw = set.tracked();
    let kept = acags::model::feature_mask::binary_mask(raw.mask_logits(), 0.01).detach();
    let value = |t: &Tensor<1>| host_values(&t.clone().reshape([1]))[0];
    let terms_with = |sim: &acags::model::anchors::AnchorTensors, bit_estimate| {
        let t = rate(
            &models.tracked(),
            sim,
            &RateInputs {
                steps: &steps,
                base_channels: 5,
                adapt_kept: Some(kept.clone()),
                slot_gates: set.slot_gates.mirror().cloned(),
                frame: 1,
                raw: &raw,
                bit_estimate,
                trajectory: TrajectoryRate::Unpriced,
            },
            NoiseStream {
                seed: 9,
                step: 0,
                stream: 0,
            },
        );
        [
            t.log_scales,
            t.offsets,
            t.factors,
            t.features,
            t.time_features,
        ]
        .map(|v| value(&v))
    };
    let terms =
        |sim: &acags::model::anchors::AnchorTensors| terms_with(sim, BitEstimate::Unquantised);
    let plain = terms(&raw);
    // Without simulation both estimates price the same values.
    assert_eq!(terms_with(&raw, BitEstimate::Simulated), plain);
    let round = QuantizationPhase::Round;
    let mut sim = raw.clone();
    sim.columns[Column::LogScales] = ColumnTensor::Rows(fake_quantize(
        raw.log_scales(),
        steps.log_scales,
        round,
        NoiseKey::new(10, 0, 0, 0),
    ));
    sim.columns[Column::Offsets] = ColumnTensor::Grid(fake_quantize(
        raw.offsets(),
        steps.offsets,
        round,
        NoiseKey::new(10, 0, 0, 1),
    ));
    sim.columns[Column::Factors] = ColumnTensor::Rows(fake_quantize_gate_logits(
        raw.factors(),
        &steps.gate_steps(),
        round,
        NoiseKey::new(10, 0, 0, 2),
    ));
    assert_ne!(
        host_values(&sim.log_scales()),
        host_values(&raw.log_scales())
    );
    assert_eq!(terms(&sim), plain);
    // The pre-issue-19 estimate (`bit_estimate = "simulated"`) prices the rounded values instead.
    // (Not the gates: this model's σ(gate) is 0.5, already on the grid.)
    let priced_simulated = terms_with(&sim, BitEstimate::Simulated);
    for (term, (a, b)) in ["scales", "offsets"]
        .iter()
        .zip(priced_simulated.iter().zip(&plain))
    {
        assert_ne!(a, b, "the simulated estimate ignores the simulated {term}");
    }
    sim.columns[Column::Features] = ColumnTensor::Rows(fake_quantize(
        raw.features(),
        steps.features,
        round,
        NoiseKey::new(10, 0, 0, 3),
    ));
    assert_ne!(host_values(&sim.features()), host_values(&raw.features()));
    let with_contexts = terms(&sim);
    // (The features' own context is chunks j−3..j−1: this model's 8 channels are one chunk, so
    // it is the zero padding.)
    for (term, (a, b)) in ["scales", "offsets", "gates"]
        .iter()
        .zip(with_contexts.iter().zip(&plain))
    {
        assert_ne!(a, b, "the {term} bits ignore the simulated context");
    }
}

#[test]
fn the_trajectory_rate_prices_the_knots_as_the_file_codes_them() {
    // Knots on the grid, uniform in ±0.2 (±40 steps), a knot every frame; every fourth anchor's
    // motion gate closed.
    let m = model_with(FeatureMasking::Off, 0, true, 23, 1);
    let d = m.anchors.dims;
    let steps = RatePreset::R0.steps();
    let models = started_entropy_models(&m);
    let value = |t: &Tensor<1>| host_values(&t.clone().reshape([1]))[0];
    let terms_of = |set: &AnchorSet, trajectory| {
        let tensors = set.tracked();
        let terms = rate(
            &models.tracked(),
            &tensors,
            &RateInputs {
                steps: &steps,
                base_channels: d.feature_dim,
                adapt_kept: None,
                slot_gates: set.slot_gates.mirror().cloned(),
                frame: 1,
                raw: &tensors,
                bit_estimate: BitEstimate::Simulated,
                trajectory,
            },
            NoiseStream {
                seed: 5,
                step: 0,
                stream: 0,
            },
        );
        (terms, tensors)
    };
    let (unpriced, _) = terms_of(&m.anchors, TrajectoryRate::Unpriced);
    assert!(unpriced.trajectory.is_none());
    let (terms, tensors) = terms_of(&m.anchors, TrajectoryRate::Factorized);
    let per_value = value(terms.trajectory.as_ref().unwrap());
    // Priced on top of the other attributes.
    assert!(
        (value(&terms.total()) - value(&unpriced.total()) - per_value).abs() < 1e-3,
        "the total adds the trajectory's bits"
    );

    // Against the coder: the file's factorized `trajectory` section, per stored value.
    let scene = quantize(&m);
    let bytes = scene
        .encode(None, ModelChoice::Factorized)
        .unwrap()
        .to_bytes();
    let container = Container::from_bytes(&bytes, "mem").unwrap();
    let section = container.get("trajectory").unwrap();
    assert_eq!(section[0], 0, "uniform knots: the per-axis coding");
    // Without its header: kind, channel count, 3 × (mean, level), radius, stream length.
    let header = 1 + 4 + 3 * 5 + 4 + 4;
    let moving = (0..scene.voxels.len())
        .filter(|&a| {
            let q = scene.factors[a * 4 + acags::model::anchors::MOTION_GATE];
            q as f32 * steps.motion_gate_step() >= 0.1
        })
        .count();
    let stored = (moving * d.trajectory_width()) as f32;
    let file_per_value = (section.len() - header) as f32 * 8.0 / stored;
    assert!(
        (per_value / file_per_value - 1.0).abs() < 0.05,
        "the rate prices {per_value:.3} bits per knot value, the file spends {file_per_value:.3}"
    );

    // Knots of anchors whose motion gate is closed are not priced; the others' are, and get
    // gradients (the closed ones none).
    let grads = terms.trajectory.unwrap().backward();
    let g = host_values(&tensors.columns[Column::Trajectory].grad(&grads).unwrap());
    let w = d.trajectory_width();
    for a in 0..m.anchors.len() {
        let row = &g[a * w..(a + 1) * w];
        if a % 4 == 0 {
            assert!(
                row.iter().all(|&v| v == 0.0),
                "closed anchor {a} gets a gradient"
            );
        } else {
            assert!(
                row.iter().any(|&v| v != 0.0),
                "open anchor {a} gets no gradient"
            );
        }
    }
    let mut moved = m.anchors.clone();
    let mut knots = moved.host(Column::Trajectory);
    knots[4 * w] += 0.3;
    moved.set_host(Column::Trajectory, knots.clone());
    let (closed_moved, _) = terms_of(&moved, TrajectoryRate::Factorized);
    assert_eq!(value(&closed_moved.trajectory.unwrap()), per_value);
    knots[5 * w] += 0.3;
    moved.set_host(Column::Trajectory, knots);
    let (open_moved, _) = terms_of(&moved, TrajectoryRate::Factorized);
    assert_ne!(value(&open_moved.trajectory.unwrap()), per_value);
}

#[test]
fn the_rate_on_sampled_anchors_is_the_rate_of_those_anchors() {
    let (m, models) = masked_model_with_started_entropy_models(19);
    let set = &m.anchors;
    let steps = RatePreset::R0.steps();
    let rows: Vec<u32> = vec![0, 3, 4, 17, 30, 31, 58];
    let value = |t: &Tensor<1>| host_values(&t.clone().reshape([1]))[0];
    let terms_of = |tensors: &acags::model::anchors::AnchorTensors,
                    raw: &acags::model::anchors::AnchorTensors,
                    kept: Tensor<2>,
                    gates: Option<Tensor<2>>| {
        rate(
            &models.tracked(),
            tensors,
            &RateInputs {
                steps: &steps,
                base_channels: 5,
                adapt_kept: Some(kept),
                slot_gates: gates,
                frame: 2,
                raw,
                bit_estimate: BitEstimate::Unquantised,
                trajectory: TrajectoryRate::Unpriced,
            },
            NoiseStream {
                seed: 8,
                step: 0,
                stream: 0,
            },
        )
    };
    // Sampled through `sample_rows`...
    let tensors = set.tracked();
    let kept = acags::model::feature_mask::binary_mask(tensors.mask_logits(), 0.01).detach();
    assert!(
        set.slot_gates.mirror().is_some(),
        "some slots are gated, so the sampled gates are priced"
    );
    let (sim, raw, kept, gates) = acags::codec::rate::sample_rows(
        &tensors,
        &tensors,
        Some(&kept),
        set.slot_gates.mirror(),
        &rows,
    );
    let sampled = terms_of(&sim, &raw, kept.unwrap(), gates);
    // ...equals the rate of a set holding only those anchors.
    let mut subset = set.clone();
    subset.keep(&rows.iter().map(|&r| r as usize).collect::<Vec<_>>());
    let t = subset.tracked();
    let k = acags::model::feature_mask::binary_mask(t.mask_logits(), 0.01).detach();
    let direct = terms_of(&t, &t, k, subset.slot_gates.mirror().cloned());
    for (a, b) in [
        (&sampled.log_scales, &direct.log_scales),
        (&sampled.offsets, &direct.offsets),
        (&sampled.factors, &direct.factors),
        (&sampled.features, &direct.features),
        (&sampled.time_features, &direct.time_features),
    ] {
        assert!(
            (value(a) - value(b)).abs() <= 1e-5,
            "{} vs {}",
            value(a),
            value(b)
        );
    }
    // Gradients reach the sampled anchors only.
    let grads = sampled.total().backward();
    let g = host_values(&tensors.columns[Column::Features].grad(&grads).unwrap());
    let cf = set.dims.feature_dim;
    for a in 0..set.len() {
        let touched = g[a * cf..(a + 1) * cf].iter().any(|&v| v != 0.0);
        assert_eq!(touched, rows.contains(&(a as u32)), "anchor {a}");
    }
}

#[test]
fn fuzz_records_round_trip_and_random_records_never_panic() {
    // The record format of the `decode_sections` fuzz target: a real file survives it...
    let (scene, container) = encoded();
    let records = acags::codec::bitstream::records_from_container(&container);
    let rebuilt = acags::codec::bitstream::container_from_records(&records);
    assert_eq!(QuantizedScene::decode(&rebuilt, "mem").unwrap().0, scene);
    // ...and what the fuzzer starts from (mutated seeds, random records) is an error or a scene,
    // never a panic.
    let mut rng = StdRng::seed_from_u64(21);
    for i in 0..400 {
        let mut data = records.clone();
        for _ in 0..1 + i % 8 {
            let at = rng.random_range(0..data.len());
            data[at] = rng.random();
        }
        if i % 3 == 0 {
            data.truncate(rng.random_range(0..data.len()));
        }
        let _ = QuantizedScene::decode(
            &acags::codec::bitstream::container_from_records(&data),
            "fuzz",
        );
        let noise: Vec<u8> = (0..rng.random_range(0..300))
            .map(|_| rng.random())
            .collect();
        let _ = QuantizedScene::decode(
            &acags::codec::bitstream::container_from_records(&noise),
            "fuzz",
        );
    }
}

#[test]
fn trajectories_round_trip_and_closed_motion_gates_store_none() {
    // Attributes on the grid, no kNN: decode → render must equal the model's render at every
    // frame, including the frame between two knots, and the trajectory must move the render.
    let m = model_with(FeatureMasking::Off, 0, true, 21, 2);
    let knots = m.anchors.dims.trajectory_knots();
    assert_eq!(knots, 2, "3 frames, a knot every 2: frames 0 and 2");
    let scene = quantize(&m);
    assert_eq!(scene.meta.trajectory_spacing, 2);
    let bytes = scene
        .encode(None, ModelChoice::Smallest)
        .unwrap()
        .to_bytes();
    let container = Container::from_bytes(&bytes, "mem").unwrap();
    assert!(container.get("trajectory").is_some());
    let (decoded, _) = QuantizedScene::decode(&container, "mem").unwrap();
    assert_eq!(decoded, scene);
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    assert_renders_alike(&m, &rebuilt, 3);
    let mut still = m.clone();
    let zeros = vec![0.0; still.anchors.len() * still.anchors.dims.trajectory_width()];
    still.anchors.set_host(Column::Trajectory, zeros);
    assert_ne!(
        render(&m, 1),
        render(&still, 1),
        "the trajectory moves the scene"
    );

    // Knots decode to the model's values where the motion gate is open, to zero where it is
    // closed (no decode reads them); the stored rows are knot-to-knot increments.
    let original = m.anchors.host(Column::Trajectory);
    let values = rebuilt.anchors.host(Column::Trajectory);
    let factors = rebuilt.anchors.host(Column::Factors);
    let width = 3 * knots;
    let mut open = 0;
    for (a, row) in values.chunks_exact(width).enumerate() {
        let gate = 1.0 / (1.0 + (-factors[a * 4 + 1]).exp());
        if gate < 0.1 {
            assert!(row.iter().all(|&v| v == 0.0), "anchor {a}: {row:?}");
        } else {
            open += 1;
            let source = source_row(&m, rebuilt.anchors.positions[a]);
            let want = &original[source * width..(source + 1) * width];
            for (x, y) in row.iter().zip(want) {
                assert!((x - y).abs() < 1e-6, "anchor {a}: {row:?} vs {want:?}");
            }
        }
    }
    assert!(open > 30, "{open} anchors with an open motion gate");
}

/// Turns derived from the paths (`model.trajectory_turn = "paths"`) are not stored: the file has
/// no `turn` section and the decoder derives, from the decoded trajectories and neighbour lists,
/// the turns the model had, which act on the render.
#[test]
fn derived_turns_are_not_stored_and_the_decoder_derives_the_same() {
    derived_turns_round_trip(TrajectoryTurn::Paths);
}

/// The same for turns derived per object (`model.trajectory_turn = "objects"`), on a compact
/// cloud whose open-gated anchors move rigidly (its paths on the file's grid): the decoder
/// groups the decoded paths as training grouped its own and derives the same turns.
#[test]
fn turns_derived_per_object_are_not_stored_and_the_decoder_derives_the_same() {
    derived_turns_round_trip(TrajectoryTurn::Objects);
}

fn derived_turns_round_trip(turn: TrajectoryTurn) {
    use acags::model::path_turns::derive_path_turns;
    use glam::{Quat, Vec3};
    let m = model_with(FeatureMasking::Off, 6, true, 37, 2);
    let d = AnchorDims {
        trajectory_turn: turn,
        ..m.anchors.dims
    };
    let factors = m.anchors.host(Column::Factors);
    let gate = |a: usize| 1.0 / (1.0 + (-factors[a * 4 + 1]).exp());
    let width = d.trajectory_width();
    let (positions, mut trajectory) = if turn == TrajectoryTurn::Objects {
        // Anchors 5 voxels apart, on the voxel grid; knot 1 turns them 0.6 rad about their
        // centroid and shifts them by 0.1.
        let positions: Vec<[f32; 3]> = (0..m.anchors.len())
            .map(|i| {
                [
                    (i % 10) as f32 * 5.0 * VOXEL,
                    (i / 10) as f32 * 5.0 * VOXEL,
                    (300 + (i % 3) * 2) as f32 * VOXEL,
                ]
            })
            .collect();
        let centre = positions.iter().map(|&p| Vec3::from(p)).sum::<Vec3>()
            / positions.len() as f32;
        let rotation = Quat::from_axis_angle(Vec3::new(0.2, 0.3, 0.9).normalize(), 0.6);
        let steps = RatePreset::R0.steps();
        let trajectory: Vec<f32> = (0..positions.len())
            .flat_map(|a| {
                let p = Vec3::from(positions[a]);
                let moved = rotation * (p - centre) + centre + Vec3::new(0.1, 0.0, 0.0);
                let knot = round_to_grid(&((moved - p) / gate(a)).to_array(), steps.trajectory);
                [0.0, 0.0, 0.0].into_iter().chain(knot)
            })
            .collect();
        (positions, trajectory)
    } else {
        (m.anchors.positions.clone(), m.anchors.host(Column::Trajectory))
    };
    assert_eq!(trajectory.len(), m.anchors.len() * width);
    // As the file keeps them: no knots where the motion gate is closed ...
    for (a, row) in trajectory.chunks_exact_mut(width).enumerate() {
        if gate(a) < 0.1 {
            row.fill(0.0);
        }
    }
    let rows = copied_rows(&m, positions)
        .with(Column::Trajectory, trajectory)
        .with(Column::Turn, vec![0.0; m.anchors.len() * d.turn_width()]);
    let mut anchors = AnchorSet::from_rows(d, rows, &Device::ndarray());
    anchors.slot_gates = m.anchors.slot_gates.clone();
    let m = AnchoredModel { anchors, ..m };
    // ... and only the anchors it keeps (training prunes the others at its last step), in the
    // model's order, which the file does not keep.
    let stored = quantize(&m).to_model(&Device::ndarray()).unwrap();
    let mut kept: Vec<usize> = (0..stored.anchors.len())
        .map(|a| source_row(&m, stored.anchors.positions[a]))
        .collect();
    kept.sort_unstable();
    assert!(kept.len() < m.anchors.len(), "the file drops anchors");
    let pick = |c: Column| -> Vec<f32> {
        let (values, w) = (m.anchors.host(c), c.width(&d).unwrap());
        kept.iter()
            .flat_map(|&a| values[a * w..(a + 1) * w].to_vec())
            .collect()
    };
    let positions = kept.iter().map(|&a| m.anchors.positions[a]).collect();
    let rows =
        Column::present(&d).fold(NewAnchors::new(positions), |rows, c| rows.with(c, pick(c)));
    let mut anchors = AnchorSet::from_rows(d, rows, &Device::ndarray());
    anchors.slot_gates = m.anchors.slot_gates.clone();
    anchors.slot_gates.keep_anchors(&kept);
    derive_path_turns(&mut anchors);
    let m = AnchoredModel { anchors, ..m };
    let turns = m.anchors.host(Column::Turn);
    assert!(
        turns.iter().filter(|v| v.abs() > 0.05).count() > 30,
        "the random paths imply turns"
    );

    let scene = quantize(&m);
    assert_eq!(scene.meta.trajectory_turn, turn);
    assert!(scene.turn.is_empty());
    let container = scene.encode(None, ModelChoice::Smallest).unwrap();
    assert!(container.get("turn").is_none());
    let container = Container::from_bytes(&container.to_bytes(), "mem").unwrap();
    let (decoded, _) = QuantizedScene::decode(&container, "mem").unwrap();
    assert_eq!(decoded, scene);
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    assert_eq!(rebuilt.anchors.len(), m.anchors.len());
    let derived = rebuilt.anchors.host(Column::Turn);
    let width = d.turn_width();
    for (a, row) in derived.chunks_exact(width).enumerate() {
        // The file orders the anchors its own way.
        let source = source_row(&m, rebuilt.anchors.positions[a]);
        let want = &turns[source * width..(source + 1) * width];
        for (x, y) in row.iter().zip(want) {
            assert!(
                (x - y).abs() < 1e-4,
                "anchor {a}: decoded {row:?} vs trained {want:?}"
            );
        }
    }
    assert_renders_alike(&m, &rebuilt, 3);
    let mut unturned = m.clone();
    unturned
        .anchors
        .set_host(Column::Turn, vec![0.0; turns.len()]);
    assert_ne!(render(&m, 2), render(&unturned, 2));
}

#[test]
fn trajectory_turns_round_trip_and_turn_the_render() {
    let m = turned_model(31, 1.5);
    let scene = quantize(&m);
    assert_eq!(scene.meta.trajectory_turn, TrajectoryTurn::Knots);
    let container = scene.encode(None, ModelChoice::Smallest).unwrap();
    let bytes = container.to_bytes();
    let container = Container::from_bytes(&bytes, "mem").unwrap();
    assert!(container.get("turn").is_some());
    let (decoded, _) = QuantizedScene::decode(&container, "mem").unwrap();
    assert_eq!(decoded, scene);
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    assert_renders_alike(&m, &rebuilt, 3);
    // The turns act on the render (frame 0 included: knot 0 holds a turn too) ...
    let mut unturned = m.clone();
    let zeros = vec![0.0; m.anchors.len() * m.anchors.dims.turn_width()];
    unturned.anchors.set_host(Column::Turn, zeros);
    for frame in 0..3 {
        assert_ne!(render(&m, frame), render(&unturned, frame), "frame {frame}");
    }
    // ... and a closed motion gate stores none: its anchor decodes with zero turns.
    let factors = rebuilt.anchors.host(Column::Factors);
    let turns = rebuilt.anchors.host(Column::Turn);
    let width = m.anchors.dims.turn_width();
    let mut closed = 0;
    for (a, row) in turns.chunks_exact(width).enumerate() {
        if 1.0 / (1.0 + (-factors[a * 4 + 1]).exp()) < 0.1 {
            closed += 1;
            assert!(row.iter().all(|&v| v == 0.0), "anchor {a}: {row:?}");
        }
    }
    assert!(closed > 5, "{closed} anchors with a closed motion gate");

    // A turn section that went missing, a v2 file claiming turns, turns without trajectories,
    // and a turn section in a scene without turns are named.
    let mut c = container.clone();
    c.sections.retain(|s| s.name != "turn");
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("no `turn` section"), "{err}");
    let edit_meta = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut meta: serde_json::Value =
            serde_json::from_slice(container.get("meta").unwrap()).unwrap();
        edit(&mut meta);
        let mut c = container.clone();
        c.sections[0].data = serde_json::to_vec(&meta).unwrap();
        format!("{:#}", decode(&c).unwrap_err())
    };
    let err = edit_meta(&|m| m["codec_version"] = serde_json::json!(2));
    assert!(
        err.contains("version-2 scene cannot hold trajectory turns"),
        "{err}"
    );
    let err = edit_meta(&|m| m["trajectory_spacing"] = serde_json::json!(0));
    assert!(
        err.contains("turns in a scene without trajectories"),
        "{err}"
    );
    let err = edit_meta(&|m| m["steps"]["turn"] = serde_json::json!(0.0));
    assert!(err.contains("quantisation step of turn"), "{err}");
    let plain = quantize(&model_with(FeatureMasking::Off, 0, true, 31, 2))
        .encode(None, ModelChoice::Smallest)
        .unwrap();
    let mut c = plain.clone();
    c.push("turn", container.get("turn").unwrap().to_vec())
        .unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(
        err.contains("scene without stored trajectory turns"),
        "{err}"
    );
}

#[test]
fn knot_tables_of_mostly_still_anchors_are_coded_by_the_previous_knot() {
    // Two in three stored anchors keep still after their first knot, the others move by up to
    // ±500 steps per knot: one Gaussian per axis prices every still increment at the movers' σ,
    // the knot context (codec version 4) at almost nothing from the third knot on.
    let mut scene = quantize(&model_with(FeatureMasking::Off, 0, true, 24, 1));
    // Versions before 5 have no motion-gate step: the gates on the factors' grid.
    one_gate_grid(&mut scene);
    // A longer clip than the model's 3 frames: 12 knots (the streams left empty).
    let frames = 12;
    scene.meta.frames = frames;
    scene.meta.gop_frames = frames;
    scene.time_features = vec![0; scene.voxels.len() * frames * scene.meta.time_feature_dim];
    let knots = scene.meta.dims().trajectory_knots();
    assert_eq!(knots, frames);
    scene.trajectory = vec![0; scene.voxels.len() * knots * 3];
    let mut rng = StdRng::seed_from_u64(24);
    let stored = scene.trajectory.len() / (3 * knots);
    for a in 0..stored {
        let gate = scene.factors[a * 4 + acags::model::anchors::MOTION_GATE];
        let moving = gate as f32 * scene.meta.steps.motion_gate_step() >= 0.1;
        for j in 0..knots {
            for c in 0..3 {
                scene.trajectory[(a * knots + j) * 3 + c] = if !moving {
                    0
                } else if j == 0 || a % 3 == 0 {
                    rng.random_range(-500..=500)
                } else {
                    0
                };
            }
        }
    }
    let section = |scene: &QuantizedScene| {
        let c = scene.encode(None, ModelChoice::Smallest).unwrap();
        let (decoded, _) = QuantizedScene::decode(&c, "mem").unwrap();
        let version = scene.meta.codec_version;
        assert_eq!(decoded, *scene, "round trip at codec version {version}");
        (c.get("trajectory").unwrap().to_vec(), c)
    };
    assert_eq!(scene.meta.codec_version, CODEC_VERSION);
    let (by_knot, container) = section(&scene);
    let mut v3 = scene.clone();
    v3.meta.codec_version = 3;
    let (per_axis, _) = section(&v3);
    assert_eq!(by_knot[0], 2, "the knot-context coding is chosen");
    assert_eq!(
        per_axis[0], 0,
        "a version-3 scene keeps the per-axis coding"
    );
    assert!(
        by_knot.len() * 5 < per_axis.len() * 4,
        "knot context {} bytes, per axis {}",
        by_knot.len(),
        per_axis.len()
    );
    // A knot-context section in a file that claims version 3 is named.
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta["codec_version"] = serde_json::json!(3);
    let mut c = container.clone();
    c.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let err = format!("{:#}", QuantizedScene::decode(&c, "mem").unwrap_err());
    assert!(
        err.contains("knot-context coding in a version-3 scene"),
        "{err}"
    );
}

/// Moves the motion gate onto the factors' grid (what files before codec version 5 hold); the
/// test models' gates lie on the 1/16 grid, so nothing is rounded.
fn one_gate_grid(scene: &mut QuantizedScene) {
    let steps = scene.meta.steps;
    let ratio = steps.motion_gate_step() / steps.factors;
    for row in scene.factors.chunks_exact_mut(4) {
        let q = row[acags::model::anchors::MOTION_GATE] as f32 * ratio;
        assert_eq!(q, q.round(), "a motion gate off the factors' grid");
        row[acags::model::anchors::MOTION_GATE] = q as i32;
    }
    scene.meta.steps.motion_gate = None;
}

#[test]
fn version_one_files_decode_and_a_missing_trajectory_is_named() {
    // A v1 file (no trajectories, canonical culling): what earlier builds wrote.
    let m = model(FeatureMasking::Off, 0, true, 22);
    let mut scene = quantize(&m);
    one_gate_grid(&mut scene);
    scene.meta.codec_version = 1;
    let bytes = scene
        .encode(None, ModelChoice::Smallest)
        .unwrap()
        .to_bytes();
    let mut container = Container::from_bytes(&bytes, "mem").unwrap();
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta.as_object_mut().unwrap().remove("culling");
    meta.as_object_mut().unwrap().remove("trajectory_spacing");
    meta.as_object_mut().unwrap().remove("trajectory_turn");
    meta["steps"].as_object_mut().unwrap().remove("trajectory");
    meta["steps"].as_object_mut().unwrap().remove("turn");
    container.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let (decoded, _) = QuantizedScene::decode(&container, "mem").unwrap();
    assert_eq!(decoded.meta.trajectory_spacing, 0);
    assert_eq!(
        decoded.to_model(&Device::ndarray()).unwrap().culling,
        acags::model::view::AnchorCulling::Canonical
    );

    // A scene with trajectories whose section went missing, or one that claims v1.
    let scene = quantize(&model_with(FeatureMasking::Off, 0, true, 23, 1));
    let container = scene.encode(None, ModelChoice::Smallest).unwrap();
    // As a v2 build wrote it (trajectories, no turn keys, per-axis knot coding): decodes,
    // without turns.
    let mut v2_scene = scene.clone();
    one_gate_grid(&mut v2_scene);
    v2_scene.meta.codec_version = 2;
    let mut v2 = v2_scene.encode(None, ModelChoice::Smallest).unwrap();
    let mut meta: serde_json::Value = serde_json::from_slice(v2.get("meta").unwrap()).unwrap();
    meta.as_object_mut().unwrap().remove("trajectory_turn");
    meta["steps"].as_object_mut().unwrap().remove("turn");
    v2.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let (decoded, _) = QuantizedScene::decode(&v2, "mem").unwrap();
    assert_eq!(decoded.meta.trajectory_turn, TrajectoryTurn::Off);
    assert_eq!(decoded.trajectory, scene.trajectory);
    let rebuilt = decoded.to_model(&Device::ndarray()).unwrap();
    assert!(rebuilt.anchors.columns.get(Column::Turn).is_none());
    let mut c = container.clone();
    c.sections.retain(|s| s.name != "trajectory");
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("no `trajectory` section"), "{err}");
    let mut meta: serde_json::Value =
        serde_json::from_slice(container.get("meta").unwrap()).unwrap();
    meta["codec_version"] = serde_json::json!(1);
    let mut c = container.clone();
    c.sections[0].data = serde_json::to_vec(&meta).unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("cannot hold trajectories"), "{err}");
    // And a trajectory section in a scene without trajectories.
    let (_, plain) = encoded();
    let mut c = plain.clone();
    c.push("trajectory", container.get("trajectory").unwrap().to_vec())
        .unwrap();
    let err = format!("{:#}", decode(&c).unwrap_err());
    assert!(err.contains("scene without trajectories"), "{err}");
}
