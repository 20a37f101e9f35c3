//! `polarimeter bench stats`: speed against error of the analytic DoLP and AoP statistics
//! (the integration, first-order Taylor, second-order Taylor mean, Rice) and of the whole-chain
//! Monte Carlo at
//! 1e3 .. 1e6 frame sets, for a few representative states, every error measured against a
//! reference Monte Carlo of the whole chain computed in the same run (seeded, 1e7 sets by
//! default). Then the "equal error" comparison: the Monte Carlo sets needed to match each
//! analytic answer's error (Monte Carlo error `c / sqrt(n)`, `c` fitted from the measured
//! points), their time, and the speed ratio.
//!
//! Times are medians of repeated runs (`std::time::Instant`), the Monte Carlo on one thread like
//! the analytic path; ratios are taken within one run.
//!
//! `polarimeter bench stats --grid`: the accuracy grid of the DoLP/AoP statistics against a
//! Monte Carlo of the Stokes estimate (at least 4e5 draws per state) over polarised SNR 0.5 .. 20,
//! three analyzer sets and isotropic, shot-noise and correlated intensity noise ([`run_grid`],
//! [`grid_markdown`]; with `--out`, [`write_grid_report`] writes docs/validation/dolp-aop-grid.md,
//! see [`GRID_COMMAND`]).

pub use crate::validation::GRID_COMMAND;
use crate::validation::{ValidationError, CAMERAS};
use polar_model::atmosphere::Band;
use polar_model::polarization::Stokes;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_model::stats::{dolp_aop_stats, MethodChoice, RegimeChoice, StatsMethod};
use polar_model::validation::{analytic_products, simulate_products, McConfig, McProducts};
use std::fmt::Write as _;
use std::hint::black_box;
use std::time::{Duration, Instant};

/// A state of the benchmark.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchState {
    /// What it represents.
    pub name: String,
    /// The camera through the band.
    pub model: SensorModel,
    /// Analyzer angles, degrees.
    pub angles_deg: Vec<f64>,
    /// The exposure.
    pub exposure: Exposure,
}

impl BenchState {
    fn angles_rad(&self) -> Vec<f64> {
        self.angles_deg.iter().map(|d| d.to_radians()).collect()
    }
}

/// The benchmark's states, all on the example CMOS camera through a flat 500-600 nm band:
/// high polarised SNR (Taylor; DoLP 0.3 at 4500 e-/frame, 0/45/90/135), moderate SNR (Taylor;
/// DoLP 0.3 at 500 e-/frame), low SNR (Rice; DoLP 0.02 at 4500 e-/frame, 0/60/120) and
/// unpolarised (Rice; 0/45/90/135).
pub fn states() -> Result<Vec<BenchState>, ValidationError> {
    let cam = Camera::from_toml_str(CAMERAS[1].2)?;
    let model = SensorModel::new(&cam, &Band::flat(500.0, 600.0)?)?;
    let make = |name: &str, angles_deg: &[f64], electrons: f64, dolp: f64, aop_deg: f64| {
        let angles: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
        let w = model.intensities_from_stokes(&angles)?;
        let s0 = 0.1;
        let t_int_s = electrons / (model.responsivity_e_per_s() * w.column(0).mean() * s0);
        let two_a = 2.0 * aop_deg.to_radians();
        Ok::<_, ValidationError>(BenchState {
            name: name.to_string(),
            model: model.clone(),
            angles_deg: angles_deg.to_vec(),
            exposure: Exposure::new(
                t_int_s,
                Stokes::new(s0, s0 * dolp * two_a.cos(), s0 * dolp * two_a.sin()),
            ),
        })
    };
    let four = [0.0, 45.0, 90.0, 135.0];
    Ok(vec![
        make("high SNR (Taylor)", &four, 4500.0, 0.3, 15.0)?,
        make("moderate SNR (Taylor)", &four, 500.0, 0.3, 15.0)?,
        make("low SNR (Rice)", &[0.0, 60.0, 120.0], 4500.0, 0.02, 15.0)?,
        make("unpolarised (Rice)", &four, 4500.0, 0.0, 0.0)?,
    ])
}

/// DoLP mean, DoLP std, AoP std.
type Triple = [f64; 3];

/// One row: an analytic method or a Monte Carlo size.
#[derive(Debug, Clone, PartialEq)]
pub struct BenchRow {
    /// Method label.
    pub method: String,
    /// Monte Carlo frame sets (0 for an analytic method).
    pub sets: usize,
    /// Whether this is the method the automatic choice uses (the integration).
    pub auto: bool,
    /// Median wall time of the whole path (sensor statistics, estimator, DoLP/AoP statistics;
    /// or the Monte Carlo on one thread).
    pub time: Duration,
    /// Median wall time of the DoLP/AoP statistics alone (analytic rows).
    pub stats_time: Option<Duration>,
    /// `[DoLP mean, DoLP std, AoP std]`.
    pub values: Triple,
    /// Relative errors against the reference.
    pub rel_errors: Triple,
    /// The largest of the three, or the reference's resolution when all three are below it.
    pub error: f64,
    /// Whether `error` is only the reference's resolution (the true error is smaller).
    pub unresolved: bool,
    /// Monte Carlo sets for the same error (`(c / error)^2`), analytic rows.
    pub equal_error_sets: Option<f64>,
    /// Their time (`tau` per set times the sets), analytic rows.
    pub equal_error_time: Option<Duration>,
    /// `equal_error_time / time`.
    pub speed_ratio: Option<f64>,
}

/// One state's result.
#[derive(Debug, Clone, PartialEq)]
pub struct StateResult {
    /// The state.
    pub name: String,
    /// Polarised SNR `p / sigma_p` of the analytic Stokes statistics.
    pub polarised_snr: f64,
    /// The reference's values.
    pub reference: Triple,
    /// Its relative resolution (twice its standard error over its value), per statistic.
    pub reference_resolution: Triple,
    /// Reference frame sets.
    pub reference_sets: usize,
    /// The fitted Monte Carlo error constant `c` (error `c / sqrt(n)`).
    pub mc_error_constant: f64,
    /// Monte Carlo time per frame set (one thread), from the largest run.
    pub mc_time_per_set: Duration,
    /// The rows.
    pub rows: Vec<BenchRow>,
}

fn triple(m: &McProducts) -> Triple {
    [m.dolp_mean, m.dolp_std, m.aop_std_rad]
}

/// Median of `runs` timed calls of `f`, at least `min_runs` and at least `min_time`.
fn median_time<T>(min_runs: usize, min_time: Duration, mut f: impl FnMut() -> T) -> Duration {
    let mut times = Vec::new();
    let start = Instant::now();
    while times.len() < min_runs || (start.elapsed() < min_time && times.len() < 100_000) {
        let t = Instant::now();
        black_box(f());
        times.push(t.elapsed());
    }
    times.sort();
    times[times.len() / 2]
}

/// Options of the benchmark.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchOptions {
    /// Reference frame sets (>= 1e7 for the report).
    pub reference_sets: usize,
    /// Largest Monte Carlo size exponent (`1e3 ..= 10^max_exponent`).
    pub max_exponent: u32,
    /// Seed.
    pub seed: u64,
    /// Minimum timing runs of each Monte Carlo size.
    pub min_runs: usize,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            reference_sets: 10_000_000,
            max_exponent: 6,
            seed: 1,
            min_runs: 3,
        }
    }
}

/// Runs the benchmark on `states`. Errors: the model's, or options out of range.
pub fn run(states: &[BenchState], opt: &BenchOptions) -> Result<Vec<StateResult>, ValidationError> {
    if !(3..=7).contains(&opt.max_exponent) {
        return Err(ValidationError::Invalid(format!(
            "max_exponent = {} is out of range: allowed 3 to 7",
            opt.max_exponent
        )));
    }
    if !(10usize.pow(opt.max_exponent)..=100_000_000).contains(&opt.reference_sets) {
        return Err(ValidationError::Invalid(format!(
            "reference_sets = {} is out of range: allowed 10^max_exponent to 1e8",
            opt.reference_sets
        )));
    }
    let mut out = Vec::new();
    for (k, st) in states.iter().enumerate() {
        out.push(run_state(st, opt, k as u64)?);
    }
    Ok(out)
}

fn run_state(st: &BenchState, opt: &BenchOptions, k: u64) -> Result<StateResult, ValidationError> {
    let angles = st.angles_rad();
    let ex = &st.exposure;
    let model = &st.model;
    // Reference: all threads, its own seed.
    let reference_mc = simulate_products(
        model,
        &angles,
        ex,
        &McConfig {
            threads: 0,
            ..McConfig::new(opt.reference_sets, opt.seed ^ 0x7265_6665_7265_6e63 ^ k)
        },
    )?;
    let reference = triple(&reference_mc);
    let ref_se = [
        reference_mc.dolp_mean_se,
        reference_mc.dolp_std_se,
        reference_mc.aop_std_se_rad,
    ];
    let reference_resolution: Triple =
        std::array::from_fn(|i| 2.0 * ref_se[i] / reference[i].abs().max(1e-300));
    let rel: &dyn Fn(&Triple) -> Triple =
        &|v| std::array::from_fn(|i| (v[i] - reference[i]) / reference[i].abs().max(1e-300));
    // An error is resolved when at least one statistic's error exceeds its resolution.
    let error_of = |r: &Triple| -> (f64, bool) {
        let resolved = (0..3).any(|i| r[i].abs() > reference_resolution[i]);
        if resolved {
            (r.iter().fold(0.0f64, |m, v| m.max(v.abs())), false)
        } else {
            (
                reference_resolution.iter().copied().fold(0.0, f64::max),
                true,
            )
        }
    };

    // Analytic methods.
    let auto = analytic_products(model, &angles, ex, MethodChoice::Auto, RegimeChoice::Auto)?;
    let mean_s = auto.stokes_mean_w_m2_sr;
    let cov_s = auto.estimator.cov;
    let mut rows = Vec::new();
    let analytic_min = Duration::from_millis(200);
    for (label, choice, first_order) in [
        ("Integration", RegimeChoice::Auto, false),
        ("Taylor, first order", RegimeChoice::Taylor, true),
        ("Taylor, second-order mean", RegimeChoice::Taylor, false),
        ("Rice", RegimeChoice::Rice, false),
    ] {
        let run = || -> Result<Triple, ValidationError> {
            let a = analytic_products(model, &angles, ex, MethodChoice::Auto, choice)?;
            let s = &a.stokes_mean_w_m2_sr;
            let mean = if first_order && a.stats.method == StatsMethod::Taylor {
                s[1].hypot(s[2]) / s[0]
            } else {
                a.stats.dolp_mean
            };
            Ok([mean, a.stats.dolp_std, a.stats.aop_std_rad])
        };
        let values = run()?;
        let method = dolp_aop_stats(&mean_s, &cov_s, choice)?.method;
        if choice == RegimeChoice::Taylor && method != StatsMethod::Taylor {
            // The Taylor forms are singular here (p = 0): the row would repeat Rice.
            continue;
        }
        let time = median_time(11, analytic_min, || run().ok());
        let stats_time = median_time(11, analytic_min, || {
            dolp_aop_stats(&mean_s, &cov_s, choice).ok()
        });
        let rel_errors = rel(&values);
        let (error, unresolved) = error_of(&rel_errors);
        rows.push(BenchRow {
            method: label.to_string(),
            sets: 0,
            auto: choice == RegimeChoice::Auto,
            time,
            stats_time: Some(stats_time),
            values,
            rel_errors,
            error,
            unresolved,
            equal_error_sets: None,
            equal_error_time: None,
            speed_ratio: None,
        });
    }

    // Monte Carlo sizes, one thread.
    let mut fit = Vec::new();
    let mut mc_time_per_set = Duration::ZERO;
    for e in 3..=opt.max_exponent {
        let sets = 10usize.pow(e);
        let cfg = McConfig {
            threads: 1,
            ..McConfig::new(sets, opt.seed.wrapping_add(1000 * (k + 1) + e as u64))
        };
        let mc = simulate_products(model, &angles, ex, &cfg)?;
        let min_time = Duration::from_millis(if e >= 6 { 0 } else { 300 });
        let time = median_time(opt.min_runs.max(1), min_time, || {
            simulate_products(model, &angles, ex, &cfg).ok()
        });
        let values = triple(&mc);
        let rel_errors = rel(&values);
        let max_err = rel_errors.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        fit.push((sets as f64, max_err));
        mc_time_per_set = time / sets as u32;
        let (error, unresolved) = error_of(&rel_errors);
        rows.push(BenchRow {
            method: "Monte Carlo, whole chain".to_string(),
            sets,
            auto: false,
            time,
            stats_time: None,
            values,
            rel_errors,
            error,
            unresolved,
            equal_error_sets: None,
            equal_error_time: None,
            speed_ratio: None,
        });
    }
    // c = sqrt(mean(err^2 n)): the least-squares fit of err^2 = c^2 / n in the squared errors'
    // scale.
    let c = (fit.iter().map(|(n, e)| e * e * n).sum::<f64>() / fit.len().max(1) as f64).sqrt();
    let tau = mc_time_per_set.as_secs_f64();
    for r in rows.iter_mut().filter(|r| r.sets == 0) {
        let n = (c / r.error).powi(2);
        // Finite unless every measured Monte Carlo error was exactly 0 or the analytic one is.
        if let Ok(t) = Duration::try_from_secs_f64((tau * n).min(1e9)) {
            r.equal_error_sets = Some(n);
            r.equal_error_time = Some(t);
            r.speed_ratio = Some(t.as_secs_f64() / r.time.as_secs_f64().max(1e-12));
        }
    }
    Ok(StateResult {
        name: st.name.clone(),
        polarised_snr: auto.stats.polarised_snr,
        reference,
        reference_resolution,
        reference_sets: opt.reference_sets,
        mc_error_constant: c,
        mc_time_per_set,
        rows,
    })
}

fn fmt_time(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 1.0 {
        format!("{s:.2} s")
    } else if s >= 1e-3 {
        format!("{:.2} ms", s * 1e3)
    } else {
        format!("{:.2} us", s * 1e6)
    }
}

fn sci(x: f64) -> String {
    format!("{x:.1e}")
}

/// The results as Markdown.
pub fn markdown(results: &[StateResult], opt: &BenchOptions) -> String {
    let mut o = String::new();
    let _ = writeln!(
        o,
        "Reference: whole-chain Monte Carlo, {} frame sets per state (seeded, all threads); \
         errors are relative errors against it. When every statistic's error is below twice \
         the reference's standard error the error is shown as `< resolution` and the equal-error \
         sets and ratio are lower bounds (`>=`). Monte Carlo rows: one thread, median of at least \
         {} runs. Analytic rows: the whole path (sensor statistics, GLS estimator, DoLP/AoP \
         statistics), median of many runs; \"stats only\" is `dolp_aop_stats` alone. The \
         automatic method's row (the integration) is in bold.\n",
        opt.reference_sets, opt.min_runs
    );
    for r in results {
        let _ = writeln!(
            o,
            "**{}** (polarised SNR {:.2}; reference DoLP mean {:.5}, DoLP std {:.5}, AoP std \
             {:.3} deg; MC error ~ {:.3} / sqrt(n); MC {:.0} ns per set)\n",
            r.name,
            r.polarised_snr,
            r.reference[0],
            r.reference[1],
            r.reference[2].to_degrees(),
            r.mc_error_constant,
            r.mc_time_per_set.as_secs_f64() * 1e9
        );
        o += "| method | sets | time | stats only | DoLP mean err. | DoLP std err. | AoP std err. | error | MC sets at equal error | MC time at equal error | speed ratio |\n";
        o += "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n";
        for row in &r.rows {
            let bound = if row.unresolved { ">= " } else { "" };
            let name = if row.auto {
                format!("**{}**", row.method)
            } else {
                row.method.clone()
            };
            let _ = writeln!(
                o,
                "| {name} | {} | {} | {} | {:+.2e} | {:+.2e} | {:+.2e} | {}{} | {} | {} | {} |",
                if row.sets == 0 {
                    "-".to_string()
                } else {
                    sci(row.sets as f64)
                },
                fmt_time(row.time),
                row.stats_time.map(fmt_time).unwrap_or_else(|| "-".into()),
                row.rel_errors[0],
                row.rel_errors[1],
                row.rel_errors[2],
                if row.unresolved { "< " } else { "" },
                sci(row.error),
                row.equal_error_sets
                    .map(|n| format!("{bound}{}", sci(n)))
                    .unwrap_or_else(|| "-".into()),
                row.equal_error_time
                    .map(|t| format!("{bound}{}", fmt_time(t)))
                    .unwrap_or_else(|| "-".into()),
                row.speed_ratio
                    .map(|s| format!("{bound}{}", sci(s)))
                    .unwrap_or_else(|| "-".into()),
            );
        }
        o += "\n";
    }
    o
}

// ---------------------------------------------------------------------------------------------
// Accuracy grid: `polarimeter bench stats --grid`
// ---------------------------------------------------------------------------------------------

/// Polarised SNRs of the accuracy grid.
pub const GRID_SNRS: [f64; 12] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 7.0, 10.0, 20.0];

/// Analyzer sets of the accuracy grid, degrees.
pub const GRID_SETS: [&[f64]; 3] = [
    &[0.0, 60.0, 120.0],
    &[0.0, 45.0, 90.0, 135.0],
    &[0.0, 36.0, 72.0, 108.0, 144.0],
];

/// Smallest Monte Carlo draws per grid state.
pub const GRID_MIN_SAMPLES: usize = 400_000;

/// The intensity noise of a grid state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridNoise {
    /// `Sigma_I = 27.2^2 I` (OLS; isotropic `(S1, S2)` noise for these symmetric sets).
    Isotropic,
    /// Shot noise plus read noise 10: `Sigma_I = diag(100 + I_k)`, `I_k` the frame's mean
    /// intensity (GLS; anisotropic `(S1, S2)` noise growing with the DoLP, `S0` correlated).
    Shot,
    /// `27.2^2` with frame 0 four times noisier and neighbouring frames correlated 0.3 (GLS;
    /// anisotropic and correlated at every SNR).
    Correlated,
}

impl GridNoise {
    fn name(self) -> &'static str {
        match self {
            GridNoise::Isotropic => "isotropic",
            GridNoise::Shot => "shot",
            GridNoise::Correlated => "correlated",
        }
    }

    fn intensity_cov(self, intensities: &[f64]) -> nalgebra::DMatrix<f64> {
        let n = intensities.len();
        let var = 27.2f64 * 27.2;
        match self {
            GridNoise::Isotropic => nalgebra::DMatrix::identity(n, n) * var,
            GridNoise::Shot => nalgebra::DMatrix::from_fn(n, n, |i, j| {
                if i == j {
                    100.0 + intensities[i].max(0.0)
                } else {
                    0.0
                }
            }),
            GridNoise::Correlated => {
                let sd: Vec<f64> = (0..n)
                    .map(|k| if k == 0 { 2.0 } else { 1.0 } * var.sqrt())
                    .collect();
                nalgebra::DMatrix::from_fn(n, n, |i, j| {
                    if i == j {
                        sd[i] * sd[i]
                    } else if i.abs_diff(j) == 1 {
                        0.3 * sd[i] * sd[j]
                    } else {
                        0.0
                    }
                })
            }
        }
    }
}

/// One state of the accuracy grid and its comparison.
#[derive(Debug, Clone, PartialEq)]
pub struct GridRow {
    /// Analyzer angles, degrees.
    pub angles_deg: Vec<f64>,
    /// The noise.
    pub noise: GridNoise,
    /// Polarised SNR asked for and obtained.
    pub polarised_snr: f64,
    /// DoLP of the mean Stokes vector.
    pub dolp: f64,
    /// Ratio of the `(S1, S2)` covariance's eigenvalues (1 = isotropic).
    pub anisotropy: f64,
    /// Largest `|corr(S0, S1 or S2)|`.
    pub s0_correlation: f64,
    /// Predicted `[DoLP mean, DoLP std, AoP std]` (the integration).
    pub predicted: Triple,
    /// The integration's estimated relative error.
    pub predicted_error: f64,
    /// The closed-form approximation's `[DoLP mean, DoLP std, AoP std]` (Rice below polarised
    /// SNR 3, Taylor above).
    pub approximation: Triple,
    /// Monte Carlo `[DoLP mean, DoLP std, AoP std]`.
    pub monte_carlo: Triple,
    /// Their standard errors.
    pub monte_carlo_se: Triple,
}

impl GridRow {
    /// Relative errors of the prediction against the Monte Carlo.
    pub fn rel_errors(&self) -> Triple {
        std::array::from_fn(|i| (self.predicted[i] - self.monte_carlo[i]) / self.monte_carlo[i])
    }

    /// The same in Monte Carlo standard errors.
    pub fn z_scores(&self) -> Triple {
        std::array::from_fn(|i| (self.predicted[i] - self.monte_carlo[i]) / self.monte_carlo_se[i])
    }

    /// Relative errors of the closed-form approximation against the Monte Carlo.
    pub fn approximation_rel_errors(&self) -> Triple {
        std::array::from_fn(|i| (self.approximation[i] - self.monte_carlo[i]) / self.monte_carlo[i])
    }
}

/// The Stokes mean (S0 = 1000, AoP 20 deg) of polarised SNR `snr` and its covariance for
/// `noise` through ideal analyzers at `angles_deg`; the shot-noise covariance depends on the
/// mean, so `p` is found by fixed-point iteration `p = snr sigma_p(p)` (a contraction: `sigma_p`
/// changes by well under 1 % per unit of `p / S0`).
fn grid_state(
    angles_deg: &[f64],
    noise: GridNoise,
    snr: f64,
) -> Result<(nalgebra::Vector3<f64>, nalgebra::Matrix3<f64>), ValidationError> {
    use polar_model::analyzer::AnalyzerSet;
    use polar_model::stats::StokesEstimator;
    let angles: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
    let set = AnalyzerSet::ideal(&angles)?;
    let s0 = 1000.0;
    let two_a = 2.0 * 20f64.to_radians();
    let mut p = 0.0;
    let mut out = None;
    for _ in 0..60 {
        let mean = Stokes::new(s0, p * two_a.cos(), p * two_a.sin());
        let cov_i = noise.intensity_cov(set.intensities(&mean).as_slice());
        let cov = StokesEstimator::for_analyzers(&set, &cov_i, MethodChoice::Auto)?.cov;
        let sigma_p = (0.5 * (cov[(1, 1)] + cov[(2, 2)])).sqrt();
        let next = snr * sigma_p;
        out = Some((mean.0, cov));
        if (next - p).abs() <= 1e-12 * next {
            break;
        }
        p = next;
    }
    out.ok_or_else(|| ValidationError::Invalid("grid state did not converge".into()))
}

/// Runs the accuracy grid: every SNR of [`GRID_SNRS`], set of [`GRID_SETS`] and noise, the
/// prediction ([`dolp_aop_stats`], automatic method) against `samples` Monte Carlo draws of the
/// Stokes estimate ([`polar_model::stats::monte_carlo_dolp_aop`], seeded `seed + index`), states
/// in parallel. Errors: `samples` outside `[GRID_MIN_SAMPLES, 5e7]`, or the model's.
pub fn run_grid(samples: usize, seed: u64) -> Result<Vec<GridRow>, ValidationError> {
    use polar_model::stats::{monte_carlo_dolp_aop, MAX_MC_SAMPLES};
    use rayon::prelude::*;
    if !(GRID_MIN_SAMPLES..=MAX_MC_SAMPLES).contains(&samples) {
        return Err(ValidationError::Invalid(format!(
            "--grid-samples = {samples} is out of range: allowed {GRID_MIN_SAMPLES} to \
             {MAX_MC_SAMPLES}"
        )));
    }
    let mut jobs = Vec::new();
    for angles in GRID_SETS {
        for noise in [GridNoise::Isotropic, GridNoise::Shot, GridNoise::Correlated] {
            for snr in GRID_SNRS {
                jobs.push((angles, noise, snr));
            }
        }
    }
    jobs.par_iter()
        .enumerate()
        .map(|(i, &(angles, noise, snr))| {
            let (mean, cov) = grid_state(angles, noise, snr)?;
            let a = dolp_aop_stats(&mean, &cov, RegimeChoice::Auto)?;
            let approx_choice = if a.polarised_snr < polar_model::stats::RICE_SNR_THRESHOLD {
                RegimeChoice::Rice
            } else {
                RegimeChoice::Taylor
            };
            let b = dolp_aop_stats(&mean, &cov, approx_choice)?;
            let mc = monte_carlo_dolp_aop(&mean, &cov, samples, seed.wrapping_add(i as u64))?;
            let block = nalgebra::Matrix2::new(cov[(1, 1)], cov[(1, 2)], cov[(2, 1)], cov[(2, 2)]);
            let e = block.symmetric_eigen().eigenvalues;
            let corr = |k: usize| cov[(0, k)] / (cov[(0, 0)] * cov[(k, k)]).sqrt();
            Ok(GridRow {
                angles_deg: angles.to_vec(),
                noise,
                polarised_snr: a.polarised_snr,
                dolp: mean[1].hypot(mean[2]) / mean[0],
                anisotropy: e.max() / e.min(),
                s0_correlation: corr(1).abs().max(corr(2).abs()),
                predicted: [a.dolp_mean, a.dolp_std, a.aop_std_rad],
                predicted_error: a.rel_error_estimate.unwrap_or(f64::NAN),
                approximation: [b.dolp_mean, b.dolp_std, b.aop_std_rad],
                monte_carlo: [mc.dolp_mean, mc.dolp_std, mc.aop_std_rad],
                monte_carlo_se: [mc.dolp_mean_se, mc.dolp_std_se, mc.aop_std_se_rad],
            })
        })
        .collect()
}

fn angles_label(a: &[f64]) -> String {
    a.iter()
        .map(|d| format!("{d:.0}"))
        .collect::<Vec<_>>()
        .join("/")
}

/// The accuracy grid as a stand-alone Markdown report: title, the `command` that generated it,
/// what it checks, the grid, one row per state, then the worst cases. Every figure in the text
/// is computed from `rows`.
pub fn grid_markdown(rows: &[GridRow], samples: usize, seed: u64, command: &str) -> String {
    let mut o = String::new();
    o += "# DoLP and AoP statistics against a Stokes-level Monte Carlo\n\n";
    let _ = writeln!(
        o,
        "Generated by\n\n    {command}\n\n(release build; `--grid-samples` at least \
         {GRID_MIN_SAMPLES}). Do not edit by hand: rerun the command. The whole-chain \
         validation, [../VALIDATION.md](../VALIDATION.md), links here.\n"
    );
    o += "What it checks: `dolp_aop_stats` (MODEL.md section 7, the integration over the \
          Gaussian Stokes estimate, used at every polarised SNR) against Monte Carlo draws of \
          the same Gaussian Stokes estimate `N(mu_S, Sigma_S)` (`monte_carlo_dolp_aop`), so \
          that the only difference is the statistics' own error: DoLP mean and standard \
          deviation over the draws with `S0_hat > 0`; AoP spread as the root-mean-square of the \
          AoP error about the AoP of `mu_S`, each error wrapped into (-90, 90] deg (the same \
          quantity as in the whole-chain validation). The Monte Carlo's standard errors come \
          from its running fourth moments.\n\n";
    let snrs = GRID_SNRS
        .iter()
        .map(|s| format!("{s}"))
        .collect::<Vec<_>>()
        .join(", ");
    let sets = GRID_SETS
        .iter()
        .map(|a| angles_label(a))
        .collect::<Vec<_>>()
        .join(", ");
    let extent = |noise: GridNoise| {
        rows.iter()
            .filter(|r| r.noise == noise)
            .fold((0.0f64, 0.0f64), |(a, c), r| {
                (a.max(r.anisotropy), c.max(r.s0_correlation))
            })
    };
    let (shot_aniso, shot_corr) = extent(GridNoise::Shot);
    let (cor_aniso, cor_corr) = extent(GridNoise::Correlated);
    let _ = writeln!(
        o,
        "Grid: {} states, polarised SNR `p / sigma_p` {snrs}; ideal analyzers at {sets} deg; \
         S0 = 1000, AoP 20 deg; intensity noise\n\n\
         * *isotropic*: `Sigma_I = 27.2^2 I` (OLS; isotropic `(S1, S2)` noise, `S0` \
         uncorrelated);\n\
         * *shot*: `Sigma_I = diag(100 + I_k)`, `I_k` the frame's mean (GLS; the `(S1, S2)` \
         covariance grows anisotropic with the DoLP, up to {shot_aniso:.1}:1, and `S0` \
         correlates with `S1`, `S2` up to {shot_corr:.2});\n\
         * *correlated*: `27.2^2` with frame 0 four times the variance and neighbouring frames \
         correlated 0.3 (GLS; anisotropic, up to {cor_aniso:.1}:1, and correlated with `S0`, up \
         to {cor_corr:.2}, at every SNR).\n\n\
         Where the noise depends on the DoLP (shot), the DoLP giving the SNR is found by \
         fixed-point iteration.\n",
        rows.len()
    );
    let _ = writeln!(
        o,
        "Reference: {samples} Monte Carlo draws per state (seed {seed} + state index). Columns: \
         *aniso.* the ratio of the `(S1, S2)` covariance's eigenvalues, *corr S0* the largest \
         `|corr(S0, S1 or S2)|`, the three relative errors of `dolp_aop_stats` against the \
         Monte Carlo, *max z* the largest of the three in Monte Carlo standard errors, *est. \
         error* the integration's own error estimate, *approx. worst err.* the largest \
         relative error against the same draws of the closed-form approximation for that SNR \
         (the isotropic Rice moments below SNR 3, the Taylor delta method above), for \
         reference.\n"
    );
    o += "| angles | noise | SNR_p | DoLP | aniso. | corr S0 | DoLP mean err. | DoLP std err. | AoP std err. | max z | est. error | approx. worst err. |\n";
    o += "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n";
    let abs_max = |t: Triple| t.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for r in rows {
        let e = r.rel_errors();
        let _ = writeln!(
            o,
            "| {} | {} | {:.2} | {:.4} | {:.2} | {:.2} | {:+.2e} | {:+.2e} | {:+.2e} | {:.1} | {:.0e} | {:.1e} |",
            angles_label(&r.angles_deg),
            r.noise.name(),
            r.polarised_snr,
            r.dolp,
            r.anisotropy,
            r.s0_correlation,
            e[0],
            e[1],
            e[2],
            abs_max(r.z_scores()),
            r.predicted_error,
            abs_max(r.approximation_rel_errors()),
        );
    }
    let names = ["DoLP mean", "DoLP std", "AoP std"];
    o += "\nWorst cases over the grid:\n\n";
    for (i, name) in names.iter().enumerate() {
        if let Some(w) = rows
            .iter()
            .max_by(|a, b| a.rel_errors()[i].abs().total_cmp(&b.rel_errors()[i].abs()))
        {
            let _ = writeln!(
                o,
                "* {name}: {:+.2e} ({:+.1} SE) at {} {}, SNR_p {:.2}; the closed-form \
                 approximation's worst: {:.2e}",
                w.rel_errors()[i],
                w.z_scores()[i],
                angles_label(&w.angles_deg),
                w.noise.name(),
                w.polarised_snr,
                rows.iter()
                    .map(|r| r.approximation_rel_errors()[i].abs())
                    .fold(0.0, f64::max)
            );
        }
    }
    let z_max = rows
        .iter()
        .map(|r| abs_max(r.z_scores()))
        .fold(0.0, f64::max);
    let n = rows.len() * 3;
    let within_3 = rows
        .iter()
        .flat_map(|r| r.z_scores())
        .filter(|z| z.abs() < 3.0)
        .count();
    let est_max = rows.iter().map(|r| r.predicted_error).fold(0.0, f64::max);
    let _ = writeln!(
        o,
        "* largest |z| over the {n} comparisons: {z_max:.2} (for {n} independent standard \
         normal deviates the expected largest |z| is about {:.1}); {within_3} of {n} within 3 \
         standard errors\n\
         * the integration's largest estimated relative error: {est_max:.0e}",
        expected_max_abs_normal(n)
    );
    o
}

/// Runs the accuracy grid and writes [`grid_markdown`] to `out` (creating its directory).
/// Returns the rows. Errors: those of [`run_grid`]; the file or directory cannot be written.
pub fn write_grid_report(
    out: &std::path::Path,
    samples: usize,
    seed: u64,
    command: &str,
) -> Result<Vec<GridRow>, ValidationError> {
    let rows = run_grid(samples, seed)?;
    let io = |source| ValidationError::Io {
        path: out.to_path_buf(),
        source,
    };
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    std::fs::write(out, grid_markdown(&rows, samples, seed, command)).map_err(io)?;
    Ok(rows)
}

/// The approximate expected maximum of `n` absolute standard normal deviates from the Gumbel
/// limit of the maximum of `m = 2n` one-sided tails: location
/// `b = a - (ln ln m + ln 4 pi) / (2 a)`, `a = sqrt(2 ln m)`, scale `1 / a`, mean
/// `b + 0.5772 / a` (Euler's constant).
fn expected_max_abs_normal(n: usize) -> f64 {
    let m = (2 * n) as f64;
    let a = (2.0 * m.ln()).sqrt();
    a - (m.ln().ln() + (4.0 * std::f64::consts::PI).ln()) / (2.0 * a) + 0.577_215_664_9 / a
}
