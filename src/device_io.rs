//! Host↔device crossings of acags' step code, counted (`acags_kernels::transfers`): every
//! upload of host values into a tensor and every read-back of a tensor's values goes through
//! here, so `bench train` can report them per step.

use burn::tensor::kind::Basic;
use burn::tensor::{Device, Tensor, TensorData};

pub use acags_kernels::transfers::TransferCounts;
use acags_kernels::transfers::{record_read_back, record_upload};

/// A tensor on `device` holding `data` (one upload).
/// With `ACAGS_TRACE_UPLOADS` set, each upload is written to stderr as `upload BYTES FILE:LINE`
/// (the caller), to find which code sends what.
#[track_caller]
pub fn upload<const D: usize, K: Basic>(data: TensorData, device: &Device) -> Tensor<D, K> {
    record_upload(data.bytes().len());
    static TRACE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    if *TRACE.get_or_init(|| std::env::var_os("ACAGS_TRACE_UPLOADS").is_some()) {
        eprintln!(
            "upload {} {}",
            data.bytes().len(),
            std::panic::Location::caller()
        );
    }
    Tensor::from_data(data, device)
}

/// The values of `t` on the host (one read-back: the host waits for the device).
pub fn read_back<const D: usize, K: Basic>(t: Tensor<D, K>) -> TensorData {
    let data = t.into_data();
    record_read_back(data.bytes().len());
    data
}

/// Device constants uploaded once per key and device and then reused (issue 21: a step sends no
/// table it has sent before), e.g. the stream window's averaging matrix or γ(t) of a frame.
/// Entries are few and small; past `limit` the list starts over (a process that sees many keys,
/// such as a schedule that changes the key every step, re-uploads instead of growing).
pub struct KeptUploads<K, const D: usize> {
    entries: std::sync::Mutex<Vec<(K, Device, bool, Tensor<D>)>>,
    limit: usize,
}

impl<K: PartialEq, const D: usize> KeptUploads<K, D> {
    pub const fn new(limit: usize) -> Self {
        Self {
            entries: std::sync::Mutex::new(Vec::new()),
            limit,
        }
    }

    /// The tensor kept for `key` on `device` (autodiff or not counts: [`Device`]'s equality
    /// ignores it), or `make()`'s values uploaded now and kept.
    #[track_caller]
    pub fn get(&self, key: K, device: &Device, make: impl FnOnce() -> TensorData) -> Tensor<D> {
        let autodiff = device.is_autodiff();
        let mut entries = self.entries.lock().unwrap();
        if let Some((.., kept)) = entries
            .iter()
            .find(|(k, d, a, _)| *k == key && d == device && *a == autodiff)
        {
            return kept.clone();
        }
        let tensor = upload::<D, burn::tensor::Float>(make(), device);
        if entries.len() >= self.limit {
            entries.clear();
        }
        entries.push((key, device.clone(), autodiff, tensor.clone()));
        tensor
    }
}
