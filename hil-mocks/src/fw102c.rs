//! Thorlabs FW102C (6 positions) / FW212C (12 positions) motorised filter wheels, simulated at
//! the byte level (`docs/DEVICES.md` section 1.2): ASCII command lines ending in
//! `\r`, an echo of every line, the answer line of a query, then a prompt.
//!
//! # Wire format (exact bytes)
//!
//! * Host: a command then `\r`. A `\n` at the start of a line (as in `\r\n`) is ignored and
//!   not echoed. Commands are case-sensitive and take no spaces: `pos=4`, not `POS = 4`.
//! * Echo: the line's bytes as received (any bytes, not only ASCII) then `\r`, sent as soon as
//!   the `\r` arrives, even while the wheel moves.
//! * Answer of a query: the value then `\r`: `pos?` gives `4\r`, `*idn?` gives
//!   `THORLABS FW102C/FW212C Filter Wheel version 1.07\r` (from [`Fw102cConfig`]).
//! * Errors, in place of an answer: `Command error CMD_NOT_DEFINED\r` (unknown command or
//!   setting, `*idn=1`, `POS?`, non-ASCII bytes) and `Command error CMD_ARG_INVALID\r` (an
//!   argument that is not 1 to 9 decimal digits or is out of range: `pos=0`, `pos=7` on six
//!   positions, `speed=2`, `pcount=8`, `pos=`).
//! * Prompt: [`PROMPT`] = `> ` ends every reply. An empty line gives its echo `\r` then `> `.
//!
//! # Timing
//!
//! The device is sequential: one command at a time, in order. `pos=n` sends its echo at once
//! and its prompt only when the move and the settle time have ended (from [`Simulator::tick`]);
//! lines that arrive meanwhile are echoed at once, queued and processed in order after it, so a
//! `pos?` sent during a move is answered after the move. At most [`MAX_QUEUED`] lines wait;
//! further lines are lost without an echo. A line longer than [`MAX_LINE`] bytes is discarded up
//! to and including its `\r` (no echo, no reply). `pos=n` to the current position prompts at
//! once.
//!
//! # Motion
//!
//! Moves follow a [`Profile`] in slot units with the [`WheelSpeed`] of `speed=0` or `speed=1`,
//! then wait the settle time. The wheel goes the short way round; a move of exactly half a turn
//! goes forward (towards higher position numbers). `pcount=n` changes the controller's idea of
//! the positions per turn (range of `pos=`, spacing of positions) but not the physical wheel:
//! `pcount=12` on a six-slot wheel puts even positions between slots. `pos?` reports the nearest
//! position. `trig`, `sensors` and `baud` are stored and read back but change nothing: the
//! simulated line stays at 115200 baud.
//!
//! # Faults ([`FaultProfile`])
//!
//! * Reply faults ([`Dice::reply_faults`]): two units per command, the echo, and the rest of
//!   the reply (answer or error line with the prompt, or the prompt of a move).
//! * `spurious_busy`: a command is processed 0.5 s ([`BUSY_DELAY_S`]) late (the FW102C has no
//!   busy reply); its echo is still immediate.
//! * `stall`: a move stops one slot short of its target along the way it goes (a one-slot move
//!   does not move); the controller does not notice and prompts at the time the full move would
//!   have ended; `pos?` then reports where the wheel stopped.
//! * `spontaneous_reset`: when a move has ended and been prompted (the motor's current surge
//!   browns the controller out), it reboots silently:
//!   settings go back to the saved ones, the partial line and queued lines are lost, and the
//!   wheel returns to position 1 (a move at the saved speed, with no prompt; it never stalls).
//! * `thermal_duty` does not apply: the FW102C has no thermal cut-out.
//!
//! # Power
//!
//! `save` stores `pcount`, `speed`, `trig`, `sensors` and `baud` as power-up defaults; a power
//! cycle restores them and puts the wheel at position 1 at once. The device sends nothing when
//! the port opens. [`Simulator::truth`] gives the slot at rest and `None` while the wheel moves
//! or settles.

use std::collections::VecDeque;

use crate::faults::{Dice, FaultProfile};
use crate::motion::Profile;
use crate::simulator::{SimDialect, Simulator, Truth};

/// The prompt that ends every reply.
pub const PROMPT: &[u8] = b"> ";
/// The error line for an unknown command.
pub const ERR_NOT_DEFINED: &[u8] = b"Command error CMD_NOT_DEFINED\r";
/// The error line for a bad argument.
pub const ERR_ARG_INVALID: &[u8] = b"Command error CMD_ARG_INVALID\r";
/// The longest line accepted, bytes without the `\r`.
pub const MAX_LINE: usize = 64;
/// The most complete lines that wait while the device is busy.
pub const MAX_QUEUED: usize = 32;
/// How late a command is processed under the `spurious_busy` fault, seconds.
pub const BUSY_DELAY_S: f64 = 0.5;

/// A move profile: cruise velocity and acceleration in slot units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WheelSpeed {
    /// Cruise velocity, slots/s (> 0).
    pub velocity_slots_per_s: f64,
    /// Acceleration, slots/s^2 (> 0).
    pub acceleration_slots_per_s2: f64,
}

impl WheelSpeed {
    /// A profile of `velocity_slots_per_s` and `acceleration_slots_per_s2`.
    pub const fn new(velocity_slots_per_s: f64, acceleration_slots_per_s2: f64) -> Self {
        WheelSpeed {
            velocity_slots_per_s,
            acceleration_slots_per_s2,
        }
    }
}

/// What the simulated wheel is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fw102cConfig {
    /// Physical slots: 6 (FW102C) or 12 (FW212C); `pcount` starts at this value.
    pub slots: u8,
    /// First word of the `*idn?` answer.
    pub vendor: &'static str,
    /// Model part of the `*idn?` answer.
    pub model: &'static str,
    /// The product, for [`Simulator::describe`].
    pub product: &'static str,
    /// The serial number, for [`Simulator::describe`] (the protocol never reports it).
    pub serial: &'static str,
    /// Firmware version in the `*idn?` answer.
    pub firmware: &'static str,
    /// Moves with `speed=0`.
    pub slow: WheelSpeed,
    /// Moves with `speed=1` (the power-on default).
    pub high: WheelSpeed,
    /// Time from the end of a move to the prompt, seconds.
    pub settle_s: f64,
}

impl Fw102cConfig {
    /// A six-slot FW102C. With the 0.1 s settle, high speed (3 slots/s, 20 slots/s^2) takes
    /// 0.58 s for one slot and 1.25 s for half a turn; slow speed (1.2 slots/s, 6 slots/s^2)
    /// 1.13 s and 2.8 s.
    pub fn fw102c() -> Self {
        Fw102cConfig {
            slots: 6,
            vendor: "THORLABS",
            model: "FW102C/FW212C",
            product: "FW102C",
            serial: "FW102C-0001",
            firmware: "1.07",
            slow: WheelSpeed::new(1.2, 6.0),
            high: WheelSpeed::new(3.0, 20.0),
            settle_s: 0.1,
        }
    }

    /// A twelve-slot FW212C. With the 0.1 s settle, high speed (5 slots/s, 30 slots/s^2) takes
    /// 0.47 s for one slot and 1.47 s for half a turn; slow speed (2 slots/s, 10 slots/s^2)
    /// 0.8 s and 3.3 s.
    pub fn fw212c() -> Self {
        Fw102cConfig {
            slots: 12,
            product: "FW212C",
            serial: "FW212C-0001",
            slow: WheelSpeed::new(2.0, 10.0),
            high: WheelSpeed::new(5.0, 30.0),
            ..Self::fw102c()
        }
    }
}

/// The settings `save` stores, indexed by [`NAMES`]: `pcount`, then 0/1 flags.
type Settings = [u8; 5];
/// The settings' names, for `name=n` and `name?`.
const NAMES: [&[u8]; 5] = [b"pcount", b"speed", b"trig", b"sensors", b"baud"];
const PCOUNT: usize = 0;
const SPEED: usize = 1;

/// A parsed command line; settings by their index in [`NAMES`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Cmd {
    Empty,
    Idn,
    PosQuery,
    Pos(u32),
    Get(usize),
    Set(usize, u32),
    Save,
}

/// Why a line was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CmdError {
    NotDefined,
    ArgInvalid,
}

fn parse(line: &[u8]) -> Result<Cmd, CmdError> {
    match line {
        b"" => return Ok(Cmd::Empty),
        b"*idn?" => return Ok(Cmd::Idn),
        b"pos?" => return Ok(Cmd::PosQuery),
        b"save" => return Ok(Cmd::Save),
        _ => {}
    }
    let key = |name: &[u8]| NAMES.iter().position(|n| *n == name);
    if let Some(name) = line.strip_suffix(b"?") {
        return key(name).map(Cmd::Get).ok_or(CmdError::NotDefined);
    }
    let mut parts = line.splitn(2, |&b| b == b'=');
    let (Some(name), Some(arg)) = (parts.next(), parts.next()) else {
        return Err(CmdError::NotDefined);
    };
    let key = match name {
        b"pos" => None,
        _ => Some(key(name).ok_or(CmdError::NotDefined)?),
    };
    if arg.is_empty() || arg.len() > 9 || !arg.iter().all(u8::is_ascii_digit) {
        return Err(CmdError::ArgInvalid);
    }
    let value = arg.iter().fold(0u32, |n, &d| n * 10 + u32::from(d - b'0'));
    Ok(match key {
        None => Cmd::Pos(value),
        Some(k) => Cmd::Set(k, value),
    })
}

/// What the device is doing until `end_s`.
#[derive(Debug, Clone)]
struct Job {
    end_s: f64,
    work: Work,
}

#[derive(Debug, Clone)]
enum Work {
    /// A move (physical slots) and its settle time; a stalled wheel stops at `jam`; the return
    /// to position 1 after a reset has no prompt.
    Move {
        profile: Profile,
        jam: Option<f64>,
        prompt: bool,
    },
    /// A line held back by the `spurious_busy` fault.
    Busy(Vec<u8>),
}

/// The simulated wheel and its controller.
#[derive(Debug, Clone)]
pub struct Fw102cDevice {
    config: Fw102cConfig,
    faults: FaultProfile,
    dice: Dice,
    settings: Settings,
    saved: Settings,
    /// The wheel at rest (or where the current move started), physical slots from position 1,
    /// in `[0, slots)`.
    at: f64,
    job: Option<Job>,
    /// When the device last became free, seconds.
    free_s: f64,
    /// Complete lines waiting, with their arrival times.
    queue: VecDeque<(f64, Vec<u8>)>,
    /// The line being received.
    line: Vec<u8>,
    /// The line being received is too long and is being discarded.
    overflow: bool,
}

impl Fw102cDevice {
    /// A wheel at power-on: at position 1, idle, with the default settings (`pcount` = slots,
    /// `speed=1`, `trig=0`, `sensors=0`, `baud=1`) also saved; faults from `faults`, all
    /// randomness from `seed`.
    pub fn new(config: Fw102cConfig, faults: FaultProfile, seed: u64) -> Self {
        let settings = [config.slots.max(1), 1, 0, 0, 1];
        Fw102cDevice {
            config,
            faults,
            dice: Dice::new(seed),
            settings,
            saved: settings,
            at: 0.0,
            job: None,
            free_s: 0.0,
            queue: VecDeque::new(),
            line: Vec::new(),
            overflow: false,
        }
    }

    fn slots(&self) -> f64 {
        f64::from(self.config.slots.max(1))
    }

    /// The controller's position (from 1) nearest to a wheel angle in slots.
    fn position_of(&self, at: f64) -> u32 {
        let pcount = f64::from(self.settings[PCOUNT].max(1));
        (at * pcount / self.slots()).round().rem_euclid(pcount) as u32 + 1
    }

    /// A reply unit through the reply faults.
    fn send(&mut self, bytes: Vec<u8>) -> Vec<u8> {
        self.dice.reply_faults(&self.faults, bytes)
    }

    /// Runs the jobs and queued lines that fall due by `now_s`, at their exact times.
    fn advance(&mut self, now_s: f64, out: &mut Vec<u8>) {
        loop {
            if let Some(job) = self.job.take_if(|j| j.end_s <= now_s) {
                self.free_s = job.end_s;
                self.finish(job, out);
                continue;
            }
            if self.job.is_some() {
                return;
            }
            let Some((arrived_s, line)) = self.queue.pop_front() else {
                return;
            };
            let t = arrived_s.max(self.free_s);
            self.free_s = t;
            if self.dice.chance(self.faults.spurious_busy) {
                let end_s = t + BUSY_DELAY_S;
                let work = Work::Busy(line);
                self.job = Some(Job { end_s, work });
            } else {
                self.execute(t, &line, out);
            }
        }
    }

    fn finish(&mut self, job: Job, out: &mut Vec<u8>) {
        match job.work {
            Work::Move {
                profile,
                jam,
                prompt,
            } => {
                self.at = jam.unwrap_or(profile.target).rem_euclid(self.slots());
                if prompt {
                    out.extend(self.send(PROMPT.to_vec()));
                    self.after_command(job.end_s);
                }
            }
            Work::Busy(line) => self.execute(job.end_s, &line, out),
        }
    }

    /// Processes one line at `t`: sends the reply, or starts a move whose prompt comes later.
    fn execute(&mut self, t: f64, line: &[u8], out: &mut Vec<u8>) {
        let mut reply = match self.command(t, line) {
            Ok(Some(answer)) => answer,
            Ok(None) => return,
            Err(CmdError::NotDefined) => ERR_NOT_DEFINED.to_vec(),
            Err(CmdError::ArgInvalid) => ERR_ARG_INVALID.to_vec(),
        };
        reply.extend_from_slice(PROMPT);
        out.extend(self.send(reply));
    }

    /// The answer line (empty for a command), or `None` when a move has started.
    fn command(&mut self, t: f64, line: &[u8]) -> Result<Option<Vec<u8>>, CmdError> {
        let c = self.config;
        let answer = match parse(line)? {
            Cmd::Empty => String::new(),
            Cmd::Idn => format!(
                "{} {} Filter Wheel version {}\r",
                c.vendor, c.model, c.firmware
            ),
            Cmd::PosQuery => format!("{}\r", self.position_of(self.at)),
            Cmd::Get(key) => format!("{}\r", self.settings[key]),
            Cmd::Set(key, value) => {
                if !matches!((key, value), (PCOUNT, 6 | 12) | (1.., 0 | 1)) {
                    return Err(CmdError::ArgInvalid);
                }
                self.settings[key] = value as u8;
                String::new()
            }
            Cmd::Save => {
                self.saved = self.settings;
                String::new()
            }
            Cmd::Pos(n) => {
                let pcount = self.settings[PCOUNT].max(1);
                if n == 0 || n > u32::from(pcount) {
                    return Err(CmdError::ArgInvalid);
                }
                let target = f64::from(n - 1) * self.slots() / f64::from(pcount);
                if let Some(job) = self.plan_move(t, target, true) {
                    self.job = Some(job);
                    return Ok(None);
                }
                String::new()
            }
        };
        Ok(Some(answer.into_bytes()))
    }

    /// A move from the wheel's angle to `target` (slots) the short way round starting at `t`,
    /// or `None` if it is already there. Only a move with a prompt may stall.
    fn plan_move(&mut self, t: f64, target: f64, prompt: bool) -> Option<Job> {
        let n = self.slots();
        let mut delta = (target - self.at).rem_euclid(n);
        if delta > n / 2.0 {
            delta -= n;
        }
        if delta.abs() < 1e-9 || !delta.is_finite() {
            return None;
        }
        let speed = if self.settings[SPEED] == 0 {
            self.config.slow
        } else {
            self.config.high
        };
        let profile = Profile {
            start: self.at,
            target: self.at + delta,
            t0_s: t,
            v: speed.velocity_slots_per_s,
            a: speed.acceleration_slots_per_s2,
        };
        let jam = (prompt && self.dice.chance(self.faults.stall))
            .then(|| profile.target - profile.direction() * delta.abs().min(1.0));
        let end_s = profile.end_s() + self.config.settle_s;
        let work = Work::Move {
            profile,
            jam,
            prompt,
        };
        Some(Job { end_s, work })
    }

    /// The `spontaneous_reset` fault, rolled after each prompted move. (A reset after a query
    /// would move the wheel after the host verified it, which no driver can see.)
    fn after_command(&mut self, t: f64) {
        if self.dice.chance(self.faults.spontaneous_reset) {
            self.reboot();
            self.job = self.plan_move(t, 0.0, false);
        }
    }

    /// The controller restarts: saved settings; the partial and queued lines are lost.
    fn reboot(&mut self) {
        self.settings = self.saved;
        self.queue.clear();
        self.line.clear();
        self.overflow = false;
    }

    /// The slot (from 0) the wheel rests on, if it is at rest on one (no advance).
    fn slot_now(&self) -> Option<usize> {
        if let Some(Job {
            work: Work::Move { .. },
            ..
        }) = &self.job
        {
            return None;
        }
        let s = self.at.round();
        ((self.at - s).abs() < 1e-6).then(|| s as usize % usize::from(self.config.slots.max(1)))
    }
}

impl Simulator for Fw102cDevice {
    fn describe(&self) -> String {
        let c = self.config;
        format!(
            "thorlabs {} filter wheel ({} slots) serial {}",
            c.product, c.slots, c.serial
        )
    }

    fn baud(&self) -> u32 {
        115_200
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        self.advance(now_s, &mut out);
        for &b in bytes {
            match b {
                b'\r' => {
                    let line = std::mem::take(&mut self.line);
                    if std::mem::take(&mut self.overflow) || self.queue.len() >= MAX_QUEUED {
                        continue;
                    }
                    let mut echo = line.clone();
                    echo.push(b'\r');
                    out.extend(self.send(echo));
                    self.queue.push_back((now_s, line));
                    self.advance(now_s, &mut out);
                }
                b'\n' if self.line.is_empty() && !self.overflow => {}
                _ if self.overflow => {}
                _ if self.line.len() >= MAX_LINE => {
                    self.line.clear();
                    self.overflow = true;
                }
                _ => self.line.push(b),
            }
        }
        out
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = Vec::new();
        self.advance(now_s, &mut out);
        out
    }

    fn next_event_s(&self) -> Option<f64> {
        self.job.as_ref().map(|j| j.end_s)
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        // The FW102C sends nothing at boot or when the port opens.
        Vec::new()
    }

    /// Settings go back to the saved ones; the wheel is at position 1 at once (its homing at
    /// boot is not simulated); moves, queued lines and the partial line are lost.
    fn power_cycle(&mut self, now_s: f64) {
        self.reboot();
        self.at = 0.0;
        self.job = None;
        self.free_s = now_s;
    }

    /// The slot while at rest, `None` while moving or settling, or between slots (a `pcount`
    /// that does not match the wheel). Exact without a prior tick: a copy is advanced to
    /// `now_s`.
    fn truth(&self, now_s: f64) -> Truth {
        let mut copy = self.clone();
        copy.advance(now_s, &mut Vec::new());
        Truth::Slot {
            slot: copy.slot_now(),
        }
    }
}

/// The fw102c dialect's simulators (`polar_drivers::fw102c::DIALECT`'s models), for
/// [`crate::sim::SIMULATORS`].
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::fw102c::DIALECT.name,
    models: polar_drivers::fw102c::DIALECT.models,
    build: |model, faults, seed| {
        let config = match model {
            "fw102c" => Fw102cConfig::fw102c(),
            "fw212c" => Fw102cConfig::fw212c(),
            _ => return None,
        };
        Some(Box::new(Fw102cDevice::new(config, faults, seed)))
    },
    at_speed: None,
    on_bus: None,
    motion: None,
};

#[cfg(test)]
mod tests {
    use super::*;

    fn show(bytes: &[u8]) -> String {
        bytes.escape_ascii().to_string()
    }

    fn dev(config: Fw102cConfig, faults: FaultProfile) -> Fw102cDevice {
        Fw102cDevice::new(config, faults, 1)
    }

    /// Sends `send` at `t` and checks the exact bytes that come back.
    fn expect(d: &mut Fw102cDevice, t: f64, send: &[u8], want: &[u8]) {
        assert_eq!(show(&d.receive(t, send)), show(want), "sent {}", show(send));
    }

    /// Ticks to `t` and checks the exact bytes that come back.
    fn expect_tick(d: &mut Fw102cDevice, t: f64, want: &[u8]) {
        assert_eq!(show(&d.tick(t)), show(want), "tick at {t}");
    }

    /// The time a move of `slots` (signed) takes at `speed`, plus the settle time.
    fn move_s(c: &Fw102cConfig, speed: WheelSpeed, slots: f64) -> f64 {
        let p = Profile {
            start: 0.0,
            target: slots,
            t0_s: 0.0,
            v: speed.velocity_slots_per_s,
            a: speed.acceleration_slots_per_s2,
        };
        p.duration_s() + c.settle_s
    }

    /// The next event is at `want`, within 1e-9 s (the device adds the start time, duration
    /// and settle in another order than the test).
    fn next_at(d: &Fw102cDevice, want: f64) {
        let next = d.next_event_s();
        assert!(next.is_some_and(|t| (t - want).abs() < 1e-9), "{next:?}");
    }

    /// Every device fault at probability `p` (`thermal_duty` does not apply).
    fn all_faults(p: f64) -> FaultProfile {
        FaultProfile {
            drop_reply: p,
            corrupt_reply: p,
            duplicate_reply: p,
            spurious_busy: p,
            stall: p,
            spontaneous_reset: p,
            ..FaultProfile::default()
        }
    }

    /// The default profile with one change.
    fn with(change: fn(&mut FaultProfile)) -> FaultProfile {
        let mut p = FaultProfile::default();
        change(&mut p);
        p
    }

    fn slot(d: &Fw102cDevice, t: f64) -> Option<usize> {
        match d.truth(t) {
            Truth::Slot { slot } => slot,
            other => panic!("{other:?}"),
        }
    }

    /// Queries answer echo, answer line, prompt, byte for byte: `*idn?`, `pos?` (1 at power-on),
    /// `pcount?` (6 and 12), and the default settings; `save` and an empty line give echo and
    /// prompt only.
    #[test]
    fn queries_echo_answer_prompt() {
        let mut d = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        assert!(d.on_open(0.0).is_empty());
        let idn = b"*idn?\rTHORLABS FW102C/FW212C Filter Wheel version 1.07\r> ";
        expect(&mut d, 0.0, b"*idn?\r", idn);
        expect(&mut d, 0.0, b"pos?\r", b"pos?\r1\r> ");
        expect(&mut d, 0.0, b"pcount?\r", b"pcount?\r6\r> ");
        expect(&mut d, 0.0, b"speed?\r", b"speed?\r1\r> ");
        expect(&mut d, 0.0, b"trig?\r", b"trig?\r0\r> ");
        expect(&mut d, 0.0, b"sensors?\r", b"sensors?\r0\r> ");
        expect(&mut d, 0.0, b"baud?\r", b"baud?\r1\r> ");
        expect(&mut d, 0.0, b"save\r", b"save\r> ");
        expect(&mut d, 0.0, b"\r", b"\r> ");
        assert_eq!(slot(&d, 0.0), Some(0));
        assert_eq!(d.baud(), 115_200);
        let mut d = dev(Fw102cConfig::fw212c(), FaultProfile::default());
        expect(&mut d, 0.0, b"pcount?\r", b"pcount?\r12\r> ");
        assert!(d.describe().contains("FW212C"), "{}", d.describe());
    }

    /// `pos=4` from 1 on six slots (half a turn, forward) echoes at once and prompts exactly
    /// when the profile plus settle says: checked 1 ms either side (the tolerance only keeps
    /// the check away from the exact boundary). The wheel is between slots meanwhile.
    /// `pos=3` from 4 then goes one slot back, the short way, in the one-slot time.
    #[test]
    fn move_prompts_after_the_profile_time() {
        let c = Fw102cConfig::fw102c();
        let mut d = dev(c, FaultProfile::default());
        expect(&mut d, 1.0, b"pos=4\r", b"pos=4\r");
        let end = 1.0 + move_s(&c, c.high, 3.0);
        assert!((1.2..1.3).contains(&(end - 1.0)), "{end}");
        next_at(&d, end);
        assert_eq!(slot(&d, end - 0.5), None);
        expect_tick(&mut d, end - 1e-3, b"");
        expect_tick(&mut d, end + 1e-3, b"> ");
        assert_eq!(slot(&d, end + 1e-3), Some(3));
        expect(&mut d, 3.0, b"pos?\r", b"pos?\r4\r> ");
        expect(&mut d, 3.0, b"pos=3\r", b"pos=3\r");
        let end = 3.0 + move_s(&c, c.high, -1.0);
        assert!((0.3..0.7).contains(&(end - 3.0)), "{end}");
        expect_tick(&mut d, end - 1e-3, b"");
        expect_tick(&mut d, end + 1e-3, b"> ");
        // From 3 to 6 is half a turn: forward, 3 slots, not 3 back.
        expect(&mut d, 5.0, b"pos=6\r", b"pos=6\r");
        next_at(&d, 5.0 + move_s(&c, c.high, 3.0));
        // From 6 to 1 is one slot forward across the boundary.
        expect(&mut d, 10.0, b"pos=1\r", b"> pos=1\r");
        next_at(&d, 10.0 + move_s(&c, c.high, 1.0));
        // To where it already is: prompt at once.
        expect(&mut d, 20.0, b"pos=1\r", b"> pos=1\r> ");
    }

    /// `speed=0` makes the same move take the slow profile's time (checked within 1 ms, see
    /// above), which is longer than the high-speed time; `speed=1` restores it.
    #[test]
    fn slow_speed_moves_slower() {
        let c = Fw102cConfig::fw102c();
        let mut d = dev(c, FaultProfile::default());
        expect(&mut d, 0.0, b"speed=0\r", b"speed=0\r> ");
        expect(&mut d, 0.0, b"speed?\r", b"speed?\r0\r> ");
        expect(&mut d, 0.0, b"pos=2\r", b"pos=2\r");
        let slow = move_s(&c, c.slow, 1.0);
        assert!(slow > move_s(&c, c.high, 1.0) + 0.3, "{slow}");
        expect_tick(&mut d, slow - 1e-3, b"");
        expect_tick(&mut d, slow + 1e-3, b"> ");
        expect(&mut d, 5.0, b"speed=1\r", b"speed=1\r> ");
        expect(&mut d, 5.0, b"pos=3\r", b"pos=3\r");
        next_at(&d, 5.0 + move_s(&c, c.high, 1.0));
    }

    /// Bad arguments give `CMD_ARG_INVALID`, unknown commands (including upper case, a
    /// query-only or set-only form, non-ASCII bytes) `CMD_NOT_DEFINED`, each after the echo and
    /// before the prompt; nothing changes.
    #[test]
    fn errors() {
        let mut d = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        let arg = "pos=7|pos=0|pos=|pos=x|pos=-1|pos=1234567890|speed=2|pcount=8|trig=1=1";
        let undefined = "foo|POS?|*idn=1|save?|pos|speed =1|\u{ff}?";
        for (list, error) in [(arg, "CMD_ARG_INVALID"), (undefined, "CMD_NOT_DEFINED")] {
            for bad in list.split('|') {
                let want = format!("{bad}\rCommand error {error}\r> ");
                expect(&mut d, 0.0, format!("{bad}\r").as_bytes(), want.as_bytes());
            }
        }
        expect(&mut d, 0.0, b"pos?\r", b"pos?\r1\r> ");
        expect(&mut d, 0.0, b"speed?\r", b"speed?\r1\r> ");
    }

    /// A script sent one byte at a time gives the same bytes as sent at once; `\r\n` works
    /// like `\r` (the `\n` is not echoed); a line over 64 bytes is discarded silently while one
    /// of 64 is answered.
    #[test]
    fn framing() {
        let script = b"*idn?\rpos=2\rpos?\r";
        let mut a = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        let mut b = a.clone();
        let whole = [a.receive(0.0, script), a.tick(5.0)].concat();
        let mut bytes: Vec<u8> = script.iter().flat_map(|&x| b.receive(0.0, &[x])).collect();
        bytes.extend(b.tick(5.0));
        assert_eq!(show(&bytes), show(&whole));
        assert!(whole.ends_with(b"pos=2\rpos?\r> 2\r> "), "{}", show(&whole));
        expect(&mut a, 6.0, b"pos?\r\n", b"pos?\r2\r> ");
        expect(&mut a, 6.0, b"speed=0\r\n", b"speed=0\r> ");
        expect(&mut a, 6.0, b"\nspeed?\r\n", b"speed?\r0\r> ");
        expect(&mut a, 6.0, &[[b'a'; 65].as_slice(), b"\r"].concat(), b"");
        let mut want = vec![b'a'; 64];
        want.extend_from_slice(b"\rCommand error CMD_NOT_DEFINED\r> ");
        expect(&mut a, 6.0, &[[b'a'; 64].as_slice(), b"\r"].concat(), &want);
        expect(&mut a, 6.0, b"pos?\r", b"pos?\r2\r> ");
    }

    /// Lines that arrive during a move are echoed at once and answered in order after it:
    /// `pos?` gets the new position right after the move's prompt, a queued `pos=` starts
    /// exactly when the first move ended (prompt at the sum of both times, within 1 ms).
    #[test]
    fn commands_during_a_move_wait_for_it() {
        let c = Fw102cConfig::fw212c();
        let mut d = dev(c, FaultProfile::default());
        expect(&mut d, 0.0, b"pos=7\r", b"pos=7\r");
        let first = move_s(&c, c.high, 6.0);
        expect(&mut d, 0.2, b"pos?\rpos=8\rpos?\r", b"pos?\rpos=8\rpos?\r");
        expect_tick(&mut d, first - 1e-3, b"");
        expect_tick(&mut d, first + 1e-3, b"> 7\r> ");
        let second = first + move_s(&c, c.high, 1.0);
        expect_tick(&mut d, second - 1e-3, b"");
        expect(&mut d, second + 1e-3, b"", b"> 8\r> ");
        assert_eq!(slot(&d, second + 1e-3), Some(7));
    }

    /// A stall stops the wheel one slot short along its way (1 to 4 ends at 3; 3 back to 1 ends
    /// at 2); the prompt still comes at the full move's time (within 1 ms, see above) and `pos?`
    /// reports the truth. A one-slot move does not move at all.
    #[test]
    fn stall_jams_one_slot_short() {
        let c = Fw102cConfig::fw102c();
        let mut d = dev(c, with(|f| f.stall = 1.0));
        expect(&mut d, 0.0, b"pos=4\r", b"pos=4\r");
        let end = move_s(&c, c.high, 3.0);
        expect_tick(&mut d, end - 1e-3, b"");
        expect_tick(&mut d, end + 1e-3, b"> ");
        assert_eq!(slot(&d, end + 1e-3), Some(2));
        expect(&mut d, 3.0, b"pos?\r", b"pos?\r3\r> ");
        // Back from 3 to 1 stops at 2.
        expect(&mut d, 3.0, b"pos=1\r", b"pos=1\r");
        expect(&mut d, 10.0, b"pos?\rpos=3\r", b"> pos?\r2\r> pos=3\r");
        expect(&mut d, 20.0, b"pos?\r", b"> pos?\r2\r> ");
    }

    /// A spontaneous reset when a move ends restores the saved settings (high speed) and sends
    /// the wheel back to position 1 (a silent move at the saved speed, between slots meanwhile).
    #[test]
    fn reset_returns_to_position_one() {
        let c = Fw102cConfig::fw102c();
        let mut d = dev(c, with(|f| f.spontaneous_reset = 1.0));
        expect(&mut d, 0.0, b"speed=0\r", b"speed=0\r> ");
        expect(&mut d, 0.0, b"speed?\r", b"speed?\r0\r> ");
        expect(&mut d, 0.0, b"pos=3\r", b"pos=3\r");
        let end = move_s(&c, c.slow, 2.0);
        expect_tick(&mut d, end + 1e-6, b"> ");
        let back = end + move_s(&c, c.high, -2.0);
        next_at(&d, back);
        assert_eq!(slot(&d, back - 0.01), None);
        expect_tick(&mut d, back + 1e-6, b"");
        assert_eq!(slot(&d, back + 1e-6), Some(0));
        expect(&mut d, back + 1e-6, b"pos?\r", b"pos?\r1\r> ");
        expect(&mut d, back + 1e-6, b"speed?\r", b"speed?\r1\r> ");
    }

    /// `save` keeps settings over a power cycle, which puts the wheel at position 1; settings
    /// changed after the save are lost.
    #[test]
    fn save_and_power_cycle() {
        let mut d = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        let set = b"speed=0\rtrig=1\rsensors=1\rbaud=0\rsave\rspeed=1\rtrig=0\rpos=3\r";
        d.receive(0.0, set);
        expect(&mut d, 10.0, b"pos?\r", b"> pos?\r3\r> ");
        expect(&mut d, 10.0, b"speed?\r", b"speed?\r1\r> ");
        d.power_cycle(11.0);
        assert_eq!(slot(&d, 11.0), Some(0));
        let want = b"pos?\r1\r> speed?\r0\r> trig?\r1\r> sensors?\r1\r> baud?\r0\r> ";
        let ask = b"pos?\rspeed?\rtrig?\rsensors?\rbaud?\r";
        expect(&mut d, 11.0, ask, want);
        let mut d = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        d.receive(0.0, b"speed=0\r");
        d.power_cycle(1.0);
        expect(&mut d, 1.0, b"speed?\r", b"speed?\r1\r> ");
    }

    /// `spurious_busy` holds a command back exactly 0.5 s (its echo is immediate);
    /// `pcount=12` on a six-slot wheel puts position 2 between slots.
    #[test]
    fn busy_delay_and_pcount() {
        let mut d = dev(Fw102cConfig::fw102c(), with(|f| f.spurious_busy = 1.0));
        expect(&mut d, 1.0, b"pos?\r", b"pos?\r");
        expect_tick(&mut d, 1.499, b"");
        expect_tick(&mut d, 1.5, b"1\r> ");
        let mut d = dev(Fw102cConfig::fw102c(), FaultProfile::default());
        d.receive(0.0, b"pcount=12\rpos=2\r");
        assert_eq!(slot(&d, 10.0), None);
        expect(&mut d, 10.0, b"pos?\rpos=3\r", b"> pos?\r2\r> pos=3\r");
        assert_eq!(slot(&d, 20.0), Some(1));
    }

    /// A session under every device fault gives the same bytes for the same seed and different
    /// bytes for another seed.
    #[test]
    fn seeded_faults_are_reproducible() {
        let p = all_faults(0.2);
        let run = |seed| {
            let mut d = Fw102cDevice::new(Fw102cConfig::fw102c(), p, seed);
            let mut out = Vec::new();
            for i in 0..60 {
                let t = f64::from(i) * 3.0;
                let line = format!("pos={}\rpos?\rspeed={}\r", i % 6 + 1, i % 2);
                out.extend(d.receive(t, line.as_bytes()));
                out.extend(d.tick(t + 2.9));
            }
            out
        };
        assert_eq!(run(9), run(9));
        assert_ne!(run(9), run(10));
    }

    /// Random bytes (with many `\r`, digits and command fragments), random chunking and time
    /// steps, under every fault, never panic; the queue stays bounded and every call is safe.
    #[test]
    fn random_bytes_never_panic() {
        let mut dice = Dice::new(42);
        let p = all_faults(0.1);
        let words: [&[u8]; 6] = [b"pos=", b"pcount=", b"speed?", b"\r", b"\n", b"save"];
        for config in [Fw102cConfig::fw102c(), Fw102cConfig::fw212c()] {
            let mut d = Fw102cDevice::new(config, p, 7);
            let mut t = 0.0;
            for _ in 0..20_000 {
                let mut bytes = Vec::new();
                for _ in 0..dice.index(12) {
                    match dice.index(4) {
                        0 => bytes.extend_from_slice(words[dice.index(words.len())]),
                        1 => bytes.push(b'0' + dice.index(14) as u8),
                        _ => bytes.push(dice.byte()),
                    }
                }
                t += dice.uniform() * 0.3;
                d.receive(t, &bytes);
                d.tick(t);
                let _ = (d.truth(t), d.next_event_s());
                assert!(d.queue.len() <= MAX_QUEUED && d.line.len() <= MAX_LINE);
                if dice.chance(0.001) {
                    d.power_cycle(t);
                }
            }
        }
    }
}
