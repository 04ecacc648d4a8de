//! Anchor initialisation from a point cloud (spec §3) and k-nearest-neighbour queries.

use std::collections::BTreeSet;
use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

/// Lower bound on the mean squared neighbour distance (GIFStream clamps `distCUDA2` at 1e-7).
pub const MIN_MEAN_SQUARED_DISTANCE: f64 = 1e-7;

/// Anchors on a voxel grid: `unique(round(p / voxel)) * voxel` (GIFStream L324-L327).
///
/// GIFStream shuffles the points first, but `torch.unique` returns sorted rows, so the result is
/// the voxel centres in lexicographic order of their integer coordinates whatever the shuffle;
/// this returns exactly that order. Non-finite points are skipped.
pub fn voxelize(points: &[[f32; 3]], voxel: f32) -> Vec<[f32; 3]> {
    assert!(
        voxel > 0.0 && voxel.is_finite(),
        "voxel size must be positive, got {voxel}"
    );
    let cells: BTreeSet<[i64; 3]> = points
        .iter()
        .filter(|p| p.iter().all(|v| v.is_finite()))
        .map(|p| p.map(|v| (v / voxel).round() as i64))
        .collect();
    cells
        .into_iter()
        .map(|c| c.map(|i| i as f32 * voxel))
        .collect()
}

fn tree(points: &[[f32; 3]]) -> ImmutableKdTree<f32, 3> {
    ImmutableKdTree::new_from_slice(points).expect("k-d tree over finite points")
}

/// Indices of the `k` nearest other points of every point, nearest first (fewer when the cloud
/// has fewer than k + 1 points). Ties are broken by the tree, deterministically.
pub fn nearest_neighbors(points: &[[f32; 3]], k: usize) -> Vec<Vec<u32>> {
    if points.is_empty() || k == 0 {
        return vec![Vec::new(); points.len()];
    }
    let tree = tree(points);
    let want = NonZero::new((k + 1).min(points.len())).unwrap();
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            tree.query(p)
                .nearest_n::<SquaredEuclidean<f32>>(want)
                .execute()
                .into_iter()
                .map(|r| r.item as u32)
                .filter(|&j| j as usize != i)
                .take(k)
                .collect()
        })
        .collect()
}

/// Points beyond the `k` nearest that [`neighbourhoods`] asks the tree for, so that the points
/// tied with the k-th are found: a whole 3 × 3 × 3 shell of voxels.
const TIE_ROOM: usize = 26;

/// Relative difference of squared distances under which two points count as tied.
const TIE_TOLERANCE: f32 = 1e-4;

/// Every point's neighbourhood: the other points no farther than its k-th nearest, ties
/// included, ascending by index. Unlike [`nearest_neighbors`] the set does not depend on the
/// order of the points (on a voxel grid many are equidistant), so a decoder that orders the
/// anchors its own way finds the same sets (up to [`TIE_ROOM`] tied points).
pub fn neighbourhoods(points: &[[f32; 3]], k: usize) -> Vec<Vec<u32>> {
    if points.is_empty() || k == 0 {
        return vec![Vec::new(); points.len()];
    }
    let tree = tree(points);
    let want = NonZero::new((k + 1 + TIE_ROOM).min(points.len())).unwrap();
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let mut found: Vec<(f32, u32)> = tree
                .query(p)
                .nearest_n::<SquaredEuclidean<f32>>(want)
                .execute()
                .into_iter()
                .map(|r| (r.distance, r.item as u32))
                .filter(|&(_, j)| j as usize != i)
                .collect();
            found.sort_by(|a, b| a.0.total_cmp(&b.0));
            let Some(reach) = found
                .iter()
                .map(|&(d, _)| d)
                .nth(k.min(found.len()).saturating_sub(1))
            else {
                return Vec::new();
            };
            // Ties within rounding: a decoder's positions are the grid's integers times the
            // voxel, which can differ from the trained ones in the last bits.
            let reach = reach * (1.0 + TIE_TOLERANCE);
            let mut within: Vec<u32> = found
                .into_iter()
                .filter(|&(d, _)| d <= reach)
                .map(|(_, j)| j)
                .collect();
            within.sort_unstable();
            within
        })
        .collect()
}

/// Initial log-scale of every anchor: log(sqrt(mean of the squared distances to its 3 nearest
/// other anchors)), the mean clamped at 1e-7 (GIFStream L332-L334, `distCUDA2`). The caller
/// repeats it for the 6 scale dimensions.
pub fn initial_log_scales(anchors: &[[f32; 3]]) -> Vec<f32> {
    let neighbors = nearest_neighbors(anchors, 3);
    anchors
        .par_iter()
        .zip(&neighbors)
        .map(|(p, nn)| {
            let mean = if nn.is_empty() {
                MIN_MEAN_SQUARED_DISTANCE
            } else {
                nn.iter()
                    .map(|&j| {
                        let q = anchors[j as usize];
                        (0..3)
                            .map(|a| (p[a] as f64 - q[a] as f64).powi(2))
                            .sum::<f64>()
                    })
                    .sum::<f64>()
                    / nn.len() as f64
            };
            (0.5 * mean.max(MIN_MEAN_SQUARED_DISTANCE).ln()) as f32
        })
        .collect()
}
