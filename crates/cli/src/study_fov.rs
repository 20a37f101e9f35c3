//! `polarimeter report study fov`: the scene-geometry variation over the field of view, Meng (2012)
//! Sec. 4.2.3 (Table 4.2, "DoLP variation at different field of view", Figs. 4.5-4.7).
//!
//! A camera with a wide field sees each surface under many sun-surface-sensor geometries, so
//! the surface's radiance and DoLP vary across the image even where the material is uniform:
//! the geometry variation `Sigma_g` of Meng (2012) Sec. 3.1.5 (the field is split into tiles,
//! each evaluated with its own geometry; MODEL.md section 5). The study sweeps the square field
//! of view of the Chapter 4 scene (`crate::study`) for three facet-slope roughnesses of both
//! targets (asphalt keeps its own), and reports for each class:
//!
//! * the DoLP of the field's mean radiance;
//! * the DoLP spread that the geometry alone causes: the delta-method standard deviation of
//!   DoLP under `Sigma_g` (Table 4.2's quantity);
//! * the relative spread of S0 under `Sigma_g` (the reflected radiance's variation, Fig. 4.5);
//! * the path radiance's share of S0 (the upwelled radiance, Fig. 4.6);
//! * for each target against asphalt, the DoLP threshold detector's Pd at `--pfa` with the whole
//!   clutter (geometry and texture) and the sensor noise, and its ROC (Fig. 4.7).
//!
//! Table 4.2 sweeps the field of view against the relative azimuth; the roughness is swept here
//! instead (the reading of the study), and the azimuth stays the scene's (the specular
//! plane). Meng (2012)'s values of Table 4.2 are not in the available text.

use crate::plot::{canvas, draw_err, legend, FigureError, FONT};
use crate::study::{with_sigma, Radiance, Study, StudyArgs, StudyError};
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use polar_model::scene::{Prepared, SceneMaterial};
use polar_model::stats::{dolp_aop_stats, RegimeChoice};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The fields of view, degrees (square). Up to 10: at 20 deg the S0 of a glint varies by 40 %
/// over the field and the first-order DoLP moments no longer hold.
pub const FOV_DEG: [f64; 7] = [0.5, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0];

/// The targets' facet-slope roughness values.
pub const SIGMAS: [f64; 3] = [0.1, 0.3, 0.5];

/// One class at one field of view and roughness.
#[derive(Debug, Clone, PartialEq)]
pub struct FovRow {
    /// Field of view, degrees (square).
    pub fov_deg: f64,
    /// The targets' roughness.
    pub sigma: f64,
    /// The material.
    pub class: String,
    /// DoLP of the field's mean radiance.
    pub dolp: f64,
    /// DoLP standard deviation from the geometry variation alone.
    pub dolp_std_geometry: f64,
    /// `sqrt(Sigma_g[0, 0]) / S0`.
    pub s0_rel_std_geometry: f64,
    /// Path radiance relative to S0.
    pub path_relative: f64,
    /// DoLP standard deviation of the estimate: geometry, texture and sensor noise.
    pub dolp_std_total: f64,
    /// Targets: the DoLP detector's Pd at `pfa` against the background (`None` for the
    /// background, or out of the detector's domain).
    pub pd_dolp: Option<f64>,
    /// Targets: its ROC, `[pfa, pd]`.
    pub roc: Vec<[f64; 2]>,
}

fn model(context: String) -> impl FnOnce(polar_model::ModelError) -> StudyError {
    move |source| StudyError::Model { context, source }
}

/// Runs the sweep over `fovs_deg` and [`SIGMAS`].
pub fn run(study: &Study, fovs_deg: &[f64]) -> Result<Vec<FovRow>, StudyError> {
    if let Some(bad) = fovs_deg
        .iter()
        .find(|v| !(v.is_finite() && **v > 0.0 && **v <= 60.0))
    {
        return Err(StudyError::Invalid {
            field: "values",
            reason: format!("field of view {bad} deg: allowed (0, 60]"),
        });
    }
    let mut rows = Vec::new();
    for &sigma in &SIGMAS {
        let base = study.materials();
        let context = format!("study fov, sigma {sigma}");
        let materials: [SceneMaterial; 3] = [
            with_sigma(&base[0], sigma).map_err(model(context.clone()))?,
            with_sigma(&base[1], sigma).map_err(model(context.clone()))?,
            base[2].clone(),
        ];
        for &fov in fovs_deg {
            let context = format!("study fov, fov {fov} deg, sigma {sigma}");
            let mut spec = study.spec().clone();
            spec.pointing.fov_deg = (fov, fov);
            let p =
                Prepared::new(&spec, study.settings().tolerance).map_err(model(context.clone()))?;
            let r = p.evaluate_all(&materials).map_err(model(context.clone()))?;
            let radiance = [
                Radiance::from_result(&r[0]),
                Radiance::from_result(&r[1]),
                Radiance::from_result(&r[2]),
            ];
            let point = study.point(
                fov,
                format!("{fov}"),
                &radiance,
                study.base_sensor(),
                &context,
            )?;
            for (k, m) in r.iter().enumerate() {
                let geometry = dolp_aop_stats(&m.mean.0, &m.cov_geometry, RegimeChoice::Auto)
                    .map_err(model(context.clone()))?;
                let (class, detector) = if k < 2 {
                    let t = &point.targets[k];
                    (&t.class, t.dolp.as_ref())
                } else {
                    (&point.background, None)
                };
                rows.push(FovRow {
                    fov_deg: fov,
                    sigma,
                    class: m.name.clone(),
                    dolp: m.mean.dolp().unwrap_or(0.0),
                    dolp_std_geometry: geometry.dolp_std,
                    s0_rel_std_geometry: m.cov_geometry[(0, 0)].max(0.0).sqrt()
                        / m.mean.0[0].abs().max(f64::MIN_POSITIVE),
                    path_relative: class.path_relative,
                    dolp_std_total: class.dolp_std,
                    pd_dolp: detector.map(|d| d.pd),
                    roc: detector.map(|d| d.curve.clone()).unwrap_or_default(),
                });
            }
        }
    }
    Ok(rows)
}

/// `fov.csv`.
pub fn csv(rows: &[FovRow]) -> String {
    let mut out = String::from(
        "fov_deg,target_sigma,class,dolp,dolp_std_geometry,s0_rel_std_geometry,path_relative,dolp_std_total,pd_dolp\n",
    );
    for r in rows {
        let pd = r.pd_dolp.map(|p| format!("{p:.6}")).unwrap_or_default();
        let _ = writeln!(
            out,
            "{},{},{},{:.6},{:.6e},{:.6e},{:.6e},{:.6e},{pd}",
            r.fov_deg,
            r.sigma,
            r.class,
            r.dolp,
            r.dolp_std_geometry,
            r.s0_rel_std_geometry,
            r.path_relative,
            r.dolp_std_total
        );
    }
    out
}

/// `fov_roc.csv`: the DoLP detector's ROC of each target.
pub fn roc_csv(rows: &[FovRow]) -> String {
    let mut out = String::from("fov_deg,target_sigma,target,pfa,pd\n");
    for r in rows {
        for [pfa, pd] in &r.roc {
            let _ = writeln!(
                out,
                "{},{},{},{pfa:.6e},{pd:.6}",
                r.fov_deg, r.sigma, r.class
            );
        }
    }
    out
}

const CLASS_COLORS: [RGBColor; 3] = [
    RGBColor(214, 95, 14),
    RGBColor(31, 119, 180),
    RGBColor(90, 90, 90),
];

/// `fov.png`: the geometry's DoLP spread and the DoLP detector's Pd against the field of view
/// (one line per class and roughness: solid 0.1, dashed 0.3, dotted 0.5), and the glass's ROC
/// family over the field of view at the smoothest roughness.
pub fn draw(rows: &[FovRow], scene: &str, path: &Path) -> Result<(), FigureError> {
    let e = draw_err(path);
    let root = canvas(path, (1900, 650))?;
    let (top, body) = root.split_vertically(40);
    top.draw_text(
        &format!(
            "Study 'fov' (Meng (2012) Sec. 4.2.3, Table 4.2, Figs. 4.5-4.7): scene {scene}; target roughness 0.1 solid, 0.3 dashed, 0.5 dotted"
        ),
        &(FONT, 18).into_text_style(&top),
        (15, 10),
    )
    .map_err(&e)?;
    let panels = body.split_evenly((1, 3));
    let fovs: Vec<f64> = {
        let mut v: Vec<f64> = rows.iter().map(|r| r.fov_deg).collect();
        v.sort_by(f64::total_cmp);
        v.dedup();
        v
    };
    let (flo, fhi) = (
        fovs.first().copied().unwrap_or(0.1),
        fovs.last().copied().unwrap_or(1.0),
    );
    let mut classes: Vec<&str> = rows.iter().map(|r| r.class.as_str()).collect();
    classes.dedup();
    classes.truncate(3);
    let dash = |k: usize| -> (u32, u32) { [(30, 1), (12, 6), (3, 5)][k % 3] };
    // Panel 1: geometry DoLP spread.
    let smax = rows
        .iter()
        .map(|r| r.dolp_std_geometry)
        .fold(1e-9, f64::max);
    let smin = rows
        .iter()
        .map(|r| r.dolp_std_geometry)
        .filter(|v| *v > 0.0)
        .fold(smax, f64::min);
    let mut chart = ChartBuilder::on(&panels[0])
        .caption("DoLP spread from the geometry alone (Sigma_g)", (FONT, 17))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(
            (flo / 1.3..fhi * 1.3).log_scale(),
            (smin / 2.0..smax * 2.0).log_scale(),
        )
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("field of view (deg, log)")
        .y_desc("std DoLP (geometry)")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 14))
        .draw()
        .map_err(&e)?;
    for (ci, class) in classes.iter().enumerate() {
        let color = CLASS_COLORS[ci % 3];
        for (si, &sigma) in SIGMAS.iter().enumerate() {
            let pts: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.class == *class && r.sigma == sigma)
                .map(|r| (r.fov_deg, r.dolp_std_geometry.max(smin / 2.0)))
                .collect();
            let (d, g) = dash(si);
            let series = chart
                .draw_series(std::iter::once(DashedPathElement::new(
                    pts,
                    d,
                    g,
                    color.stroke_width(2),
                )))
                .map_err(&e)?;
            if si == 0 {
                series.label(class.to_string()).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            }
        }
    }
    legend(&mut chart, SeriesLabelPosition::UpperLeft, 14).map_err(&e)?;
    // Panel 2: Pd of the DoLP detector.
    let mut chart = ChartBuilder::on(&panels[1])
        .caption(
            "Pd of the DoLP detector at Pfa, against asphalt",
            (FONT, 17),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((flo / 1.3..fhi * 1.3).log_scale(), 0.0f64..1.02f64)
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("field of view (deg, log)")
        .y_desc("Pd")
        .label_style((FONT, 14))
        .draw()
        .map_err(&e)?;
    for (ci, class) in classes.iter().take(2).enumerate() {
        let color = CLASS_COLORS[ci];
        for (si, &sigma) in SIGMAS.iter().enumerate() {
            let pts: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.class == *class && r.sigma == sigma)
                .filter_map(|r| r.pd_dolp.map(|p| (r.fov_deg, p)))
                .collect();
            let (d, g) = dash(si);
            chart
                .draw_series(std::iter::once(DashedPathElement::new(
                    pts,
                    d,
                    g,
                    color.stroke_width(2),
                )))
                .map_err(&e)?;
        }
    }
    // Panel 3: ROC family of glass at the first roughness.
    let glass = classes.get(1).copied().unwrap_or("");
    let mut chart = ChartBuilder::on(&panels[2])
        .caption(
            format!("ROC of the DoLP detector, {glass}, roughness {}", SIGMAS[0]),
            (FONT, 17),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((1e-6f64..1.0f64).log_scale(), 0.0f64..1.02f64)
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("Pfa")
        .y_desc("Pd")
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 14))
        .draw()
        .map_err(&e)?;
    let palette = [
        RGBColor(68, 1, 84),
        RGBColor(59, 82, 139),
        RGBColor(33, 145, 140),
        RGBColor(94, 201, 98),
        RGBColor(200, 180, 20),
        RGBColor(214, 39, 40),
    ];
    for (k, r) in rows
        .iter()
        .filter(|r| r.class == glass && r.sigma == SIGMAS[0] && !r.roc.is_empty())
        .enumerate()
    {
        let color = palette[k % palette.len()];
        chart
            .draw_series(LineSeries::new(
                r.roc.iter().filter(|p| p[0] >= 1e-6).map(|p| (p[0], p[1])),
                color.stroke_width(2),
            ))
            .map_err(&e)?
            .label(format!("fov {} deg", r.fov_deg))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    legend(&mut chart, SeriesLabelPosition::LowerRight, 14).map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(())
}

/// Runs the study (the default fields of view, or `--values` in degrees) and writes `fov.csv`,
/// `fov_roc.csv` and `fov.png` into `args.out`.
pub fn execute(args: &StudyArgs) -> Result<Vec<PathBuf>, StudyError> {
    let study = Study::load(args)?;
    let fovs: Vec<f64> = if args.values.is_empty() {
        FOV_DEG.to_vec()
    } else {
        args.values.clone()
    };
    let rows = run(&study, &fovs)?;
    std::fs::create_dir_all(&args.out).map_err(|e| StudyError::Figure(draw_err(&args.out)(e)))?;
    let main = args.out.join("fov.csv");
    std::fs::write(&main, csv(&rows)).map_err(|e| StudyError::Figure(draw_err(&main)(e)))?;
    let roc = args.out.join("fov_roc.csv");
    std::fs::write(&roc, roc_csv(&rows)).map_err(|e| StudyError::Figure(draw_err(&roc)(e)))?;
    let png = args.out.join("fov.png");
    draw(&rows, study.scene_label(), &png)?;
    Ok(vec![main, roc, png])
}
