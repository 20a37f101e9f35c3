//! The files of Meng (2012)'s Ch. 4 trade studies (`polarimeter report study`): `<kind>.csv`
//! (one row per swept value and target), `<kind>_roc.csv` (the ROC curves) and `<kind>.png`
//! (DoLP SNR, Pd at `pfa` of the three detectors, and the DoLP detector's ROC family for each
//! target), and [`execute`], which runs the studies a command line selects and writes them.

use crate::plot::{canvas, draw_err, FigureError, FONT};
use crate::study::{
    format_value, Study, StudyArgs, StudyError, StudyKind, StudyPoint, StudyResult, StudySelection,
    GLASS_BREWSTER_DEG,
};
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use polar_model::stats::Regime;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

fn regime_name(r: Regime) -> &'static str {
    match r {
        Regime::Taylor => "taylor",
        Regime::Rice => "rice",
    }
}

/// The main CSV: one row per swept value and target.
pub fn csv(result: &StudyResult) -> String {
    let mut out = format!(
        "study,{},label,target,background,t_int_ms,noise_factor,pfa,\
         target_S0,target_S1,target_S2,target_dolp_true,target_dolp_mean,target_dolp_std,\
         target_dolp_snr,target_dolp_snr_clutter_limit,target_regime,target_s0_rel_std,\
         target_saturated,\
         target_max_electrons,target_path_rel,target_scene_error,\
         background_S0,background_S1,background_S2,background_dolp_true,background_dolp_mean,\
         background_dolp_std,background_dolp_snr,background_dolp_snr_clutter_limit,\
         background_regime,background_s0_rel_std,background_saturated,background_path_rel,\
         dolp_contrast,dolp_contrast_snr,scr,pd_mf,pd_rx,pd_dolp{}\n",
        result.kind.parameter(),
        if result.kind == StudyKind::Roughness {
            ",target_dolp_off_specular"
        } else {
            ""
        }
    );
    for p in &result.points {
        let (t_int, noise) = match result.kind {
            StudyKind::IntegrationTime => (p.value, result.noise_factor),
            StudyKind::NoiseFactor => (result.t_int_ms, p.value),
            _ => (result.t_int_ms, result.noise_factor),
        };
        for t in &p.targets {
            let c = &t.class;
            let b = &p.background;
            let _ = writeln!(
                out,
                "{},{},{},{},{},{},{},{:e},\
                 {:.6e},{:.6e},{:.6e},{:.6},{:.6},{:.6e},{:.6e},{:.6e},{},{:.3e},{},{:.6e},{:.4e},\
                 {:.2e},{:.6e},{:.6e},{:.6e},{:.6},{:.6},{:.6e},{:.6e},{:.6e},{},{:.3e},{},{:.4e},\
                 {:.6},{:.6e},{:.6e},{:.6},{},{}{}",
                result.kind.name(),
                p.value,
                p.label,
                c.name,
                b.name,
                t_int,
                noise,
                result.pfa,
                c.radiance_mean[0],
                c.radiance_mean[1],
                c.radiance_mean[2],
                c.dolp_true,
                c.dolp_mean,
                c.dolp_std,
                c.dolp_snr,
                c.dolp_snr_clutter_limit,
                regime_name(c.regime),
                c.s0_rel_std,
                c.saturated,
                c.max_electrons,
                c.path_relative,
                c.scene_error,
                b.radiance_mean[0],
                b.radiance_mean[1],
                b.radiance_mean[2],
                b.dolp_true,
                b.dolp_mean,
                b.dolp_std,
                b.dolp_snr,
                b.dolp_snr_clutter_limit,
                regime_name(b.regime),
                b.s0_rel_std,
                b.saturated,
                b.path_relative,
                t.dolp_contrast,
                t.dolp_contrast_snr,
                t.scr,
                t.matched_filter.pd,
                t.rx.as_ref()
                    .map_or(String::new(), |r| format!("{:.6}", r.pd)),
                t.dolp
                    .as_ref()
                    .map_or(String::new(), |r| format!("{:.6}", r.pd)),
                t.dolp_off_specular
                    .map_or(String::new(), |d| format!(",{d:.6}")),
            );
        }
    }
    out
}

/// The ROC curves: one row per swept value, target, detector and false-alarm rate.
pub fn roc_csv(result: &StudyResult) -> String {
    let mut out = format!("{},label,target,detector,pfa,pd\n", result.kind.parameter());
    for p in &result.points {
        for t in &p.targets {
            let rocs = [
                ("mf", Some(&t.matched_filter)),
                ("rx", t.rx.as_ref()),
                ("dolp", t.dolp.as_ref()),
            ];
            for (name, roc) in rocs {
                let Some(roc) = roc else { continue };
                for [pfa, pd] in &roc.curve {
                    let _ = writeln!(
                        out,
                        "{},{},{},{name},{pfa:.6e},{pd:.6}",
                        p.value, p.label, t.class.name
                    );
                }
            }
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Figures
// ---------------------------------------------------------------------------------------------

const PAINT: RGBColor = RGBColor(214, 95, 14);
const GLASS: RGBColor = RGBColor(31, 119, 180);
const ASPHALT: RGBColor = RGBColor(90, 90, 90);

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;

/// A legend entry: label, colour, dash pattern (`None`: solid).
type LegendEntry = (String, RGBColor, Option<(u32, u32)>);

/// Width of the legend column to the right of each panel's plot, pixels.
const LEGEND_W: u32 = 230;

/// A legend glyph 24 px wide: solid, or the line's dash pattern.
fn glyph(
    (x, y): (i32, i32),
    color: RGBColor,
    dash: Option<(u32, u32)>,
) -> DashedPathElement<std::vec::IntoIter<(i32, i32)>, u32> {
    let (d, g) = dash.unwrap_or((30, 1));
    DashedPathElement::new(vec![(x, y), (x + 24, y)], d, g, color.stroke_width(3))
}

/// A line with markers: label, colour, dashed, points (x, y, saturated).
struct Line {
    label: String,
    color: RGBColor,
    dash: Option<(u32, u32)>,
    points: Vec<(f64, f64, bool)>,
}

/// Draws `lines` on one panel with x coordinate `x` and y coordinate `y`.
#[allow(clippy::too_many_arguments)]
fn line_panel<X, Y>(
    area: &Area,
    path: &Path,
    title: &str,
    x: X,
    y: Y,
    x_desc: &str,
    y_desc: &str,
    x_fmt: &dyn Fn(&f64) -> String,
    lines: &[Line],
    vline: Option<(f64, &str)>,
) -> Result<(), FigureError>
where
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let e = draw_err(path);
    let mut chart = ChartBuilder::on(area)
        .caption(title, (FONT, 17))
        .margin(12)
        .margin_right(LEGEND_W)
        .x_label_area_size(48)
        .y_label_area_size(70)
        .build_cartesian_2d(x, y)
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(x_fmt)
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 15))
        .draw()
        .map_err(&e)?;
    if let Some((xv, text)) = vline {
        let yr = chart.y_range();
        let grey = BLACK.mix(0.45);
        chart
            .draw_series(DashedLineSeries::new(
                vec![(xv, yr.start), (xv, yr.end)],
                5,
                5,
                grey.stroke_width(1),
            ))
            .map_err(&e)?;
        chart
            .draw_series(std::iter::once(Text::new(
                text.to_string(),
                (xv, yr.end),
                (FONT, 13).into_font().color(&grey),
            )))
            .map_err(&e)?;
    }
    for l in lines {
        let c = l.color;
        let pts: Vec<(f64, f64)> = l.points.iter().map(|p| (p.0, p.1)).collect();
        let style = c.stroke_width(2);
        match l.dash {
            Some((d, g)) => chart
                .draw_series(DashedLineSeries::new(pts, d, g, style))
                .map_err(&e)?,
            None => chart.draw_series(LineSeries::new(pts, style)).map_err(&e)?,
        };
        let dash = l.dash;
        chart
            .draw_series(l.points.iter().map(|&(px, py, sat)| {
                if sat {
                    Cross::new((px, py), 6, c.stroke_width(2)).into_dyn()
                } else if dash.is_some() {
                    TriangleMarker::new((px, py), 5, c.filled()).into_dyn()
                } else {
                    Circle::new((px, py), 4, c.filled()).into_dyn()
                }
            }))
            .map_err(&e)?;
    }
    drop(chart);
    let entries: Vec<LegendEntry> = lines
        .iter()
        .map(|l| (l.label.clone(), l.color, l.dash))
        .collect();
    legend_column(area, path, &entries)
}

/// The legend in the column right of a panel's plot: one glyph and label per entry.
fn legend_column(area: &Area, path: &Path, entries: &[LegendEntry]) -> Result<(), FigureError> {
    let e = draw_err(path);
    let (w, _) = area.dim_in_pixel();
    let x0 = w as i32 - LEGEND_W as i32 + 8;
    let mut y = 48;
    for (label, color, dash) in entries {
        area.draw(&glyph((x0, y), *color, *dash)).map_err(&e)?;
        area.draw_text(label, &(FONT, 14).into_text_style(area), (x0 + 30, y - 8))
            .map_err(&e)?;
        y += 21;
    }
    Ok(())
}

/// The ROC family of target `k` (DoLP threshold detector).
fn roc_panel(area: &Area, path: &Path, result: &StudyResult, k: usize) -> Result<(), FigureError> {
    let e = draw_err(path);
    let name = result
        .points
        .first()
        .map_or("target", |p| p.targets[k].class.name.as_str());
    let bg = result
        .points
        .first()
        .map_or("background", |p| p.background.name.as_str());
    let mut chart = ChartBuilder::on(area)
        .caption(
            format!("ROC, DoLP threshold detector: {name} vs {bg}"),
            (FONT, 17),
        )
        .margin(12)
        .margin_right(LEGEND_W)
        .x_label_area_size(48)
        .y_label_area_size(70)
        .build_cartesian_2d((1e-6..1.0).log_scale(), 0.0..1.02)
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("probability of false alarm (log)")
        .y_desc("probability of detection")
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 15))
        .draw()
        .map_err(&e)?;
    let n = result.points.len().max(2);
    let mut entries = Vec::with_capacity(result.points.len());
    for (i, p) in result.points.iter().enumerate() {
        let t = ViridisRGB.get_color((0.92 * i as f64 / (n - 1) as f64) as f32);
        let c = RGBColor(t.0, t.1, t.2);
        let Some(roc) = &p.targets[k].dolp else {
            entries.push((format!("{} (n/a)", roc_label(result.kind, p, k)), c, None));
            continue;
        };
        let pts: Vec<(f64, f64)> = roc.curve.iter().map(|[pfa, pd]| (*pfa, *pd)).collect();
        chart
            .draw_series(LineSeries::new(pts, c.stroke_width(2)))
            .map_err(&e)?;
        entries.push((roc_label(result.kind, p, k), c, None));
    }
    chart
        .draw_series(DashedLineSeries::new(
            vec![(result.pfa, 0.0), (result.pfa, 1.02)],
            4,
            4,
            BLACK.mix(0.5).stroke_width(1),
        ))
        .map_err(&e)?;
    drop(chart);
    legend_column(area, path, &entries)
}

/// A ROC curve's legend entry: the swept value with its unit, and whether a frame of the two
/// classes is near saturation.
fn roc_label(kind: StudyKind, p: &StudyPoint, k: usize) -> String {
    let unit = match kind {
        StudyKind::Sources => "",
        StudyKind::Altitude => " m",
        StudyKind::Geometry => " deg",
        StudyKind::Roughness => "",
        StudyKind::NoiseFactor => "",
        StudyKind::IntegrationTime => " ms",
    };
    let prefix = match kind {
        StudyKind::Roughness => "sigma ",
        StudyKind::NoiseFactor => "F_n ",
        _ => "",
    };
    let sat = if p.targets[k].class.saturated || p.background.saturated {
        " (sat.)"
    } else {
        ""
    };
    format!("{prefix}{}{unit}{sat}", p.label)
}

/// Draws the four panels for x coordinate `x` (linear or log).
fn draw_panels<X>(
    panels: &[Area],
    path: &Path,
    result: &StudyResult,
    x: impl Fn() -> X,
    x_fmt: &dyn Fn(&f64) -> String,
) -> Result<(), FigureError>
where
    X: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
{
    let kind = result.kind;
    let vline = (kind == StudyKind::Geometry).then_some((GLASS_BREWSTER_DEG, " glass Brewster"));
    let px = |p: &StudyPoint| p.value;
    let class_line = |label: &str, color, f: &dyn Fn(&StudyPoint) -> (f64, bool)| Line {
        label: label.to_string(),
        color,
        dash: None,
        points: result
            .points
            .iter()
            .map(|p| {
                let (y, s) = f(p);
                (px(p), y, s)
            })
            .collect(),
    };
    let names = result.points.first().map_or(
        [
            "paint".to_string(),
            "glass".to_string(),
            "background".to_string(),
        ],
        |p| {
            [
                p.targets[0].class.name.clone(),
                p.targets[1].class.name.clone(),
                p.background.name.clone(),
            ]
        },
    );
    let mut snr_lines = vec![
        class_line(&names[0], PAINT, &|p| {
            (p.targets[0].class.dolp_snr, p.targets[0].class.saturated)
        }),
        class_line(&names[1], GLASS, &|p| {
            (p.targets[1].class.dolp_snr, p.targets[1].class.saturated)
        }),
        class_line(&names[2], ASPHALT, &|p| {
            (p.background.dolp_snr, p.background.saturated)
        }),
    ];
    for (k, color) in [(0, PAINT), (1, GLASS)] {
        let mut l = class_line(
            &format!("{} - {} contrast", names[k], names[2]),
            color,
            &|p| {
                let t = &p.targets[k];
                (
                    t.dolp_contrast_snr,
                    t.class.saturated || p.background.saturated,
                )
            },
        );
        l.dash = Some((8, 5));
        snr_lines.push(l);
    }
    let (lo, hi) = snr_lines
        .iter()
        .flat_map(|l| l.points.iter().map(|p| p.1))
        .filter(|v| *v > 0.0 && v.is_finite())
        .fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    let (lo, hi) = if hi > 0.0 {
        (lo.max(hi * 1e-6) * 0.6, hi * 1.8)
    } else {
        (0.1, 10.0)
    };
    for l in &mut snr_lines {
        for p in &mut l.points {
            p.1 = p.1.clamp(lo, hi);
        }
    }
    line_panel(
        &panels[0],
        path,
        "DoLP SNR = E[DoLP]/std[DoLP]; dashed: DoLP contrast SNR (x: near saturation)",
        x(),
        (lo..hi).log_scale(),
        kind.axis_title(),
        "DoLP SNR (log)",
        x_fmt,
        &snr_lines,
        vline,
    )?;
    let mut pd_lines = Vec::new();
    for (k, color) in [(0, PAINT), (1, GLASS)] {
        for (det, dash) in [("DoLP", None), ("MF", Some((10, 5))), ("RX", Some((3, 4)))] {
            let points: Vec<(f64, f64, bool)> = result
                .points
                .iter()
                .filter_map(|p| {
                    let t = &p.targets[k];
                    let pd = match det {
                        "DoLP" => t.dolp.as_ref().map(|r| r.pd),
                        "MF" => Some(t.matched_filter.pd),
                        _ => t.rx.as_ref().map(|r| r.pd),
                    }?;
                    Some((px(p), pd, t.class.saturated || p.background.saturated))
                })
                .collect();
            if points.is_empty() {
                continue;
            }
            pd_lines.push(Line {
                label: format!("{} {det}", names[k]),
                color,
                dash,
                points,
            });
        }
    }
    line_panel(
        &panels[1],
        path,
        &format!(
            "Pd at Pfa = {:.0e} against {}: DoLP threshold, matched filter, RX",
            result.pfa, names[2]
        ),
        x(),
        -0.02..1.05,
        kind.axis_title(),
        "probability of detection",
        x_fmt,
        &pd_lines,
        vline,
    )?;
    roc_panel(&panels[2], path, result, 0)?;
    roc_panel(&panels[3], path, result, 1)?;
    Ok(())
}

/// The study's PNG: DoLP SNR, Pd at `pfa`, and the two ROC families.
pub fn draw(result: &StudyResult, path: &Path) -> Result<(), FigureError> {
    let e = draw_err(path);
    let root = canvas(path, (1900, 1150))?;
    let (top, body) = root.split_vertically(56);
    let kind = result.kind;
    let sweep = match kind {
        StudyKind::IntegrationTime => format!("noise factor {}", result.noise_factor),
        StudyKind::NoiseFactor => format!("t_int {} ms", result.t_int_ms),
        _ => format!(
            "t_int {} ms, noise factor {}",
            result.t_int_ms, result.noise_factor
        ),
    };
    top.draw_text(
        &format!(
            "Study '{}' (Meng (2012) Sec. {}): scene {}, {sweep}",
            kind.name(),
            meng_section(kind),
            result.scene
        ),
        &(FONT, 20).into_text_style(&top),
        (15, 6),
    )
    .map_err(&e)?;
    top.draw_text(
        "scene model -> camera frames (EMVA 1288) -> GLS Stokes -> DoLP moments; clutter (geometry + texture) and sensor noise included",
        &(FONT, 14).into_text_style(&top),
        (15, 32),
    )
    .map_err(&e)?;
    let panels = body.split_evenly((2, 2));
    let values: Vec<f64> = result.points.iter().map(|p| p.value).collect();
    let (vmin, vmax) = values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !(vmin.is_finite() && vmax.is_finite()) {
        return Err(FigureError::Draw {
            path: path.to_path_buf(),
            message: "no points to draw".into(),
        });
    }
    if kind == StudyKind::Sources {
        let labels: Vec<String> = result.points.iter().map(|p| p.label.clone()).collect();
        let fmt = move |v: &f64| -> String {
            let i = v.round();
            if (v - i).abs() < 1e-6 && i >= 0.0 {
                labels.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        };
        draw_panels(&panels, path, result, || -0.4..vmax + 0.4, &fmt)?;
    } else if kind.log_axis() && vmin > 0.0 {
        let fmt = |v: &f64| format_value(*v);
        draw_panels(
            &panels,
            path,
            result,
            || (vmin / 1.3..vmax * 1.3).log_scale(),
            &fmt,
        )?;
    } else {
        let pad = 0.04 * (vmax - vmin).max(1e-9);
        let fmt = |v: &f64| format_value((v * 1e6).round() / 1e6);
        draw_panels(&panels, path, result, || vmin - pad..vmax + pad, &fmt)?;
    }
    root.present().map_err(&e)?;
    Ok(())
}

/// The section of Meng (2012) a study reproduces.
fn meng_section(kind: StudyKind) -> &'static str {
    match kind {
        StudyKind::Sources => "4.2.1",
        StudyKind::Altitude => "4.2.2",
        StudyKind::Geometry => "4.2.5",
        StudyKind::Roughness => "4.2.4",
        StudyKind::NoiseFactor => "4.2.6",
        StudyKind::IntegrationTime => "4.2.7",
    }
}

/// Writes `<kind>.csv`, `<kind>_roc.csv` and `<kind>.png` into `out_dir`; returns the files.
pub fn write(result: &StudyResult, out_dir: &Path) -> Result<Vec<PathBuf>, StudyError> {
    std::fs::create_dir_all(out_dir).map_err(draw_err(out_dir))?;
    let name = result.kind.name();
    let main = out_dir.join(format!("{name}.csv"));
    let roc = out_dir.join(format!("{name}_roc.csv"));
    let png = out_dir.join(format!("{name}.png"));
    std::fs::write(&main, csv(result)).map_err(draw_err(&main))?;
    std::fs::write(&roc, roc_csv(result)).map_err(draw_err(&roc))?;
    draw(result, &png)?;
    Ok(vec![main, roc, png])
}

/// Runs the studies `args` selects and writes their files; returns the files written.
pub fn execute(args: &StudyArgs) -> Result<Vec<PathBuf>, StudyError> {
    match args.kind {
        StudySelection::ScrTime => return crate::study_scr::execute_time(args),
        StudySelection::ScrSets => return crate::study_scr::execute_sets(args),
        StudySelection::Fov => return crate::study_fov::execute(args),
        StudySelection::Aptd => {
            return crate::study_aptd::execute(args).map_err(StudyError::from);
        }
        _ => {}
    }
    let kinds = args.kind.kinds();
    if !args.values.is_empty() && kinds.len() != 1 {
        return Err(StudyError::Invalid {
            field: "values",
            reason: "a custom sweep needs one study, not all".into(),
        });
    }
    let study = Study::load(args)?;
    let values = (!args.values.is_empty()).then_some(args.values.as_slice());
    let mut written = Vec::new();
    for kind in kinds {
        let result = study.run(kind, values)?;
        written.extend(write(&result, &args.out)?);
    }
    Ok(written)
}
