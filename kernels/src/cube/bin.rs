//! Tile binning on the device, the CPU twin's order (`cpu::bin`): the Gaussians are sorted by
//! depth (ties by index), every visible one emits its tiles in that order at offsets from a
//! prefix sum of its tile counts, and a stable sort by tile id groups them, so each tile's list
//! stays front to back. One read back (the intersection count) sizes the intersection buffers,
//! unless the caller sizes them ahead ([`IntersectionCapacity::AtMost`]): then nothing is read,
//! the unused tail of the keys holds a key past every tile (sorted last, outside every tile's
//! range), and intersections beyond the buffers are dropped, which the [1] count returned with
//! the bins tells the caller.

use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::read_sync;
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use super::buffers::fresh_u32;
use super::radix_sort::sort_pairs;
use super::scan::exclusive_scan;
use crate::raster_io::IntersectionCapacity;
use crate::conventions::{PROJECTED_COLUMNS, TILE_SIZE, projected_column as col};

/// Depth key of an invisible Gaussian: after every visible one (depths are positive floats,
/// whose bit patterns order like their values).
const INVISIBLE_KEY: u32 = u32::MAX;

/// Tiles [x0, x1) × [y0, y1) of a projected row (gsplat's rule, as `cpu::bin::tile_rect`).
#[cube]
fn tile_rect(
    projected: &Tensor<f32>,
    g: usize,
    tiles_x: u32,
    tiles_y: u32,
) -> (u32, u32, u32, u32) {
    let t = TILE_SIZE as f32;
    let mx = projected[g * PROJECTED_COLUMNS + col::MEAN2D_X];
    let my = projected[g * PROJECTED_COLUMNS + col::MEAN2D_Y];
    let rx = projected[g * PROJECTED_COLUMNS + col::RADIUS_X];
    let ry = projected[g * PROJECTED_COLUMNS + col::RADIUS_Y];
    let x0 = f32::clamp(f32::floor((mx - rx) / t), 0.0, tiles_x as f32) as u32;
    let x1 = f32::clamp(f32::ceil((mx + rx) / t), 0.0, tiles_x as f32) as u32;
    let y0 = f32::clamp(f32::floor((my - ry) / t), 0.0, tiles_y as f32) as u32;
    let y1 = f32::clamp(f32::ceil((my + ry) / t), 0.0, tiles_y as f32) as u32;
    (x0, x1, y0, y1)
}

#[cube]
fn is_visible(projected: &Tensor<f32>, g: usize) -> bool {
    projected[g * PROJECTED_COLUMNS + col::RADIUS_X] != 0.0
        || projected[g * PROJECTED_COLUMNS + col::RADIUS_Y] != 0.0
}

#[cube(launch)]
fn depth_keys_kernel(projected: &Tensor<f32>, keys: &mut Tensor<u32>, indices: &mut Tensor<u32>) {
    let g = ABSOLUTE_POS;
    if g >= keys.len() {
        terminate!();
    }
    if is_visible(projected, g) {
        keys[g] = u32::reinterpret(projected[g * PROJECTED_COLUMNS + col::DEPTH]);
    } else {
        keys[g] = INVISIBLE_KEY;
    }
    indices[g] = g as u32;
}

#[cube(launch)]
fn tile_counts_kernel(
    projected: &Tensor<f32>,
    gaussian_from_depth_rank: &Tensor<u32>,
    counts: &mut Tensor<u32>,
    tiles_x: u32,
    tiles_y: u32,
) {
    let j = ABSOLUTE_POS;
    if j >= counts.len() {
        terminate!();
    }
    let g = gaussian_from_depth_rank[j] as usize;
    if is_visible(projected, g) {
        let (x0, x1, y0, y1) = tile_rect(projected, g, tiles_x, tiles_y);
        counts[j] = (x1 - x0) * (y1 - y0);
    } else {
        counts[j] = 0u32;
    }
}

#[cube(launch)]
fn emit_intersections_kernel(
    projected: &Tensor<f32>,
    gaussian_from_depth_rank: &Tensor<u32>,
    offsets: &Tensor<u32>,
    tile_keys: &mut Tensor<u32>,
    gaussian_from_intersection: &mut Tensor<u32>,
    tiles_x: u32,
    tiles_y: u32,
) {
    let j = ABSOLUTE_POS;
    if j >= offsets.len() {
        terminate!();
    }
    let g = gaussian_from_depth_rank[j];
    if is_visible(projected, g as usize) {
        let (x0, x1, y0, y1) = tile_rect(projected, g as usize, tiles_x, tiles_y);
        let mut slot = offsets[j] as usize;
        // Buffers sized ahead may be too short: what does not fit is dropped (and counted).
        let capacity = tile_keys.len();
        for ty in y0..y1 {
            for tx in x0..x1 {
                if slot < capacity {
                    tile_keys[slot] = ty * tiles_x + tx;
                    gaussian_from_intersection[slot] = g;
                }
                slot += 1;
            }
        }
    }
}

/// `tile_offsets[t]` = first intersection whose tile is ≥ t (binary search in the sorted keys),
/// so empty tiles get empty ranges and `tile_offsets[tiles]` = the intersection count.
#[cube(launch)]
fn tile_offsets_kernel(tile_keys: &Tensor<u32>, tile_offsets: &mut Tensor<u32>) {
    let t = ABSOLUTE_POS;
    if t >= tile_offsets.len() {
        terminate!();
    }
    let mut lo = 0usize;
    let mut hi = tile_keys.len();
    while lo < hi {
        let mid = (lo + hi) / 2;
        if (tile_keys[mid] as usize) < t {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    tile_offsets[t] = lo as u32;
}

/// Tile bins on the device: `tile_offsets` [tiles + 1] and `gaussian_from_intersection`
/// [intersections, or the capacity sized ahead], both u32, as `cpu::TileBins`, and the [1] u32
/// count of intersections the Gaussians make.
pub struct DeviceTileBins {
    pub tile_offsets: CubeTensor,
    pub gaussian_from_intersection: CubeTensor,
    pub intersections: CubeTensor,
}

fn launch_elemwise(client: &cubecl::client::Client, n: usize) -> (CubeCount, CubeDim) {
    let cube_dim = CubeDim::new_1d(256);
    (
        cubecl::calculate_cube_count_elemwise(client, n, cube_dim),
        cube_dim,
    )
}

/// Bins the visible rows of `projected` ([N, 8] f32, N ≥ 1) into tiles.
pub fn bin_tiles(
    projected: &CubeTensor,
    tiles_x: u32,
    tiles_y: u32,
    capacity: IntersectionCapacity,
) -> DeviceTileBins {
    let n = projected.meta.shape()[0];
    assert!(n > 0);
    let client = projected.client.clone();
    let tiles = (tiles_x * tiles_y) as usize;

    let keys = fresh_u32(projected, &[n]);
    let indices = fresh_u32(projected, &[n]);
    let (count, dim) = launch_elemwise(&client, n);
    depth_keys_kernel::launch(
        &client,
        count.clone(),
        dim,
        projected.clone().into_tensor_arg(),
        keys.clone().into_tensor_arg(),
        indices.clone().into_tensor_arg(),
    );
    let (_, gaussian_from_depth_rank) = sort_pairs(keys, indices, 32);

    let counts = fresh_u32(projected, &[n]);
    tile_counts_kernel::launch(
        &client,
        count.clone(),
        dim,
        projected.clone().into_tensor_arg(),
        gaussian_from_depth_rank.clone().into_tensor_arg(),
        counts.clone().into_tensor_arg(),
        tiles_x,
        tiles_y,
    );
    let (offsets, total) = exclusive_scan(&counts);
    // The scan counts in u32: where N × tiles could pass 2^32 the count may have wrapped, so
    // it is checked against a float sum first (only then: it costs a reduction and a read).
    let may_wrap = n as u64 * tiles as u64 > u32::MAX as u64;
    if may_wrap {
        let approximate = float_total(&counts);
        if let Some(message) = intersection_overflow(approximate) {
            panic!("{message}");
        }
    }
    let max_buffer_bytes = client.properties().memory.max_page_size;
    let sized_ahead = match capacity {
        // A count that may have wrapped cannot tell an overflow: counted exactly instead.
        IntersectionCapacity::AtMost(slots) if !may_wrap => Some(slots),
        _ => None,
    };
    let slots = match sized_ahead {
        // No more than one buffer holds: a count beyond it overflows, and the exact render the
        // caller then asks for names the limit.
        // Nor more than the Gaussians can make (≤ 2^32 here: the count did not wrap).
        Some(slots) => {
            let most = (max_buffer_bytes / 4).min(n as u64 * tiles as u64);
            slots.min(usize::try_from(most).unwrap_or(usize::MAX)).max(1)
        }
        None => {
            // The one read back of the forward: the buffers below are sized by it.
            let intersections = read_count(total.clone());
            if let Some(message) =
                intersection_capacity_error(intersections as u64, max_buffer_bytes)
            {
                panic!("{message}");
            }
            intersections
        }
    };

    let tile_offsets = fresh_u32(projected, &[tiles + 1]);
    if slots == 0 {
        super::buffers::fill_words(&tile_offsets, 0);
        return DeviceTileBins {
            tile_offsets,
            gaussian_from_intersection: fresh_u32(projected, &[0]),
            intersections: total,
        };
    }
    let tile_keys = fresh_u32(projected, &[slots]);
    let gaussian_from_intersection = fresh_u32(projected, &[slots]);
    // Real keys are tile ids < tiles. Slots no intersection fills get a key ≥ tiles, so they
    // sort after every tile and fall in no tile's range: the largest key the sort's bits for
    // the tile ids hold, unless that is a tile id (then `tiles`, one bit more).
    let id_bits = (u32::BITS - (tiles as u32 - 1).leading_zeros()).max(1);
    let unused_key = match ((1u64 << id_bits) - 1) as u32 {
        key if key as usize >= tiles => key,
        _ => tiles as u32,
    };
    if sized_ahead.is_some() {
        super::buffers::fill_words(&tile_keys, unused_key);
    }
    emit_intersections_kernel::launch(
        &client,
        count,
        dim,
        projected.clone().into_tensor_arg(),
        gaussian_from_depth_rank.into_tensor_arg(),
        offsets.into_tensor_arg(),
        tile_keys.clone().into_tensor_arg(),
        gaussian_from_intersection.clone().into_tensor_arg(),
        tiles_x,
        tiles_y,
    );
    let largest_key = if sized_ahead.is_some() {
        unused_key
    } else {
        tiles as u32 - 1
    };
    let tile_bits = u32::BITS - largest_key.leading_zeros();
    let (tile_keys, gaussian_from_intersection) =
        sort_pairs(tile_keys, gaussian_from_intersection, tile_bits);
    let (count, dim) = launch_elemwise(&client, tiles + 1);
    tile_offsets_kernel::launch(
        &client,
        count,
        dim,
        tile_keys.into_tensor_arg(),
        tile_offsets.clone().into_tensor_arg(),
    );
    DeviceTileBins {
        tile_offsets,
        gaussian_from_intersection,
        intersections: total,
    }
}

/// Why `approximate` intersections (a float sum, good to far better than the margin) cannot
/// be counted in the u32 offsets, or `None`. The margin keeps float rounding from letting a
/// wrapped count through; a count that close to 2^32 could not be allocated anyway.
pub fn intersection_overflow(approximate: f64) -> Option<String> {
    (approximate >= 0.93 * u32::MAX as f64).then(|| {
        format!(
            "rasterizer: about {approximate:.3e} tile intersections, more than the u32 offsets \
             can count (2^32); the Gaussians' screen footprints are too large for this image \
             (fewer or smaller Gaussians, or a smaller image)"
        )
    })
}

/// Why `intersections` do not fit in one device buffer of at most `max_buffer_bytes`, or
/// `None`. Each of the intersection buffers (tile keys, Gaussian ids and the sort's second
/// copies) holds one u32 per intersection and must be one binding.
pub fn intersection_capacity_error(intersections: u64, max_buffer_bytes: u64) -> Option<String> {
    let bytes = intersections * 4;
    (bytes > max_buffer_bytes).then(|| {
        format!(
            "rasterizer: {intersections} tile intersections need {:.1} MiB per intersection \
             buffer, more than this device's largest buffer ({:.1} MiB); the Gaussians' screen \
             footprints are too large for this image (fewer or smaller Gaussians, or a smaller \
             image), or use a device with larger storage buffers",
            bytes as f64 / (1u64 << 20) as f64,
            max_buffer_bytes as f64 / (1u64 << 20) as f64,
        )
    })
}

/// Sum of the u32 `counts` in f32 on the device, read back (immune to u32 wrap-around).
fn float_total(counts: &CubeTensor) -> f64 {
    let as_float = burn_cubecl::kernel::cast(counts.clone(), DType::F32);
    let sum = burn_cubecl::kernel::reduce::sum_fallback(as_float, Default::default())
        .expect("rasterizer: summing the tile counts on the device failed");
    crate::transfers::record_read_back(4);
    let data = read_sync(CubeBackend::float_into_data(sum))
        .expect("rasterizer: reading the tile-count sum back from the device failed");
    data.convert::<f32>().try_to_vec::<f32>().expect("a sum")[0] as f64
}

/// Reads a [1] u32 count back to the host.
fn read_count(total: CubeTensor) -> usize {
    crate::transfers::record_read_back(4);
    let data = read_sync(CubeBackend::int_into_data(total))
        .expect("rasterizer: reading the intersection count back from the device failed");
    data.convert::<i64>().try_to_vec::<i64>().expect("a count")[0] as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intersection_buffers_are_refused_exactly_past_the_device_limit() {
        let limit = 128u64 << 20;
        assert_eq!(intersection_capacity_error(limit / 4, limit), None);
        let message = intersection_capacity_error(limit / 4 + 1, limit).unwrap();
        assert!(
            message.contains("33554433 tile intersections need 128.0 MiB"),
            "{message}"
        );
        assert!(message.contains("largest buffer (128.0 MiB)"), "{message}");
    }

    #[test]
    fn counts_near_two_to_the_32_are_refused() {
        assert_eq!(intersection_overflow(3.9e9), None);
        assert!(intersection_overflow(4.0e9).is_some());
        assert!(intersection_overflow(4.59e9).unwrap().contains("4.590e9"));
    }
}
