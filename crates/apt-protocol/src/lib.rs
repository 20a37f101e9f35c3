//! The Thorlabs APT message codec (`docs/DEVICES.md`, section "Thorlabs APT"): 6-byte headers,
//! little-endian, with an optional data packet, as the "APT Controllers Host-Controller
//! Communications Protocol" defines them and thorlabs-apt-device and pylablib send them.
//!
//! * Short form: `id: u16, param1: u8, param2: u8, dest: u8, source: u8`.
//! * Long form: `id: u16, length: u16, dest | 0x80, source`, then `length` data bytes.
//!
//! The protocol has no checksum, so a reply is accepted only if its identifier is one the host
//! expects, its form (short or long) and data length are that identifier's, it is addressed to
//! the host and comes from a controller. Anything else is skipped one byte at a time until a
//! plausible header lines up again (what thorlabs-apt-device's unpacker does).
#![warn(missing_docs)]

/// The host (the PC).
pub const HOST: u8 = 0x01;
/// A stand-alone USB controller (K-Cube, T-Cube, K10CR1).
pub const USB: u8 = 0x50;
/// The only channel of a single-channel controller.
pub const CHANNEL: u8 = 1;

/// `HW_DISCONNECT`.
pub const HW_DISCONNECT: u16 = 0x0002;
/// `HW_REQ_INFO`.
pub const HW_REQ_INFO: u16 = 0x0005;
/// `HW_GET_INFO` (84 data bytes).
pub const HW_GET_INFO: u16 = 0x0006;
/// `HW_START_UPDATEMSGS`: unsolicited status updates every 100 ms.
pub const HW_START_UPDATEMSGS: u16 = 0x0011;
/// `HW_STOP_UPDATEMSGS`.
pub const HW_STOP_UPDATEMSGS: u16 = 0x0012;
/// `HW_NO_FLASH_PROGRAMMING`, sent once at connect.
pub const HW_NO_FLASH_PROGRAMMING: u16 = 0x0018;
/// `HW_RESPONSE`: an event without details.
pub const HW_RESPONSE: u16 = 0x0080;
/// `HW_RICHRESPONSE`: an event with a code and 64 bytes of notes.
pub const HW_RICHRESPONSE: u16 = 0x0081;
/// `MOD_SET_CHANENABLESTATE` (param2 1 = enable, 2 = disable).
pub const MOD_SET_CHANENABLESTATE: u16 = 0x0210;
/// `MOD_REQ_CHANENABLESTATE`.
pub const MOD_REQ_CHANENABLESTATE: u16 = 0x0211;
/// `MOD_GET_CHANENABLESTATE`.
pub const MOD_GET_CHANENABLESTATE: u16 = 0x0212;
/// `MOD_IDENTIFY`: flash the front panel.
pub const MOD_IDENTIFY: u16 = 0x0223;
/// `MOT_SET_ENCCOUNTER`.
pub const MOT_SET_ENCCOUNTER: u16 = 0x0409;
/// `MOT_REQ_ENCCOUNTER`.
pub const MOT_REQ_ENCCOUNTER: u16 = 0x040A;
/// `MOT_GET_ENCCOUNTER`.
pub const MOT_GET_ENCCOUNTER: u16 = 0x040B;
/// `MOT_SET_POSCOUNTER`.
pub const MOT_SET_POSCOUNTER: u16 = 0x0410;
/// `MOT_REQ_POSCOUNTER`.
pub const MOT_REQ_POSCOUNTER: u16 = 0x0411;
/// `MOT_GET_POSCOUNTER`.
pub const MOT_GET_POSCOUNTER: u16 = 0x0412;
/// `MOT_SET_VELPARAMS`.
pub const MOT_SET_VELPARAMS: u16 = 0x0413;
/// `MOT_REQ_VELPARAMS`.
pub const MOT_REQ_VELPARAMS: u16 = 0x0414;
/// `MOT_GET_VELPARAMS`.
pub const MOT_GET_VELPARAMS: u16 = 0x0415;
/// `MOT_SET_JOGPARAMS`.
pub const MOT_SET_JOGPARAMS: u16 = 0x0416;
/// `MOT_REQ_JOGPARAMS`.
pub const MOT_REQ_JOGPARAMS: u16 = 0x0417;
/// `MOT_GET_JOGPARAMS`.
pub const MOT_GET_JOGPARAMS: u16 = 0x0418;
/// `MOT_REQ_STATUSBITS`.
pub const MOT_REQ_STATUSBITS: u16 = 0x0429;
/// `MOT_GET_STATUSBITS`.
pub const MOT_GET_STATUSBITS: u16 = 0x042A;
/// `MOT_SET_GENMOVEPARAMS` (backlash distance).
pub const MOT_SET_GENMOVEPARAMS: u16 = 0x043A;
/// `MOT_REQ_GENMOVEPARAMS`.
pub const MOT_REQ_GENMOVEPARAMS: u16 = 0x043B;
/// `MOT_GET_GENMOVEPARAMS`.
pub const MOT_GET_GENMOVEPARAMS: u16 = 0x043C;
/// `MOT_SET_HOMEPARAMS`.
pub const MOT_SET_HOMEPARAMS: u16 = 0x0440;
/// `MOT_REQ_HOMEPARAMS`.
pub const MOT_REQ_HOMEPARAMS: u16 = 0x0441;
/// `MOT_GET_HOMEPARAMS`.
pub const MOT_GET_HOMEPARAMS: u16 = 0x0442;
/// `MOT_MOVE_HOME`.
pub const MOT_MOVE_HOME: u16 = 0x0443;
/// `MOT_MOVE_HOMED`.
pub const MOT_MOVE_HOMED: u16 = 0x0444;
/// `MOT_SET_MOVERELPARAMS`.
pub const MOT_SET_MOVERELPARAMS: u16 = 0x0445;
/// `MOT_REQ_MOVERELPARAMS`.
pub const MOT_REQ_MOVERELPARAMS: u16 = 0x0446;
/// `MOT_GET_MOVERELPARAMS`.
pub const MOT_GET_MOVERELPARAMS: u16 = 0x0447;
/// `MOT_MOVE_RELATIVE`.
pub const MOT_MOVE_RELATIVE: u16 = 0x0448;
/// `MOT_SET_MOVEABSPARAMS`.
pub const MOT_SET_MOVEABSPARAMS: u16 = 0x0450;
/// `MOT_REQ_MOVEABSPARAMS`.
pub const MOT_REQ_MOVEABSPARAMS: u16 = 0x0451;
/// `MOT_GET_MOVEABSPARAMS`.
pub const MOT_GET_MOVEABSPARAMS: u16 = 0x0452;
/// `MOT_MOVE_ABSOLUTE`.
pub const MOT_MOVE_ABSOLUTE: u16 = 0x0453;
/// `MOT_MOVE_VELOCITY` (param2 1 = forward, 2 = reverse).
pub const MOT_MOVE_VELOCITY: u16 = 0x0457;
/// `MOT_MOVE_COMPLETED` (14 data bytes: a status update).
pub const MOT_MOVE_COMPLETED: u16 = 0x0464;
/// `MOT_MOVE_STOP` (param2 1 = immediate, 2 = profiled).
pub const MOT_MOVE_STOP: u16 = 0x0465;
/// `MOT_MOVE_STOPPED` (14 data bytes: a status update).
pub const MOT_MOVE_STOPPED: u16 = 0x0466;
/// `MOT_MOVE_JOG` (param2 1 = forward, 2 = reverse).
pub const MOT_MOVE_JOG: u16 = 0x046A;
/// `MOT_REQ_STATUSUPDATE` (steppers: K10CR1).
pub const MOT_REQ_STATUSUPDATE: u16 = 0x0480;
/// `MOT_GET_STATUSUPDATE`: position, encoder count, status bits.
pub const MOT_GET_STATUSUPDATE: u16 = 0x0481;
/// `MOT_ACK_DCSTATUSUPDATE`: the host's keep-alive while update messages run.
pub const MOT_ACK_DCSTATUSUPDATE: u16 = 0x0492;
/// `MOT_REQ_DCSTATUSUPDATE` (DC servo controllers: KDC101).
pub const MOT_REQ_DCSTATUSUPDATE: u16 = 0x0490;
/// `MOT_GET_DCSTATUSUPDATE`: position, velocity, status bits.
pub const MOT_GET_DCSTATUSUPDATE: u16 = 0x0491;

/// Status bits (`MOT_GET_STATUSBITS` and the status updates; the protocol's
/// `P_MOT_SB_*` names). Forward is toward increasing counts.
pub mod status {
    /// Forward (clockwise) hardware limit switch.
    pub const FWD_LIMIT: u32 = 0x0000_0001;
    /// Reverse (counter-clockwise) hardware limit switch; on the rotation mounts, the home
    /// switch.
    pub const REV_LIMIT: u32 = 0x0000_0002;
    /// Moving forward.
    pub const MOVING_FWD: u32 = 0x0000_0010;
    /// Moving in reverse.
    pub const MOVING_REV: u32 = 0x0000_0020;
    /// Jogging forward.
    pub const JOGGING_FWD: u32 = 0x0000_0040;
    /// Jogging in reverse.
    pub const JOGGING_REV: u32 = 0x0000_0080;
    /// Motor connected.
    pub const CONNECTED: u32 = 0x0000_0100;
    /// Homing.
    pub const HOMING: u32 = 0x0000_0200;
    /// Homed (the datum is set).
    pub const HOMED: u32 = 0x0000_0400;
    /// Position within the trajectory (DC servo).
    pub const TRACKING: u32 = 0x0000_1000;
    /// Settled at the target (DC servo).
    pub const SETTLED: u32 = 0x0000_2000;
    /// Excessive position error.
    pub const MOTION_ERROR: u32 = 0x0000_4000;
    /// Over temperature.
    pub const OVERTEMP: u32 = 0x0002_0000;
    /// Channel enabled.
    pub const ENABLED: u32 = 0x8000_0000;
    /// Any motion (moving, jogging or homing).
    pub const IN_MOTION: u32 = MOVING_FWD | MOVING_REV | JOGGING_FWD | JOGGING_REV | HOMING;
}

/// The form of a message the host receives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Form {
    Short,
    Long(usize),
}

/// The replies and events a host accepts, with their forms.
fn reply_form(id: u16) -> Option<Form> {
    Some(match id {
        HW_DISCONNECT | HW_RESPONSE | MOD_GET_CHANENABLESTATE | MOT_MOVE_HOMED => Form::Short,
        HW_GET_INFO => Form::Long(84),
        HW_RICHRESPONSE => Form::Long(68),
        MOT_GET_POSCOUNTER | MOT_GET_ENCCOUNTER | MOT_GET_STATUSBITS | MOT_GET_GENMOVEPARAMS => {
            Form::Long(6)
        }
        MOT_GET_VELPARAMS
        | MOT_GET_HOMEPARAMS
        | MOT_MOVE_COMPLETED
        | MOT_MOVE_STOPPED
        | MOT_GET_STATUSUPDATE
        | MOT_GET_DCSTATUSUPDATE => Form::Long(14),
        MOT_GET_JOGPARAMS => Form::Long(22),
        _ => return None,
    })
}

/// One APT message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Message {
    /// Message identifier.
    pub id: u16,
    /// First header parameter (short form; 0 in the long form).
    pub param1: u8,
    /// Second header parameter (short form; 0 in the long form).
    pub param2: u8,
    /// Destination.
    pub dest: u8,
    /// Source.
    pub source: u8,
    /// The data packet (`None` for the short form).
    pub data: Option<Vec<u8>>,
}

impl Message {
    /// A short-form message from the host to a USB controller.
    pub fn short(id: u16, param1: u8, param2: u8) -> Self {
        Message {
            id,
            param1,
            param2,
            dest: USB,
            source: HOST,
            data: None,
        }
    }

    /// A long-form message from the host to a USB controller.
    pub fn long(id: u16, data: Vec<u8>) -> Self {
        Message {
            id,
            param1: 0,
            param2: 0,
            dest: USB,
            source: HOST,
            data: Some(data),
        }
    }

    /// The bytes on the wire.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(6 + self.data.as_ref().map_or(0, Vec::len));
        out.extend_from_slice(&self.id.to_le_bytes());
        match &self.data {
            Some(data) => {
                out.extend_from_slice(&(data.len() as u16).to_le_bytes());
                out.push(self.dest | 0x80);
                out.push(self.source);
                out.extend_from_slice(data);
            }
            None => {
                out.extend_from_slice(&[self.param1, self.param2, self.dest, self.source]);
            }
        }
        out
    }

    /// The data packet, or an empty slice.
    pub fn data(&self) -> &[u8] {
        self.data.as_deref().unwrap_or(&[])
    }

    /// The same message sent the other way: from the controller to the host (the simulators'
    /// replies).
    pub fn sent_by_controller(mut self) -> Self {
        std::mem::swap(&mut self.dest, &mut self.source);
        self
    }

    /// The little-endian `i32` at data offset `at` (0 if the packet is too short).
    pub fn i32_at(&self, at: usize) -> i32 {
        le_i32(self.data(), at)
    }

    /// The little-endian `u32` at data offset `at`.
    pub fn u32_at(&self, at: usize) -> u32 {
        self.i32_at(at) as u32
    }

    /// The little-endian `u16` at data offset `at` (0 if the packet is too short).
    pub fn u16_at(&self, at: usize) -> u16 {
        le_u16(self.data(), at)
    }
}

/// The little-endian `i32` at offset `at` of a data packet (0 if the packet is too short).
pub fn le_i32(data: &[u8], at: usize) -> i32 {
    data.get(at..at + 4)
        .map_or(0, |b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// The little-endian `u16` at offset `at` of a data packet (0 if the packet is too short).
pub fn le_u16(data: &[u8], at: usize) -> u16 {
    data.get(at..at + 2)
        .map_or(0, |b| u16::from_le_bytes([b[0], b[1]]))
}

/// A move to `position` counts on channel 1 (`MOT_MOVE_ABSOLUTE`, long form).
pub fn move_absolute(position: i32) -> Message {
    Message::long(MOT_MOVE_ABSOLUTE, chan_i32(position))
}

/// A relative move by `distance` counts on channel 1 (`MOT_MOVE_RELATIVE`, long form).
pub fn move_relative(distance: i32) -> Message {
    Message::long(MOT_MOVE_RELATIVE, chan_i32(distance))
}

fn chan_i32(value: i32) -> Vec<u8> {
    let mut d = u16::from(CHANNEL).to_le_bytes().to_vec();
    d.extend_from_slice(&value.to_le_bytes());
    d
}

/// What [`decode`] found at the start of a buffer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decoded {
    /// A whole message, and how many bytes it took.
    Message(Message, usize),
    /// The start of a plausible message: more bytes are needed.
    Incomplete,
    /// The first byte cannot start a message the host accepts: drop it and look again.
    Invalid,
}

/// Decodes the message at the start of `buf` (host side: replies and events only).
pub fn decode(buf: &[u8]) -> Decoded {
    if buf.len() < 6 {
        return Decoded::Incomplete;
    }
    let id = u16::from_le_bytes([buf[0], buf[1]]);
    let long = buf[4] & 0x80 != 0;
    let dest = buf[4] & 0x7F;
    let source = buf[5];
    let source_ok = source == USB || source == 0x11 || (0x21..=0x2A).contains(&source);
    if !(dest == HOST || dest == 0) || !source_ok {
        return Decoded::Invalid;
    }
    match (reply_form(id), long) {
        (Some(Form::Short), false) => Decoded::Message(
            Message {
                id,
                param1: buf[2],
                param2: buf[3],
                dest,
                source,
                data: None,
            },
            6,
        ),
        (Some(Form::Long(n)), true) => {
            let length = usize::from(u16::from_le_bytes([buf[2], buf[3]]));
            if length != n {
                return Decoded::Invalid;
            }
            if buf.len() < 6 + n {
                return Decoded::Incomplete;
            }
            Decoded::Message(
                Message {
                    id,
                    param1: 0,
                    param2: 0,
                    dest,
                    source,
                    data: Some(buf[6..6 + n].to_vec()),
                },
                6 + n,
            )
        }
        _ => Decoded::Invalid,
    }
}

/// The `HW_GET_INFO` data packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HwInfo {
    /// Serial number (its first two digits name the controller type: 27 KDC101, 55 K10CR1).
    pub serial: u32,
    /// Model number, such as `KDC101` or `K10CR1`.
    pub model: String,
    /// Hardware type (44 = brushless DC controller, 45 = multi-channel motherboard).
    pub hw_type: u16,
    /// Firmware version (major, interim, minor).
    pub firmware: (u8, u8, u8),
    /// Free text.
    pub notes: String,
    /// The stage the controller is set up for, where it reports one (KDC101: 6 = PRM1-Z8,
    /// pylablib's table); 0 otherwise.
    pub stage_id: u16,
    /// Hardware version.
    pub hw_version: u16,
    /// Modification state.
    pub mod_state: u16,
    /// Number of channels.
    pub channels: u16,
}

impl HwInfo {
    /// Parses the 84-byte data packet.
    pub fn parse(data: &[u8]) -> Result<Self, String> {
        if data.len() != 84 {
            return Err(format!(
                "HW_GET_INFO data has {} bytes: allowed 84",
                data.len()
            ));
        }
        let u16_at = |a: usize| u16::from_le_bytes([data[a], data[a + 1]]);
        let text = |a: usize, b: usize| {
            String::from_utf8_lossy(&data[a..b])
                .trim_matches(|c: char| c == '\0' || c.is_whitespace())
                .to_string()
        };
        Ok(HwInfo {
            serial: u32::from_le_bytes([data[0], data[1], data[2], data[3]]),
            model: text(4, 12),
            hw_type: u16_at(12),
            firmware: (data[16], data[15], data[14]),
            notes: text(18, 66),
            stage_id: u16_at(76),
            hw_version: u16_at(78),
            mod_state: u16_at(80),
            channels: u16_at(82),
        })
    }
}

/// Velocity parameters in the controller's units (`MOT_GET_VELPARAMS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VelParams {
    /// Minimum (start) velocity.
    pub min_velocity: i32,
    /// Acceleration.
    pub acceleration: i32,
    /// Maximum (cruise) velocity.
    pub max_velocity: i32,
}

impl VelParams {
    /// From a `MOT_GET_VELPARAMS` message.
    pub fn from_message(m: &Message) -> Self {
        VelParams {
            min_velocity: m.i32_at(2),
            acceleration: m.i32_at(6),
            max_velocity: m.i32_at(10),
        }
    }

    /// The `MOT_SET_VELPARAMS` message for channel 1.
    pub fn set_message(&self) -> Message {
        let mut d = u16::from(CHANNEL).to_le_bytes().to_vec();
        for v in [self.min_velocity, self.acceleration, self.max_velocity] {
            d.extend_from_slice(&v.to_le_bytes());
        }
        Message::long(MOT_SET_VELPARAMS, d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(bytes: &[u8]) -> String {
        bytes.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Requests encode to the bytes thorlabs-apt-device 0.3.8's `protocol.functions` produce for
    /// the same arguments (dest 0x50, source 0x01, channel 1): the golden vectors were taken
    /// from that library.
    #[test]
    fn requests_match_the_public_client_bytes() {
        assert_eq!(
            hex(&move_absolute(172_800).encode()),
            "53040600d001010000a30200"
        );
        assert_eq!(
            hex(&move_absolute(-1919).encode()),
            "53040600d001010081f8ffff"
        );
        assert_eq!(
            hex(&Message::short(HW_REQ_INFO, 0, 0).encode()),
            "050000005001"
        );
        assert_eq!(
            hex(&Message::short(MOT_MOVE_HOME, 1, 0).encode()),
            "430401005001"
        );
        assert_eq!(
            hex(&Message::short(MOD_SET_CHANENABLESTATE, 1, 1).encode()),
            "100201015001"
        );
        let v = VelParams {
            min_velocity: 0,
            acceleration: 4506,
            max_velocity: 42941,
        };
        assert_eq!(
            hex(&v.set_message().encode()),
            "13040e00d0010100000000009a110000bda70000"
        );
        assert_eq!(
            hex(&Message::short(MOT_REQ_POSCOUNTER, 1, 0).encode()),
            "110401005001"
        );
        assert_eq!(
            hex(&Message::short(MOT_MOVE_STOP, 1, 2).encode()),
            "650401025001"
        );
        assert_eq!(
            hex(&Message::short(HW_NO_FLASH_PROGRAMMING, 0, 0).encode()),
            "180000005001"
        );
    }

    /// A `MOT_MOVE_COMPLETED` (the bytes thorlabs-apt-device parses as position -5, homed,
    /// enabled) decodes with its fields; a short read is incomplete; a wrong length, a wrong
    /// destination, an unknown identifier or a request's identifier are invalid.
    #[test]
    fn replies_decode_strictly() {
        let bytes = [
            0x64, 0x04, 0x0e, 0x00, 0x81, 0x50, 0x01, 0x00, 0xfb, 0xff, 0xff, 0xff, 0, 0, 0, 0,
            0x00, 0x04, 0x00, 0x80,
        ];
        let Decoded::Message(m, n) = decode(&bytes) else {
            panic!("not decoded")
        };
        assert_eq!((m.id, n, m.source), (MOT_MOVE_COMPLETED, 20, USB));
        assert_eq!(m.i32_at(2), -5);
        assert_eq!(m.u32_at(10), status::HOMED | status::ENABLED);
        assert_eq!(decode(&bytes[..10]), Decoded::Incomplete);
        let mut bad_len = bytes;
        bad_len[2] = 0x0d;
        assert_eq!(decode(&bad_len), Decoded::Invalid);
        let mut bad_dest = bytes;
        bad_dest[4] = 0x83;
        assert_eq!(decode(&bad_dest), Decoded::Invalid);
        assert_eq!(decode(&[0x99, 0x09, 0, 0, 0x01, 0x50]), Decoded::Invalid);
        assert_eq!(
            decode(&[0x53, 0x04, 1, 0, 0x01, 0x50]),
            Decoded::Invalid,
            "a request"
        );
        let homed = decode(&[0x44, 0x04, 0x01, 0x00, 0x01, 0x50]);
        assert!(
            matches!(homed, Decoded::Message(ref m, 6) if m.id == MOT_MOVE_HOMED && m.param1 == 1)
        );
    }

    /// `HW_GET_INFO` fields at the offsets both public clients read: serial at 0, model at 4..12,
    /// type at 12, firmware (minor, interim, major) at 14..17, stage at 76, channels at 82.
    #[test]
    fn hw_info_parses() {
        let mut d = vec![0u8; 84];
        d[..4].copy_from_slice(&27_000_123u32.to_le_bytes());
        d[4..10].copy_from_slice(b"KDC101");
        d[12..14].copy_from_slice(&16u16.to_le_bytes());
        d[14..17].copy_from_slice(&[3, 0, 1]);
        d[18..23].copy_from_slice(b"brush");
        d[76..78].copy_from_slice(&6u16.to_le_bytes());
        d[82..84].copy_from_slice(&1u16.to_le_bytes());
        let info = HwInfo::parse(&d).unwrap();
        assert_eq!(info.serial, 27_000_123);
        assert_eq!(info.model, "KDC101");
        assert_eq!(info.firmware, (1, 0, 3));
        assert_eq!(info.notes, "brush");
        assert_eq!((info.stage_id, info.channels), (6, 1));
        assert!(HwInfo::parse(&d[..80]).unwrap_err().contains("80 bytes"));
    }
}
