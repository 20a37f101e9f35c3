//! `polarimeter-gui`: the plan runner and live view of the polarimeter, on egui.
//!
//! The UI thread never waits on a device: the engine runs on its own thread (named `engine`,
//! a current-thread tokio runtime with a `LocalSet`, see [`engine`]) and the two talk through
//! bounded channels that the UI polls once per frame.
//!
//! The device panel also runs the two live modes ([`live`]): the camera streaming with its
//! histogram, saturation and frame rate, and live polarimetry (the analyzer spinning, a
//! Stokes estimate every half turn); their device loop runs on the same worker.
//!
//! [`App`] holds the whole UI state and draws itself into any [`egui::Ui`], so the tests
//! drive it with `egui_kittest` without a window or a GPU.

#![warn(missing_docs)]

pub mod colour;
mod connection;
mod device_panel;
pub mod engine;
mod fields;
mod forecast;
pub mod live;
mod live_worker;
pub mod messages;
pub mod planner_panel;
pub mod rooftop;
pub mod state_report;
pub mod station_panel;
pub mod view;

pub(crate) use view::{colour_bar, finite_mean, histogram};
pub use view::{fit_texture, probe_text, render, Rendered, View, HIST_BINS};

use eframe::egui;
use engine::{Command, DeviceStatus, EngineHandle, LiveProducts, Reply, Snapshot};
use polar_engine::run::{Control, Event, Outcome, RunState};
use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::Duration;

/// The plan the editor starts with: three sets of four angles on a small simulated scene.
pub const DEFAULT_PLAN: &str = r#"name = "gui capture"
kind = "capture"

[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [250]
repeats = 3
darks_before = 1
darks_after = 0

[simulation]
width = 96
height = 72
seed = 3
stage_deg_per_s = 360
"#;

/// The largest plan file Open reads, bytes.
const MAX_PLAN_BYTES: u64 = 1 << 20;

/// Lines the log keeps.
const LOG_LINES: usize = 500;

/// The least height of the log's view, points (about eight lines).
const LOG_MIN_HEIGHT: f32 = 120.0;

/// Where the UI's idea of the run is.
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    /// No run yet.
    Idle,
    /// A run's state (the last one seen).
    Run(RunState),
    /// The run could not start or failed.
    Failed(String),
    /// A paused run was left to `polarimeter resume`.
    Detached(String),
}

impl Status {
    /// The state label's text: `State: Running`, `State: Paused: reason`, ...
    pub fn text(&self) -> String {
        match self {
            Status::Idle => "State: Idle".into(),
            Status::Run(s) => match s {
                RunState::Starting => "State: Starting".into(),
                RunState::Running => "State: Running".into(),
                RunState::Pausing => "State: Pausing".into(),
                RunState::Paused(r) => format!("State: Paused: {r}"),
                RunState::Aborting => "State: Aborting".into(),
                RunState::Done => "State: Done".into(),
                RunState::Aborted(r) => format!("State: Aborted: {r}"),
            },
            Status::Failed(e) => format!("State: Failed: {e}"),
            Status::Detached(r) => format!("State: Detached: {r}"),
        }
    }
}

/// The central panel's tabs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tab {
    /// The live products of the run.
    Live,
    /// Device control: connect, home, move, exposure and gain, a snapshot.
    Devices,
    /// The planner: SCR and ROC of the optimal angles against the conventional sets.
    Planner,
    /// The rooftop: the sun and the sky's polarisation for a site and time.
    Rooftop,
    /// An unattended station, attached over its API.
    Station,
}

impl Tab {
    /// Every tab, in the selector's order.
    pub const ALL: [Tab; 5] = [
        Tab::Live,
        Tab::Devices,
        Tab::Planner,
        Tab::Rooftop,
        Tab::Station,
    ];

    /// The selector's label.
    pub fn label(self) -> &'static str {
        match self {
            Tab::Live => "Live view",
            Tab::Devices => "Devices",
            Tab::Planner => "Planner",
            Tab::Rooftop => "Rooftop",
            Tab::Station => "Station",
        }
    }
}

/// The last snapshot as the device panel shows it.
struct ShownSnapshot {
    frame: Snapshot,
    texture: Option<egui::TextureHandle>,
    /// Display range, DN.
    range: (f32, f32),
    /// Mean, DN.
    mean: f64,
}

/// The application: the plan editor, the run controls, the log and the live view.
pub struct App {
    engine: EngineHandle,
    /// Real devices (not the simulated rig).
    hardware: bool,
    /// The window is closing: the run is being paused and detached first.
    closing: bool,
    detach_sent: bool,
    /// The plan being edited (TOML).
    pub plan_text: String,
    /// The plan file's path (the Open and Save buttons).
    pub plan_path: String,
    plan_file_note: Option<Result<String, String>>,
    /// The plan text of the last start (a failed start's state goes once the text changes).
    started_text: Option<String>,
    forecast: Option<Result<String, String>>,
    forecast_for: Option<String>,
    forecast_pending: bool,
    status: Status,
    active: bool,
    done: u64,
    planned: u64,
    log: VecDeque<String>,
    run_dir: Option<PathBuf>,
    live: Option<LiveProducts>,
    products_received: u64,
    view: View,
    texture: Option<(egui::TextureHandle, View, u64)>,
    rendered: Option<Rendered>,
    probe: Option<(usize, usize)>,
    tab: Tab,
    devices: DeviceStatus,
    device_pending: bool,
    move_deg: f64,
    exposure_us: f64,
    gain: f64,
    snapshot: Option<ShownSnapshot>,
    planner: planner_panel::PlannerPanel,
    rooftop: rooftop::RooftopPanel,
    live_panel: live::LivePanel,
    /// The station tab (public: `--station` attaches it at start).
    pub station: station_panel::StationPanel,
}

impl App {
    /// A new app whose runs go into new directories under `base_dir`. `ctx`, when given, is
    /// woken by the engine after each reply.
    pub fn new(base_dir: PathBuf, ctx: Option<egui::Context>) -> std::io::Result<App> {
        Self::new_on(base_dir, engine::Devices::Simulated, ctx)
    }

    /// A new app driving `devices`.
    pub fn new_on(
        base_dir: PathBuf,
        devices: engine::Devices,
        ctx: Option<egui::Context>,
    ) -> std::io::Result<App> {
        let wake: Option<Box<dyn Fn() + Send>> =
            ctx.map(|c| Box::new(move || c.request_repaint()) as Box<dyn Fn() + Send>);
        let hardware = matches!(devices, engine::Devices::Hardware(_));
        Ok(App {
            hardware,
            closing: false,
            detach_sent: false,
            engine: EngineHandle::spawn_on(base_dir, devices, wake)?,
            plan_text: DEFAULT_PLAN.to_string(),
            plan_path: String::new(),
            plan_file_note: None,
            started_text: None,
            forecast: None,
            forecast_for: None,
            forecast_pending: false,
            status: Status::Idle,
            active: false,
            done: 0,
            planned: 0,
            log: VecDeque::new(),
            run_dir: None,
            live: None,
            products_received: 0,
            view: View::S0,
            texture: None,
            rendered: None,
            probe: None,
            tab: Tab::Live,
            devices: DeviceStatus {
                description: "not connected".into(),
                ..DeviceStatus::default()
            },
            device_pending: false,
            move_deg: 45.0,
            exposure_us: 250.0,
            gain: 0.0,
            snapshot: None,
            planner: planner_panel::PlannerPanel::new(),
            rooftop: rooftop::RooftopPanel::new(),
            live_panel: live::LivePanel::new(),
            station: station_panel::StationPanel::new(),
        })
    }

    /// The devices as last reported.
    pub fn devices(&self) -> &DeviceStatus {
        &self.devices
    }

    /// The planner panel.
    pub fn planner(&self) -> &planner_panel::PlannerPanel {
        &self.planner
    }

    /// The rooftop panel.
    pub fn rooftop(&self) -> &rooftop::RooftopPanel {
        &self.rooftop
    }

    /// The device panel's live modes.
    pub fn live_panel(&self) -> &live::LivePanel {
        &self.live_panel
    }

    /// Starts a live mode (as the device panel's Live buttons do); `false` if it cannot
    /// start now (no devices, a run or a device command in progress, a mode running, or the
    /// engine's queue full).
    pub fn start_live(&mut self, mode: live::LiveMode) -> bool {
        if self.active
            || !self.devices.connected
            || self.device_pending
            || self.live_panel.running().is_some()
        {
            return false;
        }
        let cmd = self.live_panel.start(mode);
        let ok = self.engine.send(cmd);
        if !ok {
            self.live_panel.start_refused();
        }
        ok
    }

    /// Stops the live mode (as the Stop button does); `false` if the engine's queue is full.
    pub fn stop_live(&mut self) -> bool {
        let cmd = self.live_panel.stop();
        self.engine.send(cmd)
    }

    /// A device command is on its way (the device buttons are disabled until it answers).
    pub fn device_pending(&self) -> bool {
        self.device_pending
    }

    /// The tab shown.
    pub fn tab(&self) -> Tab {
        self.tab
    }

    /// The last snapshot taken from the device panel.
    pub fn snapshot(&self) -> Option<&Snapshot> {
        self.snapshot.as_ref().map(|s| &s.frame)
    }

    /// The run's status.
    pub fn status(&self) -> &Status {
        &self.status
    }

    /// Frames done and planned.
    pub fn progress(&self) -> (u64, u64) {
        (self.done, self.planned)
    }

    /// How many product updates arrived.
    pub fn products_received(&self) -> u64 {
        self.products_received
    }

    /// The latest products.
    pub fn live(&self) -> Option<&LiveProducts> {
        self.live.as_ref()
    }

    /// The log, oldest first.
    pub fn log_lines(&self) -> impl Iterator<Item = &str> {
        self.log.iter().map(String::as_str)
    }

    /// The last forecast (or why there is none).
    pub fn forecast(&self) -> Option<&Result<String, String>> {
        self.forecast.as_ref()
    }

    /// A run is in progress.
    pub fn is_active(&self) -> bool {
        self.active
    }

    /// The current run directory.
    pub fn run_dir(&self) -> Option<&std::path::Path> {
        self.run_dir.as_deref()
    }

    fn say(&mut self, line: impl Into<String>) {
        self.log.push_back(line.into());
        while self.log.len() > LOG_LINES {
            self.log.pop_front();
        }
    }

    /// Takes every waiting reply of the engine (never waits).
    pub fn poll(&mut self) {
        while let Some(r) = self.engine.try_recv() {
            self.on_reply(r);
        }
    }

    fn on_reply(&mut self, r: Reply) {
        match r {
            Reply::Started { run_dir, planned } => {
                if self.devices.connected {
                    self.devices.description = "held by the run".into();
                }
                self.say(format!("run directory {}", run_dir.display()));
                self.run_dir = Some(run_dir);
                self.planned = planned;
            }
            Reply::State(s) => {
                if self.active {
                    self.status = Status::Run(s);
                }
            }
            Reply::Event(e) => self.on_event(e),
            Reply::Products(p) => {
                self.live = Some(*p);
                self.products_received += 1;
            }
            Reply::Finished(r) => {
                self.active = false;
                self.device_pending = false;
                match r {
                    Ok(Outcome::Done(s)) => {
                        self.status = Status::Run(RunState::Done);
                        self.done = self.done.max(s.frames_accepted);
                        self.say(format!(
                            "done: {} frames ({} accepted), {} sets accepted, {} rejected, \
                             {} retries, {:.1} s",
                            s.frames_stored,
                            s.frames_accepted,
                            s.sets_accepted,
                            s.sets_rejected,
                            s.retries,
                            s.elapsed_s
                        ));
                    }
                    Ok(Outcome::Paused(r)) => {
                        self.say(format!("left paused: {r}"));
                        self.status = Status::Detached(r);
                    }
                    Ok(Outcome::Aborted(r)) => {
                        self.say(format!("aborted: {r}"));
                        self.status = Status::Run(RunState::Aborted(r));
                    }
                    Err(e) => {
                        self.say(format!("failed: {e}"));
                        self.status = Status::Failed(e);
                    }
                }
            }
            Reply::Error(e) => {
                self.active = false;
                self.device_pending = false;
                self.say(format!("error: {e}"));
                self.status = Status::Failed(e);
            }
            Reply::Log(l) => self.say(l),
            Reply::Forecast(f) => {
                self.forecast_pending = false;
                self.forecast = Some(f);
            }
            Reply::Devices(d) => {
                self.device_pending = false;
                if !d.last.is_empty() {
                    self.say(format!("devices: {}", d.last));
                }
                if let Some(e) = &d.error {
                    self.say(format!("device error: {e}"));
                }
                if let Some(e) = d.exposure_us {
                    self.exposure_us = e;
                }
                if let Some(g) = d.gain {
                    self.gain = g;
                }
                self.devices = d;
            }
            Reply::Live(u) => {
                match &u {
                    live::LiveUpdate::Started { note, .. } => self.say(note.clone()),
                    live::LiveUpdate::Stopped { mode, error } => match error {
                        Some(e) => self.say(format!("{} stopped: {e}", mode.label())),
                        None => self.say(format!("{} stopped", mode.label())),
                    },
                    live::LiveUpdate::HalfTurn(h) => {
                        let p = &h.products;
                        self.say(format!(
                            "half turn {}: mean DoLP {:.4}",
                            h.index,
                            finite_mean(&p.dolp)
                        ));
                    }
                    live::LiveUpdate::Frame(_) => {}
                }
                self.live_panel.on_update(u);
            }
            Reply::Snapshot(f) => {
                let values: Vec<f32> = f.pixels.iter().map(|&p| f32::from(p)).collect();
                let range = colour::robust_range(&values).unwrap_or((0.0, 1.0));
                let mean =
                    values.iter().map(|&v| f64::from(v)).sum::<f64>() / values.len().max(1) as f64;
                self.snapshot = Some(ShownSnapshot {
                    frame: *f,
                    texture: None,
                    range,
                    mean,
                });
            }
        }
    }

    /// Sends a device command (as the device panel's buttons do); `false` if the engine's
    /// queue is full.
    pub fn device_command(&mut self, cmd: Command) -> bool {
        if self.active {
            // The run holds the devices.
            return false;
        }
        let ok = self.engine.send(cmd);
        if ok {
            self.device_pending = true;
        }
        ok
    }

    fn device(&mut self, cmd: Command) {
        if !self.device_command(cmd) {
            self.say("the engine is busy; try again");
        }
    }

    fn on_event(&mut self, e: Event) {
        match e {
            Event::State(s) => {
                let text = Status::Run(s.clone()).text();
                // Only logged: the state watch (`Reply::State`) is the truth, and events can
                // lag behind it.
                self.say(format!("now {}", text.trim_start_matches("State: ")));
            }
            Event::Progress {
                done,
                planned,
                label,
            } => {
                self.done = done;
                self.planned = planned.max(done);
                self.say(format!("frame {done}/{planned}: {label}"));
            }
            Event::Set {
                set,
                verdict,
                mean_s0,
                mean_dolp,
            } => {
                if verdict.accepted {
                    self.say(format!(
                        "set {set} accepted: mean S0 {mean_s0:.1} DN, DoLP {mean_dolp:.3}"
                    ));
                } else {
                    self.say(format!("set {set} rejected: {}", verdict.reason));
                }
            }
            Event::Decision(d) => self.say(format!("decision: {d}")),
            Event::Retry(m) => self.say(format!("retry: {m}")),
        }
    }

    /// Closing the window during a run: the close is held back, the run pauses at once, and
    /// once it is paused it is detached (resumable with `polarimeter resume RUN_DIR`, nothing
    /// acquired is lost); then the window closes.
    pub fn guard_close(&mut self, ctx: &egui::Context) {
        if ctx.input(|i| i.viewport().close_requested()) && self.active {
            ctx.send_viewport_cmd(egui::ViewportCommand::CancelClose);
            if !self.closing {
                self.closing = true;
                self.say("closing: pausing the run, then leaving it to `polarimeter resume`");
                self.control(Control::PauseNow);
            }
        }
        if self.closing {
            ctx.request_repaint_after(Duration::from_millis(50));
            match (&self.status, self.active) {
                (_, false) => ctx.send_viewport_cmd(egui::ViewportCommand::Close),
                (Status::Run(RunState::Paused(_)), true) if !self.detach_sent => {
                    self.detach_sent = true;
                    self.control(Control::Detach);
                }
                _ => {}
            }
        }
    }

    /// Shows `tab`.
    pub fn set_tab(&mut self, tab: Tab) {
        self.tab = tab;
    }

    /// Shows `view` in the live view.
    pub fn set_view(&mut self, view: View) {
        self.view = view;
    }

    /// Starts the plan in the editor (as the Start button does).
    pub fn start_run(&mut self) {
        if !self.active {
            self.start();
        }
    }

    fn start(&mut self) {
        if self.engine.send(Command::Start {
            plan_text: self.plan_text.clone(),
        }) {
            self.started_text = Some(self.plan_text.clone());
            self.active = true;
            self.status = Status::Run(RunState::Starting);
            self.done = 0;
            self.planned = 0;
            self.live = None;
            self.texture = None;
            self.rendered = None;
            self.say("start");
        } else {
            self.say("the engine is busy; try again");
        }
    }

    fn control(&mut self, c: Control) {
        if !self.engine.send(Command::Control(c)) {
            self.say(format!("{c:?}: the engine is busy; try again"));
        }
    }

    /// Draws the whole application into `ui` (and polls the engine first).
    pub fn show(&mut self, ui: &mut egui::Ui) {
        self.poll();
        state_report::clear(ui.ctx());
        let stale = self.forecast_for.as_deref() != Some(self.plan_text.as_str());
        if !self.active
            && matches!(self.status, Status::Failed(_))
            && self.started_text.as_deref() != Some(self.plan_text.as_str())
        {
            // The plan was edited since a start failed: the failure (kept in the log) no
            // longer describes the plan shown.
            self.status = Status::Idle;
        }
        if !self.active
            && !self.forecast_pending
            && stale
            && self.engine.send(Command::Forecast {
                plan_text: self.plan_text.clone(),
            })
        {
            self.forecast_pending = true;
            self.forecast_for = Some(self.plan_text.clone());
        }
        if self.active
            || self.forecast_pending
            || self.device_pending
            || self.live_panel.running().is_some()
        {
            ui.ctx().request_repaint_after(Duration::from_millis(100));
        }
        egui::Panel::top("controls").show(ui, |ui| self.controls(ui));
        let panel = egui::Panel::left("plan")
            .resizable(true)
            .default_size(380.0)
            .show(ui, |ui| self.plan_panel(ui));
        state_report::place(ui, "plan panel", &panel.response);
        egui::CentralPanel::default_margins().show(ui, |ui| {
            ui.horizontal(|ui| {
                for t in Tab::ALL {
                    let r = ui.selectable_value(&mut self.tab, t, t.label());
                    state_report::place(ui, t.label(), &r);
                }
            });
            ui.separator();
            match self.tab {
                Tab::Live => self.live_view(ui),
                Tab::Devices => self.device_panel(ui),
                Tab::Planner => {
                    // The plan's planner section (target, background, exposure) seeds the
                    // panel; the same text again changes nothing.
                    self.planner.set_plan_text(&self.plan_text);
                    egui::ScrollArea::vertical()
                        .id_salt("planner")
                        .show(ui, |ui| self.planner.show(ui));
                }
                Tab::Rooftop => {
                    egui::ScrollArea::vertical()
                        .id_salt("rooftop")
                        .show(ui, |ui| self.rooftop.show(ui));
                }
                Tab::Station => {
                    egui::ScrollArea::vertical()
                        .id_salt("station")
                        .show(ui, |ui| self.station.show(ui));
                }
            }
        });
    }

    fn controls(&mut self, ui: &mut egui::Ui) {
        let paused = matches!(self.status, Status::Run(RunState::Paused(_)));
        let running = matches!(
            self.status,
            Status::Run(RunState::Running | RunState::Pausing)
        );
        ui.horizontal(|ui| {
            ui.label(match (self.devices.connected, self.hardware) {
                (true, _) => "Devices: connected",
                (false, true) => "Devices: hardware, connected at start",
                (false, false) => "Devices: simulated rig per run",
            });
            let button = |ui: &mut egui::Ui, enabled: bool, name: &str| {
                let r = ui.add_enabled(enabled, egui::Button::new(name));
                state_report::place(ui, name, &r);
                r
            };
            if button(ui, !self.active, "Start").clicked() {
                self.start();
            }
            if button(ui, self.active && running, "Pause").clicked() {
                self.control(Control::Pause);
            }
            if button(ui, self.active && running, "Pause now").clicked() {
                self.control(Control::PauseNow);
            }
            if button(ui, self.active && paused, "Resume").clicked() {
                self.control(Control::Resume);
            }
            if button(ui, self.active && (paused || running), "Abort")
                .on_hover_text(
                    "end the run for good, now (the operation in flight is cancelled; what was \
                     acquired stays)",
                )
                .clicked()
            {
                self.control(Control::Abort);
            }
            if ui
                .add_enabled(self.active && paused, egui::Button::new("Detach"))
                .on_hover_text("leave the paused run to `polarimeter resume RUN_DIR`")
                .clicked()
            {
                self.control(Control::Detach);
            }
            ui.separator();
            ui.label(self.status.text());
        });
        let frac = if self.planned > 0 {
            self.done as f32 / self.planned as f32
        } else {
            0.0
        };
        ui.add(
            egui::ProgressBar::new(frac.clamp(0.0, 1.0))
                .text(format!("{}/{} frames", self.done, self.planned)),
        );
    }

    /// Opens the plan file at [`App::plan_path`] into the editor: TOML as it is, YAML
    /// (`.yaml`, `.yml`) parsed and shown as TOML. Its folder becomes the one the plan's
    /// relative paths (`simulation.scene`, `simulation.camera`) start from.
    pub fn open_plan(&mut self) {
        let path = PathBuf::from(self.plan_path.trim());
        let r = (|| {
            // A plan is a small text file: anything else (a device, a FIFO, a huge file)
            // is refused before it is read, so the UI never waits on it.
            let meta = std::fs::metadata(&path)
                .map_err(|e| format!("plan file {}: {e}", path.display()))?;
            if !meta.is_file() || meta.len() > MAX_PLAN_BYTES {
                return Err(format!(
                    "plan file {}: not a regular file of at most {MAX_PLAN_BYTES} bytes ({} bytes)",
                    path.display(),
                    meta.len()
                ));
            }
            let text = std::fs::read_to_string(&path)
                .map_err(|e| format!("plan file {}: {e}", path.display()))?;
            let yaml = matches!(
                path.extension().and_then(|e| e.to_str()),
                Some("yaml" | "yml")
            );
            if yaml {
                let plan = polar_engine::plan::Plan::from_yaml_str(&text)
                    .map_err(|e| format!("{}: {e}", path.display()))?;
                toml::to_string(&plan).map_err(|e| format!("{}: as TOML: {e}", path.display()))
            } else {
                Ok(text)
            }
        })();
        match r {
            Ok(text) if !self.active => {
                let dir = path
                    .parent()
                    .filter(|p| !p.as_os_str().is_empty())
                    .map_or_else(|| PathBuf::from("."), PathBuf::from);
                if self.engine.send(Command::PlanDir(dir)) {
                    self.plan_text = text;
                    self.say(format!("opened {}", path.display()));
                    self.plan_file_note = Some(Ok(format!("opened {}", path.display())));
                } else {
                    self.plan_file_note = Some(Err("the engine is busy; try again".into()));
                }
            }
            Ok(_) => {
                self.plan_file_note = Some(Err(
                    "a run is in progress: open the plan when it ends".into()
                ))
            }
            Err(e) => self.plan_file_note = Some(Err(e)),
        }
    }

    /// Saves the editor's plan (TOML) to [`App::plan_path`].
    pub fn save_plan(&mut self) {
        let path = PathBuf::from(self.plan_path.trim());
        let r = match path.extension().and_then(|e| e.to_str()) {
            Some("toml") => std::fs::write(&path, &self.plan_text)
                .map(|()| format!("saved {}", path.display()))
                .map_err(|e| format!("plan file {}: {e}", path.display())),
            _ => Err(format!(
                "plan file {:?}: the editor holds TOML: allowed a path ending in .toml",
                self.plan_path
            )),
        };
        if let Ok(m) = &r {
            self.say(m.clone());
        }
        self.plan_file_note = Some(r);
    }

    /// What the last Open or Save did.
    pub fn plan_file_note(&self) -> Option<&Result<String, String>> {
        self.plan_file_note.as_ref()
    }

    /// The left panel: the plan file, the editor, the forecast and the log. It scrolls both
    /// ways as a whole, so at any window size the log's newest lines (done, errors) can be
    /// reached; the editor and the log keep a useful height of their own.
    fn plan_panel(&mut self, ui: &mut egui::Ui) {
        let height = ui.available_height();
        egui::ScrollArea::both()
            .id_salt("plan panel")
            .auto_shrink([false, false])
            .show(ui, |ui| self.plan_panel_inner(ui, height));
    }

    fn plan_panel_inner(&mut self, ui: &mut egui::Ui, height: f32) {
        ui.horizontal(|ui| {
            let l = ui.label("Plan file");
            let path = ui
                .add(
                    egui::TextEdit::singleline(&mut self.plan_path)
                        .hint_text("path/to/plan.toml or .yaml")
                        .desired_width(200.0),
                )
                .labelled_by(l.id);
            if path.changed() {
                // What the last Open or Save said was about another path.
                self.plan_file_note = None;
            }
            if ui
                .add_enabled(!self.active, egui::Button::new("Open"))
                .clicked()
            {
                self.open_plan();
            }
            if ui.button("Save").clicked() {
                self.save_plan();
            }
        });
        match &self.plan_file_note {
            Some(Ok(m)) => {
                ui.label(m.as_str());
            }
            Some(Err(e)) => {
                ui.colored_label(ui.visuals().error_fg_color, e.as_str());
            }
            None => {}
        }
        let label = ui.label("Plan (TOML)");
        egui::ScrollArea::vertical()
            .id_salt("plan editor")
            .max_height((height * 0.4).max(160.0))
            .show(ui, |ui| {
                ui.add_enabled(
                    !self.active,
                    egui::TextEdit::multiline(&mut self.plan_text)
                        .code_editor()
                        .desired_width(f32::INFINITY)
                        .desired_rows(14),
                )
                .labelled_by(label.id);
            });
        ui.separator();
        let r = ui.label("Forecast");
        state_report::place(ui, "Forecast", &r);
        match &self.forecast {
            Some(Ok(f)) => {
                ui.label(f.as_str());
            }
            Some(Err(e)) => {
                ui.colored_label(ui.visuals().error_fg_color, format!("plan error: {e}"));
            }
            None => {
                ui.label("...");
            }
        }
        ui.separator();
        ui.label("Log");
        egui::ScrollArea::vertical()
            .id_salt("log")
            .stick_to_bottom(true)
            .min_scrolled_height(LOG_MIN_HEIGHT)
            .max_height((height * 0.3).max(LOG_MIN_HEIGHT))
            .show(ui, |ui| {
                for l in &self.log {
                    let r = ui.label(egui::RichText::new(l.as_str()).monospace().small());
                    state_report::place(ui, "log last line", &r);
                }
            });
    }

    fn live_view(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            ui.label("Show");
            for v in View::ALL {
                ui.selectable_value(&mut self.view, v, v.label());
            }
        });
        let Some(live) = &self.live else {
            ui.label("No products yet: they appear after the first accepted set.");
            return;
        };
        let key = self.products_received;
        let fresh = matches!(&self.texture, Some((_, v, k)) if *v == self.view && *k == key);
        if !fresh {
            self.rendered = render(live, self.view);
            let max_side = ui.ctx().input(|i| i.max_texture_side);
            self.texture = self.rendered.as_ref().map(|r| {
                // Shown at the full image's size: a decimated texture only loses detail.
                let (rgb, w, h, _) = fit_texture(&r.rgb, r.width, r.height, max_side);
                let img = egui::ColorImage::from_rgb([w, h], &rgb);
                (
                    ui.ctx()
                        .load_texture("live view", img, egui::TextureOptions::NEAREST),
                    self.view,
                    key,
                )
            });
        }
        let (Some((tex, _, _)), Some(r)) = (&self.texture, &self.rendered) else {
            ui.label(format!("{} is not available yet", self.view.label()));
            return;
        };
        if self.view == View::Raw {
            ui.label(format!(
                "the last stored frame (index {}), not necessarily of set {}",
                live.raw_index.map_or("?".into(), |i| i.to_string()),
                live.set.map_or("?".into(), |s| s.to_string()),
            ));
        } else {
            ui.label(format!(
                "set {} (slot {})",
                live.set.map_or("?".into(), |s| s.to_string()),
                live.slot
            ));
        }
        let avail = ui.available_width().max(64.0) - 180.0;
        let scale = (avail.max(64.0) / r.width as f32).min(6.0);
        let size = egui::vec2(r.width as f32 * scale, r.height as f32 * scale);
        let mut probe_line = None;
        ui.horizontal_top(|ui| {
            let resp = ui.add(
                egui::Image::from_texture((tex.id(), size))
                    .fit_to_exact_size(size)
                    .alt_text(format!("{} image", self.view.label()))
                    .sense(egui::Sense::hover()),
            );
            if let Some(pos) = resp.hover_pos() {
                let x = ((pos.x - resp.rect.min.x) / scale).floor();
                let y = ((pos.y - resp.rect.min.y) / scale).floor();
                if x >= 0.0 && y >= 0.0 {
                    self.probe = Some((x as usize, y as usize));
                }
            }
            ui.vertical(|ui| {
                colour_bar(ui, self.view, r);
                ui.separator();
                ui.label("Pixel probe");
                probe_line = self.probe.and_then(|(x, y)| probe_text(live, x, y));
                ui.label(
                    egui::RichText::new(
                        probe_line
                            .as_deref()
                            .unwrap_or("hover over the image")
                            .to_string(),
                    )
                    .monospace(),
                );
            });
        });
        ui.label(format!("Histogram of {}", self.view.label()));
        histogram(ui, self.view, r);
    }
}

impl eframe::App for App {
    fn logic(&mut self, ctx: &egui::Context, _frame: &mut eframe::Frame) {
        // Also while the window is hidden, so the engine's replies never back up.
        self.poll();
        self.guard_close(ctx);
    }

    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.show(ui);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use polar_engine::products::Products;

    pub(crate) fn live(w: u32, h: u32) -> LiveProducts {
        let n = (w * h) as usize;
        let ramp: Vec<f32> = (0..n).map(|i| i as f32).collect();
        LiveProducts {
            slot: 0,
            set: Some(0),
            products: Products {
                width: w,
                height: h,
                s0: ramp.clone(),
                s1: vec![1.0; n],
                s2: vec![0.0; n],
                dolp: vec![0.5; n],
                aop_rad: vec![0.1; n],
                sigma_s0: vec![2.0; n],
                sigma_s1: vec![2.0; n],
                sigma_s2: vec![2.0; n],
                sigma_dolp: vec![0.01; n],
                sigma_aop_rad: vec![0.02; n],
                saturated: 0,
            },
            raw: Some(vec![100; n]),
            raw_index: Some(0),
        }
    }

    /// The status label's texts.
    #[test]
    fn status_texts() {
        assert_eq!(Status::Run(RunState::Running).text(), "State: Running");
        assert_eq!(
            Status::Run(RunState::Paused("x".into())).text(),
            "State: Paused: x"
        );
        assert_eq!(Status::Run(RunState::Done).text(), "State: Done");
    }

    /// The default plan parses and has a forecast.
    #[test]
    fn default_plan_forecast() {
        let f = engine::forecast_text(DEFAULT_PLAN, std::path::Path::new(".")).unwrap();
        assert!(f.contains("13 frames"), "{f}");
    }
}
