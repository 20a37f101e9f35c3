//! How a message shows a number or the user's text: numbers compact, long quoted spans cut.

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
