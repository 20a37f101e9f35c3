//! The model's error type: every variant names the offending field, its value and what is allowed.

/// An input outside a function's documented domain.
///
/// Public functions never return NaN or infinity for inputs in their domain; inputs outside it
/// produce this error, which names the field, the value received and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// A scalar outside its allowed range (or not finite).
    #[error("{field} = {value} is out of range: allowed {allowed}")]
    OutOfRange {
        /// Name of the field, as the user spells it (`theta_i_deg`, `sigma`, ...).
        field: &'static str,
        /// The value received.
        value: f64,
        /// The allowed range, in words (`[0, 90]`, `> 0 and finite`, ...).
        allowed: &'static str,
    },
    /// A list of inputs that is malformed as a whole (too short, mismatched lengths, degenerate).
    #[error("{field} is invalid: {reason}")]
    Invalid {
        /// Name of the field.
        field: &'static str,
        /// What is wrong and what is allowed.
        reason: String,
    },
}

impl ModelError {
    /// Checks that `value` is finite and lies in `[lo, hi]`.
    pub fn check_range(
        field: &'static str,
        value: f64,
        lo: f64,
        hi: f64,
        allowed: &'static str,
    ) -> Result<f64, ModelError> {
        if value.is_finite() && value >= lo && value <= hi {
            Ok(value)
        } else {
            Err(ModelError::OutOfRange {
                field,
                value,
                allowed,
            })
        }
    }
}
