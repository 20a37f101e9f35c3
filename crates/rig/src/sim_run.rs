//! A run of any plan on the simulated rig ([`crate::simulated::SimRig`]): the library entry point of
//! the demo's and the benchmarks' simulated runs.

use crate::simulated::{SimError, SimRig};
use polar_engine::plan::Plan;
use polar_engine::run::{noise_stream, run, Outcome, RunError, RunLink};
use std::path::Path;

/// Why a simulated run could not go on.
#[derive(Debug, thiserror::Error)]
pub enum SimRunError {
    /// The simulated rig did not start.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The run.
    #[error(transparent)]
    Run(#[from] RunError),
}

/// Starts the simulated rig for `plan` (files relative to `plan_dir`; the stage's
/// pseudo-terminal in `run_dir/.sim`), runs (or, with `resume`, continues) the plan into
/// `run_dir` through [`run`], and stops the
/// rig. A finished run's [`Summary`](polar_engine::run::Summary) has its timings (`elapsed_s`, `device_s`). Call it inside
/// a [`tokio::task::LocalSet`].
pub async fn run_simulated(
    plan: &Plan,
    plan_dir: &Path,
    run_dir: &Path,
    resume: bool,
    link: RunLink,
) -> Result<Outcome, SimRunError> {
    let link_dir = run_dir.join(".sim");
    let (rig, engine_rig) =
        SimRig::start_rig(plan, plan_dir, &link_dir, noise_stream(run_dir)).await?;
    let outcome = run(plan, engine_rig, run_dir, resume, link).await;
    rig.shutdown().await;
    Ok(outcome?)
}
