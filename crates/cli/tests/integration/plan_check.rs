//! One validation path: every plan that `acquire run --simulate` refuses before acquiring, `plan
//! check` refuses too, with the same error line, and neither leaves a run behind.
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

const CAPTURE: &str = r#"
name = "parity"
kind = "capture"
[capture]
angles_deg = [0, 60, 120]
exposure_us = [300]
repeats = 1
[simulation]
width = 40
height = 30
seed = 2
"#;

const ADAPTIVE: &str = r#"
name = "parity adaptive"
kind = "adaptive"
[adaptive]
initial_angles_deg = [0, 60, 120]
channels = 3
exposure_us = 300
frame_budget = 9
target = TARGET
[simulation]
width = 40
height = 30
seed = 2
"#;

/// A command's error: its stderr from the first `error: ` line on (log lines before it
/// differ between commands).
fn error_text(out: &std::process::Output) -> String {
    let text = String::from_utf8_lossy(&out.stderr);
    text.find("error: ")
        .map(|i| text[i..].trim_end().to_string())
        .unwrap_or_default()
}

fn check_parity(dir: &Path, name: &str, text: &str, expect: &str) {
    let plan = dir.join(format!("{name}.toml"));
    std::fs::write(&plan, text).unwrap();
    let check = Command::new(BIN)
        .args(["plan", "check", plan.to_str().unwrap()])
        .output()
        .unwrap();
    let out_dir = dir.join(format!("{name}-run"));
    let run = Command::new(BIN)
        .args([
            "acquire",
            "run",
            plan.to_str().unwrap(),
            "--simulate",
            "--out",
        ])
        .arg(&out_dir)
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    let (c, r) = (error_text(&check), error_text(&run));
    assert!(!check.status.success(), "{name}: plan check passed");
    assert!(!run.status.success(), "{name}: run passed");
    assert_eq!(c, r, "{name}: plan check and run disagree");
    assert!(c.contains(expect), "{name}: {c:?} should name {expect:?}");
    assert!(
        !out_dir.join("journal.jsonl").exists() && !out_dir.join("run.zarr").exists(),
        "{name}: the refused run left a run behind"
    );
}

#[test]
fn plan_check_refuses_what_run_refuses() {
    let dir = std::env::temp_dir().join(format!("polar-plan-check-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cases = [
        (
            "unknown-knob",
            format!("{CAPTURE}[simulation.stage_faults]\nno_such_knob = 0.1\n"),
            "no_such_knob",
        ),
        (
            "rate-above-one",
            format!("{CAPTURE}[simulation.stage_faults]\ndrop_reply = 2.0\n"),
            "drop_reply",
        ),
        (
            "negative-rate",
            format!("{CAPTURE}[simulation.camera_faults]\ndrop_frame = -0.5\n"),
            "drop_frame",
        ),
        (
            "no-such-material",
            ADAPTIVE.replace("TARGET", r#"{ material = "unobtainium" }"#),
            "adaptive.target.material",
        ),
        (
            "rect-outside",
            ADAPTIVE.replace("TARGET", "{ rect = [10, 10, 60, 20] }"),
            "adaptive.target.rect",
        ),
    ];
    for (name, text, expect) in &cases {
        check_parity(&dir, name, text, expect);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
