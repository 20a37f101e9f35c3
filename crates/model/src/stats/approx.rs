//! The closed-form approximations of the DoLP and AoP statistics, kept for comparison with the
//! integration of [`super::dolp_aop`] (MODEL.md section 7): the delta method ("Taylor":
//! second-order mean, first-order variance, AoP spread scaled by the Rician phase spread) and the
//! isotropic Rice moments with the `S0` noise to first order ("Rice").
//!
//! Both replace the `(S1, S2)` noise by simplifications: the Taylor forms drop every term of
//! order `1 / SNR^2` in the variance (percent-level errors between polarised SNR 2 and 7), and
//! the Rice forms replace an anisotropic `(S1, S2)` covariance by its isotropic equivalent
//! `sigma_p^2 = (var S1 + var S2) / 2`.

use super::special::{bessel_i0e, bessel_i1e, erf, laguerre_half};
use crate::quadrature::{integrate, Tolerance};
use nalgebra::{Matrix2, Matrix3, Vector3};
use std::f64::consts::{FRAC_PI_2, PI};

/// Below this polarised SNR the Taylor approximation's first-order AoP spread is corrected by
/// the exact Rician phase spread (see [`taylor_approximation`]); above it the correction is
/// below 0.5 %.
pub const AOP_PHASE_SNR: f64 = 10.0;

/// Standard deviation of an angle uniform over an interval of length `pi` (the AoP of an
/// unpolarised state): `pi / sqrt(12)` radians (about 51.96 deg).
pub const AOP_STD_UNIFORM_RAD: f64 = 0.906_899_682_117_108_9;

/// Moments from one of the closed-form approximations.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ApproxMoments {
    pub(crate) dolp_mean: f64,
    pub(crate) dolp_var: f64,
    pub(crate) aop_std_rad: f64,
    pub(crate) warnings: Vec<String>,
}

/// Gradient and Hessian of `f(S) = p / S0` at `S` with `p > 0` (see [`taylor_approximation`]).
fn dolp_grad_hessian(s: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    let (s0, s1, s2) = (s[0], s[1], s[2]);
    let p = s1.hypot(s2);
    let (u1, u2) = (s1 / p, s2 / p);
    let grad = Vector3::new(-p / (s0 * s0), u1 / s0, u2 / s0);
    let h00 = 2.0 * p / (s0 * s0 * s0);
    let h01 = -u1 / (s0 * s0);
    let h02 = -u2 / (s0 * s0);
    let c = 1.0 / (p * s0);
    let hess = Matrix3::new(
        h00,
        h01,
        h02, //
        h01,
        u2 * u2 * c,
        -u1 * u2 * c, //
        h02,
        -u1 * u2 * c,
        u1 * u1 * c,
    );
    (grad, hess)
}

/// Taylor-regime moments `(dolp_mean, dolp_var, aop_var)`; `None` if not finite.
fn taylor_moments(s: &Vector3<f64>, cov: &Matrix3<f64>) -> Option<(f64, f64, f64)> {
    let p = s[1].hypot(s[2]);
    if p <= 0.0 {
        return None;
    }
    let (grad, hess) = dolp_grad_hessian(s);
    let tr_h_sigma = hess.component_mul(cov).sum();
    let dolp_mean = p / s[0] + 0.5 * tr_h_sigma;
    let dolp_var = (grad.transpose() * cov * grad)[0].max(0.0);
    let (u1, u2) = (s[1] / p, s[2] / p);
    let grad_aop = Vector3::new(0.0, -u2 / (2.0 * p), u1 / (2.0 * p));
    let aop_var = (grad_aop.transpose() * cov * grad_aop)[0].max(0.0);
    (dolp_mean.is_finite() && dolp_var.is_finite() && aop_var.is_finite())
        .then_some((dolp_mean, dolp_var, aop_var))
}

/// Polarised SNR above which the Rice moments use their large-SNR expansions (the closed forms
/// lose digits to cancellation in `E[p^2] - E[p]^2` there).
const RICE_ASYMPTOTIC_SNR: f64 = 1e3;

/// Rice moments of `p_hat = |(S1, S2)_hat|` for true `p` and per-component noise `sigma`:
/// `(E[p_hat], Var[p_hat], dE[p_hat]/dp)`.
///
/// `E[p_hat] = sigma sqrt(pi/2) L_{1/2}(-rho^2/2)`, `rho = p / sigma`, `E[p_hat^2] = p^2 +
/// 2 sigma^2`; with `z = rho^2 / 4`, `L_{1/2}(-2z) = (1 + 2z) I0e(z) + 2z I1e(z)` and
/// `d/dz L_{1/2}(-2z) = I0e(z) + I1e(z)`, so `dE/dp = sqrt(pi/2) (rho/2) (I0e(z) + I1e(z))`
/// (0 at `p = 0`, 1 at high SNR). Above `rho = 1000`: `E = p + sigma^2/(2p) + sigma^4/(8p^3)`,
/// `Var = sigma^2 (1 - 1/(2 rho^2))`.
pub(crate) fn rice_moments(p: f64, sigma: f64) -> (f64, f64, f64) {
    if sigma <= 0.0 {
        return (p, 0.0, if p > 0.0 { 1.0 } else { 0.0 });
    }
    let rho = p / sigma;
    if rho > RICE_ASYMPTOTIC_SNR {
        let r2 = rho * rho;
        let m1 = sigma * (rho + 0.5 / rho + 0.125 / (r2 * rho));
        let var = sigma * sigma * (1.0 - 0.5 / r2);
        let d = 1.0 - 0.5 / r2;
        return (m1, var, d);
    }
    let z = 0.25 * rho * rho;
    let (i0e, i1e) = (bessel_i0e(z), bessel_i1e(z));
    let sqrt_half_pi = FRAC_PI_2.sqrt();
    let m1 = sigma * sqrt_half_pi * laguerre_half(-2.0 * z);
    let var = (p * p + 2.0 * sigma * sigma - m1 * m1).max(0.0);
    let d = sqrt_half_pi * 0.5 * rho * (i0e + i1e);
    (m1, var, d)
}

/// Density of the phase `phi` (about the true phase) of a Rician variable with SNR `rho`
/// (per-component noise 1): `f = (1/2pi) [e^{-rho^2/2} + sqrt(pi/2) rho cos(phi)
/// e^{-rho^2 sin^2(phi)/2} (1 + erf(rho cos(phi) / sqrt 2))]` (Rice 1945; the standard
/// phase-noise density, written with `e^{-rho^2/2} e^{rho^2 cos^2/2} = e^{-rho^2 sin^2/2}` so that
/// nothing overflows).
fn rician_phase_density(phi: f64, rho: f64) -> f64 {
    let (s, c) = phi.sin_cos();
    let u = rho * c;
    ((-0.5 * rho * rho).exp()
        + FRAC_PI_2.sqrt() * u * (-0.5 * rho * rho * s * s).exp() * (1.0 + erf(u / 2f64.sqrt())))
        / (2.0 * PI)
}

/// Standard deviation of the AoP in the Rice regime, `sqrt(Var phi) / 2` with `Var phi` the
/// variance over `(-pi, pi]` of the Rician phase; returns it and whether the quadrature met its
/// tolerance.
pub(crate) fn rice_aop_std(rho: f64) -> (f64, bool) {
    if rho <= 0.0 {
        return (AOP_STD_UNIFORM_RAD, true);
    }
    if rho > RICE_ASYMPTOTIC_SNR {
        // Var phi = (1/rho^2) (1 + 1/rho^2 + O(rho^-4)).
        return (0.5 / rho * (1.0 + 0.5 / (rho * rho)), true);
    }
    let tol = Tolerance {
        abs: 1e-12,
        rel: 1e-10,
        max_intervals: 200,
    };
    // Symmetric density: Var phi = 2 int_0^pi phi^2 f. At high SNR the mass sits within a few
    // 1/rho of 0: split there (beyond 12/rho the density is below e^-72 of its peak) so that the
    // adaptive rule sees the peak.
    let integrand = |phi: f64| phi * phi * rician_phase_density(phi, rho);
    let split = (12.0 / rho).min(PI);
    let mut r = integrate(integrand, 0.0, split, tol);
    if split < PI {
        let tail = integrate(integrand, split, PI, tol);
        r.value += tail.value;
        r.converged &= tail.converged;
    }
    ((2.0 * r.value).max(0.0).sqrt() * 0.5, r.converged)
}

/// The delta-method ("Taylor") approximation at `s` with covariance `cov` (`p > 0`), with the
/// first-order AoP spread scaled below [`AOP_PHASE_SNR`] by `2 rho s(rho)`, `s(rho)` the exact
/// Rician phase spread halved; `None` where the forms are singular or overflow.
///
/// Gradient `grad f = [-p/S0^2, S1/(p S0), S2/(p S0)]` of `f = p / S0`, exact Hessian
///
/// ```text
///     H = [  2p/S0^3       -S1/(p S0^2)      -S2/(p S0^2)    ]
///         [ -S1/(p S0^2)    S2^2/(p^3 S0)    -S1 S2/(p^3 S0) ]
///         [ -S2/(p S0^2)   -S1 S2/(p^3 S0)    S1^2/(p^3 S0)  ]
/// ```
///
/// `E[f] = f(mu) + 0.5 tr(H Sigma)`, `Var f = grad^T Sigma grad`; AoP gradient
/// `[0, -S2/(2p^2), S1/(2p^2)]`.
pub(crate) fn taylor_approximation(
    s: &Vector3<f64>,
    cov: &Matrix3<f64>,
    polarised_snr: f64,
) -> Option<ApproxMoments> {
    let (dolp_mean, dolp_var, aop_var) = taylor_moments(s, cov)?;
    let mut warnings = Vec::new();
    let mut aop_std_rad = aop_var.sqrt();
    if polarised_snr < AOP_PHASE_SNR {
        let (phase_std, converged) = rice_aop_std(polarised_snr);
        aop_std_rad *= phase_std * 2.0 * polarised_snr;
        if !converged {
            warnings.push(format!(
                "AoP phase-distribution quadrature did not meet 1e-10 at SNR {polarised_snr:.3e}"
            ));
        }
    }
    aop_std_rad.is_finite().then_some(ApproxMoments {
        dolp_mean,
        dolp_var,
        aop_std_rad,
        warnings,
    })
}

/// The isotropic Rice approximation: `(S1, S2)_hat` treated as isotropic bivariate normal with
/// per-component variance `sigma_p^2`, so `p_hat` is Rician (Rice 1945; moments as in Sijbers
/// et al. 1998): `m1 = E[p_hat] = sigma_p sqrt(pi/2) L_{1/2}(-p^2/(2 sigma_p^2))`,
/// `E[p_hat^2] = p^2 + 2 sigma_p^2`. `S0_hat` enters through the delta method on the ratio
/// `p_hat / S0_hat`: `E[DoLP] = m1/S0 - c/S0^2 + m1 Sigma_00/S0^3`,
/// `Var DoLP = Var p_hat/S0^2 - 2 m1 c/S0^3 + m1^2 Sigma_00/S0^4`, with
/// `c = Cov(p_hat, S0_hat) = (Sigma_01 u1 + Sigma_02 u2) dm1/dp` by Stein's lemma, clamped to
/// the Cauchy-Schwarz bound of the isotropic variance. The AoP spread is that of the Rician
/// phase, halved.
pub(crate) fn rice_approximation(
    s: &Vector3<f64>,
    cov: &Matrix3<f64>,
    sigma_p: f64,
    polarised_snr: f64,
) -> ApproxMoments {
    let (s0, s1, s2) = (s[0], s[1], s[2]);
    let p = s1.hypot(s2);
    let mut warnings = Vec::new();
    let block = Matrix2::new(cov[(1, 1)], cov[(1, 2)], cov[(2, 1)], cov[(2, 2)]);
    let e = block.symmetric_eigen().eigenvalues;
    let (l_hi, l_lo) = (e.max(), e.min());
    if l_hi > 0.0 && (l_hi - l_lo) > 0.05 * l_hi {
        warnings.push(format!(
            "(S1, S2) covariance anisotropic (eigenvalues {l_hi:.3e}, {l_lo:.3e}): Rice moments \
             use the isotropic equivalent sigma_p^2 = (var S1 + var S2)/2 = {:.3e}; DoLP bias and \
             AoP spread are approximate",
            sigma_p * sigma_p
        ));
    }
    let (m1, var_p, dm1_dp) = rice_moments(p, sigma_p);
    let mut c = if p > 0.0 {
        (cov[(0, 1)] * s1 / p + cov[(0, 2)] * s2 / p) * dm1_dp
    } else {
        0.0
    };
    let c_max = (var_p * cov[(0, 0)]).max(0.0).sqrt();
    if c.abs() > c_max {
        warnings.push(format!(
            "Cov(p_hat, S0_hat) = {c:.3e} exceeds the Cauchy-Schwarz bound {c_max:.3e} of the \
             isotropic Rice variance (anisotropic noise correlated with S0): clamped, the DoLP \
             spread is approximate"
        ));
        c = c.signum() * c_max;
    }
    let sig00 = cov[(0, 0)];
    let dolp_mean = m1 / s0 - c / (s0 * s0) + m1 * sig00 / (s0 * s0 * s0);
    let dolp_var = (var_p / (s0 * s0) - 2.0 * m1 * c / (s0 * s0 * s0)
        + m1 * m1 * sig00 / (s0 * s0 * s0 * s0))
        .max(0.0);
    let aop_std_rad = if p > 0.0 && sigma_p == 0.0 {
        0.0
    } else {
        let (std, converged) = rice_aop_std(polarised_snr);
        if !converged {
            warnings.push(format!(
                "AoP phase-distribution quadrature did not meet 1e-10 at SNR {polarised_snr:.3e}"
            ));
        }
        std
    };
    ApproxMoments {
        dolp_mean,
        dolp_var,
        aop_std_rad,
        warnings,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    /// (step 1e-3 relative; truncation O(h^2) ~ 1e-6, rounding ~ eps/h^2 ~ 1e-10: tolerance 1e-5).
    #[test]
    fn dolp_hessian_matches_finite_differences() {
        let s = Vector3::new(3.0, 0.7, -1.1);
        let (grad, hess) = dolp_grad_hessian(&s);
        let f = |v: &Vector3<f64>| v[1].hypot(v[2]) / v[0];
        let h = 1e-3;
        for i in 0..3 {
            let mut e_i = Vector3::zeros();
            e_i[i] = h;
            let g = (f(&(s + e_i)) - f(&(s - e_i))) / (2.0 * h);
            assert!((g - grad[i]).abs() < 1e-5, "grad {i}");
            for j in 0..3 {
                let mut e_j = Vector3::zeros();
                e_j[j] = h;
                let d = (f(&(s + e_i + e_j)) - f(&(s + e_i - e_j)) - f(&(s - e_i + e_j))
                    + f(&(s - e_i - e_j)))
                    / (4.0 * h * h);
                assert!(
                    (d - hess[(i, j)]).abs() < 1e-5,
                    "H {i}{j}: {d} vs {}",
                    hess[(i, j)]
                );
            }
        }
    }

    /// The Rice AoP std tends to the Taylor value `sigma_p/(2p)` at high SNR (within 1 % at SNR
    /// 30, where the next term is `1/(2 SNR^2)` = 0.06 %), is continuous across the asymptotic
    /// switch at SNR 1000 to 1e-9 (quadrature tolerance 1e-10; the dropped expansion term is
    /// O(SNR^-4) = 1e-12), and tends to the uniform `pi/sqrt(12)` as SNR -> 0.
    #[test]
    fn rice_aop_std_limits() {
        let (a, ok) = rice_aop_std(30.0);
        assert!(ok && rel(a, 0.5 / 30.0) < 0.01);
        let rho = 999.999;
        let (below, _) = rice_aop_std(rho);
        let expansion = 0.5 / rho * (1.0 + 0.5 / (rho * rho));
        assert!(rel(below, expansion) < 1e-9, "{below} vs {expansion}");
        let (above, _) = rice_aop_std(1000.001);
        assert!(rel(below, above) < 3e-6, "{below} vs {above}");
        let (small, _) = rice_aop_std(1e-12);
        assert!((small - AOP_STD_UNIFORM_RAD).abs() < 1e-9);
    }

    /// Rice mean `E[p_hat]/sigma = sqrt(pi/2) L_{1/2}(-rho^2/2)` against mpmath (30 digits),
    /// tolerance 1e-12 relative (the Bessel functions are good to a few ulp).
    #[test]
    fn rice_mean_against_known_values() {
        for (rho, m) in [
            (0.0, 1.253_314_137_315_500_3),
            (1.0, 1.5485724605511455),
            (3.0, 3.172577287900718),
            (10.0, 10.05012693667742),
        ] {
            let (m1, _, _) = rice_moments(rho, 1.0);
            assert!(rel(m1, m) < 1e-12, "rho {rho}: {m1}");
            assert!(rel(FRAC_PI_2.sqrt() * laguerre_half(-0.5 * rho * rho), m) < 1e-12);
        }
    }
}
