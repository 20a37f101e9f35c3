//! Analyzer sets: measurement matrices, Stokes reconstruction, conditioning and noise gains
//! (Meng (2012) Sec. 2.4, MODEL.md sections 1 and 6).
//!
//! `N` frames taken through analyzers at angles `psi_1..psi_N` measure `I = W S` with `W` the
//! `N x 3` matrix whose rows are `m(psi_k)^T` (`intensities_from_stokes`). The least-squares
//! reconstruction is `S_hat = W^+ I` with `W^+ = (W^T W)^-1 W^T` (`stokes_from_intensities`),
//! computed here from the singular value decomposition for numerical stability. The classic
//! three- and four-angle formulas of Meng (2012) Sec. 2.4 are special cases (see the tests).

use crate::error::ModelError;
use crate::polarization::Stokes;
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

/// A real linear analyzer: principal transmittances `k1 >= k2 >= 0` and an angle offset.
///
/// Its row is `0.5 [k1 + k2, (k1 - k2) cos 2(psi + dpsi), (k1 - k2) sin 2(psi + dpsi)]`
/// (MODEL.md section 6). The ideal analyzer has `k1 = 1, k2 = 0, dpsi = 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnalyzerModel {
    /// Major principal transmittance `k1`, in `(0, 1]`.
    pub k1: f64,
    /// Minor principal transmittance `k2`, in `[0, k1)`.
    pub k2: f64,
    /// Angle offset `dpsi` added to every commanded angle, radians.
    pub offset_rad: f64,
}

impl AnalyzerModel {
    /// The ideal analyzer.
    pub const IDEAL: AnalyzerModel = AnalyzerModel {
        k1: 1.0,
        k2: 0.0,
        offset_rad: 0.0,
    };

    /// An analyzer of extinction ratio `k1/k2 > 1` (infinite for ideal) with `k1 = 1`.
    /// Errors name `extinction_ratio` or `offset_deg`.
    pub fn from_extinction_ratio(
        extinction_ratio: f64,
        offset_rad: f64,
    ) -> Result<Self, ModelError> {
        if extinction_ratio.is_nan() || extinction_ratio <= 1.0 {
            return Err(ModelError::OutOfRange {
                field: "extinction_ratio",
                value: extinction_ratio,
                allowed: "> 1 (inf for an ideal analyzer)",
            });
        }
        ModelError::check_range(
            "offset_deg",
            offset_rad.to_degrees(),
            -180.0,
            180.0,
            "[-180, 180]",
        )?;
        Ok(AnalyzerModel {
            k1: 1.0,
            k2: 1.0 / extinction_ratio,
            offset_rad,
        })
    }

    /// The analyzer row for commanded angle `psi_rad`.
    pub fn row(&self, psi_rad: f64) -> Vector3<f64> {
        let (s, c) = (2.0 * (psi_rad + self.offset_rad)).sin_cos();
        let d = self.k1 - self.k2;
        Vector3::new(0.5 * (self.k1 + self.k2), 0.5 * d * c, 0.5 * d * s)
    }
}

/// A set of analyzer angles with its measurement matrix and singular value decomposition.
#[derive(Debug, Clone, PartialEq)]
pub struct AnalyzerSet {
    angles_rad: Vec<f64>,
    /// `W`, `N x 3`.
    intensities_from_stokes: DMatrix<f64>,
    /// Singular values of `W`, descending.
    singular_values: [f64; 3],
    /// `W^+`, `3 x N`.
    stokes_from_intensities: DMatrix<f64>,
}

/// The pseudo-inverse `W^+` (`3 x N`) of a measurement matrix `W` (`N x 3` analyzer rows,
/// `N >= 3`) by its singular value decomposition, and `W`'s singular values, descending: the
/// one Stokes estimator of the workspace (the model's analyzer sets and the engine's live
/// products). Errors (naming `angles_deg`) when `W` is rank-deficient at the conventional
/// numerical threshold `s_max * eps * N` (as `numpy.linalg.matrix_rank`), or has fewer than
/// 3 rows or columns other than 3.
pub fn stokes_from_intensities(w: &DMatrix<f64>) -> Result<(DMatrix<f64>, [f64; 3]), ModelError> {
    let n = w.nrows();
    if n < 3 || w.ncols() != 3 {
        return Err(ModelError::Invalid {
            field: "angles_deg",
            reason: format!(
                "a {n} x {} measurement matrix; allowed N x 3 with N >= 3",
                w.ncols()
            ),
        });
    }
    let svd = w.clone().svd(true, true);
    let mut sv = [
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    ];
    sv.sort_by(|a, b| b.total_cmp(a));
    // Rank test at the conventional numerical threshold (as numpy.linalg.matrix_rank).
    let threshold = sv[0] * f64::EPSILON * n as f64;
    if sv[2] <= threshold {
        return Err(ModelError::Invalid {
            field: "angles_deg",
            reason: format!(
                "the measurement matrix is singular (singular values {:.3e}, {:.3e}, {:.3e}): \
                 need at least 3 distinct angles modulo 180 deg",
                sv[0], sv[1], sv[2]
            ),
        });
    }
    let pinv = svd
        .pseudo_inverse(threshold)
        .map_err(|e| ModelError::Invalid {
            field: "angles_deg",
            reason: format!("pseudo-inverse failed: {e}"),
        })?;
    Ok((pinv, sv))
}

/// Largest number of analyzer angles accepted (a generous bound on any acquisition plan).
pub const MAX_ANGLES: usize = 4096;

impl AnalyzerSet {
    /// Ideal analyzers at `angles_rad`.
    pub fn ideal(angles_rad: &[f64]) -> Result<Self, ModelError> {
        AnalyzerSet::new(angles_rad, &AnalyzerModel::IDEAL)
    }

    /// Real analyzers at `angles_rad`. Errors (naming `angles_deg`) for fewer than 3 angles, more
    /// than [`MAX_ANGLES`], non-finite angles, or a rank-deficient `W` (fewer than 3 distinct
    /// angles modulo 180 deg, or an analyzer with `k1 = k2`).
    pub fn new(angles_rad: &[f64], analyzer: &AnalyzerModel) -> Result<Self, ModelError> {
        let n = angles_rad.len();
        if !(3..=MAX_ANGLES).contains(&n) {
            return Err(ModelError::Invalid {
                field: "angles_deg",
                reason: format!("{n} angles given; allowed 3 to {MAX_ANGLES} (a linear Stokes vector has 3 unknowns)"),
            });
        }
        if let Some(bad) = angles_rad.iter().find(|a| !a.is_finite() || a.abs() > 1e6) {
            return Err(ModelError::OutOfRange {
                field: "angles_deg",
                value: bad.to_degrees(),
                allowed: "finite, |angle| <= 1e6 rad",
            });
        }
        let w = DMatrix::from_fn(n, 3, |i, j| analyzer.row(angles_rad[i])[j]);
        let (pinv, sv) = stokes_from_intensities(&w)?;
        Ok(AnalyzerSet {
            angles_rad: angles_rad.to_vec(),
            intensities_from_stokes: w,
            singular_values: sv,
            stokes_from_intensities: pinv,
        })
    }

    /// The commanded angles, radians.
    pub fn angles_rad(&self) -> &[f64] {
        &self.angles_rad
    }

    /// The measurement matrix `W` (`N x 3`).
    pub fn intensities_from_stokes(&self) -> &DMatrix<f64> {
        &self.intensities_from_stokes
    }

    /// The pseudo-inverse `W^+` (`3 x N`).
    pub fn stokes_from_intensities(&self) -> &DMatrix<f64> {
        &self.stokes_from_intensities
    }

    /// Singular values of `W`, descending.
    pub fn singular_values(&self) -> [f64; 3] {
        self.singular_values
    }

    /// 2-norm condition number of `W`, `s_max / s_min` (finite: singular sets are rejected).
    pub fn cond2(&self) -> f64 {
        self.singular_values[0] / self.singular_values[2]
    }

    /// `(W^T W)^-1 = V diag(1/s^2) V^T`, the Stokes covariance per unit i.i.d. intensity variance.
    pub fn stokes_covariance_per_unit_variance(&self) -> Matrix3<f64> {
        let p = &self.stokes_from_intensities;
        let c = p * p.transpose();
        Matrix3::from_fn(|i, j| c[(i, j)])
    }

    /// Noise gains: the variance of each reconstructed Stokes component per unit i.i.d. intensity
    /// variance, `diag((W^T W)^-1)`.
    pub fn noise_gains(&self) -> [f64; 3] {
        let c = self.stokes_covariance_per_unit_variance();
        [c[(0, 0)], c[(1, 1)], c[(2, 2)]]
    }

    /// Equally weighted variance `EWV = trace((W^T W)^-1)` (Tyo 2002): total Stokes variance per
    /// unit intensity variance.
    pub fn ewv(&self) -> f64 {
        self.noise_gains().iter().sum()
    }

    /// Forward model `I = W S`.
    pub fn intensities(&self, s: &Stokes) -> DVector<f64> {
        &self.intensities_from_stokes * s.0
    }

    /// Least-squares reconstruction `S_hat = W^+ I`. Errors name `intensities` if the length
    /// differs from the number of angles or a value is not finite.
    pub fn reconstruct(&self, intensities: &[f64]) -> Result<Stokes, ModelError> {
        if intensities.len() != self.angles_rad.len() {
            return Err(ModelError::Invalid {
                field: "intensities",
                reason: format!(
                    "{} values for {} angles; allowed exactly one per angle",
                    intensities.len(),
                    self.angles_rad.len()
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
        let i = DVector::from_column_slice(intensities);
        let s = &self.stokes_from_intensities * i;
        Ok(Stokes::new(s[0], s[1], s[2]))
    }
}

/// Pickering's 0/45/90 method (Meng (2012) Sec. 2.4): `S0 = I0 + I90`, `S1 = I0 - I90`,
/// `S2 = 2 I45 - I0 - I90`.
pub fn pickering(i0: f64, i45: f64, i90: f64) -> Stokes {
    Stokes::new(i0 + i90, i0 - i90, 2.0 * i45 - i0 - i90)
}

/// The 0/60/120 method (Meng (2012) Sec. 2.4, sign of `S2` derived from `W^+`):
/// `S0 = 2/3 (I0 + I60 + I120)`, `S1 = 2/3 (2 I0 - I60 - I120)`, `S2 = 2/sqrt(3) (I60 - I120)`.
pub fn three_angle_0_60_120(i0: f64, i60: f64, i120: f64) -> Stokes {
    Stokes::new(
        2.0 / 3.0 * (i0 + i60 + i120),
        2.0 / 3.0 * (2.0 * i0 - i60 - i120),
        2.0 / 3f64.sqrt() * (i60 - i120),
    )
}

/// The modified Pickering 0/45/90/135 method (Meng (2012) Sec. 2.4): `S0 = 0.5 (I0 + I45 + I90 + I135)`,
/// `S1 = I0 - I90`, `S2 = I45 - I135`.
pub fn modified_pickering(i0: f64, i45: f64, i90: f64, i135: f64) -> Stokes {
    Stokes::new(0.5 * (i0 + i45 + i90 + i135), i0 - i90, i45 - i135)
}
