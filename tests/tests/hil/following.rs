//! The simulated camera behind a stage the rig does not simulate: a rig file naming the port of
//! a stage simulator served apart (as `polarimeter simulate stage` serves one) and `camera =
//! sim`. The camera renders through the positions that stage reports (`polar_rig::follow`), so
//! the frames follow the analyzer; a spinning analyzer cannot be followed that way and is
//! refused before anything runs.

use polar_engine::store::RunStore;
use polar_hil_tests::{repo_root, run_cli, scratch, serve, stokes_within_two_sigma};
use std::path::{Path, PathBuf};

/// Serves the native rotator's simulator on its own thread and runtime (the command under test
/// makes its own runtime) until the returned sender is dropped; returns the link.
fn serve_apart(
    dir: &Path,
) -> (
    PathBuf,
    std::sync::mpsc::Sender<()>,
    std::thread::JoinHandle<()>,
) {
    let (link_tx, link_rx) = std::sync::mpsc::channel();
    let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
    let dir = dir.to_path_buf();
    let thread = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("runtime");
        rt.block_on(async {
            let server = serve("native", "rotator", 5, &dir).unwrap_or_else(|e| panic!("{e}"));
            let _ = link_tx.send(server.link().map(Path::to_path_buf).expect("a link"));
            let _ = tokio::task::spawn_blocking(move || stop_rx.recv()).await;
            server.shutdown().await;
        });
    });
    let link = link_rx.recv().expect("the simulator's link");
    (link, stop_tx, thread)
}

/// A rig file for the stage on `link` and the simulated camera with the example camera file.
fn rig_for(dir: &Path, link: &Path) -> PathBuf {
    let camera = repo_root().join("examples/cameras/cmos_modern.toml");
    let path = dir.join("apart.toml");
    std::fs::write(
        &path,
        format!(
            "[stage]\ndialect = \"native\"\nport = {:?}\n\n[camera]\nbackend = \"sim\"\n\
             file = {:?}\n",
            link.display().to_string(),
            camera.display().to_string()
        ),
    )
    .expect("write the rig");
    path
}

/// `tests/fixtures/capture_k10cr1.toml` (one set of 0/45/90/135 and two darks) on that rig:
/// the run finishes done with no pause, the store says what the camera follows, and the set's
/// Stokes products agree with the rendered truth within their predicted sigma as on the rig's
/// own simulated stage (93-97.5 % within 2 sigma; an unbiased Gaussian estimate gives 95.45 %).
/// Frames rendered at one fixed angle (a camera not following its stage) fail this: their S1
/// and S2 are near 0 where the scene's are many sigma away.
#[test]
fn sim_camera_follows_a_stage_served_apart() {
    let dir = scratch("following");
    let (link, stop, thread) = serve_apart(&dir);
    let rig = rig_for(&dir, &link);
    let run_dir = dir.join("run");
    let plan = repo_root().join("tests/fixtures/capture_k10cr1.toml");
    let (out, code) = run_cli(&plan, &rig, &run_dir, 0, false).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((out["state"].as_str(), code), (Some("done"), 0), "{out}");
    let store = RunStore::open(&run_dir).expect("store");
    let devices = &store.attributes().expect("attributes")["devices"];
    assert!(
        devices["camera_follows"]
            .as_str()
            .is_some_and(|s| s.contains("positions the stage reports")),
        "{devices}"
    );
    let camera = repo_root().join("examples/cameras/cmos_modern.toml");
    let share = stokes_within_two_sigma(&store, &camera, 250.0);
    println!(
        "camera following a stage apart: {:.2} % within 2 sigma",
        100.0 * share
    );
    assert!((0.93..=0.975).contains(&share), "{:.2} %", 100.0 * share);
    drop(stop);
    let _ = thread.join();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuous plan on that rig is refused before anything runs, naming the camera, the port
/// and what is allowed; nothing is written.
#[test]
fn continuous_refused_when_the_camera_follows_reports() {
    let dir = scratch("following-continuous");
    let (link, stop, thread) = serve_apart(&dir);
    let rig = rig_for(&dir, &link);
    let run_dir = dir.join("run");
    let plan = repo_root().join("tests/fixtures/continuous.toml");
    let e = run_cli(&plan, &rig, &run_dir, 0, false).expect_err("refused");
    assert!(
        e.contains("camera = \"sim\"") && e.contains("spinning analyzer") && e.contains("port"),
        "{e}"
    );
    assert!(
        !run_dir.join("journal.jsonl").exists(),
        "nothing is written: {e}"
    );
    drop(stop);
    let _ = thread.join();
    let _ = std::fs::remove_dir_all(&dir);
}
