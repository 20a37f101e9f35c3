//! The planner: which analyzer angles (and, later, which integration time) best separate a
//! target from its background, from the model alone (MODEL.md section 9; Meng (2012)'s Chapter 5,
//! reconstructed). Pure: it depends on the model's maths, never on devices.
//!
//! * [`scr`]: the signal-to-clutter ratio of an analyzer set and its gradient, for the ideal
//!   analyzer or a camera's real rows and noise ([`Contrast::from_sensor`]: the SCR the
//!   forecast of a plan reports).
//! * [`aptd`]: adaptive polarimetric target detection as a state machine (frames in, the next
//!   set out, with a decision record).
//! * [`optimize`]: the SCR-optimal set of `N = 1..6` angles under a rotator's or a wheel's
//!   constraints (a Stokes set's condition bound among them), and the conventional sets it
//!   is compared with.
//! * [`continuous`]: frames per half turn, exposure and speed of a spinning analyzer under the
//!   camera's and the stage's limits, and which limit binds.
//! * [`log_search`]: a scan then golden-section search on a logarithmic axis.
//! * [`step`]: the step-and-shoot set on the continuous planner's problem, its exposure chosen
//!   by the same objective and saturation rule (`plan scene` and `plan continuous` share it).
//! * [`stokes`]: when a set forms a Stokes image, the condition number of the ideal
//!   analyzer's measurement matrix.
#![warn(missing_docs)]

pub mod aptd;
pub mod continuous;
pub mod log_search;
pub mod optimize;
pub mod scr;
pub mod step;
pub mod stokes;

pub use optimize::{conventional, optimise, Constraints, Optimum};
pub use scr::{Contrast, Instrument};

/// Errors of the planner: the field, the value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// A number out of its range.
    #[error("{field} = {value} is out of range: allowed {allowed}")]
    OutOfRange {
        /// The field.
        field: &'static str,
        /// The value.
        value: f64,
        /// The allowed range.
        allowed: &'static str,
    },
    /// A value that is not acceptable, and why.
    #[error("{field}: {reason}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Why.
        reason: String,
    },
}

impl PlanError {
    pub(crate) fn invalid(field: &'static str, reason: impl Into<String>) -> PlanError {
        PlanError::Invalid {
            field,
            reason: reason.into(),
        }
    }
}
