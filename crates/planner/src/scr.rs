//! Signal-to-clutter ratio of an analyzer set and its gradient (MODEL.md section 9).
//!
//! For analyzer angles `psi_1..psi_N` the measurement rows are `w_i = w(psi_i)`, so `W` is
//! `N x 3`: the ideal analyzer's `0.5 [1, cos 2psi, sin 2psi]`, or a camera's real rows
//! `M_opt^T a(psi)` with its analyzer's principal transmittances `k1, k2`, offset and
//! fore-optics ([`Instrument`]). The target-background Stokes mean difference is `d`, the
//! background clutter covariance `Sigma_b` and the per-frame sensor noise variance
//! `v_i = v(psi_i) = V + c max(0, w(psi_i) . mu_b)`: a floor `V` (dark current, read noise,
//! quantisation) and the background's shot noise, which follows the light the analyzer lets
//! through (`c = F_n / G`, `G` electrons per radiance unit in one frame; `c = 0` for the ideal
//! model with a constant `V`). With `D = diag(v_i)`,
//!
//! `SCR = (W d)^T (W Sigma_b W^T + D)^-1 (W d)`.
//!
//! This is the squared Mahalanobis distance of the two class means in intensity space
//! (MODEL.md section 9), the matched filter's SCR that the forecast of a plan reports
//! for the same frames (`polarimeter plan --scene`, `plan check`). With
//! `A = W^T D^-1 W = sum_i w_i w_i^T / v_i` (3x3), the push-through identity
//! `W^T (W Sigma W^T + D)^-1 W = (A Sigma + I)^-1 A` gives
//!
//! `SCR = d^T (A Sigma_b + I)^-1 A d`.
//!
//! So it depends on the angles only through `A`. That is why order and 180-degree periodicity
//! leave it unchanged. (It is computed from the definition, a Cholesky solve of the `N x N`
//! `M = W Sigma_b W^T + D` for `N <= 6`, whose rounding error is a few epsilon times
//! `cond(M)`, as the forecast's own; the 3x3 inverse of `A Sigma + I` loses more digits when
//! the clutter dominates the noise.) For `N >= 3` and an invertible `A` it
//! equals the SCR of the Stokes images `S_hat = (W^T D^-1 W)^-1 W^T D^-1 I`:
//! `d^T (Sigma_b + A^-1)^-1 d`.
//!
//! Gradient. With `r = M^-1 W d`, `w'_k = dw/dpsi` at `psi_k` and `v'_k = c (w'_k . mu_b)` (0
//! where the transmitted light is clamped at 0), differentiating `(W d)^T M^-1 (W d)` gives
//! `dSCR/dpsi_k = 2 r_k (w'_k . d) - 2 r_k w'_k^T Sigma_b W^T r - r_k^2 v'_k`: O(N) per angle
//! after the one solve.

use crate::PlanError;
use nalgebra::{Matrix3, Vector3};
use polar_model::analyzer::AnalyzerModel;
use polar_model::sensor::{Exposure, SensorModel};

/// A measurement row `w(psi) = 0.5 [1, cos 2psi, sin 2psi]` (ideal analyzer, MODEL.md section 0).
pub fn row(psi_rad: f64) -> Vector3<f64> {
    let (s, c) = (2.0 * psi_rad).sin_cos();
    Vector3::new(0.5, 0.5 * c, 0.5 * s)
}

/// How one frame sees a Stokes vector: the analyzer's rows and the part of the sensor noise
/// that depends on the angle (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Instrument {
    /// The rotating analyzer (principal transmittances `k1 >= k2`, angle offset).
    pub analyzer: AnalyzerModel,
    /// The fore-optics' linear Mueller block `M_opt`: the row is `M_opt^T a(psi)`.
    pub fore_optics: Matrix3<f64>,
    /// `c`, the shot-noise variance per unit of transmitted radiance (the unit of `d`):
    /// `F_n / G` for a camera, 0 for a constant noise.
    pub shot_var_per_radiance: f64,
    /// `mu_b`, the Stokes mean whose transmitted part `w(psi) . mu_b` makes the shot noise (the
    /// background's, in the unit of `d`).
    pub shot_source: Vector3<f64>,
}

impl Instrument {
    /// The ideal analyzer, no fore-optics, constant noise: the rows of [`row`].
    pub fn ideal() -> Instrument {
        Instrument {
            analyzer: AnalyzerModel::IDEAL,
            fore_optics: Matrix3::identity(),
            shot_var_per_radiance: 0.0,
            shot_source: Vector3::zeros(),
        }
    }

    /// The row `w(psi) = M_opt^T a(psi)` and its derivative per radian.
    pub fn row_and_derivative(&self, psi_rad: f64) -> (Vector3<f64>, Vector3<f64>) {
        let a = self.analyzer;
        let (s, c) = (2.0 * (psi_rad + a.offset_rad)).sin_cos();
        let diff = a.k1 - a.k2;
        let row = Vector3::new(0.5 * (a.k1 + a.k2), 0.5 * diff * c, 0.5 * diff * s);
        let drow = Vector3::new(0.0, -diff * s, diff * c);
        let m = self.fore_optics.transpose();
        (m * row, m * drow)
    }

    /// The angle-dependent noise `c max(0, w . mu_b)` and its derivative given `w` and `w'`.
    fn shot(&self, w: &Vector3<f64>, dw: &Vector3<f64>) -> (f64, f64) {
        let light = w.dot(&self.shot_source);
        if light > 0.0 {
            (
                self.shot_var_per_radiance * light,
                self.shot_var_per_radiance * dw.dot(&self.shot_source),
            )
        } else {
            (0.0, 0.0)
        }
    }
}

/// What separates the classes, and what the sensor adds: the inputs of the SCR.
#[derive(Debug, Clone, PartialEq)]
pub struct Contrast {
    /// Target minus background Stokes mean, `d` (any consistent unit, e.g. DN or radiance).
    pub d: Vector3<f64>,
    /// Background clutter covariance `Sigma_b` (the unit of `d`, squared), symmetric PSD.
    pub sigma_b: Matrix3<f64>,
    /// The angle-independent per-frame noise variance `V` (the unit of `d`, squared), `> 0`
    /// after [`Contrast::new`]; the whole noise for the ideal instrument.
    pub noise_var: f64,
    /// The rows and the angle-dependent noise ([`Instrument::ideal`] from [`Contrast::new`]).
    pub instrument: Instrument,
    /// What was done to make the problem well posed (regularisation), for the report.
    pub notes: Vec<String>,
    /// Condition number of `Sigma_b` (2-norm) as given.
    pub clutter_condition: f64,
}

/// With no sensor noise (`V = 0`), the noise floor used instead and the ridge added to a
/// singular clutter covariance, relative to the mean clutter variance `trace(Sigma_b) / 3`.
pub const RIDGE: f64 = 1e-9;

impl Contrast {
    /// Checks and conditions the inputs for the ideal instrument. Errors name the field.
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
        Contrast::with_instrument(d, sigma_b, noise_var, Instrument::ideal())
    }

    /// As [`Contrast::new`] with a real instrument. Errors also for an instrument whose
    /// fore-optics or shot-noise terms are not finite, whose `c` is negative, or whose analyzer
    /// has `k1 <= k2` (no polarisation sensitivity), naming the field.
    pub fn with_instrument(
        d: Vector3<f64>,
        sigma_b: Matrix3<f64>,
        noise_var: f64,
        instrument: Instrument,
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
        let inst = &instrument;
        if inst.fore_optics.iter().any(|v| !v.is_finite())
            || inst.shot_source.iter().any(|v| !v.is_finite())
        {
            return Err(PlanError::invalid(
                "instrument",
                "fore-optics or shot-noise source not finite",
            ));
        }
        if !(inst.shot_var_per_radiance.is_finite() && inst.shot_var_per_radiance >= 0.0) {
            return Err(PlanError::OutOfRange {
                field: "instrument.shot_var_per_radiance",
                value: inst.shot_var_per_radiance,
                allowed: "finite, >= 0",
            });
        }
        let a = inst.analyzer;
        if !(a.k1.is_finite() && a.k2.is_finite() && a.offset_rad.is_finite() && a.k1 > a.k2) {
            return Err(PlanError::invalid(
                "instrument.analyzer",
                format!(
                    "k1 = {}, k2 = {}: allowed finite with k1 > k2 (a polariser)",
                    a.k1, a.k2
                ),
            ));
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
            instrument,
            notes,
            clutter_condition,
        })
    }

    /// The contrast a camera sees at `t_int_s`, in radiance units (W m^-2 sr^-1): the class
    /// means' difference `d = mu_t - mu_b`, the background's clutter `Sigma_b`, the camera's
    /// real rows ([`SensorModel::intensities_from_stokes`]: analyzer and fore-optics), and its
    /// noise per frame at the background's light (shot, dark current, read noise and
    /// quantisation of [`SensorModel::signal`], times the noise factor, divided by `(K G)^2`).
    /// Its SCR is exactly the matched-filter SCR of the background's and target's frames that
    /// `SensorModel::signal` gives with the background's clutter (module docs), so the planner
    /// maximises the number the forecast prints.
    ///
    /// Errors: the model's (naming its field), a camera that does not respond in the band,
    /// or the contrast's own ([`Contrast::with_instrument`]).
    pub fn from_sensor(
        sensor: &SensorModel,
        t_int_s: f64,
        target_mean: &Vector3<f64>,
        background_mean: &Vector3<f64>,
        background_cov: &Matrix3<f64>,
    ) -> Result<Contrast, PlanError> {
        let model = |e: polar_model::ModelError| PlanError::invalid("camera", e.to_string());
        let s = sensor
            .signal(
                &[0.0],
                &Exposure::new(t_int_s, polar_model::polarization::Stokes(*background_mean)),
            )
            .map_err(model)?;
        let k = sensor.camera().gain_dn_per_e;
        let kg = k * s.electrons_from_radiance;
        if !(kg.is_finite() && kg > 0.0) {
            return Err(PlanError::invalid(
                "camera",
                format!("K G = {kg} DN per W m^-2 sr^-1: the camera does not respond in the band"),
            ));
        }
        let v = &s.variance;
        let floor_dn2 = v.dark_dn2[0] + v.read_dn2[0] + v.quantization_dn2[0];
        let instrument = Instrument {
            analyzer: sensor.analyzer(),
            fore_optics: sensor.camera().fore_optics().0,
            // shot_dn2 = F K^2 G (w . mu_b): per radiance unit F K^2 G / (K G)^2 = F / G.
            shot_var_per_radiance: s.noise_variance_factor / s.electrons_from_radiance,
            shot_source: *background_mean,
        };
        Contrast::with_instrument(
            target_mean - background_mean,
            0.5 * (background_cov + background_cov.transpose()),
            floor_dn2 / (kg * kg),
            instrument,
        )
    }

    /// The same contrast without sensor noise (the floor [`RIDGE`] stands in, as
    /// [`Contrast::new`] does with `V = 0`): its optimum is the clutter-limited SCR a set of
    /// these rows reaches as the integration time grows.
    pub fn noise_free(&self) -> Result<Contrast, PlanError> {
        let instrument = Instrument {
            shot_var_per_radiance: 0.0,
            ..self.instrument.clone()
        };
        Contrast::with_instrument(self.d, self.sigma_b, 0.0, instrument)
    }

    /// The row of angle `psi_rad` (the instrument's).
    pub fn row(&self, psi_rad: f64) -> Vector3<f64> {
        self.instrument.row_and_derivative(psi_rad).0
    }

    /// The per-frame noise variance at angle `psi_rad`: `V + c max(0, w . mu_b)`.
    pub fn frame_noise_var(&self, psi_rad: f64) -> f64 {
        let (w, dw) = self.instrument.row_and_derivative(psi_rad);
        self.noise_var + self.instrument.shot(&w, &dw).0
    }

    /// The measurement matrix's 2-norm condition number `s_max / s_min` for the set (infinite
    /// for fewer than 3 independent rows): how much the Stokes estimate amplifies the noise.
    pub fn condition_number(&self, angles_rad: &[f64]) -> f64 {
        let a = angles_rad.iter().fold(Matrix3::zeros(), |acc, &p| {
            let w = self.row(p);
            acc + w * w.transpose()
        });
        let e = a.symmetric_eigenvalues();
        let (lo, hi) = (e.min(), e.max());
        if lo <= hi * 1e-15 || angles_rad.len() < 3 {
            f64::INFINITY
        } else {
            (hi / lo).sqrt()
        }
    }

    /// The SCR of the analyzer set (intensity images; for `N >= 3` with an invertible `A` also
    /// the Stokes images'). 0 for an empty set.
    pub fn scr(&self, angles_rad: &[f64]) -> f64 {
        self.scr_and_gradient(angles_rad, None)
    }

    /// The information one frame at `psi_rad` adds about the Stokes difference,
    /// `w w^T / v` (its row over its noise variance): a set's is the sum of its frames', and
    /// [`Contrast::scr_of_information`] of that sum is the set's SCR.
    pub fn frame_information(&self, psi_rad: f64) -> Matrix3<f64> {
        let (w, dw) = self.instrument.row_and_derivative(psi_rad);
        let v = self.noise_var + self.instrument.shot(&w, &dw).0;
        w * w.transpose() / v
    }

    /// The SCR of a set whose frames' summed information is `a`
    /// ([`Contrast::frame_information`]): `d^T (A Sigma_b + I)^-1 A d`, the matched filter on
    /// frames whose Stokes estimate has covariance `Sigma_b + A^-1`. It rises with `a` in the
    /// Loewner order (more information never lowers it), which bounds what frames not yet
    /// chosen can add. 0 where `A Sigma_b + I` is singular.
    pub fn scr_of_information(&self, a: &Matrix3<f64>) -> f64 {
        match (a * self.sigma_b + Matrix3::identity()).try_inverse() {
            Some(inv) => self.d.dot(&(inv * a * self.d)).max(0.0),
            None => 0.0,
        }
    }

    /// The SCR and, into `gradient` (one entry per angle), its derivative per radian.
    pub fn scr_and_gradient(&self, angles_rad: &[f64], gradient: Option<&mut [f64]>) -> f64 {
        if angles_rad.is_empty() {
            return 0.0;
        }
        let rows: Vec<(Vector3<f64>, Vector3<f64>, f64, f64)> = angles_rad
            .iter()
            .map(|&p| {
                let (w, dw) = self.instrument.row_and_derivative(p);
                let (shot, dshot) = self.instrument.shot(&w, &dw);
                (w, dw, self.noise_var + shot, dshot)
            })
            .collect();
        // M = W Sigma W^T + D (N x N, symmetric positive definite as every v_i > 0), solved
        // by Cholesky: its rounding error is a few epsilon times cond(M), as the forecast's
        // own whitening (a 3x3 inverse of A Sigma + I loses more when clutter dominates).
        let n = rows.len();
        let sw: Vec<Vector3<f64>> = rows.iter().map(|(w, ..)| self.sigma_b * w).collect();
        let mut m = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..=i {
                let mut v = rows[i].0.dot(&sw[j]);
                if i == j {
                    v += rows[i].2;
                }
                m[i * n + j] = v;
                m[j * n + i] = v;
            }
        }
        let wd: Vec<f64> = rows.iter().map(|(w, ..)| w.dot(&self.d)).collect();
        let Some(r) = cholesky_solve(&mut m, n, &wd) else {
            if let Some(g) = gradient {
                g.iter_mut().for_each(|v| *v = 0.0);
            }
            return 0.0;
        };
        let scr: f64 = r.iter().zip(&wd).map(|(a, b)| a * b).sum();
        if let Some(g) = gradient {
            // dSCR/dpsi_k = 2 r_k (w'_k . d) - 2 r_k w'_k^T Sigma W^T r - r_k^2 v'_k.
            let swr: Vector3<f64> = sw
                .iter()
                .zip(&r)
                .fold(Vector3::zeros(), |acc, (v, rk)| acc + v * *rk);
            for (k, (gk, (_, dw, _, dv))) in g.iter_mut().zip(&rows).enumerate() {
                *gk = 2.0 * r[k] * (dw.dot(&self.d) - dw.dot(&swr)) - r[k] * r[k] * dv;
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

/// Solves `M x = b` for a symmetric positive definite `n x n` `M` (row-major, overwritten by
/// its Cholesky factor); `None` when `M` is not positive definite.
fn cholesky_solve(m: &mut [f64], n: usize, b: &[f64]) -> Option<Vec<f64>> {
    for j in 0..n {
        let mut diag = m[j * n + j];
        for k in 0..j {
            diag -= m[j * n + k] * m[j * n + k];
        }
        if diag.is_nan() || diag <= 0.0 {
            return None;
        }
        let l = diag.sqrt();
        m[j * n + j] = l;
        for i in j + 1..n {
            let mut v = m[i * n + j];
            for k in 0..j {
                v -= m[i * n + k] * m[j * n + k];
            }
            m[i * n + j] = v / l;
        }
    }
    let mut y = b.to_vec();
    for i in 0..n {
        for k in 0..i {
            y[i] -= m[i * n + k] * y[k];
        }
        y[i] /= m[i * n + i];
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            y[i] -= m[k * n + i] * y[k];
        }
        y[i] /= m[i * n + i];
    }
    Some(y)
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

    /// A real instrument: a leaky analyzer with an offset, a diattenuating fore-optics and
    /// shot noise that follows the transmitted light.
    fn real(noise_var: f64) -> Contrast {
        let base = example(noise_var);
        let instrument = Instrument {
            analyzer: AnalyzerModel {
                k1: 0.85,
                k2: 0.02,
                offset_rad: 0.03,
            },
            fore_optics: Matrix3::new(1.0, 0.1, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0, 0.99),
            shot_var_per_radiance: 0.4,
            shot_source: Vector3::new(5.0, 1.0, -0.5),
        };
        Contrast::with_instrument(base.d, base.sigma_b, noise_var, instrument).expect("valid")
    }

    /// With angle-dependent noise the 3x3 form equals the definition
    /// `(Wd)^T (W Sigma W^T + D)^-1 (W d)` (N x N solve, `D = diag(v(psi_i))`) to rounding,
    /// and the analytic gradient matches central differences (as above).
    #[test]
    fn real_instrument_definition_and_gradient() {
        let c = real(0.3);
        for n in 1..=5 {
            let angles: Vec<f64> = (0..n).map(|i| 0.21 + 0.67 * i as f64).collect();
            let w = nalgebra::DMatrix::from_fn(n, 3, |i, j| c.row(angles[i])[j]);
            let s = nalgebra::DMatrix::from_fn(3, 3, |i, j| c.sigma_b[(i, j)]);
            let d = nalgebra::DMatrix::from_diagonal(&nalgebra::DVector::from_fn(n, |i, _| {
                c.frame_noise_var(angles[i])
            }));
            let m = &w * s * w.transpose() + d;
            let wd = &w * nalgebra::DVector::from_column_slice(c.d.as_slice());
            let direct = wd.dot(&(m.try_inverse().expect("pd") * &wd));
            let fast = c.scr(&angles);
            assert!(
                (fast - direct).abs() <= 1e-12 * direct,
                "n={n}: {fast} vs {direct}"
            );
        }
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
