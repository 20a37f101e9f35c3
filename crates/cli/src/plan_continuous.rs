//! `polarimeter plan continuous`: frames per half turn, exposure and speed of a spinning
//! analyzer for a target against a background of a scene, within the camera's and the stage's
//! limits, which limit binds, and the step-and-shoot set on the same rig beside it
//! ([`polar_planner::continuous`]; MODEL.md, exposures while the analyzer turns).

use crate::plan_problem::{self, ProblemArgs};
use anyhow::bail;
use clap::Args;
use polar_engine::continuous::planner_defaults;
use polar_planner::continuous::{
    plan_continuous, ContinuousChoice, ContinuousProblem, Objective, MAX_FRAMES_PER_HALF_TURN,
};
use polar_planner::step::{step_and_shoot, ExposureRule, StepPrediction};
use serde_json::{json, Value};

/// `plan continuous` arguments: the planning flags `plan scene` shares
/// ([`crate::plan_problem`]: the defaults are the simulated rig's stage and camera), and the
/// continuous planner's own.
#[derive(Debug, Clone, Args)]
pub struct PlanContinuousArgs {
    /// The flags shared with `plan scene`.
    #[command(flatten)]
    pub problem: ProblemArgs,
    /// Timing uncertainty of each frame, microseconds, [0, 1e6] (0: frames triggered at
    /// encoder positions; a free-running camera's timestamp uncertainty otherwise).
    #[arg(long, default_value_t = 0.0)]
    pub timing_sigma_us: f64,
    /// The most frames per half turn, 3..=360.
    #[arg(long, default_value_t = planner_defaults::MAX_FRAMES_PER_HALF_TURN as usize)]
    pub max_frames_per_half_turn: usize,
    /// Print JSON (one object) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// The planner's problem from the arguments (errors name the flag) and where the stage's
/// limits came from.
pub fn problem(args: &PlanContinuousArgs) -> anyhow::Result<(ContinuousProblem, &'static str)> {
    let objective = plan_problem::objective(&args.problem)?;
    let timing_us = plan_problem::flag("timing-sigma-us", args.timing_sigma_us, 0.0, 1e6, false)?;
    if !(3..=MAX_FRAMES_PER_HALF_TURN).contains(&args.max_frames_per_half_turn) {
        bail!(
            "--max-frames-per-half-turn {} is out of range: allowed 3 to \
             {MAX_FRAMES_PER_HALF_TURN}",
            args.max_frames_per_half_turn
        );
    }
    Ok(plan_problem::problem(
        &args.problem,
        objective,
        timing_us * 1e-6,
        args.max_frames_per_half_turn,
    )?)
}

/// Why the continuous exposure and the step-and-shoot set's differ (or that they agree), in
/// one sentence: the same saturation rule and objective choose both.
pub fn exposure_comparison(c: &ContinuousChoice, step: &StepPrediction) -> String {
    let (tc, ts) = (c.exposure_s * 1e6, step.exposure_s * 1e6);
    if (tc / ts - 1.0).abs() <= 1e-9 {
        return format!(
            "the same exposure, {tc:.1} us, for both: {}",
            step.exposure_rule.describe()
        );
    }
    let pct = 100.0 * (tc / ts - 1.0);
    let interval_us = c.frame_interval_s * 1e6;
    let rule = step.exposure_rule.describe();
    let why = if tc < ts {
        format!(
            "the continuous exposure is held by its frame timing ({interval_us:.1} us between \
             frames at {} frames per half turn and {:.2} deg/s); the still set's is {rule}",
            c.frames_per_half_turn,
            c.speed_rad_per_s.to_degrees()
        )
    } else if step.exposure_rule == ExposureRule::Saturation {
        format!(
            "the analyzer turns {:.3} deg during each continuous exposure, which lowers the \
             brightest frame, so saturation allows a longer one; the still set's is {rule}",
            c.span_rad.to_degrees()
        )
    } else {
        format!(
            "the still set's is {rule}; the continuous one is the longest its frame timing and \
             saturation allow (a longer exposure always helps a spinning analyzer)"
        )
    };
    format!("continuous {tc:.3} us, step-and-shoot {ts:.3} us ({pct:+.3} %): {why}")
}

/// The choice and the step-and-shoot comparison as JSON (degrees, microseconds, seconds),
/// with the stage's limits and their source.
pub fn to_json(
    problem: &ContinuousProblem,
    stage_from: &str,
    c: &ContinuousChoice,
    step: &StepPrediction,
) -> Value {
    let binds: Vec<Value> = c
        .binds
        .iter()
        .map(|b| json!({"limit": b.limit.name(), "gain": b.gain, "message": b.message}))
        .collect();
    let opt = |v: Option<f64>| v.map_or(Value::Null, |x| json!(x));
    let ratio = match (step.time_to_target_s, c.time_to_target_s) {
        (Some(s), Some(k)) => json!(s / k),
        _ => Value::Null,
    };
    json!({
        "target": problem.target.name,
        "background": problem.background.name,
        "objective": match problem.objective {
            Objective::TimeToDolpSigma { dolp_sigma } =>
                json!({"time_to_dolp_sigma": dolp_sigma}),
            Objective::ScrPerSecond => json!("scr_per_second"),
        },
        "stage": plan_problem::stage_json(&problem.stage, stage_from),
        "continuous": {
            "frames_per_half_turn": c.frames_per_half_turn,
            "exposure_us": c.exposure_s * 1e6,
            "speed_deg_per_s": c.speed_rad_per_s.to_degrees(),
            "frame_interval_us": c.frame_interval_s * 1e6,
            "span_deg": c.span_rad.to_degrees(),
            "half_turn_s": c.half_turn_s,
            "sets_per_s": 1.0 / c.half_turn_s,
            "spin_up_s": c.spin_up_s,
            "condition": c.condition,
            "s0_dn": c.s0_dn,
            "sigma_s0_dn": c.sigma_stokes_dn[0],
            "sigma_s1_dn": c.sigma_stokes_dn[1],
            "sigma_s2_dn": c.sigma_stokes_dn[2],
            "dolp": c.dolp,
            "sigma_dolp_per_half_turn": c.sigma_dolp,
            "scr_per_half_turn": c.scr,
            "scr_per_s": c.scr_per_s,
            "half_turns_to_target": opt(c.half_turns),
            "time_to_target_s": opt(c.time_to_target_s),
            "peak_fraction_of_saturation": c.peak_fraction,
            "binds": binds,
        },
        "step_and_shoot": {
            "angles_deg": step.angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
            "exposure_us": step.exposure_s * 1e6,
            "exposure_rule": step.exposure_rule.describe(),
            "exposure_limit_us": step.exposure_limit_s * 1e6,
            "set_s": step.set_s,
            "sets_per_s": 1.0 / step.set_s,
            "s0_dn": step.s0_dn,
            "sigma_s0_dn": step.sigma_stokes_dn[0],
            "sigma_s1_dn": step.sigma_stokes_dn[1],
            "sigma_s2_dn": step.sigma_stokes_dn[2],
            "sigma_dolp_per_set": step.sigma_dolp,
            "scr_per_set": step.scr,
            "scr_per_s": step.scr_per_s,
            "sets_to_target": opt(step.sets),
            "time_to_target_s": opt(step.time_to_target_s),
        },
        "time_to_target_ratio": ratio,
        "exposure_comparison": exposure_comparison(c, step),
    })
}

/// The JSON of [`to_json`] as text for a terminal.
pub fn text(v: &Value) -> String {
    let c = &v["continuous"];
    let s = &v["step_and_shoot"];
    let f = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
    let mut out = format!(
        "continuous rotation, target {} against {}:\n  {} frames per half turn, exposure {:.1} \
         us, {:.2} deg/s (span {:.3} deg, one set every {:.4} s, spin-up {:.3} s)\n  per half \
         turn: sigma S1 {:.3} DN, S2 {:.3} DN (S0 {:.1} DN), DoLP {:.4} +- {:.5}, SCR {:.4}; \
         SCR per second {:.4}\n",
        v["target"].as_str().unwrap_or(""),
        v["background"].as_str().unwrap_or(""),
        c["frames_per_half_turn"],
        f(&c["exposure_us"]),
        f(&c["speed_deg_per_s"]),
        f(&c["span_deg"]),
        f(&c["half_turn_s"]),
        f(&c["spin_up_s"]),
        f(&c["sigma_s1_dn"]),
        f(&c["sigma_s2_dn"]),
        f(&c["s0_dn"]),
        f(&c["dolp"]),
        f(&c["sigma_dolp_per_half_turn"]),
        f(&c["scr_per_half_turn"]),
        f(&c["scr_per_s"]),
    );
    if let Some(t) = c["time_to_target_s"].as_f64() {
        out += &format!(
            "  time to the DoLP target: {t:.4} s ({:.2} half turns)\n",
            f(&c["half_turns_to_target"])
        );
    }
    match c["binds"].as_array() {
        Some(b) if !b.is_empty() => {
            out += "  binding limits:\n";
            for x in b {
                out += &format!("  - {}\n", x["message"].as_str().unwrap_or(""));
            }
        }
        _ => {
            out += "  no limit binds: the target is met in one half turn, at a speed inside \
                    the limits\n"
        }
    }
    out += &format!(
        "step-and-shoot at {:?} deg: exposure {:.1} us, one set every {:.4} s, sigma S1 {:.3} \
         DN, S2 {:.3} DN (S0 {:.1} DN), DoLP sigma per set {:.5}\n",
        s["angles_deg"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect::<Vec<_>>())
            .unwrap_or_default(),
        f(&s["exposure_us"]),
        f(&s["set_s"]),
        f(&s["sigma_s1_dn"]),
        f(&s["sigma_s2_dn"]),
        f(&s["s0_dn"]),
        f(&s["sigma_dolp_per_set"]),
    );
    if let (Some(t), Some(r)) = (
        s["time_to_target_s"].as_f64(),
        v["time_to_target_ratio"].as_f64(),
    ) {
        out += &format!(
            "  time to the DoLP target: {t:.4} s, {r:.2} times the continuous rotation's\n"
        );
    }
    if let Some(why) = v["exposure_comparison"].as_str() {
        out += &format!("exposure: {why}\n");
    }
    out
}

/// The choice as JSON: the problem, the planner, the step-and-shoot set 0/45/90/135 beside it
/// (its exposure chosen by the same objective and saturation rule, as `plan scene` chooses).
pub fn plan(args: &PlanContinuousArgs) -> anyhow::Result<Value> {
    let (p, stage_from) = problem(args)?;
    let choice = plan_continuous(&p)?;
    let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|d| d.to_radians())
        .collect();
    let step = step_and_shoot(&p, &angles, args.problem.settle_s)?;
    Ok(to_json(&p, stage_from, &choice, &step))
}

/// `plan continuous`: the output to print (JSON with --json, else text).
pub fn run(args: &PlanContinuousArgs) -> anyhow::Result<String> {
    let v = plan(args)?;
    Ok(if args.json {
        format!("{v}\n")
    } else {
        text(&v)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn root() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
    }

    fn args() -> PlanContinuousArgs {
        PlanContinuousArgs {
            problem: ProblemArgs {
                scene: root().join("examples/rooftop_panels.toml"),
                camera: Some(root().join("examples/cameras/cmos_modern.toml")),
                rig: None,
                target: "panel".into(),
                background: "asphalt".into(),
                objective: "time-to-dolp-sigma".into(),
                dolp_sigma: 1e-3,
                max_speed_deg_per_s: Some(360.0),
                acceleration_deg_per_s2: Some(2880.0),
                max_frame_rate_hz: 200.0,
                readout_us: 0.0,
                min_exposure_us: 10.0,
                max_exposure_us: 1e6,
                saturation_sigma: 3.0,
                settle_s: 0.0,
                tolerance: 1e-3,
            },
            timing_sigma_us: 0.0,
            max_frames_per_half_turn: 24,
            json: true,
        }
    }

    /// The rooftop scene on the simulated rig: the JSON carries the choice within the limits
    /// (speed at most 360 deg/s, frames at most 200 per second, each exposure inside its
    /// frame interval, to rounding 1e-9), the binding limits with their messages, and the
    /// step-and-shoot set; the continuous time to the DoLP target is shorter than
    /// step-and-shoot's (its set takes four 45-degree moves, 1 s, against a half turn, 0.5 s,
    /// at the same exposure limit: the ratio is at least 1.9); the text names the same
    /// figures.
    #[test]
    fn rooftop_plan_is_within_the_limits_and_beats_step_and_shoot() {
        let a = args();
        let v = plan(&a).unwrap();
        let c = &v["continuous"];
        let f = |x: &Value| x.as_f64().unwrap();
        assert!(f(&c["speed_deg_per_s"]) <= 360.0 * (1.0 + 1e-9));
        let n = c["frames_per_half_turn"].as_u64().unwrap() as f64;
        assert!(n * f(&c["speed_deg_per_s"]) / 180.0 <= 200.0 * (1.0 + 1e-9));
        assert!(f(&c["exposure_us"]) <= f(&c["frame_interval_us"]) * (1.0 + 1e-9));
        let binds = c["binds"].as_array().unwrap();
        assert!(!binds.is_empty());
        assert!(binds
            .iter()
            .all(|b| !b["message"].as_str().unwrap().is_empty()));
        assert!(f(&v["time_to_target_ratio"]) >= 1.9, "{v}");
        let t = text(&v);
        assert!(
            t.contains("frames per half turn") && t.contains("step-and-shoot"),
            "{t}"
        );
        assert!(run(&a).unwrap().starts_with('{'));
    }

    /// Bad flags are named with their value and range; an unknown material lists the scene's.
    #[test]
    fn bad_flags_are_named() {
        let mut a = args();
        a.problem.max_speed_deg_per_s = Some(-5.0);
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--max-speed-deg-per-s -5") && e.contains("allowed"),
            "{e}"
        );
        let mut a = args();
        a.problem.max_exposure_us = 1.0;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--max-exposure-us 1"), "{e}");
        let mut a = args();
        a.problem.objective = "fastest".into();
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--objective") && e.contains("scr-per-second"),
            "{e}"
        );
        let mut a = args();
        a.problem.target = "moon".into();
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--target \"moon\"") && e.contains("asphalt"),
            "{e}"
        );
        let mut a = args();
        a.problem.camera = None;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--camera is missing"), "{e}");
        let mut a = args();
        a.max_frames_per_half_turn = 2;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--max-frames-per-half-turn 2"), "{e}");
    }
}
