//! Where a test view moves: a mask of the dynamic pixels, computed from the ground truth alone,
//! so quality can be reported on the moving pixels and on the static ones separately.
//!
//! Definition (per test camera, over the frames of the GOP):
//! 1. the reference is the per-pixel, per-channel temporal **median** of the ground truth (the
//!    mean of the two middle values for an even frame count): the static background wherever an
//!    object passes for less than half of the clip;
//! 2. a pixel of frame f is *moving* when its colour departs from the reference by more than
//!    `threshold` in any channel (max-channel absolute difference, on [0, 1] values);
//! 3. the moving pixels are dilated by `dilation` pixels (a (2r+1)² square), so the mask also
//!    covers the object's anti-aliased rim and a render that puts it a little off;
//! 4. *static* is everything else.
//!
//! Default parameters: threshold 12/255 (above 8-bit noise and the synthetic scenes' 2×2
//! supersampling jitter, below the contrast of any object against the background), dilation 2
//! px. A camera with a single frame has no dynamic pixels.

use serde::{Deserialize, Serialize};

/// The mask's parameters (config section `[eval]`: `motion_threshold`, `motion_dilation`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionMaskConfig {
    /// Max-channel departure from the temporal median that marks a pixel as moving, in 8-bit
    /// levels (12 = 12/255).
    pub motion_threshold: f32,
    /// Dilation radius in pixels (square structuring element).
    pub motion_dilation: usize,
}

impl Default for MotionMaskConfig {
    fn default() -> Self {
        Self {
            motion_threshold: 12.0,
            motion_dilation: 2,
        }
    }
}

impl MotionMaskConfig {
    pub fn threshold(&self) -> f32 {
        self.motion_threshold / 255.0
    }
}

/// Per-pixel, per-channel temporal median of `frames` (each [H, W, 3] flattened, same length).
pub fn temporal_median(frames: &[&[f32]]) -> Vec<f32> {
    assert!(!frames.is_empty(), "a temporal median needs at least one frame");
    let len = frames[0].len();
    assert!(
        frames.iter().all(|f| f.len() == len),
        "frames of one camera must have the same size"
    );
    let mut column = vec![0.0f32; frames.len()];
    (0..len)
        .map(|i| {
            for (c, f) in column.iter_mut().zip(frames) {
                *c = f[i];
            }
            median(&mut column)
        })
        .collect()
}

/// The median of `values` (the mean of the middle two for an even count); sorts them.
pub fn median(values: &mut [f32]) -> f32 {
    values.sort_unstable_by(f32::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// The dilated moving-pixel mask [H·W] of one frame against its camera's `reference`.
pub fn motion_mask(
    frame: &[f32],
    reference: &[f32],
    width: usize,
    height: usize,
    config: &MotionMaskConfig,
) -> Vec<bool> {
    assert_eq!(frame.len(), width * height * 3, "frame is not {width}x{height}x3");
    assert_eq!(reference.len(), frame.len(), "reference is not {width}x{height}x3");
    let threshold = config.threshold();
    let moving: Vec<bool> = frame
        .chunks_exact(3)
        .zip(reference.chunks_exact(3))
        .map(|(p, r)| (0..3).any(|c| (p[c] - r[c]).abs() > threshold))
        .collect();
    dilate(&moving, width, height, config.motion_dilation)
}

/// Square (Chebyshev) dilation by `radius`, separably: rows, then columns.
pub fn dilate(mask: &[bool], width: usize, height: usize, radius: usize) -> Vec<bool> {
    if radius == 0 {
        return mask.to_vec();
    }
    let mut rows = vec![false; mask.len()];
    for y in 0..height {
        for x in 0..width {
            let (lo, hi) = (x.saturating_sub(radius), (x + radius).min(width - 1));
            rows[y * width + x] = (lo..=hi).any(|xx| mask[y * width + xx]);
        }
    }
    let mut out = vec![false; mask.len()];
    for y in 0..height {
        let (lo, hi) = (y.saturating_sub(radius), (y + radius).min(height - 1));
        for x in 0..width {
            out[y * width + x] = (lo..=hi).any(|yy| rows[yy * width + x]);
        }
    }
    out
}

/// The masks of every frame of one camera (frames in GOP order).
pub fn camera_motion_masks(
    frames: &[&[f32]],
    width: usize,
    height: usize,
    config: &MotionMaskConfig,
) -> Vec<Vec<bool>> {
    if frames.len() < 2 {
        return frames.iter().map(|_| vec![false; width * height]).collect();
    }
    let reference = temporal_median(frames);
    frames
        .iter()
        .map(|f| motion_mask(f, &reference, width, height, config))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(width: usize, height: usize, square: Option<(usize, usize, usize)>) -> Vec<f32> {
        let mut img = vec![0.5f32; width * height * 3];
        if let Some((x0, y0, size)) = square {
            for y in y0..y0 + size {
                for x in x0..x0 + size {
                    img[(y * width + x) * 3] = 0.9;
                }
            }
        }
        img
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        let a = [0.0f32, 1.0];
        let b = [1.0f32, 3.0];
        let c = [5.0f32, 2.0];
        assert_eq!(temporal_median(&[&a, &b, &c]), vec![1.0, 2.0]);
        assert_eq!(temporal_median(&[&a, &b]), vec![0.5, 2.0]);
    }

    #[test]
    fn moving_square_mask_is_the_square_dilated() {
        let (w, h) = (20, 16);
        // A 3×3 square at a different place in each of 3 frames: the median is the background.
        let frames: Vec<Vec<f32>> = [(2, 2), (8, 6), (14, 10)]
            .iter()
            .map(|&(x, y)| image(w, h, Some((x, y, 3))))
            .collect();
        let refs: Vec<&[f32]> = frames.iter().map(|f| f.as_slice()).collect();
        let config = MotionMaskConfig::default();
        let masks = camera_motion_masks(&refs, w, h, &config);
        let m = &masks[1];
        for y in 0..h {
            for x in 0..w {
                let inside = (6..=12).contains(&x) && (4..=10).contains(&y);
                assert_eq!(m[y * w + x], inside, "pixel ({x}, {y})");
            }
        }
        assert_eq!(m.iter().filter(|&&v| v).count(), 49);
    }

    #[test]
    fn below_threshold_changes_are_static_and_dilation_clips_at_borders() {
        let (w, h) = (10, 10);
        let base = image(w, h, None);
        let mut faint = base.clone();
        faint[0] += 11.0 / 255.0; // below 12 levels
        let mut corner = base.clone();
        corner[0] += 30.0 / 255.0;
        let config = MotionMaskConfig::default();
        assert!(motion_mask(&faint, &base, w, h, &config).iter().all(|&v| !v));
        let m = motion_mask(&corner, &base, w, h, &config);
        assert_eq!(m.iter().filter(|&&v| v).count(), 9); // 3×3 inside the image
        assert!(m[2 * w + 2] && !m[3 * w]);
    }

    #[test]
    fn a_single_frame_has_no_motion() {
        let img = image(12, 12, Some((1, 1, 4)));
        let masks = camera_motion_masks(&[&img], 12, 12, &MotionMaskConfig::default());
        assert!(masks[0].iter().all(|&v| !v));
    }
}
