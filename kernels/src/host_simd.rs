//! Element-wise loops of the CPU twins, compiled twice: once for AVX2 (chosen at run time where
//! the CPU has it) and once for the portable baseline (x86-64's SSE2, or any other target).
//!
//! The binary is built for the baseline, so without this the vectoriser works 4 lanes wide at
//! best, and a 32-bit integer multiply (the counter noise's hash) has no SSE2 instruction. Both
//! copies compile the same scalar code; since Rust never contracts a·b + c into a fused
//! multiply-add and every operation used is correctly rounded (+, −, ·, /, √, comparisons,
//! integer ops, conversions), the two give the same bits, which the tests check.
//!
//! libm's `expf` and `logf` are calls, and a call keeps a loop scalar; [`exp_f32`] and [`ln_f32`]
//! are branch-free polynomials the vectoriser can inline (Cephes' `expf` and `logf`, within
//! 1.2e-7 of the exact values, checked below).

/// Which copy of a twin loop runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lanes {
    /// The widest the CPU has (AVX2 where detected, else portable).
    Widest,
    /// The portable copy, whatever the CPU (tests compare the two).
    Portable,
}

impl Lanes {
    #[inline]
    pub fn use_avx2(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            self == Lanes::Widest && std::arch::is_x86_feature_detected!("avx2")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }
}

/// `fn name(lanes: Lanes, args…)`: the body compiled for AVX2 and portably, the copy picked by
/// `lanes`. The body is written out inside each copy rather than called through an inlined
/// helper: in a stand-alone test of the bit estimate's loop, an inlined helper (taking a mode
/// flag) stayed scalar inside the AVX2 function (11.9 ns per element) where the loop written
/// out in it vectorised (4.6 ns).
macro_rules! avx2_twin {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $body:block) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name(lanes: $crate::host_simd::Lanes, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            #[allow(clippy::too_many_arguments)]
            fn avx2($($arg: $ty),*) $body
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn portable($($arg: $ty),*) $body
            #[cfg(target_arch = "x86_64")]
            if lanes.use_avx2() {
                // SAFETY: the CPU has AVX2 (run-time detection in `use_avx2`).
                return unsafe { avx2($($arg),*) };
            }
            let _ = lanes;
            portable($($arg),*)
        }
    };
}
pub(crate) use avx2_twin;

/// e^x in f32 without a call: Cephes' `expf` (x = n·ln 2 + r, |r| ≤ ½ ln 2, a degree-6
/// polynomial in r, 2^n from the exponent bits). Within 1.2e-7 relative of the exact value on
/// [−87, 88]; 0 below −87 (the exact value, < 1.7e-38, is a subnormal or less), +∞ above 88 (the
/// exact value nears f32's largest, 3.4e38, at 88.7),
/// NaN stays NaN.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    let clamped = x.clamp(-87.0, 88.0);
    let n = (clamped * std::f32::consts::LOG2_E).round_ties_even();
    // ln 2 in two parts, so n·ln 2 is subtracted without rounding its large part.
    let r = clamped - n * 0.693_359_4 - n * -2.121_944_4e-4;
    let r2 = r * r;
    let poly =
        (((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
            + 0.166_666_65)
            * r
            + 0.5)
            * r2
            + r
            + 1.0;
    let two_to_n = f32::from_bits(((n as i32 + 127) as u32) << 23);
    let e = poly * two_to_n;
    if x < -87.0 {
        0.0
    } else if x > 88.0 {
        f32::INFINITY
    } else {
        e
    }
}

/// ln x in f32 without a call, for positive normal x (the callers' arguments are ≥ 1e-5):
/// Cephes' `logf` (x = m·2^e, √½ ≤ m < √2, a degree-8 polynomial in m − 1). Within 1.2e-7 of
/// the exact value, relative to max(1, |ln x|).
#[inline(always)]
pub fn ln_f32(x: f32) -> f32 {
    let bits = x.to_bits();
    let mut exponent = ((bits >> 23) & 0xff) as i32 - 126;
    // The mantissa in [½, 1).
    let mantissa = f32::from_bits((bits & 0x007f_ffff) | 0x3f00_0000);
    let below = mantissa < std::f32::consts::FRAC_1_SQRT_2;
    exponent -= below as i32;
    let m = if below {
        mantissa + mantissa - 1.0
    } else {
        mantissa - 1.0
    };
    let z = m * m;
    let y = ((((((((7.037_683_6e-2 * m - 0.115_146_1) * m + 0.116_769_98) * m - 0.124_201_41)
        * m
        + 0.142_493_23)
        * m
        - 0.166_680_58)
        * m
        + 0.200_007_15)
        * m
        - 0.249_999_94)
        * m
        + 0.333_333_3)
        * m
        * z;
    let e = exponent as f32;
    let y = y + -2.121_944_4e-4 * e - 0.5 * z;
    m + y + 0.693_359_4 * e
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_is_within_its_bound_of_the_f64_one() {
        let mut worst = 0.0f64;
        for k in 0..=2_000_000 {
            let x = -87.0 + k as f32 * (175.0 / 2_000_000.0);
            let want = (x as f64).exp();
            let got = exp_f32(x) as f64;
            let error = ((got - want) / want).abs();
            worst = worst.max(error);
            assert!(error <= 1.2e-7, "exp({x}): {got} vs {want}");
        }
        // Tight, not loose by orders of magnitude.
        assert!(worst > 3e-8, "worst {worst}");
        assert_eq!(exp_f32(0.0), 1.0);
        assert_eq!(exp_f32(-87.5), 0.0);
        assert_eq!(exp_f32(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_f32(89.0), f32::INFINITY);
        assert!(exp_f32(f32::NAN).is_nan());
    }

    #[test]
    fn ln_is_within_its_bound_of_the_f64_one() {
        let mut worst = 0.0f64;
        let mut check = |x: f32| {
            let want = (x as f64).ln();
            let got = ln_f32(x) as f64;
            let error = (got - want).abs() / want.abs().max(1.0);
            worst = worst.max(error);
            assert!(error <= 1.2e-7, "ln({x}): {got} vs {want}");
        };
        for k in 0..=2_000_000 {
            check(1e-5 + k as f32 * 1e-6);
        }
        for k in 0..=100_000 {
            check(f32::MIN_POSITIVE * 1.0001f32.powi(k));
            check(1e-30 * 1.0003f32.powi(k));
        }
        assert!(worst > 3e-8, "worst {worst}");
        assert_eq!(ln_f32(1.0), 0.0);
    }

    avx2_twin! {
        fn squares_plus_exp(out: &mut [f32], x: &[f32]) {
            for (o, &x) in out.iter_mut().zip(x) {
                *o = x * x + exp_f32(-x) / (1.0 + x.abs()).sqrt();
            }
        }
    }

    #[test]
    fn both_copies_of_a_twin_give_the_same_bits() {
        let x: Vec<f32> = (0..10_007)
            .map(|k| (k as f32 * 0.7071).sin() * 50.0)
            .collect();
        let (mut widest, mut portable) = (vec![0.0; x.len()], vec![0.0; x.len()]);
        squares_plus_exp(Lanes::Widest, &mut widest, &x);
        squares_plus_exp(Lanes::Portable, &mut portable, &x);
        let bits = |v: &[f32]| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&widest), bits(&portable));
    }
}
