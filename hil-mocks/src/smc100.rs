//! Newport SMC100 and CONEX-AGP controllers with their rotation stages, simulated at the byte
//! level (`docs/DEVICES.md` section 1.4): one or several controllers on one port (the SMC100's
//! RS-485 bus), each at its address, speaking the wire format of
//! `polar_drivers::smc100::wire` (shared with the driver).
//!
//! **Defaults are the healthy device**: a client written for the real controller works
//! unchanged (`docs/DEVICES-conformance.md` runs public clients against it); the faults are
//! knobs of [`FaultProfile`], off by default.
//!
//! Behaviour, with its source where there is one (the SMC100 and CONEX-AGP user's manuals as
//! public clients quote them); the rest are choices where the sources are silent:
//! * **Lines.** A command ends with CR LF (a lone LF also ends it; a CR alone does not). It is
//!   `xxAA` then its argument: the address 1..=31 (a line without one is taken by the
//!   controller at address 1, as the first controller of a chain does), two letters (either
//!   case), a number, `?`, or nothing. A line for an address nobody has, or that is not a
//!   command, is ignored. Only queries are answered, `xxAAvalue` CR LF; a refused command is
//!   silent and sets the command error that `TE` (and `TB`, with its text) reads once.
//! * **States** (`TS`: four hex digits of positioner errors, then the state). Power-on and `RS`:
//!   NOT REFERENCED from reset (`0A`), the counter at 0 wherever the stage is (a random angle),
//!   settings as last saved. `OR` (only when NOT REFERENCED, else error `K`, `E` while
//!   homing) searches the index in the positive direction at the home velocity (`OH`), then
//!   the counter reads 0 at the index: READY from HOMING (`32`). `PA`/`PR` (only when READY,
//!   else `H` NOT REFERENCED, `I` CONFIGURATION, `J` DISABLE, `L` HOMING, `M` MOVING) move with a
//!   trapezoid at `VA` and `AC`: MOVING (`28`), then READY from MOVING (`33`). `ST` decelerates
//!   a move to READY from MOVING, a homing to NOT REFERENCED from HOMING (`0B`). `MM0` (READY)
//!   gives DISABLE from READY (`3C`), `MM1` (DISABLE) READY from DISABLE (`34`). `PW1` (NOT
//!   REFERENCED) gives CONFIGURATION (`14`); `PW0` saves the settings (the controller does not
//!   answer for [`SAVE_S`]) and gives NOT REFERENCED from CONFIGURATION (`0C`). `RS` reboots: no
//!   answer for [`RESET_S`].
//! * **Limits.** A `PA` target outside `SL`..`SR` is error `C`, a `PR` beyond them `G`. The
//!   rotation stages here turn without end, and their limits are +/-1E+12 deg.
//! * **Settings**, read with `?`: `VA` (velocity, 1E-6 to the stage's maximum), `AC`
//!   (acceleration), `OH` (home search velocity), `SL`, `SR`, `FE` (following error limit),
//!   `BA` (backlash compensation, read back only), `HT` (home type), `ID` (the stage; set in
//!   CONFIGURATION only). A value outside its range is error `C`; a setting other than `SL`,
//!   `SR`, `VA`, `AC` outside CONFIGURATION is `D`... except those four, which READY also takes.
//! * **Other queries.** `TP` position, `TH` target, `TE` command error, `TB` its text, `VE` the
//!   controller and firmware, `PT x` the time a relative move of `x` takes, `ZT` the settings
//!   one per line. Anything else is error `A`.
//! * **Faults.** Answers go through the reply faults (dropped, a bit flipped, twice). A stall
//!   stops a move half way with a following error: DISABLE from MOVING (`3D`), positioner error
//!   bit `0020`. A spontaneous reset, rolled when a move or homing is commanded, loses that
//!   command and reboots the controller (as `RS`). A power cycle is a reset of every controller.

use crate::faults::{Dice, FaultProfile};
use crate::motion::{output_from_motor, Profile};
use crate::simulator::{SimDialect, Simulator, Truth};
use polar_drivers::smc100::wire;

/// How long a controller does not answer after `RS` or a reset, seconds.
pub const RESET_S: f64 = 1.0;
/// How long a controller does not answer while `PW0` saves its settings, seconds.
pub const SAVE_S: f64 = 1.5;
/// The software limits' widest range, degrees (the manual: SL in (-1E12, 0], SR in [0, 1E12)).
pub const LIMIT_RANGE_DEG: f64 = 1e12;
/// An endless rotation stage's limits are this many encoder steps either way (the manual:
/// "set +/-2147000000 x the encoder increment" for a rotation stage).
pub const ENDLESS_LIMIT_STEPS: f64 = 2_147_000_000.0;
/// The longest command line kept, bytes (a longer one is dropped at its end).
pub const MAX_LINE: usize = 64;

/// Which controller and stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Smc100Model {
    /// SMC100CC with a PR50CC rotation stage.
    Pr50cc,
    /// SMC100CC with a URS75BCC rotation stage.
    Urs,
    /// CONEX-AGP with an AG-PR100P piezo rotation stage.
    ConexAgp,
}

/// What a simulated controller and its stage are.
#[derive(Debug, Clone, PartialEq)]
pub struct Smc100Config {
    /// The model.
    pub model: Smc100Model,
    /// The stage's name (`ID?`).
    pub stage_id: &'static str,
    /// The controller and firmware (`VE`).
    pub version: &'static str,
    /// Line rate, baud.
    pub baud: u32,
    /// Velocity at power-on and its maximum, degrees per second.
    pub velocity_deg_s: f64,
    /// Acceleration at power-on, degrees per second squared.
    pub acceleration_deg_s2: f64,
    /// Home search velocity, degrees per second.
    pub home_velocity_deg_s: f64,
    /// The position's step (what `TP` is rounded to), degrees.
    pub resolution_deg: f64,
    /// Backlash between the encoder and the output, degrees.
    pub backlash_deg: f64,
    /// Encoder noise on every position read (standard deviation), degrees.
    pub encoder_noise_deg: f64,
}

impl Smc100Config {
    /// PR50CC on an SMC100CC: 20 deg/s, 80 deg/s^2 (its data sheet's maximum speed), 0.0005 deg
    /// steps, 0.002 deg backlash.
    pub fn pr50cc() -> Self {
        Smc100Config {
            model: Smc100Model::Pr50cc,
            stage_id: "PR50CC_PN:B148210_UD:21250",
            version: "SMC_CC - Controller-driver version  3. 1. 2",
            baud: 57_600,
            velocity_deg_s: 20.0,
            acceleration_deg_s2: 80.0,
            home_velocity_deg_s: 10.0,
            resolution_deg: 0.0005,
            backlash_deg: 0.002,
            encoder_noise_deg: 0.0002,
        }
    }

    /// URS75BCC on an SMC100CC: 80 deg/s, 320 deg/s^2.
    pub fn urs() -> Self {
        Smc100Config {
            model: Smc100Model::Urs,
            stage_id: "URS75BCC_PN:B162455_UD:22031",
            velocity_deg_s: 80.0,
            acceleration_deg_s2: 320.0,
            home_velocity_deg_s: 20.0,
            ..Self::pr50cc()
        }
    }

    /// AG-PR100P on a CONEX-AGP at 921600 baud: a piezo stage at its nominal 1.5 deg/s (the
    /// figure public drivers use), 0.001 deg steps; its controller has no `VA`, `AC` or `OH`.
    pub fn conex_agp() -> Self {
        Smc100Config {
            model: Smc100Model::ConexAgp,
            stage_id: "AG-PR100P_PN:A10431_UD:23114",
            version: "CONEX-AGP 2.0.1",
            baud: 921_600,
            velocity_deg_s: 1.5,
            acceleration_deg_s2: 15.0,
            home_velocity_deg_s: 1.5,
            resolution_deg: 0.001,
            backlash_deg: 0.0,
            encoder_noise_deg: 0.0,
        }
    }

    /// The same stage moving and homing at `deg_s` (a test's or a plan's speed), reaching it in
    /// 0.1 s.
    pub fn at_speed(mut self, deg_s: f64) -> Self {
        self.velocity_deg_s = deg_s;
        self.home_velocity_deg_s = deg_s;
        self.acceleration_deg_s2 = deg_s / 0.1;
        self
    }
}

/// The settings a controller keeps until a reset (and saves with `PW0`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Settings {
    velocity_deg_s: f64,
    acceleration_deg_s2: f64,
    home_velocity_deg_s: f64,
    limits_deg: (f64, f64),
    following_error_deg: f64,
    home_type: u8,
}

/// A motion in progress, in counter degrees.
#[derive(Debug, Clone, Copy)]
struct Motion {
    profile: Profile,
    /// A homing search: the counter reads 0 at its end.
    home: bool,
    /// Where a stall stops it (a following error).
    stall_at_s: Option<f64>,
    /// Stopped by `ST` (a stopped homing finds no index).
    stopped: bool,
}

/// One controller and its stage.
#[derive(Debug, Clone)]
struct Controller {
    config: Smc100Config,
    address: u8,
    settings: Settings,
    saved: Settings,
    state: u8,
    errors: u16,
    command_error: u8,
    /// The counter's reading at rest, degrees.
    counter_deg: f64,
    /// The output angle at which the counter reads 0, degrees.
    origin_deg: f64,
    target_deg: f64,
    direction: f64,
    motion: Option<Motion>,
    /// Not answering until then (a reset, saving).
    silent_until_s: f64,
}

impl Controller {
    fn new(config: Smc100Config, address: u8, origin_deg: f64) -> Self {
        let settings = Settings {
            velocity_deg_s: config.velocity_deg_s,
            acceleration_deg_s2: config.acceleration_deg_s2,
            home_velocity_deg_s: config.home_velocity_deg_s,
            limits_deg: (
                -ENDLESS_LIMIT_STEPS * config.resolution_deg,
                ENDLESS_LIMIT_STEPS * config.resolution_deg,
            ),
            following_error_deg: 0.5,
            home_type: 0,
        };
        Controller {
            config,
            address,
            settings,
            saved: settings,
            state: wire::NOT_REFERENCED_FROM_RESET,
            errors: 0,
            command_error: wire::NO_ERROR,
            counter_deg: 0.0,
            origin_deg,
            target_deg: 0.0,
            direction: 1.0,
            motion: None,
            silent_until_s: 0.0,
        }
    }

    /// Ends what has ended by `now_s`.
    fn advance(&mut self, now_s: f64) {
        let Some(m) = self.motion else { return };
        let end_s = m.stall_at_s.unwrap_or(m.profile.end_s());
        if now_s < end_s {
            return;
        }
        self.counter_deg = m.profile.position(end_s);
        self.motion = None;
        if m.stall_at_s.is_some() {
            self.errors |= wire::FOLLOWING_ERROR;
            self.state = wire::DISABLE_FROM_MOVING;
        } else if m.home && !m.stopped {
            // The index: the counter reads 0 here from now on.
            self.origin_deg += self.counter_deg;
            self.counter_deg = 0.0;
            self.target_deg = 0.0;
            self.state = wire::READY_FROM_HOMING;
        } else if m.home {
            self.state = wire::NOT_REFERENCED_FROM_HOMING;
        } else {
            self.state = wire::READY_FROM_MOVING;
        }
    }

    /// The counter's reading at `now_s` (no noise).
    fn counter_at(&self, now_s: f64) -> f64 {
        match self.motion {
            Some(m) => m
                .profile
                .position(now_s.min(m.stall_at_s.unwrap_or(f64::MAX))),
            None => self.counter_deg,
        }
    }

    /// The output angle at `now_s`, degrees (behind the encoder by half the backlash).
    fn output_deg(&self, now_s: f64) -> f64 {
        let motor = self.origin_deg + self.counter_at(now_s);
        output_from_motor(motor, self.direction, self.config.backlash_deg)
    }

    /// A reboot: counter 0 where the stage stands, saved settings, NOT REFERENCED from reset.
    fn reset(&mut self, now_s: f64) {
        self.origin_deg += self.counter_at(now_s);
        self.counter_deg = 0.0;
        self.target_deg = 0.0;
        self.motion = None;
        self.settings = self.saved;
        self.state = wire::NOT_REFERENCED_FROM_RESET;
        self.errors = 0;
        self.command_error = wire::NO_ERROR;
        self.silent_until_s = now_s + RESET_S;
    }

    /// A move or a homing from the counter's reading to `target_deg` at `v`.
    fn start(&mut self, now_s: f64, target_deg: f64, v: f64, home: bool, stall: bool) {
        let start = self.counter_at(now_s);
        let profile = Profile {
            start,
            target: target_deg,
            t0_s: now_s,
            v: v.max(1e-9),
            a: self.settings.acceleration_deg_s2.max(1e-9),
        };
        if target_deg != start {
            self.direction = profile.direction();
        }
        let stall_at_s = (stall && target_deg != start).then(|| now_s + 0.5 * profile.duration_s());
        self.motion = Some(Motion {
            profile,
            home,
            stall_at_s,
            stopped: false,
        });
        self.target_deg = target_deg;
        self.errors = 0;
        self.state = if home { wire::HOMING } else { wire::MOVING };
    }

    /// The command error of a motion command in this state (`None`: allowed; a move while
    /// moving takes the new target, as the manual's error list for `PA` has no M).
    fn refuse_motion(&self) -> Option<u8> {
        match self.state {
            s if wire::is_ready(s) || s == wire::MOVING => None,
            s if wire::is_not_referenced(s) => Some(b'H'),
            wire::CONFIGURATION => Some(b'I'),
            s if wire::is_disabled(s) => Some(b'J'),
            wire::HOMING => Some(b'L'),
            _ => Some(b'M'),
        }
    }
}

/// One port: the controllers on its bus and the line being received.
#[derive(Debug, Clone)]
pub struct Smc100Bus {
    controllers: Vec<Controller>,
    faults: FaultProfile,
    dice: Dice,
    pending: Vec<u8>,
    baud: u32,
}

impl Smc100Bus {
    /// Controllers of `config` at `addresses` (each 1..=31; others are dropped) at power-on,
    /// each stage at a random angle; faults from `faults`, all randomness from `seed`.
    pub fn new(config: Smc100Config, addresses: &[u8], faults: FaultProfile, seed: u64) -> Self {
        let mut dice = Dice::new(seed);
        let mut controllers: Vec<Controller> = Vec::new();
        for &a in addresses {
            if wire::ADDRESSES.contains(&a) && controllers.iter().all(|c| c.address != a) {
                let origin = 360.0 * dice.uniform();
                controllers.push(Controller::new(config.clone(), a, origin));
            }
        }
        Smc100Bus {
            controllers,
            faults,
            dice,
            pending: Vec::new(),
            baud: config.baud,
        }
    }

    /// The addresses on the bus.
    pub fn addresses(&self) -> Vec<u8> {
        self.controllers.iter().map(|c| c.address).collect()
    }

    /// The true output angle of the controller at `address` at `now_s`, radians in [0, 2 pi).
    pub fn output_rad(&self, address: u8, now_s: f64) -> Option<f64> {
        self.controllers
            .iter()
            .find(|c| c.address == address)
            .map(|c| c.output_deg(now_s).rem_euclid(360.0).to_radians())
    }

    /// Handles one command line; the answer, if any. A line without an address is `ST` or
    /// `MM` for every controller (the manual: a missing address is 0, all); any other command
    /// without one is error B at the first controller.
    fn line(&mut self, now_s: f64, line: &[u8]) -> Vec<u8> {
        let Some(cmd) = wire::parse_command(line) else {
            return Vec::new();
        };
        let targets: Vec<usize> = match cmd.address {
            Some(a) => self
                .controllers
                .iter()
                .position(|c| c.address == a)
                .into_iter()
                .collect(),
            None if matches!(cmd.code(), "ST" | "MM") && cmd.argument != "?" => {
                (0..self.controllers.len()).collect()
            }
            None => {
                if let Some(c) = self.controllers.first_mut() {
                    c.advance(now_s);
                    if now_s >= c.silent_until_s {
                        c.command_error = b'B';
                    }
                }
                return Vec::new();
            }
        };
        let faults = self.faults;
        let mut out = Vec::new();
        for k in targets {
            let c = &mut self.controllers[k];
            c.advance(now_s);
            if now_s < c.silent_until_s {
                continue;
            }
            let answer = handle(c, &cmd, now_s, &faults, &mut self.dice);
            out.extend(self.dice.reply_faults(&faults, answer));
        }
        out
    }
}

/// A setting's value from `argument`, in `range`; `Err(letter)` otherwise.
fn value_in(argument: &str, range: std::ops::RangeInclusive<f64>) -> Result<f64, u8> {
    wire::parse_number(argument)
        .filter(|x| range.contains(x))
        .ok_or(b'C')
}

/// One command to one controller; the answer bytes.
fn handle(
    c: &mut Controller,
    cmd: &wire::Command,
    now_s: f64,
    faults: &FaultProfile,
    dice: &mut Dice,
) -> Vec<u8> {
    let code = cmd.code();
    if code == "ZT" {
        return settings_listing(c, &cmd.address_text);
    }
    let result = match query(c, cmd, now_s, dice) {
        Some(answer) => answer,
        None => match code {
            "PA" | "PR" => motion_command(c, code, &cmd.argument, now_s, faults, dice),
            "OR" => home_command(c, now_s, faults, dice),
            "ST" => {
                if let Some(m) = c.motion {
                    c.motion = Some(Motion {
                        profile: m.profile.stopped_at(now_s),
                        stall_at_s: None,
                        stopped: true,
                        ..m
                    });
                }
                Ok(None)
            }
            "RS" => {
                c.reset(now_s);
                Ok(None)
            }
            "MM" => disable_command(c, &cmd.argument),
            "PW" => configuration_command(c, &cmd.argument, now_s),
            _ => setting(c, code, &cmd.argument),
        },
    };
    match result {
        Ok(Some(value)) => wire::answer(&cmd.address_text, code, &value),
        Ok(None) => Vec::new(),
        Err(letter) => {
            c.command_error = letter;
            Vec::new()
        }
    }
}

/// The queries that take no argument (anything after them is ignored, as the manual says:
/// `1TS?` is `1TS`), and `ID?`, `PA?`, `MM?`, `PW?`, `PT x`; `None` for other commands.
fn query(
    c: &mut Controller,
    cmd: &wire::Command,
    now_s: f64,
    dice: &mut Dice,
) -> Option<Result<Option<String>, u8>> {
    let value = match (cmd.code(), cmd.argument.as_str()) {
        ("TS", _) => {
            // Reading the state clears the positioner errors.
            let errors = std::mem::take(&mut c.errors);
            wire::status(errors, c.state)
        }
        ("TE", _) => {
            let e = std::mem::replace(&mut c.command_error, wire::NO_ERROR);
            (e as char).to_string()
        }
        ("TB", "") => {
            let e = std::mem::replace(&mut c.command_error, wire::NO_ERROR);
            format!("{} {}", e as char, wire::command_error(e))
        }
        ("TB", x) => {
            let e = x.bytes().next().unwrap_or(wire::NO_ERROR);
            format!("{} {}", e as char, wire::command_error(e))
        }
        ("TP", _) => {
            let noise = c.config.encoder_noise_deg * dice.normal();
            let step = c.config.resolution_deg;
            wire::number(((c.counter_at(now_s) + noise) / step).round() * step)
        }
        ("TH", _) | ("PA", "?") => wire::number(c.target_deg),
        ("VE", _) => format!(" {}", c.config.version),
        ("ID", "?") => c.config.stage_id.to_string(),
        ("MM", "?") => format!("{:02X}", c.state),
        ("PW", "?") => u8::from(c.state == wire::CONFIGURATION).to_string(),
        ("PT", x) => {
            let Some(d) = wire::parse_number(x) else {
                return Some(Err(b'C'));
            };
            let p = Profile {
                start: 0.0,
                target: d.abs(),
                t0_s: 0.0,
                v: c.settings.velocity_deg_s,
                a: c.settings.acceleration_deg_s2,
            };
            wire::number(p.duration_s())
        }
        _ => return None,
    };
    Some(Ok(Some(value)))
}

/// `OR`: the index search, allowed only when NOT REFERENCED.
fn home_command(
    c: &mut Controller,
    now_s: f64,
    faults: &FaultProfile,
    dice: &mut Dice,
) -> Result<Option<String>, u8> {
    match c.state {
        s if wire::is_not_referenced(s) => {
            if dice.chance(faults.spontaneous_reset) {
                c.reset(now_s);
                return Ok(None);
            }
            // The index is at output angle 0: the next one in the positive direction.
            let to_index = (-(c.origin_deg + c.counter_deg)).rem_euclid(360.0);
            let target = c.counter_deg + to_index;
            let v = c.settings.home_velocity_deg_s;
            c.start(now_s, target, v, true, false);
            Ok(None)
        }
        wire::HOMING => Err(b'E'),
        s if wire::is_ready(s) => Err(b'K'),
        wire::CONFIGURATION => Err(b'I'),
        s if wire::is_disabled(s) => Err(b'J'),
        _ => Err(b'M'),
    }
}

/// `MM0` (READY to DISABLE) and `MM1` (DISABLE to READY); either is harmless in the state it
/// asks for.
fn disable_command(c: &mut Controller, argument: &str) -> Result<Option<String>, u8> {
    match (argument, c.state) {
        ("0", s) if wire::is_ready(s) => c.state = wire::DISABLE_FROM_READY,
        ("1", s) if wire::is_disabled(s) => {
            c.state = wire::READY_FROM_DISABLE;
            c.errors = 0;
        }
        ("0" | "1", s) if wire::is_ready(s) || wire::is_disabled(s) => {}
        ("0" | "1", s) if wire::is_not_referenced(s) => return Err(b'H'),
        ("0" | "1", wire::CONFIGURATION) => return Err(b'I'),
        ("0" | "1", wire::HOMING) => return Err(b'L'),
        ("0" | "1", _) => return Err(b'M'),
        _ => return Err(b'C'),
    }
    Ok(None)
}

/// `PW1` (NOT REFERENCED to CONFIGURATION) and `PW0` (saves, silent for [`SAVE_S`]).
fn configuration_command(
    c: &mut Controller,
    argument: &str,
    now_s: f64,
) -> Result<Option<String>, u8> {
    match (argument, c.state) {
        ("1", s) if wire::is_not_referenced(s) => c.state = wire::CONFIGURATION,
        ("0", wire::CONFIGURATION) => {
            c.saved = c.settings;
            c.state = wire::NOT_REFERENCED_FROM_CONFIGURATION;
            c.silent_until_s = now_s + SAVE_S;
        }
        ("0" | "1", s) if wire::is_ready(s) => return Err(b'K'),
        ("0" | "1", s) if wire::is_disabled(s) => return Err(b'J'),
        ("0" | "1", wire::HOMING) => return Err(b'L'),
        ("0" | "1", wire::MOVING) => return Err(b'M'),
        ("0" | "1", _) => return Err(b'D'),
        _ => return Err(b'C'),
    }
    Ok(None)
}

/// `PA x` or `PR x`.
fn motion_command(
    c: &mut Controller,
    code: &str,
    argument: &str,
    now_s: f64,
    faults: &FaultProfile,
    dice: &mut Dice,
) -> Result<Option<String>, u8> {
    let x = wire::parse_number(argument).ok_or(b'C')?;
    if let Some(letter) = c.refuse_motion() {
        return Err(letter);
    }
    let target = match code {
        "PA" => x,
        _ => c.target_deg + x,
    };
    let (lo, hi) = c.settings.limits_deg;
    if !(lo..=hi).contains(&target) {
        return Err(b'G');
    }
    // The controller rounds a target to the closest encoder position.
    let step = c.config.resolution_deg;
    let target = (target / step).round() * step;
    if dice.chance(faults.spontaneous_reset) {
        c.reset(now_s);
        return Ok(None);
    }
    let stall = dice.chance(faults.stall);
    let v = c.settings.velocity_deg_s;
    c.start(now_s, target, v, false, stall);
    Ok(None)
}

/// `VA`, `AC`, `OH`, `SL`, `SR`, `FE`, `BA`, `HT`, `ID`: read with `?`, set with a value.
fn setting(c: &mut Controller, code: &str, argument: &str) -> Result<Option<String>, u8> {
    let max_v = c.config.velocity_deg_s.max(1e-6);
    if c.config.model == Smc100Model::ConexAgp && matches!(code, "VA" | "AC" | "OH") {
        return Err(b'A');
    }
    let s = &mut c.settings;
    let (value, range): (&mut f64, std::ops::RangeInclusive<f64>) = match code {
        "VA" => (&mut s.velocity_deg_s, 1e-6..=max_v),
        "AC" => (&mut s.acceleration_deg_s2, 1e-6..=1e12),
        "OH" => (&mut s.home_velocity_deg_s, 1e-6..=max_v),
        "SL" => (&mut s.limits_deg.0, -LIMIT_RANGE_DEG..=0.0),
        "SR" => (&mut s.limits_deg.1, 0.0..=LIMIT_RANGE_DEG),
        "FE" => (&mut s.following_error_deg, 1e-6..=1e12),
        "BA" => {
            return match argument {
                "?" => Ok(Some("0".into())),
                _ if c.state == wire::CONFIGURATION => value_in(argument, 0.0..=1e12).map(|_| None),
                _ => Err(b'D'),
            }
        }
        "HT" => {
            return match argument {
                "?" => Ok(Some(s.home_type.to_string())),
                _ if c.state != wire::CONFIGURATION => Err(b'D'),
                _ => value_in(argument, 0.0..=4.0).map(|h| {
                    s.home_type = h as u8;
                    None
                }),
            }
        }
        "ID" => {
            return match c.state {
                wire::CONFIGURATION if !argument.is_empty() => Ok(None),
                wire::CONFIGURATION => Err(b'C'),
                _ => Err(b'D'),
            }
        }
        _ => return Err(b'A'),
    };
    if argument == "?" {
        return Ok(Some(wire::number(*value)));
    }
    let in_motion = wire::is_in_motion(c.state);
    let allowed =
        c.state == wire::CONFIGURATION || (!in_motion && matches!(code, "VA" | "AC" | "SL" | "SR"));
    if !allowed {
        return Err(if in_motion { b'M' } else { b'D' });
    }
    *value = value_in(argument, range)?;
    Ok(None)
}

/// `ZT`: the settings, one line each as their queries answer them, between `PW1` and `PW0`
/// (the manual's example).
fn settings_listing(c: &Controller, address: &str) -> Vec<u8> {
    let s = &c.settings;
    let mut out = wire::answer(address, "PW", "1");
    for (code, v) in [
        ("AC", s.acceleration_deg_s2),
        ("FE", s.following_error_deg),
        ("HT", f64::from(s.home_type)),
        ("OH", s.home_velocity_deg_s),
        ("SL", s.limits_deg.0),
        ("SR", s.limits_deg.1),
        ("VA", s.velocity_deg_s),
    ] {
        out.extend(wire::answer(address, code, &wire::number(v)));
    }
    out.extend(wire::answer(address, "ID", c.config.stage_id));
    out.extend(wire::answer(address, "PW", "0"));
    out
}

impl Simulator for Smc100Bus {
    fn describe(&self) -> String {
        let first = self.controllers.first();
        format!(
            "smc100 {} at address{} {}",
            first.map_or("(none)", |c| c.config.stage_id),
            if self.controllers.len() > 1 { "es" } else { "" },
            self.addresses()
                .iter()
                .map(u8::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        )
    }

    fn baud(&self) -> u32 {
        self.baud
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        for &b in bytes {
            if b == b'\n' {
                let mut line = std::mem::take(&mut self.pending);
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                out.extend(self.line(now_s, &line));
            } else if self.pending.len() < MAX_LINE {
                self.pending.push(b);
            }
        }
        out
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        for c in &mut self.controllers {
            c.advance(now_s);
        }
        Vec::new()
    }

    fn next_event_s(&self) -> Option<f64> {
        None
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        Vec::new()
    }

    fn power_cycle(&mut self, now_s: f64) {
        self.pending.clear();
        for c in &mut self.controllers {
            c.reset(now_s);
        }
    }

    fn truth(&self, now_s: f64) -> Truth {
        match self.controllers.first() {
            Some(c) => Truth::Angle {
                output_rad: c.output_deg(now_s).rem_euclid(360.0).to_radians(),
                moving: c
                    .motion
                    .is_some_and(|m| now_s < m.stall_at_s.unwrap_or(m.profile.end_s())),
            },
            None => Truth::Angle {
                output_rad: 0.0,
                moving: false,
            },
        }
    }
}

/// The configuration of a model, by its registry name.
pub fn config(model: &str) -> Option<Smc100Config> {
    match model {
        "pr50cc" => Some(Smc100Config::pr50cc()),
        "urs" => Some(Smc100Config::urs()),
        "conex-agp" => Some(Smc100Config::conex_agp()),
        _ => None,
    }
}

/// Newport SMC100 and CONEX-AGP: one controller at address 1 by default, several on one
/// port with `simulate stage --address`.
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::smc100::DIALECT.name,
    models: polar_drivers::smc100::DIALECT.models,
    build: |model, faults, seed| {
        config(model).map(|c| Box::new(Smc100Bus::new(c, &[1], faults, seed)) as _)
    },
    at_speed: Some(|model, deg_s, faults, seed| {
        config(model).map(|c| Box::new(Smc100Bus::new(c.at_speed(deg_s), &[1], faults, seed)) as _)
    }),
    on_bus: Some(|model, addresses, faults, seed| {
        config(model).map(|c| Box::new(Smc100Bus::new(c, addresses, faults, seed)) as _)
    }),
    motion: None,
};

#[cfg(test)]
mod tests {
    use super::*;

    fn bus(addresses: &[u8], faults: FaultProfile) -> Smc100Bus {
        Smc100Bus::new(Smc100Config::pr50cc(), addresses, faults, 3)
    }

    fn send(b: &mut Smc100Bus, now_s: f64, line: &str) -> String {
        let out = b.receive(now_s, format!("{line}\r\n").as_bytes());
        String::from_utf8_lossy(&out).into_owned()
    }

    fn state(b: &mut Smc100Bus, now_s: f64, address: u8) -> (u16, u8) {
        let a = send(b, now_s, &format!("{address}TS"));
        let v = wire::parse_answer(&a, address, "TS").expect("a TS answer");
        wire::parse_status(v).expect("6 hex digits")
    }

    /// Power-on is NOT REFERENCED and refuses moves (error H, read once by TE); homing runs
    /// at the home speed to the index and ends READY from HOMING with the counter at 0 on
    /// the true index (output angle 0).
    #[test]
    fn homing_finds_the_index() {
        let mut b = bus(&[1], FaultProfile::default());
        assert_eq!(state(&mut b, 0.0, 1), (0, wire::NOT_REFERENCED_FROM_RESET));
        assert_eq!(send(&mut b, 0.0, "1PA10"), "");
        assert_eq!(send(&mut b, 0.0, "1TE"), "1TEH\r\n");
        assert_eq!(send(&mut b, 0.0, "1TE"), "1TE@\r\n");
        send(&mut b, 0.0, "1OR");
        assert_eq!(state(&mut b, 0.01, 1).1, wire::HOMING);
        // At most a turn at 10 deg/s plus the ramps.
        assert_eq!(state(&mut b, 40.0, 1), (0, wire::READY_FROM_HOMING));
        let tp = send(&mut b, 40.0, "1TP");
        let p = wire::parse_number(wire::parse_answer(&tp, 1, "TP").unwrap()).unwrap();
        assert!(p.abs() <= 0.001, "{tp}");
        let Truth::Angle { output_rad, .. } = b.truth(40.0) else {
            panic!("a rotator")
        };
        let off = output_rad.min(std::f64::consts::TAU - output_rad);
        assert!(off.to_degrees() < 0.002, "{output_rad}");
    }

    /// A move from READY: MOVING during the trapezoid (90 deg at 20 deg/s and 80 deg/s^2:
    /// 4.75 s), then READY from MOVING at the target within the encoder noise; the true
    /// output is there within half the backlash.
    #[test]
    fn a_move_follows_its_trapezoid() {
        let mut b = bus(&[1], FaultProfile::default());
        send(&mut b, 0.0, "1OR");
        send(&mut b, 40.0, "1PA90");
        assert_eq!(send(&mut b, 40.0, "1TE"), "1TE@\r\n");
        assert_eq!(state(&mut b, 44.0, 1).1, wire::MOVING);
        assert_eq!(state(&mut b, 44.8, 1), (0, wire::READY_FROM_MOVING));
        let tp = send(&mut b, 44.8, "1TP");
        let p = wire::parse_number(wire::parse_answer(&tp, 1, "TP").unwrap()).unwrap();
        assert!((p - 90.0).abs() <= 0.002, "{tp}");
        assert_eq!(send(&mut b, 44.8, "1TH"), "1TH90.000000\r\n");
        let Truth::Angle { output_rad, .. } = b.truth(45.0) else {
            panic!("a rotator")
        };
        assert!(
            (output_rad.to_degrees() - 90.0).abs() <= 0.0011,
            "{output_rad}"
        );
    }

    /// Several controllers on one port: each answers only its own address; an address nobody
    /// has gets no answer; a line without an address goes to controller 1.
    #[test]
    fn controllers_share_a_bus() {
        let mut b = bus(&[1, 2, 31], FaultProfile::default());
        assert_eq!(b.addresses(), vec![1, 2, 31]);
        assert!(send(&mut b, 0.0, "2ID?").starts_with("2IDPR50CC_"));
        assert_eq!(send(&mut b, 0.0, "31TS"), "31TS00000A\r\n");
        assert_eq!(send(&mut b, 0.0, "3TS"), "");
        send(&mut b, 0.0, "2OR");
        assert_eq!(state(&mut b, 0.01, 2).1, wire::HOMING);
        assert_eq!(state(&mut b, 0.01, 1).1, wire::NOT_REFERENCED_FROM_RESET);
        assert_eq!(send(&mut b, 0.0, "TS"), "", "no address: error B");
        assert_eq!(send(&mut b, 0.0, "1TE?"), "1TEB\r\n");
        // MM and ST without an address are for every controller; `01` is echoed as sent.
        send(&mut b, 30.0, "MM0");
        assert_eq!(send(&mut b, 30.0, "02TS"), "02TS00003C\r\n");
    }

    /// Settings: read with `?`, set within range (else error C), refused while moving (M);
    /// an unknown command is error A; PW1/PW0 enter and leave CONFIGURATION, and a reset
    /// restores the saved settings and is silent for RESET_S.
    #[test]
    fn settings_errors_and_reset() {
        let mut b = bus(&[1], FaultProfile::default());
        assert_eq!(send(&mut b, 0.0, "1VA?"), "1VA20.000000\r\n");
        send(&mut b, 0.0, "1VA500");
        assert_eq!(send(&mut b, 0.0, "1TE"), "1TEC\r\n");
        send(&mut b, 0.0, "1VA5");
        assert_eq!(send(&mut b, 0.0, "1VA?"), "1VA5.000000\r\n");
        send(&mut b, 0.0, "1XX");
        assert_eq!(
            send(&mut b, 0.0, "1TB"),
            "1TBA unknown message code or floating point controller address\r\n"
        );
        send(&mut b, 0.0, "1PW1");
        assert_eq!(state(&mut b, 0.0, 1).1, wire::CONFIGURATION);
        send(&mut b, 0.0, "1PW0");
        assert_eq!(send(&mut b, 0.5, "1TS"), "", "silent while saving");
        assert_eq!(
            state(&mut b, 2.0, 1).1,
            wire::NOT_REFERENCED_FROM_CONFIGURATION
        );
        send(&mut b, 2.0, "1RS");
        assert_eq!(send(&mut b, 2.5, "1TS"), "", "silent while rebooting");
        assert_eq!(state(&mut b, 3.1, 1).1, wire::NOT_REFERENCED_FROM_RESET);
        assert_eq!(send(&mut b, 3.1, "1VA?"), "1VA5.000000\r\n", "saved by PW0");
    }

    /// A stall stops a move half way with a following error: DISABLE from MOVING, error bit
    /// 0020; MM1 makes it READY again. ST stops a move early, READY from MOVING.
    #[test]
    fn stalls_and_stops() {
        let stall = FaultProfile {
            stall: 1.0,
            ..FaultProfile::default()
        };
        let mut b = bus(&[1], stall);
        send(&mut b, 0.0, "1OR");
        send(&mut b, 40.0, "1PA90");
        assert_eq!(
            state(&mut b, 50.0, 1),
            (wire::FOLLOWING_ERROR, wire::DISABLE_FROM_MOVING)
        );
        send(&mut b, 50.0, "1MM1");
        assert_eq!(state(&mut b, 50.0, 1), (0, wire::READY_FROM_DISABLE));
        let mut b = bus(&[1], FaultProfile::default());
        send(&mut b, 0.0, "1OR");
        send(&mut b, 40.0, "1PA180");
        send(&mut b, 41.0, "1ST");
        assert_eq!(state(&mut b, 43.0, 1), (0, wire::READY_FROM_MOVING));
        let tp = send(&mut b, 43.0, "1TP");
        let p = wire::parse_number(wire::parse_answer(&tp, 1, "TP").unwrap()).unwrap();
        assert!(p > 1.0 && p < 30.0, "{tp}");
    }
}
