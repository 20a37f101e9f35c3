//! The `model` subcommands: argument structs shared by the command line (clap) and the JSON-lines
//! batch mode (serde), and their evaluation to JSON.
//!
//! Field names are the flag names with underscores. Every range check is the model's own, so a
//! bad value gets the same message (field, value, allowed range) from a flag and from a batch line.

use clap::Args;
use polar_model::analyzer::{AnalyzerModel, AnalyzerSet};
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::material::{MaterialLibrary, MaterialModel};
use polar_model::pbrdf::{DiffuseTerm, Geometry, Surface};
use polar_model::quadrature::Tolerance;
use polar_model::ModelError;
use serde::Deserialize;
use serde_json::{json, Value};
use std::collections::HashMap;
use std::path::PathBuf;

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

fn required<T>(value: Option<T>, field: &str, allowed: &str) -> Result<T, CommandError> {
    value.ok_or_else(|| CommandError(format!("{field} is missing: allowed {allowed}")))
}

fn deg_to_rad(
    field: &'static str,
    deg: f64,
    lo: f64,
    hi: f64,
    allowed: &'static str,
) -> Result<f64, CommandError> {
    Ok(ModelError::check_range(field, deg, lo, hi, allowed)?.to_radians())
}

/// `polarimeter model fresnel`: Fresnel amplitudes and reflectances at one angle.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FresnelArgs {
    /// Real part of the refractive index, (0, 100].
    #[arg(long)]
    pub n: Option<f64>,
    /// Extinction coefficient, [0, 100] (0 for a dielectric).
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub k: f64,
    /// Angle of incidence from the normal, degrees, [0, 90].
    #[arg(long)]
    pub theta_i_deg: Option<f64>,
}

/// Evaluates [`FresnelArgs`].
pub fn fresnel(a: &FresnelArgs) -> Result<Value, CommandError> {
    let idx = RefractiveIndex::new(required(a.n, "n", "(0, 100]")?, a.k)?;
    let ti = deg_to_rad(
        "theta_i_deg",
        required(a.theta_i_deg, "theta_i_deg", "[0, 90]")?,
        0.0,
        90.0,
        "[0, 90]",
    )?;
    let r = amplitudes(&idx, ti)?;
    let mut out = json!({
        "rs": [r.rs.re, r.rs.im],
        "rp": [r.rp.re, r.rp.im],
        "Rs": r.rs_power(),
        "Rp": r.rp_power(),
        "re_rs_rp_conj": r.re_rs_rp_conj(),
    });
    if idx.k > 0.0 {
        // An absorbing medium has no Brewster angle (Rp never vanishes): the pseudo-Brewster
        // angle, where Rp is smallest, and that Rp.
        let pb = idx.pseudo_brewster();
        out["pseudo_brewster_deg"] = json!(pb.angle_rad.to_degrees());
        out["rp_min"] = json!(pb.rp_min);
    } else {
        out["brewster_deg"] = json!(idx.brewster_angle_rad().to_degrees());
    }
    Ok(out)
}

/// `polarimeter model pbrdf`: the full pBRDF Mueller matrix at one geometry.
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PbrdfArgs {
    /// Real part of the refractive index, (0, 100].
    #[arg(long)]
    pub n: Option<f64>,
    /// Extinction coefficient, [0, 100] (default 0, or the material's).
    #[arg(long)]
    #[serde(default)]
    pub k: Option<f64>,
    /// A built-in material (glass, black_paint, asphalt, vegetation, aluminium, copper, gold,
    /// silver; see `polarimeter model materials`) supplying n, k, sigma, dhr and the model;
    /// explicit flags override its values.
    #[arg(long)]
    #[serde(default)]
    pub material: Option<String>,
    /// Facet-slope roughness sigma_h / l, [1e-6, 10] (not used with --vegetation).
    #[arg(long)]
    pub sigma: Option<f64>,
    /// Directional-hemispherical reflectance, [0, 1]. With --vegetation the diffuse term is dhr/pi
    /// (Meng (2012)'s vegetation: --n 1.5 --dhr 0.04).
    #[arg(long)]
    pub dhr: Option<f64>,
    /// Incident (sun) zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub theta_i_deg: Option<f64>,
    /// View zenith angle, degrees, [0, 90].
    #[arg(long)]
    pub theta_r_deg: Option<f64>,
    /// Relative azimuth between source and view directions, degrees, [-360, 360]; 180 is specular.
    #[arg(long)]
    pub phi_deg: Option<f64>,
    /// Use the vegetation model (Meng (2012) Eq. 3.19) instead of the microfacet model.
    #[arg(long)]
    #[serde(default)]
    pub vegetation: bool,
    /// Absolute error target of the specular-albedo quadrature, [1e-14, 1e-2].
    #[arg(long, default_value_t = 1e-9)]
    #[serde(default = "default_tolerance")]
    pub tolerance: f64,
}

fn default_tolerance() -> f64 {
    1e-9
}

impl PbrdfArgs {
    /// Fills unset parameters from `--material` (explicit flags win).
    fn resolved(&self) -> Result<PbrdfArgs, CommandError> {
        let Some(name) = &self.material else {
            return Ok(self.clone());
        };
        let lib = MaterialLibrary::builtin();
        let m = lib
            .get(name)
            .map_err(|e| CommandError(format!("material: {e}")))?;
        let vegetation = self.vegetation || m.model == MaterialModel::Vegetation;
        Ok(PbrdfArgs {
            n: self.n.or(Some(m.n)),
            k: self.k.or(Some(m.k)),
            sigma: self.sigma.or(m.sigma),
            // The vegetation model's diffuse term is dhr / pi.
            dhr: self
                .dhr
                .or(m.dhr)
                .or(m.f00_diffuse.map(|f| f * std::f64::consts::PI)),
            vegetation,
            material: None,
            ..self.clone()
        })
    }

    fn surface(&self) -> Result<Surface, CommandError> {
        let idx = RefractiveIndex::new(required(self.n, "n", "(0, 100]")?, self.k.unwrap_or(0.0))?;
        let dhr = required(self.dhr, "dhr", "[0, 1]")?;
        if self.vegetation {
            ModelError::check_range("dhr", dhr, 0.0, 1.0, "[0, 1]")?;
            Ok(Surface::vegetation(idx, dhr / std::f64::consts::PI)?)
        } else {
            Ok(Surface::microfacet(
                idx,
                required(self.sigma, "sigma", "[1e-6, 10]")?,
                dhr,
            )?)
        }
    }
}

/// Caches diffuse terms across evaluations that share material and incidence angle (a batch of
/// view directions under one sun integrates the specular albedo once).
#[derive(Debug, Default)]
pub struct DiffuseCache {
    map: HashMap<[u64; 6], DiffuseTerm>,
}

impl DiffuseCache {
    /// Number of distinct diffuse terms computed.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// Whether nothing has been cached yet.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }
}

/// Evaluates [`PbrdfArgs`], reusing diffuse terms from `cache`.
pub fn pbrdf(a: &PbrdfArgs, cache: &mut DiffuseCache) -> Result<Value, CommandError> {
    let a = &a.resolved()?;
    let surface = a.surface()?;
    let ti = required(a.theta_i_deg, "theta_i_deg", "[0, 90]")?;
    let tr = required(a.theta_r_deg, "theta_r_deg", "[0, 90]")?;
    let phi = required(a.phi_deg, "phi_deg", "[-360, 360]")?;
    let g = Geometry::from_deg(ti, tr, phi)?;
    let tol = ModelError::check_range("tolerance", a.tolerance, 1e-14, 1e-2, "[1e-14, 1e-2]")?;
    let key = [
        a.n.unwrap_or(0.0).to_bits(),
        a.k.unwrap_or(0.0).to_bits(),
        if a.vegetation {
            u64::MAX
        } else {
            a.sigma.unwrap_or(0.0).to_bits()
        },
        a.dhr.unwrap_or(0.0).to_bits(),
        ti.to_bits(),
        tol.to_bits(),
    ];
    let diffuse = match cache.map.get(&key) {
        Some(d) => *d,
        None => {
            let d = surface.diffuse(ti.to_radians(), Tolerance::absolute(tol))?;
            cache.map.insert(key, d);
            d
        }
    };
    let f = surface.mueller_with(&g, &diffuse);
    let out = f.response_to_unpolarized();
    let mut warnings = Vec::new();
    if let Some(w) = diffuse.clamped {
        warnings.push(w.to_string());
    }
    if !diffuse.specular_albedo.converged {
        warnings.push(format!(
            "specular albedo quadrature did not reach tolerance {tol:e}: error estimate {:e}",
            diffuse.specular_albedo.error
        ));
    }
    let m = f.0;
    Ok(json!({
        "f": [[m[(0, 0)], m[(0, 1)], m[(0, 2)]], [m[(1, 0)], m[(1, 1)], m[(1, 2)]], [m[(2, 0)], m[(2, 1)], m[(2, 2)]]],
        "dolp": out.dolp().unwrap_or(0.0),
        "aop_deg": out.aop_rad().map(f64::to_degrees),
        "f00_diffuse": diffuse.f00,
        "specular_albedo": diffuse.specular_albedo.value,
        "specular_albedo_error": diffuse.specular_albedo.error,
        "quadrature_evaluations": diffuse.specular_albedo.evaluations,
        "warnings": warnings,
    }))
}

/// `polarimeter model stokes`: least-squares Stokes reconstruction from analyzer intensities.
#[derive(Debug, Clone, Default, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StokesArgs {
    /// Analyzer angles, degrees, comma-separated; at least 3 distinct modulo 180.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// Measured intensities, one per angle, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub intensities: Vec<f64>,
}

fn analyzer_set(angles_deg: &[f64], model: &AnalyzerModel) -> Result<AnalyzerSet, CommandError> {
    if let Some(bad) = angles_deg
        .iter()
        .find(|a| !a.is_finite() || a.abs() > 3600.0)
    {
        return Err(CommandError(format!(
            "angles_deg contains {}: allowed finite values in [-3600, 3600]",
            compact(*bad)
        )));
    }
    let rad: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    Ok(AnalyzerSet::new(&rad, model)?)
}

/// Evaluates [`StokesArgs`]. Intensities are powers: a negative one (noise after a dark is
/// subtracted) is a warning, and a fit without light (S0 <= 0) is refused.
pub fn stokes(a: &StokesArgs) -> Result<Value, CommandError> {
    let set = analyzer_set(&a.angles_deg, &AnalyzerModel::IDEAL)?;
    if let Some((i, v)) = a
        .intensities
        .iter()
        .enumerate()
        .find(|(_, v)| !v.is_finite())
    {
        return Err(CommandError(format!(
            "intensities[{i}] = {} is out of range: allowed finite values >= 0",
            compact(*v)
        )));
    }
    let s = set.reconstruct(&a.intensities)?;
    if s.0[0].is_nan() || s.0[0] <= 0.0 {
        let list: Vec<String> = a.intensities.iter().map(|v| compact(*v)).collect();
        return Err(CommandError(format!(
            "intensities = {} give S0 = {}: allowed values >= 0 (measured powers) whose fit \
             has S0 > 0",
            echo(&list.join(",")),
            compact(s.0[0])
        )));
    }
    let warnings: Vec<String> = a
        .intensities
        .iter()
        .enumerate()
        .filter(|(_, v)| **v < 0.0)
        .map(|(i, v)| {
            format!(
                "intensities[{i}] = {} is negative: allowed >= 0 (kept as noise; a dark \
                 subtracted twice?)",
                compact(*v)
            )
        })
        .collect();
    let predicted = set.intensities(&s);
    let n = a.intensities.len() as f64;
    let rss: f64 = predicted
        .iter()
        .zip(&a.intensities)
        .map(|(p, i)| (p - i).powi(2))
        .sum();
    Ok(json!({
        "s": [s.0[0], s.0[1], s.0[2]],
        "dolp": s.dolp(),
        "aop_deg": s.aop_rad().map(f64::to_degrees),
        "residual_rms": (rss / n).sqrt(),
        "warnings": warnings,
    }))
}

/// `polarimeter model polarimeter`: conditioning and noise gains of an analyzer set.
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolarimeterArgs {
    /// Analyzer angles, degrees, comma-separated; at least 3 distinct modulo 180.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// Analyzer extinction ratio k1/k2, > 1 (inf: ideal).
    #[arg(long, default_value_t = f64::INFINITY)]
    #[serde(default = "infinite")]
    pub extinction_ratio: f64,
    /// Analyzer angle offset added to every angle, degrees, [-180, 180].
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    #[serde(default)]
    pub offset_deg: f64,
}

fn infinite() -> f64 {
    f64::INFINITY
}

/// Evaluates [`PolarimeterArgs`].
pub fn polarimeter(a: &PolarimeterArgs) -> Result<Value, CommandError> {
    ModelError::check_range("offset_deg", a.offset_deg, -180.0, 180.0, "[-180, 180]")?;
    let model =
        AnalyzerModel::from_extinction_ratio(a.extinction_ratio, a.offset_deg.to_radians())?;
    let set = analyzer_set(&a.angles_deg, &model)?;
    let rows = |m: &nalgebra::DMatrix<f64>| -> Vec<Vec<f64>> {
        (0..m.nrows())
            .map(|i| m.row(i).iter().copied().collect())
            .collect()
    };
    Ok(json!({
        "cond2": set.cond2(),
        "ewv": set.ewv(),
        "singular_values": set.singular_values(),
        "pinv": rows(set.stokes_from_intensities()),
        "w": rows(set.intensities_from_stokes()),
        "noise_gains": set.noise_gains(),
    }))
}

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
            CommandError(format!(
                "time = {} is invalid ({e}): allowed RFC 3339, e.g. 2026-06-21T15:00:00Z",
                echo(text)
            ))
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
            .unwrap_or(Weather::STANDARD.pressure_hpa * (-a.elevation_m / 8434.0).exp());
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
            let path = a
                .table
                .as_ref()
                .ok_or_else(|| CommandError("model = \"table\" needs --table FILE.csv".into()))?;
            let reference = match a.reference.as_str() {
                "horizontal" => polar_model::sky::table::StokesReference::Horizontal,
                "vertical" => polar_model::sky::table::StokesReference::Vertical,
                other => {
                    return Err(CommandError(format!(
                        "reference = {} is invalid: allowed horizontal or vertical",
                        echo(other)
                    )))
                }
            };
            let text = std::fs::read_to_string(path).map_err(|e| {
                CommandError(format!(
                    "table = {:?}: cannot read ({e})",
                    path.display().to_string()
                ))
            })?;
            let t = polar_model::sky::table::SkyTable::from_csv_str(&text, reference)
                .map_err(|e| CommandError(format!("{}: {e}", path.display())))?;
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
            return Err(CommandError(format!(
                "model = {} is invalid: allowed rayleigh, berry or table",
                echo(other)
            )))
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
        CommandError(format!(
            "tiles = {} is invalid: allowed NxM with N, M >= 1, e.g. 3x3",
            echo(text)
        ))
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
            return Err(CommandError(format!(
            "fov_deg has {} values: allowed one (square) or two (across,along), each in (0, 120]",
            other.len()
        )))
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
        CommandError(format!(
            "scene = {:?}: cannot read ({e})",
            path.display().to_string()
        ))
    })?;
    let base = path.parent().unwrap_or(std::path::Path::new("."));
    polar_model::scene_file::Scene::from_toml_str_with_files(&text, &|p| read_relative(base, p))
        .map_err(|e| CommandError(format!("{}: {e}", path.display())))
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
        return Err(CommandError(format!(
            "step_deg = {step} is invalid: allowed a divisor of 90 in [1, 30]"
        )));
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
        .map_err(|e| CommandError(format!("{}: {}", a.scene.display(), e.0)))
}

/// `polarimeter model roc`: the analytic ROC of a detector for a target against a background,
/// each given by its mean and covariance (Stokes S0, S1, S2 when `angles_deg` is given, which
/// maps them to the intensities behind those analyzers; any feature space otherwise).
#[derive(Debug, Clone, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RocArgs {
    /// Detector: mf (linear matched filter), rx (quadratic), dolp (DoLP threshold; needs
    /// Stokes means and covariances).
    #[arg(long)]
    pub detector: String,
    /// Target mean, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_mean: Vec<f64>,
    /// Target covariance, row-major, n*n values.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub target_cov: Vec<f64>,
    /// Background mean.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub background_mean: Vec<f64>,
    /// Background covariance, row-major.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub background_cov: Vec<f64>,
    /// Analyzer angles, degrees: the means and covariances are Stokes vectors, detected in the
    /// intensities behind these analyzers (mf, rx).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    #[serde(default)]
    pub angles_deg: Vec<f64>,
    /// False-alarm rate, (0, 1).
    #[arg(long, default_value_t = 1e-3)]
    #[serde(default = "default_pfa")]
    pub pfa: f64,
    /// Fraction of the pixel the target fills, [0, 1].
    #[arg(long, default_value_t = 1.0)]
    #[serde(default = "one")]
    pub fill_fraction: f64,
}

fn default_pfa() -> f64 {
    1e-3
}

fn one() -> f64 {
    1.0
}

fn class_stats(
    mean_field: &'static str,
    cov_field: &'static str,
    mean: &[f64],
    cov: &[f64],
) -> Result<polar_model::metrics::ClassStats, CommandError> {
    use nalgebra::{DMatrix, DVector};
    let n = mean.len();
    if n == 0 {
        return Err(CommandError(format!(
            "{mean_field} is empty: allowed 1 or more values"
        )));
    }
    if cov.len() != n * n {
        return Err(CommandError(format!(
            "{cov_field} has {} values: allowed {} (a {n}x{n} matrix, row-major)",
            cov.len(),
            n * n
        )));
    }
    Ok(polar_model::metrics::ClassStats::new(
        cov_field,
        DVector::from_column_slice(mean),
        DMatrix::from_row_slice(n, n, cov),
    )?)
}

/// Evaluates [`RocArgs`].
pub fn roc(a: &RocArgs) -> Result<Value, CommandError> {
    use polar_model::metrics;
    let t = class_stats("target_mean", "target_cov", &a.target_mean, &a.target_cov)?;
    let b = class_stats(
        "background_mean",
        "background_cov",
        &a.background_mean,
        &a.background_cov,
    )?;
    let t = t.mixed(&b, a.fill_fraction).map_err(CommandError::from)?;
    if a.detector == "dolp" {
        // Each class's DoLP moments from its Stokes mean and covariance.
        use polar_model::stats::{dolp_aop_stats, RegimeChoice};
        if t.mean.len() != 3 {
            return Err(CommandError(format!(
                "target_mean has {} values: the dolp detector needs Stokes S0,S1,S2",
                t.mean.len()
            )));
        }
        let moments = |c: &metrics::ClassStats| -> Result<(f64, f64, Vec<String>), CommandError> {
            let mean = nalgebra::Vector3::new(c.mean[0], c.mean[1], c.mean[2]);
            let cov = nalgebra::Matrix3::from_fn(|i, j| c.cov[(i, j)]);
            let s = dolp_aop_stats(&mean, &cov, RegimeChoice::Auto)?;
            Ok((s.dolp_mean, s.dolp_std, s.warnings))
        };
        let (mt, st, mut warnings) = moments(&t)?;
        let (mb, sb, wb) = moments(&b)?;
        warnings.extend(wb);
        let r = metrics::dolp_threshold((mt, st), (mb, sb), a.pfa)?;
        warnings.extend(r.warnings.iter().cloned());
        return Ok(json!({
            "pd": r.pd,
            "pfa": r.pfa,
            "scr": r.scr,
            "curve": r.curve,
            "target_dolp": [mt, st],
            "background_dolp": [mb, sb],
            "warnings": warnings,
        }));
    }
    let (t, b) = if a.angles_deg.is_empty() {
        (t, b)
    } else {
        if t.mean.len() != 3 {
            return Err(CommandError(format!(
                "target_mean has {} values: with angles_deg allowed 3 (S0, S1, S2)",
                t.mean.len()
            )));
        }
        let set = analyzer_set(&a.angles_deg, &AnalyzerModel::IDEAL)?;
        let w = set.intensities_from_stokes();
        let to_intensity = |c: &metrics::ClassStats| metrics::ClassStats {
            mean: w * &c.mean,
            cov: w * &c.cov * w.transpose(),
        };
        (to_intensity(&t), to_intensity(&b))
    };
    let r = match a.detector.as_str() {
        "mf" => metrics::matched_filter(&t, &b, a.pfa)?,
        "rx" => metrics::rx(&t, &b, a.pfa)?,
        other => {
            return Err(CommandError(format!(
                "detector = {} is invalid: allowed mf, rx, dolp",
                echo(other)
            )))
        }
    };
    Ok(json!({
        "pd": r.pd,
        "pfa": r.pfa,
        "scr": r.scr,
        "curve": r.curve,
        "condition_number": r.condition_number,
        "pd_error": r.pd_error,
        "warnings": r.warnings,
    }))
}

/// `polarimeter model sensor`: the N frames' mean and covariance in DN for a scene radiance
/// seen through a camera (TOML file) behind analyzers at the given angles.
#[derive(Debug, Clone, Args)]
pub struct SensorArgs {
    /// Camera description (TOML; examples in examples/cameras/).
    #[arg(long)]
    pub camera: PathBuf,
    /// Analyzer angles, degrees, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angles_deg: Vec<f64>,
    /// Mean band Stokes radiance S0,S1,S2, W m^-2 sr^-1.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub radiance_mean: Vec<f64>,
    /// Its covariance (scene clutter), 9 values row-major, (W m^-2 sr^-1)^2; default none.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub radiance_cov: Vec<f64>,
    /// Integration time, ms.
    #[arg(long, allow_hyphen_values = true)]
    pub t_int_ms: f64,
    /// Spectral band, nm: lower,upper (flat response).
    #[arg(long, value_delimiter = ',', default_values_t = [500.0, 600.0])]
    pub band_nm: Vec<f64>,
    /// Sensor noise factor F_n (scales the sensor noise variance, or with
    /// --noise-factor-scales std its standard deviation).
    #[arg(long, default_value_t = 1.0)]
    pub noise_factor: f64,
    /// What the noise factor scales: variance or std.
    #[arg(long, default_value = "variance")]
    pub noise_factor_scales: String,
    /// Relative frame-to-frame calibration drift, [0, 1].
    #[arg(long, default_value_t = 0.0)]
    pub drift: f64,
    /// Frame sets for a Monte Carlo of the whole chain (0: none), up to 1e7.
    #[arg(long, default_value_t = 0)]
    pub monte_carlo: usize,
    /// Monte Carlo seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Evaluates [`SensorArgs`].
pub fn sensor(a: &SensorArgs) -> Result<Value, CommandError> {
    use polar_model::sensor::{Camera, Exposure, NoiseFactor, SensorModel};
    let text = std::fs::read_to_string(&a.camera)
        .map_err(|e| CommandError(format!("--camera {}: cannot read: {e}", a.camera.display())))?;
    let camera = Camera::from_toml_str(&text)
        .map_err(|e| CommandError(format!("--camera {}: {e}", a.camera.display())))?;
    let [lo, hi] = a.band_nm[..] else {
        return Err(CommandError(format!(
            "band_nm has {} values: allowed 2 (lower,upper)",
            a.band_nm.len()
        )));
    };
    let band = polar_model::atmosphere::Band::flat(lo, hi)?;
    let model = SensorModel::new(&camera, &band)?;
    let [s0, s1, s2] = a.radiance_mean[..] else {
        return Err(CommandError(format!(
            "radiance_mean has {} values: allowed 3 (S0,S1,S2)",
            a.radiance_mean.len()
        )));
    };
    // The model checks seconds; the user gave milliseconds.
    if !(a.t_int_ms.is_finite() && a.t_int_ms > 0.0 && a.t_int_ms <= 1e8) {
        return Err(CommandError(format!(
            "t_int_ms = {} is out of range: allowed > 0 and <= 1e8 ms",
            compact(a.t_int_ms)
        )));
    }
    let mut exposure = Exposure::new(
        a.t_int_ms * 1e-3,
        polar_model::polarization::Stokes::new(s0, s1, s2),
    );
    match a.radiance_cov.len() {
        0 => {}
        9 => exposure.radiance_cov_w2_m4_sr2 = nalgebra::Matrix3::from_row_slice(&a.radiance_cov),
        n => {
            return Err(CommandError(format!(
                "radiance_cov has {n} values: allowed 9 (3x3 row-major) or none"
            )))
        }
    }
    exposure.noise_factor = match a.noise_factor_scales.as_str() {
        "variance" => NoiseFactor::Variance(a.noise_factor),
        "std" => NoiseFactor::StdDev(a.noise_factor),
        other => {
            return Err(CommandError(format!(
                "noise_factor_scales = {} is invalid: allowed variance, std",
                echo(other)
            )))
        }
    };
    exposure.eps_cal = a.drift;
    let angles: Vec<f64> = a.angles_deg.iter().map(|d| d.to_radians()).collect();
    let s = model.signal(&angles, &exposure)?;
    let rows = |m: &nalgebra::DMatrix<f64>| -> Vec<Vec<f64>> {
        (0..m.nrows())
            .map(|i| m.row(i).iter().copied().collect())
            .collect()
    };
    let v = |x: &nalgebra::DVector<f64>| x.iter().copied().collect::<Vec<f64>>();
    let mut warnings = model.warnings().to_vec();
    warnings.extend(s.warnings.iter().cloned());
    let mc = if a.monte_carlo > 0 {
        let mc = polar_model::montecarlo::simulate_frames(
            &model,
            &angles,
            &exposure,
            a.monte_carlo,
            a.seed,
        )?;
        json!({
            "sets": mc.sets,
            "seed": a.seed,
            "mean": v(&mc.mean_dn),
            "cov": rows(&mc.cov_dn),
            "saturated_fraction": mc.saturated_fraction,
        })
    } else {
        Value::Null
    };
    Ok(json!({
        "mc": mc,
        "mean": v(&s.mean_dn),
        "cov": rows(&s.cov_dn),
        "saturated": s.saturated,
        "saturation_dn": s.saturation_dn,
        "electrons": v(&s.electrons),
        "dark_electrons": s.dark_electrons,
        "variance_dn2": {
            "shot": v(&s.variance.shot_dn2),
            "dark": v(&s.variance.dark_dn2),
            "read": v(&s.variance.read_dn2),
            "quantization": v(&s.variance.quantization_dn2),
            "clutter": v(&s.variance.clutter_dn2),
            "drift": v(&s.variance.drift_dn2),
        },
        "w": rows(&s.intensities_from_stokes),
        "warnings": warnings,
    }))
}

/// `polarimeter model dolp-stats`: DoLP and AoP mean and spread of the Stokes estimate from
/// intensities with independent noise `sigma_i` behind ideal analyzers (the integration over the
/// Gaussian Stokes estimate at every polarised SNR, or on request the Taylor or Rice
/// approximation), optionally checked by a seeded Monte Carlo.
#[derive(Debug, Clone, Args)]
pub struct DolpStatsArgs {
    /// Analyzer angles, degrees.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub angles_deg: Vec<f64>,
    /// The true Stokes vector S0,S1,S2 (intensity units).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub stokes: Vec<f64>,
    /// Standard deviation of each intensity, same units, > 0.
    #[arg(long)]
    pub sigma_i: f64,
    /// Method: auto (the integration, valid at every polarised SNR, with an error estimate),
    /// taylor (delta-method approximation) or rice (isotropic Rice approximation); the last two
    /// for comparison.
    #[arg(long, default_value = "auto")]
    pub regime: String,
    /// Monte Carlo samples for a check (0: none), up to 5e7.
    #[arg(long, default_value_t = 0)]
    pub monte_carlo: usize,
    /// Monte Carlo seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// A Stokes mean, its covariance and the estimator's warnings.
type StokesMoments = (nalgebra::Vector3<f64>, nalgebra::Matrix3<f64>, Vec<String>);

/// The Stokes mean and covariance of [`DolpStatsArgs`].
fn stokes_moments(
    angles_deg: &[f64],
    stokes: &[f64],
    sigma_i: f64,
) -> Result<StokesMoments, CommandError> {
    let [s0, s1, s2] = stokes[..] else {
        return Err(CommandError(format!(
            "stokes has {} values: allowed 3 (S0,S1,S2)",
            stokes.len()
        )));
    };
    if !(s0.is_finite() && s0 > 0.0 && s1.is_finite() && s2.is_finite()) {
        return Err(CommandError(format!(
            "stokes = {},{},{} is out of range: allowed finite values with S0 > 0",
            compact(s0),
            compact(s1),
            compact(s2)
        )));
    }
    let dolp = s1.hypot(s2) / s0;
    if dolp > 1.0 + 1e-12 {
        return Err(CommandError(format!(
            "stokes = {},{},{} has DoLP = sqrt(S1^2 + S2^2) / S0 = {}: allowed DoLP <= 1 \
             (a Stokes vector of light)",
            compact(s0),
            compact(s1),
            compact(s2),
            compact(dolp)
        )));
    }
    if !(sigma_i.is_finite() && sigma_i > 0.0) {
        return Err(CommandError(format!(
            "sigma_i = {} is out of range: allowed > 0 and finite",
            compact(sigma_i)
        )));
    }
    let set = analyzer_set(angles_deg, &AnalyzerModel::IDEAL)?;
    let w = set.intensities_from_stokes();
    let n = w.nrows();
    let cov_i = nalgebra::DMatrix::<f64>::identity(n, n) * (sigma_i * sigma_i);
    let est = polar_model::stats::stokes_cov_from_intensity_cov(w, &cov_i)?;
    Ok((nalgebra::Vector3::new(s0, s1, s2), est.cov, est.warnings))
}

/// Evaluates [`DolpStatsArgs`].
pub fn dolp_stats(a: &DolpStatsArgs) -> Result<Value, CommandError> {
    use polar_model::stats::{self, Regime, RegimeChoice, StatsMethod};
    let (mean, cov, mut warnings) = stokes_moments(&a.angles_deg, &a.stokes, a.sigma_i)?;
    let choice = match a.regime.as_str() {
        "auto" => RegimeChoice::Auto,
        "taylor" => RegimeChoice::Taylor,
        "rice" => RegimeChoice::Rice,
        other => {
            return Err(CommandError(format!(
                "regime = {} is invalid: allowed auto, taylor, rice",
                echo(other)
            )))
        }
    };
    let s = stats::dolp_aop_stats(&mean, &cov, choice)?;
    warnings.extend(s.warnings.iter().cloned());
    let mut out = json!({
        "mean": s.dolp_mean,
        "std": s.dolp_std,
        "aop_mean_deg": s.aop_mean_rad.to_degrees(),
        "aop_std_deg": s.aop_std_rad.to_degrees(),
        "aop_bias_deg": s.aop_bias_rad.to_degrees(),
        "method": match s.method {
            StatsMethod::Integration => "integration",
            StatsMethod::Taylor => "taylor",
            StatsMethod::Rice => "rice",
        },
        "rel_error_estimate": s.rel_error_estimate,
        "regime": match s.regime { Regime::Taylor => "taylor", Regime::Rice => "rice" },
        "polarised_snr": s.polarised_snr,
        "sigma_p": s.sigma_p,
        "stokes_cov": (0..3).map(|i| (0..3).map(|j| cov[(i, j)]).collect::<Vec<f64>>()).collect::<Vec<_>>(),
        "warnings": warnings,
    });
    if a.monte_carlo > 0 {
        let mc = stats::monte_carlo_dolp_aop(&mean, &cov, a.monte_carlo, a.seed)?;
        out["mc"] = json!({
            "samples": a.monte_carlo,
            "seed": a.seed,
            "mean": mc.dolp_mean,
            "std": mc.dolp_std,
            "aop_std_deg": mc.aop_std_rad.to_degrees(),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A metal gets the pseudo-Brewster angle (copper 68.454 deg, the published value in
    /// crates/model/tests/reference.rs, to its 6e-4 deg) with Rp there (0.428, between 0 and
    /// Rp at 60 deg); a dielectric keeps atan(n) = 56.659 deg and no pseudo angle.
    #[test]
    fn fresnel_reports_pseudo_brewster_for_metals_only() {
        let copper = fresnel(&FresnelArgs {
            n: Some(1.02),
            k: 2.577,
            theta_i_deg: Some(60.0),
        })
        .unwrap();
        assert!(copper.get("brewster_deg").is_none(), "{copper}");
        let pb = copper["pseudo_brewster_deg"].as_f64().unwrap();
        assert!((pb - 68.454).abs() < 6e-4, "{pb}");
        let rp_min = copper["rp_min"].as_f64().unwrap();
        assert!(
            rp_min > 0.0 && rp_min < copper["Rp"].as_f64().unwrap(),
            "{copper}"
        );
        let glass = fresnel(&FresnelArgs {
            n: Some(1.52),
            k: 0.0,
            theta_i_deg: Some(60.0),
        })
        .unwrap();
        assert!(glass.get("pseudo_brewster_deg").is_none(), "{glass}");
        assert!((glass["brewster_deg"].as_f64().unwrap() - 56.659293).abs() < 1e-6);
    }

    /// The rooftop lit by its 10-degree sky table, asked for 1e-9: every material states its
    /// floor (above 1e-4 of S0: a 10-degree grid), a note that 1e-9 is below it, an
    /// integration tolerance of at least a quarter of it, and an error estimate that includes
    /// it. The same scene with the model sky has no floor at all.
    #[test]
    fn scene_json_states_the_table_floor() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples");
        let table = load_scene(&root.join("rooftop_table.toml")).unwrap();
        let v = scene_json(&table, 1e-9).unwrap();
        for m in v["materials"].as_array().unwrap() {
            let f = &m["error_floor"];
            let relative = f["relative"].as_f64().unwrap();
            assert!(relative > 1e-4, "{m}");
            assert!(f["note"].as_str().unwrap().contains("below"), "{f}");
            assert!(f["source"].as_str().unwrap().contains("sky table"), "{f}");
            let to = f["integrated_to"].as_f64().unwrap();
            assert!(
                to >= 0.9 * polar_model::scene::FLOOR_FRACTION * relative,
                "{f}"
            );
            assert!(m["error_estimate"].as_f64().unwrap() >= relative, "{m}");
        }
        let model = load_scene(&root.join("rooftop.toml")).unwrap();
        let v = scene_json(&model, 1e-3).unwrap();
        for m in v["materials"].as_array().unwrap() {
            assert!(m.get("error_floor").is_none(), "{m}");
        }
    }

    #[test]
    fn numbers_print_compactly_and_long_text_is_cut() {
        assert_eq!(compact(1e300), "1e300");
        assert_eq!(compact(-1e-300), "-1e-300");
        assert_eq!(compact(95.0), "95");
        assert_eq!(compact(0.001), "0.001");
        assert_eq!(compact(f64::NAN), "NaN");
        let long = "y".repeat(1000);
        let e = echo(&long);
        assert!(
            e.contains('…') && e.ends_with("(1000 characters)") && e.len() < 120,
            "{e}"
        );
        assert_eq!(echo("3x3"), "\"3x3\"");
        // Foreign messages: long quoted spans cut, long numbers compact, once.
        let msg = format!(
            "invalid type: string \"{long}\", unknown field `{long}`, value {}.0",
            "1".to_string() + &"0".repeat(300)
        );
        let t = tidy(&msg);
        assert!(t.len() < 300, "{t}");
        assert!(
            t.contains("value 1e300") && t.matches("(1000 characters)").count() == 2,
            "{t}"
        );
        assert_eq!(tidy(&t), t);
        assert_eq!(
            tidy(&format!("x = {}", echo(&long))),
            format!("x = {}", echo(&long))
        );
        assert_eq!(
            tidy("a 12345 b_123456789012345678901234 \"q\""),
            "a 12345 b_123456789012345678901234 \"q\""
        );
    }
}
