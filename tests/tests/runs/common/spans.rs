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
use polar_hil_mocks::camera::{CameraFaults, SimCamera, SimCameraConfig};
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
