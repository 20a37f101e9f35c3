//! Continuous rotation: how many frames per half turn, how long each exposure and how fast the
//! analyzer spins, within the camera's and the stage's limits, and which limit binds.
//!
//! # The set
//!
//! The analyzer turns at `omega` (rad/s) and the camera takes `N >= 3` frames per half turn
//! (a half turn, `pi`, is one full period of the analyzer's modulation), equally spaced: frame
//! `k` starts every `Delta = pi / (N omega)` seconds and exposes for `t`, so it integrates over
//! the span `D = omega t` centred on `k pi / N` (the phase of the first trigger; the figures are
//! given at phase 0). Its measurement row is the span row of `polar_model::span` (Malus's law
//! averaged over the span: the polarised terms scaled by `sin D / D`), and the half turn's
//! Stokes estimate and its covariance are `polar_model::span::span_signal`'s: the sensor
//! noise of the camera model and, for a free-running camera whose angles come from timestamps,
//! the timing uncertainty `sigma_t` as an angle error `omega sigma_t` on every span.
//!
//! # The limits
//!
//! * Frame rate and readout: `Delta >= max(t + t_readout, 1 / f_max)` (a camera that reads
//!   one frame while it exposes the next has `t_readout = 0`). So `D <= pi / N`.
//! * Exposure range: `t_min <= t <= t_max`.
//! * Saturation: the brightest frame of either class over the analyzer's phase
//!   (`polar_model::span::span_peak`: mean plus `k` standard deviations, sensor noise and
//!   texture) stays below the camera's saturation level.
//! * Stage: `omega <= omega_max`; reaching `omega` from rest at acceleration `a` takes
//!   `omega / a` seconds before the first half turn (the spin-up, whose frames are not used).
//! * Stokes conditioning: the ideal span rows `[1, sinc D cos 2psi, sinc D sin 2psi]` of the
//!   set have a condition number at most [`crate::stokes::STOKES_MAX_CONDITION`], the rule of
//!   the step-and-shoot sets. For equally spaced frames it is `sqrt 2 / sinc D <= 1.71`
//!   (`D <= pi / 3`), so the rule holds for every set the frame timing allows; it is checked
//!   anyway and reported.
//! * Frames per half turn at most a cap (the data rate the user accepts).
//!
//! # The objectives
//!
//! * [`Objective::TimeToDolpSigma`]: the time until the target's DoLP standard deviation
//!   reaches `sigma*`, `omega / a + m pi / omega` with `m = max(1, (sigma_1 / sigma*)^2)` half
//!   turns, `sigma_1` that of one half turn (delta method on the half turn's Stokes
//!   covariance: averaging `m` independent half turns divides the covariance by `m`). `m` is
//!   kept real (the last half turn counted in part), so the objective is smooth; the whole
//!   half turns are reported beside it.
//! * [`Objective::ScrPerSecond`]: the target-background SCR of one half turn's frames
//!   (`d^T (A Sigma_b + I)^-1 A d`, `A = sum_k w_k w_k^T / v_k`, as [`crate::scr`]), times half
//!   turns per second, `omega / pi`: the SCR of independent half-turn looks gathered per second.
//!
//! # The search
//!
//! For fixed `N` and `omega`, a longer exposure always helps both objectives: the polarised
//! signal `t sinc(omega t)` grows while `D < 1.166` (where `tan D = 2 D`), and `D <= pi / 3`
//! here; the jitter's variance scales with the signal's square, so it does not change this. So
//! the exposure is the longest the limits allow (saturation by bisection on `log t`). For each
//! `N` from 3 to the cap, `omega` is scanned on a logarithmic grid from half the slowest useful
//! speed (where `t_max` fills the frame interval) to the fastest the limits allow, the best
//! grid point refined by golden-section search in `log omega` between its neighbours, and the
//! ends of the range scored exactly. The tests compare the answer with a brute-force grid over
//! `(N, t, omega)`.
//!
//! # Which limit binds
//!
//! A limit binds when loosening it by 1 % (the top speed, acceleration, frame rate, full well
//! and exposure range up by 1 %, the readout down by 1 %, the frame cap up by one frame)
//! improves the objective by more than 1e-6 relative after re-optimising; the improvement is
//! reported with it.

use crate::log_search::{bisect, scan_then_golden};
use crate::stokes::STOKES_MAX_CONDITION;
use crate::PlanError;
use nalgebra::{Matrix3, Vector3};
use polar_model::sensor::SensorModel;
use polar_model::span::{sinc, span_peak, span_signal, SpanExposure, SpanSignal};
use std::f64::consts::PI;

/// Points of the logarithmic speed scan per `N`.
const SPEED_SCAN: usize = 120;
/// Golden-section iterations in `log omega` (the bracket shrinks by 0.618 each).
const GOLDEN_ITERATIONS: usize = 70;
/// Bisection steps on `log t` for the saturation limit.
pub(crate) const SATURATION_BISECTIONS: usize = 60;
/// Relative step by which a limit is loosened to see whether it binds.
pub const LOOSEN: f64 = 0.01;
/// Relative improvement of the objective above which a loosened limit counts as binding.
pub const BINDS_ABOVE: f64 = 1e-6;
/// The largest cap on frames per half turn accepted.
pub const MAX_FRAMES_PER_HALF_TURN: usize = 360;

/// The camera's limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraLimits {
    /// Shortest exposure, s, `> 0`.
    pub min_exposure_s: f64,
    /// Longest exposure, s, `>= min_exposure_s`, at most 1e5.
    pub max_exposure_s: f64,
    /// Highest frame rate, Hz, `> 0`.
    pub max_frame_rate_hz: f64,
    /// Dead time after each exposure before the next can start, s, `>= 0` (0 for a camera
    /// that reads out while it exposes).
    pub readout_s: f64,
    /// Saturation margin: the brightest frame's mean plus this many standard deviations stays
    /// below saturation, `[0, 10]`.
    pub saturation_sigma: f64,
}

/// The stage's limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageLimits {
    /// Top speed, rad/s, `> 0`.
    pub max_speed_rad_per_s: f64,
    /// Acceleration, rad/s^2, `> 0`.
    pub acceleration_rad_per_s2: f64,
}

/// One class of the scene: its mean band radiance and texture at the aperture.
#[derive(Debug, Clone, PartialEq)]
pub struct ClassRadiance {
    /// The material's name.
    pub name: String,
    /// Mean band Stokes radiance `[S0, S1, S2]`, W m^-2 sr^-1, `S0 > 0`.
    pub mean_w_m2_sr: Vector3<f64>,
    /// Texture covariance over the class's pixels, (W m^-2 sr^-1)^2, symmetric.
    pub cov_w2_m4_sr2: Matrix3<f64>,
}

/// What the planner optimises.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Objective {
    /// The shortest time until the target's DoLP standard deviation is `dolp_sigma`, in
    /// `(0, 1)`.
    TimeToDolpSigma {
        /// The DoLP standard deviation to reach.
        dolp_sigma: f64,
    },
    /// The largest SCR of one half turn times half turns per second.
    ScrPerSecond,
}

/// The planner's inputs.
#[derive(Debug, Clone)]
pub struct ContinuousProblem {
    /// The camera through its band (the noise model).
    pub sensor: SensorModel,
    /// The target class.
    pub target: ClassRadiance,
    /// The background class.
    pub background: ClassRadiance,
    /// The scene's other classes: not in the objective, but no frame of theirs may saturate
    /// either (a bright metal panel beside the target and background).
    pub others: Vec<ClassRadiance>,
    /// The camera's limits.
    pub camera: CameraLimits,
    /// The stage's limits.
    pub stage: StageLimits,
    /// Timing uncertainty of each frame, s (0 for frames triggered at encoder positions).
    pub timing_sigma_s: f64,
    /// The most frames per half turn, `3..=360`.
    pub max_frames_per_half_turn: usize,
    /// What to optimise.
    pub objective: Objective,
}

/// A limit of the camera or the stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Limit {
    /// The stage's top speed.
    StageSpeed,
    /// The stage's acceleration (the spin-up before the first half turn).
    StageAcceleration,
    /// The camera's highest frame rate.
    FrameRate,
    /// The camera's readout (dead time between exposures).
    Readout,
    /// Saturation of the brightest frame.
    Saturation,
    /// The camera's exposure range.
    ExposureRange,
    /// The cap on frames per half turn.
    FrameCount,
}

impl Limit {
    /// Every limit, in the order they are reported.
    pub const ALL: [Limit; 7] = [
        Limit::StageSpeed,
        Limit::StageAcceleration,
        Limit::FrameRate,
        Limit::Readout,
        Limit::Saturation,
        Limit::ExposureRange,
        Limit::FrameCount,
    ];

    /// The limit's name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Limit::StageSpeed => "stage_speed",
            Limit::StageAcceleration => "stage_acceleration",
            Limit::FrameRate => "frame_rate",
            Limit::Readout => "readout",
            Limit::Saturation => "saturation",
            Limit::ExposureRange => "exposure_range",
            Limit::FrameCount => "frame_count",
        }
    }
}

/// A binding limit and what loosening it would give.
#[derive(Debug, Clone, PartialEq)]
pub struct Binding {
    /// The limit.
    pub limit: Limit,
    /// Relative improvement of the objective from loosening it by [`LOOSEN`].
    pub gain: f64,
    /// In words, with the limit's value.
    pub message: String,
}

/// The planner's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct ContinuousChoice {
    /// Frames per half turn `N`.
    pub frames_per_half_turn: usize,
    /// Exposure of each frame, s.
    pub exposure_s: f64,
    /// The analyzer's speed, rad/s.
    pub speed_rad_per_s: f64,
    /// Time from one frame's start to the next, s.
    pub frame_interval_s: f64,
    /// Angle each frame spans, rad.
    pub span_rad: f64,
    /// Time per half turn (one Stokes set), s.
    pub half_turn_s: f64,
    /// Spin-up from rest to the speed, s.
    pub spin_up_s: f64,
    /// Condition number of the ideal span rows.
    pub condition: f64,
    /// The target's `K G S0`, DN (the scale of the Stokes estimate).
    pub s0_dn: f64,
    /// Standard deviations of the target's `S0`, `S1`, `S2` from one half turn, DN.
    pub sigma_stokes_dn: [f64; 3],
    /// The target's DoLP.
    pub dolp: f64,
    /// Standard deviation of the target's DoLP from one half turn (delta method).
    pub sigma_dolp: f64,
    /// SCR of one half turn.
    pub scr: f64,
    /// SCR of one half turn times half turns per second, 1/s.
    pub scr_per_s: f64,
    /// Half turns to the DoLP target (real; [`Objective::TimeToDolpSigma`] only).
    pub half_turns: Option<f64>,
    /// Spin-up plus the half turns to the DoLP target, s ([`Objective::TimeToDolpSigma`]).
    pub time_to_target_s: Option<f64>,
    /// The brightest frame (mean plus the saturation margin) as a fraction of saturation.
    pub peak_fraction: f64,
    /// The objective's value (the time in s, or minus the SCR per second).
    pub objective_value: f64,
    /// The limits that bind.
    pub binds: Vec<Binding>,
}

/// The limits as the search uses them (loosened copies for the binding test).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Limits {
    camera: CameraLimits,
    stage: StageLimits,
    saturation_scale: f64,
    max_n: usize,
}

/// One scored point.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Point {
    n: usize,
    t: f64,
    omega: f64,
    value: f64,
}

fn out_of_range(field: &'static str, value: f64, allowed: &'static str) -> PlanError {
    PlanError::OutOfRange {
        field,
        value,
        allowed,
    }
}

pub(crate) fn check(p: &ContinuousProblem) -> Result<(), PlanError> {
    let c = &p.camera;
    let pos = |field, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(out_of_range(field, v, "finite, > 0"))
        }
    };
    pos("camera.min_exposure_s", c.min_exposure_s)?;
    if !(c.max_exposure_s.is_finite()
        && c.max_exposure_s >= c.min_exposure_s
        && c.max_exposure_s <= 1e5)
    {
        return Err(out_of_range(
            "camera.max_exposure_s",
            c.max_exposure_s,
            "finite, >= camera.min_exposure_s, <= 1e5 s",
        ));
    }
    pos("camera.max_frame_rate_hz", c.max_frame_rate_hz)?;
    if !(c.readout_s.is_finite() && c.readout_s >= 0.0) {
        return Err(out_of_range(
            "camera.readout_s",
            c.readout_s,
            "finite, >= 0",
        ));
    }
    if !(c.saturation_sigma.is_finite() && (0.0..=10.0).contains(&c.saturation_sigma)) {
        return Err(out_of_range(
            "camera.saturation_sigma",
            c.saturation_sigma,
            "[0, 10]",
        ));
    }
    pos("stage.max_speed_rad_per_s", p.stage.max_speed_rad_per_s)?;
    pos(
        "stage.acceleration_rad_per_s2",
        p.stage.acceleration_rad_per_s2,
    )?;
    if !(p.timing_sigma_s.is_finite() && p.timing_sigma_s >= 0.0) {
        return Err(out_of_range(
            "timing_sigma_s",
            p.timing_sigma_s,
            "finite, >= 0",
        ));
    }
    if !(3..=MAX_FRAMES_PER_HALF_TURN).contains(&p.max_frames_per_half_turn) {
        return Err(out_of_range(
            "max_frames_per_half_turn",
            p.max_frames_per_half_turn as f64,
            "3 to 360",
        ));
    }
    if let Objective::TimeToDolpSigma { dolp_sigma } = p.objective {
        if !(dolp_sigma.is_finite() && dolp_sigma > 0.0 && dolp_sigma < 1.0) {
            return Err(out_of_range("objective.dolp_sigma", dolp_sigma, "(0, 1)"));
        }
    }
    for (field, class) in [("target", &p.target), ("background", &p.background)] {
        let m = class.mean_w_m2_sr;
        if !(m.iter().all(|v| v.is_finite()) && m[0] > 0.0) {
            return Err(PlanError::invalid(
                field,
                format!(
                    "{}: mean radiance {m:?}: allowed finite with S0 > 0",
                    class.name
                ),
            ));
        }
        if class.cov_w2_m4_sr2.iter().any(|v| !v.is_finite()) {
            return Err(PlanError::invalid(
                field,
                format!("{}: texture covariance not finite", class.name),
            ));
        }
    }
    if (p.target.mean_w_m2_sr - p.background.mean_w_m2_sr).norm() == 0.0
        && p.objective == Objective::ScrPerSecond
    {
        return Err(PlanError::invalid(
            "target",
            "the target's and background's means are equal: the SCR is 0 at every setting",
        ));
    }
    Ok(())
}

pub(crate) fn model(field: &'static str) -> impl Fn(polar_model::ModelError) -> PlanError {
    move |e| PlanError::invalid(field, e.to_string())
}

/// The half turn's frame spans for `n` frames of span `d`, centres `k pi / n`.
fn spans(n: usize, d: f64) -> Vec<(f64, f64)> {
    (0..n)
        .map(|k| {
            let c = k as f64 * PI / n as f64;
            (c - 0.5 * d, c + 0.5 * d)
        })
        .collect()
}

/// Condition number of the ideal span rows `[1, sinc D cos 2psi, sinc D sin 2psi]` of `n`
/// equally spaced frames.
pub fn span_condition(n: usize, span_rad: f64) -> f64 {
    let s = sinc(span_rad);
    let gram = (0..n).fold(Matrix3::zeros(), |acc: Matrix3<f64>, k| {
        let (sn, c) = (2.0 * k as f64 * PI / n as f64).sin_cos();
        let r = Vector3::new(1.0, s * c, s * sn);
        acc + r * r.transpose()
    });
    let e = gram.symmetric_eigenvalues();
    if n < 3 || e.min() <= e.max() * 1e-15 {
        f64::INFINITY
    } else {
        (e.max() / e.min()).sqrt()
    }
}

/// Standard deviation of the DoLP of the Stokes estimate `s` with covariance `cov` (first-order
/// delta method; the isotropic polarised spread over `S0` where `S1 = S2 = 0`).
pub fn dolp_sigma_delta(s: &Vector3<f64>, cov: &Matrix3<f64>) -> f64 {
    let p = s[1].hypot(s[2]);
    if p > 0.0 {
        let g = Vector3::new(-p / (s[0] * s[0]), s[1] / (p * s[0]), s[2] / (p * s[0]));
        g.dot(&(cov * g)).max(0.0).sqrt()
    } else {
        (0.5 * (cov[(1, 1)] + cov[(2, 2)])).max(0.0).sqrt() / s[0]
    }
}

/// The brightest frame of every class of the scene (target, background and the others), span
/// `d`, exposure `t`, with its margin, as a fraction of saturation.
pub(crate) fn peak_fraction(
    p: &ContinuousProblem,
    lim: &Limits,
    d: f64,
    t: f64,
) -> Result<f64, PlanError> {
    let sat = p.sensor.camera().saturation_dn() * lim.saturation_scale;
    let mut worst: f64 = 0.0;
    let classes = [("target", &p.target), ("background", &p.background)]
        .into_iter()
        .chain(p.others.iter().map(|c| ("scene material", c)));
    for (role, class) in classes {
        let (mean, sd) = span_peak(&p.sensor, d, t, &class.mean_w_m2_sr, &class.cov_w2_m4_sr2)
            .map_err(model(role))?;
        worst = worst.max((mean + lim.camera.saturation_sigma * sd) / sat);
    }
    Ok(worst)
}

/// The longest exposure the limits allow for `n` frames at `omega` (module docs), or `None`.
fn best_exposure(
    p: &ContinuousProblem,
    lim: &Limits,
    n: usize,
    omega: f64,
) -> Result<Option<f64>, PlanError> {
    let c = &lim.camera;
    let interval = PI / (n as f64 * omega);
    if interval * c.max_frame_rate_hz < 1.0 - 1e-12 || omega > lim.stage.max_speed_rad_per_s {
        return Ok(None);
    }
    let cap = c.max_exposure_s.min(interval - c.readout_s);
    if cap < c.min_exposure_s {
        return Ok(None);
    }
    let fits =
        |t: f64| -> Result<bool, PlanError> { Ok(peak_fraction(p, lim, omega * t, t)? <= 1.0) };
    if fits(cap)? {
        return Ok(Some(cap));
    }
    if !fits(c.min_exposure_s)? {
        return Ok(None);
    }
    let lo = bisect(
        c.min_exposure_s.ln(),
        cap.ln(),
        SATURATION_BISECTIONS,
        |x| fits(x.exp()),
    )?;
    Ok(Some(lo.exp()))
}

/// Everything about one setting.
struct Scored {
    n: usize,
    t: f64,
    omega: f64,
    d: f64,
    condition: f64,
    s0_dn: f64,
    sigma_stokes_dn: [f64; 3],
    dolp: f64,
    sigma_dolp: f64,
    scr: f64,
    scr_per_s: f64,
    half_turns: Option<f64>,
    time_to_target_s: Option<f64>,
    spin_up_s: f64,
    value: f64,
}

/// Scores `n` frames of exposure `t` at `omega` under `lim`, or `None` when a limit forbids it.
fn score(
    p: &ContinuousProblem,
    lim: &Limits,
    n: usize,
    t: f64,
    omega: f64,
) -> Result<Option<Scored>, PlanError> {
    let c = &lim.camera;
    let interval = PI / (n as f64 * omega);
    let d = omega * t;
    let ok = (3..=lim.max_n).contains(&n)
        && omega > 0.0
        && omega <= lim.stage.max_speed_rad_per_s * (1.0 + 1e-12)
        && t >= c.min_exposure_s * (1.0 - 1e-12)
        && t <= c.max_exposure_s * (1.0 + 1e-12)
        && interval * c.max_frame_rate_hz >= 1.0 - 1e-12
        && interval >= (t + c.readout_s) * (1.0 - 1e-12);
    if !ok {
        return Ok(None);
    }
    let condition = span_condition(n, d);
    if condition > STOKES_MAX_CONDITION || peak_fraction(p, lim, d, t)? > 1.0 + 1e-12 {
        return Ok(None);
    }
    let angle_sigma_rad = omega * p.timing_sigma_s;
    let frames = spans(n, d);
    let signal = |class: &ClassRadiance, field| {
        span_signal(
            &p.sensor,
            &frames,
            &SpanExposure {
                t_int_s: t,
                radiance_w_m2_sr: class.mean_w_m2_sr,
                angle_sigma_rad,
            },
        )
        .map_err(model(field))
    };
    let tgt = signal(&p.target, "target")?;
    let bkg = signal(&p.background, "background")?;
    let cov = tgt.stokes_cov_dn2;
    let sigma_dolp = dolp_sigma_delta(&tgt.stokes_dn, &cov);
    let scr = frames_scr(p, &bkg);
    let half_turn_s = PI / omega;
    let scr_per_s = scr / half_turn_s;
    let spin_up_s = omega / lim.stage.acceleration_rad_per_s2;
    let (half_turns, time_to_target_s, value) = match p.objective {
        Objective::TimeToDolpSigma { dolp_sigma } => {
            let m = (sigma_dolp / dolp_sigma).powi(2).max(1.0);
            let time = spin_up_s + m * half_turn_s;
            (Some(m), Some(time), time)
        }
        Objective::ScrPerSecond => (None, None, -scr_per_s),
    };
    Ok(Some(Scored {
        n,
        t,
        omega,
        d,
        condition,
        s0_dn: tgt.stokes_dn[0],
        sigma_stokes_dn: [0, 1, 2].map(|i| cov[(i, i)].max(0.0).sqrt()),
        dolp: tgt.stokes_dn[1].hypot(tgt.stokes_dn[2]) / tgt.stokes_dn[0],
        sigma_dolp,
        scr,
        scr_per_s,
        half_turns,
        time_to_target_s,
        spin_up_s,
        value,
    }))
}

/// The target-background SCR of one set of frames whose background signal is `bkg` (module
/// docs), in DN: `d^T (A Sigma_b + I)^-1 A d` with `d = K G (L_t - L_b)`; 0 where the matrix
/// is singular.
pub(crate) fn frames_scr(p: &ContinuousProblem, bkg: &SpanSignal) -> f64 {
    let kg = bkg.dn_from_radiance;
    let diff = (p.target.mean_w_m2_sr - p.background.mean_w_m2_sr) * kg;
    let sigma_b =
        0.5 * (p.background.cov_w2_m4_sr2 + p.background.cov_w2_m4_sr2.transpose()) * (kg * kg);
    let a = bkg
        .rows
        .iter()
        .zip(&bkg.var_dn2)
        .fold(Matrix3::zeros(), |acc, (w, v)| acc + w * w.transpose() / *v);
    match (a * sigma_b + Matrix3::identity()).try_inverse() {
        Some(inv) => diff.dot(&(inv * a * diff)).max(0.0),
        None => 0.0,
    }
}

/// The objective at `n` frames and speed `omega`, the exposure the longest allowed.
fn at_speed(
    p: &ContinuousProblem,
    lim: &Limits,
    n: usize,
    omega: f64,
) -> Result<Option<Point>, PlanError> {
    let Some(t) = best_exposure(p, lim, n, omega)? else {
        return Ok(None);
    };
    Ok(score(p, lim, n, t, omega)?.map(|s| Point {
        n,
        t,
        omega,
        value: s.value,
    }))
}

fn better(a: Option<Point>, b: Option<Point>) -> Option<Point> {
    match (a, b) {
        (Some(x), Some(y)) => Some(if y.value < x.value { y } else { x }),
        (x, None) => x,
        (None, y) => y,
    }
}

/// The best speed for `n` frames (module docs).
fn best_for_n(p: &ContinuousProblem, lim: &Limits, n: usize) -> Result<Option<Point>, PlanError> {
    let c = &lim.camera;
    let nf = n as f64;
    let hi = lim
        .stage
        .max_speed_rad_per_s
        .min(PI * c.max_frame_rate_hz / nf)
        .min(PI / (nf * (c.min_exposure_s + c.readout_s)));
    let lo = (0.5 * PI / (nf * (c.max_exposure_s + c.readout_s))).min(0.5 * hi);
    let mut best: Option<Point> = None;
    scan_then_golden(lo.ln(), hi.ln(), SPEED_SCAN, GOLDEN_ITERATIONS, |x| {
        // The scan's last point is the top speed itself, not its log's exponential.
        let omega = if x == hi.ln() { hi } else { x.exp() };
        let pt = at_speed(p, lim, n, omega)?;
        best = better(best, pt);
        Ok(pt.map_or(f64::INFINITY, |q| q.value))
    })?;
    Ok(best)
}

fn optimum(p: &ContinuousProblem, lim: &Limits) -> Result<Option<Point>, PlanError> {
    let mut best = None;
    for n in 3..=lim.max_n {
        best = better(best, best_for_n(p, lim, n)?);
    }
    Ok(best)
}

pub(crate) fn limits_of(p: &ContinuousProblem) -> Limits {
    Limits {
        camera: p.camera,
        stage: p.stage,
        saturation_scale: 1.0,
        max_n: p.max_frames_per_half_turn,
    }
}

/// `lim` with `limit` loosened (module docs); `None` when loosening cannot change anything
/// (no readout to shorten).
fn loosened(lim: &Limits, limit: Limit) -> Option<Limits> {
    let mut l = *lim;
    let up = 1.0 + LOOSEN;
    match limit {
        Limit::StageSpeed => l.stage.max_speed_rad_per_s *= up,
        Limit::StageAcceleration => l.stage.acceleration_rad_per_s2 *= up,
        Limit::FrameRate => l.camera.max_frame_rate_hz *= up,
        Limit::Readout => {
            if l.camera.readout_s == 0.0 {
                return None;
            }
            l.camera.readout_s /= up;
        }
        Limit::Saturation => l.saturation_scale *= up,
        Limit::ExposureRange => {
            l.camera.min_exposure_s /= up;
            l.camera.max_exposure_s = (l.camera.max_exposure_s * up).min(1e5);
        }
        Limit::FrameCount => {
            if l.max_n >= MAX_FRAMES_PER_HALF_TURN {
                return None;
            }
            l.max_n += 1;
        }
    }
    Some(l)
}

fn describe(p: &ContinuousProblem, limit: Limit, gain: f64) -> String {
    let what = match p.objective {
        Objective::TimeToDolpSigma { .. } => "shorten the time to the DoLP target",
        Objective::ScrPerSecond => "raise the SCR per second",
    };
    let pct = gain * 100.0;
    let c = &p.camera;
    match limit {
        Limit::StageSpeed => format!(
            "the stage's top speed ({:.4} deg/s): 1 % faster would {what} by {pct:.3} %",
            p.stage.max_speed_rad_per_s.to_degrees()
        ),
        Limit::StageAcceleration => format!(
            "the stage's acceleration ({:.4} deg/s^2, the spin-up): 1 % more would {what} by \
             {pct:.3} %",
            p.stage.acceleration_rad_per_s2.to_degrees()
        ),
        Limit::FrameRate => format!(
            "the camera's frame rate ({} Hz): 1 % more would {what} by {pct:.3} %",
            c.max_frame_rate_hz
        ),
        Limit::Readout => format!(
            "the camera's readout ({} us between exposures): 1 % shorter would {what} by \
             {pct:.3} %",
            c.readout_s * 1e6
        ),
        Limit::Saturation => format!(
            "saturation (the brightest frame plus {} sigma at the camera's saturation level): \
             1 % more full well would {what} by {pct:.3} %",
            c.saturation_sigma
        ),
        Limit::ExposureRange => format!(
            "the camera's exposure range ({} to {} us): 1 % wider would {what} by {pct:.3} %",
            c.min_exposure_s * 1e6,
            c.max_exposure_s * 1e6
        ),
        Limit::FrameCount => format!(
            "the cap of {} frames per half turn: one more would {what} by {pct:.3} %",
            p.max_frames_per_half_turn
        ),
    }
}

/// The best setting of `problem` (module docs), with the limits that bind. Errors name the
/// field of an input out of range, and `limits` when no setting satisfies them all (for
/// instance the scene saturates the camera at its shortest exposure).
pub fn plan_continuous(problem: &ContinuousProblem) -> Result<ContinuousChoice, PlanError> {
    check(problem)?;
    let lim = limits_of(problem);
    let best = optimum(problem, &lim)?.ok_or_else(|| {
        PlanError::invalid(
            "limits",
            "no setting of frames per half turn, exposure and speed satisfies the camera's and \
             the stage's limits (e.g. the scene saturates the camera at the shortest exposure, \
             or 3 frames per half turn do not fit the frame rate at any speed)",
        )
    })?;
    let s = score(problem, &lim, best.n, best.t, best.omega)?
        .ok_or_else(|| PlanError::invalid("limits", "the optimum does not satisfy the limits"))?;
    let mut binds = Vec::new();
    for limit in Limit::ALL {
        if limit == Limit::StageAcceleration && problem.objective == Objective::ScrPerSecond {
            continue;
        }
        let Some(l) = loosened(&lim, limit) else {
            continue;
        };
        if let Some(q) = optimum(problem, &l)? {
            let gain = (best.value - q.value) / best.value.abs();
            if gain > BINDS_ABOVE {
                binds.push(Binding {
                    limit,
                    gain,
                    message: describe(problem, limit, gain),
                });
            }
        }
    }
    Ok(ContinuousChoice {
        frames_per_half_turn: s.n,
        exposure_s: s.t,
        speed_rad_per_s: s.omega,
        frame_interval_s: PI / (s.n as f64 * s.omega),
        span_rad: s.d,
        half_turn_s: PI / s.omega,
        spin_up_s: s.spin_up_s,
        condition: s.condition,
        s0_dn: s.s0_dn,
        sigma_stokes_dn: s.sigma_stokes_dn,
        dolp: s.dolp,
        sigma_dolp: s.sigma_dolp,
        scr: s.scr,
        scr_per_s: s.scr_per_s,
        half_turns: s.half_turns,
        time_to_target_s: s.time_to_target_s,
        peak_fraction: peak_fraction(problem, &lim, s.d, s.t)?,
        objective_value: s.value,
        binds,
    })
}

/// The objective at a given setting (`n` frames per half turn, exposure `t_s`, speed
/// `omega_rad_per_s`), `None` when the limits forbid it: what [`plan_continuous`] minimises,
/// for checking its answer against a grid.
pub fn objective_at(
    problem: &ContinuousProblem,
    n: usize,
    t_s: f64,
    omega_rad_per_s: f64,
) -> Result<Option<f64>, PlanError> {
    check(problem)?;
    Ok(score(problem, &limits_of(problem), n, t_s, omega_rad_per_s)?.map(|s| s.value))
}

/// Time of a trapezoidal move of `angle_rad` from rest to rest at top speed `v` and
/// acceleration `a`.
pub fn move_s(angle_rad: f64, v: f64, a: f64) -> f64 {
    let d = angle_rad.abs();
    if d >= v * v / a {
        d / v + v / a
    } else {
        2.0 * (d / a).sqrt()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use polar_model::atmosphere::Band;
    use polar_model::sensor::Camera;

    const CMOS: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

    fn sensor() -> SensorModel {
        let cam = Camera::from_toml_str(CMOS).unwrap();
        SensorModel::new(&cam, &Band::flat(450.0, 650.0).unwrap()).unwrap()
    }

    /// The simulated rig's limits: 360 deg/s at 2880 deg/s^2, 200 Hz, no readout dead time,
    /// exposures 10 us to 1 s.
    pub(crate) fn problem(scale: f64, objective: Objective) -> ContinuousProblem {
        let class = |name: &str, m: [f64; 3]| ClassRadiance {
            name: name.into(),
            mean_w_m2_sr: Vector3::from(m) * scale,
            cov_w2_m4_sr2: Matrix3::from_diagonal(&Vector3::new(1e-4, 4e-5, 4e-5))
                * (scale * scale),
        };
        ContinuousProblem {
            sensor: sensor(),
            target: class("panel", [30.0, 6.0, 3.0]),
            background: class("roof", [28.0, 1.0, 0.5]),
            others: Vec::new(),
            camera: CameraLimits {
                min_exposure_s: 10e-6,
                max_exposure_s: 1.0,
                max_frame_rate_hz: 200.0,
                readout_s: 0.0,
                saturation_sigma: 3.0,
            },
            stage: StageLimits {
                max_speed_rad_per_s: 360f64.to_radians(),
                acceleration_rad_per_s2: 2880f64.to_radians(),
            },
            timing_sigma_s: 0.0,
            max_frames_per_half_turn: 12,
            objective,
        }
    }

    pub(crate) const TIME: Objective = Objective::TimeToDolpSigma { dolp_sigma: 1e-3 };

    fn limits(c: &ContinuousChoice) -> Vec<Limit> {
        c.binds.iter().map(|b| b.limit).collect()
    }

    /// The planner's answer against a brute-force grid over every `N` up to the cap, 50
    /// exposures and 50 speeds (both logarithmic over their whole ranges): never worse than
    /// the grid's best by more than 1e-3 relative; and a local check, where no neighbour
    /// (`N +- 1`, exposure and speed `x (1 +- 1e-4)`) that the limits allow is better by more
    /// than 1e-9 relative (the golden-section search's tolerance is far below that). Bright and
    /// dim scenes, both objectives.
    #[test]
    fn the_choice_is_at_least_the_grid_optimum() {
        for scale in [1.0, 1e-3] {
            for objective in [TIME, Objective::ScrPerSecond] {
                let mut p = problem(scale, objective);
                p.camera.max_exposure_s = 0.1;
                let c = plan_continuous(&p).unwrap();
                let logs = |lo: f64, hi: f64, k: usize| -> Vec<f64> {
                    (0..k)
                        .map(|i| (lo.ln() + (hi / lo).ln() * i as f64 / (k - 1) as f64).exp())
                        .collect()
                };
                let mut grid = f64::INFINITY;
                for n in 3..=p.max_frames_per_half_turn {
                    for &t in &logs(p.camera.min_exposure_s, p.camera.max_exposure_s, 50) {
                        for &w in &logs(1e-2, p.stage.max_speed_rad_per_s, 50) {
                            if let Some(v) = objective_at(&p, n, t, w).unwrap() {
                                grid = grid.min(v);
                            }
                        }
                    }
                }
                assert!(grid.is_finite());
                assert!(
                    c.objective_value <= grid + 1e-3 * grid.abs(),
                    "scale {scale}, {objective:?}: chosen {} against grid {grid}",
                    c.objective_value
                );
                let at = objective_at(&p, c.frames_per_half_turn, c.exposure_s, c.speed_rad_per_s)
                    .unwrap()
                    .unwrap();
                assert_eq!(at, c.objective_value);
                for dn in [-1i64, 0, 1] {
                    let n = (c.frames_per_half_turn as i64 + dn) as usize;
                    for ft in [1.0 - 1e-4, 1.0, 1.0 + 1e-4] {
                        for fw in [1.0 - 1e-4, 1.0, 1.0 + 1e-4] {
                            let t = c.exposure_s * ft;
                            let w = c.speed_rad_per_s * fw;
                            if let Some(v) = objective_at(&p, n, t, w).unwrap() {
                                assert!(
                                    v >= c.objective_value - 1e-9 * c.objective_value.abs(),
                                    "scale {scale}, {objective:?}: neighbour N {n}, t {t}, \
                                     omega {w} gives {v} < {}",
                                    c.objective_value
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// On the bright scene the exposure is saturation-limited, so more frames per second
    /// help: the stage's top speed and the frame rate bind (200 Hz at 360 deg/s allows 100
    /// frames per half turn, the cap 12 binds first; at 20 Hz the frame rate does), and
    /// saturation does.
    #[test]
    fn bright_scene_binds_speed_saturation_and_frames() {
        let p = problem(1.0, TIME);
        let c = plan_continuous(&p).unwrap();
        let l = limits(&c);
        for want in [Limit::StageSpeed, Limit::Saturation, Limit::FrameCount] {
            assert!(l.contains(&want), "{want:?} not in {l:?}");
        }
        assert!((c.speed_rad_per_s / p.stage.max_speed_rad_per_s - 1.0).abs() < 1e-9);
        assert!(
            c.peak_fraction <= 1.0 && c.peak_fraction > 0.999,
            "{}",
            c.peak_fraction
        );
        let mut slow = problem(1.0, TIME);
        slow.camera.max_frame_rate_hz = 20.0;
        let c = plan_continuous(&slow).unwrap();
        let l = limits(&c);
        assert!(l.contains(&Limit::FrameRate), "{l:?}");
        // N omega = pi f_max at the frame rate's limit.
        let rate = c.frames_per_half_turn as f64 * c.speed_rad_per_s / PI;
        assert!(rate <= 20.0 * (1.0 + 1e-9), "{rate}");
        let b = &c.binds[l.iter().position(|x| *x == Limit::FrameRate).unwrap()];
        assert!(
            b.message.contains("frame rate") && b.message.contains("20 Hz"),
            "{}",
            b.message
        );
    }

    /// A scene material brighter than the target and the background (a metal panel, twice the
    /// target's radiance) limits the exposure too: with it among the others the planner picks
    /// a shorter exposure, and its brightest frame, margin included, stays within saturation
    /// (the same 1e-9 relative the saturation bisection reaches).
    #[test]
    fn every_scene_material_stays_below_saturation() {
        let alone = plan_continuous(&problem(1.0, TIME)).unwrap();
        let mut p = problem(1.0, TIME);
        let mut metal = p.target.clone();
        metal.name = "metal".into();
        metal.mean_w_m2_sr *= 2.0;
        p.others.push(metal.clone());
        let c = plan_continuous(&p).unwrap();
        assert!(
            c.exposure_s < alone.exposure_s,
            "{} s with the metal, {} s without",
            c.exposure_s,
            alone.exposure_s
        );
        let (mean, sd) = span_peak(
            &p.sensor,
            c.span_rad,
            c.exposure_s,
            &metal.mean_w_m2_sr,
            &metal.cov_w2_m4_sr2,
        )
        .unwrap();
        let peak = (mean + p.camera.saturation_sigma * sd) / p.sensor.camera().saturation_dn();
        assert!(
            peak <= 1.0 + 1e-9,
            "the metal's peak is {peak} of saturation"
        );
        assert!(
            (c.peak_fraction - peak).abs() < 1e-9,
            "{} {peak}",
            c.peak_fraction
        );
    }

    /// On the dim scene, with a readout dead time, the exposures fill the frame interval but
    /// for the readout, which binds; with a short exposure range the range binds; with a slow
    /// spin-up and a loose target the acceleration binds (the speed stops below the top).
    #[test]
    fn dim_scene_binds_readout_exposure_range_and_acceleration() {
        let mut p = problem(1e-3, TIME);
        p.camera.readout_s = 2e-3;
        let c = plan_continuous(&p).unwrap();
        assert!(limits(&c).contains(&Limit::Readout), "{:?}", c.binds);
        assert!(
            (c.exposure_s + 2e-3 - c.frame_interval_s).abs() < 1e-9 * c.frame_interval_s,
            "{} + readout against {}",
            c.exposure_s,
            c.frame_interval_s
        );
        let mut short = problem(1e-3, TIME);
        short.camera.max_exposure_s = 2e-3;
        let c = plan_continuous(&short).unwrap();
        assert!(limits(&c).contains(&Limit::ExposureRange), "{:?}", c.binds);
        assert!((c.exposure_s / 2e-3 - 1.0).abs() < 1e-12);
        let mut lazy = problem(1.0, Objective::TimeToDolpSigma { dolp_sigma: 0.02 });
        lazy.stage.acceleration_rad_per_s2 = 5f64.to_radians();
        let c = plan_continuous(&lazy).unwrap();
        assert!(
            limits(&c).contains(&Limit::StageAcceleration),
            "{:?}",
            c.binds
        );
        assert!(c.speed_rad_per_s < 0.99 * lazy.stage.max_speed_rad_per_s);
    }

    /// Physical facts of the answer. Dim scene, no readout, frame rate not binding: the
    /// exposure fills the frame interval (duty 1, to 1e-9: the bound is computed as
    /// `pi / (N omega)`), so each span is `pi / N`; the time to the target is the spin-up
    /// plus `m` half turns and one half turn's DoLP sigma over `sqrt m` is the target (1e-12,
    /// rounding); the span rows' condition number is `sqrt 2 / sinc(pi / N)` (1e-9).
    #[test]
    fn dim_scene_exposes_the_whole_turn() {
        let p = problem(1e-3, TIME);
        let c = plan_continuous(&p).unwrap();
        let n = c.frames_per_half_turn as f64;
        assert!((c.exposure_s / c.frame_interval_s - 1.0).abs() < 1e-9);
        assert!((c.span_rad - PI / n).abs() < 1e-9 * PI / n);
        let m = c.half_turns.unwrap();
        assert!(m > 1.0);
        let time = c.time_to_target_s.unwrap();
        assert!((time - (c.spin_up_s + m * c.half_turn_s)).abs() < 1e-12 * time);
        assert!((c.sigma_dolp / m.sqrt() / 1e-3 - 1.0).abs() < 1e-12);
        let kappa = std::f64::consts::SQRT_2 / sinc(PI / n);
        assert!(
            (c.condition / kappa - 1.0).abs() < 1e-9,
            "{} {kappa}",
            c.condition
        );
    }

    /// Timing jitter of a free-running camera costs time: with 20 ms of timing uncertainty
    /// (7.2 deg at the top speed, where the jitter's share of the DoLP variance exceeds the
    /// shot noise's) the time to the target is longer than with triggered frames, and the
    /// planner turns slower than the top speed, which triggered frames use (the angle error
    /// is the speed times the timing error, so its variance grows as the speed squared while
    /// the time per half turn falls only as the speed).
    #[test]
    fn jitter_slows_the_analyzer() {
        let p = problem(1.0, TIME);
        let triggered = plan_continuous(&p).unwrap();
        let mut free = problem(1.0, TIME);
        free.timing_sigma_s = 20e-3;
        let free = plan_continuous(&free).unwrap();
        assert!(free.time_to_target_s.unwrap() > triggered.time_to_target_s.unwrap());
        assert!((triggered.speed_rad_per_s / p.stage.max_speed_rad_per_s - 1.0).abs() < 1e-9);
        assert!(
            free.speed_rad_per_s < 0.9 * p.stage.max_speed_rad_per_s,
            "{} rad/s",
            free.speed_rad_per_s
        );
    }

    #[test]
    fn bad_inputs_are_named() {
        let mut p = problem(1.0, TIME);
        p.stage.max_speed_rad_per_s = -1.0;
        let e = plan_continuous(&p).unwrap_err().to_string();
        assert!(
            e.contains("stage.max_speed_rad_per_s") && e.contains("-1"),
            "{e}"
        );
        let mut p = problem(1.0, TIME);
        p.camera.max_exposure_s = 1e-6;
        let e = plan_continuous(&p).unwrap_err().to_string();
        assert!(e.contains("camera.max_exposure_s"), "{e}");
        let mut p = problem(1.0, TIME);
        p.max_frames_per_half_turn = 2;
        let e = plan_continuous(&p).unwrap_err().to_string();
        assert!(e.contains("max_frames_per_half_turn"), "{e}");
        let p = problem(1.0, Objective::TimeToDolpSigma { dolp_sigma: 0.0 });
        let e = plan_continuous(&p).unwrap_err().to_string();
        assert!(e.contains("dolp_sigma"), "{e}");
        // Saturated at the shortest exposure: no setting.
        let mut p = problem(1e4, TIME);
        p.camera.min_exposure_s = 1e-3;
        let e = plan_continuous(&p).unwrap_err().to_string();
        assert!(e.contains("limits"), "{e}");
    }
}
