//! The crash campaign (`polarimeter bench crash`): runs of every plan kind on the simulated
//! devices, interrupted at random moments by SIGKILL (during the first run and during the
//! resumes) and by Ctrl-C (a pause: the process leaves the run for `acquire resume`), then resumed
//! until they finish. Each finished dataset is then checked by [`polar_engine::check`] and,
//! given a Python with zarr, xarray and xxhash, from the outside by `scripts/check_run.py`
//! (every array readable by zarr-python, frames as planned, no duplicate frame or product
//! slot, every frame's metadata present, hashes equal to the journal's); with that Python,
//! every interrupted dataset is also checked from the outside before its resume (xarray
//! opens both groups whole; the store mirrors the journal's first frames).

use crate::commands::CommandError;
use polar_engine::journal::replay;
use polar_hil_mocks::faults::Dice;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The plan kinds of the campaign: (name, plan text). Small frames, so a run takes about a
/// second and a kill can land anywhere in it.
pub const PLANS: [(&str, &str); 7] = [
    (
        "capture",
        r#"name = "crash capture"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [300]
repeats = 4
darks_before = 2
darks_after = 1
[simulation]
width = 48
height = 36
seed = 9
"#,
    ),
    (
        "exposures",
        r#"name = "crash exposures"
kind = "capture"
[capture]
angles_deg = [0, 60, 120]
exposure_us = [150, 300]
repeats = 2
darks_before = 1
[simulation]
width = 48
height = 36
seed = 10
"#,
    ),
    (
        "time-lapse",
        r#"name = "crash time-lapse"
kind = "time-lapse"
[time-lapse]
angles_deg = [0, 60, 120]
exposure_us = 250
interval_s = 0.4
count = 4
[simulation]
width = 48
height = 36
seed = 11
"#,
    ),
    (
        "adaptive",
        r#"name = "crash adaptive"
kind = "adaptive"
[adaptive]
initial_angles_deg = [0, 60, 120]
channels = 3
exposure_us = 250
frame_budget = 12
darks = 1
target = { material = "panel" }
min_separation_deg = 30
[simulation]
width = 64
height = 48
seed = 12
"#,
    ),
    (
        "calibrate-noise",
        r#"name = "crash noise calibration"
kind = "calibrate-noise"
[calibrate-noise]
exposure_us = [100, 1000, 3000, 10000, 30000]
pairs = 1
[simulation]
width = 48
height = 36
seed = 13
"#,
    ),
    (
        "calibrate-analyzer",
        r#"name = "crash analyzer calibration"
kind = "calibrate-analyzer"
[calibrate-analyzer]
reference_angle_deg = 30
steps = 12
exposure_us = 3000
darks = 1
[simulation]
width = 48
height = 36
seed = 14
"#,
    ),
    (
        "continuous",
        r#"name = "crash continuous"
kind = "continuous"
[continuous]
frames_per_half_turn = 4
exposure_us = 300
speed_deg_per_s = 360
half_turns = 8
[simulation]
width = 48
height = 36
seed = 15
"#,
    ),
];

/// What the campaign is asked to do.
#[derive(Debug, Clone)]
pub struct CrashConfig {
    /// SIGKILLs per plan kind, at least.
    pub kills_per_kind: u32,
    /// The campaign's seed (kill moments, Ctrl-C or SIGKILL).
    pub seed: u64,
    /// The `polarimeter` binary to run.
    pub binary: PathBuf,
    /// Where the run directories go (kept: the evidence).
    pub base: PathBuf,
    /// A Python with zarr, xarray and xxhash, and the outside checker, if any.
    pub outside: Option<(String, PathBuf)>,
    /// Plan kinds to run (names of [`PLANS`]); empty: all.
    pub kinds: Vec<String>,
}

/// One plan kind's tally.
#[derive(Debug, Clone, Default, Serialize)]
pub struct KindTally {
    /// The plan kind.
    pub kind: String,
    /// Datasets run to the end.
    pub datasets: u32,
    /// SIGKILLs during a first run.
    pub kills_in_run: u32,
    /// SIGKILLs during a resume.
    pub kills_in_resume: u32,
    /// Ctrl-C pauses (then resumed).
    pub pauses: u32,
    /// Interrupted datasets checked from the outside (zarr-python and xarray open them
    /// whole) before their resume.
    pub checked_before_resume: u32,
    /// Of those, how many passed.
    pub passed_before_resume: u32,
    /// What the outside check found in the others (dataset and finding).
    pub before_resume_findings: Vec<String>,
    /// Datasets that passed every check.
    pub passed: u32,
    /// What failed (dataset and finding).
    pub failures: Vec<String>,
}

/// The campaign's result.
#[derive(Debug, Clone, Serialize)]
pub struct CrashReport {
    /// Per plan kind.
    pub kinds: Vec<KindTally>,
    /// SIGKILLs in all.
    pub kills: u32,
    /// Datasets in all.
    pub datasets: u32,
    /// Interrupted datasets checked from the outside before their resume, in all.
    pub checked_before_resume: u32,
    /// Of those, how many passed.
    pub passed_before_resume: u32,
    /// Datasets that passed every check.
    pub passed: u32,
    /// The outside checker ran (zarr-python, xarray).
    pub outside_checked: bool,
    /// Wall time, s.
    pub elapsed_s: f64,
}

fn spawn(binary: &Path, args: &[&str]) -> Result<Child, CommandError> {
    Command::new(binary)
        .args(args)
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| CommandError::layer(format!("{}: ", binary.display()), e))
}

/// How a process of the campaign ended.
enum Ended {
    /// It exited by itself (finished, left paused, or failed).
    Exited,
    /// It was killed.
    Killed,
    /// It was sent Ctrl-C.
    Interrupted,
}

/// Waits for `child` until `after`, then kills it (SIGKILL) or sends Ctrl-C (SIGINT).
fn interrupt_after(child: &mut Child, after: Duration, ctrl_c: bool) -> Ended {
    let t0 = Instant::now();
    loop {
        if let Ok(Some(_)) = child.try_wait() {
            return Ended::Exited;
        }
        if t0.elapsed() >= after {
            if ctrl_c {
                let _ = Command::new("kill")
                    .args(["-INT", &child.id().to_string()])
                    .status();
                // A paused run leaves at once (no terminal); a stuck one is killed.
                let deadline = Instant::now() + Duration::from_secs(30);
                while Instant::now() < deadline {
                    if let Ok(Some(_)) = child.try_wait() {
                        return Ended::Interrupted;
                    }
                    std::thread::sleep(Duration::from_millis(5));
                }
            }
            let _ = child.kill();
            let _ = child.wait();
            return Ended::Killed;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Waits for `child` to exit, at most `limit`.
fn wait_for(child: &mut Child, limit: Duration) -> Result<bool, CommandError> {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        match child.try_wait() {
            Ok(Some(s)) => return Ok(s.success()),
            Ok(None) => std::thread::sleep(Duration::from_millis(5)),
            Err(e) => return Err(CommandError::of(e)),
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    Ok(false)
}

/// Runs one dataset of `plan` in `dir` to the end with kills and pauses as `dice` says;
/// adds to `tally`. Returns a finding if the run could not be finished.
fn one_dataset(
    cfg: &CrashConfig,
    plan: &Path,
    dir: &Path,
    kills_left: &mut u32,
    dice: &mut Dice,
    tally: &mut KindTally,
) -> Result<Option<String>, CommandError> {
    let (plan_s, dir_s) = (plan.to_string_lossy(), dir.to_string_lossy());
    let mut first = true;
    for attempt in 0..40 {
        let started = replay(dir).is_ok_and(|r| r.run_started().is_some());
        let args: Vec<&str> = if started {
            vec!["acquire", "resume", &dir_s]
        } else {
            vec!["acquire", "run", &plan_s, "--simulate", "--out", &dir_s]
        };
        let mut child = spawn(&cfg.binary, &args)?;
        // Interrupt most processes while work remains; let the last ones finish.
        if *kills_left > 0 && attempt < 30 && dice.chance(0.8) {
            let after = Duration::from_millis(30 + dice.index(1200) as u64);
            let ctrl_c = dice.chance(0.2);
            let ended = interrupt_after(&mut child, after, ctrl_c);
            match ended {
                Ended::Exited => {}
                Ended::Interrupted => tally.pauses += 1,
                Ended::Killed => {
                    *kills_left -= 1;
                    if first {
                        tally.kills_in_run += 1;
                    } else {
                        tally.kills_in_resume += 1;
                    }
                }
            }
            if !matches!(ended, Ended::Exited) {
                check_interrupted(cfg, dir, tally);
            }
        } else if !wait_for(&mut child, Duration::from_secs(120))? && !paused(dir) {
            return Ok(Some(format!(
                "{}: `{}` failed or took over 120 s",
                dir.display(),
                args.join(" ")
            )));
        }
        first = false;
        if polar_engine::run::is_finished(dir) {
            return Ok(None);
        }
    }
    Ok(Some(format!(
        "{}: not finished after 40 processes",
        dir.display()
    )))
}

/// The journal's last word is a pause (the process left the run for `acquire resume`).
fn paused(dir: &Path) -> bool {
    replay(dir).is_ok_and(|r| {
        matches!(
            r.entries.last(),
            Some(polar_engine::journal::Entry::Paused { .. })
        )
    })
}

/// Checks an interrupted dataset from the outside, before its resume (if a Python is
/// configured and the run has started): zarr-python reads every array and xarray opens both
/// groups whole.
fn check_interrupted(cfg: &CrashConfig, dir: &Path, tally: &mut KindTally) {
    let Some((py, script)) = &cfg.outside else {
        return;
    };
    if !replay(dir).is_ok_and(|r| r.run_started().is_some()) {
        return;
    }
    tally.checked_before_resume += 1;
    match Command::new(py).arg(script).arg(dir).output() {
        Ok(o) if o.status.success() => tally.passed_before_resume += 1,
        Ok(o) => tally.before_resume_findings.push(format!(
            "{} (interrupted, before its resume): check_run.py: {}{}",
            dir.display(),
            String::from_utf8_lossy(&o.stdout).trim(),
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Err(e) => tally.failures.push(format!("{}: {py}: {e}", dir.display())),
    }
}

/// Checks a finished dataset: the engine's check and, if configured, the outside one.
fn check_dataset(cfg: &CrashConfig, dir: &Path) -> Vec<String> {
    let mut problems = Vec::new();
    match polar_engine::check::check_run(dir) {
        Ok(c) if c.ok => {}
        Ok(c) => problems.push(format!(
            "{}: check: {:?} {:?}",
            dir.display(),
            c.damaged,
            c.findings
        )),
        Err(e) => problems.push(format!("{}: check: {e}", dir.display())),
    }
    if let Some((py, script)) = &cfg.outside {
        match Command::new(py)
            .arg(script)
            .arg(dir)
            .arg("--finished")
            .output()
        {
            Ok(o) if o.status.success() => {}
            Ok(o) => problems.push(format!(
                "{}: check_run.py: {}{}",
                dir.display(),
                String::from_utf8_lossy(&o.stdout).trim(),
                String::from_utf8_lossy(&o.stderr).trim()
            )),
            Err(e) => problems.push(format!("{}: {py}: {e}", dir.display())),
        }
    }
    problems
}

/// Runs the campaign.
pub fn campaign(cfg: &CrashConfig) -> Result<CrashReport, CommandError> {
    let t0 = Instant::now();
    std::fs::create_dir_all(&cfg.base)
        .map_err(|e| CommandError::layer(format!("{}: ", cfg.base.display()), e))?;
    let mut dice = Dice::new(cfg.seed);
    let mut kinds = Vec::new();
    for (kind, text) in PLANS {
        if !cfg.kinds.is_empty() && !cfg.kinds.iter().any(|k| k == kind) {
            continue;
        }
        let plan = cfg.base.join(format!("{kind}.toml"));
        std::fs::write(&plan, text)
            .map_err(|e| CommandError::layer(format!("{}: ", plan.display()), e))?;
        let mut tally = KindTally {
            kind: kind.to_string(),
            ..KindTally::default()
        };
        let mut kills_left = cfg.kills_per_kind;
        let mut n = 0;
        while kills_left > 0 || n == 0 {
            let dir = cfg.base.join(format!("{kind}-{n}"));
            if dir.exists() {
                return Err(CommandError::failed(format!(
                    "{} exists: give the campaign an empty --out directory",
                    dir.display()
                )));
            }
            n += 1;
            let before = kills_left;
            match one_dataset(cfg, &plan, &dir, &mut kills_left, &mut dice, &mut tally)? {
                Some(failure) => tally.failures.push(failure),
                None => {
                    tally.datasets += 1;
                    let problems = check_dataset(cfg, &dir);
                    if problems.is_empty() {
                        tally.passed += 1;
                    }
                    tally.failures.extend(problems);
                }
            }
            if kills_left == before && n > 3 * cfg.kills_per_kind as usize + 3 {
                break;
            }
        }
        kinds.push(tally);
    }
    Ok(CrashReport {
        kills: kinds
            .iter()
            .map(|k| k.kills_in_run + k.kills_in_resume)
            .sum(),
        datasets: kinds.iter().map(|k| k.datasets).sum(),
        checked_before_resume: kinds.iter().map(|k| k.checked_before_resume).sum(),
        passed_before_resume: kinds.iter().map(|k| k.passed_before_resume).sum(),
        passed: kinds.iter().map(|k| k.passed).sum(),
        outside_checked: cfg.outside.is_some(),
        elapsed_s: t0.elapsed().as_secs_f64(),
        kinds,
    })
}

/// The report as a Markdown table (one row per plan kind) and the failures.
pub fn markdown(r: &CrashReport) -> String {
    let mut s = String::from(
        "| plan kind | datasets | SIGKILL in run | SIGKILL in resume | Ctrl-C pauses | \
         opened whole before resume | passed |\n\
         |---|---:|---:|---:|---:|---:|---:|\n",
    );
    for k in &r.kinds {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {}/{} | {} |\n",
            k.kind,
            k.datasets,
            k.kills_in_run,
            k.kills_in_resume,
            k.pauses,
            k.passed_before_resume,
            k.checked_before_resume,
            k.passed
        ));
    }
    s.push_str(&format!(
        "\n{} SIGKILLs, {} of {} datasets passed every check ({}), {:.0} s.\n",
        r.kills,
        r.passed,
        r.datasets,
        if r.outside_checked {
            "engine check and zarr-python/xarray"
        } else {
            "engine check only: no Python given"
        },
        r.elapsed_s
    ));
    for k in &r.kinds {
        for f in &k.failures {
            s.push_str(&format!("- {}: {f}\n", k.kind));
        }
        for f in &k.before_resume_findings {
            s.push_str(&format!("- {} (repaired by its resume): {f}\n", k.kind));
        }
    }
    s
}
