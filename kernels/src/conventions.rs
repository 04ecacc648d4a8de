//! Numeric conventions shared by every rasterizer implementation (CPU twin and CubeCL kernels).
//!
//! They are gsplat 1.5.3's, as GIFStream calls it (`rasterization(..., eps2d=0.3, near_plane=0.01,
//! rasterize_mode="classic")`), restated in `../shared/fixtures/gsplat/README.md`.

/// Added to the diagonal of every projected 2D covariance (no antialiasing compensation).
pub const EPS2D: f32 = 0.3;
/// Gaussians whose camera-space z is below this are culled.
pub const NEAR_PLANE: f32 = 0.01;
/// Gaussians whose camera-space z is above this are culled.
pub const FAR_PLANE: f32 = 1e10;
/// A (pixel, Gaussian) pair with alpha below this is skipped; Gaussians whose opacity is below it
/// are culled at projection.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Alpha is clamped to this (and the clamp has zero gradient).
pub const ALPHA_MAX: f32 = 0.999;
/// A pixel stops when the transmittance after the next Gaussian would be at or below this; that
/// Gaussian is not composited.
pub const TRANSMITTANCE_STOP: f32 = 1e-4;
/// Side of the square screen tiles Gaussians are binned into.
pub const TILE_SIZE: u32 = 16;
/// Upper bound of the opacity-aware extent in standard deviations: min(3.33, sqrt(2 ln(255 o))).
pub const MAX_EXTENT_SIGMAS: f32 = 3.33;
/// The Jacobian is evaluated with x/z, y/z clamped to 1.3x the field of view: the image half-extent
/// on each side plus 0.15 of the full extent.
pub const FOV_CLAMP_MARGIN: f32 = 0.15;

/// Columns of the per-Gaussian projection tensor [N, PROJECTED_COLUMNS] that the forward hands
/// to the backward (CPU twin rows, CubeCL buffers and `RasterForward::projected` alike).
pub mod projected_column {
    pub const MEAN2D_X: usize = 0;
    pub const MEAN2D_Y: usize = 1;
    pub const CONIC_A: usize = 2;
    pub const CONIC_B: usize = 3;
    pub const CONIC_C: usize = 4;
    pub const DEPTH: usize = 5;
    pub const RADIUS_X: usize = 6;
    pub const RADIUS_Y: usize = 7;
}
pub const PROJECTED_COLUMNS: usize = 8;

/// Number of tiles along an image side of `pixels` pixels.
pub const fn tiles_along(pixels: u32) -> u32 {
    pixels.div_ceil(TILE_SIZE)
}
