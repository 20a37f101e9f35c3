//! Crash safety through the binary: the crash campaign (`polarimeter bench crash`) kills
//! (SIGKILL) and pauses (Ctrl-C) runs of every plan kind at random moments, in first runs and
//! in resumes, resumes them to the end, and checks every dataset with the engine's check and
//! from the outside with zarr-python and xarray (`scripts/check_run.py`). Also: `plan check`
//! forecasts without running.
#![allow(clippy::unwrap_used)]

use polar_cli::bench_crash::{campaign, markdown, CrashConfig, PLANS};
use std::path::{Path, PathBuf};
use std::process::Command;

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

/// The Python with zarr, xarray and xxhash (`POLARIMETER_PYTHON`, else the venv of
/// `scripts/test.sh`), or `None` with `POLARIMETER_SKIP_PYTHON=1`.
fn python() -> Option<String> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/py-venv/bin/python");
    let py = std::env::var("POLARIMETER_PYTHON").unwrap_or_else(|_| venv.display().to_string());
    let ok = Command::new(&py)
        .args(["-c", "import zarr, xarray, xxhash"])
        .output()
        .is_ok_and(|o| o.status.success());
    if ok {
        return Some(py);
    }
    assert!(
        std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1"),
        "{py} cannot import zarr, xarray and xxhash: run `bash scripts/test.sh` (it makes the \
         venv), or set POLARIMETER_SKIP_PYTHON=1"
    );
    None
}

/// 9 SIGKILLs per plan kind (63 in all, over 7 kinds), plus Ctrl-C pauses: every dataset
/// opens whole from the outside after each interruption, before its resume, finishes and
/// passes every check. The full campaign is `polarimeter bench crash`.
#[test]
fn crash_campaign_over_every_plan_kind() {
    let base = std::env::temp_dir().join(format!("polar-crash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&base);
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../scripts/check_run.py");
    let cfg = CrashConfig {
        kills_per_kind: 9,
        seed: 20_261_127,
        binary: PathBuf::from(BIN),
        base: base.clone(),
        outside: python().map(|p| (p, script)),
        kinds: Vec::new(),
    };
    let r = campaign(&cfg).unwrap();
    let text = markdown(&r);
    println!("{text}");
    assert_eq!(r.kinds.len(), PLANS.len());
    assert!(r.kills >= 60, "only {} kills\n{text}", r.kills);
    for k in &r.kinds {
        assert!(k.kills_in_run > 0 && k.kills_in_resume > 0, "{text}");
        assert!(k.failures.is_empty(), "{text}");
        assert_eq!(k.passed, k.datasets, "{text}");
        assert!(k.datasets > 0, "{text}");
        assert!(
            cfg.outside.is_none() || k.checked_before_resume > 0,
            "{text}"
        );
    }
    // With Python, the interrupted runs (the kills and pauses that left a started run) open
    // whole in xarray before their resume. A kill inside the few milliseconds in which a
    // mirror renames its files into place (at most one frames mirror a second, one products
    // write a set) can leave two lengths, which the resume repairs: at most 1 in 10 of the
    // interruptions may (measured: 2 of 68 in one campaign; before the mirror moved to set
    // boundaries, every kill between two pauses).
    let (checked, passed): (u32, u32) = r.kinds.iter().fold((0, 0), |(c, p), k| {
        (c + k.checked_before_resume, p + k.passed_before_resume)
    });
    if cfg.outside.is_some() {
        assert!(
            10 * (checked - passed) <= checked,
            "{passed} of {checked}\n{text}"
        );
    }
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
