//! The Standa driver's velocity mode (`smov`, `left`/`rigt`, `sstp`) through its [`Rotator`]
//! methods against the simulated 8SMC5-USB with the 8MPR16-1 on a pseudo-terminal. Speeds and
//! durations are measured on the simulator's own clock and truth, so the figures do not depend
//! on how fast the test machine is. The simulated stage moves and homes at 90 deg/s so that
//! the test takes seconds; the driver still spins it at most at the profile's 6.25 deg/s.
#![allow(clippy::unwrap_used)]

mod common;

use common::sample;
use polar_drivers::standa::{self, StandaRotator, MAX_SPIN_DEG_PER_S};
use polar_hal::{signed_difference, ContinuousSupport, ErrorKind, Rotator, TURN_RAD};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::standa::{StandaConfig, StandaDevice};
use std::time::Duration;

/// Velocity mode reports `Velocity` support (no trigger output). Speeds of zero, beyond 6.25
/// deg/s or not finite are refused as OutOfRange naming `rad_per_s` and the limit, without
/// moving the stage. Spinning backward (`left`) at 3 deg/s turns the true output at -3 deg/s
/// (to 0.5 %: 240 full steps/s is exact in the controller's units, and the clock reads
/// bracket the truth reads by microseconds over 1 s); the stop ends the motion where the
/// driver reads it (within one full step, 0.0125 deg, the driver's tolerance); and the move
/// settings of before the spin are back: a 45 deg move then takes the 90 deg/s profile's
/// 0.5 s and a little, not the 15 s it would take at the spin's 3 deg/s (on the simulator's
/// clock, under 2 s).
#[tokio::test(flavor = "current_thread")]
async fn velocity_mode_left_and_back() {
    let dir = std::env::temp_dir().join(format!("polar-standa-spin-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let healthy = FaultProfile::default();
    let link = dir.join("standa");
    let device = StandaDevice::new(StandaConfig::mpr16().at_speed(90.0), healthy, 11);
    let server = SimServer::pty(device, healthy, 11, &link).unwrap();
    let connector = standa::DIALECT.connector(&link.to_string_lossy());
    let mut r = StandaRotator::connect(connector, standa::default_policy())
        .await
        .unwrap();
    assert_eq!(r.continuous_support(), ContinuousSupport::Velocity);

    for bad in [
        0.0,
        1.01 * MAX_SPIN_DEG_PER_S,
        f64::NAN,
        -1.01 * MAX_SPIN_DEG_PER_S,
    ] {
        let e = r.spin(bad.to_radians()).await.unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
        let text = e.to_string();
        assert!(
            text.contains("rad_per_s") && text.contains(&format!("<= {MAX_SPIN_DEG_PER_S}")),
            "{text}"
        );
        assert!(!sample(&server).2, "a refused spin moved the stage");
    }

    r.spin((-3.0f64).to_radians()).await.unwrap();
    // Past the ramp (3 deg/s at 65535 steps/s^2 is reached in 4 ms).
    tokio::time::sleep(Duration::from_millis(200)).await;
    let (ta, a, moving_a) = sample(&server);
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (tb, b, moving_b) = sample(&server);
    assert!(moving_a && moving_b, "the stage is not turning");
    let speed =
        signed_difference(b.to_radians(), a.to_radians(), TURN_RAD).to_degrees() / (tb - ta);
    assert!(
        (speed / -3.0 - 1.0).abs() < 0.005,
        "true speed {speed} deg/s"
    );

    let stopped = r.stop_spin().await.unwrap().to_degrees();
    let (_, truth, moving) = sample(&server);
    assert!(!moving, "still turning after stop_spin");
    let off = signed_difference(stopped.to_radians(), truth.to_radians(), TURN_RAD).to_degrees();
    assert!(
        off.abs() <= 0.0125,
        "stopped at {stopped} deg, truly at {truth} deg"
    );

    let target = (stopped + 45.0).rem_euclid(360.0);
    let t0 = server.now_s();
    r.move_to(target.to_radians()).await.unwrap();
    let took_s = server.now_s() - t0;
    assert!(
        took_s < 2.0,
        "a 45 deg move took {took_s} s: the spin's speed stayed"
    );
    server.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
}
