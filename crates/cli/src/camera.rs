//! `polarimeter camera --camera sim|genicam:ID|v4l:NAME grab ...`: frames from a camera to
//! 16-bit TIFF files, each with a JSON sidecar of its metadata, and the cameras that
//! `devices list` shows.
//!
//! The simulated camera (`sim`) renders a scene file (default: the rooftop example with an
//! aluminium panel added) through an analyzer at a fixed angle (`--analyzer-deg`), with the
//! sensor model of a camera file (default: the modern CMOS example). The GenICam and V4L2
//! backends are cargo features of this crate (`genicam`, `v4l`): the default build needs no
//! system library.

use polar_drivers::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{Camera, DeviceError, Frame};
use polar_hil_mocks::camera::{AngleSource, Layout, SimCamera, SimCameraConfig, SimScene};
use polar_model::scene_file::Scene;
use polar_model::sensor::Camera as CameraModel;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The default scene of the simulated camera: `examples/rooftop_panels.toml`, the rooftop
/// example with an aluminium panel added.
pub const DEFAULT_SCENE: &str = include_str!("../../../examples/rooftop_panels.toml");

/// The default camera of the simulated camera.
pub const DEFAULT_CAMERA: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

/// Errors of the camera command.
#[derive(Debug, thiserror::Error)]
pub enum CameraCmdError {
    /// A device error.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// A bad option or file; the message names it.
    #[error("{0}")]
    Input(String),
    /// Writing the output failed.
    #[error("{path}: cannot write: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// How the simulated camera is set up.
#[derive(Debug, Clone)]
pub struct SimOptions {
    /// Scene file (None: [`DEFAULT_SCENE`]).
    pub scene: Option<PathBuf>,
    /// Camera file (None: [`DEFAULT_CAMERA`]).
    pub camera_file: Option<PathBuf>,
    /// Analyzer angle, degrees.
    pub analyzer_deg: f64,
    /// Sensor size, pixels.
    pub width: u32,
    /// Sensor size, pixels.
    pub height: u32,
    /// Seed of the texture and the noise.
    pub seed: u64,
}

fn read(path: &Path, what: &str) -> Result<String, CameraCmdError> {
    std::fs::read_to_string(path).map_err(|e| {
        CameraCmdError::Input(format!("--{what} {}: cannot read: {e}", path.display()))
    })
}

/// The simulated camera, as a blocking camera.
pub fn sim_camera(opts: &SimOptions) -> Result<SimCamera, CameraCmdError> {
    let scene_text = match &opts.scene {
        Some(p) => read(p, "scene")?,
        None => DEFAULT_SCENE.to_string(),
    };
    let base = opts
        .scene
        .as_ref()
        .and_then(|p| p.parent().map(Path::to_path_buf))
        .unwrap_or_default();
    let scene = Scene::from_toml_str_with_files(&scene_text, &|name| {
        std::fs::read_to_string(base.join(name)).map_err(|e| e.to_string())
    })
    .map_err(|e| CameraCmdError::Input(format!("scene: {e}")))?;
    let camera_text = match &opts.camera_file {
        Some(p) => read(p, "camera-file")?,
        None => DEFAULT_CAMERA.to_string(),
    };
    let camera = CameraModel::from_toml_str(&camera_text)
        .map_err(|e| CameraCmdError::Input(format!("camera file: {e}")))?;
    if !opts.analyzer_deg.is_finite() {
        return Err(CameraCmdError::Input(format!(
            "analyzer_deg = {} is invalid: allowed a finite angle",
            opts.analyzer_deg
        )));
    }
    let names: Vec<String> = scene.materials.iter().map(|m| m.name.clone()).collect();
    let sim_scene = SimScene::render(
        &scene.spec,
        &scene.materials,
        &Layout::panels_on_ground(&names),
        opts.width,
        opts.height,
        1e-3,
        opts.seed,
    )
    .map_err(|e| CameraCmdError::Input(e.to_string()))?;
    let psi = opts.analyzer_deg.to_radians();
    let angle: AngleSource = Arc::new(move || psi);
    SimCamera::new(
        SimCameraConfig {
            id: "sim".into(),
            camera,
            scene: Arc::new(sim_scene),
            max_frame_rate_hz: 100.0,
            faults: Default::default(),
            seed: opts.seed,
            noise_stream: 0,
        },
        angle,
    )
    .map_err(|e| CameraCmdError::Input(e.to_string()))
}

/// Opens a camera by its spec: `sim`, `genicam:ID` or `v4l:NAME`.
pub fn open(spec: &str, sim: &SimOptions) -> Result<ThreadedCamera, CameraCmdError> {
    let policy = ThreadPolicy::default();
    match spec.split_once(':') {
        None if spec == "sim" => Ok(ThreadedCamera::spawn(sim_camera(sim)?, policy)?),
        Some(("genicam", id)) => open_genicam(id, policy),
        Some(("v4l", name)) => open_v4l(name, policy),
        _ => Err(CameraCmdError::Input(format!(
            "camera = {spec:?} is invalid: allowed sim, genicam:ID or v4l:NAME"
        ))),
    }
}

#[cfg(feature = "genicam")]
fn open_genicam(id: &str, policy: ThreadPolicy) -> Result<ThreadedCamera, CameraCmdError> {
    let cam = polar_camera_aravis::AravisCamera::open(id).map_err(DeviceError::from)?;
    Ok(ThreadedCamera::spawn(cam, policy)?)
}

#[cfg(not(feature = "genicam"))]
fn open_genicam(_id: &str, _policy: ThreadPolicy) -> Result<ThreadedCamera, CameraCmdError> {
    Err(CameraCmdError::Input(
        "camera = genicam:...: this build has no GenICam support; rebuild with \
         `cargo build --release -p polar-cli --features genicam` (needs libaravis-dev and \
         libusb-1.0-0-dev)"
            .into(),
    ))
}

#[cfg(feature = "v4l")]
fn open_v4l(name: &str, policy: ThreadPolicy) -> Result<ThreadedCamera, CameraCmdError> {
    let cam = polar_camera_v4l::V4lCamera::open(name)?;
    Ok(ThreadedCamera::spawn(cam, policy)?)
}

#[cfg(not(feature = "v4l"))]
fn open_v4l(_name: &str, _policy: ThreadPolicy) -> Result<ThreadedCamera, CameraCmdError> {
    Err(CameraCmdError::Input(
        "camera = v4l:...: this build has no V4L2 support; rebuild with \
         `cargo build --release -p polar-cli --features v4l`"
            .into(),
    ))
}

/// The cameras `devices list` shows: the compiled-in backends' discoveries, and the simulated
/// camera with `simulate`.
pub fn list(simulate: bool) -> Value {
    let mut cameras = Vec::new();
    if simulate {
        cameras.push(json!({
            "camera": "sim",
            "backend": "simulated",
            "model": "rendered from the model (scene and camera files)",
        }));
    }
    #[cfg(feature = "genicam")]
    match polar_camera_aravis::list() {
        Ok(found) => cameras.extend(found.into_iter().map(|d| {
            json!({ "camera": format!("genicam:{}", d.id), "backend": "genicam",
                    "model": format!("{} {}", d.vendor, d.model), "address": d.address })
        })),
        Err(e) => cameras.push(json!({ "backend": "genicam", "error": e.to_string() })),
    }
    #[cfg(feature = "v4l")]
    match polar_camera_v4l::list() {
        Ok(found) => cameras.extend(found.into_iter().map(|d| {
            json!({ "camera": format!("v4l:{}", d.card), "backend": "v4l2",
                    "path": d.path.display().to_string(), "bus": d.bus_info, "driver": d.driver,
                    "formats": d.fourccs })
        })),
        Err(e) => cameras.push(json!({ "backend": "v4l2", "error": e.to_string() })),
    }
    json!({
        "cameras": cameras,
        "backends": {
            "genicam": cfg!(feature = "genicam"),
            "v4l": cfg!(feature = "v4l"),
        },
    })
}

/// What `grab` was asked for.
#[derive(Debug, Clone)]
pub struct GrabOptions {
    /// Exposure, microseconds.
    pub exposure_us: f64,
    /// Gain, in the camera's unit (None: leave as is).
    pub gain: Option<f64>,
    /// Frames to write.
    pub count: usize,
    /// Output directory.
    pub out: PathBuf,
    /// Deadline of each grab.
    pub deadline: Duration,
}

fn unix_ns(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

/// The JSON sidecar of a frame.
pub fn sidecar(frame: &Frame, camera: &polar_hal::CameraInfo, file: &str) -> Value {
    json!({
        "file": file,
        "camera": camera.id,
        "vendor": camera.vendor,
        "model": camera.model,
        "serial": camera.serial,
        "width": frame.width,
        "height": frame.height,
        "pixel_format": frame.format.name(),
        "frame_id": frame.frame_id,
        "host_time_unix_ns": unix_ns(frame.host_time),
        "device_timestamp_ns": frame.device_timestamp_ns,
        "exposure_us": frame.exposure_us,
        "gain": frame.gain,
        "gain_unit": format!("{:?}", camera.gain_unit),
        "mean": frame.mean(),
    })
}

/// Grabs `count` frames and writes `frame_NNNN.tif` and `frame_NNNN.json` for each into `out`;
/// returns a summary (files, counters). Frames already written stay written if a later grab
/// fails (the error says how many were written).
pub async fn grab(cam: &mut ThreadedCamera, opts: &GrabOptions) -> Result<Value, CameraCmdError> {
    if !(1..=100_000).contains(&opts.count) {
        return Err(CameraCmdError::Input(format!(
            "count = {} is out of range: allowed 1 to 100000",
            opts.count
        )));
    }
    std::fs::create_dir_all(&opts.out).map_err(|source| CameraCmdError::Write {
        path: opts.out.clone(),
        source,
    })?;
    let applied_us = cam.set_exposure_us(opts.exposure_us).await?;
    let applied_gain = match opts.gain {
        Some(g) => Some(cam.set_gain(g).await?),
        None => None,
    };
    cam.start().await?;
    let mut files = Vec::new();
    for i in 0..opts.count {
        let frame = match cam.grab(opts.deadline).await {
            Ok(f) => f,
            Err(e) => {
                let _ = cam.stop().await;
                return Err(CameraCmdError::Input(format!(
                    "{e} (after {i} of {} frames; those are written in {})",
                    opts.count,
                    opts.out.display()
                )));
            }
        };
        let stem = format!("frame_{i:04}");
        let tif = opts.out.join(format!("{stem}.tif"));
        write_tiff16(&tif, frame.width, frame.height, &frame.pixels)?;
        let meta = sidecar(&frame, cam.info(), &format!("{stem}.tif"));
        let json_path = opts.out.join(format!("{stem}.json"));
        let text = serde_json::to_string_pretty(&meta).unwrap_or_default();
        std::fs::write(&json_path, text + "\n").map_err(|source| CameraCmdError::Write {
            path: json_path.clone(),
            source,
        })?;
        files.push(format!("{stem}.tif"));
    }
    cam.stop().await?;
    let s = cam.stats();
    Ok(json!({
        "camera": cam.info().id,
        "out": opts.out.display().to_string(),
        "files": files,
        "exposure_us": applied_us,
        "gain": applied_gain,
        "stats": { "delivered": s.delivered, "incomplete": s.incomplete, "dropped": s.dropped, "timeouts": s.timeouts },
    }))
}

/// Writes a 16-bit single-channel TIFF.
pub fn write_tiff16(
    path: &Path,
    width: u32,
    height: u32,
    data: &[u16],
) -> Result<(), CameraCmdError> {
    crate::calibrate::write_tiff(path, width, height, data).map_err(|e| CameraCmdError::Write {
        path: path.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    })
}
