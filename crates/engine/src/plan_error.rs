//! A bad plan: the one error type of reading and checking a plan.

/// A bad plan: the field (dotted path), the value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// The text does not parse, or a field has the wrong type.
    #[error("plan {path}: {message}")]
    Parse {
        /// The field's dotted path (or the line and column).
        path: String,
        /// What the parser said.
        message: String,
    },
    /// A field's value is outside its allowed range.
    #[error("plan field {field} = {value} is out of range: allowed {allowed}")]
    Invalid {
        /// The field's dotted path.
        field: String,
        /// The value, as written.
        value: String,
        /// What is allowed.
        allowed: String,
    },
    /// The file cannot be read.
    #[error("plan file {path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        message: String,
    },
}
