//! The panels driven by their labels with egui_kittest, headless (no window, no GPU): start
//! a simulated run, pause, resume, and check the state, the progress and the live products.
#![allow(clippy::unwrap_used)]

use eframe::egui;
use egui_kittest::kittest::{NodeT, Queryable};
use egui_kittest::Harness;
use polar_engine::run::RunState;
use polar_gui::{App, Status};
use std::path::PathBuf;
use std::time::{Duration, Instant};

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("polar-gui-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn harness(app: App) -> Harness<'static, App> {
    Harness::builder()
        .with_size(egui::vec2(1200.0, 900.0))
        .build_ui_state(|ui, app: &mut App| app.show(ui), app)
}

/// A new app on the simulated devices with runs under a fresh temp folder, drawn once.
fn start(name: &str) -> (PathBuf, Harness<'static, App>) {
    let dir = temp_dir(name);
    let app = App::new(dir.clone(), None).unwrap();
    let mut h = harness(app);
    h.step();
    (dir, h)
}

/// Opens the device panel and connects, by label; waits until the devices answer.
fn connect(h: &mut Harness<'static, App>) {
    h.get_by_label("Devices").click();
    h.run_steps(2);
    h.get_by_label("Connect").click();
    step_until(h, Duration::from_secs(30), "connected", |h| {
        h.state().devices().connected && !h.state().device_pending()
    });
}

/// Steps the harness until `done` holds, for at most `limit`.
fn step_until(
    h: &mut Harness<'static, App>,
    limit: Duration,
    what: &str,
    done: impl Fn(&Harness<'static, App>) -> bool,
) {
    let t0 = Instant::now();
    while !done(h) {
        assert!(
            t0.elapsed() < limit,
            "waited {limit:?} for {what}; state {:?}; log:\n{}",
            h.state().status(),
            h.state().log_lines().collect::<Vec<_>>().join("\n")
        );
        h.step();
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn label_shows(h: &Harness<'static, App>, text: &str) -> bool {
    h.query_all_by_label_contains(text).next().is_some()
}

/// Start, pause, resume: the state label follows the run, the run takes every planned
/// frame, and a product image arrives.
#[test]
fn start_pause_resume_done() {
    let (dir, mut h) = start("run");
    assert!(label_shows(&h, "State: Idle"));
    // The forecast of the default plan.
    step_until(&mut h, Duration::from_secs(20), "the forecast", |h| {
        h.state().forecast().is_some()
    });
    assert!(matches!(h.state().forecast(), Some(Ok(_))));

    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(30), "Running", |h| {
        label_shows(h, "State: Running")
    });
    h.get_by_label("Pause").click();
    step_until(&mut h, Duration::from_secs(30), "Paused", |h| {
        label_shows(h, "State: Paused")
    });
    assert!(matches!(
        h.state().status(),
        Status::Run(RunState::Paused(_))
    ));
    let (done_at_pause, planned) = h.state().progress();
    assert!(done_at_pause < planned, "{done_at_pause} of {planned}");
    h.get_by_label("Resume").click();
    step_until(&mut h, Duration::from_secs(30), "Done", |h| {
        label_shows(h, "State: Done")
    });
    // Let the last replies in.
    h.run_steps(3);
    let app = h.state();
    assert_eq!(app.status(), &Status::Run(RunState::Done));
    let (done, planned) = app.progress();
    assert_eq!(planned, 13);
    assert_eq!(done, planned);
    assert!(app.products_received() >= 1);
    let live = app.live().unwrap();
    assert_eq!(live.products.s0.len(), 96 * 72);
    assert!(live.products.s0.iter().any(|v| v.is_finite() && *v > 0.0));
    assert!(live.raw.is_some());
    assert!(label_shows(&h, "13/13 frames"));
    assert!(h.state().log_lines().any(|l| l.contains("accepted")));

    // The live view: the pixel probe under the pointer, and AoP with its DoLP key.
    h.get_by_label("S0 image").hover();
    h.run_steps(2);
    assert!(label_shows(&h, "pixel ("));
    assert!(label_shows(&h, "S1 = "));
    h.get_by_label("AoP").click();
    h.run_steps(2);
    assert!(label_shows(&h, "AoP image"));
    assert!(label_shows(&h, "saturation: DoLP"));
    h.get_by_label("Raw frame").click();
    h.run_steps(2);
    assert!(label_shows(&h, "Raw frame image"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Abort while the run is going, no pause first: the button is enabled while running and the
/// run ends aborted, with fewer frames than planned and no pause on the way.
#[test]
fn abort_while_running() {
    let (dir, mut h) = start("abort-running");
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(30), "a frame", |h| {
        label_shows(h, "State: Running") && h.state().progress().0 >= 1
    });
    h.get_by_label("Abort").click();
    step_until(&mut h, Duration::from_secs(30), "Aborted", |h| {
        label_shows(h, "State: Aborted")
    });
    let (done, planned) = h.state().progress();
    assert!(done < planned, "{done} of {planned}");
    assert!(
        !h.state().log_lines().any(|l| l.contains("paused")),
        "{}",
        h.state().log_lines().collect::<Vec<_>>().join("\n")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A plan that does not parse: the error is shown and nothing runs.
#[test]
fn bad_plan_shows_error() {
    let (dir, mut h) = start("bad");
    h.state_mut().plan_text = "kind = \"nonsense\"".into();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(10), "Failed", |h| {
        label_shows(h, "State: Failed")
    });
    assert!(!h.state().is_active());
    // The forecast of the edited plan says why (after the default plan's, still in flight).
    step_until(&mut h, Duration::from_secs(20), "the plan error", |h| {
        label_shows(h, "plan error")
    });
    let _ = std::fs::remove_dir_all(&dir);
}

/// The live view's selector switches between the images by their labels.
#[test]
fn view_selector_by_label() {
    let (dir, mut h) = start("views");
    for v in ["AoP", "DoLP", "sigma S0", "Raw frame", "S0"] {
        h.get_by_label(v).click();
        h.step();
        h.step();
    }
    assert!(label_shows(&h, "No products yet"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The device panel by its labels: connect the simulated devices, move the analyzer, set the
/// exposure, take a snapshot; then a run takes the devices over, and they are connected again
/// with the panel's settings when it ends.
#[test]
fn devices_connect_move_snapshot_then_run() {
    let (dir, mut h) = start("devices");
    assert!(label_shows(&h, "Devices: simulated rig per run"));
    connect(&mut h);
    // Homed at connect: the stage reads 0 deg (the simulated stage has no zero offset).
    let d = h.state().devices().clone();
    assert!(d.error.is_none(), "{d:?}");
    let stage = d.stage_deg.unwrap();
    assert!(stage.abs() < 0.01, "stage at {stage} deg after homing");

    // Move to the default 45 deg: the analyzer reads it back within the stage's tolerance
    // (5 counts of 144000 per turn = 0.0125 deg).
    h.get_by_label("Move").click();
    step_until(&mut h, Duration::from_secs(30), "the move", |h| {
        h.state()
            .devices()
            .analyzer_deg
            .is_some_and(|a| (a - 45.0).abs() < 0.0125)
    });
    assert!(label_shows(&h, "analyzer at 45.0"));

    // Exposure: the camera applies what was asked (250 us is inside its range).
    h.get_by_label("Set exposure").click();
    h.step();
    step_until(&mut h, Duration::from_secs(30), "the exposure", |h| {
        !h.state().device_pending()
            && h.state()
                .log_lines()
                .any(|l| l.contains("exposure 250.0 us"))
    });
    let e = h.state().devices().exposure_us.unwrap();
    assert!((e - 250.0).abs() < 1.0, "exposure {e} us");

    h.get_by_label("Snapshot").click();
    step_until(&mut h, Duration::from_secs(30), "the snapshot", |h| {
        h.state().snapshot().is_some()
    });
    let s = h.state().snapshot().unwrap();
    assert_eq!(s.pixels.len(), (s.width * s.height) as usize);
    // The scene is lit: the frame's mean is well above the dark offset (a few DN).
    let mean = s.pixels.iter().map(|&p| f64::from(p)).sum::<f64>() / s.pixels.len() as f64;
    assert!(mean > 20.0, "snapshot mean {mean} DN");
    h.run_steps(2);
    assert!(label_shows(&h, "snapshot image"));

    // A run on the connected devices; when it ends they are connected again with the
    // panel's exposure (250 us), so the user goes on without Connect, Home and Set exposure.
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done")
    });
    step_until(&mut h, Duration::from_secs(30), "connected again", |h| {
        h.state().devices().connected
            && h.state()
                .log_lines()
                .any(|l| l.contains("connected again after the run"))
    });
    let e = h.state().devices().exposure_us.unwrap();
    assert!((e - 250.0).abs() < 1.0, "exposure {e} us after the run");
    assert!(label_shows(&h, "Devices: connected"));
    assert!(h
        .state()
        .log_lines()
        .any(|l| l.contains("on the connected devices")));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A device command without devices: the engine answers with an error naming the command,
/// and the UI thread never waits for it.
#[test]
fn device_command_without_devices_is_refused() {
    use polar_gui::engine::{Command, EngineHandle, Reply};
    let dir = temp_dir("nodev");
    let mut engine = EngineHandle::spawn(dir.clone(), None).unwrap();
    assert!(engine.send(Command::MoveAnalyzer { angle_deg: 30.0 }));
    let t0 = Instant::now();
    let reply = loop {
        if let Some(r) = engine.try_recv() {
            break r;
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "no reply");
        std::thread::sleep(Duration::from_millis(5));
    };
    match reply {
        Reply::Devices(d) => {
            assert!(!d.connected);
            let e = d.error.unwrap();
            assert!(
                e.contains("MoveAnalyzer") && e.contains("connect the devices first"),
                "{e}"
            );
        }
        other => panic!("expected a device status, got {other:?}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The hardware path (`--port --dialect --camera --camera-file`), on our stage's simulator
/// behind a real pseudo-terminal and the rig's simulated camera, which follows that stage
/// through the positions it reports and caps its own lens for darks: connect by label, move,
/// then a run that finishes with no operator pause.
#[test]
fn hardware_flags_path_on_a_simulated_stage() {
    use polar_engine::plan::Plan;
    use polar_gui::engine::Devices;
    use polar_rig::Hardware;
    use polar_rig::SimRig;

    let dir = temp_dir("hardware");
    std::fs::create_dir_all(&dir).unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let plan = Plan::from_toml_str(polar_gui::DEFAULT_PLAN).unwrap();
    let (stage, camera) = {
        let _g = rt.enter();
        SimRig::start(&plan, std::path::Path::new("."), &dir.join("stage"), 0).unwrap()
    };
    drop(camera); // the stage's server is what this test needs
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let hw = Hardware {
        port: stage.link.display().to_string(),
        dialect: polar_drivers::registry::find("native").expect("the native dialect"),
        address: 0,
        model: None,
        camera: "sim".into(),
        camera_file: root.join("examples/cameras/cmos_modern.toml"),
        zero_offset_deg: 0.0,
        extinction_ratio: None,
        provenance: Default::default(),
    };
    let app = App::new_on(dir.join("runs"), Devices::Hardware(Box::new(hw)), None).unwrap();
    let mut h = harness(app);
    h.step();
    assert!(label_shows(&h, "Devices: hardware, connected at start"));
    connect(&mut h);
    h.get_by_label("Move").click();
    step_until(&mut h, Duration::from_secs(30), "the move", |h| {
        h.state()
            .devices()
            .analyzer_deg
            .is_some_and(|a| (a - 45.0).abs() < 0.0125)
    });
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done")
    });
    assert_eq!(h.state().progress(), (13, 13));
    drop(h);
    rt.block_on(stage.shutdown());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Open and Save by label: a YAML example plan opens as TOML that parses to the same plan; a
/// save to a path without `.toml` is refused with the reason; a missing file names the path.
#[test]
fn open_and_save_plans() {
    let (dir, mut h) = start("open");
    std::fs::create_dir_all(&dir).unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let yaml = root.join("examples/plans/calibrate_noise.yaml");
    h.state_mut().plan_path = yaml.display().to_string();
    h.get_by_label("Open").click();
    h.run_steps(2);
    let text = h.state().plan_text.clone();
    let from_yaml =
        polar_engine::plan::Plan::from_yaml_str(&std::fs::read_to_string(&yaml).unwrap()).unwrap();
    assert_eq!(
        polar_engine::plan::Plan::from_toml_str(&text).unwrap(),
        from_yaml
    );
    assert!(label_shows(&h, "opened"));

    let saved = dir.join("saved.toml");
    h.state_mut().plan_path = saved.display().to_string();
    h.get_by_label("Save").click();
    h.run_steps(2);
    assert_eq!(std::fs::read_to_string(&saved).unwrap(), text);

    h.state_mut().plan_path = dir.join("saved.yaml").display().to_string();
    h.get_by_label("Save").click();
    h.run_steps(2);
    assert!(label_shows(&h, "allowed a path ending in .toml"));

    h.state_mut().plan_path = dir.join("missing.toml").display().to_string();
    h.get_by_label("Open").click();
    h.run_steps(2);
    assert!(label_shows(&h, "missing.toml"));
    assert_eq!(
        h.state().plan_text,
        text,
        "a failed open keeps the editor's plan"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A plan that does not parse leaves connected devices connected; a plan whose
/// `[simulation]` section changed since Connect gets its own simulated devices.
#[test]
fn bad_plan_keeps_devices_and_changed_simulation_rebuilds() {
    let (dir, mut h) = start("keep");
    connect(&mut h);
    let good = h.state().plan_text.clone();
    h.state_mut().plan_text = "kind = \"nonsense\"".into();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(10), "Failed", |h| {
        label_shows(h, "State: Failed")
    });
    h.run_steps(3);
    assert!(h.state().devices().connected, "{:?}", h.state().devices());

    // Another seed: the simulated world differs, so the devices are rebuilt for the run.
    h.state_mut().plan_text = good.replace("seed = 3", "seed = 4");
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done")
    });
    assert!(h
        .state()
        .log_lines()
        .any(|l| l.contains("rebuilding the simulated devices")));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Closing the window during a run: the close is cancelled, the run pauses at once and is
/// detached (left for `polarimeter resume`, not finished, its frames kept), then the window
/// closes.
#[test]
fn closing_during_a_run_pauses_and_detaches_first() {
    use egui::{ViewportCommand, ViewportEvent, ViewportId};
    let dir = temp_dir("close");
    let app = App::new(dir.clone(), None).unwrap();
    let mut h = Harness::builder()
        .with_size(egui::vec2(1200.0, 900.0))
        .build_ui_state(
            |ui, app: &mut App| {
                app.show(ui);
                app.guard_close(ui.ctx());
            },
            app,
        );
    h.step();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(30), "a frame", |h| {
        h.state().progress().0 >= 2
    });
    h.input_mut()
        .viewports
        .entry(ViewportId::ROOT)
        .or_default()
        .events
        .push(ViewportEvent::Close);
    h.step();
    let commands = |h: &Harness<'static, App>| {
        h.output()
            .viewport_output
            .get(&ViewportId::ROOT)
            .map(|v| v.commands.clone())
            .unwrap_or_default()
    };
    assert!(
        commands(&h)
            .iter()
            .any(|c| matches!(c, ViewportCommand::CancelClose)),
        "the close must wait for the run"
    );
    let t0 = Instant::now();
    let mut closed = false;
    while !closed {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no close; state {:?}",
            h.state().status()
        );
        h.step();
        closed = commands(&h)
            .iter()
            .any(|c| matches!(c, ViewportCommand::Close));
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(
        matches!(h.state().status(), Status::Detached(_)),
        "{:?}",
        h.state().status()
    );
    let run_dir = h.state().run_dir().unwrap().to_path_buf();
    assert!(!polar_engine::run::is_finished(&run_dir));
    let (done, planned) = h.state().progress();
    assert!(done >= 2 && done < planned, "{done} of {planned}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuous plan (4 frames per half turn at 360 deg/s, 3 half turns) started from the
/// run panel on the simulated devices: it runs through the continuous loop (the stage spins,
/// its compare output triggers the camera), takes every planned frame (counts, so exact) and
/// sends the products of its half turns to the live view.
#[test]
fn continuous_plan_runs_from_the_run_panel() {
    let (dir, mut h) = start("continuous");
    h.state_mut().plan_text = "name = \"gui continuous\"\nkind = \"continuous\"\n\
        [continuous]\nframes_per_half_turn = 4\nexposure_us = 1000\nspeed_deg_per_s = 360\n\
        half_turns = 3\n[simulation]\nwidth = 48\nheight = 36\n"
        .into();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done") || label_shows(h, "State: Failed")
    });
    h.run_steps(3);
    let app = h.state();
    assert_eq!(app.status(), &Status::Run(RunState::Done));
    assert_eq!(app.progress(), (12, 12), "3 half turns x 4 frames");
    assert!(app.products_received() >= 1);
    let live = app.live().unwrap();
    assert_eq!(live.products.s0.len(), 48 * 36);
    assert!(label_shows(&h, "12/12 frames"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuous plan whose spin comes `from_planner`, started from the run panel: the GUI
/// resolves it as `acquire run` does (the same planner on the plan's simulated scene and
/// camera), so the run takes exactly 2 half turns of the planner's frames per half turn
/// (counts, so exact), and the log names the choice.
#[test]
fn continuous_from_planner_resolves_in_the_gui() {
    let text = "name = \"gui continuous planner\"\nkind = \"continuous\"\n[continuous]\n\
        half_turns = 2\nfrom_planner = { target = \"panel\", background = \"asphalt\", \
        max_frames_per_half_turn = 8 }\n[simulation]\nwidth = 48\nheight = 36\n";
    let mut plan = polar_engine::plan::Plan::from_toml_str(text).unwrap();
    let here = std::path::Path::new(".");
    let world = polar_rig::SimRig::world(&plan, here).unwrap();
    let stage = polar_rig::sim_stage::stage_limits(&plan.simulation).unwrap();
    let choice = polar_engine::continuous_planner::resolve(
        &mut plan,
        &world.scene_file,
        &world.camera_model,
        stage,
    )
    .unwrap()
    .unwrap();
    let n = u64::from(plan.continuous().unwrap().frames_per_half_turn);
    assert!((3..=8).contains(&n), "{n} frames per half turn");
    let (dir, mut h) = start("continuous-planner");
    h.state_mut().plan_text = text.into();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done") || label_shows(h, "State: Failed")
    });
    h.run_steps(3);
    let app = h.state();
    assert_eq!(app.status(), &Status::Run(RunState::Done));
    assert_eq!(app.progress(), (2 * n, 2 * n), "2 half turns of {n} frames");
    let said = polar_engine::continuous_planner::describe(&choice);
    assert!(
        app.log_lines().any(|l| l.contains(&said)),
        "the log names the choice {said:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Connect needs only the plan's `[simulation]` section: an error elsewhere in the editor
/// (here `capture.repeats = -1`) does not stop it, and the log says the plan itself does not
/// load; an error in `[simulation]` is refused naming that section, the key and its line.
#[test]
fn connect_reads_only_the_simulation_section() {
    let (dir, mut h) = start("connect-section");
    let good = h.state().plan_text.clone();
    h.state_mut().plan_text = good.replace("repeats = 3", "repeats = -1");
    connect(&mut h);
    assert!(
        h.state().devices().error.is_none(),
        "{:?}",
        h.state().devices()
    );
    assert!(h
        .state()
        .log_lines()
        .any(|l| l.contains("[simulation] section") && l.contains("repeats")));
    h.get_by_label("Disconnect").click();
    step_until(&mut h, Duration::from_secs(10), "disconnected", |h| {
        !h.state().devices().connected && !h.state().device_pending()
    });
    // Line 12 of the default plan is `width = 96` in [simulation].
    h.state_mut().plan_text = good.replace("width = 96", "width = \"wide\"");
    h.get_by_label("Connect").click();
    step_until(&mut h, Duration::from_secs(10), "refused", |h| {
        h.state().devices().error.is_some() && !h.state().device_pending()
    });
    let e = h.state().devices().error.clone().unwrap();
    assert!(
        e.contains("[simulation]") && e.contains("simulation.width") && e.contains("line 12"),
        "{e}"
    );
    assert!(!h.state().devices().connected);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Numbers outside their range are never clamped without a word: an exposure of 1 us (the
/// simulated camera's range starts at 10 us) stays as typed, a note names the field, the
/// value and the range, and Set exposure stays disabled until it is fixed.
#[test]
fn out_of_range_numbers_are_named_not_clamped() {
    let (dir, mut h) = start("ranges");
    connect(&mut h);
    h.get_by_label("Exposure (us)").set_value_accesskit(1.0);
    h.run_steps(2);
    assert!(
        label_shows(
            &h,
            "Exposure (us) = 1 is outside the allowed range [10, 10000000]"
        ),
        "no note"
    );
    let shown = h.get_by_label("Exposure (us)").value().unwrap_or_default();
    assert!(
        shown.trim() == "1",
        "the field shows {shown:?}, not what was typed"
    );
    let disabled = |h: &Harness<'static, App>| {
        h.get_by_label("Set exposure")
            .accesskit_node()
            .is_disabled()
    };
    assert!(disabled(&h));
    h.get_by_label("Exposure (us)").set_value_accesskit(20.0);
    h.run_steps(2);
    assert!(!label_shows(&h, "is outside the allowed range"));
    assert!(!disabled(&h));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A failed start's state goes once the plan is edited (the log keeps it), and a TOML error
/// in the forecast names its line.
#[test]
fn stale_failure_goes_and_toml_errors_name_the_line() {
    let (dir, mut h) = start("stale");
    let good = h.state().plan_text.clone();
    h.state_mut().plan_text = good.replace("repeats = 3", "repeats = [3");
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(10), "Failed", |h| {
        label_shows(h, "State: Failed")
    });
    step_until(&mut h, Duration::from_secs(20), "the plan error", |h| {
        label_shows(h, "plan error")
    });
    // `repeats = [3` is on line 6 of the default plan; TOML finds the array unclosed where the
    // next key starts, line 8, column 1.
    assert!(
        label_shows(&h, "line 8, column 1"),
        "no line in the forecast's error"
    );
    h.state_mut().plan_text = good;
    h.run_steps(2);
    assert!(label_shows(&h, "State: Idle"));
    assert!(h.state().log_lines().any(|l| l.contains("error")));
    let _ = std::fs::remove_dir_all(&dir);
}

/// At 900 x 650 (a laptop's small window) the whole left panel scrolls: after a run, the
/// log's newest line (done) is brought into the window by scrolling the panel (before, the
/// panel did not scroll and the log's end lay below the window).
#[test]
fn the_log_is_reachable_in_a_small_window() {
    let dir = temp_dir("small");
    let app = App::new(dir.clone(), None).unwrap();
    let mut h = Harness::builder()
        .with_size(egui::vec2(900.0, 650.0))
        .build_ui_state(|ui, app: &mut App| app.show(ui), app);
    h.step();
    h.get_by_label("Start").click();
    step_until(&mut h, Duration::from_secs(60), "Done", |h| {
        label_shows(h, "State: Done")
    });
    h.run_steps(3);
    // The mouse wheel over the panel (at its "Forecast" heading), 100 points a turn.
    h.get_by_label("Forecast").hover();
    h.run_steps(2);
    for _ in 0..10 {
        h.event(egui::Event::MouseWheel {
            unit: egui::MouseWheelUnit::Point,
            delta: egui::vec2(0.0, -100.0),
            phase: egui::TouchPhase::Move,
            source: egui::MouseWheelSource::Unknown,
            modifiers: egui::Modifiers::NONE,
        });
        h.run_steps(2);
    }
    let r = h.get_by_label_contains("done: 13 frames").rect();
    assert!(
        r.min.y >= 0.0 && r.max.y <= 650.0 && r.min.x >= 0.0 && r.min.x < 900.0,
        "the log's last line is at {r:?}, outside the 900x650 window"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
