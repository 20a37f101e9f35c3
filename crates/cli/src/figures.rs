//! `polarimeter report figures`: the analogues of the seed's Fig. 2.1 (Fresnel reflectances of
//! glass and copper), Fig. 3.6 (glass DoLP over the view hemisphere for four roughnesses) and
//! Fig. 3.7 (glass against vegetation at three incidence angles), drawn with plotters into PNGs.
//!
//! Polar maps: the radius is the view zenith `theta_r` (0 at the centre, 90 deg at the rim), the
//! polar angle the relative azimuth `phi`, with `phi = 180 deg` (the specular plane's forward
//! side) to the right. Each also writes the numbers it drew as a CSV beside the PNG, so the
//! figure can be checked or re-plotted.

use plotters::prelude::*;
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::pbrdf::{Geometry, Surface};
use polar_model::quadrature::Tolerance;
use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Errors drawing figures.
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    /// Plotting or file-system failure.
    #[error("{path}: {message}")]
    Draw {
        /// The file being written.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A model evaluation failed (a bug: every input here is in range).
    #[error("model: {0}")]
    Model(#[from] polar_model::ModelError),
}

fn draw_err<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> FigureError + '_ {
    move |e| FigureError::Draw {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

const FONT: &str = "sans-serif";

fn register_font() {
    // Registering twice is harmless; an invalid embedded font would be a build bug and leaves
    // plotters to report a font error when drawing text.
    let _ = plotters::style::register_font(
        FONT,
        FontStyle::Normal,
        include_bytes!("../assets/DejaVuSans.ttf"),
    );
}

/// Draws every figure into `out_dir` and returns the files written.
pub fn draw_all(out_dir: &Path) -> Result<Vec<PathBuf>, FigureError> {
    std::fs::create_dir_all(out_dir).map_err(draw_err(out_dir))?;
    register_font();
    let mut written = Vec::new();
    written.extend(fig_2_1(out_dir)?);
    written.extend(fig_3_6(out_dir)?);
    written.extend(fig_3_7(out_dir)?);
    Ok(written)
}

fn write_csv(path: &Path, text: &str) -> Result<(), FigureError> {
    std::fs::write(path, text).map_err(draw_err(path))
}

/// A named curve: label, colour, points.
type Series = (String, RGBColor, Vec<(f64, f64)>);

/// Fig. 2.1: Rs and Rp of glass (n = 1.52) and copper (1.02 + 2.577i) against incidence angle.
fn fig_2_1(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig2_1_fresnel.png");
    let csv = out.join("fig2_1_fresnel.csv");
    let glass = RefractiveIndex::new(1.52, 0.0)?;
    let copper = RefractiveIndex::new(1.02, 2.577)?;
    let mut series: Vec<Series> = vec![
        ("glass Rs".into(), RGBColor(31, 119, 180), vec![]),
        ("glass Rp".into(), RGBColor(31, 119, 180), vec![]),
        ("copper Rs".into(), RGBColor(214, 95, 14), vec![]),
        ("copper Rp".into(), RGBColor(214, 95, 14), vec![]),
    ];
    let mut text = String::from("theta_i_deg,glass_Rs,glass_Rp,copper_Rs,copper_Rp\n");
    for step in 0..=900 {
        let t = step as f64 * 0.1;
        let g = amplitudes(&glass, t.to_radians())?;
        let c = amplitudes(&copper, t.to_radians())?;
        let v = [g.rs_power(), g.rp_power(), c.rs_power(), c.rp_power()];
        for (s, y) in series.iter_mut().zip(v) {
            s.2.push((t, y));
        }
        if step % 10 == 0 {
            let _ = writeln!(text, "{t},{},{},{},{}", v[0], v[1], v[2], v[3]);
        }
    }
    write_csv(&csv, &text)?;
    let root = BitMapBackend::new(&png, (900, 600)).into_drawing_area();
    let e = draw_err(&png);
    root.fill(&WHITE).map_err(&e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Fresnel reflectance: glass n = 1.52, copper n = 1.02 + 2.577i (550 nm)",
            (FONT, 22),
        )
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(55)
        .build_cartesian_2d(0.0..90.0, 0.0..1.0)
        .map_err(&e)?;
    chart
        .configure_mesh()
        .x_desc("angle of incidence theta_i (deg)")
        .y_desc("reflectance")
        .label_style((FONT, 16))
        .draw()
        .map_err(&e)?;
    for (i, (name, color, pts)) in series.into_iter().enumerate() {
        let style = if i % 2 == 0 {
            color.stroke_width(3)
        } else {
            color.mix(0.6).stroke_width(2)
        };
        let legend_color = color;
        let dashed = i % 2 == 1;
        if dashed {
            chart
                .draw_series(DashedLineSeries::new(pts, 8, 5, style))
                .map_err(&e)?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(
                        vec![(x, y), (x + 20, y)],
                        legend_color.mix(0.6).stroke_width(2),
                    )
                });
        } else {
            chart
                .draw_series(LineSeries::new(pts, style))
                .map_err(&e)?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], legend_color.stroke_width(3))
                });
        }
    }
    let brewster = glass.brewster_angle_rad().to_degrees();
    chart
        .draw_series(std::iter::once(Text::new(
            format!("Brewster {brewster:.2} deg"),
            (brewster - 14.0, 0.07),
            (FONT, 15),
        )))
        .map_err(&e)?;
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, 16))
        .draw()
        .map_err(&e)?;
    root.present().map_err(&e)?;
    drop(chart);
    drop(root);
    Ok(vec![png.clone(), csv])
}

/// DoLP of a surface for unpolarised light over the view hemisphere at one incidence angle.
struct PolarMap {
    title: String,
    surface: Surface,
    theta_i_deg: f64,
}

/// Renders polar DoLP maps on a grid of panels with a shared colour bar; returns the CSV text
/// (a coarse 5-deg grid of the values drawn).
fn polar_panels(
    path: &Path,
    rows: usize,
    cols: usize,
    caption: &str,
    maps: &[PolarMap],
) -> Result<String, FigureError> {
    let e = draw_err(path);
    let panel = 330u32;
    let (w, h) = (cols as u32 * panel + 110, rows as u32 * panel + 60);
    let root = BitMapBackend::new(path, (w, h)).into_drawing_area();
    root.fill(&WHITE).map_err(&e)?;
    let (top, body) = root.split_vertically(50);
    top.draw_text(caption, &(FONT, 18).into_text_style(&top), (15, 6))
        .map_err(&e)?;
    top.draw_text(
        "radius: view zenith theta_r (rings at 30, 60, 90 deg); angle: relative azimuth phi, 180 deg (specular) at right",
        &(FONT, 12).into_text_style(&top),
        (15, 30),
    )
    .map_err(&e)?;
    let (grid, bar) = body.split_horizontally(cols as u32 * panel);
    let cells = grid.split_evenly((rows, cols));
    let cmap = ViridisRGB;
    let mut csv = String::from("panel,theta_i_deg,theta_r_deg,phi_deg,dolp\n");
    for (cell, map) in cells.iter().zip(maps) {
        let diffuse = map
            .surface
            .diffuse(map.theta_i_deg.to_radians(), Tolerance::absolute(1e-9))?;
        let dolp_at = |tr: f64, phi: f64| -> Result<f64, FigureError> {
            let g = Geometry::from_deg(map.theta_i_deg, tr, phi)?;
            Ok(map
                .surface
                .mueller_with(&g, &diffuse)
                .dolp_unpolarized()
                .unwrap_or(0.0))
        };
        let (pw, ph) = cell.dim_in_pixel();
        let radius = (pw.min(ph) as f64 - 70.0) / 2.0;
        let (cx, cy) = (pw as f64 / 2.0, ph as f64 / 2.0 + 12.0);
        for py in 0..ph {
            for px in 0..pw {
                let (dx, dy) = (px as f64 + 0.5 - cx, cy - (py as f64 + 0.5));
                let r = dx.hypot(dy) / radius;
                if r > 1.0 {
                    continue;
                }
                // phi = 180 deg points right (+x): phi = 180 - atan2(dy, dx).
                let phi = (180.0 - dy.atan2(dx).to_degrees()).rem_euclid(360.0);
                let d = dolp_at(r * 90.0, phi)?.clamp(0.0, 1.0);
                cell.draw_pixel((px as i32, py as i32), &cmap.get_color(d as f32))
                    .map_err(&e)?;
            }
        }
        // Rings every 30 deg of view zenith and spokes every 45 deg of azimuth.
        for ring in [30.0, 60.0, 90.0] {
            let rr = radius * ring / 90.0;
            let pts: Vec<(i32, i32)> = (0..=180)
                .map(|k| {
                    let a = k as f64 * 2.0 * PI / 180.0;
                    ((cx + rr * a.cos()) as i32, (cy - rr * a.sin()) as i32)
                })
                .collect();
            cell.draw(&PathElement::new(pts, WHITE.mix(0.6)))
                .map_err(&e)?;
        }
        for (phi, label) in [(0.0, "0"), (90.0, "90"), (180.0, "180"), (270.0, "270")] {
            let a = (180.0f64 - phi).to_radians();
            let (x, y) = (
                cx + (radius + 16.0) * a.cos(),
                cy - (radius + 16.0) * a.sin(),
            );
            cell.draw_text(
                label,
                &(FONT, 13).into_text_style(cell),
                ((x - 10.0) as i32, (y - 6.0) as i32),
            )
            .map_err(&e)?;
        }
        cell.draw_text(&map.title, &(FONT, 16).into_text_style(cell), (8, 4))
            .map_err(&e)?;
        for tr in (0..=90).step_by(5) {
            for phi in (0..360).step_by(5) {
                let _ = writeln!(
                    csv,
                    "{},{},{tr},{phi},{:.6}",
                    map.title.replace(',', ";"),
                    map.theta_i_deg,
                    dolp_at(tr as f64, phi as f64)?
                );
            }
        }
    }
    // Colour bar.
    let (_, bh) = bar.dim_in_pixel();
    let (x0, y0, y1) = (20i32, 40i32, bh as i32 - 40);
    for y in y0..y1 {
        let v = 1.0 - (y - y0) as f64 / (y1 - y0) as f64;
        for x in x0..x0 + 22 {
            bar.draw_pixel((x, y), &cmap.get_color(v as f32))
                .map_err(&e)?;
        }
    }
    for v in [0.0, 0.25, 0.5, 0.75, 1.0] {
        let y = y0 + ((1.0 - v) * (y1 - y0) as f64) as i32;
        bar.draw_text(
            &format!("{v:.2}"),
            &(FONT, 13).into_text_style(&bar),
            (x0 + 28, y - 6),
        )
        .map_err(&e)?;
    }
    bar.draw_text("DoLP", &(FONT, 15).into_text_style(&bar), (x0, 12))
        .map_err(&e)?;
    root.present().map_err(&e)?;
    Ok(csv)
}

/// Fig. 3.6: glass DoLP over the view hemisphere, sigma 0.1/0.3/0.5/0.7, theta_i = 60 deg.
fn fig_3_6(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig3_6_glass_dolp_roughness.png");
    let csv = out.join("fig3_6_glass_dolp_roughness.csv");
    let glass = RefractiveIndex::new(1.52, 0.0)?;
    let maps = [0.1, 0.3, 0.5, 0.7]
        .iter()
        .map(|&sigma| {
            Ok(PolarMap {
                title: format!("sigma = {sigma}"),
                surface: Surface::microfacet(glass, sigma, 0.1)?,
                theta_i_deg: 60.0,
            })
        })
        .collect::<Result<Vec<_>, FigureError>>()?;
    let text = polar_panels(
        &png,
        2,
        2,
        "Glass DoLP for unpolarised light, n = 1.52, DHR = 0.1, theta_i = 60 deg",
        &maps,
    )?;
    write_csv(&csv, &text)?;
    Ok(vec![png, csv])
}

/// Fig. 3.7: glass (sigma 0.1, DHR 0.1) against vegetation (n 1.5, f00_d = 0.04/pi) at
/// theta_i = 20/40/60 deg.
fn fig_3_7(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig3_7_glass_vs_vegetation.png");
    let csv = out.join("fig3_7_glass_vs_vegetation.csv");
    let glass = Surface::microfacet(RefractiveIndex::new(1.52, 0.0)?, 0.1, 0.1)?;
    let veg = Surface::vegetation(RefractiveIndex::new(1.5, 0.0)?, 0.04 / PI)?;
    let mut maps = Vec::new();
    for ti in [20.0, 40.0, 60.0] {
        maps.push(PolarMap {
            title: format!("glass, theta_i = {ti}"),
            surface: glass,
            theta_i_deg: ti,
        });
        maps.push(PolarMap {
            title: format!("vegetation, theta_i = {ti}"),
            surface: veg,
            theta_i_deg: ti,
        });
    }
    let text = polar_panels(
        &png,
        3,
        2,
        "DoLP: glass (sigma 0.1, DHR 0.1) vs vegetation (Eq. 3.19)",
        &maps,
    )?;
    write_csv(&csv, &text)?;
    Ok(vec![png, csv])
}
