//! `exp` and GELU over slices, written without branches so that the compiler vectorises them, and
//! compiled for the widest instruction set found at run time.
//!
//! In a `perf` profile of `mvmp bench model --backward` the scalar `expf` of the attention's softmax and
//! libm's `erff` of GELU took 3.0% and 3.3% of the samples, one value at a time. Here `exp` is a
//! Cody-Waite reduction to `[-ln2/2, ln2/2]`, a degree-7 Taylor polynomial (truncation under 1e-8
//! relative) and the power of two set in the exponent's bits; the error function is the complementary
//! one's Chebyshev fit `erfc(z) = t exp(-z^2 + P(t))`, `t = 1 / (1 + z/2)` (Numerical Recipes' `erfcc`,
//! under 1.2e-7 relative error for every `z >= 0`), so that GELU keeps its relative accuracy on the
//! negative side, where `1 + erf` is `erfc`. Every lane does the same IEEE operations in the same
//! order (nothing is fused), so the values are the same bits with AVX-512, AVX2 or plain Rust.
use crate::cpu::Isa;

/// Below this `exp` returns 0 (the true value is under 2.7e-38, near the smallest normal float).
const EXP_LOW: f32 = -86.5;
/// Above this `exp` overflows to infinity.
const EXP_HIGH: f32 = 88.72;

/// `exp(x)` to a few units in the last place on `[EXP_LOW, EXP_HIGH]`; 0 below it, infinity above,
/// NaN for NaN.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    // 1.5 * 2^23: adding and subtracting it rounds to the nearest integer with arithmetic alone.
    const ROUND: f32 = 12_582_912.0;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let xc = x.clamp(EXP_LOW, EXP_HIGH);
    let n = (xc * std::f32::consts::LOG2_E + ROUND) - ROUND;
    let r = (xc - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (1.0 / 2.0
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r / 5040.0))))));
    // n lies in [-125, 128]: 2^n as two normal powers of two. A NaN gives n = 0 and p = NaN.
    let y = p * f32::from_bits(((n as i32 + 126) << 23) as u32) * 2.0;
    if x < EXP_LOW {
        0.0
    } else if x > EXP_HIGH {
        f32::INFINITY
    } else {
        y
    }
}

/// `erfc(z)` for `z >= 0` (see the module's notes).
#[inline(always)]
fn erfc_nonnegative(z: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -1.265_512_2
        + t * (1.000_023_7
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_204
                                + t * (1.488_515_9 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    t * exp(-z * z + poly)
}

/// `1 + erf(x / sqrt 2)`: twice the normal distribution's cdf at `x`.
#[inline(always)]
fn twice_cdf(x: f32) -> f32 {
    let c = erfc_nonnegative(x.abs() * std::f32::consts::FRAC_1_SQRT_2);
    if x < 0.0 { c } else { 2.0 - c }
}

/// `gelu(x) = x / 2 * (1 + erf(x / sqrt 2))`.
#[inline(always)]
pub fn gelu(x: f32) -> f32 {
    0.5 * x * twice_cdf(x)
}

/// `gelu'(x) = cdf(x) + x * pdf(x)`.
#[inline(always)]
pub fn gelu_slope(x: f32) -> f32 {
    // 1 / sqrt(2 pi)
    const INV_SQRT_2PI: f32 = 0.398_942_3;
    0.5 * twice_cdf(x) + x * INV_SQRT_2PI * exp(-0.5 * x * x)
}

/// A public function over slices whose body is compiled three times (AVX-512F, AVX2, the build's
/// target) and run in the widest form this machine has.
macro_rules! simd_fn {
    ($(#[$m:meta])* pub fn $name:ident($($a:ident: $t:ty),*) $body:block) => {
        $(#[$m])*
        pub fn $name($($a: $t),*) {
            #[inline(always)]
            fn body($($a: $t),*) $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f")]
            unsafe fn avx512($($a: $t),*) {
                body($($a),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2($($a: $t),*) {
                body($($a),*)
            }
            match Isa::detect() {
                // SAFETY: the instruction set was detected.
                #[cfg(target_arch = "x86_64")]
                Isa::Avx512 => unsafe { avx512($($a),*) },
                // SAFETY: as above.
                #[cfg(target_arch = "x86_64")]
                Isa::Avx2 => unsafe { avx2($($a),*) },
                Isa::Portable => body($($a),*),
            }
        }
    };
}

simd_fn! {
    /// `row[i] = exp(row[i] - shift)`.
    pub fn exp_shifted(row: &mut [f32], shift: f32) {
        // Index loops over slices cut to one length: iterator adapters' folds were left uninlined,
        // outside the instruction set's copy of this body.
        for v in row.iter_mut() {
            *v = exp(*v - shift);
        }
    }
}

simd_fn! {
    /// `out[i] = gelu(x[i])` (slices of one length).
    pub fn gelu_into(x: &[f32], out: &mut [f32]) {
        let n = out.len().min(x.len());
        let (x, out) = (&x[..n], &mut out[..n]);
        #[allow(clippy::needless_range_loop)]
        for i in 0..n {
            out[i] = gelu(x[i]);
        }
    }
}

simd_fn! {
    /// `out[i] = g[i] * gelu'(x[i])`: GELU's backward.
    pub fn gelu_backward_into(g: &[f32], x: &[f32], out: &mut [f32]) {
        let n = out.len().min(g.len()).min(x.len());
        let (g, x, out) = (&g[..n], &x[..n], &mut out[..n]);
        #[allow(clippy::needless_range_loop)]
        for i in 0..n {
            out[i] = g[i] * gelu_slope(x[i]);
        }
    }
}
