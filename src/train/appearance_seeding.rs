//! Seeding anchors on objects that appear after frame 0 (`train.appearance_seeding`; not in
//! GIFStream or ACA-GS).
//!
//! Why: anchors come from frame 0's point cloud, and growth only adds anchors next to Gaussians
//! that are drawn. An object outside every view at frame 0 (large-motion's sphere enters at frame
//! 8 and leaves at 32) gets no anchor, no Gaussian and no gradient: it is absent from every frame
//! whatever the training length (docs/results.md, Follow-up 11). The knot search
//! (`train/knot_search.rs`) cannot help: it re-finds anchors that exist.
//!
//! How (plane-sweep stereo on the moving pixels): when a trajectory knot opens, every moving pixel
//! of that frame's training images (the evaluation's motion mask, every second row and column) is
//! swept along its ray over the depths the scene occupies in that camera; a depth is scored as the
//! knot search scores a candidate (mean-channel L1 between the pixel's colour and what the other
//! cameras show there, trimmed over the best three quarters of the views for occlusion, on moving
//! pixels in most of them) and the best one is kept when it agrees within the tolerance. The
//! points are pooled in cells of the anchors' typical spacing; a cell seen by at least two
//! cameras that no anchor occupies at that frame (within two cells: the tracked objects and the
//! static surfaces a moving shadow falls on are explained already) becomes a new anchor. Costs no
//! rendering: bilinear look-ups only, for the moving pixels only.

use std::collections::{HashMap, HashSet};

use rayon::prelude::*;

use super::knot_search::{FrameViews, agreement, bilinear, project_with_depth};
use crate::raster::RasterCamera;

/// The sweep's parameters.
#[derive(Clone, Copy, Debug)]
pub struct SeedParams {
    /// Colour agreement as `train.knot_search_tolerance`.
    pub tolerance: f32,
    /// Edge of the cells points are pooled in, world units (the anchors' typical spacing).
    pub cell: f32,
}

/// Every `PIXEL_STRIDE`-th row and column of the moving pixels is swept.
const PIXEL_STRIDE: usize = 2;
/// Depths per ray, uniform in inverse depth, then `FINE_DEPTHS` between the best one's neighbours.
const COARSE_DEPTHS: usize = 96;
const FINE_DEPTHS: usize = 8;
/// Cameras whose rays must have put a point in a cell for it to become an anchor: one camera's
/// wrong depths scatter, two cameras agreeing on a surface do not.
const MIN_SUPPORT: usize = 2;
/// A cell within this many cells (Chebyshev) of an existing anchor is explained already.
const EXPLAINED_CELLS: i64 = 2;

/// What a sweep found, for the log.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SeedReport {
    /// Moving pixels swept.
    pub rays: usize,
    /// Rays that found a depth at which the cameras agree.
    pub consistent: usize,
    /// Cells those points fell in with enough support, and those of them no anchor explains.
    pub cells: usize,
    pub seeded: usize,
}

/// The positions of new anchors for what the `views` (one frame) show moving that no anchor in
/// `anchors` (their positions at that frame) explains, in a deterministic order.
pub fn seed_positions(
    views: &FrameViews,
    anchors: &[[f32; 3]],
    params: SeedParams,
) -> (Vec<[f32; 3]>, SeedReport) {
    assert!(params.cell > 0.0 && params.cell.is_finite());
    let to_cell = |p: [f32; 3]| p.map(|v| (v / params.cell).floor() as i64);
    let occupied: HashSet<[i64; 3]> = anchors.iter().map(|&p| to_cell(p)).collect();
    // Per camera, the rays through its moving pixels and the point each found.
    let per_camera: Vec<(usize, Vec<[f32; 3]>)> = (0..views.cameras.len())
        .into_par_iter()
        .map(|r| sweep_camera(views, r, anchors, params.tolerance))
        .collect();
    let mut report = SeedReport {
        rays: per_camera.iter().map(|c| c.0).sum(),
        consistent: per_camera.iter().map(|c| c.1.len()).sum(),
        ..SeedReport::default()
    };
    // Cell → (sum of points, count, cameras that put a point there).
    let mut cells: HashMap<[i64; 3], ([f64; 3], usize, Vec<usize>)> = HashMap::new();
    for (r, (_, points)) in per_camera.iter().enumerate() {
        for &p in points {
            let e = cells.entry(to_cell(p)).or_default();
            for c in 0..3 {
                e.0[c] += p[c] as f64;
            }
            e.1 += 1;
            if e.2.last() != Some(&r) {
                e.2.push(r);
            }
        }
    }
    let explained = |c: &[i64; 3]| {
        let k = EXPLAINED_CELLS;
        (-k..=k).any(|i| {
            (-k..=k).any(|j| (-k..=k).any(|l| occupied.contains(&[c[0] + i, c[1] + j, c[2] + l])))
        })
    };
    let mut seeds: Vec<([i64; 3], [f32; 3])> = cells
        .iter()
        .filter(|(_, (_, _, cameras))| cameras.len() >= MIN_SUPPORT)
        .inspect(|_| report.cells += 1)
        .filter(|(c, _)| !explained(c))
        .map(|(c, (sum, n, _))| (*c, sum.map(|s| (s / *n as f64) as f32)))
        .collect();
    seeds.sort_by_key(|s| s.0);
    report.seeded = seeds.len();
    (seeds.into_iter().map(|s| s.1).collect(), report)
}

/// Camera `r`'s swept rays and the consistent points they found.
fn sweep_camera(
    views: &FrameViews,
    r: usize,
    anchors: &[[f32; 3]],
    tolerance: f32,
) -> (usize, Vec<[f32; 3]>) {
    let camera = &views.cameras[r];
    let image = views.images[r];
    let mask = &views.moving[r];
    let (w, h) = (image.width as usize, image.height as usize);
    let Some((near, far)) = depth_range(camera, anchors) else {
        return (0, Vec::new());
    };
    let ray = Ray::new(camera);
    // Inverse depth from 1/near to 1/far: equal steps in pixel displacement in the other views.
    let inverse = |i: f32, n: usize| 1.0 / near + (1.0 / far - 1.0 / near) * i / (n - 1) as f32;
    let (mut rays, mut points) = (0, Vec::new());
    for y in (0..h).step_by(PIXEL_STRIDE) {
        for x in (0..w).step_by(PIXEL_STRIDE) {
            if !mask[y * w + x] {
                continue;
            }
            rays += 1;
            let xy = [x as f32 + 0.5, y as f32 + 0.5];
            let Some(colour) = bilinear(image, xy) else {
                continue;
            };
            // Ranked by the mean over all the cameras, accepted by the trimmed score, as the
            // knot search does (its `scan` explains why).
            let best_at = |depths: &mut dyn Iterator<Item = f32>| {
                let mut best: Option<(f32, f32, f32)> = None;
                for inv in depths {
                    let p = ray.at(xy, 1.0 / inv);
                    let Some(a) = agreement(views, p, colour) else {
                        continue;
                    };
                    if a.on_moving && best.is_none_or(|b| a.mean < b.0) {
                        best = Some((a.mean, a.trimmed, inv));
                    }
                }
                best
            };
            let Some((_, _, inv)) =
                best_at(&mut (0..COARSE_DEPTHS).map(|i| inverse(i as f32, COARSE_DEPTHS)))
            else {
                continue;
            };
            let step = (1.0 / far - 1.0 / near) / (COARSE_DEPTHS - 1) as f32;
            // Within the scene's depths: inverse depths between 1/far and 1/near.
            let (lo, hi) = (1.0 / far, 1.0 / near);
            let mut fine = (0..=FINE_DEPTHS)
                .map(|i| inv - step + 2.0 * step * i as f32 / FINE_DEPTHS as f32)
                .map(|v| v.clamp(lo, hi));
            let Some((_, trimmed, inv)) = best_at(&mut fine) else {
                continue;
            };
            if trimmed <= tolerance {
                points.push(ray.at(xy, 1.0 / inv));
            }
        }
    }
    (rays, points)
}

/// Depths (camera z) the scene occupies in `camera`: from half the nearest anchor in view to
/// just past the farthest. `None` when no anchor is in view.
fn depth_range(camera: &RasterCamera, anchors: &[[f32; 3]]) -> Option<(f32, f32)> {
    let (w, h) = (camera.width as f32, camera.height as f32);
    let (mut near, mut far) = (f32::INFINITY, 0.0f32);
    for &p in anchors {
        let Some(([u, v], z)) = project_with_depth(camera, p) else {
            continue;
        };
        if (0.0..w).contains(&u) && (0.0..h).contains(&v) {
            near = near.min(z);
            far = far.max(z);
        }
    }
    (far > 0.0).then_some((0.5 * near, 1.05 * far))
}

/// World points along a camera's pixel rays.
struct Ray {
    /// Camera-to-world rotation (the transpose of world_to_camera's) and the camera centre.
    rotation: [[f32; 3]; 3],
    centre: [f32; 3],
    camera: RasterCamera,
}

impl Ray {
    fn new(camera: &RasterCamera) -> Self {
        let m = &camera.world_to_camera;
        let rotation: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]));
        let t = [m[0][3], m[1][3], m[2][3]];
        let centre: [f32; 3] =
            std::array::from_fn(|i| -(0..3).map(|j| rotation[i][j] * t[j]).sum::<f32>());
        Self {
            rotation,
            centre,
            camera: camera.clone(),
        }
    }

    /// The world point at camera depth `z` on the ray through pixel position `xy` (pixel centres
    /// at +0.5, as `knot_search::project` returns them).
    fn at(&self, xy: [f32; 2], z: f32) -> [f32; 3] {
        let c = [
            (xy[0] - self.camera.cx) / self.camera.fx * z,
            (xy[1] - self.camera.cy) / self.camera.fy * z,
            z,
        ];
        std::array::from_fn(|i| {
            self.centre[i] + (0..3).map(|j| self.rotation[i][j] * c[j]).sum::<f32>()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::frames::Frame;
    use crate::train::knot_search::project;
    use crate::train::knot_search::tests::{BALL_AT_F, BALL_RADIUS, render, rig};

    const PARAMS: SeedParams = SeedParams {
        tolerance: 0.08,
        cell: 0.1,
    };

    /// Floor anchors every 0.1 over [−1.5, 1.5]², and the back of the scene.
    fn floor() -> Vec<[f32; 3]> {
        let mut anchors = Vec::new();
        for i in -15..=15 {
            for k in -15..=15 {
                anchors.push([i as f32 * 0.1, 0.0, k as f32 * 0.1]);
            }
        }
        anchors
    }

    fn seed(anchors: &[[f32; 3]], moving: Option<bool>) -> (Vec<[f32; 3]>, SeedReport) {
        let cameras = rig();
        let (images, on_ball): (Vec<Frame>, Vec<Vec<bool>>) =
            cameras.iter().map(|c| render(c, BALL_AT_F)).unzip();
        let masks: Vec<Vec<bool>> = match moving {
            Some(all) => on_ball.iter().map(|m| vec![all; m.len()]).collect(),
            None => on_ball,
        };
        let refs: Vec<&Frame> = images.iter().collect();
        seed_positions(
            &FrameViews {
                cameras: &cameras,
                images: &refs,
                moving: &masks,
            },
            anchors,
            PARAMS,
        )
    }

    fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f32>().sqrt()
    }

    #[test]
    fn a_ball_no_anchor_explains_is_seeded_on_its_surface() {
        let (seeds, report) = seed(&floor(), None);
        assert!(
            report.rays > 100 && report.consistent > report.rays / 2,
            "{report:?}"
        );
        // The ball's visible surface spans some 25 cells of 0.1.
        assert!(seeds.len() >= 10, "{report:?}");
        for s in &seeds {
            let d = distance(*s, BALL_AT_F);
            // In the ball (a uniform colour agrees all through its visual hull, so interior
            // depths tie with the surface), within a cell of the sweep's resolution.
            assert!(
                d < BALL_RADIUS + 0.12,
                "seed {s:?} is {d} from the ball's centre (radius {BALL_RADIUS})"
            );
        }
        // Every camera can check a ray: the seeds come from the ring, not one side.
        let centre: [f32; 3] =
            std::array::from_fn(|i| seeds.iter().map(|s| s[i]).sum::<f32>() / seeds.len() as f32);
        assert!(
            distance(centre, BALL_AT_F) < 0.15,
            "seed centroid {centre:?}"
        );
        // Projected, every seed lands on the ball in a camera that faces it.
        let cameras = rig();
        for s in &seeds {
            assert!(cameras.iter().any(|c| project(c, *s).is_some()));
        }
    }

    #[test]
    fn an_explained_ball_and_an_empty_mask_seed_nothing() {
        // Anchors already on the ball at this frame (as the tracked ones are).
        let mut anchors = floor();
        for i in -3..=3 {
            for j in -3..=3 {
                for k in -3..=3 {
                    let p = [
                        BALL_AT_F[0] + i as f32 * 0.1,
                        BALL_AT_F[1] + j as f32 * 0.1,
                        BALL_AT_F[2] + k as f32 * 0.1,
                    ];
                    if distance(p, BALL_AT_F) <= BALL_RADIUS + 0.05 {
                        anchors.push(p);
                    }
                }
            }
        }
        let (seeds, report) = seed(&anchors, None);
        assert!(report.cells > 0, "{report:?}");
        assert_eq!(seeds, Vec::<[f32; 3]>::new(), "{report:?}");
        // Nothing moving: nothing swept, nothing seeded.
        let (seeds, report) = seed(&floor(), Some(false));
        assert_eq!((seeds.len(), report.rays), (0, 0));
    }
}
