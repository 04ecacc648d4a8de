//! The independent random streams of a training step. Every random choice of a step comes from a
//! generator seeded by (seed, step, purpose), so a run resumed from a checkpoint draws exactly
//! what an uninterrupted one would.

use acags_kernels::counter_noise::NoiseStream;
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

/// The device-drawn noise tensors of `stream` at `step` (`acags_kernels::counter_noise`): what
/// the quantisation simulation and the rate term add, keyed like [`step_rng`] so a resumed run
/// draws the same noise.
pub fn step_noise(seed: u64, step: usize, stream: Stream) -> NoiseStream {
    NoiseStream {
        seed,
        step: step as u64,
        stream: stream as u32,
    }
}
