//! The scene: the sun (`model sun`), the sky (`model sky`, `model sky-table`), the sensor's
//! ground geometry (`model geometry`) and a scene file's class radiances (`model scene`).

use super::args::required;
use super::error::CommandError;
use super::text::echo;
use clap::Args;
use polar_model::ModelError;
use serde::Deserialize;
use serde_json::{json, Value};
use std::path::PathBuf;

/// `polarimeter model sun`: the sun's position (NREL SPA). Azimuth clockwise from north.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SunArgs {
    /// UTC instant, RFC 3339 (`2026-06-21T15:00:00Z`, or with an offset `...-04:00`).
    #[arg(long)]
    pub time: Option<String>,
    /// Latitude, degrees north, [-90, 90].
    #[arg(long, allow_hyphen_values = true)]
    pub lat_deg: Option<f64>,
    /// Longitude, degrees east, [-180, 180] (west is negative).
    #[arg(long, allow_hyphen_values = true)]
    pub lon_deg: Option<f64>,
    /// Elevation above sea level, metres, [-500, 9000].
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    #[serde(default)]
    pub elevation_m: f64,
    /// Surface pressure for the refraction correction, hPa (default: standard atmosphere scaled
    /// to the elevation with an 8.4 km scale height).
    #[arg(long)]
    #[serde(default)]
    pub pressure_hpa: Option<f64>,
    /// Air temperature for the refraction correction, degrees Celsius.
    #[arg(long, default_value_t = 15.0, allow_hyphen_values = true)]
    #[serde(default = "standard_temperature")]
    pub temperature_c: f64,
    /// TT - UT in seconds (default: Espenak-Meeus estimate for the date).
    #[arg(long, allow_hyphen_values = true)]
    #[serde(default)]
    pub delta_t_s: Option<f64>,
    /// Report the geometric position, without atmospheric refraction.
    #[arg(long)]
    #[serde(default)]
    pub no_refraction: bool,
}

fn standard_temperature() -> f64 {
    15.0
}

/// Parses an RFC 3339 instant into UTC calendar fields.
pub fn parse_utc(text: &str) -> Result<polar_model::sun::UtcTime, CommandError> {
    use chrono::{Datelike, Timelike};
    let t = chrono::DateTime::parse_from_rfc3339(text)
        .map_err(|e| {
            CommandError::input(
                "time",
                format!(
                    " = {} is invalid ({e}): allowed RFC 3339, e.g. 2026-06-21T15:00:00Z",
                    echo(text)
                ),
            )
        })?
        .naive_utc();
    Ok(polar_model::sun::UtcTime {
        year: t.year(),
        month: t.month(),
        day: t.day(),
        hour: t.hour(),
        minute: t.minute(),
        second: t.second() as f64 + t.nanosecond().min(999_999_999) as f64 * 1e-9,
    })
}

/// Evaluates [`SunArgs`].
pub fn sun(a: &SunArgs) -> Result<Value, CommandError> {
    use polar_model::sun::{sun_position, Site, Weather};
    let time = parse_utc(&required(
        a.time.clone(),
        "time",
        "RFC 3339, e.g. 2026-06-21T15:00:00Z",
    )?)?;
    let site = Site::new(
        required(a.lat_deg, "lat_deg", "[-90, 90]")?,
        required(a.lon_deg, "lon_deg", "[-180, 180]")?,
        a.elevation_m,
    )?;
    let weather = if a.no_refraction {
        None
    } else {
        let p = a
            .pressure_hpa
            .unwrap_or(Weather::standard_pressure_hpa(a.elevation_m));
        ModelError::check_range("pressure_hpa", p, 1.0, 2000.0, "[1, 2000]")?;
        ModelError::check_range("temperature_c", a.temperature_c, -100.0, 60.0, "[-100, 60]")?;
        Some(Weather {
            pressure_hpa: p,
            temperature_c: a.temperature_c,
        })
    };
    let p = sun_position(&time, &site, a.delta_t_s, weather)?;
    Ok(json!({
        "zenith_deg": p.zenith_deg,
        "azimuth_deg": p.azimuth_deg,
        "elevation_deg": 90.0 - p.zenith_deg,
        "delta_t_s": p.delta_t_s,
        "refraction": weather.is_some(),
    }))
}

/// `polarimeter model sky`: Rayleigh single-scattering sky radiance and polarisation.
/// Azimuths clockwise from north; the Stokes frame's x axis is horizontal (S1 > 0: horizontal
/// E-vector); radiance per unit top-of-atmosphere solar irradiance (sr^-1).
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SkyArgs {
    /// Sun zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub sun_zenith_deg: Option<f64>,
    /// Sun azimuth, degrees clockwise from north, [-360, 360].
    #[arg(long, allow_hyphen_values = true)]
    pub sun_azimuth_deg: Option<f64>,
    /// Zenith angle of the sky direction viewed, degrees, [0, 90].
    #[arg(long)]
    pub zenith_deg: Option<f64>,
    /// Azimuth of the sky direction viewed, degrees clockwise from north, [-360, 360].
    #[arg(long, allow_hyphen_values = true)]
    pub azimuth_deg: Option<f64>,
    /// Wavelength, nm, [200, 3000].
    #[arg(long, default_value_t = 550.0)]
    #[serde(default = "default_wavelength")]
    pub wavelength_nm: f64,
    /// Sky model: rayleigh (single scattering), berry (Berry-Dennis-Lee: the Rayleigh
    /// radiance with the neutral points split by --separation-deg, as in the real sky) or table
    /// (--table FILE).
    #[arg(long, default_value = "rayleigh")]
    #[serde(default = "default_sky_model")]
    pub model: String,
    /// Berry model: angle between the Babinet and Brewster neutral points, degrees, [0, 60].
    #[arg(long, default_value_t = 30.0)]
    #[serde(default = "default_separation")]
    pub separation_deg: f64,
    /// Table model: a CSV sky (zenith_deg,azimuth_deg,S0,S1,S2) exported from a
    /// radiative-transfer code; the answer is in the table's units.
    #[arg(long)]
    #[serde(default)]
    pub table: Option<std::path::PathBuf>,
    /// Table model: the axis the table's S1 > 0 refers to, horizontal or vertical (meridian
    /// plane, as libRadtran).
    #[arg(long, default_value = "horizontal")]
    #[serde(default = "default_reference")]
    pub reference: String,
}

fn default_reference() -> String {
    "horizontal".into()
}

fn default_wavelength() -> f64 {
    550.0
}

fn default_sky_model() -> String {
    "rayleigh".into()
}

fn default_separation() -> f64 {
    30.0
}

/// Evaluates [`SkyArgs`].
pub fn sky(a: &SkyArgs) -> Result<Value, CommandError> {
    use polar_model::sky::{direction_from_deg, RayleighSky};
    let angle = |v: Option<f64>, field: &'static str, lo: f64, hi: f64, allowed: &'static str| {
        let v = required(v, field, allowed)?;
        ModelError::check_range(field, v, lo, hi, allowed).map_err(CommandError::from)
    };
    let sun_z = angle(a.sun_zenith_deg, "sun_zenith_deg", 0.0, 90.0, "[0, 90]")?;
    let sun_a = angle(
        a.sun_azimuth_deg,
        "sun_azimuth_deg",
        -360.0,
        360.0,
        "[-360, 360]",
    )?;
    let z = angle(a.zenith_deg, "zenith_deg", 0.0, 90.0, "[0, 90]")?;
    let az = angle(a.azimuth_deg, "azimuth_deg", -360.0, 360.0, "[-360, 360]")?;
    let model = RayleighSky::at_wavelength(a.wavelength_nm)?;
    let sun = direction_from_deg(sun_z, sun_a);
    let view = direction_from_deg(z, az);
    let rayleigh = model.stokes(&sun, &view)?;
    let (s, name) = match a.model.as_str() {
        "rayleigh" => (rayleigh, "rayleigh single scattering"),
        "berry" => {
            let sep =
                ModelError::check_range("separation_deg", a.separation_deg, 0.0, 60.0, "[0, 60]")?;
            let b = polar_model::sky::BerrySky {
                sun,
                separation_rad: sep.to_radians(),
                max_dolp: model.dolp(0.0),
            };
            let (p, c2, s2) = b.polarization(&view);
            let i = rayleigh.0[0];
            (
                polar_model::polarization::Stokes::new(i, i * p * c2, i * p * s2),
                "berry-dennis-lee (rayleigh radiance)",
            )
        }
        "table" => {
            let path = a.table.as_ref().ok_or_else(|| {
                CommandError::input("model", " = \"table\" needs --table FILE.csv")
            })?;
            let reference = match a.reference.as_str() {
                "horizontal" => polar_model::sky::table::StokesReference::Horizontal,
                "vertical" => polar_model::sky::table::StokesReference::Vertical,
                other => {
                    return Err(CommandError::input(
                        "reference",
                        format!(
                            " = {} is invalid: allowed horizontal or vertical",
                            echo(other)
                        ),
                    ))
                }
            };
            let text = std::fs::read_to_string(path).map_err(|e| {
                CommandError::input(
                    "table",
                    format!(" = {:?}: cannot read ({e})", path.display().to_string()),
                )
            })?;
            let t = polar_model::sky::table::SkyTable::from_csv_str(&text, reference)
                .map_err(|e| CommandError::layer(format!("{}: ", path.display()), e))?;
            let s = t.stokes_at_deg(z, az);
            return Ok(json!({
                "s": [s.0[0], s.0[1], s.0[2]],
                "dolp": s.dolp(),
                "aop_deg": s.aop_rad().map(f64::to_degrees),
                "model": "table",
                "grid": [t.grid().0, t.grid().1],
                "interpolation_error": t.interpolation_error(),
                "units": "the table's",
            }));
        }
        other => {
            return Err(CommandError::input(
                "model",
                format!(
                    " = {} is invalid: allowed rayleigh, berry or table",
                    echo(other)
                ),
            ))
        }
    };
    Ok(json!({
        "s": [s.0[0], s.0[1], s.0[2]],
        "dolp": s.dolp(),
        "aop_deg": s.aop_rad().map(f64::to_degrees),
        "model": name,
        "optical_depth": model.optical_depth,
        "units": "sr^-1 per unit top-of-atmosphere solar irradiance",
    }))
}

/// `polarimeter model geometry`: per-tile sun/view geometry of a sensor above flat ground
/// (Appendix A). Azimuths clockwise from north; ground_m is [east, north] of the nadir point.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometryArgs {
    /// Sensor height above the ground, metres, (0, 1e5].
    #[arg(long)]
    pub altitude_m: Option<f64>,
    /// Boresight angle from nadir, degrees, [0, 89].
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub off_nadir_deg: f64,
    /// Azimuth the boresight looks towards, degrees clockwise from north.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    #[serde(default)]
    pub look_azimuth_deg: f64,
    /// Field of view across,along the image, degrees, each (0, 120].
    #[arg(long, value_delimiter = ',')]
    #[serde(default)]
    pub fov_deg: Vec<f64>,
    /// Tiles across x along, e.g. 3x3.
    #[arg(long, default_value = "3x3")]
    #[serde(default = "default_tiles")]
    pub tiles: String,
    /// Sun zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub sun_zenith_deg: Option<f64>,
    /// Sun azimuth, degrees clockwise from north.
    #[arg(long, allow_hyphen_values = true)]
    pub sun_azimuth_deg: Option<f64>,
}

fn default_tiles() -> String {
    "3x3".into()
}

/// Parses `NxM` tile counts.
pub fn parse_tiles(text: &str) -> Result<(usize, usize), CommandError> {
    let bad = || {
        CommandError::input(
            "tiles",
            format!(
                " = {} is invalid: allowed NxM with N, M >= 1, e.g. 3x3",
                echo(text)
            ),
        )
    };
    let (a, b) = text.split_once(['x', 'X']).ok_or_else(bad)?;
    Ok((
        a.trim().parse().map_err(|_| bad())?,
        b.trim().parse().map_err(|_| bad())?,
    ))
}

/// Evaluates [`GeometryArgs`].
pub fn geometry(a: &GeometryArgs) -> Result<Value, CommandError> {
    use polar_model::tiles::{tiles, Pointing};
    let fov = match a.fov_deg.as_slice() {
        [x, y] => (*x, *y),
        [x] => (*x, *x),
        other => {
            return Err(CommandError::input(
                "fov_deg",
                format!(
                    " has {} values: allowed one (square) or two (across,along), each in (0, 120]",
                    other.len()
                ),
            ))
        }
    };
    let pointing = Pointing {
        altitude_m: required(a.altitude_m, "altitude_m", "(0, 1e5]")?,
        off_nadir_deg: a.off_nadir_deg,
        look_azimuth_deg: a.look_azimuth_deg,
        fov_deg: fov,
    };
    let t = tiles(
        &pointing,
        parse_tiles(&a.tiles)?,
        required(a.sun_zenith_deg, "sun_zenith_deg", "[0, 90]")?,
        required(a.sun_azimuth_deg, "sun_azimuth_deg", "[-360, 360]")?,
    )?;
    let rows: Vec<Value> = t
        .iter()
        .map(|t| {
            let (c, s) = t.camera_from_surface;
            json!({
                "index": [t.index.0, t.index.1],
                "theta_i_deg": t.theta_i_deg,
                "theta_r_deg": t.theta_r_deg,
                "phi_deg": t.phi_deg,
                "ground_m": t.ground_m,
                "range_m": t.range_m,
                "camera_from_surface_deg": 0.5 * s.atan2(c).to_degrees(),
            })
        })
        .collect();
    Ok(json!({ "tiles": rows }))
}

/// `polarimeter model scene`: the mean Stokes radiance and covariance of each material of a
/// TOML scene (see `examples/`), to a tolerance, with the error estimate and the terms evaluated
/// and skipped.
#[derive(Debug, Clone, Args)]
pub struct SceneArgs {
    /// The scene file (TOML; see examples/rooftop.toml).
    #[arg(long)]
    pub scene: PathBuf,
    /// Relative tolerance of each material's mean S0, [1e-10, 0.1].
    #[arg(long, default_value_t = 1e-4)]
    pub tolerance: f64,
}

fn term_json(t: &polar_model::scene::TermReport) -> Value {
    json!({"evaluated": t.evaluated, "relative_size": t.relative_size, "reason": t.reason})
}

fn matrix_json(m: &nalgebra::Matrix3<f64>) -> Value {
    json!((0..3)
        .map(|i| (0..3).map(|j| m[(i, j)]).collect::<Vec<_>>())
        .collect::<Vec<_>>())
}

/// One material's result as JSON.
pub fn material_json(r: &polar_model::scene::MaterialResult) -> Value {
    let t = &r.terms;
    let mut out = json!({
        "material": r.name,
        "mean": [r.mean.0[0], r.mean.0[1], r.mean.0[2]],
        "cov": matrix_json(&r.cov),
        "cov_geometry": matrix_json(&r.cov_geometry),
        "dolp": r.mean.dolp(),
        "aop_deg": r.mean.aop_rad().map(f64::to_degrees),
        "error_estimate": r.error_estimate,
        "terms": {
            "direct": term_json(&t.direct),
            "skylight": term_json(&t.skylight),
            "path": term_json(&t.path),
            "geometry": term_json(&t.geometry),
            "texture": term_json(&t.texture),
            "field_rays": t.field_order * t.field_order,
            "spectral_nodes": t.spectral_nodes,
        },
        "evaluations": r.evaluations,
    });
    if let Some(f) = &r.floor {
        out["error_floor"] = floor_json(f);
    }
    out
}

/// An input's error floor as JSON: its size, source and the tolerance integrated to, with a
/// note when the tolerance asked for is below it.
fn floor_json(f: &polar_model::scene::ErrorFloor) -> Value {
    let mut out = json!({
        "relative": f.relative,
        "source": f.source,
        "integrated_to": f.tolerance,
    });
    if f.below_floor {
        out["note"] = json!(format!(
            "the tolerance asked for is below this input's error floor ({:.2e} of S0), which \
             no integration can improve: integrated to {:.2e} (the larger of the tolerance and \
             {} of the floor); error_estimate includes the floor",
            f.relative,
            f.tolerance,
            polar_model::scene::FLOOR_FRACTION
        ));
    }
    out
}

/// Reads a file a scene names, relative to the scene file's directory.
pub fn read_relative(base: &std::path::Path, path: &str) -> Result<String, String> {
    let full = base.join(path);
    std::fs::read_to_string(&full).map_err(|e| format!("{}: cannot read ({e})", full.display()))
}

/// Reads and parses a scene file; files it names are read relative to its directory. Errors
/// name the file.
pub fn load_scene(path: &std::path::Path) -> Result<polar_model::scene_file::Scene, CommandError> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        CommandError::input(
            "scene",
            format!(" = {:?}: cannot read ({e})", path.display().to_string()),
        )
    })?;
    let base = path.parent().unwrap_or(std::path::Path::new("."));
    polar_model::scene_file::Scene::from_toml_str_with_files(&text, &|p| read_relative(base, p))
        .map_err(|e| CommandError::layer(format!("{}: ", path.display()), e))
}

/// Evaluates a parsed scene to JSON.
pub fn scene_json(
    scene: &polar_model::scene_file::Scene,
    tolerance: f64,
) -> Result<Value, CommandError> {
    let results = polar_model::scene::evaluate(&scene.spec, &scene.materials, tolerance)?;
    let all: Vec<Value> = results.iter().map(material_json).collect();
    let mut out = all.first().cloned().unwrap_or(Value::Null);
    out["units"] = json!("W m^-2 sr^-1 in the band (times the relative response), camera frame: S1 > 0 along the image rows");
    out["sun"] =
        json!({"zenith_deg": scene.spec.sun_zenith_deg, "azimuth_deg": scene.spec.sun_azimuth_deg});
    out["tolerance"] = json!(tolerance);
    out["materials"] = json!(all);
    Ok(out)
}

/// A scene's band sky at the ground as sky-table CSV on a `step_deg` grid (zenith 0..=90,
/// azimuth 0..360); each zenith-0 row is the limit along its own azimuth.
pub fn sky_table_csv(path: &std::path::Path, step_deg: f64) -> Result<String, CommandError> {
    let step = ModelError::check_range("step_deg", step_deg, 1.0, 30.0, "[1, 30]")?;
    if (90.0 / step).fract().abs() > 1e-9 || (360.0 / step).fract().abs() > 1e-9 {
        return Err(CommandError::input(
            "step_deg",
            format!(" = {step} is invalid: allowed a divisor of 90 in [1, 30]"),
        ));
    }
    let scene = load_scene(path)?;
    let prepared = polar_model::scene::Prepared::new(&scene.spec, 1e-6)?;
    let sky = prepared.ground_sky();
    let mut out = format!(
        "# band sky at the ground from {} (sun zenith {:.4} deg, azimuth {:.4} deg), W m^-2 sr^-1;\n\
         # S1 > 0: E-vector horizontal. Written by polarimeter model sky-table.\n\
         zenith_deg,azimuth_deg,S0,S1,S2\n",
        path.display(),
        scene.spec.sun_zenith_deg,
        scene.spec.sun_azimuth_deg
    );
    let (nz, na) = (
        (90.0 / step).round() as usize,
        (360.0 / step).round() as usize,
    );
    for i in 0..=nz {
        for j in 0..na {
            let (z, a) = (i as f64 * step, j as f64 * step);
            let d = polar_model::sky::direction_from_deg(z.max(1e-7), a);
            let v = sky.stokes_from(&d).0;
            out += &format!("{z},{a},{:.9e},{:.9e},{:.9e}\n", v[0], v[1], v[2]);
        }
    }
    Ok(out)
}

/// Evaluates [`SceneArgs`].
pub fn scene(a: &SceneArgs) -> Result<Value, CommandError> {
    let scene = load_scene(&a.scene)?;
    scene_json(&scene, a.tolerance)
        .map_err(|e| CommandError::failed(format!("{}: {e}", a.scene.display())))
}
