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
//! * [`simulated`]: the simulated rig of `--simulate`, `demo` and the tests (a stage simulator
//!   on a pseudo-terminal driven by its dialect's real driver, the camera rendering through
//!   the stage's true angle), [`sim_stage`] the plan's choice of its stage and that stage's
//!   limits, and [`sim_run`] a plan run on it.
//! * [`store_forecast`]: the disk a run's store will take, measured on one set of the plan's
//!   frames rendered by the simulated camera and stored as the run stores them.
//! * [`flags`]: the hardware flags (`--rig`, `--port`, `--dialect`, ...) the CLI and the GUI
//!   both parse, defined once.
//! * [`file`]: the rig file (TOML) that names a lab's stage, camera, site and analyzer once,
//!   and the calibrations written back to it as new revisions.
//!
//! The CLI and the GUI both use this crate; neither depends on the other.
#![warn(missing_docs)]

pub mod camera;
pub mod file;
pub mod flags;
pub mod follow;
pub mod hardware;
pub mod sim_run;
pub mod sim_stage;
pub mod simulated;
pub mod store_forecast;

pub use file::{Overrides, Rig};
pub use hardware::{
    connect_hardware, connect_hardware_for, Connected, Hardware, HardwareRig, SIM_PORT,
};
pub use sim_run::{run_simulated, SimRunError};
pub use simulated::{SimError, SimRig, SimWorld};

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
