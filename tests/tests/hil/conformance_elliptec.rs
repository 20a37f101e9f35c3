//! Public client libraries against the simulated devices: every simulated model (ELL14, ELL18,
//! ELL6, ELL9, FW102C, FW212C) is served on its own real pseudo-terminal, as a real device on
//! a USB-serial adapter, and `scripts/conformance/elliptec_clients.py` drives each through
//! pylablib, thorlabs_elliptec and roesel's elliptec, as those libraries' own examples do.
//! Every operation a client offers must pass or be a client difference whose reason the script
//! states and checks; none may fail. At the end each device must truly be where the last
//! client left it (the simulator's ground truth, not the client's readback).
//!
//! The clients live in a Python venv that `scripts/test.sh` creates (`target/py-venv`, pinned in
//! `scripts/requirements.txt`) and names in `POLARIMETER_PYTHON`. Without it
//! this test fails, unless `POLARIMETER_SKIP_PYTHON=1`. The script takes about 40 s of real
//! time (homing and moves at the devices' speeds; the six devices run in parallel). The table
//! it prints is the one in `docs/DEVICES-conformance.md`; it is also written to
//! `target/client-conformance.md`.

use polar_hil_mocks::elliptec::{ElliptecConfig, ElliptecDevice};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::fw102c::{Fw102cConfig, Fw102cDevice};
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::{Simulator, Truth};
use polar_hil_tests::conformance::{client_python, clients_available};
use polar_hil_tests::repo_root;
use std::f64::consts::TAU;
use std::process::Command;

/// One row of the script's results.
#[derive(Debug)]
struct Row {
    client: String,
    model: String,
    operation: String,
    status: String,
    detail: String,
}

fn parse_rows(text: &str) -> Vec<Row> {
    text.lines()
        .filter(|l| !l.is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split('\t').collect();
            assert!(f.len() >= 5, "a results row has 5 fields: {l:?}");
            Row {
                client: f[0].to_string(),
                model: f[1].to_string(),
                operation: f[2].to_string(),
                status: f[3].to_string(),
                detail: f[4].to_string(),
            }
        })
        .collect()
}

/// Every model through every client that supports it: no FAILED row; every operation of the
/// checklist (identify, home, absolute moves back to back, relative moves, velocity, status,
/// jog, home offset, motor info and frequencies, address change, slots, wheel settings, a bad
/// command refused) passed by at least one client on each model that has it; each client
/// difference has a reason; the devices end where the clients left them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn public_clients_drive_every_simulated_model() {
    let python = client_python();
    let imports = "pylablib.devices.Thorlabs, thorlabs_elliptec, elliptec, serial";
    if !clients_available(&python, imports) {
        return;
    }
    let dir = std::env::temp_dir().join(format!("polar-clients-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    // Default devices: no faults, the healthy module.
    let healthy = FaultProfile::default();
    let sims: Vec<(&str, Box<dyn Simulator>)> = vec![
        (
            "ell14",
            Box::new(ElliptecDevice::new(ElliptecConfig::ell14(), healthy, 1)),
        ),
        (
            "ell18",
            Box::new(ElliptecDevice::new(ElliptecConfig::ell18(), healthy, 2)),
        ),
        (
            "ell6",
            Box::new(ElliptecDevice::new(ElliptecConfig::ell6(), healthy, 3)),
        ),
        (
            "ell9",
            Box::new(ElliptecDevice::new(ElliptecConfig::ell9(), healthy, 4)),
        ),
        (
            "fw102c",
            Box::new(Fw102cDevice::new(Fw102cConfig::fw102c(), healthy, 5)),
        ),
        (
            "fw212c",
            Box::new(Fw102cDevice::new(Fw102cConfig::fw212c(), healthy, 6)),
        ),
    ];
    let mut servers = Vec::new();
    let mut args = Vec::new();
    for (model, sim) in sims {
        let link = dir.join(model);
        let server = SimServer::pty(sim, healthy, 7, &link).expect("a pty");
        args.push(format!("{model}={}", link.display()));
        servers.push((model, server));
    }
    let results = dir.join("results.tsv");
    let script = repo_root().join("scripts/conformance/elliptec_clients.py");
    let t0 = std::time::Instant::now();
    let output = tokio::task::spawn_blocking(move || {
        Command::new(&python)
            .arg(&script)
            .args(&args)
            .arg("--results")
            .arg(&results)
            .output()
            .expect("run the conformance script")
    })
    .await
    .expect("the script's thread");
    let elapsed = t0.elapsed();
    let table = String::from_utf8_lossy(&output.stdout).into_owned();
    let log = String::from_utf8_lossy(&output.stderr).into_owned();
    println!("{table}\n{log}\nscript time {elapsed:.1?}");
    let _ = std::fs::write(repo_root().join("target/client-conformance.md"), &table);
    let rows = parse_rows(&std::fs::read_to_string(dir.join("results.tsv")).unwrap_or_default());
    let failed: Vec<&Row> = rows.iter().filter(|r| r.status == "FAILED").collect();
    assert!(failed.is_empty(), "failed: {failed:#?}\n{log}");
    assert!(output.status.success(), "the script failed:\n{log}");
    for r in &rows {
        let known = ["passed", "client difference", "not offered"];
        assert!(known.contains(&r.status.as_str()), "{r:?}");
        if r.status != "passed" {
            assert!(
                !r.detail.is_empty(),
                "a {} without its reason: {r:?}",
                r.status
            );
        }
    }
    // The checklist: each operation passed by at least one client on each model that has it.
    let passed = |model: &str, op: &str| {
        rows.iter()
            .any(|r| r.model == model && r.operation == op && r.status == "passed")
    };
    let elliptec = [
        "identify",
        "home",
        "absolute moves back to back",
        "relative moves",
        "raw-count moves",
        "velocity",
        "status",
        "jog",
        "home offset",
        "motor info",
        "motor frequencies",
        "frequency search",
        "address change",
        "save settings",
    ];
    for model in ["ell14", "ell18", "ell6", "ell9"] {
        for op in elliptec {
            assert!(passed(model, op), "{model}: {op} passed by no client");
        }
        let mut clients: Vec<&str> = rows
            .iter()
            .filter(|r| r.model == model && r.operation == "identify")
            .map(|r| r.client.as_str())
            .collect();
        clients.sort_unstable();
        let all = ["elliptec", "pylablib", "thorlabs_elliptec"];
        assert_eq!(clients, all, "{model}: every client ran");
    }
    for model in ["ell6", "ell9"] {
        assert!(passed(model, "slots"), "{model}: slots");
    }
    for model in ["fw102c", "fw212c"] {
        for op in [
            "identify",
            "slots",
            "position count",
            "speed mode",
            "trigger mode",
            "sensor mode",
            "save settings",
            "bad command",
        ] {
            assert!(passed(model, op), "{model}: {op} passed by no client");
        }
    }
    // The ground truth where the last client left each device. A rotator's output lags the
    // motor by half its 10-count backlash, and the client truncates 123 deg to a whole count:
    // 6 counts. Sliders and wheels rest exactly in a slot.
    for (model, server) in &servers {
        let truth = server.truth();
        match *model {
            "ell14" | "ell18" => {
                let pulses = if *model == "ell14" {
                    143_360.0
                } else {
                    262_144.0
                };
                let Truth::Angle { output_rad, moving } = truth else {
                    panic!("{model}: {truth:?}")
                };
                let want = 123f64.to_radians();
                let off = ((output_rad - want + TAU / 2.0).rem_euclid(TAU)) - TAU / 2.0;
                assert!(
                    !moving && off.abs() <= 6.0 / pulses * TAU,
                    "{model}: {truth:?}"
                );
            }
            "ell6" | "ell9" => assert_eq!(truth, Truth::Slot { slot: Some(1) }, "{model}"),
            _ => assert_eq!(
                truth,
                Truth::Slot { slot: Some(2) },
                "{model} at position 3"
            ),
        }
        assert!(
            server.describe().ends_with("address 0") || !model.starts_with("ell"),
            "{model}: address restored: {}",
            server.describe()
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
