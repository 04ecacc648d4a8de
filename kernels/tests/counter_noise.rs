//! Counter-based noise: reproducible from its key, different for different keys, uniform and
//! uncorrelated (statistical checks with fixed keys, so they cannot flake), the same on the plain
//! and the autodiff device, and the same bits from the wgpu kernel as from the CPU twin
//! (lavapipe in CI; fails instead of skipping under ACAGS_REQUIRE_WGPU=1).
#![allow(deprecated)] // Device::ndarray

mod cube_common;

use acags_kernels::counter_noise::{NoiseKey, NoiseStream, noise_element, uniform_noise_like};
use burn::tensor::{Device, DeviceKind, Tensor};
use cube_common::{cube_device, values};

fn noise(device: &Device, shape: [usize; 2], key: NoiseKey, amplitude: f32) -> Vec<f32> {
    let like = Tensor::<2>::zeros(shape, device);
    values(&uniform_noise_like(&like, key, amplitude))
}

#[test]
fn noise_is_reproducible_from_its_key_and_differs_between_keys() {
    let device = Device::ndarray();
    let stream = NoiseStream {
        seed: 42,
        step: 1000,
        stream: 4,
    };
    let a = noise(&device, [300, 77], stream.key(2), 1.0);
    assert_eq!(
        a,
        noise(&device, [300, 77], stream.key(2), 1.0),
        "same key, other noise"
    );
    // Element i depends on i and the key only, not on the shape.
    assert_eq!(a[..1000], noise(&device, [10, 100], stream.key(2), 1.0)[..]);
    for other in [
        stream.key(3),
        NoiseStream {
            step: 1001,
            ..stream
        }
        .key(2),
        NoiseStream { seed: 43, ..stream }.key(2),
        NoiseStream {
            stream: 5,
            ..stream
        }
        .key(2),
    ] {
        let b = noise(&device, [300, 77], other, 1.0);
        let same = a.iter().zip(&b).filter(|(x, y)| x == y).count();
        // Two independent draws on a 2^24 grid agree by chance on ~0.001 of 23,100 elements.
        assert!(same < 10, "{same} equal elements between different keys");
    }
    // On the autodiff device (a tracked reference) the same values, untracked.
    let tracked = Tensor::<2>::zeros([300, 77], &Device::ndarray().autodiff()).require_grad();
    let drawn = uniform_noise_like(&tracked, stream.key(2), 1.0);
    assert!(!drawn.is_require_grad());
    assert_eq!(values(&drawn), a);
}

#[test]
fn noise_is_uniform_and_uncorrelated() {
    let n = 1 << 20;
    let amplitude = 0.37f32;
    let key = NoiseKey::new(7, 123, 4, 0);
    let x: Vec<f64> = (0..n as u32)
        .map(|i| noise_element(i, key, amplitude) as f64)
        .collect();
    let half = amplitude as f64 / 2.0;
    assert!(
        x.iter().all(|&v| (-half..half).contains(&v)),
        "outside [-a/2, a/2)"
    );
    let mean = x.iter().sum::<f64>() / n as f64;
    let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
    let sd = amplitude as f64 / 12f64.sqrt();
    assert!(mean.abs() < 4.0 * sd / (n as f64).sqrt(), "mean {mean}");
    assert!(
        (var / (sd * sd) - 1.0).abs() < 0.01,
        "variance ratio {}",
        var / (sd * sd)
    );
    // 256 equal bins: chi-square with 255 degrees of freedom has mean 255, sd ~22.6.
    let bins = 256;
    let mut counts = vec![0usize; bins];
    for &v in &x {
        counts[(((v + half) / amplitude as f64) * bins as f64) as usize] += 1;
    }
    let expected = n as f64 / bins as f64;
    let chi2: f64 = counts
        .iter()
        .map(|&c| (c as f64 - expected).powi(2) / expected)
        .sum();
    assert!(
        chi2 < 255.0 + 6.0 * 22.6,
        "chi-square {chi2} over {bins} bins"
    );
    // Neighbouring elements (rows of a tensor are neighbours) and elements a row apart.
    for lag in [1usize, 48, 320] {
        let c: f64 = (0..n - lag)
            .map(|i| (x[i] - mean) * (x[i + lag] - mean))
            .sum::<f64>()
            / ((n - lag) as f64 * var);
        assert!(
            c.abs() < 5.0 / (n as f64).sqrt(),
            "lag-{lag} correlation {c}"
        );
    }
    // Consecutive keys (draws of one step, steps of one stream) are uncorrelated too.
    let other = NoiseKey::new(7, 124, 4, 0);
    let y: Vec<f64> = (0..n as u32)
        .map(|i| noise_element(i, other, amplitude) as f64)
        .collect();
    let c: f64 = x.iter().zip(&y).map(|(a, b)| a * b).sum::<f64>() / (n as f64 * var);
    assert!(
        c.abs() < 5.0 / (n as f64).sqrt(),
        "correlation across steps {c}"
    );
}

#[test]
fn the_wgpu_kernel_draws_the_cpu_twins_bits() {
    if cube_device().is_none() {
        return;
    }
    let wgpu = Device::wgpu(DeviceKind::DefaultDevice);
    let stream = NoiseStream {
        seed: 42,
        step: 77,
        stream: 5,
    };
    for (shape, draw, amplitude) in [
        ([1000, 37], 0, 1.0f32),
        ([3, 5], 1, 0.25),
        ([70_001, 3], 2, 1e-3),
    ] {
        let on_gpu = noise(&wgpu, shape, stream.key(draw), amplitude);
        let on_cpu = noise(&Device::ndarray(), shape, stream.key(draw), amplitude);
        let differing = on_gpu
            .iter()
            .zip(&on_cpu)
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count();
        assert_eq!(
            differing, 0,
            "{shape:?}: {differing} elements differ from the CPU twin"
        );
    }
}
