//! Processing statistics (MODEL.md section 7): Stokes estimation with covariance, and the mean
//! and spread of the estimated DoLP and AoP, in the Taylor (high polarised SNR) and Rice (low
//! polarised SNR) regimes, with a seeded Monte Carlo check at the Stokes level.
//!
//! # Stokes estimation
//!
//! `N` intensities `I = W S + n`, `Cov(n) = Sigma_I`, `W` the `N x 3` matrix
//! `intensities_from_stokes` of [`AnalyzerSet`]. Two linear estimators `S_hat = G I`:
//!
//! * ordinary least squares (OLS): `G = W^+`, `Sigma_S = W^+ Sigma_I W^+T`;
//! * generalised least squares (GLS): `G = (W^T Sigma_I^-1 W)^-1 W^T Sigma_I^-1`,
//!   `Sigma_S = (W^T Sigma_I^-1 W)^-1` (Aitken; the best linear unbiased estimator).
//!
//! GLS is chosen automatically when `Sigma_I` is not a multiple of the identity (for which both
//! coincide). It is computed without inverting `Sigma_I`: from the symmetric eigendecomposition
//! `Sigma_I = Q diag(lambda) Q^T` the whitening `T = diag(lambda^-1/2) Q^T` turns the problem into
//! OLS on `T W`, solved by the SVD pseudo-inverse, `G = (T W)^+ T`. A near-singular `Sigma_I`
//! (condition number above [`SIGMA_COND_LIMIT`]) has its eigenvalues floored at
//! `lambda_max / SIGMA_COND_LIMIT` (a ridge on the weights) and says so in `warnings`. The reported
//! covariance is always the sandwich `G Sigma_I G^T` with the caller's `Sigma_I`, which equals
//! `(W^T Sigma_I^-1 W)^-1` for unregularised GLS and stays exact when the weights were
//! regularised.
//!
//! # DoLP and AoP statistics
//!
//! For an estimated Stokes vector with mean `mu_S = [S0, S1, S2]` and covariance `Sigma_S`, with
//! `p = sqrt(S1^2 + S2^2)` and the isotropic-equivalent polarised noise
//! `sigma_p^2 = (var S1 + var S2) / 2`, the *polarised SNR* is `p / sigma_p`.
//!
//! * **Taylor regime** (`p / sigma_p >= 3`, [`RICE_SNR_THRESHOLD`]): second-order mean and
//!   first-order variance of `f(S) = p / S0` and of `AoP = 0.5 atan2(S2, S1)` (see
//!   [`dolp_aop_stats`] for the gradient and exact Hessian).
//! * **Rice regime** (`p / sigma_p < 3`): the Rice-distribution moments of `p_hat`,
//!   `E[p_hat] = sigma_p sqrt(pi/2) L_{1/2}(-p^2 / (2 sigma_p^2))`, `E[p_hat^2] = p^2 + 2 sigma_p^2`
//!   (S. O. Rice, *Bell Syst. Tech. J.* 24, 46-156, 1945; the moments as written in J. Sijbers et
//!   al., "Maximum-likelihood estimation of Rician distribution parameters", *IEEE Trans. Med.
//!   Imaging* 17(3), 357-361, 1998), and the exact distribution of the phase of a Rician
//!   variable for the AoP. They are smooth at `p = 0`, where the Taylor gradient is singular.
//!
//! Modified Bessel functions for the Laguerre function are [`bessel_i0e`] and [`bessel_i1e`]
//! (exponentially scaled: no overflow for large arguments).

use crate::analyzer::AnalyzerSet;
use crate::error::ModelError;
use crate::polarization::Stokes;
use crate::quadrature::{integrate, Tolerance};
use nalgebra::{DMatrix, Matrix2, Matrix3, Vector3};
use std::f64::consts::{FRAC_PI_2, PI};

/// Largest condition number of `Sigma_I` used as is in GLS; above it the eigenvalues are floored
/// at `lambda_max / SIGMA_COND_LIMIT` and a warning is issued.
pub const SIGMA_COND_LIMIT: f64 = 1e10;

/// Condition number of `W` above which a Stokes estimate carries a warning (the estimate then
/// amplifies intensity noise by up to this factor; nearly repeated analyzer angles).
pub const W_COND_WARN: f64 = 1e8;

/// Polarised SNR `p / sigma_p` below which [`RegimeChoice::Auto`] uses the Rice regime
/// (MODEL.md section 7: "the Taylor forms fail when the polarised SNR is below about 3").
pub const RICE_SNR_THRESHOLD: f64 = 3.0;

/// Below this polarised SNR the Taylor regime's first-order AoP spread is corrected by the
/// exact Rician phase spread (see [`dolp_aop_stats`]); above it the correction is below 0.5 %.
pub const AOP_PHASE_SNR: f64 = 10.0;

/// Standard deviation of an angle uniform over an interval of length `pi` (the AoP of an
/// unpolarised state): `pi / sqrt(12)` radians (about 51.96 deg).
pub const AOP_STD_UNIFORM_RAD: f64 = 0.906_899_682_117_108_9;

/// Relative asymmetry tolerated in a covariance matrix (it is symmetrised).
const SYMMETRY_TOL: f64 = 1e-9;

/// Largest number of Monte Carlo samples accepted by [`monte_carlo_dolp_aop`].
pub const MAX_MC_SAMPLES: usize = 50_000_000;

// ---------------------------------------------------------------------------------------------
// Stokes estimation
// ---------------------------------------------------------------------------------------------

/// The linear Stokes estimator used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Ordinary least squares, `S_hat = W^+ I`.
    Ols,
    /// Generalised least squares, `S_hat = (W^T Sigma_I^-1 W)^-1 W^T Sigma_I^-1 I`.
    Gls,
}

/// Which estimator to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MethodChoice {
    /// OLS when `Sigma_I` is a multiple of the identity (relative tolerance 1e-12), GLS otherwise.
    #[default]
    Auto,
    /// Always OLS (its covariance is still the exact sandwich `W^+ Sigma_I W^+T`).
    Ols,
    /// Always GLS (for a multiple of the identity it is OLS, and is computed as such).
    Gls,
}

/// A linear Stokes estimator `S_hat = G I` for a measurement matrix and an intensity covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct StokesEstimator {
    /// The gain `G` (`3 x N`).
    pub stokes_from_intensities: DMatrix<f64>,
    /// Covariance of the estimate, `G Sigma_I G^T`.
    pub cov: Matrix3<f64>,
    /// The estimator used.
    pub method: Method,
    /// 2-norm condition number of `W`.
    pub cond_w: f64,
    /// 2-norm condition number of `Sigma_I` as given: 1 for a multiple of the identity (including
    /// zero), `f64::MAX` when singular.
    pub cond_intensity_cov: f64,
    /// What was regularised or is ill-conditioned, in words.
    pub warnings: Vec<String>,
}

/// A Stokes estimate with its covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct StokesEstimate {
    /// `S_hat = [S0, S1, S2]`.
    pub stokes: Vector3<f64>,
    /// Its covariance `Sigma_S` (3 x 3).
    pub cov: Matrix3<f64>,
    /// The estimator used.
    pub method: Method,
    /// What was regularised or is ill-conditioned, in words.
    pub warnings: Vec<String>,
}

/// Checks `W` (shape, finiteness, rank) and returns its pseudo-inverse and condition number.
/// A rank-deficient matrix is an error naming `angles_deg` with the condition number.
fn pinv_checked(w: &DMatrix<f64>, what: &str) -> Result<(DMatrix<f64>, f64), ModelError> {
    let n = w.nrows();
    let svd = w.clone().svd(true, true);
    let s_max = svd.singular_values.max();
    let s_min = svd.singular_values.min();
    let cond = if s_min > 0.0 {
        s_max / s_min
    } else {
        f64::INFINITY
    };
    // Rank test at the conventional numerical threshold (as numpy.linalg.matrix_rank).
    let threshold = s_max * f64::EPSILON * n as f64;
    if s_min <= threshold {
        return Err(ModelError::Invalid {
            field: "angles_deg",
            reason: format!(
                "{what} is singular (condition number {cond:.3e}, singular values {s_max:.3e} .. \
                 {s_min:.3e}): need at least 3 distinct analyzer angles modulo 180 deg"
            ),
        });
    }
    let pinv = svd
        .pseudo_inverse(threshold)
        .map_err(|e| ModelError::Invalid {
            field: "angles_deg",
            reason: format!("pseudo-inverse of {what} failed: {e}"),
        })?;
    Ok((pinv, cond))
}

/// Validates and symmetrises an `n x n` intensity covariance.
fn check_intensity_cov(cov: &DMatrix<f64>, n: usize) -> Result<DMatrix<f64>, ModelError> {
    if cov.nrows() != n || cov.ncols() != n {
        return Err(ModelError::Invalid {
            field: "intensity_cov",
            reason: format!(
                "shape {} x {}; allowed {n} x {n} (one row and column per analyzer angle)",
                cov.nrows(),
                cov.ncols()
            ),
        });
    }
    if let Some(bad) = cov.iter().find(|v| !v.is_finite()) {
        return Err(ModelError::OutOfRange {
            field: "intensity_cov",
            value: *bad,
            allowed: "finite entries",
        });
    }
    let scale = cov.amax();
    let asym = (cov - cov.transpose()).amax();
    if asym > SYMMETRY_TOL * scale {
        return Err(ModelError::Invalid {
            field: "intensity_cov",
            reason: format!(
                "not symmetric (largest |C_ij - C_ji| = {asym:.3e}, largest |C_ij| = {scale:.3e})"
            ),
        });
    }
    if let Some(bad) = cov.diagonal().iter().find(|v| **v < 0.0) {
        return Err(ModelError::OutOfRange {
            field: "intensity_cov",
            value: *bad,
            allowed: "variances (diagonal) >= 0",
        });
    }
    Ok(0.5 * (cov + cov.transpose()))
}

/// Whether a symmetric matrix is a multiple of the identity to a relative 1e-12.
fn is_isotropic(cov: &DMatrix<f64>) -> bool {
    let n = cov.nrows();
    let scale = cov.amax();
    let tol = 1e-12 * scale;
    let d0 = cov[(0, 0)];
    (0..n).all(|i| {
        (0..n).all(|j| {
            if i == j {
                (cov[(i, i)] - d0).abs() <= tol
            } else {
                cov[(i, j)].abs() <= tol
            }
        })
    })
}

impl StokesEstimator {
    /// The estimator for measurement matrix `intensities_from_stokes` (`W`, `N x 3`, `N >= 3`)
    /// and intensity covariance `intensity_cov` (`Sigma_I`, `N x N`, symmetric positive
    /// semidefinite) (MODEL.md section 7).
    ///
    /// Errors: `intensities_from_stokes` of the wrong shape or not finite; `angles_deg` when `W`
    /// (or the whitened `T W`) is rank deficient, with its condition number; `intensity_cov` of
    /// the wrong shape, not finite, not symmetric or not positive semidefinite.
    pub fn new(
        intensities_from_stokes: &DMatrix<f64>,
        intensity_cov: &DMatrix<f64>,
        choice: MethodChoice,
    ) -> Result<Self, ModelError> {
        let w = intensities_from_stokes;
        let n = w.nrows();
        if w.ncols() != 3 || n < 3 {
            return Err(ModelError::Invalid {
                field: "intensities_from_stokes",
                reason: format!(
                    "shape {} x {}; allowed N x 3 with N >= 3 (one row per analyzer angle)",
                    n,
                    w.ncols()
                ),
            });
        }
        if let Some(bad) = w.iter().find(|v| !v.is_finite()) {
            return Err(ModelError::OutOfRange {
                field: "intensities_from_stokes",
                value: *bad,
                allowed: "finite entries",
            });
        }
        let sigma = check_intensity_cov(intensity_cov, n)?;
        let (w_pinv, cond_w) = pinv_checked(w, "the measurement matrix W")?;
        let mut warnings = Vec::new();
        if cond_w > W_COND_WARN {
            warnings.push(format!(
                "angles_deg: W is ill-conditioned (condition number {cond_w:.3e} > {W_COND_WARN:e}): \
                 the estimate amplifies intensity noise by up to that factor"
            ));
        }
        let isotropic = is_isotropic(&sigma);
        let method = match choice {
            MethodChoice::Auto if isotropic => Method::Ols,
            MethodChoice::Auto => Method::Gls,
            MethodChoice::Ols => Method::Ols,
            MethodChoice::Gls => Method::Gls,
        };
        let mut cond_intensity_cov = 1.0;
        let mut gain = w_pinv;
        if !isotropic {
            let eig = sigma.clone().symmetric_eigen();
            let l_max = eig.eigenvalues.max();
            let l_min = eig.eigenvalues.min();
            if l_max <= 0.0 || l_min < -SYMMETRY_TOL * l_max {
                return Err(ModelError::Invalid {
                    field: "intensity_cov",
                    reason: format!(
                        "not positive semidefinite (eigenvalues {l_min:.3e} .. {l_max:.3e})"
                    ),
                });
            }
            cond_intensity_cov = if l_min > l_max / f64::MAX {
                l_max / l_min
            } else {
                f64::MAX
            };
            if method == Method::Gls {
                let floor = l_max / SIGMA_COND_LIMIT;
                if cond_intensity_cov > SIGMA_COND_LIMIT {
                    warnings.push(format!(
                        "intensity_cov is near-singular (condition number {cond_intensity_cov:.3e} \
                         > {SIGMA_COND_LIMIT:e}): eigenvalues floored at {floor:.3e} \
                         (lambda_max / {SIGMA_COND_LIMIT:e}) for the GLS weights; the reported \
                         covariance is the exact sandwich with the given intensity_cov"
                    ));
                }
                // Whitening T = diag(lambda^-1/2) Q^T (rows scaled).
                let mut t = eig.eigenvectors.transpose();
                for (i, mut row) in t.row_iter_mut().enumerate() {
                    row /= eig.eigenvalues[i].max(floor).sqrt();
                }
                let tw = &t * w;
                let (tw_pinv, _) = pinv_checked(&tw, "the whitened measurement matrix T W")?;
                gain = tw_pinv * t;
            }
        }
        let c = &gain * &sigma * gain.transpose();
        let cov = Matrix3::from_fn(|i, j| 0.5 * (c[(i, j)] + c[(j, i)]));
        Ok(StokesEstimator {
            stokes_from_intensities: gain,
            cov,
            method,
            cond_w,
            cond_intensity_cov,
            warnings,
        })
    }

    /// The estimator for an analyzer set (its `W`); see [`StokesEstimator::new`].
    pub fn for_analyzers(
        analyzers: &AnalyzerSet,
        intensity_cov: &DMatrix<f64>,
        choice: MethodChoice,
    ) -> Result<Self, ModelError> {
        StokesEstimator::new(analyzers.intensities_from_stokes(), intensity_cov, choice)
    }

    /// Applies the estimator to `N` measured intensities. Errors name `intensities` if the
    /// length differs from `N` or a value is not finite.
    pub fn estimate(&self, intensities: &[f64]) -> Result<StokesEstimate, ModelError> {
        let n = self.stokes_from_intensities.ncols();
        if intensities.len() != n {
            return Err(ModelError::Invalid {
                field: "intensities",
                reason: format!(
                    "{} values for {n} angles; allowed exactly one per angle",
                    intensities.len()
                ),
            });
        }
        if let Some(bad) = intensities.iter().find(|v| !v.is_finite()) {
            return Err(ModelError::OutOfRange {
                field: "intensities",
                value: *bad,
                allowed: "finite",
            });
        }
        let g = &self.stokes_from_intensities;
        let stokes = Vector3::from_fn(|r, _| (0..n).map(|k| g[(r, k)] * intensities[k]).sum());
        Ok(StokesEstimate {
            stokes,
            cov: self.cov,
            method: self.method,
            warnings: self.warnings.clone(),
        })
    }
}

/// Stokes estimate and covariance from `N` intensities measured through `analyzers`, with
/// intensity covariance `intensity_cov` (OLS for isotropic noise, GLS otherwise; MODEL.md
/// section 7). Errors as [`StokesEstimator::new`] and [`StokesEstimator::estimate`].
pub fn estimate_stokes(
    analyzers: &AnalyzerSet,
    intensities: &[f64],
    intensity_cov: &DMatrix<f64>,
) -> Result<StokesEstimate, ModelError> {
    StokesEstimator::for_analyzers(analyzers, intensity_cov, MethodChoice::Auto)?
        .estimate(intensities)
}

/// As [`estimate_stokes`], from the measurement matrix `W` (`N x 3`) directly.
pub fn estimate_stokes_from_matrix(
    intensities_from_stokes: &DMatrix<f64>,
    intensities: &[f64],
    intensity_cov: &DMatrix<f64>,
) -> Result<StokesEstimate, ModelError> {
    StokesEstimator::new(intensities_from_stokes, intensity_cov, MethodChoice::Auto)?
        .estimate(intensities)
}

/// Analytical propagation without data: the estimator (gain, `Sigma_S`, method, warnings) for
/// `W` and `Sigma_I`, OLS `W^+ Sigma_I W^+T` for isotropic noise and GLS
/// `(W^T Sigma_I^-1 W)^-1` otherwise. Errors as [`StokesEstimator::new`].
pub fn stokes_cov_from_intensity_cov(
    intensities_from_stokes: &DMatrix<f64>,
    intensity_cov: &DMatrix<f64>,
) -> Result<StokesEstimator, ModelError> {
    StokesEstimator::new(intensities_from_stokes, intensity_cov, MethodChoice::Auto)
}

// ---------------------------------------------------------------------------------------------
// Special functions
// ---------------------------------------------------------------------------------------------

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
fn laguerre_half(x: f64) -> f64 {
    let z = (-0.5 * x).max(0.0);
    (1.0 + 2.0 * z) * bessel_i0e(z) + 2.0 * z * bessel_i1e(z)
}

/// Error function by the series `erf x = 2/sqrt(pi) e^{-x^2} sum_n 2^n x^{2n+1} / (1 3 ... (2n+1))`
/// (Abramowitz & Stegun 7.1.6; positive terms, a few ulp) for `|x| < 6`, and `+-1` beyond
/// (`erfc 6 = 2.2e-17`).
fn erf(x: f64) -> f64 {
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

// ---------------------------------------------------------------------------------------------
// DoLP and AoP statistics
// ---------------------------------------------------------------------------------------------

/// Which approximation an answer came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Regime {
    /// Delta method: second-order mean, first-order variance.
    Taylor,
    /// Rice-distribution moments of the polarised intensity, Rician phase for the AoP.
    Rice,
}

/// The caller's choice of regime.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RegimeChoice {
    /// Rice when the polarised SNR is below [`RICE_SNR_THRESHOLD`], Taylor otherwise.
    #[default]
    Auto,
    /// Taylor (falls back to Rice, with a warning, where the Taylor forms are singular: `p = 0`).
    Taylor,
    /// Rice.
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
    /// Standard deviation of the AoP estimate about `aop_mean_rad` (deviations wrapped into
    /// `(-pi/2, pi/2]`), radians; `pi / sqrt(12)` for an unpolarised state.
    pub aop_std_rad: f64,
    /// Which approximation produced the figures.
    pub regime: Regime,
    /// Polarised SNR `p / sigma_p` (`f64::MAX` when `sigma_p = 0 < p`, 0 when `p = 0`).
    pub polarised_snr: f64,
    /// Isotropic-equivalent polarised noise `sigma_p = sqrt((var S1 + var S2) / 2)`.
    pub sigma_p: f64,
    /// Approximations worth knowing about, in words.
    pub warnings: Vec<String>,
}

/// Validates a Stokes mean and covariance; returns the symmetrised covariance.
fn check_stokes_inputs(
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
fn fold_aop(a: f64) -> f64 {
    let r = a - PI * (a / PI).round();
    if r <= -FRAC_PI_2 {
        r + PI
    } else {
        r
    }
}

/// Gradient and Hessian of `f(S) = p / S0` at `S` with `p > 0` (see [`dolp_aop_stats`]).
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
fn rice_moments(p: f64, sigma: f64) -> (f64, f64, f64) {
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
fn rice_aop_std(rho: f64) -> (f64, bool) {
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

/// DoLP and AoP statistics of an estimated linear Stokes vector with mean `mean_stokes`
/// (`mu_S = [S0, S1, S2]`) and covariance `stokes_cov` (`Sigma_S`), MODEL.md section 7.
///
/// Notation: `p = sqrt(S1^2 + S2^2)`, `u = (S1, S2) / p`, `f = p / S0`,
/// `sigma_p^2 = (Sigma_11 + Sigma_22) / 2` (the isotropic equivalent of the `(S1, S2)` noise),
/// polarised SNR `rho = p / sigma_p`.
///
/// **Regime rule.** [`RegimeChoice::Auto`] uses Rice when `rho < 3` ([`RICE_SNR_THRESHOLD`]) and
/// Taylor when `rho >= 3`. A forced Taylor at `p = 0` (or where the Taylor forms overflow) falls
/// back to Rice, and `regime` says so.
///
/// **Taylor regime** (delta method). Gradient
/// `grad f = [-p/S0^2, S1/(p S0), S2/(p S0)]`, exact Hessian
///
/// ```text
///     H = [  2p/S0^3       -S1/(p S0^2)      -S2/(p S0^2)    ]
///         [ -S1/(p S0^2)    S2^2/(p^3 S0)    -S1 S2/(p^3 S0) ]
///         [ -S2/(p S0^2)   -S1 S2/(p^3 S0)    S1^2/(p^3 S0)  ]
/// ```
///
/// (from `d(S1/p)/dS1 = S2^2/p^3`, `d(S1/p)/dS2 = -S1 S2/p^3`, `d^2(1/S0)/dS0^2 = 2/S0^3`);
/// `E[f] = f(mu) + 0.5 tr(H Sigma)`, `Var f = grad^T Sigma grad`. AoP `= 0.5 atan2(S2, S1)`,
/// `grad = [0, -S2/(2p^2), S1/(2p^2)]`, `Var AoP = grad^T Sigma grad` (rad^2), and below
/// `rho =` [`AOP_PHASE_SNR`] its square root is multiplied by `2 rho s(rho)`: `s(rho)` is the AoP
/// spread of the exact Rician phase (half the phase's spread), over its first-order value
/// `1/(2 rho)`; the AoP mean is
/// the AoP of `mu_S` (exact for isotropic `(S1, S2)` noise by symmetry, first order otherwise).
/// These forms use the full anisotropic covariance.
///
/// **Rice regime.** `(S1, S2)_hat` is treated as isotropic bivariate normal with per-component
/// variance `sigma_p^2`, so `p_hat` is Rician (Rice 1945; moments as in Sijbers et al. 1998):
/// `m1 = E[p_hat] = sigma_p sqrt(pi/2) L_{1/2}(-p^2/(2 sigma_p^2))`,
/// `L_{1/2}(x) = e^{x/2} [(1-x) I0(-x/2) - x I1(-x/2)]` (evaluated with [`bessel_i0e`],
/// [`bessel_i1e`]), `E[p_hat^2] = p^2 + 2 sigma_p^2`, `Var p_hat = E[p_hat^2] - m1^2`.
/// `S0_hat` enters through the delta method on the ratio `p_hat / S0_hat` (second order in the
/// mean, first order in the variance; valid while `sqrt(Sigma_00) << S0`):
/// `E[DoLP] = m1/S0 - c/S0^2 + m1 Sigma_00/S0^3`,
/// `Var DoLP = Var p_hat/S0^2 - 2 m1 c/S0^3 + m1^2 Sigma_00/S0^4`, with
/// `c = Cov(p_hat, S0_hat) = (Sigma_01 u1 + Sigma_02 u2) dm1/dp` by Stein's lemma (exact for
/// jointly Gaussian Stokes estimates; smooth and 0 at `p = 0`). The AoP standard deviation is
/// that of the exact phase distribution of a Rician variable of SNR `rho`, halved (the AoP is
/// half the phase), by adaptive quadrature: it tends to the uniform value `pi/sqrt(12)`
/// ([`AOP_STD_UNIFORM_RAD`]) as `p -> 0` and to the Taylor value `sigma_p / (2p)` as `rho` grows.
/// When the `(S1, S2)` covariance is anisotropic (eigenvalues differing by more than 5 %) the
/// isotropic equivalent is an approximation and `warnings` says so.
///
/// At `p = 0` the AoP is undefined: `aop_mean_rad = 0`, `aop_std_rad = pi/sqrt(12)`, with a warning.
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
                "p = 0: the AoP is undefined; aop_mean_rad set to 0 and aop_std_rad to the \
                 uniform value pi/sqrt(12)"
                    .to_string(),
            );
            0.0
        }
    };
    let mut regime = match choice {
        RegimeChoice::Auto if polarised_snr < RICE_SNR_THRESHOLD => Regime::Rice,
        RegimeChoice::Auto | RegimeChoice::Taylor => Regime::Taylor,
        RegimeChoice::Rice => Regime::Rice,
    };
    if regime == Regime::Taylor {
        if let Some((dolp_mean, dolp_var, aop_var)) = taylor_moments(mean_stokes, &cov) {
            if polarised_snr < RICE_SNR_THRESHOLD {
                warnings.push(format!(
                    "Taylor regime forced at polarised SNR {polarised_snr:.3} < \
                     {RICE_SNR_THRESHOLD}: the DoLP mean misses the Rician bias"
                ));
            }
            // The first-order AoP spread is the large-SNR limit `1/(2 rho)` of the Rician phase;
            // below AOP_PHASE_SNR it is scaled by the exact phase spread over that limit (exact
            // for isotropic noise; the full-chain validation found the plain first-order value
            // up to 17 % low at rho = 3..5, docs/VALIDATION.md).
            let mut aop_std_rad = aop_var.sqrt();
            if polarised_snr < AOP_PHASE_SNR {
                let (phase_std, converged) = rice_aop_std(polarised_snr);
                aop_std_rad *= phase_std * 2.0 * polarised_snr;
                if !converged {
                    warnings.push(format!(
                        "AoP phase-distribution quadrature did not meet 1e-10 at SNR \
                         {polarised_snr:.3e}"
                    ));
                }
            }
            return Ok(PolarizationStats {
                dolp_mean,
                dolp_std: dolp_var.sqrt(),
                aop_mean_rad,
                aop_std_rad,
                regime,
                polarised_snr,
                sigma_p,
                warnings,
            });
        }
        warnings.push(format!(
            "Taylor forms singular at p = {p:.3e} (the gradient of p is undefined at p = 0): \
             Rice regime used"
        ));
        regime = Regime::Rice;
    }
    // Rice regime.
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
    // `Var p_hat` is the isotropic equivalent's while `c` comes from the full covariance: with
    // anisotropic noise strongly correlated with S0 they can violate Cauchy-Schwarz, and the
    // DoLP variance would come out negative. Keep the pair a covariance: |c| <= sqrt(Var p S00).
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
    let finite = dolp_mean.is_finite() && dolp_var.is_finite() && aop_std_rad.is_finite();
    if !finite {
        return Err(ModelError::Invalid {
            field: "stokes_cov",
            reason: format!(
                "DoLP statistics overflow for S = [{s0:e}, {s1:e}, {s2:e}] with this covariance \
                 (sqrt(Sigma_00) must be small against S0)"
            ),
        });
    }
    Ok(PolarizationStats {
        dolp_mean,
        dolp_std: dolp_var.sqrt(),
        aop_mean_rad,
        aop_std_rad,
        regime,
        polarised_snr,
        sigma_p,
        warnings,
    })
}

// ---------------------------------------------------------------------------------------------
// Monte Carlo check
// ---------------------------------------------------------------------------------------------

/// SplitMix64 (Steele, Lea and Flood, OOPSLA 2014): a small seeded generator, ample for a
/// statistics check (the crate has no `rand` dependency).
pub(crate) struct SplitMix64(pub(crate) u64);

impl SplitMix64 {
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in the open interval (0, 1): 53 random bits, centred in their cell.
    pub(crate) fn uniform_open(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64)
    }

    /// A pair of independent standard normals (Box-Muller).
    pub(crate) fn normal_pair(&mut self) -> (f64, f64) {
        let r = (-2.0 * self.uniform_open().ln()).sqrt();
        let (s, c) = (2.0 * PI * self.uniform_open()).sin_cos();
        (r * c, r * s)
    }
}

/// A factor `F` with `F F^T = cov` of a symmetric positive semidefinite 3x3 covariance, for
/// drawing correlated normals `F z`: the Cholesky factor, or, for a singular covariance,
/// `Q sqrt(max(lambda, 0))` from its eigendecomposition (eigenvalues below zero from rounding
/// taken as zero).
pub fn psd_factor(cov: &Matrix3<f64>) -> Matrix3<f64> {
    if let Some(ch) = cov.cholesky() {
        return ch.l();
    }
    let eig = cov.symmetric_eigen();
    eig.eigenvectors * Matrix3::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt()))
}

/// Sample statistics of DoLP and AoP from Monte Carlo draws of the Stokes estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct MonteCarloPolarization {
    /// Sample mean of `p_hat / S0_hat` over draws with `S0_hat > 0`.
    pub dolp_mean: f64,
    /// Sample standard deviation (n - 1) of the DoLP.
    pub dolp_std: f64,
    /// Circular mean direction of `2 AoP`, halved, in `(-pi/2, pi/2]`.
    pub aop_mean_rad: f64,
    /// Root-mean-square deviation of the AoP from `aop_mean_rad`, each deviation wrapped into
    /// `(-pi/2, pi/2]` (comparable with [`PolarizationStats::aop_std_rad`]; `pi/sqrt(12)` for a
    /// uniform AoP).
    pub aop_std_rad: f64,
    /// Circular standard deviation `sqrt(-2 ln R) / 2` of the AoP, `R` the mean resultant length
    /// of `2 AoP` (Mardia and Jupp 2000, Sec. 2.3.4); grows without bound as the AoP becomes
    /// uniform (reported with `R` floored at 1e-300).
    pub aop_circular_std_rad: f64,
    /// Draws used for the DoLP (`S0_hat > 0`).
    pub samples_used: usize,
    /// Draws with `S0_hat <= 0` (no DoLP), left out.
    pub samples_dark: usize,
}

/// A seeded Monte Carlo check of [`dolp_aop_stats`] at the Stokes level (MODEL.md section 7,
/// "Monte Carlo validation"): draws `S ~ N(mean_stokes, stokes_cov)` `n_samples` times (Cholesky
/// factor; a positive semidefinite but singular covariance is factored as `Q sqrt(max(lambda, 0))`
/// from its eigendecomposition), and returns the sample mean and standard deviation of the DoLP
/// and circular statistics of the AoP (on `2 AoP`, mapped back). SplitMix64 and Box-Muller; the
/// same `seed` gives the same answer.
///
/// Errors as [`dolp_aop_stats`], and `n_samples` outside `[2, MAX_MC_SAMPLES]`.
pub fn monte_carlo_dolp_aop(
    mean_stokes: &Vector3<f64>,
    stokes_cov: &Matrix3<f64>,
    n_samples: usize,
    seed: u64,
) -> Result<MonteCarloPolarization, ModelError> {
    let cov = check_stokes_inputs(mean_stokes, stokes_cov)?;
    if !(2..=MAX_MC_SAMPLES).contains(&n_samples) {
        return Err(ModelError::OutOfRange {
            field: "n_samples",
            value: n_samples as f64,
            allowed: "2 to 50 000 000",
        });
    }
    let factor = psd_factor(&cov);
    let mut rng = SplitMix64(seed);
    let mut spare: Option<f64> = None;
    let mut normal = || match spare.take() {
        Some(v) => v,
        None => {
            let (a, b) = rng.normal_pair();
            spare = Some(b);
            a
        }
    };
    // Welford's running mean and variance of the DoLP.
    let (mut n_used, mut mean, mut m2) = (0usize, 0.0, 0.0);
    let mut phases = Vec::with_capacity(n_samples);
    let (mut sum_c, mut sum_s) = (0.0, 0.0);
    for _ in 0..n_samples {
        let z = Vector3::new(normal(), normal(), normal());
        let s = mean_stokes + factor * z;
        if s[1] != 0.0 || s[2] != 0.0 {
            let phi = s[2].atan2(s[1]);
            sum_c += phi.cos();
            sum_s += phi.sin();
            phases.push(phi);
        }
        if s[0] > 0.0 {
            let d = s[1].hypot(s[2]) / s[0];
            n_used += 1;
            let delta = d - mean;
            mean += delta / n_used as f64;
            m2 += delta * (d - mean);
        }
    }
    if n_used < 2 || phases.is_empty() {
        return Err(ModelError::Invalid {
            field: "S0",
            reason: format!(
                "only {n_used} of {n_samples} draws have S0 > 0 and a defined AoP: the covariance \
                 is too large for the mean"
            ),
        });
    }
    let n_ph = phases.len() as f64;
    let (c_bar, s_bar) = (sum_c / n_ph, sum_s / n_ph);
    let r = c_bar.hypot(s_bar);
    let phi_mean = s_bar.atan2(c_bar);
    let ms_dev = phases
        .iter()
        .map(|phi| {
            let d = 0.5 * fold_aop_phase(phi - phi_mean);
            d * d
        })
        .sum::<f64>()
        / n_ph;
    Ok(MonteCarloPolarization {
        dolp_mean: mean,
        dolp_std: (m2 / (n_used - 1) as f64).sqrt(),
        aop_mean_rad: fold_aop(0.5 * phi_mean),
        aop_std_rad: ms_dev.sqrt(),
        aop_circular_std_rad: 0.5 * (-2.0 * r.max(1e-300).ln()).sqrt(),
        samples_used: n_used,
        samples_dark: n_samples - n_used,
    })
}

/// Wraps a phase difference into `(-pi, pi]`.
fn fold_aop_phase(d: f64) -> f64 {
    2.0 * fold_aop(0.5 * d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyzer::modified_pickering;
    use crate::polarization::analyzer_row;

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
    }

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    fn w_from_deg(angles: &[f64]) -> DMatrix<f64> {
        DMatrix::from_fn(angles.len(), 3, |i, j| {
            analyzer_row(angles[i].to_radians())[j]
        })
    }

    /// OLS at 0/45/90/135 with i.i.d. noise reproduces the modified Pickering formulas
    /// (`S0 = (I0+I45+I90+I135)/2`, `S1 = I0 - I90`, `S2 = I45 - I135`) and their covariance
    /// `sigma^2 (W^T W)^-1 = sigma^2 diag(1, 2, 2)`. Tolerance 1e-12 relative: both are a few
    /// floating-point operations on O(1) numbers (SVD rounding only).
    #[test]
    fn ols_reproduces_modified_pickering_and_covariance() {
        let set = AnalyzerSet::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap();
        let truth = Stokes::new(1000.0, 120.0, -80.0);
        let i = set.intensities(&truth);
        let i = [i[0] + 1.3, i[1] - 0.7, i[2] + 2.1, i[3] - 0.4];
        let sigma2 = 25.0;
        let cov_i = DMatrix::identity(4, 4) * sigma2;
        let est = estimate_stokes(&set, &i, &cov_i).unwrap();
        assert_eq!(est.method, Method::Ols);
        assert!(est.warnings.is_empty());
        let mp = modified_pickering(i[0], i[1], i[2], i[3]);
        for k in 0..3 {
            assert!((est.stokes[k] - mp.0[k]).abs() < 1e-12 * 1000.0);
        }
        let expected = Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 2.0)) * sigma2;
        assert!((est.cov - expected).amax() < 1e-12 * sigma2);
        let from_set = set.stokes_covariance_per_unit_variance() * sigma2;
        assert!((est.cov - from_set).amax() < 1e-12 * sigma2);
    }

    /// GLS equals OLS for isotropic noise (the whitening is a scalar), on an irregular 5-angle
    /// set, and `Auto` picks OLS. Tolerance 1e-10 relative: eigendecomposition and two SVDs.
    #[test]
    fn gls_equals_ols_for_isotropic_noise() {
        let w = w_from_deg(&[3.0, 41.0, 77.0, 118.0, 160.0]);
        let cov_i = DMatrix::identity(5, 5) * 4.0;
        let ols = StokesEstimator::new(&w, &cov_i, MethodChoice::Ols).unwrap();
        let gls = StokesEstimator::new(&w, &cov_i, MethodChoice::Gls).unwrap();
        let auto = stokes_cov_from_intensity_cov(&w, &cov_i).unwrap();
        assert_eq!(
            (ols.method, gls.method, auto.method),
            (Method::Ols, Method::Gls, Method::Ols)
        );
        let scale = ols.cov.amax();
        assert!((ols.cov - gls.cov).amax() < 1e-10 * scale);
        let g_scale = ols.stokes_from_intensities.amax();
        assert!(
            (&ols.stokes_from_intensities - &gls.stokes_from_intensities).amax() < 1e-10 * g_scale
        );
        let i = [510.0, 480.0, 300.0, 320.0, 640.0];
        let (a, b) = (ols.estimate(&i).unwrap(), gls.estimate(&i).unwrap());
        assert!((a.stokes - b.stokes).amax() < 1e-10 * a.stokes.amax());
    }

    /// With one frame 100 times noisier in variance, GLS has a smaller `trace(Sigma_S)` than OLS
    /// (Gauss-Markov: `Sigma_OLS - Sigma_GLS` is positive semidefinite), and its covariance is
    /// `(W^T Sigma^-1 W)^-1` (checked with an explicit inverse of the well-conditioned diagonal
    /// `Sigma` and 3x3 normal matrix, to 1e-10 relative).
    #[test]
    fn gls_beats_ols_with_one_noisy_frame() {
        let w = w_from_deg(&[0.0, 45.0, 90.0, 135.0]);
        let cov_i =
            DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![1.0, 1.0, 100.0, 1.0]));
        let ols = StokesEstimator::new(&w, &cov_i, MethodChoice::Ols).unwrap();
        let gls = StokesEstimator::new(&w, &cov_i, MethodChoice::Auto).unwrap();
        assert_eq!(gls.method, Method::Gls);
        assert!(
            gls.cov.trace() < 0.5 * ols.cov.trace(),
            "{} vs {}",
            gls.cov.trace(),
            ols.cov.trace()
        );
        let diff = ols.cov - gls.cov;
        assert!(diff.symmetric_eigen().eigenvalues.min() > -1e-10 * ols.cov.amax());
        let sigma_inv =
            DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![1.0, 1.0, 0.01, 1.0]));
        let normal = w.transpose() * sigma_inv * &w;
        let normal = Matrix3::from_fn(|i, j| normal[(i, j)]);
        let expected = normal.try_inverse().unwrap();
        assert!((gls.cov - expected).amax() < 1e-10 * expected.amax());
    }

    /// A near-singular `Sigma_I` (two frames correlated to 1 - 1e-14, condition number ~2e14)
    /// is regularised with a warning quoting the condition number, and a singular one (perfect
    /// correlation) too; outputs stay finite and positive semidefinite.
    #[test]
    fn ill_conditioned_intensity_cov_is_regularised() {
        let w = w_from_deg(&[0.0, 45.0, 90.0, 135.0]);
        for rho in [1.0 - 1e-14, 1.0] {
            let mut cov_i = DMatrix::identity(4, 4);
            cov_i[(0, 1)] = rho;
            cov_i[(1, 0)] = rho;
            let est = StokesEstimator::new(&w, &cov_i, MethodChoice::Auto).unwrap();
            assert_eq!(est.method, Method::Gls);
            assert!(est.cond_intensity_cov > SIGMA_COND_LIMIT);
            assert!(
                est.warnings
                    .iter()
                    .any(|m| m.contains("intensity_cov") && m.contains("condition number")),
                "{:?}",
                est.warnings
            );
            assert!(est.cov.iter().all(|v| v.is_finite()));
            assert!(est.cov.symmetric_eigen().eigenvalues.min() > -1e-9 * est.cov.amax());
            let s = est.estimate(&[10.0, 9.0, 5.0, 6.0]).unwrap();
            assert!(s.stokes.iter().all(|v| v.is_finite()));
        }
    }

    /// A singular analyzer set (0, 0, 90 deg: no sensitivity to S2) is an error naming
    /// `angles_deg` with the condition number, both from `W` and from `AnalyzerSet`.
    #[test]
    fn singular_angle_set_is_an_error_naming_angles() {
        let w = w_from_deg(&[0.0, 0.0, 90.0]);
        let err =
            StokesEstimator::new(&w, &DMatrix::identity(3, 3), MethodChoice::Auto).unwrap_err();
        match err {
            ModelError::Invalid { field, reason } => {
                assert_eq!(field, "angles_deg");
                assert!(reason.contains("condition number"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
        let err = AnalyzerSet::ideal(&deg(&[0.0, 0.0, 90.0])).unwrap_err();
        assert!(matches!(
            err,
            ModelError::Invalid {
                field: "angles_deg",
                ..
            }
        ));
    }

    /// The exact Hessian of `p/S0` in the doc comment agrees with central second differences
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

    /// Stokes covariance of `S = (1000, 100, 50)` through 0/60/120 with `sigma_I = 10`.
    fn high_snr_case() -> (Vector3<f64>, Matrix3<f64>) {
        let set = AnalyzerSet::ideal(&deg(&[0.0, 60.0, 120.0])).unwrap();
        let cov = set.stokes_covariance_per_unit_variance() * 100.0;
        (Vector3::new(1000.0, 100.0, 50.0), cov)
    }

    /// At high polarised SNR (S = (1000, 100, 50), sigma_I = 10 through 0/60/120: SNR 6.8) the
    /// Taylor DoLP mean and std match 200k Monte Carlo draws within 1 % and 3 %, and the AoP std
    /// within 3 %. MC standard errors: mean `std/sqrt(n)` = 3.7e-5 (0.03 % of 0.112), std about
    /// `std/sqrt(2n)` (0.16 %); the rest of the budget is the Taylor truncation (the next Rician
    /// term is `sigma^4/(8 p^3)`, 6e-5 relative, and the first-order variance is `1 - 1/(2 SNR^2)`
    /// = 1 % high in variance).
    #[test]
    fn taylor_matches_monte_carlo_at_high_snr() {
        let (mu, cov) = high_snr_case();
        let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(st.regime, Regime::Taylor);
        assert!(
            st.polarised_snr > 6.0 && st.polarised_snr < 7.0,
            "{}",
            st.polarised_snr
        );
        let mc = monte_carlo_dolp_aop(&mu, &cov, 200_000, 42).unwrap();
        let (dm, ds, da) = (
            rel(st.dolp_mean, mc.dolp_mean),
            rel(st.dolp_std, mc.dolp_std),
            rel(st.aop_std_rad, mc.aop_std_rad),
        );
        eprintln!("taylor vs MC: mean {dm:.2e}, std {ds:.2e}, aop std {da:.2e}");
        assert!(dm < 0.01 && ds < 0.03 && da < 0.03);
        assert!(
            (st.aop_mean_rad - mc.aop_mean_rad).abs() < 4.0 * st.aop_std_rad / 200_000f64.sqrt()
        );
    }

    /// Unpolarised state (p = 0, S0 = 1000, Sigma_S = diag(100, 200, 200) from sigma_I = 10
    /// through 0/45/90/135): Rice regime; the DoLP mean is the Rayleigh mean
    /// `sigma_p sqrt(pi/2) / S0` (times `1 + Sigma_00/S0^2` = 1.0001 from the S0 noise), the AoP
    /// std the uniform `pi/sqrt(12)`; 200k MC draws agree within 4 standard errors (mean SE =
    /// 0.0093/sqrt(2e5) = 2.1e-5, i.e. 0.12 %) and within 1 % on both standard deviations
    /// (SE ~0.2 %).
    #[test]
    fn rice_unpolarised_gives_rayleigh_mean() {
        let set = AnalyzerSet::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap();
        let cov = set.stokes_covariance_per_unit_variance() * 100.0;
        let mu = Vector3::new(1000.0, 0.0, 0.0);
        let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(st.regime, Regime::Rice);
        assert_eq!(st.polarised_snr, 0.0);
        let sigma_p = 200f64.sqrt();
        let rayleigh = sigma_p * FRAC_PI_2.sqrt() / 1000.0;
        assert!(rel(st.dolp_mean, rayleigh * (1.0 + 100.0 / 1e6)) < 1e-12);
        assert!(rel(st.dolp_mean, rayleigh) < 2e-4);
        assert!((st.aop_std_rad - AOP_STD_UNIFORM_RAD).abs() < 1e-12);
        let mc = monte_carlo_dolp_aop(&mu, &cov, 200_000, 7).unwrap();
        let se = mc.dolp_std / 200_000f64.sqrt();
        eprintln!(
            "rice p=0 vs MC: mean {:.2e} SE, std {:.2e}, aop std {:.2e}",
            (st.dolp_mean - mc.dolp_mean).abs() / se,
            rel(st.dolp_std, mc.dolp_std),
            rel(st.aop_std_rad, mc.aop_std_rad)
        );
        assert!((st.dolp_mean - mc.dolp_mean).abs() < 4.0 * se);
        assert!(rel(st.dolp_std, mc.dolp_std) < 0.01);
        assert!(rel(st.aop_std_rad, mc.aop_std_rad) < 0.01);
        assert!(st.warnings.iter().any(|w| w.contains("AoP is undefined")));
    }

    /// At polarised SNR 1 (p = sigma_p) the Rice answer matches 200k MC draws (mean within 4 SE,
    /// std and AoP std within 1.5 %), where the Taylor mean (`p + sigma^2/(2p)` = 1.5 sigma
    /// against the true 1.549 sigma) is off by more than 10 SE.
    #[test]
    fn rice_matches_monte_carlo_at_snr_one() {
        let cov = Matrix3::from_diagonal(&Vector3::new(50.0, 200.0, 200.0));
        let sigma_p = 200f64.sqrt();
        let mu = Vector3::new(1000.0, 0.6 * sigma_p, -0.8 * sigma_p);
        let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(st.regime, Regime::Rice);
        assert!((st.polarised_snr - 1.0).abs() < 1e-12);
        let taylor = dolp_aop_stats(&mu, &cov, RegimeChoice::Taylor).unwrap();
        assert_eq!(taylor.regime, Regime::Taylor);
        assert!(!taylor.warnings.is_empty());
        let mc = monte_carlo_dolp_aop(&mu, &cov, 200_000, 11).unwrap();
        let se = mc.dolp_std / 200_000f64.sqrt();
        let (z_rice, z_taylor) = (
            (st.dolp_mean - mc.dolp_mean).abs() / se,
            (taylor.dolp_mean - mc.dolp_mean).abs() / se,
        );
        eprintln!(
            "SNR 1 vs MC: rice mean {z_rice:.2} SE, taylor mean {z_taylor:.1} SE, std {:.2e}, aop std {:.2e}",
            rel(st.dolp_std, mc.dolp_std),
            rel(st.aop_std_rad, mc.aop_std_rad)
        );
        assert!(z_rice < 4.0 && z_taylor > 10.0);
        assert!(rel(st.dolp_std, mc.dolp_std) < 0.015);
        assert!(rel(st.aop_std_rad, mc.aop_std_rad) < 0.015);
        assert!((st.aop_mean_rad - mc.aop_mean_rad).abs() < 0.01);
    }

    /// Just above the switch (polarised SNR 3.2, isotropic noise) the Taylor regime's AoP
    /// spread matches 200k MC draws within 1.5 % (the MC std's own relative error is ~0.2 %),
    /// where the plain first-order `1/(2 rho)` is more than 4 % low.
    #[test]
    fn taylor_aop_spread_is_corrected_near_the_switch() {
        let cov = Matrix3::from_diagonal(&Vector3::new(50.0, 200.0, 200.0));
        let sigma_p = 200f64.sqrt();
        let mu = Vector3::new(1000.0, 1.92 * sigma_p, 2.56 * sigma_p);
        let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(st.regime, Regime::Taylor);
        let mc = monte_carlo_dolp_aop(&mu, &cov, 200_000, 5).unwrap();
        assert!(
            rel(st.aop_std_rad, mc.aop_std_rad) < 0.015,
            "{} vs {}",
            st.aop_std_rad,
            mc.aop_std_rad
        );
        let first_order = 0.5 / st.polarised_snr;
        assert!(
            rel(first_order, mc.aop_std_rad) > 0.05,
            "{first_order} vs {}",
            mc.aop_std_rad
        );
    }

    /// Rice regime with anisotropic noise strongly correlated with S0 (a dark panel behind
    /// correlated clutter: corr(S0, S1) = 0.94). The Stein covariance of `p_hat` and `S0_hat`
    /// then exceeds what the isotropic Rice variance allows; unclamped, the DoLP variance came
    /// out negative and was reported as a standard deviation of 0. Clamped, it is positive, says
    /// so, and lies within a factor of 2 of 2e5 MC draws: the S0 noise is 20 % here, far outside
    /// the delta method's validity, so only the order of magnitude is claimed.
    #[test]
    fn rice_with_correlated_anisotropic_noise_keeps_a_positive_spread() {
        let mu = Vector3::new(1.0, 0.40, -0.01);
        let cov = Matrix3::new(
            0.0417, 0.0518, 0.0110, 0.0518, 0.0725, 0.0137, 0.0110, 0.0137, 0.0138,
        );
        let st = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(st.regime, Regime::Rice);
        assert!(
            st.warnings.iter().any(|w| w.contains("Cauchy-Schwarz")),
            "{:?}",
            st.warnings
        );
        let mc = monte_carlo_dolp_aop(&mu, &cov, 200_000, 3).unwrap();
        eprintln!("DoLP std: model {:.4}, MC {:.4}", st.dolp_std, mc.dolp_std);
        assert!(
            st.dolp_std > 0.5 * mc.dolp_std && st.dolp_std < 2.0 * mc.dolp_std,
            "{} vs MC {}",
            st.dolp_std,
            mc.dolp_std
        );
    }

    /// Continuity at the switch: at polarised SNR exactly 3 `Auto` answers Taylor; forced Rice
    /// differs in DoLP mean by less than 0.01 sigma_p / S0 (the exact gap is
    /// `E[p_hat] - (p + sigma^2/(2p))` = 3.17258 - 3.16667 = 0.0059 sigma_p, 0.19 % of the mean),
    /// in DoLP std by less than 5 % (Rice `Var p_hat = 0.935 sigma^2` against Taylor's `sigma^2`)
    /// and in AoP std by less than 10 %. Just below 3, `Auto` answers Rice.
    #[test]
    fn regimes_are_continuous_at_snr_three() {
        let cov = Matrix3::from_diagonal(&Vector3::new(10.0, 100.0, 100.0));
        let mu = Vector3::new(1000.0, 30.0, 0.0);
        let t = dolp_aop_stats(&mu, &cov, RegimeChoice::Auto).unwrap();
        assert_eq!(t.regime, Regime::Taylor);
        assert_eq!(t.polarised_snr, 3.0);
        let r = dolp_aop_stats(&mu, &cov, RegimeChoice::Rice).unwrap();
        assert_eq!(r.regime, Regime::Rice);
        let gap = (r.dolp_mean - t.dolp_mean).abs() / (10.0 / 1000.0);
        eprintln!(
            "SNR 3: mean gap {gap:.4} sigma_p/S0, std {:.3e}, aop std {:.3e}",
            rel(r.dolp_std, t.dolp_std),
            rel(r.aop_std_rad, t.aop_std_rad)
        );
        assert!(gap < 0.01 && gap > 0.005);
        assert!(rel(r.dolp_std, t.dolp_std) < 0.05);
        assert!(rel(r.aop_std_rad, t.aop_std_rad) < 0.10);
        let below = Vector3::new(1000.0, 29.99, 0.0);
        assert_eq!(
            dolp_aop_stats(&below, &cov, RegimeChoice::Auto)
                .unwrap()
                .regime,
            Regime::Rice
        );
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

    /// No NaN at the hard cases: S = (1, 0, 0) with zero and non-zero covariance, and
    /// S = (1e-12, 0, 0) with a tiny covariance (sigma = 1e-15), in every regime choice; results
    /// are finite and the Taylor request falls back to Rice at p = 0.
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
            }
        }
        let st = dolp_aop_stats(&cases[2].0, &cases[2].1, RegimeChoice::Auto).unwrap();
        // Rayleigh mean 1e-15 sqrt(pi/2) / 1e-12, times 1 + Sigma_00/S0^2 = 1 + 1e-6.
        assert!(rel(st.dolp_mean, 1e-3 * FRAC_PI_2.sqrt() * (1.0 + 1e-6)) < 1e-12);
        let mc = monte_carlo_dolp_aop(&cases[0].0, &cases[0].1, 10, 1);
        assert!(
            mc.is_err(),
            "zero covariance at p = 0 leaves the AoP undefined in every draw"
        );
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

    /// Bessel functions against mpmath (30 digits): `I0(1) = 1.2660658777520082`,
    /// `I1(1) = 0.5651591039924851`, and scaled values on both sides of the series/asymptotic
    /// switch at 30 and far beyond; tolerance 1e-12 relative (tighter than the 1e-7 asked; the
    /// series and the asymptotic expansion are both good to a few ulp there). Also `erf`.
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
        // Rice mean E[p_hat]/sigma = sqrt(pi/2) L_{1/2}(-rho^2/2) against mpmath.
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

    /// The Monte Carlo helper is reproducible for a seed, differs across seeds, and handles a
    /// PSD-but-singular covariance (S0 noise-free) by the eigen factor: with `S = (10, 5, 0)`,
    /// `Sigma = diag(0, 1, 1)` the DoLP is `p_hat/10`, `p_hat` Rician of SNR 5, whose mean
    /// `E[p_hat]/10` = 0.5102 the analytical answer gives; 20k draws agree within 4 standard errors
    /// (SE = 0.1/sqrt(2e4) = 7e-4).
    #[test]
    fn monte_carlo_is_seeded_and_handles_singular_cov() {
        let (mu, cov) = high_snr_case();
        let a = monte_carlo_dolp_aop(&mu, &cov, 1000, 5).unwrap();
        let b = monte_carlo_dolp_aop(&mu, &cov, 1000, 5).unwrap();
        let c = monte_carlo_dolp_aop(&mu, &cov, 1000, 6).unwrap();
        assert_eq!(a, b);
        assert_ne!(a.dolp_mean, c.dolp_mean);
        let singular = Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 1.0));
        let s = monte_carlo_dolp_aop(&Vector3::new(10.0, 5.0, 0.0), &singular, 20_000, 3).unwrap();
        assert_eq!(s.samples_dark, 0);
        let st =
            dolp_aop_stats(&Vector3::new(10.0, 5.0, 0.0), &singular, RegimeChoice::Rice).unwrap();
        assert!(rel(st.dolp_mean, rice_moments(5.0, 1.0).0 / 10.0) < 1e-12);
        assert!((s.dolp_mean - st.dolp_mean).abs() < 4.0 * s.dolp_std / 20_000f64.sqrt());
    }
}
