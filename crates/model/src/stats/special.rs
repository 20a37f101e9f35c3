//! Special functions of the DoLP and AoP statistics: exponentially scaled modified Bessel
//! functions `I0`, `I1` and the Laguerre function `L_{1/2}` (Rice moments), the error function,
//! the moments of a truncated standard normal, and the Gauss-Hermite rule for a normal
//! expectation.

use std::f64::consts::PI;

/// Below this argument the Bessel power series is used, above it the asymptotic expansion.
const BESSEL_SERIES_MAX: f64 = 30.0;

/// `(I0(|x|), I1(|x|))` by the power series (Abramowitz & Stegun 9.6.10): all terms positive, so
/// the relative error is a few ulp for `|x| <= 30` (at most about 90 terms).
fn bessel_i01_series(ax: f64) -> (f64, f64) {
    let q = 0.25 * ax * ax;
    let (mut t0, mut t1) = (1.0, 0.5 * ax);
    let (mut s0, mut s1) = (t0, t1);
    let mut k = 0.0;
    loop {
        k += 1.0;
        t0 *= q / (k * k);
        t1 *= q / (k * (k + 1.0));
        s0 += t0;
        s1 += t1;
        if (t0 <= 1e-17 * s0 && t1 <= 1e-17 * s1) || k > 500.0 {
            return (s0, s1);
        }
    }
}

/// `e^-x I_nu(x)` for `x >= 30` by the asymptotic expansion (Abramowitz & Stegun 9.7.1):
/// `I_nu(x) ~ e^x / sqrt(2 pi x) [1 - (mu-1)/(8x) + (mu-1)(mu-9)/(2! (8x)^2) - ...]`,
/// `mu = 4 nu^2`. Summed until the terms fall below 1e-17 (at `x = 30` the smallest term is
/// about 1e-26, so the truncation error is negligible).
fn bessel_ie_asymptotic(nu: f64, x: f64) -> f64 {
    let mu = 4.0 * nu * nu;
    let mut term = 1.0;
    let mut sum = 1.0;
    for k in 1..200 {
        let kf = k as f64;
        let odd = 2.0 * kf - 1.0;
        let next = -term * (mu - odd * odd) / (kf * 8.0 * x);
        if next.abs() >= term.abs() {
            break; // the series is asymptotic: stop at its smallest term
        }
        term = next;
        sum += term;
        if term.abs() < 1e-17 * sum.abs() {
            break;
        }
    }
    sum / (2.0 * PI * x).sqrt()
}

/// Exponentially scaled modified Bessel function of the first kind, order 0:
/// `e^-|x| I0(x)` (finite for every finite `x`; 0 at infinity; NaN propagates).
///
/// Power series (Abramowitz & Stegun 9.6.10) for `|x| <= 30`, asymptotic expansion (A&S 9.7.1)
/// above; relative error below 1e-14 (tested against mpmath to 1e-12).
pub fn bessel_i0e(x: f64) -> f64 {
    let ax = x.abs();
    if ax.is_infinite() {
        0.0
    } else if ax <= BESSEL_SERIES_MAX {
        bessel_i01_series(ax).0 * (-ax).exp()
    } else {
        bessel_ie_asymptotic(0.0, ax)
    }
}

/// Exponentially scaled modified Bessel function of the first kind, order 1:
/// `e^-|x| I1(x)` (odd in `x`; finite for every finite `x`; 0 at infinity; NaN propagates).
/// Same methods and accuracy as [`bessel_i0e`].
pub fn bessel_i1e(x: f64) -> f64 {
    let ax = x.abs();
    let v = if ax.is_infinite() {
        0.0
    } else if ax <= BESSEL_SERIES_MAX {
        bessel_i01_series(ax).1 * (-ax).exp()
    } else {
        bessel_ie_asymptotic(1.0, ax)
    };
    if x < 0.0 {
        -v
    } else {
        v
    }
}

/// The Laguerre function `L_{1/2}(x)` for `x <= 0` (the Rice moments' argument
/// `x = -p^2 / (2 sigma^2)`), from `L_{1/2}(x) = e^{x/2} [(1 - x) I0(-x/2) - x I1(-x/2)]`: with
/// `z = -x/2 >= 0`, `L_{1/2}(-2z) = (1 + 2z) e^-z I0(z) + 2z e^-z I1(z)`, which uses the scaled
/// Bessel functions and cannot overflow. Positive `x` is treated as 0.
pub(crate) fn laguerre_half(x: f64) -> f64 {
    let z = (-0.5 * x).max(0.0);
    (1.0 + 2.0 * z) * bessel_i0e(z) + 2.0 * z * bessel_i1e(z)
}

/// Error function by the series `erf x = 2/sqrt(pi) e^{-x^2} sum_n 2^n x^{2n+1} / (1 3 ... (2n+1))`
/// (Abramowitz & Stegun 7.1.6; positive terms, a few ulp) for `|x| < 6`, and `+-1` beyond
/// (`erfc 6 = 2.2e-17`).
pub(crate) fn erf(x: f64) -> f64 {
    let ax = x.abs();
    let v = if ax >= 6.0 {
        1.0
    } else {
        let x2 = 2.0 * ax * ax;
        let (mut term, mut sum) = (ax, ax);
        let mut n = 0.0;
        loop {
            n += 1.0;
            term *= x2 / (2.0 * n + 1.0);
            sum += term;
            if term <= 1e-17 * sum || n > 400.0 {
                break;
            }
        }
        2.0 / PI.sqrt() * (-ax * ax).exp() * sum
    };
    if x < 0.0 {
        -v
    } else {
        v
    }
}

/// Complementary error function with relative accuracy into the far tail: `1 - erf x` for
/// `x < 1` (where `erfc x > 0.157`, so [`erf`]'s few-ulp error stays below 1e-14 relative), the
/// continued fraction `erfc x = e^{-x^2} / sqrt(pi) / (x + (1/2) / (x + 1 / (x + (3/2) / (x +
/// ...))))` (Abramowitz & Stegun 7.1.14) evaluated backwards from 300 terms for `x >= 1`
/// (converged to an ulp there), and
/// `2 - erfc(-x)` for negative `x`.
pub(crate) fn erfc(x: f64) -> f64 {
    if x < 0.0 {
        return 2.0 - erfc(-x);
    }
    if x < 1.0 {
        return 1.0 - erf(x);
    }
    if x > 27.3 {
        return 0.0; // below the smallest subnormal
    }
    let mut f = x;
    for k in (1..=300).rev() {
        f = x + 0.5 * k as f64 / f;
    }
    (-x * x).exp() / (PI.sqrt() * f)
}

/// The moments `K_n = int_L^inf z^n phi(z) dz`, `n = 0..=N-1`, of the standard normal density
/// `phi` truncated below at `L`: `K_0 = erfc(L / sqrt 2) / 2`, `K_1 = phi(L)`,
/// `K_n = (n - 1) K_{n-2} + L^{n-1} phi(L)` (integration by parts). The recursion adds positive
/// terms for `L >= 0`; for `L < 0` the boundary terms are bounded by `|L|^{n-1} phi(L)` and the
/// moments approach the full normal moments `(n-1)!!`, so no digits are lost either way.
/// `K_0` uses [`erfc`], which keeps its relative accuracy for large positive `L` until it
/// underflows.
pub(crate) fn truncated_normal_moments<const N: usize>(lower: f64) -> [f64; N] {
    let mut k = [0.0; N];
    let phi = (-0.5 * lower * lower).exp() / (2.0 * PI).sqrt();
    if N > 0 {
        k[0] = 0.5 * erfc(lower / 2f64.sqrt());
    }
    if N > 1 {
        k[1] = phi;
    }
    let mut l_pow = 1.0; // L^{n-1}
    for n in 2..N {
        l_pow *= lower;
        k[n] = (n - 1) as f64 * k[n - 2] + l_pow * phi;
    }
    k
}

/// The positive nodes and weights of the 8-point Gauss-Hermite rule for the standard normal
/// (probabilists' Hermite polynomial `He_8`, weights normalised to sum 1 over the 8 nodes
/// `+-x`): `E[g(Z)] = sum_i w_i (g(x_i) + g(-x_i))`, exact for polynomials of degree <= 15.
pub(crate) const GAUSS_HERMITE_8: [(f64, f64); 4] = [
    (0.539_079_811_351_375_1, 0.373_012_257_679_077_3),
    (1.636_519_042_435_108, 0.117_239_907_661_759_04),
    (2.802_485_861_287_541_6, 0.009_635_220_120_788_256),
    (4.144_547_186_125_894_5, 0.000_112_614_538_375_367_62),
];

#[cfg(test)]
mod tests {
    use super::*;

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    #[test]
    fn bessel_against_known_values() {
        let e = std::f64::consts::E;
        assert!(rel(bessel_i0e(1.0) * e, 1.266_065_877_752_008_2) < 1e-12);
        assert!(rel(bessel_i1e(1.0) * e, 0.565_159_103_992_485_1) < 1e-12);
        let table = [
            (1.0, 0.46575960759364043, 0.20791041534970844),
            (5.0, 0.18354081260932306, 0.16397226694454237),
            (29.9, 0.07326921904600191, 0.07203337491186879),
            (30.1, 0.07302329413106094, 0.07179985435101434),
            (50.0, 0.05656162664745419, 0.0559931238928954),
            (700.0, 0.015081295651531358, 0.015070519444716848),
            (1e4, 0.003989472674604732, 0.003989273195983662),
        ];
        for (x, i0e, i1e) in table {
            assert!(
                rel(bessel_i0e(x), i0e) < 1e-12,
                "i0e({x}) = {}",
                bessel_i0e(x)
            );
            assert!(
                rel(bessel_i1e(x), i1e) < 1e-12,
                "i1e({x}) = {}",
                bessel_i1e(x)
            );
            assert!(rel(bessel_i0e(-x), i0e) < 1e-12 && rel(bessel_i1e(-x), -i1e) < 1e-12);
        }
        assert_eq!(bessel_i0e(0.0), 1.0);
        assert_eq!(bessel_i1e(0.0), 0.0);
        assert!(bessel_i0e(f64::INFINITY) == 0.0);
        for (x, v) in [
            (1.0, 0.8427007929497149),
            (0.3, 0.3286267594591274),
            (2.5, 0.999593047982555),
            (5.5, 0.9999999999999927),
        ] {
            assert!(rel(erf(x), v) < 1e-14, "erf({x})");
            assert!(rel(erf(-x), -v) < 1e-14);
        }
    }

    /// `erfc` on both sides of its switch at 1 and in the far tail against the quadrature of
    /// `2/sqrt(pi) e^{-t^2}` (tolerance 1e-13 relative).
    #[test]
    fn erfc_keeps_relative_accuracy_in_the_tail() {
        use crate::quadrature::{integrate, Tolerance};
        let tol = Tolerance {
            abs: 1e-320,
            rel: 1e-15,
            max_intervals: 400,
        };
        for x in [0.3, 0.999, 1.0, 1.2, 2.0, 2.5, 4.0, 9.0, 20.0] {
            let q = integrate(|t| 2.0 / PI.sqrt() * (-t * t).exp(), x, x + 12.0, tol).value;
            assert!(rel(erfc(x), q) < 1e-13, "erfc({x}) = {} vs {q}", erfc(x));
            assert!(rel(erfc(-x), 2.0 - q) < 1e-15);
        }
    }

    /// The truncated normal moments against direct quadrature at a negative, zero and positive
    /// truncation point (tolerance 1e-11 relative: the quadrature's own 1e-13 plus rounding), and
    /// the untruncated limit: `K_n(-40)` are the normal moments `0, 1, 0, 3, 0, 15` to 1e-15.
    #[test]
    fn truncated_normal_moments_against_quadrature() {
        use crate::quadrature::{integrate, Tolerance};
        let tol = Tolerance {
            abs: 1e-300,
            rel: 1e-13,
            max_intervals: 400,
        };
        for lower in [-2.5, -0.3, 0.0, 1.7, 6.0] {
            let k = truncated_normal_moments::<9>(lower);
            for (n, kn) in k.iter().enumerate() {
                let f = |z: f64| z.powi(n as i32) * (-0.5 * z * z).exp() / (2.0 * PI).sqrt();
                let q = integrate(f, lower, lower.max(0.0) + 40.0, tol).value;
                assert!(rel(*kn, q) < 1e-11, "L {lower} n {n}: {kn} vs {q}");
            }
        }
        let k = truncated_normal_moments::<6>(-40.0);
        for (kn, exact) in k.iter().zip([1.0, 0.0, 1.0, 0.0, 3.0, 0.0]) {
            assert!((kn - exact).abs() < 1e-14 * exact.max(1.0), "{k:?}");
        }
    }

    /// The Gauss-Hermite rule reproduces the normal moments `E Z^{2k} = (2k-1)!!` for
    /// `2k <= 14` (it is exact to degree 15; tolerance 1e-14 relative, rounding of the tabulated
    /// nodes) and its weights sum to 1/2 over the positive half.
    #[test]
    fn gauss_hermite_rule_integrates_normal_moments() {
        let mut double_fact = 1.0;
        for k in 0..8 {
            if k > 0 {
                double_fact *= (2 * k - 1) as f64;
            }
            let m: f64 = GAUSS_HERMITE_8
                .iter()
                .map(|(x, w)| 2.0 * w * x.powi(2 * k))
                .sum();
            assert!(rel(m, double_fact) < 1e-14, "k {k}: {m} vs {double_fact}");
        }
    }
}
