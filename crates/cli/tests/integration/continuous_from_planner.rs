//! A continuous plan's `from_planner`: resolved at load time to what `polarimeter plan
//! continuous` chooses for the same problem, valid, and run to the end on the simulated rig;
//! a plan that gives both the values and the table, or a bad table, is refused with the
//! field, the value and what is allowed.
#![allow(clippy::unwrap_used)]

use polar_cli::plan_continuous::{plan, PlanContinuousArgs};
use polar_cli::plan_load::{load_plan, load_plan_resolved};
use polar_cli::plan_problem::ProblemArgs;
use std::path::{Path, PathBuf};
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_polarimeter");

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A scratch directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "polarimeter-continuous-from-planner-{name}-{}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Writes a continuous plan with `continuous` as the section's body and `simulation` as the
/// simulation section's.
fn write_plan(dir: &Path, continuous: &str, simulation: &str) -> PathBuf {
    let path = dir.join("plan.toml");
    std::fs::write(
        &path,
        format!(
            "name = \"from planner\"\nkind = \"continuous\"\n[continuous]\n{continuous}\n\
             [simulation]\n{simulation}\n"
        ),
    )
    .unwrap();
    path
}

/// `plan continuous`'s arguments for the rooftop panels against the asphalt with the modern
/// CMOS camera (the simulated rig's scene and camera), the camera's default limits and the
/// simulated stage at 360 deg/s (2880 deg/s^2).
fn args(max_frames: usize) -> PlanContinuousArgs {
    PlanContinuousArgs {
        problem: ProblemArgs {
            scene: root().join("examples/rooftop_panels.toml"),
            camera: Some(root().join("examples/cameras/cmos_modern.toml")),
            rig: None,
            target: "panel".into(),
            background: "asphalt".into(),
            objective: "time-to-dolp-sigma".into(),
            dolp_sigma: 1e-3,
            max_speed_deg_per_s: Some(360.0),
            acceleration_deg_per_s2: Some(2880.0),
            max_frame_rate_hz: 200.0,
            readout_us: 0.0,
            min_exposure_us: 10.0,
            max_exposure_us: 1e6,
            saturation_sigma: 3.0,
            settle_s: 0.0,
            tolerance: 1e-3,
        },
        timing_sigma_us: 0.0,
        max_frames_per_half_turn: max_frames,
        json: true,
    }
}

/// The same problem two ways: a plan whose `from_planner` names the rooftop panels against
/// the asphalt with at most 24 frames per half turn, on the simulated stage at 360 deg/s
/// (which reaches its speed in 1/8 s: 2880 deg/s^2), and `plan continuous` with the same
/// limits (360 deg/s, 2880 deg/s^2, 200 Hz, no readout). The plan takes exactly the command's
/// frames per half turn, exposure and speed (0 tolerance: the same function on the same
/// inputs), the same binding limits are reported, and the resolved plan is valid and has no
/// table left.
#[test]
fn resolves_to_what_plan_continuous_chooses() {
    let dir = scratch("same");
    let path = write_plan(
        &dir,
        "half_turns = 4\nfrom_planner = { target = \"panel\", background = \"asphalt\", \
         max_frames_per_half_turn = 24 }",
        "stage_deg_per_s = 360",
    );
    let (resolved, _, chosen) = load_plan_resolved(&path).unwrap();
    let chosen = chosen.expect("the planner's choice");
    let c = resolved.continuous().unwrap();
    assert!(c.from_planner.is_none());
    resolved.validate().unwrap();
    c.validate().unwrap();
    let v = plan(&args(24)).unwrap();
    let cmd = &v["continuous"];
    assert_eq!(
        u64::from(c.frames_per_half_turn),
        cmd["frames_per_half_turn"].as_u64().unwrap()
    );
    assert_eq!(c.exposure_us, cmd["exposure_us"].as_f64().unwrap());
    assert_eq!(c.speed_deg_per_s, cmd["speed_deg_per_s"].as_f64().unwrap());
    let names = |b: &serde_json::Value| -> Vec<String> {
        b.as_array()
            .unwrap()
            .iter()
            .map(|x| x["limit"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(names(&chosen["binds"]), names(&cmd["binds"]));
    assert!(!names(&chosen["binds"]).is_empty());
    eprintln!(
        "resolved: {} frames per half turn, {} us, {} deg/s; binds {:?}",
        c.frames_per_half_turn,
        c.exposure_us,
        c.speed_deg_per_s,
        names(&chosen["binds"])
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `acquire run --simulate` on a short plan from the planner (2 half turns of a 32 x 24 frame,
/// at most 6 frames per half turn) finishes with both half turns accepted and N frames each,
/// N the planner's frames per half turn; `plan check` of the same file reports the choice.
#[test]
fn acquire_run_simulate_finishes() {
    let dir = scratch("run");
    let path = write_plan(
        &dir,
        "half_turns = 2\nfrom_planner = { target = \"panel\", background = \"asphalt\", \
         max_frames_per_half_turn = 6 }",
        "width = 32\nheight = 24\nstage_deg_per_s = 360",
    );
    let check = Command::new(BIN)
        .args(["plan", "check"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&check.stdout).unwrap();
    let n = v["continuous_from_planner"]["frames_per_half_turn"]
        .as_u64()
        .unwrap();
    assert!((3..=6).contains(&n), "{v}");
    assert!(String::from_utf8_lossy(&check.stderr).contains("binding:"));
    let out_dir = dir.join("run");
    let run = Command::new(BIN)
        .args(["acquire", "run", "--simulate", "--out"])
        .arg(&out_dir)
        .arg(&path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(
        run.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["state"], "done", "{v}");
    assert_eq!(v["summary"]["sets_accepted"], 2, "{v}");
    assert_eq!(v["summary"]["frames_accepted"].as_u64().unwrap(), 2 * n);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Refusals name the field, the value and what is allowed: a value the planner chooses given
/// beside the table; a missing value without one; an unknown objective (listing the two
/// allowed); a frame cap out of range; an unknown key of the table.
#[test]
fn bad_sections_are_named() {
    let dir = scratch("bad");
    let table = "from_planner = { target = \"panel\", background = \"asphalt\" }";
    let cases: Vec<(String, Vec<&str>)> = vec![
        (
            format!("exposure_us = 2000\n{table}"),
            vec![
                "continuous.exposure_us = 2000",
                "continuous.from_planner",
                "not both",
            ],
        ),
        (
            "frames_per_half_turn = 4\nexposure_us = 2000".into(),
            vec!["continuous.speed_deg_per_s is missing", "from_planner"],
        ),
        (
            "from_planner = { target = \"panel\", background = \"asphalt\", objective = \
             \"fastest\" }"
                .into(),
            vec![
                "continuous.from_planner.objective",
                "fastest",
                "time-to-dolp-sigma",
                "scr-per-second",
            ],
        ),
        (
            "from_planner = { target = \"panel\", background = \"asphalt\", \
             max_frames_per_half_turn = 2 }"
                .into(),
            vec![
                "continuous.from_planner.max_frames_per_half_turn = 2",
                "3..=360",
            ],
        ),
        (
            "from_planner = { target = \"panel\", background = \"asphalt\", frames = 8 }".into(),
            vec![
                "continuous.from_planner",
                "frames",
                "max_frames_per_half_turn",
            ],
        ),
        (
            "from_planner = { target = \"roof\", background = \"asphalt\" }".into(),
            vec!["continuous.from_planner.target", "\"roof\"", "panel, glass"],
        ),
    ];
    for (body, needles) in cases {
        let path = write_plan(&dir, &body, "");
        let e = load_plan(&path).expect_err(&body).to_string();
        for needle in needles {
            assert!(e.contains(needle), "{body}: {e} lacks {needle}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
