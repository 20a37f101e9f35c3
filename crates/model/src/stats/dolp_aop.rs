//! Mean and spread of the estimated DoLP and AoP of a Gaussian Stokes estimate (MODEL.md
//! section 7, "DoLP and AoP statistics"): the public entry point [`dolp_aop_stats`], its result,
//! and the choice between the integration of [`super::integral`] (the default, valid at every
//! polarised SNR and for any covariance) and the closed-form approximations of
//! [`super::approx`] (on request, for comparison).

use super::approx::{rice_approximation, taylor_approximation, ApproxMoments};
use super::estimation::SYMMETRY_TOL;
use super::integral::integrated_moments;
use crate::error::ModelError;
use crate::polarization::Stokes;
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::{FRAC_PI_2, PI};

/// Polarised SNR `p / sigma_p` below which a state is labelled [`Regime::Rice`] (the DoLP
/// estimate is visibly biased upwards and the AoP spread departs from its first-order value;
/// MODEL.md section 7), and below which [`RegimeChoice::Auto`] would have used the Rice forms.
pub const RICE_SNR_THRESHOLD: f64 = 3.0;

/// Which polarised-SNR regime a state is in (or, for a forced [`RegimeChoice`], which
/// approximation produced the figures).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Regime {
    /// Polarised SNR at or above [`RICE_SNR_THRESHOLD`] (the delta method's domain).
    Taylor,
    /// Polarised SNR below [`RICE_SNR_THRESHOLD`] (Rician bias of the DoLP).
    Rice,
}

/// How the figures were computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatsMethod {
    /// Integration over the Gaussian Stokes estimate ([`super::integral`]), with an error
    /// estimate: valid at every polarised SNR, any anisotropic and correlated covariance.
    Integration,
    /// The delta method (second-order mean, first-order variance).
    Taylor,
    /// The isotropic Rice moments with the `S0` noise to first order.
    Rice,
}

/// The caller's choice of method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RegimeChoice {
    /// The integration at every polarised SNR; `regime` labels the SNR regime.
    #[default]
    Auto,
    /// The delta-method approximation (falls back to Rice, with a warning, where the Taylor forms
    /// are singular: `p = 0`).
    Taylor,
    /// The isotropic Rice approximation.
    Rice,
}

/// Mean and spread of the estimated DoLP and AoP.
#[derive(Debug, Clone, PartialEq)]
pub struct PolarizationStats {
    /// `E[DoLP_hat]` (biased upwards at low SNR: the estimator is not clamped).
    pub dolp_mean: f64,
    /// Standard deviation of `DoLP_hat`.
    pub dolp_std: f64,
    /// AoP of the mean Stokes vector, `0.5 atan2(S2, S1)` in `(-pi/2, pi/2]` (the crate's
    /// convention); 0 when `p = 0` (undefined, see `warnings`).
    pub aop_mean_rad: f64,
    /// Mean of the AoP error `AoP_hat - aop_mean_rad`, wrapped into `(-pi/2, pi/2]`, radians
    /// (0 for isotropic `(S1, S2)` noise by symmetry; 0 from the approximations).
    pub aop_bias_rad: f64,
    /// Standard deviation of the AoP about `aop_mean_rad`: the root-mean-square of the wrapped
    /// AoP error, radians (it includes the bias: `aop_std_rad^2 = Var(error) + aop_bias_rad^2`);
    /// `pi / sqrt(12)` for an unpolarised state.
    pub aop_std_rad: f64,
    /// The polarised-SNR regime (with a forced [`RegimeChoice`], the approximation used).
    pub regime: Regime,
    /// How the figures were computed.
    pub method: StatsMethod,
    /// Estimated relative error of `dolp_mean`, `dolp_std` and `aop_std_rad` (the largest) from
    /// the integration's quadrature and `S0` series; `None` for the approximations, whose error
    /// is not estimated.
    pub rel_error_estimate: Option<f64>,
    /// Polarised SNR `p / sigma_p` (`f64::MAX` when `sigma_p = 0 < p`, 0 when `p = 0`).
    pub polarised_snr: f64,
    /// Isotropic-equivalent polarised noise `sigma_p = sqrt((var S1 + var S2) / 2)`.
    pub sigma_p: f64,
    /// Approximations worth knowing about, in words.
    pub warnings: Vec<String>,
}

/// Validates a Stokes mean and covariance; returns the symmetrised covariance.
pub(crate) fn check_stokes_inputs(
    mean_stokes: &Vector3<f64>,
    stokes_cov: &Matrix3<f64>,
) -> Result<Matrix3<f64>, ModelError> {
    let s0 = mean_stokes[0];
    if !(s0.is_finite() && s0 > 0.0) {
        return Err(ModelError::OutOfRange {
            field: "S0",
            value: s0,
            allowed: "> 0 and finite (a dark pixel has no DoLP)",
        });
    }
    for (field, v) in [("S1", mean_stokes[1]), ("S2", mean_stokes[2])] {
        if !v.is_finite() {
            return Err(ModelError::OutOfRange {
                field,
                value: v,
                allowed: "finite",
            });
        }
    }
    if let Some(bad) = stokes_cov.iter().find(|v| !v.is_finite()) {
        return Err(ModelError::OutOfRange {
            field: "stokes_cov",
            value: *bad,
            allowed: "finite entries",
        });
    }
    let scale = stokes_cov.amax();
    let asym = (stokes_cov - stokes_cov.transpose()).amax();
    if asym > SYMMETRY_TOL * scale {
        return Err(ModelError::Invalid {
            field: "stokes_cov",
            reason: format!("not symmetric (largest |C_ij - C_ji| = {asym:.3e})"),
        });
    }
    let sym = 0.5 * (stokes_cov + stokes_cov.transpose());
    let eig = sym.symmetric_eigen();
    let (l_min, l_max) = (eig.eigenvalues.min(), eig.eigenvalues.max());
    if l_min < -SYMMETRY_TOL * l_max.max(0.0) || (l_max <= 0.0 && l_min < 0.0) {
        return Err(ModelError::Invalid {
            field: "stokes_cov",
            reason: format!("not positive semidefinite (eigenvalues {l_min:.3e} .. {l_max:.3e})"),
        });
    }
    Ok(sym)
}

/// Folds an angle onto the AoP range `(-pi/2, pi/2]`.
pub(crate) fn fold_aop(a: f64) -> f64 {
    let r = a - PI * (a / PI).round();
    if r <= -FRAC_PI_2 {
        r + PI
    } else {
        r
    }
}

/// Estimated relative error above which the integration's answer carries a warning.
const WARN_REL_ERROR: f64 = 1e-3;

/// DoLP and AoP statistics of an estimated linear Stokes vector with mean `mean_stokes`
/// (`mu_S = [S0, S1, S2]`) and covariance `stokes_cov` (`Sigma_S`), MODEL.md section 7.
///
/// `DoLP_hat = |(S1, S2)_hat| / S0_hat` and `AoP_hat = 0.5 atan2(S2_hat, S1_hat)` of
/// `S_hat ~ N(mu_S, Sigma_S)`. `p = |(S1, S2)|`, `sigma_p^2 = (Sigma_11 + Sigma_22) / 2`,
/// polarised SNR `p / sigma_p`. The AoP spread is the standard deviation of the AoP about the
/// AoP of `mu_S` (the root-mean-square of the error, each error wrapped into `(-pi/2, pi/2]`;
/// what [`super::monte_carlo::monte_carlo_dolp_aop`] and the whole-chain validation measure);
/// the error's mean is `aop_bias_rad`.
///
/// * [`RegimeChoice::Auto`]: the integration of [`super::integral`] at every SNR, for the full
///   covariance (anisotropic `(S1, S2)` noise, `S0` noise correlated with it); `regime` is
///   [`Regime::Rice`] below polarised SNR [`RICE_SNR_THRESHOLD`] and [`Regime::Taylor`] above,
///   a label only (the method does not change, so nothing jumps there). Where the `(S1, S2)`
///   covariance is singular (zero, or `q` confined to a line), the integration does not apply
///   and the Taylor (or, at `p = 0`, Rice) approximation is used, with a warning.
/// * [`RegimeChoice::Taylor`], [`RegimeChoice::Rice`]: the closed-form approximations of
///   [`super::approx`] (for comparison; percent-level errors at polarised SNR 2 to 7).
///
/// At `p = 0` the AoP is undefined: `aop_mean_rad = 0` and `aop_std_rad` is the spread about 0
/// (`pi/sqrt(12)` for isotropic `(S1, S2)` noise; anisotropic noise concentrates the AoP along
/// its major axis), with a warning.
///
/// Errors: `S0` not finite or `<= 0`; `S1`, `S2` not finite; `stokes_cov` not finite, not
/// symmetric or not positive semidefinite.
pub fn dolp_aop_stats(
    mean_stokes: &Vector3<f64>,
    stokes_cov: &Matrix3<f64>,
    choice: RegimeChoice,
) -> Result<PolarizationStats, ModelError> {
    let cov = check_stokes_inputs(mean_stokes, stokes_cov)?;
    let (s0, s1, s2) = (mean_stokes[0], mean_stokes[1], mean_stokes[2]);
    let p = s1.hypot(s2);
    let sigma_p = (0.5 * (cov[(1, 1)] + cov[(2, 2)])).max(0.0).sqrt();
    let polarised_snr = if sigma_p > 0.0 {
        (p / sigma_p).min(f64::MAX)
    } else if p > 0.0 {
        f64::MAX
    } else {
        0.0
    };
    let mut warnings = Vec::new();
    let aop_mean_rad = match Stokes::new(s0, s1, s2).aop_rad() {
        Some(a) => a,
        None => {
            warnings.push(
                "p = 0: the AoP is undefined; aop_mean_rad set to 0 and aop_std_rad is the \
                 spread about 0 (the uniform value pi/sqrt(12) for isotropic (S1, S2) noise)"
                    .to_string(),
            );
            0.0
        }
    };
    let label = if polarised_snr < RICE_SNR_THRESHOLD {
        Regime::Rice
    } else {
        Regime::Taylor
    };
    let finish = |dolp_mean: f64,
                  dolp_var: f64,
                  aop_bias_rad: f64,
                  aop_std_rad: f64,
                  regime: Regime,
                  method: StatsMethod,
                  rel_error_estimate: Option<f64>,
                  warnings: Vec<String>| {
        if !(dolp_mean.is_finite() && dolp_var.is_finite() && aop_std_rad.is_finite()) {
            return Err(ModelError::Invalid {
                field: "stokes_cov",
                reason: format!(
                    "DoLP statistics overflow for S = [{s0:e}, {s1:e}, {s2:e}] with this \
                     covariance (sqrt(Sigma_00) must be small against S0)"
                ),
            });
        }
        Ok(PolarizationStats {
            dolp_mean,
            dolp_std: dolp_var.max(0.0).sqrt(),
            aop_mean_rad,
            aop_bias_rad,
            aop_std_rad,
            regime,
            method,
            rel_error_estimate,
            polarised_snr,
            sigma_p,
            warnings,
        })
    };
    let from_approx = |a: ApproxMoments, regime, method, mut warnings: Vec<String>| {
        warnings.extend(a.warnings);
        finish(
            a.dolp_mean,
            a.dolp_var,
            0.0,
            a.aop_std_rad,
            regime,
            method,
            None,
            warnings,
        )
    };
    if choice == RegimeChoice::Auto {
        if let Some(m) = integrated_moments(mean_stokes, &cov) {
            if !m.converged || m.rel_error > WARN_REL_ERROR {
                warnings.push(format!(
                    "DoLP/AoP integration: estimated relative error {:.1e} (S0 series {:.1e}: \
                     relative S0 noise {:.3}; quadrature converged: {})",
                    m.rel_error,
                    m.s0_series_error,
                    cov[(0, 0)].max(0.0).sqrt() / s0,
                    m.converged
                ));
            }
            return finish(
                m.dolp_mean,
                m.dolp_var,
                m.aop_bias_rad,
                m.aop_ms_rad2.sqrt(),
                label,
                StatsMethod::Integration,
                Some(m.rel_error),
                warnings,
            );
        }
        warnings.push(format!(
            "(S1, S2) covariance singular ([{:.3e}, {:.3e}; {:.3e}]): the integration does not \
             apply; closed-form approximation used",
            cov[(1, 1)],
            cov[(1, 2)],
            cov[(2, 2)]
        ));
    }
    if choice != RegimeChoice::Rice && p > 0.0 {
        if choice == RegimeChoice::Taylor && polarised_snr < RICE_SNR_THRESHOLD {
            warnings.push(format!(
                "Taylor approximation forced at polarised SNR {polarised_snr:.3} < \
                 {RICE_SNR_THRESHOLD}: the DoLP mean misses the Rician bias"
            ));
        }
        if let Some(a) = taylor_approximation(mean_stokes, &cov, polarised_snr) {
            let regime = if choice == RegimeChoice::Auto {
                label
            } else {
                Regime::Taylor
            };
            return from_approx(a, regime, StatsMethod::Taylor, warnings);
        }
    }
    if choice == RegimeChoice::Taylor {
        warnings.push(format!(
            "Taylor forms singular at p = {p:.3e} (the gradient of p is undefined at p = 0): \
             Rice approximation used"
        ));
    }
    let a = rice_approximation(mean_stokes, &cov, sigma_p, polarised_snr);
    let regime = if choice == RegimeChoice::Auto {
        label
    } else {
        Regime::Rice
    };
    from_approx(a, regime, StatsMethod::Rice, warnings)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::approx::{rice_aop_std, rice_moments, AOP_STD_UNIFORM_RAD};
    use crate::stats::monte_carlo::monte_carlo_dolp_aop;

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    /// Isotropic `(S1, S2)` noise and a noise-free `S0`: the DoLP is a Rician variable over
    /// `S0`, so the integration must give the closed-form Rice moments and the Rician phase
    /// spread exactly, at every polarised SNR from 0 to 100. Tolerance 1e-8 relative: the
    /// integration's tolerance is 1e-11 and its estimate is checked below 1e-9; the closed forms
    /// are good to about 1e-12 (`Var = p^2 + 2 sigma^2 - m1^2` loses 4 digits at SNR 100).
    #[test]
    fn integration_reproduces_the_rice_moments_for_isotropic_noise() {
        let sigma = 2.0;
        let cov = Matrix3::from_diagonal(&Vector3::new(0.0, sigma * sigma, sigma * sigma));
        for rho in [0.0, 0.3, 1.0, 2.0, 2.9, 3.0, 3.1, 5.0, 10.0, 30.0, 100.0] {
            let p = rho * sigma;
            // An AoP away from the axes: the polar integration must not care.
            let mu = Vector3::new(50.0, p * 0.6, -p * 0.8);
            let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
            assert_eq!(st.method, StatsMethod::Integration);
            let (m1, var_p, _) = rice_moments(p, sigma);
            let err = st.rel_error_estimate.unwrap();
            assert!(err < 1e-9, "rho {rho}: error estimate {err:e}");
            assert!(rel(st.dolp_mean, m1 / 50.0) < 1e-8, "rho {rho}: {st:?}");
            assert!(
                rel(st.dolp_std, var_p.sqrt() / 50.0) < 1e-8,
                "rho {rho}: {st:?}"
            );
            let aop = if rho > 0.0 {
                rice_aop_std(rho).0
            } else {
                AOP_STD_UNIFORM_RAD
            };
            assert!(
                rel(st.aop_std_rad, aop) < 1e-8,
                "rho {rho}: {st:?} vs {aop}"
            );
            assert!(
                st.aop_bias_rad.abs() < 1e-10,
                "symmetric: {}",
                st.aop_bias_rad
            );
        }
    }

    /// An independent `S0` noise (relative 5 %) with isotropic `(S1, S2)` noise: `p_hat` and
    /// `S0_hat` are independent, so `E[D] = E[p_hat] E[1/S0]` and
    /// `E[D^2] = E[p_hat^2] E[1/S0^2]`, with the moments of `1/S0` from the series
    /// `E[1/S0] = (1/S0) sum (2k-1)!! eta^(2k)`, `E[1/S0^2] = (1/S0^2) sum (2k+1)!! eta^(2k)`
    /// summed here to k = 8 (terms below 1e-15). Tolerance 1e-9 relative (quadrature 1e-11, series
    /// truncation estimate 1e-10).
    #[test]
    fn integration_handles_independent_s0_noise_exactly() {
        let (s0, eta, sigma): (f64, f64, f64) = (10.0, 0.05, 0.5);
        let cov = Matrix3::from_diagonal(&Vector3::new(
            (eta * s0).powi(2),
            sigma * sigma,
            sigma * sigma,
        ));
        let (mut inv1, mut inv2, mut df1, mut df2) = (0.0, 0.0, 1.0, 1.0);
        for k in 0..=8 {
            if k > 0 {
                df1 *= (2 * k - 1) as f64;
                df2 *= (2 * k + 1) as f64;
            }
            inv1 += df1 * eta.powi(2 * k);
            inv2 += df2 * eta.powi(2 * k);
        }
        let (inv1, inv2) = (inv1 / s0, inv2 / (s0 * s0));
        for rho in [0.0, 1.5, 3.0, 8.0] {
            let p = rho * sigma;
            let mu = Vector3::new(s0, 0.0, p);
            let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
            let (m1, var_p, _) = rice_moments(p, sigma);
            let mean = m1 * inv1;
            let var = (var_p + m1 * m1) * inv2 - mean * mean;
            assert!(
                rel(st.dolp_mean, mean) < 1e-9,
                "rho {rho}: {st:?} vs {mean}"
            );
            assert!(rel(st.dolp_std, var.sqrt()) < 1e-9, "rho {rho}: {st:?}");
        }
    }

    /// A correlated, anisotropic covariance (GLS-like: `S0` correlated with `S1` and `S2`,
    /// `(S1, S2)` eigenvalues 3:1).
    fn anisotropic_cov() -> Matrix3<f64> {
        Matrix3::new(
            120.0, 25.0, -10.0, //
            25.0, 300.0, 90.0, //
            -10.0, 90.0, 150.0,
        )
    }

    /// No discontinuity at the regime label's switch (polarised SNR 3): the method is the same
    /// on both sides, the label flips, and the statistics a relative 1e-9 apart in SNR differ by
    /// less than 1e-7 relative (their derivatives in SNR are O(1); quadrature noise 1e-11).
    /// Across 2.5 .. 3.5 in steps of 0.01 the second differences are below 1e-4 of the values
    /// (a smooth curve has second differences ~ h^2 f'' ~ 1e-4 f; a 0.1 % jump would give 1e-3).
    #[test]
    fn statistics_are_continuous_across_snr_three() {
        let cov = anisotropic_cov();
        let sigma_p = (0.5 * (cov[(1, 1)] + cov[(2, 2)])).sqrt();
        let at = |rho: f64| {
            let p = rho * sigma_p;
            let mu = Vector3::new(1000.0, 0.8 * p, 0.6 * p);
            dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap()
        };
        let (below, above) = (at(3.0 * (1.0 - 1e-9)), at(3.0));
        assert_eq!((below.regime, above.regime), (Regime::Rice, Regime::Taylor));
        assert_eq!(below.method, above.method);
        for (a, b) in [
            (below.dolp_mean, above.dolp_mean),
            (below.dolp_std, above.dolp_std),
            (below.aop_std_rad, above.aop_std_rad),
        ] {
            assert!(rel(a, b) < 1e-7, "{a} vs {b}");
        }
        let scan: Vec<PolarizationStats> = (0..=100).map(|i| at(2.5 + 0.01 * i as f64)).collect();
        for w in scan.windows(3) {
            for get in [
                |s: &PolarizationStats| s.dolp_mean,
                |s: &PolarizationStats| s.dolp_std,
                |s: &PolarizationStats| s.aop_std_rad,
            ] {
                let d2 = get(&w[0]) - 2.0 * get(&w[1]) + get(&w[2]);
                assert!(
                    d2.abs() < 1e-4 * get(&w[1]),
                    "SNR {}: second difference {d2:e}",
                    w[1].polarised_snr
                );
            }
        }
    }

    /// At high polarised SNR the integration tends to the delta method, whose relative errors
    /// are O(1/SNR^2) (the next terms of the expansion): at SNR 1e3 and 1e6, with the correlated
    /// anisotropic covariance, they agree within 10/SNR^2 (DoLP mean within 10/SNR^2 of the bias
    /// scale `sigma_p^2 / (p S0)`), and the integration's own error estimate stays below 1e-6.
    #[test]
    fn integration_tends_to_the_delta_method_at_high_snr() {
        let cov = anisotropic_cov();
        let sigma_p = (0.5 * (cov[(1, 1)] + cov[(2, 2)])).sqrt();
        for rho in [1e3, 1e6] {
            let p = rho * sigma_p;
            let s0 = 2.0 * p;
            let mu = Vector3::new(s0, -0.28 * p, 0.96 * p);
            let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
            let t = dolp_aop_stats(&mu, &cov, RegimeChoice::Taylor).unwrap();
            assert_eq!(
                (st.method, t.method),
                (StatsMethod::Integration, StatsMethod::Taylor)
            );
            let tol = 10.0 / (rho * rho);
            assert!(st.rel_error_estimate.unwrap() < 1e-6, "{st:?}");
            let bias_scale = sigma_p * sigma_p / (p * s0);
            assert!(
                (st.dolp_mean - t.dolp_mean).abs() < tol * t.dolp_mean + 0.1 * bias_scale,
                "SNR {rho}: {} vs {}",
                st.dolp_mean,
                t.dolp_mean
            );
            assert!(
                rel(st.dolp_std, t.dolp_std) < tol,
                "SNR {rho}: {st:?} vs {t:?}"
            );
            assert!(
                rel(st.aop_std_rad, t.aop_std_rad) < tol,
                "SNR {rho}: {st:?} vs {t:?}"
            );
        }
    }

    /// No NaN at the hard cases: S = (1, 0, 0) with zero and non-zero covariance, and
    /// S = (1e-12, 0, 0) with a tiny covariance (sigma = 1e-15), in every regime choice; results
    /// are finite, `p = 0` is labelled Rice, and a zero `(S1, S2)` covariance falls back to a
    /// closed form with a warning.
    #[test]
    fn no_nan_at_zero_dolp_and_tiny_s0() {
        let cases = [
            (Vector3::new(1.0, 0.0, 0.0), Matrix3::zeros()),
            (Vector3::new(1.0, 0.0, 0.0), Matrix3::identity() * 1e-4),
            (Vector3::new(1e-12, 0.0, 0.0), Matrix3::identity() * 1e-30),
            (Vector3::new(1.0, 0.5, 0.0), Matrix3::zeros()),
        ];
        for (mu, cov) in cases {
            for choice in [RegimeChoice::Auto, RegimeChoice::Taylor, RegimeChoice::Rice] {
                let st = dolp_aop_stats(&mu, &cov, choice).unwrap();
                let vals = [
                    st.dolp_mean,
                    st.dolp_std,
                    st.aop_mean_rad,
                    st.aop_std_rad,
                    st.polarised_snr,
                ];
                assert!(
                    vals.iter().all(|v| v.is_finite()),
                    "{mu:?} {choice:?}: {st:?}"
                );
                if mu[1] == 0.0 {
                    assert_eq!(st.regime, Regime::Rice);
                }
                if choice == RegimeChoice::Auto && cov[(1, 1)] == 0.0 {
                    assert_ne!(st.method, StatsMethod::Integration);
                    assert!(st.warnings.iter().any(|w| w.contains("singular")));
                }
            }
        }
        // Rayleigh mean 1e-15 sqrt(pi/2) / 1e-12, times E[1/S0] S0 = 1 + 1e-6 + 3e-12.
        let st = dolp_aop_stats(&cases[2].0, &cases[2].1, RegimeChoice::Auto).unwrap();
        assert_eq!(st.method, StatsMethod::Integration);
        assert!(rel(st.dolp_mean, 1e-3 * FRAC_PI_2.sqrt() * (1.0 + 1e-6)) < 1e-10);
        // A fully determined state: DoLP 0.5 exactly, no spread.
        let st = dolp_aop_stats(&cases[3].0, &cases[3].1, RegimeChoice::Auto).unwrap();
        assert!(st.dolp_mean == 0.5 && st.dolp_std == 0.0 && st.aop_std_rad == 0.0);
    }

    /// `S0 = 0`, negative or NaN is an error naming `S0`; a non-PSD covariance names `stokes_cov`.
    #[test]
    fn dark_or_invalid_inputs_are_errors() {
        for s0 in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let err = dolp_aop_stats(
                &Vector3::new(s0, 0.1, 0.0),
                &Matrix3::identity(),
                RegimeChoice::Auto,
            )
            .unwrap_err();
            assert!(
                matches!(err, ModelError::OutOfRange { field: "S0", .. }),
                "{err:?}"
            );
            assert!(
                monte_carlo_dolp_aop(&Vector3::new(s0, 0.0, 0.0), &Matrix3::identity(), 10, 1)
                    .is_err()
            );
        }
        let bad = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, 1.0));
        let err =
            dolp_aop_stats(&Vector3::new(1.0, 0.1, 0.0), &bad, RegimeChoice::Auto).unwrap_err();
        assert!(matches!(
            err,
            ModelError::Invalid {
                field: "stokes_cov",
                ..
            }
        ));
    }
}
