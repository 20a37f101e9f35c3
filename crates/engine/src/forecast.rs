//! The forecast of a plan without running it (`polarimeter plan check FILE`): frames, sets,
//! darks, the run's duration, and per material of the scene the frames' mean, the Stokes,
//! DoLP and AoP a set measures and their predicted noise, with the saturation margin.
//!
//! # Noise per class (MODEL.md sections 6 and 7)
//!
//! For a class of mean band radiance `L` (W m^-2 sr^-1) the sensor model
//! ([`SensorModel::signal`]) gives the `N` frames of one set at exposure `t_int`:
//! `y_mean = K G W L + (K mu_I t_int + b) 1` and `Sigma_y = F_n Sigma_n` with
//! `Sigma_n = diag_i[K^2 (sigma_d^2 + mu_I t_int + G m_i^T L) + 1/12]` (MODEL.md section 6).
//! **No clutter**: the scene's texture covariance `Sigma_LS` is left out, so the sigmas are the
//! temporal noise one pixel of the class sees. The Stokes vector in DN is the least-squares
//! estimate `S_dn = W^+ (y - K mu_I t_int - b) = K G L` with the sensor's real analyzer rows
//! `W` ([`SensorModel::intensities_from_stokes`], fore-optics included), covariance
//! `Sigma_S = W^+ Sigma_y W^+T` (MODEL.md section 7, ordinary least squares), and the DoLP and
//! AoP spreads are [`polar_model::stats::dolp_aop_stats`] of `(S_dn, Sigma_S)` (Taylor or Rice
//! regime by the polarised SNR, MODEL.md section 7). The DoLP and AoP are scale-free, so DN
//! serve as well as radiance.
//!
//! # Duration
//!
//! The steps of [`Plan::steps`] in order, the stage starting at 0 deg (homed): each step moves
//! the analyzer the short way (`|delta|` in `[0, 90]` deg after reducing modulo 180: an analyzer
//! angle is a direction) at the stage's constant speed, settles after a move (not when it stays),
//! exposes and reads out; a time-lapse set does not start before its time. An adaptive plan
//! adds at most as many sets as its frame budget leaves room for, each frame with a worst-case
//! 90-degree move (an upper bound).

use crate::plan::{FromPlanner, Plan, PlanError, PlanKind, StepSpec};
use crate::FrameKind;
use nalgebra::{DMatrix, Vector3};
use polar_model::scene::{MaterialResult, Prepared};
use polar_model::scene_file::Scene;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_model::stats::{dolp_aop_stats, MethodChoice, Regime, RegimeChoice, StokesEstimator};
use polar_planner::continuous::StageLimits;
use polar_planner::{conventional, optimise, Constraints, Contrast};
use serde::Serialize;
use serde_json::{json, Value};

use crate::forecast_basis::{camera_at_gain, model_err};
pub use crate::forecast_basis::{ForecastError, SCENE_TOL};

/// The planner's angle tolerance, degrees.
const PLANNER_TOL_DEG: f64 = 0.01;

/// Angles closer than this modulo 180 deg count as one (the plan's rule).
const DISTINCT_DEG: f64 = 0.01;

/// How long the rig takes for its parts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Timing {
    /// The stage's speed, degrees per second (constant: no acceleration ramps).
    pub stage_deg_per_s: f64,
    /// Settling after each move, seconds.
    pub settle_s: f64,
    /// Per frame beyond the exposure (readout, transfer), seconds.
    pub readout_s: f64,
    /// The stage's limits for a continuous plan's `from_planner`, where the rig knows them.
    #[serde(skip)]
    pub stage_limits: Option<StageLimits>,
}

impl Timing {
    /// The simulated rig's: the plan's `simulation.stage_deg_per_s`, no settling, and 1/200 s
    /// of readout per frame (the simulated camera's highest frame rate is 200 Hz). The
    /// simulated stage also ramps its speed up and down, which this constant-speed timing
    /// leaves out: the forecast is a lower bound for it. `stage_limits`: the simulated stage's
    /// (`polar_rig::sim_stage::timing` passes them).
    pub fn simulated(plan: &Plan, stage_limits: Option<StageLimits>) -> Timing {
        Timing {
            stage_deg_per_s: plan.simulation.stage_deg_per_s,
            settle_s: 0.0,
            readout_s: 1.0 / 200.0,
            stage_limits,
        }
    }

    fn validate(&self) -> Result<(), ForecastError> {
        let bad = |field: &str, v: f64, allowed: &str| ForecastError::Invalid {
            field: field.to_string(),
            value: v.to_string(),
            allowed: allowed.to_string(),
        };
        if !(self.stage_deg_per_s.is_finite() && self.stage_deg_per_s > 0.0) {
            return Err(bad(
                "timing.stage_deg_per_s",
                self.stage_deg_per_s,
                "finite and > 0",
            ));
        }
        if !(self.settle_s.is_finite() && self.settle_s >= 0.0) {
            return Err(bad("timing.settle_s", self.settle_s, "finite and >= 0"));
        }
        if !(self.readout_s.is_finite() && self.readout_s >= 0.0) {
            return Err(bad("timing.readout_s", self.readout_s, "finite and >= 0"));
        }
        Ok(())
    }
}

/// What a plan will take and give (module docs).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Forecast {
    /// The plan's kind, as written in plans.
    pub kind: String,
    /// Frames, darks included (an adaptive plan: the most its budget allows).
    pub frames: u64,
    /// Angle sets (an adaptive plan: the most its budget allows).
    pub sets: u64,
    /// Dark frames.
    pub darks: u64,
    /// The run's duration, seconds (module docs; an upper bound for an adaptive plan).
    pub duration_s: f64,
    /// A set's angles, degrees, when known (an adaptive plan: its first set; none for the
    /// calibrations, which have no sets).
    pub angles_deg: Option<Vec<f64>>,
    /// Per material of the scene, one set at the plan's first exposure and angles (empty for
    /// the calibrations: `notes` says why).
    pub classes: Vec<ClassForecast>,
    /// Where the angles came from, the bounds, saturation warnings, regimes.
    pub notes: Vec<String>,
}

/// One material's frames and products for one set (module docs for the equations).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClassForecast {
    /// The material's name in the scene.
    pub material: String,
    /// Mean of each frame of the set, DN (offset and dark signal included), per angle.
    pub mean_dn: Vec<f64>,
    /// `S0` in DN, `K G L0` (the dark-subtracted scale of the Stokes estimate).
    pub s0_dn: f64,
    /// DoLP of the class's mean Stokes vector (MODEL.md section 0, Eq. 2.14).
    pub dolp: f64,
    /// AoP of the class's mean Stokes vector, degrees in `(-90, 90]` (Eq. 2.15).
    pub aop_deg: f64,
    /// Standard deviation of the `S0` estimate from one set, DN (sensor noise only).
    pub sigma_s0_dn: f64,
    /// Standard deviation of the DoLP estimate from one set (MODEL.md section 7).
    pub sigma_dolp: f64,
    /// Standard deviation of the AoP estimate from one set, degrees.
    pub sigma_aop_deg: f64,
    /// `(saturation - max_i(mean_i + 3 sigma_i)) / saturation`, `sigma_i` the frame's spread
    /// over the class's pixels (sensor noise and the scene's texture); negative: some pixels
    /// saturate.
    pub saturation_margin: f64,
}

/// The short way between two analyzer angles, degrees in `[0, 90]`.
fn move_deg(from: f64, to: f64) -> f64 {
    let d = (to - from).rem_euclid(180.0);
    d.min(180.0 - d)
}

/// The duration of `steps` from a homed stage (0 deg), and the angle it ends at (module docs).
fn schedule(steps: &[StepSpec], timing: &Timing) -> (f64, f64) {
    let mut t = 0.0;
    let mut at = 0.0;
    for s in steps {
        if let Some(not_before) = s.not_before_s {
            t = f64::max(t, not_before);
        }
        let d = move_deg(at, s.angle_deg);
        if d > 0.0 {
            t += d / timing.stage_deg_per_s + timing.settle_s;
        }
        t += s.exposure_us * 1e-6 + timing.readout_s;
        at = s.angle_deg;
    }
    (t, at)
}

fn distinct_angles(angles_deg: &[f64]) -> usize {
    let mut seen: Vec<f64> = Vec::new();
    for a in angles_deg {
        let a = a.rem_euclid(180.0);
        let new = !seen.iter().any(|s| move_deg(*s, a) < DISTINCT_DEG);
        if new {
            seen.push(a);
        }
    }
    seen.len()
}

/// The scene's materials, evaluated once.
fn evaluate_materials(scene: &Scene, names: &[&str]) -> Result<Vec<MaterialResult>, ForecastError> {
    let prepared = Prepared::new(&scene.spec, SCENE_TOL).map_err(model_err("scene"))?;
    names
        .iter()
        .map(|name| {
            let m = scene
                .materials
                .iter()
                .find(|m| m.name == *name)
                .ok_or_else(|| ForecastError::UnknownMaterial {
                    field: "scene".into(),
                    name: name.to_string(),
                    allowed: material_names(scene),
                })?;
            prepared
                .evaluate(m)
                .map_err(model_err(format!("material {name}")))
        })
        .collect()
}

fn material_names(scene: &Scene) -> String {
    scene
        .materials
        .iter()
        .map(|m| m.name.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

fn check_material(scene: &Scene, field: &str, name: &str) -> Result<(), ForecastError> {
    if scene.materials.iter().any(|m| m.name == name) {
        Ok(())
    } else {
        Err(ForecastError::UnknownMaterial {
            field: field.to_string(),
            name: name.to_string(),
            allowed: material_names(scene),
        })
    }
}

/// The planner's contrast at `t_int_s` (MODEL.md section 9, as `plan --scene`):
/// [`Contrast::from_sensor`], the camera's real analyzer rows and its noise at the background's
/// light, so that the SCR the planner maximises is the matched-filter SCR of the frames this
/// forecast describes.
fn contrast_at(
    sensor: &SensorModel,
    target: &MaterialResult,
    background: &MaterialResult,
    t_int_s: f64,
) -> Result<Contrast, ForecastError> {
    Contrast::from_sensor(
        sensor,
        t_int_s,
        &target.mean.0,
        &background.mean.0,
        &background.cov,
    )
    .map_err(|e| ForecastError::Model {
        field: "capture.from_planner".into(),
        message: e.to_string(),
    })
}

/// The planner's choice from evaluated classes (see [`planner_angles`]).
fn planner_choice(
    sensor: &SensorModel,
    target: &MaterialResult,
    background: &MaterialResult,
    from: &FromPlanner,
    exposure_us: f64,
) -> Result<(Vec<f64>, Value), ForecastError> {
    let contrast = contrast_at(sensor, target, background, exposure_us * 1e-6)?;
    let constraints = Constraints {
        min_separation_rad: from.min_separation_deg.to_radians(),
        max_condition: Some(polar_planner::stokes::STOKES_MAX_CONDITION),
        ..Constraints::default()
    };
    let planner = |e: polar_planner::PlanError| ForecastError::Model {
        field: "capture.from_planner".into(),
        message: e.to_string(),
    };
    let opt = optimise(
        &contrast,
        from.channels,
        &constraints,
        PLANNER_TOL_DEG.to_radians(),
    )
    .map_err(planner)?;
    let mut angles_deg: Vec<f64> = opt
        .angles_rad
        .iter()
        // To 1e-6 deg (the optimiser's tolerance is 0.01 deg): readable, and 180 wraps to 0.
        .map(|a| ((a.to_degrees() * 1e6).round() / 1e6).rem_euclid(180.0))
        .collect();
    angles_deg.sort_by(f64::total_cmp);
    if opt.scr <= 0.0 {
        return Err(ForecastError::Invalid {
            field: "capture.from_planner".into(),
            value: format!("target {:?}, background {:?}", from.target, from.background),
            allowed: "two materials whose Stokes means differ (their SCR is 0 for every set)"
                .into(),
        });
    }
    let distinct = distinct_angles(&angles_deg);
    if distinct < 3 {
        return Err(ForecastError::Invalid {
            field: "capture.from_planner.min_separation_deg".into(),
            value: from.min_separation_deg.to_string(),
            allowed: format!(
                "a separation that keeps 3 distinct angles (the SCR-optimal set {angles_deg:?} \
                 has {distinct}, and forms no Stokes image): e.g. 30"
            ),
        });
    }
    let conv: serde_json::Map<String, Value> = conventional(&contrast)
        .into_iter()
        .map(|(name, scr)| (name.to_string(), json!(scr)))
        .collect();
    let limit = contrast.clutter_limit();
    let why = json!({
        "target": from.target,
        "background": from.background,
        "channels": from.channels,
        "min_separation_deg": from.min_separation_deg,
        "exposure_us": exposure_us,
        "angles_deg": angles_deg,
        "scr": opt.scr,
        "scr_conventional": conv,
        "scr_clutter_limit": if limit.is_finite() { json!(limit) } else { Value::Null },
        "noise_var_w2_m4_sr2": contrast.noise_var,
        "shot_noise_var_per_w_m2_sr": contrast.instrument.shot_var_per_radiance,
        "notes": contrast.notes,
    });
    Ok((angles_deg, why))
}

/// The SCR-optimal analyzer set (MODEL.md section 9) for a capture's `from_planner`: the
/// target's and background's statistics from the scene (at [`SCENE_TOL`]), the sensor noise of
/// `camera` at `exposure_us` (the contrast as `plan --scene` builds it), and
/// [`polar_planner::optimise`] with `from.channels` angles at least `from.min_separation_deg`
/// apart (the stage's constraint) forming a Stokes set (the ideal measurement matrix's condition
/// number at most [`polar_planner::stokes::STOKES_MAX_CONDITION`], as `plan --scene` requires:
/// the capture computes Stokes products), to 0.01 deg.
///
/// Returns the angles (degrees in `[0, 180)`, sorted) and why: the choice's SCR beside the
/// conventional sets' (0/45/90, 0/60/120, 0/45/90/135), the clutter limit, the noise variance.
///
/// Errors: a target or background not in the scene (the message lists the scene's
/// materials); `exposure_us` not finite or `<= 0`; the model's (camera, band, materials); no
/// contrast between the two; fewer than 3 channels (no Stokes set).
pub fn planner_angles(
    scene: &Scene,
    camera: &Camera,
    from: &FromPlanner,
    exposure_us: f64,
) -> Result<(Vec<f64>, Value), ForecastError> {
    check_material(scene, "capture.from_planner.target", &from.target)?;
    check_material(scene, "capture.from_planner.background", &from.background)?;
    check_exposure("capture.exposure_us", exposure_us)?;
    let results = evaluate_materials(scene, &[&from.target, &from.background])?;
    let sensor = SensorModel::new(camera, &scene.spec.band).map_err(model_err("camera"))?;
    planner_choice(&sensor, &results[0], &results[1], from, exposure_us)
}

fn check_exposure(field: &str, exposure_us: f64) -> Result<(), ForecastError> {
    if exposure_us.is_finite() && exposure_us > 0.0 && exposure_us <= 1e11 {
        Ok(())
    } else {
        Err(ForecastError::Invalid {
            field: field.to_string(),
            value: exposure_us.to_string(),
            allowed: "finite, in (0, 1e11] us".into(),
        })
    }
}

/// One class's forecast for one set at `angles_deg` and `t_int_s` (module docs).
fn class_forecast(
    sensor: &SensorModel,
    class: &MaterialResult,
    angles_deg: &[f64],
    t_int_s: f64,
    notes: &mut Vec<String>,
) -> Result<ClassForecast, ForecastError> {
    let field = format!("material {}", class.name);
    let angles: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
    let quiet = sensor
        .signal(&angles, &Exposure::new(t_int_s, class.mean))
        .map_err(model_err(field.clone()))?;
    let cam = sensor.camera();
    let dn_per_radiance = cam.gain_dn_per_e * quiet.electrons_from_radiance;
    let w: &DMatrix<f64> = &quiet.intensities_from_stokes;
    let estimator = StokesEstimator::new(w, &quiet.cov_dn, MethodChoice::Ols)
        .map_err(model_err(field.clone()))?;
    let s_dn: Vector3<f64> = class.mean.0 * dn_per_radiance;
    let stats = dolp_aop_stats(&s_dn, &estimator.cov, RegimeChoice::Auto)
        .map_err(model_err(field.clone()))?;
    if stats.regime == Regime::Rice {
        notes.push(format!(
            "{}: polarised SNR {:.2} per set, below 3: Rice regime (the DoLP estimate is biased \
             upwards to {:.4})",
            class.name, stats.polarised_snr, stats.dolp_mean
        ));
    }
    // Saturation over the class's pixels: the texture spreads them too.
    let mut textured = Exposure::new(t_int_s, class.mean);
    textured.radiance_cov_w2_m4_sr2 = 0.5 * (class.cov + class.cov.transpose());
    let spread = sensor
        .signal(&angles, &textured)
        .map_err(model_err(field.clone()))?;
    let margin = saturation_margin(&spread);
    if margin < 0.0 {
        notes.push(format!(
            "{}: mean + 3 sigma exceeds saturation ({} DN) at {:.1} us: shorten the exposure \
             or lower the gain",
            class.name,
            spread.saturation_dn,
            t_int_s * 1e6
        ));
    }
    let p = s_dn[1].hypot(s_dn[2]);
    Ok(ClassForecast {
        material: class.name.clone(),
        mean_dn: quiet.mean_dn.iter().copied().collect(),
        s0_dn: s_dn[0],
        dolp: if s_dn[0] > 0.0 { p / s_dn[0] } else { 0.0 },
        aop_deg: stats.aop_mean_rad.to_degrees(),
        sigma_s0_dn: estimator.cov[(0, 0)].max(0.0).sqrt(),
        sigma_dolp: stats.dolp_std,
        sigma_aop_deg: stats.aop_std_rad.to_degrees(),
        saturation_margin: margin,
    })
}

/// The classes of a continuous plan: each half turn's frames through the span rows
/// (`polar_model::span::span_signal`), sigmas per half turn, the saturation margin from the
/// brightest span over the analyzer's phase (`polar_model::span::span_peak`, mean + 3 sigma).
fn continuous_classes(
    scene: &Scene,
    camera: &Camera,
    c: &crate::continuous::Continuous,
    names: &[&str],
    notes: &mut Vec<String>,
) -> Result<Vec<ClassForecast>, ForecastError> {
    use polar_model::span::{span_peak, span_signal, SpanExposure};
    let camera = camera_at_gain(camera, c.gain_db);
    let sensor = SensorModel::new(&camera, &scene.spec.band).map_err(model_err("camera"))?;
    notes.extend(sensor.warnings().iter().cloned());
    let spans = c.spans_rad();
    let t = c.exposure_us * 1e-6;
    notes.push(format!(
        "continuous: {} frames per half turn, each sweeping {:.4} deg (span rows, sinc {:.6});          sigmas are per half turn; the duration is at speed ({} deg/s), the stage's spin-up          not included",
        c.frames_per_half_turn,
        c.span_deg(),
        polar_model::span::sinc(c.span_deg().to_radians()),
        c.speed_deg_per_s
    ));
    let mut out = Vec::new();
    for r in evaluate_materials(scene, names)? {
        let field = format!("material {}", r.name);
        let s = span_signal(
            &sensor,
            &spans,
            &SpanExposure {
                t_int_s: t,
                radiance_w_m2_sr: r.mean.0,
                angle_sigma_rad: c.angle_sigma_rad(),
            },
        )
        .map_err(model_err(field.clone()))?;
        let stats = dolp_aop_stats(&s.stokes_dn, &s.stokes_cov_dn2, RegimeChoice::Auto)
            .map_err(model_err(field.clone()))?;
        let cov = 0.5 * (r.cov + r.cov.transpose());
        let (peak, peak_sigma) = span_peak(&sensor, c.span_deg().to_radians(), t, &r.mean.0, &cov)
            .map_err(model_err(field.clone()))?;
        let saturation = sensor.camera().saturation_dn();
        let margin = (saturation - (peak + 3.0 * peak_sigma)) / saturation;
        if margin < 0.0 {
            notes.push(format!(
                "{}: mean + 3 sigma of the brightest span exceeds saturation ({saturation} DN)",
                r.name
            ));
        }
        let p = s.stokes_dn[1].hypot(s.stokes_dn[2]);
        out.push(ClassForecast {
            material: r.name.clone(),
            mean_dn: s.mean_dn.clone(),
            s0_dn: s.stokes_dn[0],
            dolp: if s.stokes_dn[0] > 0.0 {
                p / s.stokes_dn[0]
            } else {
                0.0
            },
            aop_deg: stats.aop_mean_rad.to_degrees(),
            sigma_s0_dn: s.stokes_cov_dn2[(0, 0)].max(0.0).sqrt(),
            sigma_dolp: stats.dolp_std,
            sigma_aop_deg: stats.aop_std_rad.to_degrees(),
            saturation_margin: margin,
        });
    }
    Ok(out)
}

/// `(saturation - max_i(mean_i + 3 sigma_i)) / saturation`.
fn saturation_margin(s: &polar_model::sensor::SensorSignal) -> f64 {
    let top = (0..s.mean_dn.len())
        .map(|i| s.mean_dn[i] + 3.0 * s.cov_dn[(i, i)].max(0.0).sqrt())
        .fold(f64::NEG_INFINITY, f64::max);
    (s.saturation_dn - top) / s.saturation_dn
}

/// What point-row classes are computed at: the angles (degrees), the exposures (us; the first
/// is the classes', the rest are checked for saturation) and the gain (dB).
type ClassSettings = (Vec<f64>, Vec<f64>, f64);

/// The angles, exposures and gain a plan's classes are computed at (`None`: the kind has no
/// point-row classes: a continuous plan's come from its span rows, the calibrations use a
/// uniform source). A capture's or a continuous plan's `from_planner` is resolved in `plan`,
/// and said in `notes`.
fn class_settings(
    plan: &mut Plan,
    scene: &Scene,
    camera: &Camera,
    stage_limits: Option<StageLimits>,
    notes: &mut Vec<String>,
) -> Result<Option<ClassSettings>, ForecastError> {
    Ok(match plan.kind() {
        PlanKind::Capture => {
            let c = plan.capture().cloned().ok_or_else(|| PlanError::Invalid {
                field: "capture".into(),
                value: "(missing)".into(),
                allowed: "a [capture] section".into(),
            })?;
            let first = c
                .exposure_us
                .first()
                .copied()
                .ok_or_else(|| PlanError::Invalid {
                    field: "capture.exposure_us".into(),
                    value: "[]".into(),
                    allowed: "at least one exposure".into(),
                })?;
            check_exposure("capture.exposure_us[0]", first)?;
            let angles = match (&c.angles_deg, &c.from_planner) {
                (Some(a), _) => a.clone(),
                (None, Some(fp)) => {
                    let (angles, why) = planner_angles(scene, camera, fp, first)?;
                    notes.push(format!(
                        "angles from the planner: {angles:.2?} deg for target {:?} against \
                         background {:?} at {} us (SCR {}; conventional sets {})",
                        fp.target, fp.background, first, why["scr"], why["scr_conventional"]
                    ));
                    plan.resolve_angles(angles.clone())?;
                    angles
                }
                (None, None) => {
                    return Err(PlanError::Invalid {
                        field: "capture.angles_deg".into(),
                        value: "(neither)".into(),
                        allowed: "capture.angles_deg or capture.from_planner".into(),
                    }
                    .into())
                }
            };
            Some((angles, c.exposure_us.clone(), c.gain_db))
        }
        PlanKind::TimeLapse => plan
            .time_lapse()
            .map(|t| (t.angles_deg.clone(), vec![t.exposure_us], t.gain_db)),
        PlanKind::Adaptive => plan
            .adaptive()
            .map(|a| (a.initial_angles_deg.clone(), vec![a.exposure_us], a.gain_db)),
        // Span rows, not point rows: classes below from `continuous_classes`.
        PlanKind::Continuous => {
            if let Some(choice) =
                crate::continuous_planner::resolve(plan, scene, camera, stage_limits)?
            {
                notes.push(crate::continuous_planner::describe(&choice));
            }
            None
        }
        PlanKind::CalibrateNoise => {
            notes.push(
                "calibrate-noise: a uniform unpolarised source (an integrating sphere) fills \
                 the frame for the photon-transfer series, so the scene's classes do not apply"
                    .into(),
            );
            None
        }
        PlanKind::CalibrateAnalyzer => {
            if let Some(c) = plan.calibrate_analyzer() {
                notes.push(format!(
                    "calibrate-analyzer: a uniform source behind the reference polarizer at {} \
                     deg, swept through {} angles ({} deg apart) x {} repeats; fitted with \
                     Malus's law (analyzer_cal), so the scene's classes do not apply",
                    c.reference_angle_deg,
                    c.steps,
                    180.0 / f64::from(c.steps),
                    c.repeats
                ));
            }
            None
        }
    })
}

/// Each material's class forecast with point rows at `angles` (degrees), the first of
/// `exposures` (us) and `gain_db`; the longer exposures are checked for saturation, in `notes`.
fn point_classes(
    scene: &Scene,
    camera: &Camera,
    names: &[&str],
    (angles, exposures, gain_db): (&[f64], &[f64], f64),
    notes: &mut Vec<String>,
) -> Result<Vec<ClassForecast>, ForecastError> {
    let mut classes = Vec::new();
    let camera = camera_at_gain(camera, gain_db);
    let sensor = SensorModel::new(&camera, &scene.spec.band).map_err(model_err("camera"))?;
    notes.extend(sensor.warnings().iter().cloned());
    let results = evaluate_materials(scene, names)?;
    let t0 = exposures[0] * 1e-6;
    for r in &results {
        classes.push(class_forecast(&sensor, r, angles, t0, notes)?);
    }
    if exposures.len() > 1 {
        notes.push(format!(
            "classes at the first of {} exposures ({} us); sigmas are per set (one frame \
             per angle)",
            exposures.len(),
            exposures[0]
        ));
        // The longer exposures can saturate where the first does not.
        let radians: Vec<f64> = angles.iter().map(|a| a.to_radians()).collect();
        for &e in &exposures[1..] {
            for r in &results {
                let mut x = Exposure::new(e * 1e-6, r.mean);
                x.radiance_cov_w2_m4_sr2 = 0.5 * (r.cov + r.cov.transpose());
                let s = sensor
                    .signal(&radians, &x)
                    .map_err(model_err(format!("material {}", r.name)))?;
                if saturation_margin(&s) < 0.0 {
                    notes.push(format!(
                        "{}: mean + 3 sigma exceeds saturation ({} DN) at {e} us",
                        r.name, s.saturation_dn
                    ));
                }
            }
        }
    } else {
        notes.push("sigmas are per set (one frame per angle), sensor noise only".into());
    }
    if gain_db != 0.0 {
        notes.push(format!(
            "analog gain {gain_db} dB: K = {} DN/e-",
            camera.gain_dn_per_e
        ));
    }
    Ok(classes)
}

/// The forecast of `plan` (module docs) with the model of `scene` and `camera` and the rig's
/// `timing`. A capture whose angles come `from_planner` is resolved here with
/// [`planner_angles`] at its first exposure, a continuous plan's `from_planner` with
/// [`crate::continuous_planner::resolve`] (each says so in `notes`).
///
/// Errors: the plan's (a missing section); `timing` values not finite or negative (the speed
/// must be `> 0`); a planner target or background not in the scene (the message lists the
/// scene's materials); the model's, naming the material or the camera.
pub fn forecast(
    plan: &Plan,
    scene: &Scene,
    camera: &Camera,
    timing: &Timing,
) -> Result<Forecast, ForecastError> {
    timing.validate()?;
    let mut plan = plan.clone();
    let mut notes: Vec<String> = Vec::new();
    let names: Vec<&str> = scene.materials.iter().map(|m| m.name.as_str()).collect();
    let at = class_settings(&mut plan, scene, camera, timing.stage_limits, &mut notes)?;

    let steps = plan.steps()?;
    let darks = steps.iter().filter(|s| s.kind == FrameKind::Dark).count() as u64;
    let mut sets: Vec<u64> = steps.iter().filter_map(|s| s.set).collect();
    sets.dedup();
    let mut sets = sets.len() as u64;
    let mut frames = steps.len() as u64;
    let (mut duration_s, _) = schedule(&steps, timing);
    if let Some(a) = plan.adaptive() {
        let first = a.initial_angles_deg.len();
        let more = a.frame_budget.saturating_sub(first) / a.channels.max(1);
        let extra = (more * a.channels) as u64;
        frames += extra;
        sets += more as u64;
        duration_s += extra as f64
            * (90.0 / timing.stage_deg_per_s
                + timing.settle_s
                + a.exposure_us * 1e-6
                + timing.readout_s);
        notes.push(format!(
            "adaptive: the frames are at most the budget ({} frames: the first set of {first} \
             and up to {more} more sets of {}), and the loop may stop sooner; the duration is \
             an upper bound (90-degree moves for the planner's sets, the planner's own time \
             left out)",
            a.frame_budget, a.channels
        ));
    }
    if let Some(t) = plan.time_lapse() {
        notes.push(format!(
            "time-lapse: the last set starts at {} s",
            f64::from(t.count.saturating_sub(1)) * t.interval_s
        ));
    }

    let mut classes = Vec::new();
    if let Some(c) = plan.continuous() {
        // The schedule above is step-and-shoot's; at speed the half turns take their time.
        duration_s = c.duration_at_speed_s();
        classes = continuous_classes(scene, camera, c, &names, &mut notes)?;
    }
    let angles_deg = at.as_ref().map(|(a, _, _)| a.clone());
    if let Some((angles, exposures, gain_db)) = at {
        classes = point_classes(
            scene,
            camera,
            &names,
            (&angles, &exposures, gain_db),
            &mut notes,
        )?;
    }
    Ok(Forecast {
        kind: plan.kind().name().to_string(),
        frames,
        sets,
        darks,
        duration_s,
        angles_deg,
        classes,
        notes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use polar_model::validation::{simulate_products, McConfig, McSource};

    const SCENE: &str = include_str!("../../../examples/rooftop_panels.toml");
    const CAMERA: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

    fn models() -> (Scene, Camera) {
        (
            Scene::from_toml_str(SCENE).expect("scene"),
            Camera::from_toml_str(CAMERA).expect("camera"),
        )
    }

    const CAPTURE: &str = r#"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [2000]
repeats = 2
darks_before = 1
darks_after = 1
"#;

    /// The example continuous plan (4 frames per half turn, 20 half turns at 360 deg/s, 2 ms
    /// each): 80 frames in 20 sets, 10 s at speed (exact: 20 x 180 / 360); one class per
    /// material with finite sigmas. Its S1/S2 rows are scaled by sinc(0.72 deg); the same
    /// section spun at 20000 deg/s (beyond a plan's range, taken here for its 40-deg span at
    /// the same exposure) predicts a larger DoLP sigma for every class: the polarised terms
    /// shrink by sinc(40 deg) = 0.92 and nothing else changes.
    #[test]
    fn continuous_frames_duration_and_span_rows() {
        let (scene, camera) = models();
        let plan =
            Plan::from_toml_str(include_str!("../../../examples/plans/continuous.toml")).unwrap();
        let f =
            forecast(&plan, &scene, &camera, &Timing::simulated(&plan, None)).expect("forecast");
        assert_eq!((f.frames, f.sets, f.darks), (80, 20, 0));
        assert!((f.duration_s - 10.0).abs() < 1e-12, "{}", f.duration_s);
        assert_eq!(f.classes.len(), scene.materials.len());
        let mut wide = plan.clone();
        if let Some(c) = wide.continuous_mut() {
            c.speed_deg_per_s = 20_000.0;
        }
        let w =
            forecast(&wide, &scene, &camera, &Timing::simulated(&wide, None)).expect("forecast");
        for (a, b) in f.classes.iter().zip(&w.classes) {
            assert!(a.sigma_dolp.is_finite() && a.sigma_s0_dn > 0.0, "{a:?}");
            assert!(
                b.sigma_dolp > a.sigma_dolp,
                "{}: {b:?} vs {a:?}",
                a.material
            );
        }
    }

    /// A capture of 4 angles x 2 repeats with a dark before and after: the frames are the
    /// steps, and the duration is the sum of the parts by hand (tolerance 1e-12 relative:
    /// the same sums in another order). The stage starts at 0: the dark before and the first
    /// 0-deg frame do not move; then 45-deg moves 0 -> 45 -> 90 -> 135 -> 0 (the short way)
    /// -> 45 -> 90 -> 135, and 135 -> 0 for the dark after: 8 moves of 45 deg.
    #[test]
    fn capture_frames_and_duration() {
        let (scene, camera) = models();
        let plan = Plan::from_toml_str(CAPTURE).expect("plan");
        let timing = Timing {
            stage_deg_per_s: 90.0,
            settle_s: 0.1,
            readout_s: 0.005,
            stage_limits: None,
        };
        let f = forecast(&plan, &scene, &camera, &timing).expect("forecast");
        assert_eq!(f.frames, plan.steps().expect("steps").len() as u64);
        assert_eq!(f.frames, 10);
        assert_eq!((f.sets, f.darks), (2, 2));
        let by_hand = 8.0 * (45.0 / 90.0 + 0.1) + 10.0 * (2000e-6 + 0.005);
        assert!(
            (f.duration_s - by_hand).abs() < 1e-12 * by_hand,
            "{} against {by_hand}",
            f.duration_s
        );
        assert_eq!(f.angles_deg.as_deref(), Some(&[0.0, 45.0, 90.0, 135.0][..]));
        assert_eq!(f.classes.len(), scene.materials.len());
        for c in &f.classes {
            assert_eq!(c.mean_dn.len(), 4);
            assert!(c.sigma_dolp > 0.0 && c.sigma_dolp.is_finite(), "{c:?}");
            assert!(c.saturation_margin < 1.0);
        }
        // Timing::simulated: the plan's stage speed (720 deg/s by default), 200 Hz readout.
        let sim = Timing::simulated(&plan, None);
        assert_eq!(
            (sim.stage_deg_per_s, sim.settle_s, sim.readout_s),
            (720.0, 0.0, 0.005)
        );
        let json = serde_json::to_value(&f).expect("json");
        assert_eq!(json["kind"], "capture");
    }

    /// sigma_dolp of the rooftop panel class against the whole-chain Monte Carlo of the same
    /// frames (Poisson electrons, read noise, rounding; no clutter; OLS Stokes): within 10 %.
    /// The Monte Carlo's own standard error of the DoLP spread is about 1/sqrt(2 n) = 0.5 %
    /// for n = 20 000 sets, so the bound tests the analytic propagation, not the sampling.
    #[test]
    fn panel_sigma_dolp_matches_monte_carlo() {
        let (scene, camera) = models();
        let plan = Plan::from_toml_str(CAPTURE).expect("plan");
        let f =
            forecast(&plan, &scene, &camera, &Timing::simulated(&plan, None)).expect("forecast");
        let panel = f
            .classes
            .iter()
            .find(|c| c.material == "panel")
            .expect("panel");
        let results = evaluate_materials(&scene, &["panel"]).expect("panel");
        let sensor = SensorModel::new(&camera, &scene.spec.band).expect("sensor");
        let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let exposure = Exposure::new(2000e-6, results[0].mean);
        let mc = simulate_products(
            &sensor,
            &angles,
            &exposure,
            &McConfig {
                sets: 20_000,
                seed: 7,
                threads: 1,
                method: MethodChoice::Ols,
                source: McSource::Chain,
            },
        )
        .expect("monte carlo");
        let rel = panel.sigma_dolp / mc.dolp_std - 1.0;
        let rel_aop = panel.sigma_aop_deg / mc.aop_std_rad.to_degrees() - 1.0;
        eprintln!(
            "panel: DoLP {:.4}, sigma_dolp forecast {:.5} MC {:.5} +- {:.5} ({:+.2} %); sigma_aop \
             forecast {:.4} deg MC {:.4} deg ({:+.2} %); s0 {:.1} DN, margin {:.3}",
            panel.dolp,
            panel.sigma_dolp,
            mc.dolp_std,
            mc.dolp_std_se,
            100.0 * rel,
            panel.sigma_aop_deg,
            mc.aop_std_rad.to_degrees(),
            100.0 * rel_aop,
            panel.s0_dn,
            panel.saturation_margin
        );
        assert!(rel.abs() < 0.10, "sigma_dolp off by {rel}");
        assert!(rel_aop.abs() < 0.10, "sigma_aop off by {rel_aop}");
    }

    /// The planner's set scores at least the conventional sets of as many channels (it
    /// maximises the SCR over all sets that respect the 30-degree separation, which those
    /// do), to 1e-9 relative; with 4 channels also the 3-angle sets (a 4th angle only adds
    /// information). Its SCR is the matched-filter SCR of the frames this forecast describes
    /// (`SensorModel::signal` with the background's clutter), to 1e-9 relative (the same
    /// number by two algebraic routes), not an ideal-analyzer figure.
    #[test]
    fn planner_beats_conventional_sets() {
        let (scene, camera) = models();
        let results = evaluate_materials(&scene, &["panel", "asphalt"]).expect("classes");
        let sensor = SensorModel::new(&camera, &scene.spec.band).expect("sensor");
        let forecast_scr = |angles_deg: &[f64]| {
            let rad: Vec<f64> = angles_deg.iter().map(|a| a.to_radians()).collect();
            let frames = |r: &MaterialResult, field| {
                let mut e = Exposure::new(2000e-6, r.mean);
                e.radiance_cov_w2_m4_sr2 = 0.5 * (results[1].cov + results[1].cov.transpose());
                let s = sensor.signal(&rad, &e).expect("frames");
                polar_model::metrics::ClassStats::new(field, s.mean_dn, s.cov_dn).expect("class")
            };
            let (t, b) = (
                frames(&results[0], "target"),
                frames(&results[1], "background"),
            );
            polar_model::metrics::matched_filter(&t, &b, 1e-3)
                .expect("roc")
                .scr
        };
        for channels in [3usize, 4] {
            let from = FromPlanner {
                target: "panel".into(),
                background: "asphalt".into(),
                channels,
                min_separation_deg: 30.0,
            };
            let (angles, why) = planner_angles(&scene, &camera, &from, 2000.0).expect("angles");
            assert_eq!(angles.len(), channels);
            assert!(distinct_angles(&angles) == channels, "{angles:?}");
            let scr = why["scr"].as_f64().expect("scr");
            let forecast = forecast_scr(&angles);
            assert!(
                (scr - forecast).abs() <= 1e-9 * forecast,
                "planner {scr} against the forecast's {forecast}"
            );
            let conv = why["scr_conventional"].as_object().expect("conventional");
            eprintln!("{channels} channels: {angles:.2?} SCR {scr:.6}; conventional {conv:?}");
            for (name, v) in conv {
                let v = v.as_f64().expect("number");
                let n = name.split('/').count();
                if n <= channels {
                    assert!(scr >= v * (1.0 - 1e-9), "{name}: {v} > {scr}");
                }
            }
        }
    }

    /// A planner target not in the scene is an error that names the field and lists the
    /// scene's materials; a capture from the planner is resolved in the forecast and says so.
    #[test]
    fn planner_errors_and_resolution() {
        let (scene, camera) = models();
        let from = FromPlanner {
            target: "roof".into(),
            background: "asphalt".into(),
            channels: 3,
            min_separation_deg: 30.0,
        };
        let e = planner_angles(&scene, &camera, &from, 2000.0)
            .expect_err("unknown")
            .to_string();
        assert!(e.contains("capture.from_planner.target"), "{e}");
        assert!(e.contains("panel, glass, asphalt, grass, metal"), "{e}");
        let text = r#"
kind = "capture"
[capture]
from_planner = { target = "panel", background = "asphalt" }
exposure_us = [2000]
"#;
        let plan = Plan::from_toml_str(text).expect("plan");
        let f =
            forecast(&plan, &scene, &camera, &Timing::simulated(&plan, None)).expect("forecast");
        assert_eq!(f.frames, 3);
        assert!(
            f.notes
                .iter()
                .any(|n| n.contains("angles from the planner")),
            "{:?}",
            f.notes
        );
        let bad = Timing {
            stage_deg_per_s: 0.0,
            settle_s: 0.0,
            readout_s: 0.0,
            stage_limits: None,
        };
        let e = forecast(&plan, &scene, &camera, &bad)
            .expect_err("timing")
            .to_string();
        assert!(e.contains("timing.stage_deg_per_s"), "{e}");
    }

    /// A continuous plan from the planner is resolved in the forecast: its frames are the
    /// chosen frames per half turn times the half turns, its duration the half turns at the
    /// chosen speed (1e-12 relative: one product and one quotient), and a note names the
    /// choice and the limits that bind.
    #[test]
    fn continuous_from_planner_is_resolved() {
        let (scene, camera) = models();
        let plan = Plan::from_toml_str(
            "kind = \"continuous\"\n[continuous]\nhalf_turns = 3\nfrom_planner = { target = \
             \"panel\", background = \"asphalt\", max_frames_per_half_turn = 12 }\n\
             [simulation]\nstage_deg_per_s = 360\n",
        )
        .expect("plan");
        // The simulated rig's default stage at 360 deg/s (`polar_rig::sim_stage`).
        let stage = Some(polar_planner::continuous::StageLimits {
            max_speed_rad_per_s: 360f64.to_radians(),
            acceleration_rad_per_s2: 2880f64.to_radians(),
        });
        let f =
            forecast(&plan, &scene, &camera, &Timing::simulated(&plan, stage)).expect("forecast");
        let mut resolved = plan.clone();
        crate::continuous_planner::resolve(&mut resolved, &scene, &camera, stage).expect("resolve");
        let c = resolved.continuous().cloned().expect("section");
        assert_eq!(f.frames, 3 * u64::from(c.frames_per_half_turn));
        let at_speed = 3.0 * 180.0 / c.speed_deg_per_s;
        assert!((f.duration_s - at_speed).abs() <= 1e-12 * at_speed);
        assert!(
            f.notes
                .iter()
                .any(|n| n.starts_with("continuous.from_planner") && n.contains("binding")),
            "{:?}",
            f.notes
        );
    }

    /// Time-lapse: the last set starts at (count - 1) x interval, then takes its own frames;
    /// adaptive: the budget bounds the frames; calibrations: no classes, with the reason.
    #[test]
    fn other_kinds() {
        let (scene, camera) = models();
        let timing = Timing {
            stage_deg_per_s: 60.0,
            settle_s: 0.0,
            readout_s: 0.01,
            stage_limits: None,
        };
        let tl = Plan::from_toml_str(
            "kind = \"time-lapse\"\n[time-lapse]\nangles_deg = [0, 60, 120]\nexposure_us = \
             1000\ninterval_s = 10\ncount = 3\n",
        )
        .expect("plan");
        let f = forecast(&tl, &scene, &camera, &timing).expect("forecast");
        // Last set: from 120 (end of set 2) to 0 is 60 deg (1 s), then 60 -> 120: 2 more moves.
        let last_set = 3.0 * 1.0 + 3.0 * (1e-3 + 0.01);
        assert!(
            (f.duration_s - (20.0 + last_set)).abs() < 1e-9,
            "{}",
            f.duration_s
        );
        assert_eq!((f.frames, f.sets, f.darks), (9, 3, 0));

        let ad = Plan::from_toml_str(
            "kind = \"adaptive\"\n[adaptive]\ninitial_angles_deg = [0, 60, 120]\nexposure_us = \
             3000\nframe_budget = 13\ndarks = 2\ntarget = { material = \"panel\" }\n",
        )
        .expect("plan");
        let f = forecast(&ad, &scene, &camera, &timing).expect("forecast");
        // 3 + 3 x 3 = 12 <= 13 frames, plus 2 darks; 4 sets.
        assert_eq!((f.frames, f.sets, f.darks), (14, 4, 2));
        assert!(f.frames <= ad.max_frames().expect("max"));
        assert!(f.notes.iter().any(|n| n.contains("at most the budget")));
        assert_eq!(f.classes.len(), 5);

        let ca = Plan::from_toml_str(
            "kind = \"calibrate-analyzer\"\n[calibrate-analyzer]\nreference_angle_deg = \
             10\nsteps = 36\nexposure_us = 2000\n",
        )
        .expect("plan");
        let f = forecast(&ca, &scene, &camera, &timing).expect("forecast");
        assert_eq!((f.frames, f.darks), (38, 2));
        assert!(f.classes.is_empty());
        assert!(f.notes.iter().any(|n| n.contains("do not apply")));
        // 35 moves of 5 deg after the first angle (0 deg, where the stage is).
        let by_hand = 35.0 * 5.0 / 60.0 + 38.0 * (2e-3 + 0.01);
        assert!((f.duration_s - by_hand).abs() < 1e-9, "{}", f.duration_s);
    }
}
