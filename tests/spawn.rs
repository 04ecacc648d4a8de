//! Spawning Neural Gaussians from decoded anchors, and the decoder → spawn → rasterize → loss chain.
#![allow(deprecated)] // Device::ndarray

use acags::model::decoders::{DecodedAnchors, DecoderSizes, Decoders, TIME_EMBEDDING_DIM};
use acags::model::spawn::{SpawnInputs, rotation_matrices, spawn};
use acags::raster::random_scene::identity_camera;
use acags::raster::rasterize;
use acags::train::losses::photometric_loss;
use burn::tensor::{Device, Distribution, Tensor, TensorData};

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

fn t2(v: Vec<f32>, shape: [usize; 2], d: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v, shape), d)
}

#[test]
fn rotation_matrices_match_glam() {
    let device = Device::ndarray();
    let quats = [
        [0.9f32, 0.1, -0.3, 0.2],
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 2.0],
        [-0.2, 0.7, 0.1, -0.4],
    ];
    let r = values(rotation_matrices(t2(quats.concat(), [4, 4], &device)));
    for (i, [w, x, y, z]) in quats.into_iter().enumerate() {
        let m = glam::Mat3::from_quat(glam::Quat::from_xyzw(x, y, z, w).normalize());
        for row in 0..3 {
            for col in 0..3 {
                let got = r[i * 9 + row * 3 + col];
                assert!(
                    (got - m.col(col)[row]).abs() < 1e-6,
                    "quat {i} entry ({row},{col}): {got} vs {}",
                    m.col(col)[row]
                );
            }
        }
    }
}

/// One anchor at (1, 2, 3), offset scale 2, two slots; the motion head is set by hand.
fn one_anchor(
    motion: [f32; 7],
    motion_gate: f32,
    opacity: [f32; 2],
) -> acags::raster::GaussianTensors {
    let d = Device::ndarray();
    let inputs = SpawnInputs {
        anchors: t2(vec![1.0, 2.0, 3.0], [1, 3], &d),
        offsets: Tensor::<3>::from_data(
            TensorData::new(vec![0.5, 0.0, 0.0, 0.0, 0.0, 1.0], [1, 2, 3]),
            &d,
        ),
        scales: t2(vec![2.0, 2.0, 2.0, 0.4, 0.6, 0.8], [1, 6], &d),
        motion_gate: Tensor::<1>::from_data(TensorData::new(vec![motion_gate], [1]), &d),
    };
    let decoded = DecodedAnchors {
        opacity: t2(opacity.to_vec(), [1, 2], &d),
        // Slot 0: scale logits 0 (sigmoid 0.5), quat (2, 0, 0, 0); slot 1: logits ln 3 (0.75), quat (0, 0, 0, 5).
        cov: t2(
            vec![
                0.0,
                0.0,
                0.0,
                2.0,
                0.0,
                0.0,
                0.0,
                3f32.ln(),
                3f32.ln(),
                3f32.ln(),
                0.0,
                0.0,
                0.0,
                5.0,
            ],
            [1, 14],
            &d,
        ),
        color: t2(vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [1, 6], &d),
        motion: t2(motion.to_vec(), [1, 7], &d),
    };
    spawn(&inputs, &decoded)
}

#[test]
fn static_anchor_places_slots_at_scaled_offsets() {
    let g = one_anchor([0.0; 7], 1.0, [0.5, -0.1]);
    assert_eq!(values(g.means), vec![2.0, 2.0, 3.0, 1.0, 2.0, 5.0]);
    let scales = values(g.scales);
    let want = [0.2, 0.3, 0.4, 0.3, 0.45, 0.6];
    assert!(
        scales.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{scales:?}"
    );
    assert_eq!(
        values(g.quats),
        vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    );
    assert_eq!(values(g.gates), vec![1.0, 0.0], "opacity <= 0 is gated off");
    assert_eq!(values(g.colors), vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
}

#[test]
fn motion_translates_and_rotates_offsets_about_the_anchor() {
    // Δq = (0, 0, 0, 10): normalize(0.1·Δq + (1, 0, 0, 0)) = 90° about z; x offsets turn to y.
    let g = one_anchor([0.2, 0.0, -0.4, 0.0, 0.0, 0.0, 10.0], 1.0, [0.5, 0.5]);
    let means = values(g.means);
    let want = [1.2, 3.0, 2.6, 1.2, 2.0, 4.6];
    assert!(
        means.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5),
        "{means:?}"
    );
    // The motion gate scales the whole motion; at 0 (canonical phase) nothing moves.
    let still = values(one_anchor([0.2, 0.0, -0.4, 0.0, 0.0, 0.0, 10.0], 0.0, [0.5, 0.5]).means);
    assert_eq!(still, vec![2.0, 2.0, 3.0, 1.0, 2.0, 5.0]);
}

/// Decoders → spawn → rasterize → photometric loss: gradients reach every decoder and the offsets.
#[test]
fn gradients_flow_from_the_image_to_decoders_and_offsets() {
    let device = Device::ndarray().autodiff();
    let sizes = DecoderSizes {
        feature_dim: 16,
        time_feature_dim: 4,
        slots: 5,
    };
    let decoders = Decoders::new(sizes, &device);
    let m = 40;
    // Anchors spread in front of a 64x48 camera.
    let anchors: Vec<f32> = (0..m)
        .flat_map(|i| {
            [
                ((i % 8) as f32 - 3.5) * 0.35,
                ((i / 8) as f32 - 2.0) * 0.35,
                3.0,
            ]
        })
        .collect();
    let offsets =
        Tensor::<3>::random([m, 5, 3], Distribution::Normal(0.0, 0.5), &device).require_grad();
    let inputs = SpawnInputs {
        anchors: t2(anchors, [m, 3], &device),
        offsets: offsets.clone(),
        scales: Tensor::<2>::full([m, 6], 0.15, &device),
        motion_gate: Tensor::<1>::ones([m], &device),
    };
    let features =
        Tensor::<2>::random([m, 20], Distribution::Normal(0.0, 1.0), &device).require_grad();
    let motion_in = Tensor::cat(
        vec![
            features.clone(),
            Tensor::<2>::zeros([m, TIME_EMBEDDING_DIM], &device),
        ],
        1,
    );
    let decoded = decoders.forward(features.clone(), motion_in);
    let gaussians = spawn(&inputs, &decoded);
    let camera = identity_camera(64, 48);
    let out = rasterize(&gaussians, &camera, [0.0; 3]).unwrap();
    let target = Tensor::<3>::full([48, 64, 3], 0.5, &device);
    let loss = photometric_loss(out.image, target, 0.2, None).loss;
    let grads = loss.backward();
    let nonzero = |t: Option<Tensor<2>>| {
        values(t.expect("gradient"))
            .iter()
            .any(|v| *v != 0.0 && v.is_finite())
    };
    assert!(
        nonzero(decoders.opacity.output.weight.val().grad(&grads)),
        "opacity head"
    );
    assert!(
        nonzero(decoders.cov.output.weight.val().grad(&grads)),
        "cov head"
    );
    assert!(
        nonzero(decoders.color.output.weight.val().grad(&grads)),
        "colour head"
    );
    assert!(
        nonzero(decoders.motion.output.weight.val().grad(&grads)),
        "motion head"
    );
    assert!(nonzero(features.grad(&grads)), "anchor features");
    let g_offsets = values(offsets.grad(&grads).expect("offset gradient"));
    assert!(g_offsets.iter().all(|v| v.is_finite()) && g_offsets.iter().any(|v| *v != 0.0));
}
