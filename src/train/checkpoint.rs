//! Checkpoint files: named f32 tensors in safetensors plus one JSON metadata entry, written
//! atomically (a temporary file in the same directory, synced, then renamed over the old one), so
//! a kill mid-write leaves the previous checkpoint intact.

use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result, bail};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

/// Key of the JSON metadata inside the safetensors header.
const METADATA_KEY: &str = "acags";

/// Named f32 arrays with their shapes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NamedTensors {
    pub entries: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
}

impl NamedTensors {
    pub fn insert(&mut self, name: impl Into<String>, shape: Vec<usize>, values: Vec<f32>) {
        assert_eq!(
            shape.iter().product::<usize>(),
            values.len(),
            "tensor shape and value count disagree"
        );
        self.entries.insert(name.into(), (shape, values));
    }

    /// The tensor `name`, which must have `rank` dimensions; `origin` names the file in errors.
    pub fn get(&self, name: &str, origin: &Path) -> Result<&(Vec<usize>, Vec<f32>)> {
        self.entries
            .get(name)
            .with_context(|| format!("{}: tensor `{name}` is missing", origin.display()))
    }

    /// [`Self::take`] of `name`, or of `former` (the name older checkpoints wrote) when only that
    /// is present.
    pub fn take_renamed(
        &mut self,
        name: &str,
        former: &str,
        expected: &[Option<usize>],
        origin: &Path,
    ) -> Result<(Vec<usize>, Vec<f32>)> {
        let stored = if !self.entries.contains_key(name) && self.entries.contains_key(former) {
            former
        } else {
            name
        };
        self.take(stored, expected, origin)
    }

    /// Removes and returns `name`, checking its shape against `expected` (None = any extent).
    pub fn take(
        &mut self,
        name: &str,
        expected: &[Option<usize>],
        origin: &Path,
    ) -> Result<(Vec<usize>, Vec<f32>)> {
        let (shape, values) = self
            .entries
            .remove(name)
            .with_context(|| format!("{}: tensor `{name}` is missing", origin.display()))?;
        let fits = shape.len() == expected.len()
            && shape
                .iter()
                .zip(expected)
                .all(|(s, e)| e.is_none_or(|e| e == *s));
        if !fits {
            bail!(
                "{}: tensor `{name}` has shape {shape:?}, expected {:?}",
                origin.display(),
                expected
                    .iter()
                    .map(|e| e.map_or("*".to_string(), |v| v.to_string()))
                    .collect::<Vec<_>>()
            );
        }
        Ok((shape, values))
    }
}

/// Writes `tensors` and `metadata` to `path` atomically.
pub fn write_checkpoint(
    path: &Path,
    tensors: &NamedTensors,
    metadata: &serde_json::Value,
) -> Result<()> {
    let bytes: Vec<(String, Vec<u8>, Vec<usize>)> = tensors
        .entries
        .iter()
        .map(|(name, (shape, values))| {
            let raw = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name.clone(), raw, shape.clone())
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(name, raw, shape)| {
            TensorView::new(Dtype::F32, shape.clone(), raw).map(|v| (name.as_str(), v))
        })
        .collect::<Result<Vec<_>, _>>()
        .context("building the checkpoint")?;
    let info = HashMap::from([(METADATA_KEY.to_string(), metadata.to_string())]);
    let serialized =
        safetensors::serialize(views, Some(info)).context("serialising the checkpoint")?;

    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let tmp = dir.join(format!(
        ".{}.tmp-{}",
        path.file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("checkpoint"),
        std::process::id()
    ));
    let result = (|| -> Result<()> {
        let mut file = std::fs::File::create(&tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        file.write_all(&serialized)
            .with_context(|| format!("cannot write {}", tmp.display()))?;
        file.sync_all()
            .with_context(|| format!("cannot sync {}", tmp.display()))?;
        std::fs::rename(&tmp, path)
            .with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Reads a checkpoint written by [`write_checkpoint`].
pub fn read_checkpoint(path: &Path) -> Result<(NamedTensors, serde_json::Value)> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read checkpoint {}", path.display()))?;
    let parsed = SafeTensors::deserialize(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: not a valid checkpoint ({e})", path.display()))?;
    let (_, header) = SafeTensors::read_metadata(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: not a valid checkpoint ({e})", path.display()))?;
    let metadata = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get(METADATA_KEY))
        .with_context(|| format!("{}: not an acags checkpoint (no metadata)", path.display()))?;
    let metadata: serde_json::Value = serde_json::from_str(metadata)
        .with_context(|| format!("{}: checkpoint metadata is not JSON", path.display()))?;
    let mut tensors = NamedTensors::default();
    for name in parsed.names() {
        let view = parsed.tensor(name).expect("listed tensor");
        if view.dtype() != Dtype::F32 {
            bail!(
                "{}: tensor `{name}` is {:?}, expected F32",
                path.display(),
                view.dtype()
            );
        }
        let values = view
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        tensors.insert(name, view.shape().to_vec(), values);
    }
    Ok((tensors, metadata))
}
