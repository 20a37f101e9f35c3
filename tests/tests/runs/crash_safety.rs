//! Interrupted, resumed and damaged runs stay whole datasets: each test is a way a run could
//! lose or spoil data, checked from the outside (the journal, the store, and zarr-python
//! through `scripts/check_run.py`).
#![allow(clippy::unwrap_used)]

use super::common;

use common::{check_frame_set, done, go, outside_check, temp_dir, try_run, Script};
use polar_engine::check::check_run;
use polar_engine::journal::{replay, Entry};
use polar_engine::plan::Plan;
use polar_engine::run::Outcome;
use polar_engine::store::RunStore;
use std::collections::BTreeSet;
use std::time::Duration;

/// 1 dark, 3 sets of 4 angles, 1 dark: 14 steps.
const CAPTURE: &str = r#"
name = "capture"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [300]
repeats = 3
darks_before = 1
darks_after = 1
[simulation]
width = 48
height = 36
seed = 5
"#;

/// A process that stops at a pause and a new one that resumes: the sets done before the
/// pause are not checked again, so each set has one product slot and the summary counts 3
/// sets; every array reads in zarr-python, whose parser refuses a checksum codec written as
/// a bare string (what zarrs writes when it re-serialises metadata it read back).
#[test]
fn resumed_run_has_one_product_slot_per_set_and_reads_in_python() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("resume-products");
    let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(6));
    assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
    let done_before = replay(&dir).unwrap().sets_done().len();
    assert!(done_before >= 1, "no set was done before the pause");
    let (o, _, _) = go(&plan, &dir, true, Script::Watch);
    let s = done(&o);
    assert_eq!(s.sets_accepted, 3, "{s:?}");
    check_frame_set(&dir, 14);
    let store = RunStore::open(&dir).unwrap();
    let sets: Vec<u64> = store
        .product_slots()
        .unwrap()
        .iter()
        .filter_map(|s| s.set)
        .collect();
    assert_eq!(sets, vec![0, 1, 2], "product slots' sets");
    let meta = std::fs::read_to_string(dir.join("run.zarr/frames/pixels/zarr.json")).unwrap();
    assert!(
        meta.contains(r#""name":"crc32c""#) || meta.contains(r#""name": "crc32c""#),
        "the checksum codec must be an object: {meta}"
    );
    assert!(check_run(&dir).unwrap().ok);
    outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `run` into a directory that holds a run's store (its journal gone) refuses, names
/// `resume`, and leaves every stored frame as it was.
#[test]
fn run_refuses_a_directory_holding_a_run() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("refuse");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    done(&o);
    let hashes = |d: &std::path::Path| -> Vec<u64> {
        let store = RunStore::open(d).unwrap();
        (0..store.frame_count())
            .map(|i| polar_engine::pixel_hash(&store.read_frame(i).unwrap()))
            .collect()
    };
    let before = hashes(&dir);
    std::fs::remove_file(dir.join(polar_engine::journal::JOURNAL_FILE)).unwrap();
    let e = try_run(&plan, &dir, false).unwrap_err().to_string();
    assert!(e.contains("resume") && e.contains("run.zarr"), "{e}");
    assert_eq!(hashes(&dir), before, "stored frames changed");
    // An empty journal is no different.
    std::fs::write(dir.join(polar_engine::journal::JOURNAL_FILE), b"").unwrap();
    assert!(try_run(&plan, &dir, false).is_err());
    assert_eq!(hashes(&dir), before, "stored frames changed");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The simulated camera's frame ids restart in a new process; its noise must not. Darks at
/// one exposure differ only by their noise (read noise of a few DN on 1728 pixels), so two
/// equal darks mean a repeated draw. With 17 darks the products subtract the dark map (16 or
/// more), half of it taken by the process before the pause: docs/DATASET.md's reference
/// recomputes the products from the store alone (`dark_source`), as for a scalar dark.
#[test]
fn a_resumed_process_never_repeats_a_noise_draw() {
    let text = CAPTURE.replace("darks_before = 1", "darks_before = 17");
    let plan = Plan::from_toml_str(&text).unwrap();
    let dir = temp_dir("noise");
    let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(3));
    assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
    let (o, _, _) = go(&plan, &dir, true, Script::Watch);
    done(&o);
    let r = replay(&dir).unwrap();
    let frames = r.frames();
    let hashes: BTreeSet<u64> = frames.values().map(|f| f.hash).collect();
    assert_eq!(hashes.len(), frames.len(), "two frames have equal pixels");
    let ids: Vec<u64> = frames.values().map(|f| f.frame_id).collect();
    assert!(
        ids.iter().filter(|&&i| i == 0).count() >= 2,
        "the test needs a frame id taken by both processes: {ids:?}"
    );
    let meta = std::fs::read(dir.join("run.zarr/products/zarr.json")).unwrap();
    let sources: serde_json::Value = serde_json::from_slice(&meta).unwrap();
    assert_eq!(
        sources["attributes"]["dark_source"]["0"]["dark_frames"],
        serde_json::json!(17),
        "{sources:?}"
    );
    outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Three angles at two exposures: the suspender's S0-change check compares a set with the
/// last one at its own exposure (S0 doubles between exposures by design), so every set is
/// accepted at its first try.
#[test]
fn three_angles_at_two_exposures_finish() {
    let text = CAPTURE
        .replace("[0, 45, 90, 135]", "[0, 60, 120]")
        .replace("exposure_us = [300]", "exposure_us = [150, 300]")
        .replace("repeats = 3", "repeats = 2");
    let plan = Plan::from_toml_str(&text).unwrap();
    let dir = temp_dir("two-exposures");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    let s = done(&o);
    assert_eq!(s.sets_accepted, 4, "{s:?}");
    assert_eq!(s.sets_rejected, 0, "{s:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A frame chunk damaged while the run was paused: the resume names it, keeps the chunk
/// aside (renamed, not deleted), takes the step and its set again, and finishes within a
/// deadline (a 120 s watchdog, not a hang); `check_run` and zarr-python find the finished
/// run whole.
#[test]
fn a_damaged_chunk_is_kept_aside_and_its_step_taken_again() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("damaged");
    let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(6));
    assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
    let r = replay(&dir).unwrap();
    let victim = r
        .sets_done()
        .first()
        .map(|s| s.frames[1])
        .expect("a set done before the pause");
    let victim_step = r.frames()[&victim].step;
    let chunk = dir.join(format!("run.zarr/frames/pixels/c/{victim}/0/0"));
    let mut bytes = std::fs::read(&chunk).unwrap();
    bytes[40] ^= 0xFF;
    std::fs::write(&chunk, &bytes).unwrap();

    let (tx, rx) = std::sync::mpsc::channel();
    let (p, d) = (plan.clone(), dir.clone());
    std::thread::spawn(move || {
        let _ = tx.send(go(&p, &d, true, Script::Watch).0);
    });
    let o = rx
        .recv_timeout(Duration::from_secs(120))
        .expect("the resume did not finish within 120 s");
    done(&o);
    let r = replay(&dir).unwrap();
    let found: Vec<(u64, u64, String)> = r
        .entries
        .iter()
        .filter_map(|e| match e {
            Entry::FrameDamaged {
                index,
                step,
                kept_as,
                ..
            } => Some((*index, *step, kept_as.clone())),
            _ => None,
        })
        .collect();
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!((found[0].0, found[0].1), (victim, victim_step));
    let kept = std::fs::read(dir.join(&found[0].2)).unwrap();
    assert_eq!(kept, bytes, "the damaged chunk is kept as it was");
    let later = r
        .frames()
        .values()
        .filter(|f| f.step == victim_step && f.index > victim)
        .count();
    assert_eq!(later, 1, "the damaged step was taken again once");
    let c = check_run(&dir).unwrap();
    assert!(c.ok && c.kept_aside.len() == 1, "{c:?}");
    outside_check(&dir, true);

    // Damage after the run finished: `check` names it; nothing is changed.
    let other = r.frames().keys().copied().find(|&i| i != victim).unwrap();
    let chunk = dir.join(format!("run.zarr/frames/pixels/c/{other}/0/0"));
    let mut bytes = std::fs::read(&chunk).unwrap();
    bytes[40] ^= 0xFF;
    std::fs::write(&chunk, &bytes).unwrap();
    let c = check_run(&dir).unwrap();
    assert!(!c.ok, "{c:?}");
    assert!(
        c.damaged.len() == 1 && c.damaged[0].contains(&format!("frame {other}")),
        "{c:?}"
    );
    assert_eq!(std::fs::read(&chunk).unwrap(), bytes);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A time-lapse of 1 s intervals left paused for 3 s: the sets whose time passed by more
/// than half an interval follow the plan's `late` policy, and the journal and the store's
/// `late_sets` say which and how late. With "skip" they are neither taken nor planned; with
/// the default ("take") they are taken at once.
#[test]
fn a_late_time_lapse_follows_its_stated_policy() {
    for policy in ["skip", "take"] {
        let text = format!(
            r#"
name = "late"
kind = "time-lapse"
[time-lapse]
angles_deg = [0, 60, 120]
exposure_us = 250
interval_s = 1.0
count = 5
late = "{policy}"
[simulation]
width = 32
height = 24
seed = 4
"#
        );
        let plan = Plan::from_toml_str(&text).unwrap();
        let dir = temp_dir(&format!("late-{policy}"));
        let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(3));
        assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
        std::thread::sleep(Duration::from_secs(3));
        let (o, _, _) = go(&plan, &dir, true, Script::Watch);
        let s = done(&o).clone();
        let r = replay(&dir).unwrap();
        let late: Vec<(u64, f64, String)> = r
            .entries
            .iter()
            .filter_map(|e| match e {
                Entry::SetLate {
                    set,
                    late_s,
                    action,
                    ..
                } => Some((*set, *late_s, action.clone())),
                _ => None,
            })
            .collect();
        // Sets 1 and 2 were due 1 s and 2 s after the start; the resume came after 3 s.
        assert!(late.len() >= 2, "{policy}: {late:?}");
        let want = if policy == "skip" { "skipped" } else { "taken" };
        for (set, late_s, action) in &late {
            assert_eq!(action, want, "{policy}: set {set}");
            assert!(*late_s > 0.5, "{policy}: set {set} late by {late_s}");
        }
        let store = RunStore::open(&dir).unwrap();
        let stored = store.attributes().unwrap()["late_sets"]
            .as_array()
            .map_or(0, Vec::len);
        assert_eq!(stored, late.len(), "{policy}: the store's late_sets");
        let sets_with_frames: BTreeSet<u64> = r.frames().values().filter_map(|f| f.set).collect();
        if policy == "skip" {
            assert_eq!(s.sets_accepted as usize, 5 - late.len(), "{policy}: {s:?}");
            for (set, _, _) in &late {
                assert!(
                    !sets_with_frames.contains(set),
                    "skipped set {set} has frames"
                );
            }
        } else {
            assert_eq!(s.sets_accepted, 5, "{policy}: {s:?}");
        }
        assert!(check_run(&dir).unwrap().ok);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// An adaptive run interrupted (twice, if the planner goes on past its second set) and resumed: the planner's decision log, replayed over
/// the stored frames (the planner rebuilt set by set from what the store holds), gives the
/// decisions recorded, so the planner saw exactly the stored frames; each decision counts
/// the frames of the sets before it.
#[test]
fn a_resumed_adaptive_run_replays_to_its_recorded_decisions() {
    let text = r#"
name = "adaptive"
kind = "adaptive"
[adaptive]
initial_angles_deg = [0, 60, 120]
channels = 3
exposure_us = 250
frame_budget = 15
darks = 1
target = { material = "panel" }
min_separation_deg = 30
[simulation]
width = 64
height = 48
seed = 6
"#;
    let plan = Plan::from_toml_str(text).unwrap();
    let dir = temp_dir("adaptive-replay");
    // A pause asked during the first set takes effect after it; the second during the
    // second set (the count of frames done runs over both processes).
    let (o, _, _) = go(&plan, &dir, false, Script::PauseDetach(2));
    assert!(matches!(o, Outcome::Paused(_)), "{o:?}");
    let (o, _, _) = go(&plan, &dir, true, Script::PauseDetach(5));
    assert!(matches!(o, Outcome::Paused(_) | Outcome::Done(_)), "{o:?}");
    if matches!(o, Outcome::Paused(_)) {
        let (o, _, _) = go(&plan, &dir, true, Script::Watch);
        done(&o);
    }
    let r = replay(&dir).unwrap();
    let recorded: Vec<serde_json::Value> =
        r.decisions().into_iter().map(|(_, v)| v.clone()).collect();
    assert!(recorded.len() >= 2, "{recorded:?}");
    let world = polar_rig::SimRig::world(&plan, std::path::Path::new(".")).unwrap();
    let mask = polar_rig::simulated::target_mask(&plan, &world.scene).unwrap();
    let replayed =
        polar_engine::run::replayed_decisions(&plan, &dir, &world.camera_model, &mask).unwrap();
    assert_eq!(
        replayed, recorded,
        "replayed decisions differ from the recorded ones"
    );
    // Each decision uses the frames of every set before it (3 per set).
    for (k, d) in recorded.iter().enumerate() {
        assert_eq!(d["frames_used"].as_u64(), Some(3 * (k as u64 + 1)), "{d}");
    }
    assert!(check_run(&dir).unwrap().ok);
    outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Every frame of a finished step-and-shoot run records its analyzer span as the settled
/// reading (start = end = measured angle, exactly: the same value; source settled), which
/// `scripts/check_run.py` accepts; a store whose span runs backwards (end 1 deg before start)
/// or that lacks one of the four span arrays is refused, naming what is wrong.
#[test]
fn frames_record_their_span_and_the_outside_check_reads_it() {
    let plan = Plan::from_toml_str(CAPTURE).unwrap();
    let dir = temp_dir("span");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    done(&o);
    let store = RunStore::open(&dir).unwrap();
    let mut records = store.read_frame_metadata().unwrap();
    assert_eq!(records.len(), 14);
    for r in &records {
        assert_eq!(r.angle_source, polar_engine::AngleSource::Settled);
        assert_eq!(r.angle_start_deg.to_bits(), r.measured_angle_deg.to_bits());
        assert_eq!(r.angle_end_deg.to_bits(), r.measured_angle_deg.to_bits());
    }
    outside_check(&dir, true);
    let Some(py) = common::python() else {
        let _ = std::fs::remove_dir_all(&dir);
        return;
    };
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/check_run.py");
    let check = || {
        let out = std::process::Command::new(&py)
            .arg(&script)
            .arg(&dir)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
        )
    };
    records[3].angle_end_deg = records[3].angle_start_deg - 1.0;
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    let (code, text) = check();
    assert_eq!(code, Some(1), "{text}");
    assert!(
        text.contains("analyzer span") && text.contains("[3]"),
        "{text}"
    );
    // A span array one value short.
    std::fs::remove_dir_all(dir.join("run.zarr/frames/angle_sigma_deg")).unwrap();
    let (code, text) = check();
    assert_eq!(code, Some(1), "{text}");
    assert!(text.contains("angle_sigma_deg"), "{text}");
    let _ = std::fs::remove_dir_all(&dir);
}
