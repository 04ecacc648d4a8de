//! Uniform noise from a counter-based generator, a Burn backend extension (CPU twin + CubeCL
//! kernel): element i of a noise tensor is a hash of (key, i), so the device draws it where it
//! is used, nothing is generated on the host or uploaded, and a key built from (seed, step,
//! stream, draw) makes a resumed run draw exactly what an uninterrupted one would.
//!
//! The hash is 32-bit only (WGSL has no 64-bit integers): `lowbias32` (Chris Wellons' integer
//! hash, a bijection on u32 with low bias) applied twice around the key words,
//! h = lowbias32(lowbias32(i ^ a) + b), and u = (h >> 8) · 2⁻²⁴ ∈ [0, 1) on the f32 grid.
//! Everything is exact integer arithmetic up to (u − ½) · amplitude, so the kernel and the CPU
//! twin draw the same bits (a test checks it). Tensors must have fewer than 2³² elements.

#![allow(deprecated)] // NdArray is deprecated in Burn 0.22 but remains the CPU backend.

use burn::backend::autodiff::{Autodiff, checkpoint::strategy::CheckpointStrategy};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    AutodiffBackend, Backend, Dispatch, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::host_simd::{Lanes, avx2_twin};

/// The key of one noise tensor: two 32-bit words mixed from (seed, step, stream, draw).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NoiseKey {
    pub a: u32,
    pub b: u32,
}

impl NoiseKey {
    /// `stream` says what the noise is for, `draw` which tensor of that stream in the step.
    pub fn new(seed: u64, step: u64, stream: u32, draw: u32) -> Self {
        let mut x = splitmix64(seed ^ 0xA0761D6478BD642F);
        x = splitmix64(x ^ step);
        x = splitmix64(x ^ ((stream as u64) << 32 | draw as u64));
        Self {
            a: x as u32,
            b: (x >> 32) as u32,
        }
    }
}

/// The noise tensors of one purpose in one training step: tensor `draw` has key
/// `NoiseKey::new(seed, step, stream, draw)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NoiseStream {
    pub seed: u64,
    pub step: u64,
    pub stream: u32,
}

impl NoiseStream {
    pub fn key(&self, draw: u32) -> NoiseKey {
        NoiseKey::new(self.seed, self.step, self.stream, draw)
    }
}

fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Chris Wellons' `lowbias32` (https://nullprogram.com/blog/2018/07/31/).
#[inline(always)]
pub fn lowbias32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// Element `i` of the noise of `key`: U(−½, ½) · amplitude. The kernel (`cube::noise`) computes
/// the same expression.
#[inline(always)]
pub fn noise_element(i: u32, key: NoiseKey, amplitude: f32) -> f32 {
    let h = lowbias32(lowbias32(i ^ key.a).wrapping_add(key.b));
    let u = (h >> 8) as f32 * (1.0 / 16_777_216.0);
    (u - 0.5) * amplitude
}

avx2_twin! {
    /// `values[j]` = the noise of element `start + j` (8 lanes at a time with AVX2: the hash's
    /// 32-bit multiplies have no SSE2 instruction).
    pub(crate) fn fill_noise(values: &mut [f32], start: u32, key: NoiseKey, amplitude: f32) {
        for (j, v) in values.iter_mut().enumerate() {
            *v = noise_element(start.wrapping_add(j as u32), key, amplitude);
        }
    }
}

#[backend_extension(NdArray, Cube, Autodiff)]
pub trait CounterNoiseBackend: Backend {
    /// Noise shaped like `like` (whose values are not read): element i (row-major) is
    /// [`noise_element`]`(i, key, amplitude)`. Not differentiable.
    fn uniform_noise_like(
        like: FloatTensor<Self>,
        key_a: u32,
        key_b: u32,
        amplitude: f32,
    ) -> FloatTensor<Self>;
}

fn check_len(n: usize) {
    assert!(
        n <= u32::MAX as usize,
        "counter noise: {n} elements exceed the 2^32 counter range"
    );
}

impl CounterNoiseBackend for NdArray {
    fn uniform_noise_like(
        like: FloatTensor<Self>,
        key_a: u32,
        key_b: u32,
        amplitude: f32,
    ) -> FloatTensor<Self> {
        let shape = like.shape();
        let dims: Vec<usize> = (0..shape.num_dims()).map(|d| shape[d]).collect();
        let n = shape.num_elements();
        check_len(n);
        let key = NoiseKey { a: key_a, b: key_b };
        let mut out = vec![0.0f32; n];
        const CHUNK: usize = 8192;
        out.par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(chunk, values)| {
                fill_noise(
                    Lanes::Widest,
                    values,
                    (chunk * CHUNK) as u32,
                    key,
                    amplitude,
                )
            });
        NdArray::float_from_data(TensorData::new(out, dims), &like.device())
    }
}

impl CounterNoiseBackend for burn::backend::Cube {
    fn uniform_noise_like(
        like: FloatTensor<Self>,
        key_a: u32,
        key_b: u32,
        amplitude: f32,
    ) -> FloatTensor<Self> {
        use crate::backend::fused::{inner_float, register};
        check_len(like.shape().num_elements());
        let client = like.client.clone();
        let noise =
            crate::cube::noise::uniform_noise_like(&inner_float(like), key_a, key_b, amplitude);
        register(&client, noise)
    }
}

impl<B: CounterNoiseBackend, C: CheckpointStrategy> CounterNoiseBackend for Autodiff<B, C> {
    fn uniform_noise_like(
        like: FloatTensor<Self>,
        key_a: u32,
        key_b: u32,
        amplitude: f32,
    ) -> FloatTensor<Self> {
        Self::from_inner(B::uniform_noise_like(
            Self::inner(like),
            key_a,
            key_b,
            amplitude,
        ))
    }
}

/// U(−½, ½) · amplitude noise shaped like `like`, drawn on `like`'s device from `key`.
pub fn uniform_noise_like<const D: usize>(
    like: &Tensor<D>,
    key: NoiseKey,
    amplitude: f32,
) -> Tensor<D> {
    Tensor::from_dispatch(<Dispatch as CounterNoiseBackend>::uniform_noise_like(
        like.clone().into_dispatch(),
        key.a,
        key.b,
        amplitude,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_copies_of_the_noise_loop_give_the_element_formula_to_the_bit() {
        let key = NoiseStream {
            seed: 42,
            step: 7,
            stream: 3,
        }
        .key(1);
        let start = u32::MAX - 20_000;
        let (mut widest, mut portable) = (vec![0.0f32; 10_003], vec![0.0f32; 10_003]);
        fill_noise(Lanes::Widest, &mut widest, start, key, 0.5);
        fill_noise(Lanes::Portable, &mut portable, start, key, 0.5);
        for (j, (w, p)) in widest.iter().zip(&portable).enumerate() {
            let want = noise_element(start + j as u32, key, 0.5);
            assert_eq!(w.to_bits(), want.to_bits(), "element {j}");
            assert_eq!(p.to_bits(), want.to_bits(), "element {j}");
        }
    }
}
