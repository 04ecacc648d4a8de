//! Helpers shared by the integration tests of the `acags` crate.

/// An RNG whose uniform draws are all ≈ 1: every random keep test of densification passes.
pub struct AlwaysHigh;

impl rand::RngCore for AlwaysHigh {
    fn next_u32(&mut self) -> u32 {
        u32::MAX
    }
    fn next_u64(&mut self) -> u64 {
        u64::MAX
    }
    fn fill_bytes(&mut self, dst: &mut [u8]) {
        dst.fill(0xff)
    }
}
