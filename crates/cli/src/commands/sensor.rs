//! The sensor and detection: the frames' mean and covariance (`model sensor`), the DoLP and AoP
//! statistics of a Stokes estimate (`model dolp-stats`) and a detector's ROC (`model roc`).

use super::error::CommandError;
use super::optics::analyzer_set;
use super::text::{compact, echo};
use clap::Args;
use polar_model::analyzer::AnalyzerModel;
use serde::Deserialize;
use serde_json::{json, Value};
use std::path::PathBuf;

/// `polarimeter model roc`: the analytic ROC of a detector for a target against a background,
/// each given by its mean and covariance (Stokes S0, S1, S2 when `angles_deg` is given, which
/// maps them to the intensities behind those analyzers; any feature space otherwise).
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RocArgs {
    /// Detector: mf (linear matched filter), rx (quadratic), dolp (DoLP threshold; needs
    /// Stokes means and covariances).
    #[arg(long)]
    pub detector: String,
    /// Target mean, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_mean: Vec<f64>,
    /// Target covariance, row-major, n*n values.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_cov: Vec<f64>,
    /// Background mean.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub background_mean: Vec<f64>,
    /// Background covariance, row-major.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub background_cov: Vec<f64>,
    /// Analyzer angles, degrees: the means and covariances are Stokes vectors, detected in the
    /// intensities behind these analyzers (mf, rx).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// False-alarm rate, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    #[serde(default = "default_pfa")]
    pub pfa: f64,
    /// Fraction of the pixel the target fills, [0, 1].
    #[arg(long, default_value_t = 1.0)]
    #[serde(default = "one")]
    pub fill_fraction: f64,
}

fn default_pfa() -> f64 {
    1e-3
}

fn one() -> f64 {
    1.0
}

fn class_stats(
    mean_field: &'static str,
    cov_field: &'static str,
    mean: &[f64],
    cov: &[f64],
) -> Result<polar_model::metrics::ClassStats, CommandError> {
    use nalgebra::{DMatrix, DVector};
    let n = mean.len();
    if n == 0 {
        return Err(CommandError::input(
            mean_field,
            " is empty: allowed 1 or more values",
        ));
    }
    if cov.len() != n * n {
        return Err(CommandError::input(
            cov_field,
            format!(
                " has {} values: allowed {} (a {n}x{n} matrix, row-major)",
                cov.len(),
                n * n
            ),
        ));
    }
    Ok(polar_model::metrics::ClassStats::new(
        cov_field,
        DVector::from_column_slice(mean),
        DMatrix::from_row_slice(n, n, cov),
    )?)
}

/// Evaluates [`RocArgs`].
pub fn roc(a: &RocArgs) -> Result<Value, CommandError> {
    use polar_model::metrics;
    let t = class_stats("target_mean", "target_cov", &a.target_mean, &a.target_cov)?;
    let b = class_stats(
        "background_mean",
        "background_cov",
        &a.background_mean,
        &a.background_cov,
    )?;
    let t = t.mixed(&b, a.fill_fraction).map_err(CommandError::from)?;
    if a.detector == "dolp" {
        // Each class's DoLP moments from its Stokes mean and covariance.
        use polar_model::stats::{dolp_aop_stats, RegimeChoice};
        if t.mean.len() != 3 {
            return Err(CommandError::input(
                "target_mean",
                format!(
                    " has {} values: the dolp detector needs Stokes S0,S1,S2",
                    t.mean.len()
                ),
            ));
        }
        let moments = |c: &metrics::ClassStats| -> Result<(f64, f64, Vec<String>), CommandError> {
            let mean = nalgebra::Vector3::new(c.mean[0], c.mean[1], c.mean[2]);
            let cov = nalgebra::Matrix3::from_fn(|i, j| c.cov[(i, j)]);
            let s = dolp_aop_stats(&mean, &cov, RegimeChoice::Auto)?;
            Ok((s.dolp_mean, s.dolp_std, s.warnings))
        };
        let (mt, st, mut warnings) = moments(&t)?;
        let (mb, sb, wb) = moments(&b)?;
        warnings.extend(wb);
        let r = metrics::dolp_threshold((mt, st), (mb, sb), a.pfa)?;
        warnings.extend(r.warnings.iter().cloned());
        return Ok(json!({
            "pd": r.pd,
            "pfa": r.pfa,
            "scr": r.scr,
            "curve": r.curve,
            "target_dolp": [mt, st],
            "background_dolp": [mb, sb],
            "warnings": warnings,
        }));
    }
    let (t, b) = if a.angles_deg.is_empty() {
        (t, b)
    } else {
        if t.mean.len() != 3 {
            return Err(CommandError::input(
                "target_mean",
                format!(
                    " has {} values: with angles_deg allowed 3 (S0, S1, S2)",
                    t.mean.len()
                ),
            ));
        }
        let set = analyzer_set(&a.angles_deg, &AnalyzerModel::IDEAL)?;
        let w = set.intensities_from_stokes();
        let to_intensity = |c: &metrics::ClassStats| metrics::ClassStats {
            mean: w * &c.mean,
            cov: w * &c.cov * w.transpose(),
        };
        (to_intensity(&t), to_intensity(&b))
    };
    let r = match a.detector.as_str() {
        "mf" => metrics::matched_filter(&t, &b, a.pfa)?,
        "rx" => metrics::rx(&t, &b, a.pfa)?,
        other => {
            return Err(CommandError::input(
                "detector",
                format!(" = {} is invalid: allowed mf, rx, dolp", echo(other)),
            ))
        }
    };
    Ok(json!({
        "pd": r.pd,
        "pfa": r.pfa,
        "scr": r.scr,
        "curve": r.curve,
        "condition_number": r.condition_number,
        "pd_error": r.pd_error,
        "warnings": r.warnings,
    }))
}

/// `polarimeter model sensor`: the N frames' mean and covariance in DN for a scene radiance
/// seen through a camera (TOML file) behind analyzers at the given angles.
#[derive(Debug, Clone, Args)]
pub struct SensorArgs {
    /// Camera description (TOML; examples in examples/cameras/).
    #[arg(long)]
    pub camera: PathBuf,
    /// Analyzer angles, degrees, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angles_deg: Vec<f64>,
    /// Mean band Stokes radiance S0,S1,S2, W m^-2 sr^-1.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub radiance_mean: Vec<f64>,
    /// Its covariance (scene clutter), 9 values row-major, (W m^-2 sr^-1)^2; default none.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub radiance_cov: Vec<f64>,
    /// Integration time, ms.
    #[arg(long, allow_hyphen_values = true)]
    pub t_int_ms: f64,
    /// Spectral band, nm: lower,upper (flat response).
    #[arg(long, value_delimiter = ',', default_values_t = [500.0, 600.0])]
    pub band_nm: Vec<f64>,
    /// Sensor noise factor F_n (scales the sensor noise variance, or with
    /// --noise-factor-scales std its standard deviation).
    #[arg(long, default_value_t = 1.0)]
    pub noise_factor: f64,
    /// What the noise factor scales: variance or std.
    #[arg(long, default_value = "variance")]
    pub noise_factor_scales: String,
    /// Relative frame-to-frame calibration drift, [0, 1].
    #[arg(long, default_value_t = 0.0)]
    pub drift: f64,
    /// Frame sets for a Monte Carlo of the whole chain (0: none), up to 1e7.
    #[arg(long, default_value_t = 0,
          value_parser = crate::count_arg::range(0, polar_model::montecarlo::MAX_SETS))]
    pub monte_carlo: usize,
    /// Monte Carlo seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Evaluates [`SensorArgs`].
pub fn sensor(a: &SensorArgs) -> Result<Value, CommandError> {
    use polar_model::sensor::{Camera, Exposure, NoiseFactor, SensorModel};
    let text = std::fs::read_to_string(&a.camera).map_err(|e| {
        CommandError::input(
            "--camera",
            format!(" {}: cannot read: {e}", a.camera.display()),
        )
    })?;
    let camera = Camera::from_toml_str(&text)
        .map_err(|e| CommandError::input("--camera", format!(" {}: {e}", a.camera.display())))?;
    let [lo, hi] = a.band_nm[..] else {
        return Err(CommandError::input(
            "band_nm",
            format!(" has {} values: allowed 2 (lower,upper)", a.band_nm.len()),
        ));
    };
    let band = polar_model::atmosphere::Band::flat(lo, hi)?;
    let model = SensorModel::new(&camera, &band)?;
    let [s0, s1, s2] = a.radiance_mean[..] else {
        return Err(CommandError::input(
            "radiance_mean",
            format!(
                " has {} values: allowed 3 (S0,S1,S2)",
                a.radiance_mean.len()
            ),
        ));
    };
    // The model checks seconds; the user gave milliseconds.
    if !(a.t_int_ms.is_finite() && a.t_int_ms > 0.0 && a.t_int_ms <= 1e8) {
        return Err(CommandError::input(
            "t_int_ms",
            format!(
                " = {} is out of range: allowed > 0 and <= 1e8 ms",
                compact(a.t_int_ms)
            ),
        ));
    }
    let mut exposure = Exposure::new(
        a.t_int_ms * 1e-3,
        polar_model::polarization::Stokes::new(s0, s1, s2),
    );
    match a.radiance_cov.len() {
        0 => {}
        9 => exposure.radiance_cov_w2_m4_sr2 = nalgebra::Matrix3::from_row_slice(&a.radiance_cov),
        n => {
            return Err(CommandError::input(
                "radiance_cov",
                format!(" has {n} values: allowed 9 (3x3 row-major) or none"),
            ))
        }
    }
    exposure.noise_factor = match a.noise_factor_scales.as_str() {
        "variance" => NoiseFactor::Variance(a.noise_factor),
        "std" => NoiseFactor::StdDev(a.noise_factor),
        other => {
            return Err(CommandError::input(
                "noise_factor_scales",
                format!(" = {} is invalid: allowed variance, std", echo(other)),
            ))
        }
    };
    exposure.eps_cal = a.drift;
    let angles: Vec<f64> = a.angles_deg.iter().map(|d| d.to_radians()).collect();
    let s = model.signal(&angles, &exposure)?;
    let rows = |m: &nalgebra::DMatrix<f64>| -> Vec<Vec<f64>> {
        (0..m.nrows())
            .map(|i| m.row(i).iter().copied().collect())
            .collect()
    };
    let v = |x: &nalgebra::DVector<f64>| x.iter().copied().collect::<Vec<f64>>();
    let mut warnings = model.warnings().to_vec();
    warnings.extend(s.warnings.iter().cloned());
    let mc = if a.monte_carlo > 0 {
        let mc = polar_model::montecarlo::simulate_frames(
            &model,
            &angles,
            &exposure,
            a.monte_carlo,
            a.seed,
        )?;
        json!({
            "sets": mc.sets,
            "seed": a.seed,
            "mean": v(&mc.mean_dn),
            "cov": rows(&mc.cov_dn),
            "saturated_fraction": mc.saturated_fraction,
        })
    } else {
        Value::Null
    };
    Ok(json!({
        "mc": mc,
        "mean": v(&s.mean_dn),
        "cov": rows(&s.cov_dn),
        "saturated": s.saturated,
        "saturation_dn": s.saturation_dn,
        "electrons": v(&s.electrons),
        "dark_electrons": s.dark_electrons,
        "variance_dn2": {
            "shot": v(&s.variance.shot_dn2),
            "dark": v(&s.variance.dark_dn2),
            "read": v(&s.variance.read_dn2),
            "quantization": v(&s.variance.quantization_dn2),
            "clutter": v(&s.variance.clutter_dn2),
            "drift": v(&s.variance.drift_dn2),
        },
        "w": rows(&s.intensities_from_stokes),
        "warnings": warnings,
    }))
}

/// `polarimeter model dolp-stats`: DoLP and AoP mean and spread of the Stokes estimate from
/// intensities with independent noise `sigma_i` behind ideal analyzers (the integration over the
/// Gaussian Stokes estimate at every polarised SNR, or on request the Taylor or Rice
/// approximation), optionally checked by a seeded Monte Carlo.
#[derive(Debug, Clone, Args)]
pub struct DolpStatsArgs {
    /// Analyzer angles, degrees.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angles_deg: Vec<f64>,
    /// The true Stokes vector S0,S1,S2 (intensity units).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub stokes: Vec<f64>,
    /// Standard deviation of each intensity, same units, > 0.
    #[arg(long)]
    pub sigma_i: f64,
    /// Method: auto (the integration, valid at every polarised SNR, with an error estimate),
    /// taylor (delta-method approximation) or rice (isotropic Rice approximation); the last two
    /// for comparison.
    #[arg(long, default_value = "auto")]
    pub regime: String,
    /// Monte Carlo samples for a check (0: none), up to 5e7.
    #[arg(long, default_value_t = 0,
          value_parser = crate::count_arg::range(0, polar_model::stats::MAX_MC_SAMPLES))]
    pub monte_carlo: usize,
    /// Monte Carlo seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// A Stokes mean, its covariance and the estimator's warnings.
type StokesMoments = (nalgebra::Vector3<f64>, nalgebra::Matrix3<f64>, Vec<String>);

/// The Stokes mean and covariance of [`DolpStatsArgs`].
fn stokes_moments(
    angles_deg: &[f64],
    stokes: &[f64],
    sigma_i: f64,
) -> Result<StokesMoments, CommandError> {
    let [s0, s1, s2] = stokes[..] else {
        return Err(CommandError::input(
            "stokes",
            format!(" has {} values: allowed 3 (S0,S1,S2)", stokes.len()),
        ));
    };
    if !(s0.is_finite() && s0 > 0.0 && s1.is_finite() && s2.is_finite()) {
        return Err(CommandError::input(
            "stokes",
            format!(
                " = {},{},{} is out of range: allowed finite values with S0 > 0",
                compact(s0),
                compact(s1),
                compact(s2)
            ),
        ));
    }
    let dolp = s1.hypot(s2) / s0;
    if dolp > 1.0 + 1e-12 {
        return Err(CommandError::input(
            "stokes",
            format!(
                " = {},{},{} has DoLP = sqrt(S1^2 + S2^2) / S0 = {}: allowed DoLP <= 1 \
             (a Stokes vector of light)",
                compact(s0),
                compact(s1),
                compact(s2),
                compact(dolp)
            ),
        ));
    }
    if !(sigma_i.is_finite() && sigma_i > 0.0) {
        return Err(CommandError::input(
            "sigma_i",
            format!(
                " = {} is out of range: allowed > 0 and finite",
                compact(sigma_i)
            ),
        ));
    }
    let set = analyzer_set(angles_deg, &AnalyzerModel::IDEAL)?;
    let w = set.intensities_from_stokes();
    let n = w.nrows();
    let cov_i = nalgebra::DMatrix::<f64>::identity(n, n) * (sigma_i * sigma_i);
    let est = polar_model::stats::stokes_cov_from_intensity_cov(w, &cov_i)?;
    Ok((nalgebra::Vector3::new(s0, s1, s2), est.cov, est.warnings))
}

/// Evaluates [`DolpStatsArgs`].
pub fn dolp_stats(a: &DolpStatsArgs) -> Result<Value, CommandError> {
    use polar_model::stats::{self, Regime, RegimeChoice, StatsMethod};
    let (mean, cov, mut warnings) = stokes_moments(&a.angles_deg, &a.stokes, a.sigma_i)?;
    let choice = match a.regime.as_str() {
        "auto" => RegimeChoice::Auto,
        "taylor" => RegimeChoice::Taylor,
        "rice" => RegimeChoice::Rice,
        other => {
            return Err(CommandError::input(
                "regime",
                format!(" = {} is invalid: allowed auto, taylor, rice", echo(other)),
            ))
        }
    };
    let s = stats::dolp_aop_stats(&mean, &cov, choice)?;
    warnings.extend(s.warnings.iter().cloned());
    let mut out = json!({
        "mean": s.dolp_mean,
        "std": s.dolp_std,
        "aop_mean_deg": s.aop_mean_rad.to_degrees(),
        "aop_std_deg": s.aop_std_rad.to_degrees(),
        "aop_bias_deg": s.aop_bias_rad.to_degrees(),
        "method": match s.method {
            StatsMethod::Integration => "integration",
            StatsMethod::Taylor => "taylor",
            StatsMethod::Rice => "rice",
        },
        "rel_error_estimate": s.rel_error_estimate,
        "regime": match s.regime { Regime::Taylor => "taylor", Regime::Rice => "rice" },
        "polarised_snr": s.polarised_snr,
        "sigma_p": s.sigma_p,
        "stokes_cov": (0..3).map(|i| (0..3).map(|j| cov[(i, j)]).collect::<Vec<f64>>()).collect::<Vec<_>>(),
        "warnings": warnings,
    });
    if a.monte_carlo > 0 {
        let mc = stats::monte_carlo_dolp_aop(&mean, &cov, a.monte_carlo, a.seed)?;
        out["mc"] = json!({
            "samples": a.monte_carlo,
            "seed": a.seed,
            "mean": mc.dolp_mean,
            "std": mc.dolp_std,
            "aop_std_deg": mc.aop_std_rad.to_degrees(),
        });
    }
    Ok(out)
}
