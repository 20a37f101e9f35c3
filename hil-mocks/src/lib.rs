//! Simulated polarimeter devices: byte-level state machines with physical motion and seeded,
//! reproducible faults (`ARCHITECTURE.md`, "Simulated devices").
//!
//! * One module per serial dialect, each declaring its simulators as `SIM` (a
//!   [`simulator::SimDialect`] with the driver's dialect name and models);
//!   [`sim::SIMULATORS`] lists them and [`sim::simulator`] finds one by dialect and model.
//! * [`simulator::Simulator`]: what every device simulator offers the transport and the tests.
//! * [`camera::SimCamera`]: a camera whose frames are rendered from the model through the
//!   simulated stage's true analyzer angle ([`camera::SimScene`] is the ground truth).
//! * [`serve::SimServer`]: serves a simulator over a real pseudo-terminal or in memory, with the
//!   transport faults.
//! * [`motion`]: trapezoidal moves, backlash, encoder noise.
//! * [`faults::FaultProfile`]: the fault knobs, loadable from TOML.
//!
//! The simulators run on simulated time: every call takes `now_s`, so a test steps time
//! exactly and a real-time server maps the wall clock onto it. They never panic on any input
//! bytes.
#![warn(missing_docs)]

pub mod apt;
pub mod camera;
pub mod elliptec;
pub mod faults;
pub mod fw102c;
pub mod motion;
pub mod native;
pub mod serve;
pub mod sim;
pub mod simulator;
pub mod smc100;
pub mod standa;

/// Blocks the thread until `until`, to within a few microseconds: an OS sleep overshoots by
/// its wake-up latency (up to a millisecond on an idle virtual machine), which would make a
/// simulated device slower than the real one. The OS sleeps until 0.5 ms before, and the rest
/// is spun.
pub(crate) fn sleep_until_precisely(until: std::time::Instant) {
    const SPIN: std::time::Duration = std::time::Duration::from_micros(500);
    let now = std::time::Instant::now();
    if until > now + SPIN {
        std::thread::sleep(until - now - SPIN);
    }
    while std::time::Instant::now() < until {
        std::hint::spin_loop();
    }
}
