//! Per-tile alpha compositing on the device, forward and backward: one cube per 16×16 tile, one
//! unit per pixel, the tile's Gaussians streamed through shared memory in batches of 256. The
//! per-pixel arithmetic is the CPU twin's (`cpu::composite`).
//!
//! Forward: front to back; a pixel stops before the Gaussian that would bring its transmittance
//! to ≤ 1e-4, and the cube stops loading batches once every pixel of the tile has stopped.
//! Backward: back to front from each pixel's last contributor, walking the transmittance back;
//! each (pixel, Gaussian) pair adds its share to the Gaussian's splat gradient with a float
//! atomic add, or with a compare-and-swap loop on the bits where the device has no float atomics.
//! Where the device has subgroup arithmetic the pairs' shares are first summed over each subgroup
//! (every unit of a tile walks the same Gaussian at the same step), one atomic per subgroup.

use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use super::buffers::{fresh_f32, fresh_u32, zeros_f32};
use super::DeviceGaussians;
use super::atomics::accumulate;
use super::project::SPLAT_GRAD_COLUMNS;
use super::scan::spread;
use crate::conventions::{
    ALPHA_MAX, ALPHA_MIN, PROJECTED_COLUMNS, TILE_SIZE, TRANSMITTANCE_STOP, projected_column as col,
};

const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;
/// Gaussians per shared-memory batch: one per unit.
const BATCH: usize = TILE_PIXELS;

/// Image geometry and background, passed by value to the kernels.
#[derive(CubeLaunch, CubeType, Clone, Copy)]
pub struct TileGrid {
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles: u32,
    background_r: f32,
    background_g: f32,
    background_b: f32,
}

/// One batch of splats in shared memory, one column per quantity.
#[derive(CubeType)]
struct SharedSplats {
    mean_x: Shared<[f32]>,
    mean_y: Shared<[f32]>,
    conic_a: Shared<[f32]>,
    conic_b: Shared<[f32]>,
    conic_c: Shared<[f32]>,
    opacity: Shared<[f32]>,
    color_r: Shared<[f32]>,
    color_g: Shared<[f32]>,
    color_b: Shared<[f32]>,
    gaussian: Shared<[u32]>,
}

#[cube]
fn shared_splats() -> SharedSplats {
    SharedSplats {
        mean_x: Shared::<[f32]>::new_slice(BATCH),
        mean_y: Shared::<[f32]>::new_slice(BATCH),
        conic_a: Shared::<[f32]>::new_slice(BATCH),
        conic_b: Shared::<[f32]>::new_slice(BATCH),
        conic_c: Shared::<[f32]>::new_slice(BATCH),
        opacity: Shared::<[f32]>::new_slice(BATCH),
        color_r: Shared::<[f32]>::new_slice(BATCH),
        color_g: Shared::<[f32]>::new_slice(BATCH),
        color_b: Shared::<[f32]>::new_slice(BATCH),
        gaussian: Shared::<[u32]>::new_slice(BATCH),
    }
}

/// Loads Gaussian `g` into batch slot `slot`.
#[cube]
fn load_splat(
    splats: &mut SharedSplats,
    slot: usize,
    g: u32,
    projected: &Tensor<f32>,
    opacities: &Tensor<f32>,
    gates: &Tensor<f32>,
    colors: &Tensor<f32>,
) {
    let gi = g as usize;
    let row = gi * PROJECTED_COLUMNS;
    splats.mean_x[slot] = projected[row + col::MEAN2D_X];
    splats.mean_y[slot] = projected[row + col::MEAN2D_Y];
    splats.conic_a[slot] = projected[row + col::CONIC_A];
    splats.conic_b[slot] = projected[row + col::CONIC_B];
    splats.conic_c[slot] = projected[row + col::CONIC_C];
    splats.opacity[slot] = gates[gi] * opacities[gi];
    splats.color_r[slot] = colors[gi * 3];
    splats.color_g[slot] = colors[gi * 3 + 1];
    splats.color_b[slot] = colors[gi * 3 + 2];
    splats.gaussian[slot] = g;
}

/// The tile's intersection range, read through shared memory so the cube sees it as uniform
/// (its loop bounds hold barriers).
#[cube]
fn uniform_tile_range(tile_offsets: &Tensor<u32>, tile: usize) -> (u32, u32) {
    let mut range = Shared::<[u32]>::new_slice(2usize);
    if UNIT_POS == 0 {
        range[0] = tile_offsets[tile];
        range[1] = tile_offsets[tile + 1];
    }
    let start = workgroup_uniform_load(&range[0]);
    let end = workgroup_uniform_load(&range[1]);
    (start, end)
}

#[cube(launch)]
fn rasterize_forward_kernel(
    projected: &Tensor<f32>,
    opacities: &Tensor<f32>,
    gates: &Tensor<f32>,
    colors: &Tensor<f32>,
    tile_offsets: &Tensor<u32>,
    gaussian_from_intersection: &Tensor<u32>,
    image_alpha: &mut Tensor<f32>,
    final_transmittance: &mut Tensor<f32>,
    n_contrib: &mut Tensor<u32>,
    grid: TileGrid,
) {
    let tile = CUBE_POS;
    if tile >= grid.tiles as usize {
        terminate!();
    }
    let unit = UNIT_POS as usize;
    let tx = tile as u32 % grid.tiles_x;
    let ty = tile as u32 / grid.tiles_x;
    let px = tx * TILE_SIZE + unit as u32 % TILE_SIZE;
    let py = ty * TILE_SIZE + unit as u32 / TILE_SIZE;
    let inside = px < grid.width && py < grid.height;
    let (cx, cy) = (px as f32 + 0.5, py as f32 + 0.5);

    let done_count = Shared::<[Atomic<u32>]>::new_slice(1usize);
    if unit == 0 {
        done_count[0].store(0u32);
    }
    sync_cube();
    let mut done = !inside;
    if done {
        done_count[0].fetch_add(1u32);
    }
    let (start, end) = uniform_tile_range(tile_offsets, tile);
    let mut splats = shared_splats();
    let mut t = 1.0f32;
    let mut r = 0.0f32;
    let mut g = 0.0f32;
    let mut b = 0.0f32;
    let mut last = 0u32;
    let batches = (end - start).div_ceil(BATCH as u32);
    for batch in 0..batches {
        // Barrier + uniform read: the whole cube leaves once every pixel has stopped.
        if workgroup_uniform_load_atomic(&done_count[0]) == TILE_PIXELS as u32 {
            break;
        }
        let first = start + batch * BATCH as u32;
        let k = first + unit as u32;
        if k < end {
            load_splat(
                &mut splats,
                unit,
                gaussian_from_intersection[k as usize],
                projected,
                opacities,
                gates,
                colors,
            );
        }
        sync_cube();
        let count = u32::min(BATCH as u32, end - first);
        if !done {
            for j in 0..count {
                let jj = j as usize;
                let dx = splats.mean_x[jj] - cx;
                let dy = splats.mean_y[jj] - cy;
                let sigma = 0.5 * (splats.conic_a[jj] * dx * dx + splats.conic_c[jj] * dy * dy)
                    + splats.conic_b[jj] * dx * dy;
                let alpha = f32::min(ALPHA_MAX, splats.opacity[jj] * f32::exp(-sigma));
                if sigma >= 0.0 && alpha >= ALPHA_MIN {
                    let next_t = t * (1.0 - alpha);
                    if next_t <= TRANSMITTANCE_STOP {
                        done = true;
                        done_count[0].fetch_add(1u32);
                        break;
                    }
                    let weight = alpha * t;
                    r += splats.color_r[jj] * weight;
                    g += splats.color_g[jj] * weight;
                    b += splats.color_b[jj] * weight;
                    t = next_t;
                    last = batch * BATCH as u32 + j + 1;
                }
            }
        }
        sync_cube();
    }
    if inside {
        let p = (py * grid.width + px) as usize;
        image_alpha[p * 4] = r + t * grid.background_r;
        image_alpha[p * 4 + 1] = g + t * grid.background_g;
        image_alpha[p * 4 + 2] = b + t * grid.background_b;
        image_alpha[p * 4 + 3] = 1.0 - t;
        final_transmittance[p] = t;
        n_contrib[p] = last;
    }
}

/// The largest of one u32 per unit over the cube, uniform.
#[cube]
fn cube_max(value: u32) -> u32 {
    let unit = UNIT_POS as usize;
    let mut shared = Shared::<[u32]>::new_slice(TILE_PIXELS);
    shared[unit] = value;
    sync_cube();
    #[unroll]
    for step in 0..8usize {
        let stride = comptime![(TILE_PIXELS >> 1) >> step];
        if unit < stride {
            shared[unit] = u32::max(shared[unit], shared[unit + stride]);
        }
        sync_cube();
    }
    workgroup_uniform_load(&shared[0])
}

#[cube(launch)]
fn rasterize_backward_kernel(
    projected: &Tensor<f32>,
    opacities: &Tensor<f32>,
    gates: &Tensor<f32>,
    colors: &Tensor<f32>,
    tile_offsets: &Tensor<u32>,
    gaussian_from_intersection: &Tensor<u32>,
    final_transmittance: &Tensor<f32>,
    n_contrib: &Tensor<u32>,
    grad_image_alpha: &Tensor<f32>,
    splat_grads: &mut Tensor<Atomic<f32>>,
    splat_grad_bits: &mut Tensor<Atomic<u32>>,
    grid: TileGrid,
    #[comptime] native_float_atomics: bool,
    #[comptime] subgroup_sums: bool,
) {
    let tile = CUBE_POS;
    if tile >= grid.tiles as usize {
        terminate!();
    }
    let unit = UNIT_POS as usize;
    let tx = tile as u32 % grid.tiles_x;
    let ty = tile as u32 / grid.tiles_x;
    let px = tx * TILE_SIZE + unit as u32 % TILE_SIZE;
    let py = ty * TILE_SIZE + unit as u32 / TILE_SIZE;
    let inside = px < grid.width && py < grid.height;
    let (cx, cy) = (px as f32 + 0.5, py as f32 + 0.5);
    let p = (py * grid.width + px) as usize;

    let mut contrib = 0u32;
    let mut t = 0.0f32;
    let mut t_final = 0.0f32;
    let mut vr = 0.0f32;
    let mut vg = 0.0f32;
    let mut vb = 0.0f32;
    let mut v_final = 0.0f32;
    if inside {
        contrib = n_contrib[p];
        t = final_transmittance[p];
        t_final = t;
        vr = grad_image_alpha[p * 4];
        vg = grad_image_alpha[p * 4 + 1];
        vb = grad_image_alpha[p * 4 + 2];
        // dLoss/dT_final's coefficient: the alpha gradient minus the background's share.
        v_final = grad_image_alpha[p * 4 + 3]
            - (grid.background_r * vr + grid.background_g * vg + grid.background_b * vb);
    }
    // Colour composited behind the current Gaussian.
    let mut behind_r = 0.0f32;
    let mut behind_g = 0.0f32;
    let mut behind_b = 0.0f32;

    let (start, _) = uniform_tile_range(tile_offsets, tile);
    let deepest = cube_max(contrib);
    let mut splats = shared_splats();
    let batches = deepest.div_ceil(BATCH as u32);
    for batch in 0..batches {
        // List positions [lo, hi) of this batch, from the back.
        let hi = deepest - batch * BATCH as u32;
        let lo = select(hi > BATCH as u32, hi - BATCH as u32, 0u32);
        let k = lo + unit as u32;
        if k < hi {
            load_splat(
                &mut splats,
                unit,
                gaussian_from_intersection[(start + k) as usize],
                projected,
                opacities,
                gates,
                colors,
            );
        }
        sync_cube();
        let count = hi - lo;
        for step in 0..count {
            let jj = (count - 1 - step) as usize;
            let position = lo + jj as u32;
            // This unit's share of the Gaussian's splat gradient (zero where it adds none).
            let mut contributes = false;
            let mut unclamped = false;
            let mut grad_mean_x = 0.0f32;
            let mut grad_mean_y = 0.0f32;
            let mut grad_conic_a = 0.0f32;
            let mut grad_conic_b = 0.0f32;
            let mut grad_conic_c = 0.0f32;
            let mut grad_opacity = 0.0f32;
            let mut grad_r = 0.0f32;
            let mut grad_g = 0.0f32;
            let mut grad_b = 0.0f32;
            if inside && position < contrib {
                let dx = splats.mean_x[jj] - cx;
                let dy = splats.mean_y[jj] - cy;
                let (ca, cb, cc) = (splats.conic_a[jj], splats.conic_b[jj], splats.conic_c[jj]);
                let sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
                let opacity = splats.opacity[jj];
                let raw = opacity * f32::exp(-sigma);
                let alpha = f32::min(ALPHA_MAX, raw);
                if sigma >= 0.0 && alpha >= ALPHA_MIN {
                    let one_minus = 1.0 - alpha;
                    t = t / one_minus; // transmittance in front of this Gaussian
                    let inv_one_minus = 1.0 / one_minus;
                    let weight = alpha * t;
                    let (sr, sg, sb) = (splats.color_r[jj], splats.color_g[jj], splats.color_b[jj]);
                    let mut v_alpha = (sr * t - behind_r * inv_one_minus) * vr
                        + (sg * t - behind_g * inv_one_minus) * vg
                        + (sb * t - behind_b * inv_one_minus) * vb;
                    v_alpha += t_final * inv_one_minus * v_final;
                    behind_r += sr * weight;
                    behind_g += sg * weight;
                    behind_b += sb * weight;
                    grad_r = weight * vr;
                    grad_g = weight * vg;
                    grad_b = weight * vb;
                    // The 0.999 clamp is a constant: no gradient to opacity or sigma there.
                    if raw <= ALPHA_MAX {
                        let v_sigma = -raw * v_alpha;
                        grad_mean_x = v_sigma * (ca * dx + cb * dy);
                        grad_mean_y = v_sigma * (cb * dx + cc * dy);
                        grad_conic_a = 0.5 * dx * dx * v_sigma;
                        grad_conic_b = dx * dy * v_sigma;
                        grad_conic_c = 0.5 * dy * dy * v_sigma;
                        grad_opacity = raw / opacity * v_alpha;
                        unclamped = true;
                    }
                    contributes = true;
                }
            }
            // `step` and `count` are uniform over the cube, so every unit of a subgroup reaches
            // this point together and the subgroup operations see all of them.
            let base = splats.gaussian[jj] as usize * SPLAT_GRAD_COLUMNS;
            if subgroup_sums {
                if plane_any(contributes) {
                    let sum_mean_x = plane_sum(grad_mean_x);
                    let sum_mean_y = plane_sum(grad_mean_y);
                    let sum_conic_a = plane_sum(grad_conic_a);
                    let sum_conic_b = plane_sum(grad_conic_b);
                    let sum_conic_c = plane_sum(grad_conic_c);
                    let sum_opacity = plane_sum(grad_opacity);
                    let sum_r = plane_sum(grad_r);
                    let sum_g = plane_sum(grad_g);
                    let sum_b = plane_sum(grad_b);
                    if UNIT_POS_PLANE == 0 {
                        accumulate(splat_grads, splat_grad_bits, base, sum_mean_x, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 1, sum_mean_y, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 2, sum_conic_a, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 3, sum_conic_b, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 4, sum_conic_c, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 5, sum_opacity, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 6, sum_r, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 7, sum_g, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 8, sum_b, native_float_atomics);
                    }
                }
            } else {
                if contributes {
                    accumulate(splat_grads, splat_grad_bits, base + 6, grad_r, native_float_atomics);
                    accumulate(splat_grads, splat_grad_bits, base + 7, grad_g, native_float_atomics);
                    accumulate(splat_grads, splat_grad_bits, base + 8, grad_b, native_float_atomics);
                    if unclamped {
                        accumulate(splat_grads, splat_grad_bits, base, grad_mean_x, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 1, grad_mean_y, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 2, grad_conic_a, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 3, grad_conic_b, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 4, grad_conic_c, native_float_atomics);
                        accumulate(splat_grads, splat_grad_bits, base + 5, grad_opacity, native_float_atomics);
                    }
                }
            }
        }
        sync_cube();
    }
}

/// Forward outputs of compositing.
pub struct DeviceComposite {
    /// [H, W, 4] f32.
    pub image_alpha: CubeTensor,
    /// [H, W] f32.
    pub final_transmittance: CubeTensor,
    /// [H, W] u32.
    pub n_contrib: CubeTensor,
}

fn grid(camera: &crate::RasterCamera, background: [f32; 3]) -> TileGridLaunch {
    TileGridLaunch::new(
        camera.width,
        camera.height,
        camera.tiles_x(),
        camera.tiles_x() * camera.tiles_y(),
        background[0],
        background[1],
        background[2],
    )
}

fn tile_launch(client: &cubecl::client::Client, camera: &crate::RasterCamera) -> (CubeCount, CubeDim) {
    let tiles = (camera.tiles_x() * camera.tiles_y()) as usize;
    (spread(client, tiles), CubeDim::new_1d(TILE_PIXELS as u32))
}

pub fn composite_forward(
    gaussians: &DeviceGaussians,
    projected: &CubeTensor,
    tile_offsets: &CubeTensor,
    gaussian_from_intersection: &CubeTensor,
    camera: &crate::RasterCamera,
    background: [f32; 3],
) -> DeviceComposite {
    let (h, w) = (camera.height as usize, camera.width as usize);
    let like = &gaussians.means;
    let out = DeviceComposite {
        image_alpha: fresh_f32(like, vec![h, w, 4]),
        final_transmittance: fresh_f32(like, vec![h, w]),
        n_contrib: fresh_u32(like, &[h, w]),
    };
    let client = like.client.clone();
    let (count, dim) = tile_launch(&client, camera);
    // An empty intersection list still needs a bound buffer.
    let gaussian_from_intersection = non_empty(gaussian_from_intersection);
    rasterize_forward_kernel::launch(
        &client,
        count,
        dim,
        projected.clone().into_tensor_arg(),
        gaussians.opacities.clone().into_tensor_arg(),
        gaussians.gates.clone().into_tensor_arg(),
        gaussians.colors.clone().into_tensor_arg(),
        tile_offsets.clone().into_tensor_arg(),
        gaussian_from_intersection.into_tensor_arg(),
        out.image_alpha.clone().into_tensor_arg(),
        out.final_transmittance.clone().into_tensor_arg(),
        out.n_contrib.clone().into_tensor_arg(),
        grid(camera, background),
    );
    out
}

/// `t`, or a one-element stand-in when it is empty (kernels never read it then).
fn non_empty(t: &CubeTensor) -> CubeTensor {
    if t.meta.num_elements() > 0 {
        t.clone()
    } else {
        fresh_u32(t, &[1])
    }
}

/// The per-Gaussian splat gradients [N, 9] (see `SPLAT_GRAD_COLUMNS`) of compositing.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    gaussians: &DeviceGaussians,
    projected: &CubeTensor,
    tile_offsets: &CubeTensor,
    gaussian_from_intersection: &CubeTensor,
    final_transmittance: &CubeTensor,
    n_contrib: &CubeTensor,
    grad_image_alpha: &CubeTensor,
    camera: &crate::RasterCamera,
    background: [f32; 3],
) -> CubeTensor {
    let n = gaussians.len();
    let like = &gaussians.means;
    let splat_grads = zeros_f32(like, vec![n, SPLAT_GRAD_COLUMNS]);
    let client = like.client.clone();
    let native = super::atomics::native_float_add(&client);
    let subgroup_sums =
        super::atomics::gradient_accumulation(&client) == super::atomics::GradientAccumulation::SubgroupSum;
    // The accumulator is bound once, as f32 or as u32 bits; the other binding gets a stand-in
    // (one buffer may not be bound twice for writing).
    let stand_in = fresh_f32(like, vec![1]);
    let (as_float, as_bits) = if native {
        (splat_grads.clone(), stand_in)
    } else {
        (stand_in, splat_grads.clone())
    };
    let (count, dim) = tile_launch(&client, camera);
    rasterize_backward_kernel::launch(
        &client,
        count,
        dim,
        projected.clone().into_tensor_arg(),
        gaussians.opacities.clone().into_tensor_arg(),
        gaussians.gates.clone().into_tensor_arg(),
        gaussians.colors.clone().into_tensor_arg(),
        tile_offsets.clone().into_tensor_arg(),
        non_empty(gaussian_from_intersection).into_tensor_arg(),
        final_transmittance.clone().into_tensor_arg(),
        n_contrib.clone().into_tensor_arg(),
        grad_image_alpha.clone().into_tensor_arg(),
        as_float.into_tensor_arg(),
        as_bits.into_tensor_arg(),
        grid(camera, background),
        native,
        subgroup_sums,
    );
    splat_grads
}
