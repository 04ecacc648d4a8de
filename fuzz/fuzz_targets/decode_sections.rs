//! Section payloads behind valid checksums (what a buggy writer would produce): the input is a
//! sequence of `u32 length + bytes` records assigned to the scene's sections in file order, so
//! the fuzzer reaches every section parser and the rANS glue directly instead of stopping at a
//! CRC mismatch.
#![no_main]

use acags::codec::bitstream::QuantizedScene;
use acags::codec::container::Container;
use libfuzzer_sys::fuzz_target;

const NAMES: [&str; 11] = [
    "meta",
    "decoders",
    "entropy_models",
    "positions",
    "slot_gates",
    "feature_mask",
    "features",
    "factors",
    "log_scales",
    "offsets",
    "time_features",
];

fuzz_target!(|data: &[u8]| {
    let mut container = Container::default();
    let mut rest = data;
    for name in NAMES {
        if rest.len() < 4 {
            break;
        }
        let len = u32::from_le_bytes(rest[..4].try_into().unwrap()) as usize;
        rest = &rest[4..];
        let take = len.min(rest.len());
        // An empty record skips the section (e.g. no entropy models, no feature mask).
        if take > 0 {
            let _ = container.push(name, rest[..take].to_vec());
        }
        rest = &rest[take..];
    }
    let _ = QuantizedScene::decode(&container, "fuzz");
});
