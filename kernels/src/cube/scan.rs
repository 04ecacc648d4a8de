//! Exclusive prefix sum of u32 values on the device: blocks of 1024 values scanned in shared
//! memory, the block totals scanned recursively and added back. Tile counts → intersection
//! offsets, and the radix sort's digit histograms → scatter offsets.

use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use cubecl::server::CubeCountSelection;

use super::buffers::fresh_u32;

/// Units per cube of the block kernels.
pub(crate) const BLOCK_UNITS: usize = 256;
/// Values each unit owns (contiguous), so a cube scans `SCAN_BLOCK` values.
const ITEMS_PER_UNIT: usize = 4;
pub(crate) const SCAN_BLOCK: usize = BLOCK_UNITS * ITEMS_PER_UNIT;

/// Exclusive scan of one value per unit over the cube (`BLOCK_UNITS` units), Hillis-Steele in
/// shared memory. Every unit of the cube must call it (it holds barriers). Returns the unit's
/// exclusive prefix; `shared[BLOCK_UNITS - 1]` holds the cube's total afterwards.
#[cube]
pub(crate) fn cube_exclusive_scan(shared: &mut Shared<[u32]>, value: u32) -> u32 {
    let unit = UNIT_POS as usize;
    shared[unit] = value;
    sync_cube();
    #[unroll]
    for step in 0..8usize {
        // 2^8 = BLOCK_UNITS.
        let offset = comptime![1usize << step];
        let mut add = 0u32;
        if unit >= offset {
            add = shared[unit - offset];
        }
        sync_cube();
        shared[unit] += add;
        sync_cube();
    }
    shared[unit] - value
}

#[cube(launch)]
fn scan_blocks_kernel(
    input: &Tensor<u32>,
    output: &mut Tensor<u32>,
    block_totals: &mut Tensor<u32>,
    blocks: usize,
) {
    let block = CUBE_POS;
    // Uniform per cube: whole surplus cubes of a spread dispatch leave together.
    if block >= blocks {
        terminate!();
    }
    let n = input.len();
    let base = block * SCAN_BLOCK + UNIT_POS as usize * ITEMS_PER_UNIT;
    let mut sum = 0u32;
    #[unroll]
    for i in 0..ITEMS_PER_UNIT {
        if base + i < n {
            sum += input[base + i];
        }
    }
    let mut shared = Shared::<[u32]>::new_slice(BLOCK_UNITS);
    let mut running = cube_exclusive_scan(&mut shared, sum);
    #[unroll]
    for i in 0..ITEMS_PER_UNIT {
        if base + i < n {
            let v = input[base + i];
            output[base + i] = running;
            running += v;
        }
    }
    if UNIT_POS as usize == BLOCK_UNITS - 1 {
        block_totals[block] = shared[BLOCK_UNITS - 1];
    }
}

#[cube(launch)]
fn add_block_offsets_kernel(values: &mut Tensor<u32>, block_offsets: &Tensor<u32>) {
    let i = ABSOLUTE_POS;
    if i >= values.len() {
        terminate!();
    }
    values[i] += block_offsets[i / SCAN_BLOCK];
}

/// The cube count for `cubes` cubes, spread over dimensions when it exceeds one dimension's limit.
pub(crate) fn spread(client: &cubecl::client::Client, cubes: usize) -> CubeCount {
    CubeCountSelection::new(client, cubes as u32).cube_count()
}

/// Exclusive prefix sum of `values` (u32, [n], n ≥ 1) and the total ([1]). Sums wrap at 2^32;
/// callers bound their totals.
pub fn exclusive_scan(values: &CubeTensor) -> (CubeTensor, CubeTensor) {
    let n = values.meta.num_elements();
    assert!(n > 0, "exclusive_scan of an empty buffer");
    let client = values.client.clone();
    let blocks = n.div_ceil(SCAN_BLOCK);
    let output = fresh_u32(values, &[n]);
    let block_totals = fresh_u32(values, &[blocks]);
    scan_blocks_kernel::launch(
        &client,
        spread(&client, blocks),
        CubeDim::new_1d(BLOCK_UNITS as u32),
        values.clone().into_tensor_arg(),
        output.clone().into_tensor_arg(),
        block_totals.clone().into_tensor_arg(),
        blocks,
    );
    if blocks == 1 {
        return (output, block_totals);
    }
    let (block_offsets, total) = exclusive_scan(&block_totals);
    let cube_dim = CubeDim::new_1d(BLOCK_UNITS as u32);
    add_block_offsets_kernel::launch(
        &client,
        cubecl::calculate_cube_count_elemwise(&client, n, cube_dim),
        cube_dim,
        output.clone().into_tensor_arg(),
        block_offsets.into_tensor_arg(),
    );
    (output, total)
}
