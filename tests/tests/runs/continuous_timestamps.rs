//! Continuous rotation with `trigger = "timestamps"`: a simulated Thorlabs K10CR1 (velocity
//! mode, no trigger output) spins the analyzer, the camera is triggered by software, and each
//! frame's span comes from the line through the stage's position reads at the exposure's end.
//! The recorded spans are checked against the simulator's true angle, the per-half-turn
//! span-row estimates against the scene's truth and their predicted sigma, and the refusals
//! (encoder triggers on the K10CR1, any continuous plan on a stage that cannot spin) name
//! `continuous.trigger`.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use polar_engine::continuous::TriggerSource;
use polar_engine::plan::Plan;
use polar_engine::run::{self, Outcome};
use polar_engine::AngleSource;
use polar_rig::SimRig;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use super::common;

const PLAN: &str = include_str!("../../../examples/plans/continuous_timestamps.toml");

fn unix_s(t: SystemTime) -> f64 {
    t.duration_since(UNIX_EPOCH).unwrap().as_secs_f64()
}

/// The simulated stage's true output angle (radians, in `[0, 2 pi)`) sampled on the host's
/// wall clock (unix seconds, the midpoint of the clock reads around each truth read).
struct TruthTrace(Vec<(f64, f64)>);

impl TruthTrace {
    /// The true angle at unix time `t_s`, linearly interpolated between the bracketing samples
    /// (the stage turns 10 deg/s x 0.5 ms = 0.005 deg between samples at most, at constant
    /// speed, so the interpolation is exact but for the samples' own timing).
    fn at(&self, t_s: f64) -> Option<f64> {
        let i = self.0.partition_point(|s| s.0 <= t_s);
        if i == 0 || i == self.0.len() {
            return None;
        }
        let (t0, a0) = self.0[i - 1];
        let (t1, a1) = self.0[i];
        let d = polar_hal::signed_difference(a1, a0, polar_hal::TURN_RAD);
        Some(a0 + d * (t_s - t0) / (t1 - t0))
    }
}

/// Runs `plan` on the simulated rig into `dir` with nobody at the controller, sampling the
/// stage's true angle every ~0.2 ms on a thread of its own.
fn run_with_truth(plan: &Plan, dir: &Path) -> (Result<Outcome, run::RunError>, TruthTrace) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let local = tokio::task::LocalSet::new();
    local.block_on(&rt, async {
        let (rig, engine_rig) = SimRig::start_rig(
            plan,
            common::spans::plan_dir(),
            &dir.join(".sim"),
            run::noise_stream(dir),
        )
        .await
        .unwrap();
        let stop = Arc::new(AtomicBool::new(false));
        let sampler = {
            let truth = rig.server.truth_handle().angle_source();
            let stop = Arc::clone(&stop);
            std::thread::spawn(move || {
                let mut trace = Vec::new();
                while !stop.load(Ordering::Relaxed) {
                    let before = unix_s(SystemTime::now());
                    let angle = truth();
                    let after = unix_s(SystemTime::now());
                    trace.push((0.5 * (before + after), angle));
                    std::thread::sleep(Duration::from_micros(200));
                }
                trace
            })
        };
        // Nobody at the controller (a pause would detach); retries are printed.
        let (controller, link) = run::link();
        let run::Controller {
            control,
            mut events,
            ..
        } = controller;
        drop(control);
        let watcher = tokio::task::spawn_local(async move {
            while let Some(e) = events.recv().await {
                if let run::Event::Retry(reason) = e {
                    println!("retry: {reason}");
                }
            }
        });
        let outcome = run::run(plan, engine_rig, dir, false, link).await;
        let _ = watcher.await;
        stop.store(true, Ordering::Relaxed);
        let trace = sampler.join().unwrap();
        rig.shutdown().await;
        (outcome, TruthTrace(trace))
    })
}

/// A timestamps run on the simulated K10CR1 (4 frames per half turn at 10 deg/s, its top
/// speed; 2 half turns of 18 s each; 40 x 30 pixels; an exposure that saturates no pixel)
/// finishes with every frame, each recorded as `timestamps` with a positive angle sigma, and:
///
/// - each frame sweeps speed x exposure: the recorded end minus start is the fitted speed
///   times the exposure, within 0.5 % of the plan's (the fitted speed's standard error over
///   reads seconds apart is far below 0.1 %; the K10CR1's velocity parameter rounds 10 deg/s
///   to 1e-8);
/// - each frame's recorded span start is within 3 recorded sigma, plus 2 ms of the stage's
///   turn for the host's scheduling (below), of the simulator's true angle at the exposure's
///   start, after removing the one offset the reads cannot see: the
///   simulated K10CR1's output lags its counter by half its 0.02 deg backlash while it turns
///   forward (`polar_hil_mocks::apt::AptSimConfig::k10cr1`), so the true angle is the
///   counter's less 0.01 deg. The exposure's end on the wall clock is the frame's device
///   timestamp plus the smallest host-minus-device offset of its half turn (the camera stamps
///   the host time after drawing the frame, a few tens of microseconds);
/// - the per-half-turn span-row estimates of S1 and S2 from the stored frames, recorded spans
///   and the largest recorded sigma are within 2 predicted sigma of the scene's truth for
///   95 +/- 2 % of the 4800 values (95.45 % for Gaussian errors; the binomial spread over
///   4800 values is 0.3 %, and the rest covers the Gaussian approximation of Poisson and
///   quantisation noise; a span misplaced by a tenth of a degree would not show here, which is
///   what the truth check above is for);
/// - the store holds one product set per half turn; `check` and scripts/check_run.py accept it.
#[test]
fn timestamps_run_on_the_simulated_k10cr1() {
    let mut plan = Plan::from_toml_str(PLAN).unwrap();
    // Small frames: the camera stamps a frame's host time after drawing it, and the truth
    // check below takes the exposure's end from those stamps.
    plan.simulation.width = 40;
    plan.simulation.height = 30;
    let world = SimRig::world(&plan, common::spans::plan_dir()).unwrap();
    let exposure_us = common::spans::unsaturated_exposure_us(&world);
    {
        let c = plan.continuous_mut().unwrap();
        c.half_turns = 2;
        c.exposure_us = exposure_us;
    }
    let c = plan.continuous().cloned().unwrap();
    assert_eq!(c.trigger, TriggerSource::Timestamps);
    c.validate().unwrap();
    let dir = common::temp_dir("continuous-timestamps-k10cr1");
    let (outcome, truth) = run_with_truth(&plan, &dir);
    let summary = match outcome.unwrap() {
        Outcome::Done(s) => s,
        other => panic!("the run did not finish: {other:?}"),
    };
    let n = u64::from(c.frames_per_half_turn) * u64::from(c.half_turns);
    println!(
        "timestamps run: {} frames, {} half turns, {} retries, elapsed {:.2} s, exposure {exposure_us} us",
        summary.frames_accepted, summary.sets_accepted, summary.retries, summary.elapsed_s
    );
    assert_eq!(summary.frames_accepted, n);
    assert_eq!(summary.sets_accepted, u64::from(c.half_turns));

    let store = polar_engine::store::RunStore::open(&dir).unwrap();
    // The frames that count: a half turn cut by a late exposure is taken again whole, its
    // earlier frames stored but superseded in the journal.
    let superseded = polar_engine::journal::replay(&dir)
        .unwrap()
        .rejected_frames();
    let records: Vec<_> = store
        .read_frame_metadata()
        .unwrap()
        .into_iter()
        .filter(|r| !superseded.contains(&r.index))
        .collect();
    assert_eq!(records.len() as u64, n, "one frame per planned step");
    let exposure_s = exposure_us * 1e-6;
    let half_backlash_deg = 0.01;
    // The reference is no better than 2 ms on a shared 2-core host (10 deg/s x 2 ms): the
    // truth sampler and the camera's host stamps run on threads the host may run late, and
    // the run's own exposure-end and read times meet the same scheduling, which the recorded
    // sigma (the reads' round trip and the line's fit) does not cover.
    let host_slack_deg = c.speed_deg_per_s * 2e-3;
    let mut worst_z: f64 = 0.0;
    for h in 0..u64::from(c.half_turns) {
        let frames: Vec<_> = records.iter().filter(|r| r.set == Some(h)).collect();
        let offset_s = frames
            .iter()
            .map(|r| {
                r.host_time_unix_ns as f64 * 1e-9 - r.device_timestamp_ns.unwrap() as f64 * 1e-9
            })
            .fold(f64::INFINITY, f64::min);
        for r in frames {
            assert_eq!(r.angle_source, AngleSource::Timestamps);
            assert!(
                r.angle_sigma_deg > 0.0,
                "frame {}: sigma {}",
                r.index,
                r.angle_sigma_deg
            );
            let swept = r.angle_end_deg - r.angle_start_deg;
            assert!(
                (swept / c.span_deg() - 1.0).abs() < 0.005,
                "frame {}: swept {swept} deg, speed x exposure {} deg",
                r.index,
                c.span_deg()
            );
            let end_s = r.device_timestamp_ns.unwrap() as f64 * 1e-9 + offset_s;
            let true_start_deg = truth
                .at(end_s - exposure_s)
                .expect("the truth trace covers the run")
                .to_degrees();
            let d = (r.angle_start_deg - half_backlash_deg - true_start_deg).rem_euclid(180.0);
            let d = if d > 90.0 { d - 180.0 } else { d };
            let z = d / r.angle_sigma_deg;
            println!(
                "frame {}: start {:.5} deg, truth {:.5} deg (+ {half_backlash_deg}), error \
                 {d:+.5} deg, sigma {:.5} deg, z {z:+.2}",
                r.index,
                r.angle_start_deg,
                true_start_deg.rem_euclid(180.0),
                r.angle_sigma_deg
            );
            worst_z = worst_z.max(z.abs());
            assert!(
                d.abs() <= 3.0 * r.angle_sigma_deg + host_slack_deg,
                "frame {}: span start {} deg is {d} deg from the true {} deg (sigma {} deg)",
                r.index,
                r.angle_start_deg,
                true_start_deg,
                r.angle_sigma_deg
            );
        }
    }
    assert_eq!(
        store.product_slots().unwrap().len() as u64,
        u64::from(c.half_turns),
        "one product set per half turn"
    );

    let z = common::spans::half_turn_z_scores(&store, &world, &records, u64::from(c.half_turns));
    let within = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
    let mean = z.iter().sum::<f64>() / z.len() as f64;
    println!(
        "timestamps run: worst span z {worst_z:.2}; {} values, within 2 sigma {within:.4}, mean z {mean:.4}",
        z.len()
    );
    assert!((within - 0.95).abs() <= 0.02, "within 2 sigma {within}");

    assert!(polar_engine::check::check_run(&dir).unwrap().ok);
    common::outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `trigger = "encoder"` on the K10CR1 (no position-compare output) is refused at the start
/// with an error naming `continuous.trigger`, its value and the allowed `timestamps`, and a
/// continuous plan on a stage that cannot spin at all (an Elliptec ELL14) is refused naming
/// `continuous.trigger`; nothing is stored either time.
#[test]
fn refusals_name_the_trigger() {
    let mut plan = Plan::from_toml_str(PLAN).unwrap();
    plan.continuous_mut().unwrap().trigger = TriggerSource::Encoder;
    let dir = common::temp_dir("continuous-timestamps-encoder");
    let e = common::spans::run_sim(&plan, &dir)
        .expect_err("refused")
        .to_string();
    assert!(
        e.contains("continuous.trigger = \"encoder\"") && e.contains("\"timestamps\""),
        "{e}"
    );
    assert!(!dir.join("run.zarr").exists(), "nothing stored");
    let _ = std::fs::remove_dir_all(&dir);

    let mut plan = Plan::from_toml_str(PLAN).unwrap();
    plan.simulation.stage = Some(polar_engine::plan::SimStage {
        dialect: "elliptec".into(),
        model: Some("ell14".into()),
    });
    let dir = common::temp_dir("continuous-timestamps-elliptec");
    let e = common::spans::run_sim(&plan, &dir)
        .expect_err("refused")
        .to_string();
    assert!(
        e.contains("continuous.trigger = timestamps") && e.contains("cannot spin"),
        "{e}"
    );
    assert!(!dir.join("run.zarr").exists(), "nothing stored");
    let _ = std::fs::remove_dir_all(&dir);
}
