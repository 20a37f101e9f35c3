//! The acquisition engine (`ARCHITECTURE.md`, "Engine, storage, products").
//!
//! - [`plan`]: plans as data (TOML or YAML), validated with errors that name the field, and
//!   compiled to the steps a run takes; forecasts without running.
//! - [`run`]: the run state machine (running, pausing at the next safe point, paused,
//!   aborting, done) with one actor per device, the suspender, retries and deadlines.
//! - [`journal`]: the append-only journal, flushed before a step counts; a crashed run resumes
//!   from it in a new process.
//! - [`store`]: the run's Zarr v3 store (one chunk per frame), its metadata and products.
//! - [`products`]: live Stokes, DoLP, AoP and their predicted per-pixel sigma.
//! - [`export`]: TIFF export for viewers.
//! - [`continuous`]: continuous-rotation plans, their spans and the span-row Stokes estimate.
//! - [`continuous_planner`]: the continuous planner's problem for a scene and a camera, and a
//!   continuous plan's `from_planner` resolved with it.
//! - [`analyzer_cal`]: the analyzer's zero offset and extinction ratio from Malus's law.
//!
//! The engine knows devices only through the HAL's traits: the simulated rig of `--simulate`
//! and `demo` is `polar_rig::simulated`, and a run on it `polar_rig::run_simulated`.

#![warn(missing_docs)]

pub mod analyzer_cal;
pub mod check;
pub mod continuous;
pub mod continuous_planner;
pub mod export;
pub mod flags;
pub mod forecast;
mod forecast_basis;
pub mod journal;
pub mod plan;
mod plan_error;
pub mod plan_schema;
pub mod products;
pub mod run;
pub mod store;
pub mod tiff_io;

use serde::{Deserialize, Serialize};

/// What a frame is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FrameKind {
    /// A frame of the scene through the analyzer.
    Light,
    /// A dark frame (lens capped or shutter closed).
    Dark,
}

impl FrameKind {
    /// The code stored in the `frames/kind` array: 0 light, 1 dark.
    pub fn code(self) -> u8 {
        match self {
            FrameKind::Light => 0,
            FrameKind::Dark => 1,
        }
    }

    /// The kind of a stored code.
    pub fn from_code(code: u8) -> Option<FrameKind> {
        match code {
            0 => Some(FrameKind::Light),
            1 => Some(FrameKind::Dark),
            _ => None,
        }
    }
}

/// How a frame's analyzer span (`angle_start_deg`, `angle_end_deg`) was measured: the code
/// of `frames/angle_source`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AngleSource {
    /// Step and shoot: the stage's reading after the move settled (start and end equal).
    Settled,
    /// Continuous rotation with a position-compare trigger: the start is the encoder count
    /// latched at the trigger pulse, the end that count plus the speed times the exposure.
    EncoderTrigger,
    /// Continuous rotation with a free-running camera: start and end from the frame's
    /// timestamps and the stage's position samples (uncertainty in `angle_sigma_deg`).
    Timestamps,
}

impl AngleSource {
    /// Every source with its code and name, in code order.
    pub const CODES: [(u8, &'static str); 3] =
        [(0, "settled"), (1, "encoder_trigger"), (2, "timestamps")];

    /// The code stored in `frames/angle_source`.
    pub fn code(self) -> u8 {
        match self {
            AngleSource::Settled => 0,
            AngleSource::EncoderTrigger => 1,
            AngleSource::Timestamps => 2,
        }
    }

    /// The source of a stored code.
    pub fn from_code(code: u8) -> Option<AngleSource> {
        match code {
            0 => Some(AngleSource::Settled),
            1 => Some(AngleSource::EncoderTrigger),
            2 => Some(AngleSource::Timestamps),
            _ => None,
        }
    }
}

/// Everything recorded about one stored frame (journal entry and `frames/*` arrays).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRecord {
    /// Index in the run's `frames` arrays, in the order frames were acquired: 0, 1, 2, ...
    pub index: u64,
    /// The plan step this frame fulfils (a re-acquired step has several frames; the last
    /// accepted one counts).
    #[serde(default)]
    pub step: u64,
    /// Light or dark.
    pub kind: FrameKind,
    /// The angle set it belongs to (`None` for darks and frames outside a set).
    pub set: Option<u64>,
    /// The step's label (e.g. `"set 3 angle 45"`, `"dark before 1"`).
    pub label: String,
    /// Commanded analyzer angle, degrees in `[0, 180)`.
    pub commanded_angle_deg: f64,
    /// Analyzer angle read back after the move, degrees in `[0, 180)` (NaN if not read).
    pub measured_angle_deg: f64,
    /// Analyzer angle when the exposure started, degrees in `[0, 180)` (NaN if not known).
    /// Step and shoot: the settled reading, equal to `measured_angle_deg`.
    pub angle_start_deg: f64,
    /// Analyzer angle when the exposure ended, degrees, unwrapped from `angle_start_deg`:
    /// `angle_end_deg - angle_start_deg` is the span swept, in `[0, 180)`.
    pub angle_end_deg: f64,
    /// How the span was measured.
    pub angle_source: AngleSource,
    /// Standard uncertainty of each end of the span, degrees (NaN: not estimated).
    pub angle_sigma_deg: f64,
    /// Exposure the camera applied, microseconds.
    pub exposure_us: f64,
    /// Gain the camera applied, in the camera's gain unit.
    pub gain: f64,
    /// Host time at the end of the grab, nanoseconds since the Unix epoch.
    pub host_time_unix_ns: i64,
    /// The device's own timestamp, nanoseconds, if it gives one.
    pub device_timestamp_ns: Option<u64>,
    /// The device's frame id.
    pub frame_id: u64,
    /// Sun zenith, degrees, when the plan has a site.
    pub sun_zenith_deg: Option<f64>,
    /// Sun azimuth clockwise from north, degrees, when the plan has a site.
    pub sun_azimuth_deg: Option<f64>,
    /// Frame size, pixels.
    pub width: u32,
    /// Frame size, pixels.
    pub height: u32,
    /// [`pixel_hash`] of the pixels as stored.
    pub hash: u64,
}

/// The hash of a frame's pixels that the journal records (XXH3-64 of the little-endian
/// bytes), so that a stored chunk can be checked against what was acquired.
pub fn pixel_hash(pixels: &[u16]) -> u64 {
    let mut bytes = Vec::with_capacity(pixels.len() * 2);
    for p in pixels {
        bytes.extend_from_slice(&p.to_le_bytes());
    }
    xxhash_rust::xxh3::xxh3_64(&bytes)
}

/// The software that wrote a run: crate version and the git commit it was built from (if
/// known at build time: `build.rs`).
pub fn software_version() -> serde_json::Value {
    serde_json::json!({
        "name": "polarimeter",
        "version": env!("CARGO_PKG_VERSION"),
        "git_hash": env!("POLARIMETER_GIT_HASH"),
    })
}
