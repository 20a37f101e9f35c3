//! The planner panel: the SCR-optimal analyzer set for a target against a background
//! of the simulated scene, beside the conventional sets, with each set's matched-filter
//! detection probability and ROC curve.
//!
//! # What is computed (MODEL.md sections 8 and 9)
//!
//! The scene and camera are the simulated rig's defaults
//! ([`polar_rig::simulated::DEFAULT_SCENE`], [`polar_rig::simulated::DEFAULT_CAMERA`]). The two
//! materials are evaluated over the field of view at [`polar_engine::forecast::SCENE_TOL`]
//! (their band Stokes means `mu_t`, `mu_b` and texture covariances `Sigma_t`, `Sigma_b`, in
//! W m^-2 sr^-1). The planner's contrast is the one `polarimeter plan --scene` and
//! [`polar_engine::forecast::planner_angles`] build, [`Contrast::from_sensor`]:
//! `d = mu_t - mu_b`, the background's clutter `Sigma_b`, the camera's real analyzer rows
//! (principal transmittances, offset, fore-optics) and its per-frame noise at the background's
//! light (a floor `V` from dark current, read noise and quantisation, and the shot noise, which
//! follows the light each angle lets through), in radiance units. Then (MODEL.md section 9)
//!
//! `SCR(Psi) = (W d)^T (W Sigma_b W^T + D)^-1 (W d)`, `D = diag(V + c w_i . mu_b)`,
//!
//! maximised by [`polar_planner::optimise`] over `N` angles at least `min_separation_deg` apart
//! (to 0.01 deg), and evaluated for the conventional sets of [`polar_planner::conventional`].
//!
//! Detection (MODEL.md section 8): the linear matched filter [`polar_model::metrics::matched_filter`]
//! on the frames of a set as the camera model gives them ([`SensorModel::signal`]: each class's
//! mean and texture through the real analyzer, each class's own sensor noise), in DN: the
//! forecast of `plan --scene`. Its SCR is the planner's objective (the panel notes any
//! difference above 1e-6 relative), so the optimum the table prints is optimal under the same
//! numbers the table and the ROC curves show.
//!
//! An optimum over `N` frames is compared fairly only with sets of the same number of frames
//! (one more frame never lowers the SCR), so the table's relative column divides each set's
//! SCR by the optimum with as many angles as that set has. The optimum keeps the minimum
//! separation; a conventional set with closer angles is outside that constraint and may beat
//! it (the notes say so).

use eframe::egui;
use egui_plot::{Legend, Line, Plot, PlotPoints};
use nalgebra::Matrix3;
use polar_engine::forecast::SCENE_TOL;
use polar_engine::plan::{Plan, PlanKind};
use polar_model::metrics::{matched_filter, ClassStats};
use polar_model::scene::{MaterialResult, Prepared};
use polar_model::scene_file::Scene;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_planner::optimize::MAX_CHANNELS;
use polar_planner::{conventional, optimise, Constraints, Contrast};
use polar_rig::simulated::{DEFAULT_CAMERA, DEFAULT_SCENE};

/// The optimiser's angle tolerance, degrees (as the engine's forecast and the CLI use).
const PLANNER_TOL_DEG: f64 = 0.01;

/// Angles closer than this (degrees, modulo 180) count as one when counting distinct angles.
const DISTINCT_DEG: f64 = 0.01;

/// Colours of the ROC curves: the optimum first, then the conventional sets.
const COLOURS: [egui::Color32; 4] = [
    egui::Color32::from_rgb(220, 60, 40),
    egui::Color32::from_rgb(40, 110, 220),
    egui::Color32::from_rgb(30, 160, 80),
    egui::Color32::from_rgb(170, 90, 200),
];

/// What the planner is asked: two materials of the default scene and the acquisition.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannerInputs {
    /// Target material (a name in the scene).
    pub target: String,
    /// Background material (a name in the scene).
    pub background: String,
    /// Exposure of every frame, microseconds, in `(0, 1e11]`.
    pub exposure_us: f64,
    /// Analyzer angles of the optimal set, `1..=6`.
    pub channels: usize,
    /// Smallest separation between two angles of the optimal set, degrees, `[0, 90)` and at
    /// most `180 / channels`.
    pub min_separation_deg: f64,
    /// False-alarm rate of the table's `Pd`, `(0, 1)`.
    pub pfa: f64,
}

impl Default for PlannerInputs {
    /// The default scene's glass against asphalt at 250 us, three angles at least 30 degrees
    /// apart, `Pd` at `Pfa = 1e-3`: a pair whose ROC curves separate (glass's DoLP is low at
    /// this geometry; the painted panel of `examples/plans/planner.toml` is detected with
    /// `Pd = 1` by every set, which shows nothing).
    fn default() -> Self {
        PlannerInputs {
            target: "glass".into(),
            background: "asphalt".into(),
            exposure_us: 250.0,
            channels: 3,
            min_separation_deg: 30.0,
            pfa: 1e-3,
        }
    }
}

/// One analyzer set of the table: its SCR, its detection probability and ROC curve.
#[derive(Debug, Clone, PartialEq)]
pub struct SetRow {
    /// The set's name: `optimal N` or the conventional set's (`0/45/90`, ...).
    pub name: String,
    /// Whether this is the planner's optimum.
    pub optimal: bool,
    /// The angles, degrees in `[0, 180)`.
    pub angles_deg: Vec<f64>,
    /// Signal-to-clutter ratio (MODEL.md section 9), dimensionless.
    pub scr: f64,
    /// The optimum's SCR with as many angles as this set (same separation), for the relative
    /// column.
    pub scr_optimum_same_n: f64,
    /// `scr / scr_optimum_same_n` (NaN when that optimum is 0: no contrast).
    pub scr_relative: f64,
    /// Matched-filter detection probability at the inputs' `pfa` (MODEL.md section 8).
    pub pd: f64,
    /// The ROC curve, `[pfa, pd]`, `pfa` log-spaced from `1e-6` to `1`.
    pub roc: Vec<[f64; 2]>,
}

/// The last computation: one row per set (the optimum first), and the notes.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannerResult {
    /// What was computed.
    pub inputs: PlannerInputs,
    /// The optimum, then the conventional sets of [`polar_planner::conventional`].
    pub rows: Vec<SetRow>,
    /// The clutter-limited SCR `d^T Sigma_b^-1 d` (no sensor noise; infinite if `Sigma_b` is
    /// singular along `d`).
    pub scr_clutter_limit: f64,
    /// Condition number of the background's clutter covariance `Sigma_b`, as given.
    pub clutter_condition: f64,
    /// The angle-independent part of the per-frame sensor noise variance, the floor `V` (dark
    /// current, read noise, quantisation), (W m^-2 sr^-1)^2; the shot noise adds to it per angle.
    pub noise_var_w2_m4_sr2: f64,
    /// What the user should know: the planner's regularisation, no contrast, the sensor's and
    /// the ROC's warnings, degenerate sets.
    pub notes: Vec<String>,
}

impl PlannerResult {
    /// The optimum's row.
    pub fn optimum(&self) -> Option<&SetRow> {
        self.rows.iter().find(|r| r.optimal)
    }
}

/// The default scene and camera, and the materials evaluated so far (the scene's evaluation is
/// the slow part, so the panel keeps it between computations).
struct Model {
    scene: Scene,
    sensor: SensorModel,
    prepared: Option<Prepared>,
    evaluated: Vec<MaterialResult>,
}

impl Model {
    fn new() -> Result<Model, String> {
        let scene =
            Scene::from_toml_str(DEFAULT_SCENE).map_err(|e| format!("default scene: {e}"))?;
        let camera =
            Camera::from_toml_str(DEFAULT_CAMERA).map_err(|e| format!("default camera: {e}"))?;
        let sensor = SensorModel::new(&camera, &scene.spec.band)
            .map_err(|e| format!("default camera: {e}"))?;
        Ok(Model {
            scene,
            sensor,
            prepared: None,
            evaluated: Vec::new(),
        })
    }

    fn material_names(&self) -> Vec<String> {
        self.scene
            .materials
            .iter()
            .map(|m| m.name.clone())
            .collect()
    }

    /// The material's band Stokes mean and clutter over the field of view (cached).
    fn material(&mut self, field: &str, name: &str) -> Result<MaterialResult, String> {
        if let Some(m) = self.evaluated.iter().find(|m| m.name == name) {
            return Ok(m.clone());
        }
        let spec = self
            .scene
            .materials
            .iter()
            .find(|m| m.name == name)
            .ok_or_else(|| {
                format!(
                    "{field} = {name:?} is not a material of the scene: allowed {}",
                    self.material_names().join(", ")
                )
            })?;
        let prepared = match self.prepared.take() {
            Some(p) => p,
            None => {
                Prepared::new(&self.scene.spec, SCENE_TOL).map_err(|e| format!("scene: {e}"))?
            }
        };
        let result = prepared
            .evaluate(spec)
            .map_err(|e| format!("material {name}: {e}"));
        self.prepared = Some(prepared);
        let result = result?;
        self.evaluated.push(result.clone());
        Ok(result)
    }

    fn compute(&mut self, inputs: &PlannerInputs) -> Result<PlannerResult, String> {
        check_inputs(inputs)?;
        let target = self.material("target", &inputs.target)?;
        let background = self.material("background", &inputs.background)?;
        compute_from(&self.sensor, &target, &background, inputs)
    }
}

fn check_inputs(inputs: &PlannerInputs) -> Result<(), String> {
    if !(inputs.exposure_us.is_finite() && inputs.exposure_us > 0.0 && inputs.exposure_us <= 1e11) {
        return Err(format!(
            "exposure_us = {} is out of range: allowed finite, in (0, 1e11] us",
            inputs.exposure_us
        ));
    }
    if !(1..=MAX_CHANNELS).contains(&inputs.channels) {
        return Err(format!(
            "channels = {} is out of range: allowed 1 to {MAX_CHANNELS}",
            inputs.channels
        ));
    }
    if !(inputs.pfa.is_finite() && inputs.pfa > 0.0 && inputs.pfa < 1.0) {
        return Err(format!(
            "pfa = {} is out of range: allowed (0, 1)",
            inputs.pfa
        ));
    }
    if !(inputs.min_separation_deg.is_finite() && (0.0..90.0).contains(&inputs.min_separation_deg))
    {
        return Err(format!(
            "min_separation_deg = {} is out of range: allowed [0, 90)",
            inputs.min_separation_deg
        ));
    }
    Ok(())
}

/// The planner's contrast in radiance units at `t_int_s` (module docs; the call sequence of the
/// engine's forecast and of `polarimeter plan --scene`).
fn contrast_at(
    sensor: &SensorModel,
    target: &MaterialResult,
    background: &MaterialResult,
    t_int_s: f64,
) -> Result<Contrast, String> {
    Contrast::from_sensor(
        sensor,
        t_int_s,
        &target.mean.0,
        &background.mean.0,
        &symmetric(&background.cov),
    )
    .map_err(|e| format!("planner: {e}"))
}

/// The matched filter on the frames of one set at `t_int_s` (module docs): the forecast.
fn forecast_roc(
    sensor: &SensorModel,
    angles_rad: &[f64],
    t_int_s: f64,
    target: &MaterialResult,
    background: &MaterialResult,
    pfa: f64,
) -> Result<polar_model::metrics::Roc, String> {
    let frames = |field: &'static str, class: &MaterialResult| -> Result<ClassStats, String> {
        let mut e = Exposure::new(t_int_s, class.mean);
        e.radiance_cov_w2_m4_sr2 = symmetric(&class.cov);
        let s = sensor
            .signal(angles_rad, &e)
            .map_err(|e| format!("material {}: {e}", class.name))?;
        ClassStats::new(field, s.mean_dn, s.cov_dn)
            .map_err(|e| format!("material {}: {e}", class.name))
    };
    matched_filter(
        &frames("target", target)?,
        &frames("background", background)?,
        pfa,
    )
    .map_err(|e| format!("matched filter: {e}"))
}

fn symmetric(m: &Matrix3<f64>) -> Matrix3<f64> {
    0.5 * (m + m.transpose())
}

/// Distinct angles of a set (degrees), modulo 180.
fn distinct_angles(angles_deg: &[f64]) -> usize {
    let mut seen: Vec<f64> = Vec::new();
    for a in angles_deg {
        let a = a.rem_euclid(180.0);
        let new = !seen.iter().any(|s| {
            let d = (a - s).rem_euclid(180.0);
            d.min(180.0 - d) < DISTINCT_DEG
        });
        if new {
            seen.push(a);
        }
    }
    seen.len()
}

/// The smallest separation between two angles of a set (radians in), degrees modulo 180
/// (180 for fewer than two angles).
fn closest_pair_deg(angles_rad: &[f64]) -> f64 {
    let mut closest = 180.0f64;
    for (i, a) in angles_rad.iter().enumerate() {
        for b in &angles_rad[i + 1..] {
            let d = (a - b).to_degrees().rem_euclid(180.0);
            closest = closest.min(d.min(180.0 - d));
        }
    }
    closest
}

fn compute_from(
    sensor: &SensorModel,
    target: &MaterialResult,
    background: &MaterialResult,
    inputs: &PlannerInputs,
) -> Result<PlannerResult, String> {
    let contrast = contrast_at(sensor, target, background, inputs.exposure_us * 1e-6)?;
    let constraints = Constraints {
        min_separation_rad: inputs.min_separation_deg.to_radians(),
        ..Constraints::default()
    };
    let tol_rad = PLANNER_TOL_DEG.to_radians();
    // The optimum per number of angles, computed once each.
    let mut optima: Vec<(usize, polar_planner::Optimum)> = Vec::new();
    let mut optimum_for = |n: usize| -> Result<polar_planner::Optimum, String> {
        if let Some((_, o)) = optima.iter().find(|(k, _)| *k == n) {
            return Ok(o.clone());
        }
        let o =
            optimise(&contrast, n, &constraints, tol_rad).map_err(|e| format!("planner: {e}"))?;
        optima.push((n, o.clone()));
        Ok(o)
    };
    let opt = optimum_for(inputs.channels)?;

    let mut notes: Vec<String> = sensor.warnings().to_vec();
    notes.extend(contrast.notes.iter().cloned());
    let mut rows = Vec::new();
    let mut sets: Vec<(String, bool, Vec<f64>, f64)> = vec![(
        format!("optimal {}", inputs.channels),
        true,
        opt.angles_rad.clone(),
        opt.scr,
    )];
    for (name, scr) in conventional(&contrast) {
        let rad: Vec<f64> = name
            .split('/')
            .filter_map(|d| d.parse::<f64>().ok())
            .map(f64::to_radians)
            .collect();
        sets.push((name.to_string(), false, rad, scr));
    }
    for (name, optimal, angles_rad, scr) in sets {
        if !optimal {
            let closest_deg = closest_pair_deg(&angles_rad);
            if closest_deg < inputs.min_separation_deg - 1e-9 {
                notes.push(format!(
                    "{name} has angles {closest_deg:.1} deg apart, closer than the minimum \
                     separation of {} deg the optimum keeps: it may beat that optimum",
                    inputs.min_separation_deg
                ));
            }
        }
        let scr_optimum_same_n = if optimal {
            scr
        } else {
            match optimum_for(angles_rad.len()) {
                Ok(o) => o.scr,
                Err(e) => {
                    // The separation may not admit as many angles as the set has.
                    notes.push(format!(
                        "{name}: no optimum with {} angles: {e}",
                        angles_rad.len()
                    ));
                    f64::NAN
                }
            }
        };
        let roc = forecast_roc(
            sensor,
            &angles_rad,
            inputs.exposure_us * 1e-6,
            target,
            background,
            inputs.pfa,
        )
        .map_err(|e| format!("{name}: {e}"))?;
        if (roc.scr - scr).abs() > 1e-6 * roc.scr.max(1e-300) {
            notes.push(format!(
                "{name}: the forecast's SCR {} differs from the planner's {scr} by more than \
                 1e-6 relative",
                roc.scr
            ));
        }
        for w in &roc.warnings {
            let line = format!("{name}: {w}");
            if !notes.contains(&line) {
                notes.push(line);
            }
        }
        let angles_deg: Vec<f64> = angles_rad
            .iter()
            // To 1e-6 deg (the optimiser's tolerance is 0.01 deg): readable, and 180 wraps to 0.
            .map(|a| ((a.to_degrees() * 1e6).round() / 1e6).rem_euclid(180.0))
            .collect();
        if optimal {
            let distinct = distinct_angles(&angles_deg);
            if distinct < 3 {
                notes.push(format!(
                    "the optimal set has {distinct} distinct angle(s): it detects in the \
                     intensity frames but forms no Stokes image (raise the separation, e.g. 30 deg)"
                ));
            }
        }
        let scr_relative = if scr_optimum_same_n > 0.0 {
            scr / scr_optimum_same_n
        } else {
            f64::NAN
        };
        rows.push(SetRow {
            name,
            optimal,
            angles_deg,
            scr,
            scr_optimum_same_n,
            scr_relative,
            pd: roc.pd,
            roc: roc.curve,
        });
    }
    if contrast.clutter_condition > 1e8 {
        notes.push(format!(
            "the background clutter covariance is ill-conditioned (condition number {:.3e})",
            contrast.clutter_condition
        ));
    }
    Ok(PlannerResult {
        inputs: inputs.clone(),
        rows,
        scr_clutter_limit: contrast.clutter_limit(),
        clutter_condition: contrast.clutter_condition,
        noise_var_w2_m4_sr2: contrast.noise_var,
        notes,
    })
}

/// The planner's table and ROC curves for `inputs` on the default scene and camera (module
/// docs). Pure: it parses the scene and camera and evaluates the two materials each call (a
/// fraction of a second; the panel keeps the evaluation between calls).
///
/// Errors (as text naming the field): a material not in the scene (the message lists the
/// scene's materials), inputs out of range, the model's or the planner's failures.
pub fn compute(inputs: &PlannerInputs) -> Result<PlannerResult, String> {
    Model::new()?.compute(inputs)
}

/// The names of the default scene's materials, in the scene's order (for the combo boxes).
pub fn scene_materials() -> Result<Vec<String>, String> {
    let scene = Scene::from_toml_str(DEFAULT_SCENE).map_err(|e| format!("default scene: {e}"))?;
    Ok(scene.materials.iter().map(|m| m.name.clone()).collect())
}

/// The planner panel: inputs, a Compute button, the table, the ROC plot and the notes.
pub struct PlannerPanel {
    /// The inputs as edited.
    inputs: PlannerInputs,
    /// The model, or why it could not be built.
    model: Result<Model, String>,
    /// The last computation's outcome.
    outcome: Option<Result<PlannerResult, String>>,
    /// The plan text last given to [`PlannerPanel::set_plan_text`].
    plan_seen: Option<String>,
    /// What [`PlannerPanel::set_plan_text`] said about the plan.
    plan_note: Option<String>,
    /// Compute on the next [`PlannerPanel::show`].
    pending: bool,
}

impl Default for PlannerPanel {
    fn default() -> Self {
        PlannerPanel::new()
    }
}

impl PlannerPanel {
    /// A panel with the default inputs ([`PlannerInputs::default`]: the default simulated
    /// scene's painted panel against asphalt); it computes on its first [`PlannerPanel::show`].
    pub fn new() -> Self {
        PlannerPanel {
            inputs: PlannerInputs::default(),
            model: Model::new(),
            outcome: None,
            plan_seen: None,
            plan_note: None,
            pending: true,
        }
    }

    /// The inputs as edited.
    pub fn inputs(&self) -> &PlannerInputs {
        &self.inputs
    }

    /// Replaces the inputs (recomputed on the next [`PlannerPanel::show`]).
    pub fn set_inputs(&mut self, inputs: PlannerInputs) {
        self.inputs = inputs;
        self.pending = true;
    }

    /// Takes the planner's inputs from a plan (TOML): a capture's `from_planner` (target,
    /// background, channels, separation) and its first exposure, or an adaptive plan's target
    /// material, channels, separation and exposure. Anything the plan does not give keeps its
    /// value; a plan that does not parse changes nothing (the panel says why). The same text
    /// again is a no-op, so this may be called every frame. The scene stays the default one
    /// (a plan's `simulation.scene` file is not read here).
    pub fn set_plan_text(&mut self, plan_toml: &str) {
        if self.plan_seen.as_deref() == Some(plan_toml) {
            return;
        }
        self.plan_seen = Some(plan_toml.to_string());
        let plan = match Plan::from_toml_str(plan_toml) {
            Ok(p) => p,
            Err(e) => {
                self.plan_note = Some(format!("plan not used: {e}"));
                return;
            }
        };
        let mut inputs = self.inputs.clone();
        let mut used = false;
        match plan.kind() {
            PlanKind::Capture => {
                if let Some(c) = plan.capture() {
                    if let Some(fp) = &c.from_planner {
                        inputs.target = fp.target.clone();
                        inputs.background = fp.background.clone();
                        inputs.channels = fp.channels;
                        inputs.min_separation_deg = fp.min_separation_deg;
                        used = true;
                    }
                    if let Some(&first) = c.exposure_us.first() {
                        inputs.exposure_us = first;
                        used = true;
                    }
                }
            }
            PlanKind::Adaptive => {
                if let Some(a) = plan.adaptive() {
                    if let Some(m) = &a.target.material {
                        inputs.target = m.clone();
                    }
                    inputs.channels = a.channels;
                    inputs.min_separation_deg = a.min_separation_deg;
                    inputs.exposure_us = a.exposure_us;
                    used = true;
                }
            }
            _ => {}
        }
        if inputs.target == inputs.background {
            // An adaptive plan names no background: take the first other material.
            if let Ok(m) = &self.model {
                if let Some(other) = m.material_names().into_iter().find(|n| *n != inputs.target) {
                    inputs.background = other;
                }
            }
        }
        self.plan_note = Some(if used {
            format!(
                "inputs from the plan {:?} ({})",
                plan.name,
                plan.kind().name()
            )
        } else {
            format!(
                "the plan {:?} ({}) has no planner inputs: defaults kept",
                plan.name,
                plan.kind().name()
            )
        });
        if inputs != self.inputs {
            self.inputs = inputs;
            self.pending = true;
        }
    }

    /// The last computation's result (`None` before the first, or after an error).
    pub fn result(&self) -> Option<&PlannerResult> {
        self.outcome.as_ref().and_then(|o| o.as_ref().ok())
    }

    /// The last computation's error, if it failed.
    pub fn error(&self) -> Option<&str> {
        match &self.outcome {
            Some(Err(e)) => Some(e.as_str()),
            _ => None,
        }
    }

    /// Computes now from the current inputs.
    pub fn compute_now(&mut self) {
        self.pending = false;
        self.outcome = Some(match &mut self.model {
            Ok(m) => m.compute(&self.inputs),
            Err(e) => Err(e.clone()),
        });
    }

    /// Draws the panel: the inputs, the Compute button, the table, the ROC plot and the
    /// notes. Computes on the first call, when Compute is pressed, and once after
    /// [`PlannerPanel::set_plan_text`] or [`PlannerPanel::set_inputs`] changed the inputs;
    /// never on other frames.
    pub fn show(&mut self, ui: &mut egui::Ui) {
        ui.heading("Planner: SCR-optimal angles against the conventional sets");
        if self.inputs_ui(ui) || self.pending {
            self.compute_now();
        }
        if let Some(note) = &self.plan_note {
            ui.label(note);
        }
        match &self.outcome {
            None => {
                ui.label("Press Compute.");
            }
            Some(Err(e)) => {
                ui.colored_label(ui.visuals().error_fg_color, format!("Error: {e}"));
            }
            Some(Ok(r)) => {
                if r.inputs != self.inputs {
                    ui.colored_label(
                        ui.visuals().warn_fg_color,
                        "The inputs changed: press Compute to update.",
                    );
                }
                result_ui(ui, r);
            }
        }
    }

    /// The input widgets; true when Compute was pressed.
    fn inputs_ui(&mut self, ui: &mut egui::Ui) -> bool {
        let names = match &self.model {
            Ok(m) => m.material_names(),
            Err(_) => Vec::new(),
        };
        let mut pressed = false;
        let (mut ok, mut notes) = (true, Vec::new());
        egui::Grid::new("planner_inputs")
            .num_columns(2)
            .spacing([12.0, 4.0])
            .show(ui, |ui| {
                for (label, value) in [
                    ("Target material", &mut self.inputs.target),
                    ("Background material", &mut self.inputs.background),
                ] {
                    let l = ui.label(label);
                    egui::ComboBox::from_id_salt(label)
                        .selected_text(value.as_str())
                        .show_ui(ui, |ui| {
                            for n in &names {
                                ui.selectable_value(value, n.clone(), n);
                            }
                        })
                        .response
                        .labelled_by(l.id);
                    ui.end_row();
                }
                ok &= crate::fields::number_field(
                    ui,
                    "Exposure (us)",
                    &mut self.inputs.exposure_us,
                    (1.0, 1e7),
                    5.0,
                    &mut notes,
                );
                ui.end_row();
                let l = ui.label("Angles N");
                ui.add(egui::Slider::new(
                    &mut self.inputs.channels,
                    1..=MAX_CHANNELS,
                ))
                .labelled_by(l.id);
                ui.end_row();
                ok &= crate::fields::number_field(
                    ui,
                    "Min separation (deg)",
                    &mut self.inputs.min_separation_deg,
                    (0.0, 89.0),
                    0.5,
                    &mut notes,
                );
                ui.end_row();
                let l = ui.label("Pfa for Pd");
                ui.add(egui::Slider::new(&mut self.inputs.pfa, 1e-6..=0.5).logarithmic(true))
                    .labelled_by(l.id);
                ui.end_row();
            });
        crate::fields::show_notes(ui, &notes);
        if ui.add_enabled(ok, egui::Button::new("Compute")).clicked() {
            pressed = true;
        }
        pressed
    }
}

/// Formats a number for the table: 4 significant figures, or `n/a`.
fn fmt_num(v: f64) -> String {
    if !v.is_finite() {
        return "n/a".into();
    }
    let a = v.abs();
    if a != 0.0 && !(1e-3..1e5).contains(&a) {
        format!("{v:.3e}")
    } else {
        format!("{v:.4}")
    }
}

fn result_ui(ui: &mut egui::Ui, r: &PlannerResult) {
    ui.separator();
    ui.label(format!(
        "{} against {} at {} us; Pd at Pfa = {:e}",
        r.inputs.target, r.inputs.background, r.inputs.exposure_us, r.inputs.pfa
    ));
    egui::Grid::new("planner_table")
        .striped(true)
        .num_columns(5)
        .spacing([16.0, 4.0])
        .show(ui, |ui| {
            for h in ["Set", "Angles (deg)", "SCR", "Pd", "SCR / optimum (same N)"] {
                ui.strong(h);
            }
            ui.end_row();
            for row in &r.rows {
                if row.optimal {
                    ui.strong(&row.name);
                } else {
                    ui.label(&row.name);
                }
                let angles: Vec<String> =
                    row.angles_deg.iter().map(|a| format!("{a:.2}")).collect();
                ui.label(angles.join(", "));
                ui.label(fmt_num(row.scr));
                ui.label(format!("{:.4}", row.pd));
                ui.label(fmt_num(row.scr_relative));
                ui.end_row();
            }
        });
    ui.label(format!(
        "Clutter limit (no sensor noise): SCR {}; clutter condition number {}; sensor noise \
         floor {} (W m^-2 sr^-1)^2 per frame, plus shot noise",
        fmt_num(r.scr_clutter_limit),
        fmt_num(r.clutter_condition),
        fmt_num(r.noise_var_w2_m4_sr2)
    ));
    for n in &r.notes {
        ui.label(format!("Note: {n}"));
    }
    Plot::new("planner_roc")
        .legend(Legend::default())
        .x_axis_label("log10(Pfa)")
        .y_axis_label("Pd")
        .include_x(-6.0)
        .include_x(0.0)
        .include_y(0.0)
        .include_y(1.0)
        .height(280.0)
        .show(ui, |plot_ui| {
            for (i, row) in r.rows.iter().enumerate() {
                let pts: PlotPoints = row
                    .roc
                    .iter()
                    .filter(|p| p[0] > 0.0)
                    .map(|p| [p[0].log10(), p[1]])
                    .collect();
                plot_ui.line(
                    Line::new(format!("ROC {}", row.name), pts)
                        .color(COLOURS[i % COLOURS.len()])
                        .width(if row.optimal { 2.5 } else { 1.5 }),
                );
            }
        });
}
