//! The harness of the workspace's hardware-in-the-loop tests (`tests/hil.rs`, one test binary):
//! a simulator of a registered dialect on a real pseudo-terminal, a plan run through the `acquire
//! run` command's entry point on a rig file, scratch folders, and the conformance tests' runs of
//! public client scripts ([`conformance`]). The tests themselves live in `tests/hil/`.
#![warn(missing_docs)]

pub mod conformance;

use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use std::path::{Path, PathBuf};

/// The repository's root (for `examples/`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from(".."))
}

/// A fresh scratch folder under the system's temporary folder.
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("polar-hil-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    let _ = std::fs::create_dir_all(&d);
    d
}

/// The simulator of `dialect`'s `model` from the simulators' registry, healthy, served on a
/// pseudo-terminal whose link is `dir/DIALECT-MODEL`. Call inside a tokio runtime.
pub fn serve(dialect: &str, model: &str, seed: u64, dir: &Path) -> Result<SimServer, String> {
    let faults = FaultProfile::default();
    let sim = polar_hil_mocks::sim::simulator(dialect, Some(model), faults, seed)
        .map_err(|e| e.to_string())?;
    SimServer::pty(sim, faults, seed, &dir.join(format!("{dialect}-{model}")))
        .map_err(|e| format!("{dialect} {model}: cannot open a pseudo-terminal: {e}"))
}

/// As [`serve`], but a rotator whose simulator can be built at a speed turns at `deg_s` (a
/// test's speed: the AG-PR100P's real 1.5 deg/s would take minutes to home); the others run
/// at their real speed.
pub fn serve_at(
    dialect: &str,
    model: &str,
    deg_s: f64,
    seed: u64,
    dir: &Path,
) -> Result<SimServer, String> {
    let faults = FaultProfile::default();
    let fast = polar_hil_mocks::sim::SIMULATORS
        .iter()
        .find(|s| s.dialect == dialect)
        .and_then(|s| s.at_speed)
        .and_then(|build| build(model, deg_s, faults, seed));
    let Some(sim) = fast else {
        return serve(dialect, model, seed, dir);
    };
    SimServer::pty(sim, faults, seed, &dir.join(format!("{dialect}-{model}")))
        .map_err(|e| format!("{dialect} {model}: cannot open a pseudo-terminal: {e}"))
}

/// Runs the plan file `plan` with the rig file `rig` as `polarimeter run --rig RIG PLAN --out
/// OUT` does (`polar_cli::acquire::run_cmd`, no terminal): on the rig's devices, or with
/// `simulate` on the engine's simulated rig (`run --simulate --rig`: the rig file gives the
/// site and receives a calibration's write-back). A pause that is not the user's is resumed,
/// at most `max_resumes` times (0: a pause leaves the run, exit status 3). Returns the
/// command's JSON output and exit status.
pub fn run_cli(
    plan: &Path,
    rig: &Path,
    out: &Path,
    max_resumes: u32,
    simulate: bool,
) -> Result<(serde_json::Value, i32), String> {
    let rig = polar_cli::rig::load(rig).map_err(|e| e.to_string())?;
    let hw = if simulate {
        None
    } else {
        Some(
            rig.hardware(&polar_rig::Overrides::default())
                .map_err(|e| e.to_string())?
                .ok_or_else(|| format!("{}: the rig names no devices", rig.path.display()))?,
        )
    };
    let ui = polar_cli::acquire::Ui::unattended(max_resumes);
    polar_cli::acquire::run_cmd(plan, hw, Some(&rig), Some(out.to_path_buf()), ui)
        .map_err(|e| e.to_string())
}

/// The share of the first product set's S0, S1 and S2 values (all pixels) within 2 predicted
/// sigma of the truth: the scene the rig's simulated camera renders with `camera_file`, at
/// `exposure_us`, in DN. An unbiased Gaussian estimate puts 95.45 % there.
pub fn stokes_within_two_sigma(
    store: &polar_engine::store::RunStore,
    camera_file: &Path,
    exposure_us: f64,
) -> f64 {
    use polar_rig::camera::{sim_camera_following, SimOptions};
    let opts = SimOptions {
        camera_file: Some(camera_file.to_path_buf()),
        ..SimOptions::default()
    };
    let cam =
        sim_camera_following(&opts, std::sync::Arc::new(|| 0.0)).unwrap_or_else(|e| panic!("{e}"));
    let camera = polar_model::sensor::Camera::from_toml_str(
        &std::fs::read_to_string(camera_file).expect("the camera file"),
    )
    .expect("a camera file");
    let scale = camera.gain_dn_per_e * cam.sensor().responsivity_e_per_s() * exposure_us * 1e-6;
    let img = |n: &str| {
        store
            .read_product(n, 0)
            .unwrap_or_else(|e| panic!("{n}: {e}"))
    };
    let est = [img("s0"), img("s1"), img("s2")];
    let sig = [img("sigma_s0"), img("sigma_s1"), img("sigma_s2")];
    let (mut within, mut total) = (0usize, 0usize);
    for (p, t) in cam.scene().stokes.iter().enumerate() {
        for c in 0..3 {
            let z = (f64::from(est[c][p]) - t[c] * scale) / f64::from(sig[c][p]);
            total += 1;
            within += usize::from(z.abs() < 2.0);
        }
    }
    within as f64 / total as f64
}
