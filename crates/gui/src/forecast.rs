//! The forecast of a plan on the simulated rig, as the planner panel and the run tab show it.

use polar_engine::forecast;
use polar_engine::plan::Plan;
use polar_rig::SimRig;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The forecast of a plan on the simulated rig, as text (on a blocking thread: a large
/// simulated scene takes a while to build).
pub(crate) async fn compute_forecast(
    plan_text: String,
    plan_dir: PathBuf,
) -> Result<String, String> {
    tokio::task::spawn_blocking(move || forecast_text(&plan_text, &plan_dir))
        .await
        .map_err(|e| format!("forecast: {e}"))?
}

/// The forecast of `plan_text` as text (its relative paths against `plan_dir`).
pub fn forecast_text(plan_text: &str, plan_dir: &Path) -> Result<String, String> {
    let plan = Plan::from_toml_str(plan_text).map_err(|e| e.to_string())?;
    let world = SimRig::world(&plan, plan_dir).map_err(|e| e.to_string())?;
    let timing = polar_rig::sim_stage::timing(&plan).map_err(|e| e.to_string())?;
    let f = forecast::forecast(&plan, &world.scene_file, &world.camera_model, &timing)
        .map_err(|e| e.to_string())?;
    let mut s = format!(
        "{}: {} frames ({} darks) in {} sets, about {:.1} s",
        f.kind, f.frames, f.darks, f.sets, f.duration_s
    );
    if let Some(a) = &f.angles_deg {
        let a: Vec<String> = a.iter().map(|d| format!("{d:.1}")).collect();
        let _ = write!(s, "\nangles: {} deg", a.join(", "));
    }
    for c in &f.classes {
        let _ = write!(
            s,
            "\n{}: S0 {:.0} +/- {:.1} DN, DoLP {:.3} +/- {:.3}, AoP {:.1} +/- {:.1} deg",
            c.material, c.s0_dn, c.sigma_s0_dn, c.dolp, c.sigma_dolp, c.aop_deg, c.sigma_aop_deg
        );
    }
    for n in &f.notes {
        let _ = write!(s, "\nnote: {n}");
    }
    Ok(s)
}

/// Where runs go and where a plan's relative paths start.
#[derive(Clone, Copy)]
pub(crate) struct Places<'a> {
    pub(crate) base_dir: &'a Path,
    pub(crate) plan_dir: &'a Path,
}

/// Resolves `plan`'s `from_planner` tables as `acquire run` does, with the models its
/// forecast uses (the plan's simulated scene and camera): a capture's angles, a continuous
/// plan's frames per half turn, exposure and speed. Returns what the planners chose.
pub(crate) fn resolve_planners(plan: &mut Plan, plan_dir: &Path) -> Result<Vec<String>, String> {
    let wants_angles = plan
        .capture()
        .is_some_and(|c| c.angles_deg.is_none() && c.from_planner.is_some());
    let wants_spin = plan.continuous().is_some_and(|c| c.from_planner.is_some());
    if !wants_angles && !wants_spin {
        return Ok(Vec::new());
    }
    let world = SimRig::world(plan, plan_dir).map_err(|e| e.to_string())?;
    let mut chosen = Vec::new();
    if let Some(c) = plan.capture().cloned().filter(|_| wants_angles) {
        if let (Some(fp), Some(&first)) = (&c.from_planner, c.exposure_us.first()) {
            let (angles, _why) =
                forecast::planner_angles(&world.scene_file, &world.camera_model, fp, first)
                    .map_err(|e| e.to_string())?;
            chosen.push(format!("angles from the planner: {angles:.2?} deg"));
            plan.resolve_angles(angles).map_err(|e| e.to_string())?;
        }
    }
    if wants_spin {
        let stage =
            polar_rig::sim_stage::stage_limits(&plan.simulation).map_err(|e| e.to_string())?;
        if let Some(choice) = polar_engine::continuous_planner::resolve(
            plan,
            &world.scene_file,
            &world.camera_model,
            stage,
        )
        .map_err(|e| e.to_string())?
        {
            chosen.push(polar_engine::continuous_planner::describe(&choice));
        }
    }
    Ok(chosen)
}
