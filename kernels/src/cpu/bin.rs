//! Tile binning: which Gaussians touch which 16x16 tile, each tile's list sorted front to back.

use rayon::prelude::*;

use super::project::Projected;
use crate::conventions::TILE_SIZE;

/// Intersections of visible Gaussians with screen tiles, grouped by tile (row-major tile ids),
/// front to back (ascending depth, ties by Gaussian index) inside each tile.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// `tile_offsets[t]..tile_offsets[t + 1]` is tile `t`'s range in `gaussian_from_intersection`.
    pub tile_offsets: Vec<u32>,
    pub gaussian_from_intersection: Vec<u32>,
}

impl TileBins {
    pub fn intersection_count(&self) -> usize {
        self.gaussian_from_intersection.len()
    }

    /// Intersection range of tile row `ty` (contiguous because tile ids are row-major).
    pub fn row_range(&self, ty: u32) -> std::ops::Range<usize> {
        let first = (ty * self.tiles_x) as usize;
        self.tile_offsets[first] as usize..self.tile_offsets[first + self.tiles_x as usize] as usize
    }
}

/// Tiles `[x0, x1) x [y0, y1)` covered by a projected Gaussian's screen box (gsplat's rule).
pub fn tile_rect(p: &Projected, tiles_x: u32, tiles_y: u32) -> [u32; 4] {
    let t = TILE_SIZE as f32;
    let [mx, my] = p.mean2d;
    let (rx, ry) = (p.radius[0] as f32, p.radius[1] as f32);
    let clamp = |v: f32, hi: u32| v.clamp(0.0, hi as f32) as u32;
    [
        clamp(((mx - rx) / t).floor(), tiles_x),
        clamp(((mx + rx) / t).ceil(), tiles_x),
        clamp(((my - ry) / t).floor(), tiles_y),
        clamp(((my + ry) / t).ceil(), tiles_y),
    ]
}

pub fn is_visible(p: &Projected) -> bool {
    p.radius != [0, 0]
}

/// Maps a depth to a u32 whose unsigned order is `f32::total_cmp`'s (negatives flipped, sign bit
/// set on positives).
fn depth_order_key(depth: f32) -> u32 {
    let bits = depth.to_bits();
    if bits >> 31 == 1 {
        !bits
    } else {
        bits | 0x8000_0000
    }
}

/// Bins the visible Gaussians (radius != 0) into tiles.
///
/// Sorting the Gaussians once by depth and then counting-sorting intersections by tile keeps every
/// tile's list in depth order without a per-intersection key sort.
pub fn bin_tiles(projected: &[Projected], tiles_x: u32, tiles_y: u32) -> TileBins {
    // Sort (depth, index) keys packed in one u64: the depth's bits mapped so that integer order
    // is `f32::total_cmp` order, the index below breaking ties (equal depths keep index order).
    // Sorting plain integers avoids a comparator that looks each depth up by index, which was
    // the slowest part of binning a million Gaussians.
    let mut keys: Vec<u64> = projected
        .par_iter()
        .enumerate()
        .filter(|(_, p)| is_visible(p))
        .map(|(i, p)| ((depth_order_key(p.depth) as u64) << 32) | i as u64)
        .collect();
    keys.par_sort_unstable();
    let order: Vec<u32> = keys.par_iter().map(|&k| k as u32).collect();

    let rects: Vec<[u32; 4]> = order
        .par_iter()
        .map(|&g| tile_rect(&projected[g as usize], tiles_x, tiles_y))
        .collect();
    let tile_count = (tiles_x * tiles_y) as usize;
    let mut counts = vec![0u32; tile_count + 1];
    for &[x0, x1, y0, y1] in &rects {
        for ty in y0..y1 {
            for tx in x0..x1 {
                counts[(ty * tiles_x + tx) as usize] += 1;
            }
        }
    }
    // Exclusive prefix sum into offsets.
    let mut tile_offsets = Vec::with_capacity(tile_count + 1);
    let mut total = 0u64;
    for &c in &counts[..tile_count] {
        tile_offsets.push(total as u32);
        total += c as u64;
    }
    assert!(
        total <= u32::MAX as u64,
        "more than 2^32 tile intersections ({total})"
    );
    tile_offsets.push(total as u32);

    let mut cursor = tile_offsets.clone();
    let mut gaussian_from_intersection = vec![0u32; total as usize];
    for (&g, &[x0, x1, y0, y1]) in order.iter().zip(&rects) {
        for ty in y0..y1 {
            for tx in x0..x1 {
                let slot = &mut cursor[(ty * tiles_x + tx) as usize];
                gaussian_from_intersection[*slot as usize] = g;
                *slot += 1;
            }
        }
    }
    TileBins {
        tiles_x,
        tiles_y,
        tile_offsets,
        gaussian_from_intersection,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The packed keys order depths as `f32::total_cmp` does, ties by index: the same order as
    /// the stable comparator sort they replace.
    #[test]
    fn depth_keys_sort_like_a_stable_total_cmp_sort() {
        let depths = [
            3.5f32,
            0.25,
            3.5,
            1e-3,
            7.0,
            0.25,
            1e9,
            2.0,
            3.5,
            f32::MIN_POSITIVE,
            0.0,
            -0.0,
            -2.0,
        ];
        let projected: Vec<Projected> = depths
            .iter()
            .map(|&depth| Projected {
                depth,
                radius: [1, 1],
                ..Default::default()
            })
            .collect();
        let mut want: Vec<u32> = (0..depths.len() as u32).collect();
        want.sort_by(|&a, &b| depths[a as usize].total_cmp(&depths[b as usize]));
        let bins = bin_tiles(&projected, 1, 1);
        assert_eq!(bins.gaussian_from_intersection, want);
    }
}
