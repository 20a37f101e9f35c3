//! The simulated camera: every frame rendered from the model (`ARCHITECTURE.md`,
//! "Simulated devices").
//!
//! * [`SimScene`]: the scene as the camera sees it. It is a layout of regions (panels of paint,
//!   glass or metal on asphalt and grass), each pixel holding a Stokes radiance. Each region takes
//!   the mean of its material from the scene model (`polar_model::scene::evaluate` for the
//!   scene's sun, sky, atmosphere and view geometry). Each pixel adds a seeded draw from that
//!   material's covariance (geometry and texture variation, MODEL.md section 11), so the
//!   per-pixel texture stays fixed from frame to frame. It is the ground truth the tests check
//!   against.
//! * [`SimCamera`]: a [`BlockingCamera`].
//!   - It reads the analyzer's true angle from the simulated stage (an [`AngleSource`], usually
//!     [`crate::serve::TruthHandle::angle_source`]) through each exposure (every 1 ms).
//!   - It integrates the analyzer's row along the path sampled through the exposure
//!     ([`SimCamera::mean_electrons_along`]), so a move or a spin during the exposure smears
//!     the frame as it would on a real camera.
//!   - It turns the radiance into mean photo-electrons with the sensor model (camera equation,
//!     real analyzer, fore-optics: `polar_model::sensor::SensorModel`).
//!   - It draws the frame with `polar_model::montecarlo::expose_pixels`: Poisson electrons and
//!     dark electrons, full well, read noise, gain, rounding and the ADC's range.
//!   - The analog gain is in dB and scales the system gain `K` by `10^(gain_db / 20)`.
//! * A hardware trigger input ([`SimCamera::wire_line`], GenICam `TriggerSource = Line`):
//!   with trigger mode hardware, each rising edge of the wired [`LineSource`] starts an
//!   exposure (of the set exposure time), which integrates the analyzer's true path as any
//!   other. The camera polls the line every [`LINE_POLL`], so an exposure starts up to about
//!   that much after its edge; an edge that arrives while the sensor is exposing is dropped
//!   (GenICam `TriggerOverlap = Off`), and edges before [`BlockingCamera::start`] are ignored.
//! * [`CameraFaults`]: dropped frames, truncated frames, stalls (timeouts), a stuck frame
//!   (the same pixels again under a new id) and a disconnect, all seeded.

use crate::faults::Dice;
use crate::serve::TruthHandle;
use crate::simulator::Truth;
use nalgebra::{Matrix3, Vector3};
use polar_hal::{
    BlockingCamera, CameraInfo, DeviceError, ErrorKind, ExposureEndHook, Frame, GainUnit, Grabbed,
    PixelFormat, Roi, TriggerMode,
};
use polar_model::atmosphere::Band;
use polar_model::error::ModelError;
use polar_model::scene::{self, SceneMaterial, SceneSpec};
use polar_model::sensor::{Camera, SensorModel};
use polar_model::stats::psd_factor;
use serde::Deserialize;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// Where the analyzer is, radians (the simulated stage's true output angle).
pub type AngleSource = Arc<dyn Fn() -> f64 + Send + Sync>;

/// A trigger input line: the number of rising edges it has carried so far (never decreasing),
/// e.g. a stage's position-compare output.
pub type LineSource = Arc<dyn Fn() -> u64 + Send + Sync>;

/// How often a camera in hardware-trigger mode looks at its line.
pub const LINE_POLL: Duration = Duration::from_micros(50);

impl TruthHandle {
    /// The stage's true angle as an [`AngleSource`] (a wheel or slider reads as angle 0).
    pub fn angle_source(&self) -> AngleSource {
        let handle = self.clone();
        Arc::new(move || match handle.truth() {
            Truth::Angle { output_rad, .. } => output_rad,
            Truth::Slot { .. } => 0.0,
        })
    }
}

/// Errors building the simulated scene or camera.
#[derive(Debug, thiserror::Error)]
pub enum SimCameraError {
    /// The model refused an input (names the field).
    #[error(transparent)]
    Model(#[from] ModelError),
    /// A layout or configuration value out of range.
    #[error("{field} = {value} is invalid: {allowed}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Its value.
        value: String,
        /// What is allowed.
        allowed: String,
    },
}

/// One region of the layout: a material over a rectangle given as fractions of the frame.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Region {
    /// The material's name in the scene.
    pub material: String,
    /// `[x0, y0, x1, y1]`, fractions of the width and height, `0 <= x0 < x1 <= 1`.
    pub rect: [f64; 4],
}

/// Regions drawn in order, later over earlier; the first should cover the frame.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layout {
    /// The regions.
    pub regions: Vec<Region>,
}

impl Layout {
    /// Panels on the ground for the scene's materials.
    /// - The background is `asphalt` over the frame, with a band of `grass` along the top if
    ///   the scene has them. Otherwise the last material is the background.
    /// - Every other material is a panel, in file order, side by side across the middle of the
    ///   frame.
    pub fn panels_on_ground(materials: &[String]) -> Layout {
        let has = |n: &str| materials.iter().any(|m| m == n);
        let mut regions = Vec::new();
        let mut ground: Vec<&str> = Vec::new();
        if has("asphalt") {
            ground.push("asphalt");
            regions.push(Region {
                material: "asphalt".into(),
                rect: [0.0, 0.0, 1.0, 1.0],
            });
            if has("grass") {
                ground.push("grass");
                regions.push(Region {
                    material: "grass".into(),
                    rect: [0.0, 0.0, 1.0, 0.25],
                });
            }
        } else if let Some(last) = materials.last() {
            ground.push(last);
            regions.push(Region {
                material: last.clone(),
                rect: [0.0, 0.0, 1.0, 1.0],
            });
        }
        let panels: Vec<&String> = materials
            .iter()
            .filter(|m| !ground.contains(&m.as_str()))
            .collect();
        let n = panels.len().max(1) as f64;
        for (i, m) in panels.into_iter().enumerate() {
            let (x0, x1) = (i as f64 / n, (i as f64 + 1.0) / n);
            let margin = 0.15 * (x1 - x0);
            regions.push(Region {
                material: m.clone(),
                rect: [x0 + margin, 0.4, x1 - margin, 0.85],
            });
        }
        Layout { regions }
    }
}

/// The scene as the camera sees it: per-pixel Stokes radiance (W m^-2 sr^-1, camera frame) over
/// the full sensor.
#[derive(Debug, Clone, PartialEq)]
pub struct SimScene {
    /// Sensor width, pixels.
    pub width: u32,
    /// Sensor height, pixels.
    pub height: u32,
    /// Row-major per-pixel Stokes radiance `[S0, S1, S2]`.
    pub stokes: Vec<[f64; 3]>,
    /// Row-major region index per pixel (into `materials`).
    pub region: Vec<u8>,
    /// The materials' names, by region index.
    pub materials: Vec<String>,
    /// Each material's mean Stokes radiance from the scene model.
    pub material_means: Vec<[f64; 3]>,
    /// The band the scene was evaluated in.
    pub band: Band,
}

impl SimScene {
    /// Evaluates the scene's materials at relative tolerance `tol`, then draws the
    /// `width x height` layout with seeded per-pixel variation. Errors name the field: an
    /// unknown material, a bad rectangle, a size of 0 or over 4096.
    pub fn render(
        spec: &SceneSpec,
        materials: &[SceneMaterial],
        layout: &Layout,
        width: u32,
        height: u32,
        tol: f64,
        seed: u64,
    ) -> Result<SimScene, SimCameraError> {
        for (field, v) in [("width", width), ("height", height)] {
            if !(1..=4096).contains(&v) {
                return Err(SimCameraError::Invalid {
                    field,
                    value: v.to_string(),
                    allowed: "1 to 4096 pixels".into(),
                });
            }
        }
        if layout.regions.is_empty() || layout.regions.len() > 255 {
            return Err(SimCameraError::Invalid {
                field: "layout.regions",
                value: layout.regions.len().to_string(),
                allowed: "1 to 255 regions".into(),
            });
        }
        let names: Vec<String> = materials.iter().map(|m| m.name.clone()).collect();
        let mut used: Vec<usize> = Vec::new();
        for r in &layout.regions {
            let Some(i) = names.iter().position(|n| *n == r.material) else {
                return Err(SimCameraError::Invalid {
                    field: "layout.regions.material",
                    value: r.material.clone(),
                    allowed: format!("a material of the scene: {}", names.join(", ")),
                });
            };
            let [x0, y0, x1, y1] = r.rect;
            let ok = [x0, y0, x1, y1].iter().all(|v| v.is_finite())
                && 0.0 <= x0
                && x0 < x1
                && x1 <= 1.0
                && 0.0 <= y0
                && y0 < y1
                && y1 <= 1.0;
            if !ok {
                return Err(SimCameraError::Invalid {
                    field: "layout.regions.rect",
                    value: format!("{:?}", r.rect),
                    allowed: "[x0, y0, x1, y1] with 0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1".into(),
                });
            }
            if !used.contains(&i) {
                used.push(i);
            }
        }
        let chosen: Vec<SceneMaterial> = used.iter().map(|&i| materials[i].clone()).collect();
        let results = scene::evaluate(spec, &chosen, tol)?;
        let factors: Vec<Matrix3<f64>> = results
            .iter()
            .map(|r| psd_factor(&(0.5 * (r.cov + r.cov.transpose()))))
            .collect();
        let means: Vec<Vector3<f64>> = results.iter().map(|r| r.mean.0).collect();

        let (w, h) = (width as usize, height as usize);
        let mut region = vec![0u8; w * h];
        for r in &layout.regions {
            let idx = chosen
                .iter()
                .position(|m| m.name == r.material)
                .unwrap_or_default() as u8;
            let [x0, y0, x1, y1] = r.rect;
            let (c0, c1) = (
                (x0 * w as f64).round() as usize,
                (x1 * w as f64).round() as usize,
            );
            let (r0, r1) = (
                (y0 * h as f64).round() as usize,
                (y1 * h as f64).round() as usize,
            );
            for row in r0..r1.min(h) {
                for col in c0..c1.min(w) {
                    region[row * w + col] = idx;
                }
            }
        }
        let mut dice = Dice::new(seed);
        let stokes = region
            .iter()
            .map(|&k| {
                let k = usize::from(k);
                let z = Vector3::new(dice.normal(), dice.normal(), dice.normal());
                let mut s = means[k] + factors[k] * z;
                // A physical Stokes vector: S0 >= 0 and DoLP <= 1.
                s[0] = s[0].max(0.0);
                let p = s[1].hypot(s[2]);
                if p > s[0] && p > 0.0 {
                    s[1] *= s[0] / p;
                    s[2] *= s[0] / p;
                }
                [s[0], s[1], s[2]]
            })
            .collect();
        Ok(SimScene {
            width,
            height,
            stokes,
            region,
            materials: chosen.into_iter().map(|m| m.name).collect(),
            material_means: means.iter().map(|m| [m[0], m[1], m[2]]).collect(),
            band: spec.band.clone(),
        })
    }
}

/// The simulated camera's fault knobs (TOML: every field optional; all off by default).
/// Probabilities are per frame, in `[0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraFaults {
    /// A frame is never delivered (its id is skipped).
    pub drop_frame: f64,
    /// A frame arrives truncated (an incomplete buffer).
    pub truncate_frame: f64,
    /// The camera stops delivering for `stall_s` (grabs time out).
    pub stall: f64,
    /// How long a stall lasts, seconds, `[0, 60]` (default 0.5).
    pub stall_s: f64,
    /// A frame repeats the previous frame's pixels under a new id (a stuck sensor or buffer).
    pub stuck_frame: f64,
    /// The camera disconnects after this many frames (0 = never).
    pub disconnect_after_frames: u64,
}

impl Default for CameraFaults {
    fn default() -> Self {
        CameraFaults {
            drop_frame: 0.0,
            truncate_frame: 0.0,
            stall: 0.0,
            stall_s: 0.5,
            stuck_frame: 0.0,
            disconnect_after_frames: 0,
        }
    }
}

impl CameraFaults {
    /// Checks every knob's range; the error names the field.
    pub fn validate(&self) -> Result<(), SimCameraError> {
        for (field, p) in [
            ("drop_frame", self.drop_frame),
            ("truncate_frame", self.truncate_frame),
            ("stall", self.stall),
            ("stuck_frame", self.stuck_frame),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(SimCameraError::Invalid {
                    field,
                    value: p.to_string(),
                    allowed: "a probability in [0, 1]".into(),
                });
            }
        }
        if !(0.0..=60.0).contains(&self.stall_s) {
            return Err(SimCameraError::Invalid {
                field: "stall_s",
                value: self.stall_s.to_string(),
                allowed: "[0, 60] s".into(),
            });
        }
        Ok(())
    }
}

/// How the simulated camera is built.
#[derive(Debug, Clone)]
pub struct SimCameraConfig {
    /// The id it reports.
    pub id: String,
    /// The camera (detector, optics, analyzer) as the sensor model knows it.
    pub camera: Camera,
    /// The scene it looks at (its size is the sensor's).
    pub scene: Arc<SimScene>,
    /// Free-run frame rate limit, Hz, `(0, 1000]`.
    pub max_frame_rate_hz: f64,
    /// Fault knobs.
    pub faults: CameraFaults,
    /// Seed of the noise and the faults.
    pub seed: u64,
    /// The noise stream: frame `id` of stream `k` draws its noise from `(seed, k, id)`. A
    /// process that continues a run (whose frame ids restart at 0) takes a stream no earlier
    /// process of the run used, so no draw repeats within a run; 0 for a new run.
    pub noise_stream: u64,
}

/// An exposure under way.
#[derive(Debug, Clone)]
struct Exposing {
    start: Instant,
    end: Instant,
    /// The analyzer's true angle sampled through the exposure: (seconds from its start, angle).
    path: Vec<(f64, f64)>,
}

/// How often the analyzer's angle is sampled during an exposure: often enough that the stage
/// turns far less than 90 deg between samples at any speed it reaches (2 turns/s: 0.7 deg).
const PATH_SAMPLE: Duration = Duration::from_millis(1);

/// The simulated camera (a [`BlockingCamera`]; wrap it in `polar_hal::camera_thread` for
/// the async [`polar_hal::Camera`]).
pub struct SimCamera {
    config: SimCameraConfig,
    sensor: SensorModel,
    angle: AngleSource,
    info: CameraInfo,
    exposure_us: f64,
    gain_db: f64,
    format: PixelFormat,
    roi: Roi,
    trigger_mode: TriggerMode,
    streaming: bool,
    triggers: u32,
    next_start: Instant,
    exposing: Option<Exposing>,
    stalled_until: Option<Instant>,
    frame_id: u64,
    last_pixels: Option<Vec<u16>>,
    disconnected: bool,
    dice: Dice,
    /// The device clock's zero (device timestamps are exposure ends since it).
    epoch: Instant,
    /// The scene's illumination, shared with whoever darkens it.
    illumination: Illumination,
    /// Told each exposure's end, before the frame is drawn.
    exposure_end: Option<ExposureEndHook>,
    /// Each exposure's true start and end angles.
    exposures: ExposureLog,
    /// The trigger input, if wired.
    line: Option<LineSource>,
    /// Edges of the line already acted on (or ignored).
    line_seen: u64,
}

/// A handle on the simulated scene's illumination: a factor on every pixel's radiance, 1 by
/// default. A lens cap is 0 (dark frames); a passing cloud is below 1. Clones share the value;
/// a change applies to the exposures that end after it.
#[derive(Debug, Clone)]
pub struct Illumination(Arc<std::sync::atomic::AtomicU64>);

impl Illumination {
    /// Full illumination.
    pub fn new() -> Illumination {
        Illumination(Arc::new(std::sync::atomic::AtomicU64::new(1f64.to_bits())))
    }

    /// The factor.
    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(std::sync::atomic::Ordering::Relaxed))
    }

    /// Sets the factor (clamped to `[0, 10]`; not a number counts as 0).
    pub fn set(&self, factor: f64) {
        let f = if factor.is_nan() {
            0.0
        } else {
            factor.clamp(0.0, 10.0)
        };
        self.0
            .store(f.to_bits(), std::sync::atomic::Ordering::Relaxed);
    }
}

impl Default for Illumination {
    fn default() -> Self {
        Illumination::new()
    }
}

/// What an exposure truly saw: the analyzer's true angle at its start and its end, as the
/// camera sampled them (the simulator's ground truth, for tests that judge recorded spans).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExposureTruth {
    /// The frame's id.
    pub frame_id: u64,
    /// The analyzer's true angle when the exposure started, radians.
    pub start_rad: f64,
    /// Its true angle when the exposure ended, radians.
    pub end_rad: f64,
}

/// The truth of the last [`EXPOSURE_LOG_LEN`] exposures, shared with whoever judges them.
#[derive(Debug, Clone, Default)]
pub struct ExposureLog(Arc<std::sync::Mutex<std::collections::VecDeque<ExposureTruth>>>);

/// Exposures an [`ExposureLog`] keeps (older ones leave it).
pub const EXPOSURE_LOG_LEN: usize = 100_000;

impl ExposureLog {
    fn push(&self, truth: ExposureTruth) {
        let mut log = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if log.len() == EXPOSURE_LOG_LEN {
            log.pop_front();
        }
        log.push_back(truth);
    }

    /// The truth of frame `frame_id`, while the log holds it.
    pub fn get(&self, frame_id: u64) -> Option<ExposureTruth> {
        let log = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        log.iter().rev().find(|t| t.frame_id == frame_id).copied()
    }
}

/// The analog gain range, dB.
pub const GAIN_RANGE_DB: [f64; 2] = [0.0, 24.0];

impl SimCamera {
    /// A simulated camera looking at `config.scene` through the analyzer at `angle()`. Errors
    /// name the field (the camera's, the scene's band, the frame rate, a fault knob).
    pub fn new(config: SimCameraConfig, angle: AngleSource) -> Result<SimCamera, SimCameraError> {
        config.faults.validate()?;
        if !(config.max_frame_rate_hz > 0.0 && config.max_frame_rate_hz <= 1000.0) {
            return Err(SimCameraError::Invalid {
                field: "max_frame_rate_hz",
                value: config.max_frame_rate_hz.to_string(),
                allowed: "(0, 1000] Hz".into(),
            });
        }
        let sensor = SensorModel::new(&config.camera, &config.scene.band)?;
        let bits = config.camera.bit_depth;
        let mut formats = vec![PixelFormat::Mono8];
        if bits == 12 {
            formats.push(PixelFormat::Mono12);
        }
        if bits > 8 {
            formats.push(PixelFormat::Mono16);
        }
        let native = match bits {
            8 => PixelFormat::Mono8,
            12 => PixelFormat::Mono12,
            _ => PixelFormat::Mono16,
        };
        let info = CameraInfo {
            id: config.id.clone(),
            vendor: "polarimeter".into(),
            model: format!("simulated {}", config.camera.name),
            serial: format!("SIM{:08X}", config.seed as u32),
            sensor_width: config.scene.width,
            sensor_height: config.scene.height,
            exposure_range_us: [10.0, 10_000_000.0],
            gain_range: GAIN_RANGE_DB,
            gain_unit: GainUnit::Decibel,
            formats,
        };
        let roi = Roi::full(config.scene.width, config.scene.height);
        let dice = Dice::new(config.seed ^ 0x5eed_ca3e);
        Ok(SimCamera {
            sensor,
            angle,
            info,
            exposure_us: 10_000.0,
            gain_db: 0.0,
            format: native,
            roi,
            trigger_mode: TriggerMode::FreeRun,
            streaming: false,
            triggers: 0,
            next_start: Instant::now(),
            exposing: None,
            stalled_until: None,
            frame_id: 0,
            last_pixels: None,
            disconnected: false,
            dice,
            epoch: Instant::now(),
            illumination: Illumination::new(),
            exposure_end: None,
            exposures: ExposureLog::default(),
            line: None,
            line_seen: 0,
            config,
        })
    }

    /// Wires the hardware trigger input to `line` (GenICam `TriggerSource = Line`): trigger
    /// mode hardware becomes available (module docs).
    pub fn wire_line(&mut self, line: LineSource) {
        self.line = Some(line);
    }

    /// The ground truth.
    pub fn scene(&self) -> &Arc<SimScene> {
        &self.config.scene
    }

    /// The handle on the scene's illumination (lens cap, clouds).
    pub fn illumination(&self) -> Illumination {
        self.illumination.clone()
    }

    /// The handle on the exposures' truth (each frame's true start and end angles).
    pub fn exposures(&self) -> ExposureLog {
        self.exposures.clone()
    }

    /// The sensor model the frames are drawn from.
    pub fn sensor(&self) -> &SensorModel {
        &self.sensor
    }

    /// The camera with the analog gain applied (`K` scaled by `10^(gain_db / 20)`).
    pub fn camera_at_gain(&self, gain_db: f64) -> Camera {
        let mut c = self.config.camera.clone();
        c.gain_dn_per_e *= 10f64.powf(gain_db / 20.0);
        c
    }

    /// Mean photo-electrons of each pixel of `roi` (row-major) for an exposure of
    /// `exposure_us` during which the analyzer turns at constant speed from `psi_rad` to
    /// `psi_end_rad` (equal for a still analyzer): `G rbar^T S`, `rbar` the span's average row
    /// ([`SimCamera::span_row`]), `G` the camera equation's electrons per radiance (MODEL.md
    /// section 6), clamped at 0.
    pub fn mean_electrons(
        &self,
        roi: Roi,
        psi_rad: f64,
        psi_end_rad: f64,
        exposure_us: f64,
    ) -> Result<Vec<f64>, SimCameraError> {
        let row = self.span_row(psi_rad, psi_end_rad)?;
        Ok(self.electrons_for_row(roi, row, exposure_us))
    }

    /// The camera's measurement row (real analyzer and fore-optics) averaged over an analyzer
    /// turning at constant speed from `psi_rad` to `psi_end_rad`. The row is
    /// `A + B cos 2psi + C sin 2psi`, so its average is `A + sinc(D) (B cos 2psi_c + C sin
    /// 2psi_c)` (`polar_model::span`), with `A` and the modulated part read off the rows at the
    /// centre `psi_c` and at `psi_c + 90 deg`.
    pub fn span_row(&self, psi_rad: f64, psi_end_rad: f64) -> Result<[f64; 3], SimCameraError> {
        let centre = 0.5 * (psi_rad + psi_end_rad);
        let w = self
            .sensor
            .intensities_from_stokes(&[centre, centre + 0.5 * std::f64::consts::PI])?;
        let factor = polar_model::span::sinc(psi_end_rad - psi_rad);
        Ok(std::array::from_fn(|j| {
            let (a, m) = (0.5 * (w[(0, j)] + w[(1, j)]), 0.5 * (w[(0, j)] - w[(1, j)]));
            a + factor * m
        }))
    }

    /// Mean photo-electrons as [`SimCamera::mean_electrons`], for an analyzer path sampled as
    /// `(time, angle)` pairs through the exposure (any time unit; at least one sample): the
    /// time-weighted average of the span rows between consecutive samples, each angle
    /// unwrapped modulo 180 deg against the previous one (the row's period), so the samples
    /// must be less than 90 deg apart.
    pub fn mean_electrons_along(
        &self,
        roi: Roi,
        path: &[(f64, f64)],
        exposure_us: f64,
    ) -> Result<Vec<f64>, SimCameraError> {
        let half_turn = std::f64::consts::PI;
        let mut row = [0.0; 3];
        let mut total = 0.0;
        let mut previous: Option<(f64, f64)> = None;
        for &(t, psi) in path {
            let psi = match previous {
                Some((_, last)) => last + polar_hal::signed_difference(psi, last, half_turn),
                None => psi,
            };
            if let Some((t0, psi0)) = previous {
                let dt = (t - t0).max(0.0);
                let r = self.span_row(psi0, psi)?;
                row.iter_mut().zip(r).for_each(|(acc, v)| *acc += dt * v);
                total += dt;
            }
            previous = Some((t, psi));
        }
        if total <= 0.0 {
            let psi = previous.map_or(0.0, |(_, p)| p);
            row = self.span_row(psi, psi)?;
            total = 1.0;
        }
        Ok(self.electrons_for_row(roi, row.map(|v| v / total), exposure_us))
    }

    /// `G row^T S` for each pixel of `roi`, clamped at 0.
    fn electrons_for_row(&self, roi: Roi, row: [f64; 3], exposure_us: f64) -> Vec<f64> {
        let g = self.sensor.responsivity_e_per_s() * exposure_us * 1e-6;
        let row = row.map(|v| v * g);
        let scene = &self.config.scene;
        let mut out = Vec::with_capacity(roi.pixels());
        for y in roi.y..roi.y + roi.height {
            let base = y as usize * scene.width as usize;
            for x in roi.x..roi.x + roi.width {
                let s = scene.stokes[base + x as usize];
                out.push((row[0] * s[0] + row[1] * s[1] + row[2] * s[2]).max(0.0));
            }
        }
        out
    }

    /// Waits for the line's next rising edge until `deadline`, polling every [`LINE_POLL`]:
    /// the time it was seen, or `None`. Edges that came while the sensor was busy are
    /// dropped (only the latest starts an exposure).
    fn wait_edge(&mut self, deadline: Instant) -> Option<Instant> {
        let line = self.line.clone()?;
        loop {
            let edges = line();
            if edges > self.line_seen {
                self.line_seen = edges;
                return Some(Instant::now());
            }
            let now = Instant::now();
            if now >= deadline {
                return None;
            }
            std::thread::sleep(LINE_POLL.min(deadline - now));
        }
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError::new(kind, &self.info.id, message)
    }

    fn check_stopped(&self, what: &str) -> Result<(), DeviceError> {
        if self.streaming {
            Err(self.error(
                ErrorKind::Busy,
                format!("{what} can only be changed while stopped"),
            ))
        } else {
            Ok(())
        }
    }

    /// Draws the frame whose exposure just ended.
    fn finish(&mut self, mut started: Exposing) -> Result<Grabbed, DeviceError> {
        // What the sensor saw is fixed when the exposure ends; only then is the end reported,
        // so a move started on the report cannot reach this frame.
        let end_s = started
            .end
            .saturating_duration_since(started.start)
            .as_secs_f64();
        started.path.push((end_s, (self.angle)()));
        let light = self.illumination.get();
        let id = self.frame_id;
        self.frame_id += 1;
        self.exposures.push(ExposureTruth {
            frame_id: id,
            start_rad: started.path.first().map_or(f64::NAN, |p| p.1),
            end_rad: started.path.last().map_or(f64::NAN, |p| p.1),
        });
        if let Some(hook) = &self.exposure_end {
            hook(id);
        }
        let faults = self.config.faults;
        if faults.disconnect_after_frames > 0 && id >= faults.disconnect_after_frames {
            self.disconnected = true;
            return Err(self.error(ErrorKind::Disconnected, "the camera went away (fault)"));
        }
        if self.dice.chance(faults.stall) {
            self.stalled_until = Some(Instant::now() + Duration::from_secs_f64(faults.stall_s));
            return Ok(Grabbed::Nothing);
        }
        if self.dice.chance(faults.drop_frame) {
            return Ok(Grabbed::Nothing);
        }
        let truncated = self.dice.chance(faults.truncate_frame);
        let stuck = self.dice.chance(faults.stuck_frame) && self.last_pixels.is_some();
        let pixels = match (stuck, &self.last_pixels) {
            (true, Some(last)) => last.clone(),
            _ => {
                let mut electrons = self
                    .mean_electrons_along(self.roi, &started.path, self.exposure_us)
                    .map_err(|e| self.error(ErrorKind::Other, e.to_string()))?;
                if light != 1.0 {
                    electrons.iter_mut().for_each(|e| *e *= light);
                }
                let camera = self.camera_at_gain(self.gain_db);
                let seed = noise_seed(self.config.seed, self.config.noise_stream, id);
                let raw = polar_model::montecarlo::expose_pixels(
                    &camera,
                    &electrons,
                    self.exposure_us * 1e-6,
                    seed,
                )
                .map_err(|e| self.error(ErrorKind::Other, e.to_string()))?;
                let shift = self.config.camera.bit_depth as i32 - self.format.bits() as i32;
                raw.into_iter()
                    .map(|v| {
                        if shift >= 0 {
                            v >> shift
                        } else {
                            v << (-shift)
                        }
                    })
                    .collect()
            }
        };
        if truncated {
            return Ok(Grabbed::Incomplete {
                frame_id: Some(id),
                reason: format!(
                    "truncated: {} of {} bytes",
                    pixels.len(),
                    2 * self.roi.pixels()
                ),
            });
        }
        self.last_pixels = Some(pixels.clone());
        let frame = Frame {
            pixels,
            width: self.roi.width,
            height: self.roi.height,
            format: self.format,
            host_time: SystemTime::now(),
            device_timestamp_ns: Some(
                started.end.saturating_duration_since(self.epoch).as_nanos() as u64
            ),
            frame_id: id,
            exposure_us: self.exposure_us,
            gain: self.gain_db,
        };
        frame.check(&self.info.id)?;
        Ok(Grabbed::Frame(frame))
    }
}

impl BlockingCamera for SimCamera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        // The simulated sensor's exposure step is 1 us.
        self.exposure_us = self.info.check_exposure_us(exposure_us)?.round();
        Ok(self.exposure_us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        // 0.1 dB steps.
        self.gain_db = (self.info.check_gain(gain)? * 10.0).round() / 10.0;
        Ok(self.gain_db)
    }

    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.check_stopped("pixel_format")?;
        self.format = self.info.check_format(format)?;
        Ok(())
    }

    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        self.check_stopped("roi")?;
        roi.check(
            &self.info.id,
            self.info.sensor_width,
            self.info.sensor_height,
        )?;
        self.roi = roi;
        Ok(roi)
    }

    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        self.check_stopped("trigger")?;
        if mode == TriggerMode::Hardware && self.line.is_none() {
            return Err(self.error(
                ErrorKind::OutOfRange,
                "trigger = hardware needs a wired trigger line (none is wired): allowed \
                 free-run, software",
            ));
        }
        self.trigger_mode = mode;
        Ok(())
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        if self.disconnected {
            return Err(self.error(ErrorKind::Disconnected, "the camera is gone"));
        }
        self.streaming = true;
        self.triggers = 0;
        self.line_seen = self.line.as_ref().map_or(0, |line| line());
        self.exposing = None;
        self.next_start = Instant::now();
        Ok(())
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        self.streaming = false;
        self.exposing = None;
        Ok(())
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        if self.disconnected {
            return Err(self.error(ErrorKind::Disconnected, "the camera is gone"));
        }
        if !self.streaming || self.trigger_mode != TriggerMode::Software {
            return Err(self.error(
                ErrorKind::Other,
                "a software trigger needs trigger = software and a started stream",
            ));
        }
        // One trigger waits while the sensor is busy; more are ignored, as on real cameras.
        self.triggers = (self.triggers + 1).min(1 + u32::from(self.exposing.is_some()));
        Ok(())
    }

    fn supports_hardware_trigger(&self) -> bool {
        self.line.is_some()
    }

    fn on_exposure_end(&mut self, hook: ExposureEndHook) -> bool {
        self.exposure_end = Some(hook);
        true
    }

    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
        if self.disconnected {
            return Err(self.error(ErrorKind::Disconnected, "the camera is gone"));
        }
        let deadline = Instant::now() + wait;
        if !self.streaming {
            std::thread::sleep(wait);
            return Ok(Grabbed::Nothing);
        }
        if let Some(until) = self.stalled_until {
            if Instant::now() < until {
                std::thread::sleep(wait.min(until - Instant::now()));
                return Ok(Grabbed::Nothing);
            }
            self.stalled_until = None;
            self.next_start = self.next_start.max(Instant::now());
        }
        if self.exposing.is_none() {
            let exposure = Duration::from_secs_f64(self.exposure_us * 1e-6);
            let start = match self.trigger_mode {
                TriggerMode::Software if self.triggers > 0 => {
                    self.triggers -= 1;
                    Instant::now()
                }
                TriggerMode::Hardware => match self.wait_edge(deadline) {
                    Some(at) => at,
                    None => return Ok(Grabbed::Nothing),
                },
                TriggerMode::Software => {
                    std::thread::sleep(wait);
                    return Ok(Grabbed::Nothing);
                }
                TriggerMode::FreeRun => {
                    if self.next_start > deadline {
                        std::thread::sleep(wait);
                        return Ok(Grabbed::Nothing);
                    }
                    std::thread::sleep(self.next_start.saturating_duration_since(Instant::now()));
                    Instant::now()
                }
            };
            let period = Duration::from_secs_f64(1.0 / self.config.max_frame_rate_hz);
            self.next_start = start + exposure.max(period);
            self.exposing = Some(Exposing {
                start,
                end: start + exposure,
                path: vec![(0.0, (self.angle)())],
            });
        }
        let Some(end) = self.exposing.as_ref().map(|e| e.end) else {
            return Ok(Grabbed::Nothing);
        };
        // Sample the analyzer's path while exposing, up to the end or the caller's deadline.
        // The samples' times are read after each (imprecise) OS sleep; only the end is precise.
        let until = end.min(deadline);
        while Instant::now() + PATH_SAMPLE < until {
            std::thread::sleep(PATH_SAMPLE);
            let angle = (self.angle)();
            let now = Instant::now();
            if let Some(e) = self.exposing.as_mut() {
                e.path
                    .push((now.saturating_duration_since(e.start).as_secs_f64(), angle));
            }
        }
        crate::sleep_until_precisely(until);
        if end > deadline {
            return Ok(Grabbed::Nothing);
        }
        match self.exposing.take() {
            Some(exposing) => self.finish(exposing),
            None => Ok(Grabbed::Nothing),
        }
    }
}

/// The noise seed of frame `id` in `stream` (see [`SimCameraConfig::noise_stream`]): the three
/// mixed through SplitMix64's finaliser, so distinct `(stream, id)` pairs give unrelated
/// seeds.
pub fn noise_seed(seed: u64, stream: u64, id: u64) -> u64 {
    let mix = |mut z: u64| {
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    mix(mix(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ stream).wrapping_add(id))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    fn camera() -> SimCamera {
        let n = 16 * 16;
        let scene = SimScene {
            width: 16,
            height: 16,
            stokes: vec![[1.0, 0.2, 0.0]; n],
            region: vec![0; n],
            materials: vec!["uniform".into()],
            material_means: vec![[1.0, 0.2, 0.0]],
            band: Band::flat(400.0, 700.0).expect("band"),
        };
        let camera = Camera::from_toml_str(include_str!("../../examples/cameras/cmos_modern.toml"))
            .expect("camera file");
        SimCamera::new(
            SimCameraConfig {
                id: "line".into(),
                camera,
                scene: Arc::new(scene),
                max_frame_rate_hz: 1000.0,
                faults: CameraFaults::default(),
                seed: 3,
                noise_stream: 0,
            },
            Arc::new(|| 0.0),
        )
        .expect("camera")
    }

    /// Hardware trigger (`TriggerSource = Line`): refused while no line is wired (the error
    /// names the trigger and what is allowed); once wired, edges before the start are ignored,
    /// no frame comes without an edge, one edge gives exactly one frame, and two edges that
    /// arrive while the camera is not looking give one frame (the second dropped: trigger
    /// overlap off), with consecutive frame ids.
    #[test]
    fn line_trigger_exposes_once_per_edge() {
        let mut cam = camera();
        assert!(!cam.supports_hardware_trigger());
        let e = cam.set_trigger(TriggerMode::Hardware).expect_err("no line");
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.to_string().contains("trigger = hardware"), "{e}");
        let edges = Arc::new(AtomicU64::new(5));
        let reader = Arc::clone(&edges);
        cam.wire_line(Arc::new(move || reader.load(Ordering::SeqCst)));
        assert!(cam.supports_hardware_trigger());
        cam.set_trigger(TriggerMode::Hardware).expect("wired");
        cam.set_exposure_us(100.0).expect("exposure");
        cam.start().expect("start");
        let wait = Duration::from_millis(20);
        assert!(matches!(cam.wait_frame(wait), Ok(Grabbed::Nothing)));
        edges.fetch_add(1, Ordering::SeqCst);
        let first = match cam.wait_frame(Duration::from_secs(2)) {
            Ok(Grabbed::Frame(f)) => f,
            other => panic!("expected a frame, got {other:?}"),
        };
        assert!(matches!(cam.wait_frame(wait), Ok(Grabbed::Nothing)));
        edges.fetch_add(2, Ordering::SeqCst);
        let second = match cam.wait_frame(Duration::from_secs(2)) {
            Ok(Grabbed::Frame(f)) => f,
            other => panic!("expected a frame, got {other:?}"),
        };
        assert_eq!(second.frame_id, first.frame_id + 1);
        assert!(matches!(cam.wait_frame(wait), Ok(Grabbed::Nothing)));
    }
}
