//! GIFStream's decoders: sizes, activations, initialisation and the time embedding.
#![allow(deprecated)] // Device::ndarray

use acags::model::decoders::{
    DecoderInit, DecoderSizes, Decoders, ExtraHiddenUnits, TIME_EMBEDDING_DIM, time_embedding,
};
use burn::module::Module;
use burn::tensor::activation::relu;
use burn::tensor::{Device, Distribution, Tensor};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

const ACA: DecoderSizes = DecoderSizes {
    feature_dim: 48,
    time_feature_dim: 8,
    slots: 10,
};

#[test]
fn aca_gs_decoders_have_the_specified_size() {
    let decoders = Decoders::new(ACA, &Device::ndarray());
    // Spec §4.3: "≈17.4k parameters in total for C_T = 8" (C_F = 48, K = 10).
    assert_eq!(decoders.num_params(), 17_445);
}

#[test]
fn outputs_have_the_right_shapes_and_ranges() {
    let device = Device::ndarray().autodiff();
    let decoders = Decoders::new(ACA, &device);
    let m = 64;
    let attr = Tensor::<2>::random([m, 56], Distribution::Normal(0.0, 3.0), &device);
    let motion_in = Tensor::<2>::random(
        [m, 56 + TIME_EMBEDDING_DIM],
        Distribution::Normal(0.0, 1.0),
        &device,
    );
    let out = decoders.forward(attr, motion_in);
    assert_eq!(out.opacity.dims(), [m, 10]);
    assert_eq!(out.cov.dims(), [m, 70]);
    assert_eq!(out.color.dims(), [m, 30]);
    assert_eq!(out.motion.dims(), [m, 7]);
    assert!(
        values(out.opacity.clone())
            .iter()
            .all(|v| *v > -1.0 && *v < 1.0)
    );
    assert!(
        values(out.color.clone())
            .iter()
            .all(|v| *v > 0.0 && *v < 1.0)
    );
    // Motion is exactly zero at the start, yet its last layer receives a gradient.
    assert!(values(out.motion.clone()).iter().all(|v| *v == 0.0));
    let grads = out.motion.sum().backward();
    let g = values(decoders.motion.output.weight.val().grad(&grads).unwrap());
    assert!(g.iter().any(|v| *v != 0.0));
}

#[test]
fn initialisation_is_pytorch_linear_default() {
    check_pytorch_init(&Decoders::new(ACA, &Device::ndarray()));
    let seeded = Decoders::seeded(ACA, 7, &Device::ndarray());
    check_pytorch_init(&seeded);
    // Seeded: the same seed gives the same model, another seed another one; motion head zero.
    let again = Decoders::seeded(ACA, 7, &Device::ndarray());
    let other = Decoders::seeded(ACA, 8, &Device::ndarray());
    let w = |d: &Decoders| values(d.cov.hidden.weight.val());
    assert_eq!(w(&seeded), w(&again));
    assert_ne!(w(&seeded), w(&other));
    assert!(
        values(seeded.motion.output.weight.val())
            .iter()
            .all(|v| *v == 0.0)
    );
}

fn check_pytorch_init(decoders: &Decoders) {
    for (name, layer, fan_in) in [
        ("opacity.hidden", &decoders.opacity.hidden, 56usize),
        ("cov.output", &decoders.cov.output, 48),
        ("motion.hidden", &decoders.motion.hidden, 72),
    ] {
        let bound = 1.0 / (fan_in as f32).sqrt();
        let w = values(layer.weight.val());
        let b = values(layer.bias.as_ref().unwrap().val());
        assert!(
            w.iter().chain(&b).all(|v| v.abs() <= bound),
            "{name}: outside ±1/sqrt(fan_in)"
        );
        // Uniform on [-bound, bound]: the spread fills most of the range.
        let max = w.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(max > 0.9 * bound, "{name}: max |w| {max} vs bound {bound}");
    }
}

#[test]
fn time_embedding_values() {
    let device = Device::ndarray();
    let at_zero = values(time_embedding(0.0, 8.0, &device));
    assert_eq!(&at_zero[..8], &[0.0; 8]);
    assert_eq!(&at_zero[8..], &[1.0; 8]);
    let quarter = values(time_embedding(0.25, 8.0, &device));
    // n = 0: sin(pi/4); n = 1: sin(pi/2) = 1; n = 2: sin(pi) = 0; cos terms likewise.
    assert!((quarter[0] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
    assert!((quarter[1] - 1.0).abs() < 1e-6 && quarter[2].abs() < 1e-6);
    assert!(
        (quarter[8] - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6
            && quarter[9].abs() < 1e-6
            && (quarter[10] + 1.0).abs() < 1e-6
    );
}

/// Every parameter of `d`, by name, as host values.
fn parameters(d: &Decoders) -> Vec<(String, Vec<f32>)> {
    let mut out = Vec::new();
    for (head, mlp) in [
        ("opacity", &d.opacity),
        ("cov", &d.cov),
        ("color", &d.color),
        ("motion", &d.motion),
    ] {
        for (layer, linear) in [("hidden", &mlp.hidden), ("output", &mlp.output)] {
            out.push((
                format!("{head}.{layer}.weight"),
                values(linear.weight.val()),
            ));
            let bias = linear.bias.as_ref().unwrap().val();
            out.push((format!("{head}.{layer}.bias"), values(bias)));
        }
    }
    out
}

#[test]
fn paired_decoders_at_the_baselines_own_size_are_the_seeded_ones_bit_for_bit() {
    let device = Device::ndarray();
    for sizes in [ACA, BASE] {
        let seeded = parameters(&Decoders::seeded(sizes, 7, &device));
        // At its own size a model has no extra units: both ways of silencing them are `seeded`.
        for extra_units in [ExtraHiddenUnits::Silent, ExtraHiddenUnits::ZeroBias] {
            let paired = parameters(&Decoders::seeded_paired(
                sizes,
                sizes,
                extra_units,
                7,
                &device,
            ));
            assert_eq!(seeded, paired, "{sizes:?}, {extra_units:?}");
        }
        let initial = Decoders::initial(sizes, BASE, DecoderInit::Independent, 7, &device);
        assert_eq!(parameters(&initial), seeded, "independent is `seeded`");
    }
}

/// GIFStream's decoders on the synthetic scene (C_F = 24, K = 5).
const BASE: DecoderSizes = DecoderSizes {
    feature_dim: 24,
    time_feature_dim: 8,
    slots: 5,
};

/// Columns `range` of `t` [m, n].
fn columns(t: Tensor<2>, range: std::ops::Range<usize>) -> Vec<f32> {
    let m = t.dims()[0];
    values(t.slice([0..m, range]))
}

fn assert_close(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-5, "{what}: largest difference {worst}");
}

#[test]
fn a_paired_wider_model_decodes_its_baselines_gaussians_in_the_baselines_slots() {
    // Features start at 0, so at step 0 the decoded opacities are the same for every anchor and
    // decide for the whole set how many slots spawn; pairing makes a K_max = 10 (and C_F = 48)
    // model decode its baseline's Gaussians there. It holds for any feature on the baseline's
    // channels (and any stream), not only at zero, as long as the extra channels are zero.
    let device = Device::ndarray();
    let m = 32;
    let wide_cases = [
        (BASE, ACA),                                // ACA-GS over GIFStream
        (BASE, DecoderSizes { slots: 10, ..BASE }), // +AAC (C_F unchanged)
        (
            DecoderSizes {
                feature_dim: 48,
                ..BASE
            },
            ACA,
        ), // panoptic: C_F 48 in both
    ];
    for (baseline, sizes) in wide_cases {
        let base = Decoders::seeded(baseline, 42, &device);
        let wide = Decoders::seeded_paired(sizes, baseline, ExtraHiddenUnits::Silent, 42, &device);
        let (fb, f, t) = (
            baseline.feature_dim,
            sizes.feature_dim,
            baseline.time_feature_dim,
        );
        for zero_features in [true, false] {
            let features = if zero_features {
                Tensor::<2>::zeros([m, fb], &device)
            } else {
                Tensor::<2>::random([m, fb], Distribution::Normal(0.0, 1.0), &device)
            };
            let stream = Tensor::<2>::random([m, t], Distribution::Normal(0.0, 1.0), &device);
            let gamma =
                Tensor::<2>::random([m, TIME_EMBEDDING_DIM], Distribution::Default, &device);
            let extra = Tensor::<2>::zeros([m, f - fb], &device);
            let attr_base = Tensor::cat(vec![features.clone(), stream.clone()], 1);
            let attr_wide = Tensor::cat(vec![features, extra, stream], 1);
            let motion_base = Tensor::cat(vec![attr_base.clone(), gamma.clone()], 1);
            let motion_wide = Tensor::cat(vec![attr_wide.clone(), gamma], 1);
            let b = base.forward(attr_base, motion_base.clone());
            let w = wide.forward(attr_wide, motion_wide.clone());
            let k = baseline.slots;
            let what = |name: &str| {
                format!("{baseline:?} → {sizes:?}, {name}, zero features {zero_features}")
            };
            assert_close(
                &columns(w.opacity.clone(), 0..k),
                &values(b.opacity),
                &what("opacity"),
            );
            assert_close(
                &columns(w.cov.clone(), 0..7 * k),
                &values(b.cov),
                &what("cov"),
            );
            assert_close(
                &columns(w.color.clone(), 0..3 * k),
                &values(b.color),
                &what("colour"),
            );
            // The motion head's output is zero in both; its hidden units are paired too.
            assert_close(
                &columns(wide.motion.hidden.forward(motion_wide), 0..fb),
                &values(base.motion.hidden.forward(motion_base)),
                &what("motion hidden"),
            );
            // The extra slots are drawn, not copies or zeros.
            if sizes.slots > k {
                let extra_opacity = columns(w.opacity, k..sizes.slots);
                let spread = extra_opacity.iter().fold(0.0f32, |s, v| s.max(v.abs()));
                assert!(spread > 1e-2, "{}: extra slots {spread}", what("opacity"));
                let extra_cov = columns(w.cov, 7 * k..7 * sizes.slots);
                assert!(extra_cov.iter().any(|v| v.abs() > 1e-2), "{}", what("cov"));
            }
        }
        // Independently drawn, the same wide model does not decode the baseline's Gaussians
        // (the confound this removes).
        let independent = Decoders::seeded(sizes, 42, &device);
        assert_ne!(
            columns(
                values_tensor(&independent.opacity.output.bias),
                0..baseline.slots
            ),
            columns(values_tensor(&base.opacity.output.bias), 0..baseline.slots),
        );
    }
}

/// A bias as a [1, n] tensor.
fn values_tensor(bias: &Option<burn::module::Param<Tensor<1>>>) -> Tensor<2> {
    bias.as_ref().unwrap().val().unsqueeze::<2>()
}

#[test]
fn the_unpaired_weights_of_a_paired_model_are_pytorch_draws_and_its_extra_hidden_units_learn() {
    let device = Device::ndarray().autodiff();
    let wide = Decoders::seeded_paired(ACA, BASE, ExtraHiddenUnits::Silent, 42, &device);
    let hidden = values(wide.opacity.hidden.weight.val()); // [56, 48]
    let wide_bound = 1.0 / (56f32).sqrt();
    let base_bound = 1.0 / (32f32).sqrt();
    // Rows 24..48 are the extra feature channels and columns 24..48 the extra hidden units:
    // both are the wide layer's own draw; the paired block is the baseline's (larger) bound.
    let unpaired: Vec<f32> = (0..56)
        .flat_map(|i| (0..48).map(move |j| (i, j)))
        .filter(|&(i, j)| (24..48).contains(&i) || j >= 24)
        .map(|(i, j)| hidden[i * 48 + j])
        .collect();
    assert!(unpaired.iter().all(|v| v.abs() <= wide_bound));
    assert!(unpaired.iter().fold(0.0f32, |m, v| m.max(v.abs())) > 0.9 * wide_bound);
    assert!(hidden.iter().all(|v| v.abs() <= base_bound));
    // The extra hidden units' outgoing weights start at 0, yet take a gradient at step 0.
    let output = values(wide.opacity.output.weight.val()); // [48, 10]
    assert!(output[24 * 10..].iter().all(|v| *v == 0.0));
    assert!(output[..24 * 10].iter().any(|v| *v != 0.0));
    let attr = Tensor::<2>::random([64, 56], Distribution::Normal(0.0, 1.0), &device);
    let motion = Tensor::<2>::zeros([64, 56 + TIME_EMBEDDING_DIM], &device);
    let grads = wide.forward(attr, motion).opacity.sum().backward();
    let g = values(wide.opacity.output.weight.val().grad(&grads).unwrap());
    assert!(
        g[24 * 10..].iter().any(|v| *v != 0.0),
        "extra hidden units get no gradient"
    );
}

#[test]
#[should_panic(expected = "not a widening")]
fn pairing_with_a_wider_baseline_is_refused() {
    Decoders::seeded_paired(BASE, ACA, ExtraHiddenUnits::Silent, 1, &Device::ndarray());
}

#[test]
fn paired_drawn_units_start_as_the_baseline_at_step_0_and_their_extra_units_wake_with_the_features()
{
    // `paired-drawn-units`: the extra hidden units keep drawn outgoing weights and start with
    // bias 0, so on the all-zero step-0 input (features and time features start at 0) they
    // output 0 and the model decodes the baseline's Gaussians; once the features move they feed
    // the output at their drawn scale, where `paired`'s (outgoing 0) feed nothing.
    let device = Device::ndarray();
    let m = 16;
    let base = Decoders::seeded(BASE, 42, &device);
    let drawn = Decoders::initial(ACA, BASE, DecoderInit::PairedDrawnUnits, 42, &device);
    let silent = Decoders::initial(ACA, BASE, DecoderInit::Paired, 42, &device);
    let zero_attr = Tensor::<2>::zeros([m, 56], &device);
    let gamma = Tensor::<2>::random([m, TIME_EMBEDDING_DIM], Distribution::Default, &device);
    let motion_wide = Tensor::cat(vec![zero_attr.clone(), gamma.clone()], 1);
    let motion_base = Tensor::cat(vec![Tensor::<2>::zeros([m, 32], &device), gamma], 1);
    let b = base.forward(Tensor::<2>::zeros([m, 32], &device), motion_base);
    let w = drawn.forward(zero_attr, motion_wide);
    assert_close(&columns(w.opacity, 0..5), &values(b.opacity), "opacity");
    assert_close(&columns(w.cov, 0..35), &values(b.cov), "cov");
    assert_close(&columns(w.color, 0..15), &values(b.color), "colour");
    // Biases 0 on units 24..48, drawn outgoing weights within the wide layer's bound.
    for (head, mlp) in [
        ("opacity", &drawn.opacity),
        ("cov", &drawn.cov),
        ("color", &drawn.color),
    ] {
        let bias = values(mlp.hidden.bias.as_ref().unwrap().val());
        assert!(bias[24..].iter().all(|v| *v == 0.0), "{head}: extra biases");
        assert!(
            bias[..24].iter().any(|v| *v != 0.0),
            "{head}: paired biases"
        );
        let [_, outputs] = mlp.output.weight.dims();
        let out = values(mlp.output.weight.val());
        let extra = &out[24 * outputs..];
        let bound = 1.0 / (48f32).sqrt();
        assert!(extra.iter().all(|v| v.abs() <= bound), "{head}");
        assert!(
            extra.iter().fold(0.0f32, |a, v| a.max(v.abs())) > 0.5 * bound,
            "{head}"
        );
    }
    // Every weight but the extra units' biases and outgoing weights is `paired`'s.
    assert_eq!(
        values(drawn.opacity.hidden.weight.val()),
        values(silent.opacity.hidden.weight.val())
    );
    assert_eq!(
        values(drawn.opacity.output.weight.val())[..24 * 10],
        values(silent.opacity.output.weight.val())[..24 * 10]
    );
    // Moved features: the drawn units change the baseline slots' opacity, the silent ones do
    // not (paired's extra units reach no output).
    let features = Tensor::<2>::random([m, 48], Distribution::Normal(0.0, 1.0), &device);
    let attr = Tensor::cat(vec![features, Tensor::<2>::zeros([m, 8], &device)], 1);
    let silent_units = relu(silent.opacity.hidden.forward(attr.clone()));
    let drawn_units = relu(drawn.opacity.hidden.forward(attr));
    let awake = values(drawn_units.clone().slice([0..m, 24..48]));
    assert!(
        awake.iter().filter(|v| **v > 0.0).count() > m * 24 / 4,
        "extra units stay asleep"
    );
    // The opacity head's output from all hidden units, and from the baseline's 24 alone.
    let outputs = |d: &Decoders, units: Tensor<2>| {
        let base_only = units
            .clone()
            .slice_assign([0..m, 24..48], Tensor::zeros([m, 24], &device));
        (
            values(d.opacity.output.forward(units)),
            values(d.opacity.output.forward(base_only)),
        )
    };
    let (silent_out, silent_from_base) = outputs(&silent, silent_units);
    assert_close(&silent_out, &silent_from_base, "silent units feed nothing");
    let (drawn_out, drawn_from_base) = outputs(&drawn, drawn_units);
    let moved = drawn_out
        .iter()
        .zip(&drawn_from_base)
        .fold(0.0f32, |a, (x, y)| a.max((x - y).abs()));
    assert!(moved > 1e-2, "drawn units feed the output ({moved})");
}
