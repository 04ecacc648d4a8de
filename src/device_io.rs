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
