//! What the continuous-rotation tests share: an exposure that saturates no pixel of the
//! simulated scene, a plan run on the simulated rig with nobody at the controller, and the
//! span-row estimates of a stored run against the scene's truth.

use nalgebra::Vector3;
use polar_engine::continuous::SpanEstimator;
use polar_engine::plan::Plan;
use polar_engine::run::{self, Outcome};
use polar_engine::store::RunStore;
use polar_engine::FrameRecord;
use polar_hal::Roi;
use polar_hil_mocks::camera::{CameraFaults, ExposureLog, SimCamera, SimCameraConfig};
use polar_rig::SimWorld;
use std::path::Path;
use std::sync::Arc;

/// The example plans' folder, where their relative paths start.
pub fn plan_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/plans"))
}

/// The longest exposure, us, at which the scene's brightest pixel stays below 60 % of the full
/// well at any of 8 analyzer angles 22.5 deg apart (no pixel saturates: the span estimator's
/// model has no clipping).
pub fn unsaturated_exposure_us(world: &SimWorld) -> f64 {
    let camera = SimCamera::new(
        SimCameraConfig {
            id: "exposure".into(),
            camera: world.camera_model.clone(),
            scene: Arc::clone(&world.scene),
            max_frame_rate_hz: 200.0,
            faults: CameraFaults::default(),
            seed: 1,
            noise_stream: 0,
        },
        Arc::new(|| 0.0),
    )
    .unwrap();
    let roi = Roi::full(world.scene.width, world.scene.height);
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
    (0.6 * world.camera_model.full_well_e / peak_1ms * 1000.0).floor()
}

/// Runs `plan` on the simulated rig into `dir` with nobody at the controller (a pause
/// detaches; the outcome says why).
pub fn run_sim(plan: &Plan, dir: &Path) -> Result<Outcome, polar_rig::SimRunError> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let local = tokio::task::LocalSet::new();
    local.block_on(&rt, async {
        let (controller, link) = run::link();
        drop(controller);
        polar_rig::run_simulated(plan, plan_dir(), dir, false, link).await
    })
}

/// Per half turn `0..half_turns` of a stored run: the span-row estimate of S1 and S2 from its
/// frames, their recorded spans and the largest recorded angle sigma, against the scene's
/// truth, in units of the predicted sigma (one value per pixel and component).
pub fn half_turn_z_scores(
    store: &RunStore,
    world: &SimWorld,
    records: &[FrameRecord],
    half_turns: u64,
) -> Vec<f64> {
    let mut z = Vec::new();
    for h in 0..half_turns {
        let mut frames: Vec<_> = records.iter().filter(|r| r.set == Some(h)).collect();
        frames.sort_by_key(|r| r.step);
        let spans: Vec<(f64, f64)> = frames
            .iter()
            .map(|r| (r.angle_start_deg.to_radians(), r.angle_end_deg.to_radians()))
            .collect();
        let sigma_rad = frames
            .iter()
            .map(|r| r.angle_sigma_deg.to_radians())
            .fold(0.0, f64::max);
        let pixels: Vec<Vec<u16>> = frames
            .iter()
            .map(|r| store.read_frame(r.index).unwrap())
            .collect();
        let exposure_s = frames[0].exposure_us * 1e-6;
        let est = SpanEstimator::new(&world.sensor, &spans, exposure_s, sigma_rad).unwrap();
        for (p, s) in world.scene.stokes.iter().enumerate() {
            let y: Vec<f64> = pixels.iter().map(|f| f64::from(f[p])).collect();
            let e = est.estimate(&y);
            let predicted = est.predict(Vector3::new(s[0], s[1], s[2])).unwrap();
            for k in 1..3 {
                let sigma = predicted.stokes_cov_dn2[(k, k)].sqrt();
                z.push((e[k] - predicted.stokes_dn[k]) / sigma);
            }
        }
    }
    z
}

/// The frames of a stored run that count: a half turn cut by a late exposure is taken again
/// whole, its earlier frames stored but superseded in the journal.
pub fn counted_records(store: &RunStore, dir: &Path) -> Vec<FrameRecord> {
    let superseded = polar_engine::journal::replay(dir)
        .unwrap()
        .rejected_frames();
    store
        .read_frame_metadata()
        .unwrap()
        .into_iter()
        .filter(|r| !superseded.contains(&r.index))
        .collect()
}

/// Recorded span starts against the simulated camera's true angles.
pub struct SpanStarts {
    /// The fraction within 2 recorded sigma.
    pub within_2_sigma: f64,
    /// The largest error in recorded sigma.
    pub worst_z: f64,
    /// The mean error, degrees (a bias of the recorded starts).
    pub mean_error_deg: f64,
}

/// Each record's span start, less `lag_deg` (an offset of the stage's output from its reads,
/// such as half a backlash), against the analyzer's true angle when its exposure started (the
/// camera's `exposures` log, by frame id), in recorded sigma; prints each frame.
pub fn span_start_z(records: &[FrameRecord], exposures: &ExposureLog, lag_deg: f64) -> SpanStarts {
    let mut z = Vec::with_capacity(records.len());
    let mut errors = Vec::with_capacity(records.len());
    for r in records {
        let truth = exposures
            .get(r.frame_id)
            .unwrap_or_else(|| panic!("frame {}: no exposure truth", r.frame_id));
        let true_deg = truth.start_rad.to_degrees();
        let d = (r.angle_start_deg - lag_deg - true_deg).rem_euclid(180.0);
        let d = if d > 90.0 { d - 180.0 } else { d };
        let zi = d / r.angle_sigma_deg;
        println!(
            "frame {}: start {:.5} deg, truth {:.5} deg (+ {lag_deg}), error {d:+.5} deg, \
             sigma {:.5} deg, z {zi:+.2}",
            r.index,
            r.angle_start_deg,
            true_deg.rem_euclid(180.0),
            r.angle_sigma_deg
        );
        z.push(zi);
        errors.push(d);
    }
    let n = z.len().max(1) as f64;
    let starts = SpanStarts {
        within_2_sigma: z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / n,
        worst_z: z.iter().fold(0.0, |m: f64, v| m.max(v.abs())),
        mean_error_deg: errors.iter().sum::<f64>() / n,
    };
    println!(
        "span starts: {} frames, {:.1} % within 2 recorded sigma, worst z {:.2}, mean error \
         {:+.5} deg",
        z.len(),
        100.0 * starts.within_2_sigma,
        starts.worst_z,
        starts.mean_error_deg
    );
    starts
}
