//! The `scene.acags` container: exact round trips, byte-identical re-encoding, and a clear error
//! (never a panic, never wrong data) for every truncation and every single-bit flip of a file,
//! and for wrong versions and checksums.

use acags::codec::container::{Container, FORMAT_VERSION, MAGIC};
use rand::{Rng, SeedableRng, rngs::StdRng};

fn sample() -> Container {
    let mut rng = StdRng::seed_from_u64(5);
    let mut c = Container::default();
    c.push("decoders", (0..300).map(|_| rng.random()).collect())
        .unwrap();
    c.push("positions", (0..77).map(|_| rng.random()).collect())
        .unwrap();
    c.push("empty", Vec::new()).unwrap();
    c.push("gates", vec![0b1010_1010; 13]).unwrap();
    c
}

#[test]
fn round_trip_is_exact_and_reencoding_is_byte_identical() {
    let c = sample();
    let bytes = c.to_bytes();
    assert_eq!(&bytes[..8], &MAGIC);
    let back = Container::from_bytes(&bytes, "mem").unwrap();
    assert_eq!(back, c);
    assert_eq!(back.to_bytes(), bytes);
    assert_eq!(back.get("gates"), Some(&[0b1010_1010u8; 13][..]));
    assert_eq!(back.get("empty"), Some(&[][..]));
    assert!(back.get("missing").is_none());
    // Through a file.
    let dir = std::env::temp_dir().join(format!("acags-container-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scene.acags");
    c.write(&path).unwrap();
    assert_eq!(Container::read(&path).unwrap(), c);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn every_truncation_and_every_bit_flip_is_rejected_with_a_message() {
    let bytes = sample().to_bytes();
    for len in 0..bytes.len() {
        let err = Container::from_bytes(&bytes[..len], "cut.acags").unwrap_err();
        assert!(err.to_string().starts_with("cut.acags: "), "{err}");
    }
    let mut flips = 0;
    for byte in 0..bytes.len() {
        for bit in 0..8 {
            let mut damaged = bytes.clone();
            damaged[byte] ^= 1 << bit;
            let err = Container::from_bytes(&damaged, "flip.acags")
                .expect_err("a flipped bit must not decode");
            assert!(err.to_string().starts_with("flip.acags: "), "{err}");
            flips += 1;
        }
    }
    assert!(flips > 3000, "{flips} corrupted inputs");
    // Extra bytes after the last section.
    let mut longer = bytes.clone();
    longer.push(0);
    let err = Container::from_bytes(&longer, "long.acags").unwrap_err();
    assert!(err.to_string().contains("unexpected bytes"), "{err}");
}

#[test]
fn random_garbage_never_panics() {
    let mut rng = StdRng::seed_from_u64(9);
    let valid = sample().to_bytes();
    for i in 0..2000 {
        // Random bytes behind a valid prefix of random length, and random splices.
        let keep = rng.random_range(0..valid.len());
        let mut bytes = valid[..keep].to_vec();
        bytes.extend((0..rng.random_range(0..64)).map(|_| rng.random::<u8>()));
        if i % 2 == 0 {
            let at = rng.random_range(0..valid.len());
            bytes = [&valid[..at], &bytes[..]].concat();
        }
        if bytes != valid {
            assert!(Container::from_bytes(&bytes, "garbage").is_err());
        }
    }
}

#[test]
fn wrong_version_and_bad_names_are_named() {
    let mut bytes = sample().to_bytes();
    bytes[8..10].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
    let err = Container::from_bytes(&bytes, "v.acags")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("format version 2") && err.contains("version 1"),
        "{err}"
    );
    let err = Container::from_bytes(b"PK\x03\x04 not ours at all", "zip.acags")
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad magic"), "{err}");
    let mut c = Container::default();
    assert!(c.push("", vec![]).is_err());
    assert!(c.push("seventeen_chars__", vec![]).is_err());
    assert!(c.push("with space", vec![]).is_err());
    c.push("a", vec![1]).unwrap();
    assert!(
        c.push("a", vec![2])
            .unwrap_err()
            .to_string()
            .contains("duplicate")
    );
}
