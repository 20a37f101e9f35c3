//! A seeded Monte Carlo check of the DoLP and AoP statistics at the Stokes level (MODEL.md
//! section 7, "Monte Carlo validation"), and the small generator it and other modules use.

use super::dolp_aop::{check_stokes_inputs, fold_aop};
use crate::error::ModelError;
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::PI;

/// Largest number of Monte Carlo samples accepted by [`monte_carlo_dolp_aop`].
pub const MAX_MC_SAMPLES: usize = 50_000_000;

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
    /// Standard error of `dolp_mean`.
    pub dolp_mean_se: f64,
    /// Standard error of `dolp_std` (from the sample fourth moment).
    pub dolp_std_se: f64,
    /// Circular mean direction of `2 AoP`, halved, in `(-pi/2, pi/2]`.
    pub aop_mean_rad: f64,
    /// Sample mean of the AoP error about the AoP of the mean Stokes vector (0 when `p = 0`),
    /// each error wrapped into `(-pi/2, pi/2]` (comparable with
    /// [`super::dolp_aop::PolarizationStats::aop_bias_rad`]).
    pub aop_bias_rad: f64,
    /// Root-mean-square of that wrapped AoP error: the AoP's standard deviation about the AoP of
    /// the mean Stokes vector (comparable with
    /// [`super::dolp_aop::PolarizationStats::aop_std_rad`]; `pi/sqrt(12)` for a uniform AoP).
    pub aop_std_rad: f64,
    /// Standard error of `aop_std_rad` (from the sample variance of the squared errors).
    pub aop_std_se_rad: f64,
    /// Circular standard deviation `sqrt(-2 ln R) / 2` of the AoP, `R` the mean resultant length
    /// of `2 AoP` (Mardia and Jupp 2000, Sec. 2.3.4); grows without bound as the AoP becomes
    /// uniform (reported with `R` floored at 1e-300).
    pub aop_circular_std_rad: f64,
    /// Draws used for the DoLP (`S0_hat > 0`).
    pub samples_used: usize,
    /// Draws with `S0_hat <= 0` (no DoLP), left out.
    pub samples_dark: usize,
}

/// Running mean and central moments (Welford's update extended to the fourth moment; Pébay,
/// "Formulas for robust, one-pass parallel computation of covariances and arbitrary-order
/// statistical moments", Sandia SAND2008-6212, eqs. 2.1-2.3).
#[derive(Default)]
struct Running {
    n: usize,
    mean: f64,
    m2: f64,
    m3: f64,
    m4: f64,
}

impl Running {
    fn push(&mut self, x: f64) {
        let n1 = self.n as f64;
        self.n += 1;
        let n = self.n as f64;
        let delta = x - self.mean;
        let delta_n = delta / n;
        let delta_n2 = delta_n * delta_n;
        let term1 = delta * delta_n * n1;
        self.mean += delta_n;
        self.m4 += term1 * delta_n2 * (n * n - 3.0 * n + 3.0) + 6.0 * delta_n2 * self.m2
            - 4.0 * delta_n * self.m3;
        self.m3 += term1 * delta_n * (n - 2.0) - 3.0 * delta_n * self.m2;
        self.m2 += term1;
    }

    fn std(&self) -> f64 {
        (self.m2 / (self.n.max(2) - 1) as f64).sqrt()
    }

    /// Standard error of the mean, `s / sqrt(n)`.
    fn mean_se(&self) -> f64 {
        self.std() / (self.n.max(1) as f64).sqrt()
    }

    /// Large-sample standard error of the standard deviation, `sqrt((mu4 - s^4) / n) / (2 s)`
    /// (the delta method on the sample variance, whose variance is `(mu4 - sigma^4) / n`).
    fn std_se(&self) -> f64 {
        let n = self.n.max(1) as f64;
        let var = self.m2 / n;
        let mu4 = self.m4 / n;
        if var > 0.0 {
            ((mu4 - var * var).max(0.0) / n).sqrt() / (2.0 * var.sqrt())
        } else {
            0.0
        }
    }
}

/// A seeded Monte Carlo check of [`super::dolp_aop::dolp_aop_stats`] at the Stokes level:
/// draws `S ~ N(mean_stokes, stokes_cov)` `n_samples` times (Cholesky factor; a positive
/// semidefinite but singular covariance is factored as `Q sqrt(max(lambda, 0))` from its
/// eigendecomposition), and returns the sample mean and standard deviation of the DoLP (draws
/// with `S0_hat > 0`), the mean and root-mean-square of the AoP error about the AoP of
/// `mean_stokes` wrapped into `(-pi/2, pi/2]`, and circular statistics of the AoP (on `2 AoP`, mapped back). SplitMix64 and
/// Box-Muller; the same `seed` gives the same answer.
///
/// Errors as [`super::dolp_aop::dolp_aop_stats`], and `n_samples` outside
/// `[2, MAX_MC_SAMPLES]`.
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
    let phase_true = if mean_stokes[1] != 0.0 || mean_stokes[2] != 0.0 {
        mean_stokes[2].atan2(mean_stokes[1])
    } else {
        0.0
    };
    let (mut dolp, mut aop_err, mut aop_sq) =
        (Running::default(), Running::default(), Running::default());
    let (mut sum_c, mut sum_s) = (0.0, 0.0);
    for _ in 0..n_samples {
        let z = Vector3::new(normal(), normal(), normal());
        let s = mean_stokes + factor * z;
        if s[1] != 0.0 || s[2] != 0.0 {
            let phi = s[2].atan2(s[1]);
            sum_c += phi.cos();
            sum_s += phi.sin();
            let e = 0.5 * fold_aop_phase(phi - phase_true);
            aop_err.push(e);
            aop_sq.push(e * e);
        }
        if s[0] > 0.0 {
            dolp.push(s[1].hypot(s[2]) / s[0]);
        }
    }
    if dolp.n < 2 || aop_err.n < 2 {
        return Err(ModelError::Invalid {
            field: "S0",
            reason: format!(
                "only {} of {n_samples} draws have S0 > 0 and {} a defined AoP: the covariance \
                 is too large for the mean",
                dolp.n, aop_err.n
            ),
        });
    }
    let n_ph = aop_err.n as f64;
    let (c_bar, s_bar) = (sum_c / n_ph, sum_s / n_ph);
    let r = c_bar.hypot(s_bar);
    let phi_mean = s_bar.atan2(c_bar);
    let aop_rms = aop_sq.mean.max(0.0).sqrt();
    Ok(MonteCarloPolarization {
        dolp_mean: dolp.mean,
        dolp_std: dolp.std(),
        dolp_mean_se: dolp.mean_se(),
        dolp_std_se: dolp.std_se(),
        aop_mean_rad: fold_aop(0.5 * phi_mean),
        aop_bias_rad: aop_err.mean,
        aop_std_rad: aop_rms,
        aop_std_se_rad: aop_sq.mean_se() / (2.0 * aop_rms.max(f64::MIN_POSITIVE)),
        aop_circular_std_rad: 0.5 * (-2.0 * r.max(1e-300).ln()).sqrt(),
        samples_used: dolp.n,
        samples_dark: n_samples - dolp.n,
    })
}

/// Wraps a phase difference into `(-pi, pi]`.
fn fold_aop_phase(d: f64) -> f64 {
    2.0 * fold_aop(0.5 * d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::approx::rice_moments;

    /// The Monte Carlo is reproducible for a seed, differs across seeds, and handles a
    /// PSD-but-singular covariance (S0 noise-free) by the eigen factor: with `S = (10, 5, 0)`,
    /// `Sigma = diag(0, 1, 1)` the DoLP is `p_hat/10`, `p_hat` Rician of SNR 5, whose mean
    /// `E[p_hat]/10` = 0.5102 and std `sqrt(Var p_hat)/10` are closed forms; 20k draws agree
    /// within 4 of the Monte Carlo's own standard errors (a chance failure is about 6e-5 each).
    #[test]
    fn monte_carlo_is_seeded_and_handles_singular_cov() {
        let mu = Vector3::new(1000.0, 100.0, 50.0);
        let cov = Matrix3::new(100.0, 10.0, 0.0, 10.0, 200.0, 0.0, 0.0, 0.0, 200.0);
        let a = monte_carlo_dolp_aop(&mu, &cov, 1000, 5).unwrap();
        let b = monte_carlo_dolp_aop(&mu, &cov, 1000, 5).unwrap();
        let c = monte_carlo_dolp_aop(&mu, &cov, 1000, 6).unwrap();
        assert_eq!(a, b);
        assert_ne!(a.dolp_mean, c.dolp_mean);
        let singular = Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 1.0));
        let s = monte_carlo_dolp_aop(&Vector3::new(10.0, 5.0, 0.0), &singular, 20_000, 3).unwrap();
        assert_eq!(s.samples_dark, 0);
        let (m1, var_p, _) = rice_moments(5.0, 1.0);
        assert!((s.dolp_mean - m1 / 10.0).abs() < 4.0 * s.dolp_mean_se);
        assert!((s.dolp_std - var_p.sqrt() / 10.0).abs() < 4.0 * s.dolp_std_se);
    }

    /// The standard errors from the running fourth moment: for a Gaussian DoLP (high SNR,
    /// noise-free S0, so `DoLP = |q| / S0` is nearly normal) the std's standard error is
    /// `s / sqrt(2 n)` within 10 % (the fourth-moment estimate's own scatter at n = 1e5 is
    /// ~2 %), and the AoP of an unpolarised state, uniform, has kurtosis 9/5, so its std's
    /// standard error is `s sqrt(0.8 / (4 n))` within 10 %.
    #[test]
    fn standard_errors_follow_the_fourth_moment() {
        let n = 100_000;
        let cov = Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 1.0));
        let g = monte_carlo_dolp_aop(&Vector3::new(1000.0, 300.0, 400.0), &cov, n, 9).unwrap();
        let expect = g.dolp_std / (2.0 * n as f64).sqrt();
        assert!((g.dolp_std_se / expect - 1.0).abs() < 0.1, "{g:?}");
        assert!((g.dolp_mean_se - g.dolp_std / (n as f64).sqrt()).abs() < 1e-15);
        let u = monte_carlo_dolp_aop(&Vector3::new(1000.0, 0.0, 0.0), &cov, n, 9).unwrap();
        let expect = u.aop_std_rad * (0.8 / (4.0 * n as f64)).sqrt();
        assert!((u.aop_std_se_rad / expect - 1.0).abs() < 0.1, "{u:?}");
    }
}
