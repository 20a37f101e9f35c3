//! The fast f32 arctangent of the products: the minimax polynomial, `fast_atan2` and the
//! half-angle AoP, with their measured error bounds.

use std::f32::consts::{FRAC_PI_2 as FRAC_PI_2_F32, PI as PI_F32};

/// The maximum absolute error of [`fast_atan2`] against f64 `atan2` of the same f32 inputs,
/// in radians, including the f32 rounding of the result. Measured by the unit test
/// `atan2_error_is_measured_and_below_the_const` on a dense grid (2 million directions at 3
/// magnitudes, the reduced argument on `[0, 1]` in steps of 1e-6, the axes): 5.67e-7; a
/// search over 3e8 random f32 pairs found 5.88e-7. The const rounds up.
pub const ATAN2_MAX_ERROR_RAD: f64 = 7e-7;

/// The maximum absolute error of the AoP the products report ([`fast_aop`], the half-angle
/// form the hot loop uses) against f64 `0.5 atan2(S2, S1)` of the same f32 `S1, S2`, modulo
/// pi, in radians, including the f32 rounding of `L`. Measured by the unit test
/// `aop_error_is_measured_and_below_the_const` (2 million directions at 4 magnitudes, the
/// axes, signed zeros): 5.00e-7; a search over 3e8 random f32 pairs found 5.11e-7. The
/// const rounds up. See the module doc for how it compares with `sigma_aop_rad`.
pub const AOP_MAX_ERROR_RAD: f64 = 6e-7;

/// Coefficients `c0..c6` of `atan z ~ z (c0 + c1 z^2 + c2 z^4 + ... + c6 z^12)` for
/// `0 <= z <= 1` (odd, so also for `-1 <= z <= 0`): the minimax (equal-ripple) polynomial of
/// degree 13 for the absolute error, derived with the Remez exchange algorithm (8 reference
/// points, f64 solves, error extrema on a 2e5-point grid, iterated to convergence). Its
/// exact-arithmetic max error is 2.47e-7 rad; evaluated in f32 (Estrin's scheme, as
/// [`fast_atan2`] and [`fast_aop`] do) it is 3.8e-7 (1e8 points on `[0, 1]`). Check of the
/// derivation: the same procedure at degree 9 reproduces Abramowitz and Stegun, *Handbook
/// of Mathematical Functions* (1964), 4.4.47 (0.9998660, -0.3302995, 0.1801410, -0.0851330,
/// 0.0208351; error 1e-5), and each added degree divides the error by about
/// `(1 + sqrt 2)^2 = 5.8`, as expected from atan's poles at `±i`. Degree 13 is the smallest
/// whose exact error is below the f32 rounding of the result (degree 11: 1.7e-6).
pub const ATAN_COEFFS: [f64; 7] = [
    0.999_996_111_55,
    -0.333_173_680_53,
    0.198_078_155_51,
    -0.132_333_420_42,
    0.079_623_671_389,
    -0.033_604_219_717,
    0.006_811_793_010_9,
];

/// [`ATAN_COEFFS`] rounded to f32 (the test's measured error is of these).
pub(super) const ATAN_COEFFS_F32: [f32; 7] = {
    let mut c = [0.0f32; 7];
    let mut i = 0;
    while i < 7 {
        c[i] = ATAN_COEFFS[i] as f32;
        i += 1;
    }
    c
};

/// Fast `atan2(y, x)` in f32, in `(-pi, pi]`, branch-free (vectorisable).
///
/// Octant reduction: `t = min(|x|, |y|) / max(|x|, |y|)` in `[0, 1]`, `atan t` from the
/// minimax polynomial [`ATAN_COEFFS`], then `pi/2 - r` when `|y| > |x|`,
/// `pi - r` when `x < 0`, and the sign of `y`. Max error [`ATAN2_MAX_ERROR_RAD`] for finite
/// inputs. Differences from `f32::atan2`: `y = -0.0` with `x < 0` gives `+pi` (not `-pi`),
/// so the result never leaves `(-pi, pi]`; `(±0, ±0)` gives 0; infinite inputs give NaN.
#[inline(always)]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    let ax = x.abs();
    let ay = y.abs();
    let swap = ay > ax;
    let num = if swap { ax } else { ay };
    let den = if swap { ay } else { ax };
    let t = num / den;
    let t = if den > 0.0 { t } else { 0.0 };
    let r = atan_unit(t);
    let r = if swap { FRAC_PI_2_F32 - r } else { r };
    let r = if x < 0.0 { PI_F32 - r } else { r };
    if y < 0.0 {
        -r
    } else {
        r
    }
}

/// The largest f32 below pi/2 (pi/2 = 1.5707963268; this is 1.5707962513): the AoP branch
/// constant, so that AoP stays inside `(-pi/2, pi/2)` in f32 (an error of 7.5e-8 rad,
/// included in [`AOP_MAX_ERROR_RAD`]).
pub(super) const HALF_PI_BELOW: f32 = 1.570_796_2;

/// `atan z` for `|z| <= 1` with the degree-13 minimax polynomial [`ATAN_COEFFS`].
#[inline(always)]
pub(super) fn atan_unit(z: f32) -> f32 {
    // Estrin's scheme: two more operations than Horner's, but a dependency chain of 4
    // multiply-adds instead of 6 (the pixel loop is partly latency-bound).
    let [c0, c1, c2, c3, c4, c5, c6] = ATAN_COEFFS_F32;
    let z2 = z * z;
    let z4 = z2 * z2;
    let z8 = z4 * z4;
    let p01 = c1 * z2 + c0;
    let p23 = c3 * z2 + c2;
    let p45 = c5 * z2 + c4;
    let q0 = p23 * z4 + p01;
    let q1 = c6 * z4 + p45;
    z * (q1 * z8 + q0)
}

/// AoP `= 0.5 atan2(S2, S1)` from `S1, S2` and `L = sqrt(S1^2 + S2^2)`, in `(-pi/2, pi/2)`,
/// by the half-angle identities (no octant reduction and one division, as `L` is already
/// known): for `S1 >= 0`, `tan AoP = S2 / (L + S1)`; for `S1 < 0`, `cot AoP = S2 / (L - S1)`.
/// Both ratios lie in `[-1, 1]`, where the polynomial applies:
/// `AoP = atan(z)` for `S1 >= 0` and `AoP = ±pi/2 - atan(z)` (the sign of `S2`) for `S1 < 0`,
/// `z = S2 / (L + |S1|)`. The branches are sign-bit operations (vectorisable). Max error
/// [`AOP_MAX_ERROR_RAD`] (measured by a unit test) for finite inputs; NaN when `L = 0`.
#[inline(always)]
pub fn fast_aop(s1: f32, s2: f32, l: f32) -> f32 {
    const SIGN: u32 = 0x8000_0000;
    let a = atan_unit(s2 / (l + s1.abs()));
    let b1 = s1.to_bits();
    // All ones when S1 is negative (or -0, where both branches agree), else zero.
    let neg1 = ((b1 as i32) >> 31) as u32;
    // -atan(z) when S1 < 0.
    let a = f32::from_bits(a.to_bits() ^ (b1 & SIGN));
    // ±pi/2 with the sign of S2, kept only when S1 < 0.
    let q = (HALF_PI_BELOW.to_bits() | (s2.to_bits() & SIGN)) & neg1;
    a + f32::from_bits(q)
}
