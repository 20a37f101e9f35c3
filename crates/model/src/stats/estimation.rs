//! Linear Stokes estimation with covariance (MODEL.md section 7, "Stokes estimation").
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

use crate::analyzer::AnalyzerSet;
use crate::error::ModelError;
use nalgebra::{DMatrix, Matrix3, Vector3};

/// Largest condition number of `Sigma_I` used as is in GLS; above it the eigenvalues are floored
/// at `lambda_max / SIGMA_COND_LIMIT` and a warning is issued.
pub const SIGMA_COND_LIMIT: f64 = 1e10;

/// Condition number of `W` above which a Stokes estimate carries a warning (the estimate then
/// amplifies intensity noise by up to this factor; nearly repeated analyzer angles).
pub const W_COND_WARN: f64 = 1e8;

/// Relative asymmetry tolerated in a covariance matrix (it is symmetrised).
pub(crate) const SYMMETRY_TOL: f64 = 1e-9;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analyzer::modified_pickering;
    use crate::polarization::analyzer_row;
    use crate::polarization::Stokes;

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
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
}
