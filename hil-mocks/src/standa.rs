//! Standa 8SMC4/5-USB controllers with the 8MPR16-1 rotation stage, simulated at the byte level
//! (`docs/DEVICES.md` section 1.5), speaking the wire format of `polar_drivers::standa::wire`
//! (shared with the driver).
//!
//! **Defaults are the healthy device** with Standa's own 8MPR16-1 profile (as libximc ships it):
//! a 20-step motor at 1/256 microsteps through a 1440:1 reduction (28 800 full steps, 80 per
//! degree), moves at 500 steps/s (6.25 deg/s) with 2000 and 4000 steps/s^2 of acceleration and
//! deceleration, homing at 100 steps/s. pylablib's `Standa8SMC` drives it over a
//! pseudo-terminal (`docs/DEVICES-conformance.md`). The faults are knobs of [`FaultProfile`],
//! off by default.
//!
//! Behaviour, with its source (the protocol specification in libximc's `protocol.xi` and the
//! 8SMC5-USB manual); the rest are choices where the sources are silent:
//! * **Frames.** A zero byte where a command would start is answered with one zero
//!   (resynchronisation). Then four code bytes; a known code waits for its fixed data and CRC
//!   (reserved bytes may hold anything: libximc fills them with 0xCC), an unknown one is
//!   answered `errc` at once. A bad CRC is `errd`. A partial frame idle for
//!   [`IDLE_TIMEOUT_S`] is dropped. Every reply is written whole, at once.
//! * **Motion.** `move` (absolute) and `movr` (relative to the current *target*) follow a
//!   trapezoid at the move settings; `left`/`rigt` turn at the set speed until `sstp`
//!   (decelerates) or `stop` (at once). While a command runs, `gets` says so
//!   (MvCmdSts = command | 0x80, MoveSts bit 0, bit 1 at the target speed).
//! * **Homing** (`home`): the first phase of the home settings, toward the home sensor (the
//!   stage's index at output angle 0) at FastHome, in the direction of HOME_DIR_FIRST (left,
//!   negative, in the 8MPR16-1's profile), then HomeDelta; `STATE_IS_HOMED` is set, the counter
//!   is not changed (clients send `zero` after it, as libximc's `command_homezero` does).
//! * **Settings** `gmov`/`smov`, `geng`/`seng`, `gent`/`sent`, `ghom`/`shom`, `gpwr`/`spwr`
//!   read back what was set. A speed over 100 000 steps/s, an acceleration of 0 or a
//!   MicrostepMode outside 1..=9 is corrected and answered `errv`. `spos` sets the counter;
//!   `zero` sets it to 0 (a running `move` keeps its absolute destination).
//! * **Faults.** Replies go through the reply faults. A stall skips steps half way through a
//!   move: the command ends with its error bit and `STATE_IS_HOMED` cleared. A spontaneous reset
//!   (rolled on a motion command) loses the command, unanswered, and reboots the controller:
//!   counter 0 where the stage stands, not homed, settings as at power-on.

use crate::faults::{Dice, FaultProfile};
use crate::motion::{output_from_motor, Profile, Ramp};
use crate::simulator::{SimDialect, SimMotion, Simulator, Truth};
use polar_drivers::standa::wire::{self, Code, Fields};

/// A partial frame idle this long (simulated seconds) is dropped (the manual's 400 ms).
pub const IDLE_TIMEOUT_S: f64 = 0.4;
/// The most steps per second a speed may be (larger ones are `errv`).
pub const MAX_SPEED_STEPS_S: u32 = 100_000;

/// The 8MPR16-1 on an 8SMC5-USB.
#[derive(Debug, Clone, PartialEq)]
pub struct StandaConfig {
    /// Full steps per turn of the stage.
    pub steps_per_turn: u32,
    /// Serial number (`gser`).
    pub serial: u32,
    /// Move speed, full steps per second.
    pub speed_steps_s: u32,
    /// Acceleration and deceleration, full steps per second squared.
    pub accel_steps_s2: (u16, u16),
    /// Home search speed, full steps per second.
    pub home_steps_s: u32,
    /// Backlash between the counter and the output, microsteps.
    pub backlash_usteps: f64,
}

impl StandaConfig {
    /// Standa's 8MPR16-1 profile.
    pub fn mpr16() -> Self {
        StandaConfig {
            steps_per_turn: 28_800,
            serial: 17_654,
            speed_steps_s: 500,
            accel_steps_s2: (2000, 4000),
            home_steps_s: 100,
            backlash_usteps: 0.0,
        }
    }

    /// The same stage moving and homing at `deg_s` (a test's or a plan's speed), reaching it in
    /// 0.1 s.
    pub fn at_speed(mut self, deg_s: f64) -> Self {
        let steps_s = (deg_s / 360.0 * f64::from(self.steps_per_turn))
            .round()
            .max(1.0);
        self.speed_steps_s = steps_s as u32;
        self.home_steps_s = steps_s as u32;
        let a = (steps_s / 0.1).min(65_535.0) as u16;
        self.accel_steps_s2 = (a, a);
        self
    }
}

/// The settings blocks as the controller keeps them (their data bytes).
#[derive(Debug, Clone, PartialEq)]
struct Settings {
    gmov: Vec<u8>,
    geng: Vec<u8>,
    gent: Vec<u8>,
    ghom: Vec<u8>,
    gpwr: Vec<u8>,
}

impl Settings {
    fn power_on(c: &StandaConfig) -> Self {
        let mut gmov = vec![0u8; 24];
        gmov[0..4].copy_from_slice(&c.speed_steps_s.to_le_bytes());
        gmov[5..7].copy_from_slice(&c.accel_steps_s2.0.to_le_bytes());
        gmov[7..9].copy_from_slice(&c.accel_steps_s2.1.to_le_bytes());
        gmov[9..13].copy_from_slice(&500u32.to_le_bytes());
        let mut geng = vec![0u8; 28];
        geng[0..2].copy_from_slice(&300u16.to_le_bytes());
        geng[2..4].copy_from_slice(&180u16.to_le_bytes());
        geng[4..8].copy_from_slice(&1000u32.to_le_bytes());
        geng[9..11].copy_from_slice(&0x92u16.to_le_bytes());
        geng[11..13].copy_from_slice(&193i16.to_le_bytes());
        geng[13] = 9;
        geng[14..16].copy_from_slice(&20u16.to_le_bytes());
        let mut gent = vec![0u8; 8];
        gent[0] = wire::ENGINE_TYPE_STEP;
        gent[1] = 2;
        let mut ghom = vec![0u8; 27];
        ghom[0..4].copy_from_slice(&c.home_steps_s.to_le_bytes());
        ghom[5..9].copy_from_slice(&10u32.to_le_bytes());
        ghom[16..18].copy_from_slice(&0x170u16.to_le_bytes());
        let mut gpwr = vec![0u8; 14];
        gpwr[0] = 50;
        gpwr[1..3].copy_from_slice(&1000u16.to_le_bytes());
        gpwr[3..5].copy_from_slice(&60u16.to_le_bytes());
        gpwr[5..7].copy_from_slice(&300u16.to_le_bytes());
        gpwr[7] = 0x05;
        Settings {
            gmov,
            geng,
            gent,
            ghom,
            gpwr,
        }
    }

    fn microsteps(&self) -> u32 {
        wire::microsteps(self.geng[13])
    }

    /// Speed, acceleration and deceleration in microsteps.
    fn motion(&self) -> (f64, f64, f64) {
        let f = Fields(&self.gmov);
        let per = f64::from(self.microsteps());
        let v = f64::from(f.u32(0)) * per + f64::from(f.u8(4));
        (
            v.max(1.0),
            (f64::from(f.u16(5)) * per).max(1.0),
            (f64::from(f.u16(7)) * per).max(1.0),
        )
    }
}

/// A motion in progress, in counter microsteps.
#[derive(Debug, Clone, Copy)]
enum Motion {
    /// A move or homing to a position.
    To {
        profile: Profile,
        /// Where a stall ends it.
        stall_at_s: Option<f64>,
    },
    /// `left` or `rigt`, or a soft stop of one.
    Spin(Ramp),
}

/// The simulated controller and stage.
#[derive(Debug, Clone)]
pub struct StandaDevice {
    config: StandaConfig,
    faults: FaultProfile,
    dice: Dice,
    settings: Settings,
    pending: Vec<u8>,
    last_byte_s: f64,
    /// The counter at rest, microsteps.
    counter: f64,
    /// The output angle (in microsteps of a turn) at which the counter reads 0.
    origin: f64,
    direction: f64,
    target: i64,
    motion: Option<Motion>,
    /// The last motion command's code and state bits (MvCmdSts).
    command: u8,
    homed: bool,
    error_flags: u32,
}

impl StandaDevice {
    /// At power-on: not homed, the counter at 0 wherever the stage stands (a random angle).
    pub fn new(config: StandaConfig, faults: FaultProfile, seed: u64) -> Self {
        let mut dice = Dice::new(seed);
        let settings = Settings::power_on(&config);
        let turn = f64::from(config.steps_per_turn * settings.microsteps());
        let origin = (dice.uniform() * turn).round();
        StandaDevice {
            config,
            faults,
            dice,
            settings,
            pending: Vec::new(),
            last_byte_s: 0.0,
            counter: 0.0,
            origin,
            direction: 1.0,
            target: 0,
            motion: None,
            command: 0,
            homed: false,
            error_flags: 0,
        }
    }

    fn turn(&self) -> f64 {
        f64::from(self.config.steps_per_turn * self.settings.microsteps())
    }

    /// The counter at `now_s`, and the signed speed (microsteps/s).
    fn at(&self, now_s: f64) -> (f64, f64) {
        match self.motion {
            Some(Motion::To {
                profile,
                stall_at_s,
            }) => {
                let t = now_s.min(stall_at_s.unwrap_or(f64::MAX));
                (profile.position(t), profile.velocity(t))
            }
            Some(Motion::Spin(r)) => (r.position(now_s), r.velocity(now_s)),
            None => (self.counter, 0.0),
        }
    }

    /// Ends what has ended by `now_s`.
    fn advance(&mut self, now_s: f64) {
        let ended = match self.motion {
            Some(Motion::To {
                profile,
                stall_at_s,
            }) => {
                let end = stall_at_s.unwrap_or(profile.end_s());
                (now_s >= end).then_some((profile.position(end), stall_at_s.is_some()))
            }
            Some(Motion::Spin(r)) if r.v1 == 0.0 && now_s >= r.settled_s() => {
                Some((r.position(r.settled_s()), false))
            }
            _ => None,
        };
        let Some((position, stalled)) = ended else {
            return;
        };
        self.counter = position;
        self.motion = None;
        self.command &= !wire::MVCMD_RUNNING;
        if stalled {
            self.command |= wire::MVCMD_ERROR;
            self.homed = false;
        } else if self.command & 0x3F == wire::MVCMD_HOME {
            self.homed = true;
        }
    }

    fn start_to(&mut self, now_s: f64, target: f64, speed: f64, command: u8, stall: bool) {
        let (start, _) = self.at(now_s);
        let (_, accel, _) = self.settings.motion();
        let profile = Profile {
            start,
            target,
            t0_s: now_s,
            v: speed,
            a: accel,
        };
        if target != start {
            self.direction = profile.direction();
        }
        let stall_at_s = (stall && target != start).then(|| now_s + 0.5 * profile.duration_s());
        self.motion = Some(Motion::To {
            profile,
            stall_at_s,
        });
        self.command = command | wire::MVCMD_RUNNING;
    }

    fn reboot(&mut self, now_s: f64) {
        let (here, _) = self.at(now_s);
        self.origin += here;
        self.counter = 0.0;
        self.target = 0;
        self.motion = None;
        self.command = 0;
        self.homed = false;
        self.error_flags = 0;
        self.settings = Settings::power_on(&self.config);
        self.pending.clear();
    }

    /// The output angle at `now_s`, microsteps of a turn.
    fn output(&self, now_s: f64) -> f64 {
        let (c, _) = self.at(now_s);
        output_from_motor(self.origin + c, self.direction, self.config.backlash_usteps)
    }

    /// The `gets` data.
    fn status(&mut self, now_s: f64) -> Vec<u8> {
        let (c, v) = self.at(now_s);
        let per = self.settings.microsteps();
        let (steps, usteps) = wire::split(c.round() as i64, per);
        let (speed_steps, speed_usteps) = wire::split(v.round() as i64, per);
        let (cruise, _, _) = self.settings.motion();
        let moving = self.motion.is_some();
        let mut move_sts = 0;
        if moving {
            move_sts |= wire::MOVE_STATE_MOVING;
            if (v.abs() - cruise).abs() < 1.0 {
                move_sts |= wire::MOVE_STATE_TARGET_SPEED;
            }
        }
        let mut flags = wire::STATE_EEPROM_CONNECTED | std::mem::take(&mut self.error_flags);
        if self.homed {
            flags |= wire::STATE_IS_HOMED;
        }
        let mut d = vec![0u8; 48];
        d[0] = move_sts;
        d[1] = self.command;
        d[2] = 3; // power: normal
        d[3] = 0; // no encoder
        d[4] = 0x33; // both windings fine
        d[5..9].copy_from_slice(&steps.to_le_bytes());
        d[9..11].copy_from_slice(&usteps.to_le_bytes());
        d[19..23].copy_from_slice(&speed_steps.to_le_bytes());
        d[23..25].copy_from_slice(&speed_usteps.to_le_bytes());
        for (at, value) in [(25, 180i16), (27, 1200), (29, 100), (31, 500), (33, 300)] {
            d[at..at + 2].copy_from_slice(&value.to_le_bytes());
        }
        d[35..39].copy_from_slice(&flags.to_le_bytes());
        d
    }

    /// One whole request: its reply.
    fn request(&mut self, now_s: f64, code: &Code, data: &[u8]) -> Vec<u8> {
        self.advance(now_s);
        let per = self.settings.microsteps();
        let reply = |d: &[u8]| wire::frame(code, d);
        match code {
            b"gpos" => {
                let (c, _) = self.at(now_s);
                let (s, u) = wire::split(c.round() as i64, per);
                let mut d = vec![0u8; 20];
                d[0..4].copy_from_slice(&s.to_le_bytes());
                d[4..6].copy_from_slice(&u.to_le_bytes());
                reply(&d)
            }
            b"gets" => {
                let d = self.status(now_s);
                reply(&d)
            }
            b"gmov" => reply(&self.settings.gmov.clone()),
            b"geng" => reply(&self.settings.geng.clone()),
            b"gent" => reply(&self.settings.gent.clone()),
            b"ghom" => reply(&self.settings.ghom.clone()),
            b"gpwr" => reply(&self.settings.gpwr.clone()),
            b"geti" => {
                let mut d = vec![0u8; 30];
                d[0..4].copy_from_slice(b"XIMC");
                d[4..6].copy_from_slice(b"SM");
                d[6..13].copy_from_slice(b"8SMC5-U");
                d[14] = 2;
                d[15] = 3;
                reply(&d)
            }
            b"gser" => reply(&self.config.serial.to_le_bytes()),
            b"gfwv" => reply(&[4, 3, 12, 0]),
            b"smov" | b"seng" | b"sent" | b"shom" | b"spwr" => self.set(code, data),
            b"spos" => {
                let f = Fields(data);
                if f.u8(14) & 0x01 == 0 && self.motion.is_none() {
                    let p = wire::join(f.i32(0), f.i16(4), per);
                    let (here, _) = self.at(now_s);
                    self.origin += here - p as f64;
                    self.counter = p as f64;
                    self.target = p;
                }
                code.to_vec()
            }
            _ => self.motion_command(now_s, code, data),
        }
    }

    /// A setter: stores the block, corrected where a value is out of range (`errv`).
    fn set(&mut self, code: &Code, data: &[u8]) -> Vec<u8> {
        let mut block = data.to_vec();
        let mut corrected = false;
        match code {
            b"smov" => {
                let f = Fields(data);
                if f.u32(0) > MAX_SPEED_STEPS_S {
                    block[0..4].copy_from_slice(&MAX_SPEED_STEPS_S.to_le_bytes());
                    corrected = true;
                }
                for at in [5, 7] {
                    if f.u16(at) == 0 {
                        block[at..at + 2].copy_from_slice(&1u16.to_le_bytes());
                        corrected = true;
                    }
                }
            }
            b"seng" if !(1..=9).contains(&data[13]) => {
                block[13] = data[13].clamp(1, 9);
                corrected = true;
            }
            _ => {}
        }
        let slot = match code {
            b"smov" => &mut self.settings.gmov,
            b"seng" => &mut self.settings.geng,
            b"sent" => &mut self.settings.gent,
            b"shom" => &mut self.settings.ghom,
            _ => &mut self.settings.gpwr,
        };
        *slot = block;
        if corrected {
            self.error_flags |= wire::STATE_ERRV;
            wire::ERRV.to_vec()
        } else {
            code.to_vec()
        }
    }

    /// `move`, `movr`, `home`, `zero`, `stop`, `sstp`, `left`, `rigt`, `loft`, `pwof`.
    fn motion_command(&mut self, now_s: f64, code: &Code, data: &[u8]) -> Vec<u8> {
        let per = self.settings.microsteps();
        let (speed, _, decel) = self.settings.motion();
        let starts_motor = matches!(code, b"move" | b"movr" | b"home" | b"left" | b"rigt");
        if starts_motor && self.dice.chance(self.faults.spontaneous_reset) {
            self.reboot(now_s);
            return Vec::new();
        }
        let stall = starts_motor && self.dice.chance(self.faults.stall);
        let (here, v) = self.at(now_s);
        match code {
            b"move" | b"movr" => {
                let f = Fields(data);
                let p = wire::join(f.i32(0), f.i16(4), per);
                self.target = if code == b"move" { p } else { self.target + p };
                let command = if code == b"move" {
                    wire::MVCMD_MOVE
                } else {
                    wire::MVCMD_MOVR
                };
                self.start_to(now_s, self.target as f64, speed, command, stall);
            }
            b"home" => {
                let f = Fields(&self.settings.ghom);
                let home_speed = (f64::from(f.u32(0)) * f64::from(per)).max(1.0);
                let turn = self.turn();
                let phys = self.origin + here;
                // HOME_DIR_FIRST set: right (positive); clear: left.
                let right = f.u16(16) & 0x1 != 0;
                let to_index = if right {
                    (-phys).rem_euclid(turn)
                } else {
                    -phys.rem_euclid(turn)
                };
                let delta = wire::join(f.i32(10), f.i16(14), per) as f64;
                self.start_to(
                    now_s,
                    here + to_index + delta,
                    home_speed,
                    wire::MVCMD_HOME,
                    false,
                );
            }
            b"zero" => {
                let shift = here;
                self.origin += shift;
                self.counter -= shift;
                self.target -= shift.round() as i64;
                if let Some(Motion::To { profile, .. }) = &mut self.motion {
                    profile.start -= shift;
                    profile.target -= shift;
                }
                if let Some(Motion::Spin(r)) = &mut self.motion {
                    r.start -= shift;
                }
            }
            b"stop" => {
                self.counter = here;
                self.motion = None;
                self.command = wire::MVCMD_STOP;
            }
            b"sstp" => {
                if self.motion.is_some() {
                    self.motion = Some(Motion::Spin(Ramp {
                        start: here,
                        v0: v,
                        v1: 0.0,
                        t0_s: now_s,
                        a: decel,
                    }));
                    self.command = wire::MVCMD_SSTP | wire::MVCMD_RUNNING;
                } else {
                    self.command = wire::MVCMD_SSTP;
                }
            }
            b"left" | b"rigt" => {
                let sign = if code == b"rigt" { 1.0 } else { -1.0 };
                let (_, accel, _) = self.settings.motion();
                self.direction = sign;
                self.motion = Some(Motion::Spin(Ramp {
                    start: here,
                    v0: v,
                    v1: sign * speed,
                    t0_s: now_s,
                    a: accel,
                }));
                self.command = if sign > 0.0 {
                    wire::MVCMD_RIGHT
                } else {
                    wire::MVCMD_LEFT
                } | wire::MVCMD_RUNNING;
            }
            b"loft" => self.command = wire::MVCMD_LOFT,
            _ => {} // pwof: the windings off; the position is kept.
        }
        code.to_vec()
    }

    /// Takes whole frames from the pending bytes; the replies.
    fn scan(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = Vec::new();
        loop {
            let Some(&first) = self.pending.first() else {
                return out;
            };
            if first == 0 {
                self.pending.remove(0);
                out.push(0);
                continue;
            }
            if self.pending.len() < 4 {
                return out;
            }
            let code: Code = [
                self.pending[0],
                self.pending[1],
                self.pending[2],
                self.pending[3],
            ];
            let Some((len, _)) = wire::lengths(&code) else {
                self.pending.drain(..4);
                self.error_flags |= wire::STATE_ERRC;
                out.extend_from_slice(wire::ERRC);
                continue;
            };
            let total = 4 + len + if len > 0 { 2 } else { 0 };
            let reply = match wire::data_of(&self.pending, len) {
                None => return out,
                Some(Err(())) => {
                    self.error_flags |= wire::STATE_ERRD;
                    wire::ERRD.to_vec()
                }
                Some(Ok(d)) => {
                    let d = d.to_vec();
                    self.request(now_s, &code, &d)
                }
            };
            self.pending.drain(..total.min(self.pending.len()));
            let faults = self.faults;
            out.extend(self.dice.reply_faults(&faults, reply));
        }
    }
}

impl Simulator for StandaDevice {
    fn describe(&self) -> String {
        format!("standa 8MPR16-1 on 8SMC5-USB serial {}", self.config.serial)
    }

    fn baud(&self) -> u32 {
        115_200
    }

    /// USB CDC: the 115200 8N2 a host sets is nominal, the bytes move in USB full-speed bulk
    /// packets (about 1 MB/s), so a reply is not held up by its length as on a UART.
    fn seconds_per_byte(&self) -> f64 {
        1e-6
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        if !self.pending.is_empty() && now_s - self.last_byte_s >= IDLE_TIMEOUT_S {
            self.pending.clear();
        }
        self.last_byte_s = now_s;
        self.pending.extend_from_slice(bytes);
        self.scan(now_s)
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        self.advance(now_s);
        Vec::new()
    }

    fn next_event_s(&self) -> Option<f64> {
        None
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        Vec::new()
    }

    fn power_cycle(&mut self, now_s: f64) {
        self.reboot(now_s);
    }

    fn truth(&self, now_s: f64) -> Truth {
        let turn = self.turn();
        Truth::Angle {
            output_rad: self.output(now_s).rem_euclid(turn) / turn * std::f64::consts::TAU,
            moving: self.motion.is_some(),
        }
    }
}

/// Standa 8SMC4/5-USB with the 8MPR16-1.
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::standa::DIALECT.name,
    models: polar_drivers::standa::DIALECT.models,
    build: |model, faults, seed| {
        (model == "8mpr16-1")
            .then(|| Box::new(StandaDevice::new(StandaConfig::mpr16(), faults, seed)) as _)
    },
    at_speed: Some(|model, deg_s, faults, seed| {
        (model == "8mpr16-1").then(|| {
            Box::new(StandaDevice::new(
                StandaConfig::mpr16().at_speed(deg_s),
                faults,
                seed,
            )) as _
        })
    }),
    on_bus: None,
    motion: Some(SimMotion {
        ramp_s: 0.1,
        max_spin_deg_per_s: polar_drivers::standa::MAX_SPIN_DEG_PER_S,
    }),
};

#[cfg(test)]
mod tests {
    use super::*;

    fn dev() -> StandaDevice {
        StandaDevice::new(StandaConfig::mpr16(), FaultProfile::default(), 5)
    }

    fn status(d: &mut StandaDevice, now_s: f64) -> (u8, u8, u32, i64) {
        let r = d.receive(now_s, b"gets");
        assert_eq!(r.len(), 54, "{r:?}");
        let data = wire::data_of(&r, 48).expect("whole").expect("crc");
        let f = Fields(data);
        (
            f.u8(0),
            f.u8(1),
            f.u32(35),
            wire::join(f.i32(5), f.i16(9), 256),
        )
    }

    /// Frames: an unknown code is errc, a bad CRC errd, a zero byte is echoed; a move runs its
    /// trapezoid (10 000 full steps at 500 steps/s with 2000 steps/s^2: 20.25 s) with the
    /// running bit, then ends at the target.
    #[test]
    fn frames_and_a_move() {
        let mut d = dev();
        assert_eq!(d.receive(0.0, b"\0\0"), vec![0, 0]);
        assert_eq!(d.receive(0.0, b"xxxx"), b"errc");
        let mut bad = wire::frame(b"move", &wire::position_data(10, 0));
        bad[5] ^= 1;
        assert_eq!(d.receive(0.0, &bad), b"errd");
        let mv = wire::frame(b"move", &wire::position_data(10_000, 0));
        assert_eq!(d.receive(1.0, &mv), b"move");
        let (m, c, _, _) = status(&mut d, 5.0);
        assert_eq!((m & 1, c), (1, wire::MVCMD_MOVE | wire::MVCMD_RUNNING));
        let (m, c, _, p) = status(&mut d, 21.3);
        assert_eq!((m, c, p), (0, wire::MVCMD_MOVE, 10_000 * 256));
    }

    /// Homing goes left to the index at 100 steps/s and sets STATE_IS_HOMED; zero then puts the
    /// counter at 0 on the index (output angle 0).
    #[test]
    fn homing_and_zero() {
        let mut d = dev();
        assert_eq!(status(&mut d, 0.0).2 & wire::STATE_IS_HOMED, 0);
        assert_eq!(d.receive(0.0, b"home"), b"home");
        let (_, c, flags, _) = status(&mut d, 400.0);
        assert_eq!(c, wire::MVCMD_HOME);
        assert_ne!(flags & wire::STATE_IS_HOMED, 0);
        assert_eq!(d.receive(400.0, b"zero"), b"zero");
        assert_eq!(status(&mut d, 400.0).3, 0);
        let Truth::Angle { output_rad, .. } = d.truth(400.0) else {
            panic!("a rotator")
        };
        assert!(output_rad.min(std::f64::consts::TAU - output_rad) < 1e-9);
    }

    /// Settings read back; an out-of-range speed is corrected and answered errv.
    #[test]
    fn settings_and_errv() {
        let mut d = dev();
        let r = d.receive(0.0, b"gmov");
        let data = wire::data_of(&r, 24).unwrap().unwrap().to_vec();
        assert_eq!(Fields(&data).u32(0), 500);
        let mut block = data.clone();
        block[0..4].copy_from_slice(&200_000u32.to_le_bytes());
        assert_eq!(d.receive(0.0, &wire::frame(b"smov", &block)), b"errv");
        let r = d.receive(0.0, b"gmov");
        let data = wire::data_of(&r, 24).unwrap().unwrap().to_vec();
        assert_eq!(Fields(&data).u32(0), MAX_SPEED_STEPS_S);
    }
}
