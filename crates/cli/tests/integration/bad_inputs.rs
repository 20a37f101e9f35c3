//! Bad inputs tried as a new user would (issue 35): each is refused with one error line that
//! names the flag or field (as the user spelled it), the value (shortened when long) and the
//! allowed range, or, in a batch, fails its own line only.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

fn polarimeter(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

/// A command reading `input` on stdin.
fn with_stdin(args: &[&str], input: &[u8]) -> Output {
    let mut child = Command::new(BIN)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = child.stdin.take().unwrap();
    stdin.write_all(input).unwrap();
    drop(stdin);
    child.wait_with_output().unwrap()
}

fn records(out: &Output) -> Vec<serde_json::Value> {
    String::from_utf8(out.stdout.clone())
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The error line of a refused command: exit status 2, one line on stderr, nothing on stdout.
fn refused(out: &Output) -> String {
    let err = String::from_utf8_lossy(&out.stderr).trim_end().to_string();
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.starts_with("error: "), "{err}");
    assert!(
        out.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    err
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("polar-bad-inputs-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A non-UTF-8 line fails that line only: the lines before and after it are evaluated, and
/// its error record names its line number.
#[test]
fn batch_non_utf8_line_fails_that_line_only() {
    let mut input = b"{\"angles_deg\":[0,45,90]}\n".to_vec();
    input.extend_from_slice(b"{\"angles_deg\":[0,\xff\xfe45,90]}\n");
    input.extend_from_slice(b"{\"angles_deg\":[0,45,90,135]}\n");
    let out = with_stdin(&["model", "polarimeter", "--batch", "-"], &input);
    assert_eq!(out.status.code(), Some(1), "{:?}", out);
    let v = records(&out);
    assert_eq!(v.len(), 3, "{v:?}");
    assert!((v[0]["ewv"].as_f64().unwrap() - 10.0).abs() < 1e-9);
    assert_eq!(v[1]["line"], 2);
    let e = v[1]["error"].as_str().unwrap();
    assert!(e.contains("UTF-8") && e.contains("line 2"), "{e}");
    assert!((v[2]["ewv"].as_f64().unwrap() - 5.0).abs() < 1e-9);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("1 of 3 lines failed"), "{stderr}");
}

/// Text after the JSON object is refused, naming the line; the next line still evaluates.
#[test]
fn batch_trailing_text_after_the_object_is_refused() {
    let input = b"{\"angles_deg\":[0,45,90]} garbage\n{\"angles_deg\":[0,45,90]}{}\n{\"angles_deg\":[0,45,90]}  \n";
    let out = with_stdin(&["model", "polarimeter", "--batch", "-"], input);
    assert_eq!(out.status.code(), Some(1));
    let v = records(&out);
    assert_eq!(v.len(), 3, "{v:?}");
    for (i, r) in v[..2].iter().enumerate() {
        assert_eq!(r["line"], i + 1);
        let e = r["error"].as_str().unwrap();
        assert!(
            e.contains("trailing")
                && e.contains(&format!("line {}", i + 1))
                && e.contains("allowed one JSON object"),
            "{e}"
        );
    }
    // Trailing white space is not text.
    assert!(
        (v[2]["ewv"].as_f64().unwrap() - 10.0).abs() < 1e-9,
        "{}",
        v[2]
    );
}

/// `--batch` with flags that only one evaluation would use is refused, naming the flags.
#[test]
fn batch_with_evaluation_flags_is_refused() {
    let dir = temp_dir("batch-flags");
    let file = dir.join("in.jsonl");
    std::fs::write(&file, "{\"n\": 1.5, \"theta_i_deg\": 60}\n").unwrap();
    let f = file.to_str().unwrap();
    for (args, flags) in [
        (
            vec!["model", "fresnel", "--batch", f, "--n", "1.5"],
            vec!["--n"],
        ),
        (
            vec![
                "model",
                "fresnel",
                "--batch",
                f,
                "--theta-i-deg",
                "10",
                "--k",
                "0",
            ],
            vec!["--theta-i-deg", "--k"],
        ),
        (
            vec!["model", "polarimeter", "--offset-deg", "5", "--batch", f],
            vec!["--offset-deg"],
        ),
    ] {
        let err = refused(&polarimeter(&args));
        assert!(err.contains("--batch"), "{err}");
        for flag in flags {
            assert!(err.contains(flag), "{args:?}: {err} lacks {flag}");
        }
    }
    // --batch alone still works (defaults are not flags given).
    let ok = polarimeter(&["model", "fresnel", "--batch", f]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Starts a simulated stage; returns the process and its port.
fn sim_stage(dialect: &str, model: &str) -> (std::process::Child, String) {
    let mut sim = Command::new(BIN)
        .args([
            "simulate",
            "stage",
            "--dialect",
            dialect,
            "--model",
            model,
            "--seed",
            "7",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(sim.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let v: serde_json::Value = serde_json::from_str(&line).unwrap();
    (sim, v["port"].as_str().unwrap().to_string())
}

/// `devices stage move --angle-deg 1e300` (or any non-finite or absurd angle) is refused before the
/// stage moves, naming the flag, the value compactly and the range; the stage stays put.
#[test]
fn stage_move_to_an_absurd_angle_is_refused_before_moving() {
    let (mut sim, port) = sim_stage("elliptec", "ell14");
    let stage = |args: &[&str]| {
        let mut all = vec![
            "devices",
            "stage",
            "--port",
            &port,
            "--dialect",
            "elliptec",
            "--json",
        ];
        all.extend_from_slice(args);
        polarimeter(&all)
    };
    let moved = stage(&["move", "--angle-deg", "20"]);
    assert!(
        moved.status.success(),
        "{}",
        String::from_utf8_lossy(&moved.stderr)
    );
    for bad in ["1e300", "-1e300", "NaN", "inf", "361", "-400"] {
        let err = refused(&stage(&["move", "--angle-deg", bad]));
        assert!(
            err.contains("--angle-deg") && err.contains("allowed") && err.contains("[-360, 360]"),
            "{bad}: {err}"
        );
        assert!(err.len() < 200, "{bad}: {err}");
    }
    let err = refused(&stage(&["move", "--angle-deg", "1e300"]));
    assert!(err.contains("1e300"), "{err}");
    // Nothing moved: the Elliptec keeps its position between connections.
    let pos = stage(&["position"]);
    assert!(pos.status.success());
    let v: serde_json::Value = serde_json::from_slice(&pos.stdout).unwrap();
    let p = v["position_deg"].as_f64().unwrap();
    assert!((p - 20.0).abs() < 0.1, "{v}");
    let _ = sim.kill();
    let _ = sim.wait();
}

/// `model dolp-stats` with a DoLP above 1 (or no light) and `model stokes` whose intensities
/// are all negative are refused naming the flag, the value and the allowed range; a slightly
/// negative intensity (noise after dark subtraction) is a warning.
#[test]
fn physically_impossible_model_inputs_are_refused() {
    let err = refused(&polarimeter(&[
        "model",
        "dolp-stats",
        "--angles-deg",
        "0,45,90",
        "--stokes",
        "1,2,0",
        "--sigma-i",
        "0.01",
    ]));
    assert!(
        err.contains("--stokes")
            && err.contains("DoLP")
            && err.contains("2")
            && err.contains("<= 1"),
        "{err}"
    );
    let err = refused(&polarimeter(&[
        "model",
        "dolp-stats",
        "--angles-deg",
        "0,45,90",
        "--stokes",
        "-1,0,0",
        "--sigma-i",
        "0.01",
    ]));
    assert!(err.contains("--stokes") && err.contains("S0 > 0"), "{err}");
    let err = refused(&polarimeter(&[
        "model",
        "stokes",
        "--angles-deg",
        "0,45,90",
        "--intensities=-1,-2,-3",
    ]));
    assert!(
        err.contains("--intensities") && err.contains("-1") && err.contains(">= 0"),
        "{err}"
    );
    // One slightly negative intensity: evaluated, with a warning naming it.
    let out = polarimeter(&[
        "model",
        "stokes",
        "--angles-deg",
        "0,45,90,135",
        "--intensities=1,0.5,-0.01,0.5",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let warn = String::from_utf8_lossy(&out.stderr);
    assert!(
        warn.starts_with("warning: ") && warn.contains("intensities[2]") && warn.contains("-0.01"),
        "{warn}"
    );
}

const PLAN: &str = r#"
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

/// `--zero-offset-deg NaN` is refused under `--simulate` as on hardware, before a run starts.
#[test]
fn zero_offset_nan_is_refused_under_simulate() {
    let dir = temp_dir("zero-offset");
    let plan = dir.join("p.toml");
    std::fs::write(&plan, format!("name = \"z\"\n{PLAN}")).unwrap();
    for bad in ["NaN", "inf", "1e300"] {
        let out_dir = dir.join(format!("run-{bad}"));
        let out = Command::new(BIN)
            .args([
                "acquire",
                "run",
                plan.to_str().unwrap(),
                "--simulate",
                "--zero-offset-deg",
                bad,
                "--out",
            ])
            .arg(&out_dir)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let err = refused(&out);
        assert!(
            err.contains("--zero-offset-deg") && err.contains(bad) && err.contains("[-360, 360]"),
            "{err}"
        );
        assert!(
            !out_dir.exists(),
            "a refused run left {}",
            out_dir.display()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A plan without a name (or a blank one) is named by its file's stem.
#[test]
fn a_plan_without_a_name_is_named_by_its_file() {
    let dir = temp_dir("noname");
    for (file, text) in [
        ("rooftop-test.toml", PLAN.to_string()),
        ("blank.toml", format!("name = \"  \"\n{PLAN}")),
    ] {
        let plan = dir.join(file);
        std::fs::write(&plan, text).unwrap();
        let out = polarimeter(&["plan", "check", plan.to_str().unwrap()]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let stem = Path::new(file).file_stem().unwrap().to_str().unwrap();
        assert_eq!(v["plan"], stem, "{v}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Errors never echo megabytes of input, print numbers compactly, name the user's flag and
/// the file the value came from.
#[test]
fn errors_are_short_compact_and_name_the_flag_and_file() {
    // One argument may hold 128 KiB at most; standard input a megabyte.
    let long_arg = "x".repeat(100_000);
    let long = "x".repeat(1_000_000);
    // A long flag value: cut to 80 characters with an ellipsis and its length.
    let err = refused(&polarimeter(&[
        "model",
        "fresnel",
        "--n",
        &long_arg,
        "--theta-i-deg",
        "60",
    ]));
    assert!(err.len() < 400, "{} characters: {}", err.len(), &err[..400]);
    assert!(
        err.contains("--n") && err.contains('…') && err.contains("100000 characters"),
        "{err}"
    );
    let err = refused(&polarimeter(&[
        "model",
        "sun",
        "--time",
        &long_arg,
        "--lat-deg",
        "0",
        "--lon-deg",
        "0",
    ]));
    assert!(err.len() < 400, "{} characters", err.len());
    assert!(
        err.contains("--time") && err.contains("100000 characters"),
        "{err}"
    );
    // Numbers compactly; the flag as the user typed it.
    let err = refused(&polarimeter(&[
        "model",
        "fresnel",
        "--n",
        "1.5",
        "--theta-i-deg",
        "1e300",
    ]));
    assert!(
        err.contains("--theta-i-deg = 1e300") && err.contains("[0, 90]"),
        "{err}"
    );
    // A batch line with a megabyte string, a megabyte key and a huge number.
    let input = format!(
        "{{\"n\": \"{long}\", \"theta_i_deg\": 60}}\n{{\"{long}\": 1}}\n{{\"n\": 1e300, \"theta_i_deg\": 60}}\n"
    );
    let out = with_stdin(&["model", "fresnel", "--batch", "-"], input.as_bytes());
    assert_eq!(out.status.code(), Some(1));
    let v = records(&out);
    assert_eq!(v.len(), 3);
    for r in &v {
        let e = r["error"].as_str().unwrap();
        assert!(e.len() < 400, "line {}: {} characters", r["line"], e.len());
    }
    let e = |i: usize| v[i]["error"].as_str().unwrap().to_string();
    assert!(
        e(0).contains("n:") && e(0).contains("1000000 characters"),
        "{}",
        e(0)
    );
    assert!(
        e(1).contains("1000000 characters") && e(1).contains("theta_i_deg"),
        "{}",
        e(1)
    );
    assert!(
        e(2).contains("n = 1e300") && e(2).contains("(0, 100]"),
        "{}",
        e(2)
    );
    // A plan's bad value: the file named, the number compact.
    let dir = temp_dir("plan-error");
    let plan = dir.join("huge.toml");
    std::fs::write(&plan, PLAN.replace("[300]", "[1e300]")).unwrap();
    let err = refused(&polarimeter(&["plan", "check", plan.to_str().unwrap()]));
    assert!(
        err.contains(plan.to_str().unwrap())
            && err.contains("capture.exposure_us[0] = 1e300")
            && err.contains("allowed"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 42's bad-input matrix, each as a user meets it: a plan listing 1.5 million angles
/// is refused in a line, not echoed (9 MB before); a TOML error in a plan names the line and
/// column; `--out` naming a file says so (it blamed the simulated stage); a bad camera file
/// named by a plan names that file beside its line and column; `--monte-carlo 1e9` is read as
/// a count and refused by its flag and range (it named the library's `n_samples`); an inverted
/// band says the edges are inverted (it said 500 was outside [300, 1100]).
#[test]
fn issue_42_bad_inputs_name_what_is_wrong() {
    let dir = temp_dir("issue-42");
    let huge: Vec<String> = (0..1_500_000).map(|i| (i % 180).to_string()).collect();
    let plan = dir.join("million.toml");
    let text = PLAN.replace("[0, 60, 120]", &format!("[{}]", huge.join(",")));
    std::fs::write(&plan, &text).unwrap();
    let err = refused(&polarimeter(&["plan", "check", plan.to_str().unwrap()]));
    assert!(err.len() < 400, "{} characters", err.len());
    assert!(
        err.contains("capture.angles_deg") && err.contains("1500000 angles"),
        "{err}"
    );
    std::fs::write(&plan, text.replace("]\nexposure_us", ",x]\nexposure_us")).unwrap();
    let err = refused(&polarimeter(&["plan", "check", plan.to_str().unwrap()]));
    assert!(err.len() < 400, "{} characters", err.len());
    assert!(err.contains("line 4, column"), "{err}");

    let good = dir.join("capture.toml");
    std::fs::write(&good, PLAN).unwrap();
    let file = dir.join("a-file");
    std::fs::write(&file, "not a run").unwrap();
    let err = refused(&polarimeter(&[
        "acquire",
        "run",
        good.to_str().unwrap(),
        "--simulate",
        "--out",
        file.to_str().unwrap(),
    ]));
    assert!(
        err.contains("--out") && err.contains("is a file") && !err.contains("stage"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "not a run");

    std::fs::write(dir.join("bad_camera.toml"), "pixel_pitch_um = \"three\"\n").unwrap();
    let with_camera = dir.join("with_camera.toml");
    std::fs::write(
        &with_camera,
        PLAN.replace("[simulation]", "[simulation]\ncamera = \"bad_camera.toml\""),
    )
    .unwrap();
    let out = polarimeter(&["plan", "check", with_camera.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("bad_camera.toml") && err.contains("line 1, column 18"),
        "{err}"
    );

    let dolp = |n: &str| {
        polarimeter(&[
            "model",
            "dolp-stats",
            "--angles-deg",
            "0,60,120",
            "--stokes",
            "1000,0,0",
            "--sigma-i",
            "10",
            "--monte-carlo",
            n,
        ])
    };
    let err = refused(&dolp("1e9"));
    assert!(
        err.contains("--monte-carlo")
            && err.contains("0 to 50000000")
            && !err.contains("n_samples"),
        "{err}"
    );
    let ok = dolp("1e3");
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&ok.stdout).unwrap();
    assert_eq!(v["mc"]["samples"], 1000, "{v}");

    let err = refused(&polarimeter(&[
        "model",
        "sensor",
        "--camera",
        &format!(
            "{}/../../examples/cameras/cmos_modern.toml",
            env!("CARGO_MANIFEST_DIR")
        ),
        "--angles-deg",
        "0,45,90,135",
        "--radiance-mean",
        "1,0.2,0.1",
        "--t-int-ms",
        "5",
        "--band-nm",
        "700,450",
    ]));
    assert!(
        err.contains("band") && err.contains("below the upper") && !err.contains("[300, 1100]"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
