//! `polarimeter report figures`: the analogues of Meng (2012)'s Fig. 2.1 (Fresnel reflectances of
//! glass and copper), Fig. 3.6 (glass DoLP over the view hemisphere for four roughnesses),
//! Fig. 3.7 (glass against vegetation at three incidence angles), Fig. 3.10 (the sky's Stokes
//! vector and DoLP over the hemisphere), Fig. 3.12 (sky DoLP for four sun zenith angles) and
//! Figs. 4.1-4.2 (direct, skylight and path contributions for black paint and glass), drawn
//! with plotters into PNGs.
//!
//! Polar maps: the radius is the view zenith `theta_r` (0 at the centre, 90 deg at the rim), the
//! polar angle the relative azimuth `phi`, with `phi = 180 deg` (the specular plane's forward
//! side) to the right. Each also writes the numbers it drew as a CSV beside the PNG, so the
//! figure can be checked or re-plotted.

use plotters::prelude::*;
use polar_model::atmosphere::{Atmosphere, Band};
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::material::MaterialLibrary;
use polar_model::pbrdf::{Geometry, Surface};
use polar_model::polarization::Stokes;
use polar_model::quadrature::Tolerance;
use polar_model::scene::{Prepared, SceneMaterial, SceneSpec, SkyModel, Texture};
use polar_model::skylight::SkyRadiance;
use polar_model::tiles::Pointing;
use std::f64::consts::PI;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub use crate::plot::FigureError;
use crate::plot::{canvas, draw_err, legend, FONT};

/// Draws every figure into `out_dir` and returns the files written.
pub fn draw_all(out_dir: &Path) -> Result<Vec<PathBuf>, FigureError> {
    std::fs::create_dir_all(out_dir).map_err(draw_err(out_dir))?;
    let mut written = Vec::new();
    written.extend(fig_2_1(out_dir)?);
    written.extend(fig_3_6(out_dir)?);
    written.extend(fig_3_7(out_dir)?);
    written.extend(fig_3_10(out_dir)?);
    written.extend(fig_3_12(out_dir)?);
    written.extend(fig_4_1_2(out_dir)?);
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
    let e = draw_err(&png);
    let root = canvas(&png, (900, 600))?;
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
    // A metal's Rp never vanishes: its pseudo-Brewster angle is where Rp is smallest.
    let pseudo = copper.pseudo_brewster();
    let pseudo_deg = pseudo.angle_rad.to_degrees();
    chart
        .draw_series(std::iter::once(Text::new(
            format!(
                "copper pseudo-Brewster {pseudo_deg:.2} deg (Rp {:.3})",
                pseudo.rp_min
            ),
            (pseudo_deg - 40.0, pseudo.rp_min - 0.06),
            (FONT, 15),
        )))
        .map_err(&e)?;
    legend(&mut chart, SeriesLabelPosition::UpperLeft, 16).map_err(&e)?;
    root.present().map_err(&e)?;
    drop(chart);
    drop(root);
    Ok(vec![png.clone(), csv])
}

/// A value over a hemisphere, drawn as one polar panel.
struct Panel<'a> {
    title: String,
    /// The value at (zenith_deg, azimuth_deg): in `[0, 1]` (viridis) or `[-1, 1]` (diverging).
    value: Box<dyn Fn(f64, f64) -> Result<f64, FigureError> + 'a>,
    diverging: bool,
    /// A point to mark (the sun): (zenith_deg, azimuth_deg).
    marker: Option<(f64, f64)>,
}

/// How the panels of one figure map azimuth to the page.
struct PolarLayout<'a> {
    caption: &'a str,
    note: &'a str,
    /// Screen angle (deg, counter-clockwise from +x) of an azimuth.
    screen_deg: fn(f64) -> f64,
    labels: [(f64, &'a str); 4],
    bar_label: &'a str,
}

/// Blue (-1) through white (0) to red (+1).
fn diverging(v: f64) -> RGBColor {
    let t = v.clamp(-1.0, 1.0);
    let (r, g, b) = if t < 0.0 {
        let k = 1.0 + t; // 0 at -1, 1 at 0
        (40.0 + 215.0 * k, 80.0 + 175.0 * k, 200.0 + 55.0 * k)
    } else {
        (255.0 - 55.0 * t, 255.0 - 205.0 * t, 255.0 - 215.0 * t)
    };
    RGBColor(r as u8, g as u8, b as u8)
}

fn colour(v: f64, div: bool) -> RGBColor {
    if div {
        diverging(v)
    } else {
        let c = ViridisRGB.get_color(v.clamp(0.0, 1.0) as f32);
        RGBColor(c.0, c.1, c.2)
    }
}

/// Renders polar panels on a grid with colour bars; returns the CSV text (a 5-deg grid of the
/// values drawn: panel, zenith_deg, azimuth_deg, value).
fn polar_panels(
    path: &Path,
    rows: usize,
    cols: usize,
    layout: &PolarLayout,
    panels: &[Panel],
) -> Result<String, FigureError> {
    let e = draw_err(path);
    let panel = 330u32;
    let any_div = panels.iter().any(|p| p.diverging);
    let any_seq = panels.iter().any(|p| !p.diverging);
    let bar_w = 90 * (u32::from(any_div) + u32::from(any_seq)) + 20;
    let (w, h) = (cols as u32 * panel + bar_w, rows as u32 * panel + 60);
    let root = canvas(path, (w, h))?;
    let (top, body) = root.split_vertically(50);
    top.draw_text(layout.caption, &(FONT, 18).into_text_style(&top), (15, 6))
        .map_err(&e)?;
    top.draw_text(layout.note, &(FONT, 12).into_text_style(&top), (15, 30))
        .map_err(&e)?;
    let (grid, bar) = body.split_horizontally(cols as u32 * panel);
    let cells = grid.split_evenly((rows, cols));
    let mut csv = String::from("panel,zenith_deg,azimuth_deg,value\n");
    let s0 = (layout.screen_deg)(0.0);
    let k = if ((layout.screen_deg)(90.0) - s0).rem_euclid(360.0) == 90.0 {
        1.0
    } else {
        -1.0
    };
    for (cell, p) in cells.iter().zip(panels) {
        let (pw, ph) = cell.dim_in_pixel();
        let radius = (pw.min(ph) as f64 - 70.0) / 2.0;
        let (cx, cy) = (pw as f64 / 2.0, ph as f64 / 2.0 + 12.0);
        let to_screen = |z: f64, az: f64| {
            let a = (layout.screen_deg)(az).to_radians();
            let r = radius * z / 90.0;
            (cx + r * a.cos(), cy - r * a.sin())
        };
        for py in 0..ph {
            for px in 0..pw {
                let (dx, dy) = (px as f64 + 0.5 - cx, cy - (py as f64 + 0.5));
                let r = dx.hypot(dy) / radius;
                if r > 1.0 {
                    continue;
                }
                // Invert the (affine, +-1 slope) screen mapping.
                let screen = dy.atan2(dx).to_degrees();
                let az = ((screen - s0) * k).rem_euclid(360.0);
                let v = (p.value)(r * 90.0, az)?;
                cell.draw_pixel((px as i32, py as i32), &colour(v, p.diverging))
                    .map_err(&e)?;
            }
        }
        for ring in [30.0, 60.0, 90.0] {
            let pts: Vec<(i32, i32)> = (0..=180)
                .map(|k| {
                    let (x, y) = to_screen(ring, k as f64 * 2.0);
                    (x as i32, y as i32)
                })
                .collect();
            cell.draw(&PathElement::new(pts, BLACK.mix(0.35)))
                .map_err(&e)?;
        }
        for (az, label) in layout.labels {
            let a = (layout.screen_deg)(az).to_radians();
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
        if let Some((z, az)) = p.marker {
            let (x, y) = to_screen(z, az);
            cell.draw(&Circle::new(
                (x as i32, y as i32),
                7,
                ShapeStyle::from(&RGBColor(255, 200, 0)).stroke_width(3),
            ))
            .map_err(&e)?;
        }
        cell.draw_text(&p.title, &(FONT, 16).into_text_style(cell), (8, 4))
            .map_err(&e)?;
        for z in (0..=90).step_by(5) {
            for az in (0..360).step_by(5) {
                let _ = writeln!(
                    csv,
                    "{},{z},{az},{:.6}",
                    p.title.replace(',', ";"),
                    (p.value)(z as f64, az as f64)?
                );
            }
        }
    }
    // Colour bars: viridis 0..1 and/or diverging -1..1.
    let (_, bh) = bar.dim_in_pixel();
    let (y0, y1) = (40i32, bh as i32 - 40);
    let mut x0 = 20i32;
    for (div, show, ticks, label) in [
        (
            false,
            any_seq,
            [0.0, 0.25, 0.5, 0.75, 1.0],
            layout.bar_label,
        ),
        (true, any_div, [-1.0, -0.5, 0.0, 0.5, 1.0], "signed"),
    ] {
        if !show {
            continue;
        }
        let (lo, hi) = (ticks[0], ticks[4]);
        for y in y0..y1 {
            let v = hi - (hi - lo) * (y - y0) as f64 / (y1 - y0) as f64;
            for x in x0..x0 + 22 {
                bar.draw_pixel((x, y), &colour(v, div)).map_err(&e)?;
            }
        }
        for v in ticks {
            let y = y0 + ((hi - v) / (hi - lo) * (y1 - y0) as f64) as i32;
            bar.draw_text(
                &format!("{v:.2}"),
                &(FONT, 13).into_text_style(&bar),
                (x0 + 26, y - 6),
            )
            .map_err(&e)?;
        }
        bar.draw_text(label, &(FONT, 14).into_text_style(&bar), (x0 - 10, 12))
            .map_err(&e)?;
        x0 += 90;
    }
    root.present().map_err(&e)?;
    Ok(csv)
}

/// DoLP of a surface for unpolarised light over the view hemisphere at one incidence angle.
fn pbrdf_panel(
    title: String,
    surface: Surface,
    theta_i_deg: f64,
) -> Result<Panel<'static>, FigureError> {
    let diffuse = surface.diffuse(theta_i_deg.to_radians(), Tolerance::absolute(1e-9))?;
    Ok(Panel {
        title,
        value: Box::new(move |tr, phi| {
            let g = Geometry::from_deg(theta_i_deg, tr, phi)?;
            Ok(surface
                .mueller_with(&g, &diffuse)
                .dolp_unpolarized()
                .unwrap_or(0.0))
        }),
        diverging: false,
        marker: None,
    })
}

/// pBRDF maps: relative azimuth phi, 180 deg (the specular plane's forward side) to the right.
fn pbrdf_layout(caption: &str) -> PolarLayout<'_> {
    PolarLayout {
        caption,
        note: "radius: view zenith theta_r (rings at 30, 60, 90 deg); angle: relative azimuth phi, 180 deg (specular) at right",
        screen_deg: |phi| 180.0 - phi,
        labels: [(0.0, "0"), (90.0, "90"), (180.0, "180"), (270.0, "270")],
        bar_label: "DoLP",
    }
}

/// Fig. 3.6: glass DoLP over the view hemisphere, sigma 0.1/0.3/0.5/0.7, theta_i = 60 deg.
fn fig_3_6(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig3_6_glass_dolp_roughness.png");
    let csv = out.join("fig3_6_glass_dolp_roughness.csv");
    let glass = RefractiveIndex::new(1.52, 0.0)?;
    let maps = [0.1, 0.3, 0.5, 0.7]
        .iter()
        .map(|&sigma| {
            pbrdf_panel(
                format!("sigma = {sigma}"),
                Surface::microfacet(glass, sigma, 0.1)?,
                60.0,
            )
        })
        .collect::<Result<Vec<_>, FigureError>>()?;
    let text = polar_panels(
        &png,
        2,
        2,
        &pbrdf_layout("Glass DoLP for unpolarised light, n = 1.52, DHR = 0.1, theta_i = 60 deg"),
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
        maps.push(pbrdf_panel(format!("glass, theta_i = {ti}"), glass, ti)?);
        maps.push(pbrdf_panel(format!("vegetation, theta_i = {ti}"), veg, ti)?);
    }
    let text = polar_panels(
        &png,
        3,
        2,
        &pbrdf_layout("DoLP: glass (sigma 0.1, DHR 0.1) vs vegetation (Eq. 3.19)"),
        &maps,
    )?;
    write_csv(&csv, &text)?;
    Ok(vec![png, csv])
}

/// The clear sky of the sky figures: a stand-in for Meng (2012)'s Table 3.3 (1976 US Standard,
/// rural aerosol at 23 km visibility, single scattering, 450 nm): our single-scattering layer
/// with aerosol optical depth 0.2 at 550 nm, a 440-460 nm band, the sun in the south.
fn sky_spec(sun_zenith_deg: f64) -> Result<SceneSpec, FigureError> {
    Ok(SceneSpec {
        sun_zenith_deg,
        sun_azimuth_deg: 180.0,
        atmosphere: Atmosphere {
            aerosol_optical_depth_550: 0.2,
            ..Atmosphere::default()
        },
        sky: SkyModel::SingleScattering,
        band: Band::flat(440.0, 460.0)?,
        pointing: Pointing {
            altitude_m: 2.0,
            off_nadir_deg: 0.0,
            look_azimuth_deg: 0.0,
            fov_deg: (1.0, 1.0),
        },
    })
}

/// Sky maps: north up, east right (a map seen from above), the sun marked.
fn sky_layout(caption: &str) -> PolarLayout<'_> {
    PolarLayout {
        caption,
        note: "radius: sky zenith (rings at 30, 60, 90 deg); north up, east right; sun circled; S1 > 0: horizontal E-vector",
        screen_deg: |az| 90.0 - az,
        labels: [(0.0, "N"), (90.0, "E"), (180.0, "S"), (270.0, "W")],
        bar_label: "value",
    }
}

fn sky_at(sky: &dyn SkyRadiance, z: f64, az: f64) -> Stokes {
    sky.stokes_from(&polar_model::sky::direction_from_deg(z.max(1e-7), az))
}

/// Fig. 3.10: the sky's S0 (log, three decades), S1/S0, S2/S0 and DoLP, sun at 46 deg zenith.
fn fig_3_10(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig3_10_sky_stokes.png");
    let csv = out.join("fig3_10_sky_stokes.csv");
    let prepared = Prepared::new(&sky_spec(46.0)?, 1e-6)?;
    let sky = prepared.ground_sky();
    let sky = sky.as_ref();
    let mut peak = 0.0f64;
    for z in 0..=90 {
        for az in (0..360).step_by(2) {
            peak = peak.max(sky_at(sky, z as f64, az as f64).0[0]);
        }
    }
    let sun = Some((46.0, 180.0));
    let panels = vec![
        Panel {
            title: "S0: log10(S0 / peak) / 3 + 1".into(),
            value: Box::new(move |z, az| {
                Ok((sky_at(sky, z, az).0[0] / peak).max(1e-300).log10() / 3.0 + 1.0)
            }),
            diverging: false,
            marker: sun,
        },
        Panel {
            title: "S1 / S0".into(),
            value: Box::new(move |z, az| {
                let s = sky_at(sky, z, az).0;
                Ok(s[1] / s[0].max(1e-300))
            }),
            diverging: true,
            marker: sun,
        },
        Panel {
            title: "S2 / S0".into(),
            value: Box::new(move |z, az| {
                let s = sky_at(sky, z, az).0;
                Ok(s[2] / s[0].max(1e-300))
            }),
            diverging: true,
            marker: sun,
        },
        Panel {
            title: "DoLP".into(),
            value: Box::new(move |z, az| Ok(sky_at(sky, z, az).dolp().unwrap_or(0.0))),
            diverging: false,
            marker: sun,
        },
    ];
    let text = polar_panels(
        &png,
        2,
        2,
        &sky_layout("Clear sky, single scattering, 440-460 nm, AOD(550) 0.2, sun at zenith 46 deg"),
        &panels,
    )?;
    write_csv(&csv, &text)?;
    Ok(vec![png, csv])
}

/// Fig. 3.12: sky DoLP with the sun at zenith 20, 40, 60 and 80 deg.
fn fig_3_12(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let png = out.join("fig3_12_sky_dolp_sun.png");
    let csv = out.join("fig3_12_sky_dolp_sun.csv");
    let prepared = [20.0, 40.0, 60.0, 80.0]
        .iter()
        .map(|&z| Ok((z, Prepared::new(&sky_spec(z)?, 1e-6)?)))
        .collect::<Result<Vec<_>, FigureError>>()?;
    let skies: Vec<(f64, Box<dyn SkyRadiance + '_>)> =
        prepared.iter().map(|(z, p)| (*z, p.ground_sky())).collect();
    let panels = skies
        .iter()
        .map(|(sun_z, sky)| {
            let sky = sky.as_ref();
            Panel {
                title: format!("sun zenith {sun_z} deg"),
                value: Box::new(move |z, az| Ok(sky_at(sky, z, az).dolp().unwrap_or(0.0))),
                diverging: false,
                marker: Some((*sun_z, 180.0)),
            }
        })
        .collect::<Vec<_>>();
    let mut layout =
        sky_layout("Sky DoLP as the sun sinks (single scattering, 440-460 nm, AOD(550) 0.2)");
    layout.bar_label = "DoLP";
    let text = polar_panels(&png, 2, 2, &layout, &panels)?;
    write_csv(&csv, &text)?;
    Ok(vec![png, csv])
}

/// Figs. 4.1-4.2 (a reconstruction: Meng (2012) keeps only their titles, "polarization
/// contributions of radiometric sources" i and ii): the direct, skylight and path terms of
/// Eq. 3.24 for black paint and glass seen from 1 km in the solar principal plane, sun at 46
/// deg zenith, against the view angle (positive: looking towards the sun's azimuth, where the
/// glint is at +46 deg). Left: S0 of each term; right: its polarised radiance.
fn fig_4_1_2(out: &Path) -> Result<Vec<PathBuf>, FigureError> {
    let library = MaterialLibrary::builtin();
    let mut written = Vec::new();
    for (fig, name) in [("fig4_1", "black_paint"), ("fig4_2", "glass")] {
        let m = library.get(name).map_err(|e| FigureError::Draw {
            path: out.to_path_buf(),
            message: e.to_string(),
        })?;
        let material = SceneMaterial {
            name: name.into(),
            surface: m.surface()?,
            texture: Texture::None,
        };
        let png = out.join(format!("{fig}_contributions_{name}.png"));
        let csv = out.join(format!("{fig}_contributions_{name}.csv"));
        let mut text = String::from(
            "view_deg,direct_S0,direct_P,skylight_S0,skylight_P,path_S0,path_P,total_S0,total_P,total_dolp\n",
        );
        // (view angle, [S0, P] per term and total)
        let mut rows: Vec<(f64, [[f64; 2]; 4])> = Vec::new();
        for step in -16..=16 {
            let view = step as f64 * 5.0;
            let mut spec = sky_spec(46.0)?;
            spec.band = Band::flat(450.0, 650.0)?;
            spec.atmosphere = Atmosphere::default();
            spec.pointing = Pointing {
                altitude_m: 1000.0,
                off_nadir_deg: view.abs(),
                look_azimuth_deg: if view >= 0.0 { 180.0 } else { 0.0 },
                fov_deg: (1.0, 1.0),
            };
            let terms = Prepared::new(&spec, 1e-4)?.boresight_terms(&material)?;
            let total = Stokes(terms[0].0 + terms[1].0 + terms[2].0);
            let sp = |s: &Stokes| [s.0[0], s.0[1].hypot(s.0[2])];
            let r = [sp(&terms[0]), sp(&terms[1]), sp(&terms[2]), sp(&total)];
            let _ = writeln!(
                text,
                "{view},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.6e},{:.6}",
                r[0][0],
                r[0][1],
                r[1][0],
                r[1][1],
                r[2][0],
                r[2][1],
                r[3][0],
                r[3][1],
                total.dolp().unwrap_or(0.0)
            );
            rows.push((view, r));
        }
        write_csv(&csv, &text)?;
        let e = draw_err(&png);
        let root = canvas(&png, (1300, 560))?;
        let (top, body) = root.split_vertically(40);
        top.draw_text(
            &format!("Contributions at the aperture, {name}: 1 km, 450-650 nm, sun zenith 46 deg, principal plane (+: towards the sun's azimuth)"),
            &(FONT, 17).into_text_style(&top),
            (15, 10),
        )
        .map_err(&e)?;
        let halves = body.split_evenly((1, 2));
        let colours = [
            ("direct sun", RGBColor(214, 95, 14)),
            ("skylight", RGBColor(31, 119, 180)),
            ("path", RGBColor(44, 160, 44)),
            ("total", BLACK),
        ];
        for (k, (half, ylabel)) in halves
            .iter()
            .zip(["S0 (W m^-2 sr^-1)", "polarised radiance sqrt(S1^2 + S2^2)"])
            .enumerate()
        {
            let positive = rows
                .iter()
                .flat_map(|(_, r)| r.iter().map(move |t| t[k]))
                .filter(|v| *v > 0.0);
            let (lo, hi) = positive.fold((f64::INFINITY, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
            let lo = lo.max(hi * 1e-5).max(1e-300);
            let mut chart = ChartBuilder::on(half)
                .margin(15)
                .x_label_area_size(40)
                .y_label_area_size(70)
                .build_cartesian_2d(-80.0..80.0, (lo * 0.8..hi * 1.5).log_scale())
                .map_err(&e)?;
            chart
                .configure_mesh()
                .x_desc("view angle from nadir (deg)")
                .y_desc(ylabel)
                .label_style((FONT, 14))
                .draw()
                .map_err(&e)?;
            for (j, (label, c)) in colours.iter().enumerate() {
                let pts: Vec<(f64, f64)> = rows
                    .iter()
                    .map(|(v, r)| (*v, r[j][k].max(lo * 0.8)))
                    .collect();
                let c = *c;
                chart
                    .draw_series(LineSeries::new(pts, c.stroke_width(2)))
                    .map_err(&e)?
                    .label(*label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                    });
            }
            legend(&mut chart, SeriesLabelPosition::LowerLeft, 14).map_err(&e)?;
        }
        root.present().map_err(&e)?;
        written.push(png.clone());
        written.push(csv);
    }
    Ok(written)
}
