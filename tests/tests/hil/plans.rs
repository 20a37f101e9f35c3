//! Plans end to end on the simulated rig named by `examples/rigs/sim.toml`.

use polar_engine::plan::Plan;
use polar_engine::run::{Control, Event, Outcome, RunState};
use polar_engine::store::RunStore;
use polar_engine::FrameKind;
use polar_hal::signed_difference;
use polar_hil_tests::{repo_root, run_cli, scratch};
use polar_rig::{connect_hardware, Overrides, Rig};

/// `examples/plans/capture.toml` on `examples/rigs/sim.toml`, as the rig file's header shows it
/// (`polarimeter acquire run --rig examples/rigs/sim.toml examples/plans/capture.toml`, no
/// terminal, no pause resumed): the rig file's native stage is simulated on a pseudo-terminal
/// and connected through the registry, the camera renders through the stage's true angle, and
/// the run caps the simulated lens itself for the darks, so it finishes done with no pause.
/// The darks are dark: their mean is within 3 DN of the camera file's black level (16 DN; dark
/// current adds 3 e/s x 250 us, far below 1 DN) and the lit frames' mean is above 10x that;
/// `check` finds every frame intact; every light frame's measured analyzer angle is within 0.05
/// deg (the driver's readback tolerance is finer) of the commanded one, modulo the analyzer's
/// half turn; and the store records the rig file, its content hash and its analyzer values.
#[test]
fn capture_on_the_simulated_rig_file() {
    let root = repo_root();
    let rig_path = root.join("examples/rigs/sim.toml");
    let plan_path = root.join("examples/plans/capture.toml");
    let plan = Plan::from_path(&plan_path).expect("the plan");
    let run_dir = scratch("capture").join("run");
    let (out, code) =
        run_cli(&plan_path, &rig_path, &run_dir, 0, false).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((out["state"].as_str(), code), (Some("done"), 0), "{out}");
    assert_eq!(out["summary"]["pauses"], 0, "no operator pause: {out}");
    assert_eq!(
        out["summary"]["frames_accepted"],
        plan.max_frames().expect("frames")
    );
    let check = polar_engine::check::check_run(&run_dir).expect("check");
    assert!(check.ok && check.finished, "{check:?}");
    let store = RunStore::open(&run_dir).expect("store");
    let mean = |index: u64| {
        let px = store.read_frame(index).expect("a frame");
        px.iter().map(|&p| f64::from(p)).sum::<f64>() / px.len() as f64
    };
    let (mut lights, mut darks) = (0, 0);
    for f in store.read_frame_metadata().expect("metadata") {
        match f.kind {
            FrameKind::Light => {
                let off = signed_difference(f.measured_angle_deg, f.commanded_angle_deg, 180.0);
                assert!(off.abs() <= 0.05, "frame {}: {off} deg off", f.index);
                assert!(
                    mean(f.index) > 160.0,
                    "frame {}: {} DN",
                    f.index,
                    mean(f.index)
                );
                lights += 1;
            }
            FrameKind::Dark => {
                let m = mean(f.index);
                assert!((m - 16.0).abs() <= 3.0, "dark frame {}: {m} DN", f.index);
                darks += 1;
            }
        }
    }
    assert_eq!(
        (lights, darks),
        (12, 4),
        "4 angles x 3 repeats, 2 + 2 darks"
    );
    let devices = &store.attributes().expect("attributes")["devices"];
    assert_eq!(devices["stage"]["dialect"], "native");
    assert_eq!(devices["stage"]["port"], "sim");
    assert_eq!(devices["rig"]["file"], rig_path.display().to_string());
    let text = std::fs::read_to_string(&rig_path).expect("the rig file");
    assert_eq!(
        devices["rig"]["content_xxh3"],
        polar_rig::file::content_hash(&text)
    );
    assert_eq!(devices["rig"]["analyzer"]["zero_offset_deg"], 0.0);
    let _ = std::fs::remove_dir_all(run_dir.parent().expect("scratch"));
}

/// Runs `plan` on a fresh connection to `hw` with the camera as real hardware has it (no
/// simulated lens cap), in a new run or resuming `run_dir`, until its first pause, which it
/// leaves for a later resume (as `acquire run` without a terminal does).
async fn until_first_pause(
    plan: &Plan,
    hw: &polar_rig::Hardware,
    run_dir: &std::path::Path,
    resume: bool,
) -> Outcome {
    let mut connected = connect_hardware(hw).await.unwrap_or_else(|e| panic!("{e}"));
    connected.rig.illumination = None;
    let simulator = connected.simulator.take();
    let (ctl, link) = polar_engine::run::link();
    let polar_engine::run::Controller {
        control,
        state: _state,
        mut events,
    } = ctl;
    let watcher = tokio::task::spawn_local(async move {
        while let Some(e) = events.recv().await {
            if let Event::State(RunState::Paused(_)) = e {
                let _ = control.send(Control::Detach).await;
                break;
            }
        }
    });
    let outcome = polar_engine::run::run(plan, connected.rig, run_dir, resume, link)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    let _ = watcher.await;
    if let Some(s) = simulator {
        s.shutdown().await;
    }
    outcome
}

/// The operator's lens-cap pauses on hardware (the rig's camera without its simulated cap), each
/// left and resumed in a new connection as `acquire resume RUN` does: the first run pauses to
/// cap the lens before the two darks; the resume takes them (the operator capped it) and
/// pauses to uncap it, not to cap it again for the darks already taken; the next resume takes
/// the three sets and pauses to cap the lens for the two last darks; the last resume takes
/// them and finishes done. Exactly these three pauses, in this order.
#[test]
fn lens_cap_pauses_on_hardware_resume_in_new_processes() {
    let root = repo_root();
    let rig = Rig::load(&root.join("examples/rigs/sim.toml")).unwrap_or_else(|e| panic!("{e}"));
    let hw = rig
        .hardware(&Overrides::default())
        .unwrap_or_else(|e| panic!("{e}"))
        .expect("the rig names its devices");
    let plan = Plan::from_path(&root.join("examples/plans/capture.toml")).expect("the plan");
    let run_dir = scratch("lens-cap").join("run");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let local = tokio::task::LocalSet::new();
    let outcomes = local.block_on(&rt, async {
        let mut outcomes = vec![until_first_pause(&plan, &hw, &run_dir, false).await];
        while matches!(outcomes.last(), Some(Outcome::Paused(_))) && outcomes.len() < 5 {
            outcomes.push(until_first_pause(&plan, &hw, &run_dir, true).await);
        }
        outcomes
    });
    let reasons: Vec<&str> = outcomes
        .iter()
        .filter_map(|o| match o {
            Outcome::Paused(r) => Some(r.as_str()),
            _ => None,
        })
        .collect();
    assert_eq!(
        reasons,
        vec![
            polar_engine::run::CAP_LENS,
            polar_engine::run::UNCAP_LENS,
            polar_engine::run::CAP_LENS
        ],
        "{outcomes:?}"
    );
    assert!(
        matches!(outcomes.last(), Some(Outcome::Done(_))),
        "{outcomes:?}"
    );
    let check = polar_engine::check::check_run(&run_dir).expect("check");
    assert!(check.ok && check.finished, "{check:?}");
    let _ = std::fs::remove_dir_all(run_dir.parent().expect("scratch"));
}
