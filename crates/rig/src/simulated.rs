//! The simulated rig of `--simulate`, `demo` and the tests: a rotation stage simulated behind
//! a real pseudo-terminal, driven by its dialect's real driver, and the simulated camera, which
//! renders every frame from the model through the stage's true angle (the stage simulator's
//! truth). The plan's `simulation.stage` chooses the stage among the simulators' registry's
//! rotators ([`crate::sim_stage`]; by default the registry's first rotator, our firmware's)
//! and the driver comes from the dialects' registry (`polar_drivers::registry::DIALECTS`), so a
//! new simulated rotator needs no change here. The stage moves and homes at
//! `simulation.stage_deg_per_s` where its simulator offers a chosen speed
//! (`SimDialect::at_speed`; the APT K10CR1 is capped at 293 deg/s, the most its velocity
//! parameter expresses), otherwise at the real device's speed.
//!
//! The scene depends on the plan: the plan's scene file (by default the rooftop panels) for
//! captures, time-lapses and adaptive runs; a uniform unpolarised source (an integrating
//! sphere) for the noise calibration; a uniform source behind a reference polarizer for the
//! analyzer calibration. Dark frames cap the lens ([`Illumination`] 0); the plan's
//! `simulation.cloud_at_set` dims the scene in the middle of that set.

use polar_drivers::any::AnyRotator;
use polar_drivers::registry;
use polar_engine::continuous::TriggerSource;
use polar_engine::plan::{Acquisition, Plan, PlanKind};
use polar_engine::run::{Rig as EngineRig, SceneLight};
use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
use polar_hal::{Approach, OnRotator};
use polar_hal::{DeviceError, Roi};
use polar_hil_mocks::camera::{
    CameraFaults, Illumination, Layout, LineSource, SimCamera, SimCameraConfig, SimScene,
};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Simulator;
use polar_model::scene_file::Scene;
use polar_model::sensor::{Camera as CameraModel, SensorModel};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The default simulated scene: the rooftop panels example.
pub const DEFAULT_SCENE: &str = include_str!("../../../examples/rooftop_panels.toml");
/// The default simulated camera: the modern CMOS example.
pub const DEFAULT_CAMERA: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

/// Why the simulated rig did not start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A file or field of the plan's `[simulation]`.
    #[error("simulation: {0}")]
    Input(String),
    /// The pseudo-terminal or the driver.
    #[error("simulated stage: {0}")]
    Stage(String),
    /// The camera.
    #[error("simulated camera: {0}")]
    Camera(String),
}

/// What the simulated camera sees.
pub struct SimWorld {
    /// The scene (ground truth).
    pub scene: Arc<SimScene>,
    /// The camera model the frames are drawn from.
    pub camera_model: CameraModel,
    /// The sensor model (camera and band).
    pub sensor: SensorModel,
    /// The scene file.
    pub scene_file: Scene,
}

/// The simulated rig: the stage's server and link, and what the camera renders.
pub struct SimRig {
    /// The stage's simulator, served on a pseudo-terminal.
    pub server: SimServer,
    /// The pseudo-terminal the driver opens.
    pub link: PathBuf,
    /// The stage's dialect (its driver's registry name).
    pub stage_dialect: &'static str,
    /// The stage's model, as the simulators' registry names it.
    pub stage_model: &'static str,
    /// The scene (ground truth).
    pub scene: Arc<SimScene>,
    /// The camera model the frames are drawn from.
    pub camera_model: CameraModel,
    /// The sensor model (camera and band).
    pub sensor: SensorModel,
    /// The lens cap and the clouds.
    pub illumination: Illumination,
    /// Each exposure's true start and end angles (ground truth for tests).
    pub exposures: polar_hil_mocks::camera::ExposureLog,
    /// Materials of the scene file (for target masks by name).
    pub scene_file: Option<Scene>,
}

fn read_relative(base: &Path, name: &str, field: &str) -> Result<String, SimError> {
    let path = base.join(name);
    std::fs::read_to_string(&path)
        .map_err(|e| SimError::Input(format!("{field} = {}: cannot read: {e}", path.display())))
}

/// A uniform scene of `stokes` radiance over `width x height` (one region, `name`).
fn uniform(
    name: &str,
    stokes: [f64; 3],
    width: u32,
    height: u32,
    band: polar_model::atmosphere::Band,
) -> SimScene {
    let n = width as usize * height as usize;
    SimScene {
        width,
        height,
        stokes: vec![stokes; n],
        region: vec![0; n],
        materials: vec![name.to_string()],
        material_means: vec![stokes],
        band,
    }
}

/// The bench a calibration plan needs in front of the simulated camera, as a scene of
/// `width x height`: an integrating sphere (uniform, unpolarised) for a noise calibration,
/// bright enough that the plan's longest exposure reaches 1.1 full wells (the series crosses
/// saturation, as EMVA 1288 asks); a reference polarizer of diattenuation 0.999 (extinction
/// ratio about 2000) at the plan's reference angle in front of a uniform source for an
/// analyzer calibration, its brightest frame at 60 % of the full well. `None` for the other
/// plan kinds, which look at their scene. The simulated rig (`--simulate`) and a rig file's
/// simulated camera both place these themselves, so a calibration runs unattended.
pub fn calibration_scene(
    plan: &Plan,
    camera_model: &CameraModel,
    band: polar_model::atmosphere::Band,
    width: u32,
    height: u32,
) -> Result<Option<SimScene>, SimError> {
    let unit_sensor = SensorModel::new(camera_model, &band)
        .map_err(|e| SimError::Input(format!("simulation.camera: {e}")))?;
    // Electrons per unit S0 radiance for an exposure, unpolarised, through the analyzer.
    let electrons_per_radiance = |exposure_us: f64| -> Result<f64, SimError> {
        let w = unit_sensor
            .intensities_from_stokes(&[0.0])
            .map_err(|e| SimError::Input(e.to_string()))?;
        Ok(w[(0, 0)] * unit_sensor.responsivity_e_per_s() * exposure_us * 1e-6)
    };
    match &plan.acquisition {
        Acquisition::CalibrateNoise(c) => {
            let longest = c.exposure_us.iter().copied().fold(0.0, f64::max);
            let l = 1.1 * camera_model.full_well_e / electrons_per_radiance(longest)?;
            Ok(Some(uniform(
                "integrating sphere",
                [l, 0.0, 0.0],
                width,
                height,
                band,
            )))
        }
        Acquisition::CalibrateAnalyzer(c) => {
            let d = 0.999;
            let two = 2.0 * c.reference_angle_deg.to_radians();
            let l = 0.6 * camera_model.full_well_e / (2.0 * electrons_per_radiance(c.exposure_us)?);
            Ok(Some(uniform(
                "reference polarizer",
                [l, l * d * two.cos(), l * d * two.sin()],
                width,
                height,
                band,
            )))
        }
        _ => Ok(None),
    }
}

/// The plan's simulated stage and camera fault profiles, checked (unknown knobs, rates
/// outside `[0, 1]`).
fn fault_profiles(plan: &Plan) -> Result<(FaultProfile, CameraFaults), SimError> {
    let sim = &plan.simulation;
    let stage = match &sim.stage_faults {
        Some(t) => {
            let text = toml::to_string(t)
                .map_err(|e| SimError::Input(format!("simulation.stage_faults: {e}")))?;
            FaultProfile::from_toml_str(&text)
                .map_err(|e| SimError::Input(format!("simulation.stage_faults: {e}")))?
        }
        None => FaultProfile::default(),
    };
    let camera: CameraFaults = match &sim.camera_faults {
        Some(t) => {
            let f: CameraFaults = t
                .clone()
                .try_into()
                .map_err(|e| SimError::Input(format!("simulation.camera_faults: {e}")))?;
            f.validate()
                .map_err(|e| SimError::Input(format!("simulation.camera_faults: {e}")))?;
            f
        }
        None => CameraFaults::default(),
    };
    Ok((stage, camera))
}

/// The plan's simulated stage (dialect, model, simulator) from the simulators' registry: at
/// `simulation.stage_deg_per_s` where the dialect offers a chosen speed, otherwise at the
/// real device's; an error names `simulation.stage` and what is allowed.
fn stage_simulator(
    plan: &Plan,
    faults: FaultProfile,
) -> Result<(&'static str, &'static str, Box<dyn Simulator>), SimError> {
    let sim = &plan.simulation;
    let (dialect, model) = crate::sim_stage::resolve(sim.stage.as_ref())
        .map_err(|e| SimError::Input(e.to_string()))?;
    let entry = crate::sim_stage::descriptor(dialect).ok_or_else(|| {
        SimError::Input(format!(
            "simulation.stage.dialect = {dialect:?} has no simulator"
        ))
    })?;
    let device = match entry.at_speed {
        Some(at_speed) => at_speed(model, sim.stage_deg_per_s, faults, sim.seed),
        None => (entry.build)(model, faults, sim.seed),
    }
    .ok_or_else(|| {
        SimError::Input(format!(
            "simulation.stage.model = {model:?}: the {dialect} simulators build no such rotator"
        ))
    })?;
    Ok((dialect, model, device))
}

/// The camera's trigger line wired to the stage's position-compare output, for a continuous
/// plan: a rising edge each time the stage's true angle crosses a whole multiple of
/// `interval_rad` (180 / N degrees) in the positive direction while the camera watches the
/// line. The continuous run arms the stage's pulses at exactly these positions (whole
/// multiples of the interval from the datum), so each edge is the exposure of the stage's
/// pulse at the same position; the edge comes from the true angle, so the exposure starts
/// where the analyzer really is when the pulse fires (up to the camera's line poll,
/// `polar_hil_mocks::camera::LINE_POLL`). The camera reads the line only while it waits for
/// an edge: a crossing while it exposes, reads out or is stopped is not seen (a busy camera
/// ignores a trigger), so reads more than [`LINE_GAP`] apart count no crossing between them.
pub fn compare_line(truth: polar_hil_mocks::serve::TruthHandle, interval_rad: f64) -> LineSource {
    let angle = truth.angle_source();
    // (time and wrapped angle of the last read, edges so far)
    let state = std::sync::Mutex::new((None::<(std::time::Instant, f64)>, 0u64));
    Arc::new(move || {
        let now = angle();
        let at = std::time::Instant::now();
        let Ok(mut guard) = state.lock() else {
            return 0;
        };
        let (last, edges) = &mut *guard;
        if let Some((then, before)) = *last {
            if at.duration_since(then) <= LINE_GAP {
                // Less than a half turn passes in LINE_GAP at any plan's speed (3600 deg/s).
                let step = polar_hal::signed_difference(now, before, polar_hal::TURN_RAD);
                let crossed =
                    ((before + step) / interval_rad).floor() - (before / interval_rad).floor();
                if step > 0.0 && crossed > 0.0 {
                    *edges += crossed as u64;
                }
            }
        }
        *last = Some((at, now));
        *edges
    })
}

/// The longest time between two reads of [`compare_line`] that still counts the crossings
/// between them. The camera polls every 50 us while it waits for an edge; the gap allows for
/// a loaded host that runs the polling thread late, and is far shorter than the pause between
/// two segments of a run (a stopped camera), whose crossings must not count.
pub const LINE_GAP: std::time::Duration = std::time::Duration::from_millis(20);

/// The run's handle on the simulated scene's light (lens cap and clouds).
pub fn scene_light(illumination: &polar_hil_mocks::camera::Illumination) -> SceneLight {
    let light = illumination.clone();
    Arc::new(move |factor| light.set(factor))
}

/// The adaptive target's material as a mask of the simulated scene (row-major), if the plan
/// names one; an error naming `adaptive.target.material` if the scene has no such material.
pub fn target_mask(plan: &Plan, scene: &SimScene) -> Result<Option<Vec<bool>>, SimError> {
    let Some(m) = plan.adaptive().and_then(|a| a.target.material.as_deref()) else {
        return Ok(None);
    };
    let k = scene.materials.iter().position(|x| x == m).ok_or_else(|| {
        SimError::Input(format!(
            "adaptive.target.material = {m:?} is not in the simulated scene: allowed one of {:?}",
            scene.materials
        ))
    })?;
    Ok(Some(
        scene.region.iter().map(|&r| usize::from(r) == k).collect(),
    ))
}

impl SimRig {
    /// Checks everything a simulated run of `plan` would refuse before it acquires anything
    /// (the stage, the scene and camera files, the fault profiles, the adaptive target's
    /// material),
    /// with the messages the run gives; [`Plan::check_frame`] checks the rest against the
    /// simulated frame. `plan check` calls it;
    /// [`SimRig::start_rig`] goes through the same functions.
    pub fn validate(plan: &Plan, plan_dir: &Path) -> Result<(), SimError> {
        crate::sim_stage::resolve(plan.simulation.stage.as_ref())
            .map_err(|e| SimError::Input(e.to_string()))?;
        fault_profiles(plan)?;
        let world = SimRig::world(plan, plan_dir)?;
        target_mask(plan, &world.scene)?;
        Ok(())
    }

    /// What the simulated camera sees for `plan` (files relative to `plan_dir`): the scene,
    /// the camera model and the sensor model, without starting anything.
    pub fn world(plan: &Plan, plan_dir: &Path) -> Result<SimWorld, SimError> {
        let sim = &plan.simulation;
        let camera_text = match &sim.camera {
            Some(name) => read_relative(plan_dir, name, "simulation.camera")?,
            None => DEFAULT_CAMERA.to_string(),
        };
        // A file's error names the file: its line and column are in that file, not the plan.
        let named = |field: &str, file: &Option<String>| match file {
            Some(name) => format!("{field} = {}", plan_dir.join(name).display()),
            None => format!("{field} (the built-in example)"),
        };
        let camera_model = CameraModel::from_toml_str(&camera_text).map_err(|e| {
            SimError::Input(format!("{}: {e}", named("simulation.camera", &sim.camera)))
        })?;
        let scene_text = match &sim.scene {
            Some(name) => read_relative(plan_dir, name, "simulation.scene")?,
            None => DEFAULT_SCENE.to_string(),
        };
        let scene_base = match &sim.scene {
            Some(name) => plan_dir
                .join(name)
                .parent()
                .map(Path::to_path_buf)
                .unwrap_or_default(),
            None => plan_dir.to_path_buf(),
        };
        let scene_file = Scene::from_toml_str_with_files(&scene_text, &|name| {
            std::fs::read_to_string(scene_base.join(name)).map_err(|e| e.to_string())
        })
        .map_err(|e| SimError::Input(format!("{}: {e}", named("simulation.scene", &sim.scene))))?;
        let band = scene_file.spec.band.clone();
        let (w, h) = (sim.width, sim.height);
        let scene = match calibration_scene(plan, &camera_model, band, w, h)? {
            Some(scene) => scene,
            None => {
                let names: Vec<String> = scene_file
                    .materials
                    .iter()
                    .map(|m| m.name.clone())
                    .collect();
                SimScene::render(
                    &scene_file.spec,
                    &scene_file.materials,
                    &Layout::panels_on_ground(&names),
                    w,
                    h,
                    1e-3,
                    sim.seed,
                )
                .map_err(|e| SimError::Input(format!("simulation.scene: {e}")))?
            }
        };
        let sensor = SensorModel::new(&camera_model, &scene.band)
            .map_err(|e| SimError::Input(format!("simulation.camera: {e}")))?;
        Ok(SimWorld {
            scene: Arc::new(scene),
            camera_model,
            sensor,
            scene_file,
        })
    }

    /// Starts the stage simulator on a pseudo-terminal at `link_dir/stage` and builds the
    /// camera for `plan` (files relative to `plan_dir`), drawing its noise from
    /// `noise_stream` ([`polar_engine::run::noise_stream`] of the run directory, so that a resumed
    /// process never repeats an earlier process's draws). Returns the rig and the camera,
    /// running on its own thread.
    pub fn start(
        plan: &Plan,
        plan_dir: &Path,
        link_dir: &Path,
        noise_stream: u64,
    ) -> Result<(SimRig, ThreadedCamera), SimError> {
        let sim = &plan.simulation;
        let SimWorld {
            scene,
            camera_model,
            sensor: _,
            scene_file,
        } = SimRig::world(plan, plan_dir)?;
        let (stage_faults, camera_faults) = fault_profiles(plan)?;
        let (stage_dialect, stage_model, device) = stage_simulator(plan, stage_faults)?;
        std::fs::create_dir_all(link_dir)
            .map_err(|e| SimError::Stage(format!("{}: {e}", link_dir.display())))?;
        let link = link_dir.join("stage");
        let server = SimServer::pty(device, stage_faults, sim.seed, &link)
            .map_err(|e| SimError::Stage(format!("pseudo-terminal {}: {e}", link.display())))?;
        let cam = SimCamera::new(
            SimCameraConfig {
                id: "sim-camera".into(),
                camera: camera_model.clone(),
                scene: Arc::clone(&scene),
                max_frame_rate_hz: 200.0,
                faults: camera_faults,
                seed: sim.seed,
                noise_stream,
            },
            server.truth_handle().angle_source(),
        )
        .map_err(|e| SimError::Camera(e.to_string()))?;
        let mut cam = cam;
        // Only an encoder-triggered plan has the stage's compare output wired to the camera:
        // a timestamps plan simulates a camera the stage does not trigger.
        if let Some(c) = plan
            .continuous()
            .filter(|c| plan.kind() == PlanKind::Continuous && c.trigger == TriggerSource::Encoder)
        {
            cam.wire_line(compare_line(
                server.truth_handle(),
                c.interval_deg().to_radians(),
            ));
        }
        let sensor = cam.sensor().clone();
        let illumination = cam.illumination();
        let exposures = cam.exposures();
        let camera = ThreadedCamera::spawn(cam, ThreadPolicy::default())
            .map_err(|e| SimError::Camera(e.to_string()))?;
        Ok((
            SimRig {
                server,
                link,
                stage_dialect,
                stage_model,
                scene,
                camera_model,
                sensor,
                illumination,
                exposures,
                scene_file: Some(scene_file),
            },
            camera,
        ))
    }

    /// Connects the stage's dialect's real driver (its registry constructor, line settings
    /// and policy) to the simulated stage (homes it).
    pub async fn connect_stage(&self) -> Result<AnyRotator, DeviceError> {
        let not_found = |what: &str| {
            DeviceError::new(
                polar_hal::ErrorKind::OutOfRange,
                self.stage_dialect,
                format!(
                    "simulation.stage.dialect = {:?} has no {what} in the dialects' registry: allowed {}",
                    self.stage_dialect,
                    registry::names()
                ),
            )
        };
        let d = registry::find(self.stage_dialect).ok_or_else(|| not_found("driver"))?;
        let connect = d.rotator.ok_or_else(|| not_found("rotator driver"))?;
        connect(
            d.connector(&self.link.to_string_lossy()),
            d.default_address(),
            (d.policy)(),
        )
        .await
    }

    /// Starts the rig for `plan` and connects the real driver to the stage: the engine's
    /// [`Rig`](polar_engine::run::Rig) (the analyzer approached from the positive side with 0.5 deg
    /// of overshoot, which takes up the simulated stage's 0.05 deg backlash) and the rig.
    pub async fn start_rig(
        plan: &Plan,
        plan_dir: &Path,
        link_dir: &Path,
        noise_stream: u64,
    ) -> Result<(SimRig, EngineRig<OnRotator<AnyRotator>, ThreadedCamera>), SimError> {
        let (rig, camera) = SimRig::start(plan, plan_dir, link_dir, noise_stream)?;
        // The link may be faulty (an unplug during the handshake): a few tries, as a person
        // would replug and retry.
        let mut tries = 0;
        let stage = loop {
            match rig.connect_stage().await {
                Ok(s) => break s,
                Err(e) if tries < 5 => {
                    tries += 1;
                    tracing::warn!("connecting the simulated stage (try {tries}): {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
                }
                Err(e) => return Err(SimError::Stage(e.to_string())),
            }
        };
        let target_mask = target_mask(plan, &rig.scene)?;
        let stage_json = if plan.simulation.stage.is_none() {
            serde_json::json!({
                "dialect": rig.stage_dialect,
                "model": "simulated native rotator (144000 counts/turn, 0.05 deg backlash)",
                "link": rig.link.display().to_string(),
            })
        } else {
            serde_json::json!({
                "dialect": rig.stage_dialect,
                "model": rig.stage_model,
                "simulator": rig.server.describe(),
                "driver": polar_hal::Rotator::info(&stage).model,
                "link": rig.link.display().to_string(),
            })
        };
        let devices = serde_json::json!({
            "kind": "simulated",
            "plan_dir": plan_dir.display().to_string(),
            "stage": stage_json,
            "camera": {
                "model": rig.camera_model.name,
                "width": rig.scene.width,
                "height": rig.scene.height,
            },
            "scene_materials": rig.scene.materials,
        });
        let engine_rig = EngineRig {
            analyzer: OnRotator {
                rotator: stage,
                zero_offset_rad: 0.0,
                approach: Approach::Positive,
                overshoot_rad: 0.5f64.to_radians(),
            },
            camera,
            camera_model: rig.camera_model.clone(),
            sensor: rig.sensor.clone(),
            illumination: Some(scene_light(&rig.illumination)),
            target_mask,
            sun_deg: rig.sun_deg(plan),
            devices,
            spin_acceleration_rad_per_s2: crate::sim_stage::stage_limits(&plan.simulation)
                .map_err(|e| SimError::Input(e.to_string()))?
                .map(|l| l.acceleration_rad_per_s2),
        };
        Ok((rig, engine_rig))
    }

    /// The target mask of a material of the scene (row-major), or `None` if the scene has
    /// no such material.
    pub fn material_mask(&self, material: &str) -> Option<Vec<bool>> {
        let k = self.scene.materials.iter().position(|m| m == material)?;
        Some(
            self.scene
                .region
                .iter()
                .map(|&r| usize::from(r) == k)
                .collect(),
        )
    }

    /// The sun of the simulated scene (zenith, azimuth, degrees), which its frames record;
    /// `None` for the calibration sources (a uniform light has no sun).
    pub fn sun_deg(&self, plan: &Plan) -> Option<(f64, f64)> {
        match plan.kind() {
            PlanKind::CalibrateNoise | PlanKind::CalibrateAnalyzer => None,
            _ => self
                .scene_file
                .as_ref()
                .map(|s| (s.spec.sun_zenith_deg, s.spec.sun_azimuth_deg)),
        }
    }

    /// The full frame.
    pub fn roi(&self) -> Roi {
        Roi::full(self.scene.width, self.scene.height)
    }

    /// Stops the stage simulator.
    pub async fn shutdown(self) {
        self.server.shutdown().await;
    }
}
