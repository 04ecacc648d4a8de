//! Anchor initialisation (spec §3): voxelisation, initial scales, k nearest neighbours.

use acags::model::init::{
    MIN_MEAN_SQUARED_DISTANCE, initial_log_scales, nearest_neighbors, voxelize,
};
use rand::{Rng, SeedableRng, rngs::StdRng};

#[test]
fn voxelisation_rounds_to_the_grid_merges_and_sorts() {
    let points = [
        [0.0049, 0.0, 0.0],   // -> (0, 0, 0)
        [0.0051, 0.0, 0.0],   // -> (1, 0, 0)
        [0.0, 0.0, 0.0],      // duplicate of the first cell
        [-0.012, 0.3, 0.0],   // -> (-1, 30, 0)
        [f32::NAN, 0.0, 0.0], // skipped
    ];
    let anchors = voxelize(&points, 0.01);
    let cells: Vec<[i64; 3]> = anchors
        .iter()
        .map(|a| a.map(|v| (v / 0.01).round() as i64))
        .collect();
    assert_eq!(cells, vec![[-1, 30, 0], [0, 0, 0], [1, 0, 0]]);
    assert_eq!(voxelize(&points, 0.1).len(), 2);
}

#[test]
fn initial_scales_are_log_rms_distances_to_three_neighbours() {
    // A 0.01 grid: every interior anchor's 3 nearest neighbours are 0.01 away.
    let mut grid = Vec::new();
    for x in 0..5 {
        for y in 0..5 {
            for z in 0..5 {
                grid.push([x as f32 * 0.01, y as f32 * 0.01, z as f32 * 0.01]);
            }
        }
    }
    let scales = initial_log_scales(&grid);
    for s in &scales {
        assert!((s - 0.01f32.ln()).abs() < 1e-4, "{s}");
    }
    // Three points on a line at 0, 1, 3: the middle one has neighbours at distances 1 and 2
    // (only two exist): log(sqrt((1 + 4) / 2)).
    let line = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]];
    let s = initial_log_scales(&line);
    assert!((s[1] - (2.5f32).sqrt().ln()).abs() < 1e-6);
    // A single point falls back to the clamp.
    assert!(
        (initial_log_scales(&[[1.0, 2.0, 3.0]])[0] as f64 - 0.5 * MIN_MEAN_SQUARED_DISTANCE.ln())
            .abs()
            < 1e-5
    );
}

#[test]
fn nearest_neighbours_match_brute_force() {
    let mut rng = StdRng::seed_from_u64(9);
    let points: Vec<[f32; 3]> = (0..500)
        .map(|_| [rng.random(), rng.random(), rng.random()])
        .collect();
    let knn = nearest_neighbors(&points, 6);
    for (i, found) in knn.iter().enumerate() {
        let d2 = |j: usize| {
            (0..3)
                .map(|a| (points[i][a] - points[j][a]).powi(2))
                .sum::<f32>()
        };
        let mut brute: Vec<usize> = (0..points.len()).filter(|&j| j != i).collect();
        brute.sort_by(|&a, &b| d2(a).total_cmp(&d2(b)));
        let want: Vec<u32> = brute[..6].iter().map(|&j| j as u32).collect();
        assert_eq!(found, &want, "neighbours of point {i}");
    }
    assert_eq!(
        nearest_neighbors(&points[..3], 6)[0].len(),
        2,
        "fewer points than k"
    );
}
