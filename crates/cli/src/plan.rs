//! `polarimeter plan angles`: the SCR-optimal analyzer set for a target against a background
//! (MODEL.md section 9), with the conventional sets beside it; and `polarimeter bench planner`:
//! the optimiser against an exhaustive grid, in the same run.

use crate::commands::CommandError;
use clap::Args;
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use polar_model::metrics::{matched_filter, ClassStats};
use polar_planner::optimize::{grid_search, MAX_CHANNELS};
use polar_planner::{conventional, optimise, Constraints, Contrast, Optimum};
use serde_json::{json, Value};
use std::time::{Duration, Instant};

/// `plan angles` arguments.
#[derive(Debug, Clone, Args)]
pub struct PlanAnglesArgs {
    /// Channels (analyzer angles), 1..=6.
    #[arg(long, default_value_t = 3)]
    pub channels: usize,
    /// Target Stokes mean S0,S1,S2 (any unit; the same as the noise variance's square root).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub target_mean: Vec<f64>,
    /// Background Stokes mean S0,S1,S2.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub background_mean: Vec<f64>,
    /// Background Stokes covariance, 9 values row-major.
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        required = true
    )]
    pub background_cov: Vec<f64>,
    /// Per-frame sensor noise variance V, in the unit of the means squared, >= 0.
    #[arg(long)]
    pub noise_var: f64,
    /// Target Stokes covariance, 9 values row-major (default: the background's); used for Pd.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_cov: Option<Vec<f64>>,
    /// A filter wheel's fixed polarizer angles, degrees: choose the best subset.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub fixed_angles_deg: Option<Vec<f64>>,
    /// Smallest separation between two angles, degrees, [0, 90).
    #[arg(long, default_value_t = 0.0)]
    pub min_separation_deg: f64,
    /// A rotator's travel LO,HI, degrees (hi - lo < 180).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angle_range_deg: Option<Vec<f64>>,
    /// The stage's smallest step, degrees (0: continuous).
    #[arg(long, default_value_t = 0.0)]
    pub step_deg: f64,
    /// Angle tolerance of the optimum, degrees.
    #[arg(long, default_value_t = 0.01)]
    pub tolerance_deg: f64,
    /// False-alarm rate for the Pd figures, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
}

fn vec3(field: &str, v: &[f64]) -> Result<Vector3<f64>, CommandError> {
    match v {
        [a, b, c] => Ok(Vector3::new(*a, *b, *c)),
        _ => Err(CommandError(format!(
            "{field} has {} values: allowed 3 (S0,S1,S2)",
            v.len()
        ))),
    }
}

fn mat3(field: &str, v: &[f64]) -> Result<Matrix3<f64>, CommandError> {
    if v.len() != 9 {
        return Err(CommandError(format!(
            "{field} has {} values: allowed 9 (3x3 row-major)",
            v.len()
        )));
    }
    Ok(Matrix3::from_row_slice(v))
}

fn planner_error(e: polar_planner::PlanError) -> CommandError {
    CommandError(e.to_string())
}

/// Matched-filter Pd at `pfa` of the set: the classes in intensity space, `W mu` and
/// `W Sigma W^T + V I` (ideal analyzer rows).
fn pd(
    angles_rad: &[f64],
    t_mean: &Vector3<f64>,
    t_cov: &Matrix3<f64>,
    b_mean: &Vector3<f64>,
    b_cov: &Matrix3<f64>,
    noise_var: f64,
    pfa: f64,
) -> Result<f64, CommandError> {
    let n = angles_rad.len();
    let w = DMatrix::from_fn(n, 3, |i, j| polar_planner::scr::row(angles_rad[i])[j]);
    let class = |field, m: &Vector3<f64>, c: &Matrix3<f64>| {
        let mean = &w * DVector::from_column_slice(m.as_slice());
        let cov = &w * DMatrix::from_fn(3, 3, |i, j| c[(i, j)]) * w.transpose()
            + DMatrix::identity(n, n) * noise_var;
        ClassStats::new(field, mean, 0.5 * (&cov + cov.transpose()))
    };
    let t = class("target_cov", t_mean, t_cov)?;
    let b = class("background_cov", b_mean, b_cov)?;
    Ok(matched_filter(&t, &b, pfa)?.pd)
}

/// `plan angles`.
pub fn angles(args: &PlanAnglesArgs) -> Result<Value, CommandError> {
    if !(1..=MAX_CHANNELS).contains(&args.channels) {
        return Err(CommandError(format!(
            "channels = {} is out of range: allowed 1 to {MAX_CHANNELS}",
            args.channels
        )));
    }
    let t_mean = vec3("target_mean", &args.target_mean)?;
    let b_mean = vec3("background_mean", &args.background_mean)?;
    let b_cov = mat3("background_cov", &args.background_cov)?;
    let t_cov = match &args.target_cov {
        Some(v) => mat3("target_cov", v)?,
        None => b_cov,
    };
    let contrast = Contrast::new(t_mean - b_mean, b_cov, args.noise_var).map_err(planner_error)?;
    let range_rad = match &args.angle_range_deg {
        None => None,
        Some(v) if v.len() == 2 => Some((v[0].to_radians(), v[1].to_radians())),
        Some(v) => {
            return Err(CommandError(format!(
                "angle_range_deg has {} values: allowed 2 (LO,HI)",
                v.len()
            )))
        }
    };
    let constraints = Constraints {
        range_rad,
        min_separation_rad: args.min_separation_deg.to_radians(),
        step_rad: args.step_deg.to_radians(),
        fixed_angles_rad: args
            .fixed_angles_deg
            .as_ref()
            .map(|v| v.iter().map(|d| d.to_radians()).collect()),
    };
    let t0 = Instant::now();
    let opt = optimise(
        &contrast,
        args.channels,
        &constraints,
        args.tolerance_deg.to_radians(),
    )
    .map_err(planner_error)?;
    let elapsed_ms = t0.elapsed().as_secs_f64() * 1e3;
    let pd_of = |a: &[f64]| {
        pd(
            a,
            &t_mean,
            &t_cov,
            &b_mean,
            &b_cov,
            contrast.noise_var,
            args.pfa,
        )
    };
    let mut scr_conv = serde_json::Map::new();
    let mut pd_conv = serde_json::Map::new();
    for (name, scr) in conventional(&contrast) {
        let rad: Vec<f64> = name
            .split('/')
            .filter_map(|d| d.parse::<f64>().ok())
            .map(f64::to_radians)
            .collect();
        scr_conv.insert(name.into(), json!(scr));
        pd_conv.insert(name.into(), json!(pd_of(&rad)?));
    }
    let limit = contrast.clutter_limit();
    Ok(json!({
        "angles_deg": opt.angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "scr": opt.scr,
        "pd": pd_of(&opt.angles_rad)?,
        "pfa": args.pfa,
        "scr_conventional": scr_conv,
        "pd_conventional": pd_conv,
        "scr_clutter_limit": if limit.is_finite() { json!(limit) } else { Value::Null },
        "clutter_condition": if contrast.clutter_condition.is_finite() { json!(contrast.clutter_condition) } else { Value::Null },
        "evaluations": opt.evaluations,
        "elapsed_ms": elapsed_ms,
        "notes": contrast.notes,
    }))
}

/// One row of `bench planner`.
#[derive(Debug, Clone)]
pub struct PlannerRow {
    /// Channels.
    pub channels: usize,
    /// The optimiser: median time and its answer.
    pub ours: (Duration, Optimum),
    /// The exhaustive 1-degree grid: time and its answer.
    pub grid: (Duration, Optimum),
}

/// A fixed benchmark problem: correlated clutter where the angles matter (a glass-like target,
/// DoLP 0.3, against asphalt-like clutter; noise comparable to the clutter).
pub fn bench_problem() -> Result<Contrast, CommandError> {
    let b_cov = Matrix3::new(400.0, 30.0, -20.0, 30.0, 60.0, 12.0, -20.0, 12.0, 45.0);
    Contrast::new(Vector3::new(40.0, 30.0, -12.0), b_cov, 80.0).map_err(planner_error)
}

/// Runs the optimiser (to 0.01 deg) `runs` times per N (median) and the exhaustive 1-degree
/// grid once, for N = 1..=max_n.
pub fn bench(max_n: usize, runs: usize) -> Result<Vec<PlannerRow>, CommandError> {
    let contrast = bench_problem()?;
    let mut rows = Vec::new();
    for n in 1..=max_n.min(MAX_CHANNELS) {
        let mut times = Vec::new();
        let mut answer = None;
        for _ in 0..runs.max(1) {
            let t0 = Instant::now();
            let opt = optimise(&contrast, n, &Constraints::default(), 0.01f64.to_radians())
                .map_err(planner_error)?;
            times.push(t0.elapsed());
            answer = Some(opt);
        }
        times.sort();
        let ours = (
            times[times.len() / 2],
            answer.ok_or_else(|| CommandError("no run".into()))?,
        );
        let t0 = Instant::now();
        let grid = grid_search(&contrast, n, 1f64.to_radians());
        rows.push(PlannerRow {
            channels: n,
            ours,
            grid: (t0.elapsed(), grid),
        });
    }
    Ok(rows)
}

/// The rows as a Markdown table.
pub fn markdown(rows: &[PlannerRow]) -> String {
    let time = |d: Duration| {
        let us = d.as_secs_f64() * 1e6;
        if us < 1000.0 {
            format!("{us:.1} us")
        } else {
            format!("{:.2} ms", us / 1e3)
        }
    };
    let deg = |a: &[f64]| {
        a.iter()
            .map(|v| format!("{:.2}", v.to_degrees()))
            .collect::<Vec<_>>()
            .join("/")
    };
    let mut out = String::from(
        "| N | optimiser (0.01 deg) | its SCR | angles, deg | 1-deg grid | grid SCR | grid evaluations | speed-up | SCR ours / grid |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        out.push_str(&format!(
            "| {} | {} | {:.6} | {} | {} | {:.6} | {} | {:.1}x | {:.9} |\n",
            r.channels,
            time(r.ours.0),
            r.ours.1.scr,
            deg(&r.ours.1.angles_rad),
            time(r.grid.0),
            r.grid.1.scr,
            r.grid.1.evaluations,
            r.grid.0.as_secs_f64() / r.ours.0.as_secs_f64().max(1e-12),
            r.ours.1.scr / r.grid.1.scr,
        ));
    }
    out
}
