//! `polarimeter plan continuous`: frames per half turn, exposure and speed of a spinning
//! analyzer for a target against a background of a scene, within the camera's and the stage's
//! limits, which limit binds, and the step-and-shoot set on the same rig beside it
//! ([`polar_planner::continuous`]; MODEL.md, exposures while the analyzer turns).

use anyhow::{anyhow, bail, Context};
use clap::Args;
use polar_engine::continuous::planner_defaults;
use polar_engine::continuous_planner::{ProblemError, Role, Settings};
use polar_model::sensor::Camera;
use polar_planner::continuous::{
    plan_continuous, step_and_shoot, CameraLimits, ContinuousChoice, ContinuousProblem, Objective,
    StageLimits, StepPrediction, MAX_FRAMES_PER_HALF_TURN,
};
use serde_json::{json, Value};
use std::path::PathBuf;

/// `plan continuous` arguments. The defaults are the simulated rig's (360 deg/s at
/// 2880 deg/s^2, a 200 Hz camera that reads out while it exposes).
#[derive(Debug, Clone, Args)]
pub struct PlanContinuousArgs {
    /// The scene (TOML, examples/*.toml).
    #[arg(long)]
    pub scene: PathBuf,
    /// The camera file (TOML, examples/cameras/*.toml); or give --rig.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// A rig file whose [camera] file is the camera (when --camera is not given).
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// The target material's name in the scene.
    #[arg(long)]
    pub target: String,
    /// The background material's name in the scene.
    #[arg(long)]
    pub background: String,
    /// What to optimise: `time-to-dolp-sigma` (the shortest time until the target's DoLP
    /// standard deviation is --dolp-sigma) or `scr-per-second`.
    #[arg(long, default_value = "time-to-dolp-sigma")]
    pub objective: String,
    /// The target's DoLP standard deviation to reach, (0, 1).
    #[arg(long, default_value_t = planner_defaults::DOLP_SIGMA)]
    pub dolp_sigma: f64,
    /// The stage's top speed, degrees per second, (0, 100000].
    #[arg(long, default_value_t = 360.0)]
    pub max_speed_deg_per_s: f64,
    /// The stage's acceleration, degrees per second squared, (0, 1e7].
    #[arg(long, default_value_t = 2880.0)]
    pub acceleration_deg_per_s2: f64,
    /// The camera's highest frame rate, Hz, (0, 100000].
    #[arg(long, default_value_t = planner_defaults::MAX_FRAME_RATE_HZ)]
    pub max_frame_rate_hz: f64,
    /// Dead time after each exposure before the next, microseconds, [0, 1e7] (0 for a camera
    /// that reads out while it exposes).
    #[arg(long, default_value_t = planner_defaults::READOUT_US)]
    pub readout_us: f64,
    /// Shortest exposure, microseconds, (0, 1e11].
    #[arg(long, default_value_t = planner_defaults::MIN_EXPOSURE_US)]
    pub min_exposure_us: f64,
    /// Longest exposure, microseconds, [--min-exposure-us, 1e11].
    #[arg(long, default_value_t = planner_defaults::MAX_EXPOSURE_US)]
    pub max_exposure_us: f64,
    /// Saturation margin: the brightest frame's mean plus this many standard deviations stays
    /// below saturation, [0, 10].
    #[arg(long, default_value_t = planner_defaults::SATURATION_SIGMA)]
    pub saturation_sigma: f64,
    /// Timing uncertainty of each frame, microseconds, [0, 1e6] (0: frames triggered at
    /// encoder positions; a free-running camera's timestamp uncertainty otherwise).
    #[arg(long, default_value_t = 0.0)]
    pub timing_sigma_us: f64,
    /// The most frames per half turn, 3..=360.
    #[arg(long, default_value_t = planner_defaults::MAX_FRAMES_PER_HALF_TURN as usize)]
    pub max_frames_per_half_turn: usize,
    /// Settling after each move of the step-and-shoot set it is compared with, seconds,
    /// [0, 60].
    #[arg(long, default_value_t = 0.0)]
    pub settle_s: f64,
    /// Relative tolerance of the scene evaluation, [1e-8, 0.1].
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Print JSON (one object) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `value` finite and in `(lo, hi]` (`lo_open`) or `[lo, hi]`, else an error naming `--flag`.
fn flag(flag: &str, value: f64, lo: f64, hi: f64, lo_open: bool) -> anyhow::Result<f64> {
    let ok = value.is_finite() && value <= hi && if lo_open { value > lo } else { value >= lo };
    if ok {
        Ok(value)
    } else {
        let open = if lo_open { "(" } else { "[" };
        bail!("--{flag} {value} is out of range: allowed {open}{lo}, {hi}]")
    }
}

fn objective(args: &PlanContinuousArgs) -> anyhow::Result<Objective> {
    match args.objective.as_str() {
        "time-to-dolp-sigma" => Ok(Objective::TimeToDolpSigma {
            dolp_sigma: flag("dolp-sigma", args.dolp_sigma, 0.0, 0.999, true)?,
        }),
        "scr-per-second" => Ok(Objective::ScrPerSecond),
        other => {
            bail!("--objective {other:?} is not known: allowed time-to-dolp-sigma, scr-per-second")
        }
    }
}

/// The camera file: --camera, else the rig's.
fn camera_path(args: &PlanContinuousArgs) -> anyhow::Result<PathBuf> {
    if let Some(p) = &args.camera {
        return Ok(p.clone());
    }
    let Some(rig) = &args.rig else {
        bail!("--camera is missing: allowed a camera file, or --rig with a [camera] file");
    };
    let rig = crate::rig::load(rig).map_err(|e| anyhow!("{e}"))?;
    rig.camera_file.clone().ok_or_else(|| {
        anyhow!(
            "--rig {}: its [camera] names no file: add file = \"cameras/NAME.toml\" or give \
             --camera",
            rig.path.display()
        )
    })
}

/// The planner's problem from the arguments: flags checked (errors name the flag), then
/// [`polar_engine::continuous_planner::problem`] (the scene's two materials evaluated, the
/// camera through the scene's band), which a continuous plan's `from_planner` uses too.
pub fn problem(args: &PlanContinuousArgs) -> anyhow::Result<ContinuousProblem> {
    let objective = objective(args)?;
    let max_speed = flag(
        "max-speed-deg-per-s",
        args.max_speed_deg_per_s,
        0.0,
        1e5,
        true,
    )?;
    let accel = flag(
        "acceleration-deg-per-s2",
        args.acceleration_deg_per_s2,
        0.0,
        1e7,
        true,
    )?;
    let fps = flag("max-frame-rate-hz", args.max_frame_rate_hz, 0.0, 1e5, true)?;
    let readout_us = flag("readout-us", args.readout_us, 0.0, 1e7, false)?;
    let min_us = flag("min-exposure-us", args.min_exposure_us, 0.0, 1e11, true)?;
    let max_us = flag("max-exposure-us", args.max_exposure_us, min_us, 1e11, false)?;
    let k = flag("saturation-sigma", args.saturation_sigma, 0.0, 10.0, false)?;
    let timing_us = flag("timing-sigma-us", args.timing_sigma_us, 0.0, 1e6, false)?;
    flag("settle-s", args.settle_s, 0.0, 60.0, false)?;
    flag("tolerance", args.tolerance, 1e-8, 0.1, false)?;
    if !(3..=MAX_FRAMES_PER_HALF_TURN).contains(&args.max_frames_per_half_turn) {
        bail!(
            "--max-frames-per-half-turn {} is out of range: allowed 3 to \
             {MAX_FRAMES_PER_HALF_TURN}",
            args.max_frames_per_half_turn
        );
    }
    let scene = crate::commands::load_scene(&args.scene).map_err(|e| anyhow!("--scene: {e}"))?;
    let camera_path = camera_path(args)?;
    let camera = Camera::from_toml_str(
        &std::fs::read_to_string(&camera_path)
            .with_context(|| format!("--camera {}: cannot read", camera_path.display()))?,
    )
    .map_err(|e| anyhow!("--camera {}: {e}", camera_path.display()))?;
    let settings = Settings {
        camera: CameraLimits {
            min_exposure_s: min_us * 1e-6,
            max_exposure_s: (max_us * 1e-6).min(1e5),
            max_frame_rate_hz: fps,
            readout_s: readout_us * 1e-6,
            saturation_sigma: k,
        },
        stage: StageLimits {
            max_speed_rad_per_s: max_speed.to_radians(),
            acceleration_rad_per_s2: accel.to_radians(),
        },
        timing_sigma_s: timing_us * 1e-6,
        max_frames_per_half_turn: args.max_frames_per_half_turn,
        objective,
    };
    polar_engine::continuous_planner::problem(
        &scene,
        &camera,
        &args.target,
        &args.background,
        args.tolerance,
        &settings,
    )
    .map_err(|e| match e {
        ProblemError::UnknownMaterial { role, .. } => {
            let flag = match role {
                Role::Target => "target",
                Role::Background => "background",
            };
            anyhow!("--{flag} {e}")
        }
        ProblemError::Scene(m) => anyhow!("--scene {}: {m}", args.scene.display()),
        ProblemError::Camera(m) => anyhow!("--camera {}: {m}", camera_path.display()),
    })
}

/// The choice and the step-and-shoot comparison as JSON (degrees, microseconds, seconds).
pub fn to_json(problem: &ContinuousProblem, c: &ContinuousChoice, step: &StepPrediction) -> Value {
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
            "set_s": step.set_s,
            "sets_per_s": 1.0 / step.set_s,
            "s0_dn": step.s0_dn,
            "sigma_s0_dn": step.sigma_stokes_dn[0],
            "sigma_s1_dn": step.sigma_stokes_dn[1],
            "sigma_s2_dn": step.sigma_stokes_dn[2],
            "sigma_dolp_per_set": step.sigma_dolp,
            "sets_to_target": opt(step.sets),
            "time_to_target_s": opt(step.time_to_target_s),
        },
        "time_to_target_ratio": ratio,
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
    out
}

/// The choice as JSON: the problem, the planner, the step-and-shoot set 0/45/90/135 beside it.
pub fn plan(args: &PlanContinuousArgs) -> anyhow::Result<Value> {
    let p = problem(args)?;
    let choice = plan_continuous(&p)?;
    let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|d| d.to_radians())
        .collect();
    let step = step_and_shoot(&p, &angles, args.settle_s)?;
    Ok(to_json(&p, &choice, &step))
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

    fn root() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
    }

    fn args() -> PlanContinuousArgs {
        PlanContinuousArgs {
            scene: root().join("examples/rooftop_panels.toml"),
            camera: Some(root().join("examples/cameras/cmos_modern.toml")),
            rig: None,
            target: "panel".into(),
            background: "asphalt".into(),
            objective: "time-to-dolp-sigma".into(),
            dolp_sigma: 1e-3,
            max_speed_deg_per_s: 360.0,
            acceleration_deg_per_s2: 2880.0,
            max_frame_rate_hz: 200.0,
            readout_us: 0.0,
            min_exposure_us: 10.0,
            max_exposure_us: 1e6,
            saturation_sigma: 3.0,
            timing_sigma_us: 0.0,
            max_frames_per_half_turn: 24,
            settle_s: 0.0,
            tolerance: 1e-3,
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
        a.max_speed_deg_per_s = -5.0;
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--max-speed-deg-per-s -5") && e.contains("allowed"),
            "{e}"
        );
        let mut a = args();
        a.max_exposure_us = 1.0;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--max-exposure-us 1"), "{e}");
        let mut a = args();
        a.objective = "fastest".into();
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--objective") && e.contains("scr-per-second"),
            "{e}"
        );
        let mut a = args();
        a.target = "moon".into();
        let e = plan(&a).unwrap_err().to_string();
        assert!(
            e.contains("--target \"moon\"") && e.contains("asphalt"),
            "{e}"
        );
        let mut a = args();
        a.camera = None;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--camera is missing"), "{e}");
        let mut a = args();
        a.max_frames_per_half_turn = 2;
        let e = plan(&a).unwrap_err().to_string();
        assert!(e.contains("--max-frames-per-half-turn 2"), "{e}");
    }
}
