//! Thorlabs Elliptec ELLx devices simulated at the byte level (`docs/DEVICES.md` section 1.1):
//! the ELL14 and ELL18 rotation mounts and the ELL6 and ELL9 indexed sliders. The host sends
//! `A cc [data]` without a terminator, the device answers `A CC data\r\n`; the reply to a
//! motion command (and to a frequency search) is held back until it ends.
//!
//! **Defaults are the healthy device**: a client written for the real module, that has never
//! seen this simulator, works unchanged (`docs/DEVICES-conformance.md` runs public client
//! libraries against it). Quirks that a real module shows only now and then are fault knobs
//! in [`FaultProfile`], off by default.
//!
//! Behaviour, with its source where there is one; the rest are choices where the sources are
//! silent (a driver must not depend on those):
//! * **Counter at power-on.** The encoder is incremental: the position reads 0 wherever the
//!   mechanism happens to be at power-on (a random angle, or a random slot for a slider), and moves
//!   work before homing, relative to that arbitrary zero. Homing makes 0 the index (plus the home
//!   offset `so`) and reports `PO00000000` exactly.
//! * **Rotator positions** stay in `[0, PULSES)`: `ma` takes its target modulo a turn, and `mr`,
//!   `fw`, `bw` end wrapped into it. A move turns the way of the sign of the difference in those
//!   counts (no short-way logic: that is the driver's job, with `mr`). `ho0` homes in the positive
//!   direction, `ho1` in the negative one. The encoder noise is added after the wrap: a reading
//!   just below 0 is a small negative 32-bit two's complement number (`FFFFFFFF` for -1), which is
//!   how the manual defines positions and how clients parse them (pylablib `_from_steps_data`,
//!   thorlabs_elliptec `struct.unpack(">i")`), not the top of the turn.
//! * **Sliders** rest only in detents: slot `k` sits at `k * pitch` counts (ELL9: 0, 32, 64, 96;
//!   ELL6: 0, 31, as roesel/elliptec uses). `ma`/`mr` go to the nearest slot, `fw`/`bw` to the
//!   next/previous one, clamped at the ends (a null move answered `PO`). `ho` takes its direction
//!   digit as on every model (`ho0` and `ho1` both end on slot 0); `sj`, `so` and `st` are `GS03`.
//!   The `IN` travel field is the last slot's position in counts and the PULSES field is 0: the
//!   indexed sliders have no pulses-per-unit scale (a user's report of a real ELL6, followed for
//!   the ELL9 too; pylablib guards for it, `pulse/travel if pulse>0 else 1`; the protocol manual
//!   could not be checked for it: `docs/DEVICES-conformance.md`).
//! * **Parsing.** Every command has a fixed data length, the same on every model (the ELLx protocol
//!   manual's command table as reported to us: `ho` takes its direction digit on every model,
//!   sliders included, and every public client sends it): `ma`, `mr`, `sj`, `so` 8; `f1`, `b1`,
//!   `f2`, `b2` 4; `sv` 2; `ho`, `ca` 1; `in`, `gs`, `gp`, `fw`, `bw`, `gj`, `go`, `gv`, `st`,
//!   `us`, `i1`, `i2`, `s1`, `s2` none. A command starts with an upper-case hex address, then a
//!   lower-case letter, then a lower-case letter or digit; a byte that cannot continue the command
//!   drops the first pending byte and the rest is scanned again (resynchronisation: a client's
//!   trailing CR LF is skipped so). Data bytes must be hex digits (any other byte there drops the
//!   command silently); lower-case digits `a`-`f` are consumed but the command is answered `GS04`.
//!   An unknown command (`i3`, `xx`) takes no data and is answered `GS03`. A partial command idle
//!   for [`IDLE_TIMEOUT_S`] or more is dropped and answered `GS01` if it was for this address.
//! * **Status.** An error reply (`GS` with a code other than `00` and `09`) latches its code; `gs`
//!   returns the latched code and clears it, else `09` while busy, else `00`. Busy is a state, not
//!   an error: a `GS09` refusal is not latched, so `gs` reads `00` once the module is idle (clients
//!   poll `gs` until it is no longer busy). `gs`, `gp`, `in`, `gv`, `gj`, `go`, `i1`, `i2`, `sv`,
//!   `sj`, `so` and `st` are answered while busy; motion commands, frequency commands, `ca` and
//!   `us` are `GS09` then.
//! * **Settings.** `sv` 1..=100 %, `sj` 1..=PULSES counts (an eighth of a turn at power-on), `so`
//!   0..=PULSES/4, `ho` data `0`/`1`, motor periods `f1`/`b1`/`f2`/`b2` nonzero; anything else
//!   `GS04`. Homing lasts `homing_s` or the trapezoid to the index, whichever is longer.
//! * **Motors.** Every model answers `i1` and `i2` (two resonant motors; `i3` is GS03): loop on,
//!   motor on, current 0.4 A (0x02EA = 746 of 1866 per ampere), ramps `FFFF`, and the forward and
//!   backward periods (frequency = 14.74 MHz / period; at power-on motor 1 0x0091/0x0088, motor 2
//!   0x0093/0x008C, about 100 kHz). A frequency search (`s1`, `s2`) holds its `GS00` for
//!   `frequency_search_s` and restores that motor's power-on periods; the mechanism does not move
//!   (a real one may move slightly).
//! * **Stop** (`st`, rotators) answers `GS00` at once; the held move reply then comes when the
//!   mechanism has decelerated, as `PO` with where it stopped (a stopped homing leaves the datum
//!   unset).
//! * **Faults.** A stall (moves only, not homing) ends half way with the held reply `GS02`; the
//!   quick-move fault ([`FaultProfile::quick_move_to_zero`], off by default) sends
//!   `ma`/`mr`/`fw`/`bw` to position 0, answered `PO` with no error, when they arrive less than
//!   [`QUICK_MOVE_S`] after the previous motion ended; a spontaneous reset (rolled when a motion
//!   command would start the motor, which browns the controller out: that command is lost,
//!   unanswered; queries never reset) and a power cycle forget the datum, the held reply, the
//!   address change, the velocity, jog step, home offset and motor periods (`us` answers `GS00` but
//!   nothing is kept in flash). Unsolicited lines are `BS00` or `BO` with the position, with equal
//!   odds, before the reply of a command for this address.

use crate::faults::{Dice, DutyCycle, FaultProfile};
use crate::motion::{output_from_motor, Profile};
use crate::simulator::{next_request, Scan, SimDialect, Simulator, Truth};
use std::f64::consts::TAU;

/// A partial command idle this long (simulated seconds) is dropped and answered `GS01`.
pub const IDLE_TIMEOUT_S: f64 = 0.05;
/// With [`FaultProfile::quick_move_to_zero`], a move command arriving sooner than this after the
/// previous motion ended may move to 0 instead (pylablib's `_pre_move_delay`: "if the move
/// command is issued too soon after a previous one, it can move to 0 instead").
pub const QUICK_MOVE_S: f64 = 0.1;
/// Motor periods at power-on, (forward, backward) for motors 1 and 2; frequency = 14.74 MHz /
/// period (pylablib `get_motor_info`).
pub const MOTOR_PERIODS: [(u16, u16); 2] = [(0x0091, 0x0088), (0x0093, 0x008C)];
/// The `I1`/`I2` current field: 746 / 1866 per ampere = 0.4 A.
const MOTOR_CURRENT: u16 = 0x02EA;
/// A slider is on a slot when within this many counts of it (roesel/elliptec).
pub const SLOT_TOLERANCE_COUNTS: f64 = 5.0;

/// `GS` status codes used here.
const OK: u8 = 0x00;
const COMM_TIMEOUT: u8 = 0x01;
const MECH_TIMEOUT: u8 = 0x02;
const COMMAND_ERROR: u8 = 0x03;
const OUT_OF_RANGE: u8 = 0x04;
const THERMAL: u8 = 0x08;
const BUSY: u8 = 0x09;

/// Which Elliptec device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ElliptecModel {
    /// ELL14 rotation mount.
    Ell14,
    /// ELL18 rotation stage.
    Ell18,
    /// ELL6 two-position slider.
    Ell6,
    /// ELL9 four-position slider.
    Ell9,
}

impl ElliptecModel {
    /// The type byte of the `IN` reply: `0E`, `12`, `06`, `09`.
    pub fn type_code(self) -> u8 {
        match self {
            ElliptecModel::Ell14 => 0x0E,
            ElliptecModel::Ell18 => 0x12,
            ElliptecModel::Ell6 => 0x06,
            ElliptecModel::Ell9 => 0x09,
        }
    }

    /// Whether it is a rotation mount.
    pub fn is_rotator(self) -> bool {
        matches!(self, ElliptecModel::Ell14 | ElliptecModel::Ell18)
    }

    /// A slider's slots (ELL6 2, ELL9 4); 0 for a rotator.
    pub fn slots(self) -> usize {
        match self {
            ElliptecModel::Ell6 => 2,
            ElliptecModel::Ell9 => 4,
            _ => 0,
        }
    }
}

/// What the simulated device is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ElliptecConfig {
    /// The model.
    pub model: ElliptecModel,
    /// Bus address at power-on, 0..=15 (higher bits are ignored).
    pub address: u8,
    /// Counts per turn (rotators, reported as the `IN` PULSES field) or per slot pitch (sliders,
    /// whose `IN` PULSES field is 0).
    pub pulses: u32,
    /// Serial number (its last 8 decimal digits are reported).
    pub serial: u32,
    /// Velocity at 100 %, counts/s.
    pub max_velocity_counts_per_s: f64,
    /// Acceleration, counts/s^2.
    pub acceleration_counts_per_s2: f64,
    /// The least time homing takes (the index search), seconds.
    pub homing_s: f64,
    /// Backlash between motor and output, counts.
    pub backlash_counts: f64,
    /// Encoder noise (standard deviation) on every position read, counts.
    pub encoder_noise_counts: f64,
    /// How long a frequency search (`s1`, `s2`) lasts, seconds (pylablib allows 10).
    pub frequency_search_s: f64,
    /// Probability per command for this address that an unsolicited `BS`/`BO` line precedes
    /// the reply.
    pub unsolicited_status: f64,
}

impl ElliptecConfig {
    /// A rotation mount: 430 deg/s at 100 %, 50 ms ramps, 1 s homing, 10 counts backlash,
    /// 0.5 count encoder noise, 2 s frequency search.
    fn rotator(model: ElliptecModel, pulses: u32, serial: u32) -> Self {
        let v = 430.0 / 360.0 * pulses as f64;
        ElliptecConfig {
            model,
            address: 0,
            pulses,
            serial,
            max_velocity_counts_per_s: v,
            acceleration_counts_per_s2: v / 0.05,
            homing_s: 1.0,
            backlash_counts: 10.0,
            encoder_noise_counts: 0.5,
            frequency_search_s: 2.0,
            unsolicited_status: 0.0,
        }
    }

    /// A slider: three slot pitches per second, 0.1 s ramps, 1 s homing, exact detents.
    fn slider(model: ElliptecModel, pitch: u32, serial: u32) -> Self {
        let v = 3.0 * pitch as f64;
        ElliptecConfig {
            max_velocity_counts_per_s: v,
            acceleration_counts_per_s2: v / 0.1,
            backlash_counts: 0.0,
            encoder_noise_counts: 0.0,
            ..Self::rotator(model, pitch, serial)
        }
    }

    /// An ELL14 rotation mount: 143360 counts per turn (what real units report).
    pub fn ell14() -> Self {
        Self::rotator(ElliptecModel::Ell14, 143_360, 11_400_001)
    }

    /// An ELL18 rotation stage: 262144 counts per turn.
    pub fn ell18() -> Self {
        Self::rotator(ElliptecModel::Ell18, 262_144, 11_800_001)
    }

    /// An ELL9 four-position slider: slots at 0, 32, 64, 96 counts.
    pub fn ell9() -> Self {
        Self::slider(ElliptecModel::Ell9, 32, 10_900_001)
    }

    /// An ELL6 two-position slider: slots at 0 and 31 counts.
    pub fn ell6() -> Self {
        Self::slider(ElliptecModel::Ell6, 31, 10_600_001)
    }
}

/// A motion in progress; its reply is held until `end_s`.
#[derive(Debug, Clone, Copy)]
struct Motion {
    profile: Profile,
    end_s: f64,
    /// A homing (not stopped): sets the datum when it ends.
    home: bool,
    /// Cut half way: the reply is `GS02`.
    stalled: bool,
    /// A frequency search, not a motion: the held reply is `GS00`.
    search: bool,
}

/// The value of an upper-case hex digit.
fn hex_digit(b: u8) -> Option<u8> {
    match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'A'..=b'F' => Some(b - b'A' + 10),
        _ => None,
    }
}

/// A 32-bit two's complement value as 8 upper-case hex digits.
fn hex32(v: i64) -> String {
    format!("{:08X}", v as u32)
}

/// The data length of a known command (the same on every model); `None` for an unknown one.
fn data_len(cc: [u8; 2]) -> Option<usize> {
    match &cc {
        b"ma" | b"mr" | b"sj" | b"so" => Some(8),
        b"f1" | b"b1" | b"f2" | b"b2" => Some(4),
        b"sv" => Some(2),
        b"ca" | b"ho" => Some(1),
        b"in" | b"gs" | b"gp" | b"fw" | b"bw" | b"gj" | b"go" | b"gv" | b"st" | b"us" | b"i1"
        | b"i2" | b"s1" | b"s2" => Some(0),
        _ => None,
    }
}

/// Whether `buf` starts with a complete command, a prefix of one, or a byte to skip.
fn scan(buf: &[u8]) -> Scan<()> {
    // Until both command letters are in, any length will do: only the prefix is checked.
    let cc = [1, 2].map(|i| buf.get(i).copied().unwrap_or(b'?'));
    let n = 3 + data_len(cc).unwrap_or(0);
    for (i, &b) in buf.iter().enumerate().take(n) {
        let fits = match i {
            0 => hex_digit(b).is_some(),
            1 => b.is_ascii_lowercase(),
            2 => b.is_ascii_lowercase() || b.is_ascii_digit(),
            _ => b.is_ascii_hexdigit(),
        };
        if !fits {
            return Scan::Skip;
        }
    }
    if buf.len() >= n {
        Scan::Complete((), n)
    } else {
        Scan::NeedMore
    }
}

/// The simulated device.
#[derive(Debug, Clone)]
pub struct ElliptecDevice {
    config: ElliptecConfig,
    faults: FaultProfile,
    dice: Dice,
    address: u8,
    /// Bytes of a command not yet complete.
    pending: Vec<u8>,
    last_byte_s: f64,
    velocity_percent: u8,
    jog_counts: i64,
    home_offset_counts: i64,
    /// Reported position when idle, counts.
    pos: f64,
    /// The physical motor position (counts from the index) that reads 0.
    origin: f64,
    /// Direction of the last motion (+1 / -1).
    direction: f64,
    homed: bool,
    latched: u8,
    motion: Option<Motion>,
    last_end_s: Option<f64>,
    duty: DutyCycle,
    /// (forward, backward) period of motors 1 and 2.
    periods: [(u16, u16); 2],
}

impl ElliptecDevice {
    /// A device at power-on (unhomed, at a random angle or slot, reading 0 there), faults from
    /// `faults`, all randomness from `seed`.
    pub fn new(config: ElliptecConfig, faults: FaultProfile, seed: u64) -> Self {
        let mut dev = ElliptecDevice {
            config,
            faults,
            dice: Dice::new(seed),
            address: 0,
            pending: Vec::new(),
            last_byte_s: 0.0,
            velocity_percent: 100,
            jog_counts: 0,
            home_offset_counts: 0,
            pos: 0.0,
            origin: 0.0,
            direction: 1.0,
            homed: false,
            latched: OK,
            motion: None,
            last_end_s: None,
            duty: DutyCycle::default(),
            periods: MOTOR_PERIODS,
        };
        dev.power_on();
        dev
    }

    /// The bus address now (after any `ca`).
    pub fn address(&self) -> u8 {
        self.address
    }

    /// Whether the device has a datum (homed since power-on or reset).
    pub fn homed(&self) -> bool {
        self.homed
    }

    /// Whether a motion or a frequency search is in progress at `now_s`.
    pub fn busy(&self, now_s: f64) -> bool {
        self.motion.is_some_and(|m| now_s < m.end_s)
    }

    /// Whether the mechanism is moving at `now_s` (a frequency search keeps it still).
    fn moving(&self, now_s: f64) -> bool {
        self.motion.is_some_and(|m| !m.search && now_s < m.end_s)
    }

    /// The motion in progress, if it moves the mechanism.
    fn mechanical(&self) -> Option<Motion> {
        self.motion.filter(|m| !m.search)
    }

    /// The output's true position in counts from the index at `now_s` (what the optics see):
    /// the motor lagged by half the backlash, without encoder noise.
    pub fn true_output_counts(&self, now_s: f64) -> f64 {
        let direction = self
            .mechanical()
            .map_or(self.direction, |m| m.profile.direction());
        output_from_motor(
            self.position_now(now_s) + self.origin,
            direction,
            self.config.backlash_counts,
        )
    }

    /// Counts per turn (rotators) or per slot pitch (sliders), at least 1.
    fn span(&self) -> f64 {
        self.config.pulses.max(1) as f64
    }

    fn power_on(&mut self) {
        let span = self.span();
        let physical = if self.config.model.is_rotator() {
            (self.dice.uniform() * span).floor()
        } else {
            self.dice.index(self.config.model.slots()) as f64 * span
        };
        self.reset_state(physical);
    }

    /// Forgets everything not mechanical; the counter reads 0 at `physical`.
    fn reset_state(&mut self, physical: f64) {
        if let Some(m) = self.motion.take().filter(|m| !m.search) {
            self.direction = m.profile.direction();
        }
        self.address = self.config.address & 0x0F;
        self.pending.clear();
        self.velocity_percent = 100;
        self.jog_counts = i64::from(self.config.pulses.max(8) / 8);
        self.home_offset_counts = 0;
        self.pos = 0.0;
        self.origin = physical;
        self.homed = false;
        self.latched = OK;
        self.last_end_s = None;
        self.periods = MOTOR_PERIODS;
    }

    fn position_now(&self, now_s: f64) -> f64 {
        self.motion.map_or(self.pos, |m| m.profile.position(now_s))
    }

    /// The encoder reading of a position: wrapped into a turn on rotators, then noisy (so an
    /// error just below 0 reads as a small negative number).
    fn reported(&mut self, pos: f64) -> i64 {
        let noisy = self.wrap(pos) + self.config.encoder_noise_counts * self.dice.normal();
        noisy.round().clamp(i32::MIN as f64, i32::MAX as f64) as i64
    }

    /// A position wrapped into `[0, PULSES)` on a rotator; unchanged on a slider.
    fn wrap(&self, x: f64) -> f64 {
        if !self.config.model.is_rotator() {
            return x;
        }
        let w = x.rem_euclid(self.span());
        if w < self.span() {
            w
        } else {
            0.0
        }
    }

    /// One reply line from the current address, through the reply faults.
    fn line(&mut self, cc: &str, data: &str) -> Vec<u8> {
        let bytes = format!("{:X}{cc}{data}\r\n", self.address).into_bytes();
        self.dice.reply_faults(&self.faults, bytes)
    }

    /// A `GS` reply; an error (a code other than `00` and `09`) is latched until `gs` reads it.
    fn status(&mut self, code: u8) -> Vec<u8> {
        if code != OK && code != BUSY {
            self.latched = code;
        }
        self.line("GS", &format!("{code:02X}"))
    }

    fn idle_deadline(&self) -> Option<f64> {
        (!self.pending.is_empty()).then_some(self.last_byte_s + IDLE_TIMEOUT_S)
    }

    /// Drops the idle partial command; `GS01` if it was for this address.
    fn time_out(&mut self) -> Vec<u8> {
        let ours = self.pending.first().and_then(|&b| hex_digit(b)) == Some(self.address);
        self.pending.clear();
        if ours {
            self.status(COMM_TIMEOUT)
        } else {
            Vec::new()
        }
    }

    /// The held reply of a motion that ended.
    fn finish(&mut self, m: Motion) -> Vec<u8> {
        if m.search {
            return self.status(OK);
        }
        self.direction = m.profile.direction();
        self.last_end_s = Some(m.end_s);
        if m.home {
            self.origin = self.wrap(self.origin + m.profile.target);
            self.pos = 0.0;
            self.homed = true;
            return self.line("PO", &hex32(0));
        }
        self.pos = self.wrap(m.profile.target);
        if m.stalled {
            self.status(MECH_TIMEOUT)
        } else {
            let p = self.reported(self.pos);
            self.line("PO", &hex32(p))
        }
    }

    /// A complete command: ignored unless for this address.
    fn execute(&mut self, now_s: f64, cmd: &[u8]) -> Vec<u8> {
        let (Some(&a), Some(&c0), Some(&c1)) = (cmd.first(), cmd.get(1), cmd.get(2)) else {
            return Vec::new();
        };
        if hex_digit(a) != Some(self.address) {
            return Vec::new();
        }
        let mut out = Vec::new();
        if self.dice.chance(self.config.unsolicited_status) {
            if self.dice.chance(0.5) {
                out.extend(self.line("BS", "00"));
            } else {
                let p = self.reported(self.position_now(now_s));
                out.extend(self.line("BO", &hex32(p)));
            }
        }
        let motion = matches!(&[c0, c1], b"ma" | b"mr" | b"ho" | b"fw" | b"bw");
        if motion && self.dice.chance(self.faults.spontaneous_reset) {
            // The motor's start browns the controller out: the command is lost, unanswered.
            let physical = self.position_now(now_s) + self.origin;
            self.reset_state(physical);
            return out;
        }
        out.extend(self.command(now_s, [c0, c1], cmd.get(3..).unwrap_or(&[])));
        out
    }

    fn command(&mut self, now_s: f64, cc: [u8; 2], data: &[u8]) -> Vec<u8> {
        if data.iter().any(|&b| hex_digit(b).is_none()) {
            return self.status(OUT_OF_RANGE);
        }
        let value = data.iter().fold(0u32, |v, &b| {
            v.wrapping_shl(4) | u32::from(hex_digit(b).unwrap_or(0))
        });
        let signed = i64::from(value as i32);
        let rotator = self.config.model.is_rotator();
        let span = i64::from(self.config.pulses.max(1));
        let busy = self.busy(now_s);
        match &cc {
            b"in" => self.line("IN", &self.info()),
            b"gs" => {
                let code = match self.latched {
                    OK if busy => BUSY,
                    code => code,
                };
                self.latched = OK;
                self.line("GS", &format!("{code:02X}"))
            }
            b"gp" => {
                let p = self.reported(self.position_now(now_s));
                self.line("PO", &hex32(p))
            }
            b"ma" | b"mr" | b"ho" | b"fw" | b"bw" => self.motion_command(now_s, cc, value, busy),
            b"i1" | b"i2" => {
                let (forward, backward) = self.periods[usize::from(cc[1] - b'1')];
                let data = format!("11{MOTOR_CURRENT:04X}FFFFFFFF{forward:04X}{backward:04X}");
                self.line(if cc[1] == b'1' { "I1" } else { "I2" }, &data)
            }
            b"f1" | b"b1" | b"f2" | b"b2" | b"s1" | b"s2" if busy => self.status(BUSY),
            b"f1" | b"b1" | b"f2" | b"b2" => {
                let motor = usize::from(cc[1] - b'1');
                let period = value as u16;
                self.set(period > 0, |d| match cc[0] {
                    b'f' => d.periods[motor].0 = period,
                    _ => d.periods[motor].1 = period,
                })
            }
            b"s1" | b"s2" => {
                let motor = usize::from(cc[1] - b'1');
                self.periods[motor] = MOTOR_PERIODS[motor];
                self.search(now_s)
            }
            b"sj" if rotator => self.set((1..=span).contains(&signed), |d| d.jog_counts = signed),
            b"gj" => {
                let jog = if rotator { self.jog_counts } else { span };
                self.line("GJ", &hex32(jog))
            }
            // ELL14 limits the home offset to a quarter turn (rwpeterson).
            b"so" if rotator => self.set((0..=span / 4).contains(&signed), |d| {
                d.home_offset_counts = signed
            }),
            b"go" => self.line("HO", &hex32(self.home_offset_counts)),
            b"sv" => self.set((1..=100).contains(&value), |d| {
                d.velocity_percent = value as u8
            }),
            b"gv" => self.line("GV", &format!("{:02X}", self.velocity_percent)),
            b"st" if rotator => {
                if let Some(m) = self.motion.as_mut() {
                    if now_s < m.end_s {
                        m.profile = m.profile.stopped_at(now_s);
                        m.end_s = m.profile.end_s();
                        m.home = false;
                    }
                }
                self.status(OK)
            }
            b"ca" | b"us" if busy => self.status(BUSY),
            b"ca" => self.set(true, |d| d.address = (value & 0x0F) as u8),
            b"us" => self.status(OK),
            _ => self.status(COMMAND_ERROR),
        }
    }

    /// A setting: applied and `GS00` if `valid`, else `GS04`.
    fn set(&mut self, valid: bool, apply: impl FnOnce(&mut Self)) -> Vec<u8> {
        if !valid {
            return self.status(OUT_OF_RANGE);
        }
        apply(self);
        self.status(OK)
    }

    /// The `IN` data: type, serial, year, firmware, hardware, travel, pulses (30 chars). The
    /// indexed sliders report PULSES 0.
    fn info(&self) -> String {
        let c = self.config;
        let (travel, pulses) = if c.model.is_rotator() {
            (360, c.pulses)
        } else {
            let last = c.model.slots().saturating_sub(1) as u64;
            (u64::from(c.pulses) * last, 0)
        };
        let (kind, serial) = (c.model.type_code(), c.serial % 100_000_000);
        // Year 2023, firmware 17, hardware 01 (metric thread), as on a real ELL14.
        format!(
            "{kind:02X}{serial:08}20231701{:04X}{pulses:08X}",
            travel.min(0xFFFF)
        )
    }

    /// Starts a frequency search: busy for `frequency_search_s`, the mechanism still, then the
    /// held `GS00`.
    fn search(&mut self, now_s: f64) -> Vec<u8> {
        let profile = Profile {
            start: self.pos,
            target: self.pos,
            t0_s: now_s,
            v: 1.0,
            a: 1.0,
        };
        self.motion = Some(Motion {
            profile,
            end_s: now_s + self.config.frequency_search_s.max(0.0),
            home: false,
            stalled: false,
            search: true,
        });
        Vec::new()
    }

    fn motion_command(&mut self, now_s: f64, cc: [u8; 2], value: u32, busy: bool) -> Vec<u8> {
        let rotator = self.config.model.is_rotator();
        if &cc == b"ho" && value > 1 {
            return self.status(OUT_OF_RANGE);
        }
        if busy || self.dice.chance(self.faults.spurious_busy) {
            return self.status(BUSY);
        }
        if self.duty.too_hot(&self.faults, now_s) {
            return self.status(THERMAL);
        }
        let span = self.span();
        let physical = self.pos + self.origin;
        if &cc == b"ho" {
            let home = self.home_offset_counts as f64;
            let target = if !rotator {
                -self.origin
            } else if value == 0 {
                self.pos + (home - physical).rem_euclid(span)
            } else {
                self.pos - (physical - home).rem_euclid(span)
            };
            return self.start(now_s, target, true);
        }
        let quick = self
            .last_end_s
            .is_some_and(|end| now_s - end < QUICK_MOVE_S)
            && self.dice.chance(self.faults.quick_move_to_zero);
        let signed = f64::from(value as i32);
        let jog = self.jog_counts as f64;
        let target = if rotator {
            match &cc {
                _ if quick => 0.0,
                b"ma" => signed.rem_euclid(span),
                b"mr" => self.pos + signed,
                b"fw" => self.pos + jog,
                _ => self.pos - jog,
            }
        } else {
            let here = (physical / span).round() * span - self.origin;
            let wanted = match &cc {
                _ if quick => 0.0,
                b"ma" => signed,
                b"mr" => self.pos + signed,
                b"fw" => here + span,
                _ => here - span,
            };
            let last = self.config.model.slots().saturating_sub(1) as f64;
            ((wanted + self.origin) / span).round().clamp(0.0, last) * span - self.origin
        };
        self.start(now_s, target, false)
    }

    /// Starts a motion whose reply is held; a stall fault (moves only) cuts it half way.
    fn start(&mut self, now_s: f64, target: f64, home: bool) -> Vec<u8> {
        let c = self.config;
        let v = c.max_velocity_counts_per_s * f64::from(self.velocity_percent) / 100.0;
        let mut profile = Profile {
            start: self.pos,
            target,
            t0_s: now_s,
            v: v.max(1e-9),
            a: c.acceleration_counts_per_s2.max(1e-9),
        };
        let stalled = !home && self.dice.chance(self.faults.stall);
        if stalled {
            profile.target = (profile.start + target) / 2.0;
        }
        let mut end_s = profile.end_s();
        if home {
            end_s = end_s.max(now_s + c.homing_s.max(0.0));
        }
        self.duty.record(now_s, end_s);
        self.motion = Some(Motion {
            profile,
            end_s,
            home,
            stalled,
            search: false,
        });
        Vec::new()
    }
}

impl Simulator for ElliptecDevice {
    fn describe(&self) -> String {
        format!(
            "elliptec ELL{} serial {:08} at address {:X}",
            self.config.model.type_code(),
            self.config.serial % 100_000_000,
            self.address
        )
    }

    fn baud(&self) -> u32 {
        9_600
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        let mut out = self.tick(now_s);
        for &b in bytes {
            self.pending.push(b);
            self.last_byte_s = now_s;
            while let Some(((), cmd)) = next_request(&mut self.pending, scan) {
                out.extend(self.execute(now_s, &cmd));
            }
        }
        // A stop may end the motion at once.
        out.extend(self.tick(now_s));
        out
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = Vec::new();
        loop {
            let motion = self.motion.map(|m| m.end_s).filter(|&t| t <= now_s);
            let idle = self.idle_deadline().filter(|&t| t <= now_s);
            match (motion, idle) {
                (Some(m), Some(i)) if i < m => out.extend(self.time_out()),
                (Some(_), _) => {
                    if let Some(m) = self.motion.take() {
                        out.extend(self.finish(m));
                    }
                }
                (None, Some(_)) => out.extend(self.time_out()),
                (None, None) => break,
            }
        }
        out
    }

    fn next_event_s(&self) -> Option<f64> {
        let due = [self.motion.map(|m| m.end_s), self.idle_deadline()];
        due.into_iter().flatten().reduce(f64::min)
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        // The interface board's FT230X does not reset the modules on open: no banner.
        Vec::new()
    }

    fn power_cycle(&mut self, _now_s: f64) {
        self.power_on();
    }

    fn truth(&self, now_s: f64) -> Truth {
        let output = self.true_output_counts(now_s);
        let moving = self.moving(now_s);
        let span = self.span();
        if self.config.model.is_rotator() {
            let a = output.rem_euclid(span) / span * TAU;
            Truth::Angle {
                output_rad: if (0.0..TAU).contains(&a) { a } else { 0.0 },
                moving,
            }
        } else {
            let s = (output / span).round();
            let on = !moving
                && (output - s * span).abs() <= SLOT_TOLERANCE_COUNTS
                && s >= 0.0
                && s < self.config.model.slots() as f64;
            Truth::Slot {
                slot: on.then_some(s as usize),
            }
        }
    }
}

/// The elliptec dialect's simulators (`polar_drivers::elliptec::DIALECT`'s models), for
/// [`crate::sim::SIMULATORS`].
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::elliptec::DIALECT.name,
    models: polar_drivers::elliptec::DIALECT.models,
    build: |model, faults, seed| {
        let config = match model {
            "ell14" => ElliptecConfig::ell14(),
            "ell18" => ElliptecConfig::ell18(),
            "ell6" => ElliptecConfig::ell6(),
            "ell9" => ElliptecConfig::ell9(),
            _ => return None,
        };
        Some(Box::new(ElliptecDevice::new(config, faults, seed)))
    },
    at_speed: None,
    on_bus: None,
    motion: None,
};

#[cfg(test)]
mod tests {
    use super::*;
    type C = ElliptecConfig;

    /// An ELL14 without encoder noise (exact reply bytes), seed 1.
    fn ell14(faults: FaultProfile) -> ElliptecDevice {
        let mut c = C::ell14();
        c.encoder_noise_counts = 0.0;
        ElliptecDevice::new(c, faults, 1)
    }

    /// A device without faults.
    fn fresh(c: ElliptecConfig, seed: u64) -> ElliptecDevice {
        ElliptecDevice::new(c, FaultProfile::default(), seed)
    }

    fn faults(set: impl FnOnce(&mut FaultProfile)) -> FaultProfile {
        let mut f = FaultProfile::default();
        set(&mut f);
        f
    }

    fn text(bytes: &[u8]) -> String {
        String::from_utf8_lossy(bytes).into_owned()
    }

    /// Sends each `command -> reply lines` exchange (separated by `;` or newlines) at `t` and
    /// checks the exact bytes said (each reply line ends in CRLF).
    fn script(d: &mut ElliptecDevice, t: f64, exchanges: &str) {
        for x in exchanges.split([';', '\n']) {
            let Some((cmd, want)) = x.split_once("->") else {
                continue;
            };
            let want = want
                .split_whitespace()
                .fold(String::new(), |s, r| s + r + "\r\n");
            assert_eq!(text(&d.receive(t, cmd.trim().as_bytes())), want, "{cmd}");
        }
    }

    /// Sends a motion command at `t` and runs to its end: (held reply, end time).
    fn run(d: &mut ElliptecDevice, t: f64, cmd: &str) -> (String, f64) {
        let r = text(&d.receive(t, cmd.as_bytes()));
        match d.next_event_s() {
            Some(end) if r.is_empty() => (text(&d.tick(end)), end),
            _ => (r, t),
        }
    }

    /// The position in a `0PO` line.
    fn po(line: &str) -> i64 {
        assert!(line.len() == 13 && line.starts_with("0PO"), "{line:?}");
        i64::from(u32::from_str_radix(&line[3..11], 16).unwrap())
    }

    /// The distance of a `0PO` line's position from `want`, modulo an ELL14 turn.
    fn po_off(line: &str, want: i64) -> i64 {
        let d = (po(line) - want).rem_euclid(143_360);
        d.min(143_360 - d)
    }

    /// Exact bytes: `in` (30 data chars: type, serial, year, firmware, hardware, travel, PULSES)
    /// for three models, `gs`, `gp` (0 at power-on); an unknown command GS03, latched for one
    /// `gs`; lower-case hex GS04; `sv`/`gv` (0 and 101 refused); commands for other addresses,
    /// line noise and a truncated command consumed silently; `ca` answered from the new
    /// address; a power cycle restores address and velocity and loses the datum.
    #[test]
    fn exact_reply_bytes() {
        let mut d = ell14(FaultProfile::default());
        let exchanges = "
            0in -> 0IN0E1140000120231701016800023000
            0gs -> 0GS00; 0gp -> 0PO00000000
            0xx -> 0GS03; 0gs -> 0GS03; 0gs -> 0GS00
            0ma0000a000 -> 0GS04
            0sv32 -> 0GS00; 0sv00 -> 0GS04; 0sv65 -> 0GS04; 0gv -> 0GV32
            1ma000010001gs1in ->; 0ma00000gp -> 0PO00000000
            0caa -> 0GS04; 0ca5 -> 5GS00; 0gs ->; 5gs -> 5GS04";
        script(&mut d, 0.0, exchanges);
        assert!(d.receive(0.0, b"\r\n\x00zzG0\xff").is_empty() && d.tick(1.0).is_empty());
        assert!(!d.busy(1.0) && d.next_event_s().is_none());
        assert_eq!(d.describe(), "elliptec ELL14 serial 11400001 at address 5");
        assert_eq!(run(&mut d, 1.0, "5ho0").0, "5PO00000000\r\n");
        d.power_cycle(5.0);
        assert!(!d.homed() && d.address() == 0 && d.baud() == 9600 && d.on_open(5.0).is_empty());
        script(&mut d, 5.0, "5gs ->; 0gv -> 0GV64; 0gp -> 0PO00000000");
        let mut d = fresh(C::ell18(), 2);
        script(&mut d, 0.0, "0in -> 0IN121180000120231701016800040000");
        let mut d = fresh(C::ell9(), 2);
        script(&mut d, 0.0, "0in -> 0IN091090000120231701006000000000");
    }

    /// Homing takes `homing_s` (1 s, longer than a turn) and reads exactly 0. `ma 0x2000`'s PO
    /// arrives only at the trapezoid's end (triangular: 2 sqrt(d/a); nothing 1e-4 s before),
    /// within 3 counts (6 sigma of the 0.5 count noise); meanwhile `gs` is 09 and another move
    /// GS09. The true angle lags by half the 10-count backlash (exact: no noise in the truth).
    /// `mr` takes negative two's complement and wraps into the turn. At 50 % the move from
    /// 0x22000 to 0x7000 (downwards: the sign of the difference) lasts the trapezoid at half
    /// velocity (1e-9 s: the same arithmetic). `st` answers GS00 and the held PO comes after
    /// braking, past the stop point and short of the target (by more than the 3-count noise).
    #[test]
    fn home_move_velocity_stop() {
        let c = ElliptecConfig::ell14();
        let mut d = fresh(c, 3);
        let (r, h) = run(&mut d, 0.0, "0ho0");
        assert!(
            r == "0PO00000000\r\n" && d.homed() && (h - 1.0).abs() < 1e-12,
            "{h}"
        );
        let t = h + 0.5;
        let dur = 2.0 * (8192.0 / c.acceleration_counts_per_s2).sqrt();
        script(&mut d, t, "0ma00002000 ->");
        script(&mut d, t + dur / 2.0, "0gs -> 0GS09; 0ma00001000 -> 0GS09");
        assert!(d.tick(t + dur - 1e-4).is_empty());
        assert!(po_off(&text(&d.tick(t + dur + 1e-9)), 0x2000) <= 3);
        let Truth::Angle { output_rad, moving } = d.truth(t + 1.0) else {
            panic!()
        };
        assert!(!moving && (output_rad - (8192.0 - 5.0) / 143_360.0 * TAU).abs() < 1e-9);
        let (r, e) = run(&mut d, t + 1.0, "0mrFFFFF000");
        assert!(po_off(&r, 0x1000) <= 3, "{r}");
        let (r, e) = run(&mut d, e + 0.5, "0mrFFFFE000");
        assert!(po_off(&r, 0x22000) <= 3, "{r}");
        let t = e + 0.5;
        script(&mut d, t, "0sv32 -> 0GS00; 0ma00007000 ->");
        let v = c.max_velocity_counts_per_s / 2.0;
        let a = c.acceleration_counts_per_s2;
        let slow = 2.0 * v / a + ((0x22000 - 0x7000) as f64 - v * v / a) / v;
        assert!((d.next_event_s().unwrap() - t - slow).abs() < 1e-9);
        let here = po(&text(&d.receive(t + slow / 2.0, b"0gp")));
        script(&mut d, t + slow / 2.0, "0st -> 0GS00");
        let end = d.next_event_s().unwrap();
        let stopped = po(&text(&d.tick(end)));
        assert!(end < t + slow && stopped < here - 3 && stopped > 0x7003);
    }

    /// One byte per call gives byte-identical output to the whole script in one call (same
    /// seed and times); bytes 40 ms apart still make a command; a partial command idle 50 ms
    /// is answered GS01 when `next_event_s` says (not 1 ms before), latched for one `gs`, and
    /// the next command works; a stale partial is dropped before new bytes are read; one for
    /// another address times out silently.
    #[test]
    fn chunking_and_idle_timeout() {
        let bytes = b"0in0gs0sv320gv0xx1gp0gs0maa00000000gp0ca30gs3gs3gp";
        let mut a = fresh(C::ell14(), 4);
        let mut b = a.clone();
        let whole = text(&a.receive(0.0, bytes));
        let pieces: Vec<u8> = bytes.iter().flat_map(|&x| b.receive(0.0, &[x])).collect();
        assert!(whole == text(&pieces) && whole.matches('\n').count() == 11);
        let mut d = ell14(FaultProfile::default());
        assert!(d.receive(0.0, b"0").is_empty() && d.receive(0.04, b"g").is_empty());
        script(&mut d, 0.08, "p -> 0PO00000000; 0m ->");
        let due = d.next_event_s().unwrap();
        assert!((due - 0.13).abs() < 1e-12 && d.tick(due - 1e-3).is_empty());
        assert_eq!(text(&d.tick(due)), "0GS01\r\n");
        script(
            &mut d,
            0.2,
            "0gp -> 0PO00000000; 0gs -> 0GS01; 0gs -> 0GS00; 0g ->",
        );
        script(&mut d, 0.26, "0gp -> 0GS01 0PO00000000; 1ma0 ->");
        assert!(d.tick(2.0).is_empty());
    }

    /// The quick-move fault injected (probability 1): a move 50 ms after the previous one ended
    /// goes to 0, answered `PO`; one 150 ms after does not; with the knob at 0 (the default)
    /// 50 ms is fine (positions within 3 counts, 6 sigma of the noise).
    #[test]
    fn quick_move_to_zero_fault() {
        for bug in [true, false] {
            let p = faults(|f| f.quick_move_to_zero = if bug { 1.0 } else { 0.0 });
            let mut d = ElliptecDevice::new(C::ell14(), p, 5);
            let (_, h) = run(&mut d, 0.0, "0ho0");
            let (r, e) = run(&mut d, h + 0.5, "0ma00002000");
            assert!(po_off(&r, 0x2000) <= 3, "{r}");
            let (r, e) = run(&mut d, e + 0.05, "0ma00004000");
            assert!(po_off(&r, if bug { 0 } else { 0x4000 }) <= 3, "{bug} {r}");
            let (r, _) = run(&mut d, e + 0.15, "0ma00004000");
            assert!(po_off(&r, 0x4000) <= 3, "{bug} {r}");
        }
    }

    /// Device faults: a stall ends half way with the held reply GS02 (position half way, exact
    /// without noise; `gs` 02 once); homing never stalls. 2 % duty: after the 1 s homing (10 %
    /// of the 10 s window) a move is GS08, 11 s later it runs. Spurious busy is GS09 at once. A
    /// spontaneous reset (on a motion command, which is lost) gives no notice: datum and address
    /// lost, position reads 0 where the mechanism stands (truth unchanged, exactly). Unsolicited
    /// BS00/BO lines precede replies, both kinds within 40 fair draws (each missing: probability
    /// 2^-40).
    #[test]
    fn device_faults() {
        let mut d = ell14(faults(|f| f.stall = 1.0));
        let (r, h) = run(&mut d, 0.0, "0ho0");
        assert_eq!(r, "0PO00000000\r\n");
        let (r, e) = run(&mut d, h + 0.5, "0ma00004000");
        assert_eq!(r, "0GS02\r\n");
        script(&mut d, e, "0gp -> 0PO00002000; 0gs -> 0GS02; 0gs -> 0GS00");
        let mut d = ell14(faults(|f| f.thermal_duty = 0.02));
        let (_, h) = run(&mut d, 0.0, "0ho0");
        script(&mut d, h + 0.2, "0ma00002000 -> 0GS08");
        assert_eq!(run(&mut d, h + 11.0, "0ma00002000").0, "0PO00002000\r\n");
        let mut d = ell14(faults(|f| f.spurious_busy = 1.0));
        script(&mut d, 0.0, "0ho0 -> 0GS09; 0mr00000010 -> 0GS09");
        let mut d = ell14(FaultProfile::default());
        let (_, h) = run(&mut d, 0.0, "0ho0");
        let (_, e) = run(&mut d, h + 0.5, "0ma00002000");
        script(&mut d, e, "0ca2 -> 2GS00");
        let before = d.truth(e);
        d.faults.spontaneous_reset = 1.0;
        script(&mut d, e, "2gs -> 2GS00");
        assert!(d.homed(), "a query never resets");
        assert!(run(&mut d, e + 0.2, "2ma00004000").0.is_empty());
        d.faults.spontaneous_reset = 0.0;
        assert!(!d.homed() && d.truth(e) == before);
        script(&mut d, e, "0gp -> 0PO00000000");
        d.config.unsolicited_status = 1.0;
        let mut seen = [0; 2];
        for _ in 0..40 {
            let r = text(&d.receive(e, b"0gs"));
            match r.strip_suffix("0GS00\r\n") {
                Some("0BS00\r\n") => seen[0] += 1,
                Some("0BO00000000\r\n") => seen[1] += 1,
                _ => panic!("{r:?}"),
            }
        }
        assert!(seen[0] > 0 && seen[1] > 0);
    }

    /// An ELL9: `ho0` ends on slot 0; `fw`/`bw` step one 32-count slot,
    /// clamped at the ends; `ma`/`mr` go to the nearest slot; the truth is the slot (exact: no
    /// noise or backlash), none while moving; `st`/`sj` are GS03; `gj` is the pitch. An ELL6's
    /// second slot is at 31.
    #[test]
    fn slider_slots() {
        let mut d = fresh(C::ell9(), 6);
        let mut t = 0.0;
        let steps =
            "0ho0 0 0, 0fw 20 1, 0ma00000055 60 3, 0fw 60 3, 0bw 40 2, 0mrFFFFFFE0 20 1, 0bw 0 0";
        for step in steps.split(", ") {
            let [cmd, pos, slot] = step.split(' ').collect::<Vec<_>>()[..] else {
                panic!()
            };
            let (r, e) = run(&mut d, t, cmd);
            assert_eq!(r, format!("0PO{pos:0>8}\r\n"), "{cmd}");
            let slot = slot.parse().ok();
            t = e + 0.2;
            assert_eq!(d.truth(t), Truth::Slot { slot }, "{cmd}");
        }
        script(
            &mut d,
            t,
            "0gj -> 0GJ00000020; 0st -> 0GS03; 0sj00000001 -> 0GS03; 0fw ->",
        );
        assert_eq!(d.truth(t + 0.01), Truth::Slot { slot: None });
        let mut d = fresh(C::ell6(), 6);
        let (_, e) = run(&mut d, 0.0, "0ho0");
        assert_eq!(run(&mut d, e + 0.2, "0ma0000001F").0, "0PO0000001F\r\n");
        assert_eq!(d.truth(e + 5.0), Truth::Slot { slot: Some(1) });
    }

    /// Same seed, same bytes (reply faults, stalls, resets, unsolicited lines and noise
    /// included); another seed differs.
    #[test]
    fn faults_are_reproducible() {
        let p = faults(|f| {
            (f.drop_reply, f.corrupt_reply, f.duplicate_reply) = (0.3, 0.1, 0.1);
            (f.stall, f.spontaneous_reset) = (0.3, 0.05);
        });
        let session = |seed| {
            let mut c = C::ell14();
            c.unsolicited_status = 0.2;
            let mut d = ElliptecDevice::new(c, p, seed);
            let mut out = Vec::new();
            for k in 0..60 {
                out.extend(d.receive(k as f64 * 0.5, b"0gs0gp0mr00001000"));
                out.extend(d.tick(k as f64 * 0.5 + 0.4));
            }
            out
        };
        assert_eq!(session(9), session(9));
        assert_ne!(session(9), session(10));
    }

    /// Random bytes (mostly the protocol's alphabet, half the time followed by a whole command),
    /// random chunks and times, power cycles, every device fault on, all four models: no panic
    /// and the truth in range; without reply faults every line is well formed (upper-case hex
    /// address, a known reply code with its fixed data length of upper-case hex, CRLF).
    #[test]
    fn random_bytes_never_panic() {
        let alphabet = b"0123456789ABCDEFabcdefghijklmnopqrstuvwxyz\r\n";
        let commands: Vec<&str> = "0gs 0gp 0in 0ho0 0ho1 0ho 0fw 0bw 0st 0gv 0sv32 0gj 0go 0us \
            0sj00001000 0so00000100 0ca1 1ca0 0ma00004000 0maFFFF0000 0mr80000000 0mr7FFFFFFF \
            0i1 0i2 0i3 0s1 0s2 0f10090 0b20000"
            .split_whitespace()
            .collect();
        let noisy = faults(|f| {
            (f.drop_reply, f.corrupt_reply, f.duplicate_reply) = (0.1, 0.1, 0.1);
            (f.spurious_busy, f.stall, f.spontaneous_reset) = (0.1, 0.2, 0.02);
            f.thermal_duty = 0.3;
        });
        let models = [C::ell14(), C::ell18(), C::ell6(), C::ell9()];
        let mut dice = Dice::new(42);
        for k in 0..8 {
            let (p, mut c) = ([noisy, FaultProfile::default()][k / 4], models[k % 4]);
            c.unsolicited_status = 0.1;
            let mut d = ElliptecDevice::new(c, p, u64::from(dice.byte()));
            let (mut t, mut out) = (0.0, Vec::new());
            for _ in 0..3000 {
                let mut bytes: Vec<u8> = (0..dice.index(8))
                    .map(|_| match dice.chance(0.8) {
                        true => alphabet[dice.index(alphabet.len())],
                        false => dice.byte(),
                    })
                    .collect();
                if dice.chance(0.5) {
                    bytes.extend(commands[dice.index(commands.len())].bytes());
                }
                t += dice.uniform() * 0.1;
                out.extend(d.receive(t, &bytes));
                if let Some(e) = d.next_event_s().filter(|_| dice.chance(0.3)) {
                    t = t.max(e);
                    out.extend(d.tick(t));
                }
                if dice.chance(0.002) {
                    d.power_cycle(t);
                }
                let ok = match d.truth(t) {
                    Truth::Angle { output_rad, .. } => (0.0..TAU).contains(&output_rad),
                    Truth::Slot { slot } => slot.is_none_or(|s| s < c.model.slots()),
                };
                assert!(ok, "{:?}", d.truth(t));
            }
            let all = String::from_utf8(out).unwrap_or_default();
            if p != FaultProfile::default() {
                continue;
            }
            assert!(all.matches("PO").count() > 50, "{all}");
            for l in all.split_terminator("\r\n").map(str::as_bytes) {
                let n = match l.get(1..3) {
                    Some(b"IN") => 30,
                    Some(b"I1" | b"I2") => 22,
                    Some(b"GS" | b"GV" | b"BS") => 2,
                    Some(b"PO" | b"GJ" | b"HO" | b"BO") => 8,
                    _ => panic!("{l:?}"),
                };
                let hex = |x: &u8| hex_digit(*x).is_some();
                assert!(l.len() == 3 + n && hex(&l[0]) && l[3..].iter().all(hex));
            }
            assert!(all.ends_with("\r\n"));
        }
    }

    // One test per defect a public client library met with the simulator
    // (docs/DEVICES-conformance.md).

    /// Defect 1: a move sent 50 ms after the previous move ended (clients such as
    /// thorlabs_elliptec send moves back to back) goes where asked on a default device: the
    /// move-to-0 is a fault knob, off by default. Positions within 3 counts (6 sigma of the 0.5
    /// count noise).
    #[test]
    fn back_to_back_moves_reach_their_targets() {
        let mut d = fresh(C::ell14(), 5);
        let (_, h) = run(&mut d, 0.0, "0ho0");
        let (r, e) = run(&mut d, h + 0.5, "0ma00004600");
        assert!(po_off(&r, 0x4600) <= 3, "{r}");
        let (r, e) = run(&mut d, e + 0.05, "0ma00008C00");
        assert!(po_off(&r, 0x8C00) <= 3, "{r}");
        let (r, _) = run(&mut d, e + 0.001, "0mr00001000");
        assert!(po_off(&r, 0x9C00) <= 3, "{r}");
    }

    /// Defect 2: `ho` takes one direction digit on every model, sliders included: `0ho0` (what
    /// clients and Thorlabs' examples send) and `0ho1` home an ELL6 and an ELL9 with one held
    /// `PO` and nothing else (no `GS01` for a stray digit); `0ho2` is out of range.
    #[test]
    fn slider_home_takes_a_direction_digit() {
        for c in [C::ell6(), C::ell9()] {
            let mut d = fresh(c, 7);
            let (r, e) = run(&mut d, 0.0, "0ho0");
            assert_eq!(r, "0PO00000000\r\n", "{:?}", c.model);
            assert!(d.tick(e + 1.0).is_empty() && d.next_event_s().is_none());
            let (r, e) = run(&mut d, e + 0.2, "0ho1");
            assert_eq!(r, "0PO00000000\r\n", "{:?}", c.model);
            script(&mut d, e + 0.2, "0ho2 -> 0GS04; 0gs -> 0GS04; 0gs -> 0GS00");
        }
    }

    /// Defect 3: `i1` and `i2` answer the motors' info (22 data characters: loop, motor,
    /// current, ramps, forward and backward periods) on every model; `i3` (no third motor) is
    /// GS03. `s1` (frequency search) holds its `GS00` for `frequency_search_s` (busy meanwhile:
    /// `gs` 09, a move GS09), then `i1` shows the searched periods; `f1`/`b1` set them.
    #[test]
    fn motor_info_and_frequency_search() {
        for c in [C::ell14(), C::ell18(), C::ell6(), C::ell9()] {
            let mut d = fresh(c, 8);
            script(
                &mut d,
                0.0,
                "0i1 -> 0I11102EAFFFFFFFF00910088; 0i2 -> 0I21102EAFFFFFFFF0093008C
                0i3 -> 0GS03; 0gs -> 0GS03",
            );
            script(&mut d, 0.1, "0f10080 -> 0GS00; 0b10099 -> 0GS00");
            script(&mut d, 0.1, "0i1 -> 0I11102EAFFFFFFFF00800099; 0s1 ->");
            let end = d.next_event_s().expect("the search's held reply");
            assert!((end - 0.1 - c.frequency_search_s).abs() < 1e-9, "{end}");
            script(&mut d, 0.2, "0gs -> 0GS09; 0ma00000000 -> 0GS09");
            assert!(d.tick(end - 1e-6).is_empty());
            assert_eq!(text(&d.tick(end)), "0GS00\r\n");
            script(
                &mut d,
                end,
                "0gs -> 0GS00; 0i1 -> 0I11102EAFFFFFFFF00910088",
            );
        }
    }

    /// Defect 4: the indexed sliders' `in` reply carries PULSES 0 (a rotator's is its counts per
    /// turn): ELL6 travel 31, ELL9 travel 96, both PULSES 00000000.
    #[test]
    fn slider_in_reply_has_no_pulses() {
        let mut d = fresh(C::ell6(), 2);
        script(&mut d, 0.0, "0in -> 0IN061060000120231701001F00000000");
        let mut d = fresh(C::ell9(), 2);
        script(&mut d, 0.0, "0in -> 0IN091090000120231701006000000000");
    }

    /// Defect 5a: an encoder error just below 0 reads as a small negative 32-bit two's
    /// complement value (`FFFFFFFF` for -1), as clients parse it (pylablib and
    /// thorlabs_elliptec read signed), not wrapped to the top of the turn (`00022FFF`, 359.997
    /// deg). Right after homing, 200 reads are all within 3 counts of 0 (6 sigma of the 0.5
    /// count noise) and some are negative (a read below -0.5 has probability 0.16).
    #[test]
    fn encoder_error_below_zero_reads_negative() {
        let mut d = fresh(C::ell14(), 11);
        let (_, h) = run(&mut d, 0.0, "0ho0");
        let mut negative = 0;
        for _ in 0..200 {
            let r = text(&d.receive(h + 0.5, b"0gp"));
            let p = po(&r) as u32 as i32;
            assert!(p.abs() <= 3, "{r}");
            negative += usize::from(p < 0);
        }
        assert!(negative > 0);
    }

    /// Defect 5b: a `GS09` refusal (a move while moving) is not latched: once the module is
    /// idle `gs` reads 00, as clients that poll `gs` until it is no longer busy expect. A real
    /// error (GS04) is still latched for one `gs`.
    #[test]
    fn busy_refusal_is_not_latched() {
        let mut d = fresh(C::ell14(), 12);
        let (_, h) = run(&mut d, 0.0, "0ho0");
        script(&mut d, h + 0.5, "0ma00004000 ->");
        script(&mut d, h + 0.51, "0ma00002000 -> 0GS09");
        let end = d.next_event_s().expect("the move's held reply");
        assert!(po_off(&text(&d.tick(end)), 0x4000) <= 3);
        script(
            &mut d,
            end + 0.01,
            "0gs -> 0GS00; 0sv00 -> 0GS04; 0gs -> 0GS04",
        );
    }
}
