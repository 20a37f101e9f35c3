//! `polarimeter plan angles`: the SCR-optimal analyzer set for a target against a background
//! (MODEL.md section 9), with the conventional sets beside it; and `polarimeter bench planner`:
//! the optimiser against an exhaustive grid, in the same run.

use crate::commands::CommandError;
use clap::Args;
use nalgebra::{Matrix3, Vector3};
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
    /// The detection-only optimum: the SCR-optimal set whatever it forms (repeated angles and
    /// 1 or 2 channels allowed), with no Stokes image; by default the set forms a Stokes image,
    /// as in `plan scene` (3 or more angles whose ideal measurement matrix has a condition
    /// number of at most 6.21, that of 0/30/60).
    #[arg(long)]
    pub detection_only: bool,
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

/// The matched filter's ROC of the set at `pfa` ([`polar_planner::scr::matched_filter_roc`]).
pub(crate) fn intensity_roc(
    angles_rad: &[f64],
    t_mean: &Vector3<f64>,
    t_cov: &Matrix3<f64>,
    b_mean: &Vector3<f64>,
    b_cov: &Matrix3<f64>,
    noise_var: f64,
    pfa: f64,
) -> Result<polar_model::metrics::Roc, CommandError> {
    Ok(polar_planner::scr::matched_filter_roc(
        angles_rad,
        (t_mean, t_cov),
        (b_mean, b_cov),
        noise_var,
        pfa,
    )?)
}

/// `plan angles`.
pub fn angles(args: &PlanAnglesArgs) -> Result<Value, CommandError> {
    if !(1..=MAX_CHANNELS).contains(&args.channels) {
        return Err(CommandError(format!(
            "channels = {} is out of range: allowed 1 to {MAX_CHANNELS}",
            args.channels
        )));
    }
    let stokes = !args.detection_only;
    if stokes && args.channels < 3 {
        return Err(CommandError(format!(
            "--channels {} is out of range for a Stokes set: allowed 3 to {MAX_CHANNELS} (a \
             linear Stokes vector has 3 unknowns), or add --detection-only for 1 or 2 channels",
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
        max_condition: stokes.then_some(STOKES_MAX_CONDITION),
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
        intensity_roc(
            a,
            &t_mean,
            &t_cov,
            &b_mean,
            &b_cov,
            contrast.noise_var,
            args.pfa,
        )
        .map(|r| r.pd)
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
    let mut notes = contrast.notes.clone();
    let distinct = {
        let mut a: Vec<f64> = opt.angles_rad.clone();
        a.sort_by(f64::total_cmp);
        a.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        a.len()
    };
    if !stokes && distinct < 3 {
        notes.push(format!(
            "detection only: the set has {distinct} distinct angle(s); it detects in the \
             intensity frames but forms no Stokes image"
        ));
    }
    let ideal_condition = polar_planner::stokes::stokes_condition(&opt.angles_rad);
    let set = json!({
        "kind": if stokes { "stokes" } else { "detection-only" },
        "rule": if stokes {
            format!(
                "{} angles whose ideal measurement matrix has a condition number of at most \
                 {STOKES_MAX_CONDITION} (that of 0/30/60, the worst 3-angle set 30 deg apart)",
                args.channels
            )
        } else {
            format!("{} angles, repeats allowed: {distinct} distinct angle(s)", args.channels)
        },
        "condition_number_ideal": if ideal_condition.is_finite() { json!(ideal_condition) } else { Value::Null },
    });
    Ok(json!({
        "angles_deg": opt.angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "set": set,
        "scr": opt.scr,
        "pd": pd_of(&opt.angles_rad)?,
        "pfa": args.pfa,
        "scr_conventional": scr_conv,
        "pd_conventional": pd_conv,
        "scr_clutter_limit": if limit.is_finite() { json!(limit) } else { Value::Null },
        "clutter_condition": if contrast.clutter_condition.is_finite() { json!(contrast.clutter_condition) } else { Value::Null },
        "evaluations": opt.evaluations,
        "elapsed_ms": elapsed_ms,
        "notes": notes,
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

/// `plan scene --scene FILE --camera FILE --target M --background M`: angles, integration time and
/// a forecast from the model alone.
#[derive(Debug, Clone, Args)]
pub struct PlanSceneArgs {
    /// The scene (TOML, examples/*.toml).
    #[arg(long)]
    pub scene: Option<std::path::PathBuf>,
    /// The camera (TOML, examples/cameras/*.toml).
    #[arg(long)]
    pub camera: Option<std::path::PathBuf>,
    /// The target material's name in the scene.
    #[arg(long)]
    pub target: Option<String>,
    /// The background material's name in the scene.
    #[arg(long)]
    pub background: Option<String>,
    /// Channels (frames per set), 1..=6.
    #[arg(long, default_value_t = 3)]
    pub channels: usize,
    /// Time budget for one set, seconds (frames, moves and settling); none by default.
    #[arg(long)]
    pub time_budget_s: Option<f64>,
    /// Smallest separation between two angles, degrees, [0, 180 / channels] and below 90: the
    /// stage's mechanical constraint (0 lets a detection-only set repeat an angle).
    #[arg(long)]
    pub min_separation_deg: Option<f64>,
    /// The detection-only optimum: the SCR-optimal set whatever it forms (repeats allowed, 1
    /// or 2 channels allowed), with no Stokes image; by default the set forms a Stokes image
    /// (3 or more angles whose ideal measurement matrix has a condition number of at most
    /// 6.21, that of 0/30/60).
    #[arg(long)]
    pub detection_only: bool,
    /// The SCR to reach, as a fraction of the clutter-limited SCR, (0, 1).
    #[arg(long, default_value_t = 0.9)]
    pub scr_fraction: f64,
    /// Saturation margin: every class's mean plus this many standard deviations stays below
    /// the saturation level at every angle, [0, 10].
    #[arg(long, default_value_t = 3.0)]
    pub saturation_sigma: f64,
    /// The stage's speed, degrees per second, (0, 10000].
    #[arg(long, default_value_t = 60.0)]
    pub stage_deg_per_s: f64,
    /// Settling time after each move, seconds, [0, 60].
    #[arg(long, default_value_t = 0.1)]
    pub settle_s: f64,
    /// False-alarm rate of the Pd forecast, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
    /// Relative tolerance of the scene evaluation.
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
}

fn need<T: Clone>(v: &Option<T>, flag: &str, what: &str) -> Result<T, CommandError> {
    v.clone()
        .ok_or_else(|| CommandError(format!("--{flag} is missing: allowed {what}")))
}

fn check_range(field: &str, v: f64, lo: f64, hi: f64, lo_open: bool) -> Result<f64, CommandError> {
    let ok = v.is_finite() && v <= hi && if lo_open { v > lo } else { v >= lo };
    if ok {
        Ok(v)
    } else {
        let open = if lo_open { "(" } else { "[" };
        Err(CommandError(format!(
            "{field} = {v} is out of range: allowed {open}{lo}, {hi}]"
        )))
    }
}

/// The frames' statistics of one class at `angles_rad` for `t_int_s`.
fn frames(
    sensor: &polar_model::sensor::SensorModel,
    angles_rad: &[f64],
    t_int_s: f64,
    class: &polar_model::scene::MaterialResult,
) -> Result<polar_model::sensor::SensorSignal, CommandError> {
    Ok(sensor.signal(angles_rad, &exposure(t_int_s, class))?)
}

/// A class's exposure for `t_int_s`: its mean radiance and its (symmetrised) clutter.
fn exposure(
    t_int_s: f64,
    class: &polar_model::scene::MaterialResult,
) -> polar_model::sensor::Exposure {
    let mut e = polar_model::sensor::Exposure::new(t_int_s, class.mean);
    e.radiance_cov_w2_m4_sr2 = 0.5 * (class.cov + class.cov.transpose());
    e
}

/// The longest integration time at which neither class saturates at any analyzer angle (1-degree
/// grid over 180 deg), with `k` standard deviations of margin: bisection on `log t` over
/// `[1 us, 100 s]`.
fn saturation_limit_s(
    sensor: &polar_model::sensor::SensorModel,
    classes: &[&polar_model::scene::MaterialResult],
    k: f64,
) -> Result<f64, CommandError> {
    let grid: Vec<f64> = (0..180).map(|d| f64::from(d).to_radians()).collect();
    let ok = |t: f64| -> Result<bool, CommandError> {
        for c in classes {
            let s = frames(sensor, &grid, t, c)?;
            for i in 0..grid.len() {
                if s.mean_dn[i] + k * s.cov_dn[(i, i)].max(0.0).sqrt() > s.saturation_dn {
                    return Ok(false);
                }
            }
        }
        Ok(true)
    };
    let (mut lo, mut hi) = (1e-6f64.ln(), 100f64.ln());
    if !ok(lo.exp())? {
        return Err(CommandError(
            "the scene saturates the camera even at 1 us: use a darker band, a smaller \
             aperture or a neutral-density filter"
                .into(),
        ));
    }
    if ok(hi.exp())? {
        return Ok(hi.exp());
    }
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if ok(mid.exp())? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(lo.exp())
}

/// The Stokes rule's bound on the ideal measurement matrix's condition number
/// ([`polar_planner::stokes`]: that of 0/30/60, the worst 3-angle set whose angles are at least
/// 30 deg apart).
pub use polar_planner::stokes::STOKES_MAX_CONDITION;

/// The planner's contrast at `t_int_s` ([`Contrast::from_sensor`]: the camera's real rows and
/// its noise at the background's light), whose SCR is the forecast's.
fn contrast_at(
    sensor: &polar_model::sensor::SensorModel,
    t: &polar_model::scene::MaterialResult,
    b: &polar_model::scene::MaterialResult,
    t_int_s: f64,
) -> Result<Contrast, CommandError> {
    Contrast::from_sensor(sensor, t_int_s, &t.mean.0, &b.mean.0, &b.cov).map_err(planner_error)
}

/// The forecast of one set at `t_int_s`: the matched filter on the frames of
/// [`polar_model::sensor::SensorModel::signal`] (the real analyzer, the background's clutter,
/// each class's noise).
fn forecast_roc(
    sensor: &polar_model::sensor::SensorModel,
    angles_rad: &[f64],
    t_int_s: f64,
    t_class: &polar_model::scene::MaterialResult,
    b_class: &polar_model::scene::MaterialResult,
    pfa: f64,
) -> Result<
    (
        polar_model::metrics::Roc,
        polar_model::sensor::SensorSignal,
        polar_model::sensor::SensorSignal,
    ),
    CommandError,
> {
    let st = frames(sensor, angles_rad, t_int_s, t_class)?;
    let sb = frames(sensor, angles_rad, t_int_s, b_class)?;
    let class = |field, s: &polar_model::sensor::SensorSignal| {
        ClassStats::new(field, s.mean_dn.clone(), s.cov_dn.clone())
    };
    let roc = matched_filter(&class("target", &st)?, &class("background", &sb)?, pfa)?;
    Ok((roc, st, sb))
}

/// Degrees in `[0, 180)`, to 1e-6 deg (the optimiser's tolerance is 0.01 deg: readable, and
/// an angle that rounds to 180 wraps to 0), sorted.
fn degrees(angles_rad: &[f64]) -> Vec<f64> {
    let mut d: Vec<f64> = angles_rad
        .iter()
        .map(|a| ((a.to_degrees() * 1e6).round() / 1e6).rem_euclid(180.0))
        .collect();
    d.sort_by(f64::total_cmp);
    d
}

/// `plan scene ...`.
///
/// The angles and the integration time are chosen jointly: the integration time is the
/// shortest `t` (below the saturation limit and the time budget) at which the best set's SCR
/// reaches the asked fraction of the clutter limit, `min t` subject to
/// `max_set SCR(set, t) >= goal`, and the set is the SCR-optimal one at that `t`. The bisection
/// on `t` is exact for this problem because every set's SCR rises with `t` (each frame's
/// noise variance in radiance units, `(dark + read^2)/G^2 + 1/(12 K^2 G^2) + w.mu_b / G`, falls
/// as `G` grows), so the best set's SCR does too. The saturation limit is the longest `t` at
/// which neither class comes within `--saturation-sigma` of saturation at any analyzer angle,
/// so it holds for every set the optimiser may choose.
///
/// The SCR the optimiser maximises is the forecast's ([`Contrast::from_sensor`]), so the
/// printed `scr` is never below that of any set the constraints allow; the conventional sets'
/// SCRs are printed at the same integration time, each with whether the constraints allow it.
pub fn scene_plan(args: &PlanSceneArgs) -> Result<Value, CommandError> {
    let scene_path = need(&args.scene, "scene", "a scene file")?;
    let camera_path = need(&args.camera, "camera", "a camera file")?;
    let target = need(&args.target, "target", "a material of the scene")?;
    let background = need(&args.background, "background", "a material of the scene")?;
    let n = args.channels;
    if !(1..=MAX_CHANNELS).contains(&n) {
        return Err(CommandError(format!(
            "--channels {n} is out of range: allowed 1 to {MAX_CHANNELS}"
        )));
    }
    let stokes = !args.detection_only;
    if stokes && n < 3 {
        return Err(CommandError(format!(
            "--channels {n} is out of range for a Stokes set: allowed 3 to {MAX_CHANNELS} (a \
             linear Stokes vector has 3 unknowns), or add --detection-only for 1 or 2 channels"
        )));
    }
    let widest = 180.0 / n as f64;
    let min_separation_deg = match args.min_separation_deg {
        None => 0.0,
        Some(v) => {
            if !(v.is_finite() && (0.0..=widest).contains(&v) && v < 90.0) {
                return Err(CommandError(format!(
                    "--min-separation-deg {v} is out of range for {n} angles: allowed [0, {}] \
                     ({n} angles that far apart must fit in 180 deg)",
                    widest.min(89.99)
                )));
            }
            v
        }
    };
    check_range("scr_fraction", args.scr_fraction, 0.0, 0.999, true)?;
    check_range("saturation_sigma", args.saturation_sigma, 0.0, 10.0, false)?;
    check_range("stage_deg_per_s", args.stage_deg_per_s, 0.0, 1e4, true)?;
    check_range("settle_s", args.settle_s, 0.0, 60.0, false)?;
    check_range("pfa", args.pfa, 0.0, 0.5, true)?;
    check_range("tolerance", args.tolerance, 1e-8, 0.1, false)?;
    if let Some(b) = args.time_budget_s {
        check_range("time_budget_s", b, 0.0, 1e6, true)?;
    }
    let scene = crate::commands::load_scene(&scene_path)?;
    let camera = polar_model::sensor::Camera::from_toml_str(
        &std::fs::read_to_string(&camera_path).map_err(|e| {
            CommandError(format!(
                "--camera {}: cannot read: {e}",
                camera_path.display()
            ))
        })?,
    )
    .map_err(|e| CommandError(format!("--camera {}: {e}", camera_path.display())))?;
    let names: Vec<&str> = scene.materials.iter().map(|m| m.name.as_str()).collect();
    let pick = |flag: &str, name: &str| {
        scene
            .materials
            .iter()
            .find(|m| m.name == name)
            .cloned()
            .ok_or_else(|| {
                CommandError(format!(
                    "--{flag} {name:?} is not a material of the scene: allowed {}",
                    names.join(", ")
                ))
            })
    };
    let materials = [pick("target", &target)?, pick("background", &background)?];
    let results = polar_model::scene::evaluate(&scene.spec, &materials, args.tolerance)?;
    let (t_class, b_class) = (&results[0], &results[1]);
    let sensor = polar_model::sensor::SensorModel::new(&camera, &scene.spec.band)?;
    let mut notes: Vec<String> = sensor.warnings().to_vec();

    // Integration time and angles jointly (see the doc comment).
    let tol_rad = 0.01f64.to_radians();
    let constraints = Constraints {
        min_separation_rad: min_separation_deg.to_radians(),
        max_condition: stokes.then_some(STOKES_MAX_CONDITION),
        ..Constraints::default()
    };
    let best_at = |t_int_s: f64| -> Result<(Contrast, Optimum), CommandError> {
        let c = contrast_at(&sensor, t_class, b_class, t_int_s)?;
        let o = optimise(&c, n, &constraints, tol_rad).map_err(planner_error)?;
        Ok((c, o))
    };
    let t_sat = saturation_limit_s(&sensor, &[t_class, b_class], args.saturation_sigma)?;
    let (c_sat, _) = best_at(t_sat)?;
    // Clutter limit: the optimum of these rows with the sensor noise removed.
    let quiet = c_sat.noise_free().map_err(planner_error)?;
    let limit = optimise(&quiet, n, &constraints, tol_rad)
        .map_err(planner_error)?
        .scr;
    if limit <= 0.0 {
        return Err(CommandError(format!(
            "no contrast between {target} and {background}: their Stokes means are equal, so no \
             analyzer set or integration time separates them"
        )));
    }
    let goal = args.scr_fraction * limit;
    let move_s = |angles: &[f64]| -> f64 {
        // Sorted angles visited in order, then back to the first for the next set.
        let span = angles.last().copied().unwrap_or(0.0) - angles.first().copied().unwrap_or(0.0);
        2.0 * span.to_degrees() / args.stage_deg_per_s
    };
    let mut t_max = t_sat;
    if let Some(budget) = args.time_budget_s {
        // A conservative move allowance: a full half turn and back.
        let overhead = 2.0 * 180.0 / args.stage_deg_per_s + n as f64 * args.settle_s;
        let t_budget = (budget - overhead) / n as f64;
        if t_budget < 1e-6 {
            return Err(CommandError(format!(
                "--time-budget-s {budget} does not cover {n} moves and settles ({overhead:.3} \
                 s): allowed more than that"
            )));
        }
        if t_budget < t_max {
            notes.push(format!(
                "the time budget limits the integration time to {:.4} ms (saturation allows {:.4} ms)",
                t_budget * 1e3,
                t_sat * 1e3
            ));
            t_max = t_budget;
        }
    }
    let (_, at_max) = best_at(t_max)?;
    let t_int_s = if at_max.scr < goal {
        notes.push(format!(
            "the SCR reaches only {:.3} of the clutter limit at the longest allowed integration \
             time ({:.4} ms); asked {}",
            at_max.scr / limit,
            t_max * 1e3,
            args.scr_fraction
        ));
        t_max
    } else {
        // The best set's SCR rises with t: bisection on log t.
        let (mut lo, mut hi) = (1e-6f64.ln().min(t_max.ln() - 1e-9), t_max.ln());
        if best_at(lo.exp())?.1.scr >= goal {
            hi = lo;
        }
        for _ in 0..40 {
            if hi - lo < 1e-4 {
                break;
            }
            let mid = 0.5 * (lo + hi);
            if best_at(mid.exp())?.1.scr >= goal {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        hi.exp()
    };
    let (contrast, opt) = best_at(t_int_s)?;
    notes.extend(contrast.notes.iter().cloned());

    // The other kind of set at the same integration time: what the Stokes constraint costs.
    // The same mechanical separation with the Stokes bound toggled.
    let other = if n >= 3 {
        let c = Constraints {
            max_condition: (!stokes).then_some(STOKES_MAX_CONDITION),
            ..constraints.clone()
        };
        Some(optimise(&contrast, n, &c, tol_rad).map_err(planner_error)?)
    } else {
        None
    };
    let distinct = {
        let mut a: Vec<f64> = opt.angles_rad.clone();
        a.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        a.len()
    };
    let condition = contrast.condition_number(&opt.angles_rad);
    let ideal_condition = polar_planner::stokes::stokes_condition(&opt.angles_rad);
    let finite = |k: f64| if k.is_finite() { json!(k) } else { Value::Null };
    let set_json = if stokes {
        let o = other.as_ref().map_or(opt.scr, |o| o.scr);
        json!({
            "kind": "stokes",
            "rule": format!(
                "{n} angles whose ideal measurement matrix has a condition number of at most \
                 {STOKES_MAX_CONDITION} (that of 0/30/60, the worst 3-angle set 30 deg apart), \
                 every two at least {min_separation_deg} deg apart (the stage's separation)"
            ),
            "condition_number_ideal": finite(ideal_condition),
            "condition_number": finite(condition),
            "scr_detection_only": o,
            "angles_detection_only_deg": other.as_ref().map(|o| degrees(&o.angles_rad)),
            "stokes_cost_scr": (o - opt.scr).max(0.0),
            "stokes_cost_percent": 100.0 * (o - opt.scr).max(0.0) / o.max(1e-300),
        })
    } else {
        let mut v = json!({
            "kind": "detection-only",
            "rule": format!(
                "{n} angles at least {min_separation_deg} deg apart, repeats allowed: \
                 {distinct} distinct angle(s)"
            ),
            "condition_number_ideal": finite(ideal_condition),
            "condition_number": finite(condition),
        });
        if let Some(o) = &other {
            v["scr_stokes"] = json!(o.scr);
            v["angles_stokes_deg"] = json!(degrees(&o.angles_rad));
            v["stokes_cost_scr"] = json!((opt.scr - o.scr).max(0.0));
            v["stokes_cost_percent"] =
                json!(100.0 * (opt.scr - o.scr).max(0.0) / opt.scr.max(1e-300));
        }
        v
    };
    if !stokes && distinct < 3 {
        notes.push(format!(
            "detection only: the set has {distinct} distinct angle(s); it detects in the \
             intensity frames but forms no Stokes image"
        ));
    }

    // The forecast with the full sensor model: the same SCR as the optimiser's (checked).
    let (roc, st, sb) = forecast_roc(
        &sensor,
        &opt.angles_rad,
        t_int_s,
        t_class,
        b_class,
        args.pfa,
    )?;
    let pd_1e3 = matched_filter(
        &ClassStats::new("target", st.mean_dn.clone(), st.cov_dn.clone())?,
        &ClassStats::new("background", sb.mean_dn.clone(), sb.cov_dn.clone())?,
        1e-3,
    )?
    .pd;
    if (roc.scr - opt.scr).abs() > 1e-6 * roc.scr.max(1e-300) {
        notes.push(format!(
            "the forecast's SCR {} differs from the optimiser's {} by more than 1e-6 relative \
             (the forecast regularised a near-singular covariance?)",
            roc.scr, opt.scr
        ));
    }
    let margin = |s: &polar_model::sensor::SensorSignal| -> f64 {
        (0..s.mean_dn.len())
            .map(|i| (s.saturation_dn - s.mean_dn[i]) / s.cov_dn[(i, i)].max(1e-300).sqrt())
            .fold(f64::INFINITY, f64::min)
    };
    let dolp_sigma = |m: &polar_model::scene::MaterialResult| -> Value {
        match polar_model::validation::analytic_products(
            &sensor,
            &opt.angles_rad,
            &exposure(t_int_s, m),
            polar_model::stats::MethodChoice::default(),
            polar_model::stats::RegimeChoice::Auto,
        ) {
            Ok(p) => json!(p.stats.dolp_std),
            Err(e) => json!({ "none": e.to_string() }),
        }
    };
    let frame_s = n as f64 * (t_int_s + args.settle_s) + move_s(&opt.angles_rad);
    // The conventional sets under the same forecast at the same integration time.
    let mut conv = serde_json::Map::new();
    for (name, deg) in polar_planner::optimize::CONVENTIONAL {
        let rad: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
        let (r, _, _) = forecast_roc(&sensor, &rad, t_int_s, t_class, b_class, args.pfa)?;
        let allowed = rad.len() == n && polar_planner::optimize::allowed(&rad, &constraints);
        conv.insert(
            name.to_string(),
            json!({ "scr": r.scr, "pd_at_pfa": r.pd, "allowed": allowed }),
        );
    }
    let sensor_sigma: Vec<f64> = (0..n)
        .map(|i| {
            (sb.cov_dn[(i, i)] - sb.variance.clutter_dn2[i])
                .max(0.0)
                .sqrt()
        })
        .collect();
    Ok(json!({
        "angles_deg": degrees(&opt.angles_rad),
        "t_int_ms": t_int_s * 1e3,
        "set": set_json,
        "forecast": {
            "scr": roc.scr,
            "scr_terms": {
                "definition": "matched filter over the set's frames: (mu_t - mu_b)^T Sigma_b^-1 (mu_t - mu_b), DN; Sigma_b = the background's clutter (off-diagonal too) plus its sensor noise",
                "mean_difference_dn": (0..n).map(|i| st.mean_dn[i] - sb.mean_dn[i]).collect::<Vec<_>>(),
                "background_sigma_dn": (0..n).map(|i| sb.cov_dn[(i, i)].max(0.0).sqrt()).collect::<Vec<_>>(),
                "clutter_sigma_dn": sb.variance.clutter_dn2.iter().map(|v| v.max(0.0).sqrt()).collect::<Vec<_>>(),
                "sensor_sigma_dn": sensor_sigma,
            },
            "scr_clutter_limit": limit,
            "scr_conventional": conv,
            "pd_at_pfa_1e-3": pd_1e3,
            "pd_at_pfa": roc.pd,
            "pfa": args.pfa,
            "dolp_sigma": { target.clone(): dolp_sigma(t_class), background.clone(): dolp_sigma(b_class) },
            "saturation_margin_sigma": { target.clone(): margin(&st), background.clone(): margin(&sb) },
            "saturation_limit_ms": t_sat * 1e3,
            "frames": n,
            "duration_s": frame_s,
        },
        "notes": notes,
        "warnings": roc.warnings,
    }))
}

/// `analyze aptd --frames DIR`: APTD offline over an image stack.
#[derive(Debug, Clone, Args)]
pub struct PlanAptdArgs {
    /// The stack: `frames.csv` (`file,angle_deg`) and the 16-bit TIFFs it names.
    #[arg(long)]
    pub frames: std::path::PathBuf,
    /// Per-frame sensor noise variance, DN^2 (from the calibrated camera), >= 0.
    #[arg(long)]
    pub noise_var: f64,
    /// Black level subtracted from every pixel, DN.
    #[arg(long, default_value_t = 0.0)]
    pub dark_dn: f64,
    /// Channels per set, 1..=6.
    #[arg(long, default_value_t = 3)]
    pub channels: usize,
    /// The first set, degrees (angles of the stack).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, default_values_t = [0.0, 60.0, 120.0])]
    pub initial_angles_deg: Vec<f64>,
    /// A known target region X0,Y0,X1,Y1 (pixels, end exclusive).
    #[arg(long, value_delimiter = ',')]
    pub target_region: Option<Vec<u32>>,
    /// Otherwise: this fraction of pixels with the highest RX score, (0, 0.5).
    #[arg(long, default_value_t = 0.01)]
    pub anomalies: f64,
    /// Frames the loop may use, first set included.
    #[arg(long, default_value_t = 15)]
    pub frame_budget: usize,
    /// False-alarm rate of the empirical Pd, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
}

/// The frames of a stack's `frames.csv`, by its header: the `file` column and the angle in
/// `angle_deg` (a stack written by hand) or `commanded_angle_deg` (an `acquire export tiff`,
/// whose measured angles sit within the driver's readback tolerance of it). In an export,
/// dark frames (`kind` = dark) and frames that do not count (`accepted` = false) are left out.
fn read_stack_list(
    list: &std::path::Path,
    text: &str,
) -> Result<Vec<(f64, std::path::PathBuf)>, CommandError> {
    let dir = list.parent().unwrap_or(std::path::Path::new("."));
    let mut lines = text.lines().enumerate();
    let header: Vec<&str> = lines
        .next()
        .map(|(_, h)| h.split(',').map(str::trim).collect())
        .unwrap_or_default();
    let col = |name: &str| header.iter().position(|h| *h == name);
    let (Some(file_col), Some(angle_col)) = (
        col("file"),
        col("angle_deg").or_else(|| col("commanded_angle_deg")),
    ) else {
        return Err(CommandError(format!(
            "{}: the header {:?} lacks a column: allowed file and angle_deg (or an export's \
             file and commanded_angle_deg)",
            list.display(),
            header.join(",")
        )));
    };
    let (kind_col, accepted_col) = (col("kind"), col("accepted"));
    let mut stack = Vec::new();
    for (i, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let cols: Vec<&str> = line.split(',').map(str::trim).collect();
        let cell = |c: usize| cols.get(c).copied();
        if kind_col.and_then(cell) == Some("dark") || accepted_col.and_then(cell) == Some("false") {
            continue;
        }
        let (Some(file), Some(angle)) = (cell(file_col), cell(angle_col)) else {
            return Err(CommandError(format!(
                "{} line {}: expected the columns {}",
                list.display(),
                i + 1,
                header.join(",")
            )));
        };
        let angle: f64 = angle
            .parse()
            .ok()
            .filter(|a: &f64| a.is_finite())
            .ok_or_else(|| {
                CommandError(format!(
                    "{} line {}: {} = {angle:?} is not a finite number",
                    list.display(),
                    i + 1,
                    header[angle_col]
                ))
            })?;
        stack.push((angle, dir.join(file)));
    }
    Ok(stack)
}

/// `analyze aptd`: runs the loop over the stack. The sets are restricted to the stack's angles (the
/// best subset each round); a frame asked for again is served by the next unused copy at that
/// angle, or by the first copy again once all are used (then the "re-acquired" frame repeats,
/// and the JSON counts the reuses).
pub fn aptd_offline(args: &PlanAptdArgs) -> Result<Value, CommandError> {
    use polar_planner::aptd::{detection_scores, empirical_pd, stokes_images};
    use polar_planner::aptd::{Aptd, AptdConfig, AptdFrame, Step, TargetSpec};
    let dir = &args.frames;
    let list = dir.join("frames.csv");
    let text = std::fs::read_to_string(&list)
        .map_err(|e| CommandError(format!("{}: cannot read: {e}", list.display())))?;
    let stack = read_stack_list(&list, &text)?;
    if stack.len() < 3 {
        return Err(CommandError(format!(
            "{}: {} frames; allowed at least 3 at distinct angles",
            list.display(),
            stack.len()
        )));
    }
    let (width, height) = polar_engine::tiff_io::dimensions(&stack[0].1)
        .map_err(|e| CommandError(format!("{}: {e}", stack[0].1.display())))?;
    let mut images = Vec::with_capacity(stack.len());
    for (angle, path) in &stack {
        let px = crate::calibrate::read_tiff(path, width, height)
            .map_err(|e| CommandError(e.to_string()))?;
        images.push((
            *angle,
            px.iter()
                .map(|&v| f64::from(v) - args.dark_dn)
                .collect::<Vec<f64>>(),
        ));
    }
    let n_px = (width * height) as usize;
    let target = match &args.target_region {
        Some(r) if r.len() == 4 && r[0] < r[2] && r[1] < r[3] && r[2] <= width && r[3] <= height => {
            let mut mask = vec![false; n_px];
            for y in r[1]..r[3] {
                for x in r[0]..r[2] {
                    mask[(y * width + x) as usize] = true;
                }
            }
            TargetSpec::Region(mask)
        }
        Some(r) => {
            return Err(CommandError(format!(
                "target_region = {r:?} is invalid: allowed X0,Y0,X1,Y1 with X0 < X1 <= {width}, Y0 < Y1 <= {height}"
            )))
        }
        None => TargetSpec::Anomalies {
            fraction: args.anomalies,
        },
    };
    let mut available: Vec<f64> = images.iter().map(|(a, _)| a.to_radians()).collect();
    available.sort_by(f64::total_cmp);
    available.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let initial: Vec<f64> = args
        .initial_angles_deg
        .iter()
        .map(|d| d.to_radians())
        .collect();
    for a in &initial {
        if !available.iter().any(|b| (a - b).abs() < 1e-6) {
            return Err(CommandError(format!(
                "initial_angles_deg: {} is not an angle of the stack (allowed {:?})",
                a.to_degrees(),
                available.iter().map(|b| b.to_degrees()).collect::<Vec<_>>()
            )));
        }
    }
    let (mut aptd, mut step) = Aptd::new(AptdConfig {
        channels: args.channels,
        initial_angles_rad: initial,
        noise_var: args.noise_var,
        // An image stack carries no camera file: the analyzer is taken as ideal.
        instrument: polar_planner::Instrument::ideal(),
        target,
        constraints: Constraints {
            fixed_angles_rad: Some(available),
            ..Constraints::default()
        },
        angle_tol_rad: 0.01f64.to_radians(),
        scr_rel_tol: 0.01,
        frame_budget: args.frame_budget,
    })
    .map_err(planner_error)?;
    let mut used = vec![false; images.len()];
    let mut reused = 0usize;
    let mut last_set = Vec::new();
    while let Step::Acquire(angles) = step {
        last_set = angles.clone();
        let mut frames = Vec::new();
        for a in &angles {
            let same = |i: &usize| (images[*i].0.to_radians() - a).abs() < 1e-6;
            let pick = (0..images.len())
                .find(|i| same(i) && !used[*i])
                .or_else(|| {
                    reused += 1;
                    (0..images.len()).find(|i| same(i))
                })
                .ok_or_else(|| CommandError(format!("no frame at {} deg", a.to_degrees())))?;
            used[pick] = true;
            frames.push(AptdFrame {
                angle_rad: *a,
                pixels: images[pick].1.clone(),
            });
        }
        step = aptd.on_frames(frames).map_err(planner_error)?;
    }
    // Detection on the Stokes image of every frame used.
    let (s, _) = stokes_images(aptd.frames()).map_err(planner_error)?;
    let mask = aptd.target_mask().to_vec();
    let (rx, mf) = detection_scores(&s, &mask).map_err(planner_error)?;
    let decisions: Vec<Value> = aptd
        .decisions()
        .iter()
        .map(|d| {
            json!({
                "round": d.round,
                "frames_used": d.frames_used,
                "target_pixels": d.target_pixels,
                "scr_last_set": d.scr_last_set,
                "next_angles_deg": d.next_angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
                "scr_next": d.scr_next,
                "reason": d.reason,
            })
        })
        .collect();
    Ok(json!({
        "angles_deg": last_set.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "stop": format!("{step:?}"),
        "decisions": decisions,
        "frames_used": aptd.frames().len(),
        "frames_reused": reused,
        "detection": {
            "pfa": args.pfa,
            "pd_rx": empirical_pd(&rx, &mask, args.pfa),
            "pd_matched_filter": empirical_pd(&mf, &mask, args.pfa),
            "target_pixels": mask.iter().filter(|&&t| t).count(),
        },
    }))
}
