//! Stable LSD radix sort of (u32 key, u32 value) pairs on the device, 4 bits per pass: a digit
//! histogram per block of 1024 keys, an exclusive scan of the histograms (digit-major, so each
//! digit's blocks follow in order), and a scatter that ranks keys inside the block in their input
//! order. Stability is what keeps each tile's intersections in depth order, ties by index, as the
//! CPU twin's counting sort does.
//!
//! Written here rather than taken from Burn: Burn 0.22's sort on the Cube backend reads the tensor
//! back to the host, and its cumulative sum is quadratic.

use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use super::buffers::fresh_u32;
use super::scan::{BLOCK_UNITS, SCAN_BLOCK, cube_exclusive_scan, exclusive_scan, spread};

const RADIX_BITS: u32 = 4;
const DIGITS: usize = 1 << RADIX_BITS;
/// Keys per unit (contiguous) and per block.
const ITEMS_PER_UNIT: usize = 4;
const SORT_BLOCK: usize = BLOCK_UNITS * ITEMS_PER_UNIT;

#[cube(launch)]
fn digit_histogram_kernel(
    keys: &Tensor<u32>,
    histogram: &mut Tensor<u32>,
    shift: u32,
    blocks: usize,
) {
    let block = CUBE_POS;
    if block >= blocks {
        terminate!();
    }
    let unit = UNIT_POS as usize;
    let counts = Shared::<[Atomic<u32>]>::new_slice(DIGITS);
    if unit < DIGITS {
        counts[unit].store(0u32);
    }
    sync_cube();
    let n = keys.len();
    let base = block * SORT_BLOCK + unit * ITEMS_PER_UNIT;
    #[unroll]
    for i in 0..ITEMS_PER_UNIT {
        if base + i < n {
            let digit = ((keys[base + i] >> shift) & (DIGITS as u32 - 1)) as usize;
            counts[digit].fetch_add(1u32);
        }
    }
    sync_cube();
    if unit < DIGITS {
        histogram[unit * blocks + block] = counts[unit].load();
    }
}

#[cube(launch)]
fn digit_scatter_kernel(
    keys_in: &Tensor<u32>,
    values_in: &Tensor<u32>,
    digit_offsets: &Tensor<u32>,
    keys_out: &mut Tensor<u32>,
    values_out: &mut Tensor<u32>,
    shift: u32,
    blocks: usize,
) {
    let block = CUBE_POS;
    if block >= blocks {
        terminate!();
    }
    let unit = UNIT_POS as usize;
    let n = keys_in.len();
    let base = block * SORT_BLOCK + unit * ITEMS_PER_UNIT;
    // counts[digit * BLOCK_UNITS + unit]: this unit's keys with that digit. Scanned digit-major,
    // entry (d, u) becomes the number of the block's keys with a smaller digit, plus those with
    // digit d held by earlier units: the stable rank of unit u's first key with digit d.
    let mut counts = Shared::<[u32]>::new_slice(DIGITS * BLOCK_UNITS);
    #[unroll]
    for d in 0..DIGITS {
        counts[d * BLOCK_UNITS + unit] = 0u32;
    }
    #[unroll]
    for i in 0..ITEMS_PER_UNIT {
        if base + i < n {
            let digit = ((keys_in[base + i] >> shift) & (DIGITS as u32 - 1)) as usize;
            counts[digit * BLOCK_UNITS + unit] += 1u32;
        }
    }
    sync_cube();
    // Unit u scans the DIGITS consecutive entries [u * DIGITS, (u + 1) * DIGITS) serially; the
    // units' totals are scanned across the cube.
    let mut own_total = 0u32;
    #[unroll]
    for j in 0..DIGITS {
        own_total += counts[unit * DIGITS + j];
    }
    let mut totals = Shared::<[u32]>::new_slice(BLOCK_UNITS);
    let mut running = cube_exclusive_scan(&mut totals, own_total);
    #[unroll]
    for j in 0..DIGITS {
        let c = counts[unit * DIGITS + j];
        counts[unit * DIGITS + j] = running;
        running += c;
    }
    sync_cube();
    #[unroll]
    for i in 0..ITEMS_PER_UNIT {
        if base + i < n {
            let key = keys_in[base + i];
            let digit = ((key >> shift) & (DIGITS as u32 - 1)) as usize;
            // Earlier keys of this unit with the same digit.
            let mut before = 0u32;
            #[unroll]
            for j in 0..i {
                if ((keys_in[base + j] >> shift) & (DIGITS as u32 - 1)) as usize == digit {
                    before += 1u32;
                }
            }
            let rank = counts[digit * BLOCK_UNITS + unit] - counts[digit * BLOCK_UNITS] + before;
            let dest = (digit_offsets[digit * blocks + block] + rank) as usize;
            keys_out[dest] = key;
            values_out[dest] = values_in[base + i];
        }
    }
}

/// Sorts `values` by `keys` (both u32, same length ≥ 1), stably, looking only at the low
/// `key_bits` bits of each key (higher bits must be zero). Returns (sorted keys, values).
pub fn sort_pairs(keys: CubeTensor, values: CubeTensor, key_bits: u32) -> (CubeTensor, CubeTensor) {
    let n = keys.meta.num_elements();
    assert_eq!(n, values.meta.num_elements(), "sort_pairs: keys and values differ in length");
    assert!(key_bits <= 32);
    let client = keys.client.clone();
    let blocks = n.div_ceil(SORT_BLOCK);
    debug_assert_eq!(SORT_BLOCK, SCAN_BLOCK);
    let (mut keys, mut values) = (keys, values);
    let passes = key_bits.div_ceil(RADIX_BITS);
    let (mut keys_spare, mut values_spare) = if passes > 0 {
        (fresh_u32(&keys, &[n]), fresh_u32(&keys, &[n]))
    } else {
        (keys.clone(), values.clone())
    };
    let histogram = fresh_u32(&keys, &[DIGITS * blocks]);
    let cube_dim = CubeDim::new_1d(BLOCK_UNITS as u32);
    for pass in 0..passes {
        let shift = pass * RADIX_BITS;
        digit_histogram_kernel::launch(
            &client,
            spread(&client, blocks),
            cube_dim,
            keys.clone().into_tensor_arg(),
            histogram.clone().into_tensor_arg(),
            shift,
            blocks,
        );
        let (digit_offsets, _) = exclusive_scan(&histogram);
        digit_scatter_kernel::launch(
            &client,
            spread(&client, blocks),
            cube_dim,
            keys.clone().into_tensor_arg(),
            values.clone().into_tensor_arg(),
            digit_offsets.into_tensor_arg(),
            keys_spare.clone().into_tensor_arg(),
            values_spare.clone().into_tensor_arg(),
            shift,
            blocks,
        );
        std::mem::swap(&mut keys, &mut keys_spare);
        std::mem::swap(&mut values, &mut values_spare);
    }
    (keys, values)
}
