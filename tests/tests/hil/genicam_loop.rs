//! The GenICam path in the closed loop with a simulated stage: Aravis's in-process fake GigE
//! camera painting each frame from the stage simulator's true angle, the stage driven by its
//! real driver over a pseudo-terminal. It lives here, above the camera backend and the
//! drivers, because it needs both.

use polar_camera_aravis::{list, AnalyzerScene, FakeAnalyzerCamera};
use polar_drivers::link::SerialPath;
use polar_drivers::native::{self, NativeRotator};
use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{Camera, Roi, Rotator};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::native::{NativeConfig, NativeDevice};
use polar_hil_mocks::serve::SimServer;
use std::time::{Duration, Instant};

/// The GenICam path in the closed loop with the simulated stage. Our firmware's simulated
/// rotator runs on a real pseudo-terminal and is driven by `NativeRotator`. The in-process fake
/// GigE camera paints each frame from the stage's **true** output angle (`TruthHandle`), not
/// from the angle commanded. Moving through 0/45/90/135 and solving least squares with the
/// angles read back recovers the scene's DoLP to 2e-3 and its AoP to 0.2 deg. The stage lands
/// within its 0.05 deg backlash and a fraction of a count (0.0025 deg) of encoder noise of the
/// readback, which moves the recovered AoP by at most that much. Mono16 rounding adds a few 1e-5.
#[test]
fn genicam_closed_loop_with_the_simulated_stage() {
    let _one = super::cameras::one_fake_at_a_time();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("tokio runtime");
    rt.block_on(async {
        let dir = std::env::temp_dir().join(format!("polar-aravis-loop-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let link = dir.join("stage");
        let sim = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 9);
        let server = SimServer::pty(sim, FaultProfile::default(), 9, &link).expect("pty");
        let mut stage = NativeRotator::connect(
            Box::new(SerialPath {
                path: link.to_string_lossy().into_owned(),
                baud: 115_200,
            }),
            native::default_policy(),
        )
        .await
        .expect("stage");

        let scene = AnalyzerScene {
            s0_full_scale: 0.8,
            dolp: 0.4,
            aop_rad: (-25f64).to_radians(),
            reference_exposure_us: 10_000.0,
        };
        let truth = server.truth_handle().angle_source();
        let mut fake = FakeAnalyzerCamera::start("LOOP", scene, move || truth()).expect("fake");
        fake.camera()
            .expect("open")
            .set_frame_rate_hz(50.0)
            .expect("rate");
        let policy = ThreadPolicy {
            queue_frames: 8,
            ..ThreadPolicy::default()
        };
        let mut cam = ThreadedCamera::spawn(fake, policy).expect("thread");
        cam.set_roi(Roi::full(32, 32)).await.expect("roi");
        cam.set_exposure_us(10_000.0).await.expect("exposure");
        cam.start().await.expect("start");

        let mut angles = Vec::new();
        let mut intensity = Vec::new();
        for deg in [0.0f64, 45.0, 90.0, 135.0] {
            let at = stage.move_to(deg.to_radians()).await.expect("move");
            // Frames exposed during the move may be queued or on the wire: wait five frame
            // periods, drop the queue, skip one more.
            tokio::time::sleep(Duration::from_millis(100)).await;
            cam.discard_pending();
            cam.grab(Duration::from_secs(3)).await.expect("a frame");
            let mut sum = 0.0;
            for _ in 0..2 {
                sum += cam.grab(Duration::from_secs(3)).await.expect("a frame").mean();
            }
            angles.push(at);
            intensity.push(sum / 2.0 / f64::from(u16::MAX));
        }
        cam.stop().await.expect("stop");

        // Least squares with rows 0.5 [1, cos 2a, sin 2a] at the angles read back.
        let mut ata = [[0.0f64; 3]; 3];
        let mut aty = [0.0f64; 3];
        for (a, y) in angles.iter().zip(&intensity) {
            let row = [0.5, 0.5 * (2.0 * a).cos(), 0.5 * (2.0 * a).sin()];
            for i in 0..3 {
                aty[i] += row[i] * y;
                for j in 0..3 {
                    ata[i][j] += row[i] * row[j];
                }
            }
        }
        let m = nalgebra::Matrix3::from_fn(|i, j| ata[i][j]);
        let s = m.try_inverse().expect("well-posed") * nalgebra::Vector3::from(aty);
        let dolp = s[1].hypot(s[2]) / s[0];
        let aop_deg = 0.5 * s[2].atan2(s[1]).to_degrees();
        println!(
            "closed loop: angles {:?} deg, DoLP {dolp:.5} (error {:.1e}), AoP {aop_deg:.3} deg (error {:.3} deg)",
            angles.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
            dolp - 0.4,
            aop_deg + 25.0
        );
        assert!((dolp - 0.4).abs() < 2e-3, "DoLP {dolp}");
        assert!((aop_deg + 25.0).abs() < 0.2, "AoP {aop_deg}");

        drop(cam);
        server.shutdown().await;
        let _ = std::fs::remove_dir_all(&dir);
        let t0 = Instant::now();
        while list()
            .expect("discovery")
            .iter()
            .any(|c| c.id == "Aravis-Fake-LOOP")
        {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "the in-process fake did not stop"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    });
}
