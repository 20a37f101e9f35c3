//! Standa 8SMC4-USB and 8SMC5-USB stepper controllers with the 8MPR16-1 rotation stage,
//! written from `docs/DEVICES.md` section 1.5 (the controller's protocol specification as
//! libximc's `protocol.xi` and the 8SMC5-USB manual give it, and the traffic of pylablib and
//! libximc).
//!
//! * A request is a four-letter code, then (for commands with data) a fixed-length
//!   little-endian payload and its CRC-16/MODBUS; the reply starts with the same code and has a
//!   fixed length too. `errc` (unknown command), `errd` (bad CRC) and `errv` (value out of
//!   range, corrected and applied) are the controller's refusals. The wire format is [`wire`],
//!   which the simulator shares.
//! * After a refusal or a reply that does not parse, the driver resynchronises as the manual
//!   says: zero bytes until a zero comes back, then the request again (every request sent here
//!   may be repeated: moves are absolute).
//! * Positions are full steps plus microsteps (`MicrostepMode`, read with `geng`: 256 at
//!   `FRAC_256`); the 8MPR16-1 turns once in 28 800 full steps (80 per degree, its data sheet),
//!   so a turn is 7 372 800 microsteps at `FRAC_256`.
//! * Connecting identifies the controller (`gent` must be a stepper, `geti`, `gser`, `gfwv`),
//!   homes it (`home`, then `gets` until the command no longer runs and `STATE_IS_HOMED` is
//!   set) and sets the position to 0 there (`zero`).
//! * Moves are `move` to the position the short way round, followed by `gets` until the command
//!   no longer runs, and judged by the position read back (`gpos`). A move that ends with the
//!   command's error bit, or a controller found without `STATE_IS_HOMED` (it reset, or skipped
//!   steps), is homed again before the next attempt.

use crate::any::AnyRotator;
use crate::dialect::{DeviceKind, Dialect, Identity, LineSettings, Position};
use crate::link::{retryable, Connector, Link, Policy};
use polar_hal::{
    angle_from_counts, signed_difference, ContinuousSupport, DeviceError, ErrorKind, Rotator,
    RotatorInfo, TURN_RAD,
};
use std::time::Duration;
use tokio::time::Instant;

pub mod wire {
    //! The 8SMC4/5 wire format, shared by the driver and the simulator: frames, the CRC, the
    //! lengths of the commands used here and the status bits.

    /// A four-letter command code.
    pub type Code = [u8; 4];

    /// CRC-16/MODBUS (reflected polynomial 0xA001, initial 0xFFFF), over a frame's data only.
    pub fn crc16(data: &[u8]) -> u16 {
        let mut crc: u16 = 0xFFFF;
        for &b in data {
            crc ^= u16::from(b);
            for _ in 0..8 {
                crc = if crc & 1 != 0 {
                    (crc >> 1) ^ 0xA001
                } else {
                    crc >> 1
                };
            }
        }
        crc
    }

    /// A frame: the code, then the data and its CRC when there is data.
    pub fn frame(code: &Code, data: &[u8]) -> Vec<u8> {
        let mut out = code.to_vec();
        if !data.is_empty() {
            out.extend_from_slice(data);
            out.extend_from_slice(&crc16(data).to_le_bytes());
        }
        out
    }

    /// The data of a whole frame of `code` with `len` data bytes at the front of `bytes`:
    /// `Some(Ok(data))`, `Some(Err(()))` for a CRC that does not match, `None` when the frame is
    /// not all there yet.
    pub fn data_of(bytes: &[u8], len: usize) -> Option<Result<&[u8], ()>> {
        let total = 4 + len + if len > 0 { 2 } else { 0 };
        if bytes.len() < total {
            return None;
        }
        if len == 0 {
            return Some(Ok(&[]));
        }
        let data = &bytes[4..4 + len];
        let crc = u16::from_le_bytes([bytes[4 + len], bytes[5 + len]]);
        Some(if crc == crc16(data) {
            Ok(data)
        } else {
            Err(())
        })
    }

    /// The lengths (request data, reply data) of the commands used here; `None` for others.
    pub fn lengths(code: &Code) -> Option<(usize, usize)> {
        Some(match code {
            b"gpos" => (0, 20),
            b"spos" => (20, 0),
            b"move" | b"movr" => (12, 0),
            b"home" | b"zero" | b"stop" | b"sstp" | b"left" | b"rigt" | b"loft" | b"pwof" => (0, 0),
            b"gets" => (0, 48),
            b"gmov" => (0, 24),
            b"smov" => (24, 0),
            b"geng" => (0, 28),
            b"seng" => (28, 0),
            b"gent" => (0, 8),
            b"sent" => (8, 0),
            b"ghom" => (0, 27),
            b"shom" => (27, 0),
            b"gpwr" => (0, 14),
            b"spwr" => (14, 0),
            b"geti" => (0, 30),
            b"gser" | b"gfwv" => (0, 4),
            _ => return None,
        })
    }

    /// Unknown command, or one that cannot be processed.
    pub const ERRC: &Code = b"errc";
    /// The data's CRC does not match.
    pub const ERRD: &Code = b"errd";
    /// A value out of range (corrected and applied).
    pub const ERRV: &Code = b"errv";

    /// `gets` MoveSts: the motor turns.
    pub const MOVE_STATE_MOVING: u8 = 0x01;
    /// `gets` MoveSts: at the target speed.
    pub const MOVE_STATE_TARGET_SPEED: u8 = 0x02;
    /// `gets` MvCmdSts: the last command has not finished.
    pub const MVCMD_RUNNING: u8 = 0x80;
    /// `gets` MvCmdSts: the last command ended with an error.
    pub const MVCMD_ERROR: u8 = 0x40;
    /// `gets` MvCmdSts codes of the last motion command (low six bits).
    pub const MVCMD_MOVE: u8 = 1;
    /// `movr`.
    pub const MVCMD_MOVR: u8 = 2;
    /// `left`.
    pub const MVCMD_LEFT: u8 = 3;
    /// `rigt`.
    pub const MVCMD_RIGHT: u8 = 4;
    /// `stop`.
    pub const MVCMD_STOP: u8 = 5;
    /// `home`.
    pub const MVCMD_HOME: u8 = 6;
    /// `loft`.
    pub const MVCMD_LOFT: u8 = 7;
    /// `sstp`.
    pub const MVCMD_SSTP: u8 = 8;
    /// `gets` Flags: the position is calibrated against the home sensor.
    pub const STATE_IS_HOMED: u32 = 0x20;
    /// `gets` Flags: the settings memory is present.
    pub const STATE_EEPROM_CONNECTED: u32 = 0x10;
    /// `gets` Flags: the last `errc`, `errd`, `errv`.
    pub const STATE_ERRC: u32 = 0x1;
    /// See [`STATE_ERRC`].
    pub const STATE_ERRD: u32 = 0x2;
    /// See [`STATE_ERRC`].
    pub const STATE_ERRV: u32 = 0x4;
    /// `gent` EngineType of a stepper motor.
    pub const ENGINE_TYPE_STEP: u8 = 3;

    /// Microsteps per full step of a `MicrostepMode` (1 full step ... 9 1/256).
    pub fn microsteps(mode: u8) -> u32 {
        1 << (mode.clamp(1, 9) - 1)
    }

    /// A position in microsteps as (full steps, microsteps), truncated toward zero, the
    /// microsteps carrying the sign of the whole (as the controller and its clients split it).
    pub fn split(usteps: i64, per_step: u32) -> (i32, i16) {
        let per = i64::from(per_step.max(1));
        let steps = (usteps / per).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32;
        (steps, (usteps % per) as i16)
    }

    /// The microsteps of (full steps, microsteps).
    pub fn join(steps: i32, usteps: i16, per_step: u32) -> i64 {
        i64::from(steps) * i64::from(per_step) + i64::from(usteps)
    }

    /// A little-endian field reader over a reply's data.
    pub struct Fields<'a>(pub &'a [u8]);

    impl Fields<'_> {
        /// `u8` at `at` (0 past the end).
        pub fn u8(&self, at: usize) -> u8 {
            self.0.get(at).copied().unwrap_or(0)
        }
        /// `u16` at `at`.
        pub fn u16(&self, at: usize) -> u16 {
            u16::from_le_bytes([self.u8(at), self.u8(at + 1)])
        }
        /// `i16` at `at`.
        pub fn i16(&self, at: usize) -> i16 {
            self.u16(at) as i16
        }
        /// `u32` at `at`.
        pub fn u32(&self, at: usize) -> u32 {
            u32::from_le_bytes([
                self.u8(at),
                self.u8(at + 1),
                self.u8(at + 2),
                self.u8(at + 3),
            ])
        }
        /// `i32` at `at`.
        pub fn i32(&self, at: usize) -> i32 {
            self.u32(at) as i32
        }
        /// Text of `n` bytes at `at`, up to its first NUL.
        pub fn text(&self, at: usize, n: usize) -> String {
            let end = (at + n).min(self.0.len());
            let raw = self.0.get(at..end).unwrap_or(&[]);
            let raw = raw.split(|&b| b == 0).next().unwrap_or(&[]);
            String::from_utf8_lossy(raw).into_owned()
        }
    }

    /// The data of `move` (and `movr`): full steps, microsteps, six reserved bytes.
    pub fn position_data(steps: i32, usteps: i16) -> Vec<u8> {
        let mut d = Vec::with_capacity(12);
        d.extend_from_slice(&steps.to_le_bytes());
        d.extend_from_slice(&usteps.to_le_bytes());
        d.extend_from_slice(&[0; 6]);
        d
    }
}

/// The 8MPR16-1's full steps per turn of the stage (80 per degree, its data sheet; Standa's
/// stage profile: a 20-step motor through a 1440:1 reduction).
pub const STEPS_PER_TURN_8MPR16_1: u32 = 28_800;
/// The readback tolerance of the registry's Standa rotator, degrees (the counter is exact; this
/// allows for one full step of the 8MPR16-1, 0.0125 deg).
pub const STANDA_TOLERANCE_DEG: f64 = 0.0125;
/// Pause between two `gets` polls while the motor runs.
const POLL: Duration = Duration::from_millis(20);
/// Zero bytes sent to resynchronise (the manual: at least 4, at most 250).
const RESYNC_ZEROS: usize = 64;

/// The default policy: a move or homing takes up to a turn at the 8MPR16-1's speeds (6.25 deg/s
/// moving, 1.25 deg/s homing).
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(500),
        move_timeout: Duration::from_secs(90),
        home_timeout: Duration::from_secs(330),
        attempts: 4,
        backoff: Duration::from_millis(50),
    }
}

/// What the controller says it is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StandaInfo {
    /// `geti`'s manufacturer and product (`XIMC 8SMC5-U`).
    pub product: String,
    /// `gser`.
    pub serial: u32,
    /// `gfwv`, as `major.minor.release`.
    pub firmware: String,
    /// Microsteps per full step (`geng`'s MicrostepMode).
    pub microsteps: u32,
}

/// A connection to one 8SMC controller.
pub struct StandaSession {
    link: Link,
    policy: Policy,
    info: Option<StandaInfo>,
    needs_init: bool,
    rehomes: u32,
}

impl StandaSession {
    /// Opens the port and identifies the controller, without moving it.
    pub async fn open(connector: Box<dyn Connector>, policy: Policy) -> Result<Self, DeviceError> {
        let mut s = StandaSession {
            link: Link::new(connector),
            policy,
            info: None,
            needs_init: true,
            rehomes: 0,
        };
        s.link.open(policy.open_timeout).await?;
        s.identify().await?;
        Ok(s)
    }

    /// What the controller said it is.
    pub fn info(&self) -> Option<&StandaInfo> {
        self.info.as_ref()
    }

    /// Times the driver homed again after finding the datum lost.
    pub fn rehomes(&self) -> u32 {
        self.rehomes
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        self.link.error(kind, message)
    }

    /// Sends `code` with `data` and returns the reply's data (`reply_len` bytes).
    async fn exchange(
        &mut self,
        code: &wire::Code,
        data: &[u8],
        reply_len: usize,
    ) -> Result<Vec<u8>, DeviceError> {
        self.link.discard_input().await?;
        self.link
            .write(&wire::frame(code, data), self.policy.query_timeout)
            .await?;
        let deadline = Instant::now() + self.policy.query_timeout;
        let name = String::from_utf8_lossy(code).into_owned();
        loop {
            let buf = self.link.buffer();
            // Zeros before a reply are resynchronisation's echoes.
            let zeros = buf.iter().take_while(|&&b| b == 0).count();
            buf.drain(..zeros);
            if buf.len() >= 4 {
                let got: wire::Code = [buf[0], buf[1], buf[2], buf[3]];
                if &got == wire::ERRV {
                    buf.clear();
                    return Err(self.error(
                        ErrorKind::OutOfRange,
                        format!("`{name}` refused: a value out of range (errv)"),
                    ));
                }
                if &got == wire::ERRC || &got == wire::ERRD {
                    buf.clear();
                    let what = if &got == wire::ERRC {
                        "not understood (errc)"
                    } else {
                        "its CRC did not match (errd)"
                    };
                    return Err(self.error(ErrorKind::Protocol, format!("`{name}` {what}")));
                }
                if &got != code {
                    buf.clear();
                    return Err(self.error(
                        ErrorKind::Protocol,
                        format!("`{name}` answered by {:?}", String::from_utf8_lossy(&got)),
                    ));
                }
                match wire::data_of(buf, reply_len) {
                    Some(Ok(d)) => return Ok(d.to_vec()),
                    Some(Err(())) => {
                        buf.clear();
                        return Err(self.error(
                            ErrorKind::Protocol,
                            format!("`{name}`'s reply failed its CRC"),
                        ));
                    }
                    None => {}
                }
            }
            self.link
                .fill(deadline, &format!("the reply to `{name}`"))
                .await?;
        }
    }

    /// Zero bytes until a zero comes back (the manual's resynchronisation), then the input is
    /// discarded.
    async fn resync(&mut self) -> Result<(), DeviceError> {
        self.link.discard_input().await?;
        self.link
            .write(&[0; RESYNC_ZEROS], self.policy.query_timeout)
            .await?;
        let deadline = Instant::now() + self.policy.query_timeout;
        while !self.link.buffer().contains(&0) {
            self.link
                .fill(deadline, "a zero back (resynchronising)")
                .await?;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
        self.link.discard_input().await?;
        Ok(())
    }

    /// `code` with `data`, retried after a resynchronisation; the reply's data.
    async fn request(
        &mut self,
        code: &wire::Code,
        data: &[u8],
        reply_len: usize,
    ) -> Result<Vec<u8>, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            match self.exchange(code, data, reply_len).await {
                Ok(d) => return Ok(d),
                Err(e) if retryable(&e) => {
                    if let Err(r) = self.resync().await {
                        tracing::debug!(port = %self.link.name(), "resync failed: {r}");
                    }
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// The position, microsteps (`gpos`).
    pub async fn position_usteps(&mut self) -> Result<i64, DeviceError> {
        let d = self.request(b"gpos", &[], 20).await?;
        let f = wire::Fields(&d);
        let per = self.info.as_ref().map_or(256, |i| i.microsteps);
        Ok(wire::join(f.i32(0), f.i16(4), per))
    }

    /// (MvCmdSts, MoveSts, Flags) of `gets`.
    pub async fn status(&mut self) -> Result<(u8, u8, u32), DeviceError> {
        let d = self.request(b"gets", &[], 48).await?;
        let f = wire::Fields(&d);
        Ok((f.u8(1), f.u8(0), f.u32(35)))
    }

    async fn identify(&mut self) -> Result<(), DeviceError> {
        let entype = self.request(b"gent", &[], 8).await?;
        let engine = wire::Fields(&entype).u8(0);
        if engine != wire::ENGINE_TYPE_STEP {
            return Err(self.error(
                ErrorKind::Other,
                format!("`gent` says engine type {engine}: this driver drives a stepper (3)"),
            ));
        }
        let eng = self.request(b"geng", &[], 28).await?;
        let microsteps = wire::microsteps(wire::Fields(&eng).u8(13));
        let id = self.request(b"geti", &[], 30).await?;
        let f = wire::Fields(&id);
        let product = format!("{} {}", f.text(0, 4), f.text(6, 8));
        let serial = wire::Fields(&self.request(b"gser", &[], 4).await?).u32(0);
        let fw = self.request(b"gfwv", &[], 4).await?;
        let f = wire::Fields(&fw);
        let firmware = format!("{}.{}.{}", f.u8(0), f.u8(1), f.u16(2));
        tracing::info!(port = %self.link.name(), %product, serial, %firmware, microsteps, "identified");
        self.info = Some(StandaInfo {
            product,
            serial,
            firmware,
            microsteps,
        });
        Ok(())
    }

    async fn ensure_ready(&mut self) -> Result<(), DeviceError> {
        if !self.link.is_open() {
            self.link.open(self.policy.open_timeout).await?;
            self.needs_init = true;
        }
        let policy = self.policy;
        policy.retry_init(self).await
    }

    async fn init(&mut self) -> Result<(), DeviceError> {
        if self.info.is_none() {
            self.identify().await?;
        }
        self.home().await
    }

    /// Polls `gets` until the last command no longer runs; its (MvCmdSts, Flags) then.
    async fn wait_done(&mut self, timeout: Duration) -> Result<(u8, u32), DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            let (cmd, moving, flags) = self.status().await?;
            if cmd & wire::MVCMD_RUNNING == 0 && moving & wire::MOVE_STATE_MOVING == 0 {
                return Ok((cmd, flags));
            }
            if Instant::now() >= deadline {
                return Err(self.error(
                    ErrorKind::Timeout,
                    format!("still moving after {timeout:?}"),
                ));
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// `home`, then `zero` at the home position.
    async fn home(&mut self) -> Result<(), DeviceError> {
        self.request(b"home", &[], 0).await?;
        let (cmd, flags) = self.wait_done(self.policy.home_timeout).await?;
        if cmd & wire::MVCMD_ERROR != 0 || flags & wire::STATE_IS_HOMED == 0 {
            return Err(self.error(
                ErrorKind::Stalled,
                format!(
                    "homing ended without the home sensor (MvCmdSts {cmd:#04x}, Flags {flags:#x})"
                ),
            ));
        }
        self.request(b"zero", &[], 0).await?;
        Ok(())
    }

    /// Moves to `target(current)` microsteps, verified by the command's status and the
    /// position read back; retried, homing again after a lost datum.
    async fn move_verified(&mut self, target: impl Fn(i64) -> i64) -> Result<i64, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.ensure_ready().await?;
            let result = match self.check_datum().await {
                Ok(current) => self.move_once(current, target(current)).await,
                Err(e) => Err(e),
            };
            match result {
                Ok(p) => return Ok(p),
                Err(e) if retryable(&e) => {
                    tracing::warn!(port = %self.link.name(), "move attempt {} failed: {e}", k + 1);
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Other, "no attempt made")))
    }

    /// The position, after checking the controller still knows its datum (a reset or skipped
    /// steps clear `STATE_IS_HOMED`).
    async fn check_datum(&mut self) -> Result<i64, DeviceError> {
        let (_, _, flags) = self.status().await?;
        if flags & wire::STATE_IS_HOMED == 0 {
            return Err(self.lost_datum("the controller is not homed (it reset)"));
        }
        self.position_usteps().await
    }

    fn lost_datum(&mut self, why: &str) -> DeviceError {
        tracing::warn!(port = %self.link.name(), "{why}; homing again");
        self.rehomes += 1;
        self.needs_init = true;
        self.error(ErrorKind::Stalled, format!("{why}: homing again"))
    }

    async fn move_once(&mut self, start: i64, target: i64) -> Result<i64, DeviceError> {
        let per = self.info.as_ref().map_or(256, |i| i.microsteps);
        let (steps, usteps) = wire::split(target, per);
        self.request(b"move", &wire::position_data(steps, usteps), 0)
            .await?;
        let (cmd, flags) = self.wait_done(self.policy.move_timeout).await?;
        if cmd & wire::MVCMD_ERROR != 0 || flags & wire::STATE_IS_HOMED == 0 {
            return Err(self.lost_datum(&format!(
                "the move from {start} to {target} microsteps ended with an error"
            )));
        }
        let p = self.position_usteps().await?;
        if p == target {
            return Ok(p);
        }
        Err(self.error(
            ErrorKind::Stalled,
            format!("the move from {start} to {target} microsteps ended at {p}"),
        ))
    }
}

crate::link::initialise_by_flag!(StandaSession);

/// The fastest the driver spins the 8MPR16-1, degrees per second: the move speed of Standa's
/// own profile for the stage (500 full steps/s); the driver does not drive it faster.
pub const MAX_SPIN_DEG_PER_S: f64 = 6.25;

/// The 8MPR16-1 on an 8SMC4/5 controller.
pub struct StandaRotator {
    session: StandaSession,
    info: RotatorInfo,
    /// The move settings (`gmov`'s data) before a spin changed the speed, written back when
    /// it stops.
    spin_restore: Option<Vec<u8>>,
}

impl StandaRotator {
    /// Connects, identifies, homes and zeroes the stage.
    pub async fn connect(
        connector: Box<dyn Connector>,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let mut session = StandaSession::open(connector, policy).await?;
        session.ensure_ready().await?;
        let Some(id) = session.info().cloned() else {
            return Err(session.error(ErrorKind::Other, "connected without `geti`"));
        };
        let counts_per_turn = STEPS_PER_TURN_8MPR16_1 * id.microsteps;
        Ok(StandaRotator {
            info: RotatorInfo {
                model: format!("Standa 8MPR16-1 on {} serial {}", id.product, id.serial),
                counts_per_turn,
                tolerance_rad: STANDA_TOLERANCE_DEG.to_radians(),
            },
            session,
            spin_restore: None,
        })
    }

    /// The session (what the controller is, re-homes).
    pub fn session(&self) -> &StandaSession {
        &self.session
    }

    fn angle(&self, usteps: i64) -> f64 {
        angle_from_counts(usteps, self.info.counts_per_turn)
    }

    /// Writes back the move settings a spin changed and whose stop did not restore them (a
    /// failed `sstp`), so a move runs at its own speed.
    async fn restore_move_settings(&mut self) -> Result<(), DeviceError> {
        if let Some(gmov) = self.spin_restore.take() {
            self.session.ensure_ready().await?;
            if let Err(e) = self.session.request(b"smov", &gmov, 0).await {
                self.spin_restore = Some(gmov);
                return Err(e);
            }
        }
        Ok(())
    }

    /// `gmov`'s data with the speed set to `deg_s` (full steps and microsteps per second).
    fn move_settings_at(&self, gmov: &[u8], deg_s: f64) -> Vec<u8> {
        let per = self.session.info().map_or(256, |i| i.microsteps);
        let usteps_s = (deg_s / 360.0 * f64::from(self.info.counts_per_turn)).round() as i64;
        let (steps, usteps) = wire::split(usteps_s, per);
        let mut data = gmov.to_vec();
        data[0..4].copy_from_slice(&(steps.max(0) as u32).to_le_bytes());
        data[4] = usteps.clamp(0, 255) as u8;
        data
    }
}

impl Rotator for StandaRotator {
    fn info(&self) -> &RotatorInfo {
        &self.info
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.restore_move_settings().await?;
        self.session.needs_init = true;
        self.session.ensure_ready().await
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        self.restore_move_settings().await?;
        if !angle_rad.is_finite() {
            return Err(self.session.error(
                ErrorKind::OutOfRange,
                format!("angle_rad = {angle_rad} is not a finite angle"),
            ));
        }
        let cpt = f64::from(self.info.counts_per_turn);
        let target = move |current: i64| {
            let here = angle_from_counts(current, cpt as u32);
            let delta = signed_difference(angle_rad, here, TURN_RAD) / TURN_RAD * cpt;
            current + delta.round() as i64
        };
        let p = self.session.move_verified(target).await?;
        Ok(self.angle(p))
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.position_usteps().await?;
        Ok(self.angle(p))
    }

    fn continuous_support(&self) -> ContinuousSupport {
        ContinuousSupport::Velocity
    }

    /// Velocity mode: the move speed set to `|rad_per_s|` (`smov`, at most
    /// [`MAX_SPIN_DEG_PER_S`]), then `rigt` (positive) or `left`; a second call changes the
    /// speed and direction. The move settings of before are written back by `stop_spin`.
    async fn spin(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        let deg_s = rad_per_s.to_degrees();
        // One microstep per second is the slowest speed the controller can be set to.
        let min_deg_s = 360.0 / f64::from(self.info.counts_per_turn.max(1));
        let size = deg_s.abs();
        if !(size.is_finite() && size >= min_deg_s && size <= MAX_SPIN_DEG_PER_S * (1.0 + 1e-9)) {
            return Err(self.session.error(
                ErrorKind::OutOfRange,
                format!(
                    "rad_per_s = {rad_per_s} ({deg_s} deg/s) is out of range for the 8MPR16-1: \
                     allowed {min_deg_s:.3e} <= |deg/s| <= {MAX_SPIN_DEG_PER_S} (one \
                     microstep per second up to the profile's move speed; the sign is the \
                     direction)"
                ),
            ));
        }
        self.session.ensure_ready().await?;
        let gmov = self.session.request(b"gmov", &[], 24).await?;
        let settings = self.move_settings_at(&gmov, deg_s.abs());
        if self.spin_restore.is_none() {
            self.spin_restore = Some(gmov);
        }
        self.session.request(b"smov", &settings, 0).await?;
        let code = if deg_s > 0.0 { b"rigt" } else { b"left" };
        self.session.request(code, &[], 0).await?;
        Ok(())
    }

    /// `sstp` (a decelerating stop), `gets` until it ends, the move settings written back;
    /// where the stage stopped.
    async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        self.session.request(b"sstp", &[], 0).await?;
        let timeout = self.session.policy.move_timeout;
        self.session.wait_done(timeout).await?;
        self.restore_move_settings().await?;
        let p = self.session.position_usteps().await?;
        Ok(self.angle(p))
    }

    /// `gpos` (the counter, unwrapped). Over USB, so no serial line's share in its round trip
    /// ([`Rotator::spin_read_wire`] stays zero).
    async fn spin_position_rad(&mut self) -> Result<f64, DeviceError> {
        let p = self.session.position_usteps().await?;
        Ok(p as f64 / f64::from(self.info.counts_per_turn.max(1)) * TURN_RAD)
    }
}

/// 8SMC4/5-USB: 8 data bits, no parity, two stop bits, no flow control.
pub const LINE_8N2: LineSettings = LineSettings {
    stop_bits: crate::dialect::StopBits::Two,
    ..crate::dialect::LINE_8N1
};

/// Standa 8SMC4/5-USB with the 8MPR16-1 (binary, one controller per port).
pub const DIALECT: Dialect = Dialect {
    name: "standa",
    description: "Standa 8SMC4/5-USB stepper controller with the 8MPR16-1 rotation stage",
    kinds: &[DeviceKind::Rotator],
    models: &["8mpr16-1"],
    baud: 115_200,
    line: LINE_8N2,
    bus: None,
    policy: default_policy,
    identify: |c, _address, policy| {
        Box::pin(async move {
            let mut s = StandaSession::open(c, policy).await?;
            let (_, _, flags) = s.status().await?;
            let p = s.position_usteps().await?;
            let info = s.info().cloned();
            let per = info.as_ref().map_or(256, |i| i.microsteps);
            let cpt = STEPS_PER_TURN_8MPR16_1 * per;
            Ok(Identity {
                kind: DeviceKind::Rotator,
                model: "8MPR16-1".into(),
                serial: info.as_ref().map_or(0, |i| i.serial).to_string(),
                firmware: info.map_or_else(String::new, |i| i.firmware),
                counts_per_turn: Some(cpt),
                slots: None,
                homed: Some(flags & wire::STATE_IS_HOMED != 0),
                position: Position::Angle {
                    deg: angle_from_counts(p, cpt).to_degrees(),
                },
            })
        })
    },
    rotator: Some(|c, _address, policy| {
        Box::pin(async move { Ok(AnyRotator::new(StandaRotator::connect(c, policy).await?)) })
    }),
    wheel: None,
};

#[cfg(test)]
mod tests {
    use super::wire::*;

    /// The CRC's check values (CRC-16/MODBUS of "123456789" is 0x4B37; of 20 zero bytes
    /// 0x1B24, as an all-zero `gpos` reply ends); frames carry a CRC only with data.
    #[test]
    fn crc_and_frames() {
        assert_eq!(crc16(b"123456789"), 0x4B37);
        assert_eq!(crc16(&[0; 20]), 0x1B24);
        assert_eq!(frame(b"gpos", &[]), b"gpos");
        let f = frame(b"gpos", &[0; 20]);
        assert_eq!(&f[24..], &[0x24, 0x1B]);
        assert_eq!(data_of(&f, 20), Some(Ok(&[0u8; 20][..])));
        let mut bad = f.clone();
        bad[5] = 1;
        assert_eq!(data_of(&bad, 20), Some(Err(())));
        assert_eq!(data_of(&f[..10], 20), None);
    }

    /// Positions split as the controller does: truncated toward zero, the microsteps carrying
    /// the sign; and join back.
    #[test]
    fn positions_split_and_join() {
        assert_eq!(split(-3 * 256 + 128, 256), (-2, -128));
        assert_eq!(split(300, 256), (1, 44));
        for u in [-1_000_000i64, -1, 0, 255, 256, 7_372_800] {
            let (s, m) = split(u, 256);
            assert_eq!(join(s, m, 256), u);
        }
        assert_eq!(microsteps(9), 256);
        assert_eq!(microsteps(1), 1);
    }
}
