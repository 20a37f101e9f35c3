//! The analyzer's zero offset and extinction ratio from Malus's law (the `calibrate-analyzer`
//! plan, [`crate::plan::CalibrateAnalyzer`]).
//!
//! # Set-up and model
//!
//! A known linear polarizer (the *reference*, transmission axis `theta` = `reference_angle_deg`
//! in the camera frame) sits in front of a uniform unpolarised source of radiance `I0`; the
//! analyzer turns through commanded angles `psi_k`. With the conventions of MODEL.md section 0
//! and the real analyzer of MODEL.md section 6, a polarizer of principal transmittances
//! `k1 >= k2` with its axis at `theta` has the Mueller matrix (linear part)
//!
//! ```text
//!   M(theta) = 0.5 [ k1 + k2          (k1 - k2) c              (k1 - k2) s            ]
//!                  [ (k1 - k2) c      (k1 + k2) c^2 + 2r s^2   (k1 + k2 - 2r) c s     ]
//!                  [ (k1 - k2) s      (k1 + k2 - 2r) c s       (k1 + k2) s^2 + 2r c^2 ]
//! ```
//!
//! with `c = cos 2 theta`, `s = sin 2 theta`, `r = sqrt(k1 k2)`. On unpolarised light only the
//! first column matters: the reference emits `S_ref = 0.5 I0 [k1 + k2, (k1 - k2) c, (k1 - k2) s]`.
//! The analyzer (principal transmittances `q1 >= q2`, true axis `psi + delta` for a commanded
//! `psi`: the zero offset `delta`) transmits its Mueller matrix's first row times `S_ref`,
//! MODEL.md section 6's row `m(psi) = 0.5 [q1 + q2, (q1 - q2) cos 2(psi + delta), (q1 - q2) sin
//! 2(psi + delta)]`:
//!
//! ```text
//!   I(psi) = a + b cos 2(psi - psi0),   psi0 = theta - delta,
//!   a = 0.25 I0 (k1 + k2)(q1 + q2),     b = 0.25 I0 (k1 - k2)(q1 - q2),
//! ```
//!
//! Meng (2012)'s Malus law (Eq. 2.17 with a real analyzer) on the dark-subtracted signal.
//!
//! # Extinction ratio of the pair
//!
//! `ER = I_max / I_min = (a + b) / (a - b) = (k1 q1 + k2 q2) / (k1 q2 + k2 q1)
//!     = (e_r e_a + 1) / (e_r + e_a)` with `e_r = k1 / k2` the reference's and `e_a = q1 / q2` the
//! analyzer's extinction ratio. **The measured ER is the pair's, not the analyzer's alone**: two
//! polarizers of the same extinction ratio `e` give `(e^2 + 1) / (2 e)`, about `e / 2`; with a
//! known reference the analyzer's is `e_a = (ER e_r - 1) / (e_r - ER)` (for `ER < e_r`), and a
//! reference much better than the analyzer (`e_r >> e_a`) gives `ER -> e_a`.
//!
//! # Fit
//!
//! Linear least squares on the basis `[1, cos 2psi, sin 2psi]`: `I_k = c0 + c1 cos 2psi_k +
//! c2 sin 2psi_k + e_k`, solved in closed form by the 3 x 3 normal equations
//! `c = (X^T V^-1 X)^-1 X^T V^-1 y` (weighted by `1 / variance` when every point gives one,
//! unweighted otherwise). Then `a = c0`, `b = sqrt(c1^2 + c2^2)`, `psi0 = 0.5 atan2(c2, c1)`,
//! `delta = theta - psi0` wrapped to `(-90, 90]` deg.
//!
//! Uncertainties: the coefficients' covariance is `C = s^2 (X^T X)^-1` with the residual
//! variance `s^2 = RSS / (n - 3)` when no variances are given, and `C = (X^T V^-1 X)^-1` when
//! they are (then the reduced chi-square `chi^2 / (n - 3)` checks them; its expected value is
//! 1). They are propagated by the delta method (first order):
//! `grad psi0 = [0, -c2, c1] / (2 b^2)`, `grad ER = [-2b, 2a c1 / b, 2a c2 / b] / (a - b)^2`.
//! The first-order ER spread is good while the minimum `a - b` is well above its own standard
//! error; near-perfect polarizers need enough signal at the minimum (long exposures, many
//! points).

use serde::Serialize;
use std::f64::consts::PI;

/// Angles closer than this modulo 180 deg count as one (the plan's own rule).
const DISTINCT_DEG: f64 = 0.01;

/// The amplitude must exceed this many of its standard errors (and 1e-12 of the mean, the
/// rounding floor) to count as modulation.
const MODULATION_SIGMAS: f64 = 3.0;

/// One frame (or the mean of a frame's region): the commanded analyzer angle and the
/// dark-subtracted mean signal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MalusPoint {
    /// Commanded analyzer angle, degrees (any value; taken modulo 180).
    pub angle_deg: f64,
    /// Dark-subtracted mean signal, DN (any linear unit).
    pub signal: f64,
    /// The signal's variance (unit squared), if known: then the fit is weighted by its inverse
    /// and gives a reduced chi-square. Either every point has one or none.
    pub variance: Option<f64>,
}

/// The analyzer calibration (module docs for the model and the equations).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AnalyzerCalibration {
    /// Zero offset `delta = reference_angle - psi0`, degrees in `(-90, 90]`: the analyzer's
    /// true axis is the commanded angle plus this.
    pub zero_offset_deg: f64,
    /// Its standard error (delta method), degrees.
    pub zero_offset_sigma_deg: f64,
    /// `I_max / I_min = (a + b) / (a - b)`: the extinction ratio of the reference and the
    /// analyzer together, `(e_r e_a + 1) / (e_r + e_a)` (module docs).
    pub extinction_ratio: f64,
    /// Its standard error (delta method).
    pub extinction_ratio_sigma: f64,
    /// `a`, the signal's mean over a half turn (the signal's unit).
    pub mean_signal: f64,
    /// `b`, the modulation amplitude (the signal's unit).
    pub amplitude: f64,
    /// Root-mean-square of the (unweighted) residuals (the signal's unit).
    pub residual_rms: f64,
    /// `chi^2 / (n - 3)` when every point has a variance (and `n > 3`); expected 1.
    pub reduced_chi2: Option<f64>,
    /// Points fitted.
    pub points: usize,
}

/// A fit that cannot be made or means nothing; every variant names the field and the value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalError {
    /// An input value is not acceptable.
    #[error("analyzer calibration: {field} = {value} is invalid: allowed {allowed}")]
    Input {
        /// The field, e.g. `points[3].signal`.
        field: String,
        /// The value, as written.
        value: String,
        /// What is allowed.
        allowed: String,
    },
    /// Fewer than 3 distinct angles modulo 180 deg (Malus's law has 3 unknowns).
    #[error(
        "analyzer calibration: points has {distinct} distinct angle(s) modulo 180 deg among \
         {points} point(s): allowed at least 3 (a + b cos 2(psi - psi0) has 3 unknowns)"
    )]
    TooFewAngles {
        /// Distinct angles (within 0.01 deg modulo 180).
        distinct: usize,
        /// Points given.
        points: usize,
    },
    /// Exactly 3 coefficients from as many points and no variances: nothing measures the
    /// noise.
    #[error(
        "analyzer calibration: points has {points} point(s) and no variances: the fit leaves \
         no residual to estimate its uncertainty; allowed more than 3 points or a variance for \
         every point"
    )]
    NoResidual {
        /// Points given.
        points: usize,
    },
    /// The amplitude `b` is zero or not significantly above its noise.
    #[error(
        "analyzer calibration: amplitude b = {amplitude} (standard error {sigma}) shows no \
         modulation: the reference polarizer is missing or the source unpolarised; allowed b > \
         3 standard errors"
    )]
    NoModulation {
        /// The fitted amplitude.
        amplitude: f64,
        /// Its standard error.
        sigma: f64,
    },
    /// The fitted minimum `a - b` is not positive: the extinction ratio is undefined.
    #[error(
        "analyzer calibration: the fit's minimum a - b = {minimum} (mean a = {mean}, amplitude \
         b = {amplitude}) is not positive, so the extinction ratio I_max / I_min is undefined: \
         the dark is not subtracted correctly or the noise exceeds the minimum signal; allowed \
         a > b"
    )]
    NegativeMinimum {
        /// `a - b`.
        minimum: f64,
        /// `a`.
        mean: f64,
        /// `b`.
        amplitude: f64,
    },
}

fn input(field: String, value: impl std::fmt::Display, allowed: &str) -> CalError {
    CalError::Input {
        field,
        value: value.to_string(),
        allowed: allowed.to_string(),
    }
}

/// Distinct angles modulo 180 deg, within [`DISTINCT_DEG`].
fn distinct_angles(points: &[MalusPoint]) -> usize {
    let mut seen: Vec<f64> = Vec::new();
    for p in points {
        let a = p.angle_deg.rem_euclid(180.0);
        let new = !seen.iter().any(|s| {
            let d = (s - a).rem_euclid(180.0);
            d.min(180.0 - d) < DISTINCT_DEG
        });
        if new {
            seen.push(a);
        }
    }
    seen.len()
}

/// Wraps degrees into `(-90, 90]`.
fn wrap_half_turn_deg(d: f64) -> f64 {
    let r = d - 180.0 * (d / 180.0).round();
    if r <= -90.0 {
        r + 180.0
    } else {
        r
    }
}

/// Fits Malus's law `I(psi) = a + b cos 2(psi - psi0)` to dark-subtracted signals and returns
/// the analyzer's zero offset and the pair's extinction ratio with their standard errors (module
/// docs: model, closed-form least squares, delta method).
///
/// `reference_angle_deg` is the reference polarizer's transmission axis in the camera frame.
///
/// Errors: `reference_angle_deg`, `points[i].angle_deg`, `points[i].signal` or
/// `points[i].variance` not finite (a variance must also be `> 0`, and given for every point or
/// none); fewer than 3 distinct angles modulo 180 deg; exactly 3 points without variances (no
/// residual); no significant modulation (`b <= 3` standard errors); a non-positive fitted
/// minimum `a - b`.
pub fn fit_malus(
    points: &[MalusPoint],
    reference_angle_deg: f64,
) -> Result<AnalyzerCalibration, CalError> {
    if !reference_angle_deg.is_finite() {
        return Err(input(
            "reference_angle_deg".into(),
            reference_angle_deg,
            "a finite angle, degrees",
        ));
    }
    let with_variance = points.iter().filter(|p| p.variance.is_some()).count();
    for (i, p) in points.iter().enumerate() {
        if !p.angle_deg.is_finite() {
            return Err(input(
                format!("points[{i}].angle_deg"),
                p.angle_deg,
                "a finite angle, degrees",
            ));
        }
        if !p.signal.is_finite() {
            return Err(input(
                format!("points[{i}].signal"),
                p.signal,
                "a finite dark-subtracted signal",
            ));
        }
        match p.variance {
            Some(v) if !(v.is_finite() && v > 0.0) => {
                return Err(input(
                    format!("points[{i}].variance"),
                    v,
                    "finite and > 0 (or absent for every point)",
                ))
            }
            None if with_variance > 0 => {
                return Err(input(
                    format!("points[{i}].variance"),
                    "(absent)",
                    "a variance for every point or for none",
                ))
            }
            _ => {}
        }
    }
    let n = points.len();
    let distinct = distinct_angles(points);
    if distinct < 3 {
        return Err(CalError::TooFewAngles {
            distinct,
            points: n,
        });
    }
    let weighted = with_variance == n;
    if n == 3 && !weighted {
        return Err(CalError::NoResidual { points: n });
    }

    // Normal equations X^T V^-1 X c = X^T V^-1 y on the basis [1, cos 2psi, sin 2psi].
    let row = |p: &MalusPoint| {
        let (s, c) = (2.0 * p.angle_deg.to_radians()).sin_cos();
        nalgebra::Vector3::new(1.0, c, s)
    };
    let weight = |p: &MalusPoint| p.variance.map_or(1.0, |v| 1.0 / v);
    let mut normal = nalgebra::Matrix3::<f64>::zeros();
    let mut rhs = nalgebra::Vector3::<f64>::zeros();
    for p in points {
        let x = row(p);
        let w = weight(p);
        normal += x * x.transpose() * w;
        rhs += x * (w * p.signal);
    }
    let inverse = normal.try_inverse().ok_or(CalError::TooFewAngles {
        distinct,
        points: n,
    })?;
    let coef = inverse * rhs;
    let (mut rss, mut chi2) = (0.0, 0.0);
    for p in points {
        let r = p.signal - row(p).dot(&coef);
        rss += r * r;
        chi2 += r * r * weight(p);
    }
    let dof = (n - 3) as f64;
    let cov = if weighted {
        inverse
    } else {
        inverse * (rss / dof)
    };
    let reduced_chi2 = (weighted && n > 3).then(|| chi2 / dof);

    let (a, c1, c2) = (coef[0], coef[1], coef[2]);
    let b = c1.hypot(c2);
    let quad = |g: nalgebra::Vector3<f64>| (g.transpose() * cov * g)[0].max(0.0).sqrt();
    let sigma_b = if b > 0.0 {
        quad(nalgebra::Vector3::new(0.0, c1 / b, c2 / b))
    } else {
        quad(nalgebra::Vector3::new(0.0, 1.0, 0.0))
    };
    // Rounding alone leaves an amplitude of ~1e-16 a on a constant signal: floor at 1e-12 a.
    let significant = b > MODULATION_SIGMAS * sigma_b && b > 1e-12 * a.abs();
    if !significant {
        return Err(CalError::NoModulation {
            amplitude: b,
            sigma: sigma_b,
        });
    }
    let minimum = a - b;
    if minimum.is_nan() || minimum <= 0.0 {
        return Err(CalError::NegativeMinimum {
            minimum,
            mean: a,
            amplitude: b,
        });
    }
    let psi0 = 0.5 * c2.atan2(c1);
    let sigma_psi0 = quad(nalgebra::Vector3::new(0.0, -c2, c1) / (2.0 * b * b));
    let er = (a + b) / minimum;
    let d2 = minimum * minimum;
    let sigma_er = quad(nalgebra::Vector3::new(
        -2.0 * b / d2,
        2.0 * a * c1 / (b * d2),
        2.0 * a * c2 / (b * d2),
    ));
    Ok(AnalyzerCalibration {
        zero_offset_deg: wrap_half_turn_deg(reference_angle_deg - psi0 * 180.0 / PI),
        zero_offset_sigma_deg: sigma_psi0.to_degrees(),
        extinction_ratio: er,
        extinction_ratio_sigma: sigma_er,
        mean_signal: a,
        amplitude: b,
        residual_rms: (rss / n as f64).sqrt(),
        reduced_chi2,
        points: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Malus signals `a + b cos 2(psi - (reference - delta))` at `n` angles evenly over 180
    /// deg.
    fn synthetic(n: usize, a: f64, b: f64, reference: f64, delta: f64) -> Vec<MalusPoint> {
        let psi0 = (reference - delta).to_radians();
        (0..n)
            .map(|k| {
                let angle_deg = 180.0 * k as f64 / n as f64;
                MalusPoint {
                    angle_deg,
                    signal: a + b * (2.0 * (angle_deg.to_radians() - psi0)).cos(),
                    variance: None,
                }
            })
            .collect()
    }

    /// Exact data: the closed-form fit recovers delta and ER = (a + b) / (a - b) to 1e-9 (the
    /// fit is exact up to rounding, ~1e-13 here), and the residual is at rounding level.
    #[test]
    fn exact_data_recovers_offset_and_extinction() {
        for (reference, delta) in [(30.0, 1.7), (0.0, -2.5), (170.0, 0.3), (90.0, -89.0)] {
            let (a, b) = (1200.0, 1000.0);
            let points = synthetic(24, a, b, reference, delta);
            let cal = fit_malus(&points, reference).expect("fit");
            assert!(
                (cal.zero_offset_deg - delta).abs() < 1e-9,
                "{reference} {delta}: {cal:?}"
            );
            let er = (a + b) / (a - b);
            assert!((cal.extinction_ratio - er).abs() < 1e-9 * er, "{cal:?}");
            assert!((cal.mean_signal - a).abs() < 1e-9 * a);
            assert!((cal.amplitude - b).abs() < 1e-9 * b);
            assert!(cal.residual_rms < 1e-9 * a, "{cal:?}");
            assert_eq!(cal.points, 24);
            assert_eq!(cal.reduced_chi2, None);
        }
    }

    /// Uneven angles (not a full half turn) fit as well: the closed form does not rely on
    /// orthogonality. Tolerance 1e-9 as above.
    #[test]
    fn uneven_angles() {
        let psi0 = (40.0f64 - 1.2).to_radians();
        let points: Vec<MalusPoint> = [3.0, 17.0, 29.5, 51.0, 66.0, 88.0, 101.0]
            .iter()
            .map(|&d: &f64| MalusPoint {
                angle_deg: d,
                signal: 500.0 + 450.0 * (2.0 * (d.to_radians() - psi0)).cos(),
                variance: None,
            })
            .collect();
        let cal = fit_malus(&points, 40.0).expect("fit");
        assert!((cal.zero_offset_deg - 1.2).abs() < 1e-9, "{cal:?}");
        assert!((cal.extinction_ratio - 950.0 / 50.0).abs() < 1e-9 * 19.0);
    }

    /// Near-perfect polarizers, ER = 1000 (a - b = 2e-3 a): the subtraction loses about 3 of
    /// 16 digits, so ER is still exact to 1e-9 relative and finite.
    #[test]
    fn extinction_1000_is_finite_and_accurate() {
        let er = 1000.0;
        let (a, b) = (1000.0 * (er + 1.0) / 2.0, 1000.0 * (er - 1.0) / 2.0);
        let points = synthetic(36, a, b, 45.0, 0.8);
        let cal = fit_malus(&points, 45.0).expect("fit");
        assert!(cal.extinction_ratio.is_finite());
        assert!(
            (cal.extinction_ratio - er).abs() < 1e-9 * er,
            "{}",
            cal.extinction_ratio
        );
        assert!((cal.zero_offset_deg - 0.8).abs() < 1e-9);
    }

    /// Noisy data (Gaussian, sigma 5 on a = 1000, b = 900, 36 angles): one fit finds delta
    /// within 3 predicted sigma; over 4000 seeded fits the predicted sigma (RMS of the per-fit
    /// residual-based values, and the fixed value from given variances) matches the spread of
    /// the estimates within 10 % for delta and ER. The sampling error of a standard deviation
    /// from M = 4000 draws is 1 / sqrt(2 (M - 1)) = 1.1 %, so 10 % is about 9 standard errors
    /// (and the delta method's bias for ER ~ 19 with a - b = 100 >> its 1.4 standard error is
    /// below 1 %).
    #[test]
    fn noisy_data_sigma_matches_monte_carlo() {
        let (a, b, reference, delta, sigma) = (1000.0, 900.0, 30.0, 1.5, 5.0);
        let clean = synthetic(36, a, b, reference, delta);
        let mut rng = polar_hil_mocks::faults::Dice::new(0x5eed);
        let draw =
            |rng: &mut polar_hil_mocks::faults::Dice, variance: Option<f64>| -> Vec<MalusPoint> {
                clean
                    .iter()
                    .map(|p| MalusPoint {
                        signal: p.signal + sigma * rng.normal(),
                        variance,
                        ..*p
                    })
                    .collect()
            };
        let one = fit_malus(&draw(&mut rng, None), reference).expect("fit");
        assert!(
            (one.zero_offset_deg - delta).abs() < 3.0 * one.zero_offset_sigma_deg,
            "{one:?}"
        );
        for variance in [None, Some(sigma * sigma)] {
            let m = 4000;
            let (mut d, mut e, mut pd2, mut pe2, mut chi) = (vec![], vec![], 0.0, 0.0, 0.0);
            for _ in 0..m {
                let cal = fit_malus(&draw(&mut rng, variance), reference).expect("fit");
                d.push(cal.zero_offset_deg);
                e.push(cal.extinction_ratio);
                pd2 += cal.zero_offset_sigma_deg.powi(2) / m as f64;
                pe2 += cal.extinction_ratio_sigma.powi(2) / m as f64;
                chi += cal.reduced_chi2.unwrap_or(1.0) / m as f64;
            }
            let std = |v: &[f64]| {
                let mean = v.iter().sum::<f64>() / v.len() as f64;
                (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
            };
            let (sd, se) = (std(&d), std(&e));
            let (rd, re) = (pd2.sqrt() / sd - 1.0, pe2.sqrt() / se - 1.0);
            eprintln!(
                "variance {variance:?}: delta sigma predicted {:.5} MC {sd:.5} ({:+.2} %), ER \
                 sigma predicted {:.5} MC {se:.5} ({:+.2} %), mean reduced chi2 {chi:.4}",
                pd2.sqrt(),
                100.0 * rd,
                pe2.sqrt(),
                100.0 * re
            );
            assert!(rd.abs() < 0.10, "delta sigma off by {rd}");
            assert!(re.abs() < 0.10, "ER sigma off by {re}");
            // The mean reduced chi-square of 4000 fits with 33 dof: 1 +- sqrt(2/33/4000) = 0.004.
            assert!((chi - 1.0).abs() < 0.02, "{chi}");
        }
    }

    /// The real analyzer model: a reference polarizer of extinction ratio e (its Mueller first
    /// column on unpolarised light is I0 times the analyzer row of a polarizer at its axis,
    /// module docs) in front of the modern CMOS camera whose analyzer has extinction ratio e
    /// and offset 0.6 deg, through the sensor model's noise-free frame means. The fit recovers
    /// the pair's ER (e^2 + 1) / (2 e) and the offset to 1e-9 (the model is exactly Malus's
    /// law; the only error is rounding).
    #[test]
    fn real_polarizer_pair_from_the_sensor_model() {
        use polar_model::analyzer::AnalyzerModel;
        use polar_model::polarization::Stokes;
        use polar_model::sensor::{Camera, Exposure, SensorModel};
        let scene = polar_model::scene_file::Scene::from_toml_str(include_str!(
            "../../../examples/rooftop_panels.toml"
        ))
        .expect("scene");
        for e in [300.0, 1000.0, 20.0] {
            let mut camera =
                Camera::from_toml_str(include_str!("../../../examples/cameras/cmos_modern.toml"))
                    .expect("camera");
            camera.polarizer.extinction_ratio = Some(e);
            camera.polarizer.offset_deg = 0.6;
            let sensor = SensorModel::new(&camera, &scene.spec.band).expect("sensor");
            let reference_deg: f64 = 25.0;
            let reference =
                AnalyzerModel::from_extinction_ratio(e, reference_deg.to_radians()).expect("ref");
            // Unpolarised I0 through the reference: its first Mueller column = I0 row(0).
            let i0 = 2.0;
            let s_ref = reference.row(0.0) * i0;
            let angles_deg: Vec<f64> = (0..72).map(|k| 2.5 * k as f64).collect();
            let angles: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
            let t = 0.002;
            let signal = sensor
                .signal(&angles, &Exposure::new(t, Stokes(s_ref)))
                .expect("signal");
            let dark_dn = camera.gain_dn_per_e * signal.dark_electrons + camera.offset_dn;
            let points: Vec<MalusPoint> = angles_deg
                .iter()
                .zip(signal.mean_dn.iter())
                .map(|(&angle_deg, &y)| MalusPoint {
                    angle_deg,
                    signal: y - dark_dn,
                    variance: None,
                })
                .collect();
            let cal = fit_malus(&points, reference_deg).expect("fit");
            let expected = (e * e + 1.0) / (2.0 * e);
            assert!(
                (cal.extinction_ratio - expected).abs() < 1e-9 * expected,
                "e {e}: {} against {expected}",
                cal.extinction_ratio
            );
            assert!((cal.zero_offset_deg - 0.6).abs() < 1e-9, "{cal:?}");
        }
    }

    /// Three points with variances: an exact fit, no residual, sigma from the variances, no
    /// reduced chi-square (0 degrees of freedom).
    #[test]
    fn three_points_with_variances() {
        let mut points = synthetic(3, 100.0, 60.0, 10.0, 0.0);
        for p in &mut points {
            p.variance = Some(4.0);
        }
        let cal = fit_malus(&points, 10.0).expect("fit");
        assert!(cal.zero_offset_deg.abs() < 1e-9);
        assert!(cal.zero_offset_sigma_deg > 0.0 && cal.zero_offset_sigma_deg.is_finite());
        assert_eq!(cal.reduced_chi2, None);
    }

    /// Every bad input gives an error that names the field and the value.
    #[test]
    fn bad_inputs_are_named() {
        let good = synthetic(12, 1000.0, 800.0, 20.0, 1.0);
        let with = |f: &dyn Fn(&mut Vec<MalusPoint>)| {
            let mut p = good.clone();
            f(&mut p);
            p
        };
        let cases: Vec<(Vec<MalusPoint>, f64, &str)> = vec![
            (good.clone(), f64::NAN, "reference_angle_deg"),
            (
                with(&|p| p[2].angle_deg = f64::INFINITY),
                20.0,
                "points[2].angle_deg",
            ),
            (with(&|p| p[5].signal = f64::NAN), 20.0, "points[5].signal"),
            (
                with(&|p| p[0].variance = Some(-1.0)),
                20.0,
                "points[0].variance",
            ),
            (
                with(&|p| {
                    for q in p.iter_mut() {
                        q.variance = Some(1.0);
                    }
                    p[7].variance = None;
                }),
                20.0,
                "points[7].variance",
            ),
            // Two distinct angles modulo 180 (0, 180, 45, 225).
            (
                [0.0, 180.0, 45.0, 225.0]
                    .iter()
                    .map(|&a| MalusPoint {
                        angle_deg: a,
                        signal: 10.0 + a / 100.0,
                        variance: None,
                    })
                    .collect(),
                0.0,
                "2 distinct angle",
            ),
            (synthetic(3, 100.0, 50.0, 0.0, 0.0), 0.0, "no residual"),
            // Unpolarised source: constant signal.
            (
                with(&|p| p.iter_mut().for_each(|q| q.signal = 500.0)),
                20.0,
                "unpolarised",
            ),
            // Dark not subtracted the right way: the minimum is negative.
            (
                with(&|p| p.iter_mut().for_each(|q| q.signal -= 300.0)),
                20.0,
                "a - b = -",
            ),
        ];
        for (points, reference, needle) in cases {
            let e = fit_malus(&points, reference).expect_err(needle).to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
    }
}
