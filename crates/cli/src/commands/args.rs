//! What every model subcommand shares: its error (field, value, allowed range), the argument
//! checks, and how a number or the user's text is echoed in a message.

use polar_model::ModelError;

/// A failure of one evaluation: the message names the field, the value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct CommandError(pub String);

impl From<ModelError> for CommandError {
    fn from(e: ModelError) -> Self {
        match e {
            ModelError::OutOfRange {
                field,
                value,
                allowed,
            } => CommandError(format!(
                "{field} = {} is out of range: allowed {allowed}",
                compact(value)
            )),
            other => CommandError(tidy(&other.to_string())),
        }
    }
}

/// Longest text an error message echoes from the user's input, characters.
pub const ECHO_MAX: usize = 80;

/// A number as an error message prints it: as Rust writes it when that is short, else in
/// exponent form (`1e300`, not 301 digits).
pub fn compact(x: f64) -> String {
    let plain = format!("{x}");
    let exp = format!("{x:e}");
    if plain.len() > 16 && exp.len() < plain.len() {
        exp
    } else {
        plain
    }
}

/// Text from the user as an error message echoes it: quoted, and cut to [`ECHO_MAX`]
/// characters with an ellipsis and its length when longer.
pub fn echo(text: &str) -> String {
    let n = text.chars().count();
    if n <= ECHO_MAX {
        format!("{text:?}")
    } else {
        let head: String = text.chars().take(ECHO_MAX).collect();
        format!("{:?} ({n} characters)", format!("{head}…"))
    }
}

/// A message from elsewhere (a parser, the model, a plan) made fit to show: every quoted span
/// (`"..."`, `` `...` ``) longer than [`ECHO_MAX`] characters is cut with an ellipsis and its
/// length, and every long decimal number is printed compactly (see [`compact`]).
pub fn tidy(message: &str) -> String {
    let chars: Vec<char> = message.chars().collect();
    let mut out = String::with_capacity(message.len().min(1024));
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c == '"' || c == '`' {
            // The closing quote (a `"` escaped by a backslash does not close).
            let mut j = i + 1;
            while j < chars.len() && chars[j] != c {
                if c == '"' && chars[j] == '\\' {
                    j += 1;
                }
                j += 1;
            }
            let end = j.min(chars.len());
            let inner = &chars[i + 1..end];
            // A span cut already (by [`echo`]) is left as it is.
            let cut_already = inner.len() == ECHO_MAX + 1 && inner.last() == Some(&'…');
            if inner.len() > ECHO_MAX && !cut_already {
                out.push(c);
                out.extend(&inner[..ECHO_MAX]);
                out.push('…');
                out.push(c);
                out.push_str(&format!(" ({} characters)", inner.len()));
            } else {
                out.push(c);
                out.extend(inner);
                if j < chars.len() {
                    out.push(c);
                }
            }
            i = j + 1;
            continue;
        }
        let starts_number = c.is_ascii_digit()
            && (i == 0 || !(chars[i - 1].is_alphanumeric() || chars[i - 1] == '_'));
        if starts_number {
            let mut j = i;
            while j < chars.len() && (chars[j].is_ascii_digit() || chars[j] == '.') {
                j += 1;
            }
            let token: String = chars[i..j].iter().collect();
            let bounded = j == chars.len() || !(chars[j].is_alphanumeric() || chars[j] == '_');
            match token.parse::<f64>() {
                Ok(x) if token.len() > 20 && bounded => out.push_str(&compact(x)),
                _ => out.push_str(&token),
            }
            i = j;
            continue;
        }
        out.push(c);
        i += 1;
    }
    out
}

pub(super) fn required<T>(value: Option<T>, field: &str, allowed: &str) -> Result<T, CommandError> {
    value.ok_or_else(|| CommandError(format!("{field} is missing: allowed {allowed}")))
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
