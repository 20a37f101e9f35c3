//! Acquisition commands on the engine: `acquire run`, `acquire resume`, `plan check`, `acquire
//! export tiff`, `demo`, `bench run` and `bench faults`.
//!
//! On the terminal a run shows a progress bar; Ctrl-C once pauses at the next safe point,
//! twice pauses at once (the device operation in flight is cancelled and taken again), a third
//! time leaves the paused run for `polarimeter acquire resume`. While paused on a terminal, the run
//! asks: `r` resumes, `a` aborts, `q` leaves it. Without a terminal, a pause leaves the run
//! for `acquire resume` (exit status 3).

use crate::commands::CommandError;
use crate::plan_load::{forecast_models, load_plan, load_plan_resolved};
use polar_engine::plan::{Plan, SimStage};
use polar_engine::run::{self, Control, Controller, Event, Outcome, Rig, RunState};
use polar_hal::{Camera, OnRotator, Rotator};
use polar_rig::{sim_stage, SimRig};
use polar_rig::{Hardware, Rig as RigFile};
use serde_json::{json, Value};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What a caller other than the terminal (the Python package) hears of a run and how it
/// asks the run to stop: every event, and its interrupts polled every [`HOOK_POLL_MS`] ms in
/// place of the terminal's Ctrl-C.
pub trait RunHooks {
    /// Called with each event of the run, in order.
    fn event(&self, event: &Event);
    /// How many times the caller has asked the run to stop so far; each new one acts as one
    /// more Ctrl-C (pause at the next safe point, then at once, then leave the run).
    fn interrupts(&self) -> u32;
    /// A control the caller asks for directly (a station's pause or abort), taken once;
    /// polled with [`RunHooks::interrupts`].
    fn control(&self) -> Option<Control> {
        None
    }
}

/// An event as callers outside the terminal read it (the Python package, the station):
/// `{"kind": "state" | "progress" | "set" | "decision" | "retry", ...}`.
pub fn event_json(event: &Event) -> Value {
    match event {
        Event::State(s) => {
            let (state, reason) = match s {
                RunState::Starting => ("starting", None),
                RunState::Running => ("running", None),
                RunState::Pausing => ("pausing", None),
                RunState::Paused(r) => ("paused", Some(r)),
                RunState::Aborting => ("aborting", None),
                RunState::Done => ("done", None),
                RunState::Aborted(r) => ("aborted", Some(r)),
            };
            json!({"kind": "state", "state": state, "reason": reason})
        }
        Event::Progress {
            done,
            planned,
            label,
        } => json!({"kind": "progress", "done": done, "planned": planned, "label": label}),
        Event::Set {
            set,
            verdict,
            mean_s0,
            mean_dolp,
        } => json!({"kind": "set", "set": set, "accepted": verdict.accepted,
                    "reason": verdict.reason, "mean_s0_dn": mean_s0, "mean_dolp": mean_dolp}),
        Event::Decision(v) => json!({"kind": "decision", "decision": v}),
        Event::Retry(m) => json!({"kind": "retry", "message": m}),
    }
}

/// How often a run polls [`RunHooks::interrupts`], milliseconds.
pub const HOOK_POLL_MS: u64 = 50;

/// How the terminal takes part in a run.
#[derive(Clone)]
pub struct Ui {
    /// Show a progress bar (on a terminal).
    pub progress: bool,
    /// Ask what to do at a pause (stdin is a terminal); otherwise a pause detaches.
    pub interactive: bool,
    /// Resume automatically after a device-error pause, up to this many times (tests and
    /// fault campaigns; 0 for people).
    pub auto_resume: u32,
    /// A caller's hooks in place of the terminal's Ctrl-C (`None` on the command line).
    pub hooks: Option<std::rc::Rc<dyn RunHooks>>,
}

impl std::fmt::Debug for Ui {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ui")
            .field("progress", &self.progress)
            .field("interactive", &self.interactive)
            .field("auto_resume", &self.auto_resume)
            .field("hooks", &self.hooks.is_some())
            .finish()
    }
}

impl Ui {
    /// A person at a terminal (if there is one).
    pub fn terminal() -> Ui {
        Ui {
            progress: std::io::stderr().is_terminal(),
            interactive: std::io::stdin().is_terminal(),
            auto_resume: 0,
            hooks: None,
        }
    }

    /// Nobody at a terminal: no progress bar, a pause leaves the run (after up to
    /// `auto_resume` automatic resumes of device-error pauses).
    pub fn unattended(auto_resume: u32) -> Ui {
        Ui {
            progress: false,
            interactive: false,
            auto_resume,
            hooks: None,
        }
    }
}

/// Drives a run with the terminal: progress bar, Ctrl-C, pause prompts.
async fn drive<R: Rotator + 'static, C: Camera + 'static>(
    plan: &Plan,
    rig: Rig<OnRotator<R>, C>,
    run_dir: &Path,
    resume: bool,
    ui: Ui,
) -> Result<Outcome, CommandError> {
    drive_with(plan, ui, |link| run::run(plan, rig, run_dir, resume, link)).await
}

/// [`drive`] for any run loop: `start` runs the plan with the link it is given.
async fn drive_with<F, Fut>(plan: &Plan, ui: Ui, start: F) -> Result<Outcome, CommandError>
where
    F: FnOnce(run::RunLink) -> Fut,
    Fut: std::future::Future<Output = Result<Outcome, run::RunError>>,
{
    let (ctl, link) = run::link();
    let Controller {
        control,
        mut state,
        mut events,
    } = ctl;
    let ctrl_c = match ui.hooks.clone() {
        Some(hooks) => tokio::task::spawn_local(hook_interrupts(hooks, control.clone())),
        None => tokio::task::spawn_local(ctrl_c_interrupts(control.clone())),
    };
    // Progress and the pause prompt.
    let bar = if ui.progress {
        let b = indicatif::ProgressBar::new(plan.max_frames().unwrap_or(0));
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} frames  {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        Some(b)
    } else {
        None
    };
    let bar2 = bar.clone();
    let ctrl = control.clone();
    let mut auto = ui.auto_resume;
    let hooks = ui.hooks.clone();
    let watcher = tokio::task::spawn_local(async move {
        while let Some(e) = events.recv().await {
            if let Some(h) = &hooks {
                h.event(&e);
            }
            match e {
                Event::Progress {
                    done,
                    planned,
                    label,
                } => {
                    if let Some(b) = &bar2 {
                        b.set_length(planned.max(done));
                        b.set_position(done);
                        b.set_message(label);
                    }
                }
                Event::Set { set, verdict, .. } if !verdict.accepted => {
                    let m = format!("set {set} rejected: {}", verdict.reason);
                    match &bar2 {
                        Some(b) => b.println(m),
                        None => eprintln!("{m}"),
                    }
                }
                Event::Retry(m) => {
                    let m = format!("retry: {m}");
                    match &bar2 {
                        Some(b) => b.println(m),
                        None => tracing::warn!("{m}"),
                    }
                }
                Event::State(RunState::Paused(reason)) => {
                    let say = |m: String| match &bar2 {
                        Some(b) => b.println(m),
                        None => eprintln!("{m}"),
                    };
                    say(format!("paused: {reason}"));
                    let c = if auto > 0 && !reason.starts_with("paused by the user") {
                        auto -= 1;
                        Control::Resume
                    } else if ui.interactive {
                        say("[r]esume, [a]bort, or [q]uit and resume later?".into());
                        let answer = tokio::task::spawn_blocking(|| {
                            let mut line = String::new();
                            std::io::stdin().read_line(&mut line).map(|_| line)
                        })
                        .await;
                        match answer.ok().and_then(Result::ok).as_deref().map(str::trim) {
                            Some("r") | Some("resume") => Control::Resume,
                            Some("a") | Some("abort") => Control::Abort,
                            _ => Control::Detach,
                        }
                    } else {
                        Control::Detach
                    };
                    if ctrl.send(c).await.is_err() {
                        break;
                    }
                }
                _ => {}
            }
        }
    });
    let outcome = start(link).await;
    drop(control);
    ctrl_c.abort();
    let _ = state.changed().await;
    if ui.hooks.is_some() {
        // The run is over: let the caller hear the events still queued (the watcher ends
        // when the run's senders are gone; 2 s at most, should a device task hold one).
        let _ = tokio::time::timeout(std::time::Duration::from_secs(2), watcher).await;
    } else {
        watcher.abort();
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    outcome.map_err(CommandError::of)
}

/// What the `n`th interrupt (from 1) asks of a run: pause at the next safe point, then at
/// once, then leave the run.
fn nth_interrupt(n: u32) -> Control {
    match n {
        1 => Control::Pause,
        2 => Control::PauseNow,
        _ => Control::Detach,
    }
}

/// Ctrl-C on the terminal: pause at the next safe point, then at once, then detach.
async fn ctrl_c_interrupts(ctrl: tokio::sync::mpsc::Sender<Control>) {
    let mut n = 0u32;
    while tokio::signal::ctrl_c().await.is_ok() {
        n += 1;
        let c = nth_interrupt(n);
        eprintln!(
            "{}",
            match c {
                Control::Pause => "pausing at the next safe point (Ctrl-C again: now)",
                Control::PauseNow =>
                    "pausing now (Ctrl-C again: leave the run for `acquire resume`)",
                _ => "leaving the run",
            }
        );
        if ctrl.send(c).await.is_err() {
            break;
        }
    }
}

/// A caller's interrupts, polled, as the terminal's Ctrl-C: the first pauses at the next safe
/// point (which, without a terminal, leaves the run for `acquire resume`), the second at once,
/// the third leaves the run.
async fn hook_interrupts(
    hooks: std::rc::Rc<dyn RunHooks>,
    ctrl: tokio::sync::mpsc::Sender<Control>,
) {
    let mut seen = 0u32;
    loop {
        tokio::time::sleep(std::time::Duration::from_millis(HOOK_POLL_MS)).await;
        while let Some(c) = hooks.control() {
            if ctrl.send(c).await.is_err() {
                return;
            }
        }
        let now = hooks.interrupts();
        while seen < now {
            seen += 1;
            let c = nth_interrupt(seen);
            if ctrl.send(c).await.is_err() {
                return;
            }
        }
    }
}

/// The simulated rig and its run.
async fn run_simulated(
    plan: &Plan,
    plan_dir: &Path,
    run_dir: &Path,
    resume: bool,
    ui: Ui,
) -> Result<(Outcome, SimRig), CommandError> {
    let link_dir = run_dir.join(".sim");
    let (rig, engine_rig) =
        SimRig::start_rig(plan, plan_dir, &link_dir, run::noise_stream(run_dir))
            .await
            .map_err(CommandError::of)?;
    let outcome = drive(plan, engine_rig, run_dir, resume, ui).await?;
    Ok((outcome, rig))
}

/// A run on the hardware rig `hw` describes (`polar_rig::connect_hardware`).
async fn run_hardware(
    plan: &Plan,
    hw: &Hardware,
    run_dir: &Path,
    resume: bool,
    ui: Ui,
) -> Result<Outcome, CommandError> {
    let connected = polar_rig::connect_hardware_for(hw, plan)
        .await
        .map_err(CommandError::of)?;
    let polar_rig::Connected { rig, simulator } = connected;
    let outcome = drive(plan, rig, run_dir, resume, ui).await;
    if let Some(s) = simulator {
        s.shutdown().await;
    }
    outcome
}

fn runtime() -> Result<tokio::runtime::Runtime, CommandError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| CommandError::failed(format!("cannot start the async runtime: {e}")))
}

fn outcome_json(o: &Outcome, run_dir: &Path) -> (Value, i32) {
    match o {
        Outcome::Done(s) => {
            let mut v =
                json!({"state": "done", "run_dir": run_dir.display().to_string(), "summary": s});
            if !s.saturation.warning.is_empty() {
                eprintln!("warning: {}", s.saturation.warning);
                v["warnings"] = json!([s.saturation.warning]);
            }
            (v, 0)
        }
        Outcome::Paused(r) => (
            json!({"state": "paused", "reason": r, "run_dir": run_dir.display().to_string(),
                   "resume": format!("polarimeter acquire resume {}", run_dir.display())}),
            3,
        ),
        Outcome::Aborted(r) => (
            json!({"state": "aborted", "reason": r, "run_dir": run_dir.display().to_string()}),
            4,
        ),
    }
}

/// `plan check FILE [--rig RIG]`: the forecast, without running; with a rig, its site (for a
/// plan without one) and its camera file.
pub fn plan_check(path: &Path, rig: Option<&RigFile>) -> Result<Value, CommandError> {
    let (mut plan, dir, chosen) = load_plan_resolved(path)?;
    if let Some(r) = rig {
        crate::rig::apply_site(&mut plan, r);
    }
    // What `acquire run --simulate` would refuse, refused here with the same message.
    polar_rig::SimRig::validate(&plan, &dir).map_err(CommandError::of)?;
    plan.check_frame(plan.simulation.width, plan.simulation.height)
        .map_err(CommandError::of)?;
    let (scene, mut camera) = forecast_models(&plan, &dir)?;
    if let Some(r) = rig {
        if let Some(c) = crate::rig::camera_model(r)? {
            camera = c;
        }
    }
    let timing = polar_rig::sim_stage::timing(&plan).map_err(CommandError::of)?;
    let f = polar_engine::forecast::forecast(&plan, &scene, &camera, &timing)
        .map_err(CommandError::of)?;
    let store = store_forecast(&plan, &dir, f.frames, f.sets)?;
    let mut v = json!({
        "plan": plan.name, "kind": plan.kind().name(), "forecast": f, "store": store,
    });
    if let Some(c) = chosen {
        v["continuous_from_planner"] = c;
    }
    if let Some(r) = rig {
        v["rig"] = json!(r.path.display().to_string());
    }
    Ok(v)
}

/// The disk the run's store will take ([`polar_rig::store_forecast`]): `bytes` in all,
/// `bytes_per_set` (a set's frames and products), the parts, and the raw frames' bytes beside.
fn store_forecast(plan: &Plan, dir: &Path, frames: u64, sets: u64) -> Result<Value, CommandError> {
    let b = polar_rig::store_forecast::forecast(plan, dir).map_err(CommandError::of)?;
    let (w, h) = (plan.simulation.width, plan.simulation.height);
    let raw = frames * u64::from(w) * u64::from(h) * 2;
    let total = b.total(frames, sets);
    let per_set = if sets > 0 {
        (total - b.fixed).div_ceil(sets)
    } else {
        0
    };
    Ok(json!({
        "bytes": total,
        "bytes_per_set": per_set,
        "parts": b,
        "raw_frame_bytes": raw,
        "store_over_raw": if raw > 0 { total as f64 / raw as f64 } else { 0.0 },
        "storage": plan.storage,
        "note": format!(
            "measured on one set of the plan's frames ({w}x{h}, its [simulation] size) \
             rendered from its scene and stored as the run stores them; a real camera's \
             frames and sky may differ"
        ),
    }))
}

/// The forecast's saturation warnings for a run of `plan` on the simulated camera (its scene
/// and camera): what `plan check` says, said again when the run starts. A forecast that
/// cannot be made says nothing here (the run itself refuses what is wrong).
fn saturation_forecast(plan: &Plan, plan_dir: &Path) -> Vec<String> {
    let Ok((scene, camera)) = forecast_models(plan, plan_dir) else {
        return Vec::new();
    };
    let Ok(timing) = polar_rig::sim_stage::timing(plan) else {
        return Vec::new();
    };
    let Ok(f) = polar_engine::forecast::forecast(plan, &scene, &camera, &timing) else {
        return Vec::new();
    };
    f.notes
        .into_iter()
        .filter(|n| n.contains("saturation"))
        .collect()
}

/// `acquire run PLAN [--simulate | hardware] [--rig RIG] [--out DIR]`. With a rig: its site for a
/// plan without one, and a finished calibrate-analyzer run's result written back to it as a new
/// revision (`rig_written` in the output).
pub fn run_cmd(
    plan_path: &Path,
    hardware: Option<Hardware>,
    rig: Option<&RigFile>,
    out: Option<PathBuf>,
    ui: Ui,
) -> Result<(Value, i32), CommandError> {
    let (mut plan, plan_dir) = load_plan(plan_path)?;
    if let Some(r) = rig {
        crate::rig::apply_site(&mut plan, r);
    }
    let run_dir = out.unwrap_or_else(|| run::default_run_dir(Path::new("."), &plan));
    if run_dir.exists() && !run_dir.is_dir() {
        return Err(CommandError::input(
            "--out",
            format!(
                " {}: is a file, not a directory; a run needs a new directory (or an empty \
             one) of its own",
                run_dir.display()
            ),
        ));
    }
    let simulated_camera = hardware.as_ref().is_none_or(|h| h.camera == "sim");
    let start_warnings = if simulated_camera {
        saturation_forecast(&plan, &plan_dir)
    } else {
        Vec::new()
    };
    for w in &start_warnings {
        eprintln!("warning (forecast): {w}");
    }
    let _log = crate::logging::to_run_dir(&run_dir);
    let rt = runtime()?;
    let local = tokio::task::LocalSet::new();
    let outcome = local.block_on(&rt, async {
        match &hardware {
            None => {
                let (o, rig) = run_simulated(&plan, &plan_dir, &run_dir, false, ui).await?;
                rig.shutdown().await;
                Ok::<_, CommandError>(o)
            }
            Some(hw) => run_hardware(&plan, hw, &run_dir, false, ui).await,
        }
    })?;
    let (mut v, code) = outcome_json(&outcome, &run_dir);
    if !start_warnings.is_empty() {
        v["forecast_warnings"] = json!(start_warnings);
    }
    if let (Some(r), Outcome::Done(_)) = (rig, &outcome) {
        let hw_zero = hardware.as_ref().map_or(0.0, |h| h.zero_offset_deg);
        if let Some(written) = crate::rig::write_back(r, &plan, &run_dir, hw_zero)? {
            v["rig_written"] = written;
        }
    }
    Ok((v, code))
}

/// `acquire resume RUN_DIR`: continues a paused or crashed run with the devices it was started on:
/// simulated runs get a new simulated rig; hardware runs take `hardware` when given, else the
/// rig file and flags the store recorded (refused, naming the values, when the analyzer's
/// values, the camera file or the dialect differ from the run's; other differences are named
/// in the output's `rig_differences`).
pub fn resume_cmd(
    run_dir: &Path,
    hardware: Option<Hardware>,
    rig: Option<&RigFile>,
    ui: Ui,
) -> Result<(Value, i32), CommandError> {
    // A finished run has nothing left to take: say so and change nothing (a script that
    // resumes whatever it finds, or a user following the README after a run that was never
    // interrupted, is not in error).
    if run::is_finished(run_dir) {
        return Ok((
            json!({
                "run_dir": run_dir.display().to_string(),
                "state": "done",
                "note": "the run is already finished: nothing to resume, nothing changed \
                         (`polarimeter acquire check RUN_DIR` verifies it)",
            }),
            0,
        ));
    }
    let plan = run::plan_of(run_dir).map_err(CommandError::of)?;
    let devices = polar_engine::journal::replay(run_dir)
        .map_err(CommandError::of)?
        .entries
        .iter()
        .find_map(|e| match e {
            polar_engine::journal::Entry::RunStarted { devices, .. } => Some(devices.clone()),
            _ => None,
        })
        .unwrap_or(Value::Null);
    let simulated = devices["kind"].as_str() == Some("simulated");
    let mut differences = Vec::new();
    let mut recorded_rig = None;
    let hardware = match hardware {
        Some(hw) => Some(hw),
        None if simulated => None,
        None => match crate::rig::recorded(&devices)? {
            Some((r, hw, diff)) => {
                refuse_changed_devices(run_dir, &diff)?;
                differences = diff;
                recorded_rig = Some(r);
                Some(hw)
            }
            None => {
                return Err(CommandError::failed(format!(
                    "the run was started on {} devices without a rig file: give --rig, or \
                     --port, --dialect, --camera and --camera-file, to resume it",
                    devices["kind"].as_str().unwrap_or("unknown")
                )))
            }
        },
    };
    let rig = rig.or(recorded_rig.as_ref());
    let _log = crate::logging::to_run_dir(run_dir);
    let rt = runtime()?;
    let local = tokio::task::LocalSet::new();
    let outcome = local.block_on(&rt, async {
        match &hardware {
            Some(hw) if !simulated => run_hardware(&plan, hw, run_dir, true, ui).await,
            _ => {
                let plan_dir = PathBuf::from(devices["plan_dir"].as_str().unwrap_or("."));
                let (o, rig) = run_simulated(&plan, &plan_dir, run_dir, true, ui).await?;
                rig.shutdown().await;
                Ok(o)
            }
        }
    })?;
    let (mut v, code) = outcome_json(&outcome, run_dir);
    if !differences.is_empty() {
        v["rig_differences"] = json!(differences);
    }
    // A calibration that finishes in a resume (after a lens-cap pause) writes back as a run.
    if let (Some(r), Outcome::Done(_)) = (rig, &outcome) {
        let hw_zero = hardware.as_ref().map_or(0.0, |h| h.zero_offset_deg);
        if let Some(written) = crate::rig::write_back(r, &plan, run_dir, hw_zero)? {
            v["rig_written"] = written;
        }
    }
    Ok((v, code))
}

/// The values a resumed run may not change without being told: the analyzer's zero offset and
/// extinction ratio, the camera file (the products' noise model) and the stage's dialect. A
/// difference in any of them refuses the resume, naming it; give `--rig` or flags to choose.
fn refuse_changed_devices(run_dir: &Path, differences: &[String]) -> Result<(), CommandError> {
    const FIXED: [&str; 4] = [
        "zero_offset_deg:",
        "extinction_ratio:",
        "camera_file:",
        "stage.dialect:",
    ];
    let changed: Vec<&String> = differences
        .iter()
        .filter(|d| FIXED.iter().any(|k| d.starts_with(k)))
        .collect();
    if changed.is_empty() {
        return Ok(());
    }
    Err(CommandError::failed(format!(
        "the rig file changed since run {} started, in values its frames depend on: {}. \
         Restore them, or give --rig and flags to resume with these devices deliberately",
        run_dir.display(),
        changed
            .iter()
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join("; ")
    )))
}

/// `acquire check RUN_DIR`: the run's frames and products against its journal; exit status 1 when
/// something is damaged.
pub fn check_cmd(run_dir: &Path) -> Result<(Value, i32), CommandError> {
    let c = polar_engine::check::check_run(run_dir).map_err(CommandError::of)?;
    let code = if c.ok { 0 } else { 1 };
    Ok((serde_json::to_value(&c).unwrap_or(Value::Null), code))
}

/// `acquire export tiff RUN_DIR [--out DIR]`.
pub fn export_tiff(run_dir: &Path, out: Option<PathBuf>) -> Result<Value, CommandError> {
    let out = out.unwrap_or_else(|| run_dir.join("tiff"));
    let s = polar_engine::export::export_tiff(run_dir, &out).map_err(CommandError::of)?;
    Ok(json!({ "out": out.display().to_string(), "export": s }))
}

/// The demo's target: the metal panel, against everything else in the rooftop panels scene.
/// Its contrast is partly polarimetric, so the analyzer angles change its SCR by half (0/60/120
/// against the best set).
pub const DEMO_TARGET: &str = "metal";

/// The demo's exposure as a fraction of the one that puts the brightest pixel at half the
/// full well: 3.5 %, about 10 us with the CMOS camera. So short that the sensor noise, not
/// the scene's clutter, limits detection: the matched filter's Pd at Pfa 1e-3 is then between
/// 0.6 and 0.9, where the SCR of the chosen angles shows in the Pd (at half the full well every
/// set detects the panel with Pd 1.0000).
pub const DEMO_EXPOSURE_FRACTION: f64 = 0.035;

/// The demo's plan: APTD on the rooftop panels (the metal panel as target), 3 channels from
/// 0/60/120, at most 15 frames, with 2 darks.
pub const DEMO_PLAN: &str = r#"
name = "demo"
kind = "adaptive"

[adaptive]
initial_angles_deg = [0, 60, 120]
channels = 3
exposure_us = 1000    # replaced: DEMO_EXPOSURE_FRACTION of the brightest pixel at half the full well
frame_budget = 15
darks = 2
target = { material = "metal" }
min_separation_deg = 30

[simulation]
width = 160
height = 120
seed = 7
stage_deg_per_s = 720

[storage]
products = "all"   # the report compares S0, S1, S2 and their sigmas with the scene's truth
"#;

/// The `demo --stage` values: the default simulated stage's dialect (`native`, our firmware's
/// rotator; the default) and every other simulated rotator's model (`k10cr1`, `ell14`, ...),
/// from the simulators' registry.
pub fn demo_stages() -> Vec<&'static str> {
    let (default, _) = sim_stage::default_stage();
    std::iter::once(default)
        .chain(
            sim_stage::rotators()
                .into_iter()
                .filter(|(d, _)| *d != default)
                .map(|(_, m)| m),
        )
        .collect()
}

/// The `[simulation] stage` of `demo --stage NAME`: `None` for the default stage; an error
/// naming `--stage`, the value and the allowed values otherwise.
pub fn demo_stage(name: &str) -> Result<Option<SimStage>, CommandError> {
    let (default, _) = sim_stage::default_stage();
    if name == default {
        return Ok(None);
    }
    sim_stage::rotators()
        .into_iter()
        .find(|(d, m)| *d != default && *m == name)
        .map(|(d, m)| {
            Some(SimStage {
                dialect: d.to_string(),
                model: Some(m.to_string()),
            })
        })
        .ok_or_else(|| {
            CommandError::input(
                "--stage",
                format!(
                    " {name:?} is not a simulated rotation stage: allowed {}",
                    demo_stages().join(", ")
                ),
            )
        })
}

/// `demo`: a short adaptive acquisition on simulated devices into `out` (replaced), the
/// analyzer on the default simulated stage (our firmware's rotator).
pub fn demo(out: &Path, ui: Ui) -> Result<String, CommandError> {
    demo_on_stage(out, sim_stage::default_stage().0, ui)
}

/// `demo --stage NAME`: the demo with the analyzer on the simulated stage `NAME` (one of
/// [`demo_stages`]), driven through its dialect's real driver over a pseudo-terminal.
pub fn demo_on_stage(out: &Path, stage: &str, ui: Ui) -> Result<String, CommandError> {
    let t0 = Instant::now();
    let mut plan = Plan::from_toml_str(DEMO_PLAN).map_err(CommandError::of)?;
    plan.simulation.stage = demo_stage(stage)?;
    // Only an earlier demo's run is replaced; any other run in `--out` is refused.
    if !run::run_parts(out).is_empty() {
        let earlier_demo = run::plan_of(out).is_ok_and(|p| p.name == plan.name);
        if !earlier_demo {
            return Err(CommandError::input(
                "--out",
                format!(
                    " {}: holds a run that is not an earlier demo; nothing was changed \
                 (choose another --out directory)",
                    out.display()
                ),
            ));
        }
        std::fs::remove_dir_all(out).map_err(|e| {
            CommandError::failed(format!(
                "{}: cannot replace the old demo run: {e}",
                out.display()
            ))
        })?;
    }
    let _log = crate::logging::to_run_dir(out);
    let rt = runtime()?;
    let local = tokio::task::LocalSet::new();
    let (outcome, truth, sensor, camera_model, stage_line) = local.block_on(&rt, async {
        // The exposure from the truth: the brightest pixel at half the full well.
        let link_dir = out.join(".sim");
        let (probe, cam) = SimRig::start(&plan, Path::new("."), &link_dir.join("probe"), 0)
            .map_err(CommandError::of)?;
        drop(cam);
        let stats = crate::study_aptd::true_stats(
            &probe.scene,
            &probe.sensor,
            &probe.camera_model,
            DEMO_TARGET,
        )?;
        probe.shutdown().await;
        if let Some(a) = plan.adaptive_mut() {
            a.exposure_us = (stats.t_int_s * 1e6 * DEMO_EXPOSURE_FRACTION)
                .round()
                .max(10.0);
        }
        let (o, rig) = run_simulated(&plan, Path::new("."), out, false, ui).await?;
        let stage_line = match plan.simulation.stage {
            None => "our firmware's protocol, simulated behind a pseudo-terminal, driven by \
                     the real driver"
                .to_string(),
            Some(_) => format!(
                "{} ({} dialect), simulated behind a pseudo-terminal, driven by the real {} driver",
                rig.server.describe(),
                rig.stage_dialect,
                rig.stage_dialect
            ),
        };
        let truth = rig.scene.clone();
        let sensor = rig.sensor.clone();
        let cm = rig.camera_model.clone();
        rig.shutdown().await;
        Ok::<_, CommandError>((o, truth, sensor, cm, stage_line))
    })?;
    let summary = match outcome {
        Outcome::Done(s) => s,
        Outcome::Paused(r) => {
            return Err(CommandError::failed(format!(
                "the demo paused: {r}; continue with `polarimeter acquire resume {}`",
                out.display()
            )))
        }
        Outcome::Aborted(r) => {
            return Err(CommandError::failed(format!("the demo was aborted: {r}")))
        }
    };
    let models = (&sensor, &camera_model);
    demo_report(out, &plan, &stage_line, &summary, &truth, models, t0)
}

fn demo_report(
    out: &Path,
    plan: &Plan,
    stage_line: &str,
    summary: &run::Summary,
    truth: &polar_hil_mocks::camera::SimScene,
    (sensor, camera): (
        &polar_model::sensor::SensorModel,
        &polar_model::sensor::Camera,
    ),
    t0: Instant,
) -> Result<String, CommandError> {
    use std::fmt::Write as _;
    let store = polar_engine::store::RunStore::open(out).map_err(CommandError::of)?;
    let attrs = store.attributes().map_err(CommandError::of)?;
    let decisions = attrs
        .get("decisions")
        .and_then(Value::as_array)
        .cloned()
        .unwrap_or_default();
    let stats = crate::study_aptd::true_stats(truth, sensor, camera, DEMO_TARGET)?;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Demo: adaptive polarimetric target detection on simulated devices\n\
         - stage: {stage_line}\n\
         - camera: simulated, {}x{} frames rendered from the rooftop scene model through the stage's true angle\n\
         - target: the metal panel against everything else (asphalt, grass, glass, paint)\n\
         - exposure: {:.0} us ({:.1} % of the exposure that puts the brightest pixel at half \
         the full well): short, so that sensor noise makes detection hard and the angles matter",
        truth.width,
        truth.height,
        plan.adaptive().map_or(0.0, |a| a.exposure_us),
        100.0 * DEMO_EXPOSURE_FRACTION
    );
    let _ = writeln!(
        s,
        "\nWhat the planner chose, and why (each round's SCR is the loop's own, from its \
         estimates of the classes with the ideal analyzer and its own noise assumption; \
         the table below scores the sets under the true statistics):"
    );
    for d in &decisions {
        let angles: Vec<String> = d["next_angles_deg"]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(Value::as_f64)
                    .map(|x| format!("{x:.1}"))
                    .collect()
            })
            .unwrap_or_default();
        let _ = writeln!(
            s,
            "  round {}: {} frames used; next set [{}] deg, SCR {:.2} (last set {:.2}); {}",
            d["round"],
            d["frames_used"],
            angles.join(", "),
            d["scr_next"].as_f64().unwrap_or(f64::NAN),
            d["scr_last_set"].as_f64().unwrap_or(f64::NAN),
            d["reason"].as_str().unwrap_or("")
        );
    }
    let final_deg = summary.final_angles_deg.clone().unwrap_or_default();
    let exposure_us = plan.adaptive().map_or(0.0, |a| a.exposure_us);
    let table = demo_detection(truth, sensor, exposure_us, &final_deg)?;
    let _ = writeln!(
        s,
        "\nSCR and matched-filter Pd (Pfa 1e-3) of one set under the scene's true statistics \
         (the camera's real analyzer and noise at {exposure_us:.0} us, as `plan scene` \
         forecasts):"
    );
    for row in &table.rows {
        let shown: Vec<String> = row.angles_deg.iter().map(|x| format!("{x:.1}")).collect();
        let _ = writeln!(
            s,
            "  {:<28} [{}] deg: SCR {:.2}, Pd {:.4}",
            row.name,
            shown.join(", "),
            row.scr,
            row.pd
        );
    }
    let _ = writeln!(s, "{}", table.meaning);
    // Stokes error of the last set's products against the truth.
    let slots = summary.sets_accepted;
    if slots > 0 {
        let slot = slots - 1;
        let img = |n: &str| store.read_product(n, slot).map_err(CommandError::of);
        let (s0, s1, s2) = (img("s0")?, img("s1")?, img("s2")?);
        let (e0, e1, e2) = (img("sigma_s0")?, img("sigma_s1")?, img("sigma_s2")?);
        // DN per radiance unit at the plan's exposure (`stats` is at its own, longer one).
        let scale = stats.k * sensor.responsivity_e_per_s() * exposure_us * 1e-6;
        let (mut within, mut total, mut rel) = (0usize, 0usize, 0.0f64);
        for (p, t) in truth.stokes.iter().enumerate() {
            let est = [s0[p], s1[p], s2[p]];
            let sig = [e0[p], e1[p], e2[p]];
            if !est.iter().chain(&sig).all(|v| v.is_finite()) {
                continue;
            }
            for c in 0..3 {
                let z = (f64::from(est[c]) - t[c] * scale) / f64::from(sig[c]).max(1e-12);
                total += 1;
                if z.abs() < 2.0 {
                    within += 1;
                }
            }
            rel += ((f64::from(est[0]) - t[0] * scale) / (t[0] * scale)).powi(2);
        }
        let n_px = total / 3;
        let _ = writeln!(
            s,
            "\nStokes error of the last set against the ground truth ({n_px} pixels):\n  \
             {:.2} % of S0, S1, S2 values within 2 predicted sigma (95.4 % expected); S0 rms \
             relative error {:.2} %",
            100.0 * within as f64 / total.max(1) as f64,
            100.0 * (rel / n_px.max(1) as f64).sqrt()
        );
    }
    let _ = writeln!(
        s,
        "\nRun: {} frames stored ({} accepted), {} sets, {} rejected by the suspender, {} retries; \
         acquisition {:.1} s, total {:.1} s.\nWritten to {}/ (run.zarr, journal.jsonl, run.log, \
         plan.toml). Read it back: `polarimeter acquire export tiff {}`, or in Python \
         `zarr.open_group('{}/run.zarr')`.",
        summary.frames_stored,
        summary.frames_accepted,
        summary.sets_accepted,
        summary.sets_rejected,
        summary.retries,
        summary.elapsed_s,
        t0.elapsed().as_secs_f64(),
        out.display(),
        out.display(),
        out.display()
    );
    Ok(s)
}

/// One set's detection figures in the demo.
struct DemoRow {
    name: String,
    angles_deg: Vec<f64>,
    scr: f64,
    pd: f64,
}

/// The demo's detection table and what its Pd differences mean.
struct DemoTable {
    rows: Vec<DemoRow>,
    meaning: String,
}

/// The demo's sets scored under the scene's true statistics: the target's pixels against all
/// others, each class's Stokes mean and covariance (radiance) from the rendered truth, through
/// the camera's real analyzer rows with each class's own sensor noise at `exposure_us`
/// ([`polar_model::sensor::SensorModel::signal`]), and the matched filter at Pfa 1e-3. The
/// planner's optimum under the same statistics ([`polar_planner::Contrast::from_sensor`], a
/// Stokes set of 3 angles at least 30 deg apart, as the demo's plan asks) is shown beside the
/// set the adaptive loop reached from its own estimates.
fn demo_detection(
    truth: &polar_hil_mocks::camera::SimScene,
    sensor: &polar_model::sensor::SensorModel,
    exposure_us: f64,
    final_deg: &[f64],
) -> Result<DemoTable, CommandError> {
    use nalgebra::Vector3;
    use polar_model::metrics::{matched_filter, ClassStats};
    use polar_model::polarization::Stokes;
    use polar_model::sensor::Exposure;
    let target_name = DEMO_TARGET;
    let t_idx = truth
        .materials
        .iter()
        .position(|m| *m == target_name)
        .ok_or_else(|| {
            CommandError::failed(format!("target {} is not in the layout", target_name))
        })?;
    let radiance: Vec<Vector3<f64>> = truth
        .stokes
        .iter()
        .map(|s| Vector3::new(s[0], s[1], s[2]))
        .collect();
    let in_target: Vec<bool> = truth
        .region
        .iter()
        .map(|&r| usize::from(r) == t_idx)
        .collect();
    let outside: Vec<bool> = in_target.iter().map(|t| !t).collect();
    let few = || {
        CommandError::failed(format!(
            "target {}: fewer than 4 pixels in a class",
            target_name
        ))
    };
    let (mu_t, cov_t) = polar_planner::aptd::mean_cov(&radiance, &in_target).ok_or_else(few)?;
    let (mu_b, cov_b) = polar_planner::aptd::mean_cov(&radiance, &outside).ok_or_else(few)?;
    let t_int_s = exposure_us * 1e-6;
    let score = |name: &str, angles_deg: &[f64]| -> Result<DemoRow, CommandError> {
        let rad: Vec<f64> = angles_deg.iter().map(|d| d.to_radians()).collect();
        let class = |field, mu: &Vector3<f64>, cov: &nalgebra::Matrix3<f64>| {
            let mut e = Exposure::new(t_int_s, Stokes(*mu));
            e.radiance_cov_w2_m4_sr2 = 0.5 * (cov + cov.transpose());
            let sig = sensor.signal(&rad, &e).map_err(CommandError::of)?;
            ClassStats::new(field, sig.mean_dn, sig.cov_dn).map_err(CommandError::of)
        };
        let roc = matched_filter(
            &class("target", &mu_t, &cov_t)?,
            &class("background", &mu_b, &cov_b)?,
            1e-3,
        )
        .map_err(CommandError::of)?;
        Ok(DemoRow {
            name: name.to_string(),
            angles_deg: angles_deg.to_vec(),
            scr: roc.scr,
            pd: roc.pd,
        })
    };
    let contrast = polar_planner::Contrast::from_sensor(sensor, t_int_s, &mu_t, &mu_b, &cov_b)
        .map_err(CommandError::of)?;
    let best = polar_planner::optimise(
        &contrast,
        3,
        &polar_planner::Constraints {
            max_condition: Some(polar_planner::stokes::STOKES_MAX_CONDITION),
            ..polar_planner::Constraints::default()
        },
        0.01f64.to_radians(),
    )
    .map_err(CommandError::of)?;
    let best_deg: Vec<f64> = best.angles_rad.iter().map(|a| a.to_degrees()).collect();
    let mut rows = Vec::new();
    if !final_deg.is_empty() {
        rows.push(score("APTD (this run's last set)", final_deg)?);
    }
    rows.push(score("planner (true statistics)", &best_deg)?);
    for (name, deg) in polar_planner::optimize::CONVENTIONAL {
        rows.push(score(name, deg)?);
    }
    let pd_of = |name: &str| {
        rows.iter()
            .find(|r| r.name == name)
            .map_or(f64::NAN, |r| r.pd)
    };
    let chosen = rows[0].pd;
    let (p45, p60) = (pd_of("0/45/90"), pd_of("0/60/120"));
    let meaning = format!(
        "What the difference means: at the same false-alarm rate (1 background pixel in 1000 \
         flagged) and with the same 3 frames per set, the {} set finds {:.0} of every 1000 \
         target pixels, 0/45/90 finds {:.0} and 0/60/120 {:.0}: {:+.0} and {:+.0} target pixels \
         per 1000 from choosing the angles alone. (0/45/90/135 takes a 4th frame, a third more \
         time.)",
        if final_deg.is_empty() {
            "planner's"
        } else {
            "APTD"
        },
        1000.0 * chosen,
        1000.0 * p45,
        1000.0 * p60,
        1000.0 * (chosen - p45),
        1000.0 * (chosen - p60)
    );
    Ok(DemoTable { rows, meaning })
}

/// Runs a simulated plan to the end in this process, resuming (with a new simulated rig, as
/// `polarimeter acquire resume` would) whenever it is left paused, at most `max_resumes` times.
/// Returns the summary, the resumes and the pauses' reasons.
pub async fn run_to_end(
    plan: &Plan,
    run_dir: &Path,
    ui: Ui,
    max_resumes: u32,
) -> Result<(run::Summary, u32, Vec<String>), CommandError> {
    let mut resume = false;
    let mut reasons = Vec::new();
    for resumes in 0..=max_resumes {
        let (o, rig) = run_simulated(plan, Path::new("."), run_dir, resume, ui.clone()).await?;
        rig.shutdown().await;
        match o {
            Outcome::Done(s) => return Ok((s, resumes, reasons)),
            Outcome::Paused(r) => reasons.push(r),
            Outcome::Aborted(r) => return Err(CommandError::failed(format!("aborted: {r}"))),
        }
        resume = true;
    }
    Err(CommandError::failed(format!(
        "{}: still paused after {max_resumes} resumes: {reasons:?}",
        run_dir.display()
    )))
}

/// The device-bound ideal of a step sequence on the simulated stage: each move (the
/// analyzer's positive approach with its overshoot, as `OnRotator` plans it) at the stage's
/// trapezoidal profile, plus each exposure.
fn ideal_s(angles_deg: &[f64], exposure_us: f64, plan: &Plan) -> f64 {
    use polar_hal::{signed_difference, wrap, TURN_RAD};
    let counts_per_rad = 144_000.0 / TURN_RAD;
    let v = (plan.simulation.stage_deg_per_s * 144_000.0 / 360.0).round();
    let a = v * 8.0;
    let move_s = |from: f64, to: f64| {
        polar_hil_mocks::motion::Profile {
            start: 0.0,
            target: signed_difference(to, from, TURN_RAD).abs() * counts_per_rad,
            t0_s: 0.0,
            v,
            a,
        }
        .duration_s()
    };
    let o = 0.5f64.to_radians();
    let mut current = 0.0;
    let mut total = 0.0;
    for deg in angles_deg {
        let psi = deg.to_radians();
        let plan_of = |t: f64| -> (f64, Vec<f64>) {
            let d = signed_difference(t, current, TURN_RAD);
            if d >= o {
                (d.abs(), vec![t])
            } else {
                let pre = wrap(t - o, TURN_RAD);
                (
                    signed_difference(pre, current, TURN_RAD).abs() + o,
                    vec![pre, t],
                )
            }
        };
        let (p0, p1) = (
            plan_of(wrap(psi, TURN_RAD)),
            plan_of(wrap(psi + std::f64::consts::PI, TURN_RAD)),
        );
        let (_, waypoints) = if p1.0 < p0.0 { p1 } else { p0 };
        for w in waypoints {
            total += move_s(current, w);
            current = w;
        }
        total += exposure_us * 1e-6;
    }
    total
}

/// `bench run`: a simulated capture's wall time against the device-bound ideal.
pub fn bench_run(sets: u32, exposure_us: f64) -> Result<String, CommandError> {
    if !(1..=1000).contains(&sets) {
        return Err(CommandError::input(
            "--sets",
            format!(" = {sets} is out of range: allowed 1..=1000"),
        ));
    }
    if !(10.0..=1e6).contains(&exposure_us) {
        return Err(CommandError::input(
            "--exposure-us",
            format!(
                " = {exposure_us} is out of range: allowed [10, 1000000] (the rooftop \
             scene's brightest pixel reaches half the full well at about 300 us)"
            ),
        ));
    }
    let text = format!(
        "name = \"bench\"\nkind = \"capture\"\n[capture]\nangles_deg = [0, 45, 90, 135]\n\
         exposure_us = [{exposure_us}]\nrepeats = {sets}\n[simulation]\nwidth = 160\nheight = 120\n\
         stage_deg_per_s = 360\n"
    );
    let plan = Plan::from_toml_str(&text).map_err(CommandError::of)?;
    let steps = plan.steps().map_err(CommandError::of)?;
    let angles: Vec<f64> = steps.iter().map(|s| s.angle_deg).collect();
    let ideal = ideal_s(&angles, exposure_us, &plan);
    let dir = std::env::temp_dir().join(format!("polarimeter-bench-run-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let rt = runtime()?;
    let local = tokio::task::LocalSet::new();
    let ui = Ui::unattended(0);
    let (summary, _, _) = local.block_on(&rt, run_to_end(&plan, &dir, ui, 0))?;
    let _ = std::fs::remove_dir_all(&dir);
    let wall = summary.elapsed_s;
    let device = summary.device_s;
    Ok(format!(
        "| sets x angles | exposure | device-bound ideal | device operations | wall time | wall / ideal | wall / device operations |\n\
         |---|---|---|---|---|---|---|\n\
         | {sets} x 4 | {:.2} ms | {ideal:.3} s | {device:.3} s | {wall:.3} s | {:.4} | {:.4} |\n\n\
         - The ideal is the simulated stage's moves (trapezoidal profile at 360 deg/s, \
         2880 deg/s^2, with the analyzer's 0.5 deg positive-approach overshoot) plus the \
         exposures.\n\
         - Device operations are the time the engine waited on the stage and the camera: the \
         moves with the driver's queries and readback over the 115200-baud link, and the grabs \
         with the simulated camera's rendering of each frame.\n\
         - The wall time is the engine's, from opening the store to the last verified frame, with \
         every frame fsynced and journaled and each set's products and suspender check computed \
         (overlapped with the next move).\n",
        exposure_us / 1000.0,
        wall / ideal,
        wall / device
    ))
}

/// One fault kind of the campaign: the plan's `[simulation]` fault tables.
fn fault_kinds() -> Vec<(&'static str, &'static str)> {
    vec![
        (
            "stage: dropped replies",
            "stage_faults = { drop_reply = 0.15 }",
        ),
        (
            "stage: corrupted replies",
            "stage_faults = { corrupt_reply = 0.15 }",
        ),
        (
            "stage: duplicated replies",
            "stage_faults = { duplicate_reply = 0.2 }",
        ),
        (
            "stage: spurious busy",
            "stage_faults = { spurious_busy = 0.3 }",
        ),
        ("stage: stalled moves", "stage_faults = { stall = 0.1 }"),
        (
            "stage: spontaneous resets",
            "stage_faults = { spontaneous_reset = 0.05 }",
        ),
        (
            "stage: late replies",
            "stage_faults = { late_reply = 0.1, late_by_s = 0.3 }",
        ),
        ("stage: line noise", "stage_faults = { garbage = 0.3 }"),
        (
            "stage: chunked and coalesced",
            "stage_faults = { chunk_reads = 0.5, coalesce_replies = 0.5 }",
        ),
        (
            "stage: unplug and replug",
            "stage_faults = { unplug = 0.05, replug_s = 0.3 }",
        ),
        (
            "camera: dropped frames",
            "camera_faults = { drop_frame = 0.2 }",
        ),
        (
            "camera: truncated frames",
            "camera_faults = { truncate_frame = 0.2 }",
        ),
        (
            "camera: stuck frames",
            "camera_faults = { stuck_frame = 0.2 }",
        ),
        (
            "camera: stalls",
            "camera_faults = { stall = 0.15, stall_s = 0.3 }",
        ),
        (
            "camera: disconnect (each counted once)",
            "camera_faults = { disconnect_after_frames = 7 }",
        ),
    ]
}

/// The result of a fault campaign.
#[derive(Debug, Clone, Default)]
pub struct Campaign {
    /// Runs.
    pub runs: u64,
    /// Faults injected (chances that came up in the simulators).
    pub faults: u64,
    /// Planned frames with no accepted frame at the end.
    pub lost_frames: u64,
    /// Accepted light frames whose mean is not the truth's at their measured angle.
    pub corrupt_frames: u64,
    /// Frames checked.
    pub frames_checked: u64,
    /// Runs left paused and resumed in a new rig.
    pub resumes: u64,
    /// Sets the suspender rejected.
    pub sets_rejected: u64,
    /// Device operations retried.
    pub retries: u64,
    /// Per kind: runs, faults, seconds.
    pub per_kind: Vec<(String, u64, u64, f64)>,
}

/// Checks every accepted light frame of a finished simulated run against the truth: its mean
/// DN must be the model's at its measured angle within 6 standard errors of the mean plus 0.5 %
/// (the stage's encoder noise and backlash, which move the mean by well under that).
pub fn check_frames_against_truth(run_dir: &Path, plan: &Plan) -> Result<(u64, u64), CommandError> {
    let store = polar_engine::store::RunStore::open(run_dir).map_err(CommandError::of)?;
    let records = store.read_frame_metadata().map_err(CommandError::of)?;
    let replay = polar_engine::journal::replay(run_dir).map_err(CommandError::of)?;
    let rejected = replay.rejected_frames();
    let rig = SimRig::world(plan, Path::new(".")).map_err(CommandError::of)?;
    let camera = &rig.camera_model;
    let (mut bad, mut checked) = (0u64, 0u64);
    let mut latest: std::collections::BTreeMap<u64, &polar_engine::FrameRecord> =
        Default::default();
    for r in &records {
        if r.kind == polar_engine::FrameKind::Light && !rejected.contains(&r.index) {
            latest.insert(r.step, r);
        }
    }
    for r in latest.values() {
        let px = store.read_frame(r.index).map_err(CommandError::of)?;
        let psi = r.measured_angle_deg.to_radians();
        let w = rig
            .sensor
            .intensities_from_stokes(&[psi])
            .map_err(CommandError::of)?;
        let k = camera.gain_dn_per_e;
        let g = rig.sensor.responsivity_e_per_s() * r.exposure_us * 1e-6;
        let n = px.len() as f64;
        let mean = px.iter().map(|&p| f64::from(p)).sum::<f64>() / n;
        let var = px
            .iter()
            .map(|&p| (f64::from(p) - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0);
        let pred_e: f64 = rig
            .scene
            .stokes
            .iter()
            .map(|s| (g * (w[(0, 0)] * s[0] + w[(0, 1)] * s[1] + w[(0, 2)] * s[2])).max(0.0))
            .sum::<f64>()
            / n;
        let pred =
            camera.offset_dn + k * (pred_e + camera.dark_current_e_per_s * r.exposure_us * 1e-6);
        let tol = 6.0 * (var / n).sqrt() + 0.005 * pred;
        checked += 1;
        if (mean - pred).abs() > tol {
            bad += 1;
            tracing::error!(
                frame = r.index,
                mean,
                pred,
                "accepted frame does not match the truth at its measured angle"
            );
        }
    }
    Ok((bad, checked))
}

/// A seeded fault campaign of at least `faults` injected faults over every fault kind.
pub fn campaign(faults: u64, seed: u64, base: &Path) -> Result<Campaign, CommandError> {
    let kinds = fault_kinds();
    let mut c = Campaign {
        per_kind: kinds
            .iter()
            .map(|(k, _)| (k.to_string(), 0, 0, 0.0))
            .collect(),
        ..Campaign::default()
    };
    let rt = runtime()?;
    let ui = Ui::unattended(3);
    let mut run = 0u64;
    // Every kind at least once, and until every kind has injected a fault (at most ten runs
    // of each), then round robin until `faults` were injected.
    let max_runs = 10 * kinds.len() as u64;
    loop {
        let silent = c.per_kind.iter().position(|k| k.2 == 0);
        let k = if (run as usize) < kinds.len() {
            run as usize
        } else if let (Some(k), true) = (silent, run < max_runs) {
            k
        } else if c.faults < faults {
            (run as usize) % kinds.len()
        } else {
            break;
        };
        let text = format!(
            "name = \"faults\"\nkind = \"capture\"\n[capture]\nangles_deg = [0, 45, 90, 135]\n\
             exposure_us = [250]\nrepeats = 2\ndarks_before = 1\n[policy]\nattempts = 4\n\
             retry_backoff_ms = 50\nmove_timeout_s = 5\ngrab_timeout_s = 1\n\
             [simulation]\nwidth = 64\nheight = 48\nseed = {}\nstage_deg_per_s = 720\n{}\n",
            seed.wrapping_mul(1000).wrapping_add(run),
            kinds[k].1
        );
        let plan = Plan::from_toml_str(&text).map_err(CommandError::of)?;
        let dir = base.join(format!("run-{run}"));
        let _ = std::fs::remove_dir_all(&dir);
        let before = polar_hil_mocks::faults::faults_fired();
        let t_run = Instant::now();
        let local = tokio::task::LocalSet::new();
        let (summary, resumes, _) = local.block_on(&rt, run_to_end(&plan, &dir, ui.clone(), 20))?;
        // A disconnect is set by a frame count, not a chance: count each (each forces a
        // pause and a resume in a new rig).
        let disconnects = if kinds[k].1.contains("disconnect_after_frames") {
            u64::from(resumes)
        } else {
            0
        };
        let fired = polar_hil_mocks::faults::faults_fired() - before + disconnects;
        let planned = plan.steps().map_err(CommandError::of)?.len() as u64;
        c.lost_frames += planned.saturating_sub(summary.frames_accepted);
        let (bad, checked) = check_frames_against_truth(&dir, &plan)?;
        c.corrupt_frames += bad;
        c.frames_checked += checked;
        c.resumes += u64::from(resumes);
        c.sets_rejected += summary.sets_rejected;
        c.retries += summary.retries;
        c.per_kind[k].1 += 1;
        c.per_kind[k].2 += fired;
        c.per_kind[k].3 += t_run.elapsed().as_secs_f64();
        c.runs += 1;
        c.faults += fired;
        let _ = std::fs::remove_dir_all(&dir);
        run += 1;
    }
    Ok(c)
}

/// `bench faults`: the campaign as Markdown.
pub fn bench_faults(faults: u64, seed: u64) -> Result<String, CommandError> {
    if !(1..=1_000_000).contains(&faults) {
        return Err(CommandError::input(
            "--faults",
            format!(" = {faults} is out of range: allowed 1..=1000000"),
        ));
    }
    let base = std::env::temp_dir().join(format!("polarimeter-faults-{}", std::process::id()));
    let t0 = Instant::now();
    let c = campaign(faults, seed, &base)?;
    let _ = std::fs::remove_dir_all(&base);
    let mut s = format!(
        "Fault campaign (seed {seed}): {} runs, {} faults injected, {:.0} s.\n\n\
         | fault kind | runs | faults injected | wall time, s |\n|---|---|---|---|\n",
        c.runs,
        c.faults,
        t0.elapsed().as_secs_f64()
    );
    for (k, runs, f, t) in &c.per_kind {
        s.push_str(&format!("| {k} | {runs} | {f} | {t:.1} |\n"));
    }
    s.push_str(&format!(
        "\n- lost frames (planned, not stored at the end): **{}**\n\
         - silently corrupt frames (accepted, but not the truth at their measured angle): **{}** of {} checked\n\
         - runs left paused and resumed in a new rig: {}\n\
         - sets rejected by the suspender and taken again: {}\n\
         - device operations retried: {}\n",
        c.lost_frames, c.corrupt_frames, c.frames_checked, c.resumes, c.sets_rejected, c.retries
    ));
    Ok(s)
}
