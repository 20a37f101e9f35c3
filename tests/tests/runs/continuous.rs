//! Continuous rotation: the span-row Stokes estimate on frames the simulated camera integrates
//! along the analyzer's true path, against the scene's truth and the predicted sigma; the bias
//! of point rows on the same frames; trigger pulses through the `Rotator` trait against the
//! simulated stage's encoder.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use nalgebra::Vector3;
use polar_engine::continuous::SpanEstimator;
use polar_engine::plan::Plan;
use polar_hal::{ContinuousSupport, Roi, Rotator, TURN_RAD};
use polar_hil_mocks::camera::{noise_seed, CameraFaults, SimCamera, SimCameraConfig};
use polar_rig::{SimRig, SimWorld};
use std::sync::Arc;
use std::time::Duration;

const PLAN: &str = include_str!("../../../examples/plans/continuous.toml");

/// One half turn's simulated frames and the estimates from them.
struct HalfTurn {
    /// Per frame, per pixel, DN.
    frames: Vec<Vec<u16>>,
    spans_rad: Vec<(f64, f64)>,
    exposure_s: f64,
    camera: SimCamera,
    world: SimWorld,
}

/// Four frames per half turn, each sweeping `span_deg` from its trigger at k * 45 deg,
/// exposed for the longest time at which the brightest pixel's mean stays below 60 % of the
/// full well (so no pixel saturates: the estimator's model has no clipping). The camera
/// integrates along a path sampled at 257 points of constant speed (its own path integration,
/// the same as in a run).
fn half_turn(span_deg: f64, seed: u64) -> HalfTurn {
    let plan = Plan::from_toml_str(PLAN).unwrap();
    let world = SimRig::world(&plan, common::spans::plan_dir()).unwrap();
    let camera = SimCamera::new(
        SimCameraConfig {
            id: "test".into(),
            camera: world.camera_model.clone(),
            scene: Arc::clone(&world.scene),
            max_frame_rate_hz: 200.0,
            faults: CameraFaults::default(),
            seed,
            noise_stream: 0,
        },
        Arc::new(|| 0.0),
    )
    .unwrap();
    let roi = Roi::full(world.scene.width, world.scene.height);
    // The brightest pixel at 1 ms over the analyzer's phase (a still analyzer is brighter
    // than any span).
    let peak_1ms = (0..8)
        .map(|k| {
            let a = f64::from(k) * 22.5f64.to_radians();
            camera
                .mean_electrons(roi, a, a, 1000.0)
                .unwrap()
                .into_iter()
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    let exposure_us = (0.6 * world.camera_model.full_well_e / peak_1ms * 1000.0).floor();
    let span_rad = span_deg.to_radians();
    let spans_rad: Vec<(f64, f64)> = (0..4)
        .map(|k| {
            let a = f64::from(k) * 45f64.to_radians();
            (a, a + span_rad)
        })
        .collect();
    let cam_model = camera.camera_at_gain(0.0);
    let frames = spans_rad
        .iter()
        .enumerate()
        .map(|(k, &(a, b))| {
            let path: Vec<(f64, f64)> = (0..=256)
                .map(|j| {
                    let f = f64::from(j) / 256.0;
                    (f * exposure_us * 1e-6, a + f * (b - a))
                })
                .collect();
            let electrons = camera
                .mean_electrons_along(roi, &path, exposure_us)
                .unwrap();
            polar_model::montecarlo::expose_pixels(
                &cam_model,
                &electrons,
                exposure_us * 1e-6,
                noise_seed(seed, 0, k as u64),
            )
            .unwrap()
        })
        .collect();
    HalfTurn {
        frames,
        spans_rad,
        exposure_s: exposure_us * 1e-6,
        camera,
        world,
    }
}

/// Per pixel: (estimate - truth) / predicted sigma for S1 and S2, with `estimator`; the
/// predicted sigma always from the span rows (the frames' true noise).
fn normalised_errors(h: &HalfTurn, estimator: &SpanEstimator, truth: &SpanEstimator) -> Vec<f64> {
    let scene = &h.world.scene;
    let mut z = Vec::with_capacity(2 * scene.stokes.len());
    for (p, s) in scene.stokes.iter().enumerate() {
        let y: Vec<f64> = h.frames.iter().map(|f| f64::from(f[p])).collect();
        let est = estimator.estimate(&y);
        let predicted = truth.predict(Vector3::new(s[0], s[1], s[2])).unwrap();
        for c in 1..3 {
            let sigma = predicted.stokes_cov_dn2[(c, c)].sqrt();
            z.push((est[c] - predicted.stokes_dn[c]) / sigma);
        }
    }
    z
}

/// The span-row estimate on simulated continuous frames (4 per half turn, each sweeping
/// 40 deg) is within its predicted sigma: the fraction of S1 and S2 pixel values within 2
/// predicted sigma of the scene's truth is 95.45 % for a Gaussian; the tolerance 95 +/- 2 %
/// covers the binomial spread of 38400 values (0.1 %) and the Gaussian approximation of the
/// Poisson and quantisation noise, not a bias (a bias of 0.3 sigma would already lower the
/// fraction to 94 %). The mean normalised error is within 0.05 (its standard error over
/// 38400 values is 0.005; pixels share their texture draw but not their noise).
#[test]
fn span_rows_estimate_within_predicted_sigma() {
    let h = half_turn(40.0, 7);
    let sensor = h.camera.sensor().clone();
    let span = SpanEstimator::new(&sensor, &h.spans_rad, h.exposure_s, 0.0).unwrap();
    let z = normalised_errors(&h, &span, &span);
    let within = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
    let mean = z.iter().sum::<f64>() / z.len() as f64;
    println!(
        "span rows: {} values, within 2 sigma {:.4}, mean z {mean:.4}, exposure {} us",
        z.len(),
        within,
        h.exposure_s * 1e6
    );
    assert!((within - 0.95).abs() <= 0.02, "within 2 sigma: {within}");
    assert!(mean.abs() < 0.05, "mean normalised error {mean}");
}

/// Without the span correction (point rows at each span's centre) the same frames give S1 and
/// S2 scaled by sinc(40 deg) = 0.9211. On the values whose predicted bias
/// `(1 - sinc D) |S| / sigma` exceeds 2 sigma (about 2000 of them), the measured bias
/// (signed towards zero) is above 2 sigma per value and within 5 % of the predicted one: each
/// value adds +-1 sigma of noise, so the mean's standard error is about 1/sqrt(2000) = 0.02
/// sigma, under 1 % of the bias; 5 % leaves room for the noise model's approximations. The
/// fraction of all values within 2 sigma falls below 93 %, outside the span rows' 95 +/- 2 %.
#[test]
fn point_rows_show_the_smear_bias() {
    let span_deg = 40.0;
    let h = half_turn(span_deg, 11);
    let sensor = h.camera.sensor().clone();
    let span = SpanEstimator::new(&sensor, &h.spans_rad, h.exposure_s, 0.0).unwrap();
    let point = SpanEstimator::point_rows(&sensor, &h.spans_rad, h.exposure_s).unwrap();
    let z_point = normalised_errors(&h, &point, &span);
    let sinc = polar_model::span::sinc(f64::to_radians(span_deg));
    let mut measured = Vec::new();
    let mut predicted_bias = Vec::new();
    for (p, s) in h.world.scene.stokes.iter().enumerate() {
        let truth = span.predict(Vector3::new(s[0], s[1], s[2])).unwrap();
        for c in 1..3 {
            let sigma = truth.stokes_cov_dn2[(c, c)].sqrt();
            let b = (1.0 - sinc) * truth.stokes_dn[c].abs() / sigma;
            if b > 2.0 {
                // The estimate is pulled towards zero: the signed error against the truth's
                // sign is negative.
                measured.push(-z_point[2 * p + c - 1] * truth.stokes_dn[c].signum());
                predicted_bias.push(b);
            }
        }
    }
    assert!(
        measured.len() > 100,
        "{} values with a predicted bias above 2 sigma",
        measured.len()
    );
    let m = measured.iter().sum::<f64>() / measured.len() as f64;
    let p = predicted_bias.iter().sum::<f64>() / predicted_bias.len() as f64;
    let within = z_point.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z_point.len() as f64;
    println!(
        "point rows: {} values with predicted bias > 2 sigma: measured {m:.3} sigma, \
         predicted {p:.3} sigma; within 2 sigma overall {within:.4}",
        measured.len()
    );
    assert!(
        m > 2.0 && (m - p).abs() <= 0.05 * p,
        "measured {m}, predicted {p}"
    );
    assert!(within < 0.93, "within 2 sigma with point rows: {within}");
}

/// Trigger pulses through the `Rotator` trait (the boxed `AnyRotator` of the simulated rig):
/// the stage reports velocity and trigger support; armed at a first count and an interval of
/// 45 deg (an eighth of a turn in counts) while spinning at 360 deg/s, every pulse's encoder
/// count is first + k x interval within the simulated encoder's read noise, its index is k,
/// and its angle is the count's angle (to 1e-12 rad).
#[test]
fn trigger_counts_match_the_encoder() {
    let plan = Plan::from_toml_str(PLAN).unwrap();
    let link_dir = std::env::temp_dir().join(format!("polar-continuous-{}", std::process::id()));
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let (rig, _camera) = SimRig::start(&plan, common::spans::plan_dir(), &link_dir, 0).unwrap();
        let mut stage = rig.connect_stage().await.unwrap();
        assert_eq!(
            stage.continuous_support(),
            ContinuousSupport::VelocityAndTrigger
        );
        let counts_per_turn = i64::from(stage.info().counts_per_turn);
        let interval = counts_per_turn / 8;
        let first = counts_per_turn / 16;
        let to_rad = |c: i64| c as f64 / counts_per_turn as f64 * TURN_RAD;
        stage
            .arm_trigger(to_rad(first), to_rad(interval), 6)
            .await
            .unwrap();
        stage.spin(360f64.to_radians()).await.unwrap();
        for k in 0..6u32 {
            let pulse = stage.next_trigger(Duration::from_secs(5)).await.unwrap();
            assert_eq!(pulse.index, k);
            // The simulated controller reports the latched count through its encoder's
            // read noise (0.3 counts rms, rounded): within 2 counts (6.7 sigma).
            let expected = first + i64::from(k) * interval;
            assert!(
                (pulse.counts - expected).abs() <= 2,
                "pulse {k}: count {} against {expected}",
                pulse.counts
            );
            assert!((pulse.angle_rad - to_rad(pulse.counts)).abs() < 1e-12);
        }
        let stopped = stage.stop_spin().await.unwrap();
        assert!((0.0..TURN_RAD).contains(&stopped));
        drop(stage);
        rig.shutdown().await;
    });
    let _ = std::fs::remove_dir_all(&link_dir);
}

use super::common;

/// A continuous run of the example plan (4 frames per half turn at 360 deg/s, 6 half turns,
/// an exposure that saturates no pixel) on the simulated rig: it finishes with every frame;
/// each frame's span starts at its frame's trigger angle within 2 encoder counts (0.005 deg:
/// the stage's pulse latches the count at the armed position) and sweeps speed x exposure
/// (within one count, 0.0025 deg); the per-half-turn span-row estimates of S1 and S2 from
/// the stored frames and their recorded spans are within 2 predicted sigma of the scene's
/// truth for 95 +/- 2 % of the values (95.45 % for Gaussian errors; the tolerance covers the
/// binomial spread over 230400 values, 0.04 %, the Gaussian approximation of Poisson and
/// quantisation noise, and the exposure starting up to one line poll (50 us, 0.018 deg)
/// after the pulse; a bias of 0.3 sigma, say a frame paired with the wrong pulse, would
/// lower it below 94 %). The store holds one product set per half turn; `check` and
/// scripts/check_run.py accept the run.
#[test]
fn continuous_run_on_the_simulated_rig() {
    let mut plan = Plan::from_toml_str(PLAN).unwrap();
    let world = SimRig::world(&plan, common::spans::plan_dir()).unwrap();
    let exposure_us = common::spans::unsaturated_exposure_us(&world);
    {
        let c = plan.continuous_mut().unwrap();
        c.half_turns = 6;
        c.exposure_us = exposure_us;
    }
    let c = plan.continuous().cloned().unwrap();
    c.validate().unwrap();
    let dir = common::temp_dir("continuous-run");
    let outcome = common::spans::run_sim(&plan, &dir).unwrap();
    let n = u64::from(c.frames_per_half_turn) * u64::from(c.half_turns);
    let summary = match outcome {
        polar_engine::run::Outcome::Done(s) => s,
        other => panic!("the run did not finish: {other:?}"),
    };
    println!(
        "continuous run: {} frames, {} half turns, elapsed {:.2} s, device {:.2} s, exposure {exposure_us} us",
        summary.frames_accepted, summary.sets_accepted, summary.elapsed_s, summary.device_s
    );
    assert_eq!(summary.frames_accepted, n);
    assert_eq!(summary.sets_accepted, u64::from(c.half_turns));

    let store = polar_engine::store::RunStore::open(&dir).unwrap();
    let records = store.read_frame_metadata().unwrap();
    assert_eq!(records.len() as u64, n, "one frame per planned step");
    let count_deg = 360.0 / 144_000.0;
    for r in &records {
        assert_eq!(r.angle_source, polar_engine::AngleSource::EncoderTrigger);
        let d = (r.angle_start_deg - r.commanded_angle_deg).rem_euclid(180.0);
        assert!(
            d.min(180.0 - d) <= 2.0 * count_deg,
            "frame {}: span starts at {} deg, its trigger angle is {}",
            r.index,
            r.angle_start_deg,
            r.commanded_angle_deg
        );
        let swept = r.angle_end_deg - r.angle_start_deg;
        assert!(
            (swept - c.span_deg()).abs() <= count_deg,
            "frame {}: swept {swept} deg, speed x exposure {} deg",
            r.index,
            c.span_deg()
        );
    }
    assert_eq!(
        store.product_slots().unwrap().len() as u64,
        u64::from(c.half_turns),
        "one product set per half turn"
    );

    // Per half turn: the span-row estimate from the stored frames against the truth.
    let z = common::spans::half_turn_z_scores(&store, &world, &records, u64::from(c.half_turns));
    let within = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
    let mean = z.iter().sum::<f64>() / z.len() as f64;
    println!(
        "continuous run: {} values, within 2 sigma {within:.4}, mean z {mean:.4}",
        z.len()
    );
    assert!((within - 0.95).abs() <= 0.02, "within 2 sigma {within}");

    assert!(polar_engine::check::check_run(&dir).unwrap().ok);
    common::outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuous run whose camera drops 8 % of its frames (a dropped frame is a trigger the
/// run sees no frame for): each half turn cut short is taken again whole, up to
/// `policy.attempts` = 10 tries (at 8 % per frame a half turn fails 10 times in a row with
/// probability 0.28^10 = 3e-6). The run finishes with every half turn; it retried at least
/// once (the seeded dice drop a frame in the first half turns); every frame the retries cut
/// off is named in a `frames-superseded` entry of its half turn, so the stored frames are the
/// accepted ones plus the superseded ones (counts, exact); and every planned step has exactly
/// one accepted frame, by the engine's check and zarr-python's (scripts/check_run.py).
#[test]
fn a_half_turn_cut_by_a_dropped_frame_is_taken_again_whole() {
    let mut plan = Plan::from_toml_str(&format!(
        "{PLAN}\n[policy]\nattempts = 10\n[simulation]\nwidth = 48\nheight = 36\nseed = 5\n\
         camera_faults = {{ drop_frame = 0.08 }}\n"
    ))
    .unwrap();
    {
        let c = plan.continuous_mut().unwrap();
        c.half_turns = 8;
        c.exposure_us = 500.0;
    }
    let dir = common::temp_dir("continuous-dropped");
    let summary = match common::spans::run_sim(&plan, &dir).unwrap() {
        polar_engine::run::Outcome::Done(s) => s,
        other => panic!("the run did not finish: {other:?}"),
    };
    println!(
        "dropped frames: {} stored, {} accepted, {} retries",
        summary.frames_stored, summary.frames_accepted, summary.retries
    );
    assert_eq!(summary.frames_accepted, 32, "8 half turns x 4 frames");
    assert_eq!(summary.sets_accepted, 8);
    assert!(summary.retries >= 1, "no frame was dropped: {summary:?}");
    let replay = polar_engine::journal::replay(&dir).unwrap();
    let superseded: Vec<(u64, Vec<u64>)> = replay
        .entries
        .iter()
        .filter_map(|e| match e {
            polar_engine::journal::Entry::FramesSuperseded { set, frames, .. } => {
                Some((*set, frames.clone()))
            }
            _ => None,
        })
        .collect();
    let named: u64 = superseded.iter().map(|(_, f)| f.len() as u64).sum();
    assert_eq!(
        summary.frames_stored,
        summary.frames_accepted + named,
        "stored = accepted + superseded: {superseded:?}"
    );
    let frames = replay.frames();
    for (set, list) in &superseded {
        for i in list {
            assert_eq!(frames[i].set, Some(*set), "frame {i} is of its half turn");
        }
    }
    let counted = replay.rejected_frames();
    let counted = frames.keys().filter(|i| !counted.contains(i)).count();
    assert_eq!(counted, 32, "one counted frame per planned step");
    common::check_frame_set(&dir, 32);
    assert!(polar_engine::check::check_run(&dir).unwrap().ok);
    common::outside_check(&dir, true);
    let _ = std::fs::remove_dir_all(&dir);
}
