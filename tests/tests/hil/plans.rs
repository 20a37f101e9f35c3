//! Plans end to end on the simulated rig named by `examples/rigs/sim.toml`.

use polar_engine::plan::Plan;
use polar_engine::run::Outcome;
use polar_engine::store::RunStore;
use polar_engine::FrameKind;
use polar_hal::signed_difference;
use polar_hil_tests::{repo_root, run_resuming, scratch};
use polar_rig::{connect_hardware, Overrides, Rig};

/// `examples/plans/capture.toml` on `examples/rigs/sim.toml`: the rig file's native stage is
/// simulated on a pseudo-terminal and connected through the registry, the camera renders
/// through the stage's true angle. The run pauses for the lens cap around its darks (a
/// hardware rig has no simulated cap) and, resumed, stores every planned frame; `check`
/// finds them intact; every light frame's measured analyzer angle is within 0.05 deg (the
/// driver's readback tolerance is finer) of the commanded one, modulo the analyzer's half
/// turn; and the store records the rig file and its analyzer values.
#[test]
fn capture_on_the_simulated_rig_file() {
    let root = repo_root();
    let rig_path = root.join("examples/rigs/sim.toml");
    let rig = Rig::load(&rig_path).unwrap_or_else(|e| panic!("{e}"));
    let hw = rig
        .hardware(&Overrides::default())
        .unwrap_or_else(|e| panic!("{e}"))
        .expect("the rig names its devices");
    let plan = Plan::from_path(&root.join("examples/plans/capture.toml")).expect("the plan");
    let run_dir = scratch("capture").join("run");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let local = tokio::task::LocalSet::new();
    let (outcome, pauses) = local.block_on(&rt, async {
        let connected = connect_hardware(&hw)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let simulator = connected.simulator;
        let r = run_resuming(&plan, connected.rig, &run_dir, 8).await;
        if let Some(s) = simulator {
            s.shutdown().await;
        }
        r.unwrap_or_else(|e| panic!("{e}"))
    });
    let Outcome::Done(summary) = outcome else {
        panic!("{outcome:?} after pauses {pauses:?}");
    };
    assert!(
        pauses.iter().any(|p| p.contains("cap")),
        "the darks pause for the lens cap: {pauses:?}"
    );
    assert_eq!(summary.frames_accepted, plan.max_frames().expect("frames"));
    let check = polar_engine::check::check_run(&run_dir).expect("check");
    assert!(check.ok && check.finished, "{check:?}");
    let store = RunStore::open(&run_dir).expect("store");
    let mut lights = 0;
    for f in store.read_frame_metadata().expect("metadata") {
        if f.kind == FrameKind::Light {
            let off = signed_difference(f.measured_angle_deg, f.commanded_angle_deg, 180.0);
            assert!(off.abs() <= 0.05, "frame {}: {off} deg off", f.index);
            lights += 1;
        }
    }
    assert_eq!(lights, 12, "4 angles x 3 repeats");
    let devices = &store.attributes().expect("attributes")["devices"];
    assert_eq!(devices["stage"]["dialect"], "native");
    assert_eq!(devices["stage"]["port"], "sim");
    assert_eq!(devices["rig"]["file"], rig_path.display().to_string());
    assert_eq!(devices["rig"]["analyzer"]["zero_offset_deg"], 0.0);
    let _ = std::fs::remove_dir_all(run_dir.parent().expect("scratch"));
}
