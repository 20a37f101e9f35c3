//! The plan kinds besides capture end to end through the `run` command's entry point
//! (`polarimeter run --rig RIG PLAN --out DIR`, `polar_cli::acquire::run_cmd`), each a small
//! plan from `tests/fixtures/`. Time-lapse, adaptive and continuous run on the devices of
//! `examples/rigs/sim.toml` (the native stage's simulator on a pseudo-terminal, the camera
//! rendering through its true angle). The two calibrations run on the same devices: the rig's
//! simulated camera finds the reference polarizer or the integrating sphere in front of it and
//! caps its own lens for darks, so they run unattended, and the rig file receives the result.

use polar_hil_tests::{repo_root, run_cli, scratch};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Runs `tests/fixtures/FIXTURE` with `rig` into `scratch_dir/run`; asserts it finishes done
/// (exit status 0) and that `check` finds every frame intact. Returns the command's output and
/// the store's attributes.
fn run_fixture(fixture: &str, rig: &Path, scratch_dir: &Path) -> (Value, Value) {
    let plan = repo_root().join("tests/fixtures").join(fixture);
    let run_dir = scratch_dir.join("run");
    let (out, code) =
        run_cli(&plan, rig, &run_dir, 0, false).unwrap_or_else(|e| panic!("{fixture}: {e}"));
    assert_eq!(
        (out["state"].as_str(), code),
        (Some("done"), 0),
        "{fixture}: {out}"
    );
    let check = polar_engine::check::check_run(&run_dir).expect("check");
    assert!(check.ok && check.finished, "{fixture}: {check:?}");
    let store = polar_engine::store::RunStore::open(&run_dir).expect("store");
    let attrs = store.attributes().expect("attributes");
    (out, Value::Object(attrs))
}

fn sim_rig() -> PathBuf {
    repo_root().join("examples/rigs/sim.toml")
}

/// `tests/fixtures/timelapse.toml` (3 sets of 0/60/120 deg, one every 2 s) on the simulated
/// rig's devices: exactly the plan's count of sets is accepted, each with its three frames
/// (counts, so exact), and no planner decision is recorded (a time-lapse repeats its angles).
#[test]
fn time_lapse_on_the_simulated_rig_file() {
    let dir = scratch("timelapse");
    let (out, attrs) = run_fixture("timelapse.toml", &sim_rig(), &dir);
    let s = &out["summary"];
    assert_eq!(s["sets_accepted"], 3, "the plan's count: {out}");
    assert_eq!(s["frames_accepted"], 9, "3 sets x 3 angles: {out}");
    assert_eq!(s["sets_rejected"], 0, "{out}");
    assert!(
        attrs["decisions"].as_array().is_none_or(Vec::is_empty),
        "{}",
        attrs["decisions"]
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `tests/fixtures/adaptive.toml` (start 0/60/120 deg, 9-frame budget, target the 1 %
/// anomalies as on hardware) on the simulated rig's devices: one decision per accepted set;
/// every re-acquire decision predicts an SCR at its new angles no lower than the last set's
/// under the same estimates (the planner maximises it; 1e-9 relative for rounding); the last
/// decision has spent the budget; and the run's final angles are those the previous decision
/// chose (1e-6 deg: the same numbers through JSON).
#[test]
fn adaptive_on_the_simulated_rig_file() {
    let dir = scratch("adaptive");
    let (out, attrs) = run_fixture("adaptive.toml", &sim_rig(), &dir);
    let decisions = attrs["decisions"].as_array().cloned().unwrap_or_default();
    let sets = out["summary"]["sets_accepted"].as_u64().expect("sets");
    assert!(sets >= 1, "{out}");
    assert_eq!(decisions.len() as u64, sets, "one decision per set: {out}");
    for d in &decisions {
        let reason = d["reason"].as_str().unwrap_or_default();
        let (last, next) = (
            d["scr_last_set"].as_f64().expect("scr_last_set"),
            d["scr_next"].as_f64().expect("scr_next"),
        );
        if reason.starts_with("re-acquire") {
            assert!(next >= last * (1.0 - 1e-9), "{d}");
        }
    }
    let last = decisions.last().expect("a decision");
    assert_eq!(last["frames_used"], 9, "the budget: {last}");
    if decisions.len() >= 2 {
        let chosen = &decisions[decisions.len() - 2]["next_angles_deg"];
        let final_deg = &out["summary"]["final_angles_deg"];
        let (a, b) = (
            chosen.as_array().expect("angles"),
            final_deg.as_array().expect("final angles"),
        );
        assert_eq!(a.len(), b.len(), "{chosen} {final_deg}");
        for (x, y) in a.iter().zip(b) {
            let d = x.as_f64().unwrap_or(f64::NAN) - y.as_f64().unwrap_or(f64::NAN);
            assert!(d.abs() < 1e-6, "{chosen} against {final_deg}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `tests/fixtures/calibrate_analyzer.toml` (12 steps through a reference polarizer) on the
/// rig file's devices, `--rig` a copy of `examples/rigs/sim.toml` (and its camera file) in a
/// scratch folder: the measured zero offset is within 0.1 deg of the simulated analyzer's true
/// offset, 0 (the simulated stage settles within its encoder count and half its backlash, a
/// few hundredths of a degree), the extinction ratio is above 100 (the simulated polarizer
/// pair's is higher); `analyzer.r1.toml` is written beside the copy with the corrected zero
/// offset, and the copy, read again, points at it with that value.
#[test]
fn calibrate_analyzer_on_the_simulated_rig_file() {
    let dir = scratch("calibrate-analyzer");
    let root = repo_root();
    std::fs::create_dir_all(dir.join("rigs")).expect("rigs");
    std::fs::create_dir_all(dir.join("cameras")).expect("cameras");
    let rig_copy = dir.join("rigs/sim.toml");
    std::fs::copy(sim_rig(), &rig_copy).expect("copy the rig");
    std::fs::copy(
        root.join("examples/cameras/cmos_modern.toml"),
        dir.join("cameras/cmos_modern.toml"),
    )
    .expect("copy the camera file");
    let (out, attrs) = run_fixture("calibrate_analyzer.toml", &rig_copy, &dir);
    let cal = &attrs["calibration"]["analyzer"];
    let measured = cal["zero_offset_deg"].as_f64().expect("zero offset");
    assert!(measured.abs() <= 0.1, "{cal}");
    assert!(
        cal["extinction_ratio"].as_f64().expect("ER") > 100.0,
        "{cal}"
    );
    let written = &out["rig_written"];
    let file = dir.join("rigs/analyzer.r1.toml");
    assert_eq!(
        written["analyzer_file"],
        file.display().to_string(),
        "{out}"
    );
    assert!(file.is_file(), "{}", file.display());
    let zero = written["zero_offset_deg"].as_f64().expect("written zero");
    assert!(
        (zero + measured).abs() < 1e-12,
        "run at 0: the new offset is -measured: {out}"
    );
    let again = polar_rig::Rig::load(&rig_copy).unwrap_or_else(|e| panic!("{e}"));
    let values = again.analyzer.expect("the rig's analyzer");
    assert_eq!(values.revision, Some(1));
    assert!((values.zero_offset_deg - zero).abs() < 1e-12, "{values:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `tests/fixtures/calibrate_noise.toml` (8 exposures past saturation, a dark and a flat pair
/// each) on the simulated rig, with `--rig` a copy of `examples/rigs/sim.toml` (and its camera
/// file) in a scratch folder: the fitted system gain K is within 4 of its own standard
/// uncertainties and 3 % of the simulated camera file's gain (the simulated rig's default
/// camera, `polar_rig::simulated::DEFAULT_CAMERA`); the measured camera is written beside the
/// copy's camera file as `cmos_modern.r1.toml` with that gain (exactly: it is the fit's), the
/// base file is kept unchanged, and the copy, read again, points at the new revision.
#[test]
fn calibrate_noise_on_the_simulated_rig_file() {
    let dir = scratch("calibrate-noise");
    let root = repo_root();
    std::fs::create_dir_all(dir.join("rigs")).expect("rigs");
    std::fs::create_dir_all(dir.join("cameras")).expect("cameras");
    let rig_copy = dir.join("rigs/sim.toml");
    std::fs::copy(sim_rig(), &rig_copy).expect("copy the rig");
    let base = root.join("examples/cameras/cmos_modern.toml");
    std::fs::copy(&base, dir.join("cameras/cmos_modern.toml")).expect("copy the camera file");
    let (out, attrs) = run_fixture("calibrate_noise.toml", &rig_copy, &dir);
    let revision = dir.join("cameras/cmos_modern.r1.toml");
    let same = |a: &Path, b: &Path| a.canonicalize().ok() == b.canonicalize().ok();
    let reported = out["rig_written"]["camera_file"].as_str().expect("written");
    assert!(same(Path::new(reported), &revision), "{out}");
    let written = polar_model::sensor::Camera::from_toml_str(
        &std::fs::read_to_string(&revision).expect("the new revision"),
    )
    .expect("a camera file");
    let fitted = attrs["calibration"]["noise"]["k_dn_per_e"]["value"]
        .as_f64()
        .expect("K");
    assert_eq!(written.gain_dn_per_e, fitted);
    assert_eq!(
        std::fs::read(dir.join("cameras/cmos_modern.toml")).expect("base"),
        std::fs::read(&base).expect("example"),
        "the base camera file is kept"
    );
    let again = polar_rig::Rig::load(&rig_copy).unwrap_or_else(|e| panic!("{e}"));
    let pointed = again.camera_file.expect("the rig's camera file");
    assert!(same(&pointed, &revision), "{}", pointed.display());
    let k = &attrs["calibration"]["noise"]["k_dn_per_e"];
    let (value, sigma) = (
        k["value"].as_f64().expect("K"),
        k["uncertainty"].as_f64().expect("sigma K"),
    );
    let camera = polar_model::sensor::Camera::from_toml_str(polar_rig::simulated::DEFAULT_CAMERA)
        .expect("the default camera");
    let truth = camera.gain_dn_per_e;
    println!("calibrate-noise: K = {value} +- {sigma} DN/e, camera file {truth} DN/e");
    assert!(
        (value - truth).abs() <= 4.0 * sigma,
        "K {value} +- {sigma} against {truth}"
    );
    assert!(
        (value - truth).abs() <= 0.03 * truth,
        "K {value} against {truth}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `tests/fixtures/continuous.toml` (4 frames per half turn at 360 deg/s, 5 half turns) on the
/// devices of `examples/rigs/sim.toml`, through the hardware path: the native stage's
/// simulator on a pseudo-terminal spins through the real serial driver and its position-compare
/// output is wired to the rendering camera's trigger line, as a cable would wire a real pair.
/// Every half turn is accepted with its four frames (counts, so exact); every frame's span is
/// an encoder-triggered one that starts at its trigger angle within 2 encoder counts (0.005
/// deg: the pulse latches the count at the armed position) and sweeps speed x exposure
/// (0.36 deg) within one count; the store holds one product set per half turn.
#[test]
fn continuous_on_the_simulated_rig_file() {
    let dir = scratch("continuous");
    let (out, _attrs) = run_fixture("continuous.toml", &sim_rig(), &dir);
    let s = &out["summary"];
    assert_eq!(s["sets_accepted"], 5, "the plan's half turns: {out}");
    assert_eq!(s["frames_accepted"], 20, "5 half turns x 4 frames: {out}");
    let store = polar_engine::store::RunStore::open(&dir.join("run")).expect("store");
    let records = store.read_frame_metadata().expect("frame metadata");
    assert_eq!(records.len(), 20, "no frame taken twice: {out}");
    let count_deg = 360.0 / 144_000.0;
    let span_deg = 360.0 * 1000e-6;
    for r in &records {
        assert_eq!(r.angle_source, polar_engine::AngleSource::EncoderTrigger);
        let d = (r.angle_start_deg - r.commanded_angle_deg).rem_euclid(180.0);
        assert!(
            d.min(180.0 - d) <= 2.0 * count_deg,
            "frame {}: span starts at {} deg, its trigger angle is {}",
            r.index,
            r.angle_start_deg,
            r.commanded_angle_deg
        );
        let swept = r.angle_end_deg - r.angle_start_deg;
        assert!(
            (swept - span_deg).abs() <= count_deg,
            "frame {}: swept {swept} deg",
            r.index
        );
    }
    assert_eq!(store.product_slots().expect("slots").len(), 5);
    let _ = std::fs::remove_dir_all(&dir);
}
