//! The continuous planner (`polar_planner::continuous`) for plans: its problem built from a
//! scene, a camera, a target and a background and the limits ([`problem`], shared by
//! `polarimeter plan continuous` and a plan's `from_planner`), and the resolution of a
//! continuous plan's `from_planner` into frames per half turn, exposure and speed
//! ([`resolve`]).
//!
//! # The problem of a plan
//!
//! A `[continuous] from_planner` table names the target and background materials of the
//! plan's scene (its `[simulation]` scene and camera, as a capture's `from_planner`); the
//! camera is taken at the section's `gain_db`; the scene is evaluated at
//! [`crate::forecast::SCENE_TOL`] (the default of `plan continuous --tolerance`). The camera's
//! limits and the objective are the table's (defaults: `plan continuous`'s flags, from
//! [`crate::continuous::planner_defaults`]); the timing uncertainty is the section's
//! `timing_sigma_us` for `trigger = "timestamps"` and 0 for encoder triggers. The stage's limits
//! are the table's `max_speed_deg_per_s` and `acceleration_deg_per_s2` where given, else the
//! limits of the stage the plan runs on, which the caller passes where it knows them (the
//! simulated rig's stage: `polar_rig::sim_stage::stage_limits`, from its simulator's
//! descriptor). The engine knows no device.

use crate::continuous::{Continuous, ContinuousFromPlanner, FromPlannerObjective, TriggerSource};
use crate::forecast_basis::{camera_at_gain, ForecastError, SCENE_TOL};
use crate::plan::{Plan, PlanError};
use polar_model::scene_file::Scene;
use polar_model::sensor::{Camera, SensorModel};
use polar_planner::continuous::{
    plan_continuous, CameraLimits, ClassRadiance, ContinuousChoice, ContinuousProblem, Objective,
    StageLimits,
};
use serde_json::{json, Value};

/// Everything of the planner's problem besides the scene and the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    /// The camera's limits.
    pub camera: CameraLimits,
    /// The stage's limits.
    pub stage: StageLimits,
    /// Timing uncertainty of each frame, s.
    pub timing_sigma_s: f64,
    /// The most frames per half turn.
    pub max_frames_per_half_turn: usize,
    /// What to optimise.
    pub objective: Objective,
}

/// Which material of the problem.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The target.
    Target,
    /// The background.
    Background,
}

/// Why the problem could not be built; each caller names its own field or flag.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProblemError {
    /// A material name not in the scene.
    #[error("{name:?} is not a material of the scene: allowed {allowed}")]
    UnknownMaterial {
        /// Target or background.
        role: Role,
        /// The name given.
        name: String,
        /// The scene's materials, comma-separated.
        allowed: String,
    },
    /// The scene's evaluation failed.
    #[error("{0}")]
    Scene(String),
    /// The camera's model through the scene's band failed.
    #[error("{0}")]
    Camera(String),
}

/// The planner's problem: the scene's `target` and `background` evaluated at `tolerance`
/// (relative), the camera through the scene's band, and `settings`. Errors: a material not in
/// the scene (checked target first), the scene's evaluation, the camera's model.
pub fn problem(
    scene: &Scene,
    camera: &Camera,
    target: &str,
    background: &str,
    tolerance: f64,
    settings: &Settings,
) -> Result<ContinuousProblem, ProblemError> {
    let pick = |role: Role, name: &str| {
        scene
            .materials
            .iter()
            .find(|m| m.name == name)
            .cloned()
            .ok_or_else(|| ProblemError::UnknownMaterial {
                role,
                name: name.to_string(),
                allowed: scene
                    .materials
                    .iter()
                    .map(|m| m.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    };
    // The target and the background, then every other material of the scene: none of their
    // frames may saturate.
    let mut materials = vec![
        pick(Role::Target, target)?,
        pick(Role::Background, background)?,
    ];
    materials.extend(
        scene
            .materials
            .iter()
            .filter(|m| m.name != target && m.name != background)
            .cloned(),
    );
    let results = polar_model::scene::evaluate(&scene.spec, &materials, tolerance)
        .map_err(|e| ProblemError::Scene(e.to_string()))?;
    let sensor = SensorModel::new(camera, &scene.spec.band)
        .map_err(|e| ProblemError::Camera(e.to_string()))?;
    let class = |r: &polar_model::scene::MaterialResult| ClassRadiance {
        name: r.name.clone(),
        mean_w_m2_sr: r.mean.0,
        cov_w2_m4_sr2: 0.5 * (r.cov + r.cov.transpose()),
    };
    Ok(ContinuousProblem {
        sensor,
        target: class(&results[0]),
        background: class(&results[1]),
        others: results[2..].iter().map(class).collect(),
        camera: settings.camera,
        stage: settings.stage,
        timing_sigma_s: settings.timing_sigma_s,
        max_frames_per_half_turn: settings.max_frames_per_half_turn,
        objective: settings.objective,
    })
}

/// The settings of a `from_planner` table (module docs), with `stage` the limits of the stage
/// the plan runs on where they are known; an error names the field that must be given.
pub fn settings(
    c: &Continuous,
    fp: &ContinuousFromPlanner,
    stage: Option<StageLimits>,
) -> Result<Settings, PlanError> {
    let stage_field = |field: &str| PlanError::Invalid {
        field: format!("continuous.from_planner.{field}"),
        value: "(none)".into(),
        allowed: "a value: the limits of this plan's stage are not known (a simulated stage \
                  gives them where its simulator says how it moves)"
            .into(),
    };
    let max_speed_rad_per_s = match (fp.max_speed_deg_per_s, stage) {
        (Some(v), _) => v.to_radians(),
        (None, Some(s)) => s.max_speed_rad_per_s,
        (None, None) => return Err(stage_field("max_speed_deg_per_s")),
    };
    let acceleration_rad_per_s2 = match (fp.acceleration_deg_per_s2, stage) {
        (Some(a), _) => a.to_radians(),
        (None, Some(s)) => s.acceleration_rad_per_s2,
        (None, None) => return Err(stage_field("acceleration_deg_per_s2")),
    };
    Ok(Settings {
        camera: CameraLimits {
            min_exposure_s: fp.min_exposure_us * 1e-6,
            max_exposure_s: fp.max_exposure_us * 1e-6,
            max_frame_rate_hz: fp.max_frame_rate_hz,
            readout_s: fp.readout_us * 1e-6,
            saturation_sigma: fp.saturation_sigma,
        },
        stage: StageLimits {
            max_speed_rad_per_s,
            acceleration_rad_per_s2,
        },
        timing_sigma_s: match c.trigger {
            TriggerSource::Encoder => 0.0,
            TriggerSource::Timestamps => c.timing_sigma_us * 1e-6,
        },
        max_frames_per_half_turn: fp.max_frames_per_half_turn as usize,
        objective: match fp.objective {
            FromPlannerObjective::TimeToDolpSigma => Objective::TimeToDolpSigma {
                dolp_sigma: fp.dolp_sigma,
            },
            FromPlannerObjective::ScrPerSecond => Objective::ScrPerSecond,
        },
    })
}

/// Resolves a continuous plan's `from_planner` with the model of `scene` and `camera` (module
/// docs): the planner's frames per half turn, exposure (us) and speed (deg/s) replace the
/// table, exactly as the planner chose them, and the section is checked. Returns the choice
/// (with the limits that bind), or `None` for a plan without a table to resolve. The choice
/// and its binding limits are logged. `stage`: the limits of the stage the plan runs on, where
/// known (the table's own values come first).
///
/// Errors name the field: the table's, a material not in the scene (listing the scene's), the
/// model's, the planner's (no setting within the limits), and a choice the section refuses.
pub fn resolve(
    plan: &mut Plan,
    scene: &Scene,
    camera: &Camera,
    stage: Option<StageLimits>,
) -> Result<Option<ContinuousChoice>, ForecastError> {
    let Some(c) = plan.continuous().cloned() else {
        return Ok(None);
    };
    let Some(fp) = c.from_planner.clone() else {
        return Ok(None);
    };
    fp.validate()?;
    let settings = settings(&c, &fp, stage)?;
    let field = |f: &str| format!("continuous.from_planner.{f}");
    let p = problem(
        scene,
        &camera_at_gain(camera, c.gain_db),
        &fp.target,
        &fp.background,
        SCENE_TOL,
        &settings,
    )
    .map_err(|e| match e {
        ProblemError::UnknownMaterial {
            role,
            name,
            allowed,
        } => ForecastError::UnknownMaterial {
            field: field(match role {
                Role::Target => "target",
                Role::Background => "background",
            }),
            name,
            allowed,
        },
        other => ForecastError::Model {
            field: "continuous.from_planner".into(),
            message: other.to_string(),
        },
    })?;
    let choice = plan_continuous(&p).map_err(|e| ForecastError::Model {
        field: "continuous.from_planner".into(),
        message: e.to_string(),
    })?;
    let section = plan.continuous_mut().ok_or_else(|| PlanError::Invalid {
        field: "continuous".into(),
        value: "(missing)".into(),
        allowed: "a [continuous] section".into(),
    })?;
    section.resolve(
        u32::try_from(choice.frames_per_half_turn).unwrap_or(u32::MAX),
        choice.exposure_s * 1e6,
        choice.speed_rad_per_s.to_degrees(),
    )?;
    tracing::info!(
        frames_per_half_turn = choice.frames_per_half_turn,
        exposure_us = choice.exposure_s * 1e6,
        speed_deg_per_s = choice.speed_rad_per_s.to_degrees(),
        binds = %binding_names(&choice),
        "continuous.from_planner resolved"
    );
    Ok(Some(choice))
}

fn binding_names(choice: &ContinuousChoice) -> String {
    if choice.binds.is_empty() {
        "none".into()
    } else {
        choice
            .binds
            .iter()
            .map(|b| b.limit.name())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// The choice in one line: the three values, the set time, the spin-up and the limits that
/// bind.
pub fn describe(choice: &ContinuousChoice) -> String {
    let mut s = format!(
        "continuous.from_planner: {} frames per half turn, exposure {:.3} us, {:.3} deg/s (one \
         set every {:.4} s, spin-up {:.4} s, DoLP sigma per half turn {:.5})",
        choice.frames_per_half_turn,
        choice.exposure_s * 1e6,
        choice.speed_rad_per_s.to_degrees(),
        choice.half_turn_s,
        choice.spin_up_s,
        choice.sigma_dolp
    );
    if let Some(t) = choice.time_to_target_s {
        s += &format!(", the DoLP target in {t:.3} s");
    }
    if choice.binds.is_empty() {
        s += "; no limit binds";
    } else {
        let binds: Vec<String> = choice
            .binds
            .iter()
            .map(|b| format!("{} ({})", b.limit.name(), b.message))
            .collect();
        s += &format!("; binding: {}", binds.join("; "));
    }
    s
}

/// The choice as JSON (degrees, microseconds, seconds), with the limits that bind.
pub fn to_json(choice: &ContinuousChoice) -> Value {
    let binds: Vec<Value> = choice
        .binds
        .iter()
        .map(|b| json!({"limit": b.limit.name(), "gain": b.gain, "message": b.message}))
        .collect();
    json!({
        "frames_per_half_turn": choice.frames_per_half_turn,
        "exposure_us": choice.exposure_s * 1e6,
        "speed_deg_per_s": choice.speed_rad_per_s.to_degrees(),
        "half_turn_s": choice.half_turn_s,
        "spin_up_s": choice.spin_up_s,
        "sigma_dolp_per_half_turn": choice.sigma_dolp,
        "time_to_target_s": choice.time_to_target_s,
        "binds": binds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = include_str!("../../../examples/rooftop_panels.toml");
    const CAMERA: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

    /// The simulated rig's default stage at 360 deg/s (`polar_rig::sim_stage`): 360 deg/s,
    /// reached in 1/8 s.
    const BENCH_STAGE: StageLimits = StageLimits {
        max_speed_rad_per_s: 360.0 * std::f64::consts::PI / 180.0,
        acceleration_rad_per_s2: 2880.0 * std::f64::consts::PI / 180.0,
    };

    fn plan(table: &str, simulation: &str) -> Result<Plan, PlanError> {
        Plan::from_toml_str(&format!(
            "kind = \"continuous\"\n[continuous]\nhalf_turns = 2\nfrom_planner = {{ {table} }}\n\
             [simulation]\n{simulation}\n"
        ))
    }

    /// Resolution on the rooftop scene: the section takes the planner's three values
    /// unchanged (0 tolerance: the same numbers), loses its table and validates; the speed
    /// stays within the stage's 360 deg/s and the frame rate within 200 Hz (to 1e-9
    /// relative, rounding); a plan without a table is left alone.
    #[test]
    fn resolves_to_the_planners_choice() {
        let scene = Scene::from_toml_str(SCENE).expect("scene");
        let camera = Camera::from_toml_str(CAMERA).expect("camera");
        let mut p = plan(
            "target = \"panel\", background = \"asphalt\", max_frames_per_half_turn = 12",
            "stage_deg_per_s = 360",
        )
        .expect("plan");
        let choice = resolve(&mut p, &scene, &camera, Some(BENCH_STAGE))
            .expect("resolve")
            .expect("a choice");
        let c = p.continuous().expect("section");
        assert!(c.from_planner.is_none());
        c.validate().expect("valid");
        assert_eq!(c.frames_per_half_turn as usize, choice.frames_per_half_turn);
        assert_eq!(c.exposure_us, choice.exposure_s * 1e6);
        assert_eq!(c.speed_deg_per_s, choice.speed_rad_per_s.to_degrees());
        assert!(c.speed_deg_per_s <= 360.0 * (1.0 + 1e-9));
        let fps = f64::from(c.frames_per_half_turn) * c.speed_deg_per_s / 180.0;
        assert!(fps <= 200.0 * (1.0 + 1e-9), "{fps}");
        assert!(describe(&choice).contains("frames per half turn"));
        assert!(resolve(&mut p, &scene, &camera, Some(BENCH_STAGE))
            .expect("again")
            .is_none());
    }

    /// Errors name the field, the value and what is allowed: a target not in the scene
    /// (listing the scene's materials), a stage without known limits, an unresolved section
    /// at the run's check (naming the commands that resolve it).
    #[test]
    fn errors_name_the_field() {
        let scene = Scene::from_toml_str(SCENE).expect("scene");
        let camera = Camera::from_toml_str(CAMERA).expect("camera");
        let mut p = plan("target = \"roof\", background = \"asphalt\"", "").expect("plan");
        let e = resolve(&mut p, &scene, &camera, Some(BENCH_STAGE))
            .expect_err("unknown")
            .to_string();
        assert!(
            e.contains("continuous.from_planner.target") && e.contains("panel, glass"),
            "{e}"
        );
        let mut p = plan(
            "target = \"panel\", background = \"asphalt\"",
            "stage = { dialect = \"apt\" }",
        )
        .expect("plan");
        let e = resolve(&mut p, &scene, &camera, None)
            .expect_err("apt")
            .to_string();
        assert!(
            e.contains("continuous.from_planner.max_speed_deg_per_s"),
            "{e}"
        );
        let e = p
            .continuous()
            .expect("section")
            .validate()
            .expect_err("unresolved")
            .to_string();
        assert!(
            e.contains("continuous.from_planner") && e.contains("polarimeter acquire run"),
            "{e}"
        );
    }
}
