//! The measurement row of an exposure taken while the analyzer turns (continuous rotation), and
//! the effect of an uncertain angle on a frame (timing jitter of a free-running camera).
//!
//! # The span row
//!
//! A frame integrates the transmitted intensity over its exposure. Through a real analyzer at
//! angle `psi` the intensity is `r(psi)^T S` with
//! `r(psi) = 0.5 [k1 + k2, (k1 - k2) cos 2psi, (k1 - k2) sin 2psi]`
//! ([`AnalyzerModel::row`]), so a frame whose analyzer angle follows `psi(t)` over the exposure
//! `[0, T]` measures `rbar^T S` with the time-averaged row `rbar = (1/T) int_0^T r(psi(t)) dt`.
//!
//! At constant angular velocity from `psi_a` to `psi_b` the average is closed-form: with the
//! span's centre `psi_c = (psi_a + psi_b) / 2` and width `D = psi_b - psi_a`,
//!
//! ```text
//! (1/D) int_{psi_a}^{psi_b} cos 2psi dpsi = cos 2psi_c * sin(D) / D
//! (1/D) int_{psi_a}^{psi_b} sin 2psi dpsi = sin 2psi_c * sin(D) / D
//! ```
//!
//! so the span row is the centre's row with its two polarised terms scaled by `sinc D =
//! sin(D)/D` ([`span_row`]). The polarised modulation is lost entirely over a half turn
//! (`D = pi`), and reduced by 1 % at `D = 14.0 deg`. Averaging the two end rows instead is
//! wrong for wide spans: it scales by `cos D`, whose loss `D^2 / 2` is three times the sinc's
//! `D^2 / 6`.
//!
//! When the velocity is not constant (a stage accelerating through the exposure), [`path_row`]
//! integrates `r(psi(t))` over normalised time with the model's adaptive Gauss-Kronrod rule and
//! reports its error estimate.
//!
//! # Angle jitter
//!
//! A free-running camera's exposure is placed in time from its timestamps, and the stage's
//! angle at that time from its position samples; both are uncertain, so the span's centre is
//! `psi_c + delta` with `delta ~ N(0, sigma^2)`. The frame's mean intensity `a + b cos(2 psi_c -
//! phi + 2 delta)` (`a` the unpolarised term, `b` the polarised amplitude after the sinc factor,
//! `phi` twice the AoP of `S`) then has the exact moments
//!
//! ```text
//! E[I]   = a + b cos(alpha) e^{-2 sigma^2}
//! Var[I] = b^2 [ (1 + cos(2 alpha) e^{-8 sigma^2}) / 2 - cos^2(alpha) e^{-4 sigma^2} ]
//! ```
//!
//! with `alpha = 2 psi_c - phi`, from the Gaussian characteristic function `E[e^{i k delta}] =
//! e^{-k^2 sigma^2 / 2}` ([`jittered_intensity`]). The variance adds to the frame's noise
//! variance in the Stokes covariance; to first order it is `(dI/dpsi)^2 sigma^2`.

use crate::analyzer::AnalyzerModel;
use crate::error::ModelError;
use crate::quadrature::{integrate_n, Tolerance};
use nalgebra::Vector3;

/// `sin(x) / x`, exact at and near 0 (a 4-term series below `|x| < 1e-3`, where its truncation
/// error `x^8/9!` is below 1e-29).
pub fn sinc(x: f64) -> f64 {
    if x.abs() < 1e-3 {
        let x2 = x * x;
        1.0 - x2 / 6.0 * (1.0 - x2 / 20.0 * (1.0 - x2 / 42.0))
    } else {
        x.sin() / x
    }
}

/// The time-averaged analyzer row of an exposure during which the analyzer turns at constant
/// angular velocity from `start_rad` to `end_rad` (commanded angles; either direction, any
/// width). Equal to [`AnalyzerModel::row`] when the two are equal.
pub fn span_row(analyzer: &AnalyzerModel, start_rad: f64, end_rad: f64) -> Vector3<f64> {
    let centre = 0.5 * (start_rad + end_rad);
    let mut row = analyzer.row(centre);
    let factor = sinc(end_rad - start_rad);
    row[1] *= factor;
    row[2] *= factor;
    row
}

/// The time-averaged analyzer row along an arbitrary angle path, and the error estimate of the
/// quadrature.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathRow {
    /// The averaged row.
    pub row: Vector3<f64>,
    /// Conservative estimate of the largest component's error.
    pub error: f64,
}

/// The time-averaged analyzer row of an exposure whose commanded analyzer angle at normalised
/// time `u` in `[0, 1]` (start to end of the exposure) is `angle_rad_at(u)`, integrated to the
/// absolute tolerance `tol` (in units of the row, whose entries are at most 1). Errors (naming
/// `tolerance`) when `tol` is not in `[1e-14, 0.1]`, and (naming `angle path`) when the path
/// gives a non-finite angle or the rule does not converge.
pub fn path_row<F: FnMut(f64) -> f64>(
    analyzer: &AnalyzerModel,
    mut angle_rad_at: F,
    tol: f64,
) -> Result<PathRow, ModelError> {
    if !(1e-14..=0.1).contains(&tol) {
        return Err(ModelError::OutOfRange {
            field: "tolerance",
            value: tol,
            allowed: "[1e-14, 0.1]",
        });
    }
    let mut bad = None;
    let integral = integrate_n(
        |u| {
            let psi = angle_rad_at(u);
            if !psi.is_finite() {
                bad.get_or_insert(u);
                return [0.0; 3];
            }
            let r = analyzer.row(psi);
            [r[0], r[1], r[2]]
        },
        0.0,
        1.0,
        Tolerance::absolute(tol),
    );
    if let Some(u) = bad {
        return Err(ModelError::Invalid {
            field: "angle path",
            reason: format!("the angle at normalised time {u} is not finite"),
        });
    }
    if !integral.converged {
        return Err(ModelError::Invalid {
            field: "angle path",
            reason: format!(
                "the row's average did not converge to {tol:e} (error estimate {:e}): the \
                 path is too rough for the adaptive rule",
                integral.error
            ),
        });
    }
    let [r0, r1, r2] = integral.value;
    Ok(PathRow {
        row: Vector3::new(r0, r1, r2),
        error: integral.error,
    })
}

/// The mean and variance of a frame's noise-free intensity `row^T S` when the span's centre
/// angle is off by a Gaussian `delta ~ N(0, sigma_rad^2)` (the whole span shifts rigidly).
/// Exact for any `sigma_rad` (see the module documentation). Errors (naming `angle sigma`) when
/// `sigma_rad` is negative or not finite.
pub fn jittered_intensity(
    analyzer: &AnalyzerModel,
    start_rad: f64,
    end_rad: f64,
    stokes: &Vector3<f64>,
    sigma_rad: f64,
) -> Result<(f64, f64), ModelError> {
    if !(sigma_rad.is_finite() && sigma_rad >= 0.0) {
        return Err(ModelError::OutOfRange {
            field: "angle sigma",
            value: sigma_rad,
            allowed: "a finite angle >= 0",
        });
    }
    let centre = 0.5 * (start_rad + end_rad) + analyzer.offset_rad;
    let d = analyzer.k1 - analyzer.k2;
    let a = 0.5 * (analyzer.k1 + analyzer.k2) * stokes[0];
    let b = 0.5 * d * sinc(end_rad - start_rad) * stokes[1].hypot(stokes[2]);
    let phi = stokes[2].atan2(stokes[1]);
    let alpha = 2.0 * centre - phi;
    let s2 = sigma_rad * sigma_rad;
    let mean = a + b * alpha.cos() * (-2.0 * s2).exp();
    let second = 0.5 * (1.0 + (2.0 * alpha).cos() * (-8.0 * s2).exp());
    let var = b * b * (second - alpha.cos().powi(2) * (-4.0 * s2).exp());
    Ok((mean, var.max(0.0)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn real_analyzer() -> AnalyzerModel {
        AnalyzerModel::from_extinction_ratio(300.0, 0.3_f64.to_radians()).unwrap()
    }

    /// The closed form against a brute-force midpoint average of Malus's law over the span
    /// (200 000 samples: the midpoint rule's error for these smooth rows is below 1e-10).
    #[test]
    fn span_row_is_the_average_of_malus_law_over_the_span() {
        let analyzer = real_analyzer();
        for (start_deg, end_deg) in [(0.0, 1.0), (10.0, 40.0), (-30.0, 60.0), (100.0, 10.0)] {
            let (a, b) = (f64::to_radians(start_deg), f64::to_radians(end_deg));
            let n = 200_000;
            let mut avg = Vector3::zeros();
            for i in 0..n {
                avg += analyzer.row(a + (b - a) * (i as f64 + 0.5) / n as f64);
            }
            avg /= n as f64;
            let closed = span_row(&analyzer, a, b);
            assert!(
                (closed - avg).amax() < 1e-10,
                "{start_deg}..{end_deg}: {closed:?} against {avg:?}"
            );
        }
    }

    /// Physical limits: a zero-width span is the point row (to rounding: the series is exact
    /// there), a half turn carries no polarised signal (sin(pi) = 0), and the unpolarised term
    /// never depends on the span.
    #[test]
    fn span_row_limits() {
        let analyzer = real_analyzer();
        let psi = 0.7;
        assert!((span_row(&analyzer, psi, psi) - analyzer.row(psi)).amax() < 1e-15);
        let near = span_row(&analyzer, psi - 1e-5, psi + 1e-5);
        assert!((near - analyzer.row(psi)).amax() < 1e-10);
        let half_turn = span_row(&analyzer, psi, psi + PI);
        assert!(half_turn[1].abs() < 1e-15 && half_turn[2].abs() < 1e-15);
        assert_eq!(half_turn[0], analyzer.row(psi)[0]);
        // The 1 % loss quoted in the documentation: sinc(14.0 deg) = 0.990.
        assert!((sinc(14.0_f64.to_radians()) - 0.990).abs() < 5e-4);
    }

    /// The adaptive path average reproduces the closed form for a linear path (to its own
    /// tolerance), and for an accelerating path it matches a brute-force average, which the
    /// closed form at the same end points does not (the centre of the time-weighted path is
    /// not the centre of the span).
    #[test]
    fn path_row_matches_brute_force_for_an_accelerating_path() {
        let analyzer = real_analyzer();
        let (a, b) = (0.2, 1.4);
        let linear = path_row(&analyzer, |u| a + (b - a) * u, 1e-12).unwrap();
        assert!((linear.row - span_row(&analyzer, a, b)).amax() < 1e-11);
        // Constant acceleration from rest: psi = a + (b - a) u^2.
        let accel = path_row(&analyzer, |u| a + (b - a) * u * u, 1e-12).unwrap();
        let n = 400_000;
        let mut avg = Vector3::zeros();
        for i in 0..n {
            let u = (i as f64 + 0.5) / n as f64;
            avg += analyzer.row(a + (b - a) * u * u);
        }
        avg /= n as f64;
        assert!((accel.row - avg).amax() < 1e-9, "{:?} {avg:?}", accel.row);
        assert!((accel.row - span_row(&analyzer, a, b)).amax() > 1e-2);
    }

    #[test]
    fn bad_inputs_are_named() {
        let analyzer = real_analyzer();
        let e = path_row(&analyzer, |u| u, 0.0).unwrap_err().to_string();
        assert!(e.contains("tolerance"), "{e}");
        let e = path_row(&analyzer, |u| if u > 0.5 { f64::NAN } else { u }, 1e-9)
            .unwrap_err()
            .to_string();
        assert!(e.contains("angle path"), "{e}");
        let s = Vector3::new(1.0, 0.3, 0.1);
        let e = jittered_intensity(&analyzer, 0.0, 0.1, &s, -1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("angle sigma"), "{e}");
    }

    /// The exact jitter moments against a seeded Monte Carlo of 400 000 shifted spans, at a
    /// small jitter (0.5 deg, where first order holds) and a large one (20 deg, where it does
    /// not). Tolerance: 5 standard errors of the sample mean and sample variance.
    #[test]
    fn jitter_moments_match_a_monte_carlo() {
        let analyzer = real_analyzer();
        let s = Vector3::new(1000.0, 180.0, -90.0);
        let (a, b) = (0.3, 0.5);
        let mut rng = crate::stats::SplitMix64(42);
        for sigma_deg in [0.5, 20.0] {
            let sigma = f64::to_radians(sigma_deg);
            let (mean, var) = jittered_intensity(&analyzer, a, b, &s, sigma).unwrap();
            let n = 400_000;
            let (mut m1, mut m2) = (0.0, 0.0);
            for _ in 0..n {
                let d = sigma * rng.normal_pair().0;
                let i = span_row(&analyzer, a + d, b + d).dot(&s);
                m1 += i;
                m2 += i * i;
            }
            let mc_mean = m1 / n as f64;
            let mc_var = m2 / n as f64 - mc_mean * mc_mean;
            let se_mean = (var / n as f64).sqrt();
            assert!(
                (mean - mc_mean).abs() < 5.0 * se_mean + 1e-9,
                "sigma {sigma_deg}: mean {mean} against {mc_mean}"
            );
            // The sample variance's standard error is var sqrt((kurtosis - 1) / n); the
            // kurtosis is 3 at small jitter (I linear in a Gaussian delta) and below 3 for the
            // bounded cosine at large jitter, so 6 var sqrt(2 / n) is 6 standard errors.
            assert!(
                (var - mc_var).abs() < 6.0 * var * (2.0 / n as f64).sqrt(),
                "sigma {sigma_deg}: var {var} against {mc_var}"
            );
        }
        // First order at small jitter: Var = (dI/dpsi)^2 sigma^2 within 1 %.
        let sigma = 0.05_f64.to_radians();
        let (_, var) = jittered_intensity(&analyzer, a, b, &s, sigma).unwrap();
        let h = 1e-6;
        let slope = (span_row(&analyzer, a + h, b + h).dot(&s)
            - span_row(&analyzer, a - h, b - h).dot(&s))
            / (2.0 * h);
        assert!((var / (slope * slope * sigma * sigma) - 1.0).abs() < 1e-2);
    }
}
