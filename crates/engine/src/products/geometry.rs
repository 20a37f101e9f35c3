//! The estimator of a set: the analyzer rows, their conditioning and the pseudo-inverse
//! `P = A^+` (the model's, [`polar_model::analyzer::stokes_from_intensities`]) that turns
//! frames into Stokes images.

use super::error::ProductsError;
use nalgebra::DMatrix;

/// Smallest reciprocal condition number of `A^T A` ([`SetGeometry`]) accepted:
/// `lambda_min / lambda_max = (s_min / s_max)^2` of the rows matrix `A`.
pub const MIN_RCOND: f64 = 1e-10;

/// Allowed range of the largest absolute entry of the analyzer rows (DN per Stokes unit;
/// an ideal polarizer's rows have 0.5). Outside it the f32 products could lose range.
pub const ROW_SCALE_RANGE: (f64, f64) = (1e-3, 1e3);

/// The analyzer rows of one angle set and their pseudo-inverse, computed once per set.
#[derive(Debug, Clone, PartialEq)]
pub struct SetGeometry {
    pub(super) rows: Vec<[f64; 3]>,
    /// Column `i` of `P` (the weights of frame `i` in S0, S1, S2), f64.
    pub(super) pinv: Vec<[f64; 3]>,
    pub(super) condition_number: f64,
}

impl SetGeometry {
    /// The geometry of analyzer rows `a_i` (row `i` = frame `i`: `y_i = a_i . S + dark`).
    ///
    /// Errors: fewer than 3 rows, a non-finite entry, a largest `|entry|` outside
    /// [`ROW_SCALE_RANGE`], or `A^T A` singular or ill-conditioned (reciprocal condition
    /// number below [`MIN_RCOND`]; the error lists the analyzer angles the rows imply).
    pub fn new(rows: &[[f64; 3]]) -> Result<SetGeometry, ProductsError> {
        if rows.len() < 3 {
            return Err(ProductsError::TooFewRows { count: rows.len() });
        }
        for (index, row) in rows.iter().enumerate() {
            if row.iter().any(|v| !v.is_finite()) {
                return Err(ProductsError::NonFiniteRow { index, row: *row });
            }
        }
        let scale = rows
            .iter()
            .flat_map(|r| r.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        if !(scale >= ROW_SCALE_RANGE.0 && scale <= ROW_SCALE_RANGE.1) {
            return Err(ProductsError::RowScale { value: scale });
        }
        let singular = |rcond: f64| ProductsError::Singular {
            angles_deg: rows.iter().map(row_angle_deg).collect(),
            rcond,
            min: MIN_RCOND,
        };
        let a = DMatrix::from_fn(rows.len(), 3, |i, k| rows[i][k]);
        // Singular values only; a (never seen) failure to converge counts as singular.
        let sv = a
            .clone()
            .try_svd(false, false, 5.0 * f64::EPSILON, 10_000)
            .ok_or_else(|| singular(0.0))?
            .singular_values;
        let s_max = sv.iter().fold(0.0f64, |m, v| m.max(*v));
        let s_min = sv.iter().fold(f64::INFINITY, |m, v| m.min(*v));
        let rcond = if s_max > 0.0 {
            (s_min / s_max).powi(2)
        } else {
            0.0
        };
        if rcond.is_nan() || rcond < MIN_RCOND {
            return Err(singular(rcond));
        }
        // The model's estimator (its one pseudo-inverse, by the SVD of A).
        let (p, _) =
            polar_model::analyzer::stokes_from_intensities(&a).map_err(|_| singular(rcond))?;
        let mut pinv: Vec<[f64; 3]> = (0..rows.len())
            .map(|i| [p[(0, i)], p[(1, i)], p[(2, i)]])
            .collect();
        // Entries that are rounding noise of an exact zero (e.g. cos 90 deg = 6e-17) are
        // snapped to 0, so that an ideal 0/45/90/135 set gives S1 = S2 = 0 exactly for equal
        // frames. The change (< 1e-12 of the largest entry) is far below f32 resolution.
        let p_max = pinv
            .iter()
            .flat_map(|c| c.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        for v in pinv.iter_mut().flat_map(|c| c.iter_mut()) {
            if v.abs() < 1e-12 * p_max {
                *v = 0.0;
            }
        }
        Ok(SetGeometry {
            rows: rows.to_vec(),
            pinv,
            condition_number: s_max / s_min,
        })
    }

    /// The geometry of an ideal linear polarizer at `angles_rad` (radians from the x axis):
    /// rows `0.5 [1, cos 2psi, sin 2psi]`. Errors as [`SetGeometry::new`], plus a
    /// non-finite angle.
    pub fn ideal(angles_rad: &[f64]) -> Result<SetGeometry, ProductsError> {
        let mut rows = Vec::with_capacity(angles_rad.len());
        for (index, &psi) in angles_rad.iter().enumerate() {
            if !psi.is_finite() {
                return Err(ProductsError::NonFiniteAngle { index, value: psi });
            }
            rows.push([0.5, 0.5 * (2.0 * psi).cos(), 0.5 * (2.0 * psi).sin()]);
        }
        SetGeometry::new(&rows)
    }

    /// The analyzer rows `a_i`, one per frame.
    pub fn rows(&self) -> &[[f64; 3]] {
        &self.rows
    }

    /// Number of frames (rows) of the set.
    pub fn frame_count(&self) -> usize {
        self.rows.len()
    }

    /// The `3 x N` pseudo-inverse `P = A^+ = (A^T A)^-1 A^T` by columns: element `i` is column `i`,
    /// the weights of frame `i` in `(S0, S1, S2)`.
    pub fn pinv(&self) -> Vec<[f64; 3]> {
        self.pinv.clone()
    }

    /// The pseudo-inverse as a `3 x N` nalgebra matrix.
    pub fn pinv_matrix(&self) -> DMatrix<f64> {
        DMatrix::from_fn(3, self.pinv.len(), |k, i| self.pinv[i][k])
    }

    /// The 2-norm condition number of the rows matrix `A` (`s_max / s_min`; that of
    /// `A^T A` is its square). At most `1 / sqrt(MIN_RCOND) = 1e5` for an accepted set.
    pub fn condition_number(&self) -> f64 {
        self.condition_number
    }
}

/// The analyzer angle a row implies, degrees in `[0, 180)` (NaN for a row with no
/// polarising part).
pub(super) fn row_angle_deg(row: &[f64; 3]) -> f64 {
    if row[1] == 0.0 && row[2] == 0.0 {
        return f64::NAN;
    }
    (0.5 * row[2].atan2(row[1])).to_degrees().rem_euclid(180.0)
}
