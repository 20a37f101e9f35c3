//! `polarimeter plan scene`: analyzer angles, exposure and a forecast for a target against a
//! background in a scene through a camera, from the model alone.
//!
//! It shares its flags, defaults, objective and saturation rule with `plan continuous`
//! ([`crate::plan_problem`]): the exposure of a step-and-shoot set is chosen by
//! [`polar_planner::step`], so both commands give the same exposure for the same scene, camera,
//! target and objective (`plan continuous` prints why its spinning analyzer's differs).
//!
//! # The objectives
//!
//! * `time-to-dolp-sigma` (the default): the set is `N` equally spaced angles (the best
//!   conditioned Stokes set, and every separation allowed), its phase the one whose target
//!   DoLP reaches the goal soonest (1-degree steps; the camera's real analyzer makes the phase
//!   matter slightly); the exposure the one that minimises the time to the goal.
//! * `scr-per-second`: the SCR-optimal set under the constraints and the exposure that
//!   maximises its SCR per second of set time, alternated twice (the set at the exposure, the
//!   exposure for the set).
//! * `scr-fraction`: the shortest exposure at which the best set's SCR reaches
//!   `--scr-fraction` of the clutter-limited SCR, `min t` subject to `max_set SCR(set, t) >=
//!   goal`, and the SCR-optimal set at that `t`. The bisection on `t` is exact because every
//!   set's SCR rises with `t` (each frame's noise variance in radiance units falls as the gain
//!   grows), so the best set's SCR does too.
//!
//! The SCR the optimiser maximises is the forecast's ([`Contrast::from_sensor`]), so the
//! printed `scr` is never below that of any set the constraints allow; the conventional sets'
//! SCRs are printed at the same exposure, each with whether the constraints allow it.

use crate::commands::CommandError;
use crate::plan_problem::{self, planner_error, ProblemArgs};
use clap::Args;
use polar_engine::continuous::planner_defaults;
use polar_model::metrics::{matched_filter, ClassStats, Roc};
use polar_model::sensor::{Exposure, SensorModel, SensorSignal};
use polar_planner::continuous::{ClassRadiance, ContinuousProblem, Objective};
use polar_planner::optimize::MAX_CHANNELS;
use polar_planner::step::{
    step_and_shoot, step_at_exposure, still_exposure_limit_s, StepPrediction,
};
use polar_planner::stokes::STOKES_MAX_CONDITION;
use polar_planner::{optimise, Constraints, Contrast, Optimum};
use serde_json::{json, Value};

/// `plan scene` arguments: the planning flags `plan continuous` shares, and the set's own.
#[derive(Debug, Clone, Args)]
pub struct PlanSceneArgs {
    /// The flags shared with `plan continuous`.
    #[command(flatten)]
    pub problem: ProblemArgs,
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
    /// 6.21, that of 0/30/60). Goes with --objective scr-per-second or scr-fraction.
    #[arg(long)]
    pub detection_only: bool,
    /// With --objective scr-fraction: the SCR to reach, as a fraction of the clutter-limited
    /// SCR, (0, 0.999].
    #[arg(long, default_value_t = 0.9)]
    pub scr_fraction: f64,
    /// False-alarm rate of the Pd forecast, (0, 0.5].
    #[arg(long, default_value_t = 1e-3)]
    pub pfa: f64,
}

/// What the set and its exposure optimise.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Goal {
    /// The planner's objectives, shared with `plan continuous`.
    Planner(Objective),
    /// The shortest exposure reaching this fraction of the clutter-limited SCR.
    ScrFraction(f64),
}

const OBJECTIVES: &str = "time-to-dolp-sigma, scr-per-second, scr-fraction";

fn goal(args: &PlanSceneArgs) -> Result<Goal, CommandError> {
    match args.problem.objective.as_str() {
        "scr-fraction" => Ok(Goal::ScrFraction(plan_problem::flag(
            "scr-fraction",
            args.scr_fraction,
            0.0,
            0.999,
            true,
        )?)),
        "time-to-dolp-sigma" | "scr-per-second" => {
            Ok(Goal::Planner(plan_problem::objective(&args.problem)?))
        }
        other => Err(CommandError::input(
            "--objective",
            format!(" {other:?} is not known: allowed {OBJECTIVES}"),
        )),
    }
}

/// The set's shape from the flags: channels, whether it forms a Stokes image, the smallest
/// separation (radians).
fn set_shape(args: &PlanSceneArgs, goal: Goal) -> Result<(usize, bool, f64), CommandError> {
    let n = args.channels;
    if !(1..=MAX_CHANNELS).contains(&n) {
        return Err(CommandError::input(
            "--channels",
            format!(" {n} is out of range: allowed 1 to {MAX_CHANNELS}"),
        ));
    }
    let stokes = !args.detection_only;
    if stokes && n < 3 {
        return Err(CommandError::input(
            "--channels",
            format!(
                " {n} is out of range for a Stokes set: allowed 3 to {MAX_CHANNELS} (a \
             linear Stokes vector has 3 unknowns), or add --detection-only for 1 or 2 channels"
            ),
        ));
    }
    if !stokes && matches!(goal, Goal::Planner(Objective::TimeToDolpSigma { .. })) {
        return Err(CommandError::input(
            "--detection-only",
            " goes with --objective scr-per-second or scr-fraction: a DoLP \
             goal needs a Stokes set",
        ));
    }
    let widest = 180.0 / n as f64;
    let min_separation_deg = match args.min_separation_deg {
        None => 0.0,
        Some(v) if v.is_finite() && (0.0..=widest).contains(&v) && v < 90.0 => v,
        Some(v) => {
            return Err(CommandError::input(
                "--min-separation-deg",
                format!(
                    " {v} is out of range for {n} angles: allowed [0, {}] \
                 ({n} angles that far apart must fit in 180 deg)",
                    widest.min(89.99)
                ),
            ))
        }
    };
    plan_problem::flag("pfa", args.pfa, 0.0, 0.5, true)?;
    if let Some(b) = args.time_budget_s {
        plan_problem::flag("time-budget-s", b, 0.0, 1e6, true)?;
    }
    Ok((n, stokes, min_separation_deg.to_radians()))
}

/// A class's exposure for `t_int_s`: its mean radiance and its clutter.
fn exposure(t_int_s: f64, class: &ClassRadiance) -> Exposure {
    let mut e = Exposure::new(
        t_int_s,
        polar_model::polarization::Stokes(class.mean_w_m2_sr),
    );
    e.radiance_cov_w2_m4_sr2 = class.cov_w2_m4_sr2;
    e
}

/// The frames' statistics of one class at `angles_rad` for `t_int_s`.
fn frames(
    sensor: &SensorModel,
    angles_rad: &[f64],
    t_int_s: f64,
    class: &ClassRadiance,
) -> Result<SensorSignal, CommandError> {
    Ok(sensor.signal(angles_rad, &exposure(t_int_s, class))?)
}

/// Everything the choice of the set and the exposure needs.
struct Ctx<'a> {
    problem: &'a ContinuousProblem,
    n: usize,
    constraints: Constraints,
    settle_s: f64,
}

/// The optimiser's angle tolerance, radians (0.01 deg).
fn tol_rad() -> f64 {
    0.01f64.to_radians()
}

impl Ctx<'_> {
    /// The planner's contrast at `t_int_s` (the camera's real rows and its noise at the
    /// background's light), whose SCR is the forecast's.
    fn contrast_at(&self, t_int_s: f64) -> Result<Contrast, CommandError> {
        let (t, b) = (&self.problem.target, &self.problem.background);
        Contrast::from_sensor(
            &self.problem.sensor,
            t_int_s,
            &t.mean_w_m2_sr,
            &b.mean_w_m2_sr,
            &b.cov_w2_m4_sr2,
        )
        .map_err(planner_error)
    }

    /// The SCR-optimal set under the constraints at `t_int_s`.
    fn best_at(&self, t_int_s: f64) -> Result<(Contrast, Optimum), CommandError> {
        let c = self.contrast_at(t_int_s)?;
        let o = optimise(&c, self.n, &self.constraints, tol_rad()).map_err(planner_error)?;
        Ok((c, o))
    }
}

/// The chosen set, its exposure, what decided the exposure, and the step-and-shoot
/// prediction (none for a detection-only set that forms no Stokes estimate).
struct Choice {
    angles_rad: Vec<f64>,
    t_s: f64,
    rule: String,
    step: Option<StepPrediction>,
    notes: Vec<String>,
}

impl Choice {
    fn from_step(step: StepPrediction, notes: Vec<String>) -> Choice {
        Choice {
            angles_rad: step.angles_rad.clone(),
            t_s: step.exposure_s,
            rule: step.exposure_rule.describe().to_string(),
            step: Some(step),
            notes,
        }
    }
}

/// `time-to-dolp-sigma`: equally spaced angles, the phase (1-degree steps) whose time to the
/// goal is least (ties to the smaller phase), each with its own exposure.
fn by_dolp_goal(ctx: &Ctx) -> Result<Choice, CommandError> {
    let spacing_deg = 180.0 / ctx.n as f64;
    let time = |p: &StepPrediction| p.time_to_target_s.unwrap_or(f64::INFINITY);
    let mut best: Option<StepPrediction> = None;
    let mut phase_deg = 0.0;
    while phase_deg < spacing_deg - 1e-9 {
        let angles: Vec<f64> = (0..ctx.n)
            .map(|k| (phase_deg + spacing_deg * k as f64).to_radians())
            .collect();
        let s = step_and_shoot(ctx.problem, &angles, ctx.settle_s).map_err(planner_error)?;
        if best
            .as_ref()
            .is_none_or(|b| time(&s) < time(b) * (1.0 - 1e-9))
        {
            best = Some(s);
        }
        phase_deg += 1.0;
    }
    let step = best.ok_or_else(|| CommandError::failed("no phase was scored"))?;
    Ok(Choice::from_step(step, Vec::new()))
}

/// The step-and-shoot prediction of `angles` at `t_s`, none for a detection-only set that
/// forms no Stokes estimate (fewer than 3 distinct angles).
fn step_for(ctx: &Ctx, angles: &[f64], t_s: f64) -> Result<Option<StepPrediction>, CommandError> {
    match step_at_exposure(ctx.problem, angles, t_s, ctx.settle_s) {
        Ok(s) => Ok(Some(s)),
        Err(_) if ctx.constraints.max_condition.is_none() => Ok(None),
        Err(e) => Err(planner_error(e)),
    }
}

/// `scr-per-second`: the exposure in `[t_min, t_max]` whose SCR-optimal set has the most SCR
/// per second of set time (scan and golden-section search in `log t`, the set re-optimised
/// at every exposure), and that set.
fn by_scr_per_second(ctx: &Ctx, t_max: f64) -> Result<Choice, CommandError> {
    let p = ctx.problem;
    let t_min = p.camera.min_exposure_s.min(t_max);
    let per_s = |t: f64| -> Result<(f64, Vec<f64>), CommandError> {
        let o = ctx.best_at(t)?.1;
        let set_s = polar_planner::step::set_s(p, &o.angles_rad, t, ctx.settle_s);
        Ok((o.scr / set_s, o.angles_rad))
    };
    let (at_max, _) = per_s(t_max)?;
    let best = polar_planner::log_search::scan_then_golden(t_min.ln(), t_max.ln(), 24, 40, |x| {
        Ok::<f64, CommandError>(-per_s(x.exp())?.0)
    })?;
    let (t, rule) = match best {
        Some((x, v)) if -v > at_max * (1.0 + 1e-9) => {
            (x.exp(), polar_planner::step::ExposureRule::ScrPerSecondPeak)
        }
        _ => (t_max, polar_planner::step::ExposureRule::Saturation),
    };
    let angles = per_s(t)?.1;
    let step = step_for(ctx, &angles, t)?;
    Ok(Choice {
        angles_rad: angles,
        t_s: t,
        rule: rule.describe().to_string(),
        step,
        notes: Vec::new(),
    })
}

/// `scr-fraction`: the shortest exposure whose best set reaches `fraction` of the clutter
/// limit `limit` (module docs), within `t_max`.
fn by_scr_fraction(
    ctx: &Ctx,
    fraction: f64,
    limit: f64,
    t_max: f64,
) -> Result<Choice, CommandError> {
    let goal = fraction * limit;
    let mut notes = Vec::new();
    let min_t = ctx.problem.camera.min_exposure_s.min(t_max);
    let (_, at_max) = ctx.best_at(t_max)?;
    let t = if at_max.scr < goal {
        notes.push(format!(
            "the SCR reaches only {:.3} of the clutter limit at the longest allowed exposure \
             ({:.4} ms); asked {fraction}",
            at_max.scr / limit,
            t_max * 1e3,
        ));
        t_max
    } else if ctx.best_at(min_t)?.1.scr >= goal {
        min_t
    } else {
        // The best set's SCR rises with t: bisection on log t.
        let (mut lo, mut hi) = (min_t.ln(), t_max.ln());
        for _ in 0..40 {
            if hi - lo < 1e-4 {
                break;
            }
            let mid = 0.5 * (lo + hi);
            if ctx.best_at(mid.exp())?.1.scr >= goal {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        hi.exp()
    };
    let angles = ctx.best_at(t)?.1.angles_rad;
    let step = step_for(ctx, &angles, t)?;
    Ok(Choice {
        angles_rad: angles,
        t_s: t,
        rule: format!(
            "the shortest exposure at which the best set's SCR reaches {fraction} of the \
             clutter limit"
        ),
        step,
        notes,
    })
}

/// The exposure a time budget for one set leaves (a conservative move allowance: `N` moves
/// of 90 deg, the longest the short way takes, and their settling), or an error when the
/// budget does not cover the moves.
fn budget_exposure_s(ctx: &Ctx, budget_s: f64) -> Result<f64, CommandError> {
    let p = ctx.problem;
    let n = ctx.n as f64;
    let move_s = polar_planner::continuous::move_s(
        std::f64::consts::FRAC_PI_2,
        p.stage.max_speed_rad_per_s,
        p.stage.acceleration_rad_per_s2,
    );
    let overhead = n * (move_s + ctx.settle_s + p.camera.readout_s);
    let t = (budget_s - overhead) / n;
    if t < p.camera.min_exposure_s {
        return Err(CommandError::input(
            "--time-budget-s",
            format!(
                " {budget_s} does not cover {} moves and settles ({overhead:.3} s) \
             and {} shortest exposures: allowed more than that",
                ctx.n, ctx.n
            ),
        ));
    }
    Ok(t)
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

/// The matched filter on the frames of [`SensorModel::signal`] at `pfa`: the ROC and the two
/// classes' frames.
fn forecast_roc(
    sensor: &SensorModel,
    angles_rad: &[f64],
    t_int_s: f64,
    p: &ContinuousProblem,
    pfa: f64,
) -> Result<(Roc, SensorSignal, SensorSignal), CommandError> {
    let st = frames(sensor, angles_rad, t_int_s, &p.target)?;
    let sb = frames(sensor, angles_rad, t_int_s, &p.background)?;
    let class =
        |field, s: &SensorSignal| ClassStats::new(field, s.mean_dn.clone(), s.cov_dn.clone());
    let roc = matched_filter(&class("target", &st)?, &class("background", &sb)?, pfa)?;
    Ok((roc, st, sb))
}

/// The set's description: its kind, rule, conditioning, and what the Stokes rule costs
/// against the other kind of set at the same exposure.
fn set_json(
    ctx: &Ctx,
    stokes: bool,
    angles: &[f64],
    scr: f64,
    contrast: &Contrast,
    by_dolp: bool,
) -> Result<(Value, Option<String>), CommandError> {
    let n = ctx.n;
    let sep_deg = ctx.constraints.min_separation_rad.to_degrees();
    let other = if n >= 3 {
        let c = Constraints {
            max_condition: (!stokes).then_some(STOKES_MAX_CONDITION),
            ..ctx.constraints.clone()
        };
        Some(optimise(contrast, n, &c, tol_rad()).map_err(planner_error)?)
    } else {
        None
    };
    let distinct = {
        let mut a = angles.to_vec();
        a.sort_by(f64::total_cmp);
        a.dedup_by(|x, y| (*x - *y).abs() < 1e-9);
        a.len()
    };
    let finite = |k: f64| if k.is_finite() { json!(k) } else { Value::Null };
    let mut v = json!({
        "condition_number_ideal": finite(polar_planner::stokes::stokes_condition(angles)),
        "condition_number": finite(contrast.condition_number(angles)),
    });
    let mut note = None;
    if stokes {
        let o = other.as_ref().map_or(scr, |o| o.scr);
        v["kind"] = json!("stokes");
        v["rule"] = json!(if by_dolp {
            format!(
                "{n} equally spaced angles (the best conditioned Stokes set), the phase whose \
                 target DoLP reaches the goal soonest"
            )
        } else {
            format!(
                "{n} angles whose ideal measurement matrix has a condition number of at most \
                 {STOKES_MAX_CONDITION} (that of 0/30/60, the worst 3-angle set 30 deg apart), \
                 every two at least {sep_deg} deg apart (the stage's separation)"
            )
        });
        v["scr_detection_only"] = json!(o);
        v["angles_detection_only_deg"] = json!(other.as_ref().map(|o| degrees(&o.angles_rad)));
        v["stokes_cost_scr"] = json!((o - scr).max(0.0));
        v["stokes_cost_percent"] = json!(100.0 * (o - scr).max(0.0) / o.max(1e-300));
    } else {
        v["kind"] = json!("detection-only");
        v["rule"] = json!(format!(
            "{n} angles at least {sep_deg} deg apart, repeats allowed: {distinct} distinct \
             angle(s)"
        ));
        if let Some(o) = &other {
            v["scr_stokes"] = json!(o.scr);
            v["angles_stokes_deg"] = json!(degrees(&o.angles_rad));
            v["stokes_cost_scr"] = json!((scr - o.scr).max(0.0));
            v["stokes_cost_percent"] = json!(100.0 * (scr - o.scr).max(0.0) / scr.max(1e-300));
        }
        if distinct < 3 {
            note = Some(format!(
                "detection only: the set has {distinct} distinct angle(s); it detects in the \
                 intensity frames but forms no Stokes image"
            ));
        }
    }
    Ok((v, note))
}

/// The objective's block of the output: its name, its goal, and the chosen set's figures.
fn objective_json(goal: Goal, step: Option<&StepPrediction>, set_s: f64) -> Value {
    let mut v = match goal {
        Goal::Planner(Objective::TimeToDolpSigma { dolp_sigma }) => {
            json!({"name": "time-to-dolp-sigma", "dolp_sigma": dolp_sigma})
        }
        Goal::Planner(Objective::ScrPerSecond) => json!({"name": "scr-per-second"}),
        Goal::ScrFraction(f) => json!({"name": "scr-fraction", "scr_fraction": f}),
    };
    v["set_s"] = json!(set_s);
    if let Some(s) = step {
        v["sigma_dolp_per_set"] = json!(s.sigma_dolp);
        v["scr_per_set"] = json!(s.scr);
        v["scr_per_s"] = json!(s.scr_per_s);
        if let (Some(m), Some(t)) = (s.sets, s.time_to_target_s) {
            v["sets_to_target"] = json!(m);
            v["time_to_target_s"] = json!(t);
        }
    }
    v
}

/// The SCR terms of the forecast, per frame.
fn scr_terms(st: &SensorSignal, sb: &SensorSignal) -> Value {
    let n = st.mean_dn.len();
    let sensor_sigma: Vec<f64> = (0..n)
        .map(|i| {
            (sb.cov_dn[(i, i)] - sb.variance.clutter_dn2[i])
                .max(0.0)
                .sqrt()
        })
        .collect();
    json!({
        "definition": "matched filter over the set's frames: (mu_t - mu_b)^T Sigma_b^-1 (mu_t - mu_b), DN; Sigma_b = the background's clutter (off-diagonal too) plus its sensor noise",
        "mean_difference_dn": (0..n).map(|i| st.mean_dn[i] - sb.mean_dn[i]).collect::<Vec<_>>(),
        "background_sigma_dn": (0..n).map(|i| sb.cov_dn[(i, i)].max(0.0).sqrt()).collect::<Vec<_>>(),
        "clutter_sigma_dn": sb.variance.clutter_dn2.iter().map(|v| v.max(0.0).sqrt()).collect::<Vec<_>>(),
        "sensor_sigma_dn": sensor_sigma,
    })
}

/// The forecast of the chosen set: the matched filter's SCR and Pd, each class's DoLP sigma
/// and saturation margin, the conventional sets at the same exposure.
fn forecast_json(
    ctx: &Ctx,
    args: &PlanSceneArgs,
    choice: &Choice,
    limit: f64,
    t_sat: f64,
) -> Result<(Value, Roc), CommandError> {
    let p = ctx.problem;
    let (sensor, t) = (&p.sensor, choice.t_s);
    let (roc, st, sb) = forecast_roc(sensor, &choice.angles_rad, t, p, args.pfa)?;
    let pd_1e3 = forecast_roc(sensor, &choice.angles_rad, t, p, 1e-3)?.0.pd;
    let margin = |s: &SensorSignal| -> f64 {
        (0..s.mean_dn.len())
            .map(|i| (s.saturation_dn - s.mean_dn[i]) / s.cov_dn[(i, i)].max(1e-300).sqrt())
            .fold(f64::INFINITY, f64::min)
    };
    let dolp_sigma = |m: &ClassRadiance| -> Value {
        match polar_model::validation::analytic_products(
            sensor,
            &choice.angles_rad,
            &exposure(t, m),
            polar_model::stats::MethodChoice::default(),
            polar_model::stats::RegimeChoice::Auto,
        ) {
            Ok(x) => json!(x.stats.dolp_std),
            Err(e) => json!({ "none": e.to_string() }),
        }
    };
    let mut conv = serde_json::Map::new();
    for (name, deg) in polar_planner::optimize::CONVENTIONAL {
        let rad: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
        let (r, _, _) = forecast_roc(sensor, &rad, t, p, args.pfa)?;
        let allowed =
            rad.len() == ctx.n && polar_planner::optimize::allowed(&rad, &ctx.constraints);
        conv.insert(
            name.to_string(),
            json!({ "scr": r.scr, "pd_at_pfa": r.pd, "allowed": allowed }),
        );
    }
    let set_s = polar_planner::step::set_s(p, &choice.angles_rad, t, ctx.settle_s);
    let (tn, bn) = (&p.target.name, &p.background.name);
    Ok((
        json!({
            "scr": roc.scr,
            "scr_terms": scr_terms(&st, &sb),
            "scr_clutter_limit": limit,
            "scr_conventional": conv,
            "pd_at_pfa_1e-3": pd_1e3,
            "pd_at_pfa": roc.pd,
            "pfa": args.pfa,
            "dolp_sigma": { tn.clone(): dolp_sigma(&p.target), bn.clone(): dolp_sigma(&p.background) },
            "saturation_margin_sigma": { tn.clone(): margin(&st), bn.clone(): margin(&sb) },
            "saturation_limit_ms": t_sat * 1e3,
            "frames": ctx.n,
            "duration_s": set_s,
        }),
        roc,
    ))
}

/// `plan scene ...` (module docs).
pub fn scene_plan(args: &PlanSceneArgs) -> Result<Value, CommandError> {
    let goal = goal(args)?;
    let (n, stokes, min_separation_rad) = set_shape(args, goal)?;
    let objective = match goal {
        Goal::Planner(o) => o,
        Goal::ScrFraction(_) => Objective::ScrPerSecond,
    };
    let frames_cap = planner_defaults::MAX_FRAMES_PER_HALF_TURN as usize;
    let (mut problem, stage_from) =
        plan_problem::problem(&args.problem, objective, 0.0, frames_cap)?;
    let mut notes: Vec<String> = problem.sensor.warnings().to_vec();
    let t_sat = still_exposure_limit_s(&problem).map_err(planner_error)?;
    let constraints = Constraints {
        min_separation_rad,
        max_condition: stokes.then_some(STOKES_MAX_CONDITION),
        ..Constraints::default()
    };
    let settle_s = args.problem.settle_s;
    let mut t_max = t_sat;
    if let Some(budget) = args.time_budget_s {
        let ctx = Ctx {
            problem: &problem,
            n,
            constraints: constraints.clone(),
            settle_s,
        };
        let t_budget = budget_exposure_s(&ctx, budget)?;
        if t_budget < t_max {
            notes.push(format!(
                "the time budget limits the exposure to {:.4} ms (saturation allows {:.4} ms)",
                t_budget * 1e3,
                t_sat * 1e3
            ));
            t_max = t_budget;
        }
    }
    let budget_binds = t_max < t_sat;
    if budget_binds {
        problem.camera.max_exposure_s = t_max;
    }
    let ctx = Ctx {
        problem: &problem,
        n,
        constraints,
        settle_s,
    };
    // Clutter limit: the optimum of these rows with the sensor noise removed.
    let quiet = ctx
        .contrast_at(t_max)?
        .noise_free()
        .map_err(planner_error)?;
    let limit = optimise(&quiet, n, &ctx.constraints, tol_rad())
        .map_err(planner_error)?
        .scr;
    if limit <= 0.0 {
        return Err(CommandError::failed(format!(
            "no contrast between {} and {}: their Stokes means are equal, so no analyzer set \
             or exposure separates them",
            problem.target.name, problem.background.name
        )));
    }
    let mut choice = match goal {
        Goal::Planner(Objective::TimeToDolpSigma { .. }) => by_dolp_goal(&ctx)?,
        Goal::Planner(Objective::ScrPerSecond) => by_scr_per_second(&ctx, t_max)?,
        Goal::ScrFraction(f) => by_scr_fraction(&ctx, f, limit, t_max)?,
    };
    if budget_binds && choice.t_s >= t_max * (1.0 - 1e-9) {
        choice.rule = "the longest exposure the time budget allows".into();
    }
    notes.extend(choice.notes.iter().cloned());
    let contrast = ctx.contrast_at(choice.t_s)?;
    notes.extend(contrast.notes.iter().cloned());
    let (forecast, roc) = forecast_json(&ctx, args, &choice, limit, t_sat)?;
    let by_dolp = matches!(goal, Goal::Planner(Objective::TimeToDolpSigma { .. }));
    if !by_dolp {
        // The optimiser's SCR is the forecast's (the same model): a difference is a sign of
        // a regularised near-singular covariance.
        let opt = ctx.best_at(choice.t_s)?.1.scr;
        if (roc.scr - opt).abs() > 1e-6 * roc.scr.max(1e-300) {
            notes.push(format!(
                "the forecast's SCR {} differs from the optimiser's {opt} by more than 1e-6 \
                 relative (the forecast regularised a near-singular covariance?)",
                roc.scr
            ));
        }
    }
    let (set, set_note) = set_json(
        &ctx,
        stokes,
        &choice.angles_rad,
        roc.scr,
        &contrast,
        by_dolp,
    )?;
    notes.extend(set_note);
    let set_s = forecast["duration_s"].as_f64().unwrap_or(f64::NAN);
    Ok(json!({
        "angles_deg": degrees(&choice.angles_rad),
        "t_int_ms": choice.t_s * 1e3,
        "exposure": {
            "us": choice.t_s * 1e6,
            "rule": choice.rule,
            "saturation_limit_us": t_sat * 1e6,
        },
        "objective": objective_json(goal, choice.step.as_ref(), set_s),
        "stage": plan_problem::stage_json(&problem.stage, stage_from),
        "set": set,
        "forecast": forecast,
        "notes": notes,
        "warnings": roc.warnings,
    }))
}
