//! Serial drivers for the polarimeter's rotation stages and filter wheels, on tokio
//! (`ARCHITECTURE.md`, `docs/DEVICES.md`).
//!
//! Each dialect is a module (its driver types and its [`dialect::Dialect`] descriptor, `DIALECT`),
//! and [`registry::DIALECTS`] lists them: the list is the one place to read which dialects
//! exist (`polarimeter devices list` prints it). [`any`] holds a stage or wheel of any dialect.
//!
//! Every driver owns its port ([`link::Link`]) and is owned by one task; every operation ends
//! within its [`link::Policy`]'s deadlines; idempotent requests are retried with backoff;
//! stale, duplicated, corrupted and unsolicited bytes are skipped; a reset or reopen is followed
//! by identification and homing; a device that goes away is reported
//! [`polar_hal::ErrorKind::Disconnected`] and reopened at the same (stable) path on the next
//! call; every move is verified by reading the position back. The default build needs no
//! system library (no libudev).
#![warn(missing_docs)]

pub mod any;
pub mod apt;
pub mod dialect;
pub mod elliptec;
pub mod fw102c;
pub mod link;
pub mod native;
pub mod registry;
pub mod smc100;
pub mod standa;
