//! `polarimeter calibrate noise` (EMVA 1288 photon transfer from a directory of frames) and
//! `polarimeter simulate photon-transfer` (a photon-transfer series from a camera file with known
//! truth, to test it).
//!
//! # The frames directory
//!
//! 16-bit single-channel (grayscale) TIFF frames, uncompressed, LZW or Deflate, and a
//! `frames.csv` with a header and one row per frame:
//!
//! ```text
//! file,exposure_us,kind,photons_per_pixel
//! flat_001_a.tif,50000,flat,1234.5
//! flat_001_b.tif,50000,flat,1234.5
//! dark_001_a.tif,50000,dark,
//! dark_001_b.tif,50000,dark,
//! ```
//!
//! `file` is relative to the directory; `kind` is `dark` or `flat`; `exposure_us` finite and in
//! `[0, 1e11]`; `photons_per_pixel` (optional column, empty allowed) the flat field's mean photon
//! count per pixel, for the QE. Flats group by exposure time and photon count, darks by exposure
//! time; each flat group needs at least two frames (a pair; more pairs are averaged, in file
//! order) and at least two darks at its exposure time. Every file is checked before any is
//! analysed, and every problem names the file and its row of `frames.csv`.
//!
//! The analysis is [`polar_model::calibration::photon_transfer`] (EMVA 1288 Release 4.0 Linear)
//! on the pair statistics ([`polar_model::calibration::pair_statistics`]).

use crate::plot::{canvas, legend, FONT};
use plotters::prelude::*;
use polar_model::calibration::{pair_statistics, photon_transfer, ExposurePoint, PhotonTransfer};
use polar_model::montecarlo::{expose_pixels, fixed_pattern, MAX_FRAME_PIXELS};
use polar_model::sensor::Camera;
use polar_model::ModelError;
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// The index file of a frames directory.
pub const FRAMES_CSV: &str = "frames.csv";

/// Fills (fractions of the saturation capacity) of the exposures [`sim_frames`] adds near and
/// past saturation, above `--max-fill`: dense around the variance peak (which lies a few
/// shot-noise sigmas below the clip) and two well past it.
pub const SATURATION_TAIL: [f64; 6] = [0.97, 0.99, 1.01, 1.03, 1.1, 1.3];

/// Longest exposure accepted, microseconds (the sensor model's 1e5 s).
pub const MAX_EXPOSURE_US: f64 = 1e11;

/// Errors of the calibration and the frame simulator; each names its file or option.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// A file that cannot be read or written, or whose content is wrong.
    #[error("{}: {message}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Problems with the frames directory, one per line, each naming its file.
    #[error("{} problem(s) with the frames in {}:\n  {}", problems.len(), dir.display(), problems.join("\n  "))]
    Frames {
        /// The frames directory.
        dir: PathBuf,
        /// One line per problem.
        problems: Vec<String>,
    },
    /// An option out of range.
    #[error("--{flag} = {value} is out of range: allowed {allowed}")]
    Option {
        /// The flag, as typed.
        flag: &'static str,
        /// The value received.
        value: String,
        /// What is allowed.
        allowed: String,
    },
    /// The photon-transfer analysis rejected the frames' statistics.
    #[error("photon transfer of {}: {source}", dir.display())]
    Analysis {
        /// The frames directory.
        dir: PathBuf,
        /// The model's error.
        source: ModelError,
    },
    /// A model call failed (simulation).
    #[error("{0}")]
    Model(#[from] ModelError),
}

fn file_err(path: &Path, message: impl Into<String>) -> CalibrateError {
    CalibrateError::File {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Loads and validates a camera file; errors name the file.
pub fn load_camera(path: &Path) -> Result<Camera, CalibrateError> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e.to_string()))?;
    Camera::from_toml_str(&text).map_err(|e| file_err(path, e.to_string()))
}

// ---------------------------------------------------------------------------------------------
// TIFF I/O
// ---------------------------------------------------------------------------------------------

/// Width and height of a 16-bit single-channel TIFF; otherwise what is wrong, in words.
fn tiff_header(path: &Path) -> Result<(u32, u32), String> {
    polar_engine::tiff_io::gray16_dimensions(path)
}

/// The pixels of a 16-bit single-channel TIFF of the expected size.
pub(crate) fn read_tiff(path: &Path, width: u32, height: u32) -> Result<Vec<u16>, CalibrateError> {
    polar_engine::tiff_io::read_gray16(path, width, height).map_err(|m| file_err(path, m))
}

/// Writes `data` (row-major, `width x height`) as an uncompressed 16-bit grayscale TIFF; errors
/// name the file.
pub fn write_tiff(
    path: &Path,
    width: u32,
    height: u32,
    data: &[u16],
) -> Result<(), CalibrateError> {
    polar_engine::tiff_io::write_gray16(path, width, height, data)
        .map_err(|e| file_err(path, format!("cannot write: {e}")))
}

// ---------------------------------------------------------------------------------------------
// frames.csv
// ---------------------------------------------------------------------------------------------

/// A frame's kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Dark,
    Flat,
}

/// One checked row of frames.csv.
#[derive(Debug, Clone)]
struct FrameRow {
    /// 1-based data row (the header is row 0).
    row: usize,
    file: String,
    path: PathBuf,
    exposure_us: f64,
    kind: Kind,
    photons_per_pixel: Option<f64>,
}

impl FrameRow {
    fn at(&self) -> String {
        format!("{} ({FRAMES_CSV} row {})", self.path.display(), self.row)
    }
}

/// Reads frames.csv: the rows that parse, and one problem per row that does not.
fn read_frames_csv(dir: &Path) -> Result<(Vec<FrameRow>, Vec<String>), CalibrateError> {
    let csv_path = dir.join(FRAMES_CSV);
    if !csv_path.is_file() {
        return Err(file_err(
            &csv_path,
            "not found: a frames directory needs a frames.csv with the columns file, \
             exposure_us, kind (dark or flat) and optionally photons_per_pixel",
        ));
    }
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_path(&csv_path)
        .map_err(|e| file_err(&csv_path, format!("cannot read: {e}")))?;
    let headers = reader
        .headers()
        .map_err(|e| file_err(&csv_path, format!("cannot read the header: {e}")))?
        .clone();
    let column = |name: &str| headers.iter().position(|h| h == name);
    let (Some(c_file), Some(c_exp), Some(c_kind)) =
        (column("file"), column("exposure_us"), column("kind"))
    else {
        return Err(file_err(
            &csv_path,
            format!(
                "header {:?}; allowed the columns file, exposure_us, kind and optionally \
                 photons_per_pixel",
                headers.iter().collect::<Vec<_>>()
            ),
        ));
    };
    let c_photons = column("photons_per_pixel");
    let mut rows = Vec::new();
    let mut problems = Vec::new();
    let mut seen = HashSet::new();
    for (i, record) in reader.records().enumerate() {
        let row = i + 1;
        let at = format!("{} row {row}", csv_path.display());
        let record = match record {
            Ok(r) => r,
            Err(e) => {
                problems.push(format!("{at}: {e}"));
                continue;
            }
        };
        let field = |c: usize| record.get(c).unwrap_or("");
        let file = field(c_file).to_string();
        let at = format!("{at} ({file})");
        if file.is_empty() {
            problems.push(format!("{at}: file is empty; allowed a TIFF file name"));
            continue;
        }
        if !seen.insert(file.clone()) {
            problems.push(format!(
                "{at}: listed twice; allowed each frame once (a pair is two files)"
            ));
        }
        let kind = match field(c_kind).to_ascii_lowercase().as_str() {
            "dark" => Some(Kind::Dark),
            "flat" => Some(Kind::Flat),
            other => {
                problems.push(format!("{at}: kind = {other:?}; allowed dark or flat"));
                None
            }
        };
        let exposure = field(c_exp);
        let exposure_us = match exposure.parse::<f64>() {
            // + 0.0 turns -0 into 0, so both group as one exposure time.
            Ok(t) if t.is_finite() && (0.0..=MAX_EXPOSURE_US).contains(&t) => Some(t + 0.0),
            _ => {
                problems.push(format!(
                    "{at}: exposure_us = {exposure:?}; allowed a number in [0, 1e11]"
                ));
                None
            }
        };
        let photons_text = c_photons.map(field).unwrap_or("");
        let photons_per_pixel = if photons_text.is_empty() {
            Ok(None)
        } else {
            match photons_text.parse::<f64>() {
                Ok(p) if p.is_finite() && p >= 0.0 => Ok(Some(p)),
                _ => Err(format!(
                    "{at}: photons_per_pixel = {photons_text:?}; allowed empty or a finite \
                     number >= 0"
                )),
            }
        };
        let photons_per_pixel = match photons_per_pixel {
            Ok(p) => p,
            Err(m) => {
                problems.push(m);
                None
            }
        };
        if kind == Some(Kind::Dark) && photons_per_pixel.is_some_and(|p| p > 0.0) {
            problems.push(format!(
                "{at}: photons_per_pixel = {photons_text} on a dark frame; allowed empty or 0"
            ));
        }
        if let (Some(kind), Some(exposure_us)) = (kind, exposure_us) {
            rows.push(FrameRow {
                row,
                path: dir.join(&file),
                file,
                exposure_us,
                kind,
                photons_per_pixel: if kind == Kind::Dark {
                    None
                } else {
                    photons_per_pixel
                },
            });
        }
    }
    if rows.is_empty() && problems.is_empty() {
        problems.push(format!("{}: no frames listed", csv_path.display()));
    }
    Ok((rows, problems))
}

/// Key of a flat group: exposure time and photon count (bit patterns: exact equality).
type FlatKey = (u64, Option<u64>);

// ---------------------------------------------------------------------------------------------
// calibrate noise
// ---------------------------------------------------------------------------------------------

/// Inputs of [`calibrate_noise`].
#[derive(Debug, Clone)]
pub struct NoiseOptions {
    /// The frames directory (TIFFs and frames.csv).
    pub frames: PathBuf,
    /// Where to write photon_transfer.png, noise.toml and camera.toml; default `frames`.
    pub out: Option<PathBuf>,
    /// A camera file whose detector fields the measurement replaces (writes camera.toml).
    pub base_camera: Option<PathBuf>,
}

/// The result of [`calibrate_noise`].
#[derive(Debug, Clone)]
pub struct NoiseReport {
    /// The frames directory.
    pub frames: PathBuf,
    /// Frame size, pixels.
    pub width: u32,
    /// Frame size, pixels.
    pub height: u32,
    /// The photon-transfer analysis.
    pub result: PhotonTransfer,
    /// The files written.
    pub files: Vec<PathBuf>,
    /// The camera written to camera.toml (with `--base-camera`).
    pub camera: Option<Camera>,
    /// Warnings about the frames and the analysis.
    pub warnings: Vec<String>,
}

impl NoiseReport {
    /// The report as one JSON object: every field of [`PhotonTransfer`] (estimates as
    /// `{value, uncertainty}`, `dark_current_e_per_s` and `qe` null when not measured), plus the
    /// frames directory, the frame size, the files written and the warnings.
    pub fn to_json(&self) -> Value {
        let mut v = serde_json::to_value(&self.result).unwrap_or(Value::Null);
        if let Value::Object(map) = &mut v {
            map.insert("frames".into(), json!(self.frames.display().to_string()));
            map.insert("width".into(), json!(self.width));
            map.insert("height".into(), json!(self.height));
            map.insert(
                "files".into(),
                json!(self
                    .files
                    .iter()
                    .map(|f| f.display().to_string())
                    .collect::<Vec<_>>()),
            );
            map.insert("warnings".into(), json!(self.warnings));
        }
        v
    }
}

/// Mean pair statistics of `frames` (paired in order; an odd last frame is left out with a
/// warning): `(mean, temporal variance, pixels x pairs)`.
fn group_statistics(
    frames: &[&FrameRow],
    width: u32,
    height: u32,
    warnings: &mut Vec<String>,
) -> Result<(f64, f64, usize), CalibrateError> {
    let pairs = frames.len() / 2;
    if frames.len() % 2 == 1 {
        if let Some(last) = frames.last() {
            warnings.push(format!("{}: unpaired frame, not used", last.at()));
        }
    }
    let (mut mean, mut var, mut pixels) = (0.0, 0.0, 0usize);
    for pair in frames.chunks_exact(2) {
        let a = read_tiff(&pair[0].path, width, height)?;
        let b = read_tiff(&pair[1].path, width, height)?;
        let s = pair_statistics(&a, &b).map_err(|e| file_err(&pair[0].path, e.to_string()))?;
        mean += s.mean_dn / pairs as f64;
        var += s.temporal_var_dn2 / pairs as f64;
        pixels += s.pixels;
    }
    Ok((mean, var, pixels))
}

/// `polarimeter calibrate noise`: checks every frame, computes the pair statistics per exposure,
/// runs the EMVA 1288 photon-transfer analysis and writes photon_transfer.png, noise.toml and
/// (with a base camera) camera.toml into the output directory.
pub fn calibrate_noise(opts: &NoiseOptions) -> Result<NoiseReport, CalibrateError> {
    let dir = &opts.frames;
    let base = opts.base_camera.as_deref().map(load_camera).transpose()?;
    if !dir.is_dir() {
        return Err(file_err(
            dir,
            "not found or not a directory; allowed a directory with frames.csv and 16-bit TIFFs",
        ));
    }
    let (rows, mut problems) = read_frames_csv(dir)?;

    // Every file: present, a 16-bit single-channel TIFF, the size of the first.
    let mut size: Option<((u32, u32), String)> = None;
    for r in &rows {
        if !r.path.is_file() {
            problems.push(format!("{}: not found", r.at()));
            continue;
        }
        match tiff_header(&r.path) {
            Err(m) => problems.push(format!("{}: {m}", r.at())),
            Ok(dims) => match &size {
                None => size = Some((dims, r.file.clone())),
                Some((first, name)) if *first != dims => problems.push(format!(
                    "{}: {}x{} pixels, but {name} is {}x{}; allowed frames of one size",
                    r.at(),
                    dims.0,
                    dims.1,
                    first.0,
                    first.1
                )),
                Some(_) => {}
            },
        }
    }

    // Groups: flats by (exposure, photons), darks by exposure.
    let mut flats: BTreeMap<FlatKey, Vec<&FrameRow>> = BTreeMap::new();
    let mut darks: BTreeMap<u64, Vec<&FrameRow>> = BTreeMap::new();
    for r in &rows {
        match r.kind {
            Kind::Flat => flats
                .entry((
                    r.exposure_us.to_bits(),
                    r.photons_per_pixel.map(f64::to_bits),
                ))
                .or_default()
                .push(r),
            Kind::Dark => darks.entry(r.exposure_us.to_bits()).or_default().push(r),
        }
    }
    let mut warnings = Vec::new();
    for (key, group) in &flats {
        let t = f64::from_bits(key.0);
        let names = group
            .iter()
            .map(|r| format!("{} (row {})", r.file, r.row))
            .collect::<Vec<_>>()
            .join(", ");
        if group.len() < 2 {
            problems.push(format!(
                "{}: {} flat frame(s) at exposure_us = {t}{}: {names}; allowed at least two (a pair)",
                dir.join(FRAMES_CSV).display(),
                group.len(),
                key.1
                    .map(|p| format!(", photons_per_pixel = {}", f64::from_bits(p)))
                    .unwrap_or_default(),
            ));
        }
        let n_dark = darks.get(&key.0).map_or(0, Vec::len);
        if n_dark < 2 {
            problems.push(format!(
                "{}: {n_dark} dark frame(s) at exposure_us = {t}, where the flats {names} are; \
                 allowed at least two darks at each flat exposure",
                dir.join(FRAMES_CSV).display()
            ));
        }
    }
    if flats.is_empty() && !rows.is_empty() {
        problems.push(format!(
            "{}: no flat frames; allowed flat pairs at several exposures",
            dir.join(FRAMES_CSV).display()
        ));
    }
    for (t, group) in &darks {
        if !flats.keys().any(|k| k.0 == *t) {
            warnings.push(format!(
                "darks at exposure_us = {} ({}) have no flats at that exposure: not used",
                f64::from_bits(*t),
                group
                    .iter()
                    .map(|r| r.file.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
    }
    let Some(((width, height), _)) = size else {
        problems.push(format!("{}: no readable frame", dir.display()));
        return Err(CalibrateError::Frames {
            dir: dir.clone(),
            problems,
        });
    };
    if !problems.is_empty() {
        return Err(CalibrateError::Frames {
            dir: dir.clone(),
            problems,
        });
    }

    // Statistics per exposure point.
    let mut dark_stats: BTreeMap<u64, (f64, f64, usize)> = BTreeMap::new();
    let mut points = Vec::new();
    for (key, group) in &flats {
        let dark = match dark_stats.get(&key.0) {
            Some(d) => *d,
            None => {
                let g = darks.get(&key.0).map(Vec::as_slice).unwrap_or(&[]);
                let d = group_statistics(g, width, height, &mut warnings)?;
                dark_stats.insert(key.0, d);
                d
            }
        };
        let flat = group_statistics(group, width, height, &mut warnings)?;
        points.push(ExposurePoint {
            exposure_us: f64::from_bits(key.0),
            photons_per_pixel: key.1.map(f64::from_bits),
            dark_mean_dn: dark.0,
            dark_var_dn2: dark.1,
            flat_mean_dn: flat.0,
            flat_var_dn2: flat.1,
            pixels: dark.2.min(flat.2),
        });
    }
    let result = photon_transfer(&points).map_err(|source| CalibrateError::Analysis {
        dir: dir.clone(),
        source,
    })?;
    warnings.extend(result.warnings.iter().cloned());

    // Outputs.
    let out = opts.out.clone().unwrap_or_else(|| dir.clone());
    std::fs::create_dir_all(&out).map_err(|e| file_err(&out, format!("cannot create: {e}")))?;
    let mut files = Vec::new();
    let png = out.join("photon_transfer.png");
    draw_photon_transfer(&png, &result)?;
    files.push(png);
    let noise = out.join("noise.toml");
    std::fs::write(&noise, noise_toml(dir, &result))
        .map_err(|e| file_err(&noise, format!("cannot write: {e}")))?;
    files.push(noise);
    let camera = match base {
        None => None,
        Some(base) => {
            let path = out.join("camera.toml");
            let camera = measured_camera(&base, &result, &path, &mut warnings)?;
            files.push(path);
            Some(camera)
        }
    };
    Ok(NoiseReport {
        frames: dir.clone(),
        width,
        height,
        result,
        files,
        camera,
        warnings,
    })
}

/// noise.toml: the measured detector fields under the camera file's names, with their standard
/// uncertainties in an `[uncertainty]` table.
fn noise_toml(dir: &Path, r: &PhotonTransfer) -> String {
    let mut fields: Vec<(&str, f64, f64)> = vec![
        (
            "gain_dn_per_e",
            r.k_dn_per_e.value,
            r.k_dn_per_e.uncertainty,
        ),
        (
            "read_noise_e",
            r.read_noise_e.value,
            r.read_noise_e.uncertainty,
        ),
    ];
    if let Some(d) = r.dark_current_e_per_s {
        fields.push(("dark_current_e_per_s", d.value, d.uncertainty));
    }
    fields.push(("offset_dn", r.offset_dn.value, r.offset_dn.uncertainty));
    fields.push((
        "full_well_e",
        r.saturation_capacity_e.value,
        r.saturation_capacity_e.uncertainty,
    ));
    if let Some(q) = r.qe {
        fields.push(("qe", q.value, q.uncertainty));
    }
    let mut text = format!(
        "# Detector parameters measured by EMVA 1288 (Release 4.0 Linear) photon transfer\n\
         # (polarimeter calibrate noise) from {}:\n\
         # {} exposure points, {} in the linear range (mu_y - mu_y.dark up to {:.1} DN, 70 % of\n\
         # saturation). full_well_e is the saturation capacity (mu_e.sat); qe, if present, is\n\
         # at the illumination's wavelength.{}\n",
        dir.display(),
        r.points.len(),
        r.linear_range.points,
        r.linear_range.max_signal_dn,
        if r.read_noise_is_upper_limit {
            "\n# read_noise_e is an UPPER LIMIT (dark variance below 0.24 DN^2)."
        } else {
            ""
        }
    );
    for (name, value, _) in &fields {
        text.push_str(&format!("{name} = {value:?}\n"));
    }
    text.push_str("\n[uncertainty]    # standard uncertainties, same units\n");
    for (name, _, u) in &fields {
        text.push_str(&format!("{name} = {u:?}\n"));
    }
    text
}

/// The base camera with the measured detector fields, validated, written to `path` and parsed
/// back (`calibrate noise --base-camera`, and a calibrate-noise run's write-back to a rig).
pub(crate) fn measured_camera(
    base: &Camera,
    r: &PhotonTransfer,
    path: &Path,
    warnings: &mut Vec<String>,
) -> Result<Camera, CalibrateError> {
    let mut cam = base.clone();
    cam.gain_dn_per_e = r.k_dn_per_e.value;
    cam.read_noise_e = r.read_noise_e.value;
    if let Some(d) = r.dark_current_e_per_s {
        if d.value < 0.0 {
            warnings.push(format!(
                "camera.toml: measured dark current {:.4} e-/s is negative; written as 0",
                d.value
            ));
        }
        cam.dark_current_e_per_s = d.value.max(0.0);
    }
    cam.offset_dn = r.offset_dn.value;
    cam.full_well_e = r.saturation_capacity_e.value;
    cam.validate().map_err(|e| {
        file_err(
            path,
            format!("the measured camera is not a valid camera file: {e}"),
        )
    })?;
    let body = cam
        .to_toml_string()
        .map_err(|e| file_err(path, e.to_string()))?;
    let text = format!(
        "# Base camera: {}\n\
         # Detector fields gain_dn_per_e, read_noise_e, dark_current_e_per_s, offset_dn and\n\
         # full_well_e measured by EMVA 1288 photon transfer (polarimeter calibrate noise); the\n\
         # rest, the QE curve included, as in the base camera.\n{body}",
        base.name.replace(['\n', '\r'], " ")
    );
    std::fs::write(path, &text).map_err(|e| file_err(path, format!("cannot write: {e}")))?;
    Camera::from_toml_str(&text).map_err(|e| file_err(path, format!("does not parse back: {e}")))
}

// ---------------------------------------------------------------------------------------------
// The figure
// ---------------------------------------------------------------------------------------------

/// photon_transfer.png: `sigma_y^2 - sigma_y.dark^2` against `mu_y - mu_y.dark` for every
/// exposure point, the fitted line of slope `K`, the linear range shaded and the saturation
/// point marked.
fn draw_photon_transfer(path: &Path, r: &PhotonTransfer) -> Result<(), CalibrateError> {
    let e = |err: &dyn std::fmt::Display| file_err(path, format!("cannot draw: {err}"));
    let x_max = r.points.iter().map(|p| p.signal_dn).fold(1.0f64, f64::max) * 1.05;
    let y_hi = r
        .points
        .iter()
        .map(|p| p.signal_var_dn2)
        .fold(1e-3f64, f64::max)
        * 1.1;
    let y_lo = r
        .points
        .iter()
        .map(|p| p.signal_var_dn2)
        .fold(0.0f64, f64::min)
        * 1.1;
    let x_lo = r.points.iter().map(|p| p.signal_dn).fold(0.0f64, f64::min);
    let k = r.k_dn_per_e;
    let root = canvas(path, (1000, 700)).map_err(|x| e(&x))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!(
                "Photon transfer (EMVA 1288): K = {:.4} +/- {:.4} DN/e-, read noise {:.2} e-",
                k.value, k.uncertainty, r.read_noise_e.value
            ),
            (FONT, 22),
        )
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(x_lo..x_max, y_lo..y_hi)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("mean signal mu_y - mu_y.dark (DN)")
        .y_desc("temporal variance sigma_y^2 - sigma_y.dark^2 (DN^2)")
        .label_style((FONT, 15))
        .draw()
        .map_err(|x| e(&x))?;
    let green = RGBColor(44, 160, 44);
    chart
        .draw_series(std::iter::once(Rectangle::new(
            [(0.0, y_lo), (r.linear_range.max_signal_dn, y_hi)],
            green.mix(0.12).filled(),
        )))
        .map_err(|x| e(&x))?
        .label("linear range (up to 70 % of saturation)")
        .legend(move |(x, y)| {
            Rectangle::new([(x, y - 5), (x + 20, y + 5)], green.mix(0.3).filled())
        });
    let blue = RGBColor(31, 119, 180);
    chart
        .draw_series(LineSeries::new(
            [(0.0, 0.0), (x_max, k.value * x_max)],
            blue.stroke_width(2),
        ))
        .map_err(|x| e(&x))?
        .label(format!("fit: slope K = {:.4} DN/e-", k.value))
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(2)));
    chart
        .draw_series(
            r.points
                .iter()
                .filter(|p| p.in_linear_range)
                .map(|p| Circle::new((p.signal_dn, p.signal_var_dn2), 5, green.filled())),
        )
        .map_err(|x| e(&x))?
        .label("fitted points")
        .legend(move |(x, y)| Circle::new((x + 10, y), 5, green.filled()));
    let red = RGBColor(214, 39, 40);
    chart
        .draw_series(
            r.points
                .iter()
                .filter(|p| !p.in_linear_range)
                .map(|p| Circle::new((p.signal_dn, p.signal_var_dn2), 5, red.stroke_width(2))),
        )
        .map_err(|x| e(&x))?
        .label("other points")
        .legend(move |(x, y)| Circle::new((x + 10, y), 5, red.stroke_width(2)));
    if let Some(s) = r.points.iter().find(|p| p.saturation) {
        chart
            .draw_series([Cross::new(
                (s.signal_dn, s.signal_var_dn2),
                10,
                BLACK.stroke_width(2),
            )])
            .map_err(|x| e(&x))?;
        chart
            .draw_series(std::iter::once(Text::new(
                format!(
                    "saturation: {:.0} e- ({:.0} DN)",
                    r.saturation_capacity_e.value, s.signal_dn
                ),
                (s.signal_dn * 0.62, s.signal_var_dn2 * 1.04),
                (FONT, 15),
            )))
            .map_err(|x| e(&x))?;
    }
    legend(&mut chart, SeriesLabelPosition::UpperLeft, 15).map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// sim frames
// ---------------------------------------------------------------------------------------------

/// Inputs of [`sim_frames`].
#[derive(Debug, Clone)]
pub struct SimFramesOptions {
    /// The camera file (truth).
    pub camera: PathBuf,
    /// Output directory (created).
    pub out: PathBuf,
    /// Frame width, pixels, 2..=16384.
    pub width: u32,
    /// Frame height, pixels, 2..=16384.
    pub height: u32,
    /// Exposure points of the linear series, 5..=1000 (plus [`SATURATION_TAIL`]).
    pub exposures: usize,
    /// Mean photo-electrons of the brightest point of the linear series as a fraction of the
    /// saturation capacity, [0.1, 1.25].
    pub max_fill: f64,
    /// Exposure time of that point, microseconds, (0, 1e10]; the series is linear in time, so
    /// the dark current spans `[0, max_exposure_us * 1.3 / max_fill]`.
    pub max_exposure_us: f64,
    /// Wavelength of the illumination, nm: the QE is the camera's there (must be > 0).
    pub wavelength_nm: f64,
    /// PRNU: rms relative gain pattern, [0, 0.1].
    pub prnu: f64,
    /// DSNU: rms offset pattern, DN (rounded to whole DN per pixel), [0, 100].
    pub dsnu_dn: f64,
    /// Write the photons_per_pixel column's values (else leave it empty: no QE).
    pub photons: bool,
    /// Seed of every random draw.
    pub seed: u64,
}

impl SimFramesOptions {
    /// The defaults: 512 x 512, 20 exposures to 95 % of saturation at 1 s, 550 nm, no PRNU or
    /// DSNU, photon counts written, seed 1.
    pub fn new(camera: PathBuf, out: PathBuf) -> SimFramesOptions {
        SimFramesOptions {
            camera,
            out,
            width: 512,
            height: 512,
            exposures: 20,
            max_fill: 0.95,
            max_exposure_us: 1e6,
            wavelength_nm: 550.0,
            prnu: 0.0,
            dsnu_dn: 0.0,
            photons: true,
            seed: 1,
        }
    }

    fn check(&self) -> Result<(), CalibrateError> {
        let bad = |flag: &'static str, value: String, allowed: &str| CalibrateError::Option {
            flag,
            value,
            allowed: allowed.to_string(),
        };
        for (flag, v) in [("width", self.width), ("height", self.height)] {
            if !(2..=16384).contains(&v) {
                return Err(bad(flag, v.to_string(), "2..=16384 pixels"));
            }
        }
        if self.width as usize * self.height as usize > MAX_FRAME_PIXELS {
            return Err(bad(
                "width",
                self.width.to_string(),
                "width x height <= 2^28 pixels",
            ));
        }
        if !(5..=1000).contains(&self.exposures) {
            return Err(bad("exposures", self.exposures.to_string(), "5..=1000"));
        }
        let ranges: [(&'static str, f64, f64, f64, &str); 5] = [
            ("max-fill", self.max_fill, 0.1, 1.25, "[0.1, 1.25]"),
            (
                "max-exposure-us",
                self.max_exposure_us,
                f64::MIN_POSITIVE,
                1e10,
                "(0, 1e10]",
            ),
            (
                "wavelength-nm",
                self.wavelength_nm,
                200.0,
                2500.0,
                "[200, 2500]",
            ),
            ("prnu", self.prnu, 0.0, 0.1, "[0, 0.1]"),
            ("dsnu-dn", self.dsnu_dn, 0.0, 100.0, "[0, 100]"),
        ];
        for (flag, v, lo, hi, allowed) in ranges {
            if !(v.is_finite() && v >= lo && v <= hi) {
                return Err(bad(flag, v.to_string(), allowed));
            }
        }
        let longest_us = self.max_exposure_us * SATURATION_TAIL[5] / self.max_fill;
        if longest_us > MAX_EXPOSURE_US {
            return Err(bad(
                "max-exposure-us",
                self.max_exposure_us.to_string(),
                "at most 1e11 * max_fill / 1.3 (the longest exposure, past saturation, must \
                 stay within 1e5 s)",
            ));
        }
        Ok(())
    }
}

/// What [`sim_frames`] wrote, and the truth it simulated.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SimSummary {
    /// The output directory.
    pub out: PathBuf,
    /// Frames written (TIFFs).
    pub frames: usize,
    /// Exposure points (each: two flats, two darks).
    pub exposure_points: usize,
    /// Exposure times, microseconds.
    pub exposure_us: Vec<f64>,
    /// The camera's QE at the wavelength.
    pub qe: f64,
    /// Photons per pixel per second of the uniform illumination.
    pub photons_per_pixel_per_s: f64,
    /// Saturation capacity of the camera, electrons: `min(full_well, (2^bits - 1 - b) / K)`.
    pub saturation_capacity_e: f64,
    /// The camera's K, DN/e-.
    pub gain_dn_per_e: f64,
    /// The camera's read noise, e-.
    pub read_noise_e: f64,
    /// The camera's dark current, e-/s.
    pub dark_current_e_per_s: f64,
    /// The camera's offset, DN.
    pub offset_dn: f64,
}

/// The SplitMix64 finaliser: a well-mixed 64-bit hash, so frame seeds start unrelated streams.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One frame to simulate.
struct FrameJob {
    file: String,
    t_s: f64,
    flat: bool,
    seed: u64,
}

/// `polarimeter simulate photon-transfer`: a photon-transfer series of `camera` under uniform
/// illumination: at each exposure time two flats and two darks, 16-bit TIFFs (`flat_NNN_a.tif`,
/// ...), and frames.csv with the photon counts. The linear series has `exposures` points evenly
/// spaced in time up to `max_exposure_us`, where the mean photo-electrons reach `max_fill` of the
/// saturation capacity; [`SATURATION_TAIL`] adds points near and past saturation. Frames are
/// [`expose_pixels`] draws (Poisson photo- and dark electrons, full well, read noise, gain, offset,
/// rounding, ADC range) with an optional fixed PRNU pattern (on the photo-electrons) and DSNU
/// pattern (whole DN, added after rounding), both of exactly zero mean, so the truth is the camera
/// file's. Deterministic for a seed (frames are drawn in parallel with per-frame seeds).
pub fn sim_frames(opts: &SimFramesOptions) -> Result<SimSummary, CalibrateError> {
    opts.check()?;
    let cam = load_camera(&opts.camera)?;
    let eta = cam.qe_at(opts.wavelength_nm);
    if eta <= 0.0 {
        return Err(CalibrateError::Option {
            flag: "wavelength-nm",
            value: opts.wavelength_nm.to_string(),
            allowed: format!(
                "a wavelength where the camera's QE is > 0 ({} has QE 0 there)",
                opts.camera.display()
            ),
        });
    }
    let k = cam.gain_dn_per_e;
    let sat_e = cam.full_well_e.min((cam.adc_max_dn() - cam.offset_dn) / k);
    let t_top_s = opts.max_exposure_us * 1e-6;
    let flux = opts.max_fill * sat_e / (eta * t_top_s);
    let mut times_s: Vec<f64> = (1..=opts.exposures)
        .map(|i| t_top_s * i as f64 / opts.exposures as f64)
        .collect();
    times_s.extend(
        SATURATION_TAIL
            .iter()
            .filter(|&&f| f > opts.max_fill)
            .map(|f| t_top_s * f / opts.max_fill),
    );
    std::fs::create_dir_all(&opts.out)
        .map_err(|e| file_err(&opts.out, format!("cannot create: {e}")))?;
    let n = opts.width as usize * opts.height as usize;
    let prnu = fixed_pattern(n, opts.prnu, mix64(opts.seed ^ 0x7072_6e75))?;
    let dsnu: Vec<i32> = fixed_pattern(n, opts.dsnu_dn, mix64(opts.seed ^ 0x6473_6e75))?
        .iter()
        // Rounding is odd-symmetric, so the whole-DN pattern keeps its exact zero mean.
        .map(|d| d.round() as i32)
        .collect();

    let mut jobs = Vec::new();
    let mut csv = String::from("file,exposure_us,kind,photons_per_pixel\n");
    for (j, &t) in times_s.iter().enumerate() {
        let exposure_us = t * 1e6;
        let photons = flux * t;
        for (kind, flat) in [("flat", true), ("dark", false)] {
            for side in ["a", "b"] {
                let file = format!("{kind}_{:03}_{side}.tif", j + 1);
                let photons_text = if flat && opts.photons {
                    photons.to_string()
                } else {
                    String::new()
                };
                csv.push_str(&format!("{file},{exposure_us},{kind},{photons_text}\n"));
                jobs.push(FrameJob {
                    seed: mix64(opts.seed ^ mix64(jobs.len() as u64 + 1)),
                    file,
                    t_s: t,
                    flat,
                });
            }
        }
    }

    let next = AtomicUsize::new(0);
    let failure: Mutex<Option<CalibrateError>> = Mutex::new(None);
    let workers = std::thread::available_parallelism()
        .map_or(1, |p| p.get())
        .clamp(1, 8)
        .min(jobs.len());
    let draw = |job: &FrameJob| -> Result<(), CalibrateError> {
        let mean_e = eta * flux * job.t_s;
        let means: Vec<f64> = if job.flat {
            prnu.iter().map(|p| (mean_e * (1.0 + p)).max(0.0)).collect()
        } else {
            vec![0.0; n]
        };
        let mut frame = expose_pixels(&cam, &means, job.t_s, job.seed)?;
        if opts.dsnu_dn > 0.0 {
            let top = i32::from(u16::try_from(cam.adc_max_dn() as u32).unwrap_or(u16::MAX));
            for (y, d) in frame.iter_mut().zip(&dsnu) {
                // Clamped to the ADC range, which fits u16.
                *y = (i32::from(*y) + d).clamp(0, top) as u16;
            }
        }
        write_tiff(&opts.out.join(&job.file), opts.width, opts.height, &frame)
    };
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(job) = jobs.get(i) else { break };
                if let Err(e) = draw(job) {
                    if let Ok(mut f) = failure.lock() {
                        f.get_or_insert(e);
                    }
                    // Stop the other workers early.
                    next.store(jobs.len(), Ordering::Relaxed);
                    break;
                }
            });
        }
    });
    if let Some(e) = failure.into_inner().ok().flatten() {
        return Err(e);
    }
    let csv_path = opts.out.join(FRAMES_CSV);
    std::fs::write(&csv_path, csv)
        .map_err(|e| file_err(&csv_path, format!("cannot write: {e}")))?;
    Ok(SimSummary {
        out: opts.out.clone(),
        frames: jobs.len(),
        exposure_points: times_s.len(),
        exposure_us: times_s.iter().map(|t| t * 1e6).collect(),
        qe: eta,
        photons_per_pixel_per_s: flux,
        saturation_capacity_e: sat_e,
        gain_dn_per_e: k,
        read_noise_e: cam.read_noise_e,
        dark_current_e_per_s: cam.dark_current_e_per_s,
        offset_dn: cam.offset_dn,
    })
}

impl SimSummary {
    /// The summary as JSON.
    pub fn to_json(&self) -> Value {
        serde_json::to_value(self).unwrap_or(Value::Null)
    }
}
