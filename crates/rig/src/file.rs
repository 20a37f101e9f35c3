//! The rig file (TOML): a lab names its stage, camera, site and analyzer once, and `run`,
//! `resume`, `plan check`, `devices`, `stage`, `camera` and the GUI take `--rig FILE`.
//!
//! ```toml
//! [stage]
//! dialect = "elliptec"                           # a name in polar_drivers::registry::DIALECTS
//! port = "/dev/serial/by-id/usb-FTDI_FT230X_Basic_UART_DK0AHAJZ-if00-port0"   # or "sim"
//! address = 0                                    # bus address (Elliptec 0..=15, SMC100 1..=31)
//! model = "ell14"                                # optional, one of the dialect's models
//!
//! [camera]
//! backend = "genicam"                            # sim | genicam | v4l
//! id = "Basler-acA1300-22gm-22334455"            # the backend's ID (not for sim)
//! file = "cameras/lab.toml"                      # the camera file, relative to this file
//!
//! [site]                                         # as a plan's [site]
//! latitude_deg = 43.08
//! longitude_deg = -77.67
//! elevation_m = 160
//!
//! [analyzer]                                     # inline values ...
//! zero_offset_deg = 0.0
//! extinction_ratio = 1000.0
//! # ... or file = "analyzer.r1.toml" (what a calibrate-analyzer run writes)
//! ```
//!
//! Unknown keys are refused, and every error names the file, the key and the allowed values.
//! Calibrations write back as new revisions: a calibrate-analyzer run writes `analyzer.rN.toml`
//! beside the rig file, a noise calibration `STEM.rN.toml` beside the camera file (N one past
//! the highest revision there; an existing file is never overwritten), and the rig file is
//! rewritten (to a temporary file, then renamed over it) to point at the new revision, keeping
//! its comments.

use crate::hardware::{Hardware, SIM_PORT};
use crate::RigError;
use polar_drivers::registry;
use polar_engine::plan::Site;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// `[stage]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct StageEntry {
    /// The dialect's registry name.
    pub dialect: String,
    /// The serial port (a stable path), or `sim`.
    pub port: String,
    /// Bus address (Elliptec 0..=15, SMC100 1..=31); default the dialect's first (0 where
    /// there is no bus).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<u8>,
    /// The model, lower case.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// `[camera]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraEntry {
    /// `sim` or a camera backend's registry name.
    pub backend: String,
    /// The backend's camera ID (required except for `sim`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// The camera file (noise model), relative to the rig file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
}

/// `[analyzer]`: inline values, or a calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AnalyzerEntry {
    /// Stage angle at which the analyzer's axis is along the camera's x axis, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zero_offset_deg: Option<f64>,
    /// The measured extinction ratio (`I_max / I_min`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extinction_ratio: Option<f64>,
    /// A calibration file (`analyzer.rN.toml`), relative to the rig file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
}

/// An analyzer calibration file (`analyzer.rN.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AnalyzerFile {
    /// Its revision (N of `analyzer.rN.toml`).
    pub revision: u32,
    /// Zero offset, degrees.
    pub zero_offset_deg: f64,
    /// Extinction ratio of the reference and the analyzer together.
    pub extinction_ratio: f64,
    /// The calibrate-analyzer run that measured it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run_dir: Option<String>,
}

/// A rig file, as written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RigFile {
    /// The stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage: Option<StageEntry>,
    /// The camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraEntry>,
    /// The site.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub site: Option<Site>,
    /// The analyzer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub analyzer: Option<AnalyzerEntry>,
}

/// The analyzer values a rig gives, and where they came from.
#[derive(Debug, Clone, PartialEq)]
pub struct AnalyzerValues {
    /// Zero offset, degrees.
    pub zero_offset_deg: f64,
    /// Extinction ratio, if given.
    pub extinction_ratio: Option<f64>,
    /// The calibration file, if any (resolved).
    pub file: Option<PathBuf>,
    /// Its revision.
    pub revision: Option<u32>,
}

/// A rig file read and checked, its paths resolved against its folder.
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    /// The file.
    pub path: PathBuf,
    /// What it says.
    pub file: RigFile,
    /// The camera file, resolved.
    pub camera_file: Option<PathBuf>,
    /// The analyzer's values.
    pub analyzer: Option<AnalyzerValues>,
    /// The file's content hash as it was read (XXH3-64 of its bytes, 16 hex digits): the store
    /// records it, and `acquire resume` says so when the file changed since.
    pub content_xxh3: String,
}

/// The content hash a rig records of its file's text (XXH3-64, 16 hex digits).
pub fn content_hash(text: &str) -> String {
    format!("{:016x}", xxhash_rust::xxh3::xxh3_64(text.as_bytes()))
}

/// Flags that override a rig file's entries (`None`: the rig's, then the default).
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    /// `--port`.
    pub port: Option<String>,
    /// `--dialect`.
    pub dialect: Option<String>,
    /// `--address`.
    pub address: Option<u8>,
    /// `--camera`.
    pub camera: Option<String>,
    /// `--camera-file`.
    pub camera_file: Option<PathBuf>,
    /// `--zero-offset-deg`.
    pub zero_offset_deg: Option<f64>,
}

impl Overrides {
    /// The flags given, as the store records them (`acquire resume` gives them again).
    pub fn to_json(&self) -> Value {
        json!({
            "port": self.port,
            "dialect": self.dialect,
            "address": self.address,
            "camera": self.camera,
            "camera_file": self.camera_file.as_ref().map(|f| f.display().to_string()),
            "zero_offset_deg": self.zero_offset_deg,
        })
    }

    /// The flags a store recorded ([`Overrides::to_json`]); absent keys are not given.
    pub fn from_json(v: &Value) -> Overrides {
        let text = |k: &str| v[k].as_str().map(String::from);
        Overrides {
            port: text("port"),
            dialect: text("dialect"),
            address: v["address"].as_u64().and_then(|a| u8::try_from(a).ok()),
            camera: text("camera"),
            camera_file: text("camera_file").map(PathBuf::from),
            zero_offset_deg: v["zero_offset_deg"].as_f64(),
        }
    }
}

fn bad(path: &Path, key: &str, value: impl std::fmt::Debug, allowed: &str) -> RigError {
    RigError(format!(
        "rig {}: {key} = {value:?} is invalid: allowed {allowed}",
        path.display()
    ))
}

fn revision_of(path: &Path) -> Option<u32> {
    let stem = path.file_stem()?.to_str()?;
    let (_, r) = stem.rsplit_once(".r")?;
    r.parse().ok()
}

impl Rig {
    /// Reads and checks a rig file.
    pub fn load(path: &Path) -> Result<Rig, RigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| RigError(format!("rig {}: cannot read: {e}", path.display())))?;
        Rig::from_str(path, &text)
    }

    /// Parses and checks rig file text (`path` names it and anchors its relative paths).
    pub fn from_str(path: &Path, text: &str) -> Result<Rig, RigError> {
        let file: RigFile = toml::from_str(text).map_err(|e| {
            RigError(format!(
                "rig {}: {}",
                path.display(),
                e.to_string().trim_end().replace('\n', " ")
            ))
        })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        if let Some(s) = &file.stage {
            let d = registry::find(&s.dialect)
                .ok_or_else(|| bad(path, "stage.dialect", &s.dialect, &registry::names()))?;
            if let Some(m) = &s.model {
                if !d.models.contains(&m.as_str()) {
                    return Err(bad(path, "stage.model", m, &d.model_list()));
                }
            }
            if let Err(e) = d.check_address(s.address.unwrap_or(d.default_address())) {
                return Err(RigError(format!("rig {}: stage.{e}", path.display())));
            }
            if s.port.is_empty() {
                return Err(bad(
                    path,
                    "stage.port",
                    &s.port,
                    "a serial port path or \"sim\"",
                ));
            }
        }
        if let Some(c) = &file.camera {
            let backends: Vec<&str> = std::iter::once("sim")
                .chain(crate::camera::CAMERA_BACKENDS.iter().map(|b| b.name))
                .collect();
            if !backends.contains(&c.backend.as_str()) {
                return Err(bad(
                    path,
                    "camera.backend",
                    &c.backend,
                    &backends.join(", "),
                ));
            }
            match (&c.id, c.backend.as_str()) {
                (Some(id), "sim") => {
                    return Err(bad(path, "camera.id", id, "none for the sim backend"))
                }
                (None, b) if b != "sim" => {
                    return Err(RigError(format!(
                        "rig {}: camera.id is missing: the {b} backend needs the camera's ID \
                         (see `polarimeter devices list`)",
                        path.display()
                    )))
                }
                _ => {}
            }
        }
        if let Some(s) = &file.site {
            for (key, v, lo, hi) in [
                ("site.latitude_deg", s.latitude_deg, -90.0, 90.0),
                ("site.longitude_deg", s.longitude_deg, -180.0, 180.0),
                ("site.elevation_m", s.elevation_m, -500.0, 9000.0),
            ] {
                if !(v.is_finite() && (lo..=hi).contains(&v)) {
                    return Err(bad(path, key, v, &format!("[{lo}, {hi}]")));
                }
            }
        }
        let analyzer = match &file.analyzer {
            None => None,
            Some(a) => Some(analyzer_values(path, dir, a)?),
        };
        let camera_file = file
            .camera
            .as_ref()
            .and_then(|c| c.file.as_ref())
            .map(|f| dir.join(f));
        Ok(Rig {
            path: path.to_path_buf(),
            file,
            camera_file,
            analyzer,
            content_xxh3: content_hash(text),
        })
    }

    /// The camera name (`sim` or `BACKEND:ID`).
    pub fn camera_name(&self) -> Option<String> {
        self.file.camera.as_ref().map(|c| match &c.id {
            Some(id) => format!("{}:{id}", c.backend),
            None => c.backend.clone(),
        })
    }

    /// The hardware the rig and the flags describe (a flag overrides the rig's entry);
    /// `None` when neither names any device. Errors name the missing key or flag.
    pub fn hardware(&self, o: &Overrides) -> Result<Option<Hardware>, RigError> {
        let stage = self.file.stage.as_ref();
        let port = o.port.clone().or_else(|| stage.map(|s| s.port.clone()));
        let dialect = o
            .dialect
            .clone()
            .or_else(|| stage.map(|s| s.dialect.clone()));
        let camera = o.camera.clone().or_else(|| self.camera_name());
        let camera_file = o.camera_file.clone().or_else(|| self.camera_file.clone());
        if port.is_none() && dialect.is_none() && camera.is_none() && camera_file.is_none() {
            return Ok(None);
        }
        let missing = |key: &str, flag: &str| {
            RigError(format!(
                "rig {}: {key} is missing (or give {flag})",
                self.path.display()
            ))
        };
        let port = port.ok_or_else(|| missing("stage.port", "--port"))?;
        let dialect = dialect.ok_or_else(|| missing("stage.dialect", "--dialect"))?;
        let camera = camera.ok_or_else(|| missing("camera.backend", "--camera"))?;
        let camera_file = camera_file.ok_or_else(|| missing("camera.file", "--camera-file"))?;
        let address = o.address.or(stage.and_then(|s| s.address));
        let zero = o
            .zero_offset_deg
            .or(self.analyzer.as_ref().map(|a| a.zero_offset_deg))
            .unwrap_or(0.0);
        let mut hw = Hardware::from_flags(
            Some(port),
            Some(&dialect),
            Some(camera),
            Some(camera_file),
            address,
            zero,
        )
        .map_err(RigError)?
        .ok_or_else(|| RigError("no hardware".into()))?;
        hw.model = stage.and_then(|s| s.model.clone());
        hw.extinction_ratio = self.analyzer.as_ref().and_then(|a| a.extinction_ratio);
        hw.provenance = self.provenance(o);
        Ok(Some(hw))
    }

    /// What the store records of the rig: the file, the analyzer's values and their revision,
    /// the camera file and its revision, and which flags overrode the rig.
    pub fn provenance(&self, o: &Overrides) -> Value {
        let analyzer = self.analyzer.as_ref().map(|a| {
            json!({
                "zero_offset_deg": a.zero_offset_deg,
                "extinction_ratio": a.extinction_ratio,
                "file": a.file.as_ref().map(|f| f.display().to_string()),
                "revision": a.revision,
            })
        });
        let overridden: Vec<&str> = [
            ("--port", o.port.is_some()),
            ("--dialect", o.dialect.is_some()),
            ("--address", o.address.is_some()),
            ("--camera", o.camera.is_some()),
            ("--camera-file", o.camera_file.is_some()),
            ("--zero-offset-deg", o.zero_offset_deg.is_some()),
        ]
        .into_iter()
        .filter_map(|(f, given)| given.then_some(f))
        .collect();
        let file = std::path::absolute(&self.path).unwrap_or_else(|_| self.path.clone());
        json!({
            "file": self.path.display().to_string(),
            "absolute_file": file.display().to_string(),
            "content_xxh3": self.content_xxh3,
            "overrides": o.to_json(),
            "analyzer": analyzer,
            "camera_file": self.camera_file.as_ref().map(|f| f.display().to_string()),
            "camera_file_revision": self.camera_file.as_deref().and_then(revision_of),
            "overridden_by_flags": overridden,
        })
    }

    /// Records an analyzer calibration: writes `analyzer.rN.toml` beside the rig file (N one
    /// past the current revision and any file there) and points the rig's `[analyzer]` at it.
    /// Returns the new file.
    pub fn record_analyzer(
        &self,
        zero_offset_deg: f64,
        extinction_ratio: f64,
        run_dir: Option<&Path>,
    ) -> Result<PathBuf, RigError> {
        let dir = self.dir();
        let current = self.analyzer.as_ref().and_then(|a| a.revision).unwrap_or(0);
        let (path, _) = new_revision(&dir, "analyzer", "toml", current, |revision| {
            let f = AnalyzerFile {
                revision,
                zero_offset_deg,
                extinction_ratio,
                run_dir: run_dir.map(|d| d.display().to_string()),
            };
            let body = toml::to_string(&f).map_err(|e| RigError(e.to_string()))?;
            Ok(format!(
                "# The analyzer's zero offset and extinction ratio (of the reference and the \
                 analyzer together),\n# measured by a calibrate-analyzer run.\n{body}"
            ))
        })?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        self.rewrite(|doc| {
            let mut t = toml_edit::Table::new();
            t.insert("file", toml_edit::value(name.clone().unwrap_or_default()));
            doc.insert("analyzer", toml_edit::Item::Table(t));
        })?;
        Ok(path)
    }

    /// Records a calibrated camera file: copies `measured` to `STEM.rN.toml` beside the rig's
    /// camera file (or `camera.rN.toml` beside the rig file if it names none) and points the
    /// rig's `[camera] file` at it. Returns the new file.
    pub fn record_camera_file(&self, measured: &Path) -> Result<PathBuf, RigError> {
        if self.file.camera.is_none() {
            return Err(RigError(format!(
                "rig {}: [camera] is missing: name the camera (backend, id) before recording \
                 its camera file",
                self.path.display()
            )));
        }
        let text = std::fs::read_to_string(measured)
            .map_err(|e| RigError(format!("{}: cannot read: {e}", measured.display())))?;
        let (dir, stem, current) = match &self.camera_file {
            Some(f) => {
                let stem = f
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "camera".into());
                let base = match stem.rsplit_once(".r") {
                    Some((b, r)) if r.parse::<u32>().is_ok() => b.to_string(),
                    _ => stem,
                };
                let dir = f
                    .parent()
                    .map(Path::to_path_buf)
                    .unwrap_or_else(|| self.dir());
                (dir, base, revision_of(f).unwrap_or(0))
            }
            None => (self.dir(), "camera".to_string(), 0),
        };
        let (path, _) = new_revision(&dir, &stem, "toml", current, |_| Ok(text.clone()))?;
        let relative = relative_to(&path, &self.dir());
        self.rewrite(|doc| {
            if let Some(t) = doc.get_mut("camera").and_then(|c| c.as_table_like_mut()) {
                t.insert("file", toml_edit::value(relative.clone()));
            }
        })?;
        Ok(path)
    }

    fn dir(&self) -> PathBuf {
        match self.path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        }
    }

    /// Edits the rig file in place, keeping its comments: written to a temporary file in the
    /// same folder, then renamed over it.
    fn rewrite(&self, edit: impl FnOnce(&mut toml_edit::DocumentMut)) -> Result<(), RigError> {
        let text = std::fs::read_to_string(&self.path)
            .map_err(|e| RigError(format!("rig {}: cannot read: {e}", self.path.display())))?;
        let mut doc: toml_edit::DocumentMut = text
            .parse()
            .map_err(|e| RigError(format!("rig {}: {e}", self.path.display())))?;
        edit(&mut doc);
        write_atomically(&self.path, &doc.to_string())
    }
}

/// Writes `text` to a new file `path`; an existing file is refused, never overwritten.
pub fn write_new(path: &Path, text: &str) -> Result<(), RigError> {
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(|e| {
            RigError(if e.kind() == std::io::ErrorKind::AlreadyExists {
                format!(
                    "{} exists: allowed a new file (it is never overwritten)",
                    path.display()
                )
            } else {
                format!("{}: cannot create: {e}", path.display())
            })
        })?;
    f.write_all(text.as_bytes())
        .and_then(|()| f.sync_all())
        .map_err(|e| RigError(format!("{}: cannot write: {e}", path.display())))
}

/// Writes `text` to `path` through a temporary file in the same folder and a rename.
pub fn write_atomically(path: &Path, text: &str) -> Result<(), RigError> {
    use std::io::Write;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "rig.toml".into());
    let tmp = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    let io = |e: std::io::Error| RigError(format!("{}: cannot write: {e}", path.display()));
    let mut f = std::fs::File::create(&tmp).map_err(io)?;
    f.write_all(text.as_bytes()).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io)
}

/// Creates `dir/STEM.rN.EXT` for the first N past `current` whose file does not exist yet
/// (never overwriting), with the text `body(N)`.
fn new_revision(
    dir: &Path,
    stem: &str,
    ext: &str,
    current: u32,
    body: impl Fn(u32) -> Result<String, RigError>,
) -> Result<(PathBuf, u32), RigError> {
    use std::io::Write;
    for revision in current.saturating_add(1)..current.saturating_add(1000) {
        let path = dir.join(format!("{stem}.r{revision}.{ext}"));
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
        {
            Ok(mut f) => {
                let io =
                    |e: std::io::Error| RigError(format!("{}: cannot write: {e}", path.display()));
                f.write_all(body(revision)?.as_bytes()).map_err(io)?;
                f.sync_all().map_err(io)?;
                return Ok((path, revision));
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(RigError(format!("{}: cannot create: {e}", path.display()))),
        }
    }
    Err(RigError(format!(
        "{}: no free revision of {stem}.rN.{ext} after r{current}",
        dir.display()
    )))
}

/// `path` relative to `dir` when it is inside it, else as it is.
fn relative_to(path: &Path, dir: &Path) -> String {
    path.strip_prefix(dir).unwrap_or(path).display().to_string()
}

fn analyzer_values(path: &Path, dir: &Path, a: &AnalyzerEntry) -> Result<AnalyzerValues, RigError> {
    let check_zero = |key: &str, v: f64| {
        if v.is_finite() && v.abs() <= 360.0 {
            Ok(v)
        } else {
            Err(bad(path, key, v, "a finite angle in [-360, 360] degrees"))
        }
    };
    let check_er = |key: &str, v: f64| {
        if v > 1.0 && !v.is_nan() {
            Ok(v)
        } else {
            Err(bad(path, key, v, "a ratio above 1 (inf: ideal)"))
        }
    };
    match (&a.file, a.zero_offset_deg, a.extinction_ratio) {
        (Some(f), None, None) => {
            let file = dir.join(f);
            let text = std::fs::read_to_string(&file).map_err(|e| {
                RigError(format!(
                    "rig {}: analyzer.file = {}: cannot read: {e}",
                    path.display(),
                    f.display()
                ))
            })?;
            let cal: AnalyzerFile = toml::from_str(&text).map_err(|e| {
                RigError(format!(
                    "rig {}: analyzer.file = {}: {}",
                    path.display(),
                    f.display(),
                    e.to_string().trim_end().replace('\n', " ")
                ))
            })?;
            Ok(AnalyzerValues {
                zero_offset_deg: check_zero(
                    "analyzer.file's zero_offset_deg",
                    cal.zero_offset_deg,
                )?,
                extinction_ratio: Some(check_er(
                    "analyzer.file's extinction_ratio",
                    cal.extinction_ratio,
                )?),
                file: Some(file),
                revision: Some(cal.revision),
            })
        }
        (Some(_), _, _) => Err(RigError(format!(
            "rig {}: analyzer.file and inline analyzer values exclude each other: allowed \
             either file or zero_offset_deg/extinction_ratio",
            path.display()
        ))),
        (None, z, er) => Ok(AnalyzerValues {
            zero_offset_deg: check_zero("analyzer.zero_offset_deg", z.unwrap_or(0.0))?,
            extinction_ratio: er
                .map(|v| check_er("analyzer.extinction_ratio", v))
                .transpose()?,
            file: None,
            revision: None,
        }),
    }
}

/// A starting rig file from what `devices list` found: the first stage that identified (or a
/// commented placeholder), the first camera found (or the simulated one).
pub fn starting_rig(stage: Option<StageEntry>, camera: Option<CameraEntry>) -> String {
    let mut out = String::from(
        "# A starting rig file (polarimeter devices list --write-rig): check each entry.\n\
         # Keys: [stage] dialect, port, address, model; [camera] backend, id, file;\n\
         # [site] latitude_deg, longitude_deg, elevation_m; [analyzer] zero_offset_deg,\n\
         # extinction_ratio or file. Paths are relative to this file.\n\n",
    );
    let rig = RigFile {
        stage: stage.clone(),
        camera: Some(camera.unwrap_or(CameraEntry {
            backend: "sim".into(),
            id: None,
            file: None,
        })),
        site: None,
        analyzer: Some(AnalyzerEntry {
            zero_offset_deg: Some(0.0),
            extinction_ratio: None,
            file: None,
        }),
    };
    if stage.is_none() {
        out.push_str(&format!(
            "# No stage identified. Name one:\n# [stage]\n# dialect = \"...\"   # {}\n\
             # port = \"/dev/serial/by-id/...\"\n\n",
            registry::names()
        ));
    }
    out.push_str(&toml::to_string(&rig).unwrap_or_default());
    out
}

impl StageEntry {
    /// Whether the entry names the simulated stage.
    pub fn is_simulated(&self) -> bool {
        self.port == SIM_PORT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("polar-rig-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    const LAB: &str = "# The lab's rig.\n[stage]\ndialect = \"elliptec\"\nport = \"/dev/serial/by-id/x\"\naddress = 2\nmodel = \"ell14\"\n\n[camera]  # the GigE camera\nbackend = \"genicam\"\nid = \"Fake_1\"\nfile = \"cam.toml\"\n\n[analyzer]\nzero_offset_deg = 1.5\n";

    /// Unknown keys and bad values are refused naming the file, the key and what is allowed.
    #[test]
    fn errors_name_file_key_and_allowed_values() {
        let p = Path::new("/lab/rig.toml");
        let e = Rig::from_str(p, "[stage]\ndialect = \"native\"\nprt = \"x\"\n")
            .unwrap_err()
            .0;
        assert!(
            e.contains("/lab/rig.toml") && e.contains("prt") && e.contains("`port`"),
            "{e}"
        );
        let e = Rig::from_str(p, "[stage]\ndialect = \"zaber\"\nport = \"x\"\n")
            .unwrap_err()
            .0;
        assert!(
            e.contains("stage.dialect = \"zaber\"") && e.contains("allowed native, elliptec"),
            "{e}"
        );
        let e = Rig::from_str(
            p,
            "[stage]\ndialect = \"elliptec\"\nport = \"x\"\nmodel = \"ell99\"\n",
        )
        .unwrap_err()
        .0;
        assert!(
            e.contains("stage.model") && e.contains("ell14, ell18, ell6, ell9"),
            "{e}"
        );
        let e = Rig::from_str(p, "[camera]\nbackend = \"usb\"\n")
            .unwrap_err()
            .0;
        assert!(
            e.contains("camera.backend") && e.contains("allowed sim, genicam, v4l"),
            "{e}"
        );
        let e = Rig::from_str(p, "[camera]\nbackend = \"genicam\"\n")
            .unwrap_err()
            .0;
        assert!(e.contains("camera.id is missing"), "{e}");
        let e = Rig::from_str(p, "[site]\nlatitude_deg = 91\nlongitude_deg = 0\n")
            .unwrap_err()
            .0;
        assert!(
            e.contains("site.latitude_deg") && e.contains("[-90, 90]"),
            "{e}"
        );
        let e = Rig::from_str(p, "[analyzer]\nextinction_ratio = 0.5\n")
            .unwrap_err()
            .0;
        assert!(
            e.contains("analyzer.extinction_ratio") && e.contains("above 1"),
            "{e}"
        );
        let e = Rig::from_str(p, "[bench]\n").unwrap_err().0;
        assert!(
            e.contains("bench") && e.contains("`stage`, `camera`, `site`, `analyzer`"),
            "{e}"
        );
    }

    /// A flag overrides the rig's entry, the rest come from the rig, and the provenance says
    /// which flags overrode it.
    #[test]
    fn flags_override_the_rig() {
        let rig = Rig::from_str(Path::new("/lab/rig.toml"), LAB).unwrap();
        let hw = rig.hardware(&Overrides::default()).unwrap().unwrap();
        assert_eq!(
            (
                hw.port.as_str(),
                hw.dialect.name,
                hw.address,
                hw.camera.as_str()
            ),
            ("/dev/serial/by-id/x", "elliptec", 2, "genicam:Fake_1")
        );
        assert_eq!(hw.camera_file, PathBuf::from("/lab/cam.toml"));
        assert_eq!(hw.zero_offset_deg, 1.5);
        let o = Overrides {
            port: Some("/dev/ttyUSB3".into()),
            zero_offset_deg: Some(-2.0),
            ..Overrides::default()
        };
        let hw = rig.hardware(&o).unwrap().unwrap();
        assert_eq!(
            (hw.port.as_str(), hw.zero_offset_deg, hw.address),
            ("/dev/ttyUSB3", -2.0, 2)
        );
        assert_eq!(
            hw.provenance["overridden_by_flags"],
            json!(["--port", "--zero-offset-deg"])
        );
        let partial = Rig::from_str(
            Path::new("r.toml"),
            "[stage]\ndialect = \"native\"\nport = \"p\"\n",
        )
        .unwrap();
        let e = partial.hardware(&Overrides::default()).unwrap_err().0;
        assert!(
            e.contains("camera.backend is missing (or give --camera)"),
            "{e}"
        );
    }

    /// Two analyzer calibrations make revisions 1 and 2 (the first kept), the rig points at
    /// the newest and keeps its comments, and reading it back gives the recorded values; a
    /// camera file revision goes beside the camera file.
    #[test]
    fn calibrations_write_new_revisions() {
        let dir = temp("revisions");
        let path = dir.join("rig.toml");
        std::fs::write(&path, LAB).unwrap();
        std::fs::write(dir.join("cam.toml"), "name = \"base\"\n").unwrap();
        let rig = Rig::load(&path).unwrap();
        let first = rig.record_analyzer(-0.25, 850.0, None).unwrap();
        assert_eq!(first, dir.join("analyzer.r1.toml"));
        let rig = Rig::load(&path).unwrap();
        let a = rig.analyzer.clone().unwrap();
        assert_eq!(
            (a.zero_offset_deg, a.extinction_ratio, a.revision),
            (-0.25, Some(850.0), Some(1))
        );
        let second = rig
            .record_analyzer(0.5, 900.0, Some(Path::new("/runs/cal")))
            .unwrap();
        assert_eq!(second, dir.join("analyzer.r2.toml"));
        assert!(first.exists(), "the old revision is kept");
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.starts_with("# The lab's rig.") && text.contains("# the GigE camera"),
            "{text}"
        );
        let rig = Rig::load(&path).unwrap();
        assert_eq!(rig.analyzer.as_ref().and_then(|a| a.revision), Some(2));
        assert_eq!(rig.analyzer.as_ref().map(|a| a.zero_offset_deg), Some(0.5));
        let measured = dir.join("measured.toml");
        std::fs::write(&measured, "name = \"measured\"\n").unwrap();
        let cam = rig.record_camera_file(&measured).unwrap();
        assert_eq!(cam, dir.join("cam.r1.toml"));
        let rig = Rig::load(&path).unwrap();
        assert_eq!(rig.camera_file, Some(dir.join("cam.r1.toml")));
        let cam2 = rig.record_camera_file(&measured).unwrap();
        assert_eq!(cam2, dir.join("cam.r2.toml"));
        assert_eq!(
            std::fs::read_to_string(dir.join("cam.toml")).unwrap(),
            "name = \"base\"\n",
            "the base camera file is untouched"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A starting rig parses back as a rig file.
    #[test]
    fn the_starting_rig_parses() {
        let stage = StageEntry {
            dialect: "fw102c".into(),
            port: "/dev/ttyUSB0".into(),
            address: None,
            model: Some("fw102c".into()),
        };
        for s in [Some(stage), None] {
            let text = starting_rig(s.clone(), None);
            let rig = Rig::from_str(Path::new("new.toml"), &text).unwrap();
            assert_eq!(rig.file.stage, s);
            assert_eq!(rig.camera_name().as_deref(), Some("sim"));
        }
    }
}
