//! Seeded random Gaussian scenes in front of a camera, for tests and benchmarks.

use rand::{Rng, SeedableRng, rngs::StdRng};
use rand_distr::{Distribution, StandardNormal};

use crate::camera::RasterCamera;
pub use crate::cpu::GaussianArrays;

/// A camera at the origin looking down +z with a ~64 degree horizontal field of view.
pub fn identity_camera(width: u32, height: u32) -> RasterCamera {
    let f = 0.8 * width as f32;
    RasterCamera {
        width,
        height,
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        world_to_camera: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    }
}

/// Parameters of [`random_scene`].
#[derive(Clone, Copy, Debug)]
pub struct SceneSpec {
    pub count: usize,
    pub seed: u64,
    /// Depth range in front of the camera.
    pub depth: (f32, f32),
    /// Range of per-axis screen standard deviations in pixels (log-uniform).
    pub pixel_std: (f32, f32),
    pub opacity: (f32, f32),
    /// Centres cover the image plus this fraction of its size on each side.
    pub border: f32,
}

impl SceneSpec {
    pub fn new(count: usize, seed: u64) -> Self {
        Self {
            count,
            seed,
            depth: (2.0, 10.0),
            pixel_std: (0.5, 8.0),
            opacity: (0.05, 0.99),
            border: 0.05,
        }
    }
}

/// Random Gaussians whose projections cover the image of `camera` (identity pose assumed for
/// placement; any pose renders them).
pub fn random_scene(camera: &RasterCamera, spec: &SceneSpec) -> GaussianArrays {
    let mut rng = StdRng::seed_from_u64(spec.seed);
    let mut s = GaussianArrays::default();
    let (w, h) = (camera.width as f32, camera.height as f32);
    for _ in 0..spec.count {
        let z = rng.random_range(spec.depth.0..spec.depth.1);
        let u = rng.random_range(-spec.border * w..(1.0 + spec.border) * w);
        let v = rng.random_range(-spec.border * h..(1.0 + spec.border) * h);
        s.means.extend([
            (u - camera.cx) / camera.fx * z,
            (v - camera.cy) / camera.fy * z,
            z,
        ]);
        let q: [f32; 4] = std::array::from_fn(|_| StandardNormal.sample(&mut rng));
        s.quats.extend(q);
        for _ in 0..3 {
            let (lo, hi) = (spec.pixel_std.0.ln(), spec.pixel_std.1.ln());
            let std_px = rng.random_range(lo..hi).exp();
            s.scales.push(std_px * z / camera.fx);
        }
        s.opacities
            .push(rng.random_range(spec.opacity.0..spec.opacity.1));
        s.gates.push(1.0);
        s.colors.extend([
            rng.random::<f32>(),
            rng.random::<f32>(),
            rng.random::<f32>(),
        ]);
    }
    s
}
