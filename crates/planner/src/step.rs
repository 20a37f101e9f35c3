//! The step-and-shoot set on the continuous planner's problem: the same scene, camera and
//! stage, the analyzer still at each angle. Its frames are the span rows at zero span
//! ([`polar_model::span`]), its set time a trapezoidal move the short way to each angle
//! (modulo pi; the set repeats, so the first angle's move comes from the last), the settling,
//! and each frame's exposure or frame interval, whichever is longer.
//!
//! # The exposure
//!
//! The exposure is chosen by the problem's objective, the rule `plan scene` and `plan
//! continuous` share:
//!
//! * the saturation rule is the continuous planner's: the brightest frame of every material
//!   of the scene, mean plus `k` standard deviations over the analyzer's phase, stays below
//!   saturation ([`still_exposure_limit_s`]);
//! * [`Objective::TimeToDolpSigma`]: the least `m T(t)` with `m = max(1, (sigma_1(t) /
//!   sigma*)^2)` sets of `T(t)` seconds: the longest exposure the limits allow unless one set
//!   already reaches the goal, where a longer exposure only lengthens the set;
//! * [`Objective::ScrPerSecond`]: the largest SCR of one set over `T(t)`; the SCR saturates
//!   at the clutter limit while `T` keeps growing, so the optimum can lie inside the range.
//!
//! Both are found by a scan in `log t` over the allowed range and golden-section search
//! ([`crate::log_search`]); the ends are scored exactly.

use crate::continuous::{
    check, dolp_sigma_delta, frames_scr, limits_of, model, move_s, peak_fraction,
    ContinuousProblem, Objective, SATURATION_BISECTIONS,
};
use crate::log_search::{bisect, scan_then_golden};
use crate::PlanError;
use polar_model::span::{span_signal, SpanExposure};
use std::f64::consts::PI;

/// Points of the exposure scan.
const EXPOSURE_SCAN: usize = 48;
/// Golden-section steps after the scan.
const EXPOSURE_GOLDEN: usize = 60;

/// What decided a step-and-shoot set's exposure.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExposureRule {
    /// The longest exposure saturation allows (every material of the scene).
    Saturation,
    /// The camera's longest exposure.
    LongestExposure,
    /// One set reaches the DoLP goal: a longer exposure would only lengthen the set.
    GoalInOneSet,
    /// The SCR per second peaks inside the range: a longer exposure adds set time faster than
    /// SCR.
    ScrPerSecondPeak,
    /// The caller's exposure.
    Given,
}

impl ExposureRule {
    /// The rule in a sentence, for the commands' output.
    pub fn describe(self) -> &'static str {
        match self {
            ExposureRule::Saturation => {
                "the longest exposure at which no material of the scene saturates (mean plus \
                 the margin's standard deviations)"
            }
            ExposureRule::LongestExposure => "the camera's longest exposure",
            ExposureRule::GoalInOneSet => {
                "one set reaches the DoLP goal at this exposure, and a longer one would only \
                 lengthen the set"
            }
            ExposureRule::ScrPerSecondPeak => {
                "where the SCR per second peaks (a longer exposure adds set time faster than \
                 SCR)"
            }
            ExposureRule::Given => "the exposure asked for",
        }
    }
}

/// A step-and-shoot set on the problem's rig.
#[derive(Debug, Clone, PartialEq)]
pub struct StepPrediction {
    /// The angles, rad.
    pub angles_rad: Vec<f64>,
    /// Exposure of each frame, s.
    pub exposure_s: f64,
    /// What decided the exposure.
    pub exposure_rule: ExposureRule,
    /// The longest exposure the range and saturation allow, s.
    pub exposure_limit_s: f64,
    /// Time per set: per angle a move (trapezoidal, top speed and acceleration), settling,
    /// exposure and readout, s.
    pub set_s: f64,
    /// The target's `K G S0`, DN.
    pub s0_dn: f64,
    /// Standard deviations of the target's `S0`, `S1`, `S2` from one set, DN.
    pub sigma_stokes_dn: [f64; 3],
    /// Standard deviation of the target's DoLP from one set.
    pub sigma_dolp: f64,
    /// The target-background SCR of one set's frames (the continuous planner's).
    pub scr: f64,
    /// `scr / set_s`, per second.
    pub scr_per_s: f64,
    /// Sets to the DoLP target (real, at least 1), if the objective has one.
    pub sets: Option<f64>,
    /// Time to the DoLP target, s.
    pub time_to_target_s: Option<f64>,
}

/// The longest exposure of the camera's range at which no material of the problem's scene
/// saturates with the analyzer still (module docs); `limits` when even the shortest does.
pub fn still_exposure_limit_s(problem: &ContinuousProblem) -> Result<f64, PlanError> {
    check(problem)?;
    let lim = limits_of(problem);
    let c = &problem.camera;
    let fits =
        |t: f64| -> Result<bool, PlanError> { Ok(peak_fraction(problem, &lim, 0.0, t)? <= 1.0) };
    if fits(c.max_exposure_s)? {
        return Ok(c.max_exposure_s);
    }
    if !fits(c.min_exposure_s)? {
        return Err(PlanError::invalid(
            "limits",
            "the scene saturates the camera at the shortest exposure: use a darker band, a \
             smaller aperture or a neutral-density filter",
        ));
    }
    let lo = bisect(
        c.min_exposure_s.ln(),
        c.max_exposure_s.ln(),
        SATURATION_BISECTIONS,
        |x| fits(x.exp()),
    )?;
    Ok(lo.exp())
}

fn check_set(angles_rad: &[f64], settle_s: f64) -> Result<(), PlanError> {
    if angles_rad.len() < 3 || angles_rad.iter().any(|a| !a.is_finite()) {
        return Err(PlanError::invalid(
            "angles_rad",
            format!("{angles_rad:?}: allowed at least 3 finite angles"),
        ));
    }
    if !(settle_s.is_finite() && settle_s >= 0.0) {
        return Err(PlanError::OutOfRange {
            field: "settle_s",
            value: settle_s,
            allowed: "finite, >= 0",
        });
    }
    Ok(())
}

/// Seconds per set at exposure `t_s` (module docs).
pub fn set_s(problem: &ContinuousProblem, angles_rad: &[f64], t_s: f64, settle_s: f64) -> f64 {
    let (v, a) = (
        problem.stage.max_speed_rad_per_s,
        problem.stage.acceleration_rad_per_s2,
    );
    let c = &problem.camera;
    let mut total = 0.0;
    let mut at = angles_rad[angles_rad.len() - 1];
    for &psi in angles_rad {
        let d = (psi - at).rem_euclid(PI);
        let d = d.min(PI - d);
        if d > 0.0 {
            total += move_s(d, v, a) + settle_s;
        }
        total += (t_s + c.readout_s).max(1.0 / c.max_frame_rate_hz);
        at = psi;
    }
    total
}

/// The set at `angles_rad` with every frame exposed `t_s` (its rule and limit as given).
fn at_exposure(
    problem: &ContinuousProblem,
    angles_rad: &[f64],
    t_s: f64,
    settle_s: f64,
    exposure_rule: ExposureRule,
    exposure_limit_s: f64,
) -> Result<StepPrediction, PlanError> {
    let frames: Vec<(f64, f64)> = angles_rad.iter().map(|&a| (a, a)).collect();
    let signal = |mean, field| {
        span_signal(
            &problem.sensor,
            &frames,
            &SpanExposure {
                t_int_s: t_s,
                radiance_w_m2_sr: mean,
                angle_sigma_rad: 0.0,
            },
        )
        .map_err(model(field))
    };
    let tgt = signal(problem.target.mean_w_m2_sr, "angles_rad")?;
    let bkg = signal(problem.background.mean_w_m2_sr, "background")?;
    let set_s = set_s(problem, angles_rad, t_s, settle_s);
    let cov = tgt.stokes_cov_dn2;
    let sigma_dolp = dolp_sigma_delta(&tgt.stokes_dn, &cov);
    let scr = frames_scr(problem, &bkg);
    let (sets, time) = match problem.objective {
        Objective::TimeToDolpSigma { dolp_sigma } => {
            let m = (sigma_dolp / dolp_sigma).powi(2).max(1.0);
            (Some(m), Some(m * set_s))
        }
        Objective::ScrPerSecond => (None, None),
    };
    Ok(StepPrediction {
        angles_rad: angles_rad.to_vec(),
        exposure_s: t_s,
        exposure_rule,
        exposure_limit_s,
        set_s,
        s0_dn: tgt.stokes_dn[0],
        sigma_stokes_dn: [0, 1, 2].map(|i| cov[(i, i)].max(0.0).sqrt()),
        sigma_dolp,
        scr,
        scr_per_s: scr / set_s,
        sets,
        time_to_target_s: time,
    })
}

/// The set at `angles_rad` with every frame exposed `t_s` ([`ExposureRule::Given`]). Errors
/// as [`step_and_shoot`], and `t_s` outside the camera's range.
pub fn step_at_exposure(
    problem: &ContinuousProblem,
    angles_rad: &[f64],
    t_s: f64,
    settle_s: f64,
) -> Result<StepPrediction, PlanError> {
    check_set(angles_rad, settle_s)?;
    let limit = still_exposure_limit_s(problem)?;
    let c = &problem.camera;
    if !(t_s >= c.min_exposure_s * (1.0 - 1e-12) && t_s <= c.max_exposure_s * (1.0 + 1e-12)) {
        return Err(PlanError::OutOfRange {
            field: "t_s",
            value: t_s,
            allowed: "the camera's exposure range",
        });
    }
    at_exposure(
        problem,
        angles_rad,
        t_s,
        settle_s,
        ExposureRule::Given,
        limit,
    )
}

/// The objective's value of a set (smaller is better).
fn value(problem: &ContinuousProblem, s: &StepPrediction) -> f64 {
    match problem.objective {
        Objective::TimeToDolpSigma { .. } => s.time_to_target_s.unwrap_or(f64::INFINITY),
        Objective::ScrPerSecond => -s.scr_per_s,
    }
}

/// The set at `angles_rad` with the exposure its objective picks (module docs). Errors name
/// the problem's field out of range, `angles_rad` when fewer than 3 or not finite, `settle_s`
/// when negative, and `limits` when the scene saturates at the shortest exposure.
pub fn step_and_shoot(
    problem: &ContinuousProblem,
    angles_rad: &[f64],
    settle_s: f64,
) -> Result<StepPrediction, PlanError> {
    check_set(angles_rad, settle_s)?;
    let limit = still_exposure_limit_s(problem)?;
    let c = &problem.camera;
    let at_limit = if limit >= c.max_exposure_s {
        ExposureRule::LongestExposure
    } else {
        ExposureRule::Saturation
    };
    let longest = at_exposure(problem, angles_rad, limit, settle_s, at_limit, limit)?;
    let lo = c.min_exposure_s.ln();
    if limit.ln() - lo < 1e-9 {
        return Ok(longest);
    }
    let best = scan_then_golden(lo, limit.ln(), EXPOSURE_SCAN, EXPOSURE_GOLDEN, |x| {
        let t = if x == limit.ln() { limit } else { x.exp() };
        let s = at_exposure(problem, angles_rad, t, settle_s, at_limit, limit)?;
        Ok(value(problem, &s))
    })?;
    match best {
        // The longest exposure wins ties: it is the rule's usual answer, exactly.
        Some((x, v)) if v < value(problem, &longest) - 1e-12 * v.abs() && x < limit.ln() => {
            let rule = match problem.objective {
                Objective::TimeToDolpSigma { .. } => ExposureRule::GoalInOneSet,
                Objective::ScrPerSecond => ExposureRule::ScrPerSecondPeak,
            };
            // Ties go to the longer exposure (more signal in the same time): the longest
            // exposure whose value is within 1e-12 of the best, by bisection towards the limit
            // (the value is flat, then rising, past the optimum).
            let tied = |t: f64| -> Result<bool, PlanError> {
                let s = at_exposure(problem, angles_rad, t, settle_s, rule, limit)?;
                Ok(value(problem, &s) <= v + 1e-12 * v.abs())
            };
            let lo = bisect(x, limit.ln(), SATURATION_BISECTIONS, |y| tied(y.exp()))?;
            at_exposure(problem, angles_rad, lo.exp(), settle_s, rule, limit)
        }
        _ => Ok(longest),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::continuous::tests::{problem, TIME};

    fn quarter_turn_set() -> Vec<f64> {
        [0.0f64, 45.0, 90.0, 135.0]
            .iter()
            .map(|d| d.to_radians())
            .collect()
    }

    /// Step-and-shoot's set time by hand: 4 moves of 45 deg at 360 deg/s and 2880 deg/s^2
    /// (45 >= 360^2 / 2880 = 45: the trapezoid just reaches top speed, 45/360 + 360/2880 =
    /// 0.25 s each) plus 4 frames of max(exposure, 5 ms); to 1e-12 relative.
    #[test]
    fn step_and_shoot_set_time_by_hand() {
        let p = problem(1.0, TIME);
        let s = step_and_shoot(&p, &quarter_turn_set(), 0.0).unwrap();
        let by_hand = 4.0 * 0.25 + 4.0 * s.exposure_s.max(1.0 / 200.0);
        assert!(
            (s.set_s / by_hand - 1.0).abs() < 1e-12,
            "{} {by_hand}",
            s.set_s
        );
        assert!(s.time_to_target_s.unwrap() >= s.set_s);
    }

    /// The exposure the objective picks is not beaten by any exposure of a 400-point grid in
    /// log t over the allowed range (to 1e-9 relative: the golden search's bracket), for
    /// both objectives, on the test scene (the saturation limit binds), one 30 times brighter and
    /// one 100 times dimmer whose goal one set reaches (the exposure stops short of saturation,
    /// and says so).
    #[test]
    fn the_exposure_is_not_beaten_by_a_grid() {
        let easy = Objective::TimeToDolpSigma { dolp_sigma: 0.01 };
        for (scale, objective) in [
            (1.0, TIME),
            (1.0, Objective::ScrPerSecond),
            (30.0, TIME),
            (30.0, Objective::ScrPerSecond),
            (0.01, easy),
        ] {
            let p = problem(scale, objective);
            let angles = quarter_turn_set();
            let s = step_and_shoot(&p, &angles, 0.1).unwrap();
            let (lo, hi) = (p.camera.min_exposure_s.ln(), s.exposure_limit_s.ln());
            for i in 0..=400 {
                let t = (lo + (hi - lo) * f64::from(i) / 400.0).exp();
                let g = at_exposure(&p, &angles, t, 0.1, s.exposure_rule, hi.exp()).unwrap();
                assert!(
                    value(&p, &s) <= value(&p, &g) + 1e-9 * value(&p, &g).abs(),
                    "scale {scale} {objective:?}: {} at {} s beaten by {} at {t} s",
                    value(&p, &s),
                    s.exposure_s,
                    value(&p, &g)
                );
            }
            if objective == easy {
                assert_eq!(s.exposure_rule, ExposureRule::GoalInOneSet);
                assert!(s.exposure_s < s.exposure_limit_s);
                // One set reaches the goal just: the DoLP sigma is the goal's to 1e-6 relative
                // (the kink of max(1, m) located by the search).
                assert_eq!(s.sets, Some(1.0));
                assert!((s.sigma_dolp / 0.01 - 1.0).abs() < 1e-6, "{}", s.sigma_dolp);
            }
        }
    }
}
