//! Rust errors as Python `ValueError`s that name the argument, its value and the allowed
//! range in the words the CLI uses (the model's and the CLI's messages already do; an
//! element of an array also gets its index).

use pyo3::exceptions::PyValueError;
use pyo3::PyErr;
use std::fmt::Display;

/// A `ValueError` with `message`.
pub fn value_error(message: impl Display) -> PyErr {
    PyValueError::new_err(message.to_string())
}

/// The error of element `index` of broadcast arrays of `count` elements: the message as it
/// is for a single value, with the element's index when there is more than one.
pub fn element_error(index: usize, count: usize, message: impl Display) -> String {
    if count > 1 {
        format!("{message} (at element {index} of the broadcast inputs)")
    } else {
        message.to_string()
    }
}

/// Checks that every array has `count` elements (the Python layer broadcasts them first).
pub fn same_length(count: usize, arrays: &[(&str, usize)]) -> Result<(), PyErr> {
    for (name, len) in arrays {
        if *len != count {
            return Err(value_error(format!(
                "{name} has {len} elements where {count} were expected: the inputs must \
                 broadcast to one shape"
            )));
        }
    }
    Ok(())
}
