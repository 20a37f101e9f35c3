//! Thorlabs Elliptec ELLx: ELL14 and ELL18 rotation mounts ([`ElliptecRotator`]) and ELL6 and
//! ELL9 sliders ([`ElliptecSlider`]), written from `docs/DEVICES.md` section 1.1
//! (the ELL18K manual, pylablib, roesel/elliptec and rwpeterson/elliptec).
//!
//! * Requests are `A cc data` without terminator, upper-case hex; replies are `A CC data\r\n`
//!   with fixed data lengths. A reply line is accepted only if its address, code, length and
//!   digits are right; anything else (line noise, a corrupted line, another module's reply, an
//!   unsolicited `BO`/`BS`) is skipped.
//! * Input is discarded before every request (stale and late bytes), and after a `GS` fault
//!   the status is read once more to clear the latched error (pylablib).
//! * The counts per turn are read from `in` (PULSES) at every connect, never assumed: ELL14
//!   units report 143360, not the manual's 262144.
//! * Homing is `ho0` on every model, sliders included (`ho` takes its direction digit on every
//!   model; a slider homes to slot 0 either way).
//! * Moves wait at least 100 ms after the previous one (an earlier move can "move to 0"), go
//!   the short way round, are absolute (so they can be repeated), and are judged by the
//!   position read back with `gp`: a `GS02` mechanical timeout or a lost `PO` is not a verdict.
//! * The device announces no reset, so the driver reads the position before every move; a jump
//!   it did not command means the datum is lost, and it homes again. It also homes after every
//!   reopen of the port.

use crate::any::{AnyRotator, AnyWheel};
use crate::dialect::{Bus, DeviceKind, Dialect, Identity, Position, LINE_8N1};
use crate::link::{retryable, Connector, Link, Policy};
use polar_hal::{
    angle_from_counts, counts_toward, DeviceError, ErrorKind, FilterWheel, Rotator, RotatorInfo,
    TURN_RAD,
};
use std::time::Duration;
use tokio::time::Instant;

/// The default policy (9600 baud; the motor gives up on its own after 2.5 s per move).
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(500),
        move_timeout: Duration::from_secs(6),
        home_timeout: Duration::from_secs(10),
        attempts: 4,
        backoff: Duration::from_millis(50),
    }
}

/// The minimum gap between the end of one move and the next move command (pylablib).
pub const PRE_MOVE_DELAY: Duration = Duration::from_millis(100);

/// The `in` reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ElliptecInfo {
    /// ELL type: 0x0E = ELL14, 0x12 = ELL18, 0x06 = ELL6, 0x09 = ELL9.
    pub model_code: u8,
    /// Serial number.
    pub serial: String,
    /// Year of manufacture.
    pub year: u16,
    /// Firmware release.
    pub firmware: u8,
    /// Hardware release (most significant bit: imperial thread).
    pub hardware: u8,
    /// Travel, degrees or mm.
    pub travel: u16,
    /// PULSES: counts per turn (rotators) or per unit of travel; 0 on the indexed sliders
    /// (ELL6, ELL9), whose slots are known by model instead ([`slider_positions`]).
    pub pulses: u32,
}

impl ElliptecInfo {
    /// Parses the 30 characters after `IN`.
    pub fn parse(data: &str) -> Result<Self, String> {
        if data.len() != 30 || !data.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("`in` data {data:?} is not 30 hex digits"));
        }
        let field = |a: usize, b: usize| &data[a..b];
        let hex = |a: usize, b: usize| u32::from_str_radix(field(a, b), 16).unwrap_or(0);
        Ok(ElliptecInfo {
            model_code: hex(0, 2) as u8,
            serial: field(2, 10).to_string(),
            year: field(10, 14).parse().unwrap_or(0),
            firmware: hex(14, 16) as u8,
            hardware: hex(16, 18) as u8,
            travel: hex(18, 22) as u16,
            pulses: hex(22, 30),
        })
    }

    /// The model's name.
    pub fn model(&self) -> String {
        match self.model_code {
            0x0E => "ELL14".to_string(),
            0x12 => "ELL18".to_string(),
            0x06 => "ELL6".to_string(),
            0x09 => "ELL9".to_string(),
            c => format!("ELL{c}"),
        }
    }
}

/// Slot positions of the indexed sliders, counts (roesel/elliptec): ELL6 0 and 31, ELL9 0,
/// 32, 64, 96; a slot is reached within 5 counts.
pub fn slider_positions(model_code: u8) -> Option<&'static [i32]> {
    match model_code {
        0x06 => Some(&[0, 31]),
        0x09 => Some(&[0, 32, 64, 96]),
        _ => None,
    }
}

/// Tolerance of a slider slot, counts.
const SLOT_TOLERANCE_COUNTS: i32 = 5;

/// The fixed data length of each reply code.
fn data_len(code: &str) -> Option<usize> {
    Some(match code {
        "IN" => 30,
        "GS" | "GV" | "BS" => 2,
        "PO" | "HO" | "GJ" | "BO" => 8,
        "I1" | "I2" | "I3" => 22,
        _ => return None,
    })
}

/// A well-formed reply line.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Line {
    address: u8,
    code: String,
    data: String,
}

fn parse_line(line: &[u8]) -> Option<Line> {
    let text = std::str::from_utf8(line).ok()?;
    if text.len() < 3 || !text.is_char_boundary(1) || !text.is_char_boundary(3) {
        return None;
    }
    let address = u8::from_str_radix(&text[..1], 16).ok()?;
    if text.as_bytes()[0].is_ascii_lowercase() {
        return None;
    }
    let code = &text[1..3];
    if !code
        .bytes()
        .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit())
    {
        return None;
    }
    let data = &text[3..];
    let upper_hex = |b: u8| b.is_ascii_digit() || (b'A'..=b'F').contains(&b);
    if data_len(code)? != data.len() || !data.bytes().all(upper_hex) {
        return None;
    }
    Some(Line {
        address,
        code: code.to_string(),
        data: data.to_string(),
    })
}

/// 32-bit two's complement, 8 upper-case hex digits.
fn hex8(counts: i32) -> String {
    format!("{:08X}", counts as u32)
}

fn from_hex8(data: &str) -> Option<i32> {
    u32::from_str_radix(data, 16).ok().map(|u| u as i32)
}

/// Status codes (`GS`), pylablib's names.
fn status_name(code: u8) -> &'static str {
    match code {
        0x00 => "ok",
        0x01 => "communication timeout",
        0x02 => "mechanical timeout",
        0x03 => "command error or not supported",
        0x04 => "value out of range",
        0x05 => "module isolated",
        0x06 => "module out of isolation",
        0x07 => "initialisation error",
        0x08 => "thermal error",
        0x09 => "busy",
        0x0A => "sensor error",
        0x0B => "motor error",
        0x0C => "out of range",
        0x0D => "over current",
        _ => "reserved",
    }
}

fn status_kind(code: u8) -> ErrorKind {
    match code {
        // `GS00` where another reply was due is a stale answer to an earlier request.
        0x00 | 0x01 | 0x03 => ErrorKind::Protocol,
        0x02 => ErrorKind::Stalled,
        0x04 | 0x0C => ErrorKind::OutOfRange,
        0x09 => ErrorKind::Busy,
        _ => ErrorKind::Other,
    }
}

/// A connection to one module on an Elliptec bus.
pub struct ElliptecSession {
    link: Link,
    policy: Policy,
    address: u8,
    info: Option<ElliptecInfo>,
    needs_init: bool,
    last_move_end: Option<Instant>,
    last_position: Option<i32>,
    rotary: bool,
    rehomes: u32,
}

/// What a move ended with.
enum MoveReply {
    /// `PO` with the position.
    Position,
    /// `GS02`, or no reply: judge by readback.
    Unknown,
}

impl ElliptecSession {
    /// Opens the port, reads `in` from module `address` (0..=15), checks it is a rotator
    /// (`rotary`) or a slider, and homes it.
    pub async fn connect(
        connector: Box<dyn Connector>,
        address: u8,
        rotary: bool,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let mut s = ElliptecSession {
            link: Link::new(connector),
            policy,
            address,
            info: None,
            needs_init: true,
            last_move_end: None,
            last_position: None,
            rotary,
            rehomes: 0,
        };
        if address > 15 {
            return Err(s.link.error(
                ErrorKind::OutOfRange,
                format!("address = {address} is out of range: allowed 0..=15"),
            ));
        }
        s.ensure_ready().await?;
        Ok(s)
    }

    /// The module's `in` reply.
    pub fn info(&self) -> Option<&ElliptecInfo> {
        self.info.as_ref()
    }

    /// Times the driver homed again after finding the datum lost.
    pub fn rehomes(&self) -> u32 {
        self.rehomes
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.link.opens()
    }

    fn name(&self) -> String {
        format!("{} address {:X}", self.link.name(), self.address)
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError::new(kind, self.name(), message)
    }

    /// Takes complete lines out of the buffer; returns the first from our address whose code is
    /// `GS` or in `accept`.
    fn scan(&mut self, accept: &[&str]) -> Option<Line> {
        loop {
            let buf = self.link.buffer();
            let end = buf.iter().position(|&b| b == b'\n')?;
            let raw: Vec<u8> = buf.drain(..=end).collect();
            let body = raw
                .strip_suffix(b"\r\n")
                .or_else(|| raw.strip_suffix(b"\n"))
                .unwrap_or(&raw);
            match parse_line(body) {
                Some(line)
                    if line.address == self.address
                        && (line.code == "GS" || accept.contains(&line.code.as_str())) =>
                {
                    return Some(line)
                }
                Some(line) => tracing::debug!(port = %self.link.name(), ?line, "skipped a reply"),
                None => {
                    tracing::debug!(port = %self.link.name(), "skipped a malformed line {raw:?}")
                }
            }
        }
    }

    /// Sends `cmd data` and waits for a `GS` or an `accept` reply from our address.
    async fn exchange(
        &mut self,
        cmd: &str,
        data: &str,
        accept: &[&str],
        timeout: Duration,
    ) -> Result<Line, DeviceError> {
        self.link.discard_input().await?;
        let request = format!("{:X}{cmd}{data}", self.address);
        self.link
            .write(request.as_bytes(), self.policy.query_timeout)
            .await?;
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(line) = self.scan(accept) {
                return Ok(line);
            }
            self.link
                .fill(deadline, &format!("reply to `{request}`"))
                .await?;
        }
    }

    /// A `GS` fault as an error; the latched status is read once more to clear it.
    async fn status_error(&mut self, line: &Line, what: &str) -> DeviceError {
        let code = u8::from_str_radix(&line.data, 16).unwrap_or(0xff);
        let _ = self
            .exchange("gs", "", &[], self.policy.query_timeout)
            .await;
        self.error(
            status_kind(code),
            format!("{what}: status {code:02X} ({})", status_name(code)),
        )
    }

    /// An idempotent query expecting `code`, retried.
    async fn query(&mut self, cmd: &str, code: &str) -> Result<Line, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            let result = self
                .exchange(cmd, "", &[code], self.policy.query_timeout)
                .await;
            let e = match result {
                Ok(line) if line.code == code => return Ok(line),
                Ok(line) => self.status_error(&line, cmd).await,
                Err(e) => e,
            };
            if !retryable(&e) {
                return Err(e);
            }
            last = Some(e);
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// The position, counts.
    pub async fn position_counts(&mut self) -> Result<i32, DeviceError> {
        let line = self.query("gp", "PO").await?;
        from_hex8(&line.data)
            .ok_or_else(|| self.error(ErrorKind::Protocol, format!("bad position {:?}", line.data)))
    }

    async fn ensure_ready(&mut self) -> Result<(), DeviceError> {
        if !self.link.is_open() {
            self.link.open(self.policy.open_timeout).await?;
            // A reopened port may be a power-cycled module: identify and home again.
            self.needs_init = true;
        }
        let policy = self.policy;
        policy.retry_init(self).await
    }

    async fn init(&mut self) -> Result<(), DeviceError> {
        let line = self.query("in", "IN").await?;
        let info =
            ElliptecInfo::parse(&line.data).map_err(|e| self.error(ErrorKind::Protocol, e))?;
        let rotary = is_rotator(info.model_code);
        let slider = slider_positions(info.model_code).is_some();
        if (self.rotary && !rotary) || (!self.rotary && !slider) {
            return Err(self.error(
                ErrorKind::Other,
                format!(
                    "module is an {} (type {:02X}), a {}; this driver wants a {}",
                    info.model(),
                    info.model_code,
                    if rotary { "rotation mount" } else { "slider" },
                    if self.rotary {
                        "rotation mount (ELL14, ELL18)"
                    } else {
                        "slider (ELL6, ELL9)"
                    }
                ),
            ));
        }
        if rotary && info.pulses == 0 {
            return Err(self.error(ErrorKind::Protocol, "PULSES = 0 in `in`: allowed > 0"));
        }
        tracing::info!(port = %self.name(), ?info, "identified; homing");
        self.info = Some(info);
        self.home().await
    }

    /// Homes (`ho0`: clockwise on rotators, slot 0 on sliders) and records the position.
    async fn home(&mut self) -> Result<(), DeviceError> {
        self.pre_move_delay().await;
        let result = self
            .exchange("ho", "0", &["PO"], self.policy.home_timeout)
            .await;
        self.last_move_end = Some(Instant::now());
        // Homing counts only with its `PO`: without it the counter may read 0 without a datum
        // (a controller that reset on the command). Homing again is harmless.
        match result {
            Ok(line) if line.code == "PO" => {}
            Ok(line) => return Err(self.status_error(&line, "home").await),
            Err(e) => return Err(e),
        }
        let p = self.position_counts().await?;
        if p.abs() > SLOT_TOLERANCE_COUNTS {
            return Err(self.error(
                ErrorKind::Stalled,
                format!("homing ended at {p} counts, not 0"),
            ));
        }
        self.last_position = Some(p);
        Ok(())
    }

    async fn pre_move_delay(&mut self) {
        if let Some(end) = self.last_move_end {
            tokio::time::sleep_until(end + PRE_MOVE_DELAY).await;
        }
    }

    /// Polls `gs` until the module no longer answers busy (`09`), within the move timeout.
    async fn wait_idle(&mut self) -> Result<(), DeviceError> {
        let deadline = Instant::now() + self.policy.move_timeout;
        loop {
            let line = self.query("gs", "GS").await?;
            if line.data != "09" {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(self.error(
                    ErrorKind::Timeout,
                    format!("still busy after {:?}", self.policy.move_timeout),
                ));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Reads the position and homes again if it moved without a command (datum lost).
    async fn check_datum(&mut self, tolerance_counts: i32) -> Result<i32, DeviceError> {
        let p = self.position_counts().await?;
        if let Some(last) = self.last_position {
            if (p.wrapping_sub(last)).abs() > tolerance_counts {
                tracing::warn!(port = %self.name(), "position {p} counts, last known {last}: datum lost; homing");
                self.rehomes += 1;
                self.needs_init = true;
                self.ensure_ready().await?;
                return self.position_counts().await;
            }
        }
        Ok(p)
    }

    /// Moves to `target` counts, verified by readback within `tolerance` (compared modulo
    /// `modulo` counts when it is > 0).
    async fn move_verified(
        &mut self,
        target: impl Fn(i32) -> i32,
        tolerance: i32,
        modulo: i64,
    ) -> Result<i32, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.ensure_ready().await?;
            let result = match self.check_datum(tolerance).await {
                Ok(current) => {
                    self.move_once(current, target(current), tolerance, modulo)
                        .await
                }
                Err(e) => Err(e),
            };
            match result {
                Ok(p) => return Ok(p),
                Err(e) if retryable(&e) => {
                    tracing::warn!(port = %self.name(), "move attempt {} failed: {e}", k + 1);
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Other, "no attempt made")))
    }

    async fn move_once(
        &mut self,
        start: i32,
        target: i32,
        tolerance: i32,
        modulo: i64,
    ) -> Result<i32, DeviceError> {
        self.pre_move_delay().await;
        let result = self
            .exchange("ma", &hex8(target), &["PO"], self.policy.move_timeout)
            .await;
        self.last_move_end = Some(Instant::now());
        let reply = match result {
            Ok(line) if line.code == "PO" => MoveReply::Position,
            // A stale status from an earlier request: judge by readback.
            Ok(line) if line.data == "00" => MoveReply::Unknown,
            Ok(line) if line.data == "02" => {
                tracing::warn!(port = %self.name(), "mechanical timeout (GS02); judging by the position");
                let _ = self.status_error(&line, "move").await;
                MoveReply::Unknown
            }
            Ok(line) => return Err(self.status_error(&line, "move").await),
            Err(e) if e.kind() == ErrorKind::Timeout => MoveReply::Unknown,
            Err(e) => return Err(e),
        };
        // A `PO` may be a late one from an earlier move: make sure the motion has ended before
        // reading the position back.
        self.wait_idle().await?;
        let p = self.position_counts().await?;
        self.last_position = Some(p);
        // Signed distance a - b, reduced modulo a turn on rotators.
        let diff = |a: i32, b: i32| {
            let d = i64::from(a) - i64::from(b);
            if modulo > 0 {
                let r = d.rem_euclid(modulo);
                if r > modulo / 2 {
                    r - modulo
                } else {
                    r
                }
            } else {
                d
            }
        };
        let near = |a: i32, b: i32| diff(a, b).abs() <= i64::from(tolerance);
        // Without its `PO`, a counter at 0 that did not start there may be a controller that
        // reset on the command (the counter restarts at 0 wherever the mechanism is).
        let suspect = matches!(reply, MoveReply::Unknown) && near(p, 0) && !near(start, 0);
        if near(p, target) && !suspect {
            return Ok(p);
        }
        // A stall and a reset without notice look alike from here, and either leaves the
        // datum in doubt: home again before the next attempt.
        tracing::warn!(port = %self.name(), "move from {start} to {target} counts ended at {p}; homing again");
        self.rehomes += 1;
        self.needs_init = true;
        Err(self.error(
            ErrorKind::Stalled,
            format!("move from {start} to {target} counts ended at {p} counts"),
        ))
    }
}

crate::link::initialise_by_flag!(ElliptecSession);

/// Opens the port and reads module `address`'s `in` reply and position, without moving it.
pub async fn probe(
    connector: Box<dyn Connector>,
    address: u8,
    policy: Policy,
) -> Result<(ElliptecInfo, i32), DeviceError> {
    let mut s = ElliptecSession {
        link: Link::new(connector),
        policy,
        address: address.min(15),
        info: None,
        needs_init: false,
        last_move_end: None,
        last_position: None,
        rotary: true,
        rehomes: 0,
    };
    if address > 15 {
        return Err(s.error(
            ErrorKind::OutOfRange,
            format!("address = {address} is out of range: allowed 0..=15"),
        ));
    }
    s.link.open(policy.open_timeout).await?;
    let line = s.query("in", "IN").await?;
    let info = ElliptecInfo::parse(&line.data).map_err(|e| s.error(ErrorKind::Protocol, e))?;
    let position = s.position_counts().await?;
    Ok((info, position))
}

/// Whether the `in` model code is a rotation mount.
pub fn is_rotator(model_code: u8) -> bool {
    matches!(model_code, 0x0E | 0x12)
}

/// An ELL14 or ELL18 rotation mount.
pub struct ElliptecRotator {
    session: ElliptecSession,
    info: RotatorInfo,
    tolerance_counts: i32,
}

impl ElliptecRotator {
    /// Connects to module `address`, reads its counts per turn and homes it. `tolerance_rad`
    /// is the readback check (0.05 degrees is 20 ELL14 counts).
    pub async fn connect(
        connector: Box<dyn Connector>,
        address: u8,
        policy: Policy,
        tolerance_rad: f64,
    ) -> Result<Self, DeviceError> {
        let session = ElliptecSession::connect(connector, address, true, policy).await?;
        let Some(info) = session.info().cloned() else {
            return Err(session.error(ErrorKind::Other, "connected without `in`"));
        };
        let tolerance_counts =
            ((tolerance_rad / TURN_RAD * info.pulses as f64).round() as i32).max(1);
        Ok(ElliptecRotator {
            info: RotatorInfo {
                model: format!("Thorlabs {} serial {}", info.model(), info.serial),
                counts_per_turn: info.pulses,
                tolerance_rad: tolerance_counts as f64 / info.pulses as f64 * TURN_RAD,
            },
            tolerance_counts,
            session,
        })
    }

    /// The session (its `in` reply, re-homes, opens).
    pub fn session(&self) -> &ElliptecSession {
        &self.session
    }

    fn angle(&self, counts: i32) -> f64 {
        angle_from_counts(i64::from(counts), self.info.counts_per_turn)
    }
}

impl Rotator for ElliptecRotator {
    fn info(&self) -> &RotatorInfo {
        &self.info
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.session.needs_init = true;
        self.session.ensure_ready().await
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        if !angle_rad.is_finite() {
            return Err(self.session.error(
                ErrorKind::OutOfRange,
                format!("angle_rad = {angle_rad} is not a finite angle"),
            ));
        }
        let cpt = self.info.counts_per_turn;
        // The short way round from where the stage is.
        let target = move |current: i32| counts_toward(current, angle_rad, cpt);
        let p = self
            .session
            .move_verified(target, self.tolerance_counts, i64::from(cpt))
            .await?;
        Ok(self.angle(p))
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.position_counts().await?;
        Ok(self.angle(p))
    }
}

/// An ELL6 (2 positions) or ELL9 (4 positions) slider, as a wheel.
pub struct ElliptecSlider {
    session: ElliptecSession,
    positions: &'static [i32],
    labels: Vec<String>,
}

impl ElliptecSlider {
    /// Connects to module `address` and homes it.
    pub async fn connect(
        connector: Box<dyn Connector>,
        address: u8,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let session = ElliptecSession::connect(connector, address, false, policy).await?;
        let positions = session
            .info()
            .and_then(|i| slider_positions(i.model_code))
            .ok_or_else(|| session.error(ErrorKind::Other, "not a slider"))?;
        Ok(ElliptecSlider {
            labels: (0..positions.len()).map(|s| format!("slot {s}")).collect(),
            positions,
            session,
        })
    }

    /// The session (its `in` reply, re-homes, opens).
    pub fn session(&self) -> &ElliptecSession {
        &self.session
    }

    fn slot_of(&self, counts: i32) -> Option<usize> {
        self.positions
            .iter()
            .position(|&p| (p - counts).abs() <= SLOT_TOLERANCE_COUNTS)
    }
}

impl FilterWheel for ElliptecSlider {
    fn slots(&self) -> &[String] {
        &self.labels
    }

    async fn select(&mut self, slot: usize) -> Result<usize, DeviceError> {
        let Some(&target) = self.positions.get(slot) else {
            return Err(self.session.error(
                ErrorKind::OutOfRange,
                format!(
                    "slot = {slot} is out of range: allowed 0..={}",
                    self.positions.len() - 1
                ),
            ));
        };
        let p = self
            .session
            .move_verified(|_| target, SLOT_TOLERANCE_COUNTS, 0)
            .await?;
        self.slot_of(p).ok_or_else(|| {
            self.session.error(
                ErrorKind::Stalled,
                format!("ended at {p} counts, between slots"),
            )
        })
    }

    async fn slot(&mut self) -> Result<Option<usize>, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.position_counts().await?;
        Ok(self.slot_of(p))
    }
}

/// The readback tolerance the registry gives Elliptec rotators, degrees.
pub const ELLIPTEC_TOLERANCE_DEG: f64 = 0.05;

/// Thorlabs Elliptec (ASCII bus, addresses 0..=F).
pub const DIALECT: Dialect = Dialect {
    name: "elliptec",
    description: "Thorlabs Elliptec: ELL14/ELL18 rotation mounts, ELL6/ELL9 sliders",
    kinds: &[DeviceKind::Rotator, DeviceKind::Wheel],
    models: &["ell14", "ell18", "ell6", "ell9"],
    baud: 9600,
    line: LINE_8N1,
    bus: Some(Bus { first: 0, last: 15 }),
    policy: default_policy,
    identify: |c, address, policy| {
        Box::pin(async move {
            let (info, counts) = probe(c, address, policy).await?;
            let slider = slider_positions(info.model_code);
            let (kind, position) = match slider {
                None => (
                    DeviceKind::Rotator,
                    Position::Angle {
                        deg: angle_from_counts(i64::from(counts), info.pulses).to_degrees(),
                    },
                ),
                Some(s) => (
                    DeviceKind::Wheel,
                    Position::Slot(s.iter().position(|&p| (p - counts).abs() <= 5)),
                ),
            };
            Ok(Identity {
                kind,
                model: info.model(),
                serial: info.serial.clone(),
                firmware: info.firmware.to_string(),
                counts_per_turn: is_rotator(info.model_code).then_some(info.pulses),
                slots: slider.map(<[i32]>::len),
                homed: None,
                position,
            })
        })
    },
    rotator: Some(|c, address, policy| {
        Box::pin(async move {
            let tolerance_rad = ELLIPTEC_TOLERANCE_DEG.to_radians();
            let r = ElliptecRotator::connect(c, address, policy, tolerance_rad).await?;
            Ok(AnyRotator::new(r))
        })
    }),
    wheel: Some(|c, address, policy| {
        Box::pin(async move {
            Ok(AnyWheel::new(
                ElliptecSlider::connect(c, address, policy).await?,
            ))
        })
    }),
};

#[cfg(test)]
mod tests {
    use super::*;

    /// Reply lines: only the right shape parses (address, code, fixed length, upper-case hex).
    #[test]
    fn reply_lines_parse_strictly() {
        assert_eq!(
            parse_line(b"0PO00002000"),
            Some(Line {
                address: 0,
                code: "PO".into(),
                data: "00002000".into()
            })
        );
        assert!(parse_line(b"0PO0000200").is_none(), "short");
        assert!(parse_line(b"0PO0000200a").is_none(), "lower-case hex");
        assert!(parse_line(b"0XX00").is_none(), "unknown code");
        assert!(parse_line(b"\xff\xfePO00002000").is_none(), "not ASCII");
        assert!(parse_line(b"").is_none());
        assert_eq!(from_hex8(&hex8(-1000)), Some(-1000));
        assert_eq!(hex8(-1), "FFFFFFFF");
    }

    /// `in` of an ELL14 with the field layout of DEVICES.md: type 0E, PULSES 0x23000 = 143360.
    #[test]
    fn in_reply_parses() {
        let info = ElliptecInfo::parse("0E1140012320211501016800023000").unwrap();
        assert_eq!(info.model(), "ELL14");
        assert_eq!(info.serial, "11400123");
        assert_eq!(info.year, 2021);
        assert_eq!(info.travel, 360);
        assert_eq!(info.pulses, 143_360);
        assert!(ElliptecInfo::parse("0E11").is_err());
    }
}
