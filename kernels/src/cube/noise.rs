//! Counter-based uniform noise on the device: one unit per element hashes (key, index), the CPU
//! twin's `counter_noise::noise_element` in integer arithmetic, so both draw the same bits.

use burn_cubecl::tensor::CubeTensor;
use cubecl::calculate_cube_count_elemwise;
use cubecl::prelude::*;

use super::buffers::fresh_f32;

#[cube]
fn lowbias32(x: u32) -> u32 {
    let mut x = x;
    x ^= x >> 16;
    x *= 0x7feb_352du32;
    x ^= x >> 15;
    x *= 0x846c_a68bu32;
    x ^= x >> 16;
    x
}

#[cube(launch)]
fn noise_kernel(out: &mut Tensor<f32>, key_a: u32, key_b: u32, amplitude: f32) {
    let i = ABSOLUTE_POS;
    if i >= out.len() {
        terminate!();
    }
    let h = lowbias32(lowbias32(u32::cast_from(i) ^ key_a) + key_b);
    let u = f32::cast_from(h >> 8) * (1.0f32 / 16_777_216.0f32);
    out[i] = (u - 0.5f32) * amplitude;
}

/// Noise shaped like `like` (its values are not read).
pub fn uniform_noise_like(like: &CubeTensor, key_a: u32, key_b: u32, amplitude: f32) -> CubeTensor {
    let shape = like.meta.shape().to_vec();
    let n: usize = shape.iter().product();
    let out = fresh_f32(like, shape);
    if n > 0 {
        let client = like.client.clone();
        let cube_dim = CubeDim::new_1d(256);
        let count = calculate_cube_count_elemwise(&client, n, cube_dim);
        noise_kernel::launch(
            &client,
            count,
            cube_dim,
            out.clone().into_tensor_arg(),
            key_a,
            key_b,
            amplitude,
        );
    }
    out
}
