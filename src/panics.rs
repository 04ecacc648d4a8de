//! Turning caught panics into messages (the CUDA probe, a sweep cell that panics).

use std::any::Any;

/// The text a panic was raised with (`panic!` with a literal gives a `&str`, with arguments a
/// `String`), or `None` for another payload.
pub fn panic_message(payload: &(dyn Any + Send)) -> Option<String> {
    payload
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
}
