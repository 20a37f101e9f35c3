//! The one entry point of every run: the strategy is picked from the plan's kind.

use super::link::RunLink;
use super::outcome::{Outcome, RunError};
use super::rig::Rig;
use super::{spin_loop, step_loop};
use crate::plan::{Plan, PlanKind};
use polar_hal::{Camera, OnRotator, Rotator};
use std::path::Path;

/// Runs (or, with `resume`, continues) `plan` into `run_dir` on `rig`, reporting through
/// `link`: a `continuous` plan spins the analyzer ([`super::spin_loop`]: the stage must spin, and
/// its trigger output or the host's timestamps give each frame's span), every other kind
/// moves it from step to step ([`super::step_loop`]). Both share one run core ([`super::core`]: the run
/// directory, the journal's replay, the storage thread, pauses and the ending). Call it
/// inside a [`tokio::task::LocalSet`] (the device actors are local tasks). Pauses wait for
/// the controller; errors that leave nothing to resume are returned.
pub async fn run<R, C>(
    plan: &Plan,
    rig: Rig<OnRotator<R>, C>,
    run_dir: &Path,
    resume: bool,
    link: RunLink,
) -> Result<Outcome, RunError>
where
    R: Rotator + 'static,
    C: Camera + 'static,
{
    if plan.kind() == PlanKind::Continuous {
        spin_loop::run(plan, rig, run_dir, resume, link).await
    } else {
        step_loop::run(plan, rig, run_dir, resume, link).await
    }
}
