//! Public Newport clients against the simulated SMC100 and CONEX-AGP controllers, each device on
//! its own real pseudo-terminal, driven by `scripts/conformance/smc100_clients.py`: pystages'
//! `SMC100` on two SMC100CC controllers sharing one port (addresses 1 and 2), and yaq's daemons
//! `yaqd-newport-smc100` and `yaqd-newport-conex-agp` through their client `yaqc`. Every
//! operation a client offers must pass or be a client difference whose reason the script states
//! and checks; none may fail. At the end each device's address 1 must truly be where the client
//! parked it (the simulator's ground truth).
//!
//! The clients live in the venv of `scripts/test.sh` (`target/py-venv`, pinned in
//! `scripts/requirements.txt`), named by `POLARIMETER_PYTHON`. Without it this test fails,
//! unless `POLARIMETER_SKIP_PYTHON=1`. The stages turn at 90 deg/s (the AG-PR100P at 30) so that
//! a homing takes a few seconds; the table the script prints is the one in
//! `docs/DEVICES-conformance.md`, also written to `target/smc100-conformance.md`.

use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use polar_hil_mocks::smc100::{Smc100Bus, Smc100Config};
use polar_hil_tests::conformance::{client_python, clients_available, run_script};

/// Where the script parks every device's address 1, degrees.
const PARK_DEG: f64 = 123.0;
/// The truth is within this of the park angle: the readback tolerance of the script (0.003
/// deg) plus half the simulated backlash (0.001 deg).
const PARK_TOL_DEG: f64 = 0.004;

/// The bus (pystages), the SMC100 and the CONEX-AGP (yaq): no FAILED row; every operation of
/// each client passed; each device's address 1 truly at 123 deg and still.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn public_newport_clients_drive_the_simulated_controllers() {
    let python = client_python();
    if !clients_available(&python, "pystages, yaqc, yaqd_newport, serial") {
        return;
    }
    let dir = std::env::temp_dir().join(format!("polar-smc100-clients-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let healthy = FaultProfile::default();
    let mut servers = Vec::new();
    let mut args = Vec::new();
    for (k, (name, config, addresses)) in [
        ("bus", Smc100Config::pr50cc().at_speed(90.0), vec![1, 2]),
        ("smc100", Smc100Config::pr50cc().at_speed(90.0), vec![1]),
        ("agp", Smc100Config::conex_agp().at_speed(30.0), vec![1]),
    ]
    .into_iter()
    .enumerate()
    {
        let link = dir.join(name);
        let device = Smc100Bus::new(config, &addresses, healthy, 30 + k as u64);
        let server = SimServer::pty(device, healthy, 7, &link).expect("a pty");
        args.push(format!("{name}={}", link.display()));
        servers.push((name, server));
    }
    let run = tokio::task::spawn_blocking({
        let dir = dir.clone();
        move || {
            run_script(
                &python,
                "smc100_clients.py",
                &args,
                &dir,
                "smc100-conformance.md",
            )
        }
    })
    .await
    .expect("the script's thread");
    run.check_rows(&["passed"]);
    let rows = &run.rows;
    for client in ["pystages", "yaqd-newport-smc100", "yaqd-newport-conex-agp"] {
        let n = rows.iter().filter(|r| r[0] == client).count();
        assert!(n >= 5, "{client}: {n} operations passed, want at least 5");
    }
    for (name, server) in servers {
        let Truth::Angle { output_rad, moving } = server.truth() else {
            panic!("{name}: not a rotator")
        };
        let off = (output_rad.to_degrees() - PARK_DEG + 180.0).rem_euclid(360.0) - 180.0;
        assert!(
            !moving && off.abs() <= PARK_TOL_DEG,
            "{name}: {off} deg from the park angle"
        );
        server.shutdown().await;
    }
    let _ = std::fs::remove_dir_all(&dir);
}
