//! The polarimeter's rig: what devices a run uses and how they are found, named and
//! connected (`ARCHITECTURE.md`, `docs/DEVICES.md`).
//!
//! * [`camera`]: the registry of camera backends ([`camera::CAMERA_BACKENDS`] lists them; all
//!   but the simulated camera behind this crate's cargo features of the same names) and the
//!   simulated camera.
//! * [`hardware`]: the hardware rig `run`, `resume` and the GUI connect, through the serial
//!   dialects' registry (`polar_drivers::registry`) and the camera backends' registry.
//! * [`follow`]: a simulated camera behind a stage the rig does not simulate, rendering through
//!   the positions the stage reports.
//! * [`file`]: the rig file (TOML) that names a lab's stage, camera, site and analyzer once,
//!   and the calibrations written back to it as new revisions.
//!
//! The CLI and the GUI both use this crate; neither depends on the other.
#![warn(missing_docs)]

pub mod camera;
pub mod file;
pub mod follow;
pub mod hardware;

pub use file::{Overrides, Rig};
pub use hardware::{
    connect_hardware, connect_hardware_for, Connected, Hardware, HardwareRig, SIM_PORT,
};

/// An error of the rig, already worded for the user (it names the file, key or flag, the
/// value and what is allowed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct RigError(pub String);

impl RigError {
    /// Any error, as its message.
    pub fn of(e: impl std::fmt::Display) -> RigError {
        RigError(e.to_string())
    }
}
