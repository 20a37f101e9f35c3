//! Mean and spread of the estimated DoLP and AoP by integration over the Gaussian Stokes
//! estimate, valid at every polarised SNR and for any 3 x 3 covariance (MODEL.md section 7,
//! "DoLP and AoP statistics").
//!
//! # Model
//!
//! `S_hat = (S0, q)`, `q = (S1, S2)`, jointly normal with mean `(mu0, m)` and covariance
//! `Sigma`; `C` the `(S1, S2)` block (positive definite), `P = C^-1`. Conditionally on `q`,
//! `S0 = mu0 + beta . (q - m) + eps` with `beta = P Sigma_q0` and `eps ~ N(0, v0)`,
//! `v0 = Sigma_00 - Sigma_0q beta` (the part of the `S0` noise not explained by `q`).
//!
//! With `p = |m|`, `d = p / mu0` (the DoLP of the mean), `theta0 = atan2(m2, m1)`, the DoLP
//! error is written without cancellation as `D - d = N / S0`, `N = |q| - p - d (S0 - mu0)`, and
//! `1 / S0 = (1/mu0) sum_k (-x)^k`, `x = (S0 - mu0) / mu0` (the `S0` series, truncated at order
//! `K` chosen from the relative `S0` noise `eta = sqrt(Sigma_00) / mu0` so that the first term
//! left out, about `K!! (K + 2) eta^(K+1)`, is below 1e-10; order at most [`MAX_S0_ORDER`]).
//!
//! # Integration
//!
//! In polar coordinates `q = r (cos theta, sin theta)`, `theta = theta0 + phi`, the normal
//! density along a ray is `exp(-(a (r - mu_r)^2 + D^2) / 2) / (2 pi sqrt(det C))` with
//! `a = u^T P u`, `mu_r = u^T P m / a` and `D^2 = (p sin phi)^2 / (a det C)` (the squared
//! Mahalanobis distance of `m` from the ray's line; the Binet-Cauchy identity). With
//! `r = mu_r + z / sqrt(a)` every radial integrand is a polynomial in `z` times the normal
//! density truncated at `z = -mu_r sqrt(a)`, integrated exactly by the truncated normal
//! moments; `eps` is integrated exactly by the 8-point Gauss-Hermite rule (the integrand is a
//! polynomial of degree at most `K + 2 <= 15` in `eps`). What is left is a smooth periodic
//! integral over `phi`, done by adaptive Gauss-Kronrod with break points at multiples of the
//! angular width `sqrt(lambda_max(C)) / p` of the phase density, with an error estimate.
//!
//! Five components are integrated on the same partition: the phase density `g(phi)` (which
//! integrates to 1: a check), the first two moments of the AoP error `phi / 2` (wrapped into
//! `(-pi/2, pi/2]` by construction: `phi` runs over `(-pi, pi]`), and `E[D - d]`,
//! `E[(D - d)^2]`. Nothing here depends on the polarised SNR being large or small: at `p = 0`
//! the same formulas give the Rayleigh case, and as the SNR grows the break points follow the
//! narrowing phase density. The quantities `mu_r - p = p u^T P (u0 - u) / a` and
//! `mu_r u - m` are computed from `u0 - u = 2 sin(phi/2) (sin(theta0 + phi/2),
//! -cos(theta0 + phi/2))`, so no digits are lost to cancellation at high SNR.

use super::special::{truncated_normal_moments, GAUSS_HERMITE_8};
use crate::quadrature::{integrate_n, Tolerance};
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::PI;

/// Highest order `K` of the `1 / S0` series (odd; the `eps` polynomial then has degree at most
/// `K + 2 = 13`, inside the Gauss-Hermite rule's exactness).
pub const MAX_S0_ORDER: usize = 11;

/// Coefficients of a polynomial in `z` (degree up to `K + 3`).
const NP: usize = MAX_S0_ORDER + 4;

/// Target of the `S0` series' truncation error (relative).
const S0_SERIES_TARGET: f64 = 1e-10;

/// Smallest eigenvalue of the `(S1, S2)` covariance, relative to the largest, for which the
/// integration is used (below it `q` lies on a line and the polar form degenerates).
pub(crate) const MIN_COV_RATIO: f64 = 1e-12;

/// The integrated moments.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct IntegratedMoments {
    pub(crate) dolp_mean: f64,
    pub(crate) dolp_var: f64,
    /// Mean of the wrapped AoP error about the AoP of the mean Stokes vector.
    pub(crate) aop_bias_rad: f64,
    /// Mean square of the wrapped AoP error (about the AoP of the mean, so it includes the bias).
    pub(crate) aop_ms_rad2: f64,
    /// Estimated relative error of the DoLP mean, the DoLP std and the AoP std (the largest).
    pub(crate) rel_error: f64,
    /// Estimated relative truncation error of the `S0` series alone.
    pub(crate) s0_series_error: f64,
    /// Whether every adaptive integral met its tolerance.
    pub(crate) converged: bool,
}

/// `(K, estimated truncation error)` for relative `S0` noise `eta`: the smallest odd `K` whose
/// first omitted term `K!! (K + 2) eta^(K+1)` is below [`S0_SERIES_TARGET`], at most
/// [`MAX_S0_ORDER`].
fn s0_series_order(eta: f64) -> (usize, f64) {
    let mut double_fact = 1.0; // K!!
    let mut k = 1;
    loop {
        let term = double_fact * (k + 2) as f64 * eta.powi(k as i32 + 1);
        if term < S0_SERIES_TARGET || k >= MAX_S0_ORDER {
            return (k, term);
        }
        k += 2;
        double_fact *= k as f64;
    }
}

/// `out = a * b` truncated to [`NP`] coefficients (`b` linear).
fn mul_linear(a: &[f64; NP], b0: f64, b1: f64) -> [f64; NP] {
    let mut out = [0.0; NP];
    for n in (0..NP).rev() {
        out[n] = a[n] * b0 + if n > 0 { a[n - 1] * b1 } else { 0.0 };
    }
    out
}

/// `sum_n c_n K_n`.
fn against(c: &[f64; NP], k: &[f64; NP]) -> f64 {
    c.iter().zip(k).map(|(a, b)| a * b).sum()
}

/// The DoLP and AoP moments of `mean_stokes`, `cov` (validated, symmetric positive
/// semidefinite, `S0 > 0`) by the integration described in the module documentation; `None`
/// when the `(S1, S2)` covariance is singular (smallest eigenvalue below [`MIN_COV_RATIO`] of
/// the largest), where the polar form does not apply.
pub(crate) fn integrated_moments(
    mean_stokes: &Vector3<f64>,
    cov: &Matrix3<f64>,
) -> Option<IntegratedMoments> {
    let mu0 = mean_stokes[0];
    let (m1, m2) = (mean_stokes[1], mean_stokes[2]);
    let (c11, c12, c22) = (cov[(1, 1)], cov[(1, 2)], cov[(2, 2)]);
    let det = c11 * c22 - c12 * c12;
    let half_tr = 0.5 * (c11 + c22);
    let disc = (0.25 * (c11 - c22).powi(2) + c12 * c12).sqrt();
    let (l_max, l_min) = (half_tr + disc, det / (half_tr + disc));
    if !(l_max > 0.0 && l_min > MIN_COV_RATIO * l_max && det > 0.0) {
        return None;
    }
    // P = C^-1.
    let (p11, p12, p22) = (c22 / det, -c12 / det, c11 / det);
    let quad = |x: (f64, f64), y: (f64, f64)| {
        x.0 * (p11 * y.0 + p12 * y.1) + x.1 * (p12 * y.0 + p22 * y.1)
    };
    let (s01, s02) = (cov[(0, 1)], cov[(0, 2)]);
    let beta = (p11 * s01 + p12 * s02, p12 * s01 + p22 * s02);
    let v0 = (cov[(0, 0)] - (s01 * beta.0 + s02 * beta.1)).max(0.0);
    let sqrt_v0 = v0.sqrt();
    let p = m1.hypot(m2);
    let theta0 = if p > 0.0 { m2.atan2(m1) } else { 0.0 };
    let d = p / mu0;
    let eta = cov[(0, 0)].max(0.0).sqrt() / mu0;
    let (order, s0_series_error) = s0_series_order(eta);
    // Scales that make every component O(1).
    let sig_max = l_max.sqrt();
    let width = if p > 0.0 { (sig_max / p).min(PI) } else { PI };
    let aop_scale = 0.5 * width;
    let dolp_scale = sig_max / mu0;
    let norm = 1.0 / ((2.0 * PI).sqrt() * det.sqrt());
    let nodes: Vec<(f64, f64)> = if v0 > 0.0 {
        GAUSS_HERMITE_8
            .iter()
            .flat_map(|&(x, w)| [(x * sqrt_v0, w), (-x * sqrt_v0, w)])
            .collect()
    } else {
        vec![(0.0, 1.0)]
    };

    let integrand = |phi: f64| -> [f64; 5] {
        let theta = theta0 + phi;
        let (sn, cs) = theta.sin_cos();
        let (sh, ch) = (theta0 + 0.5 * phi).sin_cos();
        let two_sin_half = 2.0 * (0.5 * phi).sin();
        // u0 - u and u.
        let du = (two_sin_half * sh, -two_sin_half * ch);
        let u = (cs, sn);
        let a = quad(u, u);
        let s = 1.0 / a.sqrt();
        let dmu = p * quad(u, du) / a; // mu_r - p
        let mu_r = p + dmu;
        let dist2 = (p * phi.sin()).powi(2) / (a * det);
        let weight = s * (-0.5 * dist2).exp() * norm;
        let k = truncated_normal_moments::<NP>(-mu_r / s);
        let g = weight * (mu_r * k[0] + s * k[1]);
        let half_phi = 0.5 * phi;
        let mut out = [
            g,
            g * half_phi / aop_scale,
            g * (half_phi / aop_scale).powi(2),
            0.0,
            0.0,
        ];
        if weight == 0.0 {
            return out;
        }
        // mu_r u - m = dmu u - p (u0 - u); its S0 shift at z = 0, and the slope in z.
        let v = (dmu * u.0 - p * du.0, dmu * u.1 - p * du.1);
        let e0c = beta.0 * v.0 + beta.1 * v.1;
        let e1 = s * (beta.0 * u.0 + beta.1 * u.1);
        let (mut dev1, mut dev2) = (0.0, 0.0);
        for &(eps, w) in &nodes {
            // x = (S0 - mu0) / mu0 = x0 + x1 z.
            let (x0, x1) = ((e0c + eps) / mu0, e1 / mu0);
            let mut pow = [0.0; NP];
            pow[0] = 1.0;
            let (mut r1, mut r2) = ([0.0; NP], [0.0; NP]);
            for kk in 0..=order {
                for n in 0..NP {
                    r1[n] += pow[n];
                    r2[n] += (kk + 1) as f64 * pow[n];
                }
                pow = mul_linear(&pow, -x0, -x1);
            }
            // N = n0 + n1 z with the eps term, times the Jacobian r = mu_r + s z.
            let (n0, n1) = (dmu - d * e0c - d * eps, s - d * e1);
            let t1 = mul_linear(&mul_linear(&r1, n0, n1), mu_r, s);
            let t2 = mul_linear(&mul_linear(&mul_linear(&r2, n0, n1), n0, n1), mu_r, s);
            dev1 += w * against(&t1, &k);
            dev2 += w * against(&t2, &k);
        }
        out[3] = weight * dev1 / (mu0 * dolp_scale);
        out[4] = weight * dev2 / (mu0 * mu0 * dolp_scale * dolp_scale);
        out
    };

    // Break points at multiples of the phase density's width, inside (-pi, pi).
    let mut breaks = vec![-PI];
    for m in [-20.0, -8.0, -3.0, -1.0, 0.0, 1.0, 3.0, 8.0, 20.0] {
        let x = m * width;
        if x > -PI && x < PI {
            breaks.push(x);
        }
    }
    breaks.push(PI);
    let tol = Tolerance {
        abs: 1e-13,
        rel: 1e-11,
        max_intervals: 200,
    };
    let mut total = [0.0; 5];
    let mut error = 0.0;
    let mut converged = true;
    let mut f = integrand;
    for pair in breaks.windows(2) {
        let r = integrate_n(&mut f, pair[0], pair[1], tol);
        for (t, v) in total.iter_mut().zip(r.value) {
            *t += v;
        }
        error += r.error;
        converged &= r.converged;
    }
    let [mass, a1, a2, dv1, dv2] = total;
    let aop_bias_rad = a1 * aop_scale;
    let aop_ms_rad2 = (a2 * aop_scale * aop_scale).max(0.0);
    let mean_dev = dv1 * dolp_scale;
    let dolp_mean = d + mean_dev;
    let dolp_var = ((dv2 - dv1 * dv1) * dolp_scale * dolp_scale).max(0.0);
    // Relative errors: quadrature (the error is in scaled units) and the S0 series.
    let rel_mean = error * dolp_scale / dolp_mean.abs().max(f64::MIN_POSITIVE);
    let var_scaled = (dv2 - dv1 * dv1).max(f64::MIN_POSITIVE);
    let rel_std = 0.5 * error * (1.0 + 2.0 * dv1.abs()) / var_scaled;
    let rel_aop = 0.5 * error / a2.max(f64::MIN_POSITIVE);
    let rel_error = rel_mean
        .max(rel_std)
        .max(rel_aop)
        .max((mass - 1.0).abs())
        .max(s0_series_error);
    let finite = [dolp_mean, dolp_var, aop_bias_rad, aop_ms_rad2, rel_error]
        .iter()
        .all(|v| v.is_finite());
    finite.then_some(IntegratedMoments {
        dolp_mean,
        dolp_var,
        aop_bias_rad,
        aop_ms_rad2,
        rel_error,
        s0_series_error,
        converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The series order follows the relative S0 noise: 1 for a noise-free S0, more terms as
    /// `eta` grows, and the estimate of the first omitted term below the 1e-10 target until the
    /// order cap (at `eta = 0.3` the cap leaves about 7e-2, which the caller reports).
    #[test]
    fn s0_series_order_follows_the_relative_noise() {
        assert_eq!(s0_series_order(0.0), (1, 0.0));
        let (k_small, e_small) = s0_series_order(1e-3);
        let (k_mid, e_mid) = s0_series_order(0.03);
        assert!(k_small < k_mid && e_small < 1e-10 && e_mid < 1e-10);
        let (k_big, e_big) = s0_series_order(0.3);
        assert_eq!(k_big, MAX_S0_ORDER);
        assert!(e_big > 1e-2 && e_big < 0.1, "{e_big}");
    }
}
