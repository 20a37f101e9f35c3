//! The hardware rig `run`, `resume` and the GUI connect: a rotator of any registered dialect
//! (connected and homed by its registry constructor) and a camera of any registered backend on
//! its thread, with the camera file's noise model and the analyzer's zero offset.
//!
//! A stage port `sim` starts the dialect's simulator (`polar_hil_mocks::sim::SIMULATORS`) on a
//! pseudo-terminal and connects to it through the same serial code; the `sim` camera then
//! renders through the simulated stage's true angle. That is the rig of `examples/rigs/sim.toml`
//! and of the workspace's hardware-in-the-loop tests. The `sim` camera with any other stage
//! renders through the positions that stage reports (`crate::follow`). Either way the
//! simulated camera is a whole bench: the run caps its lens for darks, and a calibration plan
//! finds its integrating sphere or reference polarizer in front of it.

use crate::camera::{self, SimOptions};
use crate::follow::{ReadBack, ReportedAngle};
use crate::RigError;
use polar_drivers::any::AnyRotator;
use polar_drivers::registry::{self, DeviceKind, Dialect};
use polar_engine::run::Rig;
use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{Approach, OnRotator};
use polar_hil_mocks::camera::AngleSource;
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::Arc;

/// The stage port that means "the dialect's simulator on a pseudo-terminal".
pub const SIM_PORT: &str = "sim";

/// Real (or simulated-at-the-byte-level) devices for a run.
#[derive(Debug, Clone)]
pub struct Hardware {
    /// The stage's serial port (a stable `/dev/serial/by-id/...` path), or [`SIM_PORT`].
    pub port: String,
    /// Its dialect.
    pub dialect: &'static Dialect,
    /// Bus address (Elliptec), else 0.
    pub address: u8,
    /// The stage's model, lower case, if named (checked against the dialect's models; picks
    /// the simulator's model with [`SIM_PORT`]).
    pub model: Option<String>,
    /// The camera (`sim`, `genicam:ID`, `v4l:NAME`).
    pub camera: String,
    /// The camera's noise model (a calibrated camera file).
    pub camera_file: PathBuf,
    /// Stage angle at which the analyzer's axis is along the camera's x axis, degrees.
    pub zero_offset_deg: f64,
    /// The analyzer's measured extinction ratio, replacing the camera file's
    /// `polarizer.extinction_ratio` (None: the camera file's).
    pub extinction_ratio: Option<f64>,
    /// Where these values came from (the rig file and its revisions), recorded in the store
    /// under the `devices` attribute's `rig` key; `Null` when they came from flags only.
    pub provenance: Value,
}

impl Hardware {
    /// The hardware the flags describe: `None` when none of `--port`, `--dialect`,
    /// `--camera`, `--camera-file` is given; an error naming the flags when only some are,
    /// the dialect is unknown, or `--zero-offset-deg` is not finite.
    pub fn from_flags(
        port: Option<String>,
        dialect: Option<&str>,
        camera: Option<String>,
        camera_file: Option<PathBuf>,
        address: Option<u8>,
        zero_offset_deg: f64,
    ) -> Result<Option<Hardware>, String> {
        match (port, dialect, camera, camera_file) {
            (None, None, None, None) => Ok(None),
            (Some(port), Some(dialect), Some(camera), Some(camera_file)) => {
                let dialect = registry::find(dialect).ok_or_else(|| {
                    format!(
                        "--dialect = {dialect:?} is invalid: allowed {}",
                        registry::names()
                    )
                })?;
                if !zero_offset_deg.is_finite() {
                    return Err(format!(
                        "--zero-offset-deg = {zero_offset_deg} is invalid: allowed a finite angle"
                    ));
                }
                let address = address.unwrap_or(dialect.default_address());
                dialect
                    .check_address(address)
                    .map_err(|e| format!("--{e}"))?;
                Ok(Some(Hardware {
                    port,
                    dialect,
                    address,
                    model: None,
                    camera,
                    camera_file,
                    zero_offset_deg,
                    extinction_ratio: None,
                    provenance: Value::Null,
                }))
            }
            _ => Err("hardware needs all of --port, --dialect, --camera and --camera-file".into()),
        }
    }
}

/// The engine's rig on these devices: a rotator of any dialect, a threaded camera.
pub type HardwareRig = Rig<OnRotator<AnyRotator>, ThreadedCamera>;

/// A connected rig, and the stage simulator behind it when the port is [`SIM_PORT`] (keep it
/// for as long as the rig is used; [`Connected::shutdown`] stops it).
pub struct Connected {
    /// The rig.
    pub rig: HardwareRig,
    /// The simulated stage's server.
    pub simulator: Option<SimServer>,
}

impl Connected {
    /// Stops the simulator, if any.
    pub async fn shutdown(self) {
        if let Some(s) = self.simulator {
            s.shutdown().await;
        }
    }
}

/// Connects the rig `hw` describes: reads the camera's noise model from `camera_file`, opens
/// the camera, connects and homes the stage through its dialect's registry constructor
/// (positive approach with 1 deg of overshoot, the analyzer's zero offset from `hw`).
///
/// Errors name the flag or key: an unreadable or invalid camera file, a camera that does not
/// open, a stage that does not answer, or a dialect without rotators (a wheel of fixed
/// polarizers cannot turn an analyzer freely).
pub async fn connect_hardware(hw: &Hardware) -> Result<Connected, RigError> {
    connect(hw, None).await
}

/// [`connect_hardware`] for a run of `plan`. On the simulated stage with the simulated camera
/// the rig is a whole simulated bench: the camera's lens cap is the run's to put on for dark
/// frames, a calibration plan finds its integrating sphere or reference polarizer in front of
/// the camera (`crate::simulated::calibration_scene`), and a continuous plan with
/// `trigger = "encoder"` has the camera's trigger line wired to the stage's position-compare
/// output (`crate::simulated::compare_line`), as the cable from a real stage's trigger output
/// to a real camera's line input would be.
pub async fn connect_hardware_for(
    hw: &Hardware,
    plan: &polar_engine::plan::Plan,
) -> Result<Connected, RigError> {
    connect(hw, Some(plan)).await
}

async fn connect(
    hw: &Hardware,
    plan: Option<&polar_engine::plan::Plan>,
) -> Result<Connected, RigError> {
    let line_interval_rad = plan
        .and_then(|plan| {
            plan.continuous().filter(|c| {
                plan.kind() == polar_engine::plan::PlanKind::Continuous
                    && c.trigger == polar_engine::continuous::TriggerSource::Encoder
            })
        })
        .map(|c| c.interval_deg().to_radians());
    let d = hw.dialect;
    let Some(connect_rotator) = d.rotator else {
        return Err(RigError(format!(
            "dialect = {}: a run needs a rotator; {}",
            d.name,
            registry::not_provided(d, DeviceKind::Rotator)
        )));
    };
    let mut camera_model = polar_model::sensor::Camera::from_toml_str(
        &std::fs::read_to_string(&hw.camera_file)
            .map_err(|e| RigError(format!("camera file {}: {e}", hw.camera_file.display())))?,
    )
    .map_err(|e| RigError(format!("camera file {}: {e}", hw.camera_file.display())))?;
    if let Some(er) = hw.extinction_ratio {
        camera_model.polarizer.extinction_ratio = Some(er);
    }
    let band = polar_model::atmosphere::Band::flat(450.0, 650.0).map_err(RigError::of)?;
    let sensor =
        polar_model::sensor::SensorModel::new(&camera_model, &band).map_err(RigError::of)?;
    // The stage: the port, or the dialect's simulator on a pseudo-terminal.
    let (port, simulator) = if hw.port == SIM_PORT {
        let server = start_simulator(hw)?;
        let link = server
            .link()
            .map(|l| l.display().to_string())
            .ok_or_else(|| RigError("the simulated stage has no link".into()))?;
        (link, Some(server))
    } else {
        (hw.port.clone(), None)
    };
    let mut illumination = None;
    let reported = ReportedAngle::default();
    let mut follows_reports = false;
    let camera = match (&simulator, hw.camera.as_str()) {
        (Some(server), "sim") => {
            let handle = server.truth_handle();
            let angle: AngleSource = Arc::new(move || match handle.truth() {
                Truth::Angle { output_rad, .. } => output_rad,
                Truth::Slot { .. } => 0.0,
            });
            let opts = SimOptions {
                camera_file: Some(hw.camera_file.clone()),
                ..SimOptions::default()
            };
            let mut cam = camera::sim_camera_for_plan(&opts, angle, plan).map_err(RigError::of)?;
            illumination = Some(crate::simulated::scene_light(&cam.illumination()));
            if let Some(interval_rad) = line_interval_rad {
                cam.wire_line(crate::simulated::compare_line(
                    server.truth_handle(),
                    interval_rad,
                ));
            }
            ThreadedCamera::spawn(cam, ThreadPolicy::default()).map_err(RigError::of)?
        }
        (None, "sim") => {
            if line_interval_rad.is_some() || plan.is_some_and(|p| p.continuous().is_some()) {
                return Err(RigError(format!(
                    "camera = \"sim\" with stage port = {:?}: the simulated camera follows a \
                     stage the rig does not simulate through the positions the stage reports, \
                     which cannot render a spinning analyzer. Allowed for a continuous plan: \
                     stage port = \"sim\" (the rig simulates the stage), or a real camera",
                    hw.port
                )));
            }
            let angle = reported.clone();
            let source: AngleSource = Arc::new(move || angle.get());
            let opts = SimOptions {
                camera_file: Some(hw.camera_file.clone()),
                ..SimOptions::default()
            };
            let cam = camera::sim_camera_for_plan(&opts, source, plan).map_err(RigError::of)?;
            illumination = Some(crate::simulated::scene_light(&cam.illumination()));
            follows_reports = true;
            ThreadedCamera::spawn(cam, ThreadPolicy::default()).map_err(RigError::of)?
        }
        _ => camera::open(&hw.camera, &SimOptions::default())
            .map_err(|e| RigError(format!("camera = {}: {e}", hw.camera)))?,
    };
    let devices = json!({
        "kind": "hardware",
        "stage": { "port": hw.port, "dialect": d.name, "address": hw.address, "model": hw.model },
        "camera": hw.camera,
        "camera_file": hw.camera_file.display().to_string(),
        "camera_info": format!("{:?}", polar_hal::Camera::info(&camera)),
        "zero_offset_deg": hw.zero_offset_deg,
        "extinction_ratio": hw.extinction_ratio,
        "rig": hw.provenance,
        "camera_follows": match (&simulator, hw.camera.as_str()) {
            (Some(_), "sim") => "the simulated stage's true angle",
            (None, "sim") => "the positions the stage reports (a stage the rig does not simulate)",
            _ => "the real scene",
        },
    });
    let connector = d.connector(&port);
    let mut rotator = connect_rotator(connector, hw.address, (d.policy)())
        .await
        .map_err(|e| RigError(format!("stage {} ({}): {e}", hw.port, d.name)))?;
    if follows_reports {
        let mut read_back = ReadBack::new(rotator, reported);
        polar_hal::Rotator::position_rad(&mut read_back)
            .await
            .map_err(|e| RigError(format!("stage {} ({}): {e}", hw.port, d.name)))?;
        rotator = AnyRotator::new(read_back);
    }
    Ok(Connected {
        rig: Rig {
            analyzer: OnRotator {
                rotator,
                zero_offset_rad: hw.zero_offset_deg.to_radians(),
                approach: Approach::Positive,
                overshoot_rad: 1f64.to_radians(),
            },
            camera,
            camera_model,
            sensor,
            illumination,
            target_mask: None,
            sun_deg: None,
            devices,
            // A stage's acceleration is not read from the device: the fixed run-up.
            spin_acceleration_rad_per_s2: None,
        },
        simulator,
    })
}

/// The dialect's simulator (model `hw.model` or its first) on a pseudo-terminal whose link is
/// in a folder of its own in the temporary directory, removed with the simulator.
fn start_simulator(hw: &Hardware) -> Result<SimServer, RigError> {
    let faults = FaultProfile::default();
    let seed = 1;
    let sim = polar_hil_mocks::sim::simulator(hw.dialect.name, hw.model.as_deref(), faults, seed)
        .map_err(|e| RigError(format!("stage: {e}")))?;
    let dir = std::env::temp_dir().join(format!(
        "polarimeter-rig-{}-{}",
        std::process::id(),
        NEXT_LINK.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    ));
    SimServer::pty_in_new_dir(sim, faults, seed, &dir, hw.dialect.name).map_err(|e| {
        RigError(format!(
            "cannot open a pseudo-terminal in {}: {e}",
            dir.display()
        ))
    })
}

static NEXT_LINK: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
