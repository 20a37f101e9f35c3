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
use polar_hil_tests::repo_root;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Where the script parks the stage, degrees.
const PARK_DEG: f64 = 123.0;
/// The truth is within one microstep of the park angle (the counter is exact and the simulated
/// stage has no backlash): 1 / 20 480 deg.
const PARK_TOL_DEG: f64 = 1.0 / 20_480.0;

fn client_python() -> PathBuf {
    std::env::var_os("POLARIMETER_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("target/py-venv/bin/python"))
}

fn has_client(python: &Path) -> bool {
    Command::new(python)
        .args(["-c", "import pylablib.devices.Standa, serial"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

/// Every operation passed (engine type, calibration, home, position reference, absolute and
/// relative moves, status, jog both ways with a soft stop, the move parameters, the park); the
/// stage truly at 123 deg and still.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pylablib_drives_the_simulated_standa() {
    let python = client_python();
    if !has_client(&python) {
        if std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1") {
            println!(
                "skipped: {} cannot import pylablib.devices.Standa",
                python.display()
            );
            return;
        }
        panic!(
            "{} cannot import pylablib.devices.Standa: run `bash scripts/test.sh`, which creates \
             the venv, or point POLARIMETER_PYTHON at a python that has it; set \
             POLARIMETER_SKIP_PYTHON=1 to skip this test",
            python.display()
        );
    }
    let dir = std::env::temp_dir().join(format!("polar-standa-clients-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let healthy = FaultProfile::default();
    let link = dir.join("standa");
    let device = StandaDevice::new(StandaConfig::mpr16().at_speed(90.0), healthy, 41);
    let server = SimServer::pty(device, healthy, 7, &link).expect("a pty");
    let results = dir.join("results.tsv");
    let script = repo_root().join("scripts/conformance/standa_clients.py");
    let output = tokio::task::spawn_blocking({
        let results = results.clone();
        let link = link.clone();
        move || {
            Command::new("timeout")
                .arg("300")
                .arg(&python)
                .arg(&script)
                .arg(&link)
                .arg("--results")
                .arg(&results)
                .output()
                .expect("run the conformance script")
        }
    })
    .await
    .expect("the script's thread");
    let table = String::from_utf8_lossy(&output.stdout).into_owned();
    let log = String::from_utf8_lossy(&output.stderr).into_owned();
    println!("{table}\n{log}");
    let _ = std::fs::write(repo_root().join("target/standa-conformance.md"), &table);
    let text = std::fs::read_to_string(&results).unwrap_or_default();
    let rows: Vec<Vec<&str>> = text
        .lines()
        .filter(|l| !l.is_empty())
        .map(|l| l.split('\t').collect())
        .collect();
    assert!(!rows.is_empty(), "no results:\n{log}");
    for r in &rows {
        assert!(r.len() >= 5, "a row has 5 fields: {r:?}");
        assert_eq!(r[3], "passed", "{r:?}\n{log}");
    }
    assert!(output.status.success(), "the script failed:\n{log}");
    assert!(rows.len() >= 11, "{} operations, want 11", rows.len());
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
