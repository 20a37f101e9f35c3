//! The TOML scene format: sun (angles, or UTC time at a site), atmosphere, spectral band, sensor
//! pointing and the materials in view (built-in library names with overrides, or complete
//! parameters). The model does no I/O: this module turns TOML text into a [`Scene`]. Examples
//! live in the repository's `examples/` directory.
//!
//! ```toml
//! [sun]
//! time_utc = "2026-06-21T15:00:00Z"    # or zenith_deg = 40, azimuth_deg = 180
//! [site]                               # needed with time_utc
//! latitude_deg = 43.08
//! longitude_deg = -77.67
//! elevation_m = 160
//! [atmosphere]                         # optional; every field optional (clear continental)
//! aerosol_optical_depth_550 = 0.1
//! [sky]                                # optional; model = "single_scattering" by default
//! model = "berry"                      # separation_deg = 30, max_dolp = 0.7; or "table" with
//!                                      # file = "sky.csv" (zenith_deg,azimuth_deg,S0,S1,S2),
//!                                      # reference = "horizontal" | "vertical"
//! [band]
//! lo_nm = 450                          # or response = [[450, 0.2], [550, 1.0], [650, 0.3]]
//! hi_nm = 650
//! [sensor]
//! altitude_m = 30
//! off_nadir_deg = 60
//! look_azimuth_deg = 180               # clockwise from north
//! fov_deg = [8, 6]
//! [[material]]
//! name = "panel"
//! library = "black_paint"              # built-in; n, k, sigma, dhr, f00_diffuse override
//! texture_cv = 0.02                    # or texture_stokes_cv = [0.02, 0.002, 0.002]
//! ```

use crate::atmosphere::{Atmosphere, Band};
use crate::error::ModelError;
use crate::material::{Material, MaterialLibrary, MaterialModel};
use crate::scene::{SceneMaterial, SceneSpec, SkyModel, Texture};
use crate::sky::table::{SkyTable, StokesReference};
use crate::sun::{sun_position, Site, UtcTime};
use crate::tiles::Pointing;
use serde::Deserialize;

/// A parsed, validated scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    /// Illumination and viewing.
    pub spec: SceneSpec,
    /// The materials, in file order (the first is the target).
    pub materials: Vec<SceneMaterial>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct File {
    /// The sun: its angles, or a UTC time at `[site]`.
    sun: SunFile,
    /// Where the scene is (needed with `sun.time_utc`).
    site: Option<SiteFile>,
    /// The atmosphere (every key optional: a clear continental atmosphere).
    #[serde(default)]
    atmosphere: AtmosphereFile,
    /// The sky's polarization model (single scattering by default).
    sky: Option<SkyFile>,
    /// The spectral band: its edges, or a response curve.
    band: BandFile,
    /// Where the camera looks from.
    sensor: SensorFile,
    /// The materials in view (`[[material]]`, the first is the target).
    #[serde(rename = "material", default)]
    materials: Vec<MaterialFile>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct SunFile {
    /// The sun's zenith angle, degrees (with `azimuth_deg`).
    zenith_deg: Option<f64>,
    /// The sun's azimuth, degrees clockwise from north (with `zenith_deg`).
    azimuth_deg: Option<f64>,
    /// Or an RFC 3339 UTC instant (`2026-06-21T15:00:00Z`): the sun's position at `[site]`.
    time_utc: Option<String>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct SiteFile {
    /// Latitude, degrees north.
    latitude_deg: f64,
    /// Longitude, degrees east.
    longitude_deg: f64,
    /// Elevation, metres.
    #[serde(default)]
    elevation_m: f64,
}

#[derive(Debug, Default, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct AtmosphereFile {
    /// Aerosol optical depth at 550 nm.
    aerosol_optical_depth_550: Option<f64>,
    /// Angstrom exponent of the aerosol's optical depth.
    angstrom_exponent: Option<f64>,
    /// Aerosol single-scattering albedo.
    aerosol_ssa: Option<f64>,
    /// Aerosol asymmetry parameter (Henyey-Greenstein g).
    aerosol_g: Option<f64>,
    /// Scale height of the molecular (Rayleigh) atmosphere, metres.
    rayleigh_scale_height_m: Option<f64>,
    /// Scale height of the aerosol, metres.
    aerosol_scale_height_m: Option<f64>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct SkyFile {
    /// `"single_scattering"`, `"berry"` or `"table"`.
    model: String,
    /// Berry's model: the separation of its singular points, degrees.
    separation_deg: Option<f64>,
    /// Berry's model: the sky's largest DoLP.
    max_dolp: Option<f64>,
    /// `"table"`: a CSV file of `zenith_deg,azimuth_deg,S0,S1,S2`, relative to the scene file.
    file: Option<String>,
    /// `"table"`: the Stokes reference of its S1 and S2, `"horizontal"` or `"vertical"`.
    reference: Option<String>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct BandFile {
    /// The band's lower edge, nm (with `hi_nm`).
    lo_nm: Option<f64>,
    /// Its upper edge, nm.
    hi_nm: Option<f64>,
    /// Or a response curve: `[[nm, relative response], ...]`.
    response: Option<Vec<(f64, f64)>>,
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct SensorFile {
    /// The camera's height above the ground, metres.
    altitude_m: f64,
    /// Its look direction from straight down, degrees.
    off_nadir_deg: f64,
    /// Its look direction's azimuth, degrees clockwise from north.
    look_azimuth_deg: f64,
    /// Its field of view, degrees, `[across, along]`.
    fov_deg: (f64, f64),
}

#[derive(Debug, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct MaterialFile {
    /// The material's name in this scene (targets and masks name it).
    name: String,
    /// A built-in material (`polarimeter model materials` lists them); the keys below
    /// override its values.
    library: Option<String>,
    /// The pBRDF model, `"microfacet"` or `"vegetation"` (without `library`).
    model: Option<MaterialModel>,
    /// Real part of the refractive index.
    n: Option<f64>,
    /// Extinction coefficient (0 for dielectrics).
    k: Option<f64>,
    /// Facet-slope roughness `sigma = sigma_h / l` (Meng (2012) Eq. 3.13); microfacet only.
    sigma: Option<f64>,
    /// Directional-hemispherical reflectance (Eq. 3.17); microfacet only.
    dhr: Option<f64>,
    /// Unpolarised diffuse BRDF `f00_d`, sr^-1; vegetation only.
    f00_diffuse: Option<f64>,
    /// Texture: the coefficient of variation of the radiance from pixel to pixel.
    texture_cv: Option<f64>,
    /// Or the coefficients of variation of S0, S1 and S2.
    texture_stokes_cv: Option<[f64; 3]>,
}

/// The JSON Schema of a scene file as written (every key, with its description).
pub fn scene_file_schema() -> schemars::Schema {
    schemars::schema_for!(File)
}

fn invalid(field: &'static str, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field,
        reason: reason.into(),
    }
}

/// Parses `YYYY-MM-DDTHH:MM:SS[.fff](Z|+00:00)`; errors name `sun.time_utc`.
pub fn parse_utc(text: &str) -> Result<UtcTime, ModelError> {
    let bad = || {
        invalid(
            "sun.time_utc",
            format!("{text:?}: allowed an RFC 3339 UTC instant such as 2026-06-21T15:00:00Z"),
        )
    };
    let body = text
        .strip_suffix('Z')
        .or_else(|| text.strip_suffix("+00:00"))
        .ok_or_else(bad)?;
    let (date, time) = body.split_once(['T', 't', ' ']).ok_or_else(bad)?;
    let d: Vec<&str> = date.split('-').collect();
    let t: Vec<&str> = time.split(':').collect();
    if d.len() != 3 || t.len() != 3 {
        return Err(bad());
    }
    let num = |s: &str| s.parse::<u32>().map_err(|_| bad());
    let time = UtcTime {
        year: d[0].parse::<i32>().map_err(|_| bad())?,
        month: num(d[1])?,
        day: num(d[2])?,
        hour: num(t[0])?,
        minute: num(t[1])?,
        second: t[2].parse::<f64>().map_err(|_| bad())?,
    };
    let ok = (1..=12).contains(&time.month)
        && (1..=31).contains(&time.day)
        && time.hour < 24
        && time.minute < 60
        && (0.0..61.0).contains(&time.second);
    if ok {
        Ok(time)
    } else {
        Err(bad())
    }
}

impl Scene {
    /// Parses and validates a scene. Errors name the field, the value and the allowed range
    /// (TOML syntax errors and unknown keys come with their line and column). A scene that
    /// names a sky table file needs [`Scene::from_toml_str_with_files`].
    pub fn from_toml_str(text: &str) -> Result<Scene, ModelError> {
        Scene::from_toml_str_with_files(text, &|path| {
            Err(format!(
                "cannot read {path:?}: this parser has no file access (load the scene through the CLI)"
            ))
        })
    }

    /// As [`Scene::from_toml_str`], with `read` returning the text of a file the scene names
    /// (`sky.file`), or why it could not.
    pub fn from_toml_str_with_files(
        text: &str,
        read: &dyn Fn(&str) -> Result<String, String>,
    ) -> Result<Scene, ModelError> {
        let f: File = toml::from_str(text)
            .map_err(|e| invalid("scene", crate::error::toml_message(text, &e)))?;
        let site = f
            .site
            .as_ref()
            .map(|s| Site::new(s.latitude_deg, s.longitude_deg, s.elevation_m))
            .transpose()?;
        let (sun_zenith_deg, sun_azimuth_deg) =
            match (f.sun.zenith_deg, f.sun.azimuth_deg, &f.sun.time_utc) {
                (Some(z), Some(a), None) => (
                    ModelError::check_range("sun.zenith_deg", z, 0.0, 90.0, "[0, 90]")?,
                    ModelError::check_range("sun.azimuth_deg", a, -360.0, 360.0, "[-360, 360]")?,
                ),
                (None, None, Some(t)) => {
                    let site = site.ok_or_else(|| {
                        invalid(
                            "site",
                            "sun.time_utc needs a [site] with latitude_deg, longitude_deg",
                        )
                    })?;
                    let p = sun_position(&parse_utc(t)?, &site, None, None)?;
                    if p.zenith_deg > 90.0 {
                        return Err(ModelError::OutOfRange {
                            field: "sun.time_utc",
                            value: p.zenith_deg,
                            allowed: "a time when the sun is up (zenith <= 90 deg)",
                        });
                    }
                    (p.zenith_deg, p.azimuth_deg)
                }
                _ => {
                    return Err(invalid(
                        "sun",
                        "give either zenith_deg and azimuth_deg, or time_utc (with [site])",
                    ))
                }
            };
        let d = Atmosphere::default();
        let a = &f.atmosphere;
        let atmosphere = Atmosphere {
            aerosol_optical_depth_550: a
                .aerosol_optical_depth_550
                .unwrap_or(d.aerosol_optical_depth_550),
            angstrom_exponent: a.angstrom_exponent.unwrap_or(d.angstrom_exponent),
            aerosol_ssa: a.aerosol_ssa.unwrap_or(d.aerosol_ssa),
            aerosol_g: a.aerosol_g.unwrap_or(d.aerosol_g),
            ground_elevation_m: site.map_or(0.0, |s| s.elevation_m),
            rayleigh_scale_height_m: a
                .rayleigh_scale_height_m
                .unwrap_or(d.rayleigh_scale_height_m),
            aerosol_scale_height_m: a.aerosol_scale_height_m.unwrap_or(d.aerosol_scale_height_m),
        };
        atmosphere.validate()?;
        let band = match (&f.band.lo_nm, &f.band.hi_nm, &f.band.response) {
            (Some(lo), Some(hi), None) => Band::flat(*lo, *hi)?,
            (None, None, Some(r)) => Band::tabulated(r.clone())?,
            _ => {
                return Err(invalid(
                    "band",
                    "give either lo_nm and hi_nm, or response = [[nm, relative], ...]",
                ))
            }
        };
        let sky = match f.sky {
            None => SkyModel::SingleScattering,
            Some(k) => sky_model(k, read)?,
        };
        let pointing = Pointing {
            altitude_m: f.sensor.altitude_m,
            off_nadir_deg: f.sensor.off_nadir_deg,
            look_azimuth_deg: f.sensor.look_azimuth_deg,
            fov_deg: f.sensor.fov_deg,
        };
        // Validates the pointing (and that every ray reaches the ground).
        let field = crate::tiles::Field::new(&pointing, sun_zenith_deg, sun_azimuth_deg)?;
        for (u, v) in [(-1.0, 1.0), (1.0, 1.0)] {
            field.ray(u, v, (0, 0))?;
        }
        if f.materials.is_empty() {
            return Err(invalid("material", "at least one [[material]] is needed"));
        }
        let library = MaterialLibrary::builtin();
        let mut materials = Vec::with_capacity(f.materials.len());
        let mut names = std::collections::HashSet::new();
        for m in f.materials {
            if !names.insert(m.name.clone()) {
                return Err(invalid(
                    "material.name",
                    format!("{:?} appears more than once", m.name),
                ));
            }
            materials.push(material(&library, m)?);
        }
        Ok(Scene {
            spec: SceneSpec {
                sun_zenith_deg,
                sun_azimuth_deg,
                atmosphere,
                sky,
                band,
                pointing,
            },
            materials,
        })
    }
}

/// Largest DoLP of the Berry sky when the file gives none: the middle of clear skies' 0.6-0.8
/// (MODEL.md section 10).
const BERRY_MAX_DOLP: f64 = 0.7;
/// Babinet-Brewster separation when the file gives none: the two points sit roughly 15 deg
/// above and below the sun in clear skies (Berry, Dennis & Lee 2004, introduction); the CLI's
/// `model sky --model berry` uses the same default.
const BERRY_SEPARATION_DEG: f64 = 30.0;

fn sky_model(
    k: SkyFile,
    read: &dyn Fn(&str) -> Result<String, String>,
) -> Result<SkyModel, ModelError> {
    let only = |field: &'static str, present: bool, model: &str| {
        if present {
            Err(invalid(
                field,
                format!("is not used by sky.model = {model:?}"),
            ))
        } else {
            Ok(())
        }
    };
    match k.model.as_str() {
        "single_scattering" => {
            only("sky.separation_deg", k.separation_deg.is_some(), &k.model)?;
            only("sky.max_dolp", k.max_dolp.is_some(), &k.model)?;
            only("sky.file", k.file.is_some(), &k.model)?;
            only("sky.reference", k.reference.is_some(), &k.model)?;
            Ok(SkyModel::SingleScattering)
        }
        "berry" => {
            only("sky.file", k.file.is_some(), &k.model)?;
            only("sky.reference", k.reference.is_some(), &k.model)?;
            Ok(SkyModel::Berry {
                separation_deg: ModelError::check_range(
                    "sky.separation_deg",
                    k.separation_deg.unwrap_or(BERRY_SEPARATION_DEG),
                    0.0,
                    60.0,
                    "[0, 60]",
                )?,
                max_dolp: ModelError::check_range(
                    "sky.max_dolp",
                    k.max_dolp.unwrap_or(BERRY_MAX_DOLP),
                    0.0,
                    1.0,
                    "[0, 1]",
                )?,
            })
        }
        "table" => {
            only("sky.separation_deg", k.separation_deg.is_some(), &k.model)?;
            only("sky.max_dolp", k.max_dolp.is_some(), &k.model)?;
            let path = k.file.ok_or_else(|| {
                invalid("sky.file", "sky.model = \"table\" needs file = \"...csv\"")
            })?;
            let reference = match k.reference.as_deref() {
                None | Some("horizontal") => StokesReference::Horizontal,
                Some("vertical") => StokesReference::Vertical,
                Some(other) => {
                    return Err(invalid(
                        "sky.reference",
                        format!("{other:?}: allowed \"horizontal\" or \"vertical\""),
                    ))
                }
            };
            let text = read(&path).map_err(|e| invalid("sky.file", e))?;
            let table = SkyTable::from_csv_str(&text, reference)
                .map_err(|e| invalid("sky.file", format!("{path}: {e}")))?;
            Ok(SkyModel::Table(std::sync::Arc::new(table)))
        }
        other => Err(invalid(
            "sky.model",
            format!("{other:?}: allowed \"single_scattering\", \"berry\" or \"table\""),
        )),
    }
}

fn material(library: &MaterialLibrary, m: MaterialFile) -> Result<SceneMaterial, ModelError> {
    let base = match &m.library {
        Some(name) => library
            .get(name)
            .map_err(|e| invalid("material.library", e.to_string()))?
            .clone(),
        None => Material {
            name: m.name.clone(),
            wavelength_nm: 550.0,
            n: m.n.ok_or_else(|| {
                invalid(
                    "material.n",
                    format!("material {:?}: give library = NAME or n", m.name),
                )
            })?,
            k: 0.0,
            model: m.model.unwrap_or(MaterialModel::Microfacet),
            sigma: None,
            dhr: None,
            f00_diffuse: None,
            source: "scene file".into(),
        },
    };
    let merged = Material {
        n: m.n.unwrap_or(base.n),
        k: m.k.unwrap_or(base.k),
        model: m.model.unwrap_or(base.model),
        sigma: m.sigma.or(base.sigma),
        dhr: m.dhr.or(base.dhr),
        f00_diffuse: m.f00_diffuse.or(base.f00_diffuse),
        ..base
    };
    let surface = merged
        .surface()
        .map_err(|e| invalid("material", format!("material {:?}: {e}", m.name)))?;
    let texture = match (m.texture_cv, m.texture_stokes_cv) {
        (None, None) => Texture::None,
        (Some(cv), None) => Texture::Cv(ModelError::check_range(
            "material.texture_cv",
            cv,
            0.0,
            1.0,
            "[0, 1]",
        )?),
        (None, Some(c)) => {
            for v in c {
                ModelError::check_range("material.texture_stokes_cv", v, 0.0, 1.0, "[0, 1] each")?;
            }
            Texture::Measured(c)
        }
        (Some(_), Some(_)) => {
            return Err(invalid(
                "material.texture_cv",
                format!(
                    "material {:?}: give texture_cv or texture_stokes_cv, not both",
                    m.name
                ),
            ))
        }
    };
    Ok(SceneMaterial {
        name: m.name,
        surface,
        texture,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = r#"
[sun]
zenith_deg = 40
azimuth_deg = 180
[band]
lo_nm = 450
hi_nm = 650
[sensor]
altitude_m = 30
off_nadir_deg = 50
look_azimuth_deg = 180
fov_deg = [8, 6]
[[material]]
name = "panel"
library = "black_paint"
texture_cv = 0.02
"#;

    fn with_sky(sky: &str) -> String {
        MINIMAL.replace("[band]", &format!("[sky]\n{sky}\n[band]"))
    }

    /// A 30 x 90 degree table, optionally without one row.
    fn table(drop: Option<&str>) -> String {
        let mut t = String::from("zenith_deg,azimuth_deg,S0,S1,S2\n");
        for z in [0, 30, 60, 90] {
            for a in [0, 90, 180, 270] {
                let row = format!("{z},{a},1.0,0.1,0.0");
                if Some(row.as_str()) != drop {
                    t += &row;
                    t += "\n";
                }
            }
        }
        t
    }

    /// The [sky] section: Berry with defaults, a table read through the caller's reader, and
    /// errors naming the field: unknown model, unused key, unreadable file, a table with a hole.
    #[test]
    fn sky_section_parses_and_errors_name_the_field() {
        let s = Scene::from_toml_str(&with_sky("model = \"berry\"")).unwrap();
        assert_eq!(
            s.spec.sky,
            SkyModel::Berry {
                separation_deg: BERRY_SEPARATION_DEG,
                max_dolp: BERRY_MAX_DOLP
            }
        );
        let read_ok = |p: &str| {
            assert_eq!(p, "sky.csv");
            Ok(table(None))
        };
        let text = with_sky("model = \"table\"\nfile = \"sky.csv\"\nreference = \"vertical\"");
        let s = Scene::from_toml_str_with_files(&text, &read_ok).unwrap();
        let SkyModel::Table(t) = &s.spec.sky else {
            panic!("{:?}", s.spec.sky)
        };
        // Vertical reference: the file's S1 = 0.1 is -0.1 in the horizontal frame.
        assert!((t.stokes_at_deg(45.0, 45.0).0[1] + 0.1).abs() < 1e-12);
        let e = Scene::from_toml_str(&text).unwrap_err().to_string();
        assert!(
            e.contains("sky.file") && e.contains("no file access"),
            "{e}"
        );
        let holed = |_: &str| Ok(table(Some("60,90,1.0,0.1,0.0")));
        let e = Scene::from_toml_str_with_files(&text, &holed)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("sky.file") && e.contains("sky.csv") && e.contains("(60.0, 90.0)"),
            "{e}"
        );
        for (sky, field) in [
            ("model = \"modtran\"", "sky.model"),
            ("model = \"berry\"\nfile = \"x.csv\"", "sky.file"),
            ("model = \"berry\"\nmax_dolp = 1.5", "sky.max_dolp"),
            ("model = \"table\"", "sky.file"),
            (
                "model = \"table\"\nfile = \"a\"\nreference = \"up\"",
                "sky.reference",
            ),
        ] {
            let e = Scene::from_toml_str(&with_sky(sky))
                .unwrap_err()
                .to_string();
            assert!(e.contains(field), "{sky}: {e}");
        }
    }

    #[test]
    fn minimal_scene_parses_with_defaults() {
        let s = Scene::from_toml_str(MINIMAL).unwrap();
        assert_eq!(s.spec.atmosphere, Atmosphere::default());
        assert_eq!(s.materials.len(), 1);
        assert_eq!(s.materials[0].texture, Texture::Cv(0.02));
    }

    /// The NREL SPA worked example through the file: zenith 50.11162 (refraction off: the
    /// geometric zenith is about 0.0136 deg larger), azimuth 194.340241.
    #[test]
    fn time_and_site_give_the_sun() {
        let text = MINIMAL.replace(
            "zenith_deg = 40\nazimuth_deg = 180",
            "time_utc = \"2003-10-17T19:30:30Z\"",
        ) + "[site]\nlatitude_deg = 39.742476\nlongitude_deg = -105.1786\nelevation_m = 1830.14\n";
        let s = Scene::from_toml_str(&text).unwrap();
        assert!(
            (s.spec.sun_zenith_deg - 50.1116).abs() < 0.02,
            "{}",
            s.spec.sun_zenith_deg
        );
        assert!(
            (s.spec.sun_azimuth_deg - 194.34).abs() < 0.01,
            "{}",
            s.spec.sun_azimuth_deg
        );
        assert_eq!(s.spec.atmosphere.ground_elevation_m, 1830.14);
    }

    #[test]
    fn errors_name_field_value_and_range() {
        let cases = [
            (
                MINIMAL.replace("zenith_deg = 40", "zenith_deg = 95"),
                "sun.zenith_deg",
                "95",
            ),
            (
                MINIMAL.replace("altitude_m = 30", "altitude_m = -3"),
                "altitude_m",
                "-3",
            ),
            (
                MINIMAL.replace("texture_cv = 0.02", "texture_cv = 2"),
                "texture_cv",
                "[0, 1]",
            ),
            (
                MINIMAL.replace("black_paint", "chalk"),
                "chalk",
                "black_paint",
            ),
            (
                MINIMAL.replace("fov_deg = [8, 6]", "fov_deg = [8, 100]"),
                "fov_deg",
                "horizon",
            ),
            (
                MINIMAL.replace(
                    "library = \"black_paint\"",
                    "library = \"black_paint\"\nsigma = -1",
                ),
                "sigma",
                "-1",
            ),
            (
                MINIMAL.replace("lo_nm = 450", "lo_nm = 250"),
                "band_nm",
                "250",
            ),
            (
                MINIMAL.replace("[sensor]", "[sensor]\ncolour = 3"),
                "colour",
                "line",
            ),
            (
                MINIMAL.replace(
                    "zenith_deg = 40\nazimuth_deg = 180",
                    "time_utc = \"2026-06-21T15:00:00Z\"",
                ),
                "site",
                "latitude_deg",
            ),
        ];
        for (text, a, b) in cases {
            let e = Scene::from_toml_str(&text).unwrap_err().to_string();
            assert!(
                e.contains(a) && e.contains(b),
                "expected {a:?} and {b:?} in: {e}"
            );
        }
    }

    #[test]
    fn utc_parser_accepts_rfc3339_utc_only() {
        let t = parse_utc("2026-06-21T15:00:30.5Z").unwrap();
        assert_eq!(
            (t.year, t.month, t.day, t.hour, t.minute),
            (2026, 6, 21, 15, 0)
        );
        assert_eq!(t.second, 30.5);
        for bad in [
            "2026-06-21T15:00:00",
            "2026-06-21T15:00:00+02:00",
            "2026-13-01T00:00:00Z",
            "x",
        ] {
            assert!(parse_utc(bad).is_err(), "{bad}");
        }
    }
}
