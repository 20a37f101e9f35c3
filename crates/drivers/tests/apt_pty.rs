//! The APT driver against the simulated K10CR1 and PRM1Z8/KDC101 over real pseudo-terminals,
//! opened with the APT line settings (RTS/CTS, RTS asserted) through a stable link: homing,
//! moves the short way across 0/360 verified against the simulator's ground truth, unsolicited
//! status updates interleaved with replies, dropped and corrupted replies recovered by retry,
//! an unplug and replug (re-identified and re-homed), a controller of the wrong model refused,
//! and the velocity set and read back. The simulated mounts run at 90 deg/s (real ones: 10 and
//! 25 deg/s) so that the tests take seconds of real time.

use polar_drivers::apt::{self, AptModel, AptRotator, AptSerial};
use polar_drivers::link::Connector;
use polar_hal::{signed_difference, ErrorKind, Rotator, TURN_RAD};
use polar_hil_mocks::apt::{AptDevice, AptSimConfig, AptSimModel};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use std::path::PathBuf;
use std::time::Duration;

/// The readback tolerance the tests give the driver: 0.01 deg.
const TOLERANCE_DEG: f64 = 0.01;

fn link(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("polar-apt-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir.join(name)
}

fn sim_model(model: AptModel) -> AptSimModel {
    match model {
        AptModel::K10cr1 => AptSimModel::K10cr1,
        AptModel::Prm1z8 => AptSimModel::Prm1z8,
    }
}

/// A fast mount of `model` served on a pty with `faults`, and its connector.
fn start(
    config: AptSimConfig,
    faults: FaultProfile,
    seed: u64,
    name: &str,
) -> (SimServer, Box<dyn Connector>) {
    let link = link(name);
    let server =
        SimServer::pty(AptDevice::new(config, faults, seed), faults, seed, &link).expect("a pty");
    let connector = Box::new(AptSerial {
        path: link.to_string_lossy().into_owned(),
    });
    (server, connector)
}

fn truth_deg(server: &SimServer) -> f64 {
    match server.truth() {
        Truth::Angle { output_rad, .. } => output_rad.to_degrees(),
        t => panic!("not a rotator: {t:?}"),
    }
}

/// The slack between the readback and the truth: the tolerance, half the backlash (K10CR1
/// 0.02 deg, PRM1Z8 2 counts) and 4 sigma of the encoder dither (PRM1Z8 0.5 count).
fn slack_deg(config: &AptSimConfig) -> f64 {
    TOLERANCE_DEG
        + (0.5 * config.backlash_counts + 4.0 * config.encoder_noise_counts) / config.counts_per_deg
}

/// Moves through `targets_deg`, each checked by readback and against the truth.
async fn moves(r: &mut AptRotator, server: &SimServer, config: &AptSimConfig, targets_deg: &[f64]) {
    for &target in targets_deg {
        let got = r.move_to(target.to_radians()).await.expect("move");
        let d = signed_difference(got, target.to_radians(), TURN_RAD).to_degrees();
        assert!(d.abs() <= TOLERANCE_DEG, "readback {d} deg off {target}");
        let t = truth_deg(server);
        let d = signed_difference(t.to_radians(), target.to_radians(), TURN_RAD).to_degrees();
        assert!(
            d.abs() <= slack_deg(config),
            "truth {t} is {d} deg off {target}"
        );
    }
}

/// Both models: homing puts the truth at the index; moves to 33 deg, then 271.5 deg go the
/// short way backwards through 0 (the counter reads -88.5 deg, not +271.5 deg), then 359.9 and
/// 0.5 deg forward through 360 (the counter advances by 0.6 deg); every readback within the
/// tolerance and every true angle within the slack.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn home_and_short_way_moves_on_both_models() {
    for model in [AptModel::K10cr1, AptModel::Prm1z8] {
        let config = AptSimConfig::of(sim_model(model)).fast(90.0);
        let (server, connector) = start(
            config,
            FaultProfile::default(),
            11,
            &format!("moves-{}", model.name()),
        );
        let mut r = AptRotator::connect(
            connector,
            model,
            apt::default_policy(),
            TOLERANCE_DEG.to_radians(),
        )
        .await
        .expect("connect");
        let hw = r.hw_info().expect("HW_GET_INFO").clone();
        assert_eq!(hw.model, model.controller());
        let t = truth_deg(&server);
        assert!(
            t.min(360.0 - t) <= slack_deg(&config),
            "{t} deg after homing"
        );
        let cpd = model.counts_per_deg();
        moves(&mut r, &server, &config, &[33.0]).await;
        moves(&mut r, &server, &config, &[271.5]).await;
        let c = f64::from(r.position_counts().await.expect("counter")) / cpd;
        assert!(
            (c + 88.5).abs() <= TOLERANCE_DEG,
            "{c} deg: not the short way back"
        );
        moves(&mut r, &server, &config, &[359.9]).await;
        let before = r.position_counts().await.expect("counter");
        moves(&mut r, &server, &config, &[0.5]).await;
        let after = r.position_counts().await.expect("counter");
        let step = f64::from(after - before) / cpd;
        assert!(
            (step - 0.6).abs() <= 2.0 * TOLERANCE_DEG,
            "{step} deg: not forward through 360"
        );
        server.shutdown().await;
    }
}

/// Unsolicited status updates before 30 % of the replies are skipped (counted) and every move
/// is still verified; with 10 % of replies dropped and 10 % corrupted (one bit flipped; the
/// protocol has no checksum) the driver still reaches every target, by retry and readback.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unsolicited_updates_and_damaged_replies() {
    let mut config = AptSimConfig::prm1z8().fast(90.0);
    config.unsolicited_status = 0.3;
    let (server, connector) = start(config, FaultProfile::default(), 5, "unsolicited");
    let mut r = AptRotator::connect(
        connector,
        AptModel::Prm1z8,
        apt::default_policy(),
        TOLERANCE_DEG.to_radians(),
    )
    .await
    .expect("connect");
    moves(&mut r, &server, &config, &[10.0, 200.0, 355.0]).await;
    assert!(r.skipped() > 0, "no unsolicited update was skipped");
    server.shutdown().await;

    let config = AptSimConfig::k10cr1().fast(90.0);
    let faults = FaultProfile {
        drop_reply: 0.1,
        corrupt_reply: 0.1,
        ..Default::default()
    };
    let (server, connector) = start(config, faults, 7, "damaged");
    let mut r = AptRotator::connect(
        connector,
        AptModel::K10cr1,
        apt::default_policy(),
        TOLERANCE_DEG.to_radians(),
    )
    .await
    .expect("connect through damaged replies");
    moves(&mut r, &server, &config, &[45.0, 300.0, 120.0, 5.0]).await;
    server.shutdown().await;
}

/// An unplug: the next call is Disconnected; after the replug (a power cycle: the counter and
/// the datum are lost) the driver reopens the port, identifies and homes again, and the next
/// move lands where asked.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unplug_reidentifies_and_rehomes() {
    let config = AptSimConfig::k10cr1().fast(90.0);
    let (server, connector) = start(config, FaultProfile::default(), 3, "unplug");
    let mut r = AptRotator::connect(
        connector,
        AptModel::K10cr1,
        apt::default_policy(),
        TOLERANCE_DEG.to_radians(),
    )
    .await
    .expect("connect");
    moves(&mut r, &server, &config, &[60.0]).await;
    let opens = r.opens();
    server.unplug(0.4);
    tokio::time::sleep(Duration::from_millis(50)).await;
    let e = r.position_rad().await.expect_err("away");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    tokio::time::sleep(Duration::from_millis(600)).await;
    moves(&mut r, &server, &config, &[150.0]).await;
    assert!(r.opens() > opens, "the port was not reopened");
    server.shutdown().await;
}

/// A KDC101 is refused as a K10CR1 (an error naming both) and detected as a PRM1Z8 when no
/// model is given; a velocity above the K10CR1's
/// 10 deg/s is out of range (naming `rad_per_s` and the allowed range); 5 deg/s is set and read
/// back to 1e-6 deg/s (the controller's unit is 1/7.3e6 deg/s).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_model_and_velocity() {
    let (server, connector) = start(
        AptSimConfig::prm1z8().fast(90.0),
        FaultProfile::default(),
        1,
        "wrong",
    );
    let e = AptRotator::connect(connector, AptModel::K10cr1, apt::default_policy(), 1e-4)
        .await
        .err()
        .expect("refused");
    assert_eq!(e.kind(), ErrorKind::Other, "{e}");
    assert!(
        e.message.contains("KDC101") && e.message.contains("k10cr1"),
        "{e}"
    );
    // Without a model, the controller's string picks it: a KDC101 is a PRM1Z8 (691071 counts
    // per turn, 360 * 1919.6418 rounded).
    let connector = Box::new(AptSerial {
        path: link("wrong").to_string_lossy().into_owned(),
    });
    let r = AptRotator::connect_detect(connector, apt::default_policy(), 1e-4)
        .await
        .expect("detected");
    assert_eq!(r.model(), AptModel::Prm1z8);
    assert_eq!(r.info().counts_per_turn, 691_071);
    drop(r);
    server.shutdown().await;

    let (server, connector) = start(
        AptSimConfig::k10cr1().fast(90.0),
        FaultProfile::default(),
        2,
        "velocity",
    );
    let mut r = AptRotator::connect(connector, AptModel::K10cr1, apt::default_policy(), 1e-4)
        .await
        .expect("connect");
    let e = r
        .set_velocity(20f64.to_radians())
        .await
        .expect_err("too fast");
    assert_eq!(e.kind(), ErrorKind::OutOfRange);
    assert!(
        e.message.contains("rad_per_s") && e.message.contains("(0, 10] deg/s"),
        "{e}"
    );
    r.set_velocity(5f64.to_radians()).await.expect("5 deg/s");
    let (v, _) = r.velocity_params().await.expect("read back");
    assert!((v - 5.0).abs() < 1e-6, "{v} deg/s");
    server.shutdown().await;
}
