//! Crash safety: `polarimeter run --simulate` is killed with SIGKILL at random moments (at
//! least 20 times, the first kill in the first run and the rest in `polarimeter resume`s),
//! then resumed to the end. The frame set must be exact: every planned step has exactly one
//! accepted frame, frame indices run 0..N without a gap, and every stored frame hashes to its
//! journaled hash. A demo run is also checked end to end through the binary.
#![allow(clippy::unwrap_used)]

use polar_engine::journal::replay;
use polar_engine::store::RunStore;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

const PLAN: &str = r#"
name = "crash"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [2000]
repeats = 5
darks_before = 2
darks_after = 1
[simulation]
width = 64
height = 48
seed = 9
"#;
const PLANNED: u64 = 23;

fn spawn(args: &[&str]) -> Child {
    Command::new(BIN)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

fn journal_frames(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join("journal.jsonl"))
        .map(|t| {
            t.lines()
                .filter(|l| l.contains("\"event\":\"frame\""))
                .count()
        })
        .unwrap_or(0)
}

#[test]
fn kill_nine_at_random_steps_then_resume_exactly() {
    let base = std::env::temp_dir().join(format!("polar-crash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    std::fs::create_dir_all(&base).unwrap();
    let plan = base.join("plan.toml");
    std::fs::write(&plan, PLAN).unwrap();
    let dir = base.join("run");
    let (plan_s, dir_s) = (plan.to_str().unwrap(), dir.to_str().unwrap());
    let mut rng = polar_hil_mocks::faults::Dice::new(20_261_121);
    let mut kills = 0;
    let mut started = false;
    let deadline = Instant::now() + Duration::from_secs(600);
    let mut finished = false;
    while kills < 20 && Instant::now() < deadline {
        // A kill before the journal's first entry leaves nothing to resume: run again.
        let resumable = replay(&dir).is_ok_and(|r| r.run_started().is_some());
        let mut child = if started && resumable {
            spawn(&["resume", dir_s])
        } else {
            started = true;
            spawn(&["run", plan_s, "--simulate", "--out", dir_s])
        };
        // Kill after a random number of further frames (0..3) plus a random 0-60 ms, so that
        // kills land before, during and after a frame's write and journal line.
        let before = journal_frames(&dir);
        let more = rng.index(3);
        let extra_ms = rng.index(60) as u64;
        let t0 = Instant::now();
        loop {
            if let Some(_status) = child.try_wait().unwrap() {
                break;
            }
            if journal_frames(&dir) >= before + more || t0.elapsed() > Duration::from_secs(20) {
                std::thread::sleep(Duration::from_millis(extra_ms));
                let _ = child.kill();
                let _ = child.wait();
                kills += 1;
                break;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        if polar_engine::run::is_finished(&dir) {
            finished = true;
            // Start over in a new directory: at least 20 kills are asked.
            let _ = std::fs::remove_dir_all(&dir);
            started = false;
        }
    }
    assert!(kills >= 20, "only {kills} kills");
    if !started {
        return;
    }
    // Resume to the end (a crash may have left the run at any point).
    if !polar_engine::run::is_finished(&dir) {
        let resumable = replay(&dir).is_ok_and(|r| r.run_started().is_some());
        let args: Vec<&str> = if resumable {
            vec!["resume", dir_s]
        } else {
            vec!["run", plan_s, "--simulate", "--out", dir_s]
        };
        let out = Command::new(BIN).args(&args).output().unwrap();
        assert!(
            out.status.success(),
            "resume: {}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let _ = finished;
    let r = replay(&dir).unwrap();
    assert!(r.is_finished());
    let frames = r.frames();
    let n = frames.len() as u64;
    assert_eq!(
        frames.keys().copied().collect::<Vec<_>>(),
        (0..n).collect::<Vec<_>>()
    );
    let rejected = r.rejected_frames();
    let mut per_step = std::collections::BTreeMap::<u64, u32>::new();
    for f in frames.values().filter(|f| !rejected.contains(&f.index)) {
        *per_step.entry(f.step).or_default() += 1;
    }
    assert_eq!(per_step.len() as u64, PLANNED, "{per_step:?}");
    assert!(
        per_step.values().all(|&c| c == 1),
        "a step with two frames: {per_step:?}"
    );
    let store = RunStore::open(&dir).unwrap();
    for f in frames.values() {
        let px = store.read_frame(f.index).unwrap();
        assert_eq!(polar_engine::pixel_hash(&px), f.hash, "frame {}", f.index);
    }
    println!("{kills} kills; {n} frames stored for {PLANNED} planned steps, exact");
    let _ = std::fs::remove_dir_all(&base);
}

/// `plan check` forecasts without running; a bad plan names its field.
#[test]
fn plan_check_and_bad_plan() {
    let base = std::env::temp_dir().join(format!("polar-plancheck-{}", std::process::id()));
    std::fs::create_dir_all(&base).unwrap();
    let plan = base.join("plan.toml");
    std::fs::write(&plan, PLAN).unwrap();
    let out = Command::new(BIN)
        .args(["plan", "check", plan.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["forecast"]["frames"].as_u64(), Some(PLANNED));
    let bad = base.join("bad.toml");
    std::fs::write(&bad, PLAN.replace("repeats = 5", "repeats = -1")).unwrap();
    let out = Command::new(BIN)
        .args(["plan", "check", bad.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("capture.repeats"), "{e}");
    let _ = std::fs::remove_dir_all(&base);
}
