//! pylablib's `Standa8SMC` against the simulated Standa 8SMC5-USB with the 8MPR16-1, on a real
//! pseudo-terminal, driven by `scripts/conformance/standa_clients.py`. Every operation the client
//! offers must pass. At the end the stage must truly be where the client parked it (the simulator's
//! ground truth).
//!
//! pylablib lives in the venv of `scripts/test.sh` (`target/py-venv`, pinned in
//! `scripts/requirements.txt`), named by `POLARIMETER_PYTHON`. Without it this test fails,
//! unless `POLARIMETER_SKIP_PYTHON=1`. The stage turns and homes at 90 deg/s (the real
//! 8MPR16-1 homes at 1.25 deg/s); the table the script prints is the one in
//! `docs/DEVICES-conformance.md`, also written to `target/standa-conformance.md`.

use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use polar_hil_mocks::standa::{StandaConfig, StandaDevice};
use polar_hil_tests::conformance::{client_python, clients_available, run_script};

/// Where the script parks the stage, degrees.
const PARK_DEG: f64 = 123.0;
/// The truth is within one microstep of the park angle (the counter is exact and the simulated
/// stage has no backlash): 1 / 20 480 deg.
const PARK_TOL_DEG: f64 = 1.0 / 20_480.0;

/// Every operation passed (engine type, calibration, home, position reference, absolute and
/// relative moves, status, jog both ways with a soft stop, the move parameters, the park); the
/// stage truly at 123 deg and still.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pylablib_drives_the_simulated_standa() {
    let python = client_python();
    if !clients_available(&python, "pylablib.devices.Standa, serial") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("polar-standa-clients-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let healthy = FaultProfile::default();
    let link = dir.join("standa");
    let device = StandaDevice::new(StandaConfig::mpr16().at_speed(90.0), healthy, 41);
    let server = SimServer::pty(device, healthy, 7, &link).expect("a pty");
    let args = vec![link.display().to_string()];
    let run = tokio::task::spawn_blocking({
        let dir = dir.clone();
        move || {
            run_script(
                &python,
                "standa_clients.py",
                &args,
                &dir,
                "standa-conformance.md",
            )
        }
    })
    .await
    .expect("the script's thread");
    run.check_rows(&["passed"]);
    assert!(
        run.rows.len() >= 11,
        "{} operations, want 11",
        run.rows.len()
    );
    let Truth::Angle { output_rad, moving } = server.truth() else {
        panic!("not a rotator")
    };
    let off = (output_rad.to_degrees() - PARK_DEG + 180.0).rem_euclid(360.0) - 180.0;
    assert!(
        !moving && off.abs() <= PARK_TOL_DEG,
        "{off} deg from the park angle"
    );
    server.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Standa's libximc through its own virtual controller (`xi-emu`) and through the simulated
/// controller's pseudo-terminal (`xi-com`), the same command sequence on both, driven by
/// `scripts/conformance/standa_ximc.py`: every call libximc makes succeeds on the simulator
/// wherever it succeeds on the emulator (no row `INCOMPATIBLE`, exit status 0), every
/// differing field has a named reason (no `UNEXPLAINED`: the emulator's generic profile, its
/// motion without acceleration, the status bits it does not keep), and the motion the two
/// agree on is there: the position after `move` and after `movr`, the engine type, the
/// settings written and read back. The simulator is the stage at Standa's real profile (the
/// script raises FastHome so homing takes seconds); the table is in
/// `docs/DEVICES-conformance.md`, also written to `target/standa-ximc.md`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn libximc_emulator_and_simulator_agree() {
    let python = client_python();
    if !clients_available(&python, "libximc") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("polar-standa-ximc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let healthy = FaultProfile::default();
    let link = dir.join("standa");
    let device = StandaDevice::new(StandaConfig::mpr16(), healthy, 43);
    let server = SimServer::pty(device, healthy, 9, &link).expect("a pty");
    let args = vec![link.display().to_string()];
    let run = tokio::task::spawn_blocking({
        let dir = dir.clone();
        move || run_script(&python, "standa_ximc.py", &args, &dir, "standa-ximc.md")
    })
    .await
    .expect("the script's thread");
    assert!(run.success, "the script failed:\n{}", run.log);
    assert!(
        run.rows.len() >= 40,
        "{} rows:\n{}",
        run.rows.len(),
        run.log
    );
    for r in &run.rows {
        assert_eq!(
            r.len(),
            5,
            "operation, verdict, emulator, simulator, reasons: {r:?}"
        );
        assert!(matches!(r[1].as_str(), "same" | "different"), "{r:?}");
        assert!(!r[4].contains("UNEXPLAINED"), "{r:?}");
        if r[1] == "different" {
            assert!(!r[4].is_empty(), "a difference without its reason: {r:?}");
        }
    }
    let same = |op: &str| {
        run.rows
            .iter()
            .any(|r| r[0].starts_with(op) && r[1] == "same")
    };
    for op in [
        "get_entype_settings",
        "get_position after move",
        "get_position after movr",
    ] {
        assert!(same(op), "{op} differs: {:?}", run.rows);
    }
    server.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}
