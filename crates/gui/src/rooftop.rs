//! The rooftop panel: the sun's position and the sky's DoLP/AoP map for a site and a
//! UTC time.
//!
//! - Sun: the NREL Solar Position Algorithm through [`polar_model::sun::sun_position`] (MODEL.md
//!   section 10), with exactly the defaults of `polarimeter model sun`: refraction for a
//!   standard atmosphere scaled to the site's elevation (8434 m scale height, 15 C) and the
//!   Espenak-Meeus estimate of Delta T.
//! - Sky: Rayleigh single scattering, [`polar_model::sky::RayleighSky`] at the chosen wavelength
//!   (MODEL.md section 10; DoLP `-P12 / P11` with molecular depolarisation 0.0279, maximum
//!   0.9457 at 90 deg from the sun), the Stokes vector in each ray's frame with its x axis
//!   horizontal (MODEL.md section 0: `S1 > 0` is a horizontal E-vector,
//!   `AoP = 0.5 atan2(S2, S1)` in (-90, 90] deg, Meng (2012) Eq. 2.15).
//! - The plane-parallel single-scattering model has no radiance when the sun is below the
//!   horizon (it returns an error naming `sun_zenith_deg`). The map then shows that error and
//!   draws the *twilight geometry*: the same single-scattering polarisation pattern (DoLP
//!   [`RayleighSky::dolp`] of the scattering angle, E-vector perpendicular to the scattering
//!   plane, from [`BerrySky`] with zero neutral-point separation, which the model tests against
//!   the Rayleigh E-vector), which is what a twilight sky, lit by sunlight passing overhead,
//!   shows to first order.
//!
//! Projection of the maps: zenith-centred equidistant fisheye, the radius proportional to the
//! zenith angle (0 at the centre, 90 deg at the rim), **north up and east left**, as an all-sky
//! camera looking up sees the sky. Pixels outside the horizon circle are background (NaN in
//! [`SkyMap`]).

use crate::colour;
use eframe::egui;
use nalgebra::Vector3;
use polar_model::polarization::Stokes;
use polar_model::sky::{direction_from_deg, BerrySky, RayleighSky};
use polar_model::sun::{sun_position, Site, UtcTime, Weather};
use std::time::Instant;

/// The accepted format of the UTC time text.
pub const TIME_FORMAT: &str = "YYYY-MM-DDTHH:MM:SSZ";

/// Pixels across the panel's maps.
pub const DEFAULT_MAP_SIZE_PX: usize = 256;

/// The smallest map [`sky_map`] accepts, pixels across.
pub const MIN_MAP_SIZE_PX: usize = 8;

/// The largest map [`sky_map`] accepts, pixels across.
pub const MAX_MAP_SIZE_PX: usize = 2048;

/// Air temperature used for the refraction correction, degrees Celsius (the CLI's default).
pub const REFRACTION_TEMPERATURE_C: f64 = 15.0;

/// The label of the AoP convention, shown next to the AoP map.
pub const AOP_CONVENTION: &str = "AoP from the local horizontal, degrees in (-90, 90], positive \
     counter-clockwise as seen looking at the sky (Stokes x axis horizontal; at the zenith the \
     reference is north)";

/// Colour of the map pixels outside the horizon circle.
const BACKGROUND: colour::Rgb = [28, 28, 32];

/// Margin around each map for the N/E/S/W labels, points.
const RIM_MARGIN: f32 = 16.0;

/// The inputs of a sky map: the site, the UTC time and the wavelength.
#[derive(Debug, Clone, PartialEq)]
pub struct SkyInputs {
    /// Geodetic latitude, degrees north, `[-90, 90]`.
    pub latitude_deg: f64,
    /// Longitude, degrees east (west negative), `[-180, 180]`.
    pub longitude_deg: f64,
    /// Elevation above sea level, metres, `[-500, 9000]`.
    pub elevation_m: f64,
    /// The UTC instant, [`TIME_FORMAT`] (`2024-06-21T18:00:00Z`).
    pub time_utc: String,
    /// Wavelength, nm, `[200, 3000]`.
    pub wavelength_nm: f64,
}

impl Default for SkyInputs {
    /// Boulder-like site (40 N, 105 W, 1600 m), the June solstice at 18:00 UTC (late morning
    /// local solar time), 550 nm.
    fn default() -> Self {
        SkyInputs {
            latitude_deg: 40.0,
            longitude_deg: -105.0,
            elevation_m: 1600.0,
            time_utc: "2024-06-21T18:00:00Z".into(),
            wavelength_nm: 550.0,
        }
    }
}

/// Which formula drew the polarisation of a [`SkyMap`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkyPattern {
    /// [`RayleighSky::stokes`]: single scattering in a plane-parallel layer (sun above the
    /// horizon).
    SingleScattering,
    /// The sun is below the horizon: the single-scattering geometry only (DoLP of the
    /// scattering angle, E-vector perpendicular to the scattering plane), no radiance.
    TwilightGeometry,
}

/// A computed all-sky map (see the module documentation for the projection).
#[derive(Debug, Clone, PartialEq)]
pub struct SkyMap {
    /// Pixels across (and down): the map is `size` x `size`, row-major, row 0 at the top (north).
    pub size: usize,
    /// The sun's topocentric zenith angle, degrees (refracted; above 90 when it has set).
    pub sun_zenith_deg: f64,
    /// The sun's azimuth, degrees clockwise from north, `[0, 360)`.
    pub sun_azimuth_deg: f64,
    /// The `Delta T = TT - UT` the SPA used, seconds.
    pub delta_t_s: f64,
    /// The wavelength, nm.
    pub wavelength_nm: f64,
    /// Rayleigh optical depth of the atmosphere at the wavelength (Hansen & Travis 1974,
    /// MODEL.md section 10). It sets the radiance, not the polarisation pattern.
    pub optical_depth: f64,
    /// DoLP of each pixel, `[0, 1]`; NaN outside the horizon circle.
    pub dolp: Vec<f32>,
    /// AoP of each pixel, degrees in (-90, 90] (see [`AOP_CONVENTION`]); NaN outside the
    /// horizon circle and where the light is unpolarised (at the sun).
    pub aop_deg: Vec<f32>,
    /// The largest DoLP over the map's pixels.
    pub max_dolp: f64,
    /// Zenith angle of the pixel with the largest DoLP, degrees.
    pub max_dolp_zenith_deg: f64,
    /// Azimuth of the pixel with the largest DoLP, degrees clockwise from north.
    pub max_dolp_azimuth_deg: f64,
    /// The model's largest DoLP, at 90 deg from the sun: `0.75 Delta / (1 - 0.25 Delta)`.
    pub model_max_dolp: f64,
    /// The formula that drew the pattern.
    pub pattern: SkyPattern,
    /// The sky model's error when it could not be evaluated as such (the sun below the
    /// horizon), shown in the panel.
    pub model_note: Option<String>,
}

/// One pixel of a map under the pointer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    /// Zenith angle of the pixel centre, degrees.
    pub zenith_deg: f64,
    /// Azimuth of the pixel centre, degrees clockwise from north.
    pub azimuth_deg: f64,
    /// DoLP there.
    pub dolp: f64,
    /// AoP there, degrees (NaN where the light is unpolarised).
    pub aop_deg: f64,
}

impl Probe {
    /// The probe line: `probe: zenith 12.3°, azimuth 45.6°: DoLP 0.812, AoP 12.3°`.
    pub fn text(&self) -> String {
        let aop = if self.aop_deg.is_finite() {
            format!("{:.1}°", self.aop_deg)
        } else {
            "undefined (unpolarised)".into()
        };
        format!(
            "probe: zenith {:.1}°, azimuth {:.1}°: DoLP {:.3}, AoP {aop}",
            self.zenith_deg, self.azimuth_deg, self.dolp
        )
    }
}

/// Zenith angle and azimuth (degrees) of the centre of pixel `(col, row)` of a `size` map, or
/// `None` outside the horizon circle or the map.
fn pixel_direction(size: usize, col: usize, row: usize) -> Option<(f64, f64)> {
    if col >= size || row >= size {
        return None;
    }
    let c = size as f64 / 2.0;
    let x = col as f64 + 0.5 - c;
    let y = row as f64 + 0.5 - c;
    let r = x.hypot(y);
    if r > c {
        return None;
    }
    // North up (-y), east left (-x).
    let azimuth_deg = (-x).atan2(-y).to_degrees().rem_euclid(360.0);
    Some((r / c * 90.0, azimuth_deg))
}

impl SkyMap {
    /// Zenith angle of one pixel step along a radius, degrees: `180 / size`.
    pub fn pixel_pitch_deg(&self) -> f64 {
        180.0 / self.size.max(1) as f64
    }

    /// Zenith angle and azimuth (degrees, clockwise from north) of the centre of pixel
    /// `(col, row)`; `None` outside the horizon circle or the map.
    pub fn direction_deg(&self, col: usize, row: usize) -> Option<(f64, f64)> {
        pixel_direction(self.size, col, row)
    }

    /// Continuous pixel coordinates `(x, y)` (pixel centres at `col + 0.5`, `row + 0.5`) of a
    /// sky direction; zenith angles above 90 deg fall outside the horizon circle.
    pub fn pixel_of(&self, zenith_deg: f64, azimuth_deg: f64) -> (f64, f64) {
        let c = self.size as f64 / 2.0;
        let r = zenith_deg / 90.0 * c;
        let (s, co) = azimuth_deg.to_radians().sin_cos();
        (c - r * s, c - r * co)
    }

    /// The sun's elevation above the horizon, degrees.
    pub fn sun_elevation_deg(&self) -> f64 {
        90.0 - self.sun_zenith_deg
    }

    /// Whether the sun has set (zenith angle above 90 deg).
    pub fn sun_below_horizon(&self) -> bool {
        self.sun_zenith_deg > 90.0
    }

    /// The values at pixel `(col, row)`; `None` outside the horizon circle or the map.
    pub fn probe(&self, col: usize, row: usize) -> Option<Probe> {
        let (zenith_deg, azimuth_deg) = self.direction_deg(col, row)?;
        let i = row * self.size + col;
        let dolp = f64::from(*self.dolp.get(i)?);
        dolp.is_finite().then(|| Probe {
            zenith_deg,
            azimuth_deg,
            dolp,
            aop_deg: self.aop_deg.get(i).map_or(f64::NAN, |&a| f64::from(a)),
        })
    }

    /// The sun line: zenith, azimuth, elevation.
    pub fn sun_text(&self) -> String {
        format!(
            "Sun: zenith {:.3}°, azimuth {:.3}° (clockwise from north), elevation {:.3}° \
             (NREL SPA, refracted, Delta T {:.1} s)",
            self.sun_zenith_deg,
            self.sun_azimuth_deg,
            self.sun_elevation_deg(),
            self.delta_t_s
        )
    }

    /// Where the maximum DoLP, the 90-deg band and the neutral points lie, in words.
    pub fn features_text(&self) -> String {
        let zs = self.sun_zenith_deg;
        let az = self.sun_azimuth_deg;
        let anti_az = (az + 180.0).rem_euclid(360.0);
        let band = if zs < 0.5 {
            "the 90° band is the horizon".to_string()
        } else {
            // The band's highest point lies in the sun's vertical plane; it crosses the
            // horizon 90 deg of azimuth either side of the sun (cos gamma = sin zs cos dA = 0).
            let (top_z, top_az) = if zs <= 90.0 {
                (90.0 - zs, anti_az)
            } else {
                (zs - 90.0, az)
            };
            format!(
                "the 90° band from the sun crosses the horizon at azimuths {:.0}° and {:.0}° \
                 and passes zenith angle {top_z:.0}° at azimuth {top_az:.0}°",
                (az - 90.0).rem_euclid(360.0),
                (az + 90.0).rem_euclid(360.0),
            )
        };
        let anti_z = 180.0 - zs;
        let antisun = if anti_z <= 90.0 {
            format!("antisun (zenith {anti_z:.1}°, azimuth {anti_az:.0}°, above the horizon)")
        } else {
            format!("antisun (zenith {anti_z:.1}°, below the horizon)")
        };
        format!(
            "Max DoLP {:.3} at zenith {:.1}°, azimuth {:.1}° (model maximum {:.4}); {band}. \
             Neutral points of single scattering: the sun and the {antisun}; a real sky splits \
             them into the Babinet/Brewster and Arago points about 15-20° away.",
            self.max_dolp, self.max_dolp_zenith_deg, self.max_dolp_azimuth_deg, self.model_max_dolp
        )
    }
}

/// `field = value is out of range: allowed allowed` unless `value` is finite and in
/// `[lo, hi]`.
fn check_range(field: &str, value: f64, lo: f64, hi: f64, allowed: &str) -> Result<f64, String> {
    if value.is_finite() && (lo..=hi).contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "{field} = {value} is out of range: allowed {allowed}"
        ))
    }
}

fn is_leap_year(year: i64) -> bool {
    (year % 4 == 0 && year % 100 != 0) || year % 400 == 0
}

/// Parses `YYYY-MM-DDTHH:MM:SSZ` (UTC; surrounding whitespace ignored) into calendar fields.
/// Errors name `time_utc`, the text, what is wrong and the allowed format. Years `[0, 6000]`
/// (the SPA's validity ends at 6000), Gregorian calendar, seconds `[0, 59]`.
pub fn parse_utc(text: &str) -> Result<UtcTime, String> {
    let t = text.trim();
    let bad = |why: String| {
        format!("time_utc = {text:?} is invalid ({why}): allowed {TIME_FORMAT}, e.g. 2024-06-21T18:00:00Z")
    };
    if t.len() != TIME_FORMAT.len() || !t.is_ascii() {
        return Err(bad(format!(
            "expected {} ASCII characters, got {}",
            TIME_FORMAT.len(),
            t.chars().count()
        )));
    }
    let b = t.as_bytes();
    for (i, sep) in [
        (4, b'-'),
        (7, b'-'),
        (10, b'T'),
        (13, b':'),
        (16, b':'),
        (19, b'Z'),
    ] {
        if b.get(i) != Some(&sep) {
            return Err(bad(format!(
                "expected '{}' at character {}",
                char::from(sep),
                i + 1
            )));
        }
    }
    let field = |from: usize, to: usize, name: &str, lo: i64, hi: i64| -> Result<i64, String> {
        let s = t.get(from..to).unwrap_or("");
        if s.is_empty() || !s.bytes().all(|c| c.is_ascii_digit()) {
            return Err(bad(format!("{name} {s:?} is not a number")));
        }
        let v: i64 = s
            .parse()
            .map_err(|_| bad(format!("{name} {s:?} is not a number")))?;
        if (lo..=hi).contains(&v) {
            Ok(v)
        } else {
            Err(bad(format!("{name} {v} is out of [{lo}, {hi}]")))
        }
    };
    let year = field(0, 4, "year", 0, 6000)?;
    let month = field(5, 7, "month", 1, 12)?;
    let days = match month {
        2 if is_leap_year(year) => 29,
        2 => 28,
        4 | 6 | 9 | 11 => 30,
        _ => 31,
    };
    let day = field(8, 10, "day", 1, days)?;
    let hour = field(11, 13, "hour", 0, 23)?;
    let minute = field(14, 16, "minute", 0, 59)?;
    let second = field(17, 19, "second", 0, 59)?;
    // The ranges above make these conversions lossless.
    Ok(UtcTime {
        year: year as i32,
        month: month as u32,
        day: day as u32,
        hour: hour as u32,
        minute: minute as u32,
        second: second as f64,
    })
}

/// Computes the sun's position and the all-sky DoLP/AoP map, `size_px` x `size_px` pixels
/// (projection in the module documentation). Pure: no clock, no UI.
///
/// Errors (a message naming the field, the value and what is allowed, never a panic):
/// `latitude_deg`, `longitude_deg`, `elevation_m`, `wavelength_nm`, `time_utc`, `size_px`.
pub fn sky_map(inputs: &SkyInputs, size_px: usize) -> Result<SkyMap, String> {
    let lat = check_range(
        "latitude_deg",
        inputs.latitude_deg,
        -90.0,
        90.0,
        "[-90, 90]",
    )?;
    let lon = check_range(
        "longitude_deg",
        inputs.longitude_deg,
        -180.0,
        180.0,
        "[-180, 180]",
    )?;
    let elev = check_range(
        "elevation_m",
        inputs.elevation_m,
        -500.0,
        9000.0,
        "[-500, 9000]",
    )?;
    let wavelength_nm = check_range(
        "wavelength_nm",
        inputs.wavelength_nm,
        200.0,
        3000.0,
        "[200, 3000]",
    )?;
    if !(MIN_MAP_SIZE_PX..=MAX_MAP_SIZE_PX).contains(&size_px) {
        return Err(format!(
            "size_px = {size_px} is out of range: allowed [{MIN_MAP_SIZE_PX}, {MAX_MAP_SIZE_PX}]"
        ));
    }
    let time = parse_utc(&inputs.time_utc)?;
    let site = Site::new(lat, lon, elev).map_err(|e| e.to_string())?;
    // As `polarimeter model sun` with its defaults: standard pressure scaled to the elevation,
    // 15 C, Delta T estimated.
    let weather = Weather {
        pressure_hpa: Weather::standard_pressure_hpa(elev),
        temperature_c: REFRACTION_TEMPERATURE_C,
    };
    let sun = sun_position(&time, &site, None, Some(weather))
        .map_err(|e| format!("sun position: {e}"))?;
    let sky = RayleighSky::at_wavelength(wavelength_nm).map_err(|e| e.to_string())?;
    let sun_dir = direction_from_deg(sun.zenith_deg, sun.azimuth_deg);
    // The model's verdict on this sun (it refuses a sun below the horizon).
    let model_note = sky
        .stokes(&sun_dir, &Vector3::z())
        .err()
        .map(|e| e.to_string());
    let pattern = if model_note.is_some() {
        SkyPattern::TwilightGeometry
    } else {
        SkyPattern::SingleScattering
    };
    let model_max_dolp = sky.dolp(0.0);
    let geometry = BerrySky {
        sun: sun_dir,
        separation_rad: 0.0,
        max_dolp: model_max_dolp,
    };

    let n = size_px * size_px;
    let mut dolp = vec![f32::NAN; n];
    let mut aop_deg = vec![f32::NAN; n];
    let mut best: Option<(f64, f64, f64)> = None;
    for row in 0..size_px {
        for col in 0..size_px {
            let Some((z, a)) = pixel_direction(size_px, col, row) else {
                continue;
            };
            let view = direction_from_deg(z, a);
            let stokes = match pattern {
                SkyPattern::SingleScattering => sky.stokes(&sun_dir, &view).ok(),
                SkyPattern::TwilightGeometry => {
                    let p = sky.dolp(sun_dir.dot(&view).clamp(-1.0, 1.0));
                    let (_, c2, s2) = geometry.polarization(&view);
                    Some(Stokes::new(1.0, p * c2, p * s2))
                }
            };
            let Some(s) = stokes else { continue };
            let Some(d) = s.dolp() else { continue };
            let i = row * size_px + col;
            dolp[i] = d as f32;
            aop_deg[i] = s.aop_rad().map_or(f32::NAN, |r| r.to_degrees() as f32);
            if best.is_none_or(|(bd, _, _)| d > bd) {
                best = Some((d, z, a));
            }
        }
    }
    let (max_dolp, max_dolp_zenith_deg, max_dolp_azimuth_deg) =
        best.unwrap_or((f64::NAN, f64::NAN, f64::NAN));
    Ok(SkyMap {
        size: size_px,
        sun_zenith_deg: sun.zenith_deg,
        sun_azimuth_deg: sun.azimuth_deg,
        delta_t_s: sun.delta_t_s,
        wavelength_nm,
        optical_depth: sky.optical_depth,
        dolp,
        aop_deg,
        max_dolp,
        max_dolp_zenith_deg,
        max_dolp_azimuth_deg,
        model_max_dolp,
        pattern,
        model_note,
    })
}

/// The DoLP map's colours: viridis over `[0, max_dolp]`, background outside the horizon.
fn dolp_rgb(map: &SkyMap) -> Vec<u8> {
    let hi = map.max_dolp as f32;
    let mut rgb = Vec::with_capacity(map.dolp.len() * 3);
    for &d in &map.dolp {
        let c = if d.is_finite() {
            colour::scalar(d, 0.0, hi)
        } else {
            BACKGROUND
        };
        rgb.extend_from_slice(&c);
    }
    rgb
}

/// The AoP map's colours: AoP as hue, DoLP as saturation (full at `max_dolp`), grey where the
/// AoP is undefined, background outside the horizon.
fn aop_rgb(map: &SkyMap) -> Vec<u8> {
    let full = map.max_dolp as f32;
    let mut rgb = Vec::with_capacity(map.dolp.len() * 3);
    for (&d, &a) in map.dolp.iter().zip(&map.aop_deg) {
        let c = if !d.is_finite() {
            BACKGROUND
        } else if a.is_finite() {
            colour::aop_dolp(a.to_radians(), d, full)
        } else {
            colour::hsv(0.0, 0.0, colour::AOP_VALUE)
        };
        rgb.extend_from_slice(&c);
    }
    rgb
}

pub(crate) fn color32(c: colour::Rgb) -> egui::Color32 {
    egui::Color32::from_rgb(c[0], c[1], c[2])
}

/// A horizontal colour bar of 64 steps coloured by `f(t)`, `t` in `[0, 1]`.
pub(crate) fn paint_bar(ui: &mut egui::Ui, width: f32, f: impl Fn(f32) -> colour::Rgb) {
    let (rect, _) = ui.allocate_exact_size(egui::vec2(width, 14.0), egui::Sense::hover());
    let n = 64;
    for i in 0..n {
        let t0 = i as f32 / n as f32;
        let t1 = (i + 1) as f32 / n as f32;
        let r = egui::Rect::from_min_max(
            egui::pos2(rect.left() + rect.width() * t0, rect.top()),
            egui::pos2(rect.left() + rect.width() * t1, rect.bottom()),
        );
        ui.painter()
            .rect_filled(r, 0.0, color32(f((t0 + t1) / 2.0)));
    }
}

/// The textures of the shown map, with the generation they were made for.
struct MapTextures {
    generation: u64,
    dolp: egui::TextureHandle,
    aop: egui::TextureHandle,
}

/// The rooftop panel: site, time and wavelength inputs, the sun's position and the two all-sky
/// maps (DoLP, AoP/DoLP) with a pixel probe.
pub struct RooftopPanel {
    /// The inputs being edited; [`RooftopPanel::update`] (the "Update" button) applies them.
    pub inputs: SkyInputs,
    /// Pixels across the computed maps.
    pub size_px: usize,
    applied: Option<SkyInputs>,
    map: Option<SkyMap>,
    error: Option<String>,
    compute_ms: f64,
    generation: u64,
    textures: Option<MapTextures>,
    probe: Option<Probe>,
}

impl Default for RooftopPanel {
    fn default() -> Self {
        Self::new()
    }
}

impl RooftopPanel {
    /// A panel with the [`SkyInputs::default`] site, time and wavelength and
    /// [`DEFAULT_MAP_SIZE_PX`] maps; the map is computed on the first [`RooftopPanel::show`].
    pub fn new() -> Self {
        RooftopPanel {
            inputs: SkyInputs::default(),
            size_px: DEFAULT_MAP_SIZE_PX,
            applied: None,
            map: None,
            error: None,
            compute_ms: 0.0,
            generation: 0,
            textures: None,
            probe: None,
        }
    }

    /// The map of the last applied inputs (`None` before the first update or when they were
    /// invalid).
    pub fn result(&self) -> Option<&SkyMap> {
        self.map.as_ref()
    }

    /// The error of the last applied inputs, if they were invalid.
    pub fn error(&self) -> Option<&str> {
        self.error.as_deref()
    }

    /// Recomputes the map from [`RooftopPanel::inputs`] (what "Update" does).
    pub fn update(&mut self) {
        let t0 = Instant::now();
        let r = sky_map(&self.inputs, self.size_px);
        self.compute_ms = t0.elapsed().as_secs_f64() * 1e3;
        self.applied = Some(self.inputs.clone());
        self.generation += 1;
        self.probe = None;
        match r {
            Ok(m) => {
                self.map = Some(m);
                self.error = None;
            }
            Err(e) => {
                self.map = None;
                self.error = Some(e);
            }
        }
    }

    /// Draws the panel into `ui`.
    pub fn show(&mut self, ui: &mut egui::Ui) {
        if self.applied.is_none() {
            self.update();
        }
        ui.heading("Rooftop: sun and sky");
        self.inputs_ui(ui);
        if let Some(e) = &self.error {
            ui.colored_label(ui.visuals().error_fg_color, format!("Error: {e}"));
            return;
        }
        let Some(map) = &self.map else {
            return;
        };
        ui.label(map.sun_text());
        if map.sun_below_horizon() {
            ui.colored_label(
                ui.visuals().warn_fg_color,
                format!(
                    "The sun is below the horizon ({:.2}° elevation): its marker sits on the \
                     rim at its azimuth.",
                    map.sun_elevation_deg()
                ),
            );
        }
        if let Some(note) = &map.model_note {
            ui.colored_label(
                ui.visuals().warn_fg_color,
                format!(
                    "Sky model: {note}. Drawn instead: the single-scattering geometry \
                     (twilight pattern, no radiance)."
                ),
            );
        }
        ui.label(map.features_text());
        ui.label(format!(
            "Rayleigh single scattering at {:.0} nm: optical depth {:.5} (sets the radiance, \
             not the polarisation pattern); {}x{} px in {:.1} ms.",
            map.wavelength_nm, map.optical_depth, map.size, map.size, self.compute_ms
        ));
        ui.label(
            "Equidistant fisheye centred on the zenith (rim = horizon), north up, east left, \
             as seen looking up.",
        );
        self.maps_ui(ui);
    }

    fn inputs_ui(&mut self, ui: &mut egui::Ui) {
        egui::Grid::new("rooftop inputs")
            .num_columns(2)
            .show(ui, |ui| {
                let l = ui.label("Latitude (deg N)");
                ui.add(egui::DragValue::new(&mut self.inputs.latitude_deg).speed(0.1))
                    .labelled_by(l.id);
                ui.end_row();
                let l = ui.label("Longitude (deg E)");
                ui.add(egui::DragValue::new(&mut self.inputs.longitude_deg).speed(0.1))
                    .labelled_by(l.id);
                ui.end_row();
                let l = ui.label("Elevation (m)");
                ui.add(egui::DragValue::new(&mut self.inputs.elevation_m).speed(10.0))
                    .labelled_by(l.id);
                ui.end_row();
                let l = ui.label(format!("UTC time ({TIME_FORMAT})"));
                ui.add(
                    egui::TextEdit::singleline(&mut self.inputs.time_utc)
                        .hint_text("2024-06-21T18:00:00Z")
                        .desired_width(180.0),
                )
                .labelled_by(l.id);
                ui.end_row();
                let l = ui.label("Wavelength (nm)");
                ui.add(egui::DragValue::new(&mut self.inputs.wavelength_nm).speed(1.0))
                    .labelled_by(l.id);
                ui.end_row();
            });
        ui.horizontal(|ui| {
            if ui.button("Update").clicked() {
                self.update();
            }
            if self.applied.as_ref() != Some(&self.inputs) {
                ui.label("inputs changed: press Update");
            }
        });
    }

    fn maps_ui(&mut self, ui: &mut egui::Ui) {
        let Some(map) = &self.map else {
            return;
        };
        if self.textures.as_ref().map(|t| t.generation) != Some(self.generation) {
            let size = [map.size, map.size];
            let ctx = ui.ctx();
            self.textures = Some(MapTextures {
                generation: self.generation,
                dolp: ctx.load_texture(
                    "rooftop dolp",
                    egui::ColorImage::from_rgb(size, &dolp_rgb(map)),
                    egui::TextureOptions::LINEAR,
                ),
                aop: ctx.load_texture(
                    "rooftop aop",
                    egui::ColorImage::from_rgb(size, &aop_rgb(map)),
                    egui::TextureOptions::LINEAR,
                ),
            });
        }
        let Some(tex) = &self.textures else {
            return;
        };
        let side = ((ui.available_width() - 4.0 * RIM_MARGIN - 24.0) / 2.0).clamp(120.0, 420.0);
        let mut hovered = None;
        ui.horizontal_top(|ui| {
            ui.vertical(|ui| {
                ui.label("DoLP");
                if let Some(p) = map_view(ui, map, &tex.dolp, side, "DoLP sky map") {
                    hovered = Some(p);
                }
                paint_bar(ui, side, colour::viridis);
                ui.label(format!("DoLP 0 .. {:.3} (viridis)", map.max_dolp));
            });
            ui.add_space(8.0);
            ui.vertical(|ui| {
                ui.label("AoP (hue) and DoLP (saturation)");
                if let Some(p) = map_view(ui, map, &tex.aop, side, "AoP sky map") {
                    hovered = Some(p);
                }
                let full = map.max_dolp as f32;
                paint_bar(ui, side, |t| {
                    colour::aop_dolp((t - 0.5) * std::f32::consts::PI, full, full)
                });
                ui.label("hue: AoP -90° .. 0° .. +90°");
                paint_bar(ui, side, |t| colour::hsv(0.0, t, colour::AOP_VALUE));
                ui.label(format!("saturation: DoLP 0 .. {:.3}", map.max_dolp));
            });
        });
        ui.label(egui::RichText::new(AOP_CONVENTION).small());
        if let Some(p) = hovered {
            self.probe = Some(p);
        }
        ui.label(
            egui::RichText::new(
                self.probe
                    .map_or_else(|| "probe: hover over a map".into(), |p| p.text()),
            )
            .monospace(),
        );
    }
}

/// Draws one map with its horizon circle, N/E/S/W labels and the sun marker; returns the probe
/// under the pointer.
fn map_view(
    ui: &mut egui::Ui,
    map: &SkyMap,
    tex: &egui::TextureHandle,
    side: f32,
    alt: &str,
) -> Option<Probe> {
    let (outer, _) = ui.allocate_exact_size(
        egui::vec2(side + 2.0 * RIM_MARGIN, side + 2.0 * RIM_MARGIN),
        egui::Sense::hover(),
    );
    let inner = outer.shrink(RIM_MARGIN);
    let resp = ui.place(
        inner,
        egui::Image::from_texture((tex.id(), inner.size()))
            .fit_to_exact_size(inner.size())
            .alt_text(alt)
            .sense(egui::Sense::hover()),
    );
    let painter = ui.painter();
    let centre = inner.center();
    let radius = side / 2.0;
    let text_colour = ui.visuals().text_color();
    painter.circle_stroke(centre, radius, egui::Stroke::new(1.0, text_colour));
    let font = egui::FontId::proportional(13.0);
    let at = RIM_MARGIN * 0.5 + radius;
    for (label, dx, dy) in [
        ("N", 0.0, -at),
        ("S", 0.0, at),
        ("E", -at, 0.0),
        ("W", at, 0.0),
    ] {
        painter.text(
            centre + egui::vec2(dx, dy),
            egui::Align2::CENTER_CENTER,
            label,
            font.clone(),
            text_colour,
        );
    }
    // The sun: at its place, or on the rim at its azimuth when it has set.
    let scale = side / map.size as f32;
    let (sx, sy) = map.pixel_of(map.sun_zenith_deg.min(90.0), map.sun_azimuth_deg);
    let sun = inner.min + egui::vec2(sx as f32 * scale, sy as f32 * scale);
    if map.sun_below_horizon() {
        painter.circle_stroke(sun, 6.0, egui::Stroke::new(2.0, egui::Color32::GRAY));
    } else {
        painter.circle_stroke(sun, 7.0, egui::Stroke::new(2.5, egui::Color32::BLACK));
        painter.circle_stroke(sun, 7.0, egui::Stroke::new(1.5, egui::Color32::YELLOW));
    }
    let pos = resp.hover_pos()?;
    let x = (pos.x - inner.min.x) / scale;
    let y = (pos.y - inner.min.y) / scale;
    if x < 0.0 || y < 0.0 {
        return None;
    }
    map.probe(x as usize, y as usize)
}
