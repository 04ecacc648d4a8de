//! Writing renders: 8-bit PNG (RGB) or float32 `.npy` (H x W x 4, RGB + alpha).

use std::path::Path;

use anyhow::{Context, Result, bail};

/// Output format, from the file extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    Png,
    Npy,
}

impl ImageFormat {
    pub fn from_path(path: &Path) -> Result<Self> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => Ok(Self::Png),
            Some("npy") => Ok(Self::Npy),
            _ => bail!("{}: output must end in .png or .npy", path.display()),
        }
    }
}

/// Writes an [H, W, 4] float RGBA buffer (alpha = coverage).
pub fn write_render(path: &Path, rgba: &[f32], width: u32, height: u32) -> Result<()> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(rgba.len(), w * h * 4, "render buffer has the wrong size");
    match ImageFormat::from_path(path)? {
        ImageFormat::Png => {
            let bytes: Vec<u8> = rgba
                .chunks_exact(4)
                .flat_map(|p| [p[0], p[1], p[2]])
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            image::RgbImage::from_raw(width, height, bytes)
                .expect("buffer size checked above")
                .save(path)
                .with_context(|| format!("cannot write {}", path.display()))
        }
        ImageFormat::Npy => {
            let file = std::fs::File::create(path)
                .with_context(|| format!("cannot create {}", path.display()))?;
            use npyz::WriterBuilder;
            let mut writer = npyz::WriteOptions::<f32>::new()
                .default_dtype()
                .shape(&[h as u64, w as u64, 4])
                .writer(std::io::BufWriter::new(file))
                .begin_nd()
                .with_context(|| format!("cannot write {}", path.display()))?;
            writer
                .extend(rgba.iter().copied())
                .with_context(|| format!("cannot write {}", path.display()))?;
            writer
                .finish()
                .with_context(|| format!("cannot write {}", path.display()))
        }
    }
}
