//! `polarimeter bench stats`: speed against error of the analytic DoLP and AoP statistics
//! (first-order Taylor, second-order Taylor mean, Rice) and of the whole-chain Monte Carlo at
//! 1e3 .. 1e6 frame sets, for a few representative states, every error measured against a
//! reference Monte Carlo of the whole chain computed in the same run (seeded, 1e7 sets by
//! default). Then the "equal error" comparison: the Monte Carlo sets needed to match each
//! analytic answer's error (Monte Carlo error `c / sqrt(n)`, `c` fitted from the measured
//! points), their time, and the speed ratio.
//!
//! Times are medians of repeated runs (`std::time::Instant`), the Monte Carlo on one thread like
//! the analytic path; ratios are taken within one run.

use crate::validation::{ValidationError, CAMERAS};
use polar_model::atmosphere::Band;
use polar_model::polarization::Stokes;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_model::stats::{dolp_aop_stats, MethodChoice, Regime, RegimeChoice};
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
    /// Whether this is the regime the automatic choice uses.
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
    let auto_regime = auto.stats.regime;
    let mean_s = auto.stokes_mean_w_m2_sr;
    let cov_s = auto.estimator.cov;
    let mut rows = Vec::new();
    let analytic_min = Duration::from_millis(200);
    for (label, choice, first_order) in [
        ("Taylor, first order", RegimeChoice::Taylor, true),
        ("Taylor, second-order mean", RegimeChoice::Taylor, false),
        ("Rice", RegimeChoice::Rice, false),
    ] {
        let run = || -> Result<Triple, ValidationError> {
            let a = analytic_products(model, &angles, ex, MethodChoice::Auto, choice)?;
            let s = &a.stokes_mean_w_m2_sr;
            let mean = if first_order && a.stats.regime == Regime::Taylor {
                s[1].hypot(s[2]) / s[0]
            } else {
                a.stats.dolp_mean
            };
            Ok([mean, a.stats.dolp_std, a.stats.aop_std_rad])
        };
        let values = run()?;
        let regime = dolp_aop_stats(&mean_s, &cov_s, choice)?.regime;
        if regime != choice_regime(choice) {
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
            auto: regime == auto_regime && !(first_order && regime == Regime::Taylor),
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

fn choice_regime(c: RegimeChoice) -> Regime {
    match c {
        RegimeChoice::Rice => Regime::Rice,
        RegimeChoice::Taylor | RegimeChoice::Auto => Regime::Taylor,
    }
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
         automatic regime's row is in bold.\n",
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
