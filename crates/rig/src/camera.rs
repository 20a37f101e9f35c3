//! The registry of camera backends: each backend is declared once, as a [`CameraBackend`]
//! (name, description, the cargo feature that compiles it in, open by ID, list), and
//! [`CAMERA_BACKENDS`] lists them. A camera is named `BACKEND:ID` (`genicam:ID`, `v4l:NAME`,
//! `uvc:BUS_OR_NAME`), or `sim` for the simulated camera, which renders a scene file through an analyzer at a fixed
//! angle with a camera file's sensor model.
//!
//! The GenICam, V4L2 and UVC backends are cargo features of this crate (`genicam`, `v4l`,
//! `uvc`), which the CLI and the GUI forward: the default build needs no system library. A backend not compiled
//! in is still listed, and opening it says which feature to build with.

use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::DeviceError;
use polar_hil_mocks::camera::{AngleSource, Layout, SimCamera, SimCameraConfig, SimScene};
use polar_model::scene_file::Scene;
use polar_model::sensor::Camera as CameraModel;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The default scene of the simulated camera: `examples/rooftop_panels.toml`, the rooftop
/// example with an aluminium panel added.
pub const DEFAULT_SCENE: &str = include_str!("../../../examples/rooftop_panels.toml");

/// The default camera of the simulated camera.
pub const DEFAULT_CAMERA: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

/// Errors of opening or listing a camera.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// A device error.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// A bad name, option or file; the message names it.
    #[error("{0}")]
    Input(String),
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

impl Default for SimOptions {
    /// The default scene and camera at 320 x 240, analyzer at 0, seed 1.
    fn default() -> Self {
        SimOptions {
            scene: None,
            camera_file: None,
            analyzer_deg: 0.0,
            width: 320,
            height: 240,
            seed: 1,
        }
    }
}

/// Opens camera `id` of a backend.
pub type OpenCamera = fn(&str, ThreadPolicy) -> Result<ThreadedCamera, CameraError>;
/// Lists a backend's cameras (JSON objects with at least `camera`, the name to open it by).
pub type ListCameras = fn() -> Result<Vec<Value>, CameraError>;

/// One camera backend, declared once.
#[derive(Debug, Clone, Copy)]
pub struct CameraBackend {
    /// The prefix of its camera names (`genicam` in `genicam:ID`).
    pub name: &'static str,
    /// One line for `--help` and `devices list`.
    pub description: &'static str,
    /// What its camera IDs are called in help and errors (`ID`, `NAME`).
    pub id_name: &'static str,
    /// The cargo feature that compiles it in.
    pub feature: &'static str,
    /// Whether this build has it.
    pub compiled: bool,
    /// Opens a camera by ID.
    pub open: OpenCamera,
    /// Lists the cameras found.
    pub list: ListCameras,
}

/// Every camera backend, one line each.
pub static CAMERA_BACKENDS: &[CameraBackend] = &[GENICAM, V4L, UVC];

/// The backend named `name`.
pub fn find(name: &str) -> Option<&'static CameraBackend> {
    CAMERA_BACKENDS.iter().find(|b| b.name == name)
}

/// The camera names allowed, for error messages: `sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME`.
pub fn allowed() -> String {
    let mut names = vec!["sim".to_string()];
    names.extend(
        CAMERA_BACKENDS
            .iter()
            .map(|b| format!("{}:{}", b.name, b.id_name)),
    );
    let last = names.pop().unwrap_or_default();
    if names.is_empty() {
        last
    } else {
        format!("{} or {last}", names.join(", "))
    }
}

/// Checks a camera name (`sim` or `BACKEND:ID` of a known backend) without opening it.
pub fn check_name(spec: &str) -> Result<(), String> {
    match spec.split_once(':') {
        None if spec == "sim" => Ok(()),
        Some((b, id)) if find(b).is_some() && !id.is_empty() => Ok(()),
        _ => Err(format!(
            "camera = {spec:?} is invalid: allowed {}",
            allowed()
        )),
    }
}

fn not_compiled(b: &CameraBackend) -> CameraError {
    CameraError::Input(format!(
        "camera = {}:...: this build has no {} support; rebuild with `--features {}`",
        b.name, b.description, b.feature
    ))
}

fn read(path: &Path, what: &str) -> Result<String, CameraError> {
    std::fs::read_to_string(path)
        .map_err(|e| CameraError::Input(format!("--{what} {}: cannot read: {e}", path.display())))
}

/// The simulated camera, as a blocking camera, with its analyzer at `opts.analyzer_deg`.
pub fn sim_camera(opts: &SimOptions) -> Result<SimCamera, CameraError> {
    if !opts.analyzer_deg.is_finite() {
        return Err(CameraError::Input(format!(
            "analyzer_deg = {} is invalid: allowed a finite angle",
            opts.analyzer_deg
        )));
    }
    let psi = opts.analyzer_deg.to_radians();
    sim_camera_following(opts, Arc::new(move || psi))
}

/// The simulated camera, its analyzer at the angle `angle` reads at each exposure (a simulated
/// stage's true angle).
pub fn sim_camera_following(
    opts: &SimOptions,
    angle: AngleSource,
) -> Result<SimCamera, CameraError> {
    sim_camera_for_plan(opts, angle, None)
}

/// [`sim_camera_following`] set up for a run of `plan`: a calibration plan finds the bench it
/// needs in front of the camera (the integrating sphere or the reference polarizer of
/// `crate::simulated::calibration_scene`), as the simulated rig of `--simulate` places them;
/// the other kinds look at the scene.
pub fn sim_camera_for_plan(
    opts: &SimOptions,
    angle: AngleSource,
    plan: Option<&polar_engine::plan::Plan>,
) -> Result<SimCamera, CameraError> {
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
    .map_err(|e| CameraError::Input(format!("scene: {e}")))?;
    let camera_text = match &opts.camera_file {
        Some(p) => read(p, "camera-file")?,
        None => DEFAULT_CAMERA.to_string(),
    };
    let camera = CameraModel::from_toml_str(&camera_text)
        .map_err(|e| CameraError::Input(format!("camera file: {e}")))?;
    let bench = match plan {
        Some(plan) => crate::simulated::calibration_scene(
            plan,
            &camera,
            scene.spec.band.clone(),
            opts.width,
            opts.height,
        )
        .map_err(|e| CameraError::Input(e.to_string()))?,
        None => None,
    };
    let sim_scene = match bench {
        Some(bench) => bench,
        None => {
            let names: Vec<String> = scene.materials.iter().map(|m| m.name.clone()).collect();
            SimScene::render(
                &scene.spec,
                &scene.materials,
                &Layout::panels_on_ground(&names),
                opts.width,
                opts.height,
                1e-3,
                opts.seed,
            )
            .map_err(|e| CameraError::Input(e.to_string()))?
        }
    };
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
    .map_err(|e| CameraError::Input(e.to_string()))
}

/// Opens a camera by name: `sim` (set up by `sim`) or `BACKEND:ID`.
pub fn open(spec: &str, sim: &SimOptions) -> Result<ThreadedCamera, CameraError> {
    let policy = ThreadPolicy::default();
    match spec.split_once(':') {
        None if spec == "sim" => Ok(ThreadedCamera::spawn(sim_camera(sim)?, policy)?),
        Some((backend, id)) => match find(backend) {
            Some(b) if b.compiled => (b.open)(id, policy),
            Some(b) => Err(not_compiled(b)),
            None => Err(CameraError::Input(format!(
                "camera = {spec:?} is invalid: allowed {}",
                allowed()
            ))),
        },
        None => Err(CameraError::Input(format!(
            "camera = {spec:?} is invalid: allowed {}",
            allowed()
        ))),
    }
}

/// The cameras `devices list` shows: the compiled-in backends' discoveries (a backend that
/// fails to list shows its error), the simulated camera with `simulate`, and which backends
/// this build has.
pub fn list(simulate: bool) -> Value {
    let mut cameras = Vec::new();
    if simulate {
        cameras.push(json!({
            "camera": "sim",
            "backend": "simulated",
            "model": "rendered from the model (scene and camera files)",
        }));
    }
    let mut backends = serde_json::Map::new();
    for b in CAMERA_BACKENDS {
        backends.insert(b.name.into(), json!(b.compiled));
        if b.compiled {
            match (b.list)() {
                Ok(found) => cameras.extend(found),
                Err(e) => cameras.push(json!({ "backend": b.name, "error": e.to_string() })),
            }
        }
    }
    json!({ "cameras": cameras, "backends": backends })
}

/// GenICam (GigE Vision, USB3 Vision) through Aravis.
const GENICAM: CameraBackend = CameraBackend {
    name: "genicam",
    description: "GenICam (GigE Vision / USB3 Vision, through Aravis)",
    id_name: "ID",
    feature: "genicam",
    compiled: cfg!(feature = "genicam"),
    open: genicam::open,
    list: genicam::list,
};

/// Video4Linux2.
const V4L: CameraBackend = CameraBackend {
    name: "v4l",
    description: "V4L2 (Linux webcams and USB/CSI video)",
    id_name: "NAME",
    feature: "v4l",
    compiled: cfg!(feature = "v4l"),
    open: v4l::open,
    list: v4l::list,
};

/// UVC cameras through nokhwa (Windows Media Foundation, macOS AVFoundation, Linux V4L2).
const UVC: CameraBackend = CameraBackend {
    name: "uvc",
    description: "UVC cameras through nokhwa (Windows, macOS; Linux: prefer v4l for Y16)",
    id_name: "BUS_OR_NAME",
    feature: "uvc",
    compiled: cfg!(feature = "uvc"),
    open: uvc::open,
    list: uvc::list,
};

#[cfg(feature = "uvc")]
mod uvc {
    use super::*;

    pub(super) fn open(id: &str, policy: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        let cam = polar_camera_uvc::UvcCamera::open(&format!("uvc:{id}"))?;
        Ok(ThreadedCamera::spawn(cam, policy)?)
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        let found = polar_camera_uvc::list().map_err(|e| CameraError::Input(e.to_string()))?;
        Ok(found
            .into_iter()
            .map(|d| {
                json!({ "camera": d.spec(), "backend": "uvc", "model": d.name,
                        "bus": d.bus_info, "description": d.description })
            })
            .collect())
    }
}

#[cfg(not(feature = "uvc"))]
mod uvc {
    use super::*;

    pub(super) fn open(_: &str, _: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        Err(not_compiled(&UVC))
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        Ok(Vec::new())
    }
}

#[cfg(feature = "genicam")]
mod genicam {
    use super::*;

    pub(super) fn open(id: &str, policy: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        let cam = polar_camera_aravis::AravisCamera::open(id).map_err(DeviceError::from)?;
        Ok(ThreadedCamera::spawn(cam, policy)?)
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        let found = polar_camera_aravis::list().map_err(|e| CameraError::Input(e.to_string()))?;
        Ok(found
            .into_iter()
            .map(|d| {
                json!({ "camera": format!("genicam:{}", d.id), "backend": "genicam",
                        "model": format!("{} {}", d.vendor, d.model), "address": d.address })
            })
            .collect())
    }
}

#[cfg(not(feature = "genicam"))]
mod genicam {
    use super::*;

    pub(super) fn open(_: &str, _: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        Err(not_compiled(&GENICAM))
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        Ok(Vec::new())
    }
}

#[cfg(feature = "v4l")]
mod v4l {
    use super::*;

    pub(super) fn open(name: &str, policy: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        let cam = polar_camera_v4l::V4lCamera::open(name)?;
        Ok(ThreadedCamera::spawn(cam, policy)?)
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        let found = polar_camera_v4l::list().map_err(|e| CameraError::Input(e.to_string()))?;
        Ok(found
            .into_iter()
            .map(|d| {
                json!({ "camera": format!("v4l:{}", d.card), "backend": "v4l",
                        "path": d.path.display().to_string(), "bus": d.bus_info,
                        "driver": d.driver, "formats": d.fourccs })
            })
            .collect())
    }
}

#[cfg(not(feature = "v4l"))]
mod v4l {
    use super::*;

    pub(super) fn open(_: &str, _: ThreadPolicy) -> Result<ThreadedCamera, CameraError> {
        Err(not_compiled(&V4L))
    }

    pub(super) fn list() -> Result<Vec<Value>, CameraError> {
        Ok(Vec::new())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Names are checked against the registry; a backend this build lacks names its feature.
    #[test]
    fn names_and_missing_backends_are_reported() {
        check_name("sim").unwrap();
        check_name("genicam:Fake_1").unwrap();
        let e = check_name("usb:3").unwrap_err();
        assert!(
            e.contains("allowed sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME"),
            "{e}"
        );
        assert!(check_name("genicam:").is_err());
        for b in CAMERA_BACKENDS.iter().filter(|b| !b.compiled) {
            let Err(e) = open(&format!("{}:x", b.name), &SimOptions::default()) else {
                panic!("{} opened without its feature", b.name);
            };
            assert!(
                e.to_string().contains(&format!("--features {}", b.feature)),
                "{e}"
            );
        }
    }
}
