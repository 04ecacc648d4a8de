//! NumPy arrays (`.npy`, and arrays inside `.npz`) as f64, with errors naming the file.

use std::io::Read;
use std::path::Path;

use anyhow::{Context, Result, bail};
use npyz::{DType, NpyFile, Order};

/// A dense row-major array.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl Array {
    /// Checks the shape is [rows, cols] with `cols` fixed; returns rows.
    pub fn expect_matrix(&self, cols: usize, what: &str) -> Result<usize> {
        match self.shape.as_slice() {
            [rows, c] if *c == cols => Ok(*rows),
            other => bail!("{what} has shape {other:?}, expected [N, {cols}]"),
        }
    }

    pub fn row(&self, r: usize) -> &[f64] {
        let cols = self.shape[1];
        &self.data[r * cols..(r + 1) * cols]
    }
}

fn decode<R: Read>(npy: NpyFile<R>) -> Result<Array> {
    if npy.order() == Order::Fortran {
        bail!("Fortran-ordered arrays are not supported (save with np.ascontiguousarray)");
    }
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let DType::Plain(type_str) = npy.dtype() else {
        bail!(
            "structured dtype {:?} is not supported; expected a float array",
            npy.dtype()
        );
    };
    let descr = type_str.to_string();
    let data: Vec<f64> = match descr.as_str() {
        "<f8" | ">f8" => npy.into_vec::<f64>()?,
        "<f4" | ">f4" => npy.into_vec::<f32>()?.into_iter().map(f64::from).collect(),
        other => bail!("unsupported dtype '{other}'; expected float32 or float64"),
    };
    Ok(Array { shape, data })
}

pub fn read_npy(path: &Path) -> Result<Array> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let npy = NpyFile::new(&bytes[..])
        .with_context(|| format!("{}: not a valid .npy file", path.display()))?;
    decode(npy).with_context(|| format!("{}", path.display()))
}

/// Array `name` of an `.npz` archive.
pub fn read_npz_array(path: &Path, name: &str) -> Result<Array> {
    let mut npz = npyz::npz::NpzArchive::open(path)
        .with_context(|| format!("{}: not a readable .npz archive", path.display()))?;
    let npy = npz
        .by_name(name)
        .with_context(|| format!("{}: array '{name}' is corrupt", path.display()))?
        .with_context(|| format!("{}: no array named '{name}'", path.display()))?;
    decode(npy).with_context(|| format!("{}: array '{name}'", path.display()))
}

/// Writes a float64 array (used for `poses_bounds.npy` of generated datasets).
pub fn write_npy_f64(path: &Path, shape: &[usize], data: &[f64]) -> Result<()> {
    use npyz::WriterBuilder;
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let shape: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut writer = npyz::WriteOptions::<f64>::new()
        .default_dtype()
        .shape(&shape)
        .writer(std::io::BufWriter::new(file))
        .begin_nd()?;
    writer.extend(data.iter().copied())?;
    writer
        .finish()
        .with_context(|| format!("cannot write {}", path.display()))
}
