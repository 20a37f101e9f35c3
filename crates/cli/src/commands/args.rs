//! The argument checks every model subcommand shares: a required value, an angle in range.

use super::error::CommandError;
use polar_model::ModelError;

pub(super) fn required<T>(value: Option<T>, field: &str, allowed: &str) -> Result<T, CommandError> {
    value.ok_or_else(|| CommandError::input(field, format!(" is missing: allowed {allowed}")))
}

pub(super) fn deg_to_rad(
    field: &'static str,
    deg: f64,
    lo: f64,
    hi: f64,
    allowed: &'static str,
) -> Result<f64, CommandError> {
    Ok(ModelError::check_range(field, deg, lo, hi, allowed)?.to_radians())
}
