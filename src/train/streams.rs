//! The independent random streams of a training step. Every random choice of a step comes from a
//! generator seeded by (seed, step, purpose), so a run resumed from a checkpoint draws exactly
//! what an uninterrupted one would.

use rand::{SeedableRng, rngs::StdRng};

/// What a stream is drawn for (the discriminant is part of the seed: never renumber).
#[derive(Clone, Copy, Debug)]
pub enum Stream {
    Smoothness = 1,
    Densify = 2,
    Relocate = 3,
    Quantization = 4,
    Rate = 5,
    Curriculum = 6,
}

/// The generator of `stream` at `step`.
pub fn step_rng(seed: u64, step: usize, stream: Stream) -> StdRng {
    let mixed = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add((step as u64) << 8 | stream as u64);
    StdRng::seed_from_u64(mixed)
}
