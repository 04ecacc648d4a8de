//! Per-pixel alpha compositing over tiles: forward, and its backward without per-pixel lists.
//!
//! Each tile row (16 image rows) is one parallel work item: its pixels, its per-pixel state and its
//! intersections are contiguous, so threads write disjoint slices and results are deterministic.
//!
//! Inside a tile, pixels are processed in groups of [`LANES`] along a row. A group walks the
//! tile's Gaussians front to back (back to front in the backward) with its per-pixel state held in
//! registers, skipping the Gaussians whose opacity-aware screen box misses it (outside the box
//! alpha is below 1/255 by construction) and stopping once all its pixels are saturated. Every
//! branch inside a group is a select, so the compiler turns a group into vector instructions
//! (8-wide with AVX2, chosen at run time; the same IEEE operations in the same order on every
//! path, so the paths agree bit for bit). Every pixel sees its Gaussians in depth order with the
//! same arithmetic, so the forward equals a dense per-pixel loop bit for bit (a test checks this).
//! `exp` is [`exp_f32`], a branch-free polynomial that vectorises, where the C library's `expf`
//! is a call per pixel.

use rayon::prelude::*;

use super::bin::TileBins;
use crate::conventions::{ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_STOP};

const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;
const TILE_SIDE: usize = TILE_SIZE as usize;
/// Pixels of a tile row processed together.
pub const LANES: usize = 8;
const LANE_OFFSET: [f32; LANES] = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];

/// `e^x` in f32 to about 1 ulp (Cephes' `expf`: x = n ln 2 + r with ln 2 split in two constants,
/// a degree-6 polynomial in r, then 2^n built in the exponent bits). Branch-free and built from
/// adds, multiplies and integer shifts only, so it vectorises and rounds identically on every CPU.
/// `x` is clamped to [-87, 88], where the result is a finite normal number: compositing evaluates
/// it on e^-sigma with sigma in [0, ln 255] for every pair it keeps.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer without a `round` call.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + ROUND;
    let n = shifted - ROUND;
    // n as an integer, read from the mantissa bits of `shifted` (an `as i32` cast saturates and
    // checks for NaN, which compiles to scalar code).
    let n_int = shifted.to_bits().wrapping_sub(ROUND.to_bits()) as i32;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let z = r * r;
    let mut p = 1.987_569_1e-4f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 5.000_000_1e-1;
    let y = (p * z + r) + 1.0;
    y * f32::from_bits((n_int.wrapping_add(127) << 23) as u32)
}

/// What compositing needs of one Gaussian, gathered per tile for locality.
#[derive(Clone, Copy, Debug, Default)]
pub struct Splat {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub color: [f32; 3],
    /// Opacity-aware half extents of the screen box (pixels).
    pub radius: [f32; 2],
}

/// The exponent of a (pixel, Gaussian) pair at offset (dx, dy) = mean2d - pixel centre, in the
/// order every implementation (the dense test reference included) evaluates it.
#[inline(always)]
fn sigma(conic: [f32; 3], dx: f32, dy: f32) -> f32 {
    let [a, b, c] = conic;
    0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
}

/// A splat with what compositing derives from it once per Gaussian: `ln(255 * opacity)` (sigma
/// above it means alpha < 1/255, which lets far pairs fail the test without the `exp`; a margin
/// keeps the shortcut from deciding a pair the exact test would keep) and its pixel box.
#[derive(Clone, Copy, Default)]
struct PreparedSplat {
    splat: Splat,
    sigma_cut: f32,
    /// Image pixel columns [x0, x1) and rows [y0, y1) whose centres lie within `radius` of the
    /// mean, widened by one pixel against rounding at the edge (saturating far off screen).
    pixel_box: [i32; 4],
}

const SIGMA_CUT_MARGIN: f32 = 1e-3;

impl PreparedSplat {
    fn new(splat: Splat) -> Self {
        let axis = |mean: f32, radius: f32| {
            (
                ((mean - radius - 0.5).floor() as i32).saturating_sub(1),
                ((mean + radius - 0.5).ceil() as i32).saturating_add(2),
            )
        };
        let (x0, x1) = axis(splat.mean2d[0], splat.radius[0]);
        let (y0, y1) = axis(splat.mean2d[1], splat.radius[1]);
        Self {
            splat,
            sigma_cut: (splat.opacity / ALPHA_MIN).ln() + SIGMA_CUT_MARGIN,
            pixel_box: [x0, x1, y0, y1],
        }
    }
}

/// [`PreparedSplat`] for every splat that a tile lists (the others are never read).
fn prepare(splats: &[Splat], bins: &TileBins) -> Vec<PreparedSplat> {
    let mut listed = vec![false; splats.len()];
    for &g in &bins.gaussian_from_intersection {
        listed[g as usize] = true;
    }
    splats
        .par_iter()
        .zip(listed.par_iter())
        .map(|(s, &listed)| {
            if listed {
                PreparedSplat::new(*s)
            } else {
                PreparedSplat::default()
            }
        })
        .collect()
}

/// A listed splat with its box clipped to one tile.
#[derive(Clone, Copy)]
struct TileSplat {
    splat: Splat,
    sigma_cut: f32,
    /// Tile-local pixel columns [x0, x1) the splat can reach.
    cols: [i32; 2],
    /// Tile-local pixel rows [y0, y1) the splat can reach.
    rows: [u32; 2],
    /// Lane groups of a row [first, last) that overlap `cols`.
    groups: [u32; 2],
}

const GROUPS_PER_ROW: usize = TILE_SIDE / LANES;

/// For each lane group of a tile (row-major), the list positions of the splats whose box reaches
/// it, ascending: a group walks only those, without a data-dependent branch per splat.
struct GroupLists {
    lists: Vec<Vec<u32>>,
}

impl GroupLists {
    fn new() -> Self {
        Self {
            lists: (0..TILE_PIXELS / LANES).map(|_| Vec::new()).collect(),
        }
    }

    fn fill(&mut self, local: &[TileSplat]) {
        for list in &mut self.lists {
            list.clear();
        }
        for (k, s) in local.iter().enumerate() {
            for ly in s.rows[0]..s.rows[1] {
                for group in s.groups[0]..s.groups[1] {
                    self.lists[ly as usize * GROUPS_PER_ROW + group as usize].push(k as u32);
                }
            }
        }
    }

    fn of(&self, ly: usize, group: usize) -> &[u32] {
        &self.lists[ly * GROUPS_PER_ROW + group]
    }
}

/// The tile at (tx, ty): its pixel origin and size.
struct TileGeometry {
    x0: u32,
    y0: u32,
    w: usize,
    h: usize,
}

impl TileGeometry {
    fn new(tx: u32, ty: u32, width: u32, height: u32) -> Self {
        let (x0, y0) = (tx * TILE_SIZE, ty * TILE_SIZE);
        Self {
            x0,
            y0,
            w: ((x0 + TILE_SIZE).min(width) - x0) as usize,
            h: ((y0 + TILE_SIZE).min(height) - y0) as usize,
        }
    }

    /// Lane groups per row.
    fn groups(&self) -> usize {
        self.w.div_ceil(LANES)
    }

    /// Centre of tile-local row `ly`. Integer pixel coordinates are exact in f32, so this and
    /// [`Self::group_origin`] + lane offset + 0.5 equal `(x0 + lx) as f32 + 0.5` for every pixel.
    fn row_centre(&self, ly: usize) -> f32 {
        (self.y0 as usize + ly) as f32 + 0.5
    }

    /// x of the first pixel of lane group `group` of a row.
    fn group_origin(&self, group: usize) -> f32 {
        (self.x0 as usize + group * LANES) as f32
    }
}

fn gather(prepared: &[PreparedSplat], ids: &[u32], tile: &TileGeometry) -> Vec<TileSplat> {
    let clip = |lo: i32, hi: i32, origin: u32, len: usize| {
        let local = |v: i32| v.saturating_sub(origin as i32).clamp(0, len as i32);
        (local(lo), local(hi))
    };
    ids.iter()
        .map(|&g| {
            let p = &prepared[g as usize];
            let [bx0, bx1, by0, by1] = p.pixel_box;
            let (x0, x1) = clip(bx0, bx1, tile.x0, tile.w);
            let (y0, y1) = clip(by0, by1, tile.y0, tile.h);
            TileSplat {
                splat: p.splat,
                sigma_cut: p.sigma_cut,
                cols: [x0, x1],
                rows: [y0 as u32, y1 as u32],
                groups: [x0 as u32 / LANES as u32, (x1 as u32).div_ceil(LANES as u32)],
            }
        })
        .collect()
}

/// A fixed-size window of a per-pixel array: one lane group.
#[inline(always)]
fn lanes<T>(values: &mut [T; TILE_PIXELS], first: usize) -> &mut [T; LANES] {
    (&mut values[first..first + LANES]).try_into().unwrap()
}

static PORTABLE_LANES_ONLY: std::sync::atomic::AtomicBool =
    std::sync::atomic::AtomicBool::new(false);

/// Test hook: run the portable lane code even where AVX2 is available, so tests can check that
/// both paths give the same bits.
#[doc(hidden)]
pub fn force_portable_lanes(on: bool) {
    PORTABLE_LANES_ONLY.store(on, std::sync::atomic::Ordering::Relaxed);
}

/// The lanes the compositing runs on: the CPU's widest, unless the test hook holds it portable
/// (the same detection as the other CPU twins' loops, `host_simd`).
#[cfg(target_arch = "x86_64")]
fn use_avx2() -> bool {
    let lanes = if PORTABLE_LANES_ONLY.load(std::sync::atomic::Ordering::Relaxed) {
        crate::host_simd::Lanes::Portable
    } else {
        crate::host_simd::Lanes::Widest
    };
    lanes.use_avx2()
}

/// Per-pixel results of the forward pass, kept for the backward.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CompositeOutput {
    /// [H, W, 4]: RGB (background included) and alpha = 1 - T_final.
    pub image_alpha: Vec<f32>,
    /// [H, W] transmittance after the last composited Gaussian.
    pub final_transmittance: Vec<f32>,
    /// [H, W] number of entries of the pixel's tile list up to and including the last composited.
    pub n_contrib: Vec<u32>,
}

fn tile_range(bins: &TileBins, tile: usize) -> std::ops::Range<usize> {
    bins.tile_offsets[tile] as usize..bins.tile_offsets[tile + 1] as usize
}

/// Per-pixel results of one tile's forward, structure of arrays (row stride [`TILE_SIDE`]).
struct ForwardTile {
    t: [f32; TILE_PIXELS],
    color: [[f32; TILE_PIXELS]; 3],
    last: [u32; TILE_PIXELS],
}

impl ForwardTile {
    fn new() -> Self {
        Self {
            t: [1.0; TILE_PIXELS],
            color: [[0.0; TILE_PIXELS]; 3],
            last: [0; TILE_PIXELS],
        }
    }
}

/// `[f(0), ..., f(LANES - 1)]` written out: straight-line code with constant indices, which the
/// compiler keeps in registers and turns into one vector operation (a loop over lanes would keep
/// the arrays in memory and update them with masked stores).
#[inline(always)]
fn per_lane<T>(f: impl Fn(usize) -> T) -> [T; LANES] {
    [f(0), f(1), f(2), f(3), f(4), f(5), f(6), f(7)]
}

/// A lane mask: all bits set where `cond` holds. Masks are kept as 32-bit lanes, like the floats
/// they select between (bool arrays would be packed into bytes and unpacked again).
#[inline(always)]
fn lane_mask(cond: bool) -> u32 {
    0u32.wrapping_sub(cond as u32)
}

/// What a splat's test at a lane group needs regardless of the pixels' state: the per-lane
/// offset dx, the row offset dy, sigma, and the mask of lanes inside the splat's box with sigma in
/// [0, cut] (where alpha can reach 1/255). Forward and backward both start from it.
#[inline(always)]
fn splat_reach(
    s: &TileSplat,
    origin: f32,
    py: f32,
    lane0: i32,
) -> ([f32; LANES], f32, [f32; LANES], [u32; LANES]) {
    let Splat {
        mean2d: [mx, my],
        conic,
        ..
    } = s.splat;
    let dy = my - py;
    let dx = per_lane(|i| mx - ((origin + LANE_OFFSET[i]) + 0.5));
    let sigma = per_lane(|i| sigma(conic, dx[i], dy));
    let reach = per_lane(|i| {
        let lx = lane0 + i as i32;
        lane_mask(
            (lx >= s.cols[0]) & (lx < s.cols[1]) & (sigma[i] >= 0.0) & (sigma[i] <= s.sigma_cut),
        )
    });
    (dx, dy, sigma, reach)
}

/// Whether any lane of a mask is set.
#[inline(always)]
fn any_lane(mask: &[u32; LANES]) -> bool {
    mask.iter().fold(0, |any, &m| any | m) != 0
}

/// Composites one lane group (row `ly`, pixels `group * LANES ..`) front to back over the tile's
/// splats, its state in locals, and stores the result.
#[inline(always)]
fn forward_group(
    local: &[TileSplat],
    reaching: &[u32],
    tile: &TileGeometry,
    ly: usize,
    group: usize,
    out: &mut ForwardTile,
) {
    let mut t = [1.0f32; LANES];
    let mut color = [[0.0f32; LANES]; 3];
    let mut last = [0u32; LANES];
    // Lanes past the tile's right edge start saturated: nothing reaches them, and the group may
    // stop once its real pixels are.
    let mut done: [u32; LANES] = per_lane(|i| lane_mask(group * LANES + i >= tile.w));
    let py = tile.row_centre(ly);
    let origin = tile.group_origin(group);
    let lane0 = (group * LANES) as i32;
    for &k in reaching {
        let s = &local[k as usize];
        let Splat {
            opacity,
            color: rgb,
            ..
        } = s.splat;
        let (_, _, sigma, reach) = splat_reach(s, origin, py, lane0);
        let near = per_lane(|i| reach[i] & !done[i]);
        if !any_lane(&near) {
            continue; // no pixel of the group can pass: skip the exp
        }
        let alpha = per_lane(|i| (opacity * exp_f32(-sigma[i])).min(ALPHA_MAX));
        let keep = per_lane(|i| near[i] & lane_mask(alpha[i] >= ALPHA_MIN));
        let next_t = per_lane(|i| t[i] * (1.0 - alpha[i]));
        let stop = per_lane(|i| keep[i] & lane_mask(next_t[i] <= TRANSMITTANCE_STOP));
        let blend = per_lane(|i| keep[i] & !stop[i]);
        let weight = per_lane(|i| alpha[i] * t[i]);
        for c in 0..3 {
            color[c] = per_lane(|i| {
                if blend[i] != 0 {
                    color[c][i] + rgb[c] * weight[i]
                } else {
                    color[c][i]
                }
            });
        }
        t = per_lane(|i| if blend[i] != 0 { next_t[i] } else { t[i] });
        last = per_lane(|i| if blend[i] != 0 { k + 1 } else { last[i] });
        done = per_lane(|i| done[i] | stop[i]);
        if done.iter().fold(u32::MAX, |all, &d| all & d) != 0 {
            break; // every pixel of the group is saturated
        }
    }
    let first = ly * TILE_SIDE + group * LANES;
    *lanes(&mut out.t, first) = t;
    *lanes(&mut out.last, first) = last;
    for c in 0..3 {
        *lanes(&mut out.color[c], first) = color[c];
    }
}

#[inline(always)]
fn forward_tile_body(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    out: &mut ForwardTile,
) {
    for ly in 0..tile.h {
        for group in 0..tile.groups() {
            forward_group(local, lists.of(ly, group), tile, ly, group, out);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn forward_tile_avx2(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    out: &mut ForwardTile,
) {
    forward_tile_body(local, lists, tile, out)
}

fn forward_tile(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    out: &mut ForwardTile,
) {
    #[cfg(target_arch = "x86_64")]
    if use_avx2() {
        // SAFETY: the CPU supports AVX2 (checked by `use_avx2`).
        return unsafe { forward_tile_avx2(local, lists, tile, out) };
    }
    forward_tile_body(local, lists, tile, out)
}

pub fn composite_forward(
    splats: &[Splat],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [f32; 3],
) -> CompositeOutput {
    let (w, h) = (width as usize, height as usize);
    let band = TILE_SIDE * w;
    let mut out = CompositeOutput {
        image_alpha: vec![0.0; h * w * 4],
        final_transmittance: vec![0.0; h * w],
        n_contrib: vec![0; h * w],
    };
    let prepared = prepare(splats, bins);
    out.image_alpha
        .par_chunks_mut(band * 4)
        .zip(out.final_transmittance.par_chunks_mut(band))
        .zip(out.n_contrib.par_chunks_mut(band))
        .enumerate()
        .for_each(|(ty, ((image, transmittance), n_contrib))| {
            let ty = ty as u32;
            let mut state = Box::new(ForwardTile::new());
            let mut lists = GroupLists::new();
            for tx in 0..bins.tiles_x {
                let tile = TileGeometry::new(tx, ty, width, height);
                let local = gather(
                    &prepared,
                    &bins.gaussian_from_intersection
                        [tile_range(bins, (ty * bins.tiles_x + tx) as usize)],
                    &tile,
                );
                lists.fill(&local);
                forward_tile(&local, &lists, &tile, &mut state);
                for ly in 0..tile.h {
                    for lx in 0..tile.w {
                        let p = ly * TILE_SIDE + lx;
                        let o = ly * w + tile.x0 as usize + lx;
                        let t = state.t[p];
                        for c in 0..3 {
                            image[o * 4 + c] = state.color[c][p] + t * background[c];
                        }
                        image[o * 4 + 3] = 1.0 - t;
                        transmittance[o] = t;
                        n_contrib[o] = state.last[p];
                    }
                }
            }
        });
    out
}

/// Gradient of the loss with respect to one intersection's (or one Gaussian's) splat.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SplatGrad {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub color: [f32; 3],
}

impl SplatGrad {
    pub fn add(&mut self, o: &SplatGrad) {
        for i in 0..2 {
            self.mean2d[i] += o.mean2d[i];
        }
        for i in 0..3 {
            self.conic[i] += o.conic[i];
            self.color[i] += o.color[i];
        }
        self.opacity += o.opacity;
    }
}

/// What the backward starts from per pixel (the forward's final values and the image
/// gradient), structure of arrays.
struct BackwardTile {
    t_final: [f32; TILE_PIXELS],
    n_contrib: [u32; TILE_PIXELS],
    v_color: [[f32; TILE_PIXELS]; 3],
    /// dLoss/dT_final's coefficient: v_alpha_out - background . v_color.
    v_final: [f32; TILE_PIXELS],
}

impl BackwardTile {
    fn zeroed() -> Self {
        Self {
            t_final: [0.0; TILE_PIXELS],
            n_contrib: [0; TILE_PIXELS],
            v_color: [[0.0; TILE_PIXELS]; 3],
            v_final: [0.0; TILE_PIXELS],
        }
    }
}

/// Per-lane partial sums of one splat's gradient over the lane groups it reached (in group
/// order); summed over lanes once per splat, so the result does not depend on the code path.
#[derive(Clone, Copy, Default)]
struct LaneGrads {
    mean2d: [[f32; LANES]; 2],
    conic: [[f32; LANES]; 3],
    opacity: [f32; LANES],
    color: [[f32; LANES]; 3],
}

impl LaneGrads {
    fn total(&self) -> SplatGrad {
        let sum = |v: &[f32; LANES]| v.iter().fold(0.0f32, |acc, x| acc + x);
        SplatGrad {
            mean2d: [sum(&self.mean2d[0]), sum(&self.mean2d[1])],
            conic: [
                sum(&self.conic[0]),
                sum(&self.conic[1]),
                sum(&self.conic[2]),
            ],
            opacity: sum(&self.opacity),
            color: [
                sum(&self.color[0]),
                sum(&self.color[1]),
                sum(&self.color[2]),
            ],
        }
    }
}

/// Un-composites one lane group back to front over the splats its pixels composited, its state
/// in locals, adding each splat's per-lane gradient to `grads`.
#[inline(always)]
fn backward_group(
    local: &[TileSplat],
    reaching: &[u32],
    tile: &TileGeometry,
    ly: usize,
    group: usize,
    start: &BackwardTile,
    grads: &mut [LaneGrads],
) {
    let first = ly * TILE_SIDE + group * LANES;
    let window = |values: &[f32; TILE_PIXELS]| -> [f32; LANES] {
        values[first..first + LANES].try_into().unwrap()
    };
    let n_contrib: [u32; LANES] = start.n_contrib[first..first + LANES].try_into().unwrap();
    let t_final = window(&start.t_final);
    let v_final = window(&start.v_final);
    let v_color = [
        window(&start.v_color[0]),
        window(&start.v_color[1]),
        window(&start.v_color[2]),
    ];
    // Transmittance in front of the current Gaussian, and the colour composited behind it
    // (sum over later j of c_j a_j T_j).
    let mut t = t_final;
    let mut behind = [[0.0f32; LANES]; 3];
    let deepest = n_contrib.iter().copied().max().unwrap_or(0) as usize;
    let py = tile.row_centre(ly);
    let origin = tile.group_origin(group);
    let lane0 = (group * LANES) as i32;
    let composited = reaching.partition_point(|&k| (k as usize) < deepest);
    for &k in reaching[..composited].iter().rev() {
        let s = &local[k as usize];
        let Splat {
            conic: [ca, cb, cc],
            opacity,
            color: rgb,
            ..
        } = s.splat;
        let (dx, dy, sigma, reach) = splat_reach(s, origin, py, lane0);
        let near = per_lane(|i| reach[i] & lane_mask(k < n_contrib[i]));
        if !any_lane(&near) {
            continue; // no pixel of the group can pass: skip the exp
        }
        let raw = per_lane(|i| opacity * exp_f32(-sigma[i]));
        let alpha = per_lane(|i| raw[i].min(ALPHA_MAX));
        let keep = per_lane(|i| near[i] & lane_mask(alpha[i] >= ALPHA_MIN));
        if !any_lane(&keep) {
            continue;
        }
        let one_minus = per_lane(|i| 1.0 - alpha[i]);
        let t_front = per_lane(|i| t[i] / one_minus[i]); // transmittance in front of Gaussian k
        let inv_one_minus = per_lane(|i| 1.0 / one_minus[i]);
        let weight = per_lane(|i| alpha[i] * t_front[i]);
        let mut g = LaneGrads::default();
        let mut v_alpha = [0.0f32; LANES];
        for c in 0..3 {
            let v = &v_color[c];
            g.color[c] = per_lane(|i| if keep[i] != 0 { weight[i] * v[i] } else { 0.0 });
            v_alpha = per_lane(|i| {
                v_alpha[i] + (rgb[c] * t_front[i] - behind[c][i] * inv_one_minus[i]) * v[i]
            });
            behind[c] = per_lane(|i| {
                if keep[i] != 0 {
                    behind[c][i] + rgb[c] * weight[i]
                } else {
                    behind[c][i]
                }
            });
        }
        let v_alpha = per_lane(|i| v_alpha[i] + t_final[i] * inv_one_minus[i] * v_final[i]);
        t = per_lane(|i| if keep[i] != 0 { t_front[i] } else { t[i] });
        // The 0.999 clamp is a constant: no gradient to opacity or sigma there.
        let through = per_lane(|i| keep[i] & lane_mask(raw[i] <= ALPHA_MAX));
        let v_sigma = per_lane(|i| -raw[i] * v_alpha[i]);
        let pick = |v: [f32; LANES]| per_lane(|i| if through[i] != 0 { v[i] } else { 0.0 });
        g.opacity = pick(per_lane(|i| raw[i] / opacity * v_alpha[i]));
        g.conic[0] = pick(per_lane(|i| 0.5 * dx[i] * dx[i] * v_sigma[i]));
        g.conic[1] = pick(per_lane(|i| dx[i] * dy * v_sigma[i]));
        g.conic[2] = pick(per_lane(|i| 0.5 * dy * dy * v_sigma[i]));
        g.mean2d[0] = pick(per_lane(|i| v_sigma[i] * (ca * dx[i] + cb * dy)));
        g.mean2d[1] = pick(per_lane(|i| v_sigma[i] * (cb * dx[i] + cc * dy)));
        let acc = &mut grads[k as usize];
        let add = |acc: &mut [f32; LANES], v: &[f32; LANES]| *acc = per_lane(|i| acc[i] + v[i]);
        for c in 0..3 {
            add(&mut acc.color[c], &g.color[c]);
            add(&mut acc.conic[c], &g.conic[c]);
        }
        add(&mut acc.opacity, &g.opacity);
        add(&mut acc.mean2d[0], &g.mean2d[0]);
        add(&mut acc.mean2d[1], &g.mean2d[1]);
    }
}

#[inline(always)]
fn backward_tile_body(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    start: &BackwardTile,
    grads: &mut [LaneGrads],
) {
    for ly in 0..tile.h {
        for group in 0..tile.groups() {
            backward_group(local, lists.of(ly, group), tile, ly, group, start, grads);
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn backward_tile_avx2(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    start: &BackwardTile,
    grads: &mut [LaneGrads],
) {
    backward_tile_body(local, lists, tile, start, grads)
}

fn backward_tile(
    local: &[TileSplat],
    lists: &GroupLists,
    tile: &TileGeometry,
    start: &BackwardTile,
    grads: &mut [LaneGrads],
) {
    #[cfg(target_arch = "x86_64")]
    if use_avx2() {
        // SAFETY: the CPU supports AVX2 (checked by `use_avx2`).
        return unsafe { backward_tile_avx2(local, lists, tile, start, grads) };
    }
    backward_tile_body(local, lists, tile, start, grads)
}

/// Backward of [`composite_forward`]: per-intersection gradients (aligned with
/// `bins.gaussian_from_intersection`), then summed per Gaussian in intersection order, so the
/// result is deterministic and needs no atomics.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    splats: &[Splat],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [f32; 3],
    forward: &CompositeOutput,
    grad_image_alpha: &[f32],
) -> Vec<SplatGrad> {
    let w = width as usize;
    let prepared = prepare(splats, bins);
    let mut per_intersection = vec![SplatGrad::default(); bins.intersection_count()];
    // Split the intersection gradients into one contiguous slice per tile row.
    let mut rows: Vec<(u32, &mut [SplatGrad])> = Vec::with_capacity(bins.tiles_y as usize);
    let mut rest = per_intersection.as_mut_slice();
    for ty in 0..bins.tiles_y {
        let (head, tail) = rest.split_at_mut(bins.row_range(ty).len());
        rows.push((ty, head));
        rest = tail;
    }
    rows.into_par_iter().for_each(|(ty, row_grads)| {
        let row_start = bins.row_range(ty).start;
        let mut start = Box::new(BackwardTile::zeroed());
        let mut lane_grads: Vec<LaneGrads> = Vec::new();
        let mut lists = GroupLists::new();
        for tx in 0..bins.tiles_x {
            let tile = TileGeometry::new(tx, ty, width, height);
            let range = tile_range(bins, (ty * bins.tiles_x + tx) as usize);
            let local = gather(
                &prepared,
                &bins.gaussian_from_intersection[range.clone()],
                &tile,
            );
            // Pixels outside the image (edge tiles) keep n_contrib 0: they touch nothing.
            *start = BackwardTile::zeroed();
            for ly in 0..tile.h {
                for lx in 0..tile.w {
                    let p = ly * TILE_SIDE + lx;
                    let o = ly * w + tile.x0 as usize + lx + tile.y0 as usize * w;
                    start.t_final[p] = forward.final_transmittance[o];
                    start.n_contrib[p] = forward.n_contrib[o];
                    let mut v_background = 0.0f32;
                    for c in 0..3 {
                        start.v_color[c][p] = grad_image_alpha[o * 4 + c];
                        v_background += background[c] * start.v_color[c][p];
                    }
                    start.v_final[p] = grad_image_alpha[o * 4 + 3] - v_background;
                }
            }
            lane_grads.clear();
            lane_grads.resize(local.len(), LaneGrads::default());
            lists.fill(&local);
            backward_tile(&local, &lists, &tile, &start, &mut lane_grads);
            let grads = &mut row_grads[range.start - row_start..range.end - row_start];
            for (g, lanes) in grads.iter_mut().zip(&lane_grads) {
                *g = lanes.total();
            }
        }
    });

    let mut per_gaussian = vec![SplatGrad::default(); splats.len()];
    for (g, grad) in bins
        .gaussian_from_intersection
        .iter()
        .zip(&per_intersection)
    {
        per_gaussian[*g as usize].add(grad);
    }
    per_gaussian
}
