//! Expectation scripts at the byte level (embedded-hal-mock style): each driver's exact bytes
//! on the wire for connect, home, move and readback, against a scripted device that checks
//! every byte it receives and answers with fixed bytes. A driver that sends one byte more,
//! less or different fails here, whatever the simulators would have tolerated.

use polar_drivers::elliptec::{self, ElliptecRotator};
use polar_drivers::fw102c::{self, Fw102c};
use polar_drivers::link::{BoxIo, Connector, FnConnector};
use polar_drivers::native::{self, NativeRotator};
use polar_firmware_protocol::{encode_vec, BootReason, Command, DeviceKind, Reply, StatusFlags};
use polar_hal::{FilterWheel, Rotator};
use std::sync::{Arc, Mutex};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio::task::JoinHandle;

/// One step: the bytes the device must receive next, and its answer.
type Step = (Vec<u8>, Vec<u8>);

/// A connector whose single connection plays `steps`; the task returns the first mismatch.
fn scripted(steps: Vec<Step>) -> (Box<dyn Connector>, JoinHandle<Result<(), String>>) {
    let (host, device) = tokio::io::duplex(4096);
    let host = Arc::new(Mutex::new(Some(host)));
    let task = tokio::spawn(play(device, steps));
    let connector = FnConnector::new("script", move || {
        let io = host.lock().expect("lock").take();
        async move {
            io.map(|io| Box::new(io) as BoxIo)
                .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::NotFound, "opened twice"))
        }
    });
    (Box::new(connector), task)
}

async fn play(mut io: DuplexStream, steps: Vec<Step>) -> Result<(), String> {
    for (k, (expect, reply)) in steps.into_iter().enumerate() {
        let mut got = vec![0u8; expect.len()];
        if !expect.is_empty() {
            io.read_exact(&mut got)
                .await
                .map_err(|e| format!("step {k}: {e}"))?;
        }
        if got != expect {
            return Err(format!(
                "step {k}: expected {:?}, got {:?}",
                String::from_utf8_lossy(&expect),
                String::from_utf8_lossy(&got)
            ));
        }
        io.write_all(&reply)
            .await
            .map_err(|e| format!("step {k}: {e}"))?;
    }
    // Nothing more may arrive.
    let mut extra = [0u8; 64];
    match tokio::time::timeout(std::time::Duration::from_millis(200), io.read(&mut extra)).await {
        Ok(Ok(n)) if n > 0 => Err(format!("unexpected bytes {:?}", &extra[..n])),
        _ => Ok(()),
    }
}

fn frame(seq: u8, c: Command) -> Vec<u8> {
    encode_vec(seq, &c)
}

fn reply(seq: u8, r: Reply) -> Vec<u8> {
    encode_vec(seq, &r)
}

fn status(position_counts: i32) -> Reply {
    Reply::Status {
        position_counts,
        flags: StatusFlags(StatusFlags::HOMED),
        slot: 0xff,
    }
}

/// Our firmware: boot notice at open, identify (seq 1), home (seq 2) with its MotionDone, a
/// status to confirm the datum (seq 3); a move to 90 deg moves absolutely to a quarter turn
/// (seq 4) from the position that status gave, and its MotionDone on target settles it: no
/// more round trips. A late Ack to an old sequence number in the middle is ignored.
#[tokio::test]
async fn native_bytes() {
    let cpt = 144_000;
    let steps = vec![
        (
            vec![],
            reply(
                0,
                Reply::Boot {
                    reason: BootReason::PowerOn,
                },
            ),
        ),
        (
            frame(1, Command::Identify),
            reply(
                1,
                Reply::Identity {
                    protocol_version: 1,
                    firmware: [1, 2, 3],
                    device: DeviceKind::Rotator,
                    counts_per_turn: cpt,
                    slots: 0,
                    serial: 7,
                },
            ),
        ),
        (frame(2, Command::Home), {
            let mut b = reply(2, Reply::Ack);
            b.extend(reply(2, Reply::MotionDone { position_counts: 0 }));
            b
        }),
        (frame(3, Command::GetStatus), reply(3, status(0))),
        (
            frame(
                4,
                Command::MoveAbsolute {
                    position_counts: cpt as i32 / 4,
                },
            ),
            {
                // A duplicate of an old reply first: skipped by its sequence number.
                let mut b = reply(2, Reply::Ack);
                b.extend(reply(4, Reply::Ack));
                b.extend(reply(
                    4,
                    Reply::MotionDone {
                        position_counts: 36_001,
                    },
                ));
                b
            },
        ),
    ];
    let (connector, device) = scripted(steps);
    let mut r = NativeRotator::connect(connector, native::default_policy())
        .await
        .expect("connect");
    assert_eq!(r.info().counts_per_turn, cpt);
    let reached = r.move_to(90f64.to_radians()).await.expect("move");
    assert!((reached.to_degrees() - 90.0).abs() < 0.01, "{reached}");
    drop(r);
    device.await.expect("task").expect("script");
}

/// Elliptec: `0in`, `0ho0`, `0gp` at connect; a move to 90 deg of an ELL14 (143360 counts per
/// turn) is `0gp` (datum check), `0ma00008C00` (35840 counts), `0gs` (idle?) and `0gp`. An
/// unsolicited `BO` line and another module's reply before the answer are skipped.
#[tokio::test]
async fn elliptec_bytes() {
    let s = |a: &str, b: &str| (a.as_bytes().to_vec(), b.as_bytes().to_vec());
    let steps = vec![
        s("0in", "0IN0E1140012320231701016800023000\r\n"),
        s("0ho0", "0PO00000000\r\n"),
        s("0gp", "0PO00000000\r\n"),
        s("0gp", "0BO00000000\r\n1PO00000005\r\n0PO00000000\r\n"),
        s("0ma00008C00", "0PO00008C00\r\n"),
        s("0gs", "0GS00\r\n"),
        s("0gp", "0PO00008C01\r\n"),
    ];
    let (connector, device) = scripted(steps);
    let mut r = ElliptecRotator::connect(
        connector,
        0,
        elliptec::default_policy(),
        0.05f64.to_radians(),
    )
    .await
    .expect("connect");
    assert_eq!(r.info().counts_per_turn, 143_360);
    let t0 = tokio::time::Instant::now();
    let reached = r.move_to(90f64.to_radians()).await.expect("move");
    assert!((reached.to_degrees() - 90.0).abs() < 0.01, "{reached}");
    // The 100 ms pre-move gap after homing is respected.
    assert!(t0.elapsed() >= elliptec::PRE_MOVE_DELAY / 2);
    drop(r);
    device.await.expect("task").expect("script");
}

/// FW102C: `*idn?` and `pcount?` at connect; slot 3 (0-based) is `pos?`, `pos=4`, `pos?`, each
/// answered with the echo, the answer and the prompt. Line noise and a stale prompt before the
/// echo are skipped.
#[tokio::test]
async fn fw102c_bytes() {
    let s = |a: &str, b: &str| (a.as_bytes().to_vec(), b.as_bytes().to_vec());
    let steps = vec![
        s(
            "*idn?\r",
            "*idn?\rTHORLABS FW102C/FW212C Filter Wheel version 1.07\r> ",
        ),
        s("pcount?\r", "\x13> pcount?\r6\r> "),
        s("pos?\r", "pos?\r1\r> "),
        s("pos=4\r", "pos=4\r> "),
        s("pos?\r", "pos?\r4\r> "),
    ];
    let (connector, device) = scripted(steps);
    let mut w = Fw102c::connect(connector, fw102c::default_policy())
        .await
        .expect("connect");
    assert_eq!(w.slots().len(), 6);
    assert_eq!(w.select(3).await.expect("select"), 3);
    drop(w);
    device.await.expect("task").expect("script");
}
