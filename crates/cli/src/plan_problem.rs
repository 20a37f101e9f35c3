//! What `plan scene` and `plan continuous` share: the scene, the camera (or a rig's), the
//! target and the background, the objective, the camera's and the stage's limits and the
//! saturation margin, with one set of defaults, and the planner's problem built from them
//! ([`polar_engine::continuous_planner::problem`], which a continuous plan's `from_planner`
//! uses too). Both commands choose a step-and-shoot set's exposure by the same rule
//! ([`polar_planner::step`]), so for the same scene, camera, target and objective they give
//! the same exposure, or say why they differ.
//!
//! The stage's limits default to the simulated rig's stage (the simulators' registry's first
//! rotator at the default `simulation.stage_deg_per_s`, from its simulator's descriptor:
//! `polar_rig::sim_stage::stage_limits`), the camera's to the simulated camera's
//! ([`polar_engine::continuous::planner_defaults`]), and the settling to the simulated rig's
//! (none).

use crate::commands::CommandError;
use clap::Args;
use polar_engine::continuous::planner_defaults;
use polar_engine::continuous_planner::{ProblemError, Role, Settings};
use polar_engine::plan::Simulation;
use polar_model::sensor::Camera;
use polar_planner::continuous::{CameraLimits, ContinuousProblem, Objective, StageLimits};
use serde_json::{json, Value};
use std::path::PathBuf;

/// The flags both planning commands take (module docs).
#[derive(Debug, Clone, Args)]
pub struct ProblemArgs {
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
    /// standard deviation is --dolp-sigma) or `scr-per-second`; `plan scene` also takes
    /// `scr-fraction` (the shortest exposure whose SCR reaches --scr-fraction of the
    /// clutter limit).
    #[arg(long, default_value = "time-to-dolp-sigma")]
    pub objective: String,
    /// The target's DoLP standard deviation to reach, (0, 1).
    #[arg(long, default_value_t = planner_defaults::DOLP_SIGMA)]
    pub dolp_sigma: f64,
    /// The stage's top speed, degrees per second, (0, 100000]; default: the simulated rig's
    /// stage (the output's `stage` says which limits were used).
    #[arg(long, visible_alias = "stage-deg-per-s")]
    pub max_speed_deg_per_s: Option<f64>,
    /// The stage's acceleration, degrees per second squared, (0, 1e7]; default: the simulated
    /// rig's stage.
    #[arg(long)]
    pub acceleration_deg_per_s2: Option<f64>,
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
    /// Saturation margin: the brightest frame of every material of the scene, mean plus this
    /// many standard deviations, stays below saturation, [0, 10].
    #[arg(long, default_value_t = planner_defaults::SATURATION_SIGMA)]
    pub saturation_sigma: f64,
    /// Settling after each move of a step-and-shoot set, seconds, [0, 60] (the simulated
    /// rig's stage settles at once).
    #[arg(long, default_value_t = 0.0)]
    pub settle_s: f64,
    /// Relative tolerance of the scene evaluation, [1e-8, 0.1].
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
}

/// `value` finite and in `(lo, hi]` (`lo_open`) or `[lo, hi]`, else an error naming `--flag`.
pub fn flag(flag: &str, value: f64, lo: f64, hi: f64, lo_open: bool) -> Result<f64, CommandError> {
    let ok = value.is_finite() && value <= hi && if lo_open { value > lo } else { value >= lo };
    if ok {
        Ok(value)
    } else {
        let open = if lo_open { "(" } else { "[" };
        Err(CommandError::input(
            format!("--{flag}"),
            format!(" {value} is out of range: allowed {open}{lo}, {hi}]"),
        ))
    }
}

/// The objective of `--objective` as the planner knows it; `scr-fraction` is `plan scene`'s
/// own and is refused here, naming the allowed values.
pub fn objective(args: &ProblemArgs) -> Result<Objective, CommandError> {
    match args.objective.as_str() {
        "time-to-dolp-sigma" => Ok(Objective::TimeToDolpSigma {
            dolp_sigma: flag("dolp-sigma", args.dolp_sigma, 0.0, 0.999, true)?,
        }),
        "scr-per-second" => Ok(Objective::ScrPerSecond),
        other => Err(CommandError::input(
            "--objective",
            format!(
                " {other:?} is not known here: allowed time-to-dolp-sigma, \
             scr-per-second{}",
                if other == "scr-fraction" {
                    " (scr-fraction is `plan scene`'s: a spinning analyzer's exposure is the \
                 longest its limits allow)"
                } else {
                    ""
                }
            ),
        )),
    }
}

/// The stage's limits and where they came from: the flags, else the simulated rig's stage.
pub fn stage(args: &ProblemArgs) -> Result<(StageLimits, &'static str), CommandError> {
    let sim = polar_rig::sim_stage::stage_limits(&Simulation::default())
        .map_err(CommandError::of)?
        .ok_or_else(|| {
            CommandError::failed(
                "the simulated rig's stage does not say how it moves: give \
                 --max-speed-deg-per-s and --acceleration-deg-per-s2",
            )
        })?;
    let source = match (args.max_speed_deg_per_s, args.acceleration_deg_per_s2) {
        (None, None) => "the simulated rig's stage",
        (Some(_), Some(_)) => "the flags",
        _ => "the flags and the simulated rig's stage",
    };
    let speed = match args.max_speed_deg_per_s {
        Some(v) => flag("max-speed-deg-per-s", v, 0.0, 1e5, true)?.to_radians(),
        None => sim.max_speed_rad_per_s,
    };
    let accel = match args.acceleration_deg_per_s2 {
        Some(v) => flag("acceleration-deg-per-s2", v, 0.0, 1e7, true)?.to_radians(),
        None => sim.acceleration_rad_per_s2,
    };
    Ok((
        StageLimits {
            max_speed_rad_per_s: speed,
            acceleration_rad_per_s2: accel,
        },
        source,
    ))
}

/// The stage's limits as JSON (degrees) with their source.
pub fn stage_json(stage: &StageLimits, source: &str) -> Value {
    json!({
        "max_speed_deg_per_s": stage.max_speed_rad_per_s.to_degrees(),
        "acceleration_deg_per_s2": stage.acceleration_rad_per_s2.to_degrees(),
        "from": source,
    })
}

/// The camera's limits from the flags (errors name the flag).
fn camera_limits(args: &ProblemArgs) -> Result<CameraLimits, CommandError> {
    let min_us = flag("min-exposure-us", args.min_exposure_us, 0.0, 1e11, true)?;
    let max_us = flag("max-exposure-us", args.max_exposure_us, min_us, 1e11, false)?;
    Ok(CameraLimits {
        min_exposure_s: min_us * 1e-6,
        max_exposure_s: (max_us * 1e-6).min(1e5),
        max_frame_rate_hz: flag("max-frame-rate-hz", args.max_frame_rate_hz, 0.0, 1e5, true)?,
        readout_s: flag("readout-us", args.readout_us, 0.0, 1e7, false)? * 1e-6,
        saturation_sigma: flag("saturation-sigma", args.saturation_sigma, 0.0, 10.0, false)?,
    })
}

/// The camera file: --camera, else the rig's.
fn camera_path(args: &ProblemArgs) -> Result<PathBuf, CommandError> {
    if let Some(p) = &args.camera {
        return Ok(p.clone());
    }
    let Some(rig) = &args.rig else {
        return Err(CommandError::input(
            "--camera",
            " is missing: allowed a camera file, or --rig with a [camera] file",
        ));
    };
    let rig = crate::rig::load(rig)?;
    rig.camera_file.clone().ok_or_else(|| {
        CommandError::input(
            "--rig",
            format!(
                " {}: its [camera] names no file: add file = \"cameras/NAME.toml\" or give \
             --camera",
                rig.path.display()
            ),
        )
    })
}

/// The planner's problem from the flags, with `objective`, `timing_sigma_s` and
/// `max_frames_per_half_turn` (the continuous planner's own) and the stage's limits' source.
/// Every flag is checked first (errors name it), then the scene's target, background and
/// other materials are evaluated and the camera taken through the scene's band.
pub fn problem(
    args: &ProblemArgs,
    objective: Objective,
    timing_sigma_s: f64,
    max_frames_per_half_turn: usize,
) -> Result<(ContinuousProblem, &'static str), CommandError> {
    let camera_limits = camera_limits(args)?;
    let (stage, source) = stage(args)?;
    flag("settle-s", args.settle_s, 0.0, 60.0, false)?;
    flag("tolerance", args.tolerance, 1e-8, 0.1, false)?;
    let scene = crate::commands::load_scene(&args.scene)
        .map_err(|e| CommandError::input("--scene", format!(": {e}")))?;
    let camera_path = camera_path(args)?;
    let text = std::fs::read_to_string(&camera_path).map_err(|e| {
        CommandError::input(
            "--camera",
            format!(" {}: cannot read: {e}", camera_path.display()),
        )
    })?;
    let camera = Camera::from_toml_str(&text)
        .map_err(|e| CommandError::input("--camera", format!(" {}: {e}", camera_path.display())))?;
    let settings = Settings {
        camera: camera_limits,
        stage,
        timing_sigma_s,
        max_frames_per_half_turn,
        objective,
    };
    let problem = polar_engine::continuous_planner::problem(
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
            CommandError::input(format!("--{flag}"), format!(" {e}"))
        }
        ProblemError::Scene(m) => {
            CommandError::input("--scene", format!(" {}: {m}", args.scene.display()))
        }
        ProblemError::Camera(m) => {
            CommandError::input("--camera", format!(" {}: {m}", camera_path.display()))
        }
    })?;
    Ok((problem, source))
}

/// A planner error as the commands print it.
pub fn planner_error(e: polar_planner::PlanError) -> CommandError {
    CommandError::of(e)
}
