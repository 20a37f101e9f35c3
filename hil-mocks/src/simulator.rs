//! What every simulated serial device offers the transport server ([`crate::serve`]) and the
//! tests: bytes in and out on simulated time, the next time something falls due, what the host
//! sees when it opens the port, a power cycle, and the ground truth a test checks a driver
//! against; and a dialect's simulator descriptor ([`SimDialect`]), which each simulator
//! module declares as its `SIM`.

use crate::faults::FaultProfile;

/// Where the mechanism really is (what the optics see), for tests.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Truth {
    /// A rotator's output angle, radians in `[0, 2 pi)`.
    Angle {
        /// The angle.
        output_rad: f64,
        /// Whether it is moving.
        moving: bool,
    },
    /// A wheel's or slider's slot (`None` between slots or while moving).
    Slot {
        /// The slot, from 0.
        slot: Option<usize>,
    },
}

/// What a simulator's request scanner finds at the front of its input buffer.
#[derive(Debug, Clone, PartialEq)]
pub enum Scan<T> {
    /// Not enough bytes for a whole request yet.
    NeedMore,
    /// The first byte starts no request (it is dropped: resynchronisation).
    Skip,
    /// A whole request, decoded as `T`, of this many bytes.
    Complete(T, usize),
}

/// The next whole request at the front of `pending` by `scan`, taken off the buffer with its
/// bytes; bytes that start no request are dropped first. `None` when the buffer holds no whole
/// request (the rest stays for later bytes).
pub fn next_request<T>(
    pending: &mut Vec<u8>,
    scan: impl Fn(&[u8]) -> Scan<T>,
) -> Option<(T, Vec<u8>)> {
    while !pending.is_empty() {
        match scan(pending) {
            Scan::NeedMore => return None,
            Scan::Skip => {
                pending.remove(0);
            }
            Scan::Complete(request, n) => {
                let n = n.min(pending.len());
                return Some((request, pending.drain(..n).collect()));
            }
        }
    }
    None
}

/// A device simulated at the byte level.
pub trait Simulator: Send + 'static {
    /// A short description, such as `"elliptec ELL14 at address 0"`.
    fn describe(&self) -> String;
    /// The line rate the real device uses.
    fn baud(&self) -> u32;
    /// How long one byte takes between host and device, seconds: the server paces both ways
    /// by it. By default a UART's ten bits (8N1) at [`Simulator::baud`].
    fn seconds_per_byte(&self) -> f64 {
        10.0 / f64::from(self.baud().max(1))
    }
    /// Feeds the host's bytes at `now_s`; returns the device's bytes (events that fell due,
    /// then replies, in order). Never panics on any input.
    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8>;
    /// Advances to `now_s`; returns the bytes that fell due (held-back replies, events).
    fn tick(&mut self, now_s: f64) -> Vec<u8>;
    /// The next time [`Simulator::tick`] has something to say, if any.
    fn next_event_s(&self) -> Option<f64>;
    /// The bytes a host finds when it opens the port (a boot notice, or nothing).
    fn on_open(&mut self, now_s: f64) -> Vec<u8>;
    /// A power cycle (unplug and replug): motion, datum and settings not saved are lost.
    fn power_cycle(&mut self, now_s: f64);
    /// The true state at `now_s`.
    fn truth(&self, now_s: f64) -> Truth;
}

/// A boxed simulator (a device chosen at run time) is served like any other.
impl Simulator for Box<dyn Simulator> {
    fn describe(&self) -> String {
        (**self).describe()
    }
    fn baud(&self) -> u32 {
        (**self).baud()
    }
    fn seconds_per_byte(&self) -> f64 {
        (**self).seconds_per_byte()
    }
    fn receive(&mut self, now_s: f64, bytes: &[u8]) -> Vec<u8> {
        (**self).receive(now_s, bytes)
    }
    fn tick(&mut self, now_s: f64) -> Vec<u8> {
        (**self).tick(now_s)
    }
    fn next_event_s(&self) -> Option<f64> {
        (**self).next_event_s()
    }
    fn on_open(&mut self, now_s: f64) -> Vec<u8> {
        (**self).on_open(now_s)
    }
    fn power_cycle(&mut self, now_s: f64) {
        (**self).power_cycle(now_s)
    }
    fn truth(&self, now_s: f64) -> Truth {
        (**self).truth(now_s)
    }
}

/// Builds a simulator of one model (lower case, as [`SimDialect::models`] spells it) with
/// device faults and a seed; `None` for a model the dialect does not have.
pub type BuildSimulator = fn(&str, FaultProfile, u64) -> Option<Box<dyn Simulator>>;

/// Builds a rotator simulator of one model moving and homing at `deg_s` degrees per second
/// (a demo's or a test's speed, not the real mount's; a simulator may cap it where its
/// protocol cannot express the speed, and says so in its documentation) with device faults
/// and a seed; `None` for a model the dialect does not have or that is not a rotator.
pub type BuildAtSpeed = fn(&str, f64, FaultProfile, u64) -> Option<Box<dyn Simulator>>;

/// Builds the simulated devices of one model at several bus addresses on one port (each
/// valid for the dialect's bus) with device faults and a seed; `None` for a model the dialect
/// does not have.
pub type BuildOnBus = fn(&str, &[u8], FaultProfile, u64) -> Option<Box<dyn Simulator>>;

/// The simulators of one serial dialect, keyed by the dialect's name in
/// `polar_drivers::registry::DIALECTS`.
#[derive(Debug, Clone, Copy)]
pub struct SimDialect {
    /// The dialect's name (`native`, `elliptec`, ...).
    pub dialect: &'static str,
    /// The models simulated, lower case; the first is the default.
    pub models: &'static [&'static str],
    /// The constructor.
    pub build: BuildSimulator,
    /// The constructor of its rotators at a chosen speed (the engine's simulated rig, whose
    /// plan sets `simulation.stage_deg_per_s`); `None`: the dialect's rotators run at their
    /// real speed only.
    pub at_speed: Option<BuildAtSpeed>,
    /// The constructor of several devices on one port at chosen addresses (`simulate stage
    /// --address`); `None`: one device per port, at the dialect's default address.
    pub on_bus: Option<BuildOnBus>,
    /// How its rotators built by `at_speed` move, for the continuous planner's stage limits;
    /// `None`: not known here (a plan must give them).
    pub motion: Option<SimMotion>,
}

/// How a dialect's simulated rotators move when built at a cruise speed
/// ([`SimDialect::at_speed`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimMotion {
    /// Seconds from rest to the cruise speed (the acceleration is the speed over this).
    pub ramp_s: f64,
    /// The fastest its velocity mode spins, degrees per second.
    pub max_spin_deg_per_s: f64,
}
