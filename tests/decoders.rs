//! GIFStream's decoders: sizes, activations, initialisation and the time embedding.
#![allow(deprecated)] // Device::ndarray

use acags::model::decoders::{DecoderSizes, Decoders, TIME_EMBEDDING_DIM, time_embedding};
use burn::module::Module;
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
