//! The station tab: the GUI attached to an unattended station (docs/STATION.md) over its HTTP
//! API, with a key from a file, as `polarimeter station status` is. A thread polls the station
//! every [`POLL`]: its status (the running item, its phase, progress and pause reason, the
//! queue, the next start, the disk), its health, and the latest S0, DoLP and AoP images (the
//! station's own PNGs). Pause, Resume and Abort act on the station's running item (the key
//! needs the control scope; another key's item, admin).

use eframe::egui;
use polar_station::client::Client;
use serde_json::{json, Value};
use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

/// How often the attached station is asked.
pub const POLL: Duration = Duration::from_secs(1);

/// The images shown: the station's product names.
pub const IMAGES: [&str; 3] = ["s0", "dolp", "aop"];

/// What the poller last heard.
#[derive(Debug, Clone, Default)]
pub struct Heard {
    /// `GET /api/v1/status` (null until answered).
    pub status: Value,
    /// `GET /healthz`.
    pub health: Value,
    /// The latest product images, decoded (name, image).
    pub images: Vec<(String, egui::ColorImage)>,
    /// The last error (unreachable, refused key, a control refused).
    pub error: Option<String>,
    /// Answers received so far.
    pub polls: u64,
}

enum Command {
    Control(&'static str),
}

struct Link {
    heard: mpsc::Receiver<Heard>,
    commands: mpsc::Sender<Command>,
}

/// The station tab's state.
pub struct StationPanel {
    /// The station's URL (`http://127.0.0.1:8750`).
    pub url: String,
    /// The key file (`station key create --key-out`).
    pub key_file: String,
    link: Option<Link>,
    heard: Heard,
    textures: Vec<(String, egui::TextureHandle)>,
    textures_for: u64,
    message: Option<String>,
}

impl Default for StationPanel {
    fn default() -> Self {
        StationPanel::new()
    }
}

fn decode_png(bytes: &[u8]) -> Result<egui::ColorImage, String> {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let size = [info.width as usize, info.height as usize];
    let data = &buf[..info.buffer_size()];
    Ok(match info.color_type {
        png::ColorType::Rgb => egui::ColorImage::from_rgb(size, data),
        png::ColorType::Rgba => egui::ColorImage::from_rgba_unmultiplied(size, data),
        png::ColorType::Grayscale => egui::ColorImage::from_gray(size, data),
        other => return Err(format!("PNG colour type {other:?}")),
    })
}

/// Asks the station once: status, health and (while a run has products) its images.
fn ask(client: &Client, polls: u64) -> Heard {
    let mut h = Heard {
        polls,
        ..Heard::default()
    };
    match client.get("/api/v1/status") {
        Ok(s) => h.status = s,
        Err(e) => h.error = Some(e.to_string()),
    }
    h.health = client.get("/healthz").unwrap_or(Value::Null);
    if h.error.is_none() {
        for name in IMAGES {
            let path = format!("/api/v1/products/latest/{name}.png");
            if let Ok(img) = client
                .get_bytes(&path)
                .and_then(|b| decode_png(&b).map_err(polar_station::error::StationError::Client))
            {
                h.images.push((name.to_string(), img));
            }
        }
    }
    h
}

/// The poller: asks every [`POLL`], and sends each control command at once.
fn poll(client: Client, heard: mpsc::Sender<Heard>, commands: mpsc::Receiver<Command>) {
    let mut polls = 0;
    let mut control_error: Option<String> = None;
    loop {
        polls += 1;
        let mut h = ask(&client, polls);
        if h.error.is_none() {
            h.error = control_error.take();
        }
        if heard.send(h).is_err() {
            return;
        }
        match commands.recv_timeout(POLL) {
            Ok(Command::Control(what)) => {
                if let Err(e) = client.post(&format!("/api/v1/run/{what}"), &json!({})) {
                    control_error = Some(e.to_string());
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => return,
        }
    }
}

impl StationPanel {
    /// Not attached.
    pub fn new() -> StationPanel {
        StationPanel {
            url: "http://127.0.0.1:8750".into(),
            key_file: "station.key".into(),
            link: None,
            heard: Heard::default(),
            textures: Vec::new(),
            textures_for: 0,
            message: None,
        }
    }

    /// Attaches to the station at `url` with the key in `key_file` (read now); an error names
    /// the field.
    pub fn attach(&mut self, url: &str, key_file: &str) -> Result<(), String> {
        self.url = url.to_string();
        self.key_file = key_file.to_string();
        let client =
            Client::new(url, Some(Path::new(key_file)), None).map_err(|e| e.to_string())?;
        let (heard_tx, heard_rx) = mpsc::channel();
        let (cmd_tx, cmd_rx) = mpsc::channel();
        std::thread::Builder::new()
            .name("station-poll".into())
            .spawn(move || poll(client, heard_tx, cmd_rx))
            .map_err(|e| format!("cannot start the poller: {e}"))?;
        self.link = Some(Link {
            heard: heard_rx,
            commands: cmd_tx,
        });
        self.heard = Heard::default();
        self.message = None;
        Ok(())
    }

    /// Whether a station is attached.
    pub fn attached(&self) -> bool {
        self.link.is_some()
    }

    /// What the station last said.
    pub fn heard(&self) -> &Heard {
        &self.heard
    }

    /// Takes what the poller heard since the last frame.
    pub fn update(&mut self) {
        if let Some(link) = &self.link {
            while let Ok(h) = link.heard.try_recv() {
                self.heard = h;
            }
        }
    }

    fn control(&mut self, what: &'static str) {
        if let Some(link) = &self.link {
            let _ = link.commands.send(Command::Control(what));
        }
    }

    fn status_lines(&self) -> Vec<String> {
        let s = &self.heard.status;
        let mut lines = Vec::new();
        let healthy = self.heard.health["ok"].as_bool();
        lines.push(format!(
            "Health: {}",
            match healthy {
                Some(true) => "ok".to_string(),
                Some(false) => format!("NOT healthy: {}", self.heard.health),
                None => "unknown".to_string(),
            }
        ));
        lines.push(format!(
            "Queue: {}, {} waiting",
            if s["queue_running"].as_bool() == Some(true) {
                "running"
            } else {
                "stopped"
            },
            s["queued"].as_u64().unwrap_or(0)
        ));
        let c = &s["current"];
        if c.is_object() {
            lines.push(format!(
                "Item {} ({}): {}{}",
                c["item"]["id"].as_u64().unwrap_or(0),
                c["item"]["name"].as_str().unwrap_or(""),
                c["phase"].as_str().unwrap_or("?"),
                c["pause_reason"]
                    .as_str()
                    .map_or(String::new(), |r| format!(": {r}"))
            ));
            let live = &s["live"];
            if live.as_object().is_some_and(|m| !m.is_empty()) {
                lines.push(format!("Progress: {live}"));
            }
        } else {
            lines.push("No item running".into());
        }
        if let Some(t) = s["next_start"]["time"].as_str() {
            lines.push(format!(
                "Next start: item {} at {t}",
                s["next_start"]["id"].as_u64().unwrap_or(0)
            ));
        }
        if let Some(b) = s["disk_free_bytes"].as_u64() {
            lines.push(format!("Disk free: {:.1} GB", b as f64 / 1e9));
        }
        lines
    }

    /// Draws the tab.
    pub fn show(&mut self, ui: &mut egui::Ui) {
        self.update();
        ui.horizontal(|ui| {
            let l = ui.label("Station URL");
            ui.text_edit_singleline(&mut self.url).labelled_by(l.id);
            let l = ui.label("Key file");
            ui.text_edit_singleline(&mut self.key_file)
                .labelled_by(l.id);
            if ui.button("Attach").clicked() {
                let (url, key) = (self.url.clone(), self.key_file.clone());
                self.message = self.attach(&url, &key).err();
            }
        });
        if let Some(m) = &self.message {
            ui.colored_label(egui::Color32::RED, m);
        }
        if !self.attached() {
            ui.label("Not attached: give the station's URL and a key file, then Attach.");
            return;
        }
        ui.ctx().request_repaint_after(Duration::from_millis(250));
        if let Some(e) = &self.heard.error {
            ui.colored_label(egui::Color32::RED, format!("Station: {e}"));
        }
        for line in self.status_lines() {
            ui.label(line);
        }
        ui.horizontal(|ui| {
            for (label, what) in [
                ("Pause the station's run", "pause"),
                ("Resume the station's run", "resume"),
                ("Abort the station's run", "abort"),
            ] {
                if ui.button(label).clicked() {
                    self.control(what);
                }
            }
        });
        if self.textures_for != self.heard.polls {
            self.textures = self
                .heard
                .images
                .iter()
                .map(|(n, img)| {
                    let t = ui.ctx().load_texture(
                        format!("station {n}"),
                        img.clone(),
                        egui::TextureOptions::NEAREST,
                    );
                    (n.clone(), t)
                })
                .collect();
            self.textures_for = self.heard.polls;
        }
        ui.horizontal_wrapped(|ui| {
            for (n, t) in &self.textures {
                ui.vertical(|ui| {
                    ui.label(format!("Latest {n}"));
                    ui.image((t.id(), egui::vec2(240.0, 240.0 * t.aspect_ratio().recip())));
                });
            }
        });
    }
}
