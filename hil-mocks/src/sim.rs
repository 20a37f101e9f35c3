//! What every simulated serial device offers the transport server ([`crate::serve`]) and the
//! tests: bytes in and out on simulated time, the next time something falls due, what the host
//! sees when it opens the port, a power cycle, and the ground truth a test checks a driver
//! against.

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

/// A device simulated at the byte level.
pub trait Simulator: Send + 'static {
    /// A short description, such as `"elliptec ELL14 at address 0"`.
    fn describe(&self) -> String;
    /// The line rate the real device uses (the server paces output at baud / 10 bytes per s).
    fn baud(&self) -> u32;
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
