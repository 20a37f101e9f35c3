//! The simulated camera through the driver stack.
//! - The closed loop: our firmware's simulated stage, served on a real pseudo-terminal and
//!   driven by `NativeRotator`, turns the analyzer. The simulated camera, run by
//!   `ThreadedCamera`, renders each frame through the stage's true angle.
//! - Stokes is reconstructed from 0/45/90/135. About 95 % of the pixels must fall within two
//!   predicted sigma of the ground truth.
//! - The camera's faults, as the async camera reports them.

use nalgebra::{DMatrix, DVector};
use polar_drivers::link::SerialPath;
use polar_drivers::native::{self, NativeRotator};
use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{Camera, ErrorKind, Roi, Rotator, TriggerMode};
use polar_hil_mocks::camera::{CameraFaults, Layout, SimCamera, SimCameraConfig, SimScene};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::native::{NativeConfig, NativeDevice};
use polar_hil_mocks::serve::SimServer;
use polar_model::scene_file::Scene;
use polar_model::sensor::Camera as CameraModel;
use std::sync::Arc;
use std::time::Duration;

const WIDTH: u32 = 160;
const HEIGHT: u32 = 120;

/// The rooftop example with an aluminium panel added (`examples/rooftop_panels.toml`): paint,
/// glass and metal on asphalt and grass.
fn scene() -> Scene {
    Scene::from_toml_str(include_str!("../../examples/rooftop_panels.toml")).expect("scene")
}

fn sim_scene() -> Arc<SimScene> {
    let scene = scene();
    let names: Vec<String> = scene.materials.iter().map(|m| m.name.clone()).collect();
    let layout = Layout::panels_on_ground(&names);
    Arc::new(
        SimScene::render(
            &scene.spec,
            &scene.materials,
            &layout,
            WIDTH,
            HEIGHT,
            1e-3,
            7,
        )
        .expect("render"),
    )
}

fn camera_model() -> CameraModel {
    CameraModel::from_toml_str(include_str!("../../examples/cameras/cmos_modern.toml"))
        .expect("camera")
}

fn config(scene: Arc<SimScene>, faults: CameraFaults) -> SimCameraConfig {
    SimCameraConfig {
        id: "sim".into(),
        camera: camera_model(),
        scene,
        max_frame_rate_hz: 200.0,
        faults,
        seed: 11,
        noise_stream: 0,
    }
}

/// The exposure at which the brightest pixel at 0, 45, 90 or 135 deg collects `fraction` of
/// the full well (whole microseconds).
fn well_fraction_exposure_us(cam: &SimCamera, fraction: f64) -> f64 {
    let full = Roi::full(WIDTH, HEIGHT);
    let peak_e_per_us = [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|d| {
            let e = cam
                .mean_electrons(full, d.to_radians(), d.to_radians(), 1.0)
                .expect("electrons");
            e.into_iter().fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    (fraction * camera_model().full_well_e / peak_e_per_us)
        .clamp(10.0, 1e6)
        .round()
}

/// Every material of the layout is in the truth, panels sit over the ground, and each
/// region's mean Stokes is its material's (the texture is zero-mean: within 5 standard errors
/// of the per-pixel spread).
#[test]
fn scene_layout_and_truth() {
    let s = sim_scene();
    assert_eq!(s.materials, ["asphalt", "grass", "panel", "glass", "metal"]);
    assert_eq!(s.stokes.len(), (WIDTH * HEIGHT) as usize);
    for (k, name) in s.materials.iter().enumerate() {
        let px: Vec<[f64; 3]> = s
            .stokes
            .iter()
            .zip(&s.region)
            .filter(|(_, &r)| usize::from(r) == k)
            .map(|(v, _)| *v)
            .collect();
        assert!(px.len() > 500, "{name}: {} pixels", px.len());
        let n = px.len() as f64;
        let mean = px.iter().map(|v| v[0]).sum::<f64>() / n;
        let var = px.iter().map(|v| (v[0] - mean).powi(2)).sum::<f64>() / (n - 1.0);
        let want = s.material_means[k][0];
        assert!(
            (mean - want).abs() <= 5.0 * (var / n).sqrt() + 1e-12 * want,
            "{name}: mean S0 {mean} vs {want}"
        );
    }
}

/// The closed loop: 0/45/90/135 deg through the native stage over a pty and the simulated
/// camera; Stokes by least squares with the analyzer model at the angles read back. For an
/// unbiased Gaussian estimate, `P(|z| < 2) = 95.45 %`. The pixels' share within 2 predicted
/// sigma must be 95 +/- 2 %. The slack covers:
/// - the sampling spread, 0.1 % for 57600 values;
/// - Poisson skew at a few hundred electrons;
/// - the stage's encoder noise. A 12-count error moves a bright pixel by well under 0.2 sigma.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closed_loop_stokes_within_predicted_sigma() {
    let dir = std::env::temp_dir().join(format!("polar-camera-loop-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let link = dir.join("stage");
    let sim = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 3);
    let server = SimServer::pty(sim, FaultProfile::default(), 3, &link).expect("pty");
    let mut stage = NativeRotator::connect(
        Box::new(SerialPath {
            path: link.to_string_lossy().into_owned(),
            baud: 115_200,
        }),
        native::default_policy(),
    )
    .await
    .expect("stage");

    let scene = sim_scene();
    let sim_cam = SimCamera::new(
        config(Arc::clone(&scene), CameraFaults::default()),
        server.truth_handle().angle_source(),
    )
    .expect("camera");
    let cam_model = camera_model();
    let exposure_us = well_fraction_exposure_us(&sim_cam, 0.5);
    let sensor = sim_cam.sensor().clone();
    let mut cam = ThreadedCamera::spawn(sim_cam, ThreadPolicy::default()).expect("spawn");
    cam.set_trigger(TriggerMode::Software)
        .await
        .expect("trigger mode");
    let applied = cam.set_exposure_us(exposure_us).await.expect("exposure");
    assert_eq!(applied, exposure_us);
    cam.start().await.expect("start");

    let mut angles = Vec::new();
    let mut frames = Vec::new();
    for deg in [0.0f64, 45.0, 90.0, 135.0] {
        let at = stage.move_to(deg.to_radians()).await.expect("move");
        cam.discard_pending();
        cam.trigger().await.expect("fire");
        let f = cam.grab(Duration::from_secs(5)).await.expect("frame");
        assert_eq!((f.width, f.height), (WIDTH, HEIGHT));
        angles.push(at);
        frames.push(f);
    }
    cam.stop().await.expect("stop");

    // Per pixel: y = K G W S + dark, Var y_i = K^2 (e_i + dark_e + sigma_d^2) + 1/12.
    let k = cam_model.gain_dn_per_e;
    let g = sensor.responsivity_e_per_s() * exposure_us * 1e-6;
    let w = sensor.intensities_from_stokes(&angles).expect("W");
    let dn_from_radiance = &w * (k * g);
    let pinv = dn_from_radiance
        .clone()
        .pseudo_inverse(1e-12)
        .expect("pseudo-inverse");
    let dark_e = cam_model.dark_current_e_per_s * exposure_us * 1e-6;
    let dark_dn = cam_model.offset_dn + k * dark_e;
    let (mut within, mut total) = (0usize, 0usize);
    let mut per_component = [0usize; 3];
    for (p, truth) in scene.stokes.iter().enumerate() {
        let y = DVector::from_iterator(4, frames.iter().map(|f| f64::from(f.pixels[p]) - dark_dn));
        let s_hat = &pinv * &y;
        let t = nalgebra::Vector3::new(truth[0], truth[1], truth[2]);
        let e = &w * t * g;
        let var = DMatrix::from_diagonal(&DVector::from_iterator(
            4,
            e.iter()
                .map(|ei| k * k * (ei + dark_e + cam_model.read_noise_e.powi(2)) + 1.0 / 12.0),
        ));
        let cov = &pinv * var * pinv.transpose();
        for c in 0..3 {
            let z = (s_hat[c] - t[c]) / cov[(c, c)].sqrt();
            total += 1;
            if z.abs() < 2.0 {
                within += 1;
                per_component[c] += 1;
            }
        }
    }
    let share = within as f64 / total as f64;
    let n = scene.stokes.len() as f64;
    let shares: Vec<f64> = per_component.iter().map(|&c| c as f64 / n).collect();
    println!(
        "within 2 sigma: {:.2} % (S0, S1, S2: {shares:.4?})",
        100.0 * share
    );
    assert!(
        (0.93..=0.97).contains(&share),
        "{:.2} % of pixels within 2 predicted sigma, shares per component {shares:?}",
        100.0 * share
    );
    server.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// A longer exposure brightens the frame in proportion above the black level, below
/// saturation (20 % and 60 % of the full well at the brightest pixel; the shot noise of 19200
/// pixels averages out to well under 1 %), and the settings read back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exposure_scales_the_signal() {
    let angle: polar_hil_mocks::camera::AngleSource = Arc::new(|| 0.3);
    let sim_cam =
        SimCamera::new(config(sim_scene(), CameraFaults::default()), angle).expect("camera");
    let short_us = well_fraction_exposure_us(&sim_cam, 0.2);
    let mut cam = ThreadedCamera::spawn(sim_cam, ThreadPolicy::default()).expect("spawn");
    let model = camera_model();
    let mut means = Vec::new();
    for exposure_us in [short_us, 3.0 * short_us] {
        assert_eq!(
            cam.set_exposure_us(exposure_us).await.expect("exposure"),
            exposure_us
        );
        cam.start().await.expect("start");
        let f = cam.grab(Duration::from_secs(5)).await.expect("frame");
        cam.stop().await.expect("stop");
        assert_eq!(f.exposure_us, exposure_us);
        let dark =
            model.offset_dn + model.gain_dn_per_e * model.dark_current_e_per_s * exposure_us * 1e-6;
        means.push(f.mean() - dark);
    }
    let ratio = means[1] / means[0];
    assert!((ratio - 3.0).abs() < 0.03, "ratio {ratio}");
}

/// Faults through the async camera: truncated frames are counted and never delivered, a stuck
/// frame repeats its predecessor's pixels under a new id, dropped frames leave gaps in the ids,
/// and a disconnect is reported as `Disconnected` (and stays so).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn faults_are_reported() {
    let faults = CameraFaults {
        drop_frame: 0.15,
        truncate_frame: 0.15,
        stuck_frame: 0.15,
        disconnect_after_frames: 60,
        ..CameraFaults::default()
    };
    let angle: polar_hil_mocks::camera::AngleSource = Arc::new(|| 0.0);
    let sim_cam = SimCamera::new(config(sim_scene(), faults), angle).expect("camera");
    let mut cam = ThreadedCamera::spawn(
        sim_cam,
        ThreadPolicy {
            queue_frames: 64,
            ..ThreadPolicy::default()
        },
    )
    .expect("spawn");
    cam.set_exposure_us(500.0).await.expect("exposure");
    cam.start().await.expect("start");
    let mut frames = Vec::new();
    let err = loop {
        match cam.grab(Duration::from_secs(5)).await {
            Ok(f) => frames.push(f),
            Err(e) => break e,
        }
    };
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    let s = cam.stats();
    assert!(s.incomplete >= 2, "{s:?}");
    let ids: Vec<u64> = frames.iter().map(|f| f.frame_id).collect();
    assert!(ids.windows(2).all(|w| w[1] > w[0]), "{ids:?}");
    let gaps = ids.windows(2).filter(|w| w[1] > w[0] + 1).count();
    assert!(gaps >= 2, "dropped or truncated frames leave gaps: {ids:?}");
    let repeats = frames
        .windows(2)
        .filter(|w| w[0].pixels == w[1].pixels)
        .count();
    assert!(repeats >= 1, "a stuck frame repeats its predecessor");
    // Fresh noise otherwise: two frames in a row are never equal without the fault.
    assert!(repeats < frames.len() / 2);
    let again = cam.grab(Duration::from_secs(1)).await.expect_err("gone");
    assert_eq!(again.kind(), ErrorKind::Disconnected);
}

/// The exposure-end report comes before the frame, names the frame that follows, and is safe
/// to move on: a camera whose analyzer jumps (0.3 -> 1.2 rad) as soon as the end is reported
/// gives a frame bit-identical to one taken with the analyzer still (same seed and frame id,
/// so the same Poisson draws for the same means). The control, a jump right after the
/// trigger of a 20 ms exposure, changes the frame: the comparison can fail.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn moving_at_exposure_end_does_not_reach_the_frame() {
    use std::sync::atomic::{AtomicU64, Ordering};
    let scene = sim_scene();
    let take = |jump_at_end: Option<bool>| {
        let scene = Arc::clone(&scene);
        async move {
            let psi = Arc::new(AtomicU64::new(0.3f64.to_bits()));
            let source = Arc::clone(&psi);
            let angle: polar_hil_mocks::camera::AngleSource =
                Arc::new(move || f64::from_bits(source.load(Ordering::SeqCst)));
            let sim_cam =
                SimCamera::new(config(scene, CameraFaults::default()), angle).expect("camera");
            let mut cam = ThreadedCamera::spawn(sim_cam, ThreadPolicy::default()).expect("spawn");
            cam.set_exposure_us(20_000.0).await.expect("exposure");
            cam.set_trigger(TriggerMode::Software)
                .await
                .expect("trigger");
            cam.start().await.expect("start");
            cam.trigger().await.expect("fire");
            if jump_at_end == Some(false) {
                psi.store(1.2f64.to_bits(), Ordering::SeqCst);
            }
            let ended = cam
                .exposure_end(Duration::from_secs(5))
                .await
                .expect("exposure end");
            if jump_at_end == Some(true) {
                psi.store(1.2f64.to_bits(), Ordering::SeqCst);
            }
            let frame = cam.grab(Duration::from_secs(5)).await.expect("frame");
            assert_eq!(ended, Some(frame.frame_id), "the end names the frame");
            frame.pixels
        }
    };
    let still = take(None).await;
    assert_eq!(take(Some(true)).await, still, "moved at the exposure end");
    assert_ne!(take(Some(false)).await, still, "moved during the exposure");
}

/// An analyzer turning during the exposure: the frame is the time average of Malus's law along
/// the path. Over a half turn every pixel sees only its unpolarised part (the mean of two
/// orthogonal still frames); a sampled constant-speed path across the 180/0 deg wrap equals the
/// closed-form span (the samples are unwrapped modulo 180 deg); and a 60 deg span differs from
/// the average of its two end rows (cos D against the true sin(D)/D). Tolerances are rounding
/// (1e-9 relative) except the last, a physical difference of several percent of the polarised
/// signal.
#[test]
fn a_turning_analyzer_averages_malus_law_along_its_path() {
    let cam = SimCamera::new(
        config(sim_scene(), CameraFaults::default()),
        Arc::new(|| 0.0),
    )
    .expect("camera");
    let full = Roi::full(WIDTH, HEIGHT);
    let deg = |d: f64| d.to_radians();
    let close = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 1e-9 * x.abs().max(y.abs()).max(1.0))
    };
    let half_turn = cam
        .mean_electrons(full, deg(20.0), deg(200.0), 1000.0)
        .expect("half turn");
    let a = cam
        .mean_electrons(full, deg(20.0), deg(20.0), 1000.0)
        .unwrap();
    let b = cam
        .mean_electrons(full, deg(110.0), deg(110.0), 1000.0)
        .unwrap();
    let unpolarised: Vec<f64> = a.iter().zip(&b).map(|(x, y)| 0.5 * (x + y)).collect();
    assert!(close(&half_turn, &unpolarised));

    // 170 -> 200 deg at constant speed, sampled every 1 deg as the stage reports it (wrapped).
    let path: Vec<(f64, f64)> = (0..=30)
        .map(|k| {
            let d = 170.0 + k as f64;
            (k as f64, deg(d).rem_euclid(std::f64::consts::TAU))
        })
        .collect();
    let sampled = cam.mean_electrons_along(full, &path, 1000.0).unwrap();
    let span = cam
        .mean_electrons(full, deg(170.0), deg(200.0), 1000.0)
        .unwrap();
    assert!(close(&sampled, &span));

    // The end-row average is wrong for a wide span: compare the polarised part of the
    // glass's brightest pixel.
    let wide = cam
        .mean_electrons(full, deg(0.0), deg(60.0), 1000.0)
        .unwrap();
    let ends: Vec<f64> = {
        let e0 = cam
            .mean_electrons(full, deg(0.0), deg(0.0), 1000.0)
            .unwrap();
        let e1 = cam
            .mean_electrons(full, deg(60.0), deg(60.0), 1000.0)
            .unwrap();
        e0.iter().zip(&e1).map(|(x, y)| 0.5 * (x + y)).collect()
    };
    let centre = cam
        .mean_electrons(full, deg(30.0), deg(30.0), 1000.0)
        .unwrap();
    let c0 = cam
        .mean_electrons(full, deg(120.0), deg(120.0), 1000.0)
        .unwrap();
    // Polarised parts relative to the unpolarised mean at the span's centre.
    let (mut best, mut k_best) = (0.0, 0);
    for k in 0..centre.len() {
        let p = (centre[k] - c0[k]).abs();
        if p > best {
            best = p;
            k_best = k;
        }
    }
    let mean = 0.5 * (centre[k_best] + c0[k_best]);
    let modulation = |x: f64| (x - mean) / (0.5 * (centre[k_best] - c0[k_best]));
    let sinc = deg(60.0).sin() / deg(60.0);
    assert!((modulation(wide[k_best]) - sinc).abs() < 1e-9);
    assert!((modulation(ends[k_best]) - deg(60.0).cos()).abs() < 1e-9);
}
