//! What the engine's run tests share: a simulated rig driven by a scripted controller, and
//! the outside checks of a run directory.
#![allow(dead_code, clippy::unwrap_used)]

use polar_engine::journal::replay;
use polar_engine::plan::Plan;
use polar_engine::run::{self, Control, Event, Outcome, RunState, Summary};
use polar_engine::store::RunStore;
use polar_rig::SimRig;
use std::path::{Path, PathBuf};

pub mod spans;

pub fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("polar-runs-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// What a test does with the controller while the run goes.
#[derive(Clone, Copy, PartialEq)]
pub enum Script {
    /// Nothing.
    Watch,
    /// Pause (at the next safe point) after `n` frames, then resume.
    PauseResume(u64),
    /// Pause now after `n` frames, then resume.
    PauseNowResume(u64),
    /// Pause after `n` frames, then abort.
    PauseAbort(u64),
    /// Pause after `n` frames, then detach.
    PauseDetach(u64),
    /// Abort after `n` frames, while the run is going (no pause first).
    AbortRunning(u64),
}

/// Runs `plan` on a new simulated rig; returns the outcome, the states seen and the events.
pub fn go(
    plan: &Plan,
    dir: &Path,
    resume: bool,
    script: Script,
) -> (Outcome, Vec<RunState>, Vec<Event>) {
    let (outcome, states, events) = go_result(plan, dir, resume, script);
    (outcome.unwrap(), states, events)
}

/// Runs `plan` into `dir` on a new simulated rig with no controller input: the engine's
/// result as it is (an error included).
pub fn try_run(plan: &Plan, dir: &Path, resume: bool) -> Result<Outcome, run::RunError> {
    go_result(plan, dir, resume, Script::Watch).0
}

/// [`go`], with the engine's result as it is.
fn go_result(
    plan: &Plan,
    dir: &Path,
    resume: bool,
    script: Script,
) -> (Result<Outcome, run::RunError>, Vec<RunState>, Vec<Event>) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let local = tokio::task::LocalSet::new();
    local.block_on(&rt, async {
        let (rig, engine_rig) = SimRig::start_rig(
            plan,
            Path::new("."),
            &dir.join(".sim"),
            run::noise_stream(dir),
        )
        .await
        .unwrap();
        let (ctl, link) = run::link();
        let run::Controller {
            control,
            state,
            mut events,
        } = ctl;
        let watcher = tokio::task::spawn_local(async move {
            let mut states = Vec::new();
            let mut seen = Vec::new();
            let mut paused_once = false;
            while let Some(e) = events.recv().await {
                match &e {
                    Event::Progress { done, .. } => {
                        let trigger = match script {
                            Script::PauseResume(n)
                            | Script::PauseAbort(n)
                            | Script::PauseDetach(n) => Some((n, Control::Pause)),
                            Script::PauseNowResume(n) => Some((n, Control::PauseNow)),
                            Script::AbortRunning(n) => Some((n, Control::Abort)),
                            Script::Watch => None,
                        };
                        if let Some((n, c)) = trigger {
                            if *done == n && !paused_once {
                                paused_once = true;
                                control.send(c).await.unwrap();
                            }
                        }
                    }
                    Event::State(s) => {
                        states.push(s.clone());
                        if let RunState::Paused(reason) = s {
                            let c = match script {
                                Script::PauseAbort(_) => Control::Abort,
                                Script::PauseDetach(_) => Control::Detach,
                                _ if reason.starts_with("paused by the user") => Control::Resume,
                                _ => Control::Resume,
                            };
                            control.send(c).await.unwrap();
                        }
                    }
                    _ => {}
                }
                seen.push(e);
            }
            (states, seen)
        });
        let outcome = run::run(plan, engine_rig, dir, resume, link).await;
        drop(state);
        let (states, seen) = watcher.await.unwrap();
        rig.shutdown().await;
        (outcome, states, seen)
    })
}

pub fn done(o: &Outcome) -> &Summary {
    match o {
        Outcome::Done(s) => s,
        other => panic!("not done: {other:?}"),
    }
}

/// The exact frame set: every planned step has one accepted frame, frame indices are
/// 0..N without gaps, and the stored pixels hash to the journaled hashes (the engine's own
/// end check, repeated here from the outside).
pub fn check_frame_set(dir: &Path, planned_steps: u64) {
    let r = replay(dir).unwrap();
    assert!(r.is_finished(), "journal has no finished entry");
    let frames = r.frames();
    let n = frames.len() as u64;
    assert_eq!(
        frames.keys().copied().collect::<Vec<_>>(),
        (0..n).collect::<Vec<_>>()
    );
    let rejected = r.rejected_frames();
    let mut steps: Vec<u64> = frames
        .values()
        .filter(|f| !rejected.contains(&f.index))
        .map(|f| f.step)
        .collect();
    steps.sort_unstable();
    steps.dedup();
    assert_eq!(steps, (0..planned_steps).collect::<Vec<_>>());
    let store = RunStore::open(dir).unwrap();
    assert_eq!(store.frame_count(), n);
    for f in frames.values() {
        let px = store.read_frame(f.index).unwrap();
        assert_eq!(polar_engine::pixel_hash(&px), f.hash, "frame {}", f.index);
    }
}

/// The Python interpreter with zarr 3, xarray and xxhash (`POLARIMETER_PYTHON`, which
/// `scripts/test.sh` sets to its venv; else the venv `target/py-venv` if it exists, else
/// `python3`), or `None` when the test may skip (`POLARIMETER_SKIP_PYTHON=1`). Panics when
/// it is missing and skipping was not asked.
pub fn python() -> Option<String> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/py-venv/bin/python");
    let py = std::env::var("POLARIMETER_PYTHON").unwrap_or_else(|_| {
        if venv.is_file() {
            venv.display().to_string()
        } else {
            "python3".into()
        }
    });
    let ok = std::process::Command::new(&py)
        .args(["-c", "import zarr, xarray, xxhash"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        return Some(py);
    }
    if std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1") {
        println!("skipped the outside check: {py} lacks zarr, xarray or xxhash");
        return None;
    }
    panic!(
        "{py} cannot import zarr, xarray and xxhash: run the tests with `bash scripts/test.sh` \
         (it makes the venv and sets POLARIMETER_PYTHON), or set POLARIMETER_SKIP_PYTHON=1"
    );
}

/// The run directory as an outside reader sees it: `scripts/check_run.py` (zarr-python,
/// xarray, xxhash; see its doc) must find nothing wrong.
pub fn outside_check(dir: &Path, finished: bool) {
    let Some(py) = python() else { return };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/check_run.py");
    let mut cmd = std::process::Command::new(&py);
    cmd.arg(&script).arg(dir);
    if finished {
        cmd.arg("--finished");
    }
    let out = cmd.output().unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success(),
        "check_run.py on {}: {text}",
        dir.display()
    );
    if finished {
        recompute_check(dir, &py);
    }
}

/// docs/DATASET.md's Python reference recomputes every set's products from the store alone
/// (`scripts/recompute_products.py`, whose doc states the float32 tolerances) and agrees with
/// the stored products.
fn recompute_check(dir: &Path, py: &str) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/recompute_products.py");
    let out = std::process::Command::new(py)
        .arg(&script)
        .arg(dir)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    println!("recompute_products.py {}: {text}", dir.display());
    assert!(
        out.status.success(),
        "recompute_products.py on {}: {text}{}",
        dir.display(),
        String::from_utf8_lossy(&out.stderr)
    );
}
