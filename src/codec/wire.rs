//! Little-endian writing and bounds-checked reading of section payloads. Every read names the
//! section and what it expected, so a damaged or truncated payload is an error, never a panic.

use anyhow::{Result, bail};

#[derive(Default)]
pub struct Writer {
    pub bytes: Vec<u8>,
}

impl Writer {
    pub fn u8(&mut self, v: u8) {
        self.bytes.push(v);
    }
    pub fn u32(&mut self, v: u32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i32(&mut self, v: i32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32(&mut self, v: f32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32s(&mut self, values: &[f32]) {
        for &v in values {
            self.f32(v);
        }
    }
    /// A length-prefixed byte block.
    pub fn block(&mut self, data: &[u8]) {
        self.u32(data.len() as u32);
        self.bytes.extend_from_slice(data);
    }
    /// LEB128 unsigned varint.
    pub fn varint(&mut self, mut v: u64) {
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                self.bytes.push(byte);
                return;
            }
            self.bytes.push(byte | 0x80);
        }
    }
}

pub struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    /// Names the payload in errors, e.g. "section `offsets`".
    what: String,
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8], what: impl Into<String>) -> Self {
        Self {
            bytes,
            at: 0,
            what: what.into(),
        }
    }

    fn take(&mut self, n: usize, field: &str) -> Result<&'a [u8]> {
        if self.bytes.len() - self.at < n {
            bail!(
                "{}: truncated while reading {field} ({n} bytes at offset {}, {} left)",
                self.what,
                self.at,
                self.bytes.len() - self.at
            );
        }
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    pub fn u8(&mut self, field: &str) -> Result<u8> {
        Ok(self.take(1, field)?[0])
    }
    pub fn u32(&mut self, field: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4, field)?.try_into().unwrap()))
    }
    pub fn i32(&mut self, field: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4, field)?.try_into().unwrap()))
    }
    pub fn f32(&mut self, field: &str) -> Result<f32> {
        Ok(f32::from_le_bytes(self.take(4, field)?.try_into().unwrap()))
    }
    pub fn f32s(&mut self, count: usize, field: &str) -> Result<Vec<f32>> {
        let bytes = self.take(count.checked_mul(4).unwrap_or(usize::MAX), field)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect())
    }
    pub fn block(&mut self, field: &str) -> Result<&'a [u8]> {
        let n = self.u32(field)? as usize;
        self.take(n, field)
    }
    pub fn varint(&mut self, field: &str) -> Result<u64> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let byte = self.u8(field)?;
            v |= ((byte & 0x7f) as u64) << shift;
            if byte & 0x80 == 0 {
                return Ok(v);
            }
        }
        bail!("{}: {field} is not a valid varint", self.what)
    }
    /// Fails unless every byte was read.
    pub fn finish(&self) -> Result<()> {
        if self.at != self.bytes.len() {
            bail!(
                "{}: {} unexpected trailing bytes",
                self.what,
                self.bytes.len() - self.at
            );
        }
        Ok(())
    }
    pub fn what(&self) -> &str {
        &self.what
    }
}
