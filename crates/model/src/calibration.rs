//! EMVA 1288 photon-transfer calibration (MODEL.md section 6, "Noise characterisation from
//! calibration frames"): the system gain `K`, the read noise `sigma_d`, the dark current
//! `mu_I`, the offset `b`, the saturation capacity and (when the photon count is known) the
//! quantum efficiency, each with a standard uncertainty, from per-exposure statistics of dark and
//! flat-field frame pairs.
//!
//! # Method (EMVA 1288 Release 4.0 Linear, European Machine Vision Association, 2021)
//!
//! * Linear signal and noise model (Sec. 2.1-2.2):
//!   `mu_y = mu_y.dark + K eta mu_p`, `sigma_y^2 = K^2 (sigma_d^2 + sigma_e^2) + sigma_q^2`, with
//!   Poisson photo-electrons (`sigma_e^2 = mu_e`) and the quantisation noise
//!   `sigma_q^2 = 1/12 DN^2`. Hence the photon transfer
//!   `sigma_y^2 - sigma_y.dark^2 = K (mu_y - mu_y.dark)`: a straight line of slope `K`.
//! * Statistics of a pair of frames `A`, `B` of `n` pixels (Sec. 6, Eqs. 16 and 18): the mean
//!   `mu_y = (<A> + <B>) / 2` and the temporal variance as half the variance of the difference,
//!   `sigma_y^2 = var(A - B) / 2`, which cancels the fixed-pattern noise (PRNU, DSNU). See
//!   [`pair_statistics`].
//! * Saturation (Sec. 6): the saturation point is the exposure at which the temporal variance
//!   is largest (past it the clipped signal's variance drops); the saturation capacity in
//!   electrons is `mu_e.sat = (mu_y.sat - mu_y.dark) / K`.
//! * System gain (Sec. 6, Eq. 50): the slope of `sigma_y^2 - sigma_y.dark^2` against
//!   `mu_y - mu_y.dark` over the linear range, from the first point with signal up to 70 % of
//!   the saturation signal `mu_y.sat - mu_y.dark`, fitted through the origin as the model has no
//!   intercept.
//! * Temporal dark noise (Sec. 6, Eqs. 53-54): `sigma_d = sqrt(sigma_y.dark^2 - sigma_q^2) / K`.
//!   The camera file's `sigma_d` excludes the dark-current shot noise `K^2 mu_I t_exp` (see
//!   [`crate::sensor`]), so `sigma_y.dark^2` here is the dark variance extrapolated to zero
//!   exposure (the intercept of the dark variance against exposure time). Below
//!   `sigma_y.dark^2 = 0.24 DN^2` the standard gives only an upper limit,
//!   `sigma_d <= sqrt(0.24 - 1/12) / K` (about `0.40 / K`): reported as such, with a warning.
//! * Dark current (Sec. 3.1 and Sec. 7.1): `mu_y.dark = b + K mu_I t_exp`; the slope of the
//!   dark mean against exposure time, divided by `K`, is `mu_I` in e-/s, its intercept the
//!   offset `b`.
//! * Quantum efficiency (Sec. 6, Eq. 52): the responsivity `R`, the slope of `mu_y - mu_y.dark`
//!   against the mean photon count `mu_p` over the same linear range (through the origin), gives
//!   `eta = R / K`, the slope of electrons against photons.
//!
//! # Uncertainties
//!
//! Every fit is weighted least squares with the sampling variance of its data: a variance
//! estimated from `n - 1` degrees of freedom has variance `2 sigma^4 / (n - 1)` (Gaussian
//! approximation; Poisson and read noise are near Gaussian at these counts), a mean of the `2n`
//! pixel values of a pair has variance `sigma^2 / (2n)`. The slope's or intercept's variance is
//! the weighted fit's, multiplied by the reduced chi-square of the residuals when that exceeds 1
//! (so scatter beyond the noise, nonlinearity or illumination drift, widens the uncertainty).
//! Derived quantities propagate these to first order, treating `K` as independent of the dark
//! fits (they share only the dark variances, a minor correlation that is neglected). Variances
//! below the quantisation floor `1/12 DN^2` are floored there for the weights only.

use crate::error::ModelError;
use serde::{Deserialize, Serialize};

/// Quantisation noise of an ideal ADC, `sigma_q^2 = 1/12 DN^2` (EMVA 1288 Release 4.0 Linear,
/// Sec. 2.2).
pub const QUANTIZATION_VARIANCE_DN2: f64 = 1.0 / 12.0;

/// Upper end of the linear range for the photon-transfer and responsivity fits, as a fraction of
/// the saturation signal `mu_y.sat - mu_y.dark` (EMVA 1288 Release 4.0 Linear, Sec. 6).
pub const LINEAR_RANGE_FRACTION: f64 = 0.7;

/// Dark variance below which the temporal dark noise is only an upper limit, DN^2 (EMVA 1288
/// Release 4.0 Linear, Sec. 6, Eq. 54).
pub const MIN_DARK_VARIANCE_DN2: f64 = 0.24;

/// Fewest exposure points in the linear range.
pub const MIN_LINEAR_POINTS: usize = 3;

/// Fewest exposure points in all: [`MIN_LINEAR_POINTS`] in the linear range, the saturation
/// point and one beyond it (where the variance has dropped).
pub const MIN_POINTS: usize = MIN_LINEAR_POINTS + 2;

/// A value with its standard uncertainty (one standard deviation, same unit).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// The value.
    pub value: f64,
    /// Its standard uncertainty, `>= 0`.
    pub uncertainty: f64,
}

/// Mean and temporal variance of one pair of frames (EMVA 1288 Release 4.0 Linear, Sec. 6,
/// Eqs. 16 and 18).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairStatistics {
    /// `(<A> + <B>) / 2`, DN.
    pub mean_dn: f64,
    /// `var(A - B) / 2` (sample variance, `n - 1`), DN^2: the temporal variance, without the
    /// fixed-pattern part.
    pub temporal_var_dn2: f64,
    /// Pixels per frame, `n`.
    pub pixels: usize,
}

/// The mean and temporal variance of two frames of equal size (EMVA 1288 Release 4.0 Linear,
/// Sec. 6, Eqs. 16 and 18): `mu = (<A> + <B>) / 2`, `sigma^2 = sum((d - <d>)^2) / (2 (n - 1))`
/// with `d = A - B`. Sums are exact (integer arithmetic). Errors: frames of different lengths or
/// fewer than 2 pixels (field `frames`).
pub fn pair_statistics(a: &[u16], b: &[u16]) -> Result<PairStatistics, ModelError> {
    if a.len() != b.len() || a.len() < 2 {
        return Err(ModelError::Invalid {
            field: "frames",
            reason: format!(
                "a pair of {} and {} pixels; allowed two frames of equal size, at least 2 pixels",
                a.len(),
                b.len()
            ),
        });
    }
    let (mut sum_a, mut sum_b, mut sum_d, mut sum_d2) = (0u128, 0u128, 0i128, 0u128);
    for (&x, &y) in a.iter().zip(b) {
        let d = i64::from(x) - i64::from(y);
        sum_a += u128::from(x);
        sum_b += u128::from(y);
        sum_d += i128::from(d);
        sum_d2 += u128::from(d.unsigned_abs() * d.unsigned_abs());
    }
    let n = a.len() as u128;
    // n sum d^2 - (sum d)^2 = n^2 * (biased variance) >= 0, exactly.
    let centred = n * sum_d2 - sum_d.unsigned_abs() * sum_d.unsigned_abs();
    let nf = n as f64;
    Ok(PairStatistics {
        mean_dn: (sum_a + sum_b) as f64 / (2.0 * nf),
        temporal_var_dn2: centred as f64 / (nf * (nf - 1.0)) / 2.0,
        pixels: a.len(),
    })
}

/// Statistics at one exposure: a dark pair and a flat-field pair taken at the same exposure time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ExposurePoint {
    /// Exposure time, microseconds, finite and `>= 0`.
    pub exposure_us: f64,
    /// Mean photons per pixel of the flat field, `mu_p`, finite and `>= 0`; `None` if not
    /// calibrated (then no QE).
    pub photons_per_pixel: Option<f64>,
    /// Dark mean `mu_y.dark`, DN, finite.
    pub dark_mean_dn: f64,
    /// Dark temporal variance `sigma_y.dark^2`, DN^2, finite and `>= 0`.
    pub dark_var_dn2: f64,
    /// Flat-field mean `mu_y`, DN, finite.
    pub flat_mean_dn: f64,
    /// Flat-field temporal variance `sigma_y^2`, DN^2, finite and `>= 0`.
    pub flat_var_dn2: f64,
    /// Pixels per frame behind each statistic, `n >= 2` (with several pairs averaged, pairs
    /// times pixels).
    pub pixels: usize,
}

/// One exposure point as the analysis used it (sorted by signal).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AnalyzedPoint {
    /// The input (its fields inline when serialised).
    #[serde(flatten)]
    pub point: ExposurePoint,
    /// `mu_y - mu_y.dark`, DN.
    pub signal_dn: f64,
    /// `sigma_y^2 - sigma_y.dark^2`, DN^2.
    pub signal_var_dn2: f64,
    /// In the photon-transfer fit.
    pub in_linear_range: bool,
    /// The saturation point (largest flat variance).
    pub saturation: bool,
}

/// The linear range the fits used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LinearRange {
    /// Points in it.
    pub points: usize,
    /// Its upper limit on `mu_y - mu_y.dark`, DN: [`LINEAR_RANGE_FRACTION`] of the saturation
    /// signal.
    pub max_signal_dn: f64,
    /// Smallest and largest `mu_y - mu_y.dark` fitted, DN.
    pub signal_dn: [f64; 2],
    /// Smallest and largest exposure time fitted, microseconds.
    pub exposure_us: [f64; 2],
}

/// The result of [`photon_transfer`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhotonTransfer {
    /// System gain `K`, DN per electron.
    pub k_dn_per_e: Estimate,
    /// Read noise `sigma_d`, electrons rms, without dark-current shot noise (the camera file's
    /// `read_noise_e`); an upper limit when `read_noise_is_upper_limit`.
    pub read_noise_e: Estimate,
    /// The dark variance was below [`MIN_DARK_VARIANCE_DN2`]: `read_noise_e` is the standard's
    /// upper limit, not a measurement.
    pub read_noise_is_upper_limit: bool,
    /// Dark variance extrapolated to zero exposure, `sigma_y.dark^2(0)`, DN^2.
    pub dark_var_at_zero_dn2: Estimate,
    /// Dark current `mu_I`, electrons per second; `None` when every dark was taken at one
    /// exposure time.
    pub dark_current_e_per_s: Option<Estimate>,
    /// Offset `b`: the dark mean extrapolated to zero exposure, DN.
    pub offset_dn: Estimate,
    /// Saturation capacity `mu_e.sat`, electrons.
    pub saturation_capacity_e: Estimate,
    /// Mean at the saturation point, `mu_y.sat`, DN.
    pub saturation_mean_dn: f64,
    /// Responsivity `R`, DN per photon; `None` without photon counts.
    pub responsivity_dn_per_photon: Option<Estimate>,
    /// Quantum efficiency `eta = R / K`; `None` without photon counts.
    pub qe: Option<Estimate>,
    /// The linear range.
    pub linear_range: LinearRange,
    /// Every point, sorted by `mu_y - mu_y.dark`.
    pub points: Vec<AnalyzedPoint>,
    /// What was assumed or could not be measured, in words.
    pub warnings: Vec<String>,
}

fn invalid(field: &'static str, reason: String) -> ModelError {
    ModelError::Invalid { field, reason }
}

fn check_point(i: usize, p: &ExposurePoint) -> Result<(), ModelError> {
    let at = |what: &str, v: f64, allowed: &str| {
        format!(
            "point {i} (exposure_us = {}): {what} = {v}; allowed {allowed}",
            p.exposure_us
        )
    };
    if !(p.exposure_us.is_finite() && p.exposure_us >= 0.0) {
        return Err(invalid(
            "points.exposure_us",
            at("exposure_us", p.exposure_us, "finite and >= 0"),
        ));
    }
    if let Some(ph) = p.photons_per_pixel {
        if !(ph.is_finite() && ph >= 0.0) {
            return Err(invalid(
                "points.photons_per_pixel",
                at("photons_per_pixel", ph, "finite and >= 0"),
            ));
        }
    }
    for (field, v) in [
        ("points.dark_mean_dn", p.dark_mean_dn),
        ("points.flat_mean_dn", p.flat_mean_dn),
    ] {
        if !v.is_finite() {
            return Err(invalid(field, at(&field[7..], v, "finite")));
        }
    }
    for (field, v) in [
        ("points.dark_var_dn2", p.dark_var_dn2),
        ("points.flat_var_dn2", p.flat_var_dn2),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(invalid(field, at(&field[7..], v, "finite and >= 0")));
        }
    }
    if p.pixels < 2 {
        return Err(invalid(
            "points.pixels",
            at("pixels", p.pixels as f64, "at least 2"),
        ));
    }
    Ok(())
}

/// A weighted fit: value and standard uncertainty of each parameter, and the reduced chi-square.
struct Fit {
    slope: Estimate,
    intercept: Estimate,
    chi2_red: f64,
}

/// Inflates a model variance by the reduced chi-square when the scatter exceeds the noise.
fn inflate(var_model: f64, chi2_red: f64) -> f64 {
    var_model * chi2_red.max(1.0)
}

/// Weighted least squares through the origin, `y = s x`, with data variances `v` (all > 0).
/// Needs at least one `x != 0`; the residual scale needs two points.
fn fit_origin(x: &[f64], y: &[f64], v: &[f64]) -> Option<Fit> {
    let sxx: f64 = x.iter().zip(v).map(|(x, v)| x * x / v).sum();
    let sxy: f64 = x.iter().zip(y).zip(v).map(|((x, y), v)| x * y / v).sum();
    if !(sxx > 0.0 && sxx.is_finite()) {
        return None;
    }
    let s = sxy / sxx;
    let dof = x.len().saturating_sub(1);
    let chi2: f64 = x
        .iter()
        .zip(y)
        .zip(v)
        .map(|((x, y), v)| (y - s * x).powi(2) / v)
        .sum();
    let chi2_red = if dof > 0 { chi2 / dof as f64 } else { 0.0 };
    Some(Fit {
        slope: Estimate {
            value: s,
            uncertainty: inflate(1.0 / sxx, chi2_red).sqrt(),
        },
        intercept: Estimate {
            value: 0.0,
            uncertainty: 0.0,
        },
        chi2_red,
    })
}

/// Weighted least squares of a line `y = a + s x`, with data variances `v` (all > 0), centred
/// on the weighted mean of `x` for accuracy. `None` when the `x` do not span an interval (then
/// only a weighted mean is possible, see [`weighted_mean`]).
fn fit_line(x: &[f64], y: &[f64], v: &[f64]) -> Option<Fit> {
    let sw: f64 = v.iter().map(|v| 1.0 / v).sum();
    let xm = x.iter().zip(v).map(|(x, v)| x / v).sum::<f64>() / sw;
    let ym = y.iter().zip(v).map(|(y, v)| y / v).sum::<f64>() / sw;
    let sxx: f64 = x.iter().zip(v).map(|(x, v)| (x - xm).powi(2) / v).sum();
    let sxy: f64 = x
        .iter()
        .zip(y)
        .zip(v)
        .map(|((x, y), v)| (x - xm) * (y - ym) / v)
        .sum();
    let span = x.iter().fold(0.0f64, |m, x| m.max((x - xm).abs()));
    if !(sxx > 0.0 && sxx.is_finite() && span > 1e-12 * xm.abs().max(1e-300)) {
        return None;
    }
    let s = sxy / sxx;
    let a = ym - s * xm;
    let dof = x.len().saturating_sub(2);
    let chi2: f64 = x
        .iter()
        .zip(y)
        .zip(v)
        .map(|((x, y), v)| (y - a - s * x).powi(2) / v)
        .sum();
    let chi2_red = if dof > 0 { chi2 / dof as f64 } else { 0.0 };
    Some(Fit {
        slope: Estimate {
            value: s,
            uncertainty: inflate(1.0 / sxx, chi2_red).sqrt(),
        },
        intercept: Estimate {
            value: a,
            uncertainty: inflate(1.0 / sw + xm * xm / sxx, chi2_red).sqrt(),
        },
        chi2_red,
    })
}

/// Weighted mean with its standard uncertainty (inflated by the scatter as [`fit_line`]).
fn weighted_mean(y: &[f64], v: &[f64]) -> Estimate {
    let sw: f64 = v.iter().map(|v| 1.0 / v).sum();
    let m = y.iter().zip(v).map(|(y, v)| y / v).sum::<f64>() / sw;
    let dof = y.len().saturating_sub(1);
    let chi2: f64 = y.iter().zip(v).map(|(y, v)| (y - m).powi(2) / v).sum();
    let chi2_red = if dof > 0 { chi2 / dof as f64 } else { 0.0 };
    Estimate {
        value: m,
        uncertainty: inflate(1.0 / sw, chi2_red).sqrt(),
    }
}

/// Sampling variance of a variance estimate `s2` from `n` values: `2 sigma^4 / (n - 1)`, with
/// `sigma^2` floored at the quantisation noise.
fn var_of_var(s2: f64, n: usize) -> f64 {
    let s2 = s2.max(QUANTIZATION_VARIANCE_DN2);
    2.0 * s2 * s2 / (n as f64 - 1.0)
}

/// Sampling variance of a pair's mean, `sigma^2 / (2 n)`, floored as [`var_of_var`].
fn var_of_mean(s2: f64, n: usize) -> f64 {
    s2.max(QUANTIZATION_VARIANCE_DN2) / (2.0 * n as f64)
}

/// `sqrt(a^2 + b^2)` of relative or absolute uncertainty terms.
fn quadrature(terms: &[f64]) -> f64 {
    terms.iter().map(|t| t * t).sum::<f64>().sqrt()
}

/// The EMVA 1288 photon-transfer analysis of `points` (see the module docs for the method and
/// the uncertainties). The points may come in any order; they are sorted by
/// `mu_y - mu_y.dark`.
///
/// Errors (all [`ModelError::Invalid`], naming the field and the point): fewer than
/// [`MIN_POINTS`] points; a point with a non-finite mean, a negative or non-finite variance or
/// exposure or photon count, or fewer than 2 pixels; no saturation (the largest flat variance at
/// the brightest point: the series must go past saturation); fewer than [`MIN_LINEAR_POINTS`]
/// points with signal up to 70 % of saturation; a photon-transfer slope `K <= 0`.
pub fn photon_transfer(points: &[ExposurePoint]) -> Result<PhotonTransfer, ModelError> {
    if points.len() < MIN_POINTS {
        return Err(invalid(
            "points",
            format!(
                "{} exposure points; allowed at least {MIN_POINTS} ({MIN_LINEAR_POINTS} in the \
                 linear range, the saturation point and one beyond it)",
                points.len()
            ),
        ));
    }
    for (i, p) in points.iter().enumerate() {
        check_point(i, p)?;
    }
    let mut warnings = Vec::new();
    let mut sorted: Vec<ExposurePoint> = points.to_vec();
    sorted.sort_by(|a, b| {
        (a.flat_mean_dn - a.dark_mean_dn).total_cmp(&(b.flat_mean_dn - b.dark_mean_dn))
    });
    let signal: Vec<f64> = sorted
        .iter()
        .map(|p| p.flat_mean_dn - p.dark_mean_dn)
        .collect();
    let signal_var: Vec<f64> = sorted
        .iter()
        .map(|p| p.flat_var_dn2 - p.dark_var_dn2)
        .collect();

    // Saturation: the largest temporal variance of the flats (the first one on ties).
    let i_sat = sorted.iter().enumerate().fold(0, |best, (i, p)| {
        if p.flat_var_dn2 > sorted[best].flat_var_dn2 {
            i
        } else {
            best
        }
    });
    if i_sat + 1 == sorted.len() {
        return Err(invalid(
            "points",
            format!(
                "no saturation: the flat-field variance rises up to the brightest point (mean \
                 {:.1} DN, variance {:.2} DN^2); allowed a series that goes past saturation, \
                 where the variance drops",
                sorted[i_sat].flat_mean_dn, sorted[i_sat].flat_var_dn2
            ),
        ));
    }
    let sat_signal = signal[i_sat];
    let max_signal_dn = LINEAR_RANGE_FRACTION * sat_signal;
    let linear: Vec<usize> = (0..i_sat)
        .filter(|&i| signal[i] > 0.0 && signal[i] <= max_signal_dn)
        .collect();
    if linear.len() < MIN_LINEAR_POINTS {
        return Err(invalid(
            "points",
            format!(
                "no linear range: {} point(s) with mu_y - mu_y.dark in (0, {max_signal_dn:.1}] \
                 DN (70 % of the saturation signal {sat_signal:.1} DN); allowed at least \
                 {MIN_LINEAR_POINTS}",
                linear.len()
            ),
        ));
    }

    // System gain: photon transfer through the origin.
    let x: Vec<f64> = linear.iter().map(|&i| signal[i]).collect();
    let y: Vec<f64> = linear.iter().map(|&i| signal_var[i]).collect();
    let v: Vec<f64> = linear
        .iter()
        .map(|&i| {
            let p = &sorted[i];
            var_of_var(p.flat_var_dn2, p.pixels) + var_of_var(p.dark_var_dn2, p.pixels)
        })
        .collect();
    let k_fit = fit_origin(&x, &y, &v).ok_or_else(|| {
        invalid(
            "points",
            "photon transfer: no signal in the linear range".to_string(),
        )
    })?;
    let k = k_fit.slope;
    if !(k.value > 0.0 && k.value.is_finite()) {
        return Err(invalid(
            "points",
            format!(
                "photon-transfer slope K = {} DN/e-; allowed > 0 (the flat-field variance must \
                 grow with the signal)",
                k.value
            ),
        ));
    }
    if k_fit.chi2_red > 4.0 {
        warnings.push(format!(
            "photon transfer: reduced chi-square {:.1} over the linear range (scatter beyond \
             the sampling noise: nonlinearity or unstable illumination); K's uncertainty is \
             inflated accordingly",
            k_fit.chi2_red
        ));
    }
    let rel_k = k.uncertainty / k.value;

    // Dark statistics: one per distinct dark pair (a dark pair shared by several flat levels at
    // one exposure time counts once).
    let mut darks: Vec<&ExposurePoint> = Vec::new();
    for p in &sorted {
        let same = |d: &&ExposurePoint| {
            d.exposure_us == p.exposure_us
                && d.dark_mean_dn == p.dark_mean_dn
                && d.dark_var_dn2 == p.dark_var_dn2
        };
        if !darks.iter().any(same) {
            darks.push(p);
        }
    }
    let t_s: Vec<f64> = darks.iter().map(|p| p.exposure_us * 1e-6).collect();
    let dark_mean: Vec<f64> = darks.iter().map(|p| p.dark_mean_dn).collect();
    let dark_var: Vec<f64> = darks.iter().map(|p| p.dark_var_dn2).collect();
    let v_mean: Vec<f64> = darks
        .iter()
        .map(|p| var_of_mean(p.dark_var_dn2, p.pixels))
        .collect();
    let v_var: Vec<f64> = darks
        .iter()
        .map(|p| var_of_var(p.dark_var_dn2, p.pixels))
        .collect();
    let (offset, dark_slope, var0) = match (
        fit_line(&t_s, &dark_mean, &v_mean),
        fit_line(&t_s, &dark_var, &v_var),
    ) {
        (Some(m), Some(s)) => (m.intercept, Some(m.slope), s.intercept),
        _ => {
            warnings.push(
                "every dark frame at one exposure time: no dark current; the offset and the \
                 read noise include the dark signal and its shot noise at that time"
                    .to_string(),
            );
            (
                weighted_mean(&dark_mean, &v_mean),
                None,
                weighted_mean(&dark_var, &v_var),
            )
        }
    };
    let dark_current_e_per_s = dark_slope.map(|s| {
        let value = s.value / k.value;
        Estimate {
            value,
            uncertainty: quadrature(&[s.uncertainty / k.value, value * rel_k]),
        }
    });
    if let Some(d) = dark_current_e_per_s {
        if d.value < -3.0 * d.uncertainty {
            warnings.push(format!(
                "dark current {:.3} e-/s is negative beyond 3 standard uncertainties ({:.3}): \
                 the dark level drifts",
                d.value, d.uncertainty
            ));
        }
    }

    // Read noise (temporal dark noise at zero exposure).
    let (read_noise_e, read_noise_is_upper_limit) = if var0.value >= MIN_DARK_VARIANCE_DN2 {
        let sd = (var0.value - QUANTIZATION_VARIANCE_DN2).sqrt() / k.value;
        let u = quadrature(&[
            var0.uncertainty / (2.0 * k.value * k.value * sd),
            sd * rel_k,
        ]);
        (
            Estimate {
                value: sd,
                uncertainty: u,
            },
            false,
        )
    } else {
        let sd = (MIN_DARK_VARIANCE_DN2 - QUANTIZATION_VARIANCE_DN2).sqrt() / k.value;
        warnings.push(format!(
            "dark variance at zero exposure {:.3} DN^2 is below {MIN_DARK_VARIANCE_DN2} DN^2: the \
             read noise is at the quantisation limit, and {sd:.3} e- is only an upper limit",
            var0.value
        ));
        (
            Estimate {
                value: sd,
                uncertainty: sd * rel_k,
            },
            true,
        )
    };

    // Saturation capacity, with the exposure grid's step around the variance peak.
    let lower = signal[i_sat.saturating_sub(1)];
    let upper = signal[i_sat + 1];
    let sat_e = sat_signal / k.value;
    let grid_e = (upper - lower).abs() / (2.0 * 12f64.sqrt()) / k.value;
    let saturation_capacity_e = Estimate {
        value: sat_e,
        uncertainty: quadrature(&[sat_e * rel_k, grid_e]),
    };

    // Responsivity and QE, if every linear point has a photon count.
    let photons: Vec<Option<f64>> = linear
        .iter()
        .map(|&i| sorted[i].photons_per_pixel)
        .collect();
    let (responsivity, qe) = if photons.iter().all(|p| p.is_some()) {
        let mp: Vec<f64> = photons.iter().map(|p| p.unwrap_or(0.0)).collect();
        let vm: Vec<f64> = linear
            .iter()
            .map(|&i| {
                let p = &sorted[i];
                var_of_mean(p.flat_var_dn2, p.pixels) + var_of_mean(p.dark_var_dn2, p.pixels)
            })
            .collect();
        match fit_origin(&mp, &x, &vm) {
            Some(r) if r.slope.value > 0.0 => {
                let eta = r.slope.value / k.value;
                if eta > 1.0 {
                    warnings.push(format!(
                        "quantum efficiency {eta:.3} > 1: check the photon counts"
                    ));
                }
                let qe = Estimate {
                    value: eta,
                    uncertainty: eta * quadrature(&[r.slope.uncertainty / r.slope.value, rel_k]),
                };
                (Some(r.slope), Some(qe))
            }
            _ => {
                warnings.push(
                    "photon counts give no positive responsivity: no quantum efficiency"
                        .to_string(),
                );
                (None, None)
            }
        }
    } else {
        if photons.iter().any(|p| p.is_some()) {
            warnings.push(
                "photons_per_pixel missing at some points of the linear range: no quantum \
                 efficiency"
                    .to_string(),
            );
        }
        (None, None)
    };

    let first = linear[0];
    let last = linear[linear.len() - 1];
    let exposures: Vec<f64> = linear.iter().map(|&i| sorted[i].exposure_us).collect();
    let linear_range = LinearRange {
        points: linear.len(),
        max_signal_dn,
        signal_dn: [signal[first], signal[last]],
        exposure_us: [
            exposures.iter().copied().fold(f64::INFINITY, f64::min),
            exposures.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        ],
    };
    let analyzed = sorted
        .iter()
        .enumerate()
        .map(|(i, p)| AnalyzedPoint {
            point: *p,
            signal_dn: signal[i],
            signal_var_dn2: signal_var[i],
            in_linear_range: linear.contains(&i),
            saturation: i == i_sat,
        })
        .collect();
    Ok(PhotonTransfer {
        k_dn_per_e: k,
        read_noise_e,
        read_noise_is_upper_limit,
        dark_var_at_zero_dn2: var0,
        dark_current_e_per_s,
        offset_dn: offset,
        saturation_capacity_e,
        saturation_mean_dn: sorted[i_sat].flat_mean_dn,
        responsivity_dn_per_photon: responsivity,
        qe,
        linear_range,
        points: analyzed,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Exact (noise-free) statistics of the EMVA linear model for a camera
    /// `[k, sd, mu_i, b, sat_e, eta]` (gain, read noise, dark current, offset, saturation in
    /// electrons, QE):
    /// `m` points with signal growing linearly in exposure to 95 % of saturation, then two
    /// clipped points whose variance has dropped.
    fn exact_points(truth: [f64; 6], m: usize, pixels: usize) -> Vec<ExposurePoint> {
        let [k, sd, mu_i, b, sat_e, eta] = truth;
        let t_top_s = 0.5;
        let mut pts = Vec::new();
        for i in 1..=m + 2 {
            let t = t_top_s * i as f64 / m as f64;
            let mu_e = 0.95 * sat_e * i as f64 / m as f64;
            let dark_e = mu_i * t;
            let dark_var = k * k * (sd * sd + dark_e) + QUANTIZATION_VARIANCE_DN2;
            let (flat_mean, flat_var) = if i <= m {
                (k * (mu_e + dark_e) + b, dark_var + k * k * mu_e)
            } else {
                // Past saturation: the mean sticks, the variance collapses.
                (k * sat_e + b, 0.1 * dark_var)
            };
            pts.push(ExposurePoint {
                exposure_us: t * 1e6,
                photons_per_pixel: Some(mu_e / eta),
                dark_mean_dn: k * dark_e + b,
                dark_var_dn2: dark_var,
                flat_mean_dn: flat_mean,
                flat_var_dn2: flat_var,
                pixels,
            });
        }
        pts
    }

    /// Exact points recover every parameter to rounding (1e-9 relative): the fits are exact
    /// when the data lie on the model. Saturation is the last unclipped point, 95 % of the
    /// capacity (the grid's own resolution), and the linear range holds the points up to 70 %.
    #[test]
    fn exact_points_recover_the_model() {
        let (k, sd, mu_i, b, sat_e, eta) = (0.35, 2.5, 3.0, 16.0, 10_000.0, 0.7);
        let pts = exact_points([k, sd, mu_i, b, sat_e, eta], 21, 65_536);
        let r = photon_transfer(&pts).unwrap();
        let rel = |a: f64, t: f64| ((a - t) / t).abs();
        assert!(rel(r.k_dn_per_e.value, k) < 1e-9, "{:?}", r.k_dn_per_e);
        assert!(rel(r.read_noise_e.value, sd) < 1e-9, "{:?}", r.read_noise_e);
        assert!(!r.read_noise_is_upper_limit);
        let dc = r.dark_current_e_per_s.unwrap();
        assert!(rel(dc.value, mu_i) < 1e-9, "{dc:?}");
        assert!(rel(r.offset_dn.value, b) < 1e-9, "{:?}", r.offset_dn);
        assert!(rel(r.qe.unwrap().value, eta) < 1e-9, "{:?}", r.qe);
        assert!(rel(r.saturation_capacity_e.value, 0.95 * sat_e) < 1e-9);
        // 70 % of 95 %: points i with 0.95 i / 21 <= 0.665, i <= 14.7.
        assert_eq!(r.linear_range.points, 14);
        assert!(r.points.iter().filter(|p| p.saturation).count() == 1);
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        // Exact data: the uncertainties are the sampling model's alone, finite and positive.
        for e in [r.k_dn_per_e, r.read_noise_e, dc, r.offset_dn] {
            assert!(e.uncertainty > 0.0 && e.uncertainty.is_finite(), "{e:?}");
        }
    }

    /// The sampling uncertainty shrinks as 1 / sqrt(pixels): 16 times the pixels, a quarter of
    /// the uncertainty of K, read noise, dark current and offset (within 1 %, the n - 1 terms).
    #[test]
    fn uncertainty_shrinks_with_more_pixels() {
        let truth = [0.1, 10.0, 1.0, 100.0, 40_000.0, 0.5];
        let small = photon_transfer(&exact_points(truth, 16, 4_096)).unwrap();
        let large = photon_transfer(&exact_points(truth, 16, 65_536)).unwrap();
        let pairs = [
            (small.k_dn_per_e, large.k_dn_per_e),
            (small.read_noise_e, large.read_noise_e),
            (
                small.dark_current_e_per_s.unwrap(),
                large.dark_current_e_per_s.unwrap(),
            ),
            (small.offset_dn, large.offset_dn),
        ];
        for (s, l) in pairs {
            let ratio = s.uncertainty / l.uncertainty;
            assert!((ratio / 4.0 - 1.0).abs() < 0.01, "{s:?} {l:?} {ratio}");
        }
    }

    /// Pair statistics: the difference cancels a fixed pattern exactly; the mean and variance
    /// of a hand-checked pair.
    #[test]
    fn pair_statistics_cancel_fixed_pattern() {
        let a = [10u16, 12, 14, 16];
        let b = [11u16, 12, 13, 16];
        let s = pair_statistics(&a, &b).unwrap();
        // d = [-1, 0, 1, 0], mean 0, sum d^2 = 2, var = 2 / 3, half = 1/3.
        assert!((s.mean_dn - 13.0).abs() < 1e-12);
        assert!((s.temporal_var_dn2 - 1.0 / 3.0).abs() < 1e-12);
        let pattern = [100u16, 0, 300, 7];
        let pa: Vec<u16> = a.iter().zip(pattern).map(|(x, p)| x + p).collect();
        let pb: Vec<u16> = b.iter().zip(pattern).map(|(x, p)| x + p).collect();
        let sp = pair_statistics(&pa, &pb).unwrap();
        assert_eq!(sp.temporal_var_dn2, s.temporal_var_dn2);
        assert!(pair_statistics(&a, &b[..3])
            .unwrap_err()
            .to_string()
            .contains("frames"));
    }

    /// Bad inputs are errors naming the field: too few points, a negative variance, a NaN
    /// mean, a series that never saturates, no linear range, no signal-dependent noise.
    #[test]
    fn errors_name_the_field() {
        let good = exact_points([0.35, 2.5, 3.0, 16.0, 10_000.0, 0.7], 20, 65_536);
        let msg = |pts: &[ExposurePoint]| photon_transfer(pts).unwrap_err().to_string();
        assert!(msg(&good[..4]).contains("at least 5"));
        let mut bad = good.clone();
        bad[3].flat_var_dn2 = -1.0;
        let m = msg(&bad);
        assert!(m.contains("points.flat_var_dn2") && m.contains("-1"), "{m}");
        let mut bad = good.clone();
        bad[2].dark_mean_dn = f64::NAN;
        assert!(msg(&bad).contains("points.dark_mean_dn"));
        let mut bad = good.clone();
        bad[0].pixels = 1;
        assert!(msg(&bad).contains("points.pixels"));
        // Drop the clipped points: the variance rises to the end.
        assert!(msg(&good[..20]).contains("no saturation"));
        // Saturation at the second point: nothing below 70 % of it but one point.
        let mut bad = good.clone();
        bad[1].flat_var_dn2 = 1e9;
        assert!(msg(&bad).contains("no linear range"));
        // Flat variance equal to the dark: no photon transfer.
        let mut bad = good.clone();
        for p in bad.iter_mut().take(15) {
            p.flat_var_dn2 = p.dark_var_dn2;
        }
        bad[15].flat_var_dn2 = 1e6;
        assert!(msg(&bad).contains("K = 0"), "{}", msg(&bad));
    }

    /// A dark variance below 0.24 DN^2 gives the standard's upper limit with a warning; darks
    /// at one exposure time give no dark current and say so.
    #[test]
    fn quantisation_limit_and_single_dark_time() {
        // K = 0.05, sigma_d = 2: dark variance 0.01 + 1/12 < 0.24.
        let pts = exact_points([0.05, 2.0, 0.0, 50.0, 40_000.0, 0.5], 12, 65_536);
        let r = photon_transfer(&pts).unwrap();
        assert!(r.read_noise_is_upper_limit);
        let limit = (0.24f64 - 1.0 / 12.0).sqrt() / 0.05;
        assert!((r.read_noise_e.value - limit).abs() < 1e-9 * limit);
        assert!(r.warnings.iter().any(|w| w.contains("upper limit")));
        let mut pts = exact_points([0.35, 2.5, 0.0, 16.0, 10_000.0, 0.7], 12, 65_536);
        for p in &mut pts {
            p.exposure_us = 1000.0;
        }
        let r = photon_transfer(&pts).unwrap();
        assert!(r.dark_current_e_per_s.is_none());
        assert!((r.k_dn_per_e.value - 0.35).abs() < 1e-9);
        assert!(r.warnings.iter().any(|w| w.contains("one exposure time")));
    }

    fn cmos() -> crate::sensor::Camera {
        crate::sensor::Camera::from_toml_str(include_str!(
            "../../../examples/cameras/cmos_modern.toml"
        ))
        .unwrap()
    }

    /// The frame simulator against the EMVA linear model on the shipped CMOS (K = 0.35,
    /// sigma_d = 2.5 e-, mu_I = 3 e-/s, b = 16 DN): 2^18 pixels at 4000 e- and 0.5 s, with a 1 %
    /// PRNU pattern. The pair mean is within 5 standard errors of `K (mu_e + mu_I t) + b`; the
    /// pair's temporal variance within 5 standard errors (`sqrt(2 / (n - 1))` relative, 0.28 %) of
    /// `K^2 (sigma_d^2 + mu_I t + mu_e) + 1/12`, so the pair difference cancelled the PRNU (whose
    /// spatial variance, `(0.01 * 4000 * 0.35)^2 = 196 DN^2`, is 40 % of the temporal one).
    #[test]
    fn expose_pixels_follows_the_linear_model() {
        use crate::montecarlo::{expose_pixels, fixed_pattern};
        let cam = cmos();
        let n = 1 << 18;
        let (mu_e, t) = (4000.0, 0.5);
        let prnu = fixed_pattern(n, 0.01, 3).unwrap();
        let means: Vec<f64> = prnu.iter().map(|p| mu_e * (1.0 + p)).collect();
        let a = expose_pixels(&cam, &means, t, 1).unwrap();
        let b = expose_pixels(&cam, &means, t, 2).unwrap();
        let s = pair_statistics(&a, &b).unwrap();
        let k = cam.gain_dn_per_e;
        let dark_e = cam.dark_current_e_per_s * t;
        let var = k * k * (cam.read_noise_e.powi(2) + dark_e + mu_e) + QUANTIZATION_VARIANCE_DN2;
        let mean = k * (mu_e + dark_e) + cam.offset_dn;
        let se_mean = (var / (2.0 * n as f64)).sqrt();
        assert!((s.mean_dn - mean).abs() < 5.0 * se_mean, "{s:?} {mean}");
        let se_var = var * (2.0 / (n as f64 - 1.0)).sqrt();
        assert!(
            (s.temporal_var_dn2 - var).abs() < 5.0 * se_var,
            "{s:?} {var}"
        );
        // Deterministic for a seed, different across seeds.
        assert_eq!(a, expose_pixels(&cam, &means, t, 1).unwrap());
        assert_ne!(a, b);
        // The pattern has zero mean (to rounding) and the asked rms within 1 % (its relative
        // standard error is sqrt(1 / n) = 0.2 %).
        let sum: f64 = prnu.iter().sum();
        assert!(sum.abs() < 1e-12 * n as f64, "{sum}");
        let rms = (prnu.iter().map(|p| p * p).sum::<f64>() / n as f64).sqrt();
        assert!((rms / 0.01 - 1.0).abs() < 0.01, "{rms}");
    }

    /// Far past the full well every pixel sits at `K full_well + b` (rounded, read noise
    /// aside); inputs out of range are errors naming the field and the pixel.
    #[test]
    fn expose_pixels_clips_and_checks() {
        use crate::montecarlo::expose_pixels;
        let cam = cmos();
        let frame = expose_pixels(&cam, &[1e7; 1000], 0.1, 5).unwrap();
        let clip = cam.gain_dn_per_e * cam.full_well_e + cam.offset_dn;
        let spread = 6.0 * cam.gain_dn_per_e * cam.read_noise_e + 1.0;
        assert!(frame.iter().all(|&y| (f64::from(y) - clip).abs() <= spread));
        let e = expose_pixels(&cam, &[1.0, 2.0, 3.0, f64::NAN], 0.1, 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("mean_photoelectrons") && e.contains("pixel 3"),
            "{e}"
        );
        let e = expose_pixels(&cam, &[1.0], -1.0, 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("t_int_s"), "{e}");
        assert!(expose_pixels(&cam, &[], 0.1, 1)
            .unwrap_err()
            .to_string()
            .contains("mean_photoelectrons"));
        let mut bad = cam.clone();
        bad.gain_dn_per_e = -1.0;
        assert!(expose_pixels(&bad, &[1.0], 0.1, 1)
            .unwrap_err()
            .to_string()
            .contains("gain_dn_per_e"));
    }
}
