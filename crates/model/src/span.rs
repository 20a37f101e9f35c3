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
//!
//! # Frames of spans through a camera
//!
//! [`span_signal`] takes a set of spans through a camera ([`SensorModel`]) and gives what the
//! forecast gives for a step-and-shoot set: each frame's mean and variance in DN and the
//! covariance of the Stokes estimate. The expected row of frame `k` is the span row times the
//! fore-optics, `rbar_k^T M_opt`, with its polarised terms also scaled by the jitter's
//! `e^{-2 sigma^2}` (the mean above), so the least-squares estimate with these rows is unbiased
//! under jitter. The frame's variance is the sensor's (MODEL.md section 6 with `F_n = 1`, no
//! clutter, no drift: the temporal noise one pixel sees, as the forecast of a plan uses) at the
//! expected electrons, plus the jitter variance above in DN^2 (`(K G)^2` times it). The frames
//! are independent, so the estimate `S_hat = W^+ (y - K mu_I t - b)` (`W` the expected rows,
//! OLS) has the exact covariance `(W^T W)^-1 W^T V W (W^T W)^-1`, `V = diag(variances)`, in
//! DN^2 of `K G L`.
//!
//! [`span_peak`] is the brightest frame a span can give a class over the analyzer's phase
//! (the span centred on the class's AoP), with the class's texture and the sensor noise: the
//! saturation check of a spinning analyzer, whose frames meet every phase.

use crate::analyzer::AnalyzerModel;
use crate::error::ModelError;
use crate::quadrature::{integrate_n, Tolerance};
use crate::sensor::SensorModel;
use nalgebra::{Matrix3, Vector3};

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

/// One set of span frames' exposure: integration time, the class's mean band radiance at the
/// aperture and the rms error of each span's centre angle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpanExposure {
    /// Integration time of each frame, s, in `(0, 1e5]`.
    pub t_int_s: f64,
    /// Mean band Stokes radiance `L`, W m^-2 sr^-1 (`[S0, S1, S2]`, finite).
    pub radiance_w_m2_sr: Vector3<f64>,
    /// Standard deviation of each span's centre angle, radians (0 for frames triggered at
    /// encoder positions; the stage's speed times the timing uncertainty for a free-running
    /// camera), finite and `>= 0`.
    pub angle_sigma_rad: f64,
}

/// The frames of a set of spans and the Stokes estimate they give (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct SpanSignal {
    /// The expected rows `W` (one per frame): span row times fore-optics, polarised terms
    /// scaled by the jitter's `e^{-2 sigma^2}`.
    pub rows: Vec<Vector3<f64>>,
    /// Each frame's mean, DN (offset and dark signal included).
    pub mean_dn: Vec<f64>,
    /// Each frame's variance, DN^2 (sensor and jitter).
    pub var_dn2: Vec<f64>,
    /// The jitter's part of each variance, DN^2.
    pub jitter_var_dn2: Vec<f64>,
    /// `K G`, DN per W m^-2 sr^-1 in one frame.
    pub dn_from_radiance: f64,
    /// What the estimate estimates, `K G L`, DN.
    pub stokes_dn: Vector3<f64>,
    /// Covariance of the OLS Stokes estimate from the set, DN^2.
    pub stokes_cov_dn2: Matrix3<f64>,
}

fn check_exposure(e: &SpanExposure) -> Result<(), ModelError> {
    if !(e.t_int_s.is_finite() && e.t_int_s > 0.0 && e.t_int_s <= crate::sensor::MAX_T_INT_S) {
        return Err(ModelError::OutOfRange {
            field: "t_int_s",
            value: e.t_int_s,
            allowed: "> 0 and <= 1e5 s",
        });
    }
    if let Some(bad) = e.radiance_w_m2_sr.iter().find(|v| !v.is_finite()) {
        return Err(ModelError::OutOfRange {
            field: "radiance_w_m2_sr",
            value: *bad,
            allowed: "finite components",
        });
    }
    if !(e.angle_sigma_rad.is_finite() && e.angle_sigma_rad >= 0.0) {
        return Err(ModelError::OutOfRange {
            field: "angle sigma",
            value: e.angle_sigma_rad,
            allowed: "a finite angle >= 0",
        });
    }
    Ok(())
}

/// The frames of the spans `spans_rad` (`(start, end)` commanded angles, radians, constant
/// velocity within each) through `sensor`, and the covariance of their OLS Stokes estimate
/// (module docs). Errors name the field: `spans` (fewer than 3, a non-finite angle, or rows
/// that do not determine the three Stokes components), `t_int_s`, `radiance_w_m2_sr`,
/// `angle sigma`.
pub fn span_signal(
    sensor: &SensorModel,
    spans_rad: &[(f64, f64)],
    exposure: &SpanExposure,
) -> Result<SpanSignal, ModelError> {
    check_exposure(exposure)?;
    if spans_rad.len() < 3 {
        return Err(ModelError::Invalid {
            field: "spans",
            reason: format!(
                "{} spans: allowed at least 3 (a linear Stokes vector has 3 unknowns)",
                spans_rad.len()
            ),
        });
    }
    if let Some((a, b)) = spans_rad
        .iter()
        .find(|(a, b)| !(a.is_finite() && b.is_finite()))
    {
        return Err(ModelError::Invalid {
            field: "spans",
            reason: format!("span ({a}, {b}) rad: allowed finite angles"),
        });
    }
    let analyzer = sensor.analyzer();
    let cam = sensor.camera();
    let m_opt = cam.fore_optics().0;
    let t = exposure.t_int_s;
    let k = cam.gain_dn_per_e;
    let big_g = sensor.responsivity_e_per_s() * t;
    let kg = k * big_g;
    // What reaches the analyzer: the fore-optics act first.
    let seen = m_opt * exposure.radiance_w_m2_sr;
    let sigma = exposure.angle_sigma_rad;
    let attenuation = (-2.0 * sigma * sigma).exp();
    let dark_e = cam.dark_current_e_per_s * t;
    let floor_dn2 = k * k * (cam.read_noise_e * cam.read_noise_e + dark_e) + 1.0 / 12.0;
    let n = spans_rad.len();
    let mut rows = Vec::with_capacity(n);
    let mut mean_dn = Vec::with_capacity(n);
    let mut var_dn2 = Vec::with_capacity(n);
    let mut jitter_var_dn2 = Vec::with_capacity(n);
    for &(a, b) in spans_rad {
        let mut r = span_row(&analyzer, a, b);
        r[1] *= attenuation;
        r[2] *= attenuation;
        let light = r.dot(&seen);
        // Exactly 0 without jitter (the closed form leaves rounding there).
        let jvar = if sigma > 0.0 {
            jittered_intensity(&analyzer, a, b, &seen, sigma)?.1
        } else {
            0.0
        };
        let electrons = (big_g * light).max(0.0);
        let jitter = kg * kg * jvar;
        rows.push(m_opt.transpose() * r);
        mean_dn.push(k * (electrons + dark_e) + cam.offset_dn);
        var_dn2.push(floor_dn2 + k * k * electrons + jitter);
        jitter_var_dn2.push(jitter);
    }
    let gram = rows
        .iter()
        .fold(Matrix3::zeros(), |acc, r| acc + r * r.transpose());
    let e = gram.symmetric_eigenvalues();
    let inv = gram.try_inverse().filter(|_| e.min() > e.max() * 1e-14);
    let Some(inv) = inv else {
        return Err(ModelError::Invalid {
            field: "spans",
            reason: format!(
                "the spans' rows do not determine S0, S1 and S2 (eigenvalues of W^T W {:e} ..                  {:e}): allowed spans whose centres spread over the half turn",
                e.min(),
                e.max()
            ),
        });
    };
    let middle = rows
        .iter()
        .zip(&var_dn2)
        .fold(Matrix3::zeros(), |acc, (r, v)| acc + r * r.transpose() * *v);
    let cov = inv * middle * inv;
    Ok(SpanSignal {
        rows,
        mean_dn,
        var_dn2,
        jitter_var_dn2,
        dn_from_radiance: kg,
        stokes_dn: exposure.radiance_w_m2_sr * kg,
        stokes_cov_dn2: 0.5 * (cov + cov.transpose()),
    })
}

/// The brightest frame a span of width `span_rad` can give a class over the analyzer's phase:
/// its mean (DN, offset and dark signal included) and standard deviation (DN: the sensor
/// noise at that mean and the class's texture `cov_w2_m4_sr2` through that frame's row), with
/// the span centred where the analyzer passes the most of the class's mean (module docs).
/// Errors as [`span_signal`], and `cov_w2_m4_sr2` when not finite.
pub fn span_peak(
    sensor: &SensorModel,
    span_rad: f64,
    t_int_s: f64,
    radiance_w_m2_sr: &Vector3<f64>,
    cov_w2_m4_sr2: &Matrix3<f64>,
) -> Result<(f64, f64), ModelError> {
    check_exposure(&SpanExposure {
        t_int_s,
        radiance_w_m2_sr: *radiance_w_m2_sr,
        angle_sigma_rad: 0.0,
    })?;
    if !span_rad.is_finite() {
        return Err(ModelError::OutOfRange {
            field: "span",
            value: span_rad,
            allowed: "a finite angle",
        });
    }
    if let Some(bad) = cov_w2_m4_sr2.iter().find(|v| !v.is_finite()) {
        return Err(ModelError::OutOfRange {
            field: "cov_w2_m4_sr2",
            value: *bad,
            allowed: "finite entries",
        });
    }
    let analyzer = sensor.analyzer();
    let cam = sensor.camera();
    let m_opt = cam.fore_optics().0;
    let seen = m_opt * radiance_w_m2_sr;
    // The row's polarised part points along (cos 2(psi + offset), sin 2(psi + offset)): most
    // light where that is along (S1, S2) of what the analyzer sees.
    let centre = 0.5 * seen[2].atan2(seen[1]) - analyzer.offset_rad;
    let r = span_row(&analyzer, centre - 0.5 * span_rad, centre + 0.5 * span_rad);
    let w = m_opt.transpose() * r;
    let k = cam.gain_dn_per_e;
    let big_g = sensor.responsivity_e_per_s() * t_int_s;
    let electrons = (big_g * r.dot(&seen)).max(0.0);
    let dark_e = cam.dark_current_e_per_s * t_int_s;
    let sym = 0.5 * (cov_w2_m4_sr2 + cov_w2_m4_sr2.transpose());
    let texture = (k * big_g).powi(2) * w.dot(&(sym * w)).max(0.0);
    let var = k * k * (cam.read_noise_e.powi(2) + dark_e + electrons) + 1.0 / 12.0 + texture;
    Ok((k * (electrons + dark_e) + cam.offset_dn, var.sqrt()))
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

    fn camera_through_fore_optics() -> SensorModel {
        let mut cam = crate::sensor::Camera::from_toml_str(include_str!(
            "../../../examples/cameras/cmos_modern.toml"
        ))
        .unwrap();
        // A mild diattenuating window in front of the analyzer, so that the rows' fore-optics
        // factor is exercised.
        cam.fore_optics = Some([[1.0, 0.05, 0.0], [0.05, 1.0, 0.0], [0.0, 0.0, 0.98]]);
        let band = crate::atmosphere::Band::flat(450.0, 650.0).unwrap();
        SensorModel::new(&cam, &band).unwrap()
    }

    /// Zero-width spans without jitter are the step-and-shoot frames: the means and variances
    /// of [`SensorModel::signal`] (no clutter) and the OLS covariance of the model's
    /// [`crate::stats::StokesEstimator`], to 1e-10 relative (the same closed forms, summed in
    /// another order; the estimator goes through an SVD).
    #[test]
    fn zero_width_spans_are_the_step_and_shoot_frames() {
        let sensor = camera_through_fore_optics();
        let l = Vector3::new(40.0, 9.0, -5.0);
        let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0, 20.0]
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let spans: Vec<(f64, f64)> = angles.iter().map(|&a| (a, a)).collect();
        let t = 2e-4;
        let got = span_signal(
            &sensor,
            &spans,
            &SpanExposure {
                t_int_s: t,
                radiance_w_m2_sr: l,
                angle_sigma_rad: 0.0,
            },
        )
        .unwrap();
        let want = sensor
            .signal(
                &angles,
                &crate::sensor::Exposure::new(
                    t,
                    crate::polarization::Stokes::new(l[0], l[1], l[2]),
                ),
            )
            .unwrap();
        let rel = |a: f64, b: f64| (a - b).abs() / b.abs();
        for i in 0..angles.len() {
            assert!(rel(got.mean_dn[i], want.mean_dn[i]) < 1e-10);
            assert!(rel(got.var_dn2[i], want.cov_dn[(i, i)]) < 1e-10);
            assert_eq!(got.jitter_var_dn2[i], 0.0);
        }
        let est = crate::stats::StokesEstimator::new(
            &want.intensities_from_stokes,
            &want.cov_dn,
            crate::stats::MethodChoice::Ols,
        )
        .unwrap();
        for i in 0..3 {
            assert!(
                rel(got.stokes_cov_dn2[(i, i)], est.cov[(i, i)]) < 1e-10,
                "{i}: {} against {}",
                got.stokes_cov_dn2[(i, i)],
                est.cov[(i, i)]
            );
        }
        assert!(
            rel(
                got.stokes_dn[0],
                l[0] * sensor.camera().gain_dn_per_e * want.electrons_from_radiance
            ) < 1e-12
        );
    }

    /// The estimate from jittered wide spans, simulated frame by frame (each frame's span
    /// shifted rigidly by a Gaussian angle error, its exact span row, Gaussian sensor noise of
    /// the predicted sensor variance), is unbiased and has the predicted covariance: 200 000
    /// seeded sets, 4 spans of 40 deg, 3 deg of jitter (about half of the S1, S2 variance).
    /// Tolerances: 5 standard errors of the sample mean; 5 sqrt(2 / n) relative for the sample
    /// variance (its standard error for a near-Gaussian estimate, kurtosis about 3).
    #[test]
    fn jittered_spans_give_the_predicted_covariance() {
        let sensor = camera_through_fore_optics();
        let analyzer = sensor.analyzer();
        let m_opt = sensor.camera().fore_optics().0;
        let l = Vector3::new(40.0, 12.0, -7.0);
        let spans: Vec<(f64, f64)> = (0..4)
            .map(|k| {
                let c = f64::from(k) * PI / 4.0 + 0.1;
                (c - 20f64.to_radians(), c + 20f64.to_radians())
            })
            .collect();
        let exposure = SpanExposure {
            t_int_s: 5e-4,
            radiance_w_m2_sr: l,
            angle_sigma_rad: 3f64.to_radians(),
        };
        let p = span_signal(&sensor, &spans, &exposure).unwrap();
        let jitter_share = p.jitter_var_dn2.iter().sum::<f64>() / p.var_dn2.iter().sum::<f64>();
        assert!(jitter_share > 0.2, "jitter share {jitter_share}");
        let w = nalgebra::DMatrix::from_fn(4, 3, |i, j| p.rows[i][j]);
        let pinv = (w.transpose() * &w).try_inverse().unwrap() * w.transpose();
        let seen = m_opt * l;
        let mut rng = crate::stats::SplitMix64(7);
        let n = 200_000;
        let (mut m1, mut m2) = (Vector3::zeros(), Vector3::zeros());
        for _ in 0..n {
            let mut y = nalgebra::DVector::zeros(4);
            for (i, &(a, b)) in spans.iter().enumerate() {
                let (g1, g2) = rng.normal_pair();
                let d = exposure.angle_sigma_rad * g1;
                let clean = p.dn_from_radiance * span_row(&analyzer, a + d, b + d).dot(&seen);
                let sensor_sd = (p.var_dn2[i] - p.jitter_var_dn2[i]).sqrt();
                // The dark-subtracted frame.
                y[i] = clean + sensor_sd * g2;
            }
            let s: Vector3<f64> = Vector3::from_iterator((&pinv * y).iter().copied());
            m1 += s;
            m2 += s.component_mul(&s);
        }
        let mean = m1 / n as f64;
        for i in 0..3 {
            let var = m2[i] / n as f64 - mean[i] * mean[i];
            let want = p.stokes_cov_dn2[(i, i)];
            let se = (want / n as f64).sqrt();
            assert!(
                (mean[i] - p.stokes_dn[i]).abs() < 5.0 * se,
                "S{i}: mean {} against {}",
                mean[i],
                p.stokes_dn[i]
            );
            assert!(
                (var / want - 1.0).abs() < 5.0 * (2.0 / n as f64).sqrt(),
                "S{i}: variance {var} against {want}"
            );
        }
    }

    /// The peak is the largest frame mean over the analyzer's phase: against a 0.01-degree scan
    /// of span centres it is not exceeded (to 1e-12 relative, rounding) and is reached within
    /// the scan's quadratic error (1e-8 relative: (0.005 deg)^2 times the modulation).
    #[test]
    fn span_peak_is_the_brightest_phase() {
        let sensor = camera_through_fore_optics();
        let l = Vector3::new(40.0, 12.0, -7.0);
        let width = 25f64.to_radians();
        let t = 3e-4;
        let (peak, sd) = span_peak(&sensor, width, t, &l, &Matrix3::zeros()).unwrap();
        let mut best: f64 = 0.0;
        let mut sd_at_best = 0.0;
        for k in 0..18_000 {
            let c = f64::from(k) * PI / 18_000.0;
            let s = span_signal(
                &sensor,
                &[
                    (c - width / 2.0, c + width / 2.0),
                    (c, c),
                    (c + 1.0, c + 1.0),
                ],
                &SpanExposure {
                    t_int_s: t,
                    radiance_w_m2_sr: l,
                    angle_sigma_rad: 0.0,
                },
            )
            .unwrap();
            if s.mean_dn[0] > best {
                best = s.mean_dn[0];
                sd_at_best = s.var_dn2[0].sqrt();
            }
        }
        assert!(best <= peak * (1.0 + 1e-12), "{best} > {peak}");
        assert!((peak - best) / peak < 1e-8, "{best} against {peak}");
        assert!((sd - sd_at_best).abs() / sd < 1e-8);
    }
}
