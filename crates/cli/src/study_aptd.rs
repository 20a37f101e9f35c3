//! `polarimeter report study aptd`: adaptive polarimetric target detection against conventional
//! analyzer sets. It is our analogue of Meng (2012)'s Table 5.2 and Figs. 5.4-5.6, whose numbers
//! are lost (MODEL.md section 9).
//!
//! **Cases.** The scene file's materials are laid out as panels on the ground
//! ([`polar_hil_mocks::camera::Layout::panels_on_ground`]), with per-pixel texture, and
//! rendered as Stokes images by the scene model at three sun positions. Each case takes every
//! panel in turn as the target, with the rest of the image as the (global) background.
//!
//! **Frames.** Frames are drawn through the whole sensor chain
//! (`polar_model::montecarlo::expose_pixels`: Poisson electrons, read noise, gain, rounding)
//! at the camera's real analyzer. The exposure puts the brightest pixel at half the full well.
//! Each frame is the dark-subtracted DN.
//!
//! **Methods**, each scored under the case's *true* statistics:
//! - **APTD**: the state machine of `polar_planner::aptd`, 3 channels, started from 0/60/120,
//!   the target region known. It estimates everything else from its own frames.
//! - **Fixed sets**: Pickering 0/45/90, 0/60/120, the modified Pickering 0/45/90/135, and the
//!   best fixed 1- and 2-channel sets. The best fixed sets are chosen by the optimiser *with the
//!   true statistics*, an oracle that no real fixed set has, so that APTD is compared with the
//!   best a fixed set could be.
//!
//! **Scores.** The true statistics are the difference of the class means `d`, the
//! background's pixel covariance `Sigma_b` (both from the rendered truth, in DN), and the
//! frame noise `V`. `V` is the mean over background pixels of `K^2 (e + e_dark + sigma_d^2) +
//! 1/12` at the unpolarised mean level. Each set is scored by its SCR
//! `(W d)^T (W Sigma_b W^T + V I)^-1 (W d)` and the matched filter's Pd at Pfa = 1e-3 on the
//! same Gaussian classes (MODEL.md section 8).

use crate::commands::CommandError;
use crate::plot::{canvas, legend};
use crate::study::StudyArgs;
use nalgebra::Vector3;
use plotters::prelude::*;
use polar_hil_mocks::camera::{Layout, SimScene};
use polar_model::sensor::{Camera, SensorModel};
use polar_planner::aptd::{mean_cov, Aptd, AptdConfig, AptdFrame, Step, TargetSpec};
use polar_planner::{optimise, Constraints, Contrast};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Image size of the rendered scenes, pixels.
const WIDTH: u32 = 96;
const HEIGHT: u32 = 72;
/// Sun positions (zenith, azimuth clockwise from north), degrees; the camera looks at 300 deg.
pub const SUNS: [(f64, f64); 3] = [(30.0, 150.0), (50.0, 220.0), (65.0, 290.0)];

/// One method's score in one case.
#[derive(Debug, Clone)]
pub struct Score {
    /// The method.
    pub method: String,
    /// Its angles, degrees.
    pub angles_deg: Vec<f64>,
    /// SCR under the true statistics.
    pub scr: f64,
    /// Matched-filter Pd at Pfa 1e-3.
    pub pd: f64,
    /// The ROC, `[pfa, pd]`.
    pub roc: Vec<[f64; 2]>,
}

/// One case: a sun and a target.
#[derive(Debug, Clone)]
pub struct Case {
    /// Sun zenith, azimuth, degrees.
    pub sun_deg: (f64, f64),
    /// Target material.
    pub target: String,
    /// Frames APTD took, and its rounds.
    pub aptd_frames: usize,
    /// APTD's rounds.
    pub aptd_rounds: usize,
    /// The scores, APTD first.
    pub scores: Vec<Score>,
}

/// Runs every case.
pub fn run(args: &StudyArgs) -> Result<Vec<Case>, CommandError> {
    let text = std::fs::read_to_string(&args.scene).map_err(|e| {
        CommandError::input(
            "--scene",
            format!(" {}: cannot read: {e}", args.scene.display()),
        )
    })?;
    let scene = polar_model::scene_file::Scene::from_toml_str(&text)
        .map_err(|e| CommandError::input("--scene", format!(" {}: {e}", args.scene.display())))?;
    let camera = Camera::from_toml_str(&std::fs::read_to_string(&args.camera).map_err(|e| {
        CommandError::input(
            "--camera",
            format!(" {}: cannot read: {e}", args.camera.display()),
        )
    })?)
    .map_err(|e| CommandError::input("--camera", format!(" {}: {e}", args.camera.display())))?;
    let names: Vec<String> = scene.materials.iter().map(|m| m.name.clone()).collect();
    let layout = Layout::panels_on_ground(&names);
    let ground = ["asphalt", "grass"];
    let targets: Vec<String> = names
        .iter()
        .filter(|n| !ground.contains(&n.as_str()))
        .cloned()
        .collect();
    if targets.is_empty() {
        return Err(CommandError::input(
            "--scene",
            format!(
                " {}: no panel material besides asphalt and grass",
                args.scene.display()
            ),
        ));
    }
    let mut cases = Vec::new();
    for (k, &(zenith, azimuth)) in SUNS.iter().enumerate() {
        let mut spec = scene.spec.clone();
        spec.sun_zenith_deg = zenith;
        spec.sun_azimuth_deg = azimuth;
        let truth = SimScene::render(
            &spec,
            &scene.materials,
            &layout,
            WIDTH,
            HEIGHT,
            args.tolerance,
            k as u64 + 1,
        )
        .map_err(CommandError::of)?;
        let sensor = SensorModel::new(&camera, &spec.band)?;
        for target in &targets {
            cases.push(one_case(
                &truth,
                &sensor,
                &camera,
                (zenith, azimuth),
                target,
                k as u64,
            )?);
        }
    }
    Ok(cases)
}

/// A target against the rest of the image, in DN, from the rendered truth (ideal rows, as the
/// planner scores): the class means and covariances, the frame noise of the background's
/// unpolarised mean, and the planner's contrast. The exposure puts the brightest pixel at half
/// the full well.
pub(crate) struct TrueStats {
    /// Target pixels.
    pub region: Vec<bool>,
    /// The target's index in the truth's materials.
    pub t_idx: usize,
    /// Integration time, seconds.
    pub t_int_s: f64,
    /// Electrons per radiance unit at that time.
    pub g: f64,
    /// DN per electron.
    pub k: f64,
    /// Dark level, DN.
    pub dark_dn: f64,
    /// Target mean, DN.
    pub mu_t: Vector3<f64>,
    /// Target covariance, DN^2.
    pub cov_t: nalgebra::Matrix3<f64>,
    /// Background mean, DN.
    pub mu_b: Vector3<f64>,
    /// Background covariance, DN^2.
    pub cov_b: nalgebra::Matrix3<f64>,
    /// Per-frame noise variance, DN^2.
    pub noise_var: f64,
    /// The planner's contrast.
    pub contrast: Contrast,
}

/// [`TrueStats`] of `target` in `truth`.
pub(crate) fn true_stats(
    truth: &SimScene,
    sensor: &SensorModel,
    camera: &Camera,
    target: &str,
) -> Result<TrueStats, CommandError> {
    let t_idx = truth
        .materials
        .iter()
        .position(|m| m == target)
        .ok_or_else(|| CommandError::failed(format!("target {target} is not in the layout")))?;
    let region: Vec<bool> = truth
        .region
        .iter()
        .map(|&r| usize::from(r) == t_idx)
        .collect();
    // Exposure: the brightest pixel at half the full well.
    let s0_max = truth.stokes.iter().map(|s| s[0]).fold(0.0, f64::max);
    let t_int_s = (0.5 * camera.full_well_e / (sensor.responsivity_e_per_s() * s0_max.max(1e-300)))
        .clamp(1e-6, 10.0);
    let g = sensor.responsivity_e_per_s() * t_int_s;
    let k = camera.gain_dn_per_e;
    let dark_e = camera.dark_current_e_per_s * t_int_s;
    let dark_dn = camera.offset_dn + k * dark_e;

    // True statistics in DN (ideal rows, as the planner scores).
    let to_dn = |s: &[f64; 3]| Vector3::new(s[0], s[1], s[2]) * (k * g);
    let dn: Vec<Vector3<f64>> = truth.stokes.iter().map(to_dn).collect();
    let background: Vec<bool> = region.iter().map(|r| !r).collect();
    let few = || CommandError::failed(format!("target {target}: fewer than 4 pixels in a class"));
    let (mu_t, cov_t) = mean_cov(&dn, &region).ok_or_else(few)?;
    let (mu_b, cov_b) = mean_cov(&dn, &background).ok_or_else(few)?;
    let e_bg = mu_b[0] / (k * 2.0);
    let noise_var =
        k * k * (e_bg + dark_e + camera.read_noise_e * camera.read_noise_e) + 1.0 / 12.0;
    let contrast = Contrast::new(mu_t - mu_b, cov_b, noise_var).map_err(CommandError::of)?;

    Ok(TrueStats {
        region,
        t_idx,
        t_int_s,
        g,
        k,
        dark_dn,
        mu_t,
        cov_t,
        mu_b,
        cov_b,
        noise_var,
        contrast,
    })
}

fn one_case(
    truth: &SimScene,
    sensor: &SensorModel,
    camera: &Camera,
    sun_deg: (f64, f64),
    target: &str,
    seed: u64,
) -> Result<Case, CommandError> {
    let TrueStats {
        region,
        t_idx,
        t_int_s,
        g,
        dark_dn,
        mu_t,
        cov_t,
        mu_b,
        cov_b,
        noise_var,
        contrast,
        ..
    } = true_stats(truth, sensor, camera, target)?;

    // Frames through the whole chain at the real analyzer.
    let mut frame_seed = seed.wrapping_mul(1_000_003) ^ (t_idx as u64) << 32;
    let mut render = |angles: &[f64]| -> Result<Vec<AptdFrame>, CommandError> {
        let w = sensor.intensities_from_stokes(angles)?;
        angles
            .iter()
            .enumerate()
            .map(|(i, &a)| {
                let e: Vec<f64> = truth
                    .stokes
                    .iter()
                    .map(|s| {
                        (g * (w[(i, 0)] * s[0] + w[(i, 1)] * s[1] + w[(i, 2)] * s[2])).max(0.0)
                    })
                    .collect();
                frame_seed = frame_seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let dn = polar_model::montecarlo::expose_pixels(camera, &e, t_int_s, frame_seed)?;
                Ok(AptdFrame {
                    angle_rad: a,
                    pixels: dn.iter().map(|&v| f64::from(v) - dark_dn).collect(),
                })
            })
            .collect()
    };

    let deg = |v: &[f64]| -> Vec<f64> { v.iter().map(|d| d.to_radians()).collect() };
    let (mut aptd, mut step) = Aptd::new(AptdConfig {
        channels: 3,
        initial_angles_rad: deg(&[0.0, 60.0, 120.0]),
        noise_var,
        // The ideal rows the true statistics below are scored with (module docs).
        instrument: polar_planner::Instrument::ideal(),
        target: TargetSpec::Region(region.clone()),
        constraints: Constraints::default(),
        angle_tol_rad: 0.5f64.to_radians(),
        scr_rel_tol: 0.02,
        frame_budget: 15,
    })
    .map_err(CommandError::of)?;
    let mut aptd_set = Vec::new();
    while let Step::Acquire(angles) = step {
        aptd_set = angles.clone();
        let frames = render(&angles)?;
        step = aptd.on_frames(frames).map_err(CommandError::of)?;
    }
    let aptd_frames = aptd.decisions().last().map(|d| d.frames_used).unwrap_or(0);

    let score = |method: &str, angles: Vec<f64>| -> Result<Score, CommandError> {
        let roc =
            crate::plan::intensity_roc(&angles, &mu_t, &cov_t, &mu_b, &cov_b, noise_var, 1e-3)?;
        Ok(Score {
            method: method.into(),
            angles_deg: angles.iter().map(|a| a.to_degrees()).collect(),
            scr: contrast.scr(&angles),
            pd: roc.pd,
            roc: roc.curve,
        })
    };
    let best = |n: usize| -> Result<Vec<f64>, CommandError> {
        Ok(
            optimise(&contrast, n, &Constraints::default(), 1e-3f64.to_radians())
                .map_err(CommandError::of)?
                .angles_rad,
        )
    };
    let scores = vec![
        score("APTD (3)", aptd_set)?,
        score("0/45/90", deg(&[0.0, 45.0, 90.0]))?,
        score("0/60/120", deg(&[0.0, 60.0, 120.0]))?,
        score("0/45/90/135", deg(&[0.0, 45.0, 90.0, 135.0]))?,
        score("best fixed 1", best(1)?)?,
        score("best fixed 2", best(2)?)?,
    ];
    Ok(Case {
        sun_deg,
        target: target.to_string(),
        aptd_frames,
        aptd_rounds: aptd.decisions().len(),
        scores,
    })
}

/// The table as CSV.
pub fn csv(cases: &[Case]) -> String {
    let mut out = String::from(
        "sun_zenith_deg,sun_azimuth_deg,target,method,angles_deg,scr,pd_at_pfa_1e-3,aptd_frames,aptd_rounds\n",
    );
    for c in cases {
        for s in &c.scores {
            let angles: Vec<String> = s.angles_deg.iter().map(|a| format!("{a:.2}")).collect();
            let _ = writeln!(
                out,
                "{},{},{},{},{},{:.6e},{:.6},{},{}",
                c.sun_deg.0,
                c.sun_deg.1,
                c.target,
                s.method,
                angles.join("/"),
                s.scr,
                s.pd,
                c.aptd_frames,
                c.aptd_rounds
            );
        }
    }
    out
}

/// ROC families, one panel per case.
pub fn draw(cases: &[Case], path: &Path) -> Result<(), CommandError> {
    let font = crate::plot::FONT;
    let cols = 3usize;
    let rows = cases.len().div_ceil(cols).max(1);
    let root = canvas(path, (1500, 420 * rows as u32)).map_err(CommandError::of)?;
    let colors = [
        RGBColor(200, 30, 30),
        RGBColor(31, 119, 180),
        RGBColor(44, 160, 44),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(127, 127, 127),
    ];
    for (case, area) in cases.iter().zip(root.split_evenly((rows, cols))) {
        let mut chart = ChartBuilder::on(&area)
            .caption(
                format!(
                    "{} on the ground, sun {:.0}/{:.0} deg",
                    case.target, case.sun_deg.0, case.sun_deg.1
                ),
                (font, 16),
            )
            .margin(8)
            .x_label_area_size(32)
            .y_label_area_size(40)
            .build_cartesian_2d((1e-6f64..1.0f64).log_scale(), 0.0f64..1.0f64)
            .map_err(CommandError::of)?;
        chart
            .configure_mesh()
            .x_desc("Pfa")
            .y_desc("Pd (matched filter)")
            .x_label_formatter(&|v| format!("{v:.0e}"))
            .draw()
            .map_err(CommandError::of)?;
        for (s, color) in case.scores.iter().zip(colors) {
            let width = if s.method.starts_with("APTD") { 3 } else { 1 };
            chart
                .draw_series(LineSeries::new(
                    s.roc.iter().map(|p| (p[0], p[1])),
                    color.stroke_width(width),
                ))
                .map_err(CommandError::of)?
                .label(format!("{} (SCR {:.1})", s.method, s.scr))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(width))
                });
        }
        legend(&mut chart, SeriesLabelPosition::LowerRight, 12).map_err(CommandError::of)?;
    }
    root.present().map_err(CommandError::of)?;
    Ok(())
}

/// Runs the study and writes `aptd.csv` and `aptd.png` into `args.out`.
pub fn execute(args: &StudyArgs) -> Result<Vec<PathBuf>, CommandError> {
    let cases = run(args)?;
    std::fs::create_dir_all(&args.out)
        .map_err(|e| CommandError::input("--out", format!(" {}: {e}", args.out.display())))?;
    let csv_path = args.out.join("aptd.csv");
    std::fs::write(&csv_path, csv(&cases))
        .map_err(|e| CommandError::layer(format!("{}: ", csv_path.display()), e))?;
    let png = args.out.join("aptd.png");
    draw(&cases, &png)?;
    Ok(vec![csv_path, png])
}
