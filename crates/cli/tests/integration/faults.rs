//! The CI-sized fault campaign: every fault kind of the simulators (stage link and device
//! faults, camera frame faults, a camera that disconnects) fires at least once, through the real
//! drivers and the engine. Every run must end done (after pauses and resumes as needed) with
//! no lost frame and no silently corrupt frame: each accepted frame's mean must be the
//! truth's at its measured angle (`acquire::check_frames_against_truth`). `polarimeter bench
//! faults --faults 1000` runs the big one.
#![allow(clippy::unwrap_used)]

#[test]
fn every_fault_kind_no_loss_no_silent_corruption() {
    let base = std::env::temp_dir().join(format!("polar-faults-test-{}", std::process::id()));
    let c = polar_cli::acquire::campaign(60, 7, &base).unwrap();
    let _ = std::fs::remove_dir_all(&base);
    println!(
        "{} runs, {} faults, {} resumes, {} sets rejected, {} retries, {} frames checked",
        c.runs, c.faults, c.resumes, c.sets_rejected, c.retries, c.frames_checked
    );
    for (kind, runs, faults, secs) in &c.per_kind {
        println!("{kind}: {runs} runs, {faults} faults, {secs:.1} s");
        assert!(*runs >= 1, "{kind} never ran");
        assert!(*faults >= 1, "{kind} never fired");
    }
    assert!(c.faults >= 60);
    assert_eq!(c.lost_frames, 0);
    assert_eq!(c.corrupt_frames, 0);
    assert!(c.frames_checked >= 8 * c.runs);
    // The faults did something the engine had to survive.
    assert!(c.retries + c.sets_rejected + c.resumes > 0);
}
