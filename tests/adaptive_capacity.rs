//! ACA-GS capacity adaptation: AAC relocation (dead slots, ρ cap, young anchors, sampling ∝
//! importance, the offset perturbation, optimizer and statistics reset), slot gating in the
//! decode (gated slots draw nothing and get no gradient), AAFM masking in the decode, row
//! bookkeeping through grow → relocate → prune, and the post-hoc step.
#![allow(deprecated)] // Device::ndarray

mod common;
use acags::model::view::ALL_TIME_BANDS;
use common::AlwaysHigh;

use acags::model::anchors::{
    AnchorDims, AnchorSet, Column, FeatureMasking, NewAnchors, TrajectoryTurn, host_values,
};
use acags::model::culling::visible_anchors;
use acags::model::decoders::{DecoderSizes, Decoders};
use acags::model::view::{Phase, ViewTime, decode_view};
use acags::raster::random_scene::identity_camera;
use acags::raster::rasterize;
use acags::train::adaptive_cardinality::{accumulate_importance, relocate};
use acags::train::anchor_state::{AnchorState, RowEdit};
use acags::train::config::{
    AacConfig, CardinalityMode, DensifyConfig, ImportanceTest, RelocationSlot,
};
use acags::train::densify::{grow_and_prune, update_stats};
use acags::train::posthoc::prune_capacity;
use acags::train::row_adam::AdamConfig;
use acags::train::statistics::DensifyView;
use burn::tensor::{Device, Int, Tensor, TensorData};
use rand::{Rng, SeedableRng, rngs::StdRng};

fn dims(slots: usize, active: usize, masking: FeatureMasking) -> AnchorDims {
    AnchorDims {
        slots,
        initial_active_slots: active,
        feature_masking: masking,
        frames: 2,
        feature_dim: 8,
        time_feature_dim: 2,
        knn: 0,
        trajectory_spacing: 0,
        trajectory_turn: TrajectoryTurn::Off,
    }
}

/// Anchors on a grid 3 units in front of the identity camera, seeded random features and
/// offsets, all created at step 0.
fn grid_set(d: AnchorDims, n: usize, seed: u64) -> (AnchorSet, AnchorState) {
    let mut rng = StdRng::seed_from_u64(seed);
    let positions: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            [
                ((i % 6) as f32 - 2.5) * 0.3,
                ((i / 6) as f32 - 1.5) * 0.3,
                3.0,
            ]
        })
        .collect();
    let mut normal = |count: usize, scale: f32| -> Vec<f32> {
        (0..count)
            .map(|_| (rng.random::<f32>() - 0.5) * 2.0 * scale)
            .collect()
    };
    let rows = NewAnchors::new(positions)
        .with(Column::LogScales, vec![0.15f32.ln(); n * 6])
        .with(Column::Features, normal(n * d.feature_dim, 1.0))
        .with(
            Column::TimeFeatures,
            normal(n * d.frames * d.time_feature_dim, 1.0),
        )
        .with(Column::MaskLogits, vec![1.0; n]);
    let mut set = AnchorSet::from_rows(d, rows, &Device::ndarray());
    set.set_host(Column::Offsets, normal(n * d.slots * 3, 0.8));
    let state = AnchorState::new(&set, 0, AdamConfig::default());
    (set, state)
}

fn aac(relocate_fraction: f32) -> AacConfig {
    AacConfig {
        mode: CardinalityMode::Adaptive,
        relocate_fraction,
        ..Default::default()
    }
}

#[test]
fn dead_slots_are_deactivated_and_relocation_is_capped_at_rho() {
    let d = dims(4, 2, FeatureMasking::Off);
    let (mut set, mut state) = grid_set(d, 10, 1);
    // Active: slots 0-1 of 10 anchors, P = 20. Dead (< 0.005): slot 1 of anchors 0..6 (7 slots).
    for a in 0..10 {
        state.importance[a * 4] = 1.0 + a as f32;
        state.importance[a * 4 + 1] = if a < 7 { 0.0004 * a as f32 } else { 0.5 };
    }
    // Inactive slots never count as dead, whatever their importance.
    state.importance[2] = 0.0;
    let report = relocate(
        &mut set,
        &mut state,
        &aac(0.2),
        3000,
        &mut StdRng::seed_from_u64(3),
    );
    assert_eq!(report.active_before, 20);
    assert_eq!(report.deactivated, 7);
    assert_eq!(report.relocated, 4, "⌊0.2 · 20⌋ = 4 < 7 dead");
    assert_eq!(report.dropped, 0);
    assert_eq!(set.active_slot_count(), 20 - 7 + 4);
    for a in 0..7 {
        // Slot 1 was dead; whatever was re-activated in this anchor came from relocation.
        assert!(set.slot_gates[a * 4], "alive slot 0 stays active");
    }
    assert!(
        state.importance.iter().all(|&i| i == 0.0),
        "the window restarts"
    );

    // With ρ = 1 every dead slot is relocated.
    let (mut set, mut state) = grid_set(d, 10, 1);
    for a in 0..10 {
        state.importance[a * 4] = 1.0;
        state.importance[a * 4 + 1] = if a < 3 { 0.0 } else { 1.0 };
    }
    let report = relocate(
        &mut set,
        &mut state,
        &aac(1.0),
        3000,
        &mut StdRng::seed_from_u64(3),
    );
    assert_eq!((report.deactivated, report.relocated), (3, 3));
    assert_eq!(
        set.active_slot_count(),
        20,
        "relocation preserves the population"
    );
}

/// Four anchors of five slots, all important; anchor 0 has live slots 0 and 1, slot 2 killed
/// this step (importance 0) and free slots 3 and 4 that would show `shown` when switched on; the
/// other anchors are full, so anchor 0 is the only parent.
fn one_parent_set(shown: [f32; 2]) -> (AnchorSet, AnchorState) {
    let (mut set, mut state) = grid_set(dims(5, 3, FeatureMasking::Off), 4, 7);
    for a in 0..4 {
        for slot in 0..5 {
            state.importance[a * 5 + slot] = 1.0;
        }
        set.slot_gates.edit(|g| g[a * 5 + 3] = a != 0);
        set.slot_gates.edit(|g| g[a * 5 + 4] = a != 0);
    }
    state.importance[2] = 0.0;
    state.importance[3] = shown[0];
    state.importance[4] = shown[1];
    (set, state)
}

#[test]
fn relocation_lands_in_the_lowest_or_most_opaque_free_slot_and_churn_is_reported() {
    // One anchor with important slots 0 and 1 and a dead slot 2 (killed this step), free slots
    // 3 (would show 0.2 when switched on) and 4 (0.9); the other anchors are full of live slots.
    let one = |target_slot| AacConfig {
        target_slot,
        ..aac(0.1)
    };
    let mut lowest = one_parent_set([0.2, 0.9]);
    let report = relocate(
        &mut lowest.0,
        &mut lowest.1,
        &one(RelocationSlot::LowestFree),
        3000,
        &mut StdRng::seed_from_u64(1),
    );
    assert_eq!((report.deactivated, report.relocated), (1, 1));
    assert_eq!(
        &lowest.0.slot_gates[0..5],
        &[true, true, true, false, false],
        "the spec's rule reuses the slot it just killed"
    );
    assert_eq!(
        &lowest.1.relocated[0..5],
        &[false, false, true, false, false]
    );
    let mut opaque = one_parent_set([0.2, 0.9]);
    let report = relocate(
        &mut opaque.0,
        &mut opaque.1,
        &one(RelocationSlot::MostOpaqueFree),
        3000,
        &mut StdRng::seed_from_u64(1),
    );
    assert_eq!((report.deactivated, report.relocated), (1, 1));
    assert_eq!(
        &opaque.0.slot_gates[0..5],
        &[true, true, false, false, true]
    );
    assert_eq!(report.previous_relocated, 0, "nothing relocated before");

    // The next step judges the relocated slot by its new window: below τ counts as churn.
    for ((set, state), seen, churned) in [(&mut lowest, 0.0, 1), (&mut opaque, 0.5, 0)] {
        state.importance.fill(1.0);
        let slot = state.relocated.iter().position(|&r| r).unwrap();
        state.importance[slot] = seen;
        let report = relocate(set, state, &aac(0.0), 3500, &mut StdRng::seed_from_u64(2));
        assert_eq!(report.previous_relocated, 1);
        assert_eq!(report.previous_below_threshold, churned);
        assert!(
            state.relocated.iter().all(|&r| !r),
            "nothing relocated at ρ = 0"
        );
    }
}

#[test]
fn above_threshold_relocation_takes_only_slots_that_would_pass_the_test() {
    // Anchor 0: live slots 0 and 1, slot 2 killed this step, free slots 3 and 4 that would show
    // `shown` when switched on; every other anchor is full, so anchor 0 is the only parent.
    let run = |target_slot, shown: [f32; 2]| {
        let (mut set, mut state) = one_parent_set(shown);
        let config = AacConfig {
            target_slot,
            ..aac(0.1)
        };
        let report = relocate(
            &mut set,
            &mut state,
            &config,
            3000,
            &mut StdRng::seed_from_u64(1),
        );
        (report, set.slot_gates[0..5].to_vec())
    };
    let tau = aac(0.1).dead_threshold;
    let below = [0.2 * tau, 0.6 * tau];
    // Most-opaque-free still switches on the better of two slots that decode (almost) nothing.
    let (report, gates) = run(RelocationSlot::MostOpaqueFree, below);
    assert_eq!((report.relocated, report.dropped), (1, 0));
    assert_eq!(gates, [true, true, false, false, true]);
    // Above-threshold-free leaves the budget unspent rather than place a Gaussian that cannot
    // be seen (nor the slot it just killed).
    let (report, gates) = run(RelocationSlot::AboveThresholdFree, below);
    assert_eq!(
        (report.deactivated, report.relocated, report.dropped),
        (1, 0, 1)
    );
    assert_eq!(gates, [true, true, false, false, false]);
    // A free slot that reached τ is taken, the more opaque of two that did.
    let (report, gates) = run(RelocationSlot::AboveThresholdFree, [0.2 * tau, 2.0 * tau]);
    assert_eq!((report.relocated, report.dropped), (1, 0));
    assert_eq!(gates, [true, true, false, false, true]);
    let (_, gates) = run(RelocationSlot::AboveThresholdFree, [3.0 * tau, 2.0 * tau]);
    assert_eq!(gates, [true, true, false, true, false]);
}

#[test]
fn young_anchors_are_not_tested_and_the_mean_test_divides_by_visits() {
    let d = dims(3, 2, FeatureMasking::Off);
    let (mut set, mut state) = grid_set(d, 4, 2);
    state.created_at = vec![0, 0, 2800, 2501];
    // Every slot has importance 0: anchors 2 and 3 are younger than T_R = 500 at step 3000.
    let report = relocate(
        &mut set,
        &mut state,
        &aac(0.0),
        3000,
        &mut StdRng::seed_from_u64(1),
    );
    assert_eq!(report.deactivated, 4, "only anchors 0 and 1 are judged");
    assert_eq!(set.cardinality(2), 2);
    assert_eq!(set.cardinality(3), 2);
    assert_eq!((set.cardinality(0), set.cardinality(1)), (0, 0));

    // Mean per visit: the same sum 0.04 is 0.004 < τ over 10 visits and 0.01 ≥ τ over 4.
    let (mut set, mut state) = grid_set(d, 2, 2);
    let opacity = vec![0.004, 0.004, 0.0, 0.01, 0.01, 0.0];
    for _ in 0..10 {
        accumulate_importance(&mut state, &d, &[0], &opacity[0..3]);
    }
    for _ in 0..4 {
        accumulate_importance(&mut state, &d, &[1], &opacity[3..6]);
    }
    assert!((state.importance[0] - 0.04).abs() < 1e-6);
    assert_eq!(state.importance_visits, vec![10.0, 4.0]);
    let config = AacConfig {
        importance: ImportanceTest::MeanPerVisit,
        ..aac(0.0)
    };
    let report = relocate(
        &mut set,
        &mut state,
        &config,
        3000,
        &mut StdRng::seed_from_u64(1),
    );
    assert_eq!(report.deactivated, 2, "anchor 0's two slots");
    assert_eq!((set.cardinality(0), set.cardinality(1)), (0, 2));
}

/// The statistics a training step gathers on the device (`train/statistics.rs`) equal, to the
/// bit, what the host functions they replaced add up (the trainer's former loop, written out
/// here): six views with random visibility, opacities of both signs, unspawned and off-screen
/// slots, frames in any order, starting from non-zero values, and a row edit half-way (which
/// reads the device's values back before the rows change).
#[test]
fn statistics_gathered_on_the_device_equal_the_host_accumulation_bit_for_bit() {
    let d = AnchorDims {
        frames: 3,
        ..dims(5, 5, FeatureMasking::Off)
    };
    let (k, t) = (d.slots, d.frames);
    let (set, mut on_device) = grid_set(d, 12, 3);
    let mut rng = StdRng::seed_from_u64(9);
    let mut uniform = |count: usize, lo: f32, hi: f32| -> Vec<f32> {
        (0..count)
            .map(|_| lo + (hi - lo) * rng.random::<f32>())
            .collect()
    };
    on_device.stats.offset_grad2d = uniform(12 * k * t, 0.0, 1e-3);
    on_device.stats.offset_visible_count = uniform(12 * k * t, 0.0, 9.0);
    on_device.stats.opacity_accum = uniform(12 * t, 0.0, 3.0);
    on_device.stats.anchor_visible_count = uniform(12 * t, 0.0, 9.0);
    on_device.importance = uniform(12 * k, 0.0, 2.0);
    on_device.importance_visits = uniform(12, 0.0, 9.0);
    let mut on_host = on_device.clone();
    let (mut set_d, mut set_h) = (set.clone(), set);
    let device = Device::ndarray();
    let mut rng = StdRng::seed_from_u64(11);
    let (w, h) = (40.0f32, 30.0f32);
    for view in 0..6 {
        let n = set_d.len();
        let visible: Vec<u32> = (0..n as u32)
            .filter(|_| rng.random::<f32>() < 0.7)
            .collect();
        let m = visible.len();
        let mut draw = |count: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..count)
                .map(|_| lo + (hi - lo) * rng.random::<f32>())
                .collect()
        };
        let slot_opacity = draw(m * k, -0.5, 1.0);
        // Slot gates off for some: their opacity is 0 after the gates.
        let opacity: Vec<f32> = (slot_opacity.iter().enumerate())
            .map(|(i, &o)| if i % 7 == 3 { 0.0 } else { o })
            .collect();
        let gates: Vec<f32> = opacity
            .iter()
            .map(|&o| if o > 0.0 { 1.0 } else { 0.0 })
            .collect();
        let radii: Vec<i64> = draw(m * k * 2, -2.0, 4.0)
            .iter()
            .map(|&r| r.max(0.0) as i64)
            .collect();
        let grad2d = draw(m * k * 2, -1e-3, 1e-3);
        let frame = [2, 0, 1, 1, 2, 0][view];

        // The host reference: the trainer's loop before the statistics moved to the device.
        accumulate_importance(&mut on_host, &d, &visible, &slot_opacity);
        let norms: Vec<f32> = (0..m * k)
            .map(|i| ((grad2d[2 * i] * w).powi(2) + (grad2d[2 * i + 1] * h).powi(2)).sqrt())
            .collect();
        let counted: Vec<bool> = (0..m * k)
            .map(|i| gates[i] > 0.0 && (radii[2 * i] > 0 || radii[2 * i + 1] > 0))
            .collect();
        update_stats(
            &mut on_host,
            &d,
            &visible,
            &opacity,
            &norms,
            &counted,
            frame,
        );

        // Odd views as a device-culled step gathers them: every anchor a row, the culled rows
        // with weight 0 and opacity 0 (`VisibleRows::Masked`); even views as the listed rows.
        let masked = view % 2 == 1;
        let (rows, seen, slot_opacity, opacity, gates, radii, grad2d) = if masked {
            let mut seen = vec![0.0f32; n];
            let (mut so, mut op, mut ga) = (vec![0.0; n * k], vec![0.0; n * k], vec![0.0; n * k]);
            let (mut ra, mut gr) = (vec![0i64; n * k * 2], vec![0.0f32; n * k * 2]);
            for (i, &a) in visible.iter().enumerate() {
                let a = a as usize;
                seen[a] = 1.0;
                for j in 0..k {
                    so[a * k + j] = slot_opacity[i * k + j];
                    op[a * k + j] = opacity[i * k + j];
                    ga[a * k + j] = gates[i * k + j];
                    for c in 0..2 {
                        ra[(a * k + j) * 2 + c] = radii[(i * k + j) * 2 + c];
                        gr[(a * k + j) * 2 + c] = grad2d[(i * k + j) * 2 + c];
                    }
                }
            }
            ((0..n as u32).collect::<Vec<_>>(), seen, so, op, ga, ra, gr)
        } else {
            (
                visible.clone(),
                vec![1.0; m],
                slot_opacity,
                opacity,
                gates,
                radii,
                grad2d,
            )
        };
        let r = rows.len();
        let index = Tensor::<1, Int>::from_data(
            TensorData::new(rows.iter().map(|&a| a as i64).collect::<Vec<_>>(), [r]),
            &device,
        );
        let seen = Tensor::<1>::from_data(TensorData::new(seen, [r]), &device);
        on_device.gather_importance(
            &d,
            index.clone(),
            seen.clone(),
            Tensor::<2>::from_data(TensorData::new(slot_opacity, [r, k]), &device),
        );
        on_device.gather_densify(
            &d,
            DensifyView {
                visible: index,
                seen,
                frame,
                opacity: Tensor::<2>::from_data(TensorData::new(opacity, [r, k]), &device),
                gates: Tensor::<1>::from_data(TensorData::new(gates, [r * k]), &device),
                radii: Tensor::<2, Int>::from_data(TensorData::new(radii, [r * k, 2]), &device),
                grad2d: Some(Tensor::<2>::from_data(
                    TensorData::new(grad2d, [r * k, 2]),
                    &device,
                )),
                half_size: [w, h],
            },
        );
        assert!(!on_device.is_settled());
        if view == 2 {
            // Two rows appended: the device's values come back first, the new rows start at 0.
            for (state, set) in [(&mut on_device, &mut set_d), (&mut on_host, &mut set_h)] {
                state.edit(
                    set,
                    RowEdit::Append {
                        rows: NewAnchors::new(vec![[0.1, 0.1, 3.0], [0.2, -0.1, 3.0]]),
                        created_at: 5,
                        reference_frames: vec![0, 0],
                    },
                );
            }
            assert!(on_device.is_settled());
            assert_eq!(on_device.stats, on_host.stats, "after the edit");
        }
    }
    on_device.settle();
    assert_eq!(on_device.stats, on_host.stats);
    assert_eq!(on_device.importance, on_host.importance);
    assert_eq!(on_device.importance_visits, on_host.importance_visits);
    assert_eq!(on_device.stats.opacity_accum.len(), 14 * t);
    // The importance window restarts from zero even with values pending on the device.
    on_device.gather_importance(
        &d,
        Tensor::<1, Int>::from_data(TensorData::new(vec![0i64], [1]), &device),
        Tensor::<1>::ones([1], &device),
        Tensor::<2>::ones([1, k], &device),
    );
    on_device.reset_importance();
    assert!(on_device.is_settled());
    assert_eq!(on_device.importance, vec![0.0; 14 * k]);
    assert_eq!(on_device.importance_visits, vec![0.0; 14]);
}

/// Parents are drawn ∝ importance: one relocation per trial among three alive slots with
/// importance 1 : 2 : 7, χ² against the expected counts (2 degrees of freedom, p = 0.001).
#[test]
fn parents_are_sampled_in_proportion_to_importance() {
    let d = dims(4, 2, FeatureMasking::Off);
    let weights = [1.0f32, 2.0, 7.0];
    let trials = 3000;
    let mut counts = [0usize; 3];
    let mut rng = StdRng::seed_from_u64(42);
    for _ in 0..trials {
        let (mut set, mut state) = grid_set(d, 4, 5);
        // Anchors 0-2: slot 0 alive with the weights, slot 1 idle (inactive). Anchor 3: one dead
        // slot, the relocation budget.
        for a in 0..3 {
            set.slot_gates.edit(|g| g[a * 4 + 1] = false);
            state.importance[a * 4] = weights[a];
        }
        state.importance[3 * 4] = 0.0;
        set.slot_gates.edit(|g| g[3 * 4 + 1] = false);
        let report = relocate(&mut set, &mut state, &aac(1.0), 3000, &mut rng);
        assert_eq!(report.relocated, 1);
        let receiver = (0..3)
            .find(|&a| set.cardinality(a) == 2)
            .expect("one of the weighted anchors received the slot");
        counts[receiver] += 1;
    }
    let total: f32 = weights.iter().sum();
    let chi2: f64 = (0..3)
        .map(|i| {
            let expected = trials as f64 * (weights[i] / total) as f64;
            (counts[i] as f64 - expected).powi(2) / expected
        })
        .sum();
    assert!(
        chi2 < 13.8,
        "counts {counts:?} for weights {weights:?}: χ² = {chi2}"
    );
}

#[test]
fn relocated_offset_is_the_parents_perturbed_by_its_magnitude_with_fresh_state() {
    let d = dims(3, 1, FeatureMasking::Off);
    let (mut set, mut state) = grid_set(d, 2, 9);
    // Anchor 0: slot 0 alive (the only parent); anchor 1: slot 0 dead → budget 1.
    state.importance[0] = 1.0;
    let parent = [0.5f32, -2.0, 0.0];
    let mut offsets = set.host(Column::Offsets);
    offsets[0..3].copy_from_slice(&parent);
    set.set_host(Column::Offsets, offsets);
    // Distinct non-zero Adam moments and statistics everywhere.
    let ones = Tensor::<2>::ones([2, 3 * 3], &Device::ndarray());
    state.adam[Column::Offsets].exp_avg = ones.clone() * 0.3;
    state.adam[Column::Offsets].exp_avg_sq = ones * 0.7;
    state.stats.offset_grad2d.fill(2.0);
    state.stats.offset_visible_count.fill(3.0);

    // δ = 0: an exact copy of the parent offset, in the lowest free slot of the parent's anchor.
    let (mut exact, mut exact_state) = (set.clone(), state.clone());
    let config = AacConfig {
        perturbation: 0.0,
        ..aac(1.0)
    };
    let report = relocate(
        &mut exact,
        &mut exact_state,
        &config,
        3000,
        &mut StdRng::seed_from_u64(0),
    );
    assert_eq!(report.relocated, 1);
    assert_eq!(
        exact.slot_gates.flags(),
        [true, true, false, false, false, false]
    );
    let o = exact.host(Column::Offsets);
    assert_eq!(&o[3..6], &parent);
    let m = host_values(&exact_state.adam[Column::Offsets].exp_avg);
    let v = host_values(&exact_state.adam[Column::Offsets].exp_avg_sq);
    assert_eq!(&m[3..6], &[0.0; 3], "first moment of the new slot reset");
    assert_eq!(&v[3..6], &[0.0; 3], "second moment of the new slot reset");
    assert!(
        m.iter()
            .enumerate()
            .all(|(i, &x)| (3..6).contains(&i) || x == 0.3)
    );
    let t = d.frames;
    assert_eq!(&exact_state.stats.offset_grad2d[t..2 * t], &[0.0, 0.0]);
    assert_eq!(
        &exact_state.stats.offset_visible_count[t..2 * t],
        &[0.0, 0.0]
    );
    assert_eq!(
        exact_state.stats.offset_visible_count[0], 3.0,
        "other slots keep theirs"
    );

    // δ = 0.05: (o − o_p) / |o_p| ~ N(0, δ²) per component; a zero component stays zero.
    let mut z = Vec::new();
    let mut rng = StdRng::seed_from_u64(11);
    for _ in 0..400 {
        let (mut s, mut s_state) = (set.clone(), state.clone());
        relocate(&mut s, &mut s_state, &aac(1.0), 3000, &mut rng);
        let o = s.host(Column::Offsets);
        for c in 0..2 {
            z.push((o[3 + c] - parent[c]) / parent[c].abs());
        }
        assert_eq!(o[5], 0.0, "|o_p| = 0 → no perturbation (spec §14 A7)");
    }
    let mean = z.iter().sum::<f32>() / z.len() as f32;
    let std = (z.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / z.len() as f32).sqrt();
    assert!(mean.abs() < 0.01, "mean {mean}");
    assert!((std - 0.05).abs() < 0.005, "std {std}");
}

#[test]
fn relocation_drops_what_cannot_be_placed() {
    // Every anchor full (2 of 2 slots active) except through dead slots: anchor 0 has a dead
    // slot (budget 1) but the only alive parents are in full anchors → no parent, dropped.
    let d = dims(2, 2, FeatureMasking::Off);
    let (mut set, mut state) = grid_set(d, 3, 4);
    state.importance = vec![0.0, 1.0, 1.0, 1.0, 1.0, 1.0];
    let report = relocate(
        &mut set,
        &mut state,
        &aac(1.0),
        3000,
        &mut StdRng::seed_from_u64(0),
    );
    assert_eq!(report.deactivated, 1);
    // Anchor 0 now has a free slot and an alive slot (importance 1): it is the one candidate.
    assert_eq!(report.relocated, 1, "{report:?}");
    assert!(set.slot_gates[0]);

    // No alive slot at all: the budget is dropped.
    let (mut set, mut state) = grid_set(d, 3, 4);
    let report = relocate(
        &mut set,
        &mut state,
        &aac(1.0),
        3000,
        &mut StdRng::seed_from_u64(0),
    );
    assert_eq!(report.deactivated, 6);
    assert_eq!((report.relocated, report.dropped), (0, 6));
    assert_eq!(set.active_slot_count(), 0);
}

fn when() -> ViewTime {
    ViewTime {
        frame: 0,
        time: 0.0,
        window_gap: 0,
        phase: Phase::Dynamic,
        time_bands: ALL_TIME_BANDS,
    }
}

fn decoders_for(d: AnchorDims, device: &Device) -> Decoders {
    Decoders::seeded(
        DecoderSizes {
            feature_dim: d.feature_dim,
            time_feature_dim: d.time_feature_dim,
            slots: d.slots,
        },
        3,
        device,
    )
}

#[test]
fn gated_slots_draw_nothing_and_receive_no_gradient() {
    let d = dims(4, 4, FeatureMasking::Off);
    let (mut set, _) = grid_set(d, 24, 7);
    let camera = identity_camera(64, 48);
    let device = Device::ndarray().autodiff();
    let decoders = decoders_for(d, &device);
    // Gate slots 1 and 3 of every even anchor.
    for a in (0..24).step_by(2) {
        set.slot_gates.edit(|g| g[a * 4 + 1] = false);
        set.slot_gates.edit(|g| g[a * 4 + 3] = false);
    }
    let render = |set: &AnchorSet| {
        let visible = visible_anchors(&set.positions, &set.log_scales_host(), &camera);
        let tensors = set.tracked();
        let view = decode_view(set, &tensors, &decoders, visible, when());
        let out = rasterize(&view.gaussians, &camera, [0.0; 3]).unwrap();
        (tensors, view, out)
    };
    let (tensors, view, out) = render(&set);
    assert_eq!(view.visible.rows(), 24);
    let opacity = host_values(&view.decoded.opacity);
    let gates = host_values(&view.gaussians.gates);
    for a in (0..24).step_by(2) {
        for slot in [1, 3] {
            assert_eq!(opacity[a * 4 + slot], 0.0);
            assert_eq!(gates[a * 4 + slot], 0.0, "not handed to the rasterizer");
        }
    }
    assert!(gates.iter().any(|&g| g > 0.0), "the scene draws something");
    // The opacity before the slot gates (AAC's importance) equals it on active slots and shows
    // what a gated slot would draw.
    let before = host_values(&view.slot_opacity);
    for (i, (&b, &o)) in before.iter().zip(&opacity).enumerate() {
        let a = view.visible.anchor_of_row(i / 4) as usize;
        if set.slot_gates[a * 4 + i % 4] {
            assert_eq!(b, o);
        }
    }
    assert!(
        (0..24).step_by(2).any(|a| before[a * 4 + 1] != 0.0),
        "gated slots keep their decoded opacity"
    );
    let diff = out.image.clone() - 0.3;
    let loss = (diff.clone() * diff).mean();
    let grads = loss.backward();
    let g = host_values(
        &tensors.columns[Column::Offsets]
            .grad(&grads)
            .expect("offset gradient"),
    );
    for a in 0..24 {
        for slot in 0..4 {
            let row = &g[(a * 4 + slot) * 3..(a * 4 + slot + 1) * 3];
            if !set.slot_gates[a * 4 + slot] {
                assert_eq!(row, &[0.0; 3], "gated slot {a}/{slot} got a gradient");
            }
        }
    }
    assert!(g.iter().any(|&v| v != 0.0), "active slots do get gradient");

    // Moving a gated slot's offset anywhere changes nothing.
    let mut moved = set.clone();
    let mut offsets = moved.host(Column::Offsets);
    for a in (0..24).step_by(2) {
        offsets[(a * 4 + 1) * 3] += 0.37;
        offsets[(a * 4 + 3) * 3 + 2] -= 1.1;
    }
    moved.set_host(Column::Offsets, offsets);
    let (_, _, moved_out) = render(&moved);
    assert_eq!(host_values(&out.image), host_values(&moved_out.image));
}

#[test]
fn masked_anchors_ignore_their_adaptive_channels() {
    let base = 5;
    let d = dims(
        3,
        3,
        FeatureMasking::Adaptive {
            base,
            threshold: 0.01,
        },
    );
    let (mut set, mut state) = grid_set(d, 12, 8);
    // Anchors 0..6 masked (σ(−6) = 0.0025 ≤ γ), the others kept (σ(1) = 0.73).
    let logits: Vec<f32> = (0..12).map(|a| if a < 6 { -6.0 } else { 1.0 }).collect();
    set.set_host(Column::MaskLogits, logits);
    assert_eq!(set.masking_ratio(), 0.5);
    assert_eq!(
        set.active_feature_channels(),
        [vec![5; 6], vec![8; 6]].concat()
    );
    let camera = identity_camera(64, 48);
    let device = Device::ndarray().autodiff();
    let decoders = decoders_for(d, &device);
    let visible = visible_anchors(&set.positions, &set.log_scales_host(), &camera);
    let tensors = set.tracked();
    let view = decode_view(&set, &tensors, &decoders, visible.clone(), when());
    let loss = view.decoded.color.clone().sum() + view.decoded.opacity.clone().sum();
    let grads = loss.backward();
    let g = host_values(&tensors.columns[Column::Features].grad(&grads).unwrap());
    let gm = host_values(&tensors.columns[Column::MaskLogits].grad(&grads).unwrap());
    for a in 0..12 {
        let adapt = &g[a * 8 + base..(a + 1) * 8];
        if a < 6 {
            assert!(
                adapt.iter().all(|&v| v == 0.0),
                "masked anchor {a}: {adapt:?}"
            );
        } else {
            assert!(adapt.iter().any(|&v| v != 0.0), "kept anchor {a}");
        }
        assert!(
            g[a * 8..a * 8 + base].iter().any(|&v| v != 0.0),
            "F_base of {a}"
        );
        // The straight-through mask passes σ'(m)·(∂L/∂M) to every anchor, masked or not.
        assert!(gm[a] != 0.0, "mask logit of {a} gets the STE gradient");
    }
    // Post-hoc zeroing of masked F_adapt changes no decode.
    let before = host_values(
        &decode_view(
            &set,
            &set.untracked(),
            &decoders_for(d, &Device::ndarray()),
            visible.clone(),
            when(),
        )
        .decoded
        .color,
    );
    let report = prune_capacity(&mut set, &mut state);
    assert_eq!(report.masked_anchors, 6);
    let after = host_values(
        &decode_view(
            &set,
            &set.untracked(),
            &decoders_for(d, &Device::ndarray()),
            visible,
            when(),
        )
        .decoded
        .color,
    );
    assert_eq!(before, after);
    let f = set.host(Column::Features);
    assert!(f[base..8].iter().all(|&v| v == 0.0));
}

#[test]
fn rows_follow_the_anchors_through_grow_relocate_and_prune() {
    let d = dims(3, 2, FeatureMasking::Off);
    let (mut set, mut state) = grid_set(d, 4, 12);
    let t = d.frames;
    // Slot 0 of anchor 0 sits far out with a high gradient → densification grows anchors.
    let mut offsets = set.host(Column::Offsets);
    offsets[0..3].copy_from_slice(&[1.0, 0.0, 0.0]);
    set.set_host(Column::Offsets, offsets);
    for f in 0..t {
        state.stats.offset_grad2d[f] = 30.0 * 1e-3;
        state.stats.offset_visible_count[f] = 30.0;
        // Anchor 3: seen often, never opaque → pruned.
        state.stats.anchor_visible_count[3 * t + f] = 60.0;
    }
    // Mark the original anchors' AAC rows.
    state.importance = (0..12).map(|j| j as f32).collect();
    set.slot_gates.edit(|g| g[2 * 3 + 2] = true); // anchor 2 has 3 active slots
    let config = DensifyConfig {
        grad_threshold: 2e-4,
        ..Default::default()
    };
    let grown = grow_and_prune(&mut set, &mut state, &config, 0.01, 2600, &mut AlwaysHigh);
    assert!(grown.added > 0 && grown.pruned == 1, "{grown:?}");
    let n = set.len();
    assert_eq!(set.slot_gates.len(), n * 3);
    assert_eq!(state.importance.len(), n * 3);
    assert_eq!(state.created_at.len(), n);
    // Old rows 0, 1, 2 keep their data; new rows follow with the first 2 slots active.
    assert_eq!(
        &state.importance[0..9],
        &(0..9).map(|j| j as f32).collect::<Vec<_>>()
    );
    assert_eq!(set.cardinality(2), 3);
    assert_eq!(&state.created_at[0..3], &[0, 0, 0]);
    for a in 3..n {
        assert_eq!(state.created_at[a], 2600);
        assert_eq!(&set.slot_gates[a * 3..a * 3 + 3], &[true, true, false]);
        assert_eq!(&state.importance[a * 3..a * 3 + 3], &[0.0; 3]);
    }
    // New anchors inherit the mask logit (scatter-max of one parent = a copy).
    let m = set.host(Column::MaskLogits);
    assert_eq!(m.len(), n);
    assert!(m.iter().all(|&v| v == 1.0));

    // Relocate at 3000: anchors born at 2600 are young (importance 0, not judged); anchor 1's
    // two slots are made dead. Anchor 0 is the only parent with a free slot: the first
    // relocation fills it, the second finds every parent's anchor full and is dropped.
    state.importance[0] = 10.0;
    state.importance[3] = 0.0;
    state.importance[4] = 0.0;
    let report = relocate(
        &mut set,
        &mut state,
        &aac(1.0),
        3000,
        &mut StdRng::seed_from_u64(0),
    );
    assert_eq!(report.deactivated, 2, "{report:?}");
    assert_eq!((report.relocated, report.dropped), (1, 1));
    assert_eq!(set.cardinality(0), 3);
    assert_eq!(set.cardinality(1), 0);
    assert_eq!(set.active_slot_count(), 3 + 3 + 2 * (n - 3));

    // Prune anchor 1 (now without active slots) and keep the order of the rest.
    let gates_before = set.slot_gates.clone();
    let born_before = state.created_at.clone();
    let posthoc = prune_capacity(&mut set, &mut state);
    let removed = (0..n)
        .filter(|&a| gates_before[a * 3..a * 3 + 3].iter().all(|&g| !g))
        .count();
    assert_eq!(posthoc.removed_anchors, removed);
    assert!(removed >= 1);
    let kept: Vec<usize> = (0..n)
        .filter(|&a| gates_before[a * 3..a * 3 + 3].iter().any(|&g| g))
        .collect();
    assert_eq!(set.len(), kept.len());
    for (row, &a) in kept.iter().enumerate() {
        assert_eq!(
            &set.slot_gates[row * 3..row * 3 + 3],
            &gates_before[a * 3..a * 3 + 3]
        );
        assert_eq!(state.created_at[row], born_before[a]);
    }
    assert_eq!(state.adam[Column::Offsets].exp_avg.dims()[0], set.len());
    assert_eq!(set.value(Column::MaskLogits).dims(), [set.len(), 1]);
}

#[test]
fn stored_size_counts_active_slots_kept_channels_and_bitmaps() {
    let d = dims(
        4,
        2,
        FeatureMasking::Adaptive {
            base: 5,
            threshold: 0.01,
        },
    );
    let (mut set, _) = grid_set(d, 3, 1);
    let logits = vec![-9.0f32, 2.0, 2.0];
    set.set_host(Column::MaskLogits, logits);
    set.slot_gates.edit(|g| g[2] = true); // anchor 0: 3 active
    let per_anchor = 3 + 6 + 4 + d.frames * d.time_feature_dim;
    let floats = 3 * per_anchor + (3 + 2 + 2) * 3 + (5 + 8 + 8);
    let bits: usize = 3 * 4 + 3;
    assert_eq!(set.stored_bytes(), floats * 4 + bits.div_ceil(8));
    assert_eq!(set.cardinality_histogram(), vec![0, 0, 2, 1, 0]);
}

#[test]
fn smoothness_means_over_active_slots_skip_switched_off_slots_and_culled_rows() {
    use acags::model::view::VisibleRows;
    let device = Device::ndarray().autodiff();
    let (m, k, width) = (6, 4, 3);
    let mut rng = StdRng::seed_from_u64(5);
    let mut values: Vec<f32> = (0..m * k * width).map(|_| rng.random::<f32>()).collect();
    // Row 2 has no active slot; the rest a mix.
    let gates: Vec<f32> = (0..m * k)
        .map(|j| if j / k == 2 || j % 3 == 1 { 0.0 } else { 1.0 })
        .collect();
    let row_mask = [1.0f32, 1.0, 1.0, 0.0, 1.0, 1.0];
    for masked in [false, true] {
        if masked {
            // A culled row's values must not enter, not even as 0·NaN.
            values[3 * k * width..4 * k * width].fill(f32::NAN);
        }
        let visible = if masked {
            VisibleRows::Masked(Tensor::<1>::from_data(
                TensorData::new(row_mask.to_vec(), [m]),
                &device,
            ))
        } else {
            VisibleRows::Listed((0..m as u32).collect())
        };
        let on = |j: usize| gates[j / width] > 0.0 && (!masked || row_mask[j / (k * width)] > 0.0);
        let active = (0..m * k * width).filter(|&j| on(j)).count();
        let expected: f32 = (0..m * k * width)
            .filter(|&j| on(j))
            .map(|j| values[j])
            .sum::<f32>()
            / active as f32;
        let x = Tensor::<2>::from_data(TensorData::new(values.clone(), [m, k * width]), &device)
            .require_grad();
        let g = Tensor::<2>::from_data(TensorData::new(gates.clone(), [m, k]), &device);
        let mean = visible.mean_over_slots(x.clone(), g, width);
        let got = host_values(&mean)[0];
        assert!(
            (got - expected).abs() < 1e-6,
            "masked {masked}: {got} vs {expected}"
        );
        // Each active element weighs 1/active; switched-off slots and culled rows weigh 0.
        let grad = host_values(&x.grad(&mean.backward()).unwrap());
        for (j, &v) in grad.iter().enumerate() {
            let want = if on(j) { 1.0 / active as f32 } else { 0.0 };
            assert!((v - want).abs() < 1e-7, "element {j}: {v} vs {want}");
        }
        // With every slot on it is the plain mean over the visible rows.
        let ones = Tensor::<2>::ones([m, k], &device);
        let all = host_values(&visible.mean_over_slots(x.clone(), ones, width))[0];
        let plain = host_values(&visible.mean(x.clone()))[0];
        assert!((all - plain).abs() < 1e-6, "{all} vs {plain}");
        // No active slot on any visible row: 0, not NaN.
        let none = Tensor::<2>::zeros([m, k], &device);
        assert_eq!(
            host_values(&visible.mean_over_slots(x, none, width))[0],
            0.0
        );
    }
}
