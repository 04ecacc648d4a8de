//! Section payloads behind valid checksums (what a buggy writer would produce): the input is a
//! sequence of `u32 length + bytes` records assigned to the scene's sections in file order
//! (`container_from_records`), so the fuzzer reaches every section parser and the rANS glue
//! directly instead of stopping at a CRC mismatch. `records_from_container` turns a real file
//! into a corpus seed.
#![no_main]

use acags::codec::bitstream::{QuantizedScene, container_from_records};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = QuantizedScene::decode(&container_from_records(data), "fuzz");
});
