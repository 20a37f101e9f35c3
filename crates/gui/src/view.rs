//! The live view of a run's products: the views (raw frame, Stokes, DoLP, AoP and their
//! sigma), their false-colour rendering with its scale and histogram, and the pixel probe.

use crate::messages::LiveProducts;
use crate::{colour, rooftop};
use eframe::egui;

/// Bins of the histogram.
pub const HIST_BINS: usize = 48;

/// The image the live view shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum View {
    /// The last stored raw frame, DN.
    Raw,
    /// S0, DN.
    S0,
    /// DoLP.
    Dolp,
    /// AoP as hue with DoLP as saturation.
    Aop,
    /// Predicted sigma of S0, DN.
    SigmaS0,
    /// Predicted sigma of DoLP.
    SigmaDolp,
    /// Predicted sigma of AoP, degrees.
    SigmaAop,
}

impl View {
    /// Every view, in the selector's order.
    pub const ALL: [View; 7] = [
        View::Raw,
        View::S0,
        View::Dolp,
        View::Aop,
        View::SigmaS0,
        View::SigmaDolp,
        View::SigmaAop,
    ];

    /// The selector's label.
    pub fn label(self) -> &'static str {
        match self {
            View::Raw => "Raw frame",
            View::S0 => "S0",
            View::Dolp => "DoLP",
            View::Aop => "AoP",
            View::SigmaS0 => "sigma S0",
            View::SigmaDolp => "sigma DoLP",
            View::SigmaAop => "sigma AoP",
        }
    }

    /// The unit of the view's values.
    pub fn unit(self) -> &'static str {
        match self {
            View::Raw | View::S0 | View::SigmaS0 => "DN",
            View::Dolp | View::SigmaDolp => "",
            View::Aop | View::SigmaAop => "deg",
        }
    }

    /// The view's values of `live` (AoP in degrees), if it has them.
    pub fn values(self, live: &LiveProducts) -> Option<Vec<f32>> {
        let p = &live.products;
        let v = match self {
            View::Raw => live.raw.as_ref()?.iter().map(|&x| f32::from(x)).collect(),
            View::S0 => p.s0.clone(),
            View::Dolp => p.dolp.clone(),
            View::Aop => p.aop_rad.iter().map(|a| a.to_degrees()).collect(),
            View::SigmaS0 => p.sigma_s0.clone(),
            View::SigmaDolp => p.sigma_dolp.clone(),
            View::SigmaAop => p.sigma_aop_rad.iter().map(|a| a.to_degrees()).collect(),
        };
        let n = p.width as usize * p.height as usize;
        (v.len() == n && n > 0).then_some(v)
    }
}

/// A view in false colour: the RGB pixels and the scale they were drawn with.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// RGB, row-major.
    pub rgb: Vec<u8>,
    /// The view's values (for the histogram).
    pub values: Vec<f32>,
    /// Display range of the values.
    pub range: (f32, f32),
    /// For AoP: the DoLP drawn at full saturation.
    pub dolp_full: Option<f32>,
    /// The histogram of the values over `range` ([`HIST_BINS`] bins), counted once.
    pub histogram: Vec<u32>,
    /// How many values are finite.
    pub finite: usize,
}

/// An RGB image decimated so that neither side exceeds `max_side` (the GPU's texture limit):
/// `(rgb, width, height, step)`, every `step`-th pixel of every `step`-th row.
pub fn fit_texture(
    rgb: &[u8],
    width: usize,
    height: usize,
    max_side: usize,
) -> (Vec<u8>, usize, usize, usize) {
    let step = width.max(height).div_ceil(max_side.max(1)).max(1);
    if step == 1 {
        return (rgb.to_vec(), width, height, 1);
    }
    let (w, h) = (width.div_ceil(step), height.div_ceil(step));
    let mut out = Vec::with_capacity(w * h * 3);
    for y in (0..height).step_by(step) {
        for x in (0..width).step_by(step) {
            let i = 3 * (y * width + x);
            out.extend_from_slice(rgb.get(i..i + 3).unwrap_or(&[0, 0, 0]));
        }
    }
    (out, w, h, step)
}

/// Draws `view` of `live` in false colour: scalar views on viridis over their 1st..99th
/// percentile, AoP as hue with DoLP as saturation (full at the 99th percentile of DoLP).
pub fn render(live: &LiveProducts, view: View) -> Option<Rendered> {
    let p = &live.products;
    let values = view.values(live)?;
    let (width, height) = (p.width as usize, p.height as usize);
    let mut rgb = Vec::with_capacity(width * height * 3);
    if view == View::Aop && p.dolp.len() != p.aop_rad.len() {
        return None;
    }
    let (range, dolp_full) = if view == View::Aop {
        let full = colour::robust_range(&p.dolp)
            .map_or(1.0, |(_, hi)| hi)
            .clamp(0.01, 1.0);
        for (a, d) in p.aop_rad.iter().zip(&p.dolp) {
            rgb.extend_from_slice(&colour::aop_dolp(*a, *d, full));
        }
        ((-90.0, 90.0), Some(full))
    } else {
        let range = colour::robust_range(&values).unwrap_or((0.0, 1.0));
        for &v in &values {
            rgb.extend_from_slice(&colour::scalar(v, range.0, range.1));
        }
        (range, None)
    };
    let histogram = colour::histogram(&values, range.0, range.1, HIST_BINS);
    let finite = values.iter().filter(|v| v.is_finite()).count();
    Some(Rendered {
        width,
        height,
        rgb,
        values,
        range,
        dolp_full,
        histogram,
        finite,
    })
}

/// The pixel probe's text for pixel `(x, y)` of `live`: Stokes, DoLP and AoP with their
/// predicted sigma.
pub fn probe_text(live: &LiveProducts, x: usize, y: usize) -> Option<String> {
    let p = &live.products;
    let (w, h) = (p.width as usize, p.height as usize);
    if x >= w || y >= h {
        return None;
    }
    let i = y * w + x;
    let at = |v: &[f32]| v.get(i).copied().unwrap_or(f32::NAN);
    let mut s = format!(
        "pixel ({x}, {y})\n\
         S0 = {:.1} +/- {:.1} DN\n\
         S1 = {:.1} +/- {:.1} DN\n\
         S2 = {:.1} +/- {:.1} DN\n\
         DoLP = {:.4} +/- {:.4}\n\
         AoP = {:.2} +/- {:.2} deg",
        at(&p.s0),
        at(&p.sigma_s0),
        at(&p.s1),
        at(&p.sigma_s1),
        at(&p.s2),
        at(&p.sigma_s2),
        at(&p.dolp),
        at(&p.sigma_dolp),
        at(&p.aop_rad).to_degrees(),
        at(&p.sigma_aop_rad).to_degrees(),
    );
    if let Some(raw) = live.raw.as_ref().and_then(|r| r.get(i)) {
        s.push_str(&format!("\nraw = {raw} DN"));
    }
    Some(s)
}

/// The mean of the finite values (NaN if none).
pub(crate) fn finite_mean(v: &[f32]) -> f64 {
    let (s, n) = v
        .iter()
        .filter(|x| x.is_finite())
        .fold((0.0f64, 0usize), |(s, n), &x| (s + f64::from(x), n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// The colour of a value at fraction `t` of the view's scale.
fn scale_rgb(view: View, t: f32) -> colour::Rgb {
    if view == View::Aop {
        colour::hsv(t, 1.0, colour::AOP_VALUE)
    } else {
        colour::viridis(t)
    }
}

pub(crate) fn colour_bar(ui: &mut egui::Ui, view: View, r: &Rendered) {
    let unit = view.unit();
    ui.label(format!("{} {}", view.label(), unit));
    rooftop::paint_bar(ui, 160.0, |t| scale_rgb(view, t));
    ui.label(format!("{:.4} .. {:.4} {unit}", r.range.0, r.range.1));
    if let Some(full) = r.dolp_full {
        ui.label("saturation: DoLP");
        rooftop::paint_bar(ui, 160.0, |t| colour::hsv(0.0, t, colour::AOP_VALUE));
        ui.label(format!("DoLP 0 .. {full:.3}"));
    }
}

pub(crate) fn histogram(ui: &mut egui::Ui, view: View, r: &Rendered) {
    let (lo, hi) = r.range;
    let counts = &r.histogram;
    let max = counts.iter().copied().max().unwrap_or(0).max(1) as f32;
    let width = ui.available_width().clamp(120.0, 480.0);
    let (rect, _) = ui.allocate_exact_size(egui::vec2(width, 80.0), egui::Sense::hover());
    ui.painter()
        .rect_filled(rect, 0.0, ui.visuals().extreme_bg_color);
    let bw = rect.width() / HIST_BINS as f32;
    for (i, &c) in counts.iter().enumerate() {
        let h = rect.height() * c as f32 / max;
        let bar = egui::Rect::from_min_max(
            egui::pos2(rect.left() + i as f32 * bw, rect.bottom() - h),
            egui::pos2(rect.left() + (i + 1) as f32 * bw - 1.0, rect.bottom()),
        );
        let t = (i as f32 + 0.5) / HIST_BINS as f32;
        ui.painter()
            .rect_filled(bar, 0.0, rooftop::color32(scale_rgb(view, t)));
    }
    ui.label(format!(
        "{lo:.4} .. {hi:.4} {} ({} finite pixels)",
        view.unit(),
        r.finite
    ));
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn live(w: u32, h: u32) -> LiveProducts {
        crate::tests::live(w, h)
    }

    /// Every view renders to `width * height` RGB pixels; the probe names the pixel.
    #[test]
    fn views_render_and_probe() {
        let l = live(8, 4);
        for v in View::ALL {
            let r = render(&l, v).unwrap();
            assert_eq!(r.rgb.len(), 8 * 4 * 3, "{v:?}");
        }
        let t = probe_text(&l, 3, 2).unwrap();
        assert!(t.contains("pixel (3, 2)"), "{t}");
        assert!(t.contains("S0 = 19.0 +/- 2.0 DN"), "{t}");
        assert!(probe_text(&l, 8, 0).is_none());
    }

    /// Images wider or taller than the GPU's texture limit are decimated to fit, keeping
    /// every `step`-th pixel; images that fit are unchanged.
    #[test]
    fn textures_fit_the_gpu_limit() {
        let (w, h) = (10_000, 3);
        let rgb: Vec<u8> = (0..w * h).flat_map(|i| [(i % 251) as u8, 0, 0]).collect();
        let (out, tw, th, step) = fit_texture(&rgb, w, h, 4096);
        assert_eq!((tw, th, step), (3334, 1, 3));
        assert_eq!(out.len(), tw * th * 3);
        // Pixel k of the texture is pixel 3k of the first row.
        assert_eq!(out[3 * 5], rgb[3 * 15]);
        let (same, sw, sh, s1) = fit_texture(&rgb[..30], 10, 1, 4096);
        assert_eq!((sw, sh, s1), (10, 1, 1));
        assert_eq!(same, rgb[..30].to_vec());
    }
}
