//! Continuous-rotation plans (`kind = "continuous"`): the analyzer spins at a constant speed
//! and the camera exposes `frames_per_half_turn` frames per half turn, each while the analyzer
//! turns through a span, and the half turn's Stokes estimate uses the span rows.
//!
//! ```toml
//! kind = "continuous"
//! [continuous]
//! frames_per_half_turn = 4     # 3..=360, equally spaced: trigger k at k * 180 / N deg
//! exposure_us = 2000           # the span swept is speed * exposure, less than 180 / N deg
//! speed_deg_per_s = 360        # (0, 3600]; the stage's own limit is checked when it spins
//! half_turns = 10              # 1..=100000; one half turn is one Stokes set
//! trigger = "encoder"          # "encoder" (position-compare pulses) | "timestamps"
//! timing_sigma_us = 20         # timestamps: the timing uncertainty of a frame, [0, 1e6]
//! gain_db = 0
//! ```
//!
//! Instead of the three values `frames_per_half_turn`, `exposure_us` and `speed_deg_per_s`,
//! `from_planner = { target = "panel", background = "asphalt" }` asks the continuous planner
//! (`polar_planner::continuous`) for them ([`ContinuousFromPlanner`]; resolved before the run
//! by `polarimeter acquire run` and `polarimeter plan check`, see
//! [`crate::continuous_planner`]). Giving both is an error naming the fields; a section whose
//! `from_planner` is still unresolved fails [`Continuous::validate`].
//!
//! # The frames of a half turn
//!
//! Half turn `h` has frames `k = 0..N`. Frame `k` is triggered when the analyzer passes
//! `psi_k = k * 180 / N` degrees (modulo the half turn: the row's period is 180 degrees) and
//! exposes for `t`, so it integrates Malus's law over the span `[psi_k, psi_k + D]`,
//! `D = omega t`. Its row is `polar_model::span::span_row`: the centre's row with the
//! polarised terms scaled by `sinc D` (Meng (2012), Eq. 2.17 for the point row; the span
//! average is derived in `polar_model::span`). The plan requires `D < 180 / N`, so that an
//! exposure ends before the next trigger (a camera that reads one frame while it exposes the
//! next).
//!
//! # The estimate
//!
//! [`SpanEstimator`] is the OLS estimate `S = (W^T W)^-1 W^T (y - b)` with the span rows `W`
//! of `polar_model::span::span_signal` (fore-optics and real analyzer included; polarised terms
//! also scaled by the jitter's `e^{-2 sigma^2}` for a free-running camera), and its predicted
//! covariance per pixel is `span_signal`'s at the pixel's radiance. With point rows at the
//! span centres instead ([`SpanEstimator::point_rows`]) the polarised components come out
//! scaled by `sinc D`: the bias the span rows remove.

use crate::plan_error::PlanError;
use nalgebra::{Matrix3, Vector3};
use polar_model::sensor::SensorModel;
use polar_model::span::{span_signal, SpanExposure, SpanSignal};
use serde::{Deserialize, Serialize};

/// How each frame's analyzer span is measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum TriggerSource {
    /// The stage's position-compare output triggers the camera (GenICam `TriggerSource =
    /// Line`); each pulse reports its encoder count, the span's start.
    Encoder,
    /// The camera runs free; the span comes from the frame's timestamps and the stage's
    /// position samples, uncertain by `speed * timing_sigma_us`.
    Timestamps,
}

fn encoder() -> TriggerSource {
    TriggerSource::Encoder
}
fn one() -> u32 {
    1
}
fn twenty() -> f64 {
    20.0
}

/// What the planner of a `from_planner` section optimises (`polar_planner::continuous`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum FromPlannerObjective {
    /// The shortest time until the target's DoLP standard deviation is `dolp_sigma`.
    TimeToDolpSigma,
    /// The largest SCR of one half turn times half turns per second.
    ScrPerSecond,
}

impl FromPlannerObjective {
    /// The name as written in plans and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            FromPlannerObjective::TimeToDolpSigma => "time-to-dolp-sigma",
            FromPlannerObjective::ScrPerSecond => "scr-per-second",
        }
    }
}

/// Defaults of the planner's settings, shared with `polarimeter plan continuous`'s flags.
pub mod planner_defaults {
    /// The target's DoLP standard deviation to reach.
    pub const DOLP_SIGMA: f64 = 0.001;
    /// The most frames per half turn.
    pub const MAX_FRAMES_PER_HALF_TURN: u32 = 60;
    /// Saturation margin, standard deviations.
    pub const SATURATION_SIGMA: f64 = 3.0;
    /// Shortest exposure, us.
    pub const MIN_EXPOSURE_US: f64 = 10.0;
    /// Longest exposure, us.
    pub const MAX_EXPOSURE_US: f64 = 1e6;
    /// The camera's highest frame rate, Hz (the simulated camera's).
    pub const MAX_FRAME_RATE_HZ: f64 = 200.0;
    /// Dead time after each exposure, us (0: a camera that reads out while it exposes).
    pub const READOUT_US: f64 = 0.0;
}

fn time_to_dolp_sigma() -> FromPlannerObjective {
    FromPlannerObjective::TimeToDolpSigma
}
fn dolp_sigma_default() -> f64 {
    planner_defaults::DOLP_SIGMA
}
fn max_frames_default() -> u32 {
    planner_defaults::MAX_FRAMES_PER_HALF_TURN
}
fn saturation_sigma_default() -> f64 {
    planner_defaults::SATURATION_SIGMA
}
fn min_exposure_default() -> f64 {
    planner_defaults::MIN_EXPOSURE_US
}
fn max_exposure_default() -> f64 {
    planner_defaults::MAX_EXPOSURE_US
}
fn frame_rate_default() -> f64 {
    planner_defaults::MAX_FRAME_RATE_HZ
}
fn readout_default() -> f64 {
    planner_defaults::READOUT_US
}

/// `[continuous] from_planner`: frames per half turn, exposure and speed chosen by the
/// continuous planner for a target against a background of the plan's scene (the
/// `[simulation]` scene and camera, as a capture's `from_planner`), within the camera's and
/// the stage's limits. The settings default to `polarimeter plan continuous`'s flags; the
/// stage's limits not given are the simulated rig's stage ([`crate::continuous_planner`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ContinuousFromPlanner {
    /// Target material (a name in the scene).
    pub target: String,
    /// Background material.
    pub background: String,
    /// What to optimise.
    #[serde(default = "time_to_dolp_sigma")]
    pub objective: FromPlannerObjective,
    /// The target's DoLP standard deviation to reach (`time-to-dolp-sigma`), `(0, 0.999]`.
    #[serde(default = "dolp_sigma_default")]
    pub dolp_sigma: f64,
    /// The most frames per half turn, 3..=360.
    #[serde(default = "max_frames_default")]
    pub max_frames_per_half_turn: u32,
    /// Saturation margin: the brightest frame's mean plus this many standard deviations
    /// stays below saturation, `[0, 10]`.
    #[serde(default = "saturation_sigma_default")]
    pub saturation_sigma: f64,
    /// Shortest exposure, us, `(0, 1e7]`.
    #[serde(default = "min_exposure_default")]
    pub min_exposure_us: f64,
    /// Longest exposure, us, `[min_exposure_us, 1e7]`.
    #[serde(default = "max_exposure_default")]
    pub max_exposure_us: f64,
    /// The camera's highest frame rate, Hz, `(0, 100000]`.
    #[serde(default = "frame_rate_default")]
    pub max_frame_rate_hz: f64,
    /// Dead time after each exposure before the next, us, `[0, 1e7]`.
    #[serde(default = "readout_default")]
    pub readout_us: f64,
    /// The stage's top speed, deg/s, `(0, 3600]`; none: the simulated stage's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_speed_deg_per_s: Option<f64>,
    /// The stage's acceleration, deg/s^2, `(0, 1e7]`; none: the simulated stage's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acceleration_deg_per_s2: Option<f64>,
}

impl ContinuousFromPlanner {
    /// A table with the defaults for `target` against `background`.
    pub fn new(target: &str, background: &str) -> ContinuousFromPlanner {
        ContinuousFromPlanner {
            target: target.to_string(),
            background: background.to_string(),
            objective: time_to_dolp_sigma(),
            dolp_sigma: planner_defaults::DOLP_SIGMA,
            max_frames_per_half_turn: planner_defaults::MAX_FRAMES_PER_HALF_TURN,
            saturation_sigma: planner_defaults::SATURATION_SIGMA,
            min_exposure_us: planner_defaults::MIN_EXPOSURE_US,
            max_exposure_us: planner_defaults::MAX_EXPOSURE_US,
            max_frame_rate_hz: planner_defaults::MAX_FRAME_RATE_HZ,
            readout_us: planner_defaults::READOUT_US,
            max_speed_deg_per_s: None,
            acceleration_deg_per_s2: None,
        }
    }

    /// Checks every field's range (errors name `continuous.from_planner.<field>`, the value
    /// and the allowed range).
    pub fn validate(&self) -> Result<(), PlanError> {
        let f = |name: &str| format!("from_planner.{name}");
        for (name, v) in [("target", &self.target), ("background", &self.background)] {
            if v.trim().is_empty() {
                return Err(invalid(&f(name), "\"\"", "a material of the scene"));
            }
        }
        let range = |name: &str, v: f64, lo: f64, hi: f64, lo_open: bool| {
            let ok = v.is_finite() && v <= hi && if lo_open { v > lo } else { v >= lo };
            if ok {
                Ok(())
            } else {
                let open = if lo_open { "(" } else { "[" };
                Err(invalid(&f(name), v, format!("{open}{lo}, {hi}]")))
            }
        };
        range("dolp_sigma", self.dolp_sigma, 0.0, 0.999, true)?;
        let n = self.max_frames_per_half_turn;
        if !(3..=360).contains(&n) {
            return Err(invalid(&f("max_frames_per_half_turn"), n, "3..=360"));
        }
        range("saturation_sigma", self.saturation_sigma, 0.0, 10.0, false)?;
        range("min_exposure_us", self.min_exposure_us, 0.0, 1e7, true)?;
        range(
            "max_exposure_us",
            self.max_exposure_us,
            self.min_exposure_us,
            1e7,
            false,
        )?;
        range("max_frame_rate_hz", self.max_frame_rate_hz, 0.0, 1e5, true)?;
        range("readout_us", self.readout_us, 0.0, 1e7, false)?;
        if let Some(v) = self.max_speed_deg_per_s {
            range("max_speed_deg_per_s", v, 0.0, 3600.0, true)?;
        }
        if let Some(v) = self.acceleration_deg_per_s2 {
            range("acceleration_deg_per_s2", v, 0.0, 1e7, true)?;
        }
        Ok(())
    }
}

/// `[continuous]`. With `from_planner` given, `frames_per_half_turn`, `exposure_us` and
/// `speed_deg_per_s` are 0 until [`Continuous::resolve`] sets the planner's choice (and
/// [`Continuous::validate`] refuses the section until then).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(try_from = "ContinuousAsWritten", into = "ContinuousAsWritten")]
pub struct Continuous {
    /// Frames per half turn, 3..=360, equally spaced.
    pub frames_per_half_turn: u32,
    /// Exposure of each frame, microseconds, `(0, 1e7]`, and short enough that the span ends
    /// before the next trigger.
    pub exposure_us: f64,
    /// The analyzer's speed, degrees per second, `(0, 3600]`.
    pub speed_deg_per_s: f64,
    /// Half turns (Stokes sets), 1..=100000.
    pub half_turns: u32,
    /// How spans are measured.
    pub trigger: TriggerSource,
    /// Timing uncertainty of a free-running frame (timestamps), microseconds, `[0, 1e6]`.
    pub timing_sigma_us: f64,
    /// Analog gain, dB, `[0, 48]`.
    pub gain_db: f64,
    /// The planner chooses the three values above (until resolved).
    pub from_planner: Option<ContinuousFromPlanner>,
}

/// `[continuous]` as written: the three values optional, or `from_planner`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
struct ContinuousAsWritten {
    /// Frames per half turn, 3..=360, equally spaced (or `from_planner`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    frames_per_half_turn: Option<u32>,
    /// Exposure of each frame, microseconds, `(0, 1e7]`, short enough that the span ends
    /// before the next trigger (or `from_planner`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    exposure_us: Option<f64>,
    /// The analyzer's speed, degrees per second, `(0, 3600]` (or `from_planner`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    speed_deg_per_s: Option<f64>,
    /// Half turns (Stokes sets), 1..=100000.
    #[serde(default = "one")]
    half_turns: u32,
    /// How spans are measured: `encoder` (the stage's position-compare pulses trigger the
    /// camera) or `timestamps` (the stage's position reads against the host's clock).
    #[serde(default = "encoder")]
    trigger: TriggerSource,
    /// Timing uncertainty of a frame's exposure end (timestamps), microseconds, `[0, 1e6]`.
    #[serde(default = "twenty")]
    timing_sigma_us: f64,
    /// Analog gain, dB, `[0, 48]`.
    #[serde(default)]
    gain_db: f64,
    /// The continuous planner chooses frames per half turn, exposure and speed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    from_planner: Option<ContinuousFromPlanner>,
}

/// Why a `[continuous]` section as written is not one: the three values and `from_planner`
/// both given, or neither.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SectionError {
    /// A value the planner chooses is given beside `from_planner`.
    #[error(
        "continuous.{field} = {value} is given with continuous.from_planner: allowed {EITHER}"
    )]
    Both {
        /// The value's field.
        field: &'static str,
        /// The value, as written.
        value: String,
    },
    /// Neither all three values nor `from_planner`.
    #[error("continuous.{field} is missing: allowed {EITHER}")]
    Missing {
        /// The first missing field.
        field: &'static str,
    },
}

const EITHER: &str = "either frames_per_half_turn, exposure_us and speed_deg_per_s (all three), \
                      or from_planner (the planner chooses the three), not both";

impl TryFrom<ContinuousAsWritten> for Continuous {
    type Error = SectionError;

    fn try_from(w: ContinuousAsWritten) -> Result<Continuous, SectionError> {
        let given: Vec<(&'static str, String)> = [
            (
                "frames_per_half_turn",
                w.frames_per_half_turn.map(|v| v.to_string()),
            ),
            ("exposure_us", w.exposure_us.map(|v| v.to_string())),
            ("speed_deg_per_s", w.speed_deg_per_s.map(|v| v.to_string())),
        ]
        .into_iter()
        .filter_map(|(name, v)| v.map(|v| (name, v)))
        .collect();
        let (frames, exposure_us, speed) = match (&w.from_planner, given.first()) {
            (Some(_), Some((field, value))) => {
                return Err(SectionError::Both {
                    field,
                    value: value.clone(),
                })
            }
            (Some(_), None) => (0, 0.0, 0.0),
            (None, _) => match (w.frames_per_half_turn, w.exposure_us, w.speed_deg_per_s) {
                (Some(n), Some(e), Some(v)) => (n, e, v),
                (n, e, _) => {
                    let field = if n.is_none() {
                        "frames_per_half_turn"
                    } else if e.is_none() {
                        "exposure_us"
                    } else {
                        "speed_deg_per_s"
                    };
                    return Err(SectionError::Missing { field });
                }
            },
        };
        Ok(Continuous {
            frames_per_half_turn: frames,
            exposure_us,
            speed_deg_per_s: speed,
            half_turns: w.half_turns,
            trigger: w.trigger,
            timing_sigma_us: w.timing_sigma_us,
            gain_db: w.gain_db,
            from_planner: w.from_planner,
        })
    }
}

impl From<Continuous> for ContinuousAsWritten {
    fn from(c: Continuous) -> ContinuousAsWritten {
        let chosen = c.from_planner.is_none();
        ContinuousAsWritten {
            frames_per_half_turn: chosen.then_some(c.frames_per_half_turn),
            exposure_us: chosen.then_some(c.exposure_us),
            speed_deg_per_s: chosen.then_some(c.speed_deg_per_s),
            half_turns: c.half_turns,
            trigger: c.trigger,
            timing_sigma_us: c.timing_sigma_us,
            gain_db: c.gain_db,
            from_planner: c.from_planner,
        }
    }
}

fn invalid(field: &str, value: impl std::fmt::Display, allowed: impl Into<String>) -> PlanError {
    PlanError::Invalid {
        field: format!("continuous.{field}"),
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

impl Continuous {
    /// Checks the section as a plan file may hold it: with `from_planner` still to be
    /// resolved, the table's fields and the fields the planner does not choose; otherwise
    /// [`Continuous::validate`].
    pub fn validate_as_written(&self) -> Result<(), PlanError> {
        match &self.from_planner {
            Some(fp) => {
                fp.validate()?;
                self.validate_common()
            }
            None => self.validate(),
        }
    }

    /// Sets the planner's choice (frames per half turn, exposure in us, speed in deg/s) in
    /// place of `from_planner` and checks the section; an error names the field and says the
    /// planner chose it.
    pub fn resolve(
        &mut self,
        frames_per_half_turn: u32,
        exposure_us: f64,
        speed_deg_per_s: f64,
    ) -> Result<(), PlanError> {
        let mut resolved = Continuous {
            frames_per_half_turn,
            exposure_us,
            speed_deg_per_s,
            from_planner: None,
            ..self.clone()
        };
        resolved.validate().map_err(|e| match e {
            PlanError::Invalid {
                field,
                value,
                allowed,
            } => PlanError::Invalid {
                field: format!("{field} (chosen by continuous.from_planner)"),
                value,
                allowed: format!(
                    "{allowed}; change the from_planner limits (e.g. readout_us > 0 keeps \
                     each exposure shorter than its frame interval)"
                ),
            },
            other => other,
        })?;
        std::mem::swap(self, &mut resolved);
        Ok(())
    }

    /// Checks every field's range (errors name `continuous.<field>`, the value and the
    /// allowed range). A section whose `from_planner` is unresolved is an error that names
    /// the commands that resolve it.
    pub fn validate(&self) -> Result<(), PlanError> {
        if self.from_planner.is_some() {
            return Err(invalid(
                "from_planner",
                "(unresolved)",
                "frames_per_half_turn, exposure_us and speed_deg_per_s chosen by the planner \
                 before the run: `polarimeter acquire run` and `polarimeter plan check` \
                 resolve it (polar_engine::continuous_planner::resolve)",
            ));
        }
        let n = self.frames_per_half_turn;
        if !(3..=360).contains(&n) {
            return Err(invalid("frames_per_half_turn", n, "3..=360"));
        }
        let in_range = |v: f64, lo: f64, hi: f64, lo_open: bool| {
            v.is_finite() && v <= hi && if lo_open { v > lo } else { v >= lo }
        };
        if !in_range(self.speed_deg_per_s, 0.0, 3600.0, true) {
            return Err(invalid(
                "speed_deg_per_s",
                self.speed_deg_per_s,
                "(0, 3600]",
            ));
        }
        if !in_range(self.exposure_us, 0.0, 1e7, true) {
            return Err(invalid("exposure_us", self.exposure_us, "(0, 1e7]"));
        }
        let longest_us = self.interval_deg() / self.speed_deg_per_s * 1e6;
        if self.exposure_us >= longest_us {
            return Err(invalid(
                "exposure_us",
                self.exposure_us,
                format!(
                    "below {longest_us:.3} us: the span swept (speed_deg_per_s {} x exposure) \
                     must end before the next trigger, {:.4} deg later",
                    self.speed_deg_per_s,
                    self.interval_deg()
                ),
            ));
        }
        self.validate_common()
    }

    /// The fields the planner does not choose.
    fn validate_common(&self) -> Result<(), PlanError> {
        let in_range = |v: f64, lo: f64, hi: f64| v.is_finite() && v <= hi && v >= lo;
        if !(1..=100_000).contains(&self.half_turns) {
            return Err(invalid("half_turns", self.half_turns, "1..=100000"));
        }
        if !in_range(self.timing_sigma_us, 0.0, 1e6) {
            return Err(invalid("timing_sigma_us", self.timing_sigma_us, "[0, 1e6]"));
        }
        if !in_range(self.gain_db, 0.0, 48.0) {
            return Err(invalid("gain_db", self.gain_db, "[0, 48]"));
        }
        Ok(())
    }

    /// Degrees between two triggers, `180 / N`.
    pub fn interval_deg(&self) -> f64 {
        180.0 / f64::from(self.frames_per_half_turn.max(1))
    }

    /// The span each frame sweeps, degrees: speed times exposure.
    pub fn span_deg(&self) -> f64 {
        self.speed_deg_per_s * self.exposure_us * 1e-6
    }

    /// The trigger angles of a half turn, degrees: `k * 180 / N`.
    pub fn trigger_angles_deg(&self) -> Vec<f64> {
        (0..self.frames_per_half_turn)
            .map(|k| f64::from(k) * self.interval_deg())
            .collect()
    }

    /// The spans of a half turn, radians: `(psi_k, psi_k + D)`.
    pub fn spans_rad(&self) -> Vec<(f64, f64)> {
        let d = self.span_deg();
        self.trigger_angles_deg()
            .into_iter()
            .map(|a| (a.to_radians(), (a + d).to_radians()))
            .collect()
    }

    /// The standard uncertainty of each span's angles, radians: 0 for encoder triggers (one
    /// encoder count is far below any other error), the speed times the timing uncertainty
    /// for timestamps.
    pub fn angle_sigma_rad(&self) -> f64 {
        match self.trigger {
            TriggerSource::Encoder => 0.0,
            TriggerSource::Timestamps => {
                (self.speed_deg_per_s * self.timing_sigma_us * 1e-6).to_radians()
            }
        }
    }

    /// Time at speed, seconds: the half turns at `speed_deg_per_s` (the spin-up before the
    /// first trigger is the stage's and not included).
    pub fn duration_at_speed_s(&self) -> f64 {
        f64::from(self.half_turns) * 180.0 / self.speed_deg_per_s
    }
}

/// The OLS Stokes estimate of one half turn's frames with given rows, and its predicted
/// covariance (module docs).
#[derive(Debug, Clone)]
pub struct SpanEstimator {
    /// The rows the estimate assumes (one per frame).
    pub rows: Vec<Vector3<f64>>,
    /// `(W^T W)^-1 W^T`, 3 x frames, row-major per Stokes component.
    pinv: Vec<[f64; 3]>,
    /// The dark level of each frame, DN (offset and dark signal).
    dark_dn: Vec<f64>,
    sensor: SensorModel,
    spans_rad: Vec<(f64, f64)>,
    exposure_s: f64,
    angle_sigma_rad: f64,
}

/// Why an estimate could not be made.
fn model_err(field: &str) -> impl Fn(polar_model::error::ModelError) -> PlanError + '_ {
    move |e| PlanError::Invalid {
        field: field.to_string(),
        value: "(model)".into(),
        allowed: e.to_string(),
    }
}

impl SpanEstimator {
    fn from_rows(
        sensor: &SensorModel,
        spans_rad: &[(f64, f64)],
        exposure_s: f64,
        angle_sigma_rad: f64,
        rows: Vec<Vector3<f64>>,
    ) -> Result<SpanEstimator, PlanError> {
        let dark = span_signal(
            sensor,
            spans_rad,
            &SpanExposure {
                t_int_s: exposure_s,
                radiance_w_m2_sr: Vector3::zeros(),
                angle_sigma_rad,
            },
        )
        .map_err(model_err("continuous"))?;
        let mut wtw = Matrix3::zeros();
        for r in &rows {
            wtw += r * r.transpose();
        }
        let inv = wtw.try_inverse().ok_or_else(|| PlanError::Invalid {
            field: "continuous.frames_per_half_turn".into(),
            value: rows.len().to_string(),
            allowed: "spans whose rows determine S0, S1 and S2".into(),
        })?;
        // `y - b = K G W L`: the estimate of `K G L` (DN) is `(W^T W)^-1 W^T (y - b)`.
        let pinv = rows
            .iter()
            .map(|r| {
                let c = inv * r;
                [c[0], c[1], c[2]]
            })
            .collect();
        Ok(SpanEstimator {
            rows,
            pinv,
            dark_dn: dark.mean_dn,
            sensor: sensor.clone(),
            spans_rad: spans_rad.to_vec(),
            exposure_s,
            angle_sigma_rad,
        })
    }

    /// The estimator with the span rows of `spans_rad` through `sensor` (exposure
    /// `exposure_s`, centre-angle uncertainty `angle_sigma_rad`). Errors name the field.
    pub fn new(
        sensor: &SensorModel,
        spans_rad: &[(f64, f64)],
        exposure_s: f64,
        angle_sigma_rad: f64,
    ) -> Result<SpanEstimator, PlanError> {
        let s = span_signal(
            sensor,
            spans_rad,
            &SpanExposure {
                t_int_s: exposure_s,
                radiance_w_m2_sr: Vector3::new(1.0, 0.0, 0.0),
                angle_sigma_rad,
            },
        )
        .map_err(model_err("continuous"))?;
        SpanEstimator::from_rows(sensor, spans_rad, exposure_s, angle_sigma_rad, s.rows)
    }

    /// The estimator that ignores the smear: point rows at each span's centre (the rows of a
    /// still analyzer there). Its polarised components are biased by `sinc D`.
    pub fn point_rows(
        sensor: &SensorModel,
        spans_rad: &[(f64, f64)],
        exposure_s: f64,
    ) -> Result<SpanEstimator, PlanError> {
        let centres: Vec<(f64, f64)> = spans_rad
            .iter()
            .map(|&(a, b)| (0.5 * (a + b), 0.5 * (a + b)))
            .collect();
        let s = span_signal(
            sensor,
            &centres,
            &SpanExposure {
                t_int_s: exposure_s,
                radiance_w_m2_sr: Vector3::new(1.0, 0.0, 0.0),
                angle_sigma_rad: 0.0,
            },
        )
        .map_err(model_err("continuous"))?;
        SpanEstimator::from_rows(sensor, spans_rad, exposure_s, 0.0, s.rows)
    }

    /// The Stokes estimate (DN of `K G L`) of one pixel from its value in each frame, DN.
    pub fn estimate(&self, frames_dn: &[f64]) -> Vector3<f64> {
        let mut s = Vector3::zeros();
        for ((y, b), c) in frames_dn.iter().zip(&self.dark_dn).zip(&self.pinv) {
            let v = y - b;
            s += Vector3::new(c[0] * v, c[1] * v, c[2] * v);
        }
        s
    }

    /// The predicted frames and Stokes covariance for a pixel of radiance `radiance`
    /// (W m^-2 sr^-1), from the span rows (`polar_model::span::span_signal`).
    pub fn predict(&self, radiance: Vector3<f64>) -> Result<SpanSignal, PlanError> {
        span_signal(
            &self.sensor,
            &self.spans_rad,
            &SpanExposure {
                t_int_s: self.exposure_s,
                radiance_w_m2_sr: radiance,
                angle_sigma_rad: self.angle_sigma_rad,
            },
        )
        .map_err(model_err("continuous"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn section() -> Continuous {
        Continuous {
            frames_per_half_turn: 4,
            exposure_us: 2000.0,
            speed_deg_per_s: 360.0,
            half_turns: 3,
            trigger: TriggerSource::Encoder,
            timing_sigma_us: 20.0,
            gain_db: 0.0,
            from_planner: None,
        }
    }

    /// Spans: 4 frames per half turn at 360 deg/s and 2 ms sweep 0.72 deg each from 0, 45,
    /// 90, 135 deg (exact in binary to 1e-12 deg); a timestamps run's angle sigma is speed x
    /// timing sigma (360 deg/s x 20 us = 0.0072 deg).
    #[test]
    fn spans_and_sigma() {
        let c = section();
        c.validate().expect("valid");
        assert_eq!(c.trigger_angles_deg(), vec![0.0, 45.0, 90.0, 135.0]);
        assert!((c.span_deg() - 0.72).abs() < 1e-12);
        assert_eq!(c.angle_sigma_rad(), 0.0);
        let t = Continuous {
            trigger: TriggerSource::Timestamps,
            ..section()
        };
        assert!((t.angle_sigma_rad().to_degrees() - 0.0072).abs() < 1e-15);
        assert!((c.duration_at_speed_s() - 1.5).abs() < 1e-12);
    }

    /// A section with `from_planner` parses with the table's defaults (those of `plan
    /// continuous`), passes the plan's check as written, is refused by the run's check until
    /// resolved, and survives a round trip through TOML (the GUI's YAML-to-TOML path) without
    /// the placeholder values; [`Continuous::resolve`] sets the three values as given (0
    /// tolerance) and drops the table; a choice the section refuses names the field and the
    /// planner.
    #[test]
    fn from_planner_parses_checks_and_resolves() {
        let text = "kind = \"continuous\"\n[continuous]\nhalf_turns = 2\nfrom_planner = { \
                    target = \"panel\", background = \"asphalt\" }\n";
        let plan = crate::plan::Plan::from_toml_str(text).expect("plan");
        let c = plan.continuous().cloned().expect("section");
        let fp = c.from_planner.clone().expect("table");
        assert_eq!(fp, ContinuousFromPlanner::new("panel", "asphalt"));
        assert_eq!(fp.objective.name(), "time-to-dolp-sigma");
        let e = c.validate().expect_err("unresolved").to_string();
        assert!(
            e.contains("continuous.from_planner") && e.contains("plan check"),
            "{e}"
        );
        let again = crate::plan::Plan::from_toml_str(&toml::to_string(&plan).expect("toml"))
            .expect("round trip");
        assert_eq!(again, plan);
        let mut r = c.clone();
        r.resolve(12, 1234.5, 360.0).expect("resolve");
        assert_eq!(
            (r.frames_per_half_turn, r.exposure_us, r.speed_deg_per_s),
            (12, 1234.5, 360.0)
        );
        assert!(r.from_planner.is_none());
        r.validate().expect("valid");
        let mut bad = c.clone();
        let e = bad
            .resolve(12, 50_000.0, 360.0)
            .expect_err("exposure beyond the interval")
            .to_string();
        assert!(
            e.contains("continuous.exposure_us (chosen by continuous.from_planner)"),
            "{e}"
        );
        assert!(bad.from_planner.is_some());
    }

    /// Each bad field is named with its value and the allowed range; an exposure whose span
    /// reaches the next trigger is refused with the longest allowed exposure.
    #[test]
    fn errors_name_the_field() {
        let cases: Vec<(Continuous, &str)> = vec![
            (
                Continuous {
                    frames_per_half_turn: 2,
                    ..section()
                },
                "continuous.frames_per_half_turn",
            ),
            (
                Continuous {
                    speed_deg_per_s: 0.0,
                    ..section()
                },
                "continuous.speed_deg_per_s",
            ),
            (
                Continuous {
                    exposure_us: 125_000.0,
                    ..section()
                },
                "continuous.exposure_us",
            ),
            (
                Continuous {
                    half_turns: 0,
                    ..section()
                },
                "continuous.half_turns",
            ),
            (
                Continuous {
                    timing_sigma_us: -1.0,
                    ..section()
                },
                "continuous.timing_sigma_us",
            ),
            (
                Continuous {
                    gain_db: 50.0,
                    ..section()
                },
                "continuous.gain_db",
            ),
        ];
        for (c, field) in cases {
            let e = c.validate().expect_err(field).to_string();
            assert!(e.contains(field), "{e}");
        }
        // 45 deg between triggers at 360 deg/s: the exposure must stay below 125 ms.
        let e = Continuous {
            exposure_us: 125_000.0,
            ..section()
        }
        .validate()
        .expect_err("too long")
        .to_string();
        assert!(e.contains("below 125000.000 us"), "{e}");
        Continuous {
            exposure_us: 124_999.0,
            ..section()
        }
        .validate()
        .expect("just shorter");
    }
}
