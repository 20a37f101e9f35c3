//! Public APT client libraries against the simulated Thorlabs APT mounts: the PRM1Z8 on its
//! KDC101 and the K10CR1, each served on its own real pseudo-terminal, driven by
//! `scripts/conformance/apt_clients.py` through thorlabs-apt-device (its `KDC101` class, its
//! generic `APTDevice_Motor` for the K10CR1, and its protocol layer for `HW_REQ_INFO`) and
//! pylablib's `KinesisMotor`. Every operation a client offers must pass or be a client
//! difference whose reason the script states and checks; none may fail. At the end each mount
//! must truly be where the client parked it (the simulator's ground truth).
//!
//! The clients live in the venv of `scripts/test.sh` (`target/py-venv`, pinned in
//! `scripts/requirements.txt`), named by `POLARIMETER_PYTHON`. Without it this test fails,
//! unless `POLARIMETER_SKIP_PYTHON=1`. The mounts run at 90 deg/s (faster than the real ones)
//! so that the script takes about 30 s of real time. The table it prints is the one in
//! `docs/DEVICES-conformance.md`; it is also written to `target/apt-conformance.md`.

use polar_hil_mocks::apt::{AptDevice, AptSimConfig};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use polar_hil_tests::repo_root;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Where the script parks every mount, degrees.
const PARK_DEG: f64 = 123.0;

fn client_python() -> PathBuf {
    std::env::var_os("POLARIMETER_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("target/py-venv/bin/python"))
}

fn has_clients(python: &Path) -> bool {
    Command::new(python)
        .args([
            "-c",
            "import thorlabs_apt_device, pylablib.devices.Thorlabs, serial",
        ])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

/// The PRM1Z8 and the K10CR1 through every client: no FAILED row; identify, enable, home,
/// absolute and relative moves, position, velocity parameters and status bits passed by
/// thorlabs-apt-device on the PRM1Z8 (its KDC101 class) and on the K10CR1; every other status
/// has its reason; both mounts end at 123 deg within 3 counts plus half the backlash.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn public_apt_clients_drive_the_simulated_mounts() {
    let python = client_python();
    if !has_clients(&python) {
        if std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1") {
            println!(
                "skipped: {} cannot import thorlabs_apt_device",
                python.display()
            );
            return;
        }
        panic!(
            "{} cannot import thorlabs_apt_device and pylablib: run `bash scripts/test.sh`, \
             which creates the venv, or point POLARIMETER_PYTHON at a python that has them; \
             set POLARIMETER_SKIP_PYTHON=1 to skip this test",
            python.display()
        );
    }
    let dir = std::env::temp_dir().join(format!("polar-apt-clients-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let healthy = FaultProfile::default();
    let mut servers = Vec::new();
    let mut args = Vec::new();
    for (k, (name, config)) in [
        ("prm1z8", AptSimConfig::prm1z8().fast(90.0)),
        ("k10cr1", AptSimConfig::k10cr1().fast(90.0)),
    ]
    .into_iter()
    .enumerate()
    {
        let link = dir.join(name);
        let device = AptDevice::new(config, healthy, 20 + k as u64);
        let server = SimServer::pty(device, healthy, 7, &link).expect("a pty");
        args.push(format!("{name}={}", link.display()));
        servers.push((name, config, server));
    }
    let results = dir.join("results.tsv");
    let script = repo_root().join("scripts/conformance/apt_clients.py");
    let output = tokio::task::spawn_blocking({
        let results = results.clone();
        move || {
            Command::new(&python)
                .arg(&script)
                .args(&args)
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
    let _ = std::fs::write(repo_root().join("target/apt-conformance.md"), &table);
    let text = std::fs::read_to_string(&results).unwrap_or_default();
    let rows: Vec<Vec<&str>> = text
        .lines()
        .filter(|l| !l.is_empty())
        .map(|l| l.split('\t').collect())
        .collect();
    assert!(!rows.is_empty(), "no results:\n{log}");
    for r in &rows {
        assert!(r.len() >= 5, "a row has 5 fields: {r:?}");
        assert_ne!(r[3], "FAILED", "{r:?}\n{log}");
        assert!(
            ["passed", "client difference", "not offered"].contains(&r[3]),
            "{r:?}"
        );
        if r[3] != "passed" {
            assert!(!r[4].is_empty(), "a {} without its reason: {r:?}", r[3]);
        }
    }
    assert!(output.status.success(), "the script failed:\n{log}");
    let passed = |client: &str, model: &str, op: &str| {
        rows.iter()
            .any(|r| r[0] == client && r[1] == model && r[2] == op && r[3] == "passed")
    };
    for (client, model) in [
        ("thorlabs-apt-device KDC101", "prm1z8"),
        ("thorlabs-apt-device APTDevice_Motor", "k10cr1"),
    ] {
        for op in [
            "identify (MOD_IDENTIFY)",
            "enable / disable channel",
            "home",
            "move absolute",
            "move relative",
            "position",
            "velocity parameters",
            "status bits",
            "jog",
            "move at velocity + stop",
            "home parameters",
            "backlash (general move parameters)",
        ] {
            assert!(
                passed(client, model, op),
                "{client} {model}: {op} not passed"
            );
        }
        assert!(passed(
            "thorlabs-apt-device (protocol)",
            model,
            "identify (HW_REQ_INFO)"
        ));
    }
    for (name, config, server) in servers {
        let Truth::Angle { output_rad, moving } = server.truth() else {
            panic!("{name}: not a rotator")
        };
        let off = (output_rad.to_degrees() - PARK_DEG + 180.0).rem_euclid(360.0) - 180.0;
        let slack = (3.0 + 0.5 * config.backlash_counts) / config.counts_per_deg;
        assert!(
            !moving && off.abs() <= slack,
            "{name}: {off} deg from the park angle"
        );
        server.shutdown().await;
    }
}
