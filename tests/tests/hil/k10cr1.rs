//! A capture on `examples/rigs/sim_k10cr1.toml` through the command's own entry point: the APT
//! dialect's simulator of the K10CR1 on a pseudo-terminal, driven through the APT driver, the
//! camera rendering through the mount's true angle.

use polar_engine::store::RunStore;
use polar_hil_tests::{repo_root, run_cli, scratch, stokes_within_two_sigma};

/// `polarimeter run --rig examples/rigs/sim_k10cr1.toml` with one set of four angles
/// (`tests/fixtures/capture_k10cr1.toml`): the run finishes done (exit status 0), `check`
/// finds every frame intact, the store records the apt dialect, and the set's Stokes products
/// agree with the rendered scene's truth within their predicted sigma: an unbiased Gaussian
/// estimate puts 95.45 % of its values within 2 sigma; 93-97.5 % is asked, as of the same
/// capture through the APT driver in `crates/drivers/tests/apt_capture.rs` (the 230 400 values
/// give a sampling spread of 0.05 %; Poisson skew and the mount's backlash add a little).
#[test]
fn capture_on_the_simulated_k10cr1_rig_file() {
    capture_on_a_rig_file(
        "sim_k10cr1.toml",
        "tests/fixtures/capture_k10cr1.toml",
        "apt",
        "k10cr1",
    );
}

/// The capture of `PLAN` (a path from the repository's root) on `examples/rigs/RIG` through
/// the command's entry point, judged as [`capture_on_the_simulated_k10cr1_rig_file`] says; the
/// store must record the stage's `dialect` and `model`.
pub(crate) fn capture_on_a_rig_file(rig: &str, plan: &str, dialect: &str, model: &str) {
    let root = repo_root();
    let rig_path = root.join("examples/rigs").join(rig);
    let plan_path = root.join(plan);
    let run_dir = scratch(model).join("run");
    let (out, code) =
        run_cli(&plan_path, &rig_path, &run_dir, 0, false).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((out["state"].as_str(), code), (Some("done"), 0), "{out}");
    assert_eq!(
        out["summary"]["frames_accepted"], 6,
        "4 lights and 2 darks: {out}"
    );
    let check = polar_engine::check::check_run(&run_dir).expect("check");
    assert!(check.ok && check.finished, "{check:?}");
    let store = RunStore::open(&run_dir).expect("store");
    let devices = &store.attributes().expect("attributes")["devices"];
    assert_eq!(devices["stage"]["dialect"], dialect);
    assert_eq!(devices["stage"]["model"], model);
    let rig = polar_rig::Rig::load(&rig_path).unwrap_or_else(|e| panic!("{e}"));
    let camera_file = rig.camera_file.expect("a camera file");
    let share = stokes_within_two_sigma(&store, &camera_file, 250.0);
    println!(
        "{model} rig: products within 2 sigma of the truth: {:.2} %",
        100.0 * share
    );
    assert!((0.93..=0.975).contains(&share), "{:.2} %", 100.0 * share);
    let _ = std::fs::remove_dir_all(run_dir.parent().expect("scratch"));
}
