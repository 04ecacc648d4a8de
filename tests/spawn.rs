//! Spawning Neural Gaussians from decoded anchors, and the decoder → spawn → rasterize → loss chain.
#![allow(deprecated)] // Device::ndarray

use acags::model::decoders::{DecodedAnchors, DecoderSizes, Decoders, TIME_EMBEDDING_DIM};
use acags::model::spawn::{
    SpawnInputs, quaternion_products, rotation_matrices, rotation_vector_quaternions, spawn,
};
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
    turned_anchor(motion, motion_gate, opacity, None)
}

/// [`one_anchor`] with a trajectory turn (rotation vector before the motion gate).
fn turned_anchor(
    motion: [f32; 7],
    motion_gate: f32,
    opacity: [f32; 2],
    turn: Option<[f32; 3]>,
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
        turn: turn.map(|r| t2(r.to_vec(), [1, 3], &d)),
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

#[test]
fn rotation_vectors_and_quaternion_products_match_glam() {
    let device = Device::ndarray();
    let vectors = [
        [0.0f32, 0.0, 0.0],
        [0.3, -1.2, 0.5],
        [0.0, 0.0, 3.1],
        [1e-4, 0.0, -2e-4],
    ];
    let q = values(rotation_vector_quaternions(t2(
        vectors.concat(),
        [4, 3],
        &device,
    )));
    let glam_q = |r: [f32; 3]| glam::Quat::from_scaled_axis(glam::Vec3::from(r));
    for (i, r) in vectors.into_iter().enumerate() {
        let want = glam_q(r);
        let got = &q[i * 4..i * 4 + 4];
        let want = [want.w, want.x, want.y, want.z];
        assert!(
            got.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
            "vector {r:?}: {got:?} vs {want:?}"
        );
    }
    let a = [[0.9f32, 0.1, -0.3, 0.2], [0.2, 0.7, 0.1, -0.4]];
    let b = [[0.5f32, -0.5, 0.5, 0.5], [1.0, 0.0, 0.0, 0.0]];
    let got = values(quaternion_products(
        t2(a.concat(), [2, 4], &device),
        t2(b.concat(), [2, 4], &device),
    ));
    for i in 0..2 {
        let quat = |[w, x, y, z]: [f32; 4]| glam::Quat::from_xyzw(x, y, z, w);
        let want = quat(a[i]) * quat(b[i]);
        let want = [want.w, want.x, want.y, want.z];
        assert!(
            got[i * 4..i * 4 + 4]
                .iter()
                .zip(want)
                .all(|(a, b)| (a - b).abs() < 1e-6),
            "product {i}: {:?} vs {want:?}",
            &got[i * 4..i * 4 + 4]
        );
    }
}

#[test]
fn a_trajectory_turn_turns_offsets_and_orientations_under_the_motion_gate() {
    // Turn 90° about z (before the gate) and a motion-head rotation of 90° about x: the offsets
    // take the head's turn first, then the trajectory's; the Gaussians only the trajectory's.
    let quarter = std::f32::consts::FRAC_PI_2;
    let head = [0.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0]; // normalize((1, 1, 0, 0)): 90° about x
    let g = turned_anchor(head, 1.0, [0.5, 0.5], Some([0.0, 0.0, quarter]));
    let turn = glam::Quat::from_rotation_z(quarter);
    let head_turn = glam::Quat::from_rotation_x(quarter);
    let anchor = glam::Vec3::new(1.0, 2.0, 3.0);
    let means = values(g.means);
    for (slot, offset) in [
        glam::Vec3::new(1.0, 0.0, 0.0),
        glam::Vec3::new(0.0, 0.0, 2.0),
    ]
    .into_iter()
    .enumerate()
    {
        let want = anchor + turn * (head_turn * offset);
        let got = &means[slot * 3..slot * 3 + 3];
        assert!(
            got.iter()
                .zip(want.to_array())
                .all(|(a, b)| (a - b).abs() < 1e-5),
            "slot {slot}: {got:?} vs {want}"
        );
    }
    // Slot 0's orientation is the identity, slot 1's 180° about z: both turned by the turn.
    let quats = values(g.quats);
    for (slot, base) in [
        glam::Quat::IDENTITY,
        glam::Quat::from_xyzw(0.0, 0.0, 1.0, 0.0),
    ]
    .into_iter()
    .enumerate()
    {
        let want = turn * base;
        let got = glam::Quat::from_xyzw(
            quats[slot * 4 + 1],
            quats[slot * 4 + 2],
            quats[slot * 4 + 3],
            quats[slot * 4],
        );
        assert!(
            got.dot(want).abs() > 1.0 - 1e-6,
            "slot {slot}: {got} vs {want}"
        );
    }
    // A turn about x does not commute with slot 1's 180° about z: the turn acts after it
    // (turn ⊗ base, not base ⊗ turn).
    let about_x = glam::Quat::from_rotation_x(quarter);
    let quats = values(turned_anchor([0.0; 7], 1.0, [0.5, 0.5], Some([quarter, 0.0, 0.0])).quats);
    let got = glam::Quat::from_xyzw(quats[5], quats[6], quats[7], quats[4]);
    let base = glam::Quat::from_xyzw(0.0, 0.0, 1.0, 0.0);
    assert!(got.dot(about_x * base).abs() > 1.0 - 1e-6, "{got}");
    assert!(
        got.dot(base * about_x).abs() < 0.5,
        "{got}: the order is pinned"
    );
    // The motion gate scales the angle: at ½ the turn is 45°; at 0 nothing turns.
    let half = values(turned_anchor([0.0; 7], 0.5, [0.5, 0.5], Some([0.0, 0.0, quarter])).means);
    let want = anchor + glam::Quat::from_rotation_z(quarter / 2.0) * glam::Vec3::X;
    assert!(
        half[..3]
            .iter()
            .zip(want.to_array())
            .all(|(a, b)| (a - b).abs() < 1e-5),
        "{half:?}"
    );
    let still = turned_anchor([0.0; 7], 0.0, [0.5, 0.5], Some([0.0, 0.0, quarter]));
    assert_eq!(values(still.means), vec![2.0, 2.0, 3.0, 1.0, 2.0, 5.0]);
    assert_eq!(
        values(still.quats),
        vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    );
}

/// Two anchors with different turns, three slots each: every Gaussian row i·K + k takes its own
/// anchor's turn (offsets and orientation).
#[test]
fn each_anchor_turns_its_own_slots() {
    let d = Device::ndarray();
    let turns = [[0.0f32, 0.0, 1.0], [0.7, -0.4, 0.0]];
    let anchors = [[1.0f32, 2.0, 3.0], [-1.0, 0.5, 2.0]];
    let offsets: Vec<f32> = (0..18).map(|i| ((i * 7) % 5) as f32 * 0.2 - 0.4).collect();
    let inputs = SpawnInputs {
        anchors: t2(anchors.concat(), [2, 3], &d),
        offsets: Tensor::<3>::from_data(TensorData::new(offsets.clone(), [2, 3, 3]), &d),
        scales: t2(vec![1.0; 12], [2, 6], &d),
        motion_gate: Tensor::<1>::ones([2], &d),
        turn: Some(t2(turns.concat(), [2, 3], &d)),
    };
    let cov: Vec<f32> = (0..6)
        .flat_map(|g| [0.0, 0.0, 0.0, 1.0, 0.1 * g as f32, -0.2, 0.3])
        .collect();
    let decoded = DecodedAnchors {
        opacity: t2(vec![0.5; 6], [2, 3], &d),
        cov: t2(cov.clone(), [2, 21], &d),
        color: t2(vec![0.1; 18], [2, 9], &d),
        motion: t2(vec![0.0; 14], [2, 7], &d),
    };
    let g = spawn(&inputs, &decoded);
    let (means, quats) = (values(g.means), values(g.quats));
    for a in 0..2 {
        let turn = glam::Quat::from_scaled_axis(glam::Vec3::from(turns[a]));
        for k in 0..3 {
            let row = a * 3 + k;
            let offset = glam::Vec3::from_slice(&offsets[row * 3..row * 3 + 3]);
            let want = glam::Vec3::from(anchors[a]) + turn * offset;
            let got = &means[row * 3..row * 3 + 3];
            assert!(
                got.iter()
                    .zip(want.to_array())
                    .all(|(x, y)| (x - y).abs() < 1e-5),
                "anchor {a} slot {k}: {got:?} vs {want}"
            );
            let c = &cov[row * 7 + 3..row * 7 + 7];
            let want = turn * glam::Quat::from_xyzw(c[1], c[2], c[3], c[0]).normalize();
            let q = &quats[row * 4..row * 4 + 4];
            let got = glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]);
            assert!(
                got.dot(want).abs() > 1.0 - 1e-6,
                "anchor {a} slot {k}: {got} vs {want}"
            );
        }
    }
}

/// The turn's gradient against central finite differences of a scalar of the spawned Gaussians
/// (means and orientations both depend on it), at a generic turn and at the identity.
#[test]
fn the_turn_gradient_matches_finite_differences() {
    let device = Device::ndarray().autodiff();
    let plain = Device::ndarray();
    let objective = |turn: Tensor<2>, d: &Device| -> Tensor<1> {
        let inputs = SpawnInputs {
            anchors: t2(vec![1.0, 2.0, 3.0], [1, 3], d),
            offsets: Tensor::<3>::from_data(
                TensorData::new(vec![0.5, -0.2, 0.3, 0.1, 0.4, 1.0], [1, 2, 3]),
                d,
            ),
            scales: t2(vec![2.0, 1.5, 1.0, 0.4, 0.6, 0.8], [1, 6], d),
            motion_gate: Tensor::<1>::from_data(TensorData::new(vec![0.8f32], [1]), d),
            turn: Some(turn),
        };
        let decoded = DecodedAnchors {
            opacity: t2(vec![0.5, 0.5], [1, 2], d),
            cov: t2(
                vec![
                    0.0, 0.0, 0.0, 0.9, 0.1, -0.3, 0.2, 0.0, 0.0, 0.0, 0.2, 0.7, 0.1, -0.4,
                ],
                [1, 14],
                d,
            ),
            color: t2(vec![0.1; 6], [1, 6], d),
            motion: t2(vec![0.1, 0.0, 0.0, 0.0, 0.3, -0.2, 0.1], [1, 7], d),
        };
        let g = spawn(&inputs, &decoded);
        let weights_means = t2(vec![0.3, -0.7, 0.5, 1.1, 0.2, -0.4], [2, 3], d);
        let weights_quats = t2(vec![0.2, -0.5, 0.9, 0.3, -0.6, 0.4, 0.1, 0.8], [2, 4], d);
        (g.means * weights_means).sum() + (g.quats * weights_quats).sum()
    };
    for at in [[0.4f32, -0.9, 1.3], [0.0, 0.0, 0.0]] {
        let turn = t2(at.to_vec(), [1, 3], &device).require_grad();
        let grads = objective(turn.clone(), &device).backward();
        let analytic = values(turn.grad(&grads).expect("turn gradient"));
        let h = 1e-3f32;
        for c in 0..3 {
            let shifted = |delta: f32| {
                let mut r = at;
                r[c] += delta;
                values(objective(t2(r.to_vec(), [1, 3], &plain), &plain))[0]
            };
            let numeric = (shifted(h) - shifted(-h)) / (2.0 * h);
            assert!(
                (analytic[c] - numeric).abs() < 2e-3 * (1.0 + numeric.abs()),
                "turn {at:?}, component {c}: analytic {} vs numeric {numeric}",
                analytic[c]
            );
        }
    }
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
        turn: None,
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
