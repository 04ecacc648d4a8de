//! Spherical-harmonics distillation: the colour a Gaussian shows from a set of viewpoints, fitted
//! by least squares with real SH of degree 0-3 in the Inria convention (colour = SH · basis(dir)
//! + 0.5, dir from the viewpoint to the Gaussian), so that standard 3DGS viewers reproduce it.
//!
//! With fewer viewpoints than coefficients (12 training cameras against 16 coefficients at degree
//! 3) the fit is under-determined, so the degree ≥ 1 coefficients carry a small ridge penalty:
//! among the fits that match the samples, the one with the least view-dependent energy, which
//! keeps unseen directions near the mean colour instead of ringing. The DC coefficient is not
//! penalised, so a colour that is the same from every viewpoint is reproduced exactly.

use anyhow::{Result, bail};
use rayon::prelude::*;

use crate::io::splat_ply::{SH_COEFFS, sh_basis};

/// Ridge weight on the degree ≥ 1 coefficients, relative to the number of viewpoints (the basis
/// values are O(1), so this is ~1e-3 of the data term per coefficient).
pub const RIDGE: f64 = 1e-3;

/// The colours of N Gaussians seen from V viewpoints.
pub struct ColourSamples<'a> {
    /// [N, 3] Gaussian centres.
    pub means: &'a [f32],
    /// [V] viewpoint positions (camera centres, world).
    pub viewpoints: &'a [[f32; 3]],
    /// [V] the [N, 3] RGB of every Gaussian as seen from each viewpoint (one shared slice when
    /// the colour does not depend on the view).
    pub colours: Vec<&'a [f32]>,
}

/// Fits [N, coeffs(degree), 3] SH coefficients (coefficient-major, DC first, as
/// [`crate::io::splat_ply::SplatScene::sh`]) to `samples`.
pub fn fit_sh(samples: &ColourSamples, degree: usize) -> Result<Vec<f32>> {
    if degree > 3 {
        bail!("SH degree {degree} is outside 0-3");
    }
    let n = samples.means.len() / 3;
    let views = samples.viewpoints.len();
    if views == 0 {
        bail!("no viewpoints to distil colours from");
    }
    let colours = &samples.colours;
    if colours.len() != views {
        bail!("{} colour sets for {views} viewpoints", colours.len());
    }
    for (v, c) in colours.iter().enumerate() {
        if c.len() != 3 * n {
            bail!("viewpoint {v}: {} colour values for {n} Gaussians", c.len());
        }
    }
    let k = SH_COEFFS[degree];
    let mut sh = vec![0.0f32; n * k * 3];
    sh.par_chunks_mut(k * 3).enumerate().for_each(|(i, out)| {
        let mean = [
            samples.means[3 * i],
            samples.means[3 * i + 1],
            samples.means[3 * i + 2],
        ];
        // Normal equations (BᵀB + λR) x = Bᵀ(y − 0.5), one matrix for the three channels.
        let mut gram = [[0.0f64; 16]; 16];
        let mut rhs = [[0.0f64; 3]; 16];
        for (v, eye) in samples.viewpoints.iter().enumerate() {
            let dir = [mean[0] - eye[0], mean[1] - eye[1], mean[2] - eye[2]];
            let b = sh_basis(degree, dir);
            for r in 0..k {
                for c in 0..k {
                    gram[r][c] += b[r] as f64 * b[c] as f64;
                }
                for ch in 0..3 {
                    rhs[r][ch] += b[r] as f64 * (colours[v][3 * i + ch] as f64 - 0.5);
                }
            }
        }
        for (r, row) in gram.iter_mut().enumerate().take(k).skip(1) {
            row[r] += RIDGE * views as f64;
        }
        let x = solve_spd(&mut gram, &rhs, k);
        for j in 0..k {
            for ch in 0..3 {
                out[j * 3 + ch] = x[j][ch] as f32;
            }
        }
    });
    Ok(sh)
}

/// Solves A x = b for a symmetric positive-definite k×k A (Cholesky, in place), three right-hand
/// sides at once.
fn solve_spd(a: &mut [[f64; 16]; 16], b: &[[f64; 3]; 16], k: usize) -> [[f64; 3]; 16] {
    // A = L Lᵀ, L stored in the lower triangle.
    for j in 0..k {
        let mut d = a[j][j];
        for p in 0..j {
            d -= a[j][p] * a[j][p];
        }
        // The DC diagonal is V·C0² > 0 and the ridge makes the rest positive: d > 0 unless the
        // input was not finite.
        let d = d.max(f64::MIN_POSITIVE).sqrt();
        a[j][j] = d;
        for i in j + 1..k {
            let mut s = a[i][j];
            for p in 0..j {
                s -= a[i][p] * a[j][p];
            }
            a[i][j] = s / d;
        }
    }
    let mut y = [[0.0f64; 3]; 16];
    for i in 0..k {
        for ch in 0..3 {
            let mut s = b[i][ch];
            for p in 0..i {
                s -= a[i][p] * y[p][ch];
            }
            y[i][ch] = s / a[i][i];
        }
    }
    let mut x = [[0.0f64; 3]; 16];
    for i in (0..k).rev() {
        for ch in 0..3 {
            let mut s = y[i][ch];
            for p in i + 1..k {
                s -= a[p][i] * x[p][ch];
            }
            x[i][ch] = s / a[i][i];
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::splat_ply::SplatScene;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn sphere_points(count: usize, radius: f32, rng: &mut StdRng) -> Vec<[f32; 3]> {
        (0..count)
            .map(|_| {
                loop {
                    let p: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
                    let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                    if n > 0.1 && n <= 1.0 {
                        break p.map(|v| v / n * radius);
                    }
                }
            })
            .collect()
    }

    /// Colours of `scene` seen from each viewpoint, as a viewer evaluates them.
    fn colours_of(scene: &SplatScene, eyes: &[[f32; 3]]) -> Vec<Vec<f32>> {
        eyes.iter().map(|&e| scene.colors_from(e)).collect()
    }

    fn random_scene(degree: usize, n: usize, rng: &mut StdRng) -> SplatScene {
        let k = SH_COEFFS[degree];
        SplatScene {
            means: (0..3 * n).map(|_| rng.random_range(-0.5..0.5)).collect(),
            quats: vec![1.0, 0.0, 0.0, 0.0].repeat(n),
            scales: vec![0.1; 3 * n],
            opacities: vec![0.5; n],
            // Small view-dependent terms around a mid-grey, so the viewer's clamp at 0 never acts.
            sh: (0..n * k * 3)
                .map(|j| {
                    if j % (k * 3) < 3 {
                        rng.random_range(-0.5..0.5)
                    } else {
                        rng.random_range(-0.08..0.08)
                    }
                })
                .collect(),
            sh_degree: degree,
        }
    }

    #[test]
    fn a_view_independent_colour_is_exact_at_every_degree() {
        let mut rng = StdRng::seed_from_u64(1);
        let n = 50;
        let means: Vec<f32> = (0..3 * n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let colours: Vec<f32> = (0..3 * n).map(|_| rng.random_range(0.0..1.0)).collect();
        let eyes = sphere_points(12, 4.0, &mut rng);
        for degree in 0..=3 {
            let samples = ColourSamples {
                means: &means,
                viewpoints: &eyes,
                colours: vec![colours.as_slice(); eyes.len()],
            };
            let sh = fit_sh(&samples, degree).unwrap();
            let scene = SplatScene {
                means: means.clone(),
                sh,
                sh_degree: degree,
                ..Default::default()
            };
            // From the sampled viewpoints and from new ones: the rest is exactly zero.
            for eye in eyes.iter().chain(&sphere_points(5, 3.0, &mut rng)) {
                for (got, want) in scene.colors_from(*eye).iter().zip(&colours) {
                    assert!(
                        (got - want).abs() < 1e-5,
                        "degree {degree}: {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn colours_made_by_sh_are_recovered_from_enough_views() {
        let mut rng = StdRng::seed_from_u64(2);
        for degree in 1..=3 {
            let truth = random_scene(degree, 20, &mut rng);
            // 64 viewpoints over the sphere: the fit is over-determined and the samples lie in
            // the model, so only the ridge separates fit and truth. It shrinks each degree ≥ 1
            // coefficient by about λ / mean(b²) ≈ 1e-3 / 0.08 ≈ 1 %, more where 64 random
            // directions sample a basis function unevenly: a few % of coefficients ≤ 0.08.
            let eyes = sphere_points(64, 6.0, &mut rng);
            let colours = colours_of(&truth, &eyes);
            let samples = ColourSamples {
                means: &truth.means,
                viewpoints: &eyes,
                colours: colours.iter().map(Vec::as_slice).collect(),
            };
            let sh = fit_sh(&samples, degree).unwrap();
            for (got, want) in sh.iter().zip(&truth.sh) {
                assert!(
                    (got - want).abs() < 5e-3,
                    "degree {degree}: {got} vs {want}"
                );
            }
            // The colours it gives from the sampled viewpoints are the truth's to < 1/255.
            let fitted = SplatScene {
                sh,
                ..truth.clone()
            };
            for (eye, want) in eyes.iter().zip(&colours) {
                for (got, want) in fitted.colors_from(*eye).iter().zip(want) {
                    assert!((got - want).abs() < 1.0 / 255.0, "degree {degree}");
                }
            }
            // And without the ridge's pull the recovery would be exact: an all-degree-0 truth
            // (zero higher terms) comes back to f32 rounding.
            let flat = SplatScene {
                sh: truth
                    .sh
                    .iter()
                    .enumerate()
                    .map(|(j, &v)| {
                        if j % (SH_COEFFS[degree] * 3) < 3 {
                            v
                        } else {
                            0.0
                        }
                    })
                    .collect(),
                ..truth.clone()
            };
            let flat_colours = colours_of(&flat, &eyes);
            let sh = fit_sh(
                &ColourSamples {
                    means: &flat.means,
                    viewpoints: &eyes,
                    colours: flat_colours.iter().map(Vec::as_slice).collect(),
                },
                degree,
            )
            .unwrap();
            for (got, want) in sh.iter().zip(&flat.sh) {
                assert!(
                    (got - want).abs() < 1e-5,
                    "degree {degree}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn the_fit_satisfies_its_normal_equations() {
        // An independent check of the solver: at the solution, the gradient of
        // |Bx − y|² + λ|x_rest|² vanishes, for colours that no SH of that degree reproduces.
        let mut rng = StdRng::seed_from_u64(3);
        let n = 8;
        let means: Vec<f32> = (0..3 * n).map(|_| rng.random_range(-0.5..0.5)).collect();
        let eyes = sphere_points(12, 5.0, &mut rng);
        let colours: Vec<Vec<f32>> = (0..eyes.len())
            .map(|_| (0..3 * n).map(|_| rng.random_range(0.0..1.0)).collect())
            .collect();
        for degree in 0..=3 {
            let k = SH_COEFFS[degree];
            let samples = ColourSamples {
                means: &means,
                viewpoints: &eyes,
                colours: colours.iter().map(Vec::as_slice).collect(),
            };
            let sh = fit_sh(&samples, degree).unwrap();
            for i in 0..n {
                for ch in 0..3 {
                    let mut grad = vec![0.0f64; k];
                    for (v, eye) in eyes.iter().enumerate() {
                        let dir: [f32; 3] = std::array::from_fn(|a| means[3 * i + a] - eye[a]);
                        let b = sh_basis(degree, dir);
                        let pred: f64 = (0..k)
                            .map(|j| b[j] as f64 * sh[(i * k + j) * 3 + ch] as f64)
                            .sum();
                        let r = pred - (colours[v][3 * i + ch] as f64 - 0.5);
                        for j in 0..k {
                            grad[j] += b[j] as f64 * r;
                        }
                    }
                    for (j, g) in grad.iter_mut().enumerate().skip(1) {
                        *g += RIDGE * eyes.len() as f64 * sh[(i * k + j) * 3 + ch] as f64;
                    }
                    for g in grad {
                        assert!(g.abs() < 1e-5, "degree {degree}: gradient {g}");
                    }
                }
            }
        }
    }

    #[test]
    fn bad_inputs_are_refused() {
        let means = vec![0.0f32; 3];
        let colours = vec![0.5f32; 3];
        let samples = ColourSamples {
            means: &means,
            viewpoints: &[[0.0, 0.0, -1.0]],
            colours: vec![&colours],
        };
        assert!(fit_sh(&samples, 4).unwrap_err().to_string().contains("0-3"));
        let none = ColourSamples {
            means: &means,
            viewpoints: &[],
            colours: vec![],
        };
        assert!(fit_sh(&none, 0).is_err());
    }
}
