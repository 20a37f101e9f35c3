//! The device panel: connect, home, move, exposure and gain, a snapshot, and the live modes
//! ([`crate::live`]).

use crate::fields::{number_field, show_notes};
use crate::messages::Command;
use crate::{colour, fit_texture, live, App, ShownSnapshot};
use eframe::egui;

/// The simulated camera's exposure range, us, shown before a camera has said its own.
const SIM_EXPOSURE_RANGE_US: (f64, f64) = (10.0, 1e7);

impl App {
    pub(crate) fn device_panel(&mut self, ui: &mut egui::Ui) {
        egui::ScrollArea::vertical()
            .id_salt("device panel")
            .show(ui, |ui| self.device_panel_inner(ui));
    }

    fn device_panel_inner(&mut self, ui: &mut egui::Ui) {
        let idle = !self.active;
        let connected = self.devices.connected;
        let live = self.live_panel.running();
        let can = idle && connected && !self.device_pending && live.is_none();
        // Exposure and gain also while the camera streams (aiming and focusing).
        let can_set = idle
            && connected
            && !self.device_pending
            && matches!(live, None | Some(live::LiveMode::Camera));
        ui.horizontal(|ui| {
            let r = ui
                .add_enabled(
                    idle && !connected && !self.device_pending,
                    egui::Button::new("Connect"),
                )
                .on_hover_text(if self.hardware {
                    "connect the stage and the camera given on the command line"
                } else {
                    "start the simulated devices of the plan's [simulation] section"
                });
            crate::state_report::place(ui, "Connect", &r);
            if r.clicked() {
                self.device(Command::Connect {
                    plan_text: self.plan_text.clone(),
                    exposure_us: self.exposure_us,
                    gain: self.gain,
                });
            }
            if ui
                .add_enabled(can, egui::Button::new("Disconnect"))
                .clicked()
            {
                self.device(Command::Disconnect);
            }
            if ui.add_enabled(can, egui::Button::new("Home")).clicked() {
                self.device(Command::Home);
            }
            if self.device_pending {
                ui.spinner();
            }
        });
        let d = &self.devices;
        ui.label(format!(
            "Devices: {}",
            if self.active && d.connected {
                "held by the run"
            } else {
                d.description.as_str()
            }
        ));
        if let (Some(s), Some(a)) = (d.stage_deg, d.analyzer_deg) {
            ui.label(format!("Stage at {s:.3} deg; analyzer at {a:.3} deg"));
        }
        let settings = match (d.exposure_us, d.gain) {
            (Some(e), Some(g)) => format!("Camera: exposure {e:.1} us, gain {g:.2}"),
            (Some(e), None) => format!("Camera: exposure {e:.1} us"),
            _ => "Camera: settings not read yet (set them or take a snapshot)".into(),
        };
        ui.label(settings);
        if let Some(e) = &d.error {
            ui.colored_label(ui.visuals().error_fg_color, format!("Device error: {e}"));
        }
        // Before Connect the camera's ranges are not known: the simulated camera's.
        let (exp_range, gain_range) = (
            d.exposure_range_us
                .map_or(SIM_EXPOSURE_RANGE_US, |r| (r[0], r[1])),
            d.gain_range.map_or((0.0, 48.0), |r| (r[0], r[1])),
        );
        let mut notes = Vec::new();
        egui::Grid::new("device controls")
            .num_columns(3)
            .show(ui, |ui| {
                let ok = number_field(
                    ui,
                    "Analyzer angle (deg)",
                    &mut self.move_deg,
                    (0.0, 180.0),
                    0.5,
                    &mut notes,
                );
                if ui
                    .add_enabled(can && ok, egui::Button::new("Move"))
                    .clicked()
                {
                    self.device(Command::MoveAnalyzer {
                        angle_deg: self.move_deg,
                    });
                }
                ui.end_row();
                let ok = number_field(
                    ui,
                    "Exposure (us)",
                    &mut self.exposure_us,
                    exp_range,
                    5.0,
                    &mut notes,
                );
                if ui
                    .add_enabled(can_set && ok, egui::Button::new("Set exposure"))
                    .clicked()
                {
                    self.device(Command::SetExposure {
                        exposure_us: self.exposure_us,
                    });
                }
                ui.end_row();
                let ok = number_field(ui, "Gain", &mut self.gain, gain_range, 0.1, &mut notes);
                if ui
                    .add_enabled(can_set && ok, egui::Button::new("Set gain"))
                    .clicked()
                {
                    self.device(Command::SetGain { gain: self.gain });
                }
                ui.end_row();
            });
        show_notes(ui, &notes);
        if ui.add_enabled(can, egui::Button::new("Snapshot")).clicked() {
            self.device(Command::Snapshot);
        }
        ui.separator();
        if let Some(cmd) = self
            .live_panel
            .show(ui, connected, idle && !self.device_pending)
        {
            let start = matches!(cmd, Command::LiveStart { .. });
            if !self.engine.send(cmd) {
                if start {
                    self.live_panel.start_refused();
                }
                self.say("the engine is busy; try again");
            }
        }
        if live.is_some()
            || self.live_panel.frame().is_some()
            || self.live_panel.half_turn().is_some()
        {
            return;
        }
        ui.separator();
        let max_side = ui.ctx().input(|i| i.max_texture_side);
        if let Some(ShownSnapshot {
            frame: snap,
            texture: tex,
            range,
            mean,
        }) = &mut self.snapshot
        {
            let mean = *mean;
            let (w, h) = (snap.width as usize, snap.height as usize);
            if tex.is_none() && w * h == snap.pixels.len() && w * h > 0 {
                let mut rgb = Vec::with_capacity(w * h * 3);
                for &p in &snap.pixels {
                    rgb.extend_from_slice(&colour::scalar(f32::from(p), range.0, range.1));
                }
                let (rgb, tw, th, _) = fit_texture(&rgb, w, h, max_side);
                let img = egui::ColorImage::from_rgb([tw, th], &rgb);
                *tex = Some(
                    ui.ctx()
                        .load_texture("snapshot", img, egui::TextureOptions::NEAREST),
                );
            }
            ui.label(format!(
                "Snapshot: frame {}, {}x{}, exposure {:.1} us, mean {mean:.1} DN (viridis {:.0} .. {:.0} DN)",
                snap.frame_id, w, h, snap.exposure_us, range.0, range.1
            ));
            if let Some(t) = tex {
                let scale = ((ui.available_width() - 16.0).max(64.0) / w as f32).min(6.0);
                let size = egui::vec2(w as f32 * scale, h as f32 * scale);
                ui.add(
                    egui::Image::from_texture((t.id(), size))
                        .fit_to_exact_size(size)
                        .alt_text("snapshot image"),
                );
            }
        }
    }
}
