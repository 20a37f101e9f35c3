//! Unit tests of the simulated APT mounts ([`super`]).

use super::*;

fn fast(model: AptSimModel) -> AptDevice {
    let mut c = AptSimConfig::of(model).fast(90.0);
    c.encoder_noise_counts = 0.0;
    c.backlash_counts = 0.0;
    AptDevice::new(c, FaultProfile::default(), 3)
}

fn req_short(msg: u16, p1: u8, p2: u8) -> Vec<u8> {
    let mut v = msg.to_le_bytes().to_vec();
    v.extend_from_slice(&[p1, p2, USB, HOST]);
    v
}

fn req_long(msg: u16, data: &[u8]) -> Vec<u8> {
    let mut v = msg.to_le_bytes().to_vec();
    v.extend_from_slice(&(data.len() as u16).to_le_bytes());
    v.extend_from_slice(&[USB | 0x80, HOST]);
    v.extend_from_slice(data);
    v
}

/// Runs the device until `t_end` and returns the bytes with the time they fell due.
fn run_until(d: &mut AptDevice, t: &mut f64, t_end: f64) -> Vec<(f64, Vec<u8>)> {
    let mut out = Vec::new();
    while let Some(next) = d.next_event_s().filter(|&n| n <= t_end) {
        *t = next.max(*t);
        let b = d.tick(*t);
        if !b.is_empty() {
            out.push((*t, b));
        }
    }
    *t = t_end;
    out
}

/// `HW_GET_INFO` is the 90-byte message both clients parse: header `06 00 54 00 81 50`,
/// serial at offset 6, model string at 10, stage id 6 (PRM1-Z8) at 82 on the KDC101; the
/// position reply is `12 04 06 00 81 50` with channel 1 and the counter.
#[test]
fn exact_reply_bytes() {
    let mut d = fast(AptSimModel::Prm1z8);
    let info = d.receive(0.0, &req_short(id::HW_REQ_INFO, 0, 0));
    assert_eq!(info.len(), 90);
    assert_eq!(&info[..6], &[0x06, 0x00, 0x54, 0x00, 0x81, 0x50]);
    assert_eq!(le_i32(&info, 6), 27_000_456);
    assert_eq!(&info[10..16], b"KDC101");
    assert_eq!(le_u16(&info, 82), 6);
    let pos = d.receive(0.0, &req_short(id::MOT_REQ_POSCOUNTER, 1, 0));
    assert_eq!(
        pos,
        vec![0x12, 0x04, 0x06, 0x00, 0x81, 0x50, 1, 0, 0, 0, 0, 0]
    );
}

/// Homing goes in reverse to the index and zeroes the counter: afterwards the true angle is
/// 0 (to 1e-9 deg) and the homed bit is set; an absolute move of 90 deg at 90 deg/s,
/// 900 deg/s^2 ends with `MOT_MOVE_COMPLETED` after 1.1 s (d/v + v/a, to 1 ms) with the
/// target in its data, the true angle at 90 deg to half a count (the target is whole).
#[test]
fn home_and_move() {
    for model in [AptSimModel::K10cr1, AptSimModel::Prm1z8] {
        let mut d = fast(model);
        let mut t = 0.0;
        assert!(d.receive(t, &req_short(id::MOT_MOVE_HOME, 1, 0)).is_empty());
        assert!(d.status_bits(0.01) & bits::HOMING != 0);
        let ev = run_until(&mut d, &mut t, 10.0);
        assert_eq!(ev.len(), 1);
        assert_eq!(&ev[0].1, &short(id::MOT_MOVE_HOMED, 1, 0));
        let Truth::Angle { output_rad, .. } = d.truth(t) else {
            panic!()
        };
        assert!(output_rad.to_degrees().min(360.0 - output_rad.to_degrees()) < 1e-9);
        assert!(d.status_bits(t) & bits::HOMED != 0);
        let cpd = d.config.counts_per_deg;
        let target = (90.0 * cpd).round() as i32;
        let t0 = t;
        d.receive(t, &req_long(id::MOT_MOVE_ABSOLUTE, &chan_then(&[target])));
        assert!(d.status_bits(t + 0.5) & bits::MOVING_FWD != 0);
        let ev = run_until(&mut d, &mut t, t0 + 5.0);
        assert_eq!(ev.len(), 1);
        assert!(
            (ev[0].0 - t0 - 1.1).abs() < 1e-3,
            "{model:?} {}",
            ev[0].0 - t0
        );
        let m = &ev[0].1;
        assert_eq!(&m[..6], &[0x64, 0x04, 0x0e, 0x00, 0x81, 0x50]);
        assert_eq!(le_i32(m, 8), target);
        let Truth::Angle { output_rad, moving } = d.truth(t) else {
            panic!()
        };
        let off = output_rad.to_degrees() - 90.0;
        // The target is a whole count: within half a count of 90 deg.
        assert!(
            !moving && off.abs() <= 0.5 / cpd + 1e-9,
            "{model:?}: {off} deg off"
        );
    }
}

/// A profiled stop during a continuous motion brakes over v^2/2a and answers
/// `MOT_MOVE_STOPPED` between v/a = 0.1 s and sqrt(2) v/a later (the braking profile of
/// [`crate::motion::Profile::stopped_at`] starts from rest over that distance); update messages come every 100 ms (10 in 1.05 s) and stop on request.
#[test]
fn stop_and_update_messages() {
    let mut d = fast(AptSimModel::Prm1z8);
    let mut t = 0.0;
    d.receive(t, &req_short(id::MOT_MOVE_VELOCITY, 1, 1));
    run_until(&mut d, &mut t, 1.0);
    d.receive(t, &req_short(id::MOT_MOVE_STOP, 1, 2));
    let ev = run_until(&mut d, &mut t, 2.0);
    assert_eq!(ev.len(), 1);
    assert!(
        (1.1 - 1e-9..=1.0 + 0.1 * 2f64.sqrt() + 1e-9).contains(&ev[0].0),
        "{}",
        ev[0].0
    );
    assert_eq!(ev[0].1[0..2], id::MOT_MOVE_STOPPED.to_le_bytes());
    d.receive(t, &req_short(id::HW_START_UPDATEMSGS, 0, 0));
    let ev = run_until(&mut d, &mut t, 3.05);
    assert_eq!(ev.len(), 10);
    assert!(ev
        .iter()
        .all(|(_, b)| b[0..2] == id::MOT_GET_DCSTATUSUPDATE.to_le_bytes()));
    d.receive(t, &req_short(id::HW_STOP_UPDATEMSGS, 0, 0));
    assert!(run_until(&mut d, &mut t, 4.0).is_empty());
}

/// Velocity parameters: the K10CR1 reports 10 deg/s as 73 291 093 units (409600/3 * 10 *
/// 53.68, rounded); a request above the top speed is capped at it.
#[test]
fn velocity_params_scale_and_cap() {
    let mut d = AptDevice::new(AptSimConfig::k10cr1(), FaultProfile::default(), 1);
    let r = d.receive(0.0, &req_short(id::MOT_REQ_VELPARAMS, 1, 0));
    assert_eq!(le_i32(&r, 16), 73_291_093);
    d.receive(
        0.0,
        &req_long(id::MOT_SET_VELPARAMS, &chan_then(&[0, 1000, i32::MAX])),
    );
    let r = d.receive(0.0, &req_short(id::MOT_REQ_VELPARAMS, 1, 0));
    assert_eq!((le_i32(&r, 12), le_i32(&r, 16)), (1000, 73_291_093));
}

/// The registry's speed constructor: a K10CR1 asked for 720 deg/s is capped at the 293.0
/// deg/s its 32-bit velocity parameter holds (i32::MAX / (53.68 * 409600/3)), so it reports
/// a positive velocity within one unit of i32::MAX rather than a wrapped one; a PRM1Z8 keeps
/// the 720 deg/s asked (its limit is 50 000 deg/s), 720 * 1919.64 * 22.37 units to 1 unit.
#[test]
fn speed_constructor_caps_at_the_protocol_limit() {
    let k = AptSimConfig::k10cr1().max_protocol_velocity_deg_s();
    assert!((k - 293.0).abs() < 0.05, "{k}");
    let p = AptSimConfig::prm1z8().max_protocol_velocity_deg_s();
    assert!(p > 49_000.0 && p < 51_000.0, "{p}");
    let mut d = simulate_at_speed("k10cr1", 720.0, FaultProfile::default(), 1).unwrap();
    let r = d.receive(0.0, &req_short(id::MOT_REQ_VELPARAMS, 1, 0));
    let v = i64::from(le_i32(&r, 16));
    assert!((0..=1).contains(&(i64::from(i32::MAX) - v)), "{v}");
    let mut d = simulate_at_speed("prm1z8", 720.0, FaultProfile::default(), 1).unwrap();
    let r = d.receive(0.0, &req_short(id::MOT_REQ_VELPARAMS, 1, 0));
    let want = 720.0 * 1_919.641_857_862_339 * KDC101_T_S * 65_536.0;
    assert!(
        (f64::from(le_i32(&r, 16)) - want).abs() <= 1.0,
        "{}",
        le_i32(&r, 16)
    );
    assert!(simulate_at_speed("ell14", 90.0, FaultProfile::default(), 1).is_none());
}

/// Faults: with every reply dropped nothing comes back; the same seed gives the same
/// replies under corruption; a stall stops half way with the motion-error bit; a disabled
/// channel ignores moves.
#[test]
fn device_faults() {
    let c = AptSimConfig::prm1z8().fast(90.0);
    let drop = FaultProfile {
        drop_reply: 1.0,
        ..Default::default()
    };
    let mut d = AptDevice::new(c, drop, 1);
    assert!(d.receive(0.0, &req_short(id::HW_REQ_INFO, 0, 0)).is_empty());
    let corrupt = FaultProfile {
        corrupt_reply: 0.5,
        ..Default::default()
    };
    let replies = |seed| {
        let mut d = AptDevice::new(c, corrupt, seed);
        (0..20)
            .map(|k| d.receive(f64::from(k), &req_short(id::HW_REQ_INFO, 0, 0)))
            .collect::<Vec<_>>()
    };
    assert_eq!(replies(5), replies(5));
    let stall = FaultProfile {
        stall: 1.0,
        ..Default::default()
    };
    let mut d = AptDevice::new(c, stall, 1);
    let mut t = 0.0;
    let target = (90.0 * c.counts_per_deg).round() as i32;
    d.receive(t, &req_long(id::MOT_MOVE_ABSOLUTE, &chan_then(&[target])));
    let ev = run_until(&mut d, &mut t, 5.0);
    assert_eq!(ev[0].1[0..2], id::MOT_MOVE_STOPPED.to_le_bytes());
    assert!(d.status_bits(t) & bits::MOTION_ERROR != 0);
    assert!((d.motor - f64::from(target) / 2.0).abs() < 1.0);
    let mut d = fast(AptSimModel::K10cr1);
    d.receive(0.0, &req_short(id::MOD_SET_CHANENABLESTATE, 1, 2));
    d.receive(0.0, &req_long(id::MOT_MOVE_ABSOLUTE, &chan_then(&[1000])));
    assert!(!d.moving(0.1) && d.status_bits(0.1) & bits::ENABLED == 0);
}

/// Random bytes (valid requests cut and mixed with noise) never panic, and the truth stays
/// in `[0, 2 pi)`.
#[test]
fn random_bytes_never_panic() {
    let requests: Vec<Vec<u8>> = vec![
        req_short(id::HW_REQ_INFO, 0, 0),
        req_short(id::MOT_MOVE_HOME, 1, 0),
        req_long(id::MOT_MOVE_ABSOLUTE, &chan_then(&[i32::MAX])),
        req_long(id::MOT_MOVE_RELATIVE, &chan_then(&[i32::MIN])),
        req_short(id::MOT_MOVE_JOG, 1, 2),
        req_short(id::MOT_MOVE_VELOCITY, 1, 1),
        req_short(id::MOT_MOVE_STOP, 1, 1),
        req_long(id::MOT_SET_VELPARAMS, &chan_then(&[-5, 0, -1])),
        req_long(id::MOT_SET_POSCOUNTER, &chan_then(&[123])),
        req_short(id::HW_START_UPDATEMSGS, 0, 0),
        req_short(id::MOT_REQ_DCSTATUSUPDATE, 1, 0),
    ];
    let noisy = FaultProfile {
        drop_reply: 0.1,
        corrupt_reply: 0.1,
        duplicate_reply: 0.1,
        stall: 0.2,
        spontaneous_reset: 0.05,
        thermal_duty: 0.3,
        ..Default::default()
    };
    let mut dice = Dice::new(9);
    for model in [AptSimModel::K10cr1, AptSimModel::Prm1z8] {
        let mut c = AptSimConfig::of(model).fast(90.0);
        c.unsolicited_status = 0.1;
        let mut d = AptDevice::new(c, noisy, 4);
        let mut t = 0.0;
        for _ in 0..3000 {
            let mut bytes = requests[dice.index(requests.len())].clone();
            if dice.chance(0.2) {
                bytes.truncate(dice.index(bytes.len() + 1));
            }
            if dice.chance(0.2) {
                bytes.push(dice.byte());
            }
            t += dice.uniform() * 0.05;
            d.receive(t, &bytes);
            let Truth::Angle { output_rad, .. } = d.truth(t) else {
                panic!()
            };
            assert!((0.0..TAU).contains(&output_rad));
        }
    }
}
