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
use polar_hil_tests::conformance::{client_python, clients_available, run_script};

/// Where the script parks every mount, degrees.
const PARK_DEG: f64 = 123.0;

/// The PRM1Z8 and the K10CR1 through every client: no FAILED row; identify, enable, home,
/// absolute and relative moves, position, velocity parameters and status bits passed by
/// thorlabs-apt-device on the PRM1Z8 (its KDC101 class) and on the K10CR1; every other status
/// has its reason; both mounts end at 123 deg within 3 counts plus half the backlash.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn public_apt_clients_drive_the_simulated_mounts() {
    let python = client_python();
    if !clients_available(
        &python,
        "thorlabs_apt_device, pylablib.devices.Thorlabs, serial",
    ) {
        return;
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
    let run = tokio::task::spawn_blocking({
        let dir = dir.clone();
        move || run_script(&python, "apt_clients.py", &args, &dir, "apt-conformance.md")
    })
    .await
    .expect("the script's thread");
    run.check_rows(&["passed", "client difference", "not offered"]);
    let rows = &run.rows;
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
