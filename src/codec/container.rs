//! The `scene.acags` container: a versioned header, a table of named sections with lengths and
//! CRC-32 checksums, then the section payloads. The codec (issue "End-to-end compression") puts
//! the decoders, entropy-model weights, positions, gate/mask bitmaps and coded attributes into
//! sections; this module only guarantees that what is read back is exactly what was written, and
//! that any damaged file is rejected with a message naming the file and the problem.
//!
//! Layout (little-endian):
//! ```text
//! magic    8 bytes  "ACAGS\r\n\x1a"   (a text-mode transfer or a `type` to a terminal shows)
//! version  u16      FORMAT_VERSION
//! count    u16      number of sections
//! table    count × { name: 16 bytes, NUL-padded ASCII; offset: u64; length: u64; crc32: u32 }
//! tablecrc u32      CRC-32 of everything before it
//! payloads          concatenated in table order, each at its offset, no gaps, file ends after
//!                   the last one
//! ```

use std::path::Path;

use anyhow::{Result, bail};

pub const MAGIC: [u8; 8] = *b"ACAGS\r\n\x1a";
pub const FORMAT_VERSION: u16 = 1;
/// Bytes of a section name in the table.
pub const NAME_BYTES: usize = 16;
const ENTRY_BYTES: usize = NAME_BYTES + 8 + 8 + 4;
const PREFIX_BYTES: usize = MAGIC.len() + 2 + 2;

/// One named payload.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Section {
    pub name: String,
    pub data: Vec<u8>,
}

/// Sections in file order.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Container {
    pub sections: Vec<Section>,
}

impl Container {
    /// Appends a section; names are 1-16 printable ASCII characters and unique.
    pub fn push(&mut self, name: &str, data: Vec<u8>) -> Result<()> {
        check_name(name)?;
        if self.get(name).is_some() {
            bail!("duplicate section `{name}`");
        }
        self.sections.push(Section {
            name: name.to_string(),
            data,
        });
        Ok(())
    }

    pub fn get(&self, name: &str) -> Option<&[u8]> {
        self.sections
            .iter()
            .find(|s| s.name == name)
            .map(|s| s.data.as_slice())
    }

    /// The bytes of the file; the same container always gives the same bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let count = u16::try_from(self.sections.len()).expect("at most 65535 sections");
        let payload_start = (PREFIX_BYTES + self.sections.len() * ENTRY_BYTES + 4) as u64;
        let mut out = Vec::with_capacity(
            payload_start as usize + self.sections.iter().map(|s| s.data.len()).sum::<usize>(),
        );
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&count.to_le_bytes());
        let mut offset = payload_start;
        for s in &self.sections {
            let mut name = [0u8; NAME_BYTES];
            name[..s.name.len()].copy_from_slice(s.name.as_bytes());
            out.extend_from_slice(&name);
            out.extend_from_slice(&offset.to_le_bytes());
            out.extend_from_slice(&(s.data.len() as u64).to_le_bytes());
            out.extend_from_slice(&crc32fast::hash(&s.data).to_le_bytes());
            offset += s.data.len() as u64;
        }
        let table_crc = crc32fast::hash(&out);
        out.extend_from_slice(&table_crc.to_le_bytes());
        for s in &self.sections {
            out.extend_from_slice(&s.data);
        }
        out
    }

    /// Parses a file's bytes; `origin` names the file in errors.
    pub fn from_bytes(bytes: &[u8], origin: &str) -> Result<Self> {
        let fail = |what: String| anyhow::anyhow!("{origin}: {what}");
        if bytes.len() < PREFIX_BYTES {
            return Err(fail(format!(
                "truncated: {} bytes is shorter than the {PREFIX_BYTES}-byte header",
                bytes.len()
            )));
        }
        if bytes[..MAGIC.len()] != MAGIC {
            return Err(fail("not an acags bitstream (bad magic bytes)".into()));
        }
        let version = u16::from_le_bytes([bytes[8], bytes[9]]);
        if version != FORMAT_VERSION {
            return Err(fail(format!(
                "format version {version}, this build reads version {FORMAT_VERSION}"
            )));
        }
        let count = u16::from_le_bytes([bytes[10], bytes[11]]) as usize;
        let table_end = PREFIX_BYTES + count * ENTRY_BYTES;
        if bytes.len() < table_end + 4 {
            return Err(fail(format!(
                "truncated: the section table of {count} entries needs {} bytes, the file has {}",
                table_end + 4,
                bytes.len()
            )));
        }
        let stored_crc = u32::from_le_bytes(bytes[table_end..table_end + 4].try_into().unwrap());
        if crc32fast::hash(&bytes[..table_end]) != stored_crc {
            return Err(fail(
                "header checksum mismatch (corrupted section table)".into(),
            ));
        }
        let mut container = Container::default();
        let mut expected_offset = (table_end + 4) as u64;
        for i in 0..count {
            let e = &bytes[PREFIX_BYTES + i * ENTRY_BYTES..PREFIX_BYTES + (i + 1) * ENTRY_BYTES];
            let name_bytes = &e[..NAME_BYTES];
            let len = name_bytes
                .iter()
                .position(|&b| b == 0)
                .unwrap_or(NAME_BYTES);
            if name_bytes[len..].iter().any(|&b| b != 0) {
                return Err(fail(format!("section {i}: malformed name")));
            }
            let name = std::str::from_utf8(&name_bytes[..len])
                .map_err(|_| fail(format!("section {i}: name is not ASCII")))?;
            let at = |k: usize| u64::from_le_bytes(e[k..k + 8].try_into().unwrap());
            let (offset, length) = (at(NAME_BYTES), at(NAME_BYTES + 8));
            let crc = u32::from_le_bytes(e[NAME_BYTES + 16..].try_into().unwrap());
            if offset != expected_offset {
                return Err(fail(format!(
                    "section `{name}` starts at byte {offset}, expected {expected_offset}"
                )));
            }
            let end = offset
                .checked_add(length)
                .filter(|&end| end <= bytes.len() as u64)
                .ok_or_else(|| {
                    fail(format!(
                        "truncated: section `{name}` ({length} bytes at {offset}) runs past the \
                         end of the {}-byte file",
                        bytes.len()
                    ))
                })?;
            let data = &bytes[offset as usize..end as usize];
            if crc32fast::hash(data) != crc {
                return Err(fail(format!("section `{name}`: checksum mismatch")));
            }
            container
                .push(name, data.to_vec())
                .map_err(|e| fail(format!("section {i}: {e}")))?;
            expected_offset = end;
        }
        if expected_offset != bytes.len() as u64 {
            return Err(fail(format!(
                "{} unexpected bytes after the last section",
                bytes.len() as u64 - expected_offset
            )));
        }
        Ok(container)
    }

    /// Writes the file through a temporary file and a rename (never a half-written file).
    pub fn write(&self, path: &Path) -> Result<()> {
        let tmp = path.with_extension("acags.partial");
        std::fs::write(&tmp, self.to_bytes())
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", tmp.display()))?;
        std::fs::rename(&tmp, path)
            .map_err(|e| anyhow::anyhow!("cannot move {} into place: {e}", path.display()))?;
        Ok(())
    }

    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path)
            .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
        Self::from_bytes(&bytes, &path.display().to_string())
    }
}

fn check_name(name: &str) -> Result<()> {
    if name.is_empty() || name.len() > NAME_BYTES || !name.bytes().all(|b| b.is_ascii_graphic()) {
        bail!("section name `{name}` must be 1-{NAME_BYTES} printable ASCII characters");
    }
    Ok(())
}
