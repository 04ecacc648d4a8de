//! Initial point clouds: COLMAP `points3D.bin` / `points3D.txt`, or a `points3D.ply` with
//! x y z and optional red green blue (uchar 0-255 or float 0-1).

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use anyhow::{Context, Result, bail};
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};

use super::scene::PointCloud;

/// Reads `points3D.bin` (COLMAP binary model).
pub fn read_points3d_bin(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut r = &bytes[..];
    let ctx = |what: &str| format!("{}: truncated COLMAP points3D.bin ({what})", path.display());
    let u64_le = |r: &mut &[u8], what: &str| -> Result<u64> {
        let mut b = [0u8; 8];
        r.read_exact(&mut b).with_context(|| ctx(what))?;
        Ok(u64::from_le_bytes(b))
    };
    let count = u64_le(&mut r, "point count")?;
    // Each point takes at least 43 bytes: reject absurd counts before allocating.
    if count > bytes.len() as u64 / 43 {
        bail!(
            "{}: claims {count} points but holds {} bytes",
            path.display(),
            bytes.len()
        );
    }
    let mut cloud = PointCloud::default();
    for i in 0..count {
        let mut rec = [0u8; 8 + 24 + 3 + 8];
        r.read_exact(&mut rec)
            .with_context(|| ctx(&format!("point {i}")))?;
        let f = |o: usize| f64::from_le_bytes(rec[o..o + 8].try_into().unwrap());
        let xyz = [f(8), f(16), f(24)];
        let rgb = [rec[32], rec[33], rec[34]];
        let track_len = u64_le(&mut r, "track length")?;
        let skip = track_len
            .checked_mul(8)
            .filter(|&s| s <= r.len() as u64)
            .with_context(|| ctx(&format!("track of point {i}")))?;
        r = &r[skip as usize..];
        if xyz.iter().any(|v| !v.is_finite()) {
            bail!("{}: point {i} has a non-finite coordinate", path.display());
        }
        cloud.positions.push(xyz.map(|v| v as f32));
        cloud.colors.push(rgb.map(|c| c as f32 / 255.0));
    }
    Ok(cloud)
}

/// Reads `points3D.txt` (COLMAP text model): `ID X Y Z R G B ERROR TRACK...` per line.
pub fn read_points3d_txt(path: &Path) -> Result<PointCloud> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut cloud = PointCloud::default();
    for (n, line) in BufReader::new(file).lines().enumerate() {
        let line =
            line.with_context(|| format!("{}: unreadable line {}", path.display(), n + 1))?;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        let parse = |i: usize| -> Result<f64> {
            let v: f64 = fields
                .get(i)
                .with_context(|| {
                    format!("{}:{}: expected at least 8 fields", path.display(), n + 1)
                })?
                .parse()
                .with_context(|| {
                    format!(
                        "{}:{}: field {} is not a number",
                        path.display(),
                        n + 1,
                        i + 1
                    )
                })?;
            if !v.is_finite() {
                bail!(
                    "{}:{}: field {} is not finite",
                    path.display(),
                    n + 1,
                    i + 1
                );
            }
            Ok(v)
        };
        cloud
            .positions
            .push([parse(1)? as f32, parse(2)? as f32, parse(3)? as f32]);
        cloud.colors.push([
            parse(4)? as f32 / 255.0,
            parse(5)? as f32 / 255.0,
            parse(6)? as f32 / 255.0,
        ]);
        parse(7)?;
    }
    Ok(cloud)
}

/// Writes `points3D.txt` (empty tracks, error 0).
pub fn write_points3d_txt(path: &Path, cloud: &PointCloud) -> Result<()> {
    let mut out = String::from(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
    );
    for (i, (p, c)) in cloud.positions.iter().zip(&cloud.colors).enumerate() {
        let rgb = c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
        out.push_str(&format!(
            "{} {} {} {} {} {} {} 0\n",
            i + 1,
            p[0],
            p[1],
            p[2],
            rgb[0],
            rgb[1],
            rgb[2]
        ));
    }
    let mut f =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    f.write_all(out.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

fn property_f32(p: &Property) -> Option<f32> {
    p.to_f32_lossy()
}

/// Reads a point PLY (`x y z` and optional colours).
pub fn read_points_ply(path: &Path) -> Result<PointCloud> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut BufReader::new(file))
        .with_context(|| format!("{}: malformed PLY", path.display()))?;
    let vertices = ply
        .payload
        .get("vertex")
        .with_context(|| format!("{}: no 'vertex' element", path.display()))?;
    let mut cloud = PointCloud::default();
    for (i, v) in vertices.iter().enumerate() {
        let get = |k: &str| v.get(k).and_then(property_f32);
        let (Some(x), Some(y), Some(z)) = (get("x"), get("y"), get("z")) else {
            bail!("{}: vertex {i} lacks x, y or z", path.display());
        };
        let color = match (v.get("red"), v.get("green"), v.get("blue")) {
            (Some(r), Some(g), Some(b)) => {
                let divisor = if matches!(r, Property::UChar(_)) {
                    255.0
                } else {
                    1.0
                };
                [r, g, b].map(|c| property_f32(c).unwrap_or(0.5) / divisor)
            }
            _ => [0.5; 3],
        };
        cloud.positions.push([x, y, z]);
        cloud.colors.push(color);
    }
    Ok(cloud)
}
