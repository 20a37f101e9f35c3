//! Each dialect's driver against its simulator over a real pseudo-terminal, opened through the
//! stable link as a real device would be (`/dev/serial/by-id/...`): moves verified against the
//! simulator's ground truth, then an unplug: the driver reports Disconnected while the device
//! is away and, once it is back at a new pseudo-terminal behind the same link, reopens it,
//! re-identifies (and re-homes) and works again. Real time, so a few moves only.

use polar_drivers::elliptec::{self, ElliptecRotator};
use polar_drivers::fw102c::{self, Fw102c};
use polar_drivers::link::{Connector, SerialPath};
use polar_drivers::native::{self, NativeRotator};
use polar_hal::{signed_difference, ErrorKind, FilterWheel, Rotator, TURN_RAD};
use polar_hil_mocks::elliptec::{ElliptecConfig, ElliptecDevice};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::fw102c::{Fw102cConfig, Fw102cDevice};
use polar_hil_mocks::native::{NativeConfig, NativeDevice};
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::{Simulator, Truth};
use std::path::PathBuf;
use std::time::Duration;

fn link(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("polar-pty-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

fn start(sim: impl Simulator, name: &str) -> (SimServer, Box<dyn Connector>, u32) {
    let baud = sim.baud();
    let link = link(name);
    let server = SimServer::pty(sim, FaultProfile::default(), 1, &link).expect("a pty");
    let connector = Box::new(SerialPath {
        path: link.to_string_lossy().into_owned(),
        baud,
    });
    (server, connector, baud)
}

/// Moves to three angles and checks the truth; returns nothing, panics on a failure.
async fn three_moves<R: Rotator>(r: &mut R, server: &SimServer, slack_rad: f64) {
    for target_deg in [33.0f64, 271.5, 359.9] {
        let target = target_deg.to_radians();
        let reached = r.move_to(target).await.expect("move");
        let tol = r.info().tolerance_rad;
        assert!(signed_difference(reached, target, TURN_RAD).abs() <= tol);
        let Truth::Angle { output_rad, moving } = server.truth() else {
            panic!("angle truth")
        };
        assert!(!moving);
        assert!(
            signed_difference(output_rad, target, TURN_RAD).abs() <= tol + slack_rad,
            "{target_deg} deg: truly at {} deg",
            output_rad.to_degrees()
        );
    }
}

/// The unplug sequence common to every driver: `op` fails Disconnected while away, then works
/// at a new pseudo-terminal.
async fn unplug_and_back(
    server: &SimServer,
    mut op: impl AsyncFnMut() -> Result<(), polar_hal::DeviceError>,
) {
    let before = server.port().expect("plugged");
    server.unplug(0.4);
    tokio::time::sleep(Duration::from_millis(50)).await;
    let e = op().await.expect_err("the device is away");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    // Still away: reopening fails, Disconnected again, quickly.
    let t0 = std::time::Instant::now();
    let e = op().await.expect_err("still away");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
    tokio::time::sleep(Duration::from_millis(600)).await;
    op().await.expect("back after the replug");
    let after = server.port().expect("plugged again");
    assert_ne!(
        before, after,
        "the device came back at a new pseudo-terminal"
    );
}

/// Our firmware's rotator over a pty: three verified moves, unplug, back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn native_rotator_over_a_pty() {
    let (server, connector, _) = start(
        NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 1),
        "native",
    );
    let mut r = NativeRotator::connect(connector, native::default_policy())
        .await
        .expect("connect");
    let slack = 12.0 / NativeConfig::rotator().counts_per_turn as f64 * TURN_RAD;
    three_moves(&mut r, &server, slack).await;
    unplug_and_back(&server, async || r.move_to(1.0).await.map(|_| ())).await;
    assert_eq!(r.session().opens(), 2);
    assert!(
        r.session().resets_seen() >= 1,
        "the boot notice after the replug"
    );
}

/// An ELL14 over a pty at 9600 baud, with the quick-move fault always on (a move within 0.1 s
/// of the previous motion's end goes to 0: the driver's pause before every move must avoid it
/// in real time): three verified moves, unplug, back (re-homed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn elliptec_rotator_over_a_pty() {
    let config = ElliptecConfig::ell14();
    let quick = FaultProfile {
        quick_move_to_zero: 1.0,
        ..FaultProfile::default()
    };
    let (server, connector, _) = start(ElliptecDevice::new(config, quick, 1), "elliptec");
    let mut r = ElliptecRotator::connect(
        connector,
        0,
        elliptec::default_policy(),
        0.05f64.to_radians(),
    )
    .await
    .expect("connect");
    assert_eq!(r.info().counts_per_turn, 143_360);
    let slack = (config.backlash_counts / 2.0 + 1.5) / config.pulses as f64 * TURN_RAD;
    three_moves(&mut r, &server, slack).await;
    unplug_and_back(&server, async || r.move_to(2.0).await.map(|_| ())).await;
    assert_eq!(r.session().opens(), 2);
}

/// An FW102C over a pty: every slot in turn, unplug, back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fw102c_over_a_pty() {
    let (server, connector, _) = start(
        Fw102cDevice::new(Fw102cConfig::fw102c(), FaultProfile::default(), 1),
        "fw102c",
    );
    let mut w = Fw102c::connect(connector, fw102c::default_policy())
        .await
        .expect("connect");
    assert_eq!(w.slots().len(), 6);
    for slot in [3, 0, 5] {
        assert_eq!(w.select(slot).await.expect("select"), slot);
        assert_eq!(server.truth(), Truth::Slot { slot: Some(slot) });
    }
    unplug_and_back(&server, async || w.select(2).await.map(|_| ())).await;
    assert_eq!(w.opens(), 2);
}
