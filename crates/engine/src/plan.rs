//! Plans as data: what a run acquires, read from TOML or YAML and validated with errors that
//! name the field, the value and the allowed range; then compiled to the steps a run takes.
//!
//! A plan has a `kind` and the section of that kind:
//!
//! ```toml
//! name = "rooftop capture"
//! kind = "capture"            # capture | calibrate-noise | calibrate-analyzer | time-lapse | adaptive
//!
//! [capture]
//! angles_deg = [0, 45, 90, 135]
//! exposure_us = [4000]        # every set at every exposure
//! repeats = 3                 # sets per exposure
//! darks_before = 2
//! darks_after = 2
//! ```
//!
//! `[policy]` (deadlines and retries), `[suspender]` (the Malus check of every set), `[site]`
//! (sun geometry recorded with every frame) and `[simulation]` (the simulated devices that
//! `--simulate` and `demo` use) are optional and shared by every kind. A capture's
//! `from_planner = { target = "panel", background = "asphalt", channels = 3 }` instead of
//! `angles_deg` asks the planner for the angles (resolved before the run by the caller, see
//! [`Plan::resolve_angles`]); a continuous plan's `from_planner` asks the continuous planner
//! for its frames, exposure and speed ([`crate::continuous_planner::resolve`]).

use crate::store::Storage;
use crate::FrameKind;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::Path;

pub use crate::plan_error::PlanError;

fn invalid(field: &str, value: impl std::fmt::Display, allowed: impl Into<String>) -> PlanError {
    PlanError::Invalid {
        field: field.to_string(),
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

/// The longest parser message a plan error quotes whole, in characters: enough for any
/// message of ours, short of echoing a value of megabytes back.
const QUOTED_MESSAGE_MAX_CHARS: usize = 400;

/// A TOML parse error as a [`PlanError::Parse`]: the key's path and its line and column.
fn toml_parse_error(text: &str, e: &serde_path_to_error::Error<toml::de::Error>) -> PlanError {
    let at = e
        .inner()
        .span()
        .map(|span| polar_model::error::line_column(text, span.start));
    let field = e.path().to_string();
    let path = match (field.as_str(), at) {
        (".", Some(at)) => at,
        (_, Some(at)) => format!("{field} ({at})"),
        (_, None) => field,
    };
    PlanError::Parse {
        path,
        message: shortened(e.inner().message().trim().replace('\n', ", ")),
    }
}

/// `message`, or its start and its length when it is longer than
/// [`QUOTED_MESSAGE_MAX_CHARS`]: an error names a value, it does not echo a file.
fn shortened(message: String) -> String {
    let chars = message.chars().count();
    if chars <= QUOTED_MESSAGE_MAX_CHARS {
        return message;
    }
    let head: String = message
        .chars()
        .take(QUOTED_MESSAGE_MAX_CHARS - 40)
        .collect();
    format!("{head}… ({chars} characters)")
}

/// A list of angles as an error quotes it: whole when short, else its count and first values.
fn quoted_angles(angles: &[f64]) -> String {
    const SHOWN: usize = 8;
    if angles.len() <= SHOWN {
        return format!("{angles:?}");
    }
    format!("{} angles {:?}...", angles.len(), &angles[..SHOWN])
}

/// The plan kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum PlanKind {
    /// Angle sets at fixed (or planner-chosen) angles, with darks.
    Capture,
    /// Dark and photon-transfer series, then the EMVA 1288 noise calibration.
    CalibrateNoise,
    /// A known polarizer in front: the analyzer's zero offset and extinction ratio.
    CalibrateAnalyzer,
    /// Angle sets at an interval, with the sun geometry of each.
    TimeLapse,
    /// The APTD loop: the planner re-aims the analyzer from the frames taken.
    Adaptive,
    /// The analyzer spins; frames are exposed while it turns, one Stokes set per half turn
    /// ([`crate::continuous`]).
    Continuous,
}

impl PlanKind {
    /// The name as written in plans.
    pub fn name(self) -> &'static str {
        match self {
            PlanKind::Capture => "capture",
            PlanKind::CalibrateNoise => "calibrate-noise",
            PlanKind::CalibrateAnalyzer => "calibrate-analyzer",
            PlanKind::TimeLapse => "time-lapse",
            PlanKind::Adaptive => "adaptive",
            PlanKind::Continuous => "continuous",
        }
    }
}

/// The planner's choice of angles for a capture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FromPlanner {
    /// Target material (a name in the scene).
    pub target: String,
    /// Background material.
    pub background: String,
    /// Channels per set, 3..=6.
    #[serde(default = "default_channels")]
    pub channels: usize,
    /// Smallest separation between two angles, degrees, [0, 90).
    #[serde(default = "default_min_separation_deg")]
    pub min_separation_deg: f64,
}

/// Channels per set when a plan does not say: the fewest that form a Stokes vector.
fn default_channels() -> usize {
    3
}
/// The planner's smallest angle separation when a plan does not say, degrees.
fn default_min_separation_deg() -> f64 {
    30.0
}
/// A count (repeats, pairs) a plan leaves out: once.
fn once() -> u32 {
    1
}
/// The calibrate-analyzer darks when a plan does not say.
fn default_analyzer_darks() -> u32 {
    2
}

/// `[capture]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Capture {
    /// Analyzer angles of a set, degrees, 3..=16 of them, each in [0, 180).
    #[serde(default)]
    pub angles_deg: Option<Vec<f64>>,
    /// Or ask the planner.
    #[serde(default)]
    pub from_planner: Option<FromPlanner>,
    /// Exposures, microseconds: every repeat is taken at each.
    pub exposure_us: Vec<f64>,
    /// Sets per exposure, 1..=100000.
    #[serde(default = "once")]
    pub repeats: u32,
    /// Dark frames before the sets, 0..=1000.
    #[serde(default)]
    pub darks_before: u32,
    /// Dark frames after the sets, 0..=1000.
    #[serde(default)]
    pub darks_after: u32,
    /// Analog gain, dB, [0, 48].
    #[serde(default)]
    pub gain_db: f64,
}

/// `[calibrate-noise]`: for each exposure, `pairs` dark pairs and light pairs (EMVA 1288).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CalibrateNoise {
    /// Exposures of the photon-transfer series, microseconds, 4..=200 of them, increasing.
    pub exposure_us: Vec<f64>,
    /// Analyzer angle during the series, degrees, [0, 180).
    #[serde(default)]
    pub angle_deg: f64,
    /// Frame pairs per exposure (dark and light each), 1..=16.
    #[serde(default = "once")]
    pub pairs: u32,
    /// Analog gain, dB, [0, 48].
    #[serde(default)]
    pub gain_db: f64,
}

/// `[calibrate-analyzer]`: a known polarizer in front; the analyzer turns through `steps`
/// angles over 180 degrees.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CalibrateAnalyzer {
    /// The reference polarizer's transmission axis in the camera frame, degrees, [0, 180).
    pub reference_angle_deg: f64,
    /// Analyzer angles, evenly over [0, 180), 8..=720.
    pub steps: u32,
    /// Frames per angle, 1..=100.
    #[serde(default = "once")]
    pub repeats: u32,
    /// Exposure, microseconds.
    pub exposure_us: f64,
    /// Dark frames before the sweep (subtracted; the extinction ratio needs them), 1..=1000.
    #[serde(default = "default_analyzer_darks")]
    pub darks: u32,
    /// Analog gain, dB, [0, 48].
    #[serde(default)]
    pub gain_db: f64,
}

/// `[time-lapse]`: `count` sets, one every `interval_s`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TimeLapse {
    /// Analyzer angles of a set, degrees, 3..=16 of them.
    pub angles_deg: Vec<f64>,
    /// Exposure, microseconds.
    pub exposure_us: f64,
    /// Seconds between the starts of two sets, (0, 86400].
    pub interval_s: f64,
    /// Sets, 1..=100000.
    pub count: u32,
    /// Analog gain, dB, [0, 48].
    #[serde(default)]
    pub gain_db: f64,
    /// What to do with a set whose start time has passed by more than half an interval (a
    /// run resumed late, a long pause): `"take"` it at once (default) or `"skip"` it. Either
    /// is recorded in the journal and in the store's `late_sets` attribute.
    #[serde(default)]
    pub late: LatePolicy,
}

/// What a time-lapse does with a set that is late (see [`TimeLapse::late`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum LatePolicy {
    /// Take the late set at once (the sets then run back to back until on time again).
    #[default]
    Take,
    /// Skip the late set: it is not taken and not counted as planned.
    Skip,
}

/// How the adaptive loop knows the target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AdaptiveTarget {
    /// A material of the simulated scene whose pixels are the target (simulation only).
    #[serde(default)]
    pub material: Option<String>,
    /// A rectangle `[x0, y0, x1, y1]` in pixels (x1, y1 exclusive).
    #[serde(default)]
    pub rect: Option<[u32; 4]>,
    /// Or the top RX anomalies, this fraction of the pixels, (0, 0.5).
    #[serde(default)]
    pub anomalies: Option<f64>,
}

/// `[adaptive]`: APTD (MODEL.md section 9).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Adaptive {
    /// The first set, degrees (a conventional set).
    pub initial_angles_deg: Vec<f64>,
    /// Channels of the sets the planner picks, 3..=6.
    #[serde(default = "default_channels")]
    pub channels: usize,
    /// Exposure, microseconds.
    pub exposure_us: f64,
    /// The most frames the loop may take, first set included.
    pub frame_budget: usize,
    /// How the target is known.
    pub target: AdaptiveTarget,
    /// Converged when no angle moves by more than this, degrees, (0, 90].
    #[serde(default = "half_degree")]
    pub angle_tol_deg: f64,
    /// ... and the SCR changes by less than this, relative, (0, 1].
    #[serde(default = "two_percent")]
    pub scr_rel_tol: f64,
    /// Smallest separation between two angles of a set, degrees, [5, 60] (each set must
    /// form Stokes images on its own).
    #[serde(default = "default_min_separation_deg")]
    pub min_separation_deg: f64,
    /// Dark frames before the loop, 0..=1000.
    #[serde(default)]
    pub darks: u32,
    /// Analog gain, dB, [0, 48].
    #[serde(default)]
    pub gain_db: f64,
}

fn half_degree() -> f64 {
    0.5
}
fn two_percent() -> f64 {
    0.02
}

/// `[policy]`: deadlines and retries.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Policy {
    /// Deadline of one move, seconds, (0, 600].
    pub move_timeout_s: f64,
    /// Deadline of one grab beyond the exposure, seconds, (0, 600].
    pub grab_timeout_s: f64,
    /// Attempts of a failed device operation before the run pauses, 1..=20.
    pub attempts: u32,
    /// Wait before a retry, milliseconds, [0, 60000].
    pub retry_backoff_ms: u64,
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            move_timeout_s: 20.0,
            grab_timeout_s: 5.0,
            attempts: 3,
            retry_backoff_ms: 200,
        }
    }
}

/// What the suspender does with a set that fails its check.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum SuspendAction {
    /// Record why and take the set again (up to `max_reacquire` times, then pause).
    Reacquire,
    /// Pause the run with the reason.
    Pause,
}

/// `[suspender]`: every angle set is checked against the model (Malus's law within the
/// predicted noise, and the analyzer where it was commanded).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Suspender {
    /// Check sets at all.
    pub enabled: bool,
    /// The largest mean reduced chi-square of a set's per-pixel Malus fit, (1, 1000]. Its
    /// expected value is 1; see `run::suspender` for the threshold's reasoning.
    pub max_reduced_chi2: f64,
    /// The largest relative change of the mean S0 between consecutive sets, (0, 10] (for
    /// sets of 3 angles, which leave no residual to test).
    pub max_s0_change: f64,
    /// The largest difference between commanded and measured analyzer angle, degrees, (0, 90].
    pub max_angle_error_deg: f64,
    /// What to do with a failing set.
    pub action: SuspendAction,
    /// Re-acquisitions of one set before the run pauses, 0..=100.
    pub max_reacquire: u32,
    /// The largest share of a set's pixels that may saturate before the run warns, [0, 1]
    /// (their products are NaN). A set over it still counts (taking it again would saturate
    /// again); the run's summary names it and the store records every set's share
    /// (`products` attribute `saturated_fraction`).
    pub max_saturated_fraction: f64,
}

impl Default for Suspender {
    fn default() -> Self {
        Suspender {
            enabled: true,
            max_reduced_chi2: 2.0,
            max_s0_change: 0.2,
            max_angle_error_deg: 1.0,
            action: SuspendAction::Reacquire,
            max_reacquire: 3,
            max_saturated_fraction: 0.01,
        }
    }
}

/// `[site]`: where the instrument is (for the sun geometry recorded with every frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Site {
    /// Latitude, degrees, [-90, 90].
    pub latitude_deg: f64,
    /// Longitude, degrees east, [-180, 180].
    pub longitude_deg: f64,
    /// Elevation, metres, [-500, 9000].
    #[serde(default)]
    pub elevation_m: f64,
}

/// `[simulation]`: the simulated devices of `--simulate` and `demo`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Simulation {
    /// Scene file (TOML, relative to the plan's folder); none: the rooftop panels example.
    pub scene: Option<String>,
    /// Camera file (TOML); none: the modern CMOS example.
    pub camera: Option<String>,
    /// Frame size, pixels, 16..=4096.
    pub width: u32,
    /// Frame size, pixels, 16..=4096.
    pub height: u32,
    /// Seed of the scene's texture, the noise and the faults.
    pub seed: u64,
    /// Stage speed, degrees per second, (0, 3600].
    pub stage_deg_per_s: f64,
    /// The simulated stage: a rotator of a dialect's simulator
    /// (`polar_hil_mocks::sim::SIMULATORS`), e.g. `stage = { dialect = "apt", model =
    /// "k10cr1" }`, driven through its dialect's driver; none: the registry's first rotator
    /// (our firmware's). The simulated rig checks the choice (`polar_rig::sim_stage`); the
    /// engine does not know the simulators.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stage: Option<SimStage>,
    /// Fault profile of the stage's serial link (hil-mocks `FaultProfile` fields).
    #[schemars(with = "Option<serde_json::Map<String, serde_json::Value>>")]
    pub stage_faults: Option<toml::Table>,
    /// Camera faults (hil-mocks `CameraFaults` fields).
    #[schemars(with = "Option<serde_json::Map<String, serde_json::Value>>")]
    pub camera_faults: Option<toml::Table>,
    /// Cloud: the illumination drops by `cloud_depth` from the middle of this set to its
    /// end, on its first try (the suspender's test case: the set is taken again).
    pub cloud_at_set: Option<u64>,
    /// Fractional drop of the illumination under the cloud, (0, 1).
    pub cloud_depth: f64,
}

impl Simulation {
    /// Checks the section's ranges; errors name the key, the value and the range.
    pub fn validate(&self) -> Result<(), PlanError> {
        check_count("simulation.width", u64::from(self.width), 16, 4096)?;
        check_count("simulation.height", u64::from(self.height), 16, 4096)?;
        check(
            "simulation.stage_deg_per_s",
            self.stage_deg_per_s,
            0.0,
            3600.0,
            true,
        )?;
        check("simulation.cloud_depth", self.cloud_depth, 0.0, 1.0, true)?;
        if self.cloud_depth >= 1.0 {
            return Err(invalid(
                "simulation.cloud_depth",
                self.cloud_depth,
                "(0, 1)",
            ));
        }
        Ok(())
    }
}

impl Default for Simulation {
    fn default() -> Self {
        Simulation {
            scene: None,
            camera: None,
            width: 160,
            height: 120,
            seed: 1,
            stage_deg_per_s: 720.0,
            stage: None,
            stage_faults: None,
            camera_faults: None,
            cloud_at_set: None,
            cloud_depth: 0.3,
        }
    }
}

/// `[simulation] stage`: which simulated rotation stage the simulated rig drives.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SimStage {
    /// The dialect (`native`, `elliptec`, `apt`, ...: one with a rotator simulator).
    pub dialect: String,
    /// The model, lower case (`k10cr1`, `ell14`, ...); none: the dialect's first rotator.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
}

/// A plan file as written: `kind` and every kind's optional section. [`Plan`] is read through
/// it (serde's messages for unknown keys and wrong types, with their paths) and converted by
/// [`Plan::try_from`], which keeps exactly the section of `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
struct PlanFile {
    /// A name for people. A plan read from a file without one (or with a blank one) is named
    /// by the file's stem ([`Plan::from_path`]).
    #[serde(default)]
    name: String,
    /// What it does.
    kind: PlanKind,
    /// `kind = "capture"`.
    #[serde(default)]
    capture: Option<Capture>,
    /// `kind = "calibrate-noise"`.
    #[serde(default, rename = "calibrate-noise")]
    calibrate_noise: Option<CalibrateNoise>,
    /// `kind = "calibrate-analyzer"`.
    #[serde(default, rename = "calibrate-analyzer")]
    calibrate_analyzer: Option<CalibrateAnalyzer>,
    /// `kind = "time-lapse"`.
    #[serde(default, rename = "time-lapse")]
    time_lapse: Option<TimeLapse>,
    /// `kind = "adaptive"`.
    #[serde(default)]
    adaptive: Option<Adaptive>,
    /// `kind = "continuous"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    continuous: Option<crate::continuous::Continuous>,
    /// Deadlines and retries.
    #[serde(default)]
    policy: Policy,
    /// The per-set check.
    #[serde(default)]
    suspender: Suspender,
    /// The site, for sun geometry.
    #[serde(default)]
    site: Option<Site>,
    /// The simulated devices.
    #[serde(default)]
    simulation: Simulation,
    /// How the run's store keeps its images.
    #[serde(default, skip_serializing_if = "is_default_storage")]
    storage: Storage,
}

fn is_default_storage(s: &Storage) -> bool {
    *s == Storage::default()
}

/// What a plan acquires: its kind with exactly that kind's section, so a plan without its
/// section, or with another kind's, cannot be made.
#[derive(Debug, Clone, PartialEq)]
pub enum Acquisition {
    /// `kind = "capture"`.
    Capture(Capture),
    /// `kind = "calibrate-noise"`.
    CalibrateNoise(CalibrateNoise),
    /// `kind = "calibrate-analyzer"`.
    CalibrateAnalyzer(CalibrateAnalyzer),
    /// `kind = "time-lapse"`.
    TimeLapse(TimeLapse),
    /// `kind = "adaptive"`.
    Adaptive(Adaptive),
    /// `kind = "continuous"`.
    Continuous(crate::continuous::Continuous),
}

impl Acquisition {
    /// Its kind.
    pub fn kind(&self) -> PlanKind {
        match self {
            Acquisition::Capture(_) => PlanKind::Capture,
            Acquisition::CalibrateNoise(_) => PlanKind::CalibrateNoise,
            Acquisition::CalibrateAnalyzer(_) => PlanKind::CalibrateAnalyzer,
            Acquisition::TimeLapse(_) => PlanKind::TimeLapse,
            Acquisition::Adaptive(_) => PlanKind::Adaptive,
            Acquisition::Continuous(_) => PlanKind::Continuous,
        }
    }
}

/// A plan: a name, what it acquires ([`Acquisition`]) and the sections every kind shares.
/// Read and written in the file's layout (`kind` and the kind's section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(try_from = "PlanFile", into = "PlanFile")]
pub struct Plan {
    /// A name for people. A plan read from a file without one (or with a blank one) is named
    /// by the file's stem ([`Plan::from_path`]).
    pub name: String,
    /// What it acquires.
    pub acquisition: Acquisition,
    /// Deadlines and retries.
    pub policy: Policy,
    /// The per-set check.
    pub suspender: Suspender,
    /// The site, for sun geometry.
    pub site: Option<Site>,
    /// The simulated devices.
    pub simulation: Simulation,
    /// How the run's store keeps its images (`[storage]`: `products = "essential"` or
    /// `"all"`, `precision = "sigma"` or `"float32"`, `compression = "zstd"` or `"none"`).
    pub storage: Storage,
}

impl TryFrom<PlanFile> for Plan {
    type Error = PlanError;

    /// Keeps the section of `kind`; an error names the missing section, or another kind's
    /// section that is present.
    fn try_from(f: PlanFile) -> Result<Plan, PlanError> {
        let kind = f.kind;
        let present = [
            (PlanKind::Capture, f.capture.is_some()),
            (PlanKind::CalibrateNoise, f.calibrate_noise.is_some()),
            (PlanKind::CalibrateAnalyzer, f.calibrate_analyzer.is_some()),
            (PlanKind::TimeLapse, f.time_lapse.is_some()),
            (PlanKind::Adaptive, f.adaptive.is_some()),
            (PlanKind::Continuous, f.continuous.is_some()),
        ];
        for (other, given) in present {
            if other != kind && given {
                return Err(invalid(
                    other.name(),
                    "(present)",
                    format!(
                        "only the [{}] section for kind = \"{}\"",
                        kind.name(),
                        kind.name()
                    ),
                ));
            }
        }
        let missing = || {
            invalid(
                kind.name(),
                "(missing)",
                format!("a [{}] section for kind = \"{}\"", kind.name(), kind.name()),
            )
        };
        let acquisition = match kind {
            PlanKind::Capture => Acquisition::Capture(f.capture.ok_or_else(missing)?),
            PlanKind::CalibrateNoise => {
                Acquisition::CalibrateNoise(f.calibrate_noise.ok_or_else(missing)?)
            }
            PlanKind::CalibrateAnalyzer => {
                Acquisition::CalibrateAnalyzer(f.calibrate_analyzer.ok_or_else(missing)?)
            }
            PlanKind::TimeLapse => Acquisition::TimeLapse(f.time_lapse.ok_or_else(missing)?),
            PlanKind::Adaptive => Acquisition::Adaptive(f.adaptive.ok_or_else(missing)?),
            PlanKind::Continuous => Acquisition::Continuous(f.continuous.ok_or_else(missing)?),
        };
        Ok(Plan {
            name: f.name,
            acquisition,
            policy: f.policy,
            suspender: f.suspender,
            site: f.site,
            simulation: f.simulation,
            storage: f.storage,
        })
    }
}

impl From<Plan> for PlanFile {
    fn from(p: Plan) -> PlanFile {
        let mut f = PlanFile {
            name: p.name,
            kind: p.acquisition.kind(),
            capture: None,
            calibrate_noise: None,
            calibrate_analyzer: None,
            time_lapse: None,
            adaptive: None,
            continuous: None,
            policy: p.policy,
            suspender: p.suspender,
            site: p.site,
            simulation: p.simulation,
            storage: p.storage,
        };
        match p.acquisition {
            Acquisition::Capture(c) => f.capture = Some(c),
            Acquisition::CalibrateNoise(c) => f.calibrate_noise = Some(c),
            Acquisition::CalibrateAnalyzer(c) => f.calibrate_analyzer = Some(c),
            Acquisition::TimeLapse(t) => f.time_lapse = Some(t),
            Acquisition::Adaptive(a) => f.adaptive = Some(a),
            Acquisition::Continuous(c) => f.continuous = Some(c),
        }
        f
    }
}

/// One step of a run: one frame at one analyzer angle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepSpec {
    /// Light or dark.
    pub kind: FrameKind,
    /// The angle set it belongs to (`None` for darks and calibration series).
    pub set: Option<u64>,
    /// Analyzer angle, degrees in [0, 180).
    pub angle_deg: f64,
    /// Exposure, microseconds.
    pub exposure_us: f64,
    /// Analog gain, dB.
    pub gain_db: f64,
    /// For people and the store.
    pub label: String,
    /// Not before this many seconds after the run's start (time-lapse).
    pub not_before_s: Option<f64>,
}

fn check(field: &str, v: f64, lo: f64, hi: f64, lo_open: bool) -> Result<(), PlanError> {
    let ok = v.is_finite() && v <= hi && if lo_open { v > lo } else { v >= lo };
    if ok {
        Ok(())
    } else {
        let open = if lo_open { "(" } else { "[" };
        Err(invalid(field, v, format!("{open}{lo}, {hi}]")))
    }
}

fn check_count(field: &str, v: u64, lo: u64, hi: u64) -> Result<(), PlanError> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(invalid(field, v, format!("{lo}..={hi}")))
    }
}

fn check_angles(field: &str, angles: &[f64], lo_n: usize, hi_n: usize) -> Result<(), PlanError> {
    if !(lo_n..=hi_n).contains(&angles.len()) {
        return Err(invalid(
            field,
            quoted_angles(angles),
            format!("{lo_n}..={hi_n} angles"),
        ));
    }
    for (i, a) in angles.iter().enumerate() {
        check(&format!("{field}[{i}]"), *a, 0.0, 180.0, false)?;
        if *a >= 180.0 {
            return Err(invalid(&format!("{field}[{i}]"), a, "[0, 180) degrees"));
        }
    }
    Ok(())
}

fn check_exposures(field: &str, exposures: &[f64]) -> Result<(), PlanError> {
    if exposures.is_empty() {
        return Err(invalid(field, "[]", "at least one exposure"));
    }
    for (i, e) in exposures.iter().enumerate() {
        check(&format!("{field}[{i}]"), *e, 1.0, 1e8, false)?;
    }
    Ok(())
}

/// Distinct angles modulo 180 degrees (within 0.01 degree).
fn distinct_angles(angles: &[f64]) -> usize {
    let mut seen: Vec<f64> = Vec::new();
    for a in angles {
        let a = a.rem_euclid(180.0);
        if !seen.iter().any(|s| {
            let d = (s - a).rem_euclid(180.0);
            d.min(180.0 - d) < 0.01
        }) {
            seen.push(a);
        }
    }
    seen.len()
}

/// A dark frame's step (the lens capped) at `angle_deg`.
fn dark_step(label: String, exposure_us: f64, gain_db: f64, angle_deg: f64) -> StepSpec {
    StepSpec {
        kind: FrameKind::Dark,
        set: None,
        angle_deg,
        exposure_us,
        gain_db,
        label,
        not_before_s: None,
    }
}

/// A light frame's step at `angle_deg`, in `set` if any.
fn light_step(
    set: Option<u64>,
    label: String,
    angle_deg: f64,
    exposure_us: f64,
    gain_db: f64,
) -> StepSpec {
    StepSpec {
        kind: FrameKind::Light,
        set,
        angle_deg,
        exposure_us,
        gain_db,
        label,
        not_before_s: None,
    }
}

impl Capture {
    /// The darks before, the sets (every exposure, `repeats` times, each angle) and the darks after.
    fn steps(&self) -> Result<Vec<StepSpec>, PlanError> {
        let c = self;
        let mut steps = Vec::new();
        let angles = c.angles_deg.as_ref().ok_or_else(|| {
            invalid(
                "capture.from_planner",
                "(unresolved)",
                "angles resolved by the planner before the run",
            )
        })?;
        let first = c.exposure_us[0];
        let last = c.exposure_us[c.exposure_us.len() - 1];
        for i in 0..c.darks_before {
            steps.push(dark_step(
                format!("dark before {i}"),
                first,
                c.gain_db,
                angles[0],
            ));
        }
        let mut set = 0u64;
        for &e in &c.exposure_us {
            for _ in 0..c.repeats {
                for &a in angles {
                    steps.push(light_step(
                        Some(set),
                        format!("set {set} {e} us {a} deg"),
                        a,
                        e,
                        c.gain_db,
                    ));
                }
                set += 1;
            }
        }
        for i in 0..c.darks_after {
            steps.push(dark_step(
                format!("dark after {i}"),
                last,
                c.gain_db,
                angles[0],
            ));
        }
        Ok(steps)
    }
}

impl CalibrateNoise {
    /// Per exposure, `2 pairs` darks then `2 pairs` lights at the angle.
    fn steps(&self) -> Vec<StepSpec> {
        let c = self;
        let mut steps = Vec::new();
        for &e in &c.exposure_us {
            for p in 0..2 * c.pairs {
                steps.push(dark_step(
                    format!("ptc dark {e} us {p}"),
                    e,
                    c.gain_db,
                    c.angle_deg,
                ));
            }
            for p in 0..2 * c.pairs {
                steps.push(light_step(
                    None,
                    format!("ptc light {e} us {p}"),
                    c.angle_deg,
                    e,
                    c.gain_db,
                ));
            }
        }
        steps
    }
}

impl CalibrateAnalyzer {
    /// The darks, then the sweep over half a turn (`repeats` frames per angle).
    fn steps(&self) -> Vec<StepSpec> {
        let c = self;
        let mut steps = Vec::new();
        for i in 0..c.darks {
            steps.push(dark_step(
                format!("dark {i}"),
                c.exposure_us,
                c.gain_db,
                0.0,
            ));
        }
        for k in 0..c.steps {
            let a = 180.0 * f64::from(k) / f64::from(c.steps);
            for r in 0..c.repeats {
                steps.push(light_step(
                    None,
                    format!("sweep {a:.3} deg {r}"),
                    a,
                    c.exposure_us,
                    c.gain_db,
                ));
            }
        }
        steps
    }
}

impl TimeLapse {
    /// `count` sets, each due `interval_s` after the last.
    fn steps(&self) -> Vec<StepSpec> {
        let t = self;
        let mut steps = Vec::new();
        for set in 0..u64::from(t.count) {
            for (i, &a) in t.angles_deg.iter().enumerate() {
                let mut s = light_step(
                    Some(set),
                    format!("set {set} {a} deg"),
                    a,
                    t.exposure_us,
                    t.gain_db,
                );
                if i == 0 {
                    s.not_before_s = Some(set as f64 * t.interval_s);
                }
                steps.push(s);
            }
        }
        steps
    }
}

impl Adaptive {
    /// The darks and the first round (the planner chooses the rest as the run goes).
    fn steps(&self) -> Vec<StepSpec> {
        let a = self;
        let mut steps = Vec::new();
        for i in 0..a.darks {
            steps.push(dark_step(
                format!("dark {i}"),
                a.exposure_us,
                a.gain_db,
                a.initial_angles_deg[0],
            ));
        }
        for &deg in &a.initial_angles_deg {
            steps.push(light_step(
                Some(0),
                format!("round 1 {deg} deg"),
                deg,
                a.exposure_us,
                a.gain_db,
            ));
        }
        steps
    }
}

/// An analog gain, dB: 0 to 48.
fn check_gain(field: &str, g: f64) -> Result<(), PlanError> {
    check(field, g, 0.0, 48.0, false)
}

impl Capture {
    /// Checks the `[capture]` section's ranges.
    fn validate(&self) -> Result<(), PlanError> {
        let c = self;
        match (&c.angles_deg, &c.from_planner) {
            (Some(a), None) => {
                check_angles("capture.angles_deg", a, 3, 16)?;
                if distinct_angles(a) < 3 {
                    return Err(invalid(
                        "capture.angles_deg",
                        format!("{a:?}"),
                        "at least 3 distinct angles (modulo 180 degrees) to form Stokes images",
                    ));
                }
            }
            (None, Some(fp)) => {
                check_count("capture.from_planner.channels", fp.channels as u64, 3, 6)?;
                check(
                    "capture.from_planner.min_separation_deg",
                    fp.min_separation_deg,
                    0.0,
                    60.0,
                    false,
                )?;
            }
            _ => {
                return Err(invalid(
                    "capture.angles_deg",
                    "(both or neither)",
                    "exactly one of capture.angles_deg and capture.from_planner",
                ))
            }
        }
        check_exposures("capture.exposure_us", &c.exposure_us)?;
        check_count("capture.repeats", u64::from(c.repeats), 1, 100_000)?;
        check_count("capture.darks_before", u64::from(c.darks_before), 0, 1000)?;
        check_count("capture.darks_after", u64::from(c.darks_after), 0, 1000)?;
        check_gain("capture.gain_db", c.gain_db)?;
        Ok(())
    }
}

impl CalibrateNoise {
    /// Checks the `[calibrate-noise]` section's ranges.
    fn validate(&self) -> Result<(), PlanError> {
        let c = self;
        if !(5..=200).contains(&c.exposure_us.len()) {
            return Err(invalid(
                "calibrate-noise.exposure_us",
                format!("{} exposures", c.exposure_us.len()),
                "5..=200 exposures (the photon transfer fit needs 3 in the linear range, \
                 the saturation point and one beyond it)",
            ));
        }
        check_exposures("calibrate-noise.exposure_us", &c.exposure_us)?;
        if c.exposure_us.windows(2).any(|w| w[1] <= w[0]) {
            return Err(invalid(
                "calibrate-noise.exposure_us",
                format!("{:?}", c.exposure_us),
                "strictly increasing exposures",
            ));
        }
        check_angles("calibrate-noise.angle_deg", &[c.angle_deg], 1, 1)?;
        check_count("calibrate-noise.pairs", u64::from(c.pairs), 1, 16)?;
        check_gain("calibrate-noise.gain_db", c.gain_db)?;
        Ok(())
    }
}

impl CalibrateAnalyzer {
    /// Checks the `[calibrate-analyzer]` section's ranges.
    fn validate(&self) -> Result<(), PlanError> {
        let c = self;
        check_angles(
            "calibrate-analyzer.reference_angle_deg",
            &[c.reference_angle_deg],
            1,
            1,
        )?;
        check_count("calibrate-analyzer.steps", u64::from(c.steps), 8, 720)?;
        check_count("calibrate-analyzer.repeats", u64::from(c.repeats), 1, 100)?;
        check_exposures("calibrate-analyzer.exposure_us", &[c.exposure_us])?;
        check_count("calibrate-analyzer.darks", u64::from(c.darks), 1, 1000)?;
        check_gain("calibrate-analyzer.gain_db", c.gain_db)?;
        Ok(())
    }
}

impl TimeLapse {
    /// Checks the `[time-lapse]` section's ranges.
    fn validate(&self) -> Result<(), PlanError> {
        let t = self;
        check_angles("time-lapse.angles_deg", &t.angles_deg, 3, 16)?;
        if distinct_angles(&t.angles_deg) < 3 {
            return Err(invalid(
                "time-lapse.angles_deg",
                format!("{:?}", t.angles_deg),
                "at least 3 distinct angles (modulo 180 degrees)",
            ));
        }
        check_exposures("time-lapse.exposure_us", &[t.exposure_us])?;
        check("time-lapse.interval_s", t.interval_s, 0.0, 86_400.0, true)?;
        check_count("time-lapse.count", u64::from(t.count), 1, 100_000)?;
        check_gain("time-lapse.gain_db", t.gain_db)?;
        Ok(())
    }
}

impl Adaptive {
    /// Checks the `[adaptive]` section's ranges and its one target.
    fn validate(&self) -> Result<(), PlanError> {
        let a = self;
        check_angles("adaptive.initial_angles_deg", &a.initial_angles_deg, 3, 6)?;
        if distinct_angles(&a.initial_angles_deg) < 3 {
            return Err(invalid(
                "adaptive.initial_angles_deg",
                format!("{:?}", a.initial_angles_deg),
                "at least 3 distinct angles (modulo 180 degrees)",
            ));
        }
        check_count("adaptive.channels", a.channels as u64, 3, 6)?;
        check_exposures("adaptive.exposure_us", &[a.exposure_us])?;
        let first = a.initial_angles_deg.len() as u64;
        check_count(
            "adaptive.frame_budget",
            a.frame_budget as u64,
            first,
            100_000,
        )?;
        check("adaptive.angle_tol_deg", a.angle_tol_deg, 0.0, 90.0, true)?;
        check("adaptive.scr_rel_tol", a.scr_rel_tol, 0.0, 1.0, true)?;
        // Each set must form Stokes images on its own (products and the suspender).
        check(
            "adaptive.min_separation_deg",
            a.min_separation_deg,
            5.0,
            60.0,
            false,
        )?;
        check_count("adaptive.darks", u64::from(a.darks), 0, 1000)?;
        check_gain("adaptive.gain_db", a.gain_db)?;
        let t = &a.target;
        let given = [
            t.material.is_some(),
            t.rect.is_some(),
            t.anomalies.is_some(),
        ];
        if given.iter().filter(|g| **g).count() != 1 {
            return Err(invalid(
                "adaptive.target",
                "(none or several)",
                "exactly one of material, rect, anomalies",
            ));
        }
        if let Some(f) = t.anomalies {
            check("adaptive.target.anomalies", f, 0.0, 0.5, true)?;
            if f >= 0.5 {
                return Err(invalid("adaptive.target.anomalies", f, "(0, 0.5)"));
            }
        }
        if let Some([x0, y0, x1, y1]) = t.rect {
            if x1 <= x0 || y1 <= y0 {
                return Err(invalid(
                    "adaptive.target.rect",
                    format!("[{x0}, {y0}, {x1}, {y1}]"),
                    "x0 < x1 and y0 < y1",
                ));
            }
        }
        Ok(())
    }
}

/// Section accessors: the plan's section of a kind, `None` for a plan of another kind.
macro_rules! sections {
    ($($get:ident, $get_mut:ident, $variant:ident, $ty:ty;)*) => {
        impl Plan {
            $(
                #[doc = concat!("The `", stringify!($variant), "` section, if the plan is of that kind.")]
                pub fn $get(&self) -> Option<&$ty> {
                    match &self.acquisition {
                        Acquisition::$variant(x) => Some(x),
                        _ => None,
                    }
                }
                #[doc = concat!("The `", stringify!($variant), "` section to change, if the plan is of that kind.")]
                pub fn $get_mut(&mut self) -> Option<&mut $ty> {
                    match &mut self.acquisition {
                        Acquisition::$variant(x) => Some(x),
                        _ => None,
                    }
                }
            )*
        }
    };
}

sections! {
    capture, capture_mut, Capture, Capture;
    calibrate_noise, calibrate_noise_mut, CalibrateNoise, CalibrateNoise;
    calibrate_analyzer, calibrate_analyzer_mut, CalibrateAnalyzer, CalibrateAnalyzer;
    time_lapse, time_lapse_mut, TimeLapse, TimeLapse;
    adaptive, adaptive_mut, Adaptive, Adaptive;
    continuous, continuous_mut, Continuous, crate::continuous::Continuous;
}

impl Plan {
    /// Its kind.
    pub fn kind(&self) -> PlanKind {
        self.acquisition.kind()
    }

    /// The file's layout (serde's messages, with the key's path), then the kind's section
    /// ([`Plan::try_from`]) and every range ([`Plan::validate`]).
    fn from_file(file: Result<PlanFile, PlanError>) -> Result<Plan, PlanError> {
        let plan = Plan::try_from(file?)?;
        plan.validate()?;
        Ok(plan)
    }

    /// Parses TOML text; errors name the field.
    pub fn from_toml_str(text: &str) -> Result<Plan, PlanError> {
        let de = toml::Deserializer::new(text);
        Plan::from_file(
            serde_path_to_error::deserialize(de).map_err(|e| toml_parse_error(text, &e)),
        )
    }

    /// The `[simulation]` section of a plan's TOML text alone, checked as a plan checks it
    /// (the default where there is none). The other sections are not read, so an error in
    /// them does not stop what needs only the simulated devices (the GUI's Connect); errors
    /// name the key and its line as [`Plan::from_toml_str`]'s do.
    pub fn simulation_from_toml_str(text: &str) -> Result<Simulation, PlanError> {
        #[derive(Deserialize)]
        struct SimulationOnly {
            #[serde(default)]
            simulation: Simulation,
        }
        let de = toml::Deserializer::new(text);
        let only: SimulationOnly =
            serde_path_to_error::deserialize(de).map_err(|e| toml_parse_error(text, &e))?;
        only.simulation.validate()?;
        Ok(only.simulation)
    }

    /// Parses YAML text; errors name the field.
    pub fn from_yaml_str(text: &str) -> Result<Plan, PlanError> {
        let de = serde_yaml_ng::Deserializer::from_str(text);
        Plan::from_file(
            serde_path_to_error::deserialize(de).map_err(|e| PlanError::Parse {
                path: e.path().to_string(),
                message: e.inner().to_string(),
            }),
        )
    }

    /// Reads a plan file: `.yaml`/`.yml` as YAML, anything else as TOML. A plan without a
    /// name (or with a blank one) is named by the file's stem: `capture.toml` is `capture`.
    pub fn from_path(path: &Path) -> Result<Plan, PlanError> {
        let mut plan = Plan::from_path_as_written(path)?;
        if plan.name.trim().is_empty() {
            if let Some(stem) = path.file_stem() {
                plan.name = stem.to_string_lossy().into_owned();
            }
        }
        Ok(plan)
    }

    fn from_path_as_written(path: &Path) -> Result<Plan, PlanError> {
        let text = std::fs::read_to_string(path).map_err(|e| PlanError::Io {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
        let yaml = matches!(
            path.extension().and_then(|e| e.to_str()),
            Some("yaml" | "yml")
        );
        if yaml {
            Plan::from_yaml_str(&text)
        } else {
            Plan::from_toml_str(&text)
        }
    }

    /// Checks every field's range: the shared sections, then the kind's.
    pub fn validate(&self) -> Result<(), PlanError> {
        self.check_common()?;
        match &self.acquisition {
            // An unresolved `from_planner` is checked as written here; the run refuses it.
            Acquisition::Continuous(c) => c.validate_as_written(),
            Acquisition::Capture(c) => c.validate(),
            Acquisition::CalibrateNoise(c) => c.validate(),
            Acquisition::CalibrateAnalyzer(c) => c.validate(),
            Acquisition::TimeLapse(t) => t.validate(),
            Acquisition::Adaptive(a) => a.validate(),
        }
    }

    /// The sections every kind has: policy, suspender, site and simulation.
    fn check_common(&self) -> Result<(), PlanError> {
        let p = &self.policy;
        check("policy.move_timeout_s", p.move_timeout_s, 0.0, 600.0, true)?;
        check("policy.grab_timeout_s", p.grab_timeout_s, 0.0, 600.0, true)?;
        check_count("policy.attempts", u64::from(p.attempts), 1, 20)?;
        check_count("policy.retry_backoff_ms", p.retry_backoff_ms, 0, 60_000)?;
        let s = &self.suspender;
        check(
            "suspender.max_reduced_chi2",
            s.max_reduced_chi2,
            1.0,
            1000.0,
            true,
        )?;
        check("suspender.max_s0_change", s.max_s0_change, 0.0, 10.0, true)?;
        check(
            "suspender.max_angle_error_deg",
            s.max_angle_error_deg,
            0.0,
            90.0,
            true,
        )?;
        check_count(
            "suspender.max_reacquire",
            u64::from(s.max_reacquire),
            0,
            100,
        )?;
        check(
            "suspender.max_saturated_fraction",
            s.max_saturated_fraction,
            0.0,
            1.0,
            false,
        )?;
        if let Some(site) = &self.site {
            check("site.latitude_deg", site.latitude_deg, -90.0, 90.0, false)?;
            check(
                "site.longitude_deg",
                site.longitude_deg,
                -180.0,
                180.0,
                false,
            )?;
            check("site.elevation_m", site.elevation_m, -500.0, 9000.0, false)?;
        }
        self.simulation.validate()
    }

    /// Replaces a capture's `from_planner` with the angles the planner chose.
    pub fn resolve_angles(&mut self, angles_deg: Vec<f64>) -> Result<(), PlanError> {
        let Some(c) = self.capture_mut() else {
            return Err(invalid("capture", "(missing)", "a capture plan"));
        };
        let angles: Vec<f64> = angles_deg.iter().map(|a| a.rem_euclid(180.0)).collect();
        check_angles("capture.angles_deg", &angles, 3, 16)?;
        c.angles_deg = Some(angles);
        c.from_planner = None;
        Ok(())
    }

    /// Checks what depends on the camera's frame size (`width x height` pixels): the
    /// adaptive target rectangle must lie inside the frame. `run` checks it against the
    /// camera it opens, `plan check` against the simulated frame.
    pub fn check_frame(&self, width: u32, height: u32) -> Result<(), PlanError> {
        if let Some([x0, y0, x1, y1]) = self.adaptive().and_then(|a| a.target.rect) {
            if x1 > width || y1 > height {
                return Err(invalid(
                    "adaptive.target.rect",
                    format!("[{x0}, {y0}, {x1}, {y1}]"),
                    format!("inside the {width}x{height} frame"),
                ));
            }
        }
        Ok(())
    }

    /// The steps of the run, in order. An adaptive plan gives its darks and its first set;
    /// the loop adds the rest. A capture must have its angles resolved.
    pub fn steps(&self) -> Result<Vec<StepSpec>, PlanError> {
        Ok(match &self.acquisition {
            Acquisition::Capture(c) => c.steps()?,
            Acquisition::CalibrateNoise(c) => c.steps(),
            Acquisition::CalibrateAnalyzer(c) => c.steps(),
            Acquisition::TimeLapse(t) => t.steps(),
            Acquisition::Adaptive(a) => a.steps(),
            Acquisition::Continuous(c) => {
                // One set per half turn; each step a frame triggered at its angle.
                let mut steps = Vec::new();
                let angles = c.trigger_angles_deg();
                for h in 0..u64::from(c.half_turns) {
                    for (k, &a) in angles.iter().enumerate() {
                        steps.push(light_step(
                            Some(h),
                            format!("half turn {h} frame {k} {a} deg"),
                            a,
                            c.exposure_us,
                            c.gain_db,
                        ));
                    }
                }
                steps
            }
        })
    }

    /// The most frames the run can take (an adaptive plan's budget plus its darks; others:
    /// their steps).
    pub fn max_frames(&self) -> Result<u64, PlanError> {
        match &self.acquisition {
            Acquisition::Adaptive(a) => Ok(a.frame_budget as u64 + u64::from(a.darks)),
            _ => Ok(self.steps()?.len() as u64),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CAPTURE: &str = r#"
name = "t"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [1000, 2000]
repeats = 2
darks_before = 1
darks_after = 3
"#;

    /// Steps: darks, then repeats x exposures sets of 4 angles, then darks; set numbers run
    /// 0..4.
    #[test]
    fn capture_compiles_to_steps() {
        let plan = Plan::from_toml_str(CAPTURE).expect("plan");
        let steps = plan.steps().expect("steps");
        assert_eq!(steps.len(), 1 + 2 * 2 * 4 + 3);
        assert_eq!(steps[0].kind, FrameKind::Dark);
        assert_eq!(steps[1].set, Some(0));
        assert_eq!(steps[16].set, Some(3));
        assert_eq!(steps[16].exposure_us, 2000.0);
        assert!(steps[17..].iter().all(|s| s.kind == FrameKind::Dark));
    }

    /// The same plan in YAML is the same plan.
    #[test]
    fn yaml_equals_toml() {
        let yaml = "name: t\nkind: capture\ncapture:\n  angles_deg: [0, 45, 90, 135]\n  \
                    exposure_us: [1000, 2000]\n  repeats: 2\n  darks_before: 1\n  darks_after: 3\n";
        assert_eq!(
            Plan::from_yaml_str(yaml).expect("yaml"),
            Plan::from_toml_str(CAPTURE).expect("toml")
        );
    }

    /// A plan file without a name (or with a blank one) is named by its stem.
    #[test]
    fn a_plan_without_a_name_is_named_by_its_file() {
        let dir = std::env::temp_dir().join(format!("polar-plan-name-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let body = "kind = \"capture\"\n[capture]\nangles_deg = [0, 60, 120]\n\
                    exposure_us = [300]\nrepeats = 1\n";
        for (file, text) in [
            ("night-sky.toml", body.to_string()),
            ("blank.toml", format!("name = \" \"\n{body}")),
            ("kept.toml", format!("name = \"roof\"\n{body}")),
        ] {
            let path = dir.join(file);
            std::fs::write(&path, text).unwrap();
            let plan = Plan::from_path(&path).unwrap();
            let want = if file == "kept.toml" {
                "roof"
            } else {
                file.trim_end_matches(".toml")
            };
            assert_eq!(plan.name, want);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Errors name the field and the allowed range.
    #[test]
    fn errors_name_the_field() {
        let cases = [
            (
                CAPTURE.replace("repeats = 2", "repeats = 0"),
                "capture.repeats",
            ),
            (
                CAPTURE.replace("[0, 45, 90, 135]", "[0, 45, 200]"),
                "capture.angles_deg[2]",
            ),
            (
                CAPTURE.replace("[0, 45, 90, 135]", "[0, 0, 90]"),
                "capture.angles_deg",
            ),
            (
                CAPTURE.replace("[1000, 2000]", "[-5]"),
                "capture.exposure_us[0]",
            ),
            (
                CAPTURE.replace("repeats = 2", "repeats = \"x\""),
                "capture.repeats",
            ),
            (CAPTURE.replace("repeats = 2", "repats = 2"), "capture"),
            (
                CAPTURE.replace("kind = \"capture\"", "kind = \"adaptive\""),
                "adaptive",
            ),
            (
                format!("{CAPTURE}\n[policy]\nattempts = 0\n"),
                "policy.attempts",
            ),
        ];
        for (text, field) in cases {
            let e = Plan::from_toml_str(&text).expect_err(field).to_string();
            assert!(e.contains(field), "{field}: {e}");
            assert!(
                e.contains("allowed") || e.contains("expected") || e.contains("unknown"),
                "{e}"
            );
        }
    }

    /// An adaptive plan gives its darks and first set; its budget bounds the frames.
    #[test]
    fn adaptive_first_set() {
        let text = r#"
kind = "adaptive"
[adaptive]
initial_angles_deg = [0, 60, 120]
exposure_us = 3000
frame_budget = 12
darks = 2
target = { material = "panel" }
"#;
        let plan = Plan::from_toml_str(text).expect("plan");
        let steps = plan.steps().expect("steps");
        assert_eq!(steps.len(), 5);
        assert_eq!(plan.max_frames().expect("max"), 14);
        let bad = text.replace("frame_budget = 12", "frame_budget = 2");
        let e = Plan::from_toml_str(&bad).expect_err("budget").to_string();
        assert!(e.contains("adaptive.frame_budget"), "{e}");
    }

    /// Every example plan in examples/plans parses and validates, in TOML and YAML.
    #[test]
    fn example_plans_are_valid() {
        let examples = [
            include_str!("../../../examples/plans/capture.toml"),
            include_str!("../../../examples/plans/planner.toml"),
            include_str!("../../../examples/plans/calibrate_analyzer.toml"),
            include_str!("../../../examples/plans/timelapse.toml"),
            include_str!("../../../examples/plans/adaptive.toml"),
            include_str!("../../../examples/plans/continuous.toml"),
            include_str!("../../../examples/plans/continuous_from_planner.toml"),
        ];
        for text in examples {
            Plan::from_toml_str(text).expect("example plan");
        }
        let yaml = include_str!("../../../examples/plans/calibrate_noise.yaml");
        let plan = Plan::from_yaml_str(yaml).expect("yaml example");
        assert_eq!(plan.kind(), PlanKind::CalibrateNoise);
        let e = Plan::from_yaml_str(&yaml.replace("pairs: 1", "pairs: 0"))
            .expect_err("pairs")
            .to_string();
        assert!(e.contains("calibrate-noise.pairs"), "{e}");
    }

    /// Time-lapse sets start at their interval.
    #[test]
    fn time_lapse_schedule() {
        let text = r#"
kind = "time-lapse"
[time-lapse]
angles_deg = [0, 60, 120]
exposure_us = 3000
interval_s = 10
count = 3
"#;
        let steps = Plan::from_toml_str(text)
            .expect("plan")
            .steps()
            .expect("steps");
        let starts: Vec<f64> = steps.iter().filter_map(|s| s.not_before_s).collect();
        assert_eq!(starts, [0.0, 10.0, 20.0]);
    }
}
