//! The UI's state as JSON for scripts and tests that drive the real window
//! (`polarimeter-gui --state-file FILE`): the run's state and progress, the devices, the live
//! mode, the log's last lines, the notes under the number fields, and where the named
//! controls are on the window (egui points; `pixels_per_point` converts to pixels), so a test
//! can move the real pointer there and click (scripts/gui_real_input.py does, with xdotool
//! under Xvfb).

use eframe::egui;
use serde_json::{json, Value};

/// The key of this frame's places in the context's temporary data.
fn key() -> egui::Id {
    egui::Id::unique("polarimeter-gui state report places")
}

/// Records where the control `name` was drawn this frame.
pub fn place(ui: &egui::Ui, name: &str, response: &egui::Response) {
    let r = response.rect;
    ui.ctx().data_mut(|d| {
        let places: &mut Vec<(String, [f32; 4])> = d.get_temp_mut_or_default(key());
        places.push((name.to_string(), [r.min.x, r.min.y, r.max.x, r.max.y]));
    });
}

/// Forgets the places of the last frame (called before a frame is drawn).
pub fn clear(ctx: &egui::Context) {
    ctx.data_mut(|d| d.remove::<Vec<(String, [f32; 4])>>(key()));
}

/// The places recorded this frame, as a JSON object `{name: [x0, y0, x1, y1]}`.
pub fn places(ctx: &egui::Context) -> Value {
    let places: Vec<(String, [f32; 4])> = ctx.data(|d| d.get_temp(key()).unwrap_or_default());
    let mut m = serde_json::Map::new();
    for (name, r) in places {
        m.insert(name, json!(r));
    }
    Value::Object(m)
}
