//! The GenICam backend against Aravis's fake GigE Vision cameras (DEVICES.md 4.1, 4.2): Debian's
//! `arv-fake-gv-camera-0.8` (package `aravis-tools`) as a child process on loopback, and the
//! in-process `GvFakeCamera` behind [`FakeAnalyzerCamera`].
//!
//! Only one fake GigE Vision camera may run per host (two on 127.0.0.1 receive each other's
//! control packets), so every test takes [`FAKE_GIGE`] first. With `POLARIMETER_GENICAM_ID`
//! set, `real_camera_when_configured` runs the grab and exposure checks on that camera.

use polar_camera_aravis::{list, AnalyzerScene, AravisCamera, FakeAnalyzerCamera};
use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{
    BlockingCamera, Camera, ErrorKind, Frame, GainUnit, PixelFormat, Roi, StreamStats, TriggerMode,
};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Serialises the tests: one fake GigE Vision camera per host.
static FAKE_GIGE: Mutex<()> = Mutex::new(());

fn one_fake_at_a_time() -> MutexGuard<'static, ()> {
    // A failed test poisons the lock; the next one may still run.
    FAKE_GIGE.lock().unwrap_or_else(|p| p.into_inner())
}

const FAKE_PROGRAM: &str = "arv-fake-gv-camera-0.8";
const FAKE_ID: &str = "Aravis-Fake-GV01";
/// GigE Vision discovery answers within about a second; the fake process starts in well under
/// one. Ten seconds leaves room for a loaded CI machine.
const DISCOVERY_DEADLINE: Duration = Duration::from_secs(10);

/// `arv-fake-gv-camera-0.8 -i 127.0.0.1 [-r N]` as a child process, killed on drop.
struct FakeGv {
    child: Child,
}

impl FakeGv {
    /// Starts the fake (losing `lost_per_mille` of its stream packets) and waits until
    /// discovery finds it.
    fn start(lost_per_mille: Option<u32>) -> FakeGv {
        let mut cmd = Command::new(FAKE_PROGRAM);
        cmd.args(["-i", "127.0.0.1"]);
        if let Some(r) = lost_per_mille {
            cmd.args(["-r", &r.to_string()]);
        }
        cmd.stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        let child = cmd.spawn().unwrap_or_else(|e| {
            panic!("cannot run {FAKE_PROGRAM}: {e}; install Debian's aravis-tools (scripts/test.sh does)")
        });
        let fake = FakeGv { child };
        let t0 = Instant::now();
        loop {
            let found = list().expect("discovery");
            if found.iter().any(|c| c.id == FAKE_ID) {
                break;
            }
            assert!(
                t0.elapsed() < DISCOVERY_DEADLINE,
                "{FAKE_ID} not discovered within {DISCOVERY_DEADLINE:?}: found {found:?}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        fake
    }

    /// SIGKILL, as a camera losing power or its cable would look: no goodbye on the wire.
    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for FakeGv {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Runs an async test body; the lock is taken outside it (a std `MutexGuard` must not live
/// across an `.await`).
fn run<F: std::future::Future>(body: F) -> F::Output {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("tokio runtime")
        .block_on(body)
}

fn policy() -> ThreadPolicy {
    ThreadPolicy {
        queue_frames: 8,
        ..ThreadPolicy::default()
    }
}

/// Grabs `n` frames after skipping `skip` (frames exposed before a setting took effect).
async fn frames(cam: &mut ThreadedCamera, skip: usize, n: usize) -> Vec<Frame> {
    let mut out = Vec::new();
    for i in 0..skip + n {
        let f = cam
            .grab(Duration::from_secs(3))
            .await
            .unwrap_or_else(|e| panic!("a frame: {e}; stats {:?}", cam.stats()));
        if i >= skip {
            out.push(f);
        }
    }
    out
}

fn mean(frames: &[Frame]) -> f64 {
    frames.iter().map(Frame::mean).sum::<f64>() / frames.len() as f64
}

/// Aravis's fake paints a diagonal ramp, `(x + y + n) % 255` scaled by
/// `1 + gain + log10(exposure / 10 ms)`: at 10 ms and gain 0 every pixel follows from its left
/// and upper neighbours. A frame with a lost packet filled in by garbage or zeros would not.
fn assert_ramp(f: &Frame) {
    let p0 = u32::from(f.pixels[0]);
    for y in 0..f.height {
        for x in 0..f.width {
            let want = (p0 + x + y) % 255;
            let got = u32::from(f.at(x, y).expect("in frame"));
            assert_eq!(got, want, "frame {} pixel ({x}, {y})", f.frame_id);
        }
    }
}

/// Discovery reports the fake's identity; opening it reads what it offers (it names its exposure
/// `ExposureTimeAbs` and its gain `GainRaw`, not the SFNC `ExposureTime` / `Gain`), and every
/// setting comes back as the device applied it.
#[test]
fn discovers_opens_and_reads_settings_back() {
    let _one = one_fake_at_a_time();
    let _fake = FakeGv::start(None);
    let found = list().expect("discovery");
    let d = found
        .iter()
        .find(|c| c.id == FAKE_ID)
        .expect("the fake is listed");
    assert_eq!(
        (d.vendor.as_str(), d.model.as_str(), d.serial.as_str()),
        ("Aravis", "Fake", "GV01")
    );
    assert_eq!(d.address, "127.0.0.1");
    assert_eq!(d.protocol, "GigEVision");

    let mut cam = AravisCamera::open(FAKE_ID).expect("open");
    let info = cam.info();
    assert_eq!(info.id, FAKE_ID);
    assert_eq!(
        (info.vendor.as_str(), info.model.as_str()),
        ("Aravis", "Fake")
    );
    assert_eq!((info.sensor_width, info.sensor_height), (2048, 2048));
    // The fake offers Mono8 and Mono16 (and colour formats this crate does not read).
    assert_eq!(info.formats, vec![PixelFormat::Mono8, PixelFormat::Mono16]);
    assert_eq!(info.exposure_range_us, [10.0, 10_000_000.0]);
    assert_eq!(info.gain_unit, GainUnit::Raw, "GainRaw, no SFNC Gain");
    assert_eq!(info.gain_range, [0.0, 10.0]);
    assert!(
        cam.supports_hardware_trigger(),
        "the fake has TriggerSource Line0"
    );

    // The fake keeps the exposure in whole microseconds: 1 us tolerance.
    assert_eq!(cam.set_exposure_us(20_000.0).expect("exposure"), 20_000.0);
    let applied = cam.set_exposure_us(12_345.4).expect("exposure");
    assert!((applied - 12_345.4).abs() <= 1.0, "{applied}");
    // GainRaw is an integer: what comes back is whole and within one step of the request.
    assert_eq!(cam.set_gain(3.0).expect("gain"), 3.0);
    let g = cam.set_gain(2.6).expect("gain");
    assert!(g.fract() == 0.0 && (g - 2.6).abs() <= 1.0, "{g}");

    cam.set_pixel_format(PixelFormat::Mono16).expect("Mono16");
    cam.set_pixel_format(PixelFormat::Mono8).expect("Mono8");
    let e = cam
        .set_pixel_format(PixelFormat::Mono12)
        .expect_err("not offered");
    assert_ne!(e.kind(), ErrorKind::Disconnected, "{e}");

    let roi = Roi {
        x: 10,
        y: 20,
        width: 100,
        height: 50,
    };
    assert_eq!(cam.set_roi(roi).expect("roi"), roi, "increments are 1");

    for mode in [
        TriggerMode::Software,
        TriggerMode::Hardware,
        TriggerMode::FreeRun,
    ] {
        cam.set_trigger(mode).expect("trigger mode");
    }
    let e = cam.trigger().expect_err("free run");
    assert_eq!(e.kind(), ErrorKind::OutOfRange);

    let missing = AravisCamera::open("Aravis-Fake-NOPE").expect_err("no such camera");
    assert_eq!(missing.kind(), ErrorKind::Disconnected, "{missing}");
}

/// Through the camera thread: frames are whole ramps, a tenfold exposure brightens them by the
/// fake's own law, and frame ids increase strictly across the 16-bit GigE Vision wrap.
#[test]
fn longer_exposure_brightens_and_ids_cross_the_wrap() {
    let _one = one_fake_at_a_time();
    run(async {
        let _fake = FakeGv::start(None);
        let mut raw = AravisCamera::open(FAKE_ID).expect("open");
        // 100 frames/s: the fake's ids start near 65401, so the wrap comes after about 1.3 s.
        assert_eq!(raw.set_frame_rate_hz(100.0).expect("frame rate"), 100.0);
        let mut cam = ThreadedCamera::spawn(raw, policy()).expect("thread");
        let roi = Roi::full(256, 256);
        assert_eq!(cam.set_roi(roi).await.expect("roi"), roi);
        cam.set_pixel_format(PixelFormat::Mono8)
            .await
            .expect("Mono8");

        let mut means = Vec::new();
        for exposure_us in [10_000.0, 100_000.0] {
            assert_eq!(
                cam.set_exposure_us(exposure_us).await.expect("exposure"),
                exposure_us
            );
            cam.start().await.expect("start");
            let got = frames(&mut cam, 2, 5).await;
            cam.stop().await.expect("stop");
            for f in &got {
                f.check(FAKE_ID).expect("consistent");
                assert_eq!(
                    (f.width, f.height, f.format),
                    (256, 256, PixelFormat::Mono8)
                );
                assert_eq!(
                    f.exposure_us, exposure_us,
                    "the applied exposure rides along"
                );
                assert!(f.device_timestamp_ns.is_some());
                if exposure_us == 10_000.0 {
                    assert_ramp(f);
                }
            }
            means.push(mean(&got));
        }
        // The ramp's values are spread evenly over 0..=254 (mean 127). At 100 ms the fake scales
        // them by 1 + log10(10) = 2 and clips at 255: (2 * sum(0..=127) + 127 * 255) / 255 = 190.75,
        // a ratio of 1.502. 0.03 allows for the 256x256 window not being an exact number of ramp
        // periods (measured: DEVICES.md 4.1 has 127.0 and 190.7).
        let ratio = means[1] / means[0];
        println!(
            "mean at 10 ms = {:.2}, at 100 ms = {:.2}, ratio = {ratio:.4}",
            means[0], means[1]
        );
        assert!(
            (ratio - 1.502).abs() < 0.03,
            "ratio {ratio}, means {means:?}"
        );

        // Ids through the wrap: keep grabbing until an id past 65536 + 10 or 10 s.
        cam.set_exposure_us(10_000.0).await.expect("exposure");
        cam.start().await.expect("start");
        let t0 = Instant::now();
        let mut ids = Vec::new();
        while ids.last().is_none_or(|&id| id < 65_546) && t0.elapsed() < Duration::from_secs(10) {
            let f = cam.grab(Duration::from_secs(3)).await.expect("frame");
            ids.push(f.frame_id);
        }
        cam.stop().await.expect("stop");
        assert!(
            ids.windows(2).all(|w| w[1] > w[0]),
            "ids not increasing: {ids:?}"
        );
        assert!(
            ids.first().is_some_and(|&i| i < 65_536) && ids.last().is_some_and(|&i| i > 65_536),
            "the wrap was not crossed: {ids:?}"
        );
        println!(
            "ids {} .. {} ({} frames)",
            ids[0],
            ids[ids.len() - 1],
            ids.len()
        );
    });
}

/// With stream packets dropped (`-r`), incomplete buffers are counted and never delivered;
/// every frame that is delivered is a whole, correct image.
#[test]
fn packet_loss_yields_counted_incomplete_frames_not_garbage() {
    const LOST_PER_MILLE: u32 = 20;
    let _one = one_fake_at_a_time();
    run(async {
        let _fake = FakeGv::start(Some(LOST_PER_MILLE));
        let mut raw = AravisCamera::open(FAKE_ID).expect("open");
        raw.set_frame_rate_hz(100.0).expect("frame rate");
        let mut cam = ThreadedCamera::spawn(raw, policy()).expect("thread");
        let roi = Roi::full(128, 128);
        cam.set_roi(roi).await.expect("roi");
        cam.set_pixel_format(PixelFormat::Mono8)
            .await
            .expect("Mono8");
        cam.start().await.expect("start");
        let t0 = Instant::now();
        let mut delivered = 0u64;
        while t0.elapsed() < Duration::from_secs(4) {
            let f = cam.grab(Duration::from_secs(3)).await.expect("frame");
            f.check(FAKE_ID).expect("consistent");
            assert_eq!((f.width, f.height, f.pixels.len()), (128, 128, 128 * 128));
            assert_ramp(&f);
            delivered += 1;
        }
        cam.stop().await.expect("stop");
        let StreamStats {
            incomplete,
            dropped,
            ..
        } = cam.stats();
        let seen = delivered + dropped + incomplete;
        let fraction = incomplete as f64 / seen as f64;
        // A 128x128 Mono8 frame is 16384 bytes: 13 data packets of at most 1364 bytes (1400 less
        // 36 of headers) plus leader and trailer, 15 packets. Each is dropped with probability
        // 0.02, so (1 - 0.98^15) = 26 % of frames lack one. Over the ~400 frames of 4 s at
        // 100 frames/s the binomial spread is about 2 %; the band below is about 5 spreads wide.
        println!(
            "-r {LOST_PER_MILLE}: {delivered} delivered, {dropped} dropped, {incomplete} incomplete ({:.1} %)",
            100.0 * fraction
        );
        assert!(delivered > 50, "too few complete frames: {delivered}");
        assert!(
            (0.15..0.40).contains(&fraction),
            "incomplete fraction {fraction} (incomplete {incomplete} of {seen})"
        );
    });
}

/// The grab deadline the engine would use.
const GRAB_DEADLINE: Duration = Duration::from_secs(8);

/// Killing the fake mid-stream (SIGKILL: no goodbye on the wire) ends the stream with
/// `Disconnected`, not `Timeout`, within one grab deadline; later grabs say so at once.
#[test]
fn killing_the_camera_mid_stream_reports_disconnected() {
    let _one = one_fake_at_a_time();
    run(async {
        let mut fake = FakeGv::start(None);
        let mut cam = ThreadedCamera::spawn(AravisCamera::open(FAKE_ID).expect("open"), policy())
            .expect("thread");
        cam.set_roi(Roi::full(64, 64)).await.expect("roi");
        cam.start().await.expect("start");
        frames(&mut cam, 0, 3).await;

        fake.kill();
        let t_kill = Instant::now();
        let err = loop {
            match cam.grab(GRAB_DEADLINE).await {
                // Frames that were already queued.
                Ok(_) => continue,
                Err(e) => break e,
            }
        };
        let detect = t_kill.elapsed();
        println!("disconnect detected {detect:?} after the kill: {err}");
        assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
        // Silence before a probe (AravisOptions: 0.5 s, or 3 frame periods + exposure = 0.13 s at
        // the fake's 25 frames/s) + the probe's register read failing after Aravis's fixed GVCP
        // timeout (2.5 s measured) = about 3 s; 5 s leaves 2 s for a loaded machine and is still
        // inside the grab deadline.
        assert!(detect < Duration::from_secs(5), "took {detect:?}");
        let t0 = Instant::now();
        let again = cam.grab(GRAB_DEADLINE).await.expect_err("still gone");
        assert_eq!(again.kind(), ErrorKind::Disconnected);
        assert!(t0.elapsed() < Duration::from_millis(100));
        let e = cam.set_exposure_us(20_000.0).await.expect_err("gone");
        assert_eq!(e.kind(), ErrorKind::Disconnected);
    });
}

/// Aravis's in-process fake with a fill callback: frames follow the analyzer angle read from a
/// shared atomic, and the four-angle estimator recovers the scene's DoLP and AoP from grabbed
/// means, through the real GigE Vision path.
#[test]
fn in_process_fake_follows_the_analyzer_angle() {
    let _one = one_fake_at_a_time();
    run(async {
        let scene = AnalyzerScene {
            s0_full_scale: 0.8,
            dolp: 0.3,
            aop_rad: 30f64.to_radians(),
            reference_exposure_us: 10_000.0,
        };
        let angle_bits = Arc::new(AtomicU64::new(0f64.to_bits()));
        let source = Arc::clone(&angle_bits);
        let mut fake = FakeAnalyzerCamera::start("ANALYZER", scene, move || {
            f64::from_bits(source.load(Ordering::SeqCst))
        })
        .expect("fake");
        fake.camera()
            .expect("open")
            .set_frame_rate_hz(50.0)
            .expect("rate");
        let mut cam = ThreadedCamera::spawn(fake, policy()).expect("thread");
        assert_eq!(cam.info().id, "Aravis-Fake-ANALYZER");
        cam.set_roi(Roi::full(64, 64)).await.expect("roi");
        let exposure_us = cam.set_exposure_us(10_000.0).await.expect("exposure");
        cam.start().await.expect("start");

        let mut intensity = Vec::new();
        for deg in [0.0f64, 45.0, 90.0, 135.0] {
            let theta = deg.to_radians();
            angle_bits.store(theta.to_bits(), Ordering::SeqCst);
            // Frames made before the move may still be on the wire or queued: wait five frame
            // periods, drop what is queued, and skip one more.
            tokio::time::sleep(Duration::from_millis(100)).await;
            cam.discard_pending();
            let got = frames(&mut cam, 1, 3).await;
            let want = scene.pixel(theta, exposure_us, PixelFormat::Mono16);
            for f in &got {
                assert_eq!(f.format, PixelFormat::Mono16);
                assert!(
                    f.pixels.iter().all(|&p| p == want),
                    "analyzer {deg} deg: frame {} is not uniformly {want} (mean {})",
                    f.frame_id,
                    f.mean()
                );
            }
            intensity.push(mean(&got) / f64::from(u16::MAX));
        }
        cam.stop().await.expect("stop");

        let (i0, i45, i90, i135) = (intensity[0], intensity[1], intensity[2], intensity[3]);
        let s0 = (i0 + i45 + i90 + i135) / 2.0;
        let (s1, s2) = (i0 - i90, i45 - i135);
        let dolp = (s1 * s1 + s2 * s2).sqrt() / s0;
        let aop_deg = 0.5 * s2.atan2(s1).to_degrees();
        println!(
            "recovered S0 = {s0:.6}, DoLP = {dolp:.6} (error {:.2e}), AoP = {aop_deg:.4} deg (error {:.2e} deg)",
            dolp - scene.dolp,
            aop_deg - 30.0
        );
        // Each intensity is rounded to a whole Mono16 count, +-0.5 in ~2e4 counts (2.5e-5
        // relative): the estimates are good to a few 1e-5, so 1e-3 and 0.05 deg leave a wide margin
        // while still catching a wrong angle, a stale frame or a byte-order slip.
        assert!((s0 - 0.8).abs() < 1e-3, "S0 {s0}");
        assert!((dolp - 0.3).abs() < 1e-3, "DoLP {dolp}");
        assert!((aop_deg - 30.0).abs() < 0.05, "AoP {aop_deg}");

        // The camera thread owns the fake and ends it after `cam` is dropped; the next test's
        // fake must not meet it on 127.0.0.1.
        drop(cam);
        let t0 = Instant::now();
        while list()
            .expect("discovery")
            .iter()
            .any(|c| c.id == "Aravis-Fake-ANALYZER")
        {
            assert!(
                t0.elapsed() < DISCOVERY_DEADLINE,
                "the in-process fake did not stop"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    });
}

/// On a real camera in the lab: `POLARIMETER_GENICAM_ID=<device id> cargo test --release -p
/// polar-camera-aravis real_camera -- --nocapture`. Without the variable this test only says
/// so.
#[test]
fn real_camera_when_configured() {
    let Ok(id) = std::env::var("POLARIMETER_GENICAM_ID") else {
        println!("POLARIMETER_GENICAM_ID is not set: no real GenICam camera checked");
        return;
    };
    let _one = one_fake_at_a_time();
    run(async {
        let raw = AravisCamera::open(&id).expect("open the camera named by POLARIMETER_GENICAM_ID");
        let info = raw.info();
        println!("{info:?}");
        let mut cam = ThreadedCamera::spawn(raw, policy()).expect("thread");
        let [lo, hi] = info.exposure_range_us;
        // Two exposures a factor 4 apart inside the camera's range, around 2 ms.
        let short = (2_000.0f64).clamp(lo, hi / 4.0);
        let mut means = Vec::new();
        for request in [short, 4.0 * short] {
            let applied = cam.set_exposure_us(request).await.expect("exposure");
            // Cameras round to their increments; 1 % or 1 us, whichever is larger.
            assert!(
                (applied - request).abs() <= (0.01 * request).max(1.0),
                "asked {request} us, applied {applied} us"
            );
            cam.start().await.expect("start");
            let got = frames(&mut cam, 2, 5).await;
            cam.stop().await.expect("stop");
            for f in &got {
                f.check(&id).expect("consistent");
                assert_eq!(f.exposure_us, applied);
            }
            means.push(mean(&got));
        }
        println!("means at {short} us and {} us: {means:?}", 4.0 * short);
        // Light or dark current only adds with exposure; a saturated short exposure cannot grow.
        assert!(means[1] >= means[0] * 0.99, "{means:?}");
        println!("stats: {:?}", cam.stats());
    });
}
