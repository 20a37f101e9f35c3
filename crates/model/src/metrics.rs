//! Detection metrics (MODEL.md section 8, a reconstruction of Meng (2012)'s Ch. 4 after FASSP):
//! signal-to-clutter ratio, and analytic ROC curves of the linear matched filter, the RX
//! (quadratic) detector and the DoLP threshold detector, for two classes (target, background)
//! described by their means and covariances after full propagation, in intensity or Stokes space.
//!
//! * Matched filter `w = Sigma_b^-1 (mu_t - mu_b)`: the statistic `w^T x` is Gaussian under both
//!   hypotheses, so `Pfa = Q((eta - m_b) / s_b)` and `Pd = Q((eta - m_t) / s_t)`; with equal
//!   covariances `Pd = Q(Q^-1(Pfa) - sqrt(SCR))`.
//! * RX `T = (x - mu_b)^T Sigma_b^-1 (x - mu_b)`: central chi-square with `n` degrees of freedom
//!   under the background; under the target a quadratic form in Gaussians
//!   `T = sum_j l_j (z_j + d_j)^2` (a generalised chi-square; non-central with non-centrality
//!   SCR when the covariances are equal). Its distribution is computed with Ruben's (1962)
//!   mixture of central chi-squares, whose truncation error is known exactly (the missing
//!   mixture weight) and reported.
//! * DoLP threshold: the DoLP estimates of each class as Gaussians with the moments of
//!   [`crate::stats`] (an approximation, good where those moments are in the Taylor regime).
//!
//! Covariances must be symmetric and positive semi-definite; near-singular ones are regularised
//! (eigenvalues floored at `1e-12` of the largest) and the answer says so with the condition
//! number. Subpixel targets use the fill fraction ([`ClassStats::mixed`]).

use crate::error::ModelError;
use nalgebra::{DMatrix, DVector, SymmetricEigen};
use statrs::distribution::{ChiSquared, ContinuousCDF, Normal};
use statrs::function::erf::erfc;
use statrs::function::gamma::gamma_lr;

/// The relative floor of eigenvalues in a regularised covariance.
pub const EIGEN_FLOOR: f64 = 1e-12;

/// Upper tail of the standard normal, `Q(x) = P(Z > x)`.
pub fn q(x: f64) -> f64 {
    0.5 * erfc(x / std::f64::consts::SQRT_2)
}

/// Inverse of [`q`]: the `x` with `Q(x) = p`, for `p` in `(0, 1)`.
pub fn q_inv(p: f64) -> f64 {
    // Phi^-1(p) = -Q^-1(p); the lower tail keeps precision for small p.
    match Normal::standard().inverse_cdf(p) {
        x if x.is_finite() => -x,
        _ if p < 0.5 => f64::INFINITY,
        _ => f64::NEG_INFINITY,
    }
}

/// Mean and covariance of one class.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassStats {
    /// Mean vector.
    pub mean: DVector<f64>,
    /// Covariance (symmetric, positive semi-definite).
    pub cov: DMatrix<f64>,
}

impl ClassStats {
    /// A class from its mean and covariance; errors name `field` (`target_cov`, ...) when the
    /// shapes disagree, a value is not finite, or the covariance is not symmetric positive
    /// semi-definite.
    pub fn new(
        field: &'static str,
        mean: DVector<f64>,
        cov: DMatrix<f64>,
    ) -> Result<Self, ModelError> {
        let n = mean.len();
        if n == 0 || cov.nrows() != n || cov.ncols() != n {
            return Err(ModelError::Invalid {
                field,
                reason: format!(
                    "a covariance of {}x{} for a mean of {n} values: allowed {n}x{n}, n > 0",
                    cov.nrows(),
                    cov.ncols()
                ),
            });
        }
        if mean.iter().chain(cov.iter()).any(|v| !v.is_finite()) {
            return Err(ModelError::Invalid {
                field,
                reason: "a value is not finite".into(),
            });
        }
        let scale = cov.amax().max(f64::MIN_POSITIVE);
        if (&cov - cov.transpose()).amax() > 1e-9 * scale {
            return Err(ModelError::Invalid {
                field,
                reason: "the covariance is not symmetric".into(),
            });
        }
        let eig = SymmetricEigen::new(cov.clone());
        let min = eig.eigenvalues.min();
        if min < -1e-9 * scale {
            return Err(ModelError::Invalid {
                field,
                reason: format!(
                    "the covariance is not positive semi-definite (smallest eigenvalue {min:.3e})"
                ),
            });
        }
        Ok(ClassStats { mean, cov })
    }

    /// The class of a pixel that a target fills by the fraction `f` in `[0, 1]` over background
    /// `b` (FASSP): mean `f mu_t + (1 - f) mu_b`, covariance `f^2 Sigma_t + (1 - f)^2 Sigma_b`
    /// (target and background radiance independent).
    pub fn mixed(&self, b: &ClassStats, f: f64) -> Result<ClassStats, ModelError> {
        ModelError::check_range("fill_fraction", f, 0.0, 1.0, "[0, 1]")?;
        if self.mean.len() != b.mean.len() {
            return Err(ModelError::Invalid {
                field: "fill_fraction",
                reason: "target and background have different dimensions".into(),
            });
        }
        Ok(ClassStats {
            mean: &self.mean * f + &b.mean * (1.0 - f),
            cov: &self.cov * (f * f) + &b.cov * ((1.0 - f) * (1.0 - f)),
        })
    }
}

/// A symmetric positive semi-definite matrix's inverse and inverse square root, regularised.
struct Whitening {
    inverse: DMatrix<f64>,
    inverse_sqrt: DMatrix<f64>,
    condition_number: f64,
    regularised: bool,
}

fn whitening(cov: &DMatrix<f64>) -> Whitening {
    let eig = SymmetricEigen::new(cov.clone());
    let max = eig.eigenvalues.max().max(f64::MIN_POSITIVE);
    let floor = EIGEN_FLOOR * max;
    let min = eig.eigenvalues.min();
    let regularised = min < floor;
    let l: Vec<f64> = eig.eigenvalues.iter().map(|&v| v.max(floor)).collect();
    let u = &eig.eigenvectors;
    let diag = |f: &dyn Fn(f64) -> f64| {
        DMatrix::from_diagonal(&DVector::from_iterator(l.len(), l.iter().map(|&v| f(v))))
    };
    Whitening {
        inverse: u * diag(&|v| 1.0 / v) * u.transpose(),
        inverse_sqrt: u * diag(&|v| 1.0 / v.sqrt()) * u.transpose(),
        condition_number: max / min.max(floor),
        regularised,
    }
}

/// A ROC curve and the figures around it.
#[derive(Debug, Clone, PartialEq)]
pub struct Roc {
    /// The signal-to-clutter ratio `(mu_t - mu_b)^T Sigma_b^-1 (mu_t - mu_b)`.
    pub scr: f64,
    /// The false-alarm rate asked for.
    pub pfa: f64,
    /// Detection probability at `pfa`.
    pub pd: f64,
    /// `[pfa, pd]` from `1e-6` to `1`, log-spaced.
    pub curve: Vec<[f64; 2]>,
    /// Condition number of the background covariance.
    pub condition_number: f64,
    /// Upper bound of the numerical error in any `pd` (series truncation), 0 when exact.
    pub pd_error: f64,
    /// What the caller should know (regularisation, no contrast, approximations).
    pub warnings: Vec<String>,
}

fn check_pfa(pfa: f64) -> Result<(), ModelError> {
    if pfa.is_finite() && pfa > 0.0 && pfa < 1.0 {
        Ok(())
    } else {
        Err(ModelError::OutOfRange {
            field: "pfa",
            value: pfa,
            allowed: "(0, 1)",
        })
    }
}

fn pfa_grid() -> Vec<f64> {
    (0..=60)
        .map(|k| 10f64.powf(-6.0 + 0.1 * k as f64))
        .collect()
}

fn check_pair(t: &ClassStats, b: &ClassStats) -> Result<(), ModelError> {
    if t.mean.len() != b.mean.len() {
        return Err(ModelError::Invalid {
            field: "target_mean",
            reason: format!(
                "{} values against the background's {}: allowed the same dimension",
                t.mean.len(),
                b.mean.len()
            ),
        });
    }
    Ok(())
}

fn regularisation_warning(w: &Whitening, warnings: &mut Vec<String>) {
    if w.regularised {
        warnings.push(format!(
            "background covariance near-singular (condition number {:.3e}): eigenvalues floored at {EIGEN_FLOOR:e} of the largest",
            w.condition_number
        ));
    }
}

/// The matched filter `Sigma_b^-1 d` by a Cholesky solve (backward stable: its relative
/// error is a few epsilon times the condition number; an eigen-whitening inverse loses up to
/// 1e-8 relative at a condition of 5e3, when the clutter dominates the noise). A covariance
/// whose smallest eigenvalues were floored (`wh` regularised) takes the regularised inverse.
/// The one solve of [`scr`] and [`matched_filter`].
fn clutter_filter(cov: &DMatrix<f64>, wh: &Whitening, d: &DVector<f64>) -> DVector<f64> {
    match (wh.regularised, cov.clone().cholesky()) {
        (false, Some(ch)) => ch.solve(d),
        _ => &wh.inverse * d,
    }
}

/// The signal-to-clutter ratio of `t` against background `b` and the background's condition
/// number (regularised when near-singular).
pub fn scr(t: &ClassStats, b: &ClassStats) -> Result<(f64, f64), ModelError> {
    check_pair(t, b)?;
    let w = whitening(&b.cov);
    let d = &t.mean - &b.mean;
    let filter = clutter_filter(&b.cov, &w, &d);
    Ok((filter.dot(&d).max(0.0), w.condition_number))
}

/// The linear matched filter's ROC (MODEL.md section 8).
pub fn matched_filter(t: &ClassStats, b: &ClassStats, pfa: f64) -> Result<Roc, ModelError> {
    check_pair(t, b)?;
    check_pfa(pfa)?;
    let wh = whitening(&b.cov);
    let mut warnings = Vec::new();
    regularisation_warning(&wh, &mut warnings);
    let d = &t.mean - &b.mean;
    let w = clutter_filter(&b.cov, &wh, &d);
    let scr = w.dot(&d).max(0.0);
    let sb = (w.transpose() * &b.cov * &w)[(0, 0)].max(0.0).sqrt();
    let st = (w.transpose() * &t.cov * &w)[(0, 0)].max(0.0).sqrt();
    let pd_at = |pfa: f64| -> f64 {
        if scr == 0.0 {
            return pfa;
        }
        // (With s_b = 0 the background statistic has no spread and the threshold sits on it.)
        // Threshold on w^T (x - mu_b): eta = s_b Q^-1(pfa); the target's mean there is SCR.
        let eta = sb * q_inv(pfa);
        if st > 0.0 {
            q((eta - scr) / st)
        } else if scr > eta {
            1.0
        } else {
            0.0
        }
    };
    if scr == 0.0 {
        warnings.push("no contrast between the classes: Pd = Pfa".into());
    } else if sb == 0.0 {
        warnings.push(
            "the filtered background has no spread: the threshold sits on its mean at any Pfa"
                .into(),
        );
    }
    Ok(Roc {
        scr,
        pfa,
        pd: pd_at(pfa),
        curve: pfa_grid().into_iter().map(|p| [p, pd_at(p)]).collect(),
        condition_number: wh.condition_number,
        pd_error: 0.0,
        warnings,
    })
}

/// `P(Q <= x)` for `Q = sum_j l_j (z_j + d_j)^2` with `l_j > 0` and `z_j` standard normal, and
/// the truncation error bound, by Ruben's (1962) expansion in central chi-square distributions
/// (the recurrence of Farebrother, Applied Statistics algorithm AS 204, 1984, with
/// `beta = 0.90625 min l`): `P = sum_k a_k P(chi2_{n+2k} <= x / beta)`, `a_k >= 0`,
/// `sum a_k = 1`, so the error after truncation is at most `1 - sum a_k`.
///
/// Far in the lower tail (the case of a well-separated target, where the series' first weight
/// `exp(-sum d^2 / 2)` underflows and thousands of terms would be needed) the Chernoff bound
/// [`quadratic_form_lower_tail_bound`] answers instead when it is below 1e-12: the CDF is then
/// reported as 0 with that bound as its error.
pub fn quadratic_form_cdf(lambdas: &[f64], deltas_sq: &[f64], x: f64) -> (f64, f64) {
    let n = lambdas.len();
    if n == 0 || x <= 0.0 {
        return (0.0, 0.0);
    }
    let mean: f64 = lambdas
        .iter()
        .zip(deltas_sq)
        .map(|(&l, &d2)| l * (1.0 + d2))
        .sum();
    if mean > x {
        let bound = quadratic_form_lower_tail_bound(lambdas, deltas_sq, x);
        if bound < 1e-12 {
            return (0.0, bound);
        }
    }
    quadratic_form_cdf_series(lambdas, deltas_sq, x)
}

/// Ruben's series of [`quadratic_form_cdf`] alone (no tail shortcut).
fn quadratic_form_cdf_series(lambdas: &[f64], deltas_sq: &[f64], x: f64) -> (f64, f64) {
    let n = lambdas.len();
    if n == 0 || x <= 0.0 {
        return (0.0, 0.0);
    }
    let lmin = lambdas.iter().copied().fold(f64::INFINITY, f64::min);
    let beta = 0.90625 * lmin;
    let ratios: Vec<f64> = lambdas.iter().map(|&l| 1.0 - beta / l).collect();
    let log_a0 = -0.5 * deltas_sq.iter().sum::<f64>()
        + 0.5 * lambdas.iter().map(|&l| (beta / l).ln()).sum::<f64>();
    let mut a = vec![log_a0.exp()];
    let mut g: Vec<f64> = vec![0.0];
    let mut sum_a = a[0];
    let mut cdf = a[0] * gamma_lr(0.5 * n as f64, 0.5 * x / beta);
    const MAX_TERMS: usize = 4000;
    const TARGET: f64 = 1e-12;
    for k in 1..MAX_TERMS {
        // g_k = 1/2 sum (1 - beta/l)^k + k beta/2 sum d^2/l (1 - beta/l)^(k-1)
        let gk: f64 = ratios
            .iter()
            .zip(lambdas)
            .zip(deltas_sq)
            .map(|((&r, &l), &d2)| {
                0.5 * r.powi(k as i32) + 0.5 * k as f64 * beta * d2 / l * r.powi(k as i32 - 1)
            })
            .sum();
        g.push(gk);
        let ak = (0..k).map(|r| g[k - r] * a[r]).sum::<f64>() / k as f64;
        a.push(ak);
        sum_a += ak;
        cdf += ak * gamma_lr(0.5 * (n + 2 * k) as f64, 0.5 * x / beta);
        if 1.0 - sum_a < TARGET {
            break;
        }
    }
    let err = (1.0 - sum_a).max(0.0);
    (cdf.clamp(0.0, 1.0), err)
}

/// The Chernoff bound on `P(Q <= x)` below the mean of `Q = sum_j l_j (z_j + d_j)^2`:
/// `P(Q <= x) <= min_{t > 0} exp(t x) E[exp(-t Q)]`, with
/// `ln E[exp(-t Q)] = sum_j [-ln(1 + 2 t l_j) / 2 - t l_j d_j^2 / (1 + 2 t l_j)]`. The exponent
/// is convex in `t`, so its minimum is found by bisection on its derivative. Returns 1 when
/// `x` is not below the mean (no bound).
pub fn quadratic_form_lower_tail_bound(lambdas: &[f64], deltas_sq: &[f64], x: f64) -> f64 {
    let slope = |t: f64| -> f64 {
        x - lambdas
            .iter()
            .zip(deltas_sq)
            .map(|(&l, &d2)| {
                let u = 1.0 + 2.0 * t * l;
                l / u + l * d2 / (u * u)
            })
            .sum::<f64>()
    };
    let exponent = |t: f64| -> f64 {
        t * x
            + lambdas
                .iter()
                .zip(deltas_sq)
                .map(|(&l, &d2)| {
                    let u = 1.0 + 2.0 * t * l;
                    -0.5 * u.ln() - t * l * d2 / u
                })
                .sum::<f64>()
    };
    if lambdas.is_empty() || slope(0.0) >= 0.0 {
        return 1.0;
    }
    let (mut lo, mut hi) = (0.0, 1.0 / x.max(f64::MIN_POSITIVE));
    while slope(hi) < 0.0 && hi < 1e300 {
        lo = hi;
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if slope(mid) < 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    exponent(0.5 * (lo + hi)).exp().min(1.0)
}

/// The RX (quadratic) detector's ROC: central chi-square threshold under the background,
/// generalised chi-square under the target (MODEL.md section 8).
pub fn rx(t: &ClassStats, b: &ClassStats, pfa: f64) -> Result<Roc, ModelError> {
    check_pair(t, b)?;
    check_pfa(pfa)?;
    let n = b.mean.len();
    let wh = whitening(&b.cov);
    let mut warnings = Vec::new();
    regularisation_warning(&wh, &mut warnings);
    let d = &t.mean - &b.mean;
    let scr = (d.transpose() * &wh.inverse * &d)[(0, 0)].max(0.0);
    // Whitened: y = Sigma_b^-1/2 (x - mu_b) ~ N(Sigma_b^-1/2 d, A) under the target.
    let a = &wh.inverse_sqrt * &t.cov * &wh.inverse_sqrt;
    let a = (&a + a.transpose()) * 0.5;
    let eig = SymmetricEigen::new(a);
    let lmax = eig.eigenvalues.max().max(f64::MIN_POSITIVE);
    if eig.eigenvalues.min() < EIGEN_FLOOR * lmax {
        warnings.push(
            "target covariance near-singular in the background's whitened frame: eigenvalues floored"
                .into(),
        );
    }
    let lambdas: Vec<f64> = eig
        .eigenvalues
        .iter()
        .map(|&l| l.max(EIGEN_FLOOR * lmax))
        .collect();
    let shift = eig.eigenvectors.transpose() * (&wh.inverse_sqrt * &d);
    let deltas_sq: Vec<f64> = shift
        .iter()
        .zip(&lambdas)
        .map(|(&s, &l)| s * s / l)
        .collect();
    let chi = ChiSquared::new(n as f64).map_err(|e| ModelError::Invalid {
        field: "background_mean",
        reason: e.to_string(),
    })?;
    let mut pd_error: f64 = 0.0;
    let mut pd_at = |pfa: f64| -> f64 {
        let eta = chi.inverse_cdf(1.0 - pfa);
        let (cdf, err) = quadratic_form_cdf(&lambdas, &deltas_sq, eta);
        pd_error = pd_error.max(err);
        1.0 - cdf
    };
    if scr == 0.0 && (t.cov.clone() - b.cov.clone()).amax() == 0.0 {
        warnings.push("no contrast between the classes: Pd = Pfa".into());
    }
    let pd = pd_at(pfa);
    let curve = pfa_grid().into_iter().map(|p| [p, pd_at(p)]).collect();
    Ok(Roc {
        scr,
        pfa,
        pd,
        curve,
        condition_number: wh.condition_number,
        pd_error,
        warnings,
    })
}

/// The DoLP threshold detector's ROC, from each class's DoLP mean and standard deviation
/// (treated as Gaussian: an approximation that holds where [`crate::stats`] answers in the
/// Taylor regime). The threshold is on the side of the target: above the background when the
/// target's DoLP is higher, below when it is lower.
pub fn dolp_threshold(
    target: (f64, f64),
    background: (f64, f64),
    pfa: f64,
) -> Result<Roc, ModelError> {
    check_pfa(pfa)?;
    let (mt, st) = target;
    let (mb, sb) = background;
    for (field, v) in [("target_dolp_mean", mt), ("background_dolp_mean", mb)] {
        ModelError::check_range(field, v, 0.0, 1.5, "[0, 1.5]")?;
    }
    for (field, v) in [("target_dolp_std", st), ("background_dolp_std", sb)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(ModelError::OutOfRange {
                field,
                value: v,
                allowed: "> 0 and finite",
            });
        }
    }
    let sign = if mt >= mb { 1.0 } else { -1.0 };
    let pd_at = |pfa: f64| q((sb * q_inv(pfa) - sign * (mt - mb)) / st);
    let scr = (mt - mb).powi(2) / (sb * sb);
    let mut warnings =
        vec!["DoLP estimates treated as Gaussian (valid where the DoLP moments are in the Taylor regime)".to_string()];
    if mt == mb {
        warnings.push("no DoLP contrast between the classes".into());
    }
    Ok(Roc {
        scr,
        pfa,
        pd: pd_at(pfa),
        curve: pfa_grid().into_iter().map(|p| [p, pd_at(p)]).collect(),
        condition_number: 1.0,
        pd_error: 0.0,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Seeded normals for the Monte Carlo checks (the crate's SplitMix64 and Box-Muller).
    struct Normals(crate::stats::SplitMix64);

    impl Normals {
        fn new(seed: u64) -> Self {
            Normals(crate::stats::SplitMix64(seed))
        }
        fn normal(&mut self) -> f64 {
            self.0.normal_pair().0
        }
        fn sample(&mut self, c: &ClassStats) -> DVector<f64> {
            let l = c.cov.clone().cholesky().unwrap().l();
            let z = DVector::from_fn(c.mean.len(), |_, _| self.normal());
            &c.mean + l * z
        }
    }

    fn class(mean: &[f64], cov: &[f64]) -> ClassStats {
        let n = mean.len();
        ClassStats::new(
            "test",
            DVector::from_column_slice(mean),
            DMatrix::from_row_slice(n, n, cov),
        )
        .unwrap()
    }

    /// Q and its inverse: Q(1.6448536269514722) = 0.05 to 1e-10 relative (statrs' erfc is good
    /// to about 4e-11 there) and Q(0) = 0.5; the inverse round-trips from 1e-12 to 0.999 to 1e-9
    /// relative.
    #[test]
    fn normal_tail_and_inverse() {
        assert!(
            (q(1.644_853_626_951_472_2) / 0.05 - 1.0).abs() < 1e-10,
            "{:e}",
            q(1.644_853_626_951_472_2) - 0.05
        );
        assert!((q(0.0) - 0.5).abs() < 1e-15);
        for p in [1e-12, 1e-6, 1e-3, 0.1, 0.5, 0.9, 0.999] {
            assert!((q(q_inv(p)) / p - 1.0).abs() < 1e-9, "{p}");
        }
    }

    /// Ruben's series: with all l = 1 and d = 0 it is the central chi-square CDF (statrs) to
    /// 1e-10; with l = 1 it matches the Poisson mixture of the non-central chi-square, written
    /// independently, to 1e-10; its reported error is below 1e-11 there.
    #[test]
    fn ruben_matches_central_and_noncentral_chi_square() {
        for x in [0.5, 3.0, 7.8, 20.0] {
            let (p, e) = quadratic_form_cdf(&[1.0; 3], &[0.0; 3], x);
            let exact = ChiSquared::new(3.0).unwrap().cdf(x);
            assert!(
                (p - exact).abs() < 1e-10 && e < 1e-11,
                "{x}: {p} {exact} {e}"
            );
            let (d2, n) = ([2.0, 0.5, 1.5], 3.0);
            let lam: f64 = d2.iter().sum();
            let (p, _) = quadratic_form_cdf(&[1.0; 3], &d2, x);
            let mut poisson = (-lam / 2.0).exp();
            let mut mix = 0.0;
            for k in 0..200 {
                mix += poisson * gamma_lr(0.5 * (n + 2.0 * k as f64), 0.5 * x);
                poisson *= lam / 2.0 / (k as f64 + 1.0);
            }
            assert!((p - mix).abs() < 1e-10, "{x}: {p} {mix}");
        }
    }

    /// The Chernoff lower-tail bound holds: it is above Ruben's CDF wherever both apply
    /// (CDFs from 4e-2 down to 1e-26, bounds 3 to 7 times above them). For a well-separated target (SCR 1e5, where
    /// the series' first weight underflows) the CDF is 0 with an error under 1e-12, and RX's Pd
    /// is 1 with `pd_error` under 1e-12 (without the bound, the error would be 1).
    #[test]
    fn chernoff_bound_covers_far_lower_tail() {
        let lambdas = [0.3, 1.0, 4.0];
        for shift in [1.0f64, 2.0, 3.0, 4.0, 5.0] {
            let d2: Vec<f64> = [0.5, 1.0, 2.0]
                .iter()
                .map(|d: &f64| (d * shift).powi(2))
                .collect();
            let x = 2.0;
            let bound = quadratic_form_lower_tail_bound(&lambdas, &d2, x);
            // Ruben's series directly (the bound would short-circuit quadratic_form_cdf).
            let (cdf, err) = quadratic_form_cdf_series(&lambdas, &d2, x);
            eprintln!("shift {shift}: cdf {cdf:.3e}, Chernoff bound {bound:.3e}");
            assert!(err < 1e-12, "shift {shift}: series error {err}");
            assert!(
                cdf <= bound * (1.0 + 1e-9),
                "shift {shift}: cdf {cdf} > bound {bound}"
            );
        }
        let d2 = [1e5 / 3.0; 3];
        let (cdf, err) = quadratic_form_cdf(&[1.0, 1.0, 1.0], &d2, 16.27);
        assert_eq!(cdf, 0.0);
        assert!(err < 1e-12, "{err}");
        let cov = DMatrix::identity(3, 3);
        let b = ClassStats::new("background_cov", DVector::zeros(3), cov.clone()).unwrap();
        let t = ClassStats::new(
            "target_cov",
            DVector::from_element(3, (1e5f64 / 3.0).sqrt()),
            cov,
        )
        .unwrap();
        let roc = rx(&t, &b, 1e-3).unwrap();
        assert!((roc.scr - 1e5).abs() < 1e-6 * 1e5);
        assert_eq!(roc.pd, 1.0);
        assert!(roc.pd_error < 1e-12, "{}", roc.pd_error);
    }

    /// A generalised chi-square (l = 0.3, 1, 4; shifts 0.5, 1, 2) against 2e5 Monte Carlo
    /// draws: within 4 binomial standard errors (<= 4.5e-3) at three thresholds.
    #[test]
    fn ruben_matches_monte_carlo_for_unequal_weights() {
        let (l, d) = ([0.3, 1.0, 4.0], [0.5, 1.0, 2.0]);
        let d2: Vec<f64> = d.iter().map(|v| v * v).collect();
        let mut g = Normals::new(11);
        let n = 200_000;
        let draws: Vec<f64> = (0..n)
            .map(|_| (0..3).map(|j| l[j] * (g.normal() + d[j]).powi(2)).sum())
            .collect();
        for x in [2.0, 10.0, 30.0] {
            let (p, e) = quadratic_form_cdf(&l, &d2, x);
            let mc = draws.iter().filter(|&&v| v <= x).count() as f64 / n as f64;
            let se = (p * (1.0 - p) / n as f64).sqrt();
            assert!((p - mc).abs() < 4.0 * se + e, "{x}: {p} {mc}");
        }
    }

    /// Equal covariances: the matched filter's Pd is Q(Q^-1(Pfa) - sqrt(SCR)) exactly (1e-12)
    /// and the RX Pd is the non-central chi-square tail with non-centrality SCR.
    #[test]
    fn equal_covariance_closed_forms() {
        let cov = [4.0, 1.0, 0.0, 1.0, 3.0, 0.5, 0.0, 0.5, 2.0];
        let b = class(&[100.0, 10.0, 5.0], &cov);
        let t = class(&[103.0, 12.0, 4.0], &cov);
        let mf = matched_filter(&t, &b, 1e-3).unwrap();
        let want = q(q_inv(1e-3) - mf.scr.sqrt());
        assert!((mf.pd - want).abs() < 1e-12, "{} {want}", mf.pd);
        let rx = rx(&t, &b, 1e-3).unwrap();
        let eta = ChiSquared::new(3.0).unwrap().inverse_cdf(1.0 - 1e-3);
        let (cdf, _) = quadratic_form_cdf(&[1.0; 3], &[rx.scr, 0.0, 0.0], eta);
        assert!(
            (rx.pd - (1.0 - cdf)).abs() < 1e-9,
            "{} {}",
            rx.pd,
            1.0 - cdf
        );
        assert!(
            mf.pd > rx.pd,
            "the matched filter knows the target's direction"
        );
        assert!((mf.scr - rx.scr).abs() < 1e-9 * mf.scr);
    }

    /// Both ROCs against Monte Carlo on 1e5 synthetic pixels per class with different
    /// covariances: the thresholds from the analytic Pfa give empirical Pfa and Pd within 4
    /// binomial standard errors of the analytic values.
    #[test]
    fn rocs_match_monte_carlo() {
        let b = class(
            &[100.0, 10.0, 5.0],
            &[4.0, 1.0, 0.0, 1.0, 3.0, 0.5, 0.0, 0.5, 2.0],
        );
        let t = class(
            &[102.0, 13.0, 4.0],
            &[9.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 5.0],
        );
        let pfa = 1e-2;
        let n = 100_000;
        let mut g = Normals::new(3);
        let xb: Vec<DVector<f64>> = (0..n).map(|_| g.sample(&b)).collect();
        let xt: Vec<DVector<f64>> = (0..n).map(|_| g.sample(&t)).collect();
        let se = |p: f64| (p * (1.0 - p) / n as f64).sqrt();
        // Matched filter.
        let mf = matched_filter(&t, &b, pfa).unwrap();
        let w = whitening(&b.cov).inverse * (&t.mean - &b.mean);
        let sb = (w.transpose() * &b.cov * &w)[(0, 0)].sqrt();
        let eta = w.dot(&b.mean) + sb * q_inv(pfa);
        let rate =
            |xs: &[DVector<f64>]| xs.iter().filter(|x| w.dot(x) > eta).count() as f64 / n as f64;
        assert!((rate(&xb) - pfa).abs() < 4.0 * se(pfa));
        assert!(
            (rate(&xt) - mf.pd).abs() < 4.0 * se(mf.pd),
            "{} {}",
            rate(&xt),
            mf.pd
        );
        // RX.
        let r = rx(&t, &b, pfa).unwrap();
        let inv = whitening(&b.cov).inverse;
        let eta = ChiSquared::new(3.0).unwrap().inverse_cdf(1.0 - pfa);
        let stat = |x: &DVector<f64>| {
            let d = x - &b.mean;
            (d.transpose() * &inv * &d)[(0, 0)]
        };
        let rate =
            |xs: &[DVector<f64>]| xs.iter().filter(|x| stat(x) > eta).count() as f64 / n as f64;
        assert!((rate(&xb) - pfa).abs() < 4.0 * se(pfa));
        assert!(
            (rate(&xt) - r.pd).abs() < 4.0 * se(r.pd) + r.pd_error,
            "{} {}",
            rate(&xt),
            r.pd
        );
    }

    /// Degenerate inputs are answered: no contrast gives Pd = Pfa and says so; a near-singular
    /// background is regularised and reports its condition number (> 1e12); a covariance that
    /// is not positive semi-definite or not symmetric is an error naming the field; a bad Pfa
    /// names `pfa`.
    #[test]
    fn degenerate_inputs() {
        let b = class(&[1.0, 2.0], &[1.0, 0.0, 0.0, 1.0]);
        let mf = matched_filter(&b, &b, 0.01).unwrap();
        assert!(
            (mf.pd - 0.01).abs() < 1e-15 && mf.warnings.iter().any(|w| w.contains("no contrast"))
        );
        let r = rx(&b, &b, 0.01).unwrap();
        assert!((r.pd - 0.01).abs() < 1e-9, "{}", r.pd);
        let singular = class(&[0.0, 0.0], &[1.0, 1.0, 1.0, 1.0]);
        let t = class(&[1.0, -1.0], &[1.0, 0.0, 0.0, 1.0]);
        let mf = matched_filter(&t, &singular, 0.01).unwrap();
        assert!(
            mf.condition_number > 1e11 && mf.warnings.iter().any(|w| w.contains("near-singular"))
        );
        // The contrast lies where the background has no clutter; the target's own noise (unit
        // variance, offset sqrt 2 along that direction) is then the only limit: Pd = Q(-sqrt 2).
        assert!(
            (mf.pd - q(-std::f64::consts::SQRT_2)).abs() < 1e-4,
            "{}",
            mf.pd
        );
        let e = ClassStats::new(
            "background_cov",
            DVector::from_column_slice(&[0.0, 0.0]),
            DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]),
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("background_cov") && e.to_string().contains("semi-definite")
        );
        let e = ClassStats::new(
            "target_cov",
            DVector::from_column_slice(&[0.0, 0.0]),
            DMatrix::from_row_slice(2, 2, &[1.0, 0.5, 0.0, 1.0]),
        )
        .unwrap_err();
        assert!(e.to_string().contains("symmetric"));
        assert!(matched_filter(&t, &b, 0.0)
            .unwrap_err()
            .to_string()
            .contains("pfa"));
    }

    /// The DoLP detector: equal spreads give Pd = Q(Q^-1(Pfa) - |dm|/s) both ways round;
    /// a fill fraction of 0 is the background, 1 the target, 0.5 halves the contrast.
    #[test]
    fn dolp_detector_and_fill_fraction() {
        let r = dolp_threshold((0.30, 0.02), (0.10, 0.02), 1e-3).unwrap();
        assert!((r.pd - q(q_inv(1e-3) - 10.0)).abs() < 1e-12);
        let r2 = dolp_threshold((0.10, 0.02), (0.30, 0.02), 1e-3).unwrap();
        assert!(
            (r.pd - r2.pd).abs() < 1e-12,
            "a lower target DoLP is detected below"
        );
        let b = class(&[1.0, 0.0], &[1.0, 0.0, 0.0, 1.0]);
        let t = class(&[3.0, 2.0], &[4.0, 0.0, 0.0, 4.0]);
        assert_eq!(t.mixed(&b, 0.0).unwrap(), b);
        assert_eq!(t.mixed(&b, 1.0).unwrap(), t);
        let half = t.mixed(&b, 0.5).unwrap();
        let (s_full, _) = scr(&t, &b).unwrap();
        let (s_half, _) = scr(&half, &b).unwrap();
        assert!(
            (s_half - s_full / 4.0).abs() < 1e-12,
            "SCR scales with the square of the fill"
        );
        assert!(t
            .mixed(&b, 1.5)
            .unwrap_err()
            .to_string()
            .contains("fill_fraction"));
    }
}
