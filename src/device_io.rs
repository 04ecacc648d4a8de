//! Host↔device crossings of acags' step code, counted (`acags_kernels::transfers`): every
//! upload of host values into a tensor and every read-back of a tensor's values goes through
//! here, so `bench train` can report them per step.

use burn::tensor::kind::Basic;
use burn::tensor::{Device, Tensor, TensorData};

pub use acags_kernels::transfers::TransferCounts;
use acags_kernels::transfers::{record_read_back, record_upload};

/// Whether tensors on `device` live in host memory (ndarray): there a read-back costs no
/// synchronisation, and host versions of some steps are the fast path.
pub fn is_host_device(device: &Device) -> bool {
    matches!(
        device.clone().inner().as_dispatch(),
        burn::backend::DispatchDevice::NdArray(_)
    )
}

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
/// Entries are few and small; past `limit` the list starts over (a process that sees many keys
/// re-uploads instead of growing).
///
/// A kept tensor is a constant: on an autodiff device a leaf that requires no gradient, which
/// no graph registers, so it may feed any number of graphs, on any thread. Never call
/// `require_grad` on one (that would make the shared leaf a root of some graph).
pub struct KeptUploads<K, const D: usize> {
    entries: std::sync::Mutex<Vec<(K, KeptOn, Tensor<D>)>>,
    limit: usize,
}

/// A device as far as a tensor on it can be used on another: [`Device`]'s equality ignores the
/// autodiff wrapper and its checkpointing strategy, which must match as well.
#[derive(PartialEq)]
struct KeptOn {
    device: Device,
    autodiff: Option<burn::tensor::GradientCheckpointingStrategy>,
}

impl KeptOn {
    fn of(device: &Device) -> Self {
        Self {
            device: device.clone(),
            autodiff: device.gradient_checkpointing_strategy(),
        }
    }
}

impl<K: PartialEq, const D: usize> KeptUploads<K, D> {
    pub const fn new(limit: usize) -> Self {
        Self {
            entries: std::sync::Mutex::new(Vec::new()),
            limit,
        }
    }

    /// The tensor kept for `key` on `device`, or `make()`'s values uploaded now and kept.
    #[track_caller]
    pub fn get(&self, key: K, device: &Device, make: impl FnOnce() -> TensorData) -> Tensor<D> {
        let on = KeptOn::of(device);
        let mut entries = self.entries.lock().unwrap();
        if let Some((.., kept)) = entries.iter().find(|(k, o, _)| *k == key && *o == on) {
            return kept.clone();
        }
        let tensor = upload::<D, burn::tensor::Float>(make(), device);
        if entries.len() >= self.limit {
            entries.clear();
        }
        entries.push((key, on, tensor.clone()));
        tensor
    }

    /// Tensors kept now.
    pub fn len(&self) -> usize {
        self.entries.lock().unwrap().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)] // Device::ndarray
    use super::*;

    #[test]
    fn a_constant_is_uploaded_once_per_key_and_device_kind() {
        let kept: KeptUploads<u32, 1> = KeptUploads::new(3);
        let made = std::cell::Cell::new(0);
        let make = |v: f32| {
            made.set(made.get() + 1);
            TensorData::new(vec![v; 2], [2])
        };
        let plain = Device::ndarray();
        let tracked = plain.clone().autodiff();
        let a = kept.get(1, &plain, || make(1.0));
        let again = kept.get(1, &plain, || make(9.0));
        assert_eq!(made.get(), 1, "a second use of the key uploads nothing");
        assert_eq!(again.into_data(), a.into_data());
        // The same hardware with autodiff on is another entry (the devices compare equal).
        assert_eq!(plain, tracked);
        let t = kept.get(1, &tracked, || make(1.0));
        assert!(t.device().is_autodiff());
        kept.get(2, &plain, || make(2.0));
        assert_eq!((made.get(), kept.len()), (3, 3));
        // Past the limit the list starts over.
        kept.get(3, &plain, || make(3.0));
        assert_eq!((made.get(), kept.len()), (4, 1));
    }
}
