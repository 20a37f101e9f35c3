//! Thorlabs APT rotation mounts simulated at the byte level (`docs/DEVICES.md`, section
//! "Thorlabs APT"): the K10CR1 stepper rotation mount and the PRM1Z8 rotation stage on a
//! KDC101 K-Cube DC servo controller. Binary messages, 6-byte little-endian headers with an
//! optional data packet; the device is `0x50` (a USB controller), the host `0x01`.
//!
//! **Defaults are the healthy device**: a client written for the real controller works
//! unchanged (`docs/DEVICES-conformance.md` runs thorlabs-apt-device's `KDC101` class and
//! pylablib's `KinesisMotor` against it). Behaviour, with its source where there is one; the
//! rest are choices where the sources are silent:
//! * **Framing.** A header is accepted when its source is the host and its destination a
//!   controller (`0x50`, `0x11`, `0x21`..`0x2A`) and, in the long form, its length is the
//!   identifier's (or at most 255 for an identifier this simulator does not know, which is
//!   consumed and ignored). Anything else drops its first byte and the rest is scanned again.
//!   A partial message idle for [`IDLE_TIMEOUT_S`] is dropped. Unknown and unsupported
//!   messages are ignored without a reply, as the controllers do.
//! * **Identity.** `HW_GET_INFO` (84 bytes): the serial number (K10CR1 `55xxxxxx`, KDC101
//!   `27xxxxxx`), the model string, the hardware type, firmware, notes, the stage identifier at
//!   offset 76 (KDC101: 6 = PRM1-Z8, pylablib's table) and one channel.
//! * **Counter and datum.** The counter reads 0 at power-on wherever the mechanism is (a random
//!   angle); moves work before homing, relative to that zero. `MOT_MOVE_HOME` turns in reverse
//!   at the homing velocity to the home switch (the index), then forward by the home offset,
//!   zeroes the counter there and answers `MOT_MOVE_HOMED`. The counter is never wrapped:
//!   a rotation mount turns without end.
//! * **Moves.** `MOT_MOVE_ABSOLUTE` / `MOT_MOVE_RELATIVE` (long form with a distance, or short
//!   form using the stored `MOT_SET_MOVEABSPARAMS` / `MOT_SET_MOVERELPARAMS`) and single-step
//!   `MOT_MOVE_JOG` run a trapezoid at the velocity parameters and end with
//!   `MOT_MOVE_COMPLETED` carrying a status update; continuous jogs and `MOT_MOVE_VELOCITY` run
//!   until `MOT_MOVE_STOP`, which decelerates (profiled) or halts (immediate) and ends with
//!   `MOT_MOVE_STOPPED`. A motion command during a motion replaces it. A disabled channel
//!   ignores motion commands.
//! * **Status.** `MOT_REQ_STATUSBITS`, `MOT_REQ_POSCOUNTER`, `MOT_REQ_ENCCOUNTER` on both
//!   models; the K10CR1 answers `MOT_REQ_STATUSUPDATE` (position, encoder count, status) and
//!   the KDC101 `MOT_REQ_DCSTATUSUPDATE` (position, velocity, status); the other model's request
//!   is ignored. Bits: moving forward/reverse, jogging, homing, homed, enabled, motor connected,
//!   the reverse limit (the home switch, lit within [`HOME_SWITCH_DEG`] of the index), and on
//!   the DC servo tracking and settled. After `HW_START_UPDATEMSGS` the model's status update
//!   is sent every [`UPDATE_INTERVAL_S`] until `HW_STOP_UPDATEMSGS` (the keep-alive
//!   `MOT_ACK_DCSTATUSUPDATE` is accepted and not required).
//! * **Scales** (pylablib, from the manuals): K10CR1 409600/3 microsteps per degree, velocity
//!   units 53.68 per microstep/s, acceleration units 53.68 * 204.94e-6 per microstep/s^2;
//!   PRM1Z8 1919.6418 counts per degree, velocity units `T * 65536` per count/s and acceleration
//!   units `T^2 * 65536` per count/s^2 with `T = 2048 / 6e6` s. `MOT_SET_VELPARAMS` is capped at
//!   the mount's top speed ([`AptSimConfig::max_velocity_deg_s`]).
//! * **Faults.** Replies (not unsolicited updates) may be dropped, corrupted or duplicated; a
//!   stall ends a move half way with `MOT_MOVE_STOPPED` and the motion-error bit; a
//!   spontaneous reset (rolled when a motion command arrives; the command is lost) and a power
//!   cycle forget the datum, the counter, the settings and the update messages; over the
//!   thermal duty a motion command is refused (the over-temperature bit, no motion, no reply).
//!   The protocol has no busy reply: `spurious_busy` and `quick_move_to_zero` do not apply.

use crate::faults::{Dice, DutyCycle, FaultProfile};
use crate::motion::{output_from_motor, Profile};
use crate::simulator::{next_request, Scan, SimDialect, Simulator, Truth};
use polar_apt_protocol::{self as id, le_i32, le_u16, Message, HOST, USB};
use std::f64::consts::TAU;

/// A partial message idle this long (simulated seconds) is dropped.
pub const IDLE_TIMEOUT_S: f64 = 0.1;
/// The interval of unsolicited status updates after `HW_START_UPDATEMSGS`, seconds.
pub const UPDATE_INTERVAL_S: f64 = 0.1;
/// The home switch (the reverse limit bit) is lit within this angle of the index, degrees.
pub const HOME_SWITCH_DEG: f64 = 0.5;
/// The KDC101's time unit, seconds.
const KDC101_T_S: f64 = 2048.0 / 6.0e6;

/// Status bits (the protocol's `P_MOT_SB_*`), as the driver's codec declares them.
pub use polar_apt_protocol::status as bits;

/// Which mount.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AptSimModel {
    /// K10CR1 stepper rotation mount.
    K10cr1,
    /// PRM1Z8 rotation stage on a KDC101.
    Prm1z8,
}

/// The simulator of an APT `model` (`k10cr1`, `prm1z8`) at the real mount's speeds, for the
/// simulators' table (`crate::sim::SIMULATORS`); `None` for another model.
pub fn simulate(
    model: &str,
    faults: FaultProfile,
    seed: u64,
) -> Option<Box<dyn crate::simulator::Simulator>> {
    let model = AptSimModel::parse(model).ok()?;
    Some(Box::new(AptDevice::new(
        AptSimConfig::of(model),
        faults,
        seed,
    )))
}

/// The simulator of an APT `model` moving and homing at `deg_s` ([`AptSimConfig::fast`]),
/// capped at [`AptSimConfig::max_protocol_velocity_deg_s`] (the K10CR1's 32-bit velocity
/// parameter holds at most 293 deg/s), for the simulators' table; `None` for another model.
pub fn simulate_at_speed(
    model: &str,
    deg_s: f64,
    faults: FaultProfile,
    seed: u64,
) -> Option<Box<dyn crate::simulator::Simulator>> {
    let model = AptSimModel::parse(model).ok()?;
    let config = AptSimConfig::of(model);
    let deg_s = deg_s.min(config.max_protocol_velocity_deg_s());
    Some(Box::new(AptDevice::new(config.fast(deg_s), faults, seed)))
}

impl AptSimModel {
    /// The model by its CLI name (`k10cr1`, `prm1z8`); an error names the allowed values.
    pub fn parse(name: &str) -> Result<Self, String> {
        match name.to_ascii_lowercase().as_str() {
            "k10cr1" => Ok(AptSimModel::K10cr1),
            "prm1z8" => Ok(AptSimModel::Prm1z8),
            _ => Err(format!(
                "--model {name:?} is not an APT model: allowed k10cr1, prm1z8"
            )),
        }
    }

    /// The controller's model string.
    pub fn controller(self) -> &'static str {
        match self {
            AptSimModel::K10cr1 => "K10CR1",
            AptSimModel::Prm1z8 => "KDC101",
        }
    }

    fn is_dc(self) -> bool {
        self == AptSimModel::Prm1z8
    }

    fn velocity_units(self) -> f64 {
        match self {
            AptSimModel::K10cr1 => 53.68,
            AptSimModel::Prm1z8 => KDC101_T_S * 65_536.0,
        }
    }

    fn acceleration_units(self) -> f64 {
        match self {
            AptSimModel::K10cr1 => 53.68 * 204.94e-6,
            AptSimModel::Prm1z8 => KDC101_T_S * KDC101_T_S * 65_536.0,
        }
    }
}

/// What the simulated mount is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AptSimConfig {
    /// The model.
    pub model: AptSimModel,
    /// Serial number.
    pub serial: u32,
    /// Position counts per degree.
    pub counts_per_deg: f64,
    /// Velocity at power-on, deg/s.
    pub velocity_deg_s: f64,
    /// Acceleration at power-on, deg/s^2.
    pub acceleration_deg_s2: f64,
    /// The top speed `MOT_SET_VELPARAMS` is capped at, deg/s.
    pub max_velocity_deg_s: f64,
    /// Homing velocity at power-on, deg/s.
    pub home_velocity_deg_s: f64,
    /// Backlash between motor and output, counts.
    pub backlash_counts: f64,
    /// Encoder noise (standard deviation) on every position read, counts.
    pub encoder_noise_counts: f64,
    /// Probability per reply that an unsolicited status update precedes it.
    pub unsolicited_status: f64,
}

impl AptSimConfig {
    /// A K10CR1: 409600/3 microsteps per degree, 10 deg/s and 10 deg/s^2 (its top speed and
    /// Kinesis' defaults), homing at 10 deg/s, 0.02 deg of worm backlash, an exact microstep
    /// counter (no encoder).
    pub fn k10cr1() -> Self {
        let cpd = 409_600.0 / 3.0;
        AptSimConfig {
            model: AptSimModel::K10cr1,
            serial: 55_000_123,
            counts_per_deg: cpd,
            velocity_deg_s: 10.0,
            acceleration_deg_s2: 10.0,
            max_velocity_deg_s: 10.0,
            home_velocity_deg_s: 10.0,
            backlash_counts: 0.02 * cpd,
            encoder_noise_counts: 0.0,
            unsolicited_status: 0.0,
        }
    }

    /// A PRM1Z8 on a KDC101: 1919.6418 counts per degree, 10 deg/s and 10 deg/s^2 (Kinesis'
    /// defaults; top speed 25 deg/s), homing at 10 deg/s, 2 counts of backlash, 0.5 count of
    /// servo dither on the encoder.
    pub fn prm1z8() -> Self {
        AptSimConfig {
            model: AptSimModel::Prm1z8,
            serial: 27_000_456,
            counts_per_deg: 1_919.641_857_862_339,
            velocity_deg_s: 10.0,
            acceleration_deg_s2: 10.0,
            max_velocity_deg_s: 25.0,
            home_velocity_deg_s: 10.0,
            backlash_counts: 2.0,
            encoder_noise_counts: 0.5,
            unsolicited_status: 0.0,
        }
    }

    /// The healthy default of `model`.
    pub fn of(model: AptSimModel) -> Self {
        match model {
            AptSimModel::K10cr1 => Self::k10cr1(),
            AptSimModel::Prm1z8 => Self::prm1z8(),
        }
    }

    /// The largest velocity `MOT_SET_VELPARAMS`' signed 32-bit field expresses for the model
    /// (with its acceleration, ten times the velocity, well inside its field), deg/s: K10CR1
    /// 293.0, PRM1Z8 50 000.
    pub fn max_protocol_velocity_deg_s(&self) -> f64 {
        f64::from(i32::MAX) / (self.counts_per_deg * self.model.velocity_units())
    }

    /// A faster mount for tests and demos (not a real mount's speed): `deg_s` velocity,
    /// homing and cap, reached in 0.1 s.
    pub fn fast(mut self, deg_s: f64) -> Self {
        self.velocity_deg_s = deg_s;
        self.max_velocity_deg_s = deg_s;
        self.home_velocity_deg_s = deg_s;
        self.acceleration_deg_s2 = deg_s * 10.0;
        self
    }
}

/// What a motion is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    /// A move or single-step jog: ends with `MOT_MOVE_COMPLETED`.
    Move { jog: bool },
    /// Homing: ends with `MOT_MOVE_HOMED` and zeroes the counter.
    Home,
    /// A continuous motion or one being stopped: ends with `MOT_MOVE_STOPPED`.
    Stopping { jog: bool, home: bool },
    /// A stall: ends with `MOT_MOVE_STOPPED` and the motion-error bit.
    Stall,
}

#[derive(Debug, Clone, Copy)]
struct Motion {
    profile: Profile,
    kind: Kind,
}

/// The settings a power cycle restores.
#[derive(Debug, Clone, Copy)]
struct Settings {
    min_velocity: i32,
    acceleration: i32,
    max_velocity: i32,
    jog_mode: u16,
    jog_step: i32,
    jog_min_velocity: i32,
    jog_acceleration: i32,
    jog_max_velocity: i32,
    jog_stop_mode: u16,
    backlash: i32,
    home_dir: u16,
    limit_switch: u16,
    home_velocity: i32,
    home_offset: i32,
    rel_distance: i32,
    abs_position: i32,
}

/// A simulated K10CR1 or PRM1Z8/KDC101.
pub struct AptDevice {
    config: AptSimConfig,
    faults: FaultProfile,
    dice: Dice,
    duty: DutyCycle,
    pending: Vec<u8>,
    last_byte_s: f64,
    /// Motor position, counts (the counter's frame).
    motor: f64,
    /// The last direction of motion (+1/-1), for backlash.
    direction: f64,
    /// The mechanism's angle at counter 0, degrees.
    zero_deg: f64,
    motion: Option<Motion>,
    homed: bool,
    enabled: bool,
    motion_error: bool,
    overtemp: bool,
    updates_at: Option<f64>,
    settings: Settings,
}

/// The data length of a long-form host message, if this simulator knows it.
fn host_long_len(msg: u16) -> Option<usize> {
    Some(match msg {
        id::MOT_SET_ENCCOUNTER
        | id::MOT_SET_POSCOUNTER
        | id::MOT_SET_GENMOVEPARAMS
        | id::MOT_SET_MOVERELPARAMS
        | id::MOT_SET_MOVEABSPARAMS
        | id::MOT_MOVE_RELATIVE
        | id::MOT_MOVE_ABSOLUTE => 6,
        id::MOT_SET_VELPARAMS | id::MOT_SET_HOMEPARAMS => 14,
        id::MOT_SET_JOGPARAMS => 22,
        _ => return None,
    })
}

/// One message from the host.
struct Request {
    msg: u16,
    p2: u8,
    data: Option<Vec<u8>>,
}

fn scan(buf: &[u8]) -> Scan<Request> {
    if buf.len() < 6 {
        return Scan::NeedMore;
    }
    let msg = u16::from_le_bytes([buf[0], buf[1]]);
    let long = buf[4] & 0x80 != 0;
    let dest = buf[4] & 0x7F;
    let dest_ok = dest == USB || dest == 0x11 || (0x21..=0x2A).contains(&dest);
    if !dest_ok || buf[5] != HOST {
        return Scan::Skip;
    }
    if !long {
        if host_long_len(msg).is_some()
            && msg != id::MOT_MOVE_ABSOLUTE
            && msg != id::MOT_MOVE_RELATIVE
        {
            return Scan::Skip;
        }
        return Scan::Complete(
            Request {
                msg,
                p2: buf[3],
                data: None,
            },
            6,
        );
    }
    let length = usize::from(u16::from_le_bytes([buf[2], buf[3]]));
    match host_long_len(msg) {
        Some(n) if n != length => return Scan::Skip,
        None if length > 255 => return Scan::Skip,
        _ => {}
    }
    if buf.len() < 6 + length {
        return Scan::NeedMore;
    }
    Scan::Complete(
        Request {
            msg,
            p2: 0,
            data: Some(buf[6..6 + length].to_vec()),
        },
        6 + length,
    )
}

fn short(msg: u16, p1: u8, p2: u8) -> Vec<u8> {
    Message::short(msg, p1, p2).sent_by_controller().encode()
}

fn long(msg: u16, data: &[u8]) -> Vec<u8> {
    Message::long(msg, data.to_vec())
        .sent_by_controller()
        .encode()
}

fn chan_then(values: &[i32]) -> Vec<u8> {
    let mut d = 1u16.to_le_bytes().to_vec();
    for v in values {
        d.extend_from_slice(&v.to_le_bytes());
    }
    d
}

impl AptDevice {
    /// A mount at power-on: a random angle, counter 0, not homed, channel enabled.
    pub fn new(config: AptSimConfig, faults: FaultProfile, seed: u64) -> Self {
        let mut d = AptDevice {
            config,
            faults,
            dice: Dice::new(seed),
            duty: DutyCycle::default(),
            pending: Vec::new(),
            last_byte_s: 0.0,
            motor: 0.0,
            direction: 1.0,
            zero_deg: 0.0,
            motion: None,
            homed: false,
            enabled: true,
            motion_error: false,
            overtemp: false,
            updates_at: None,
            settings: Self::defaults(&config),
        };
        d.power_on();
        d
    }

    fn defaults(c: &AptSimConfig) -> Settings {
        let v = |deg_s: f64| (deg_s * c.counts_per_deg * c.model.velocity_units()).round() as i32;
        let a = (c.acceleration_deg_s2 * c.counts_per_deg * c.model.acceleration_units()).round()
            as i32;
        Settings {
            min_velocity: 0,
            acceleration: a,
            max_velocity: v(c.velocity_deg_s),
            jog_mode: 2,
            jog_step: (5.0 * c.counts_per_deg).round() as i32,
            jog_min_velocity: 0,
            jog_acceleration: a,
            jog_max_velocity: v(c.velocity_deg_s),
            jog_stop_mode: 2,
            backlash: 0,
            home_dir: 2,
            limit_switch: 1,
            home_velocity: v(c.home_velocity_deg_s),
            home_offset: 0,
            rel_distance: 0,
            abs_position: 0,
        }
    }

    fn power_on(&mut self) {
        self.zero_deg = self.dice.uniform() * 360.0;
        self.reset_state();
    }

    /// Forgets the counter, datum, settings and update messages; the mechanism stays where it
    /// physically is.
    fn reset_state(&mut self) {
        self.motor = 0.0;
        self.motion = None;
        self.homed = false;
        self.enabled = true;
        self.motion_error = false;
        self.updates_at = None;
        self.pending.clear();
        self.settings = Self::defaults(&self.config);
    }

    /// Whether the datum is set.
    pub fn homed(&self) -> bool {
        self.homed
    }

    fn motor_at(&self, now_s: f64) -> f64 {
        self.motion
            .map_or(self.motor, |m| m.profile.position(now_s))
    }

    fn moving(&self, now_s: f64) -> bool {
        self.motion.is_some_and(|m| now_s < m.profile.end_s())
    }

    /// The output's true angle, degrees (unwrapped).
    pub fn true_output_deg(&self, now_s: f64) -> f64 {
        let dir = self
            .motion
            .map_or(self.direction, |m| m.profile.direction());
        let out = output_from_motor(self.motor_at(now_s), dir, self.config.backlash_counts);
        self.zero_deg + out / self.config.counts_per_deg
    }

    /// The counter as reported: rounded, with encoder noise.
    fn reported(&mut self, now_s: f64) -> i32 {
        let noise = self.config.encoder_noise_counts * self.dice.normal();
        (self.motor_at(now_s) + noise)
            .round()
            .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
    }

    fn velocity_counts_s(&self, now_s: f64) -> f64 {
        self.motion.map_or(0.0, |m| m.profile.velocity(now_s))
    }

    fn status_bits(&self, now_s: f64) -> u32 {
        let mut s = bits::CONNECTED;
        if self.enabled {
            s |= bits::ENABLED;
        }
        if self.homed {
            s |= bits::HOMED;
        }
        if self.motion_error {
            s |= bits::MOTION_ERROR;
        }
        if self.overtemp {
            s |= bits::OVERTEMP;
        }
        let moving = self.moving(now_s);
        if let Some(m) = self.motion.filter(|_| moving) {
            let fwd = m.profile.direction() > 0.0;
            let jog = matches!(
                m.kind,
                Kind::Move { jog: true } | Kind::Stopping { jog: true, .. }
            );
            let home = matches!(m.kind, Kind::Home | Kind::Stopping { home: true, .. });
            s |= match (jog, fwd) {
                (true, true) => bits::JOGGING_FWD,
                (true, false) => bits::JOGGING_REV,
                (false, true) => bits::MOVING_FWD,
                (false, false) => bits::MOVING_REV,
            };
            if home {
                s |= bits::HOMING;
            }
        } else if self.config.model.is_dc() && self.enabled {
            s |= bits::SETTLED;
        }
        if self.config.model.is_dc() && self.enabled && !self.motion_error {
            s |= bits::TRACKING;
        }
        let off = self.true_output_deg(now_s).rem_euclid(360.0);
        if off.min(360.0 - off) <= HOME_SWITCH_DEG {
            s |= bits::REV_LIMIT;
        }
        s
    }

    /// The model's 14-byte status update (also a completion's data).
    fn status_data(&mut self, now_s: f64) -> Vec<u8> {
        let p = self.reported(now_s);
        let s = self.status_bits(now_s);
        let mut d = 1u16.to_le_bytes().to_vec();
        d.extend_from_slice(&p.to_le_bytes());
        if self.config.model.is_dc() {
            let v = self
                .velocity_counts_s(now_s)
                .round()
                .clamp(-32768.0, 32767.0) as i16;
            d.extend_from_slice(&v.to_le_bytes());
            d.extend_from_slice(&0u16.to_le_bytes());
        } else {
            d.extend_from_slice(&p.to_le_bytes());
        }
        d.extend_from_slice(&s.to_le_bytes());
        d
    }

    fn status_update(&mut self, now_s: f64) -> Vec<u8> {
        let msg = if self.config.model.is_dc() {
            id::MOT_GET_DCSTATUSUPDATE
        } else {
            id::MOT_GET_STATUSUPDATE
        };
        let d = self.status_data(now_s);
        long(msg, &d)
    }

    /// A reply through the reply faults, perhaps preceded by an unsolicited status update.
    fn reply(&mut self, now_s: f64, bytes: Vec<u8>) -> Vec<u8> {
        let mut out = Vec::new();
        if self.dice.chance(self.config.unsolicited_status) {
            out.extend(self.status_update(now_s));
        }
        out.extend(self.dice.reply_faults(&self.faults, bytes));
        out
    }

    fn velocity(&self, units: i32) -> f64 {
        (f64::from(units) / self.config.model.velocity_units()).max(1.0)
    }

    fn acceleration(&self, units: i32) -> f64 {
        (f64::from(units) / self.config.model.acceleration_units()).max(1.0)
    }

    /// Starts a motion to `target` counts at the move velocity (or `v`, `a`).
    fn start(&mut self, now_s: f64, target: f64, kind: Kind, v: f64, a: f64) {
        let start = self.motor_at(now_s);
        let profile = Profile {
            start,
            target,
            t0_s: now_s,
            v,
            a,
        };
        self.duty.record(now_s, profile.end_s());
        self.motion_error = false;
        self.motion = Some(Motion { profile, kind });
    }

    /// Rolls the motion faults for a motion command; `false` if the command is lost or refused.
    fn motion_allowed(&mut self, now_s: f64) -> bool {
        if !self.enabled {
            return false;
        }
        if self.dice.chance(self.faults.spontaneous_reset) {
            let out = self.true_output_deg(now_s);
            self.reset_state();
            self.zero_deg = out;
            return false;
        }
        self.overtemp = self.duty.too_hot(&self.faults, now_s);
        !self.overtemp
    }

    fn move_to(&mut self, now_s: f64, target: f64, jog: bool) {
        if !self.motion_allowed(now_s) {
            return;
        }
        let s = self.settings;
        let (v, a) = if jog {
            (
                self.velocity(s.jog_max_velocity),
                self.acceleration(s.jog_acceleration),
            )
        } else {
            (
                self.velocity(s.max_velocity),
                self.acceleration(s.acceleration),
            )
        };
        let start = self.motor_at(now_s);
        if self.dice.chance(self.faults.stall) {
            self.start(now_s, start + (target - start) / 2.0, Kind::Stall, v, a);
        } else {
            self.start(now_s, target, Kind::Move { jog }, v, a);
        }
    }

    fn home(&mut self, now_s: f64) {
        if !self.motion_allowed(now_s) {
            return;
        }
        let here = self.motor_at(now_s);
        let cpd = self.config.counts_per_deg;
        // The index is where the mechanism's angle is 0; homing turns toward it in reverse
        // (home_dir 2) or forward (1), then by the offset.
        let angle = (self.zero_deg + here / cpd).rem_euclid(360.0);
        let to_index = if self.settings.home_dir == 1 {
            (360.0 - angle).rem_euclid(360.0)
        } else {
            -angle
        };
        let target = here + to_index * cpd + f64::from(self.settings.home_offset);
        let v = self.velocity(self.settings.home_velocity);
        let a = self.acceleration(self.settings.acceleration);
        self.start(now_s, target, Kind::Home, v, a);
    }

    fn stop(&mut self, now_s: f64, immediate: bool) {
        let Some(m) = self.motion else { return };
        let home = matches!(m.kind, Kind::Home | Kind::Stopping { home: true, .. });
        let jog = matches!(
            m.kind,
            Kind::Move { jog: true } | Kind::Stopping { jog: true, .. }
        );
        let profile = if immediate {
            let x = m.profile.position(now_s);
            Profile {
                start: x,
                target: x,
                t0_s: now_s,
                v: 1.0,
                a: 1.0,
            }
        } else {
            m.profile.stopped_at(now_s)
        };
        self.motion = Some(Motion {
            profile,
            kind: Kind::Stopping { jog, home },
        });
    }

    /// Ends a motion: its message, the counter zeroed after homing.
    fn finish(&mut self, now_s: f64, m: Motion) -> Vec<u8> {
        self.motor = m.profile.target;
        self.direction = m.profile.direction();
        match m.kind {
            Kind::Home => {
                self.zero_deg =
                    (self.zero_deg + self.motor / self.config.counts_per_deg).rem_euclid(360.0);
                self.motor = 0.0;
                self.homed = true;
                let bytes = short(id::MOT_MOVE_HOMED, 1, 0);
                self.reply(now_s, bytes)
            }
            Kind::Move { .. } => {
                let d = self.status_data(now_s);
                self.reply(now_s, long(id::MOT_MOVE_COMPLETED, &d))
            }
            Kind::Stall | Kind::Stopping { .. } => {
                self.motion_error = matches!(m.kind, Kind::Stall);
                let d = self.status_data(now_s);
                self.reply(now_s, long(id::MOT_MOVE_STOPPED, &d))
            }
        }
    }

    fn info(&self) -> Vec<u8> {
        let mut d = vec![0u8; 84];
        d[..4].copy_from_slice(&self.config.serial.to_le_bytes());
        let model = self.config.model.controller().as_bytes();
        d[4..4 + model.len()].copy_from_slice(model);
        let (hw_type, notes, stage): (u16, &[u8], u16) = match self.config.model {
            AptSimModel::K10cr1 => (16, b"K10CR1 rotation mount", 0),
            AptSimModel::Prm1z8 => (16, b"DC servo K-Cube PRM1-Z8", 6),
        };
        d[12..14].copy_from_slice(&hw_type.to_le_bytes());
        // Firmware 3.0.12 (minor, interim, major, unused).
        d[14..18].copy_from_slice(&[12, 0, 3, 0]);
        d[18..18 + notes.len()].copy_from_slice(notes);
        d[76..78].copy_from_slice(&stage.to_le_bytes());
        d[78..80].copy_from_slice(&1u16.to_le_bytes());
        d[80..82].copy_from_slice(&0u16.to_le_bytes());
        d[82..84].copy_from_slice(&1u16.to_le_bytes());
        long(id::HW_GET_INFO, &d)
    }

    fn execute(&mut self, now_s: f64, r: Request) -> Vec<u8> {
        let data = r.data.clone().unwrap_or_default();
        let s = self.settings;
        let motion_busy = self.moving(now_s);
        match r.msg {
            id::HW_REQ_INFO => {
                let b = self.info();
                self.reply(now_s, b)
            }
            id::HW_START_UPDATEMSGS => {
                self.updates_at = Some(now_s + UPDATE_INTERVAL_S);
                Vec::new()
            }
            id::HW_STOP_UPDATEMSGS => {
                self.updates_at = None;
                Vec::new()
            }
            id::HW_DISCONNECT
            | id::HW_NO_FLASH_PROGRAMMING
            | id::MOD_IDENTIFY
            | id::MOT_ACK_DCSTATUSUPDATE => Vec::new(),
            id::MOD_SET_CHANENABLESTATE => {
                match r.p2 {
                    1 => self.enabled = true,
                    2 => {
                        self.enabled = false;
                        self.stop(now_s, true);
                    }
                    _ => {}
                }
                Vec::new()
            }
            id::MOD_REQ_CHANENABLESTATE => {
                let b = short(
                    id::MOD_GET_CHANENABLESTATE,
                    1,
                    if self.enabled { 1 } else { 2 },
                );
                self.reply(now_s, b)
            }
            id::MOT_REQ_POSCOUNTER | id::MOT_REQ_ENCCOUNTER => {
                let p = self.reported(now_s);
                let reply = if r.msg == id::MOT_REQ_POSCOUNTER {
                    id::MOT_GET_POSCOUNTER
                } else {
                    id::MOT_GET_ENCCOUNTER
                };
                self.reply(now_s, long(reply, &chan_then(&[p])))
            }
            id::MOT_SET_POSCOUNTER | id::MOT_SET_ENCCOUNTER if !motion_busy => {
                let new = f64::from(le_i32(&data, 2));
                self.zero_deg += (self.motor - new) / self.config.counts_per_deg;
                self.motor = new;
                Vec::new()
            }
            id::MOT_SET_VELPARAMS => {
                let cap = (self.config.max_velocity_deg_s
                    * self.config.counts_per_deg
                    * self.config.model.velocity_units())
                .round() as i32;
                self.settings.min_velocity = le_i32(&data, 2).max(0);
                self.settings.acceleration = le_i32(&data, 6).max(1);
                self.settings.max_velocity = le_i32(&data, 10).clamp(1, cap);
                Vec::new()
            }
            id::MOT_REQ_VELPARAMS => {
                let d = chan_then(&[s.min_velocity, s.acceleration, s.max_velocity]);
                self.reply(now_s, long(id::MOT_GET_VELPARAMS, &d))
            }
            id::MOT_SET_JOGPARAMS => {
                self.settings.jog_mode = le_u16(&data, 2);
                self.settings.jog_step = le_i32(&data, 4);
                self.settings.jog_min_velocity = le_i32(&data, 8);
                self.settings.jog_acceleration = le_i32(&data, 12).max(1);
                self.settings.jog_max_velocity = le_i32(&data, 16).max(1);
                self.settings.jog_stop_mode = le_u16(&data, 20);
                Vec::new()
            }
            id::MOT_REQ_JOGPARAMS => {
                let mut d = 1u16.to_le_bytes().to_vec();
                d.extend_from_slice(&s.jog_mode.to_le_bytes());
                for v in [
                    s.jog_step,
                    s.jog_min_velocity,
                    s.jog_acceleration,
                    s.jog_max_velocity,
                ] {
                    d.extend_from_slice(&v.to_le_bytes());
                }
                d.extend_from_slice(&s.jog_stop_mode.to_le_bytes());
                self.reply(now_s, long(id::MOT_GET_JOGPARAMS, &d))
            }
            id::MOT_REQ_STATUSBITS => {
                let b = self.status_bits(now_s);
                self.reply(now_s, long(id::MOT_GET_STATUSBITS, &chan_then(&[b as i32])))
            }
            id::MOT_SET_GENMOVEPARAMS => {
                self.settings.backlash = le_i32(&data, 2);
                Vec::new()
            }
            id::MOT_REQ_GENMOVEPARAMS => self.reply(
                now_s,
                long(id::MOT_GET_GENMOVEPARAMS, &chan_then(&[s.backlash])),
            ),
            id::MOT_SET_HOMEPARAMS => {
                let dir = le_u16(&data, 2);
                self.settings.home_dir = if dir == 1 { 1 } else { 2 };
                self.settings.limit_switch = le_u16(&data, 4);
                self.settings.home_velocity = le_i32(&data, 6).max(1);
                self.settings.home_offset = le_i32(&data, 10);
                Vec::new()
            }
            id::MOT_REQ_HOMEPARAMS => {
                let mut d = 1u16.to_le_bytes().to_vec();
                d.extend_from_slice(&s.home_dir.to_le_bytes());
                d.extend_from_slice(&s.limit_switch.to_le_bytes());
                d.extend_from_slice(&s.home_velocity.to_le_bytes());
                d.extend_from_slice(&s.home_offset.to_le_bytes());
                self.reply(now_s, long(id::MOT_GET_HOMEPARAMS, &d))
            }
            id::MOT_SET_MOVERELPARAMS => {
                self.settings.rel_distance = le_i32(&data, 2);
                Vec::new()
            }
            id::MOT_REQ_MOVERELPARAMS => {
                let d = chan_then(&[s.rel_distance]);
                self.reply(now_s, long(id::MOT_GET_MOVERELPARAMS, &d))
            }
            id::MOT_SET_MOVEABSPARAMS => {
                self.settings.abs_position = le_i32(&data, 2);
                Vec::new()
            }
            id::MOT_REQ_MOVEABSPARAMS => {
                let d = chan_then(&[s.abs_position]);
                self.reply(now_s, long(id::MOT_GET_MOVEABSPARAMS, &d))
            }
            id::MOT_MOVE_HOME => {
                self.home(now_s);
                Vec::new()
            }
            id::MOT_MOVE_ABSOLUTE => {
                let target = match r.data {
                    Some(_) => le_i32(&data, 2),
                    None => s.abs_position,
                };
                self.move_to(now_s, f64::from(target), false);
                Vec::new()
            }
            id::MOT_MOVE_RELATIVE => {
                let distance = match r.data {
                    Some(_) => le_i32(&data, 2),
                    None => s.rel_distance,
                };
                let target = self.motor_at(now_s).round() + f64::from(distance);
                self.move_to(now_s, target, false);
                Vec::new()
            }
            id::MOT_MOVE_JOG => {
                let sign = if r.p2 == 2 { -1.0 } else { 1.0 };
                if s.jog_mode == 1 {
                    self.continuous(now_s, sign, true);
                } else {
                    let target = self.motor_at(now_s).round() + sign * f64::from(s.jog_step);
                    self.move_to(now_s, target, true);
                }
                Vec::new()
            }
            id::MOT_MOVE_VELOCITY => {
                let sign = if r.p2 == 2 { -1.0 } else { 1.0 };
                self.continuous(now_s, sign, false);
                Vec::new()
            }
            id::MOT_MOVE_STOP => {
                self.stop(now_s, r.p2 == 1);
                Vec::new()
            }
            id::MOT_REQ_STATUSUPDATE if !self.config.model.is_dc() => {
                let b = self.status_update(now_s);
                self.reply(now_s, b)
            }
            id::MOT_REQ_DCSTATUSUPDATE if self.config.model.is_dc() => {
                let b = self.status_update(now_s);
                self.reply(now_s, b)
            }
            _ => Vec::new(),
        }
    }

    /// A motion that runs until stopped (a day at the velocity is as good as without end).
    fn continuous(&mut self, now_s: f64, sign: f64, jog: bool) {
        if !self.motion_allowed(now_s) {
            return;
        }
        let s = self.settings;
        let (v, a) = (
            self.velocity(s.max_velocity),
            self.acceleration(s.acceleration),
        );
        let target = self.motor_at(now_s) + sign * v * 86_400.0;
        self.start(now_s, target, Kind::Stopping { jog, home: false }, v, a);
    }

    fn idle_deadline(&self) -> Option<f64> {
        (!self.pending.is_empty()).then_some(self.last_byte_s + IDLE_TIMEOUT_S)
    }
}

impl Simulator for AptDevice {
    fn describe(&self) -> String {
        match self.config.model {
            AptSimModel::K10cr1 => format!("apt K10CR1 serial {}", self.config.serial),
            AptSimModel::Prm1z8 => format!("apt PRM1Z8 on KDC101 serial {}", self.config.serial),
        }
    }

    fn baud(&self) -> u32 {
        115_200
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        let mut out = self.tick(now_s);
        self.pending.extend_from_slice(bytes);
        if !bytes.is_empty() {
            self.last_byte_s = now_s;
        }
        while let Some((r, _)) = next_request(&mut self.pending, scan) {
            out.extend(self.execute(now_s, r));
        }
        // An immediate stop ends the motion at once.
        out.extend(self.tick(now_s));
        out
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = Vec::new();
        loop {
            let due = [
                self.motion.map(|m| m.profile.end_s()),
                self.updates_at,
                self.idle_deadline(),
            ];
            let Some(t) = due
                .into_iter()
                .flatten()
                .filter(|&t| t <= now_s)
                .reduce(f64::min)
            else {
                break;
            };
            if self.idle_deadline() == Some(t) {
                self.pending.clear();
            } else if self.updates_at == Some(t) {
                self.updates_at = Some(t + UPDATE_INTERVAL_S);
                out.extend(self.status_update(t));
            } else if let Some(m) = self.motion.take() {
                out.extend(self.finish(t, m));
            }
        }
        out
    }

    fn next_event_s(&self) -> Option<f64> {
        let due = [
            self.motion.map(|m| m.profile.end_s()),
            self.updates_at,
            self.idle_deadline(),
        ];
        due.into_iter().flatten().reduce(f64::min)
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        // The FTDI bridge does not reset the controller on open: nothing is waiting.
        Vec::new()
    }

    fn power_cycle(&mut self, now_s: f64) {
        let out = self.true_output_deg(now_s);
        self.reset_state();
        self.zero_deg = out;
    }

    fn truth(&self, now_s: f64) -> Truth {
        let a = self.true_output_deg(now_s).to_radians().rem_euclid(TAU);
        Truth::Angle {
            output_rad: if (0.0..TAU).contains(&a) { a } else { 0.0 },
            moving: self.moving(now_s),
        }
    }
}

/// The apt dialect's simulators (`polar_drivers::apt::DIALECT`'s models), for
/// [`crate::sim::SIMULATORS`].
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::apt::DIALECT.name,
    models: polar_drivers::apt::DIALECT.models,
    build: simulate,
    at_speed: Some(simulate_at_speed),
    on_bus: None,
    motion: None,
};

#[cfg(test)]
#[path = "apt_tests.rs"]
mod tests;
