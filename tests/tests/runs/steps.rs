//! Every plan kind end to end on the simulated devices, through the real drivers: our
//! firmware's stage simulated behind a pseudo-terminal and driven by `NativeRotator`, and the
//! simulated camera on its own thread through `ThreadedCamera`. Also: pause, resume, abort,
//! detach and resume in a new rig, and the suspender against a passing cloud.
#![allow(clippy::unwrap_used)]

use polar_engine::journal::{replay, Entry};
use polar_engine::plan::Plan;
use polar_engine::run::{self, Event, Outcome, RunState};
use polar_engine::store::RunStore;
use polar_engine::FrameKind;
use polar_rig::SimRig;
use std::path::Path;

use super::common;
use common::{check_frame_set, done, go, temp_dir, Script};

const CAPTURE: &str = r#"
name = "capture"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [300]
repeats = 3
darks_before = 1
darks_after = 1
[storage]
products = "all"   # S1, S2 and their sigmas are judged against the truth
[simulation]
width = 96
height = 72
seed = 3
"#;

/// A capture: 3 sets of 4 angles and 2 darks. The products of every set are stored, and the
/// Stokes images agree with the ground truth within their predicted sigma: for an unbiased
/// Gaussian estimate, 95.45 % of the values fall within 2 sigma; 93-97.5 % is asked (the
/// 20736 values give a sampling spread of 0.15 %, and Poisson skew and the stage's encoder
/// noise add a little).
#[test]
fn capture_end_to_end_products_match_truth() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("capture");
    let (o, states, _) = go(&plan, &dir, false, Script::Watch);
    let s = done(&o);
    assert_eq!(s.frames_accepted, 14);
    assert_eq!(s.sets_accepted, 3);
    assert_eq!(states.last(), Some(&RunState::Done));
    check_frame_set(&dir, 14);
    let store = RunStore::open(&dir).unwrap();
    let meta = store.read_frame_metadata().unwrap();
    assert_eq!(meta.iter().filter(|r| r.kind == FrameKind::Dark).count(), 2);
    for r in meta.iter().filter(|r| r.kind == FrameKind::Light) {
        let d = (r.commanded_angle_deg - r.measured_angle_deg).rem_euclid(180.0);
        assert!(
            d.min(180.0 - d) < 0.1,
            "frame {} at {} for {}",
            r.index,
            r.measured_angle_deg,
            r.commanded_angle_deg
        );
    }
    // Products against the truth.
    let world = SimRig::world(&plan, Path::new(".")).unwrap();
    let cam = &world.camera_model;
    let g = world.sensor.responsivity_e_per_s() * 300e-6;
    let scale = cam.gain_dn_per_e * g;
    let (mut within, mut total) = (0usize, 0usize);
    for slot in 0..3 {
        let img = |n: &str| store.read_product(n, slot).unwrap();
        let est = [img("s0"), img("s1"), img("s2")];
        let sig = [img("sigma_s0"), img("sigma_s1"), img("sigma_s2")];
        for (p, t) in world.scene.stokes.iter().enumerate() {
            for c in 0..3 {
                let z = (f64::from(est[c][p]) - t[c] * scale) / f64::from(sig[c][p]);
                total += 1;
                if z.abs() < 2.0 {
                    within += 1;
                }
            }
        }
    }
    let share = within as f64 / total as f64;
    println!(
        "products within 2 sigma of the truth: {:.2} %",
        100.0 * share
    );
    assert!((0.93..=0.975).contains(&share), "{:.2} %", 100.0 * share);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pause at the next safe point, then resume: the run pauses between sets (the frames
/// stored at the pause are a whole number of sets plus the dark), and finishes exactly.
#[test]
fn pause_at_safe_point_and_resume() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("pause");
    let (o, states, _) = go(&plan, &dir, false, Script::PauseResume(3));
    done(&o);
    assert!(states.contains(&RunState::Pausing), "{states:?}");
    assert!(
        states.iter().any(|s| matches!(s, RunState::Paused(_))),
        "{states:?}"
    );
    let r = replay(&dir).unwrap();
    let at = r
        .entries
        .iter()
        .find_map(|e| match e {
            Entry::Paused { next_step, .. } => Some(*next_step),
            _ => None,
        })
        .unwrap();
    // Steps: 0 is the dark, sets are 1..=4, 5..=8, 9..=12: a safe point is 1 + 4k.
    assert_eq!((at - 1) % 4, 0, "paused before step {at}");
    check_frame_set(&dir, 14);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Pause now cancels the operation in flight; the step is taken again and the frame set is
/// still exact.
#[test]
fn pause_now_and_resume() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("pausenow");
    let (o, states, _) = go(&plan, &dir, false, Script::PauseNowResume(2));
    done(&o);
    assert!(
        states
            .iter()
            .any(|s| matches!(s, RunState::Paused(r) if r.contains("immediately"))),
        "{states:?}"
    );
    check_frame_set(&dir, 14);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Abort while the run is going (the GUI's Abort button, no pause first): the run ends aborted
/// at once, without a pause, with no more than the frame in flight stored after the abort
/// was asked (at most 2 + 1 frames of the 14), and the journal says so.
#[test]
fn abort_while_running() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("abort-running");
    let (o, states, _) = go(&plan, &dir, false, Script::AbortRunning(2));
    assert!(
        matches!(&o, Outcome::Aborted(r) if r.contains("aborted by the user")),
        "{o:?}"
    );
    assert!(
        !states.iter().any(|s| matches!(s, RunState::Paused(_))),
        "{states:?}"
    );
    let r = replay(&dir).unwrap();
    assert!(r.aborted().is_some());
    let n = r.frames().len();
    assert!((2..=3).contains(&n), "{n} frames stored");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Abort from a pause: the run ends aborted, the journal says so, what was acquired stays
/// readable, and it cannot be resumed.
#[test]
fn abort_keeps_what_was_acquired() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("abort");
    let (o, _, _) = go(&plan, &dir, false, Script::PauseAbort(2));
    assert!(matches!(o, Outcome::Aborted(_)), "{o:?}");
    let r = replay(&dir).unwrap();
    assert!(r.aborted().is_some());
    let frames = r.frames();
    assert!(!frames.is_empty());
    let store = RunStore::open(&dir).unwrap();
    for f in frames.values() {
        assert_eq!(
            polar_engine::pixel_hash(&store.read_frame(f.index).unwrap()),
            f.hash
        );
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let local = tokio::task::LocalSet::new();
    let again = local.block_on(&rt, async {
        let (rig, engine_rig) = SimRig::start_rig(
            &plan,
            Path::new("."),
            &dir.join(".sim2"),
            run::noise_stream(&dir),
        )
        .await
        .unwrap();
        let (_ctl, link) = run::link();
        let r = run::run(&plan, engine_rig, &dir, true, link).await;
        rig.shutdown().await;
        r
    });
    assert!(again.is_err(), "an aborted run resumed");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Detach at a pause, then resume with a new rig (as `polarimeter resume` does in a new
/// process): no duplicate and no missing frame.
#[test]
fn detach_then_resume_in_a_new_rig() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("detach");
    let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(6));
    assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
    let (o, _, _) = go(&plan, &dir, true, Script::Watch);
    done(&o);
    check_frame_set(&dir, 14);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A cloud passes in the middle of set 1: the suspender rejects the set (Malus's law fails)
/// and it is taken again; the run finishes with every set accepted.
#[test]
fn suspender_rejects_a_cloudy_set_and_takes_it_again() {
    let text = format!("{CAPTURE}cloud_at_set = 1\ncloud_depth = 0.3\n");
    let plan = Plan::from_toml_str(&text).unwrap();
    let dir = temp_dir("cloud");
    let (o, _, events) = go(&plan, &dir, false, Script::Watch);
    let s = done(&o);
    assert_eq!(s.sets_rejected, 1);
    assert_eq!(s.sets_accepted, 3);
    let reason = events
        .iter()
        .find_map(|e| match e {
            Event::Set {
                set: 1, verdict, ..
            } if !verdict.accepted => Some(verdict.reason.clone()),
            _ => None,
        })
        .unwrap();
    assert!(reason.contains("Malus"), "{reason}");
    // Accepted sets' chi-square is near its expected 1 (the threshold is 2).
    for e in &events {
        if let Event::Set { verdict, .. } = e {
            if verdict.accepted {
                assert!(verdict.reduced_chi2 < 1.5, "{verdict:?}");
            }
        }
    }
    check_frame_set(&dir, 14);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Time-lapse: sets start at their interval, and every frame carries the sun's geometry.
#[test]
fn time_lapse_with_sun_geometry() {
    let text = r#"
kind = "time-lapse"
[time-lapse]
angles_deg = [0, 60, 120]
exposure_us = 2000
interval_s = 0.6
count = 3
[site]
latitude_deg = 43.08
longitude_deg = -77.67
elevation_m = 160
[simulation]
width = 64
height = 48
"#;
    let plan = Plan::from_toml_str(text).unwrap();
    let dir = temp_dir("timelapse");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    done(&o);
    check_frame_set(&dir, 9);
    let meta = RunStore::open(&dir).unwrap().read_frame_metadata().unwrap();
    for r in &meta {
        let z = r.sun_zenith_deg.unwrap();
        assert!((0.0..=180.0).contains(&z) && r.sun_azimuth_deg.unwrap().is_finite());
    }
    let firsts: Vec<i64> = meta
        .iter()
        .step_by(3)
        .map(|r| r.host_time_unix_ns)
        .collect();
    for w in firsts.windows(2) {
        assert!(w[1] - w[0] >= 550_000_000, "sets {} ns apart", w[1] - w[0]);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Adaptive: APTD re-aims the analyzer from the frames; every decision is journaled and in
/// the store, the frames stay within the budget, and the final set's SCR (as the planner
/// estimated it) is at least the first set's.
#[test]
fn adaptive_end_to_end() {
    let text = r#"
kind = "adaptive"
[adaptive]
initial_angles_deg = [0, 60, 120]
exposure_us = 3000
frame_budget = 12
darks = 1
target = { material = "panel" }
[simulation]
width = 96
height = 72
seed = 5
"#;
    let plan = Plan::from_toml_str(text).unwrap();
    let dir = temp_dir("adaptive");
    let (o, _, events) = go(&plan, &dir, false, Script::Watch);
    let s = done(&o);
    assert!(s.frames_accepted <= 13);
    let decisions: Vec<&serde_json::Value> = events
        .iter()
        .filter_map(|e| match e {
            Event::Decision(v) => Some(v),
            _ => None,
        })
        .collect();
    assert!(!decisions.is_empty());
    let first = decisions[0]["scr_last_set"].as_f64().unwrap();
    let last = decisions.last().unwrap()["scr_next"].as_f64().unwrap();
    assert!(last >= first * (1.0 - 1e-9), "SCR {first} -> {last}");
    let attrs = RunStore::open(&dir).unwrap().attributes().unwrap();
    assert_eq!(
        attrs["decisions"].as_array().unwrap().len(),
        decisions.len()
    );
    check_frame_set(&dir, s.frames_accepted);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Noise calibration: the photon transfer of the simulated camera recovers its gain K within
/// 3 % (4 exposures, one pair each, 96x72 pixels: K's statistical error is about 1 %).
#[test]
fn calibrate_noise_recovers_the_gain() {
    let text = r#"
kind = "calibrate-noise"
[calibrate-noise]
exposure_us = [200, 2000, 6000, 12000, 20000, 30000]
[simulation]
width = 96
height = 72
"#;
    let plan = Plan::from_toml_str(text).unwrap();
    let dir = temp_dir("calnoise");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    done(&o);
    let attrs = RunStore::open(&dir).unwrap().attributes().unwrap();
    let k = attrs["calibration"]["noise"]["k_dn_per_e"]["value"]
        .as_f64()
        .unwrap();
    let truth = SimRig::world(&plan, Path::new("."))
        .unwrap()
        .camera_model
        .gain_dn_per_e;
    println!("K {k} (truth {truth})");
    assert!((k / truth - 1.0).abs() < 0.03, "K {k} vs {truth}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Analyzer calibration: a reference polarizer at 30 deg; the fit finds the analyzer's zero
/// offset near 0 (the simulated stage's backlash is taken up by the approach; its encoder
/// noise is 0.3 counts, 0.001 deg) and a finite extinction ratio.
#[test]
fn calibrate_analyzer_finds_the_reference() {
    let text = r#"
kind = "calibrate-analyzer"
[calibrate-analyzer]
reference_angle_deg = 30
steps = 12
exposure_us = 3000
darks = 2
[simulation]
width = 64
height = 48
"#;
    let plan = Plan::from_toml_str(text).unwrap();
    let dir = temp_dir("calanalyzer");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    done(&o);
    let attrs = RunStore::open(&dir).unwrap().attributes().unwrap();
    let cal = &attrs["calibration"]["analyzer"];
    println!("{cal}");
    let offset = cal["zero_offset_deg"].as_f64().unwrap();
    assert!(offset.abs() < 0.1, "offset {offset} deg");
    assert!(cal["extinction_ratio"].as_f64().unwrap() > 10.0, "{cal}");
    let _ = std::fs::remove_dir_all(&dir);
}
