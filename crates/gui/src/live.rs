//! The device panel's two live modes and what they show.
//!
//! * **Live** ([`LiveMode::Camera`]): the camera streams free-running with the analyzer still,
//!   for aiming and focusing. Each frame comes with its histogram over the camera's full
//!   range, the count of saturated pixels (drawn red in the image) and the frame rate
//!   measured over the last frames ([`FrameStats`], [`RateMeter`]).
//! * **Live polarimetry** ([`LiveMode::Polarimetry`]): the analyzer spins and every half turn
//!   gives a Stokes estimate ([`HalfTurn`]): S0, DoLP and AoP with their predicted sigma.
//!   Each exposure is taken while the analyzer turns, so its measurement row is the span
//!   average of Malus's law, the centre's row with its polarised terms scaled by
//!   `sin(D)/D` for a span of width `D` (`polar_model::span`); [`span_rows`] builds those rows
//!   from the sensor model and [`estimate_half_turn`] feeds them to the engine's estimator
//!   (`polar_engine::products`, the pseudo-inverse of Meng (2012) eq. 2.20 generalised to any
//!   rows) with the camera's noise model for the predicted covariance.
//!
//! The device I/O of both modes runs on the engine's worker (module `live_worker`); this
//! module holds what the UI keeps of it ([`LivePanel`]) and draws it, never waiting.

use crate::fields::{number_field, show_notes};
use crate::messages::{Command, LiveProducts};
use crate::{colour, fit_texture, render, rooftop, Rendered, View};
use eframe::egui;
use polar_engine::products::{self, Dark, NoiseModel, Products, SetGeometry};
use polar_model::sensor::{Camera as CameraModel, SensorModel};
use std::collections::VecDeque;

/// Bins of the live histogram (over the camera's full range, 0 DN to full scale).
pub const LIVE_HIST_BINS: usize = 64;

/// Frames the frame-rate meter averages over.
pub const RATE_WINDOW: usize = 16;

pub use crate::messages::{
    FrameStats, HalfTurn, LiveFrame, LiveMode, LiveUpdate, SpinSettings, FRAMES_RANGE,
    SPEED_RANGE_DEG_PER_S,
};

/// The histogram and saturation count of `pixels` (`bins >= 1`).
pub fn frame_stats(
    pixels: &[u16],
    full_scale_dn: u16,
    saturation_dn: u16,
    bins: usize,
) -> FrameStats {
    let bins = bins.max(1);
    let mut histogram = vec![0u32; bins];
    let (mut lo, mut hi, mut sum, mut saturated) = (u16::MAX, 0u16, 0u64, 0usize);
    let width = u64::from(full_scale_dn) + 1;
    for &p in pixels {
        let b = (u64::from(p) * bins as u64 / width).min(bins as u64 - 1) as usize;
        histogram[b] += 1;
        lo = lo.min(p);
        hi = hi.max(p);
        sum += u64::from(p);
        if p >= saturation_dn {
            saturated += 1;
        }
    }
    FrameStats {
        histogram,
        full_scale_dn,
        saturation_dn,
        saturated,
        min_max_dn: if pixels.is_empty() { (0, 0) } else { (lo, hi) },
        mean_dn: sum as f64 / pixels.len().max(1) as f64,
    }
}

/// The frame rate over the last [`RATE_WINDOW`] frames.
#[derive(Debug, Clone, Default)]
pub struct RateMeter {
    times_s: VecDeque<f64>,
}

impl RateMeter {
    /// A frame arrived at `t_s` (seconds on any steady clock).
    pub fn push(&mut self, t_s: f64) {
        self.times_s.push_back(t_s);
        while self.times_s.len() > RATE_WINDOW {
            self.times_s.pop_front();
        }
    }

    /// Frames per second: intervals over the time they span; `None` before two frames.
    pub fn rate_hz(&self) -> Option<f64> {
        let (first, last) = (self.times_s.front()?, self.times_s.back()?);
        let span = last - first;
        (self.times_s.len() >= 2 && span > 0.0).then(|| (self.times_s.len() - 1) as f64 / span)
    }
}

/// The measurement rows (sensor model: real analyzer, fore-optics) of exposures whose analyzer
/// turns at constant speed over `spans_rad` (start, end). The sensor's row is `A + B cos 2psi
/// + C sin 2psi`; its span average is `A + sinc(D) (B cos 2psi_c + C sin 2psi_c)` with centre
/// `psi_c` and width `D` (`polar_model::span`), so `A` and the modulated part are read off the
/// rows at `psi_c` and `psi_c + 90 deg`.
pub fn span_rows(sensor: &SensorModel, spans_rad: &[(f64, f64)]) -> Result<Vec<[f64; 3]>, String> {
    let mut rows = Vec::with_capacity(spans_rad.len());
    for &(a, b) in spans_rad {
        let c = 0.5 * (a + b);
        let w = sensor
            .intensities_from_stokes(&[c, c + 0.5 * std::f64::consts::PI])
            .map_err(|e| format!("analyzer rows: {e}"))?;
        let f = polar_model::span::sinc(b - a);
        rows.push(std::array::from_fn(|j| {
            let (mean, m) = (0.5 * (w[(0, j)] + w[(1, j)]), 0.5 * (w[(0, j)] - w[(1, j)]));
            mean + f * m
        }));
    }
    Ok(rows)
}

/// The camera's noise model at `gain_db` (EMVA 1288 in DN, as the engine's products use it)
/// and the dark level of an exposure of `exposure_us`, DN.
pub fn noise_and_dark(camera: &CameraModel, gain_db: f64, exposure_us: f64) -> (NoiseModel, f64) {
    let noise = NoiseModel::from_camera(camera, gain_db);
    let dark = noise.dark_level_dn(camera, exposure_us);
    (noise, dark)
}

/// The frames of one half turn in the exposure of `exposure_us` at `gain_db`
/// to Stokes images with their predicted sigma: the span rows of `spans_rad` (analyzer angles)
/// into the engine's estimator.
#[allow(clippy::too_many_arguments)]
pub fn estimate_half_turn(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    spans_rad: &[(f64, f64)],
    sensor: &SensorModel,
    camera: &CameraModel,
    exposure_us: f64,
    gain_db: f64,
) -> Result<Products, String> {
    let rows = span_rows(sensor, spans_rad)?;
    let geometry = SetGeometry::new(&rows).map_err(|e| e.to_string())?;
    let (noise, dark) = noise_and_dark(camera, gain_db, exposure_us);
    products::compute(
        frames,
        width,
        height,
        &geometry,
        &Dark::Scalar(dark as f32),
        &noise,
        0,
    )
    .map_err(|e| e.to_string())
}

/// What the UI keeps of the live modes.
pub struct LivePanel {
    /// The mode running (or starting), if any.
    running: Option<LiveMode>,
    /// Sent a stop, waiting for `Stopped`.
    stopping: bool,
    /// The spin settings the panel edits.
    pub spin: SpinSettings,
    note: Option<String>,
    error: Option<String>,
    frame: Option<LiveFrame>,
    frame_texture: Option<(egui::TextureHandle, u64)>,
    half_turn: Option<HalfTurn>,
    half_turn_live: Option<LiveProducts>,
    view: View,
    rendered: Option<(Rendered, View, u64, egui::TextureHandle)>,
    updates: u64,
}

impl Default for LivePanel {
    fn default() -> Self {
        Self::new()
    }
}

impl LivePanel {
    /// A panel with no mode running.
    pub fn new() -> LivePanel {
        LivePanel {
            running: None,
            stopping: false,
            spin: SpinSettings::default(),
            note: None,
            error: None,
            frame: None,
            frame_texture: None,
            half_turn: None,
            half_turn_live: None,
            view: View::Dolp,
            rendered: None,
            updates: 0,
        }
    }

    /// The mode running, if any (set when its start is sent).
    pub fn running(&self) -> Option<LiveMode> {
        self.running
    }

    /// The last live frame.
    pub fn frame(&self) -> Option<&LiveFrame> {
        self.frame.as_ref()
    }

    /// The last half turn's estimate.
    pub fn half_turn(&self) -> Option<&HalfTurn> {
        self.half_turn.as_ref()
    }

    /// The error that ended the last mode, if any.
    pub fn error(&self) -> Option<&str> {
        self.error.as_deref()
    }

    /// Shows `view` of the half-turn estimate.
    pub fn set_view(&mut self, view: View) {
        self.view = view;
    }

    /// The command that starts `mode` (exposure and gain as the device panel has them); the
    /// panel counts the mode as running from now on.
    pub fn start(&mut self, mode: LiveMode) -> Command {
        self.running = Some(mode);
        self.stopping = false;
        self.error = None;
        self.note = None;
        // The other mode's last image is not this mode's: it goes, so a stopped mode shows
        // its own last output, never an older one.
        match mode {
            LiveMode::Camera => {
                self.half_turn = None;
                self.half_turn_live = None;
            }
            LiveMode::Polarimetry => {
                self.frame = None;
                self.frame_texture = None;
            }
        }
        Command::LiveStart {
            mode,
            spin: self.spin,
        }
    }

    /// The command that stops the running mode.
    pub fn stop(&mut self) -> Command {
        self.stopping = true;
        Command::LiveStop
    }

    /// Whether the spin settings are inside their ranges.
    fn spin_settings_ok(&self) -> bool {
        let s = &self.spin;
        (SPEED_RANGE_DEG_PER_S.0..=SPEED_RANGE_DEG_PER_S.1).contains(&s.speed_deg_per_s)
            && (FRAMES_RANGE.0..=FRAMES_RANGE.1).contains(&s.frames_per_half_turn)
    }

    /// The start command was not sent (the queue was full).
    pub fn start_refused(&mut self) {
        self.running = None;
    }

    /// Takes an update from the worker.
    pub fn on_update(&mut self, u: LiveUpdate) {
        self.updates += 1;
        match u {
            LiveUpdate::Started { mode, note } => {
                self.running = Some(mode);
                self.note = Some(note);
            }
            LiveUpdate::Frame(f) => self.frame = Some(*f),
            LiveUpdate::HalfTurn(h) => {
                let p = &h.products;
                let n = p.width as usize * p.height as usize;
                self.half_turn_live = Some(LiveProducts {
                    slot: h.index,
                    set: Some(h.index),
                    products: h.products.clone(),
                    raw: (h.last_frame.len() == n).then(|| h.last_frame.clone()),
                    raw_index: None,
                });
                self.half_turn = Some(*h);
            }
            LiveUpdate::Stopped { mode: _, error } => {
                self.running = None;
                self.stopping = false;
                self.error = error;
            }
        }
    }

    /// The panel's controls and the live images. `connected` and `idle` (no run, no device
    /// command pending) enable the start buttons; the returned command is for the engine.
    pub fn show(&mut self, ui: &mut egui::Ui, connected: bool, idle: bool) -> Option<Command> {
        let mut cmd = None;
        ui.horizontal(|ui| {
            let can_start = connected && idle && self.running.is_none();
            let r = ui
                .add_enabled(can_start, egui::Button::new("Live"))
                .on_hover_text("stream the camera (the analyzer stays still): aim and focus");
            crate::state_report::place(ui, "Live (camera)", &r);
            if r.clicked() {
                cmd = Some(self.start(LiveMode::Camera));
            }
            // The spin settings below must be in their ranges (their notes say which is not).
            let spin_ok = self.spin_settings_ok();
            let r = ui
                .add_enabled(can_start && spin_ok, egui::Button::new("Live polarimetry"))
                .on_hover_text("spin the analyzer: S0, DoLP and AoP every half turn");
            crate::state_report::place(ui, "Live polarimetry", &r);
            if r.clicked() {
                cmd = Some(self.start(LiveMode::Polarimetry));
            }
            let r = ui.add_enabled(
                self.running.is_some() && !self.stopping,
                egui::Button::new("Stop"),
            );
            crate::state_report::place(ui, "Stop", &r);
            if r.clicked() {
                cmd = Some(self.stop());
            }
            if let Some(m) = self.running {
                ui.spinner();
                ui.label(format!("{} running", m.label()));
            }
        });
        let mut notes = Vec::new();
        ui.horizontal(|ui| {
            let editable = self.running.is_none();
            ui.add_enabled_ui(editable, |ui| {
                number_field(
                    ui,
                    "Spin (deg/s)",
                    &mut self.spin.speed_deg_per_s,
                    SPEED_RANGE_DEG_PER_S,
                    1.0,
                    &mut notes,
                );
                number_field(
                    ui,
                    "Frames per half turn",
                    &mut self.spin.frames_per_half_turn,
                    FRAMES_RANGE,
                    0.1,
                    &mut notes,
                );
                ui.checkbox(
                    &mut self.spin.hardware_trigger,
                    "camera trigger wired to stage",
                );
            });
        });
        show_notes(ui, &notes);
        if let Some(n) = &self.note {
            ui.label(n.as_str());
        }
        if let Some(e) = &self.error {
            ui.colored_label(ui.visuals().error_fg_color, format!("Live: {e}"));
        }
        match self.running {
            Some(LiveMode::Polarimetry) => self.show_half_turn(ui),
            Some(LiveMode::Camera) => self.show_frame(ui),
            None if self.half_turn.is_some() && self.frame.is_none() => self.show_half_turn(ui),
            None => self.show_frame(ui),
        }
        cmd
    }

    fn show_frame(&mut self, ui: &mut egui::Ui) {
        let Some(f) = &self.frame else {
            return;
        };
        let (w, h) = (f.width as usize, f.height as usize);
        if w * h != f.pixels.len() || w * h == 0 {
            return;
        }
        let s = &f.stats;
        ui.label(format!(
            "Live frame {}: {w}x{h}, exposure {:.1} us, {} | min {} max {} mean {:.1} DN | \
             saturated (red) {} px (>= {} DN)",
            f.frame_id,
            f.exposure_us,
            f.rate_hz
                .map_or("frame rate ...".into(), |r| format!("{r:.1} frames/s")),
            s.min_max_dn.0,
            s.min_max_dn.1,
            s.mean_dn,
            s.saturated,
            s.saturation_dn
        ));
        let fresh = matches!(&self.frame_texture, Some((_, id)) if *id == f.frame_id);
        if !fresh {
            let (lo, hi) = (
                f32::from(s.min_max_dn.0),
                f32::from(s.min_max_dn.1).max(1.0),
            );
            let mut rgb = Vec::with_capacity(w * h * 3);
            for &p in &f.pixels {
                if p >= s.saturation_dn {
                    rgb.extend_from_slice(&[255, 0, 0]);
                } else {
                    let v = ((f32::from(p) - lo) / (hi - lo).max(1.0) * 255.0).clamp(0.0, 255.0);
                    rgb.extend_from_slice(&[v as u8; 3]);
                }
            }
            let max_side = ui.ctx().input(|i| i.max_texture_side);
            let (rgb, tw, th, _) = fit_texture(&rgb, w, h, max_side);
            let img = egui::ColorImage::from_rgb([tw, th], &rgb);
            self.frame_texture = Some((
                ui.ctx()
                    .load_texture("live frame", img, egui::TextureOptions::NEAREST),
                f.frame_id,
            ));
        }
        if let Some((t, _)) = &self.frame_texture {
            let scale = ((ui.available_width() - 16.0).max(64.0) / w as f32).min(5.0);
            let size = egui::vec2(w as f32 * scale, h as f32 * scale);
            ui.add(
                egui::Image::from_texture((t.id(), size))
                    .fit_to_exact_size(size)
                    .alt_text("live frame image"),
            );
        }
        ui.label(format!(
            "Histogram 0 .. {} DN (log counts; saturation at {} DN in red)",
            s.full_scale_dn, s.saturation_dn
        ));
        raw_histogram(ui, s);
    }

    fn show_half_turn(&mut self, ui: &mut egui::Ui) {
        let (Some(h), Some(live)) = (&self.half_turn, &self.half_turn_live) else {
            ui.label("Spinning up: the first estimate comes after the first whole half turn.");
            return;
        };
        let p = &h.products;
        let mean = |v: &[f32]| {
            let (s, n) = v
                .iter()
                .filter(|x| x.is_finite())
                .fold((0.0f64, 0usize), |(s, n), &x| (s + f64::from(x), n + 1));
            s / n.max(1) as f64
        };
        ui.label(format!(
            "Half turn {}: {} frames at {:.1} deg/s ({}), {}; {}",
            h.index,
            h.spans_deg.len(),
            h.speed_deg_per_s,
            h.rate_hz
                .map_or("rate ...".into(), |r| format!("{r:.2} half turns/s")),
            h.timing,
            if p.saturated > 0 {
                format!("{} saturated pixels", p.saturated)
            } else {
                "no saturated pixels".into()
            }
        ));
        ui.label(format!(
            "Image means: S0 {:.1} +/- {:.1} DN, DoLP {:.4} +/- {:.4}, AoP {:.2} +/- {:.2} deg \
             (sigma: the mean predicted sigma of a pixel)",
            mean(&p.s0),
            mean(&p.sigma_s0),
            mean(&p.dolp),
            mean(&p.sigma_dolp),
            mean(&p.aop_rad).to_degrees(),
            mean(&p.sigma_aop_rad).to_degrees()
        ));
        ui.horizontal(|ui| {
            ui.label("Show");
            for v in [
                View::S0,
                View::Dolp,
                View::Aop,
                View::SigmaS0,
                View::SigmaDolp,
                View::SigmaAop,
            ] {
                ui.selectable_value(&mut self.view, v, v.label());
            }
        });
        let key = self.updates;
        let fresh = matches!(&self.rendered, Some((_, v, k, _)) if *v == self.view && *k == key);
        if !fresh {
            self.rendered = render(live, self.view).map(|r| {
                let max_side = ui.ctx().input(|i| i.max_texture_side);
                let (rgb, w, hh, _) = fit_texture(&r.rgb, r.width, r.height, max_side);
                let img = egui::ColorImage::from_rgb([w, hh], &rgb);
                let t =
                    ui.ctx()
                        .load_texture("live polarimetry", img, egui::TextureOptions::NEAREST);
                (r, self.view, key, t)
            });
        }
        let Some((r, view, _, t)) = &self.rendered else {
            ui.label(format!("{} is not available", self.view.label()));
            return;
        };
        let scale = ((ui.available_width() - 200.0).max(64.0) / r.width as f32).min(5.0);
        let size = egui::vec2(r.width as f32 * scale, r.height as f32 * scale);
        ui.horizontal_top(|ui| {
            ui.add(
                egui::Image::from_texture((t.id(), size))
                    .fit_to_exact_size(size)
                    .alt_text(format!("live {} image", view.label())),
            );
            ui.vertical(|ui| crate::colour_bar(ui, *view, r));
        });
    }
}

/// The raw histogram: bars on a log scale (a few saturated pixels stay visible), the bins at
/// or above the saturation level red.
fn raw_histogram(ui: &mut egui::Ui, s: &FrameStats) {
    let bins = s.histogram.len().max(1);
    let max = s.histogram.iter().copied().max().unwrap_or(0).max(1) as f32;
    let width = ui.available_width().clamp(120.0, 480.0);
    let (rect, _) = ui.allocate_exact_size(egui::vec2(width, 80.0), egui::Sense::hover());
    ui.painter()
        .rect_filled(rect, 0.0, ui.visuals().extreme_bg_color);
    let bw = rect.width() / bins as f32;
    let step = (f64::from(s.full_scale_dn) + 1.0) / bins as f64;
    for (i, &c) in s.histogram.iter().enumerate() {
        if c == 0 {
            continue;
        }
        let h = rect.height() * (1.0 + c as f32).ln() / (1.0 + max).ln();
        let bar = egui::Rect::from_min_max(
            egui::pos2(rect.left() + i as f32 * bw, rect.bottom() - h),
            egui::pos2(rect.left() + (i + 1) as f32 * bw - 1.0, rect.bottom()),
        );
        let hot = (i as f64 + 1.0) * step > f64::from(s.saturation_dn);
        let c = if hot {
            egui::Color32::from_rgb(230, 40, 40)
        } else {
            rooftop::color32(colour::viridis(0.6))
        };
        ui.painter().rect_filled(bar, 0.0, c);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The live histogram and saturation count of a synthetic 12-bit frame, against counts
    /// made by hand: 4096 DN over 64 bins is 64 DN a bin, so 0 and 63 fall in bin 0, 64 in
    /// bin 1, 4000 and 4095 in bin 62 and 63; with saturation at 4000 DN two pixels are
    /// saturated. Exact: these are integer counts.
    #[test]
    fn histogram_and_saturation_of_a_synthetic_frame() {
        let pixels = [0u16, 63, 64, 1000, 1000, 3999, 4000, 4095];
        let s = frame_stats(&pixels, 4095, 4000, LIVE_HIST_BINS);
        let mut want = vec![0u32; LIVE_HIST_BINS];
        want[0] = 2;
        want[1] = 1;
        want[1000 / 64] = 2;
        want[3999 / 64] = 1; // bin 62, with 4000
        want[62] += 1;
        want[63] = 1;
        assert_eq!(s.histogram, want);
        assert_eq!(s.histogram.iter().sum::<u32>(), pixels.len() as u32);
        assert_eq!(s.saturated, 2);
        assert_eq!(s.min_max_dn, (0, 4095));
        let sum: f64 = pixels.iter().map(|&p| f64::from(p)).sum();
        assert_eq!(s.mean_dn, sum / 8.0);

        // The panel keeps exactly what the frame carried.
        let mut panel = LivePanel::new();
        panel.on_update(LiveUpdate::Frame(Box::new(LiveFrame {
            width: 4,
            height: 2,
            pixels: pixels.to_vec(),
            frame_id: 9,
            exposure_us: 250.0,
            stats: s.clone(),
            rate_hz: Some(30.0),
            frames: 1,
        })));
        let f = panel.frame().unwrap();
        assert_eq!(f.stats.histogram, want);
        assert_eq!(f.stats.saturated, 2);
    }

    /// The frame-rate meter: frames 20 ms apart read 50 frames/s (to rounding, 1e-9); the
    /// window keeps the last 16 frames, so a slower tail is what it reports.
    #[test]
    fn rate_meter_reads_the_frame_interval() {
        let mut m = RateMeter::default();
        assert_eq!(m.rate_hz(), None);
        m.push(1.0);
        assert_eq!(m.rate_hz(), None);
        for k in 1..10 {
            m.push(1.0 + 0.02 * f64::from(k));
        }
        assert!((m.rate_hz().unwrap() - 50.0).abs() < 1e-9);
        let t = 1.18;
        for k in 1..=RATE_WINDOW {
            m.push(t + 0.1 * k as f64);
        }
        assert!((m.rate_hz().unwrap() - 10.0).abs() < 1e-9);
    }

    /// Bad spin settings are refused with the field, its value and the allowed range.
    #[test]
    fn spin_settings_are_checked() {
        let ok = SpinSettings::default();
        assert!(ok.check(250.0).is_ok());
        let e = SpinSettings {
            speed_deg_per_s: 1000.0,
            ..ok
        }
        .check(250.0)
        .unwrap_err();
        assert!(
            e.contains("speed_deg_per_s = 1000") && e.contains("720"),
            "{e}"
        );
        let e = SpinSettings {
            frames_per_half_turn: 2,
            ..ok
        }
        .check(250.0)
        .unwrap_err();
        assert!(e.contains("frames_per_half_turn = 2"), "{e}");
        // 180 deg/s, 8 frames: 125 ms between frames, so at most 62.5 ms of exposure.
        let e = ok.check(70_000.0).unwrap_err();
        assert!(
            e.contains("exposure_us = 70000") && e.contains("62500"),
            "{e}"
        );
    }
}
