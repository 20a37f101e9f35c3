//! What every forecast stands on: the scene tolerance, the camera at a gain, and the
//! forecast's error.

use crate::plan_error::PlanError;
use polar_model::sensor::Camera;

/// Relative tolerance of the scene evaluation (of each material's mean `S0`), as `plan
/// --scene` uses.
pub const SCENE_TOL: f64 = 1e-3;

/// Why a forecast could not be made; every variant names the field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ForecastError {
    /// The plan (unresolved angles, a missing section).
    #[error("{0}")]
    Plan(#[from] PlanError),
    /// A material the plan names is not in the scene.
    #[error("{field} = {name:?} is not a material of the scene: allowed {allowed}")]
    UnknownMaterial {
        /// The plan's field.
        field: String,
        /// The name it gives.
        name: String,
        /// The scene's materials, comma-separated.
        allowed: String,
    },
    /// A value the forecast cannot use.
    #[error("{field} = {value} is invalid: allowed {allowed}")]
    Invalid {
        /// The field.
        field: String,
        /// The value.
        value: String,
        /// What is allowed.
        allowed: String,
    },
    /// The model failed for a material, the camera or the planner.
    #[error("{field}: {message}")]
    Model {
        /// What was being computed (e.g. `material panel`, `simulation.camera`).
        field: String,
        /// The model's error.
        message: String,
    },
}

pub(crate) fn model_err(
    field: impl Into<String>,
) -> impl FnOnce(polar_model::ModelError) -> ForecastError {
    let field = field.into();
    move |e| ForecastError::Model {
        field,
        message: e.to_string(),
    }
}

/// The camera at an analog gain: `K` scaled by `10^(gain_db / 20)` (as the cameras apply it).
pub(crate) fn camera_at_gain(camera: &Camera, gain_db: f64) -> Camera {
    let mut c = camera.clone();
    c.gain_dn_per_e *= 10f64.powf(gain_db / 20.0);
    c
}
