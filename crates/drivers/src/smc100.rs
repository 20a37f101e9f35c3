//! Newport SMC100 (SMC100CC and SMC100PP, with PR50 and URS rotation stages) and CONEX-AGP
//! (with the AG-PR100P piezo rotation stage) controllers, written from `docs/DEVICES.md`
//! section 1.4 (the SMC100 and CONEX-AGP user's manuals, as public clients quote them).
//!
//! * Every command is `xxAAnn` and CR LF: the controller's address `xx` (1..=31), the
//!   two-letter command `AA`, then its argument (a number, `?` to read a setting, or nothing).
//!   Only queries are answered, with a line that repeats the address and the command before
//!   the value (`1TP` -> `1TP44.999`); other lines (another controller's, line noise, a late
//!   answer) are skipped. The wire format is [`wire`], which the simulator shares.
//! * A command that is not a query has no answer, so every one is followed by `TE` (the last
//!   command error, `@` for none): a refused command is an error naming the controller's
//!   reason, and a lost command is a missing `TE` answer (retried: every command sent here is
//!   idempotent, moves being absolute).
//! * The state (`TS`) is the datum: NOT REFERENCED after power-on or a reset, READY after
//!   homing (`OR`). A controller found NOT REFERENCED when it was READY has reset; the driver
//!   homes it again. CONFIGURATION is left with `PW0` and DISABLE with `MM1`.
//! * Moves are absolute (`PA`) in the stage's units (degrees), go the short way round from
//!   where the stage is (within the software limits `SL`/`SR`), are followed by polling `TS`
//!   until the controller is READY again, and are judged by the position read back (`TP`). A
//!   following error stops the motor and leaves the controller in DISABLE: the driver enables
//!   it again (`MM1`) and repeats the move.
//! * A controller that does not answer its address is refused with the address and the range.

use crate::any::AnyRotator;
use crate::dialect::{Bus, DeviceKind, Dialect, Identity, LineSettings, Position};
use crate::link::{retryable, Connector, Link, Policy};
use polar_hal::{signed_difference, DeviceError, ErrorKind, Rotator, RotatorInfo, TURN_RAD};
use std::time::Duration;
use tokio::time::Instant;

pub mod wire {
    //! The SMC100 / CONEX-AGP wire format, shared by the driver and the simulator: command
    //! and answer lines, numbers as the controller writes them, the state and error codes.

    /// The addresses a controller may have on the bus.
    pub const ADDRESSES: std::ops::RangeInclusive<u8> = 1..=31;
    /// What ends every command and every answer.
    pub const TERMINATOR: &[u8] = b"\r\n";

    /// A command line as the controller reads it.
    #[derive(Debug, Clone, PartialEq, Eq)]
    pub struct Command {
        /// The address (`None`: the line starts with the command).
        pub address: Option<u8>,
        /// The address's digits as sent (`01` stays `01`: the answer repeats them).
        pub address_text: String,
        /// The two-letter command, upper case.
        pub code: [u8; 2],
        /// What follows it, trimmed: a number, `?`, or nothing.
        pub argument: String,
    }

    impl Command {
        /// The command's letters.
        pub fn code(&self) -> &str {
            std::str::from_utf8(&self.code).unwrap_or("??")
        }

        /// Whether the argument is `?` (read a setting).
        pub fn is_query(&self) -> bool {
            self.argument == "?"
        }
    }

    /// The bytes of command `code` with `argument` for the controller at `address`.
    pub fn command(address: u8, code: &str, argument: &str) -> Vec<u8> {
        let mut line = format!("{address}{code}{argument}").into_bytes();
        line.extend_from_slice(TERMINATOR);
        line
    }

    /// Reads a command line (without its terminator; blanks anywhere are ignored, as the
    /// manual says): up to two address digits, two letters (the controller takes lower case
    /// too), the rest as the argument. `None`: no command (an empty line, noise).
    pub fn parse_command(line: &[u8]) -> Option<Command> {
        let text: String = std::str::from_utf8(line)
            .ok()?
            .chars()
            .filter(|c| !c.is_whitespace())
            .collect();
        let digits = text.bytes().take_while(u8::is_ascii_digit).count();
        if digits > 2 {
            return None;
        }
        let address = match digits {
            0 => None,
            _ => Some(text[..digits].parse().ok()?),
        };
        let rest = &text[digits..];
        let code = rest.get(..2)?.as_bytes();
        if !code.iter().all(u8::is_ascii_alphabetic) {
            return None;
        }
        Some(Command {
            address,
            address_text: text[..digits].to_string(),
            code: [code[0].to_ascii_uppercase(), code[1].to_ascii_uppercase()],
            argument: rest[2..].trim().to_string(),
        })
    }

    /// The answer line (with its terminator): the address as the command gave it, the
    /// command, the value.
    pub fn answer(address_text: &str, code: &str, value: &str) -> Vec<u8> {
        let mut line = format!("{address_text}{code}{value}").into_bytes();
        line.extend_from_slice(TERMINATOR);
        line
    }

    /// The value of an answer line from `address` to `code`, or `None` if the line is not one.
    pub fn parse_answer<'a>(line: &'a str, address: u8, code: &str) -> Option<&'a str> {
        let line = line.trim_end_matches(['\r', '\n']);
        let rest = line.strip_prefix(&address.to_string())?;
        // `1TP` must not match the answer of controller 11.
        let value = rest.strip_prefix(code)?;
        Some(value.trim())
    }

    /// A number as the controller writes it: six decimals (the manual's `1AC320.000000`).
    pub fn number(x: f64) -> String {
        if !x.is_finite() {
            return "0.000000".into();
        }
        let s = format!("{x:.6}");
        if s == "-0.000000" {
            "0.000000".into()
        } else {
            s
        }
    }

    /// Reads a number as the controller (or a client) writes it.
    pub fn parse_number(text: &str) -> Option<f64> {
        text.trim().parse::<f64>().ok().filter(|x| x.is_finite())
    }

    /// NOT REFERENCED from reset (the state at power-on and after `RS`).
    pub const NOT_REFERENCED_FROM_RESET: u8 = 0x0A;
    /// NOT REFERENCED from HOMING (a homing stopped or failed).
    pub const NOT_REFERENCED_FROM_HOMING: u8 = 0x0B;
    /// NOT REFERENCED from CONFIGURATION (after `PW0`).
    pub const NOT_REFERENCED_FROM_CONFIGURATION: u8 = 0x0C;
    /// CONFIGURATION (after `PW1`).
    pub const CONFIGURATION: u8 = 0x14;
    /// HOMING commanded from the serial line.
    pub const HOMING: u8 = 0x1E;
    /// MOVING.
    pub const MOVING: u8 = 0x28;
    /// READY from HOMING.
    pub const READY_FROM_HOMING: u8 = 0x32;
    /// READY from MOVING.
    pub const READY_FROM_MOVING: u8 = 0x33;
    /// READY from DISABLE.
    pub const READY_FROM_DISABLE: u8 = 0x34;
    /// DISABLE from READY (after `MM0`).
    pub const DISABLE_FROM_READY: u8 = 0x3C;
    /// DISABLE from MOVING (a following error stopped the motor).
    pub const DISABLE_FROM_MOVING: u8 = 0x3D;

    /// The state's name as the manuals give it.
    pub fn state_name(state: u8) -> &'static str {
        match state {
            0x0A => "NOT REFERENCED from reset",
            0x0B => "NOT REFERENCED from HOMING",
            0x0C => "NOT REFERENCED from CONFIGURATION",
            0x0D => "NOT REFERENCED from DISABLE",
            0x0E => "NOT REFERENCED from READY",
            0x0F => "NOT REFERENCED from MOVING",
            0x10 => "NOT REFERENCED, stage error or no parameters",
            0x11 => "NOT REFERENCED from JOGGING",
            0x14 => "CONFIGURATION",
            0x1E => "HOMING commanded from RS-232-C",
            0x1F => "HOMING commanded by SMC-RC",
            0x28 => "MOVING",
            0x32 => "READY from HOMING",
            0x33 => "READY from MOVING",
            0x34 => "READY from DISABLE",
            0x35 => "READY from JOGGING",
            0x3C => "DISABLE from READY",
            0x3D => "DISABLE from MOVING",
            0x3E => "DISABLE from JOGGING",
            0x46 => "JOGGING from READY",
            0x47 => "JOGGING from DISABLE",
            _ => "unknown state",
        }
    }

    /// Whether the state is one of NOT REFERENCED's.
    pub fn is_not_referenced(state: u8) -> bool {
        (0x0A..=0x11).contains(&state)
    }

    /// Whether the state is one of READY's.
    pub fn is_ready(state: u8) -> bool {
        (0x32..=0x36).contains(&state)
    }

    /// Whether the state is one of DISABLE's.
    pub fn is_disabled(state: u8) -> bool {
        (0x3C..=0x3E).contains(&state)
    }

    /// Whether the motor is running (homing, moving, jogging).
    pub fn is_in_motion(state: u8) -> bool {
        matches!(state, 0x1E | 0x1F | 0x28 | 0x46 | 0x47)
    }

    /// The positioner error bits of `TS` and their meanings.
    pub const POSITIONER_ERRORS: [(u16, &str); 10] = [
        (0x0200, "80 W output power exceeded"),
        (0x0100, "DC voltage too low"),
        (0x0080, "wrong ESP stage"),
        (0x0040, "homing time out"),
        (0x0020, "following error"),
        (0x0010, "short circuit detection"),
        (0x0008, "RMS current limit"),
        (0x0004, "peak current limit"),
        (0x0002, "positive end of run"),
        (0x0001, "negative end of run"),
    ];

    /// The following-error bit of `TS`.
    pub const FOLLOWING_ERROR: u16 = 0x0020;

    /// The value of a `TS` answer: four hex digits of positioner errors, two of state.
    pub fn status(errors: u16, state: u8) -> String {
        format!("{errors:04X}{state:02X}")
    }

    /// Reads a `TS` value into (positioner errors, state).
    pub fn parse_status(value: &str) -> Option<(u16, u8)> {
        let value = value.trim();
        if value.len() != 6 || !value.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        Some((
            u16::from_str_radix(&value[..4], 16).ok()?,
            u8::from_str_radix(&value[4..], 16).ok()?,
        ))
    }

    /// The positioner errors set in `bits`, by name.
    pub fn positioner_error_names(bits: u16) -> Vec<&'static str> {
        POSITIONER_ERRORS
            .iter()
            .filter(|(b, _)| bits & b != 0)
            .map(|(_, n)| *n)
            .collect()
    }

    /// No command error (`TE` answers `@`).
    pub const NO_ERROR: u8 = b'@';

    /// The meaning of a command error letter (`TE`), as the SMC100 manual lists them.
    pub fn command_error(letter: u8) -> &'static str {
        match letter {
            b'@' => "no error",
            b'A' => "unknown message code or floating point controller address",
            b'B' => "controller address not correct",
            b'C' => "parameter missing or out of range",
            b'D' => "command not allowed",
            b'E' => "home sequence already started",
            b'F' => "ESP stage name unknown",
            b'G' => "displacement out of limits",
            b'H' => "command not allowed in NOT REFERENCED state",
            b'I' => "command not allowed in CONFIGURATION state",
            b'J' => "command not allowed in DISABLE state",
            b'K' => "command not allowed in READY state",
            b'L' => "command not allowed in HOMING state",
            b'M' => "command not allowed in MOVING state",
            b'N' => "current position out of software limit",
            b'S' => "communication time out",
            b'U' => "error during EEPROM access",
            b'V' => "error during command execution",
            b'W' => "command not allowed for PP version",
            b'X' => "command not allowed for CC version",
            _ => "unknown error",
        }
    }
}

/// The default policy: a move or a homing search takes up to a turn at the stage's speed
/// (PR50CC 20 deg/s: 18 s; the AG-PR100P is slower), and a reset 1 s.
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(500),
        move_timeout: Duration::from_secs(60),
        home_timeout: Duration::from_secs(120),
        attempts: 4,
        backoff: Duration::from_millis(50),
    }
}

/// How long a controller takes to answer again after `RS` (the manuals: "a few seconds" is
/// allowed for; the SMC100 answers within about one).
pub const RESET_WAIT: Duration = Duration::from_secs(5);
/// Pause between two `TS` polls while the motor runs.
const POLL: Duration = Duration::from_millis(20);

/// The readback tolerance of the registry's SMC100 and CONEX-AGP rotators, degrees.
pub const SMC100_TOLERANCE_DEG: f64 = 0.01;

/// What the controller says it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Smc100Info {
    /// The stage (`ID?`), such as `PR50CC`.
    pub stage: String,
    /// The controller and its firmware (`VE`).
    pub version: String,
    /// The software limits (`SL?`, `SR?`), degrees.
    pub limits_deg: (f64, f64),
}

impl Smc100Info {
    /// The stage's model: `ID?` up to its first `_` (`PR50CC_PN:..._UD:...` is a PR50CC).
    pub fn model(&self) -> &str {
        self.stage.split('_').next().unwrap_or("")
    }

    /// The position's resolution, degrees: the encoder step of the stage the `ID?` names
    /// (PR50CC 0.0005 deg per its data sheet's minimum incremental motion of 0.01 deg over
    /// 20 counts; URS 0.0005 deg; AG-PR100P, open loop, 0.001 deg reported).
    pub fn resolution_deg(&self) -> f64 {
        let stage = self.stage.to_ascii_uppercase();
        if stage.contains("AG-PR") {
            0.001
        } else {
            0.0005
        }
    }
}

/// A connection to the controller at one address on a port.
pub struct Smc100Session {
    link: Link,
    policy: Policy,
    address: u8,
    info: Option<Smc100Info>,
    needs_init: bool,
    rehomes: u32,
}

impl Smc100Session {
    /// Opens the port and finds the controller at `address` (1..=31), without moving it.
    pub async fn open(
        connector: Box<dyn Connector>,
        address: u8,
        policy: Policy,
    ) -> Result<Self, DeviceError> {
        let mut s = Smc100Session {
            link: Link::new(connector),
            policy,
            address,
            info: None,
            needs_init: true,
            rehomes: 0,
        };
        if !wire::ADDRESSES.contains(&address) {
            return Err(s.error(
                ErrorKind::OutOfRange,
                format!("address = {address} is out of range: allowed 1..=31"),
            ));
        }
        s.link.open(policy.open_timeout).await?;
        s.identify().await?;
        Ok(s)
    }

    /// What the controller said it is.
    pub fn info(&self) -> Option<&Smc100Info> {
        self.info.as_ref()
    }

    /// Times the driver homed again after finding the controller reset.
    pub fn rehomes(&self) -> u32 {
        self.rehomes
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.link.opens()
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError::new(
            kind,
            format!("{} address {}", self.link.name(), self.address),
            message,
        )
    }

    /// Takes whole lines out of the buffer; the value of the first that answers `code`.
    fn scan(&mut self, code: &str) -> Option<String> {
        loop {
            let buf = self.link.buffer();
            let end = buf.iter().position(|&b| b == b'\n')?;
            let raw: Vec<u8> = buf.drain(..=end).collect();
            let text = String::from_utf8_lossy(&raw);
            match wire::parse_answer(&text, self.address, code) {
                Some(value) => return Some(value.to_string()),
                None => tracing::debug!(port = %self.link.name(), "skipped a line {raw:?}"),
            }
        }
    }

    /// Sends `code argument`; with `answer`, waits for the line that answers it.
    async fn exchange(
        &mut self,
        code: &str,
        argument: &str,
        answer: Option<&str>,
    ) -> Result<Option<String>, DeviceError> {
        self.link.discard_input().await?;
        let request = wire::command(self.address, code, argument);
        self.link.write(&request, self.policy.query_timeout).await?;
        let Some(answer) = answer else {
            return Ok(None);
        };
        let deadline = Instant::now() + self.policy.query_timeout;
        let what = format!("the answer to `{}{code}{argument}`", self.address);
        loop {
            if let Some(value) = self.scan(answer) {
                return Ok(Some(value));
            }
            self.link.fill(deadline, &what).await?;
        }
    }

    /// A query (`TP`, `TS`, `ID?`, ...) answered under `code`, retried.
    async fn query(&mut self, code: &str, argument: &str) -> Result<String, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            match self.exchange(code, argument, Some(code)).await {
                Ok(Some(value)) => return Ok(value),
                Ok(None) => {}
                Err(e) if retryable(&e) => last = Some(e),
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// A command that has no answer, then `TE`: a refusal is an error with the controller's
    /// reason. Retried while `TE` is not answered (the command may not have arrived; every
    /// command sent here may be repeated).
    async fn command(&mut self, code: &str, argument: &str) -> Result<(), DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            let sent = self.exchange(code, argument, None).await;
            let te = match sent {
                Ok(_) => self.exchange("TE", "", Some("TE")).await,
                Err(e) => Err(e),
            };
            match te {
                Ok(Some(value)) => return self.refusal(code, argument, &value),
                Ok(None) => {}
                Err(e) if retryable(&e) => last = Some(e),
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// `Ok` for `TE` = `@`, else the refusal as an error.
    fn refusal(&self, code: &str, argument: &str, te: &str) -> Result<(), DeviceError> {
        let letter = te.bytes().next().unwrap_or(b'?');
        if letter == wire::NO_ERROR {
            return Ok(());
        }
        let kind = match letter {
            b'C' | b'G' | b'N' => ErrorKind::OutOfRange,
            b'E' | b'L' | b'M' => ErrorKind::Busy,
            // Not allowed in this state: the state changed behind our back (a reset).
            b'H' | b'I' | b'J' | b'K' => ErrorKind::Protocol,
            _ => ErrorKind::Other,
        };
        Err(self.error(
            kind,
            format!(
                "`{}{code}{argument}` refused: error {} ({})",
                self.address,
                letter as char,
                wire::command_error(letter)
            ),
        ))
    }

    /// The positioner error bits and the state (`TS`).
    pub async fn status(&mut self) -> Result<(u16, u8), DeviceError> {
        let value = self.query("TS", "").await?;
        wire::parse_status(&value).ok_or_else(|| {
            self.error(
                ErrorKind::Protocol,
                format!("`TS` answered {value:?}: allowed 4 hex digits of errors and 2 of state"),
            )
        })
    }

    /// The position, degrees (`TP`).
    pub async fn position_deg(&mut self) -> Result<f64, DeviceError> {
        let value = self.query("TP", "").await?;
        wire::parse_number(&value).ok_or_else(|| {
            self.error(
                ErrorKind::Protocol,
                format!("`TP` answered {value:?}: not a number"),
            )
        })
    }

    async fn number(&mut self, code: &str) -> Result<f64, DeviceError> {
        let value = self.query(code, "?").await?;
        wire::parse_number(&value).ok_or_else(|| {
            self.error(
                ErrorKind::Protocol,
                format!("`{code}?` answered {value:?}: not a number"),
            )
        })
    }

    /// Reads `ID?`, `VE`, `SL?` and `SR?`. A controller that does not answer is named with
    /// its address.
    async fn identify(&mut self) -> Result<(), DeviceError> {
        let stage = match self.query("ID", "?").await {
            Ok(stage) => stage,
            Err(e) if e.kind() == ErrorKind::Timeout => {
                return Err(self.error(
                    ErrorKind::Timeout,
                    format!(
                        "no SMC100 or CONEX controller answers at address {} (allowed 1..=31: \
                         the address set on the controller; `devices stage --address N info` \
                         tries another)",
                        self.address
                    ),
                ))
            }
            Err(e) => return Err(e),
        };
        let version = self.query("VE", "").await?;
        let limits_deg = (self.number("SL").await?, self.number("SR").await?);
        tracing::info!(port = %self.link.name(), address = self.address, %stage, %version, "identified");
        self.info = Some(Smc100Info {
            stage,
            version,
            limits_deg,
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

    /// Brings the controller to READY: out of CONFIGURATION (`PW0`) and DISABLE (`MM1`),
    /// homed when NOT REFERENCED (a controller already READY keeps its datum).
    async fn init(&mut self) -> Result<(), DeviceError> {
        if self.info.is_none() {
            self.identify().await?;
        }
        let (_, state) = self.wait_still(self.policy.home_timeout).await?;
        match state {
            wire::CONFIGURATION => {
                self.command("PW", "0").await?;
                self.wait_answering().await?;
                self.home().await
            }
            s if wire::is_disabled(s) => self.command("MM", "1").await,
            s if wire::is_ready(s) => Ok(()),
            _ => self.home().await,
        }
    }

    /// Polls `TS` until the motor is still; the errors and state then.
    async fn wait_still(&mut self, timeout: Duration) -> Result<(u16, u8), DeviceError> {
        let deadline = Instant::now() + timeout;
        loop {
            let (errors, state) = self.status().await?;
            if !wire::is_in_motion(state) {
                return Ok((errors, state));
            }
            if Instant::now() >= deadline {
                return Err(self.error(
                    ErrorKind::Timeout,
                    format!(
                        "still {} after {timeout:?}",
                        wire::state_name(state).to_lowercase()
                    ),
                ));
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// Waits until the controller answers `TS` again (after a reset or saving settings).
    async fn wait_answering(&mut self) -> Result<(), DeviceError> {
        let deadline = Instant::now() + RESET_WAIT;
        loop {
            match self.exchange("TS", "", Some("TS")).await {
                Ok(_) => return Ok(()),
                Err(e) if e.kind() == ErrorKind::Timeout && Instant::now() < deadline => {}
                Err(e) => return Err(e),
            }
        }
    }

    /// Homes: a READY or DISABLE controller is reset first (`OR` is allowed only when NOT
    /// REFERENCED), then `OR` and `TS` until READY from HOMING.
    async fn home(&mut self) -> Result<(), DeviceError> {
        let (_, state) = self.status().await?;
        if !wire::is_not_referenced(state) {
            self.exchange("RS", "", None).await?;
            self.wait_answering().await?;
        }
        self.command("OR", "").await?;
        let (errors, state) = self.wait_still(self.policy.home_timeout).await?;
        if state != wire::READY_FROM_HOMING {
            return Err(self.error(
                ErrorKind::Stalled,
                format!(
                    "homing ended {} (errors {:?})",
                    wire::state_name(state),
                    wire::positioner_error_names(errors)
                ),
            ));
        }
        Ok(())
    }

    /// Moves to the position `target(current)` (degrees), verified by state and readback
    /// within `tolerance_deg`; retried, with a new homing after a reset and `MM1` after a
    /// following error.
    async fn move_verified(
        &mut self,
        target: impl Fn(f64) -> f64,
        tolerance_deg: f64,
    ) -> Result<f64, DeviceError> {
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.ensure_ready().await?;
            let result = match self.position_deg().await {
                Ok(current) => {
                    self.move_once(current, target(current), tolerance_deg)
                        .await
                }
                Err(e) => Err(e),
            };
            match result {
                Ok(p) => return Ok(p),
                Err(e) if retryable(&e) => {
                    tracing::warn!(port = %self.link.name(), address = self.address, "move attempt {} failed: {e}", k + 1);
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Other, "no attempt made")))
    }

    async fn move_once(
        &mut self,
        start: f64,
        target: f64,
        tolerance_deg: f64,
    ) -> Result<f64, DeviceError> {
        let sent = self.command("PA", &wire::number(target)).await;
        if let Err(e) = sent {
            self.check_reset().await?;
            return Err(e);
        }
        let (errors, state) = self.wait_still(self.policy.move_timeout).await?;
        if wire::is_not_referenced(state) {
            return Err(self.lost_datum(state));
        }
        if wire::is_disabled(state) {
            tracing::warn!(port = %self.link.name(), address = self.address, "move stopped: {:?}; enabling again", wire::positioner_error_names(errors));
            self.command("MM", "1").await?;
        }
        let p = self.position_deg().await?;
        if (p - target).abs() <= tolerance_deg && wire::is_ready(state) {
            return Ok(p);
        }
        Err(self.error(
            ErrorKind::Stalled,
            format!(
                "move from {start} to {target} deg ended at {p} deg, {} (errors {:?})",
                wire::state_name(state),
                wire::positioner_error_names(errors)
            ),
        ))
    }

    /// After a refused move: a controller found NOT REFERENCED has reset (homed again on the
    /// next attempt).
    async fn check_reset(&mut self) -> Result<(), DeviceError> {
        let (_, state) = self.status().await?;
        if wire::is_not_referenced(state) {
            return Err(self.lost_datum(state));
        }
        Ok(())
    }

    fn lost_datum(&mut self, state: u8) -> DeviceError {
        tracing::warn!(port = %self.link.name(), address = self.address, "controller {}: it reset; homing again", wire::state_name(state));
        self.rehomes += 1;
        self.needs_init = true;
        self.error(
            ErrorKind::Protocol,
            format!(
                "the controller is {} (it reset): homing again",
                wire::state_name(state)
            ),
        )
    }
}

crate::link::initialise_by_flag!(Smc100Session);

/// A rotation stage on an SMC100 or CONEX-AGP controller.
pub struct Smc100Rotator {
    session: Smc100Session,
    info: RotatorInfo,
    tolerance_deg: f64,
}

impl Smc100Rotator {
    /// Connects to the controller at `address` and brings it to READY (homing it if it is not
    /// referenced). `tolerance_deg` is the readback check.
    pub async fn connect(
        connector: Box<dyn Connector>,
        address: u8,
        policy: Policy,
        tolerance_deg: f64,
    ) -> Result<Self, DeviceError> {
        let mut session = Smc100Session::open(connector, address, policy).await?;
        session.ensure_ready().await?;
        let Some(id) = session.info().cloned() else {
            return Err(session.error(ErrorKind::Other, "connected without `ID?`"));
        };
        let counts_per_turn = (360.0 / id.resolution_deg()).round() as u32;
        Ok(Smc100Rotator {
            info: RotatorInfo {
                model: format!("Newport {} on {}", id.model(), id.version.trim()),
                counts_per_turn,
                tolerance_rad: tolerance_deg.to_radians(),
            },
            tolerance_deg,
            session,
        })
    }

    /// The session (what the controller is, re-homes, opens).
    pub fn session(&self) -> &Smc100Session {
        &self.session
    }
}

/// The position (degrees, multi-turn) nearest `current_deg` whose angle is `angle_deg`, inside
/// `limits_deg` if either way round is.
pub fn short_way(current_deg: f64, angle_deg: f64, limits_deg: (f64, f64)) -> f64 {
    let d =
        signed_difference(angle_deg.to_radians(), current_deg.to_radians(), TURN_RAD).to_degrees();
    let near = current_deg + d;
    let other = near - 360.0 * d.signum();
    let inside = |x: f64| x >= limits_deg.0 && x <= limits_deg.1;
    if inside(near) || !inside(other) {
        near
    } else {
        other
    }
}

impl Rotator for Smc100Rotator {
    fn info(&self) -> &RotatorInfo {
        &self.info
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.session.ensure_ready().await?;
        let policy = self.session.policy;
        let mut last = None;
        for k in 0..policy.attempts.max(1) {
            policy.pause_before(k).await;
            match self.session.home().await {
                Ok(()) => return Ok(()),
                Err(e) if retryable(&e) => last = Some(e),
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.session.error(ErrorKind::Other, "no attempt made")))
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        if !angle_rad.is_finite() {
            return Err(self.session.error(
                ErrorKind::OutOfRange,
                format!("angle_rad = {angle_rad} is not a finite angle"),
            ));
        }
        let limits = self
            .session
            .info()
            .map_or((f64::MIN, f64::MAX), |i| i.limits_deg);
        let angle_deg = angle_rad.to_degrees();
        let p = self
            .session
            .move_verified(|c| short_way(c, angle_deg, limits), self.tolerance_deg)
            .await?;
        Ok(p.to_radians().rem_euclid(TURN_RAD))
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.session.ensure_ready().await?;
        let p = self.session.position_deg().await?;
        Ok(p.to_radians().rem_euclid(TURN_RAD))
    }
}

/// SMC100 and CONEX-AGP: 8 data bits, no parity, one stop bit, XON/XOFF.
pub const LINE_8N1_XONXOFF: LineSettings = LineSettings {
    flow_control: crate::dialect::FlowControl::Software,
    ..crate::dialect::LINE_8N1
};

/// Newport SMC100 and CONEX-AGP (ASCII, addresses 1..=31 on one port).
pub const DIALECT: Dialect = Dialect {
    name: "smc100",
    description: "Newport SMC100 (PR50CC, URS) and CONEX-AGP (AG-PR100P) rotation stages",
    kinds: &[DeviceKind::Rotator],
    models: &["pr50cc", "urs", "conex-agp"],
    baud: 57_600,
    line: LINE_8N1_XONXOFF,
    bus: Some(Bus { first: 1, last: 31 }),
    policy: default_policy,
    identify: |c, address, policy| {
        Box::pin(async move {
            let mut s = Smc100Session::open(c, address, policy).await?;
            let (_, state) = s.status().await?;
            let p = s.position_deg().await?;
            let info = s.info().cloned().unwrap_or(Smc100Info {
                stage: String::new(),
                version: String::new(),
                limits_deg: (0.0, 0.0),
            });
            Ok(Identity {
                kind: DeviceKind::Rotator,
                model: info.model().to_string(),
                serial: String::new(),
                firmware: info.version.clone(),
                counts_per_turn: Some((360.0 / info.resolution_deg()).round() as u32),
                slots: None,
                homed: Some(wire::is_ready(state) || wire::is_disabled(state)),
                position: Position::Angle {
                    deg: p.rem_euclid(360.0),
                },
            })
        })
    },
    rotator: Some(|c, address, policy| {
        Box::pin(async move {
            let r = Smc100Rotator::connect(c, address, policy, SMC100_TOLERANCE_DEG).await?;
            Ok(AnyRotator::new(r))
        })
    }),
    wheel: None,
};

#[cfg(test)]
mod tests {
    use super::wire::*;
    use super::*;

    /// Command lines parse with one or two address digits, in either case, with their
    /// argument; answers match only their own address and command (controller 1's `TP` is not
    /// controller 11's).
    #[test]
    fn lines_parse_strictly() {
        assert_eq!(command(1, "PA", "45"), b"1PA45\r\n");
        let c = parse_command(b"12pa -1.5").unwrap();
        assert_eq!(
            (c.address, c.code(), c.argument.as_str()),
            (Some(12), "PA", "-1.5")
        );
        let c = parse_command(b"TS").unwrap();
        assert_eq!((c.address, c.code()), (None, "TS"));
        assert!(parse_command(b"123PA1").is_none());
        assert!(parse_command(b"1P").is_none());
        assert!(parse_command(b"1P1").is_none());
        assert!(parse_command(b"\xff\xfe").is_none());
        assert!(parse_command(b"").is_none());
        let c = parse_command(b"01TS").unwrap();
        assert_eq!(
            answer(&c.address_text, c.code(), "00000A"),
            b"01TS00000A\r\n"
        );
        assert_eq!(parse_answer("1TP44.999\r\n", 1, "TP"), Some("44.999"));
        assert_eq!(parse_answer("11TP44.999", 1, "TP"), None);
        assert_eq!(parse_answer("1TS000033", 1, "TP"), None);
        assert_eq!(parse_status("000033"), Some((0, 0x33)));
        assert_eq!(parse_status("00200A"), Some((FOLLOWING_ERROR, 0x0A)));
        assert_eq!(parse_status("0033"), None);
    }

    /// Numbers: six decimals; all read back.
    #[test]
    fn numbers_round_trip() {
        for (x, s) in [
            (45.0, "45.000000"),
            (-1.5, "-1.500000"),
            (44.9995, "44.999500"),
            (-0.0, "0.000000"),
            (-1_073_500.0, "-1073500.000000"),
        ] {
            assert_eq!(number(x), s);
            assert_eq!(parse_number(s), Some(x + 0.0));
        }
    }

    /// The short way round: 350 -> 10 deg goes forward 20 deg to 370, unless the limits
    /// forbid it, then backward to 10.
    #[test]
    fn moves_take_the_short_way_within_limits() {
        assert!((short_way(350.0, 10.0, (-1e12, 1e12)) - 370.0).abs() < 1e-9);
        assert!((short_way(350.0, 10.0, (-360.0, 360.0)) - 10.0).abs() < 1e-9);
        assert!((short_way(10.0, 350.0, (-1e12, 1e12)) + 10.0).abs() < 1e-9);
        assert!((short_way(725.0, 0.0, (-1e12, 1e12)) - 720.0).abs() < 1e-9);
    }
}
