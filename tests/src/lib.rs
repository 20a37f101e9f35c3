//! The harness of the workspace's hardware-in-the-loop tests (`tests/hil.rs`, one test binary):
//! a simulator of a registered dialect on a real pseudo-terminal, a run driven to its end with
//! every pause resumed (as an operator capping and uncapping the lens would), and scratch
//! folders. The tests themselves live in `tests/hil/`.
#![warn(missing_docs)]

use polar_engine::plan::Plan;
use polar_engine::run::{self, Control, Controller, Event, Outcome, Rig, RunState};
use polar_hal::{Analyzer, Camera};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use std::path::{Path, PathBuf};

/// The repository's root (for `examples/`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from(".."))
}

/// A fresh scratch folder under the system's temporary folder.
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("polar-hil-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    let _ = std::fs::create_dir_all(&d);
    d
}

/// The simulator of `dialect`'s `model` from the simulators' registry, healthy, served on a
/// pseudo-terminal whose link is `dir/DIALECT-MODEL`. Call inside a tokio runtime.
pub fn serve(dialect: &str, model: &str, seed: u64, dir: &Path) -> Result<SimServer, String> {
    let faults = FaultProfile::default();
    let sim = polar_hil_mocks::sim::simulator(dialect, Some(model), faults, seed)
        .map_err(|e| e.to_string())?;
    SimServer::pty(sim, faults, seed, &dir.join(format!("{dialect}-{model}")))
        .map_err(|e| format!("{dialect} {model}: cannot open a pseudo-terminal: {e}"))
}

/// Runs `plan` on `rig` to its end inside a `LocalSet`, resuming every pause (at most
/// `max_resumes`); returns the outcome and the pause reasons seen.
pub async fn run_resuming<A: Analyzer + 'static, C: Camera + 'static>(
    plan: &Plan,
    rig: Rig<A, C>,
    run_dir: &Path,
    max_resumes: u32,
) -> Result<(Outcome, Vec<String>), String> {
    let (ctl, link) = run::link();
    let Controller {
        control,
        state: _state,
        mut events,
    } = ctl;
    let watcher = tokio::task::spawn_local(async move {
        let mut reasons = Vec::new();
        while let Some(e) = events.recv().await {
            if let Event::State(RunState::Paused(reason)) = e {
                reasons.push(reason);
                let c = if reasons.len() as u32 <= max_resumes {
                    Control::Resume
                } else {
                    Control::Detach
                };
                if control.send(c).await.is_err() {
                    break;
                }
            }
        }
        reasons
    });
    let outcome = run::run(plan, rig, run_dir, false, link)
        .await
        .map_err(|e| e.to_string())?;
    let reasons = watcher.await.map_err(|e| e.to_string())?;
    Ok((outcome, reasons))
}

/// Runs the plan file `plan` with the rig file `rig` as `polarimeter run --rig RIG PLAN --out
/// OUT` does (`polar_cli::acquire::run_cmd`, no terminal): on the rig's devices, or with
/// `simulate` on the engine's simulated rig (`run --simulate --rig`: the rig file gives the
/// site and receives a calibration's write-back). Every pause that is not the user's (the
/// lens-cap pauses around darks) is resumed, at most `max_resumes` times. Returns the
/// command's JSON output and exit status.
pub fn run_cli(
    plan: &Path,
    rig: &Path,
    out: &Path,
    max_resumes: u32,
    simulate: bool,
) -> Result<(serde_json::Value, i32), String> {
    let rig = polar_cli::rig::load(rig).map_err(|e| e.to_string())?;
    let hw = if simulate {
        None
    } else {
        Some(
            rig.hardware(&polar_rig::Overrides::default())
                .map_err(|e| e.to_string())?
                .ok_or_else(|| format!("{}: the rig names no devices", rig.path.display()))?,
        )
    };
    let ui = polar_cli::acquire::Ui {
        progress: false,
        interactive: false,
        auto_resume: max_resumes,
    };
    polar_cli::acquire::run_cmd(plan, hw, Some(&rig), Some(out.to_path_buf()), ui)
        .map_err(|e| e.to_string())
}
