//! `polarimeter devices camera --camera sim|genicam:ID|v4l:NAME grab ...`: frames from a camera to
//! 16-bit TIFF files, each with a JSON sidecar of its metadata.
//!
//! Cameras are opened through the camera backends' registry (`polar_rig::camera`). The
//! simulated camera (`sim`) renders a scene file (default: the rooftop example with an
//! aluminium panel added) through an analyzer at a fixed angle (`--analyzer-deg`), with the
//! sensor model of a camera file (default: the modern CMOS example). The GenICam and V4L2
//! backends are cargo features (`genicam`, `v4l`) this crate forwards to `polar-rig`: the
//! default build needs no system library.

use polar_hal::camera_thread::ThreadedCamera;
use polar_hal::{Camera, DeviceError, Frame};
use polar_rig::camera::CameraError;
pub use polar_rig::camera::SimOptions;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

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

impl From<CameraError> for CameraCmdError {
    fn from(e: CameraError) -> Self {
        match e {
            CameraError::Device(d) => CameraCmdError::Device(d),
            CameraError::Input(m) => CameraCmdError::Input(m),
        }
    }
}

/// Opens a camera by name through the camera backends' registry (`polar_rig::camera`).
pub fn open(spec: &str, sim: &SimOptions) -> Result<ThreadedCamera, CameraCmdError> {
    Ok(polar_rig::camera::open(spec, sim)?)
}

/// The camera name and camera file of `devices camera`: `--camera` and `--camera-file` override the
/// rig file's `[camera]`; the error names the flag or the rig's key that is missing.
pub fn from_rig(
    rig: Option<&Path>,
    camera: Option<String>,
    camera_file: Option<PathBuf>,
) -> Result<(String, Option<PathBuf>), crate::commands::CommandError> {
    let rig = rig.map(crate::rig::load).transpose()?;
    let name = camera
        .or_else(|| rig.as_ref().and_then(polar_rig::Rig::camera_name))
        .ok_or_else(|| {
            crate::commands::CommandError::failed(match &rig {
                Some(r) => format!(
                    "rig {}: camera.backend is missing (or give --camera)",
                    r.path.display()
                ),
                None => {
                    "give --camera (sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME) or --rig".into()
                }
            })
        })?;
    let file = camera_file.or_else(|| rig.and_then(|r| r.camera_file));
    Ok((name, file))
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
        "stats": serde_json::to_value(polar_engine::run::CameraStream::from(s)).unwrap_or_default(),
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
