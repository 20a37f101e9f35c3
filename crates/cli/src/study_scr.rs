//! `polarimeter report study scr-time` and `polarimeter report study scr-sets`: the
//! signal-to-clutter ratio of analyzer sets, Meng (2012)'s Sec. 5.1-5.3 (Figs. 5.1 and 5.2).
//!
//! Both use the scene of the Chapter 4 studies (black paint and glass against asphalt,
//! `crate::study`) and score a set by the forecast's SCR, the matched filter's
//! `(W d)^T (W Sigma_b W^T + D)^-1 (W d)` with the camera's real analyzer rows and its noise at
//! the background's light ([`Contrast::from_sensor`], the objective `plan scene` optimises).
//!
//! * **`scr-time`** (Fig. 5.1, "SCR values at different sensor integration time"): the SCR of
//!   0/45/90, 0/60/120, 0/45/90/135 and of the planner's optimal 3-angle sets (a Stokes set, and
//!   detection only) against the integration time, with the clutter limit `d^T Sigma_b^-1 d`
//!   that every full-rank set approaches as the sensor noise vanishes. A point is marked
//!   saturated where a frame of either class comes within 3 sigma of the full well: the linear
//!   sensor model keeps rising there, a real camera clips.
//! * **`scr-sets`** (Fig. 5.2, "Distribution of SCR for a three-channel system", with Table
//!   5.1's settings): the SCR of every set of 3 distinct angles on a 2-degree grid over
//!   `[0, 180)` (117 480 sets), as a histogram of `SCR / SCR_opt`, with the percentile of the
//!   optimum, of the Stokes-rule optimum and of 0/45/90 and 0/60/120. Table 5.1's values are
//!   not in the available text of Meng (2012); the substitute is the study scene and camera at
//!   `--t-int-ms`.

use crate::plot::{canvas, draw_err, legend, FigureError, FONT};
use crate::study::{Study, StudyArgs, StudyError};
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use polar_model::scene::{MaterialResult, Prepared};
use polar_model::sensor::Exposure;
use polar_planner::optimize::CONVENTIONAL;
use polar_planner::stokes::STOKES_MAX_CONDITION;
use polar_planner::{optimise, Constraints, Contrast};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The integration times of `scr-time`, ms (log-spaced, from read-noise-limited to past the
/// glass glint's saturation).
pub const TIME_VALUES_MS: [f64; 13] = [
    0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0,
];

/// The angle grid of `scr-sets`, degrees.
pub const SETS_GRID_DEG: f64 = 2.0;

/// Histogram bins of `scr-sets` over `SCR / SCR_opt` in `[0, 1]`.
pub const SETS_BINS: usize = 50;

/// The optimiser's angle tolerance here, radians (0.001 deg).
const TOL_RAD: f64 = 1.745_329_251_994_33e-5;

fn planner(context: &str) -> impl Fn(polar_planner::PlanError) -> StudyError + '_ {
    move |e| StudyError::Invalid {
        field: "planner",
        reason: format!("{context}: {e}"),
    }
}

fn model(context: String) -> impl FnOnce(polar_model::ModelError) -> StudyError {
    move |source| StudyError::Model { context, source }
}

/// The three classes' statistics at the aperture (paint, glass, background).
fn classes(study: &Study, context: &str) -> Result<Vec<MaterialResult>, StudyError> {
    let p = Prepared::new(study.spec(), study.settings().tolerance)
        .map_err(model(context.to_string()))?;
    p.evaluate_all(study.materials())
        .map_err(model(context.to_string()))
}

/// The planner's contrast of `target` against `background` at `t_int_s`.
fn contrast(
    study: &Study,
    target: &MaterialResult,
    background: &MaterialResult,
    t_int_s: f64,
) -> Result<Contrast, StudyError> {
    Contrast::from_sensor(
        study.sensor(),
        t_int_s,
        &target.mean.0,
        &background.mean.0,
        &background.cov,
    )
    .map_err(planner(&target.name))
}

/// Whether a frame of `class` at `angles_rad` comes within 3 sigma of saturation.
fn saturates(
    study: &Study,
    class: &MaterialResult,
    angles_rad: &[f64],
    t_int_s: f64,
) -> Result<bool, StudyError> {
    let mut e = Exposure::new(t_int_s, class.mean);
    e.radiance_cov_w2_m4_sr2 = 0.5 * (class.cov + class.cov.transpose());
    let s = study
        .sensor()
        .signal(angles_rad, &e)
        .map_err(model(format!("study scr-time, {}", class.name)))?;
    Ok(s.saturated.iter().any(|&b| b))
}

/// One set at one integration time.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeRow {
    /// Integration time, ms.
    pub t_int_ms: f64,
    /// The target material.
    pub target: String,
    /// The set's name (a conventional set, or which optimum).
    pub set: String,
    /// Its angles, degrees.
    pub angles_deg: Vec<f64>,
    /// Its SCR (the forecast's).
    pub scr: f64,
    /// The clutter limit `d^T Sigma_b^-1 d`.
    pub scr_clutter_limit: f64,
    /// A frame of either class within 3 sigma of saturation.
    pub saturated: bool,
}

/// The names of the optima in `scr-time` and `scr-sets`.
pub const OPTIMAL_STOKES: &str = "optimal 3 (Stokes set)";
/// See [`OPTIMAL_STOKES`].
pub const OPTIMAL_DETECTION: &str = "optimal 3 (detection only)";

/// The 3-angle optima at `contrast`: the Stokes rule's and the detection-only one.
fn optima(c: &Contrast, context: &str) -> Result<[(String, Vec<f64>, f64); 2], StudyError> {
    let stokes = Constraints {
        max_condition: Some(STOKES_MAX_CONDITION),
        ..Constraints::default()
    };
    let s = optimise(c, 3, &stokes, TOL_RAD).map_err(planner(context))?;
    let d = optimise(c, 3, &Constraints::default(), TOL_RAD).map_err(planner(context))?;
    Ok([
        (OPTIMAL_STOKES.to_string(), s.angles_rad, s.scr),
        (OPTIMAL_DETECTION.to_string(), d.angles_rad, d.scr),
    ])
}

fn degrees(rad: &[f64]) -> Vec<f64> {
    rad.iter().map(|a| a.to_degrees()).collect()
}

/// `scr-time`: every set at every integration time in `values_ms`, both targets.
pub fn scr_time(study: &Study, values_ms: &[f64]) -> Result<Vec<TimeRow>, StudyError> {
    if let Some(bad) = values_ms.iter().find(|v| !(v.is_finite() && **v > 0.0)) {
        return Err(StudyError::Invalid {
            field: "values",
            reason: format!("{bad} ms: allowed integration times > 0"),
        });
    }
    let r = classes(study, "study scr-time")?;
    let mut rows = Vec::new();
    for target in &r[..2] {
        let background = &r[2];
        for &t_ms in values_ms {
            let t = t_ms * 1e-3;
            let c = contrast(study, target, background, t)?;
            let limit = c.clutter_limit();
            let mut sets: Vec<(String, Vec<f64>, f64)> = CONVENTIONAL
                .iter()
                .map(|(name, deg)| {
                    let rad: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
                    let scr = c.scr(&rad);
                    (name.to_string(), rad, scr)
                })
                .collect();
            sets.extend(optima(&c, &target.name)?);
            for (name, rad, scr) in sets {
                let saturated =
                    saturates(study, target, &rad, t)? || saturates(study, background, &rad, t)?;
                rows.push(TimeRow {
                    t_int_ms: t_ms,
                    target: target.name.clone(),
                    set: name,
                    angles_deg: degrees(&rad),
                    scr,
                    scr_clutter_limit: limit,
                    saturated,
                });
            }
        }
    }
    Ok(rows)
}

/// Degrees to 0.01 in `[0, 180)`, sorted, joined by `/`.
fn angles_text(deg: &[f64]) -> String {
    let mut v: Vec<f64> = deg
        .iter()
        .map(|a| ((a * 100.0).round() / 100.0).rem_euclid(180.0))
        .collect();
    v.sort_by(f64::total_cmp);
    v.iter()
        .map(|a| format!("{a:.2}"))
        .collect::<Vec<_>>()
        .join("/")
}

/// `scr-time.csv`.
pub fn time_csv(rows: &[TimeRow]) -> String {
    let mut out = String::from(
        "t_int_ms,target,set,angles_deg,scr,scr_clutter_limit,scr_over_limit,saturated\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{},{},{:.6e},{:.6e},{:.6},{}",
            r.t_int_ms,
            r.target,
            r.set,
            angles_text(&r.angles_deg),
            r.scr,
            r.scr_clutter_limit,
            r.scr / r.scr_clutter_limit,
            r.saturated
        );
    }
    out
}

const COLORS: [RGBColor; 5] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(214, 39, 40),
    RGBColor(255, 127, 14),
];

/// `scr-time.png`: one panel per target, SCR against integration time (log-log), the clutter
/// limit dashed, saturated points crossed.
pub fn draw_time(rows: &[TimeRow], scene: &str, path: &Path) -> Result<(), FigureError> {
    let e = draw_err(path);
    let root = canvas(path, (1600, 700))?;
    let (top, body) = root.split_vertically(40);
    top.draw_text(
        &format!(
            "Study 'scr-time' (Meng (2012) Fig. 5.1): SCR against integration time, scene {scene}; \
             x: a frame within 3 sigma of saturation"
        ),
        &(FONT, 18).into_text_style(&top),
        (15, 10),
    )
    .map_err(&e)?;
    let mut targets: Vec<&str> = rows.iter().map(|r| r.target.as_str()).collect();
    targets.dedup();
    for (target, area) in targets
        .iter()
        .zip(body.split_evenly((1, targets.len().max(1))))
    {
        let mine: Vec<&TimeRow> = rows.iter().filter(|r| r.target == *target).collect();
        let (tlo, thi) = mine.iter().fold((f64::INFINITY, 0.0f64), |(a, b), r| {
            (a.min(r.t_int_ms), b.max(r.t_int_ms))
        });
        let (slo, shi) = mine.iter().fold((f64::INFINITY, 0.0f64), |(a, b), r| {
            (
                a.min(r.scr.max(1e-12)),
                b.max(r.scr.max(r.scr_clutter_limit)),
            )
        });
        if !(tlo.is_finite() && slo.is_finite() && shi > 0.0) {
            return Err(FigureError::Draw {
                path: path.to_path_buf(),
                message: "no points to draw".into(),
            });
        }
        let mut chart = ChartBuilder::on(&area)
            .caption(format!("{target} against the background"), (FONT, 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(
                (tlo / 1.3..thi * 1.3).log_scale(),
                (slo / 2.0..shi * 2.0).log_scale(),
            )
            .map_err(&e)?;
        chart
            .configure_mesh()
            .x_desc("integration time (ms)")
            .y_desc("SCR (forecast, camera's real rows)")
            .x_label_formatter(&|v| format!("{v}"))
            .y_label_formatter(&|v| format!("{v:.1e}"))
            .label_style((FONT, 14))
            .draw()
            .map_err(&e)?;
        let mut names: Vec<&str> = mine.iter().map(|r| r.set.as_str()).collect();
        names.sort();
        names.dedup();
        for (k, name) in names.iter().enumerate() {
            let color = COLORS[k % COLORS.len()];
            let pts: Vec<&&TimeRow> = mine.iter().filter(|r| r.set == *name).collect();
            chart
                .draw_series(LineSeries::new(
                    pts.iter().map(|r| (r.t_int_ms, r.scr.max(1e-12))),
                    color.stroke_width(2),
                ))
                .map_err(&e)?
                .label(name.to_string())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            chart
                .draw_series(
                    pts.iter().filter(|r| r.saturated).map(|r| {
                        Cross::new((r.t_int_ms, r.scr.max(1e-12)), 6, color.stroke_width(2))
                    }),
                )
                .map_err(&e)?;
        }
        let mut limit: Vec<(f64, f64)> = mine
            .iter()
            .map(|r| (r.t_int_ms, r.scr_clutter_limit))
            .collect();
        limit.dedup_by(|a, b| a.0 == b.0);
        chart
            .draw_series(std::iter::once(DashedPathElement::new(
                limit,
                12,
                8,
                BLACK.stroke_width(2),
            )))
            .map_err(&e)?
            .label("clutter limit d^T Sigma_b^-1 d")
            .legend(|(x, y)| {
                DashedPathElement::new(vec![(x, y), (x + 20, y)], 5, 3, BLACK.stroke_width(2))
            });
        legend(&mut chart, SeriesLabelPosition::LowerRight, 14).map_err(&e)?;
    }
    root.present().map_err(&e)?;
    Ok(())
}

/// A marked set in the `scr-sets` distribution.
#[derive(Debug, Clone, PartialEq)]
pub struct Mark {
    /// Its name.
    pub set: String,
    /// Its angles, degrees.
    pub angles_deg: Vec<f64>,
    /// Its SCR.
    pub scr: f64,
    /// Percent of the grid's sets whose SCR is at most this one's.
    pub percentile: f64,
}

/// The `scr-sets` distribution of one target.
#[derive(Debug, Clone, PartialEq)]
pub struct Distribution {
    /// The target material.
    pub target: String,
    /// Integration time, ms.
    pub t_int_ms: f64,
    /// The optimum's SCR (the detection-only 3-angle optimum, the histogram's unit).
    pub scr_opt: f64,
    /// The clutter limit.
    pub scr_clutter_limit: f64,
    /// The grid's sets scored.
    pub sets: usize,
    /// The grid's best SCR.
    pub scr_grid_max: f64,
    /// The grid's median SCR.
    pub scr_grid_median: f64,
    /// Counts per bin of `SCR / scr_opt` over `[0, 1]` ([`SETS_BINS`] bins; the last includes 1).
    pub counts: Vec<usize>,
    /// The optima and the conventional 3-angle sets.
    pub marks: Vec<Mark>,
}

/// `scr-sets`: the distribution for both targets at `t_int_ms`.
pub fn scr_sets(study: &Study, t_int_ms: f64) -> Result<Vec<Distribution>, StudyError> {
    let r = classes(study, "study scr-sets")?;
    let m = (180.0 / SETS_GRID_DEG).round() as usize;
    let grid: Vec<f64> = (0..m)
        .map(|i| (i as f64 * SETS_GRID_DEG).to_radians())
        .collect();
    let mut out = Vec::new();
    for target in &r[..2] {
        let c = contrast(study, target, &r[2], t_int_ms * 1e-3)?;
        let mut all = Vec::with_capacity(m * m * m / 6);
        for i in 0..m {
            for j in i + 1..m {
                for k in j + 1..m {
                    all.push(c.scr(&[grid[i], grid[j], grid[k]]));
                }
            }
        }
        all.sort_by(f64::total_cmp);
        let optima = optima(&c, &target.name)?;
        let scr_opt = optima[1].2;
        let percentile = |v: f64| {
            let below = all.partition_point(|&x| x <= v * (1.0 + 1e-12));
            100.0 * below as f64 / all.len() as f64
        };
        let mut marks: Vec<Mark> = optima
            .iter()
            .map(|(name, rad, scr)| Mark {
                set: name.clone(),
                angles_deg: degrees(rad),
                scr: *scr,
                percentile: percentile(*scr),
            })
            .collect();
        for (name, deg) in CONVENTIONAL.iter().filter(|(_, d)| d.len() == 3) {
            let rad: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
            let scr = c.scr(&rad);
            marks.push(Mark {
                set: name.to_string(),
                angles_deg: deg.to_vec(),
                scr,
                percentile: percentile(scr),
            });
        }
        let mut counts = vec![0usize; SETS_BINS];
        for &v in &all {
            let b = ((v / scr_opt) * SETS_BINS as f64).floor() as usize;
            counts[b.min(SETS_BINS - 1)] += 1;
        }
        out.push(Distribution {
            target: target.name.clone(),
            t_int_ms,
            scr_opt,
            scr_clutter_limit: c.clutter_limit(),
            sets: all.len(),
            scr_grid_max: all.last().copied().unwrap_or(0.0),
            scr_grid_median: all[all.len() / 2],
            counts,
            marks,
        });
    }
    Ok(out)
}

/// `scr-sets.csv` (the histogram) and `scr-sets_marks.csv` (the marked sets).
pub fn sets_csv(dists: &[Distribution]) -> (String, String) {
    let mut hist = String::from("target,t_int_ms,bin_lo,bin_hi,count,fraction\n");
    let mut marks = String::from(
        "target,t_int_ms,set,angles_deg,scr,scr_over_optimum,percentile,scr_clutter_limit,grid_sets,grid_max_over_optimum,grid_median_over_optimum\n",
    );
    for d in dists {
        for (b, &n) in d.counts.iter().enumerate() {
            let _ = writeln!(
                hist,
                "{},{},{:.3},{:.3},{},{:.6}",
                d.target,
                d.t_int_ms,
                b as f64 / SETS_BINS as f64,
                (b + 1) as f64 / SETS_BINS as f64,
                n,
                n as f64 / d.sets as f64
            );
        }
        for m in &d.marks {
            let _ = writeln!(
                marks,
                "{},{},{},{},{:.6e},{:.6},{:.3},{:.6e},{},{:.9},{:.6}",
                d.target,
                d.t_int_ms,
                m.set,
                angles_text(&m.angles_deg),
                m.scr,
                m.scr / d.scr_opt,
                m.percentile,
                d.scr_clutter_limit,
                d.sets,
                d.scr_grid_max / d.scr_opt,
                d.scr_grid_median / d.scr_opt
            );
        }
    }
    (hist, marks)
}

/// `scr-sets.png`: one histogram per target, the marked sets as vertical lines.
pub fn draw_sets(dists: &[Distribution], scene: &str, path: &Path) -> Result<(), FigureError> {
    let e = draw_err(path);
    let root = canvas(path, (1600, 700))?;
    let (top, body) = root.split_vertically(40);
    top.draw_text(
        &format!(
            "Study 'scr-sets' (Meng (2012) Fig. 5.2): SCR of every 3-angle set on a {SETS_GRID_DEG}-deg grid, scene {scene}, t_int {} ms",
            dists.first().map_or(0.0, |d| d.t_int_ms)
        ),
        &(FONT, 18).into_text_style(&top),
        (15, 10),
    )
    .map_err(&e)?;
    for (d, area) in dists.iter().zip(body.split_evenly((1, dists.len().max(1)))) {
        let peak = d.counts.iter().copied().max().unwrap_or(1).max(1) as f64 / d.sets as f64;
        let mut chart = ChartBuilder::on(&area)
            .caption(
                format!(
                    "{} against the background: SCR_opt {:.4e}, {} sets",
                    d.target, d.scr_opt, d.sets
                ),
                (FONT, 18),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0f64..1.02f64, 0.0f64..peak * 1.1)
            .map_err(&e)?;
        chart
            .configure_mesh()
            .x_desc("SCR / SCR of the optimal 3-angle set")
            .y_desc("fraction of sets")
            .label_style((FONT, 14))
            .draw()
            .map_err(&e)?;
        let w = 1.0 / SETS_BINS as f64;
        chart
            .draw_series(d.counts.iter().enumerate().map(|(b, &n)| {
                let x = b as f64 * w;
                Rectangle::new(
                    [(x, 0.0), (x + w * 0.95, n as f64 / d.sets as f64)],
                    RGBColor(150, 150, 150).filled(),
                )
            }))
            .map_err(&e)?;
        for (k, m) in d.marks.iter().enumerate() {
            let color = COLORS[(k + 3) % COLORS.len()];
            let x = (m.scr / d.scr_opt).clamp(0.0, 1.02);
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(x, 0.0), (x, peak * 1.05)],
                    color.stroke_width(2),
                )))
                .map_err(&e)?
                .label(format!(
                    "{} ({}): {:.3}, percentile {:.1}",
                    m.set,
                    angles_text(&m.angles_deg),
                    m.scr / d.scr_opt,
                    m.percentile
                ))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
        }
        legend(&mut chart, SeriesLabelPosition::UpperLeft, 13).map_err(&e)?;
    }
    root.present().map_err(&e)?;
    Ok(())
}

fn write_file(path: &Path, text: &str) -> Result<(), StudyError> {
    std::fs::write(path, text).map_err(|e| StudyError::Figure(draw_err(path)(e)))
}

/// Runs `scr-time` (its default sweep, or `--values` in ms) and writes `scr-time.csv` and
/// `scr-time.png` into `args.out`.
pub fn execute_time(args: &StudyArgs) -> Result<Vec<PathBuf>, StudyError> {
    let study = Study::load(args)?;
    let values: Vec<f64> = if args.values.is_empty() {
        TIME_VALUES_MS.to_vec()
    } else {
        args.values.clone()
    };
    let rows = scr_time(&study, &values)?;
    std::fs::create_dir_all(&args.out).map_err(|e| StudyError::Figure(draw_err(&args.out)(e)))?;
    let csv = args.out.join("scr-time.csv");
    write_file(&csv, &time_csv(&rows))?;
    let png = args.out.join("scr-time.png");
    draw_time(&rows, study.scene_label(), &png)?;
    Ok(vec![csv, png])
}

/// Runs `scr-sets` at `--t-int-ms` and writes `scr-sets.csv`, `scr-sets_marks.csv` and
/// `scr-sets.png` into `args.out`.
pub fn execute_sets(args: &StudyArgs) -> Result<Vec<PathBuf>, StudyError> {
    if !args.values.is_empty() {
        return Err(StudyError::Invalid {
            field: "values",
            reason: "scr-sets sweeps no parameter: set the integration time with --t-int-ms".into(),
        });
    }
    let study = Study::load(args)?;
    let dists = scr_sets(&study, args.t_int_ms)?;
    std::fs::create_dir_all(&args.out).map_err(|e| StudyError::Figure(draw_err(&args.out)(e)))?;
    let (hist, marks) = sets_csv(&dists);
    let csv = args.out.join("scr-sets.csv");
    write_file(&csv, &hist)?;
    let marks_csv = args.out.join("scr-sets_marks.csv");
    write_file(&marks_csv, &marks)?;
    let png = args.out.join("scr-sets.png");
    draw_sets(&dists, study.scene_label(), &png)?;
    Ok(vec![csv, marks_csv, png])
}
