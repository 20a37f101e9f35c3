//! Counts on the command line: `--monte-carlo 1e6` means a million, and a count outside its
//! range is refused by clap naming the flag, the value and the range.

/// A parser of counts in `[lo, hi]`, written as digits (`1000000`) or in scientific notation
/// when the value is a whole number (`1e6`, `2.5e5`). For `#[arg(value_parser = ...)]`.
pub fn range(lo: usize, hi: usize) -> impl Fn(&str) -> Result<usize, String> + Clone {
    move |text: &str| {
        let value = parse(text.trim())?;
        if (lo..=hi).contains(&value) {
            Ok(value)
        } else {
            Err(format!(
                "{value} is outside the allowed range, {lo} to {hi}"
            ))
        }
    }
}

/// A whole number from digits or from scientific notation.
fn parse(text: &str) -> Result<usize, String> {
    if let Ok(v) = text.parse::<usize>() {
        return Ok(v);
    }
    let float: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a count (a whole number such as 1000 or 1e3)"))?;
    if !float.is_finite() || float < 0.0 || float.fract() != 0.0 {
        return Err(format!("{text} is not a whole number of at least 0"));
    }
    if float > usize::MAX as f64 {
        return Err(format!("{text} is too large"));
    }
    Ok(float as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scientific_counts_and_ranges() {
        let p = range(0, 50_000_000);
        assert_eq!(p("1e6"), Ok(1_000_000));
        assert_eq!(p("2.5e5"), Ok(250_000));
        assert_eq!(p("12"), Ok(12));
        let e = p("1e9").unwrap_err();
        assert!(
            e.contains("1000000000") && e.contains("0 to 50000000"),
            "{e}"
        );
        assert!(p("1.5").unwrap_err().contains("whole number"));
        assert!(p("-3").unwrap_err().contains("whole number"));
        assert!(p("many").unwrap_err().contains("not a count"));
    }
}
