//! Writes the small 3DGS scene shipped in `assets/example/` (the README's first command renders it):
//! a checkered floor, a ring of coloured ellipsoids and a sphere of small splats, SH degree 1.
//!
//! `cargo run --release --example make_example_scene` regenerates it deterministically.

use std::path::Path;

use acags::io::splat_ply::{SplatScene, write_splat_ply};
use rand::{Rng, SeedableRng, rngs::StdRng};

const SH_C0: f32 = 0.282_094_79;

fn push(
    scene: &mut SplatScene,
    mean: [f32; 3],
    scale: [f32; 3],
    quat: [f32; 4],
    opacity: f32,
    rgb: [f32; 3],
    tilt: f32,
) {
    scene.means.extend(mean);
    scene.scales.extend(scale);
    scene.quats.extend(quat);
    scene.opacities.push(opacity);
    // DC so that the colour seen head-on is `rgb`, plus a small view-dependent degree-1 term.
    scene.sh.extend(rgb.map(|c| (c - 0.5) / SH_C0));
    scene
        .sh
        .extend([0.0, 0.0, 0.0, tilt, tilt, tilt, 0.0, 0.0, 0.0]);
}

fn main() -> anyhow::Result<()> {
    let mut rng = StdRng::seed_from_u64(2026);
    let mut scene = SplatScene {
        sh_degree: 1,
        ..Default::default()
    };
    // Floor: y = 1 (OpenCV: y down), checkered, flat splats.
    for i in -30..30 {
        for k in 0..40 {
            let (x, z) = (i as f32 * 0.1 + 0.05, k as f32 * 0.1 + 1.0);
            let light = if (i + k) % 2 == 0 { 0.85 } else { 0.25 };
            push(
                &mut scene,
                [x, 1.0, z],
                [0.06, 0.004, 0.06],
                [1.0, 0.0, 0.0, 0.0],
                0.95,
                [light, light, light * 0.9],
                0.0,
            );
        }
    }
    // A ring of coloured ellipsoids.
    for j in 0..24 {
        let a = j as f32 / 24.0 * std::f32::consts::TAU;
        let (s, c) = (a * 0.5).sin_cos();
        let hue = j as f32 / 24.0;
        let rgb = [
            0.5 + 0.5 * (hue * 6.283).cos(),
            0.5 + 0.5 * (hue * 6.283 + 2.09).cos(),
            0.5 + 0.5 * (hue * 6.283 + 4.19).cos(),
        ];
        push(
            &mut scene,
            [1.2 * a.cos(), 0.55, 3.0 + 1.2 * a.sin()],
            [0.16, 0.3, 0.07],
            [c, 0.0, s, 0.0],
            0.9,
            rgb,
            0.15,
        );
    }
    // A sphere of small splats, coloured by normal.
    for _ in 0..1600 {
        let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        let d = v.map(|x| x / n);
        let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        push(
            &mut scene,
            [0.5 * d[0], 0.1 + 0.5 * d[1], 3.0 + 0.5 * d[2]],
            [0.05, 0.04, 0.02],
            q,
            0.8,
            d.map(|x| 0.5 + 0.45 * x),
            0.05,
        );
    }
    let dir = Path::new("assets/example");
    std::fs::create_dir_all(dir)?;
    write_splat_ply(&dir.join("scene.ply"), &scene)?;
    // Camera 1 unit up and 1 back, pitched 15 degrees down, 640x400.
    let (sp, cp) = 15f32.to_radians().sin_cos();
    let rot = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
    let center = [0.0f32, -0.6, -0.4];
    let t: Vec<f32> = (0..3)
        .map(|i| -(0..3).map(|j| rot[i][j] * center[j]).sum::<f32>())
        .collect();
    let camera = serde_json::json!({
        "width": 640, "height": 400, "fx": 520.0, "fy": 520.0, "cx": 320.0, "cy": 200.0,
        "world_to_camera": [
            [rot[0][0], rot[0][1], rot[0][2], t[0]],
            [rot[1][0], rot[1][1], rot[1][2], t[1]],
            [rot[2][0], rot[2][1], rot[2][2], t[2]],
            [0.0, 0.0, 0.0, 1.0]
        ]
    });
    std::fs::write(
        dir.join("camera.json"),
        serde_json::to_string_pretty(&camera)?,
    )?;
    println!("wrote {} Gaussians to {}", scene.len(), dir.display());
    Ok(())
}
