//! Reading a plan for a run or a forecast: the file parsed and checked, and what its
//! `from_planner` tables ask of the planners resolved with the plan's simulated scene and
//! camera: a capture's angles (`polar_engine::forecast::planner_angles`) and a continuous
//! plan's frames per half turn, exposure and speed (`polar_engine::continuous_planner`).

use crate::commands::CommandError;
use polar_engine::plan::Plan;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Reads a plan and resolves its `from_planner` table with the model ([`load_plan_resolved`]).
pub fn load_plan(path: &Path) -> Result<(Plan, PathBuf), CommandError> {
    load_plan_resolved(path).map(|(plan, dir, _)| (plan, dir))
}

/// [`load_plan`], which also resolves a continuous plan's `from_planner` (frames per half
/// turn, exposure and speed: [`polar_engine::continuous_planner::resolve`] with the plan's
/// simulated scene, camera and stage), printing the choice and the limits that bind on stderr;
/// the choice as JSON, if the planner made one.
pub fn load_plan_resolved(path: &Path) -> Result<(Plan, PathBuf, Option<Value>), CommandError> {
    let mut plan = Plan::from_path(path).map_err(CommandError::of)?;
    let dir = path
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    if let Some(c) = plan.capture().cloned() {
        if let Some(fp) = &c.from_planner {
            let (scene, camera) = forecast_models(&plan, &dir)?;
            let (angles, _why) =
                polar_engine::forecast::planner_angles(&scene, &camera, fp, c.exposure_us[0])
                    .map_err(CommandError::of)?;
            plan.resolve_angles(angles).map_err(CommandError::of)?;
        }
    }
    let mut chosen = None;
    if plan.continuous().is_some_and(|c| c.from_planner.is_some()) {
        use polar_engine::continuous_planner::{describe, resolve, to_json};
        let (scene, camera) = forecast_models(&plan, &dir)?;
        let stage =
            polar_rig::sim_stage::stage_limits(&plan.simulation).map_err(CommandError::of)?;
        if let Some(choice) =
            resolve(&mut plan, &scene, &camera, stage).map_err(CommandError::of)?
        {
            eprintln!("{}", describe(&choice));
            chosen = Some(to_json(&choice));
        }
    }
    Ok((plan, dir, chosen))
}

/// The scene and camera a plan's forecast uses (its simulation section's, or the defaults).
pub fn forecast_models(
    plan: &Plan,
    dir: &Path,
) -> Result<(polar_model::scene_file::Scene, polar_model::sensor::Camera), CommandError> {
    let sim = &plan.simulation;
    let scene_text = match &sim.scene {
        Some(s) => std::fs::read_to_string(dir.join(s))
            .map_err(|e| CommandError::input("simulation.scene", format!(" = {s}: {e}")))?,
        None => polar_rig::simulated::DEFAULT_SCENE.to_string(),
    };
    let scene = polar_model::scene_file::Scene::from_toml_str_with_files(&scene_text, &|name| {
        std::fs::read_to_string(dir.join(name)).map_err(|e| e.to_string())
    })
    .map_err(|e| CommandError::input("simulation.scene", format!(": {e}")))?;
    let camera_text = match &sim.camera {
        Some(c) => std::fs::read_to_string(dir.join(c))
            .map_err(|e| CommandError::input("simulation.camera", format!(" = {c}: {e}")))?,
        None => polar_rig::simulated::DEFAULT_CAMERA.to_string(),
    };
    let camera = polar_model::sensor::Camera::from_toml_str(&camera_text)
        .map_err(|e| CommandError::input("simulation.camera", format!(": {e}")))?;
    Ok((scene, camera))
}
