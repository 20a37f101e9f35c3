//! The wire format pinned by golden bytes (the same vectors as SPEC.md), and the decoder's
//! behaviour under chunking, garbage, corruption and overlong input.
#![allow(clippy::unwrap_used)] // a failed unwrap is a failed test

use polar_firmware_protocol::{
    encode, next_seq, BootReason, Command, DecodeError, Decoder, DeviceKind, ErrorCode, Message,
    Packet, Reply, StatusFlags, MAX_WIRE,
};
use proptest::prelude::*;

/// SPEC.md's command vectors: (seq, command, wire bytes).
fn command_vectors() -> Vec<(u8, Command, Vec<u8>)> {
    vec![
        (
            1,
            Command::Identify,
            vec![0x06, 0x01, 0x01, 0x01, 0xbc, 0xd8, 0x00],
        ),
        (
            2,
            Command::Home,
            vec![0x06, 0x01, 0x02, 0x02, 0x8c, 0xbd, 0x00],
        ),
        (
            3,
            Command::MoveAbsolute {
                position_counts: 36_000,
            },
            vec![
                0x06, 0x01, 0x03, 0x03, 0xa0, 0x8c, 0x01, 0x03, 0xd0, 0xcd, 0x00,
            ],
        ),
        (
            4,
            Command::MoveRelative { delta_counts: -100 },
            vec![
                0x0a, 0x01, 0x04, 0x04, 0x9c, 0xff, 0xff, 0xff, 0xc9, 0x9d, 0x00,
            ],
        ),
        (
            5,
            Command::Stop,
            vec![0x06, 0x01, 0x05, 0x05, 0xfc, 0x54, 0x00],
        ),
        (
            6,
            Command::GetStatus,
            vec![0x06, 0x01, 0x06, 0x06, 0xcc, 0x31, 0x00],
        ),
        (
            7,
            Command::SetMotion {
                velocity_counts_per_s: 20_000,
                acceleration_counts_per_s2: 50_000,
            },
            vec![
                0x06, 0x01, 0x07, 0x07, 0x20, 0x4e, 0x01, 0x03, 0x50, 0xc3, 0x01, 0x03, 0x87, 0x3f,
                0x00,
            ],
        ),
        (
            8,
            Command::SelectSlot { slot: 3 },
            vec![0x07, 0x01, 0x08, 0x08, 0x03, 0x1f, 0xe2, 0x00],
        ),
        (
            9,
            Command::Save,
            vec![0x06, 0x01, 0x09, 0x09, 0x1d, 0xd0, 0x00],
        ),
        (
            10,
            Command::Reset,
            vec![0x06, 0x01, 0x0a, 0x0a, 0x2d, 0xb5, 0x00],
        ),
        (
            11,
            Command::Spin {
                velocity_counts_per_s: -72_000,
            },
            vec![
                0x0a, 0x01, 0x0b, 0x0b, 0xc0, 0xe6, 0xfe, 0xff, 0xf9, 0xe9, 0x00,
            ],
        ),
        (
            12,
            Command::SetTrigger {
                first_counts: 1000,
                interval_counts: 4000,
                pulses: 36,
            },
            vec![
                0x06, 0x01, 0x0c, 0x0c, 0xe8, 0x03, 0x01, 0x03, 0xa0, 0x0f, 0x01, 0x02, 0x24, 0x01,
                0x01, 0x03, 0xaa, 0x73, 0x00,
            ],
        ),
    ]
}

/// SPEC.md's reply vectors.
fn reply_vectors() -> Vec<(u8, Reply, Vec<u8>)> {
    vec![
        (
            1,
            Reply::Identity {
                protocol_version: 1,
                firmware: [1, 2, 3],
                device: DeviceKind::Rotator,
                counts_per_turn: 144_000,
                slots: 0,
                serial: 0x0102_0304,
            },
            vec![
                0x0c, 0x01, 0x01, 0x82, 0x01, 0x01, 0x02, 0x03, 0x01, 0x80, 0x32, 0x02, 0x01, 0x07,
                0x04, 0x03, 0x02, 0x01, 0x7f, 0xba, 0x00,
            ],
        ),
        (
            2,
            Reply::Ack,
            vec![0x06, 0x01, 0x02, 0x80, 0x46, 0x0c, 0x00],
        ),
        (
            4,
            Reply::Nack {
                code: ErrorCode::Busy,
            },
            vec![0x07, 0x01, 0x04, 0x81, 0x04, 0x99, 0x46, 0x00],
        ),
        (
            6,
            Reply::Status {
                position_counts: 36_000,
                flags: StatusFlags(StatusFlags::HOMED | StatusFlags::MOVING),
                slot: 0xff,
            },
            vec![
                0x06, 0x01, 0x06, 0x83, 0xa0, 0x8c, 0x01, 0x05, 0x03, 0xff, 0x91, 0x03, 0x00,
            ],
        ),
        (
            3,
            Reply::MotionDone {
                position_counts: 36_000,
            },
            vec![
                0x06, 0x01, 0x03, 0x84, 0xa0, 0x8c, 0x01, 0x03, 0xd4, 0x88, 0x00,
            ],
        ),
        (
            0,
            Reply::Boot {
                reason: BootReason::Watchdog,
            },
            vec![0x02, 0x01, 0x05, 0x85, 0x01, 0x38, 0x06, 0x00],
        ),
        (
            6,
            Reply::Status {
                position_counts: 36_000,
                flags: StatusFlags(
                    StatusFlags::HOMED
                        | StatusFlags::MOVING
                        | StatusFlags::SPINNING
                        | StatusFlags::TRIGGER_ARMED,
                ),
                slot: 0xff,
            },
            vec![
                0x06, 0x01, 0x06, 0x83, 0xa0, 0x8c, 0x01, 0x05, 0x33, 0xff, 0x04, 0x06, 0x00,
            ],
        ),
        (
            12,
            Reply::Trigger {
                index: 2,
                position_counts: 9000,
                time_us: 123_456,
            },
            vec![
                0x05, 0x01, 0x0c, 0x86, 0x02, 0x01, 0x01, 0x03, 0x28, 0x23, 0x01, 0x04, 0x40, 0xe2,
                0x01, 0x03, 0xea, 0x8a, 0x00,
            ],
        ),
    ]
}

fn wire<M: Message>(seq: u8, m: &M) -> Vec<u8> {
    let mut out = [0u8; MAX_WIRE];
    let n = encode(seq, m, &mut out).unwrap();
    out[..n].to_vec()
}

fn decode_all<M: Message>(bytes: &[u8]) -> Vec<Result<Packet<M>, DecodeError>> {
    let mut d = Decoder::<M>::new();
    bytes.iter().filter_map(|&b| d.feed(b)).collect()
}

/// Every message encodes to its golden bytes and decodes back from them. The CRC is
/// CRC-16/IBM-3740 (check value 0x29b1 for "123456789"); the vectors were checked against an
/// independent implementation of it and of COBS.
#[test]
fn golden_vectors() {
    for (seq, m, bytes) in command_vectors() {
        assert_eq!(wire(seq, &m), bytes, "{m:?}");
        assert_eq!(
            decode_all::<Command>(&bytes),
            vec![Ok(Packet { seq, message: m })]
        );
    }
    for (seq, m, bytes) in reply_vectors() {
        assert_eq!(wire(seq, &m), bytes, "{m:?}");
        assert_eq!(
            decode_all::<Reply>(&bytes),
            vec![Ok(Packet { seq, message: m })]
        );
    }
}

/// A stream of every reply decodes identically whatever the chunk size (1 byte to all).
#[test]
fn any_chunking_decodes_the_same() {
    let stream: Vec<u8> = reply_vectors().into_iter().flat_map(|v| v.2).collect();
    let want: Vec<_> = reply_vectors()
        .into_iter()
        .map(|(seq, message, _)| Ok(Packet { seq, message }))
        .collect();
    for chunk in 1..=stream.len() {
        let mut d = Decoder::<Reply>::new();
        let mut got = Vec::new();
        for piece in stream.chunks(chunk) {
            got.extend(piece.iter().filter_map(|&b| d.feed(b)));
        }
        assert_eq!(got, want, "chunk {chunk}");
    }
}

/// Garbage before a frame costs at most one error, and the frame after the next delimiter
/// decodes; idle delimiters are silent.
#[test]
fn resynchronises_after_garbage() {
    let ack = wire(2, &Reply::Ack);
    let status = wire(
        6,
        &Reply::Status {
            position_counts: -5,
            flags: StatusFlags::default(),
            slot: 1,
        },
    );
    // Garbage ending in a delimiter: one error, then both frames.
    let mut s = vec![0x13, 0x37, 0xfe, 0x00, 0x00, 0x00];
    s.extend(&ack);
    s.extend(&status);
    let got = decode_all::<Reply>(&s);
    assert_eq!(got.len(), 3, "{got:?}");
    assert!(got[0].is_err());
    assert_eq!(
        got[1],
        Ok(Packet {
            seq: 2,
            message: Reply::Ack
        })
    );
    assert!(got[2].is_ok());
    // Garbage glued to a frame spoils that frame only.
    let mut s = vec![0x55, 0x66];
    s.extend(&ack);
    s.extend(&status);
    let got = decode_all::<Reply>(&s);
    assert!(
        got[0].is_err() && got[1].is_ok() && got.len() == 2,
        "{got:?}"
    );
    // Overlong garbage: TooLong, then the next frame.
    let mut s = vec![0xaa; 3 * MAX_WIRE];
    s.push(0);
    s.extend(&ack);
    let got = decode_all::<Reply>(&s);
    assert_eq!(
        got,
        vec![
            Err(DecodeError::TooLong),
            Ok(Packet {
                seq: 2,
                message: Reply::Ack
            })
        ]
    );
}

/// Every single-bit error in every golden frame is caught (CRC-16 detects all of them): the
/// decoder returns an error or, where the flip only split off an empty frame, the original
/// packet; never a different valid one.
#[test]
fn single_bit_errors_are_detected() {
    for (seq, m, bytes) in reply_vectors() {
        for i in 0..bytes.len() - 1 {
            for bit in 0..8 {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                for r in decode_all::<Reply>(&b) {
                    assert!(
                        r.is_err() || r == Ok(Packet { seq, message: m }),
                        "byte {i} bit {bit}: {r:?}"
                    );
                }
            }
        }
    }
}

/// Wrong version, unknown kind and wrong length are named.
#[test]
fn bad_frames_are_named() {
    // A command's bytes read as a reply: unknown kind 0x01.
    let e = decode_all::<Reply>(&wire(1, &Command::Identify));
    assert_eq!(e, vec![Err(DecodeError::UnknownKind { kind: 0x01 })]);
    // A reply read as a command.
    let e = decode_all::<Command>(&wire(1, &Reply::Ack));
    assert_eq!(e, vec![Err(DecodeError::UnknownKind { kind: 0x80 })]);
    // Hand-built frames through COBS: version 2, and Ack with a 1-byte payload.
    fn frame(raw: &[u8]) -> Vec<u8> {
        let crc = crc::Crc::<u16>::new(&crc::CRC_16_IBM_3740).checksum(raw);
        let mut body = raw.to_vec();
        body.extend(crc.to_le_bytes());
        let mut out = vec![0u8; body.len() + 4];
        let n = cobs::encode(&body, &mut out);
        out.truncate(n);
        out.push(0);
        out
    }
    assert_eq!(
        decode_all::<Reply>(&frame(&[2, 1, 0x80])),
        vec![Err(DecodeError::Version { found: 2 })]
    );
    assert_eq!(
        decode_all::<Reply>(&frame(&[1, 1, 0x80, 7])),
        vec![Err(DecodeError::Length {
            kind: 0x80,
            expected: 0,
            len: 1
        })]
    );
    assert_eq!(
        decode_all::<Reply>(&[0x02, 0x01, 0x00]),
        vec![Err(DecodeError::TooShort { len: 1 })]
    );
    // Unknown codes survive a round trip.
    let m = Reply::Nack {
        code: ErrorCode::Unknown(0x42),
    };
    assert_eq!(
        decode_all::<Reply>(&wire(9, &m)),
        vec![Ok(Packet { seq: 9, message: m })]
    );
    assert_eq!(next_seq(255), 1);
    assert_eq!(next_seq(1), 2);
}

fn any_command() -> impl Strategy<Value = Command> {
    prop_oneof![
        Just(Command::Identify),
        Just(Command::Home),
        any::<i32>().prop_map(|p| Command::MoveAbsolute { position_counts: p }),
        any::<i32>().prop_map(|d| Command::MoveRelative { delta_counts: d }),
        Just(Command::Stop),
        Just(Command::GetStatus),
        (any::<u32>(), any::<u32>()).prop_map(|(v, a)| Command::SetMotion {
            velocity_counts_per_s: v,
            acceleration_counts_per_s2: a
        }),
        any::<u8>().prop_map(|slot| Command::SelectSlot { slot }),
        Just(Command::Save),
        Just(Command::Reset),
        any::<i32>().prop_map(|v| Command::Spin {
            velocity_counts_per_s: v
        }),
        (any::<i32>(), any::<i32>(), any::<u32>()).prop_map(|(f, i, n)| Command::SetTrigger {
            first_counts: f,
            interval_counts: i,
            pulses: n
        }),
    ]
}

fn any_reply() -> impl Strategy<Value = Reply> {
    prop_oneof![
        Just(Reply::Ack),
        any::<u8>().prop_map(|b| Reply::Nack {
            code: ErrorCode::from_byte(b)
        }),
        (
            any::<u8>(),
            any::<[u8; 3]>(),
            any::<u8>(),
            any::<u32>(),
            any::<u8>(),
            any::<u32>()
        )
            .prop_map(|(v, f, d, c, s, n)| Reply::Identity {
                protocol_version: v,
                firmware: f,
                device: DeviceKind::from_byte(d),
                counts_per_turn: c,
                slots: s,
                serial: n
            }),
        (any::<i32>(), any::<u8>(), any::<u8>()).prop_map(|(p, f, s)| Reply::Status {
            position_counts: p,
            flags: StatusFlags(f),
            slot: s
        }),
        any::<i32>().prop_map(|p| Reply::MotionDone { position_counts: p }),
        any::<u8>().prop_map(|b| Reply::Boot {
            reason: BootReason::from_byte(b)
        }),
        (any::<u32>(), any::<i32>(), any::<u32>()).prop_map(|(k, p, t)| Reply::Trigger {
            index: k,
            position_counts: p,
            time_us: t
        }),
    ]
}

proptest! {
    /// Any command and reply with any sequence number round-trips; the wire form has exactly
    /// one zero byte, at the end.
    #[test]
    fn round_trip(seq in any::<u8>(), c in any_command(), r in any_reply()) {
        let w = wire(seq, &c);
        prop_assert_eq!(w.iter().filter(|&&b| b == 0).count(), 1);
        prop_assert_eq!(decode_all::<Command>(&w), vec![Ok(Packet { seq, message: c })]);
        let w = wire(seq, &r);
        prop_assert_eq!(decode_all::<Reply>(&w), vec![Ok(Packet { seq, message: r })]);
    }

    /// Arbitrary bytes never panic, and whatever decodes re-encodes to a frame that decodes to
    /// the same packet (the fuzz target's property, on the stable toolchain).
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        for r in decode_all::<Reply>(&bytes).into_iter().flatten() {
            let w = wire(r.seq, &r.message);
            prop_assert_eq!(decode_all::<Reply>(&w), vec![Ok(r)]);
        }
        for r in decode_all::<Command>(&bytes).into_iter().flatten() {
            let w = wire(r.seq, &r.message);
            prop_assert_eq!(decode_all::<Command>(&w), vec![Ok(r)]);
        }
    }
}
