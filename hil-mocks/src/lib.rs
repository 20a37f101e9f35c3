//! Simulated polarimeter devices: byte-level state machines with physical motion and seeded,
//! reproducible faults (`../shared/design/SYSTEM.md`, "Simulated devices").
//!
//! * [`native::NativeDevice`]: our own firmware's rotation stage or filter wheel
//!   (`firmware-protocol/SPEC.md`).
//! * [`sim::Simulator`]: what every device simulator offers the transport and the tests.
//! * [`motion`]: trapezoidal moves, backlash, encoder noise.
//! * [`faults::FaultProfile`]: the fault knobs, loadable from TOML.
//!
//! The simulators run on simulated time: every call takes `now_s`, so a test steps time
//! exactly and a real-time server maps the wall clock onto it. They never panic on any input
//! bytes.
#![warn(missing_docs)]

pub mod faults;
pub mod motion;
pub mod native;
pub mod sim;
