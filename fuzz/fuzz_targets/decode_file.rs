//! Whole files: the container's framing and checksums, then the scene decoder. Any input must
//! give Ok or an error, never a panic, a hang or an allocation beyond the file's own limits.
#![no_main]

use acags::codec::bitstream::QuantizedScene;
use acags::codec::container::Container;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(container) = Container::from_bytes(data, "fuzz") {
        let _ = QuantizedScene::decode(&container, "fuzz");
    }
});
