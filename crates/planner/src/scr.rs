//! Signal-to-clutter ratio of an analyzer set and its gradient (MODEL.md section 9).
//!
//! For analyzer angles `psi_1..psi_N` the measurement rows are `w_i = 0.5 [1, cos 2psi_i,
//! sin 2psi_i]`, so `W` is `N x 3`. The target-background Stokes mean difference is `d`, the
//! background clutter covariance `Sigma_b` and the per-frame noise variance `V`. Then
//!
//! `SCR = (W d)^T (W Sigma_b W^T + V I)^-1 (W d)`.
//!
//! This is the squared Mahalanobis distance of the two class means in intensity space
//! (issue 5; MODEL.md section 9). With `A = W^T W` (3x3), the push-through identity
//! `W^T (W Sigma W^T + V I)^-1 = (A Sigma + V I)^-1 W^T` gives
//!
//! `SCR = d^T (A Sigma_b + V I)^-1 A d`.
//!
//! This is a 3x3 solve for any `N`, and it depends on the angles only through `A`, i.e. through
//! the sums of `cos 2psi`, `sin 2psi`, `cos 4psi` and `sin 4psi`. That is why order and 180-degree
//! periodicity leave it unchanged. For `N >= 3` and an invertible `A` it equals the SCR of the
//! Stokes images `S_hat = W^+ I`: `d^T (Sigma_b + V A^-1)^-1 d`.
//!
//! Gradient. Write `B = A Sigma + V I`, `u = B^-T d` and `v = (I - Sigma B^-1 A) d`. Then
//! `dA/dpsi_k = w'_k w_k^T + w_k w'_k^T` with `w'_k = [0, -sin 2psi_k, cos 2psi_k]`, and
//! `dSCR/dpsi_k = (u . w'_k)(w_k . v) + (u . w_k)(w'_k . v)`. So the gradient costs O(N) after
//! one 3x3 solve.

use crate::PlanError;
use nalgebra::{Matrix3, Vector3};

/// A measurement row `w(psi) = 0.5 [1, cos 2psi, sin 2psi]` (ideal analyzer, MODEL.md section 5).
pub fn row(psi_rad: f64) -> Vector3<f64> {
    let (s, c) = (2.0 * psi_rad).sin_cos();
    Vector3::new(0.5, 0.5 * c, 0.5 * s)
}

/// `dw/dpsi = [0, -sin 2psi, cos 2psi]`.
fn row_derivative(psi_rad: f64) -> Vector3<f64> {
    let (s, c) = (2.0 * psi_rad).sin_cos();
    Vector3::new(0.0, -s, c)
}

/// What separates the classes, and what the sensor adds: the inputs of the SCR.
#[derive(Debug, Clone, PartialEq)]
pub struct Contrast {
    /// Target minus background Stokes mean, `d` (any consistent unit, e.g. DN or radiance).
    pub d: Vector3<f64>,
    /// Background clutter covariance `Sigma_b` (the unit of `d`, squared), symmetric PSD.
    pub sigma_b: Matrix3<f64>,
    /// Per-frame noise variance `V` (the unit of `d`, squared), `>= 0`.
    pub noise_var: f64,
    /// What was done to make the problem well posed (regularisation), for the report.
    pub notes: Vec<String>,
    /// Condition number of `Sigma_b` (2-norm) as given.
    pub clutter_condition: f64,
}

/// With no sensor noise (`V = 0`), the noise floor used instead and the ridge added to a
/// singular clutter covariance, relative to the mean clutter variance `trace(Sigma_b) / 3`.
pub const RIDGE: f64 = 1e-9;

impl Contrast {
    /// Checks and conditions the inputs. Errors name the field.
    /// - `d` and `Sigma_b` must be finite.
    /// - `Sigma_b` must be symmetric to 1e-9 relative and positive semidefinite to 1e-9 of its
    ///   largest eigenvalue.
    /// - `V` must be finite and `>= 0`.
    ///
    /// With `V = 0`, a noise floor of `RIDGE * trace / 3` is used (noted). If `Sigma_b` is also
    /// singular, where the SCR of a set whose rows reach the clutter's null space would be
    /// unbounded, the same ridge is added to it (noted). Both zero is an error.
    pub fn new(
        d: Vector3<f64>,
        sigma_b: Matrix3<f64>,
        noise_var: f64,
    ) -> Result<Contrast, PlanError> {
        if d.iter().any(|v| !v.is_finite()) {
            return Err(PlanError::invalid(
                "target_mean - background_mean",
                "not finite",
            ));
        }
        if sigma_b.iter().any(|v| !v.is_finite()) {
            return Err(PlanError::invalid("background_cov", "not finite"));
        }
        if !(noise_var.is_finite() && noise_var >= 0.0) {
            return Err(PlanError::OutOfRange {
                field: "noise_var",
                value: noise_var,
                allowed: "finite, >= 0",
            });
        }
        let scale = sigma_b.abs().max().max(f64::MIN_POSITIVE);
        let asym = (sigma_b - sigma_b.transpose()).abs().max();
        if asym > 1e-9 * scale {
            return Err(PlanError::invalid(
                "background_cov",
                format!("not symmetric (largest |C_ij - C_ji| = {asym:.3e})"),
            ));
        }
        let sym = 0.5 * (sigma_b + sigma_b.transpose());
        let eig = sym.symmetric_eigen();
        let (lo, hi) = (eig.eigenvalues.min(), eig.eigenvalues.max());
        if hi < 0.0 || lo < -1e-9 * hi.max(0.0) {
            return Err(PlanError::invalid(
                "background_cov",
                format!("not positive semidefinite (eigenvalues {lo:.3e} .. {hi:.3e})"),
            ));
        }
        let clutter_condition = if lo > 0.0 { hi / lo } else { f64::INFINITY };
        let mut notes = Vec::new();
        let mut sigma = sym;
        let mut noise_var = noise_var;
        if noise_var == 0.0 {
            if hi <= 0.0 {
                return Err(PlanError::invalid(
                    "background_cov",
                    "zero, and noise_var = 0: nothing limits the SCR",
                ));
            }
            // Without sensor noise, a singular clutter covariance (or a set of fewer than 3
            // channels) makes `A Sigma` singular; a tiny noise floor keeps every set defined.
            let eps = RIDGE * sym.trace() / 3.0;
            noise_var = eps;
            notes.push(format!(
                "noise_var = 0 taken as {eps:.3e} (RIDGE x mean clutter variance) so that every \
                 analyzer set has a finite SCR"
            ));
            if clutter_condition.is_nan() || clutter_condition >= 1e12 {
                sigma += Matrix3::identity() * eps;
                notes.push(format!(
                    "background_cov is singular or ill-conditioned (condition \
                     {clutter_condition:.3e}) and noise_var = 0: regularised with a ridge of \
                     {eps:.3e}"
                ));
            }
        }
        if d.norm() == 0.0 {
            notes.push(
                "no contrast: target and background Stokes means are equal, SCR = 0 for every \
                 analyzer set"
                    .into(),
            );
        }
        Ok(Contrast {
            d,
            sigma_b: sigma,
            noise_var,
            notes,
            clutter_condition,
        })
    }

    /// `A = sum_i w_i w_i^T` of a set.
    fn gram(angles_rad: &[f64]) -> Matrix3<f64> {
        angles_rad.iter().fold(Matrix3::zeros(), |acc, &p| {
            let w = row(p);
            acc + w * w.transpose()
        })
    }

    /// The SCR of the analyzer set (intensity images; for `N >= 3` with an invertible `A` also
    /// the Stokes images'). 0 for an empty set.
    pub fn scr(&self, angles_rad: &[f64]) -> f64 {
        self.scr_and_gradient(angles_rad, None)
    }

    /// The SCR and, into `gradient` (one entry per angle), its derivative per radian.
    pub fn scr_and_gradient(&self, angles_rad: &[f64], gradient: Option<&mut [f64]>) -> f64 {
        if angles_rad.is_empty() {
            return 0.0;
        }
        let a = Self::gram(angles_rad);
        let b = a * self.sigma_b + Matrix3::identity() * self.noise_var;
        // B = A Sigma + V I with V > 0 (Contrast::new guarantees it) is invertible.
        let Some(lu) = b.try_inverse() else {
            if let Some(g) = gradient {
                g.iter_mut().for_each(|v| *v = 0.0);
            }
            return 0.0;
        };
        let ad = a * self.d;
        let scr = self.d.dot(&(lu * ad));
        if let Some(g) = gradient {
            let u = lu.transpose() * self.d;
            let v = self.d - self.sigma_b * (lu * ad);
            for (gk, &p) in g.iter_mut().zip(angles_rad) {
                let (w, dw) = (row(p), row_derivative(p));
                *gk = u.dot(&dw) * w.dot(&v) + u.dot(&w) * dw.dot(&v);
            }
        }
        scr.max(0.0)
    }

    /// The clutter-limited SCR `d^T Sigma_b^-1 d`: what any set of `N >= 3` independent rows
    /// reaches as the noise vanishes (infinite for a singular `Sigma_b` with `d` in its null
    /// space).
    pub fn clutter_limit(&self) -> f64 {
        match self.sigma_b.try_inverse() {
            Some(inv) => self.d.dot(&(inv * self.d)).max(0.0),
            None => f64::INFINITY,
        }
    }
}

/// The matched filter's ROC of the analyzer set `angles_rad` at `pfa`, the detector the SCR
/// describes: each class in intensity space, `W mu` and `W Sigma W^T + V I` with the ideal rows
/// of [`row`] and `noise_var` the sensor's per-frame variance (the same units as the Stokes
/// covariances squared). `target` and `background` are (mean, covariance) of the Stokes vector.
/// The detector and its ROC are [`polar_model::metrics::matched_filter`]'s.
///
/// Errors: the model's, naming `target_cov` or `background_cov` when a covariance is not
/// positive definite in intensity space, or `pfa` outside (0, 1).
pub fn matched_filter_roc(
    angles_rad: &[f64],
    target: (&Vector3<f64>, &Matrix3<f64>),
    background: (&Vector3<f64>, &Matrix3<f64>),
    noise_var: f64,
    pfa: f64,
) -> Result<polar_model::metrics::Roc, polar_model::ModelError> {
    use nalgebra::{DMatrix, DVector};
    use polar_model::metrics::{matched_filter, ClassStats};
    let n = angles_rad.len();
    let w = DMatrix::from_fn(n, 3, |i, j| row(angles_rad[i])[j]);
    let class = |field, m: &Vector3<f64>, c: &Matrix3<f64>| {
        let mean = &w * DVector::from_column_slice(m.as_slice());
        let cov = &w * DMatrix::from_fn(3, 3, |i, j| c[(i, j)]) * w.transpose()
            + DMatrix::identity(n, n) * noise_var;
        ClassStats::new(field, mean, 0.5 * (&cov + cov.transpose()))
    };
    let t = class("target_cov", target.0, target.1)?;
    let b = class("background_cov", background.0, background.1)?;
    matched_filter(&t, &b, pfa)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example(noise_var: f64) -> Contrast {
        let sigma = Matrix3::new(4.0, 0.5, -0.2, 0.5, 1.0, 0.1, -0.2, 0.1, 0.8);
        Contrast::new(Vector3::new(2.0, 1.5, -0.7), sigma, noise_var).expect("valid")
    }

    /// The 3x3 push-through form equals the definition `(Wd)^T (W Sigma W^T + V I)^-1 (W d)`
    /// computed with an N x N solve, to rounding, for N = 1..6.
    #[test]
    fn push_through_matches_definition() {
        let c = example(0.3);
        for n in 1..=6 {
            let angles: Vec<f64> = (0..n).map(|i| 0.37 + 0.61 * i as f64).collect();
            let w = nalgebra::DMatrix::from_fn(n, 3, |i, j| row(angles[i])[j]);
            let s = nalgebra::DMatrix::from_fn(3, 3, |i, j| c.sigma_b[(i, j)]);
            let m = &w * s * w.transpose() + nalgebra::DMatrix::identity(n, n) * c.noise_var;
            let wd = &w * nalgebra::DVector::from_column_slice(c.d.as_slice());
            let direct = wd.dot(&(m.try_inverse().expect("pd") * &wd));
            let fast = c.scr(&angles);
            assert!(
                (fast - direct).abs() <= 1e-12 * direct,
                "n={n}: {fast} vs {direct}"
            );
        }
    }

    /// The analytic gradient matches central differences (step 1e-6 rad: truncation ~1e-12,
    /// rounding ~1e-10 relative).
    #[test]
    fn gradient_matches_finite_differences() {
        let c = example(0.3);
        let angles = [0.1, 0.9, 1.7, 2.2];
        let mut g = [0.0; 4];
        c.scr_and_gradient(&angles, Some(&mut g));
        for k in 0..4 {
            let h = 1e-6;
            let (mut up, mut dn) = (angles, angles);
            up[k] += h;
            dn[k] -= h;
            let fd = (c.scr(&up) - c.scr(&dn)) / (2.0 * h);
            assert!(
                (g[k] - fd).abs() <= 1e-6 * (1.0 + fd.abs()),
                "{k}: {} vs {fd}",
                g[k]
            );
        }
    }

    /// Order and 180-degree periodicity leave the SCR unchanged; for one channel it is
    /// `(w^T d)^2 / (w^T Sigma w + V)`; without noise, three independent channels reach the
    /// clutter limit `d^T Sigma^-1 d` whatever their angles.
    #[test]
    fn invariances_and_closed_forms() {
        let c = example(0.3);
        let s = c.scr(&[0.2, 1.1, 2.5]);
        assert!((c.scr(&[2.5, 0.2, 1.1]) - s).abs() < 1e-12 * s);
        assert!(
            (c.scr(&[0.2 + std::f64::consts::PI, 1.1, 2.5 - std::f64::consts::PI]) - s).abs()
                < 1e-12 * s
        );
        let w = row(0.4);
        let one = w.dot(&c.d).powi(2) / (w.dot(&(c.sigma_b * w)) + 0.3);
        assert!((c.scr(&[0.4]) - one).abs() < 1e-12 * one);
        // V = 0 runs on a noise floor of 1e-9 of the clutter variance: the SCR falls short
        // of the limit by about V ||A^-1|| / lambda_min(Sigma), under 1e-5 even for the
        // ill-conditioned second set.
        let quiet = example(0.0);
        let limit = quiet.clutter_limit();
        for set in [[0.0, 1.0, 2.0], [0.3, 0.35, 1.9]] {
            assert!((quiet.scr(&set) - limit).abs() < 1e-5 * limit, "{set:?}");
        }
    }

    /// Bad covariances are refused naming the field; a singular clutter covariance with no
    /// noise is regularised and says so; no contrast is said.
    #[test]
    fn degenerate_inputs() {
        let d = Vector3::new(1.0, 0.0, 0.0);
        let e = Contrast::new(
            d,
            Matrix3::new(1.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
            1.0,
        )
        .expect_err("asymmetric");
        assert!(e.to_string().contains("background_cov"), "{e}");
        let e = Contrast::new(
            d,
            Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, 1.0)),
            1.0,
        )
        .expect_err("indefinite");
        assert!(e.to_string().contains("positive semidefinite"), "{e}");
        let singular = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0));
        let c = Contrast::new(Vector3::new(0.0, 0.0, 1.0), singular, 0.0).expect("regularised");
        assert!(c.notes.iter().any(|n| n.contains("regularised")));
        assert!(c.scr(&[0.0, 1.0, 2.0]).is_finite());
        let none = Contrast::new(Vector3::zeros(), singular, 1.0).expect("no contrast");
        assert!(none.notes.iter().any(|n| n.contains("no contrast")));
        assert_eq!(none.scr(&[0.0, 1.0]), 0.0);
    }
}
