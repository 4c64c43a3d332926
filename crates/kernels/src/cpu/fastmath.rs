//! Elementwise `exp`, `erf` and `sin`/`cos` in f32 written so that a plain loop over a
//! slice vectorises (no libm call per element, branches as selects).
//!
//! Why: `erf` and `exp` in f64 through libm, one call per element, take ~9 % of a CPU
//! train step in the GELU (perf, `osrt bench model --step-only`), and the ray encoding
//! would call `sinf`/`cosf` per element. The polynomials are Taylor series on a
//! reduced range, so their constants are 1/n! and need no fitted tables; the tests below
//! bound the error against f64 `std` on dense grids and check the special values (±∞,
//! NaN, huge magnitudes) the model's extreme-input tests feed in.

/// log2(e)
const LOG2E: f32 = std::f32::consts::LOG2_E;
/// ln 2 split so that `n · LN2_HI` is exact for |n| < 2^9 (Cody–Waite reduction).
const LN2_HI: f32 = 0.693_145_75; // = 0.693145751953125 exactly (0x3F317200)
const LN2_LO: f32 = 1.428_606_8e-6;
/// Adding and subtracting 1.5·2^23 rounds an f32 of magnitude < 2^22 to the nearest integer.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// Below this `e^x` is under f32's smallest normal number and [`exp`] returns 0.
const EXP_MIN: f32 = -87.33;
/// Above this `e^x` overflows f32.
const EXP_MAX: f32 = 88.7228;

/// `e^x`, relative error < 4e-7 where the result is a normal f32 (x ∈ [−87.33, 88.72]);
/// 0 below (results under 1.2e-38 are flushed), +∞ above, NaN for NaN.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let xc = x.clamp(EXP_MIN, EXP_MAX);
    let shifted = xc * LOG2E + ROUND_MAGIC;
    let n = shifted - ROUND_MAGIC; // integer in [−126, 128]
    // The same integer from the bits: `shifted` lies in [2^23, 2^24), where one unit of
    // the mantissa is 1. (`n as i32` is a saturating conversion that LLVM does not
    // vectorise: one scalar conversion per lane made the loops about 6× slower.)
    let ni = (shifted.to_bits() as i32).wrapping_sub(ROUND_MAGIC.to_bits() as i32);
    let r = (xc - n * LN2_HI) - n * LN2_LO; // |r| ≤ ln2/2
    // Taylor series of e^r to r^7: remainder < 0.347^8/8! ≈ 6e-9.
    let p = 1.0
        + r * (1.0
            + r * (1.0 / 2.0
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    // 2^128 has no f32 exponent: build 2^127 and double.
    let top = ni > 127;
    let ni = if top { ni - 1 } else { ni };
    let scale = f32::from_bits((ni.wrapping_add(127) as u32) << 23);
    let y = p * scale * if top { 2.0 } else { 1.0 };
    let y = if x < EXP_MIN { 0.0 } else { y };
    if x > EXP_MAX { f32::INFINITY } else { y }
}

/// `erf(x)`, |error| < 4e-7 (Numerical Recipes' erfc fit, |error| < 1.2e-7, evaluated in
/// f32 with [`exp`]); ±1 at ±∞, NaN for NaN.
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -1.265_512_2
        + t * (1.000_023_7
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_204
                                + t * (1.488_515_9 + t * (-0.822_152_24 + t * 0.170_872_77))))))));
    // −z² is −∞ for huge z: exp gives 0 and t·0 = 0, so erf = ±1.
    let r = t * exp(-z * z + poly);
    (1.0 - r).copysign(x)
}

/// Adding and subtracting 1.5·2^52 rounds an f64 of magnitude < 2^51 to an integer.
const ROUND_MAGIC_F64: f64 = 6_755_399_441_055_744.0;
/// Beyond this magnitude [`sin_cos_slice`] falls back to `std` (the branch-free
/// reduction's rounding trick needs |x·2/π| < 2^51; its error grows like |x|·1e-16).
const SIN_COS_FAST_LIMIT: f32 = 1e9;

/// `(sin x, cos x)` for |x| < [`SIN_COS_FAST_LIMIT`], |error| < 2e-7 (reduction by π/2 in
/// f64); NaN for ±∞ and NaN.
#[inline(always)]
fn sin_cos_reduced(x: f32) -> (f32, f32) {
    let xd = x as f64;
    let shifted = xd * std::f64::consts::FRAC_2_PI + ROUND_MAGIC_F64;
    let q = shifted - ROUND_MAGIC_F64;
    let r = (xd - q * std::f64::consts::FRAC_PI_2) as f32; // |r| ≤ π/4
    let r2 = r * r;
    // Taylor series to r^11 / r^12: remainders < 0.786^13/13! ≈ 7e-12 and 0.786^14/14! ≈ 4e-13.
    let s = r
        * (1.0
            + r2 * (-1.0 / 6.0
                + r2 * (1.0 / 120.0
                    + r2 * (-1.0 / 5040.0 + r2 * (1.0 / 362_880.0 + r2 * (-1.0 / 39_916_800.0))))));
    let c = 1.0
        + r2 * (-1.0 / 2.0
            + r2 * (1.0 / 24.0
                + r2 * (-1.0 / 720.0
                    + r2 * (1.0 / 40_320.0
                        + r2 * (-1.0 / 3_628_800.0 + r2 * (1.0 / 479_001_600.0))))));
    // Quadrant q mod 4: (sin, cos) = (s, c), (c, −s), (−s, −c), (−c, s).
    // From the bits, as in [`exp`] (`shifted` lies where one mantissa unit is 1).
    let quadrant = (shifted.to_bits() as i64).wrapping_sub(ROUND_MAGIC_F64.to_bits() as i64) & 3;
    let (sin, cos) = if quadrant & 1 == 0 { (s, c) } else { (c, -s) };
    let (sin, cos) = if quadrant & 2 == 0 {
        (sin, cos)
    } else {
        (-sin, -cos)
    };
    if x.is_finite() {
        (sin, cos)
    } else {
        (f32::NAN, f32::NAN)
    }
}

/// Defines `pub fn $name(args)` from a loop body, compiled for the baseline target, for
/// AVX2 + FMA and for AVX-512F; the call takes the widest build the CPU supports. All
/// builds compute bit-identical results (Rust never contracts `a·b + c` into an FMA by
/// itself, and the lanes only change how many elements one instruction handles).
#[macro_export]
macro_rules! simd_kernel {
    ($(#[$m:meta])* pub fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $body:block) => {
        $(#[$m])*
        // One of two places the workspace allows `unsafe` (the other lends all-reduce
        // buffers to the transport): calling a `target_feature` function
        // needs it, and the call is guarded by the run-time feature check.
        #[allow(unsafe_code)]
        pub fn $name($($arg: $ty),*) {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn generic($($arg: $ty),*) $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn avx512($($arg: $ty),*) {
                    generic($($arg),*)
                }
                if std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx2")
                    && std::is_x86_feature_detected!("fma")
                {
                    // SAFETY: the CPU has the features `avx512` is compiled for.
                    return unsafe { avx512($($arg),*) };
                }
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn avx2($($arg: $ty),*) {
                    generic($($arg),*)
                }
                if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has the features `avx2` is compiled for.
                    return unsafe { avx2($($arg),*) };
                }
            }
            generic($($arg),*)
        }
    };
}

pub(crate) use simd_kernel as kernel;

kernel! {
    /// `out[i] = e^(x[i] − shift)`.
    pub fn exp_shifted_slice(out: &mut [f32], x: &[f32], shift: f32) {
        for (o, &x) in out.iter_mut().zip(x) {
            *o = exp(x - shift);
        }
    }
}

kernel! {
    /// `sin[i], cos[i] = sin x[i], cos x[i]` (see [`sin_cos_reduced`]; magnitudes beyond
    /// 1e9 go through `std`).
    pub fn sin_cos_slice(sin: &mut [f32], cos: &mut [f32], x: &[f32]) {
        for ((s, c), &x) in sin.iter_mut().zip(cos.iter_mut()).zip(x) {
            (*s, *c) = sin_cos_reduced(x);
        }
        for ((s, c), &x) in sin.iter_mut().zip(cos.iter_mut()).zip(x) {
            if x.is_finite() && x.abs() >= SIN_COS_FAST_LIMIT {
                let (ss, cc) = (x as f64).sin_cos();
                (*s, *c) = (ss as f32, cc as f32);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(lo: f64, hi: f64, n: usize) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| (lo + (hi - lo) * i as f64 / n as f64) as f32)
    }

    #[test]
    fn exp_is_accurate_and_keeps_special_values() {
        let mut worst = 0f64;
        for x in grid(-87.33, 88.72, 400_000) {
            let want = (x as f64).exp();
            let rel = ((exp(x) as f64 - want) / want).abs();
            worst = worst.max(rel);
        }
        assert!(worst < 4e-7, "worst relative error {worst:e}");
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-87.5), 0.0);
        assert_eq!(exp(-1e30), 0.0);
        assert_eq!(exp(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp(1e30), f32::INFINITY);
        assert_eq!(exp(f32::INFINITY), f32::INFINITY);
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn erf_is_accurate_and_keeps_special_values() {
        // f64 reference: the series/continued fraction would be longer; libm's erf is not
        // in std, so compare with a high-order f64 Taylor series near 0 and with
        // 1 − erfc asymptotics far out, via the identity checks below.
        let reference = |x: f64| -> f64 {
            // Abramowitz–Stegun 7.1.5 series, converges for all x (used to |x| ≤ 6).
            let mut term = x;
            let mut sum = x;
            let mut n = 0.0;
            while term.abs() > 1e-17 * sum.abs().max(1e-300) {
                n += 1.0;
                term *= -x * x / n;
                sum += term / (2.0 * n + 1.0);
                if n > 400.0 {
                    break;
                }
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        };
        let mut worst = 0f64;
        for x in grid(-4.5, 4.5, 90_000) {
            let err = (erf(x) as f64 - reference(x as f64)).abs();
            worst = worst.max(err);
        }
        assert!(worst < 4e-7, "worst absolute error {worst:e}");
        assert_eq!(erf(0.0), 0.0);
        assert_eq!(erf(f32::INFINITY), 1.0);
        assert_eq!(erf(f32::NEG_INFINITY), -1.0);
        assert_eq!(erf(1e30), 1.0);
        assert_eq!(erf(-1e30), -1.0);
        assert!(erf(f32::NAN).is_nan());
    }

    #[test]
    fn sin_cos_are_accurate_and_keep_special_values() {
        let xs: Vec<f32> = grid(-2000.0, 2000.0, 800_000)
            .chain(grid(-1e6, 1e6, 100_000))
            .chain(grid(-1e-3, 1e-3, 1000))
            .chain([1e9, -3e9, 1e15, 3e38, -3e38])
            .collect();
        let (mut s, mut c) = (vec![0f32; xs.len()], vec![0f32; xs.len()]);
        sin_cos_slice(&mut s, &mut c, &xs);
        let mut worst = 0f64;
        for ((&x, s), c) in xs.iter().zip(s).zip(c) {
            let xd = x as f64;
            worst = worst
                .max((s as f64 - xd.sin()).abs())
                .max((c as f64 - xd.cos()).abs());
        }
        assert!(worst < 2e-7, "worst absolute error {worst:e}");
        let special = [0.0, f32::INFINITY, f32::NEG_INFINITY, f32::NAN];
        let (mut s, mut c) = ([9f32; 4], [9f32; 4]);
        sin_cos_slice(&mut s, &mut c, &special);
        assert_eq!((s[0], c[0]), (0.0, 1.0));
        assert!(s[1..].iter().chain(&c[1..]).all(|v| v.is_nan()));
    }

    #[test]
    fn exp_kernel_matches_the_scalar_function() {
        // The vector loop (16 lanes) and its scalar tail both see the edges: the exponent
        // built from the bits at 2^127 (doubled), the flush below, ±∞ and NaN.
        let edges = [90.2, 90.22, 90.3, -85.83, -85.9, 1e30, -1e30, f32::INFINITY];
        let xs: Vec<f32> = grid(-100.0, 100.0, 10_001)
            .chain(edges.into_iter().cycle().take(35))
            .chain([f32::NEG_INFINITY, f32::NAN])
            .collect();
        let mut out = vec![0f32; xs.len()];
        exp_shifted_slice(&mut out, &xs, 1.5);
        for (&x, o) in xs.iter().zip(out) {
            let want = exp(x - 1.5);
            assert!(
                o.to_bits() == want.to_bits() || (o.is_nan() && want.is_nan()),
                "x = {x}"
            );
        }
        assert!(exp(88.72).is_finite() && exp(88.72) > 3.3e38);
    }
}
