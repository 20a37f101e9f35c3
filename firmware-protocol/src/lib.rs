//! The wire protocol of the polarimeter's own rotation-stage and filter-wheel controller
//! (`SPEC.md` beside this crate is the normative description, with golden byte vectors).
//!
//! * **Framing**: each frame is `version, seq, kind, payload..., crc16` (CRC-16/IBM-3740, also
//!   called CCITT-FALSE, little-endian, over every byte before it), COBS-encoded so that it holds
//!   no zero byte, and terminated by one `0x00`. The receiver needs no length field and finds the
//!   next frame after any garbage at the next `0x00`.
//! * **Sequence numbers**: the host numbers its commands 1..=255, wrapping to 1; the device
//!   answers with the command's number. 0 marks unsolicited messages (a boot notice).
//!   [`Reply::MotionDone`] carries the number of the command that started the motion.
//! * **Handshake**: the host sends [`Command::Identify`]; [`Reply::Identity`] gives the command
//!   set's version and the device's capabilities (counts per turn, slots). A host refuses a
//!   device whose `protocol_version` it does not know.
//! * **Decoding** is incremental ([`Decoder::feed`] takes one byte at a time, so any chunking
//!   works), never allocates, never panics, and resynchronises after garbage: bytes that do not
//!   form a valid frame cost one [`DecodeError`] and are dropped at the next delimiter.
//!
//! All integers are little-endian. The crate is `no_std`; `alloc` adds [`encode_vec`], `std`
//! adds `std::error::Error` through `core::error::Error`.
#![no_std]
#![warn(missing_docs)]

#[cfg(feature = "alloc")]
extern crate alloc;

mod message;

pub use message::{BootReason, Command, DeviceKind, ErrorCode, Reply, StatusFlags};

/// The framing version: the first byte of every frame.
pub const FRAME_VERSION: u8 = 1;
/// The command set's version that this crate speaks (reported in [`Reply::Identity`]).
pub const PROTOCOL_VERSION: u8 = 1;
/// The largest payload of any message, bytes.
pub const MAX_PAYLOAD: usize = 16;
/// Header (version, seq, kind) plus CRC, bytes.
pub const OVERHEAD: usize = 5;
/// The largest frame before COBS, bytes.
pub const MAX_FRAME: usize = OVERHEAD + MAX_PAYLOAD;
/// The largest frame on the wire: COBS adds one byte per 254 and the delimiter one more.
pub const MAX_WIRE: usize = MAX_FRAME + MAX_FRAME.div_ceil(254) + 1;

const CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_IBM_3740);

/// A message type that travels in frames: [`Command`] (host to device) or [`Reply`].
pub trait Message: Sized {
    /// The message's kind byte.
    fn kind(&self) -> u8;
    /// Writes the payload into `out` (at least [`MAX_PAYLOAD`] bytes) and returns its length.
    fn write_payload(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize;
    /// Parses a payload of `kind`.
    fn read(kind: u8, payload: &[u8]) -> Result<Self, DecodeError>;
}

/// A decoded frame: the sequence number and the message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Packet<M> {
    /// Sequence number (0: unsolicited).
    pub seq: u8,
    /// The message.
    pub message: M,
}

/// Why bytes between two delimiters were not a frame. Each names what was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The bytes are not valid COBS.
    #[error("frame is not valid COBS")]
    Cobs,
    /// More bytes than the largest frame arrived before a delimiter.
    #[error("no delimiter within {MAX_WIRE} bytes: frame too long, dropped")]
    TooLong,
    /// The frame is shorter than a header and CRC.
    #[error("frame of {len} bytes is shorter than the {OVERHEAD}-byte header and CRC")]
    TooShort {
        /// Decoded length.
        len: usize,
    },
    /// The CRC does not match.
    #[error("CRC mismatch: frame says {found:#06x}, bytes give {computed:#06x}")]
    Crc {
        /// The CRC in the frame.
        found: u16,
        /// The CRC of the bytes.
        computed: u16,
    },
    /// An unknown framing version.
    #[error("framing version {found}, this side speaks {FRAME_VERSION}")]
    Version {
        /// The version byte found.
        found: u8,
    },
    /// A kind byte this message type does not have.
    #[error("unknown message kind {kind:#04x}")]
    UnknownKind {
        /// The kind byte.
        kind: u8,
    },
    /// A payload of the wrong length for its kind.
    #[error("kind {kind:#04x} needs a {expected}-byte payload, got {len}")]
    Length {
        /// The kind byte.
        kind: u8,
        /// Expected payload length.
        expected: usize,
        /// Payload length found.
        len: usize,
    },
}

/// Encoding failures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// The output buffer is shorter than [`MAX_WIRE`].
    #[error("output buffer of {len} bytes is shorter than MAX_WIRE = {MAX_WIRE}")]
    BufferTooSmall {
        /// The buffer's length.
        len: usize,
    },
}

/// Encodes `message` with sequence number `seq` into `out` (at least [`MAX_WIRE`] bytes):
/// COBS of `version, seq, kind, payload, crc16` followed by `0x00`. Returns the bytes written.
pub fn encode<M: Message>(seq: u8, message: &M, out: &mut [u8]) -> Result<usize, EncodeError> {
    if out.len() < MAX_WIRE {
        return Err(EncodeError::BufferTooSmall { len: out.len() });
    }
    let mut raw = [0u8; MAX_FRAME];
    let mut payload = [0u8; MAX_PAYLOAD];
    let n = message.write_payload(&mut payload).min(MAX_PAYLOAD);
    raw[0] = FRAME_VERSION;
    raw[1] = seq;
    raw[2] = message.kind();
    raw[3..3 + n].copy_from_slice(&payload[..n]);
    let crc = CRC.checksum(&raw[..3 + n]);
    raw[3 + n..5 + n].copy_from_slice(&crc.to_le_bytes());
    let written = cobs::try_encode(&raw[..5 + n], &mut out[..MAX_WIRE - 1])
        .map_err(|_| EncodeError::BufferTooSmall { len: out.len() })?;
    out[written] = 0;
    Ok(written + 1)
}

/// [`encode`] into a new vector.
#[cfg(feature = "alloc")]
pub fn encode_vec<M: Message>(seq: u8, message: &M) -> alloc::vec::Vec<u8> {
    let mut out = [0u8; MAX_WIRE];
    // MAX_WIRE bytes always suffice, so this cannot fail.
    let n = encode(seq, message, &mut out).unwrap_or(0);
    out[..n].to_vec()
}

/// Parses one decoded (un-COBSed) frame.
fn parse<M: Message>(raw: &[u8]) -> Result<Packet<M>, DecodeError> {
    if raw.len() < OVERHEAD {
        return Err(DecodeError::TooShort { len: raw.len() });
    }
    let (body, crc) = raw.split_at(raw.len() - 2);
    let found = u16::from_le_bytes([crc[0], crc[1]]);
    let computed = CRC.checksum(body);
    if found != computed {
        return Err(DecodeError::Crc { found, computed });
    }
    if body[0] != FRAME_VERSION {
        return Err(DecodeError::Version { found: body[0] });
    }
    Ok(Packet {
        seq: body[1],
        message: M::read(body[2], &body[3..])?,
    })
}

/// An incremental decoder for one direction's message type (`Decoder<Reply>` on the host,
/// `Decoder<Command>` on the device). Holds at most [`MAX_WIRE`] bytes.
#[derive(Debug, Clone)]
pub struct Decoder<M> {
    buf: [u8; MAX_WIRE],
    len: usize,
    overflow: bool,
    _message: core::marker::PhantomData<M>,
}

impl<M: Message> Default for Decoder<M> {
    fn default() -> Self {
        Self::new()
    }
}

impl<M: Message> Decoder<M> {
    /// An empty decoder.
    pub const fn new() -> Self {
        Decoder {
            buf: [0; MAX_WIRE],
            len: 0,
            overflow: false,
            _message: core::marker::PhantomData,
        }
    }

    /// Feeds one byte. At each delimiter returns the frame it closes, or why the bytes since
    /// the last delimiter were not one; between delimiters (and for empty frames: repeated
    /// delimiters are idle fill) returns `None`.
    pub fn feed(&mut self, byte: u8) -> Option<Result<Packet<M>, DecodeError>> {
        if byte != 0 {
            if self.len < self.buf.len() {
                self.buf[self.len] = byte;
                self.len += 1;
            } else {
                self.overflow = true;
            }
            return None;
        }
        let len = core::mem::replace(&mut self.len, 0);
        if core::mem::replace(&mut self.overflow, false) {
            return Some(Err(DecodeError::TooLong));
        }
        if len == 0 {
            return None;
        }
        let frame = &mut self.buf[..len];
        Some(match cobs::decode_in_place(frame) {
            Ok(n) => parse(&frame[..n]),
            Err(_) => Err(DecodeError::Cobs),
        })
    }

    /// Bytes held since the last delimiter (a partial frame).
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Drops a partial frame (after a port is reopened, say).
    pub fn clear(&mut self) {
        self.len = 0;
        self.overflow = false;
    }
}

/// The next host sequence number after `seq`: 1..=255, wrapping to 1 (0 is unsolicited).
pub const fn next_seq(seq: u8) -> u8 {
    if seq == u8::MAX {
        1
    } else {
        seq + 1
    }
}
