//! Standard 3DGS PLY scenes (the Inria layout): `x y z`, `f_dc_0..2`, optional `f_rest_*`
//! (spherical harmonics up to degree 3, channel-major), `opacity` (logit), `scale_0..2` (log),
//! `rot_0..3` (w, x, y, z). Read with `ply-rs-bw`; written as binary little-endian.

use std::io::{BufReader, Write};
use std::path::Path;

use anyhow::{Context, Result, bail};
use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{PropertyAccess, PropertyAccessResult, PropertyType, ScalarType};

use burn::tensor::Device;

use crate::host_math::{logit, sigmoid};
use crate::raster::cpu::GaussianArrays;
use crate::raster::{GaussianTensors, RasterCamera, RasterOutput, rasterize};

/// SH coefficients per colour channel for degrees 0..=3.
pub const SH_COEFFS: [usize; 4] = [1, 4, 9, 16];
const MAX_REST: usize = 45;

/// A 3DGS scene in activated form, ready for the rasterizer.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SplatScene {
    pub means: Vec<f32>,
    /// (w, x, y, z), as stored (normalised by the rasterizer).
    pub quats: Vec<f32>,
    /// exp(log-scale).
    pub scales: Vec<f32>,
    /// sigmoid(logit).
    pub opacities: Vec<f32>,
    /// [N, coeffs, 3] SH coefficients, coefficient-major (DC first).
    pub sh: Vec<f32>,
    pub sh_degree: usize,
}

impl SplatScene {
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn coeffs(&self) -> usize {
        SH_COEFFS[self.sh_degree]
    }

    /// RGB per Gaussian for a camera at `camera_center` (world), as the Inria renderer evaluates
    /// it: SH in the direction from the camera to the Gaussian, + 0.5, clamped at 0.
    pub fn colors_from(&self, camera_center: [f32; 3]) -> Vec<f32> {
        let k = self.coeffs();
        let mut colors = Vec::with_capacity(3 * self.len());
        for i in 0..self.len() {
            let d = [
                self.means[3 * i] - camera_center[0],
                self.means[3 * i + 1] - camera_center[1],
                self.means[3 * i + 2] - camera_center[2],
            ];
            let basis = sh_basis(self.sh_degree, d);
            for c in 0..3 {
                let v: f32 = (0..k)
                    .map(|j| basis[j] * self.sh[(i * k + j) * 3 + c])
                    .sum();
                colors.push((v + 0.5).max(0.0));
            }
        }
        colors
    }
}

/// Renders `scene` from `camera` with acags' rasterizer (what `render-ply` draws): colours from
/// the SH at the camera centre, every Gaussian ungated.
pub fn render_splat(
    scene: &SplatScene,
    camera: &RasterCamera,
    background: [f32; 3],
    device: &Device,
) -> Result<RasterOutput> {
    let arrays = GaussianArrays {
        colors: scene.colors_from(camera.center()),
        means: scene.means.clone(),
        quats: scene.quats.clone(),
        scales: scene.scales.clone(),
        opacities: scene.opacities.clone(),
        gates: vec![1.0; scene.len()],
    };
    let gaussians = GaussianTensors::from_arrays(&arrays, device);
    Ok(rasterize(&gaussians, camera, background)?)
}

/// Real SH basis (the Inria 3DGS constants and sign conventions) at a direction.
pub fn sh_basis(degree: usize, dir: [f32; 3]) -> [f32; 16] {
    const C0: f32 = 0.282_094_79;
    const C1: f32 = 0.488_602_5;
    const C2: [f32; 5] = [
        1.092_548_4,
        -1.092_548_4,
        0.315_391_57,
        -1.092_548_4,
        0.546_274_2,
    ];
    const C3: [f32; 7] = [
        -0.590_043_6,
        2.890_611_4,
        -0.457_045_8,
        0.373_176_33,
        -0.457_045_8,
        1.445_305_7,
        -0.590_043_6,
    ];
    let mut b = [0.0f32; 16];
    b[0] = C0;
    if degree == 0 {
        return b;
    }
    let norm = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    let [x, y, z] = if norm > 0.0 {
        [dir[0] / norm, dir[1] / norm, dir[2] / norm]
    } else {
        [0.0, 0.0, 1.0]
    };
    b[1] = -C1 * y;
    b[2] = C1 * z;
    b[3] = -C1 * x;
    if degree == 1 {
        return b;
    }
    let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
    b[4] = C2[0] * xy;
    b[5] = C2[1] * yz;
    b[6] = C2[2] * (2.0 * zz - xx - yy);
    b[7] = C2[3] * xz;
    b[8] = C2[4] * (xx - yy);
    if degree == 2 {
        return b;
    }
    b[9] = C3[0] * y * (3.0 * xx - yy);
    b[10] = C3[1] * xy * z;
    b[11] = C3[2] * y * (4.0 * zz - xx - yy);
    b[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    b[13] = C3[4] * x * (4.0 * zz - xx - yy);
    b[14] = C3[5] * z * (xx - yy);
    b[15] = C3[6] * x * (xx - 3.0 * yy);
    b
}

/// One PLY vertex, properties placed by name.
struct PlyVertex {
    /// x y z, f_dc 0..2, opacity, scale 0..2, rot 0..3, then f_rest 0..44.
    values: [f32; 14 + MAX_REST],
}

const FIXED_NAMES: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

fn slot_of(name: &str) -> Option<usize> {
    if let Some(i) = FIXED_NAMES.iter().position(|n| *n == name) {
        return Some(i);
    }
    let k: usize = name.strip_prefix("f_rest_")?.parse().ok()?;
    (k < MAX_REST).then_some(14 + k)
}

impl PropertyAccess for PlyVertex {
    fn new() -> Self {
        Self {
            values: [0.0; 14 + MAX_REST],
        }
    }

    fn set_float(&mut self, name: &str, value: f32) -> PropertyAccessResult {
        match slot_of(name) {
            Some(i) => {
                self.values[i] = value;
                PropertyAccessResult::Set
            }
            None => PropertyAccessResult::Ignored,
        }
    }

    fn set_double(&mut self, name: &str, value: f64) -> PropertyAccessResult {
        self.set_float(name, value as f32)
    }
}

/// Reads a 3DGS PLY; errors name the file and the missing or malformed field.
pub fn read_splat_ply(path: &Path) -> Result<SplatScene> {
    let file = std::fs::File::open(path)
        .with_context(|| format!("cannot open PLY file {}", path.display()))?;
    let parser = Parser::<PlyVertex>::new();
    let mut reader = Reader::new(BufReader::new(file));
    let header = parser
        .read_header(&mut reader)
        .with_context(|| format!("{}: malformed PLY header", path.display()))?;
    let Some(vertex) = header.elements.get("vertex") else {
        bail!("{}: no 'vertex' element in the PLY header", path.display());
    };
    for name in FIXED_NAMES {
        match vertex.properties.get(name) {
            None => bail!(
                "{}: vertex property '{name}' is missing (not a 3DGS PLY?)",
                path.display()
            ),
            Some(def) => match def.data_type {
                PropertyType::Scalar(ScalarType::Float | ScalarType::Double) => {}
                ref other => bail!(
                    "{}: vertex property '{name}' has type {other:?}, expected float",
                    path.display()
                ),
            },
        }
    }
    let rest = (0..)
        .take_while(|k| vertex.properties.get(&format!("f_rest_{k}")).is_some())
        .count();
    let sh_degree = match rest {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        n => bail!(
            "{}: {n} f_rest properties; expected 0, 9, 24 or 45 (SH degree 0-3)",
            path.display()
        ),
    };
    // Elements before 'vertex' would have to be read first; 3DGS files have only 'vertex'.
    if header.elements.keys().next().map(String::as_str) != Some("vertex") {
        bail!("{}: 'vertex' must be the first PLY element", path.display());
    }
    let vertex = vertex.clone();
    let vertices = parser
        .read_payload_for_element(&mut reader, &vertex, &header)
        .with_context(|| format!("{}: malformed or truncated PLY payload", path.display()))?;

    let coeffs = SH_COEFFS[sh_degree];
    let rest_per_channel = coeffs - 1;
    let mut scene = SplatScene {
        sh_degree,
        ..Default::default()
    };
    for (index, v) in vertices.iter().enumerate() {
        let x = &v.values;
        if let Some(bad) = x[..14 + 3 * rest_per_channel]
            .iter()
            .position(|v| !v.is_finite())
        {
            let field = if bad < 14 {
                FIXED_NAMES[bad].to_string()
            } else {
                format!("f_rest_{}", bad - 14)
            };
            bail!(
                "{}: vertex {index} has a non-finite '{field}'",
                path.display()
            );
        }
        scene.means.extend_from_slice(&x[0..3]);
        scene.opacities.push(sigmoid(x[6]));
        scene.scales.extend(x[7..10].iter().map(|s| s.exp()));
        scene.quats.extend_from_slice(&x[10..14]);
        scene.sh.extend_from_slice(&x[3..6]);
        // f_rest is channel-major: f_rest[c * rest + j] is coefficient j + 1 of channel c.
        for j in 0..rest_per_channel {
            for c in 0..3 {
                scene.sh.push(x[14 + c * rest_per_channel + j]);
            }
        }
    }
    Ok(scene)
}

/// Writes a scene as a binary little-endian 3DGS PLY (inverse activations applied).
pub fn write_splat_ply(path: &Path, scene: &SplatScene) -> Result<()> {
    std::fs::write(path, splat_ply_bytes(scene))
        .with_context(|| format!("cannot write {}", path.display()))
}

/// `scene` as the bytes of a binary little-endian 3DGS PLY (inverse activations applied).
pub fn splat_ply_bytes(scene: &SplatScene) -> Vec<u8> {
    let mut out = Vec::with_capacity(256 + scene.len() * 4 * (14 + 3 * (scene.coeffs() - 1)));
    let rest = scene.coeffs() - 1;
    // Writing to a Vec cannot fail.
    let _ = writeln!(
        out,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}",
        scene.len()
    );
    for name in ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] {
        let _ = writeln!(out, "property float {name}");
    }
    for k in 0..3 * rest {
        let _ = writeln!(out, "property float f_rest_{k}");
    }
    for name in [
        "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        let _ = writeln!(out, "property float {name}");
    }
    let _ = writeln!(out, "end_header");
    let k = scene.coeffs();
    for i in 0..scene.len() {
        let mut row: Vec<f32> = scene.means[3 * i..3 * i + 3].to_vec();
        row.extend_from_slice(&scene.sh[i * k * 3..i * k * 3 + 3]);
        for c in 0..3 {
            for j in 1..k {
                row.push(scene.sh[(i * k + j) * 3 + c]);
            }
        }
        let o = scene.opacities[i].clamp(1e-7, 1.0 - 1e-7);
        row.push(logit(o));
        row.extend(scene.scales[3 * i..3 * i + 3].iter().map(|s| s.ln()));
        row.extend_from_slice(&scene.quats[4 * i..4 * i + 4]);
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}
