//! `polarimeter-gui [--simulate | --rig FILE | hardware flags] [--out DIR] [--plan FILE]
//! [--screenshots DIR]` (`--help` lists them): the plan runner, device panel, live view,
//! planner and rooftop panels.

use clap::Parser;
use eframe::egui;
use polar_gui::engine::Devices;
use polar_gui::{App, Status, Tab, View};
use polar_rig::flags::HardwareFlags;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// `polarimeter-gui`: its flags. The hardware flags are `polarimeter acquire run`'s, from the
/// one definition both programs parse (`polar_rig::flags`).
#[derive(Debug, Parser)]
#[command(
    name = "polarimeter-gui",
    version,
    about = "The polarimeter's desktop application: plan editor and runner, device panel, live view, planner and rooftop panels."
)]
struct GuiArgs {
    /// Drive the simulated devices (the default without a rig file or hardware flags).
    #[arg(long)]
    simulate: bool,
    #[command(flatten)]
    hardware: HardwareFlags,
    /// Base folder of the run directories.
    #[arg(long, default_value = ".")]
    out: PathBuf,
    /// Open this plan (TOML or YAML) in the editor.
    #[arg(long)]
    plan: Option<PathBuf>,
    /// Run the plan, then save PNGs of the live view, the device panel (a snapshot, the live
    /// camera stream, live polarimetry), the planner and rooftop panels into this folder and
    /// quit (CI runs this under Xvfb).
    #[arg(long)]
    screenshots: Option<PathBuf>,
    /// Attach the Station tab to the station at this URL (e.g. http://127.0.0.1:8750) and
    /// open it; the key is read from --key-file.
    #[arg(long, requires = "key_file")]
    station: Option<String>,
    /// The station key's file (`polarimeter station key create --key-out FILE`).
    #[arg(long)]
    key_file: Option<PathBuf>,
    /// The window's size in points, WIDTHxHEIGHT (default 1280x860).
    #[arg(long, value_parser = window_size, default_value = "1280x860")]
    window_size: (f32, f32),
    /// Write the UI's state (run state, progress, devices, live mode, the log's last lines)
    /// and where its controls are to this JSON file five times a second, for scripts and
    /// tests that drive the window (scripts/gui_real_input.py).
    #[arg(long)]
    state_file: Option<PathBuf>,
}

/// `WIDTHxHEIGHT` in points, each 320..=8192.
fn window_size(s: &str) -> Result<(f32, f32), String> {
    let bad = || format!("{s:?}: allowed WIDTHxHEIGHT, each 320 to 8192 (e.g. 900x650)");
    let (w, h) = s.split_once('x').ok_or_else(bad)?;
    let n = |v: &str| -> Result<f32, String> {
        v.trim()
            .parse::<u32>()
            .ok()
            .filter(|v| (320..=8192).contains(v))
            .map(|v| v as f32)
            .ok_or_else(bad)
    };
    Ok((n(w)?, n(h)?))
}

/// How long the screenshot tour may take before it gives up.
const TOUR_LIMIT: Duration = Duration::from_secs(180);

fn main() -> std::process::ExitCode {
    let args = GuiArgs::parse();
    let devices = match args.hardware.hardware() {
        Ok((None, _)) => Devices::Simulated,
        Ok((Some(_), _)) if args.simulate => {
            return usage("--simulate and the hardware flags exclude each other")
        }
        Ok((Some(h), _)) => Devices::Hardware(Box::new(h)),
        Err(e) => return usage(&e.to_string()),
    };
    if let Some(p) = &args.plan {
        match std::fs::metadata(p) {
            Ok(m) if m.is_file() => {}
            Ok(_) => return usage(&format!("--plan {}: not a file", p.display())),
            Err(e) => return usage(&format!("--plan {}: {e}", p.display())),
        }
    }
    let (out, plan, shots) = (args.out, args.plan, args.screenshots);
    let state_file = args.state_file;
    let station = args.station.zip(args.key_file);
    if let Some(d) = &shots {
        if let Err(e) = std::fs::create_dir_all(d) {
            return usage(&format!("--screenshots {}: {e}", d.display()));
        }
    }
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title("polarimeter")
            .with_inner_size([args.window_size.0, args.window_size.1]),
        ..Default::default()
    };
    let report: Arc<Mutex<Vec<Result<PathBuf, String>>>> = Arc::default();
    let tour_report = report.clone();
    let result = eframe::run_native(
        "polarimeter-gui",
        options,
        Box::new(move |cc| {
            let mut app = App::new_on(out, devices, Some(cc.egui_ctx.clone()))?;
            if let Some(p) = plan {
                // As the Open button: TOML or YAML, and its folder for relative paths.
                app.plan_path = p.display().to_string();
                app.open_plan();
            }
            if let Some((url, key)) = &station {
                app.station
                    .attach(url, &key.display().to_string())
                    .map_err(|e| format!("--station {url}: {e}"))?;
                app.set_tab(Tab::Station);
            }
            let tour = shots.map(|dir| Tour::new(dir, tour_report));
            let state = state_file.map(|path| StateFile {
                path,
                written: None,
            });
            Ok(Box::new(Gui { app, tour, state }))
        }),
    );
    if let Err(e) = result {
        eprintln!("polarimeter-gui: {e}");
        return std::process::ExitCode::FAILURE;
    }
    let report = report.lock().map(|r| r.clone()).unwrap_or_default();
    let mut failed = false;
    for r in &report {
        match r {
            Ok(p) => println!("saved {}", p.display()),
            Err(e) => {
                eprintln!("polarimeter-gui: {e}");
                failed = true;
            }
        }
    }
    if failed {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    }
}

fn usage(msg: &str) -> std::process::ExitCode {
    eprintln!("polarimeter-gui: {msg} (see --help)");
    std::process::ExitCode::from(2)
}

/// The window: the app, and the screenshot tour and the state file when asked for.
struct Gui {
    app: App,
    tour: Option<Tour>,
    state: Option<StateFile>,
}

/// `--state-file`: where, and when it was last written.
struct StateFile {
    path: PathBuf,
    written: Option<Instant>,
}

/// How often the state file is written.
const STATE_EVERY: Duration = Duration::from_millis(200);

impl StateFile {
    /// Writes the app's state (atomically: a temporary file renamed over it) if the last
    /// write is older than [`STATE_EVERY`]; keeps the frames coming meanwhile.
    fn write(&mut self, ctx: &egui::Context, app: &App) {
        ctx.request_repaint_after(STATE_EVERY);
        if self.written.is_some_and(|t| t.elapsed() < STATE_EVERY) {
            return;
        }
        self.written = Some(Instant::now());
        let (done, planned) = app.progress();
        let log: Vec<&str> = app.log_lines().collect();
        let tail = &log[log.len().saturating_sub(8)..];
        let screen = ctx.content_rect();
        let v = serde_json::json!({
            "status": app.status().text(),
            "active": app.is_active(),
            "done": done,
            "planned": planned,
            "connected": app.devices().connected,
            "device_pending": app.device_pending(),
            "live": app.live_panel().running().map(|m| m.label()),
            "half_turns": app.live_panel().half_turn().map(|h| h.index),
            "live_frame_shown": app.live_panel().frame().is_some(),
            "log_tail": tail,
            "window": [screen.width(), screen.height()],
            "pixels_per_point": ctx.pixels_per_point(),
            "controls": polar_gui::state_report::places(ctx),
        });
        let tmp = self.path.with_extension("tmp");
        let ok =
            std::fs::write(&tmp, v.to_string()).and_then(|()| std::fs::rename(&tmp, &self.path));
        if let Err(e) = ok {
            eprintln!("polarimeter-gui: --state-file {}: {e}", self.path.display());
        }
    }
}

impl eframe::App for Gui {
    fn logic(&mut self, ctx: &egui::Context, frame: &mut eframe::Frame) {
        eframe::App::logic(&mut self.app, ctx, frame);
    }

    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.app.show(ui);
        if let Some(t) = &mut self.tour {
            t.step(ui.ctx(), &mut self.app);
        }
        if let Some(s) = &mut self.state {
            s.write(ui.ctx(), &self.app);
        }
    }
}

/// The screenshot tour: run the plan, then photograph each tab.
struct Tour {
    dir: PathBuf,
    started: Instant,
    /// The shot being prepared (index into [`SHOTS`]); `SHOTS.len()` once all are asked for.
    next: usize,
    /// Frames drawn since the tab changed (a shot waits for a few, so textures are up).
    settle: u32,
    /// Shots asked for and not yet saved.
    pending: Arc<Mutex<u32>>,
    report: Arc<Mutex<Vec<Result<PathBuf, String>>>>,
    run_started: bool,
    /// Where the device panel's preparation is (see [`Tour::devices_ready`]).
    device_step: u8,
    /// Where the live shots' preparation is (see [`Tour::live_ready`]).
    live_step: u8,
}

/// The live camera shot's exposure, microseconds: long enough that the scene's brightest
/// pixels saturate (about 690 DN at 250 us against a threshold near 3500 DN).
const LIVE_SHOT_EXPOSURE_US: f64 = 1400.0;

/// What a shot needs before it is taken.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Prep {
    /// Nothing more than the finished run.
    Nothing,
    /// Devices connected, the analyzer moved, a snapshot taken.
    Devices,
    /// The camera streaming (live mode) with its frame rate measured.
    LiveCamera,
    /// Live polarimetry with a half turn's estimate shown.
    LivePolarimetry,
}

/// The shots: file name, tab, live view, what is prepared first.
const SHOTS: [(&str, Tab, View, Prep); 6] = [
    ("gui-live-aop.png", Tab::Live, View::Aop, Prep::Nothing),
    ("gui-devices.png", Tab::Devices, View::Aop, Prep::Devices),
    (
        "gui-live-camera.png",
        Tab::Devices,
        View::Aop,
        Prep::LiveCamera,
    ),
    (
        "gui-live-polarimetry.png",
        Tab::Devices,
        View::Aop,
        Prep::LivePolarimetry,
    ),
    ("gui-planner.png", Tab::Planner, View::Aop, Prep::Nothing),
    ("gui-rooftop.png", Tab::Rooftop, View::Aop, Prep::Nothing),
];

impl Tour {
    fn new(dir: PathBuf, report: Arc<Mutex<Vec<Result<PathBuf, String>>>>) -> Tour {
        Tour {
            dir,
            started: Instant::now(),
            next: 0,
            settle: 0,
            pending: Arc::default(),
            report,
            run_started: false,
            device_step: 0,
            live_step: 0,
        }
    }

    fn fail(&self, ctx: &egui::Context, why: String) {
        if let Ok(mut r) = self.report.lock() {
            r.push(Err(why));
        }
        ctx.send_viewport_cmd(egui::ViewportCommand::Close);
    }

    fn step(&mut self, ctx: &egui::Context, app: &mut App) {
        ctx.request_repaint_after(Duration::from_millis(50));
        if self.started.elapsed() > TOUR_LIMIT {
            self.fail(
                ctx,
                format!(
                    "screenshots: gave up after {TOUR_LIMIT:?}; state {:?}",
                    app.status()
                ),
            );
            self.tour_over();
            return;
        }
        if !self.run_started {
            app.start_run();
            self.run_started = true;
            return;
        }
        match app.status() {
            Status::Run(polar_engine::run::RunState::Done) if app.live().is_some() => {}
            Status::Failed(e) => {
                let e = e.clone();
                self.fail(ctx, format!("screenshots: the run failed: {e}"));
                self.tour_over();
                return;
            }
            _ => return,
        }
        if self.next < SHOTS.len() {
            let (name, tab, view, prep) = SHOTS[self.next];
            app.set_tab(tab);
            app.set_view(view);
            let ready = match prep {
                Prep::Nothing => true,
                Prep::Devices => self.devices_ready(app),
                Prep::LiveCamera | Prep::LivePolarimetry => {
                    if let Some(e) = app.live_panel().error() {
                        let e = e.to_string();
                        self.fail(ctx, format!("screenshots: live mode failed: {e}"));
                        self.tour_over();
                        return;
                    }
                    self.live_ready(app, prep)
                }
            };
            if !ready {
                return;
            }
            self.settle += 1;
            if self.settle < 8 {
                return;
            }
            self.settle = 0;
            self.next += 1;
            let path = self.dir.join(name);
            let report = self.report.clone();
            let pending = self.pending.clone();
            if let Ok(mut p) = pending.lock() {
                *p += 1;
            }
            let wake = ctx.clone();
            ctx.request_screenshot(move |image| {
                let r = save_png(&path, &image).map(|()| path.clone());
                if let Ok(mut rep) = report.lock() {
                    rep.push(r);
                }
                if let Ok(mut p) = pending.lock() {
                    *p = p.saturating_sub(1);
                }
                wake.request_repaint();
            });
            return;
        }
        if self.pending.lock().map_or(true, |p| *p == 0) {
            ctx.send_viewport_cmd(egui::ViewportCommand::Close);
            self.tour_over();
        }
    }

    /// For the device panel's shot: connect, turn the analyzer to 60 deg, take a snapshot.
    fn devices_ready(&mut self, app: &mut App) -> bool {
        use polar_gui::engine::Command;
        let d = app.devices().clone();
        // Each command is sent once its precondition holds (a full queue tries again next
        // frame).
        let send = match self.device_step {
            0 => Some(Command::Connect {
                plan_text: app.plan_text.clone(),
                exposure_us: 250.0,
                gain: 0.0,
            }),
            1 if d.connected => Some(Command::MoveAnalyzer { angle_deg: 60.0 }),
            2 if d.analyzer_deg.is_some_and(|a| (a - 60.0).abs() < 0.1) => Some(Command::Snapshot),
            3 if app.snapshot().is_some() => {
                self.device_step = 4;
                None
            }
            _ => None,
        };
        if let Some(cmd) = send {
            if app.device_command(cmd) {
                self.device_step += 1;
            }
        }
        self.device_step >= 4
    }

    /// For the live shots: the camera streaming at a longer exposure (the brightest pixels
    /// saturate and show red) with its frame rate measured; then live polarimetry at the
    /// plan's exposure (the stream stopped first) with its second half turn shown.
    fn live_ready(&mut self, app: &mut App, prep: Prep) -> bool {
        use polar_gui::engine::Command;
        use polar_gui::live::LiveMode;
        let running = app.live_panel().running();
        let idle = running.is_none() && !app.device_pending();
        let step = self.live_step;
        let advance = match (prep, step) {
            (Prep::LiveCamera, 0) => app.start_live(LiveMode::Camera),
            (Prep::LiveCamera, 1) => {
                app.live_panel().frame().is_some()
                    && app.device_command(Command::SetExposure {
                        exposure_us: LIVE_SHOT_EXPOSURE_US,
                    })
            }
            (Prep::LiveCamera, _) => {
                return app
                    .live_panel()
                    .frame()
                    .is_some_and(|f| f.exposure_us == LIVE_SHOT_EXPOSURE_US && f.rate_hz.is_some())
            }
            (Prep::LivePolarimetry, 2) => running.is_none() || app.stop_live(),
            (Prep::LivePolarimetry, 3) => {
                idle && app.device_command(Command::SetExposure { exposure_us: 250.0 })
            }
            (Prep::LivePolarimetry, 4) => idle && app.start_live(LiveMode::Polarimetry),
            (Prep::LivePolarimetry, _) => {
                return app.live_panel().half_turn().is_some_and(|h| h.index >= 1)
            }
            _ => return true,
        };
        if advance {
            self.live_step += 1;
        }
        false
    }

    fn tour_over(&mut self) {
        self.next = usize::MAX;
    }
}

/// Writes `image` (sRGB with alpha) as an 8-bit RGBA PNG.
fn save_png(path: &Path, image: &egui::ColorImage) -> Result<(), String> {
    let [w, h] = image.size;
    let mut rgba = Vec::with_capacity(w * h * 4);
    for c in &image.pixels {
        rgba.extend_from_slice(&c.to_srgba_unmultiplied());
    }
    let file = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc
        .write_header()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    writer
        .write_image_data(&rgba)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    writer
        .finish()
        .map_err(|e| format!("{}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::window_size;

    /// `--window-size` takes WIDTHxHEIGHT in points within 320..=8192 each; anything else is
    /// refused naming the form and the range.
    #[test]
    fn window_sizes_are_checked() {
        assert_eq!(window_size("900x650"), Ok((900.0, 650.0)));
        for bad in ["900", "10x650", "900x9000", "axb", "-900x650"] {
            let e = window_size(bad).unwrap_err();
            assert!(
                e.contains("WIDTHxHEIGHT") && e.contains("320 to 8192"),
                "{bad}: {e}"
            );
        }
    }
}
