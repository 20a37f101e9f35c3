//! JSON-lines batch mode: one JSON object per input line (keys are the flag names with
//! underscores), one JSON object per output line, in order. A bad line produces
//! `{"line": N, "error": "line N: ..."}` naming the field, the value (cut when long) and the
//! allowed range; the rest go on. A line that is not UTF-8, or has text after its object, is
//! such a bad line.

use crate::commands::{self, echo, tidy, CommandError, DiffuseCache, ECHO_MAX};
use serde::de::DeserializeOwned;
use serde_json::{json, Value};
use std::io::{BufRead, Write};

/// Which model command a batch runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// `model fresnel`
    Fresnel,
    /// `model pbrdf`
    Pbrdf,
    /// `model stokes`
    Stokes,
    /// `model polarimeter`
    Polarimeter,
    /// `model sun`
    Sun,
    /// `model sky`
    Sky,
    /// `model geometry`
    Geometry,
}

/// The allowed values of a field, for error messages from the parsers (the model's own range
/// checks carry their ranges already). `None` for names that are not fields.
pub fn allowed(field: &str) -> Option<&'static str> {
    Some(match field {
        "n" => "a number in (0, 100]",
        "k" => "a number in [0, 100]",
        "theta_i_deg" | "theta_r_deg" => "a number in [0, 90]",
        "phi_deg" => "a number in [-360, 360]",
        "sigma" => "a number in [1e-6, 10]",
        "dhr" => "a number in [0, 1]",
        "vegetation" => "true or false",
        "tolerance" => "a number in [1e-14, 1e-2]",
        "angles_deg" => "a list of at least 3 angles in degrees, distinct modulo 180",
        "intensities" => "a list of finite numbers, one per angle",
        "extinction_ratio" => "a number > 1",
        "offset_deg" => "a number in [-180, 180]",
        "time" => "an RFC 3339 instant, e.g. 2026-06-21T15:00:00Z",
        "lat_deg" => "a number in [-90, 90]",
        "lon_deg" => "a number in [-180, 180]",
        "elevation_m" => "a number in [-500, 9000]",
        "pressure_hpa" => "a number in [1, 2000]",
        "temperature_c" => "a number in [-100, 60]",
        "delta_t_s" => "a number of seconds in [-1e4, 1e5]",
        "no_refraction" => "true or false",
        "sun_zenith_deg" | "zenith_deg" => "a number in [0, 90]",
        "sun_azimuth_deg" | "azimuth_deg" => "a number in [-360, 360] (clockwise from north)",
        "wavelength_nm" => "a number in [200, 3000]",
        "altitude_m" => "a number in (0, 1e5]",
        "off_nadir_deg" => "a number in [0, 89]",
        "look_azimuth_deg" => "a number in [-360, 360] (clockwise from north)",
        "fov_deg" => "one or two numbers in (0, 120]",
        "tiles" => "NxM, e.g. 3x3",
        "model" => "rayleigh, berry or table",
        "separation_deg" => "a number in [0, 60]",
        "material" => "a built-in material name (polarimeter model materials)",
        _ => return None,
    })
}

/// A JSON error's message with its position as a column of the batch line (the parser sees
/// each line alone, so its "line 1" would be wrong), long echoed text cut.
fn json_message(e: &serde_json::Error) -> String {
    let text = e.to_string();
    let text = match text.rfind(" at line ") {
        Some(i) if e.line() > 0 => format!("{} at column {}", &text[..i], e.column()),
        _ => text,
    };
    tidy(&text)
}

fn parse<T: DeserializeOwned>(line: &str) -> Result<T, CommandError> {
    let de = &mut serde_json::Deserializer::from_str(line);
    let value = serde_path_to_error::deserialize(&mut *de).map_err(|e| {
        let field = e.path().to_string();
        let inner = json_message(e.inner());
        if field == "." || field.is_empty() {
            CommandError::failed(inner)
        } else {
            let base = field.split(['[', '.']).next().unwrap_or(&field).to_string();
            // An unknown key is the path: a long one is cut like any echoed text.
            let field = if field.chars().count() > ECHO_MAX {
                echo(&field)
            } else {
                field
            };
            match allowed(&base) {
                Some(a) => CommandError::input(field, format!(": {inner}; allowed {a}")),
                None => CommandError::input(field, format!(": {inner}")),
            }
        }
    })?;
    // Only white space may follow the object.
    de.end().map_err(|e| {
        CommandError::failed(format!(
            "trailing text after the JSON object at column {}: allowed one JSON object per line",
            e.column()
        ))
    })?;
    Ok(value)
}

/// Evaluates one batch line.
pub fn eval_line(kind: Kind, line: &str, cache: &mut DiffuseCache) -> Result<Value, CommandError> {
    if line.trim().is_empty() {
        return Err(CommandError::failed(
            "empty line: allowed one JSON object per line",
        ));
    }
    match kind {
        Kind::Fresnel => commands::fresnel(&parse(line)?),
        Kind::Pbrdf => commands::pbrdf(&parse(line)?, cache),
        Kind::Stokes => commands::stokes(&parse(line)?),
        Kind::Polarimeter => commands::polarimeter(&parse(line)?),
        Kind::Sun => commands::sun(&parse(line)?),
        Kind::Sky => commands::sky(&parse(line)?),
        Kind::Geometry => commands::geometry(&parse(line)?),
    }
}

/// Counts of a finished batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Summary {
    /// Lines read.
    pub lines: usize,
    /// Lines that produced an error object.
    pub errors: usize,
}

/// Runs a batch from `input` to `output`. I/O errors stop the batch; evaluation errors do not,
/// nor does a line that is not UTF-8 (it gets its error record like any bad line).
pub fn run<R: BufRead, W: Write>(
    kind: Kind,
    mut input: R,
    mut output: W,
) -> std::io::Result<Summary> {
    let mut cache = DiffuseCache::default();
    let mut summary = Summary::default();
    let mut buf = Vec::with_capacity(512);
    let mut raw = Vec::with_capacity(512);
    loop {
        raw.clear();
        if input.read_until(b'\n', &mut raw)? == 0 {
            break;
        }
        if raw.last() == Some(&b'\n') {
            raw.pop();
            if raw.last() == Some(&b'\r') {
                raw.pop();
            }
        }
        summary.lines += 1;
        let result = match std::str::from_utf8(&raw) {
            Ok(line) => eval_line(kind, line, &mut cache),
            Err(e) => Err(CommandError::failed(format!(
                "not valid UTF-8 (byte {} of the line): allowed one JSON object per line, in \
                 UTF-8",
                e.valid_up_to() + 1
            ))),
        };
        let value = match result {
            Ok(v) => v,
            Err(e) => {
                summary.errors += 1;
                let n = summary.lines;
                json!({"line": n, "error": format!("line {n}: {}", tidy(&e.to_string()))})
            }
        };
        buf.clear();
        serde_json::to_writer(&mut buf, &value)?;
        buf.push(b'\n');
        output.write_all(&buf)?;
    }
    output.flush()?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_str(kind: Kind, text: &str) -> (Vec<Value>, Summary) {
        let mut out = Vec::new();
        let s = run(kind, text.as_bytes(), &mut out).unwrap();
        let values = String::from_utf8(out)
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        (values, s)
    }

    #[test]
    fn one_line_out_per_line_in_and_bad_lines_name_the_field() {
        let text = [
            r#"{"n": 1.52, "theta_i_deg": 60}"#,
            r#"{"n": 1.52, "theta_i_deg": 95}"#,
            r#"{"n": "glass", "theta_i_deg": 60}"#,
            r#"{"n": 1.52, "theta_i": 60}"#,
            "",
            "not json",
            r#"{"n": 1.02, "k": 2.577, "theta_i_deg": 45}"#,
        ]
        .join("\n");
        let (v, s) = run_str(Kind::Fresnel, &text);
        assert_eq!(
            s,
            Summary {
                lines: 7,
                errors: 5
            }
        );
        assert_eq!(v.len(), 7);
        // Glass at 60 deg: Rs = 0.183438 (REFERENCE_VALUES.md).
        assert!((v[0]["Rs"].as_f64().unwrap() - 0.183438).abs() < 6e-7);
        let e = |i: usize| v[i]["error"].as_str().unwrap().to_string();
        assert!(
            e(1).contains("theta_i_deg") && e(1).contains("95") && e(1).contains("[0, 90]"),
            "{}",
            e(1)
        );
        assert!(e(2).contains("n:") && e(2).contains("(0, 100]"), "{}", e(2));
        assert!(e(3).contains("theta_i"), "{}", e(3));
        assert!(e(4).contains("empty"), "{}", e(4));
        assert_eq!(v[5]["line"], 6);
        // Rp = Rs^2 at 45 deg for copper.
        let (rs, rp) = (v[6]["Rs"].as_f64().unwrap(), v[6]["Rp"].as_f64().unwrap());
        assert!((rp - rs * rs).abs() < 1e-12);
    }

    #[test]
    fn pbrdf_batch_reuses_the_diffuse_term() {
        let mut cache = DiffuseCache::default();
        for phi in [0.0, 90.0, 180.0] {
            let line = format!(
                r#"{{"n":1.52,"sigma":0.1,"dhr":0.1,"theta_i_deg":60,"theta_r_deg":60,"phi_deg":{phi}}}"#
            );
            let v = eval_line(Kind::Pbrdf, &line, &mut cache).unwrap();
            // f00_d = 0.002309 (REFERENCE_VALUES.md) whatever the view direction.
            assert!((v["f00_diffuse"].as_f64().unwrap() - 0.002309).abs() < 6e-7);
        }
        assert_eq!(cache.len(), 1);
        let v = eval_line(
            Kind::Stokes,
            r#"{"angles_deg":[0,45,90],"intensities":[1,2]}"#,
            &mut cache,
        )
        .unwrap_err()
        .to_string();
        assert!(
            v.contains("intensities") && v.contains("one per angle"),
            "{v}"
        );
    }
}
