//! Counts of host↔device crossings: every upload of host data into a tensor and every read-back
//! of a tensor's values that acags' step code (and the CubeCL rasterizer's count read-back)
//! performs, for `bench train`'s per-step figures. A read-back waits for the device: each one is a
//! synchronisation. On the CPU backend nothing crosses a bus, but the counts are the same code
//! paths, so they say what a GPU step pays.
//!
//! Process-wide counters (relaxed atomics): a benchmark reads them around the steps it times.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

use serde::Serialize;

static UPLOADS: AtomicU64 = AtomicU64::new(0);
static UPLOAD_BYTES: AtomicU64 = AtomicU64::new(0);
static READ_BACKS: AtomicU64 = AtomicU64::new(0);
static READ_BACK_BYTES: AtomicU64 = AtomicU64::new(0);

pub fn record_upload(bytes: usize) {
    UPLOADS.fetch_add(1, Relaxed);
    UPLOAD_BYTES.fetch_add(bytes as u64, Relaxed);
}

pub fn record_read_back(bytes: usize) {
    READ_BACKS.fetch_add(1, Relaxed);
    READ_BACK_BYTES.fetch_add(bytes as u64, Relaxed);
}

/// Totals so far, or (with [`TransferCounts::since`]) over an interval.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct TransferCounts {
    pub uploads: u64,
    pub upload_bytes: u64,
    /// Each a synchronisation with the device.
    pub read_backs: u64,
    pub read_back_bytes: u64,
}

impl TransferCounts {
    pub fn now() -> Self {
        Self {
            uploads: UPLOADS.load(Relaxed),
            upload_bytes: UPLOAD_BYTES.load(Relaxed),
            read_backs: READ_BACKS.load(Relaxed),
            read_back_bytes: READ_BACK_BYTES.load(Relaxed),
        }
    }

    /// What happened between `earlier` and `self`.
    pub fn since(self, earlier: Self) -> Self {
        Self {
            uploads: self.uploads - earlier.uploads,
            upload_bytes: self.upload_bytes - earlier.upload_bytes,
            read_backs: self.read_backs - earlier.read_backs,
            read_back_bytes: self.read_back_bytes - earlier.read_back_bytes,
        }
    }
}
