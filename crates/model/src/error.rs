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

/// A TOML parse error in one line: `line L, column C: what is wrong` (lines and columns from
/// 1, as editors count them), without the multi-line source excerpt `toml` prints.
pub fn toml_message(text: &str, e: &toml::de::Error) -> String {
    let what = e.message().trim().replace('\n', ", ");
    match e.span() {
        Some(span) => format!("{}: {what}", line_column(text, span.start)),
        None => what,
    }
}

/// `line L, column C` (from 1) of byte `offset` of `text`.
pub fn line_column(text: &str, offset: usize) -> String {
    let before = &text.as_bytes()[..offset.min(text.len())];
    let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
    let start = before
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(0, |i| i + 1);
    let column = String::from_utf8_lossy(&before[start..]).chars().count() + 1;
    format!("line {line}, column {column}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_errors_name_the_line_and_column_in_one_line() {
        let text = "a = 1\nb = \"two\"\n";
        #[derive(serde::Deserialize, Debug)]
        #[allow(dead_code)]
        struct T {
            a: f64,
            b: f64,
        }
        let e = toml::from_str::<T>(text).unwrap_err();
        let m = toml_message(text, &e);
        assert!(m.starts_with("line 2, column 5: "), "{m}");
        assert_eq!(m.lines().count(), 1, "{m}");
        assert_eq!(line_column("é\nxé", 4), "line 2, column 2");
    }
}
