//! Velocity mode and the position-compare trigger of our firmware, through the driver, over a
//! real pseudo-terminal: the simulated stage spins, pulses arrive with the encoder position
//! latched at each armed angle and device times that follow the kinematics, and a stop ends
//! where the simulator's ground truth says.

use polar_drivers::link::SerialPath;
use polar_drivers::native::{self, NativeRotator};
use polar_hal::{signed_difference, ErrorKind, TURN_RAD};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::native::{NativeConfig, NativeDevice};
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use std::time::Duration;

/// Spin at 90 deg/s, pulses every 10 deg from 30 deg: each pulse's latched angle within the
/// encoder's 3 counts (10 sigma of its 0.3 count noise) of the armed angle, consecutive device
/// times 10/90 s apart to a microsecond (the simulator's clock is simulated time, so the pty's
/// scheduling jitter does not enter; the rounding to whole microseconds does), indices in order.
/// A stop ends at rest where the ground truth is (within the 20-count backlash and noise).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn spin_and_trigger_over_a_pty() {
    let config = NativeConfig::rotator();
    let dir = std::env::temp_dir().join(format!("polar-continuous-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let link = dir.join("native");
    let sim = NativeDevice::new(config, FaultProfile::default(), 11);
    let server = SimServer::pty(sim, FaultProfile::default(), 1, &link).expect("a pty");
    let connector = Box::new(SerialPath {
        path: link.to_string_lossy().into_owned(),
        baud: 115_200,
    });
    let mut r = NativeRotator::connect(connector, native::default_policy())
        .await
        .expect("connect");

    let e = r.spin(0.0).await.unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
    let e = r.spin(10.0 * TURN_RAD).await.unwrap_err();
    assert_eq!(
        e.kind(),
        ErrorKind::OutOfRange,
        "{e} (the stage's limit is 2 turns/s)"
    );

    let deg = TURN_RAD / 360.0;
    let start = r.read_position_rad().await.expect("position");
    let first = start + 30.0 * deg;
    r.arm_trigger(first, 10.0 * deg, 8).await.expect("arm");
    r.spin(90.0 * deg).await.expect("spin");
    let counts = f64::from(config.counts_per_turn);
    let mut last_time_us = None;
    for k in 0..8u32 {
        let pulse = r
            .next_trigger(Duration::from_secs(3))
            .await
            .expect("a pulse");
        assert_eq!(pulse.index, k);
        let armed = first + f64::from(k) * 10.0 * deg;
        let off_counts = (pulse.angle_rad - armed) / TURN_RAD * counts;
        assert!(
            off_counts.abs() <= 3.0,
            "pulse {k}: {off_counts} counts off"
        );
        if let Some(t) = last_time_us {
            let dt_us = f64::from(pulse.device_time_us.wrapping_sub(t));
            assert!(
                (dt_us - 1e6 / 9.0).abs() <= 2.0,
                "pulse {k}: {dt_us} us after the previous"
            );
        }
        last_time_us = Some(pulse.device_time_us);
    }
    let Truth::Angle { moving, .. } = server.truth() else {
        panic!("a rotator");
    };
    assert!(moving, "still spinning after the last pulse");
    let stopped = r.stop_spin().await.expect("stop");
    let Truth::Angle { output_rad, moving } = server.truth() else {
        panic!("a rotator");
    };
    assert!(!moving);
    let off_counts = signed_difference(output_rad, stopped, TURN_RAD).abs() / TURN_RAD * counts;
    assert!(
        off_counts <= 15.0,
        "stopped {off_counts} counts from the truth"
    );
}
