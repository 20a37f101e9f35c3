//! Thorlabs APT rotation mounts: the K10CR1 stepper rotation mount and the PRM1Z8 rotation
//! stage on a KDC101 K-Cube DC servo controller ([`AptRotator`]), written from
//! `docs/DEVICES.md` section "Thorlabs APT" (Thorlabs' APT communications protocol, as
//! thorlabs-apt-device and pylablib implement it). The message codec is [`codec`].
//!
//! * **Opening** (the protocol's recommended sequence): 115200 baud, 8N1, RTS/CTS flow
//!   control, RTS asserted ([`AptSerial`]); 50 ms, purge, 50 ms; `HW_NO_FLASH_PROGRAMMING`;
//!   `HW_STOP_UPDATEMSGS` (a controller left sending status updates by an earlier program is
//!   quietened; an update that still arrives is skipped).
//! * **Identification**: `HW_REQ_INFO`; the model string must be the model's controller
//!   (`K10CR1`, or `KDC101` for the PRM1Z8), else an error naming both. Then the channel is
//!   enabled (`MOD_SET_CHANENABLESTATE`, checked with `MOD_REQ_CHANENABLESTATE`), the velocity
//!   parameters are read (`MOT_REQ_VELPARAMS`: the motion deadlines follow from them), and the
//!   mount is homed (`MOT_MOVE_HOME`, until `MOT_MOVE_HOMED`).
//! * **Moves** are absolute (`MOT_MOVE_ABSOLUTE`, so a retry repeats the same move), to the
//!   count nearest the present position that is at the asked angle (the short way round: the
//!   counter is not wrapped by the controllers); the end is `MOT_MOVE_COMPLETED` (or
//!   `MOT_MOVE_STOPPED`, a stall), then the status bits must show no motion and the position
//!   read back (`MOT_REQ_POSCOUNTER`) must be within the tolerance. A lost completion is not
//!   a verdict: the status bits are polled until the motion ends.
//! * **Datum**: the status bits' `homed` flag is read before every move; a controller that lost
//!   it (a reset, a power cycle) is homed again. A reopened port is identified and homed again.
//! * **Velocity mode** ([`Rotator::spin`], [`Rotator::stop_spin`]): `MOT_SET_VELPARAMS` sets
//!   the speed (read back with `MOT_REQ_VELPARAMS`), `MOT_MOVE_VELOCITY` (param2 1 forward,
//!   2 reverse) starts the motion, which runs until `MOT_MOVE_STOP` (profiled, param2 2; the
//!   end is `MOT_MOVE_STOPPED`); the status bits must show motion in the asked direction, and
//!   the velocity parameters are restored after the stop. The mounts have no position-compare
//!   trigger output: continuous acquisition runs a free-running camera
//!   ([`polar_hal::ContinuousSupport::Velocity`]). The position counter is a signed 32-bit
//!   count that the controllers do not wrap: a K10CR1 spinning one way overflows it after 43
//!   turns (a PRM1Z8 after a million).
//! * Every request that expects a reply is idempotent and retried with backoff; input is
//!   purged before each; unsolicited status updates, stale replies and bytes that do not form
//!   a plausible message are skipped (and counted, [`AptRotator::skipped`]).

/// The APT message codec, shared with the simulator (`polar-apt-protocol`).
pub use polar_apt_protocol as codec;

use crate::any::AnyRotator;
use crate::dialect::{
    DeviceKind, Dialect, FlowControl, Identity, LineSettings, Position, LINE_8N1,
};
use crate::link::{retryable, BoxIo, Connector, Link, OpenFuture, Policy};
use codec::{status, Decoded, HwInfo, Message, VelParams};
use polar_hal::{
    signed_difference, wrap, ContinuousSupport, DeviceError, ErrorKind, Rotator, RotatorInfo,
    WireTimes, TURN_RAD,
};
use std::io;
use std::time::Duration;
use tokio::time::Instant;

/// The APT line rate.
pub const BAUD: u32 = 115_200;

/// The models this driver drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AptModel {
    /// K10CR1 stepper rotation mount (its own controller).
    K10cr1,
    /// PRM1Z8 rotation stage on a KDC101 K-Cube DC servo controller.
    Prm1z8,
}

impl AptModel {
    /// The model as the CLI spells it (`--model k10cr1|prm1z8`); an error names the allowed
    /// values.
    pub fn parse(name: &str) -> Result<Self, String> {
        match name.to_ascii_lowercase().as_str() {
            "k10cr1" => Ok(AptModel::K10cr1),
            "prm1z8" | "prm1-z8" => Ok(AptModel::Prm1z8),
            _ => Err(format!(
                "--model {name:?} is not an APT rotation mount: allowed k10cr1, prm1z8"
            )),
        }
    }

    /// The model a controller's `HW_GET_INFO` model string names (`K10CR1`, or `KDC101`: the
    /// PRM1Z8 is the rotation stage this driver drives on a KDC101).
    pub fn from_controller(controller: &str) -> Option<Self> {
        match controller {
            "K10CR1" => Some(AptModel::K10cr1),
            "KDC101" => Some(AptModel::Prm1z8),
            _ => None,
        }
    }

    /// The CLI's name.
    pub fn name(self) -> &'static str {
        match self {
            AptModel::K10cr1 => "k10cr1",
            AptModel::Prm1z8 => "prm1z8",
        }
    }

    /// The controller's model string in `HW_GET_INFO`.
    pub fn controller(self) -> &'static str {
        match self {
            AptModel::K10cr1 => "K10CR1",
            AptModel::Prm1z8 => "KDC101",
        }
    }

    /// The first two digits of the controller's serial numbers (pylablib's table).
    pub fn serial_prefix(self) -> u32 {
        match self {
            AptModel::K10cr1 => 55,
            AptModel::Prm1z8 => 27,
        }
    }

    /// Position counts per degree: K10CR1 409600/3 microsteps (200 full steps, 2048
    /// microsteps, 120:1 worm), PRM1Z8 1919.6418 encoder counts (pylablib, from the manual).
    pub fn counts_per_deg(self) -> f64 {
        match self {
            AptModel::K10cr1 => 409_600.0 / 3.0,
            AptModel::Prm1z8 => 1_919.641_857_862_339,
        }
    }

    /// Controller velocity units per count/s: K10CR1 (TST101/KST101 family) 53.68; KDC101
    /// `T * 65536` with `T = 2048 / 6e6` s (the protocol's servo-loop scaling).
    pub fn velocity_units_per_count_s(self) -> f64 {
        match self {
            AptModel::K10cr1 => 53.68,
            AptModel::Prm1z8 => KDC101_T_S * 65_536.0,
        }
    }

    /// Controller acceleration units per count/s^2: K10CR1 `53.68 * 204.94e-6`; KDC101
    /// `T^2 * 65536`.
    pub fn acceleration_units_per_count_s2(self) -> f64 {
        match self {
            AptModel::K10cr1 => 53.68 * 204.94e-6,
            AptModel::Prm1z8 => KDC101_T_S * KDC101_T_S * 65_536.0,
        }
    }

    /// The highest velocity the mount is specified for, deg/s (K10CR1 10, PRM1Z8 25).
    pub fn max_velocity_deg_s(self) -> f64 {
        match self {
            AptModel::K10cr1 => 10.0,
            AptModel::Prm1z8 => 25.0,
        }
    }

    /// The status update the controller sends (unsolicited, or as a move's completion data).
    pub fn status_update_id(self) -> u16 {
        match self {
            AptModel::K10cr1 => codec::MOT_GET_STATUSUPDATE,
            AptModel::Prm1z8 => codec::MOT_GET_DCSTATUSUPDATE,
        }
    }

    /// Degrees/s to the controller's velocity units.
    pub fn velocity_to_device(self, deg_s: f64) -> f64 {
        deg_s * self.counts_per_deg() * self.velocity_units_per_count_s()
    }

    /// The controller's velocity units to degrees/s.
    pub fn velocity_from_device(self, units: f64) -> f64 {
        units / self.velocity_units_per_count_s() / self.counts_per_deg()
    }

    /// The controller's acceleration units to degrees/s^2.
    pub fn acceleration_from_device(self, units: f64) -> f64 {
        units / self.acceleration_units_per_count_s2() / self.counts_per_deg()
    }
}

/// The KDC101's velocity time unit, seconds (2048 / 6 MHz).
pub const KDC101_T_S: f64 = 2048.0 / 6.0e6;

/// The default policy: 115200 baud replies in a few ms; the move and home deadlines are these
/// plus the motion's own duration at the controller's velocity.
pub fn default_policy() -> Policy {
    Policy {
        open_timeout: Duration::from_secs(2),
        query_timeout: Duration::from_millis(500),
        move_timeout: Duration::from_secs(5),
        home_timeout: Duration::from_secs(10),
        attempts: 4,
        backoff: Duration::from_millis(50),
    }
}

/// An APT controller's serial port by path: 115200 baud, 8N1, RTS/CTS flow control, RTS
/// asserted after opening (the protocol's opening sequence; the FTDI bridge of the real
/// controllers needs it). A pseudo-terminal has no modem lines: failing to set RTS there is
/// logged and ignored.
#[derive(Debug, Clone, PartialEq)]
pub struct AptSerial {
    /// The device path (prefer `/dev/serial/by-id/...`).
    pub path: String,
}

impl Connector for AptSerial {
    fn describe(&self) -> String {
        self.path.clone()
    }

    fn open(&self) -> OpenFuture<'_> {
        Box::pin(async move {
            use tokio_serial::SerialPort;
            let builder = tokio_serial::new(&self.path, BAUD)
                .data_bits(tokio_serial::DataBits::Eight)
                .parity(tokio_serial::Parity::None)
                .stop_bits(tokio_serial::StopBits::One)
                .flow_control(tokio_serial::FlowControl::Hardware);
            let mut port = tokio_serial::SerialStream::open(&builder).map_err(io::Error::from)?;
            if let Err(e) = port.write_request_to_send(true) {
                tracing::debug!(port = %self.path, "RTS not set (no modem lines?): {e}");
            }
            Ok(Box::new(port) as BoxIo)
        })
    }
}

/// A K10CR1 or a PRM1Z8 on a KDC101, as a [`Rotator`].
pub struct AptRotator {
    link: Link,
    policy: Policy,
    model: AptModel,
    /// Whether the model is taken from the first `HW_GET_INFO` ([`AptRotator::connect_detect`]).
    detect: bool,
    tolerance_rad: f64,
    hw: Option<HwInfo>,
    velocity: Option<VelParams>,
    /// The velocity parameters before velocity mode changed them (restored by
    /// [`Rotator::stop_spin`]).
    spin_restore: Option<VelParams>,
    needs_init: bool,
    rehomes: u32,
    skipped: u64,
    info: RotatorInfo,
    tolerance_counts: i64,
}

/// How a move ended.
enum MoveEnd {
    Completed,
    Stopped,
    Unknown,
}

impl AptRotator {
    /// Opens the port, identifies the controller as `model`'s, enables the channel, reads the
    /// velocity parameters and homes. `tolerance_rad` is the readback check (at least one
    /// count).
    pub async fn connect(
        connector: Box<dyn Connector>,
        model: AptModel,
        policy: Policy,
        tolerance_rad: f64,
    ) -> Result<Self, DeviceError> {
        Self::connect_inner(connector, model, false, policy, tolerance_rad).await
    }

    /// Like [`AptRotator::connect`], with the model taken from the controller's `HW_GET_INFO`
    /// (`K10CR1`, or `KDC101`: a PRM1Z8), for callers that have no `--model`.
    pub async fn connect_detect(
        connector: Box<dyn Connector>,
        policy: Policy,
        tolerance_rad: f64,
    ) -> Result<Self, DeviceError> {
        Self::connect_inner(connector, AptModel::K10cr1, true, policy, tolerance_rad).await
    }

    async fn connect_inner(
        connector: Box<dyn Connector>,
        model: AptModel,
        detect: bool,
        policy: Policy,
        tolerance_rad: f64,
    ) -> Result<Self, DeviceError> {
        let mut r = AptRotator {
            link: Link::new(connector),
            policy,
            model,
            detect,
            tolerance_rad,
            hw: None,
            velocity: None,
            spin_restore: None,
            needs_init: true,
            rehomes: 0,
            skipped: 0,
            info: RotatorInfo {
                model: format!("Thorlabs {}", model.controller()),
                counts_per_turn: (model.counts_per_deg() * 360.0).round() as u32,
                tolerance_rad: 0.0,
            },
            tolerance_counts: 1,
        };
        if !(0.0..TURN_RAD / 4.0).contains(&tolerance_rad) {
            return Err(r.link.error(
                ErrorKind::OutOfRange,
                format!("tolerance_rad = {tolerance_rad} is out of range: allowed [0, pi/2)"),
            ));
        }
        r.set_model(model);
        r.ensure_ready().await?;
        Ok(r)
    }

    /// Sets the model and what follows from its scale (tolerance, counts per turn).
    fn set_model(&mut self, model: AptModel) {
        self.model = model;
        let cpd = model.counts_per_deg();
        self.tolerance_counts = ((self.tolerance_rad.to_degrees() * cpd).round() as i64).max(1);
        self.info.tolerance_rad = (self.tolerance_counts as f64 / cpd).to_radians();
        self.info.counts_per_turn = (cpd * 360.0).round() as u32;
    }

    /// The model.
    pub fn model(&self) -> AptModel {
        self.model
    }

    /// The controller's `HW_GET_INFO`.
    pub fn hw_info(&self) -> Option<&HwInfo> {
        self.hw.as_ref()
    }

    /// Times the driver homed again after finding the datum lost.
    pub fn rehomes(&self) -> u32 {
        self.rehomes
    }

    /// Messages skipped while waiting for a reply (unsolicited status updates, stale replies,
    /// and one per byte that could not start a message).
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    /// How many times the port has been opened.
    pub fn opens(&self) -> u32 {
        self.link.opens()
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        self.link.error(kind, message)
    }

    fn angle(&self, counts: i32) -> f64 {
        wrap(
            (f64::from(counts) / self.model.counts_per_deg()).to_radians(),
            TURN_RAD,
        )
    }

    /// The count nearest `current` at which the mount is at `angle_rad`.
    fn toward(&self, current: i32, angle_rad: f64) -> i32 {
        let delta_deg = signed_difference(angle_rad, self.angle(current), TURN_RAD).to_degrees();
        let target = f64::from(current) + (delta_deg * self.model.counts_per_deg()).round();
        target.clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    }

    async fn send(&mut self, m: &Message) -> Result<(), DeviceError> {
        self.link
            .write(&m.encode(), self.policy.query_timeout)
            .await
    }

    /// The next message that decodes, skipping bytes that cannot start one.
    async fn next_message(
        &mut self,
        deadline: Instant,
        waiting_for: &str,
    ) -> Result<Message, DeviceError> {
        loop {
            match codec::decode(self.link.buffer()) {
                Decoded::Message(m, n) => {
                    self.link.buffer().drain(..n);
                    return Ok(m);
                }
                Decoded::Invalid => {
                    self.link.buffer().drain(..1);
                    self.skipped += 1;
                }
                Decoded::Incomplete => self.link.fill(deadline, waiting_for).await?,
            }
        }
    }

    /// Waits for a message with one of `ids`, skipping the rest.
    async fn await_reply(
        &mut self,
        ids: &[u16],
        deadline: Instant,
        waiting_for: &str,
    ) -> Result<Message, DeviceError> {
        loop {
            let m = self.next_message(deadline, waiting_for).await?;
            if ids.contains(&m.id) {
                return Ok(m);
            }
            if m.id == codec::HW_RICHRESPONSE {
                let notes = String::from_utf8_lossy(m.data().get(4..).unwrap_or(&[]))
                    .trim_matches('\0')
                    .to_string();
                tracing::warn!(port = %self.link.name(), code = m.u16_at(2), "controller event: {notes}");
            } else {
                tracing::trace!(port = %self.link.name(), id = m.id, "skipped a message");
            }
            self.skipped += 1;
        }
    }

    /// Sends `request` and waits for `reply`, retried.
    async fn query(&mut self, request: Message, reply: u16) -> Result<Message, DeviceError> {
        let what = format!("reply {reply:#06x} to {:#06x}", request.id);
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.link.discard_input().await?;
            self.send(&request).await?;
            let deadline = Instant::now() + self.policy.query_timeout;
            match self.await_reply(&[reply], deadline, &what).await {
                Ok(m) => return Ok(m),
                Err(e) if retryable(&e) => last = Some(e),
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Timeout, "no attempt made")))
    }

    /// The position counter, counts.
    pub async fn position_counts(&mut self) -> Result<i32, DeviceError> {
        let m = self
            .query(
                Message::short(codec::MOT_REQ_POSCOUNTER, codec::CHANNEL, 0),
                codec::MOT_GET_POSCOUNTER,
            )
            .await?;
        Ok(m.i32_at(2))
    }

    /// The status bits ([`codec::status`]).
    pub async fn status_bits(&mut self) -> Result<u32, DeviceError> {
        let m = self
            .query(
                Message::short(codec::MOT_REQ_STATUSBITS, codec::CHANNEL, 0),
                codec::MOT_GET_STATUSBITS,
            )
            .await?;
        Ok(m.u32_at(2))
    }

    /// The velocity parameters: (max velocity deg/s, acceleration deg/s^2).
    pub async fn velocity_params(&mut self) -> Result<(f64, f64), DeviceError> {
        let m = self
            .query(
                Message::short(codec::MOT_REQ_VELPARAMS, codec::CHANNEL, 0),
                codec::MOT_GET_VELPARAMS,
            )
            .await?;
        let v = VelParams::from_message(&m);
        self.velocity = Some(v);
        Ok((
            self.model.velocity_from_device(f64::from(v.max_velocity)),
            self.model
                .acceleration_from_device(f64::from(v.acceleration)),
        ))
    }

    /// How long a motion over `deg` degrees takes at the known velocity parameters, seconds
    /// (a trapezoid; 10 deg/s and 10 deg/s^2 if none are known).
    fn motion_s(&self, deg: f64) -> f64 {
        let (v, a) = self.velocity.map_or((10.0, 10.0), |p| {
            (
                self.model.velocity_from_device(f64::from(p.max_velocity)),
                self.model
                    .acceleration_from_device(f64::from(p.acceleration)),
            )
        });
        let (v, a) = (v.max(0.01), a.max(0.01));
        let d = deg.abs();
        if v * v / a >= d {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        }
    }

    async fn open_sequence(&mut self) -> Result<(), DeviceError> {
        self.link.open(self.policy.open_timeout).await?;
        tokio::time::sleep(Duration::from_millis(50)).await;
        self.link.discard_input().await?;
        tokio::time::sleep(Duration::from_millis(50)).await;
        self.link.discard_input().await?;
        self.send(&Message::short(codec::HW_NO_FLASH_PROGRAMMING, 0, 0))
            .await?;
        self.send(&Message::short(codec::HW_STOP_UPDATEMSGS, 0, 0))
            .await
    }

    async fn ensure_ready(&mut self) -> Result<(), DeviceError> {
        if !self.link.is_open() {
            self.open_sequence().await?;
            // A reopened port may be a power-cycled controller: identify and home again.
            self.needs_init = true;
        }
        let policy = self.policy;
        policy.retry_init(self).await
    }

    async fn init(&mut self) -> Result<(), DeviceError> {
        let m = self
            .query(Message::short(codec::HW_REQ_INFO, 0, 0), codec::HW_GET_INFO)
            .await?;
        let hw = HwInfo::parse(m.data()).map_err(|e| self.error(ErrorKind::Protocol, e))?;
        if self.detect && self.hw.is_none() {
            match AptModel::from_controller(&hw.model) {
                Some(model) => self.set_model(model),
                None => {
                    return Err(self.error(
                        ErrorKind::Other,
                        format!(
                            "controller reports model {:?} (serial {}): allowed K10CR1, KDC101 (PRM1Z8)",
                            hw.model, hw.serial
                        ),
                    ))
                }
            }
        }
        if hw.model != self.model.controller() {
            return Err(self.error(
                ErrorKind::Other,
                format!(
                    "controller reports model {:?} (serial {}); --model {} wants a {}",
                    hw.model,
                    hw.serial,
                    self.model.name(),
                    self.model.controller()
                ),
            ));
        }
        if hw.serial / 1_000_000 != self.model.serial_prefix() {
            tracing::warn!(port = %self.link.name(), serial = hw.serial, "serial number does not start with {}", self.model.serial_prefix());
        }
        self.info.model = format!("Thorlabs {} serial {}", hw.model, hw.serial);
        if self.model == AptModel::Prm1z8 {
            self.info.model = format!("Thorlabs PRM1Z8 on KDC101 serial {}", hw.serial);
        }
        tracing::info!(port = %self.link.name(), ?hw, "identified");
        self.hw = Some(hw);
        self.enable().await?;
        self.velocity_params().await?;
        self.home_now().await
    }

    /// Enables channel 1 and checks it reads back enabled.
    async fn enable(&mut self) -> Result<(), DeviceError> {
        self.send(&Message::short(
            codec::MOD_SET_CHANENABLESTATE,
            codec::CHANNEL,
            1,
        ))
        .await?;
        let m = self
            .query(
                Message::short(codec::MOD_REQ_CHANENABLESTATE, codec::CHANNEL, 0),
                codec::MOD_GET_CHANENABLESTATE,
            )
            .await?;
        if m.param2 != 1 {
            return Err(self.error(
                ErrorKind::Protocol,
                format!(
                    "channel 1 reads enable state {} after enabling: want 1",
                    m.param2
                ),
            ));
        }
        Ok(())
    }

    /// Waits until the status bits show no motion, until `deadline`.
    async fn wait_still(&mut self, deadline: Instant) -> Result<u32, DeviceError> {
        loop {
            let bits = self.status_bits().await?;
            if bits & status::IN_MOTION == 0 {
                return Ok(bits);
            }
            if Instant::now() >= deadline {
                return Err(self.error(
                    ErrorKind::Timeout,
                    format!("still moving (status {bits:#010x}) at the deadline"),
                ));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Homes (`MOT_MOVE_HOME` until `MOT_MOVE_HOMED`) and checks the datum.
    async fn home_now(&mut self) -> Result<(), DeviceError> {
        self.link.discard_input().await?;
        self.send(&Message::short(codec::MOT_MOVE_HOME, codec::CHANNEL, 0))
            .await?;
        // Homing may turn up to a full turn to the home switch.
        let budget = self.policy.home_timeout + Duration::from_secs_f64(self.motion_s(360.0));
        let deadline = Instant::now() + budget;
        let homed = self
            .await_reply(&[codec::MOT_MOVE_HOMED], deadline, "MOT_MOVE_HOMED")
            .await;
        match homed {
            Ok(_) => {}
            // A lost MOT_MOVE_HOMED is judged by the status bits below.
            Err(e) if e.kind() == ErrorKind::Timeout => {}
            Err(e) => return Err(e),
        }
        let bits = self.wait_still(deadline).await?;
        if bits & status::HOMED == 0 {
            return Err(self.error(
                ErrorKind::Stalled,
                format!("homing ended without the homed flag (status {bits:#010x})"),
            ));
        }
        let p = self.position_counts().await?;
        if i64::from(p).abs() > self.tolerance_counts {
            return Err(self.error(
                ErrorKind::Stalled,
                format!("homing ended at {p} counts, not 0"),
            ));
        }
        Ok(())
    }

    /// Stops any motion (profiled), waits for `MOT_MOVE_STOPPED` (or the motion to end) and
    /// returns the position, radians.
    pub async fn stop(&mut self) -> Result<f64, DeviceError> {
        self.link.discard_input().await?;
        self.send(&Message::short(codec::MOT_MOVE_STOP, codec::CHANNEL, 2))
            .await?;
        let deadline = Instant::now() + self.policy.move_timeout;
        let _ = self
            .await_reply(
                &[codec::MOT_MOVE_STOPPED, codec::MOT_MOVE_COMPLETED],
                Instant::now() + self.policy.query_timeout + Duration::from_secs(2),
                "MOT_MOVE_STOPPED",
            )
            .await;
        self.wait_still(deadline).await?;
        let p = self.position_counts().await?;
        Ok(self.angle(p))
    }

    /// Sets the velocity parameters' max velocity to `deg_s` and checks it reads back (the
    /// controller's rounding: one unit).
    async fn write_max_velocity(&mut self, deg_s: f64) -> Result<(), DeviceError> {
        let mut params = self.known_velocity_params().await?;
        params.max_velocity = self.model.velocity_to_device(deg_s).round() as i32;
        self.write_velocity_params(params).await
    }

    /// The velocity parameters, read from the controller if none are known.
    async fn known_velocity_params(&mut self) -> Result<VelParams, DeviceError> {
        if self.velocity.is_none() {
            self.velocity_params().await?;
        }
        self.velocity
            .ok_or_else(|| self.error(ErrorKind::Protocol, "no velocity parameters"))
    }

    /// Writes `params` (`MOT_SET_VELPARAMS`) and checks the max velocity reads back.
    async fn write_velocity_params(&mut self, params: VelParams) -> Result<(), DeviceError> {
        self.send(&params.set_message()).await?;
        self.velocity_params().await?;
        let got = self.velocity.map_or(0, |v| v.max_velocity);
        if (i64::from(got) - i64::from(params.max_velocity)).abs() > 1 {
            return Err(self.error(
                ErrorKind::Other,
                format!(
                    "max velocity reads {got} after setting {}: refused",
                    params.max_velocity
                ),
            ));
        }
        Ok(())
    }

    /// Checks a speed against the model's top speed: `|deg/s|` in `(0, max]`, positive unless
    /// `signed`. Returns deg/s.
    fn check_speed(&self, rad_per_s: f64, signed: bool) -> Result<f64, DeviceError> {
        let deg_s = rad_per_s.to_degrees();
        let max = self.model.max_velocity_deg_s();
        let size_ok = deg_s.is_finite() && deg_s != 0.0 && deg_s.abs() <= max * (1.0 + 1e-9);
        if size_ok && (signed || deg_s > 0.0) {
            return Ok(deg_s);
        }
        let allowed = if signed {
            format!("0 < |deg/s| <= {max} (the sign is the direction)")
        } else {
            format!("(0, {max}] deg/s")
        };
        Err(self.error(
            ErrorKind::OutOfRange,
            format!(
                "rad_per_s = {rad_per_s} ({deg_s} deg/s) is out of range for the {}: allowed {allowed}",
                self.model.name()
            ),
        ))
    }

    /// Starts velocity mode at `deg_s` (signed) and checks the status bits show motion in
    /// that direction; retried (the start has no reply to lose, so a start that does not show
    /// is sent again).
    async fn start_spin(&mut self, deg_s: f64) -> Result<(), DeviceError> {
        self.ensure_ready().await?;
        let before = self.known_velocity_params().await?;
        // The move parameters to restore: those before the first spin of a series.
        if self.spin_restore.is_none() {
            self.spin_restore = Some(before);
        }
        self.write_max_velocity(deg_s.abs()).await?;
        let (direction, moving) = if deg_s > 0.0 {
            (1, status::MOVING_FWD)
        } else {
            (2, status::MOVING_REV)
        };
        let mut bits = 0;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            self.send(&Message::short(
                codec::MOT_MOVE_VELOCITY,
                codec::CHANNEL,
                direction,
            ))
            .await?;
            tokio::time::sleep(Duration::from_millis(20)).await;
            bits = self.status_bits().await?;
            if bits & moving != 0 {
                return Ok(());
            }
        }
        Err(self.error(
            ErrorKind::Stalled,
            format!(
                "velocity mode at {deg_s} deg/s did not start (status {bits:#010x}, want bit {moving:#x})"
            ),
        ))
    }

    /// One absolute move to `target` counts from `start`, judged by readback.
    async fn move_once(&mut self, start: i32, target: i32) -> Result<i32, DeviceError> {
        self.link.discard_input().await?;
        self.send(&codec::move_absolute(target)).await?;
        let deg = f64::from(target - start) / self.model.counts_per_deg();
        let deadline =
            Instant::now() + self.policy.move_timeout + Duration::from_secs_f64(self.motion_s(deg));
        let end = match self
            .await_reply(
                &[codec::MOT_MOVE_COMPLETED, codec::MOT_MOVE_STOPPED],
                deadline,
                "MOT_MOVE_COMPLETED",
            )
            .await
        {
            Ok(m) if m.id == codec::MOT_MOVE_COMPLETED => MoveEnd::Completed,
            Ok(_) => MoveEnd::Stopped,
            Err(e) if e.kind() == ErrorKind::Timeout => MoveEnd::Unknown,
            Err(e) => return Err(e),
        };
        // A completion may be a late one of an earlier move: the motion must have ended.
        let bits = self.wait_still(deadline).await?;
        let tolerance = self.tolerance_counts;
        let near = move |p: i32| (i64::from(p) - i64::from(target)).abs() <= tolerance;
        let mut p = self.position_counts().await?;
        if !near(p) {
            // No checksum: a reply damaged on the line reads as a wrong position. Read again.
            p = self.position_counts().await?;
        }
        if near(p) {
            return Ok(p);
        }
        let how = match end {
            MoveEnd::Completed => "completed",
            MoveEnd::Stopped => "stopped",
            MoveEnd::Unknown => "ended without a completion message",
        };
        Err(self.error(
            ErrorKind::Stalled,
            format!(
                "move from {start} to {target} counts {how} at {p} counts (status {bits:#010x})"
            ),
        ))
    }
}

crate::link::initialise_by_flag!(AptRotator);

/// What [`probe`] reads without moving the mount.
#[derive(Debug, Clone, PartialEq)]
pub struct Probe {
    /// The controller's `HW_GET_INFO`.
    pub hw: HwInfo,
    /// The model its controller string names, if it is one this driver drives.
    pub model: Option<AptModel>,
    /// The position counter, counts.
    pub position_counts: i32,
    /// The status bits.
    pub status: u32,
}

/// Opens the port (the opening sequence) and reads the controller's identity, position and
/// status bits, without enabling, homing or moving it.
pub async fn probe(connector: Box<dyn Connector>, policy: Policy) -> Result<Probe, DeviceError> {
    let mut r = AptRotator {
        link: Link::new(connector),
        policy,
        model: AptModel::K10cr1,
        detect: false,
        tolerance_rad: 0.0,
        hw: None,
        velocity: None,
        spin_restore: None,
        needs_init: false,
        rehomes: 0,
        skipped: 0,
        info: RotatorInfo {
            model: String::new(),
            counts_per_turn: 1,
            tolerance_rad: 0.0,
        },
        tolerance_counts: 1,
    };
    r.open_sequence().await?;
    let m = r
        .query(Message::short(codec::HW_REQ_INFO, 0, 0), codec::HW_GET_INFO)
        .await?;
    let hw = HwInfo::parse(m.data()).map_err(|e| r.error(ErrorKind::Protocol, e))?;
    let position_counts = r.position_counts().await?;
    let status = r.status_bits().await?;
    Ok(Probe {
        model: AptModel::from_controller(&hw.model),
        hw,
        position_counts,
        status,
    })
}

/// The readback tolerance the registry gives APT rotation mounts, degrees.
pub const APT_TOLERANCE_DEG: f64 = 0.01;

/// Thorlabs APT (Kinesis) rotation mounts: binary protocol, RTS/CTS.
pub const DIALECT: Dialect = Dialect {
    name: "apt",
    description: "Thorlabs APT/Kinesis: K10CR1 rotation mount, PRM1Z8 on a KDC101 (binary)",
    kinds: &[DeviceKind::Rotator],
    models: &["k10cr1", "prm1z8"],
    baud: BAUD,
    line: LineSettings {
        flow_control: FlowControl::Hardware,
        ..LINE_8N1
    },
    bus: None,
    policy: default_policy,
    identify: |c, _, policy| {
        Box::pin(async move {
            let p = probe(c, policy).await?;
            let per_deg = p.model.map(AptModel::counts_per_deg);
            Ok(Identity {
                kind: DeviceKind::Rotator,
                model: p
                    .model
                    .map_or_else(|| p.hw.model.clone(), |m| m.name().to_string()),
                serial: p.hw.serial.to_string(),
                firmware: String::new(),
                counts_per_turn: per_deg.map(|c| (c * 360.0).round() as u32),
                slots: None,
                homed: Some(p.status & codec::status::HOMED != 0),
                position: Position::Angle {
                    deg: per_deg.map_or(f64::NAN, |c| {
                        (f64::from(p.position_counts) / c).rem_euclid(360.0)
                    }),
                },
            })
        })
    },
    rotator: Some(|c, _, policy| {
        Box::pin(async move {
            let tolerance_rad = APT_TOLERANCE_DEG.to_radians();
            let r = AptRotator::connect_detect(c, policy, tolerance_rad).await?;
            Ok(AnyRotator::new(r))
        })
    }),
    wheel: None,
};

impl Rotator for AptRotator {
    fn info(&self) -> &RotatorInfo {
        &self.info
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.needs_init = true;
        self.ensure_ready().await
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        if !angle_rad.is_finite() {
            return Err(self.error(
                ErrorKind::OutOfRange,
                format!("angle_rad = {angle_rad} is not a finite angle"),
            ));
        }
        let mut last = None;
        for k in 0..self.policy.attempts.max(1) {
            self.policy.pause_before(k).await;
            let result = async {
                self.ensure_ready().await?;
                let bits = self.status_bits().await?;
                if bits & status::HOMED == 0 {
                    tracing::warn!(port = %self.link.name(), "status {bits:#010x}: datum lost; homing");
                    self.rehomes += 1;
                    self.needs_init = true;
                    self.ensure_ready().await?;
                }
                let start = self.position_counts().await?;
                let target = self.toward(start, angle_rad);
                self.move_once(start, target).await
            }
            .await;
            match result {
                Ok(p) => return Ok(self.angle(p)),
                Err(e) if retryable(&e) => {
                    tracing::warn!(port = %self.link.name(), "move attempt {} failed: {e}", k + 1);
                    last = Some(e);
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| self.error(ErrorKind::Other, "no attempt made")))
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.ensure_ready().await?;
        let p = self.position_counts().await?;
        Ok(self.angle(p))
    }

    fn supports_velocity(&self) -> bool {
        true
    }

    async fn set_velocity(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        let deg_s = self.check_speed(rad_per_s, false)?;
        self.ensure_ready().await?;
        self.write_max_velocity(deg_s).await
    }

    fn continuous_support(&self) -> ContinuousSupport {
        ContinuousSupport::Velocity
    }

    /// Velocity mode at `rad_per_s` (signed: positive is forward), at most the model's top
    /// speed (K10CR1 10 deg/s, PRM1Z8 25 deg/s); a second call changes the speed and
    /// direction.
    async fn spin(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        let deg_s = self.check_speed(rad_per_s, true)?;
        self.start_spin(deg_s).await
    }

    /// A profiled stop (`MOT_MOVE_STOP` until `MOT_MOVE_STOPPED` and no motion bit), then the
    /// velocity parameters of before the spin are written back.
    async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        let at = self.stop().await?;
        if let Some(p) = self.spin_restore.take() {
            self.write_velocity_params(p).await?;
        }
        Ok(at)
    }

    async fn spin_position_rad(&mut self) -> Result<f64, DeviceError> {
        let p = self.position_counts().await?;
        Ok((f64::from(p) / self.model.counts_per_deg()).to_radians())
    }

    /// `MOT_REQ_POSCOUNTER` (6 bytes) and `MOT_GET_POSCOUNTER` (12) at 115200 baud 8N1 (the
    /// controllers' FTDI UART): 0.52 ms before the latch, 1.04 ms after it.
    fn spin_read_wire(&self) -> WireTimes {
        WireTimes::uart(6, 12, BAUD, 10)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scales: a K10CR1 turn is 49 152 000 microsteps; 10 deg/s is 73 291 093 velocity units
    /// (136533.33 * 10 * 53.68); a KDC101 velocity unit is 1 / 22.3696 counts/s (T * 65536 with
    /// T = 2048/6e6 s); round trips are exact to 1e-12.
    #[test]
    fn model_scales() {
        let k = AptModel::K10cr1;
        assert_eq!((k.counts_per_deg() * 360.0).round(), 49_152_000.0);
        assert!((k.velocity_to_device(10.0) - 73_291_093.33).abs() < 0.01);
        let p = AptModel::Prm1z8;
        assert!((p.velocity_units_per_count_s() - 22.369_621_333).abs() < 1e-6);
        for m in [k, p] {
            let v = m.velocity_from_device(m.velocity_to_device(7.5));
            assert!((v - 7.5).abs() < 1e-12);
        }
        assert_eq!(AptModel::parse("K10CR1"), Ok(AptModel::K10cr1));
        assert!(AptModel::parse("kdc101")
            .unwrap_err()
            .contains("allowed k10cr1, prm1z8"));
    }
}
