//! APT velocity mode (`MOT_MOVE_VELOCITY`, `MOT_MOVE_STOP`) through the driver's [`Rotator`]
//! methods against the simulated K10CR1 and PRM1Z8/KDC101 on pseudo-terminals. Speeds are measured on the simulator's own clock and
//! truth, so the figures do not depend on how fast the test machine is. The simulated mounts
//! home at 90 deg/s so that the tests take seconds; the driver still holds velocity mode to
//! the real mounts' top speeds (K10CR1 10 deg/s, PRM1Z8 25 deg/s).
#![allow(clippy::unwrap_used)]

mod common;

use common::sample;
use polar_drivers::apt::{self, AptModel, AptRotator, AptSerial};
use polar_hal::{signed_difference, ContinuousSupport, ErrorKind, Rotator, TURN_RAD};
use polar_hil_mocks::apt::{AptDevice, AptSimConfig, AptSimModel};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use std::time::Duration;

/// The true speed over `span_s` of the simulator's clock, deg/s (signed).
async fn true_speed(server: &SimServer, span_s: f64) -> f64 {
    let (ta, a, moving_a) = sample(server);
    tokio::time::sleep(Duration::from_secs_f64(span_s)).await;
    let (tb, b, moving_b) = sample(server);
    assert!(moving_a && moving_b, "the mount is not moving");
    signed_difference(b.to_radians(), a.to_radians(), TURN_RAD).to_degrees() / (tb - ta)
}

/// Each model: velocity mode reports `Velocity` support (no trigger output); spinning forward
/// at the model's top speed and then in reverse at 40 % of it turns the true output at that
/// speed (to 0.1 %: the clock reads bracket the truth read by microseconds, over 0.5 s, and
/// the controller's velocity unit rounds to 1e-7 relative); the stop ends the motion where
/// the driver reads it (within 0.01 deg, the driver's tolerance, plus half the backlash and 4
/// sigma of the encoder dither), and the move velocity and acceleration of before the spin are back, unit for unit.
/// Speeds of zero, beyond the top speed, or not finite are refused as OutOfRange naming
/// `rad_per_s` and the allowed range, without moving the mount.
#[tokio::test(flavor = "current_thread")]
async fn velocity_mode_on_both_models() {
    let dir = std::env::temp_dir().join(format!("polar-apt-spin-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (model, driver_model) in [
        (AptSimModel::K10cr1, AptModel::K10cr1),
        (AptSimModel::Prm1z8, AptModel::Prm1z8),
    ] {
        let config = AptSimConfig::of(model).fast(90.0);
        let healthy = FaultProfile::default();
        let link = dir.join(model.controller());
        let server = SimServer::pty(AptDevice::new(config, healthy, 5), healthy, 5, &link).unwrap();
        let connector = Box::new(AptSerial {
            path: link.to_string_lossy().into_owned(),
        });
        let mut r = AptRotator::connect(
            connector,
            driver_model,
            apt::default_policy(),
            0.01f64.to_radians(),
        )
        .await
        .unwrap();
        assert_eq!(r.continuous_support(), ContinuousSupport::Velocity);
        let before = r.velocity_params().await.unwrap();
        let top_deg_s = match model {
            AptSimModel::K10cr1 => 10.0,
            AptSimModel::Prm1z8 => 25.0,
        };
        for bad in [0.0, 1.01 * top_deg_s, f64::NAN, -1.01 * top_deg_s] {
            let rad_per_s = f64::to_radians(bad);
            let e = r.spin(rad_per_s).await.unwrap_err();
            assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
            let text = e.to_string();
            assert!(
                text.contains("rad_per_s") && text.contains(&format!("<= {top_deg_s}")),
                "{text}"
            );
            assert!(!sample(&server).2, "a refused spin moved the mount");
        }
        for deg_s in [top_deg_s, -0.4 * top_deg_s] {
            r.spin(f64::to_radians(deg_s)).await.unwrap();
            // 0.1 s: past the ramp (at 900 deg/s^2, 28 ms at most).
            tokio::time::sleep(Duration::from_millis(100)).await;
            let v = true_speed(&server, 0.5).await;
            assert!(
                (v - deg_s).abs() <= 1e-3 * deg_s.abs(),
                "{}: true speed {v} deg/s, asked {deg_s}",
                model.controller()
            );
        }
        let at = r.stop_spin().await.unwrap();
        let (_, truth_deg, moving) = sample(&server);
        assert!(!moving, "still moving after stop_spin");
        let slack = 0.01
            + (0.5 * config.backlash_counts + 4.0 * config.encoder_noise_counts)
                / config.counts_per_deg;
        let off = signed_difference(at, truth_deg.to_radians(), TURN_RAD).to_degrees();
        assert!(
            off.abs() <= slack,
            "stopped at {at} rad, truth {truth_deg} deg"
        );
        let after = r.velocity_params().await.unwrap();
        assert_eq!(
            after, before,
            "move velocity and acceleration after the spin"
        );
        server.shutdown().await;
    }
    let _ = std::fs::remove_dir_all(&dir);
}
