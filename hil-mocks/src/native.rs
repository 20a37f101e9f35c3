//! Our firmware's stage or filter wheel, simulated at the byte level
//! (`firmware-protocol/SPEC.md`): the host's bytes go in with the simulated time, the device's
//! bytes come out, including the motion-done events that fall due as time passes.

use crate::faults::{Dice, DutyCycle, FaultProfile};
use crate::motion::{output_from_motor, Profile, Ramp};
use crate::simulator::{SimDialect, SimMotion, Simulator, Truth};
use polar_firmware_protocol::{
    encode_vec, BootReason, Command, Decoder, DeviceKind, ErrorCode, Packet, Reply, StatusFlags,
    PROTOCOL_VERSION,
};

/// What the simulated device is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NativeConfig {
    /// Rotator or filter wheel.
    pub kind: DeviceKind,
    /// Encoder counts per output turn.
    pub counts_per_turn: u32,
    /// Slots (filter wheel), 0 for a rotator.
    pub slots: u8,
    /// Serial number.
    pub serial: u32,
    /// Cruise velocity at boot, counts/s.
    pub velocity_counts_per_s: u32,
    /// Acceleration at boot, counts/s^2.
    pub acceleration_counts_per_s2: u32,
    /// Time homing takes, seconds.
    pub homing_s: f64,
    /// Gear backlash between motor and output, counts.
    pub backlash_counts: f64,
    /// Encoder noise (standard deviation), counts.
    pub encoder_noise_counts: f64,
}

impl NativeConfig {
    /// A rotation stage like a small worm-gear mount: 144000 counts per turn (0.0025 deg),
    /// 60 deg/s, 0.5 s homing, 0.05 deg backlash, 0.3 count encoder noise.
    pub fn rotator() -> Self {
        NativeConfig {
            kind: DeviceKind::Rotator,
            counts_per_turn: 144_000,
            slots: 0,
            serial: 0x5000_0001,
            velocity_counts_per_s: 24_000,
            acceleration_counts_per_s2: 96_000,
            homing_s: 0.5,
            backlash_counts: 20.0,
            encoder_noise_counts: 0.3,
        }
    }

    /// A six-slot filter wheel.
    pub fn wheel() -> Self {
        NativeConfig {
            kind: DeviceKind::FilterWheel,
            counts_per_turn: 6_000,
            slots: 6,
            serial: 0x5000_0002,
            velocity_counts_per_s: 6_000,
            acceleration_counts_per_s2: 24_000,
            homing_s: 1.0,
            backlash_counts: 0.0,
            encoder_noise_counts: 0.0,
        }
    }
}

/// The simulated device.
#[derive(Debug, Clone)]
pub struct NativeDevice {
    config: NativeConfig,
    faults: FaultProfile,
    dice: Dice,
    decoder: Decoder<Command>,
    velocity: f64,
    acceleration: f64,
    /// Motor position when idle, counts.
    motor: f64,
    /// Direction of the last motion (+1 / -1).
    direction: f64,
    homed: bool,
    stalled: bool,
    /// The move in progress and the command that started it.
    motion: Option<(Profile, u8)>,
    /// Homing in progress: its end time and the command's seq.
    homing: Option<(f64, u8)>,
    /// Velocity mode: the ramp, the seq of the `Spin` that set it, and whether it is a `Stop`
    /// ramping down to rest (then a MotionDone follows).
    spin: Option<Spin>,
    /// The armed position-compare trigger.
    trigger: Option<TriggerArm>,
    duty: DutyCycle,
}

/// Velocity mode in progress.
#[derive(Debug, Clone, Copy)]
struct Spin {
    ramp: Ramp,
    seq: u8,
    stopping: bool,
}

/// An armed position-compare trigger: pulse `next` fires when the position crosses
/// `first + next * interval` moving in `interval`'s direction.
#[derive(Debug, Clone, Copy)]
struct TriggerArm {
    first: f64,
    interval: f64,
    pulses: u32,
    next: u32,
    seq: u8,
    /// Crossings are searched from this time on.
    checked_s: f64,
}

impl TriggerArm {
    fn target(&self) -> f64 {
        self.first + self.next as f64 * self.interval
    }
}

/// The fastest a simulated rotator spins, turns per second (720 deg/s).
pub const MAX_SPIN_TURNS_PER_S: f64 = 2.0;

impl NativeDevice {
    /// A device at power-on (unhomed, at a random position), faults from `faults`, all randomness
    /// from `seed`.
    pub fn new(config: NativeConfig, faults: FaultProfile, seed: u64) -> Self {
        let mut dice = Dice::new(seed);
        let motor = (dice.uniform() * config.counts_per_turn as f64).floor();
        NativeDevice {
            velocity: config.velocity_counts_per_s as f64,
            acceleration: config.acceleration_counts_per_s2 as f64,
            config,
            faults,
            dice,
            decoder: Decoder::new(),
            motor,
            direction: 1.0,
            homed: false,
            stalled: false,
            motion: None,
            homing: None,
            spin: None,
            trigger: None,
            duty: DutyCycle::default(),
        }
    }

    /// The output shaft's true angle in counts at `now_s` (what the optics see), which differs
    /// from the reported position by the backlash and the encoder noise.
    pub fn true_output_counts(&self, now_s: f64) -> f64 {
        let direction = match (self.spin, self.motion) {
            (Some(s), _) if s.ramp.velocity(now_s) != 0.0 => s.ramp.velocity(now_s).signum(),
            (_, Some((p, _))) => p.direction(),
            _ => self.direction,
        };
        output_from_motor(
            self.position_now(now_s),
            direction,
            self.config.backlash_counts,
        )
    }

    /// Whether a motion or homing is in progress at `now_s`.
    pub fn busy(&self, now_s: f64) -> bool {
        self.motion.as_ref().is_some_and(|(p, _)| now_s < p.end_s())
            || self.homing.is_some_and(|(end, _)| now_s < end)
            || self.spin.is_some()
    }

    /// The power-on notice a host sees when it opens the port after a boot.
    pub fn boot_notice(&self) -> Vec<u8> {
        encode_vec(
            0,
            &Reply::Boot {
                reason: BootReason::PowerOn,
            },
        )
    }

    /// Feeds the host's bytes at `now_s`; returns the device's bytes: events that fell due,
    /// then the replies, in order. Bytes that do not decode are ignored, as the firmware does
    /// (without a valid sequence number there is nobody to answer).
    pub fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        let mut out = self.tick(now_s);
        for &b in bytes {
            if let Some(Ok(packet)) = self.decoder.feed(b) {
                out.extend(self.handle(now_s, packet));
            }
        }
        out
    }

    /// Advances to `now_s`: returns the events (trigger pulses, MotionDone) that fell due.
    pub fn tick(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = self.fire_triggers(now_s);
        if let Some(s) = self.spin {
            if s.stopping && now_s >= s.ramp.settled_s() {
                self.spin = None;
                self.motor = s.ramp.position(now_s);
                let position_counts = self.reported(self.motor);
                out.extend(self.send(s.seq, Reply::MotionDone { position_counts }));
            }
        }
        if let Some((end, seq)) = self.homing {
            if now_s >= end {
                self.homing = None;
                self.motor = 0.0;
                self.direction = 1.0;
                self.homed = true;
                out.extend(self.send(seq, Reply::MotionDone { position_counts: 0 }));
            }
        }
        if let Some((p, seq)) = self.motion {
            if now_s >= p.end_s() {
                self.motion = None;
                self.motor = p.target;
                self.direction = p.direction();
                let position_counts = self.reported(self.motor);
                out.extend(self.send(seq, Reply::MotionDone { position_counts }));
            }
        }
        out
    }

    /// The encoder reading for a motor position.
    fn reported(&mut self, motor: f64) -> i32 {
        let noisy = motor + self.config.encoder_noise_counts * self.dice.normal();
        noisy.round().clamp(i32::MIN as f64, i32::MAX as f64) as i32
    }

    /// Encodes a reply, through the reply faults.
    fn send(&mut self, seq: u8, reply: Reply) -> Vec<u8> {
        let bytes = encode_vec(seq, &reply);
        self.dice.reply_faults(&self.faults, bytes)
    }

    fn nack(&mut self, seq: u8, code: ErrorCode) -> Vec<u8> {
        self.send(seq, Reply::Nack { code })
    }

    fn position_now(&self, now_s: f64) -> f64 {
        if let Some(s) = &self.spin {
            return s.ramp.position(now_s);
        }
        match &self.motion {
            Some((p, _)) => p.position(now_s),
            None => self.motor,
        }
    }

    /// The time, in `[from_s, to_s]`, at which the position first reaches `target` moving in
    /// `direction`, if it does by `to_s` (the position is monotonic over one motion; 60
    /// bisections resolve the time to far below a microsecond).
    fn crossing_s(&self, from_s: f64, to_s: f64, target: f64, direction: f64) -> Option<f64> {
        let past = |t: f64| direction * (self.position_now(t) - target) >= 0.0;
        if to_s < from_s || past(from_s) || !past(to_s) {
            return None;
        }
        let (mut lo, mut hi) = (from_s, to_s);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if past(mid) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        Some(hi)
    }

    /// The latest time the current motion can cross a trigger position: the end of a move or of
    /// a stop ramp, an hour ahead for a spin, nothing when idle.
    fn motion_horizon_s(&self, from_s: f64) -> Option<f64> {
        if let Some(s) = self.spin {
            return Some(if s.stopping {
                s.ramp.settled_s()
            } else {
                from_s.max(s.ramp.settled_s()) + 3600.0
            });
        }
        self.motion.map(|(p, _)| p.end_s())
    }

    /// The trigger pulses whose positions the axis crossed up to `now_s`, as events.
    fn fire_triggers(&mut self, now_s: f64) -> Vec<u8> {
        let mut out = Vec::new();
        while let Some(mut arm) = self.trigger {
            let direction = arm.interval.signum();
            let Some(t) = self.crossing_s(arm.checked_s, now_s, arm.target(), direction) else {
                arm.checked_s = arm.checked_s.max(now_s);
                self.trigger = Some(arm);
                break;
            };
            let position_counts = self.reported(arm.target());
            let time_us = ((t * 1e6).round() as u64 & u64::from(u32::MAX)) as u32;
            out.extend(self.send(
                arm.seq,
                Reply::Trigger {
                    index: arm.next,
                    position_counts,
                    time_us,
                },
            ));
            arm.next += 1;
            arm.checked_s = t;
            self.trigger = (arm.next < arm.pulses).then_some(arm);
        }
        out
    }

    /// When the next trigger pulse falls due under the current motion.
    fn next_trigger_s(&self) -> Option<f64> {
        let arm = self.trigger?;
        let horizon = self.motion_horizon_s(arm.checked_s)?;
        self.crossing_s(arm.checked_s, horizon, arm.target(), arm.interval.signum())
    }

    /// Starts a move to `target` (motor counts); a stall fault cuts it half way.
    fn start_move(&mut self, now_s: f64, seq: u8, target: f64) -> Vec<u8> {
        let start = self.motor;
        let mut p = Profile {
            start,
            target,
            t0_s: now_s,
            v: self.velocity,
            a: self.acceleration,
        };
        self.stalled = false;
        if self.dice.chance(self.faults.stall) {
            // The motor stops half way; the firmware notices and reports where it stopped.
            p.target = (start + target) / 2.0;
            self.stalled = true;
        }
        self.duty.record(now_s, p.end_s());
        self.motion = Some((p, seq));
        self.send(seq, Reply::Ack)
    }

    fn reset(&mut self) {
        self.motion = None;
        self.homing = None;
        self.spin = None;
        self.trigger = None;
        self.homed = false;
        self.stalled = false;
        self.decoder.clear();
        self.velocity = self.config.velocity_counts_per_s as f64;
        self.acceleration = self.config.acceleration_counts_per_s2 as f64;
    }

    fn handle(&mut self, now_s: f64, packet: Packet<Command>) -> Vec<u8> {
        let seq = packet.seq;
        let busy = self.busy(now_s);
        let is_motion = matches!(
            packet.message,
            Command::Home
                | Command::MoveAbsolute { .. }
                | Command::MoveRelative { .. }
                | Command::SelectSlot { .. }
        );
        let mut out = if is_motion && self.dice.chance(self.faults.spurious_busy) {
            self.nack(seq, ErrorCode::Busy)
        } else {
            self.command(now_s, seq, busy, packet.message)
        };
        if self.dice.chance(self.faults.spontaneous_reset) {
            self.reset();
            out.extend(self.send(
                0,
                Reply::Boot {
                    reason: BootReason::Watchdog,
                },
            ));
        }
        out
    }

    fn command(&mut self, now_s: f64, seq: u8, busy: bool, command: Command) -> Vec<u8> {
        let c = self.config;
        let rotator = c.kind == DeviceKind::Rotator;
        match command {
            Command::Identify => {
                let reply = Reply::Identity {
                    protocol_version: PROTOCOL_VERSION,
                    firmware: [1, 0, 0],
                    device: c.kind,
                    counts_per_turn: c.counts_per_turn,
                    slots: c.slots,
                    serial: c.serial,
                };
                self.send(seq, reply)
            }
            Command::Home if busy => self.nack(seq, ErrorCode::Busy),
            Command::Home
            | Command::MoveAbsolute { .. }
            | Command::MoveRelative { .. }
            | Command::SelectSlot { .. }
                if self.duty.too_hot(&self.faults, now_s) =>
            {
                self.nack(seq, ErrorCode::OverTemperature)
            }
            Command::Home => {
                self.duty.record(now_s, now_s + c.homing_s);
                self.motion = None;
                self.homing = Some((now_s + c.homing_s, seq));
                self.send(seq, Reply::Ack)
            }
            Command::MoveAbsolute { .. }
            | Command::MoveRelative { .. }
            | Command::SelectSlot { .. }
                if busy =>
            {
                self.nack(seq, ErrorCode::Busy)
            }
            Command::MoveAbsolute { position_counts } => {
                if !rotator {
                    self.nack(seq, ErrorCode::Unsupported)
                } else if !self.homed {
                    self.nack(seq, ErrorCode::NotHomed)
                } else {
                    self.start_move(now_s, seq, position_counts as f64)
                }
            }
            Command::MoveRelative { delta_counts } => {
                if !rotator {
                    self.nack(seq, ErrorCode::Unsupported)
                } else {
                    let target = self.motor + delta_counts as f64;
                    self.start_move(now_s, seq, target)
                }
            }
            Command::SelectSlot { slot } => {
                if rotator {
                    self.nack(seq, ErrorCode::Unsupported)
                } else if slot >= c.slots {
                    self.nack(seq, ErrorCode::OutOfRange)
                } else if !self.homed {
                    self.nack(seq, ErrorCode::NotHomed)
                } else {
                    let target = slot as f64 * c.counts_per_turn as f64 / c.slots as f64;
                    self.start_move(now_s, seq, target)
                }
            }
            Command::Stop if self.spin.is_some_and(|s| !s.stopping) => {
                if let Some(s) = self.spin {
                    let ramp = Ramp {
                        start: s.ramp.position(now_s),
                        v0: s.ramp.velocity(now_s),
                        v1: 0.0,
                        t0_s: now_s,
                        a: self.acceleration,
                    };
                    self.spin = Some(Spin {
                        ramp,
                        seq: s.seq,
                        stopping: true,
                    });
                }
                self.send(seq, Reply::Ack)
            }
            Command::Stop => {
                if let Some((p, s)) = self.motion {
                    if now_s < p.end_s() {
                        self.motion = Some((p.stopped_at(now_s), s));
                    }
                }
                self.send(seq, Reply::Ack)
            }
            Command::GetStatus => {
                let moving = self.busy(now_s);
                let mut flags = 0;
                for (on, bit) in [
                    (self.homed, StatusFlags::HOMED),
                    (moving, StatusFlags::MOVING),
                    (
                        self.spin.is_some_and(|s| !s.stopping),
                        StatusFlags::SPINNING,
                    ),
                    (self.trigger.is_some(), StatusFlags::TRIGGER_ARMED),
                    (self.stalled && !moving, StatusFlags::STALLED),
                    (
                        self.duty.too_hot(&self.faults, now_s),
                        StatusFlags::OVER_TEMPERATURE,
                    ),
                ] {
                    if on {
                        flags |= bit;
                    }
                }
                let position = self.position_now(now_s);
                let position_counts = self.reported(position);
                let slot = if rotator || moving || !self.homed {
                    0xff
                } else {
                    let per = c.counts_per_turn as f64 / c.slots.max(1) as f64;
                    let s = (position / per).round();
                    if (position - s * per).abs() < 0.5 && s >= 0.0 && s < c.slots as f64 {
                        s as u8
                    } else {
                        0xff
                    }
                };
                self.send(
                    seq,
                    Reply::Status {
                        position_counts,
                        flags: StatusFlags(flags),
                        slot,
                    },
                )
            }
            Command::SetMotion {
                velocity_counts_per_s,
                acceleration_counts_per_s2,
            } => {
                if velocity_counts_per_s == 0 || acceleration_counts_per_s2 == 0 {
                    self.nack(seq, ErrorCode::OutOfRange)
                } else {
                    self.velocity = velocity_counts_per_s as f64;
                    self.acceleration = acceleration_counts_per_s2 as f64;
                    self.send(seq, Reply::Ack)
                }
            }
            Command::Spin { .. } | Command::SetTrigger { .. } if !rotator => {
                self.nack(seq, ErrorCode::Unsupported)
            }
            Command::Spin {
                velocity_counts_per_s,
            } => {
                let v = velocity_counts_per_s as f64;
                let max = MAX_SPIN_TURNS_PER_S * c.counts_per_turn as f64;
                if velocity_counts_per_s == 0 || v.abs() > max {
                    self.nack(seq, ErrorCode::OutOfRange)
                } else if !self.homed {
                    self.nack(seq, ErrorCode::NotHomed)
                } else if self.spin.is_none() && busy {
                    self.nack(seq, ErrorCode::Busy)
                } else if self.duty.too_hot(&self.faults, now_s) {
                    self.nack(seq, ErrorCode::OverTemperature)
                } else {
                    let (start, v0) = match self.spin {
                        Some(s) => (s.ramp.position(now_s), s.ramp.velocity(now_s)),
                        None => (self.motor, 0.0),
                    };
                    self.stalled = false;
                    self.spin = Some(Spin {
                        ramp: Ramp {
                            start,
                            v0,
                            v1: v,
                            t0_s: now_s,
                            a: self.acceleration,
                        },
                        seq,
                        stopping: false,
                    });
                    self.send(seq, Reply::Ack)
                }
            }
            Command::SetTrigger {
                first_counts,
                interval_counts,
                pulses,
            } => {
                if pulses == 0 {
                    self.trigger = None;
                    self.send(seq, Reply::Ack)
                } else if interval_counts == 0 {
                    self.nack(seq, ErrorCode::OutOfRange)
                } else {
                    self.trigger = Some(TriggerArm {
                        first: first_counts as f64,
                        interval: interval_counts as f64,
                        pulses,
                        next: 0,
                        seq,
                        checked_s: now_s,
                    });
                    self.send(seq, Reply::Ack)
                }
            }
            Command::Save => self.send(seq, Reply::Ack),
            Command::Reset => {
                let mut out = self.send(seq, Reply::Ack);
                self.reset();
                out.extend(self.send(
                    0,
                    Reply::Boot {
                        reason: BootReason::Command,
                    },
                ));
                out
            }
        }
    }
}

impl Simulator for NativeDevice {
    fn describe(&self) -> String {
        let kind = match self.config.kind {
            DeviceKind::Rotator => "rotator",
            _ => "filter wheel",
        };
        format!("native {kind} serial {:08x}", self.config.serial)
    }

    fn baud(&self) -> u32 {
        115_200
    }

    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        NativeDevice::receive(self, now_s, bytes)
    }

    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        NativeDevice::tick(self, now_s)
    }

    fn next_event_s(&self) -> Option<f64> {
        let homing = self.homing.map(|(end, _)| end);
        let motion = self.motion.map(|(p, _)| p.end_s());
        let stop = self.spin.filter(|s| s.stopping).map(|s| s.ramp.settled_s());
        [homing, motion, stop, self.next_trigger_s()]
            .into_iter()
            .flatten()
            .reduce(f64::min)
    }

    fn on_open(&mut self, _now_s: f64) -> Vec<u8> {
        // The USB-serial bridge resets the controller on open (DTR): motion and datum are lost
        // (the shaft stays where it is) and the host sees a boot notice.
        self.reset();
        self.boot_notice()
    }

    fn power_cycle(&mut self, _now_s: f64) {
        self.reset();
        self.motor = (self.dice.uniform() * self.config.counts_per_turn as f64).floor();
    }

    fn truth(&self, now_s: f64) -> Truth {
        let c = self.config;
        let output = self.true_output_counts(now_s);
        let moving = self.busy(now_s);
        if c.kind == DeviceKind::Rotator {
            let turn = c.counts_per_turn as f64;
            Truth::Angle {
                output_rad: output.rem_euclid(turn) / turn * std::f64::consts::TAU,
                moving,
            }
        } else {
            let per = c.counts_per_turn as f64 / c.slots.max(1) as f64;
            let s = (output / per).round();
            let on_slot = !moving && (output - s * per).abs() < 0.5 && s >= 0.0;
            Truth::Slot {
                slot: on_slot.then_some(s as usize % c.slots.max(1) as usize),
            }
        }
    }
}

/// The native dialect's simulators (`polar_drivers::native::DIALECT`'s models), for
/// [`crate::sim::SIMULATORS`].
pub const SIM: SimDialect = SimDialect {
    dialect: polar_drivers::native::DIALECT.name,
    models: polar_drivers::native::DIALECT.models,
    build: |model, faults, seed| {
        let config = match model {
            "rotator" => NativeConfig::rotator(),
            "wheel" => NativeConfig::wheel(),
            _ => return None,
        };
        Some(Box::new(NativeDevice::new(config, faults, seed)))
    },
    // Cruise at the speed, accelerate to it in 1 / AT_SPEED_RAMP_PER_S s, home in 0.1 s.
    at_speed: Some(|model, deg_s, faults, seed| {
        if model != "rotator" {
            return None;
        }
        let mut config = NativeConfig::rotator();
        let v = (deg_s * f64::from(config.counts_per_turn) / 360.0).round();
        config.velocity_counts_per_s = v.clamp(1.0, f64::from(u32::MAX)) as u32;
        config.acceleration_counts_per_s2 = config
            .velocity_counts_per_s
            .saturating_mul(AT_SPEED_RAMP_PER_S);
        config.homing_s = 0.1;
        Some(Box::new(NativeDevice::new(config, faults, seed)))
    }),
    on_bus: None,
    motion: Some(SimMotion {
        ramp_s: 1.0 / AT_SPEED_RAMP_PER_S as f64,
        max_spin_deg_per_s: MAX_SPIN_TURNS_PER_S * 360.0,
    }),
};

/// A rotator built at a speed ([`SIM`]'s `at_speed`) reaches it in 1 / this many seconds.
pub const AT_SPEED_RAMP_PER_S: u32 = 8;

#[cfg(test)]
mod tests {
    use super::*;
    use polar_firmware_protocol::{next_seq, DecodeError};

    /// A host stub: numbers commands, decodes everything the device says.
    struct Host {
        seq: u8,
        decoder: Decoder<Reply>,
    }

    impl Host {
        fn new() -> Self {
            Host {
                seq: 0,
                decoder: Decoder::new(),
            }
        }

        fn send(
            &mut self,
            dev: &mut NativeDevice,
            now: f64,
            c: Command,
        ) -> (u8, Vec<Result<Packet<Reply>, DecodeError>>) {
            self.seq = next_seq(self.seq);
            let bytes = dev.receive(now, &encode_vec(self.seq, &c));
            (self.seq, self.decode(&bytes))
        }

        fn decode(&mut self, bytes: &[u8]) -> Vec<Result<Packet<Reply>, DecodeError>> {
            bytes.iter().filter_map(|&b| self.decoder.feed(b)).collect()
        }
    }

    fn ok(seq: u8, message: Reply) -> Result<Packet<Reply>, DecodeError> {
        Ok(Packet { seq, message })
    }

    /// Velocity mode and the position-compare trigger: pulses at the armed positions, each at
    /// the time the kinematics say (ramp 0 -> 72000 counts/s at 96000 counts/s^2: position
    /// a t^2 / 2 during the 0.75 s ramp, then 27000 + 72000 (t - 0.75)), latched within the
    /// encoder noise (0.3 counts rms: 3 counts is 10 sigma); Busy for moves while spinning; a
    /// Stop ramps down and ends with MotionDone where v^2 / 2a says.
    #[test]
    fn spin_with_position_compare_trigger() {
        let mut dev = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 5);
        let mut host = Host::new();
        let spin = Command::Spin {
            velocity_counts_per_s: 72_000,
        };
        let (s, r) = host.send(&mut dev, 0.0, spin);
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::NotHomed
                }
            )]
        );
        host.send(&mut dev, 0.0, Command::Home);
        host.decode(&dev.tick(0.5));
        for bad in [0, 288_001, -288_001] {
            let (s, r) = host.send(
                &mut dev,
                1.0,
                Command::Spin {
                    velocity_counts_per_s: bad,
                },
            );
            assert_eq!(
                r,
                vec![ok(
                    s,
                    Reply::Nack {
                        code: ErrorCode::OutOfRange
                    }
                )]
            );
        }
        let arm = Command::SetTrigger {
            first_counts: 1000,
            interval_counts: 8000,
            pulses: 5,
        };
        let (trig, r) = host.send(&mut dev, 1.0, arm);
        assert_eq!(r, vec![ok(trig, Reply::Ack)]);
        let (spin_seq, r) = host.send(&mut dev, 1.0, spin);
        assert_eq!(r, vec![ok(spin_seq, Reply::Ack)]);
        let (s, r) = host.send(&mut dev, 1.1, Command::MoveAbsolute { position_counts: 0 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::Busy
                }
            )]
        );
        let (_, r) = host.send(&mut dev, 1.1, Command::GetStatus);
        let want = StatusFlags::HOMED
            | StatusFlags::MOVING
            | StatusFlags::SPINNING
            | StatusFlags::TRIGGER_ARMED;
        assert!(
            matches!(r[..], [Ok(Packet { message: Reply::Status { flags, .. }, .. })] if flags.0 == want)
        );
        let a = 96_000.0;
        let expected_s = |p: f64| {
            if p <= 27_000.0 {
                1.0 + (2.0 * p / a).sqrt()
            } else {
                1.75 + (p - 27_000.0) / 72_000.0
            }
        };
        let mut pulses = Vec::new();
        while pulses.len() < 5 {
            let t = dev.next_event_s().expect("a pulse is due");
            for packet in host.decode(&dev.tick(t)) {
                pulses.push((packet.unwrap(), t));
            }
        }
        for (k, (packet, t)) in pulses.iter().enumerate() {
            let target = 1000.0 + 8000.0 * k as f64;
            let Reply::Trigger {
                index,
                position_counts,
                time_us,
            } = packet.message
            else {
                panic!("expected a trigger, got {packet:?}");
            };
            assert_eq!((packet.seq, index), (trig, k as u32));
            assert!(
                (position_counts as f64 - target).abs() <= 3.0,
                "{position_counts}"
            );
            assert!((t - expected_s(target)).abs() < 1e-9, "pulse {k} at {t}");
            assert!((time_us as f64 - expected_s(target) * 1e6).abs() <= 1.0);
        }
        let (_, r) = host.send(&mut dev, 2.0, Command::GetStatus);
        assert!(
            matches!(r[..], [Ok(Packet { message: Reply::Status { flags, .. }, .. })] if !flags.has(StatusFlags::TRIGGER_ARMED) && flags.has(StatusFlags::SPINNING))
        );
        // Stop at t = 2.0 (position 27000 + 72000 * 0.25 = 45000): 0.75 s to rest, 27000 on.
        let (s, r) = host.send(&mut dev, 2.0, Command::Stop);
        assert_eq!(r, vec![ok(s, Reply::Ack)]);
        assert_eq!(dev.next_event_s(), Some(2.75));
        let done = host.decode(&dev.tick(2.75));
        assert!(
            matches!(done[..], [Ok(Packet { seq, message: Reply::MotionDone { position_counts } })] if seq == spin_seq && (position_counts - 72_000).abs() <= 3),
            "{done:?}"
        );
        assert!(!dev.busy(2.75));
    }

    /// A negative interval fires on the way down; a filter wheel refuses both commands.
    #[test]
    fn trigger_direction_and_wheel() {
        let mut dev = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 6);
        let mut host = Host::new();
        host.send(&mut dev, 0.0, Command::Home);
        host.decode(&dev.tick(0.5));
        let arm = Command::SetTrigger {
            first_counts: -100,
            interval_counts: -1000,
            pulses: 3,
        };
        let (trig, _) = host.send(&mut dev, 1.0, arm);
        host.send(
            &mut dev,
            1.0,
            Command::Spin {
                velocity_counts_per_s: -36_000,
            },
        );
        let mut seen = Vec::new();
        while seen.len() < 3 {
            let t = dev.next_event_s().expect("a pulse is due");
            seen.extend(host.decode(&dev.tick(t)));
        }
        for (k, p) in seen.iter().enumerate() {
            let p = p.as_ref().unwrap();
            assert_eq!(p.seq, trig);
            assert!(
                matches!(p.message, Reply::Trigger { index, position_counts, .. } if index == k as u32 && (position_counts + 100 + 1000 * k as i32).abs() <= 3)
            );
        }
        let mut wheel = NativeDevice::new(NativeConfig::wheel(), FaultProfile::default(), 7);
        let (s, r) = host.send(&mut wheel, 0.0, arm);
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::Unsupported
                }
            )]
        );
    }

    /// The handshake, homing (Ack now, MotionDone after the homing time), a move that ends
    /// when the trapezoid says, within the encoder noise of the target, Busy while moving,
    /// NotHomed before homing, Status flags.
    #[test]
    fn stage_session() {
        let mut dev = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 3);
        let mut host = Host::new();
        let (s, r) = host.send(&mut dev, 0.0, Command::Identify);
        assert!(
            matches!(r[..], [Ok(Packet { seq, message: Reply::Identity { counts_per_turn: 144_000, protocol_version: 1, .. } })] if seq == s)
        );
        let (s, r) = host.send(
            &mut dev,
            0.0,
            Command::MoveAbsolute {
                position_counts: 1000,
            },
        );
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::NotHomed
                }
            )]
        );
        let (home, r) = host.send(&mut dev, 0.0, Command::Home);
        assert_eq!(r, vec![ok(home, Reply::Ack)]);
        assert!(host.decode(&dev.tick(0.49)).is_empty());
        assert_eq!(
            host.decode(&dev.tick(0.5)),
            vec![ok(home, Reply::MotionDone { position_counts: 0 })]
        );
        // 36000 counts (90 deg) at 24000 counts/s, 96000 counts/s^2: 1.5 + 0.25 s.
        let (mv, r) = host.send(
            &mut dev,
            1.0,
            Command::MoveAbsolute {
                position_counts: 36_000,
            },
        );
        assert_eq!(r, vec![ok(mv, Reply::Ack)]);
        let (s, r) = host.send(&mut dev, 1.5, Command::MoveRelative { delta_counts: 5 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::Busy
                }
            )]
        );
        let (s, r) = host.send(&mut dev, 1.5, Command::GetStatus);
        let Ok(Packet {
            message:
                Reply::Status {
                    flags,
                    position_counts,
                    ..
                },
            seq,
        }) = r[0]
        else {
            panic!("{r:?}")
        };
        assert_eq!(seq, s);
        assert!(flags.has(StatusFlags::HOMED | StatusFlags::MOVING));
        assert!(position_counts > 0 && position_counts < 36_000);
        assert!(host.decode(&dev.tick(2.74)).is_empty());
        let done = host.decode(&dev.tick(2.76));
        let [Ok(Packet {
            seq,
            message: Reply::MotionDone { position_counts },
        })] = done[..]
        else {
            panic!("{done:?}")
        };
        assert_eq!(seq, mv);
        // Encoder noise 0.3 counts: within 2 counts (6.7 sigma).
        assert!((position_counts - 36_000).abs() <= 2, "{position_counts}");
        // The output lags the motor by half the backlash (20 counts) after a positive move.
        assert!((dev.true_output_counts(3.0) - 35_990.0).abs() < 1e-9);
    }

    /// A wheel selects slots only after homing; a slot past the last is OutOfRange; Status
    /// reports the slot; Reset acks, then sends a Boot notice and forgets the homing.
    #[test]
    fn wheel_session_and_reset() {
        let mut dev = NativeDevice::new(NativeConfig::wheel(), FaultProfile::default(), 4);
        let mut host = Host::new();
        let (s, r) = host.send(&mut dev, 0.0, Command::SelectSlot { slot: 2 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::NotHomed
                }
            )]
        );
        host.send(&mut dev, 0.0, Command::Home);
        dev.tick(1.0);
        let (s, r) = host.send(&mut dev, 1.0, Command::SelectSlot { slot: 6 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::OutOfRange
                }
            )]
        );
        let (s, r) = host.send(&mut dev, 1.0, Command::MoveAbsolute { position_counts: 5 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::Unsupported
                }
            )]
        );
        host.send(&mut dev, 1.0, Command::SelectSlot { slot: 2 });
        dev.tick(10.0);
        let (_, r) = host.send(&mut dev, 10.0, Command::GetStatus);
        assert!(
            matches!(
                r[..],
                [Ok(Packet {
                    message: Reply::Status { slot: 2, .. },
                    ..
                })]
            ),
            "{r:?}"
        );
        let (s, r) = host.send(&mut dev, 10.0, Command::Reset);
        assert_eq!(
            r,
            vec![
                ok(s, Reply::Ack),
                ok(
                    0,
                    Reply::Boot {
                        reason: BootReason::Command
                    }
                )
            ]
        );
        let (s, r) = host.send(&mut dev, 10.0, Command::SelectSlot { slot: 1 });
        assert_eq!(
            r,
            vec![ok(
                s,
                Reply::Nack {
                    code: ErrorCode::NotHomed
                }
            )]
        );
    }

    /// Stop decelerates: MotionDone comes early, short of the target.
    #[test]
    fn stop_ends_the_move_early() {
        let mut dev = NativeDevice::new(NativeConfig::rotator(), FaultProfile::default(), 5);
        let mut host = Host::new();
        host.send(&mut dev, 0.0, Command::Home);
        dev.tick(1.0);
        let (mv, _) = host.send(
            &mut dev,
            1.0,
            Command::MoveAbsolute {
                position_counts: 72_000,
            },
        );
        let (s, r) = host.send(&mut dev, 2.0, Command::Stop);
        assert_eq!(r, vec![ok(s, Reply::Ack)]);
        let done = host.decode(&dev.tick(2.5));
        let [Ok(Packet {
            seq,
            message: Reply::MotionDone { position_counts },
        })] = done[..]
        else {
            panic!("{done:?}")
        };
        assert_eq!(seq, mv);
        assert!(
            position_counts > 20_000 && position_counts < 30_000,
            "{position_counts}"
        );
    }

    /// Faults are seeded and do what they say: with every reply corrupted the host sees only
    /// decode errors; dropped replies are silence; a stall reports where it stopped with the
    /// stalled flag; garbage from the host is ignored.
    #[test]
    fn faults_are_reproducible() {
        let corrupt = FaultProfile {
            corrupt_reply: 1.0,
            ..Default::default()
        };
        let mut dev = NativeDevice::new(NativeConfig::rotator(), corrupt, 6);
        let mut host = Host::new();
        for _ in 0..50 {
            let (_, r) = host.send(&mut dev, 0.0, Command::GetStatus);
            assert!(r.iter().all(|x| x.is_err()), "{r:?}");
        }
        let drop = FaultProfile {
            drop_reply: 1.0,
            ..Default::default()
        };
        let mut dev = NativeDevice::new(NativeConfig::rotator(), drop, 6);
        assert!(host.send(&mut dev, 0.0, Command::Identify).1.is_empty());
        let stall = FaultProfile {
            stall: 1.0,
            ..Default::default()
        };
        let mut dev = NativeDevice::new(NativeConfig::rotator(), stall, 7);
        let mut host = Host::new();
        host.send(&mut dev, 0.0, Command::Home);
        dev.tick(1.0);
        host.send(
            &mut dev,
            1.0,
            Command::MoveAbsolute {
                position_counts: 10_000,
            },
        );
        let done = host.decode(&dev.tick(5.0));
        let [Ok(Packet {
            message: Reply::MotionDone { position_counts },
            ..
        })] = done[..]
        else {
            panic!("{done:?}")
        };
        assert!((position_counts - 5_000).abs() <= 2, "{position_counts}");
        let (_, r) = host.send(&mut dev, 5.0, Command::GetStatus);
        let Ok(Packet {
            message: Reply::Status { flags, .. },
            ..
        }) = r[0]
        else {
            panic!("{r:?}")
        };
        assert!(flags.has(StatusFlags::STALLED));
        // Garbage (with and without delimiters) costs nothing; the next command is answered.
        let garbage = [0x13u8, 0x00, 0xff, 0xfe, 0x00, 0x42];
        assert!(dev.receive(5.0, &garbage).is_empty());
        let (s, r) = host.send(&mut dev, 5.0, Command::Save);
        // The first frame after "0x42" without a delimiter is spoiled; the device ignores it.
        assert!(r.is_empty() || r == vec![ok(s, Reply::Ack)], "{r:?}");
        let (s, r) = host.send(&mut dev, 5.0, Command::Save);
        assert_eq!(r, vec![ok(s, Reply::Ack)]);
        // Same seed, same faults.
        let p = FaultProfile {
            drop_reply: 0.5,
            ..Default::default()
        };
        let run = |seed| {
            let mut dev = NativeDevice::new(NativeConfig::rotator(), p, seed);
            let mut host = Host::new();
            (0..40)
                .map(|_| host.send(&mut dev, 0.0, Command::GetStatus).1.len())
                .collect::<Vec<_>>()
        };
        assert_eq!(run(9), run(9));
        assert_ne!(run(9), run(10));
    }
}
