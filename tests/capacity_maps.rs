//! The capacity heatmaps composite like the rasterizer: blend weights T·α in depth order, a
//! weighted mean of per-anchor values, and a count of the anchors that carry a visible share.

use acags::eval::capacity_maps::{
    AnchoredGaussian, CONTRIBUTION_THRESHOLD, anchor_count_color, composite_capacity,
};
use acags::raster::cpu::project::GaussianParams;
use acags::raster::random_scene::identity_camera;

/// A round Gaussian on the optical axis at `depth`, wide enough to be flat over the centre pixels.
fn on_axis(depth: f32, opacity: f32, anchor: u32) -> AnchoredGaussian {
    AnchoredGaussian {
        params: GaussianParams {
            mean: [0.0, 0.0, depth],
            quat: [1.0, 0.0, 0.0, 0.0],
            scale: [1.0; 3],
            opacity,
        },
        anchor,
    }
}

#[test]
fn two_stacked_anchors_blend_front_to_back() {
    let camera = identity_camera(64, 48);
    // Listed back to front: compositing must sort by depth.
    let gaussians = [on_axis(3.0, 0.5, 1), on_axis(2.0, 0.5, 0)];
    let cardinality = [2.0, 8.0];
    let channels = [0.5, 1.0];
    let maps = composite_capacity(&gaussians, &cardinality, &channels, &camera);
    let centre = 24 * 64 + 32;
    // Weights ≈ 0.5 (front, anchor 0) and 0.25 (behind, anchor 1).
    assert_eq!(maps.anchor_count[centre], 2);
    assert!(
        (maps.alpha[centre] - 0.75).abs() < 2e-3,
        "{}",
        maps.alpha[centre]
    );
    let want = (0.5 * 2.0 + 0.25 * 8.0) / 0.75;
    assert!(
        (maps.cardinality[centre] - want).abs() < 1e-2,
        "{}",
        maps.cardinality[centre]
    );
    let want = (0.5 * 0.5 + 0.25 * 1.0) / 0.75;
    assert!((maps.channel_fraction[centre] - want).abs() < 1e-2);

    // Swapping the depths swaps the weights.
    let gaussians = [on_axis(2.0, 0.5, 1), on_axis(3.0, 0.5, 0)];
    let maps = composite_capacity(&gaussians, &cardinality, &channels, &camera);
    let want = (0.25 * 2.0 + 0.5 * 8.0) / 0.75;
    assert!((maps.cardinality[centre] - want).abs() < 1e-2);
}

#[test]
fn anchors_hidden_behind_an_opaque_one_do_not_count() {
    let camera = identity_camera(64, 48);
    // The front Gaussian (α clamped to 0.99) leaves 1 % for the one behind: below the threshold.
    assert!(0.01 < CONTRIBUTION_THRESHOLD);
    let gaussians = [on_axis(2.0, 1.0, 0), on_axis(3.0, 1.0, 1)];
    let maps = composite_capacity(&gaussians, &[3.0, 9.0], &[1.0, 1.0], &camera);
    let centre = 24 * 64 + 32;
    assert_eq!(maps.anchor_count[centre], 1);
    assert!(maps.cardinality[centre] < 3.1);
    // Two Gaussians of the same anchor count once.
    let gaussians = [on_axis(2.0, 0.5, 4), on_axis(3.0, 0.5, 4)];
    let maps = composite_capacity(&gaussians, &[0.0, 0.0, 0.0, 0.0, 5.0], &[1.0; 5], &camera);
    assert_eq!(maps.anchor_count[centre], 1);
    assert!((maps.cardinality[centre] - 5.0).abs() < 1e-5);
}

#[test]
fn empty_views_have_no_anchors_and_undefined_means() {
    let camera = identity_camera(16, 8);
    let maps = composite_capacity(&[], &[], &[], &camera);
    assert!(maps.anchor_count.iter().all(|&c| c == 0));
    assert!(maps.cardinality.iter().all(|c| c.is_nan()));
    assert_eq!(anchor_count_color(0), anchor_count_color(1));
    assert_ne!(anchor_count_color(2), anchor_count_color(5));
}
