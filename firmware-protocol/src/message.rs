//! Commands (host to device, kinds 0x01-0x7f) and replies (device to host, kinds 0x80-0xff),
//! with their payloads (SPEC.md).

use crate::{DecodeError, Message, MAX_PAYLOAD};

/// A command from the host.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// 0x01: ask for [`Reply::Identity`] (the handshake).
    Identify,
    /// 0x02: find the index and zero the position; [`Reply::Ack`] at once, then
    /// [`Reply::MotionDone`].
    Home,
    /// 0x03: move to an absolute position in encoder counts.
    MoveAbsolute {
        /// Target, counts.
        position_counts: i32,
    },
    /// 0x04: move by a signed number of counts.
    MoveRelative {
        /// Step, counts.
        delta_counts: i32,
    },
    /// 0x05: stop now (decelerate); [`Reply::MotionDone`] follows with where it stopped.
    Stop,
    /// 0x06: ask for [`Reply::Status`].
    GetStatus,
    /// 0x07: set the motion profile.
    SetMotion {
        /// Cruise velocity, counts per second (> 0).
        velocity_counts_per_s: u32,
        /// Acceleration, counts per second squared (> 0).
        acceleration_counts_per_s2: u32,
    },
    /// 0x08: go to a filter-wheel slot (0-based).
    SelectSlot {
        /// Slot index.
        slot: u8,
    },
    /// 0x09: store the motion profile in non-volatile memory.
    Save,
    /// 0x0a: reboot; the device sends [`Reply::Ack`], then a [`Reply::Boot`] notice.
    Reset,
    /// 0x0b: turn continuously at a signed velocity (velocity mode): ramp at the set
    /// acceleration and keep turning until [`Command::Stop`] or another `Spin`, which changes the
    /// speed without stopping. [`Reply::Ack`]; the [`Reply::MotionDone`] that ends the spin
    /// carries this command's number.
    Spin {
        /// Velocity, counts per second; the sign is the direction (non-zero).
        velocity_counts_per_s: i32,
    },
    /// 0x0c: arm the position-compare trigger: a pulse on the trigger output, with a
    /// [`Reply::Trigger`] event, when the position crosses `first_counts + k * interval_counts`
    /// (k = 0 .. pulses - 1) moving in the direction of `interval_counts`'s sign. `pulses` 0
    /// disarms.
    SetTrigger {
        /// Position of the first pulse, counts.
        first_counts: i32,
        /// Signed distance between pulses, counts (non-zero when armed); its sign is the
        /// direction of motion that fires.
        interval_counts: i32,
        /// Number of pulses (0 disarms).
        pulses: u32,
    },
}

/// What kind of device answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceKind {
    /// 1: a continuous rotation stage.
    Rotator,
    /// 2: a filter wheel with fixed slots.
    FilterWheel,
    /// Any other value, kept.
    Unknown(u8),
}

/// Why a command was refused: a closed set, with a catch-all for codes from newer firmware.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorCode {
    /// 1: the kind is not a command this firmware knows.
    UnknownCommand,
    /// 2: the payload length is wrong for the kind.
    BadLength,
    /// 3: a value is out of range (a slot past the last, a zero velocity).
    OutOfRange,
    /// 4: a motion is in progress; stop or wait for [`Reply::MotionDone`].
    Busy,
    /// 5: the command needs a homed axis.
    NotHomed,
    /// 6: the motor stalled (the encoder stopped following).
    Stalled,
    /// 7: the driver is too hot; motion refused until it cools.
    OverTemperature,
    /// 8: valid, but this device cannot do it (a slot on a rotator).
    Unsupported,
    /// Any other code, kept.
    Unknown(u8),
}

/// Why the device (re)booted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BootReason {
    /// 0: power on.
    PowerOn,
    /// 1: the watchdog fired.
    Watchdog,
    /// 2: a [`Command::Reset`].
    Command,
    /// 3: a brown-out.
    Brownout,
    /// Any other value, kept.
    Unknown(u8),
}

/// Status bits of [`Reply::Status`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StatusFlags(pub u8);

impl StatusFlags {
    /// Bit 0: homed since boot.
    pub const HOMED: u8 = 1 << 0;
    /// Bit 1: moving.
    pub const MOVING: u8 = 1 << 1;
    /// Bit 2: stalled (cleared by the next move or home).
    pub const STALLED: u8 = 1 << 2;
    /// Bit 3: over temperature.
    pub const OVER_TEMPERATURE: u8 = 1 << 3;
    /// Bit 4: turning in velocity mode ([`Command::Spin`]).
    pub const SPINNING: u8 = 1 << 4;
    /// Bit 5: the position-compare trigger is armed with pulses left ([`Command::SetTrigger`]).
    pub const TRIGGER_ARMED: u8 = 1 << 5;

    /// Whether every bit of `mask` is set.
    pub const fn has(self, mask: u8) -> bool {
        self.0 & mask == mask
    }
}

/// A reply or event from the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reply {
    /// 0x80: the command was accepted.
    Ack,
    /// 0x81: the command was refused.
    Nack {
        /// Why.
        code: ErrorCode,
    },
    /// 0x82: the answer to [`Command::Identify`].
    Identity {
        /// The command set's version ([`crate::PROTOCOL_VERSION`]).
        protocol_version: u8,
        /// Firmware version: major, minor, patch.
        firmware: [u8; 3],
        /// Rotator or filter wheel.
        device: DeviceKind,
        /// Encoder counts per full turn of the output.
        counts_per_turn: u32,
        /// Number of slots (0 for a rotator).
        slots: u8,
        /// Serial number.
        serial: u32,
    },
    /// 0x83: the answer to [`Command::GetStatus`].
    Status {
        /// Position, counts.
        position_counts: i32,
        /// Status bits.
        flags: StatusFlags,
        /// Current slot, or 0xff between slots or on a rotator.
        slot: u8,
    },
    /// 0x84: a motion ended (event; `seq` is the command that started it).
    MotionDone {
        /// Where it stopped, counts.
        position_counts: i32,
    },
    /// 0x85: the device booted (event; `seq` 0).
    Boot {
        /// Why.
        reason: BootReason,
    },
    /// 0x86: a position-compare trigger pulse (event; `seq` is the [`Command::SetTrigger`] that
    /// armed it).
    Trigger {
        /// The pulse's index `k`, from 0.
        index: u32,
        /// The encoder position latched at the pulse, counts.
        position_counts: i32,
        /// The device's clock at the pulse, microseconds (wraps at 2^32).
        time_us: u32,
    },
}

fn expect(kind: u8, payload: &[u8], expected: usize) -> Result<(), DecodeError> {
    if payload.len() == expected {
        Ok(())
    } else {
        Err(DecodeError::Length {
            kind,
            expected,
            len: payload.len(),
        })
    }
}

fn i32_at(p: &[u8], at: usize) -> i32 {
    i32::from_le_bytes([p[at], p[at + 1], p[at + 2], p[at + 3]])
}

fn u32_at(p: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([p[at], p[at + 1], p[at + 2], p[at + 3]])
}

impl Message for Command {
    fn kind(&self) -> u8 {
        match self {
            Command::Identify => 0x01,
            Command::Home => 0x02,
            Command::MoveAbsolute { .. } => 0x03,
            Command::MoveRelative { .. } => 0x04,
            Command::Stop => 0x05,
            Command::GetStatus => 0x06,
            Command::SetMotion { .. } => 0x07,
            Command::SelectSlot { .. } => 0x08,
            Command::Save => 0x09,
            Command::Reset => 0x0a,
            Command::Spin { .. } => 0x0b,
            Command::SetTrigger { .. } => 0x0c,
        }
    }

    fn write_payload(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize {
        match *self {
            Command::MoveAbsolute { position_counts: v }
            | Command::MoveRelative { delta_counts: v } => {
                out[..4].copy_from_slice(&v.to_le_bytes());
                4
            }
            Command::SetMotion {
                velocity_counts_per_s,
                acceleration_counts_per_s2,
            } => {
                out[..4].copy_from_slice(&velocity_counts_per_s.to_le_bytes());
                out[4..8].copy_from_slice(&acceleration_counts_per_s2.to_le_bytes());
                8
            }
            Command::SelectSlot { slot } => {
                out[0] = slot;
                1
            }
            Command::Spin {
                velocity_counts_per_s,
            } => {
                out[..4].copy_from_slice(&velocity_counts_per_s.to_le_bytes());
                4
            }
            Command::SetTrigger {
                first_counts,
                interval_counts,
                pulses,
            } => {
                out[..4].copy_from_slice(&first_counts.to_le_bytes());
                out[4..8].copy_from_slice(&interval_counts.to_le_bytes());
                out[8..12].copy_from_slice(&pulses.to_le_bytes());
                12
            }
            Command::Identify
            | Command::Home
            | Command::Stop
            | Command::GetStatus
            | Command::Save
            | Command::Reset => 0,
        }
    }

    fn read(kind: u8, p: &[u8]) -> Result<Self, DecodeError> {
        let empty = |c: Command| expect(kind, p, 0).map(|_| c);
        match kind {
            0x01 => empty(Command::Identify),
            0x02 => empty(Command::Home),
            0x03 => expect(kind, p, 4).map(|_| Command::MoveAbsolute {
                position_counts: i32_at(p, 0),
            }),
            0x04 => expect(kind, p, 4).map(|_| Command::MoveRelative {
                delta_counts: i32_at(p, 0),
            }),
            0x05 => empty(Command::Stop),
            0x06 => empty(Command::GetStatus),
            0x07 => expect(kind, p, 8).map(|_| Command::SetMotion {
                velocity_counts_per_s: u32_at(p, 0),
                acceleration_counts_per_s2: u32_at(p, 4),
            }),
            0x08 => expect(kind, p, 1).map(|_| Command::SelectSlot { slot: p[0] }),
            0x09 => empty(Command::Save),
            0x0a => empty(Command::Reset),
            0x0b => expect(kind, p, 4).map(|_| Command::Spin {
                velocity_counts_per_s: i32_at(p, 0),
            }),
            0x0c => expect(kind, p, 12).map(|_| Command::SetTrigger {
                first_counts: i32_at(p, 0),
                interval_counts: i32_at(p, 4),
                pulses: u32_at(p, 8),
            }),
            _ => Err(DecodeError::UnknownKind { kind }),
        }
    }
}

impl ErrorCode {
    /// The wire byte.
    pub const fn to_byte(self) -> u8 {
        match self {
            ErrorCode::UnknownCommand => 1,
            ErrorCode::BadLength => 2,
            ErrorCode::OutOfRange => 3,
            ErrorCode::Busy => 4,
            ErrorCode::NotHomed => 5,
            ErrorCode::Stalled => 6,
            ErrorCode::OverTemperature => 7,
            ErrorCode::Unsupported => 8,
            ErrorCode::Unknown(b) => b,
        }
    }

    /// From the wire byte (unknown values are kept).
    pub const fn from_byte(b: u8) -> Self {
        match b {
            1 => ErrorCode::UnknownCommand,
            2 => ErrorCode::BadLength,
            3 => ErrorCode::OutOfRange,
            4 => ErrorCode::Busy,
            5 => ErrorCode::NotHomed,
            6 => ErrorCode::Stalled,
            7 => ErrorCode::OverTemperature,
            8 => ErrorCode::Unsupported,
            other => ErrorCode::Unknown(other),
        }
    }
}

impl DeviceKind {
    /// The wire byte.
    pub const fn to_byte(self) -> u8 {
        match self {
            DeviceKind::Rotator => 1,
            DeviceKind::FilterWheel => 2,
            DeviceKind::Unknown(b) => b,
        }
    }

    /// From the wire byte (unknown values are kept).
    pub const fn from_byte(b: u8) -> Self {
        match b {
            1 => DeviceKind::Rotator,
            2 => DeviceKind::FilterWheel,
            other => DeviceKind::Unknown(other),
        }
    }
}

impl BootReason {
    /// The wire byte.
    pub const fn to_byte(self) -> u8 {
        match self {
            BootReason::PowerOn => 0,
            BootReason::Watchdog => 1,
            BootReason::Command => 2,
            BootReason::Brownout => 3,
            BootReason::Unknown(b) => b,
        }
    }

    /// From the wire byte (unknown values are kept).
    pub const fn from_byte(b: u8) -> Self {
        match b {
            0 => BootReason::PowerOn,
            1 => BootReason::Watchdog,
            2 => BootReason::Command,
            3 => BootReason::Brownout,
            other => BootReason::Unknown(other),
        }
    }
}

impl Message for Reply {
    fn kind(&self) -> u8 {
        match self {
            Reply::Ack => 0x80,
            Reply::Nack { .. } => 0x81,
            Reply::Identity { .. } => 0x82,
            Reply::Status { .. } => 0x83,
            Reply::MotionDone { .. } => 0x84,
            Reply::Boot { .. } => 0x85,
            Reply::Trigger { .. } => 0x86,
        }
    }

    fn write_payload(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize {
        match *self {
            Reply::Ack => 0,
            Reply::Nack { code } => {
                out[0] = code.to_byte();
                1
            }
            Reply::Identity {
                protocol_version,
                firmware,
                device,
                counts_per_turn,
                slots,
                serial,
            } => {
                out[0] = protocol_version;
                out[1..4].copy_from_slice(&firmware);
                out[4] = device.to_byte();
                out[5..9].copy_from_slice(&counts_per_turn.to_le_bytes());
                out[9] = slots;
                out[10..14].copy_from_slice(&serial.to_le_bytes());
                14
            }
            Reply::Status {
                position_counts,
                flags,
                slot,
            } => {
                out[..4].copy_from_slice(&position_counts.to_le_bytes());
                out[4] = flags.0;
                out[5] = slot;
                6
            }
            Reply::MotionDone { position_counts } => {
                out[..4].copy_from_slice(&position_counts.to_le_bytes());
                4
            }
            Reply::Boot { reason } => {
                out[0] = reason.to_byte();
                1
            }
            Reply::Trigger {
                index,
                position_counts,
                time_us,
            } => {
                out[..4].copy_from_slice(&index.to_le_bytes());
                out[4..8].copy_from_slice(&position_counts.to_le_bytes());
                out[8..12].copy_from_slice(&time_us.to_le_bytes());
                12
            }
        }
    }

    fn read(kind: u8, p: &[u8]) -> Result<Self, DecodeError> {
        match kind {
            0x80 => expect(kind, p, 0).map(|_| Reply::Ack),
            0x81 => expect(kind, p, 1).map(|_| Reply::Nack {
                code: ErrorCode::from_byte(p[0]),
            }),
            0x82 => expect(kind, p, 14).map(|_| Reply::Identity {
                protocol_version: p[0],
                firmware: [p[1], p[2], p[3]],
                device: DeviceKind::from_byte(p[4]),
                counts_per_turn: u32_at(p, 5),
                slots: p[9],
                serial: u32_at(p, 10),
            }),
            0x83 => expect(kind, p, 6).map(|_| Reply::Status {
                position_counts: i32_at(p, 0),
                flags: StatusFlags(p[4]),
                slot: p[5],
            }),
            0x84 => expect(kind, p, 4).map(|_| Reply::MotionDone {
                position_counts: i32_at(p, 0),
            }),
            0x85 => expect(kind, p, 1).map(|_| Reply::Boot {
                reason: BootReason::from_byte(p[0]),
            }),
            0x86 => expect(kind, p, 12).map(|_| Reply::Trigger {
                index: u32_at(p, 0),
                position_counts: i32_at(p, 4),
                time_us: u32_at(p, 8),
            }),
            _ => Err(DecodeError::UnknownKind { kind }),
        }
    }
}
