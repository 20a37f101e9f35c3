//! The engine worker: a thread named `engine` with a current-thread tokio runtime and a
//! [`tokio::task::LocalSet`] (the engine's device actors are local tasks). The UI talks to it
//! through two bounded channels and never waits: commands go with `try_send`, replies are
//! read with `try_recv` once per frame.

use polar_drivers::any::AnyRotator;
use polar_engine::forecast::{self, Timing};
use polar_engine::plan::Plan;
use polar_engine::products::Products;
use polar_engine::run::{self, Control, Controller, Event, Outcome, Rig, RunState};
use polar_engine::sim::SimRig;
use polar_engine::store::RunStore;
use polar_hal::camera::{Camera, TriggerMode};
use polar_hal::{Analyzer, OnRotator};
use polar_hal::{DeviceError, Rotator};
use polar_rig::{connect_hardware_for, Hardware, HardwareRig};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::mpsc;

/// Capacity of the command channel (UI to engine).
const COMMANDS: usize = 16;
/// Capacity of the reply channel (engine to UI).
const REPLIES: usize = 256;

/// What the UI asks of the engine.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Parse `plan_text` (TOML) and run it: on the connected devices if there are any (the run
    /// takes them over and releases them when it ends), else on a simulated rig started for it.
    Start {
        /// The plan, TOML.
        plan_text: String,
    },
    /// Connect the devices (the simulated rig of `plan_text`'s `[simulation]` section) and set
    /// the camera's exposure and gain.
    Connect {
        /// The plan, TOML.
        plan_text: String,
        /// The exposure to set, microseconds.
        exposure_us: f64,
        /// The gain to set.
        gain: f64,
    },
    /// Disconnect the devices (the simulated rig shuts down).
    Disconnect,
    /// Home the stage (identify, find the datum).
    Home,
    /// Turn the analyzer to `angle_deg` (from the camera's x axis, the stage's approach).
    MoveAnalyzer {
        /// The analyzer angle, degrees.
        angle_deg: f64,
    },
    /// Set the camera's exposure.
    SetExposure {
        /// Exposure, microseconds.
        exposure_us: f64,
    },
    /// Set the camera's gain (in the camera's unit).
    SetGain {
        /// Gain.
        gain: f64,
    },
    /// Take one frame with the current settings.
    Snapshot,
    /// Resolve the plans' relative paths (`simulation.scene`, `simulation.camera`) against
    /// this folder: the folder of the plan file opened in the editor.
    PlanDir(PathBuf),
    /// Pass a control to the run in progress.
    Control(Control),
    /// Parse `plan_text` and compute its forecast.
    Forecast {
        /// The plan, TOML.
        plan_text: String,
    },
    /// Start a live mode on the connected devices (see [`crate::live`]).
    LiveStart {
        /// Live camera or live polarimetry.
        mode: crate::live::LiveMode,
        /// How live polarimetry spins and exposes.
        spin: crate::live::SpinSettings,
    },
    /// Stop the live mode.
    LiveStop,
}

/// The latest products of a run, with the last stored raw frame.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveProducts {
    /// The product slot read.
    pub slot: u64,
    /// The set the slot holds (if known).
    pub set: Option<u64>,
    /// The ten product images.
    pub products: Products,
    /// The last stored frame (row-major, `width * height`), if it could be read.
    pub raw: Option<Vec<u16>>,
    /// That frame's index in the store (it may be a frame of the next set, or a dark).
    pub raw_index: Option<u64>,
}

/// The devices as the engine last saw them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceStatus {
    /// The devices are connected (and idle: no run holds them).
    pub connected: bool,
    /// What is connected (stage and camera models), or why nothing is.
    pub description: String,
    /// The stage angle, degrees.
    pub stage_deg: Option<f64>,
    /// The analyzer angle the stage gives, degrees in [0, 180).
    pub analyzer_deg: Option<f64>,
    /// The exposure the camera applied, microseconds.
    pub exposure_us: Option<f64>,
    /// The gain the camera applied.
    pub gain: Option<f64>,
    /// The camera's exposure range, microseconds.
    pub exposure_range_us: Option<[f64; 2]>,
    /// The camera's gain range.
    pub gain_range: Option<[f64; 2]>,
    /// The last device error (cleared by the next command that succeeds).
    pub error: Option<String>,
    /// The last command carried out, for the log.
    pub last: String,
}

/// One frame taken from the device panel.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixels, DN, row-major.
    pub pixels: Vec<u16>,
    /// The exposure applied, microseconds.
    pub exposure_us: f64,
    /// The camera's frame id.
    pub frame_id: u64,
}

/// What the engine tells the UI.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// The devices' state after a device command.
    Devices(DeviceStatus),
    /// A frame from [`Command::Snapshot`].
    Snapshot(Box<Snapshot>),
    /// A run started into `run_dir`; it takes `planned` frames.
    Started {
        /// The run directory.
        run_dir: PathBuf,
        /// Frames planned (an adaptive plan: its budget).
        planned: u64,
    },
    /// The run's state (from its watch).
    State(RunState),
    /// An engine event.
    Event(Event),
    /// New products after an accepted set.
    Products(Box<LiveProducts>),
    /// The run ended.
    Finished(Result<Outcome, String>),
    /// A command could not be carried out (a bad plan, a rig that did not start).
    Error(String),
    /// A line for the log.
    Log(String),
    /// A forecast (text) or why there is none.
    Forecast(Result<String, String>),
    /// News from a live mode.
    Live(crate::live::LiveUpdate),
}

/// The UI's end of the engine worker.
pub struct EngineHandle {
    commands: mpsc::Sender<Command>,
    replies: mpsc::Receiver<Reply>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl EngineHandle {
    /// Starts the worker thread on the simulated devices; runs go into new directories under
    /// `base_dir`. `wake` is called after each reply (to request a repaint).
    pub fn spawn(
        base_dir: PathBuf,
        wake: Option<Box<dyn Fn() + Send>>,
    ) -> std::io::Result<EngineHandle> {
        Self::spawn_on(base_dir, Devices::Simulated, wake)
    }

    /// Starts the worker thread on `devices`.
    pub fn spawn_on(
        base_dir: PathBuf,
        devices: Devices,
        wake: Option<Box<dyn Fn() + Send>>,
    ) -> std::io::Result<EngineHandle> {
        let (ctx, crx) = mpsc::channel(COMMANDS);
        let (rtx, rrx) = mpsc::channel(REPLIES);
        let thread = std::thread::Builder::new()
            .name("engine".into())
            .spawn(move || {
                let out = Out { tx: rtx, wake };
                let rt = match tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = out.tx.try_send(Reply::Error(format!("tokio runtime: {e}")));
                        return;
                    }
                };
                let local = tokio::task::LocalSet::new();
                local.block_on(&rt, worker(crx, out, base_dir, devices));
            })?;
        Ok(EngineHandle {
            commands: ctx,
            replies: rrx,
            thread: Some(thread),
        })
    }

    /// Sends `cmd` without waiting; `false` if the channel is full or the worker is gone.
    pub fn send(&self, cmd: Command) -> bool {
        self.commands.try_send(cmd).is_ok()
    }

    /// The next reply, if one is waiting.
    pub fn try_recv(&mut self) -> Option<Reply> {
        self.replies.try_recv().ok()
    }
}

impl Drop for EngineHandle {
    fn drop(&mut self) {
        // A run in progress is paused now and detached when the command channel closes
        // (dropping the controller detaches a paused run). Do not wait on the thread: the UI
        // must not block on a device.
        let _ = self.commands.try_send(Command::Control(Control::PauseNow));
        drop(self.thread.take());
    }
}

/// The worker's end of the reply channel.
pub(crate) struct Out {
    tx: mpsc::Sender<Reply>,
    wake: Option<Box<dyn Fn() + Send>>,
}

impl Out {
    pub(crate) async fn send(&self, r: Reply) -> bool {
        let ok = self.tx.send(r).await.is_ok();
        if let Some(w) = &self.wake {
            w();
        }
        ok
    }

    /// Sends `r` if there is room, else drops it (for the run's loop, which must not wait).
    pub(crate) fn note(&self, r: Reply) {
        let _ = self.tx.try_send(r);
        if let Some(w) = &self.wake {
            w();
        }
    }
}

/// The devices the GUI drives.
#[derive(Debug, Clone)]
pub enum Devices {
    /// The simulated rig of each plan's `[simulation]` section (our stage's firmware on a
    /// pseudo-terminal, the model-rendered camera).
    Simulated,
    /// Real devices, as `polarimeter run --rig FILE` or `--port ... --dialect ... --camera ...
    /// --camera-file` (`polar_rig`).
    Hardware(Box<Hardware>),
}

/// Devices connected from the device panel (not held by a run).
pub(crate) struct Connected {
    /// The simulated devices' servers (`None` on hardware).
    sim: Option<SimRig>,
    /// A hardware rig's simulated stage (its port `sim`).
    stage_sim: Option<polar_hil_mocks::serve::SimServer>,
    pub(crate) rig: HardwareRig,
    /// The `[simulation]` section and plan folder the simulated rig was built from.
    built_from: Option<(polar_engine::plan::Simulation, PathBuf)>,
    /// The folder of the simulated stage's pseudo-terminal link (removed on release).
    link_dir: Option<PathBuf>,
}

impl Connected {
    /// Lets the devices go (a simulated rig shuts down).
    async fn release(self) {
        drop(self.rig);
        if let Some(sim) = self.sim {
            sim.shutdown().await;
        }
        if let Some(stage) = self.stage_sim {
            stage.shutdown().await;
        }
        if let Some(d) = self.link_dir {
            // Only if empty: the link is gone with the server.
            let _ = std::fs::remove_dir(d);
        }
    }
}

impl Connected {
    /// The status, reading the stage's position.
    pub(crate) async fn status(&mut self, last: String) -> DeviceStatus {
        let info = self.rig.camera.info().clone();
        let mut st = DeviceStatus {
            connected: true,
            description: format!(
                "stage: {}; camera: {} {} ({}x{})",
                self.rig.analyzer.rotator.info().model,
                info.vendor,
                info.model,
                info.sensor_width,
                info.sensor_height
            ),
            exposure_range_us: Some(info.exposure_range_us),
            gain_range: Some(info.gain_range),
            last,
            ..DeviceStatus::default()
        };
        match self.rig.analyzer.rotator.position_rad().await {
            Ok(stage_rad) => {
                st.stage_deg = Some(stage_rad.to_degrees());
                let psi = (stage_rad - self.rig.analyzer.zero_offset_rad)
                    .rem_euclid(std::f64::consts::PI);
                st.analyzer_deg = Some(psi.to_degrees());
            }
            Err(e) => st.error = Some(e.to_string()),
        }
        st
    }
}

/// Carries out a device command on `c`; the status after it (with the error, if any).
async fn device_command(
    c: &mut Connected,
    cmd: &Command,
    settings: &mut (Option<f64>, Option<f64>),
) -> (DeviceStatus, Option<Snapshot>) {
    let mut snapshot = None;
    let r: Result<String, DeviceError> = async {
        match *cmd {
            Command::Home => {
                c.rig.analyzer.rotator.home().await?;
                Ok("homed".to_string())
            }
            Command::MoveAnalyzer { angle_deg } => {
                let got = c.rig.analyzer.set_angle(angle_deg.to_radians()).await?;
                Ok(format!(
                    "analyzer at {:.3} deg (asked {angle_deg:.3})",
                    got.to_degrees()
                ))
            }
            Command::SetExposure { exposure_us } => {
                let e = c.rig.camera.set_exposure_us(exposure_us).await?;
                settings.0 = Some(e);
                Ok(format!("exposure {e:.1} us"))
            }
            Command::SetGain { gain } => {
                let g = c.rig.camera.set_gain(gain).await?;
                settings.1 = Some(g);
                Ok(format!("gain {g:.2}"))
            }
            Command::Snapshot => {
                let cam = &mut c.rig.camera;
                cam.set_trigger(TriggerMode::Software).await?;
                cam.start().await?;
                let grabbed = async {
                    cam.trigger().await?;
                    cam.grab(Duration::from_secs(5)).await
                }
                .await;
                let stopped = cam.stop().await;
                let f = grabbed?;
                stopped?;
                settings.0 = Some(f.exposure_us);
                settings.1 = Some(f.gain);
                let text = format!(
                    "frame {} ({}x{}), mean {:.1} DN",
                    f.frame_id,
                    f.width,
                    f.height,
                    f.mean()
                );
                snapshot = Some(Snapshot {
                    width: f.width,
                    height: f.height,
                    pixels: f.pixels,
                    exposure_us: f.exposure_us,
                    frame_id: f.frame_id,
                });
                Ok(text)
            }
            _ => Ok(String::new()),
        }
    }
    .await;
    let (last, err) = match r {
        Ok(l) => (l, None),
        Err(e) => (format!("{cmd:?} failed"), Some(e.to_string())),
    };
    let mut st = c.status(last).await;
    st.exposure_us = settings.0;
    st.gain = settings.1;
    if err.is_some() {
        st.error = err;
    }
    (st, snapshot)
}

/// Connects `devices`: on hardware the rig `polarimeter run` would use; simulated, the rig
/// of `plan`'s `[simulation]` section (its pseudo-terminal link under `link_dir`).
async fn connect(
    devices: &Devices,
    plan: &Plan,
    plan_dir: &Path,
    link_dir: &Path,
) -> Result<Connected, String> {
    match devices {
        Devices::Hardware(hw) => {
            let c = connect_hardware_for(hw, plan)
                .await
                .map_err(|e| e.to_string())?;
            Ok(Connected {
                sim: None,
                stage_sim: c.simulator,
                rig: c.rig,
                built_from: None,
                link_dir: None,
            })
        }
        Devices::Simulated => {
            // The GUI starts new runs only (noise stream 0); one connection's frame ids
            // keep counting over its runs, so no draw repeats.
            let (sim, r) = SimRig::start_rig(plan, plan_dir, link_dir, 0)
                .await
                .map_err(|e| format!("simulated rig: {e}"))?;
            let rig = Rig {
                analyzer: OnRotator {
                    rotator: AnyRotator::new(r.analyzer.rotator),
                    zero_offset_rad: r.analyzer.zero_offset_rad,
                    approach: r.analyzer.approach,
                    overshoot_rad: r.analyzer.overshoot_rad,
                },
                camera: r.camera,
                camera_model: r.camera_model,
                sensor: r.sensor,
                illumination: r.illumination,
                target_mask: r.target_mask,
                sun_deg: r.sun_deg,
                devices: r.devices,
            };
            Ok(Connected {
                sim: Some(sim),
                stage_sim: None,
                rig,
                built_from: Some((plan.simulation.clone(), plan_dir.to_path_buf())),
                link_dir: Some(link_dir.to_path_buf()),
            })
        }
    }
}

fn disconnected(description: &str, last: &str, error: Option<String>) -> DeviceStatus {
    DeviceStatus {
        description: description.into(),
        last: last.into(),
        error,
        ..DeviceStatus::default()
    }
}

async fn worker(
    mut commands: mpsc::Receiver<Command>,
    out: Out,
    base_dir: PathBuf,
    devices: Devices,
) {
    let out = std::rc::Rc::new(out);
    let mut connected: Option<Connected> = None;
    // The exposure and gain last applied (the camera trait has no getters).
    let mut settings = (None, None);
    let mut plan_dir = PathBuf::from(".");
    // Commands a live mode left for this loop.
    let mut pending: std::collections::VecDeque<Command> = std::collections::VecDeque::new();
    loop {
        let cmd = match pending.pop_front() {
            Some(c) => c,
            None => match commands.recv().await {
                Some(c) => c,
                None => break,
            },
        };
        match cmd {
            Command::LiveStart { mode, spin } => match connected.as_mut() {
                Some(c) => {
                    let left = crate::live_worker::run_live(
                        c,
                        mode,
                        spin,
                        &mut commands,
                        &out,
                        &mut settings,
                        &plan_dir,
                    )
                    .await;
                    pending.extend(left);
                    let mut st = c.status(format!("{} stopped", mode.label())).await;
                    st.exposure_us = settings.0;
                    st.gain = settings.1;
                    out.send(Reply::Devices(st)).await;
                }
                None => {
                    out.send(Reply::Live(crate::live::LiveUpdate::Stopped {
                        mode,
                        error: Some(format!("{}: connect the devices first", mode.label())),
                    }))
                    .await;
                }
            },
            Command::LiveStop => {
                out.send(Reply::Log("no live mode is running".into())).await;
            }
            Command::PlanDir(d) => plan_dir = d,
            Command::Start { plan_text } => {
                // A plan that does not parse leaves the devices as they are.
                let plan = match Plan::from_toml_str(&plan_text) {
                    Ok(p) => p,
                    Err(e) => {
                        out.send(Reply::Error(e.to_string())).await;
                        continue;
                    }
                };
                let mut held = connected.take();
                // The simulated rig is the plan's world: one built from another
                // `[simulation]` section (edited since Connect) is rebuilt for this plan.
                let stale = held.as_ref().is_some_and(|c| {
                    c.built_from
                        .as_ref()
                        .is_some_and(|(sim, dir)| *sim != plan.simulation || *dir != plan_dir)
                });
                if stale {
                    if let Some(c) = held.take() {
                        out.send(Reply::Log(
                            "the plan's [simulation] section changed since Connect: \
                             rebuilding the simulated devices"
                                .into(),
                        ))
                        .await;
                        c.release().await;
                    }
                }
                let had = held.is_some() || stale;
                let places = Places {
                    base_dir: &base_dir,
                    plan_dir: &plan_dir,
                };
                run_one(plan, held, &devices, &mut commands, &out, places).await;
                if had {
                    settings = (None, None);
                    out.send(Reply::Devices(disconnected(
                        "not connected: the run has released the devices",
                        "run ended",
                        None,
                    )))
                    .await;
                }
            }
            Command::Connect {
                plan_text,
                exposure_us,
                gain,
            } => {
                if connected.is_none() {
                    let plan = match Plan::from_toml_str(&plan_text) {
                        Ok(p) => p,
                        Err(e) => {
                            out.send(Reply::Devices(disconnected(
                                "not connected",
                                "connect failed",
                                Some(format!("the plan (its [simulation] section): {e}")),
                            )))
                            .await;
                            continue;
                        }
                    };
                    let what = match &devices {
                        Devices::Simulated => "the simulated devices".to_string(),
                        Devices::Hardware(hw) => format!("{} and {}", hw.port, hw.camera),
                    };
                    out.send(Reply::Log(format!("connecting {what}"))).await;
                    let link_dir = base_dir.join(".polarimeter-gui-sim");
                    match connect(&devices, &plan, &plan_dir, &link_dir).await {
                        Ok(c) => connected = Some(c),
                        Err(e) => {
                            out.send(Reply::Devices(disconnected(
                                "not connected",
                                "connect failed",
                                Some(e),
                            )))
                            .await;
                            continue;
                        }
                    }
                }
                if let Some(c) = connected.as_mut() {
                    // The camera's own default exposure may saturate the scene: start from the
                    // panel's settings.
                    let (st, _) =
                        device_command(c, &Command::SetExposure { exposure_us }, &mut settings)
                            .await;
                    let st = if st.error.is_some() {
                        st
                    } else {
                        device_command(c, &Command::SetGain { gain }, &mut settings)
                            .await
                            .0
                    };
                    let last = match &st.error {
                        None => "connected".to_string(),
                        Some(_) => "connected; the camera refused a setting".to_string(),
                    };
                    out.send(Reply::Devices(DeviceStatus { last, ..st })).await;
                }
            }
            Command::Disconnect => {
                if let Some(c) = connected.take() {
                    c.release().await;
                }
                settings = (None, None);
                out.send(Reply::Devices(disconnected(
                    "not connected",
                    "disconnected",
                    None,
                )))
                .await;
            }
            Command::Home
            | Command::MoveAnalyzer { .. }
            | Command::SetExposure { .. }
            | Command::SetGain { .. }
            | Command::Snapshot => match connected.as_mut() {
                Some(c) => {
                    let (st, snap) = device_command(c, &cmd, &mut settings).await;
                    out.send(Reply::Devices(st)).await;
                    if let Some(f) = snap {
                        out.send(Reply::Snapshot(Box::new(f))).await;
                    }
                }
                None => {
                    out.send(Reply::Devices(disconnected(
                        "not connected",
                        "",
                        Some(format!("{cmd:?}: connect the devices first")),
                    )))
                    .await;
                }
            },
            Command::Forecast { plan_text } => {
                let mut f = compute_forecast(plan_text, plan_dir.clone()).await;
                if let (Devices::Hardware(_), Ok(text)) = (&devices, &mut f) {
                    text.push_str(
                        "\nnote: on hardware the classes above are the simulated scene's and \
                         the duration the simulated devices'; the frames and sets are the plan's",
                    );
                }
                out.send(Reply::Forecast(f)).await;
            }
            Command::Control(c) => {
                out.send(Reply::Log(format!("{c:?}: no run in progress")))
                    .await;
            }
        }
    }
    if let Some(c) = connected.take() {
        c.release().await;
    }
}

/// The forecast of a plan on the simulated rig, as text (on a blocking thread: a large
/// simulated scene takes a while to build).
pub(crate) async fn compute_forecast(
    plan_text: String,
    plan_dir: PathBuf,
) -> Result<String, String> {
    tokio::task::spawn_blocking(move || forecast_text(&plan_text, &plan_dir))
        .await
        .map_err(|e| format!("forecast: {e}"))?
}

/// The forecast of `plan_text` as text (its relative paths against `plan_dir`).
pub fn forecast_text(plan_text: &str, plan_dir: &Path) -> Result<String, String> {
    let plan = Plan::from_toml_str(plan_text).map_err(|e| e.to_string())?;
    let world = SimRig::world(&plan, plan_dir).map_err(|e| e.to_string())?;
    let timing = Timing::simulated(&plan);
    let f = forecast::forecast(&plan, &world.scene_file, &world.camera_model, &timing)
        .map_err(|e| e.to_string())?;
    let mut s = format!(
        "{}: {} frames ({} darks) in {} sets, about {:.1} s",
        f.kind, f.frames, f.darks, f.sets, f.duration_s
    );
    if let Some(a) = &f.angles_deg {
        let a: Vec<String> = a.iter().map(|d| format!("{d:.1}")).collect();
        let _ = write!(s, "\nangles: {} deg", a.join(", "));
    }
    for c in &f.classes {
        let _ = write!(
            s,
            "\n{}: S0 {:.0} +/- {:.1} DN, DoLP {:.3} +/- {:.3}, AoP {:.1} +/- {:.1} deg",
            c.material, c.s0_dn, c.sigma_s0_dn, c.dolp, c.sigma_dolp, c.aop_deg, c.sigma_aop_deg
        );
    }
    for n in &f.notes {
        let _ = write!(s, "\nnote: {n}");
    }
    Ok(s)
}

/// A new run directory under `base` for `plan`.
fn new_run_dir(base: &Path, plan: &Plan) -> PathBuf {
    let first = run::default_run_dir(base, plan);
    let mut dir = first.clone();
    let mut n = 1;
    while dir.exists() {
        dir = PathBuf::from(format!("{}-{n}", first.display()));
        n += 1;
    }
    dir
}

/// Reads the latest product slot and the last frame of the store in `run_dir`.
fn read_latest(run_dir: &Path) -> Result<LiveProducts, String> {
    let store = RunStore::open(run_dir).map_err(|e| e.to_string())?;
    let slots = store.product_slots().map_err(|e| e.to_string())?;
    let last = slots
        .last()
        .ok_or_else(|| "no products stored yet".to_string())?;
    let read = |name: &str| {
        store
            .read_product(name, last.slot)
            .map_err(|e| e.to_string())
    };
    let products = Products {
        width: store.width(),
        height: store.height(),
        s0: read("s0")?,
        s1: read("s1")?,
        s2: read("s2")?,
        dolp: read("dolp")?,
        aop_rad: read("aop_rad")?,
        sigma_s0: read("sigma_s0")?,
        sigma_s1: read("sigma_s1")?,
        sigma_s2: read("sigma_s2")?,
        sigma_dolp: read("sigma_dolp")?,
        sigma_aop_rad: read("sigma_aop_rad")?,
        saturated: 0,
    };
    let n = store.frame_count();
    let raw_index = n.checked_sub(1);
    let raw = raw_index.and_then(|i| store.read_frame(i).ok());
    Ok(LiveProducts {
        slot: last.slot,
        set: last.set,
        products,
        raw,
        raw_index,
    })
}

/// Where runs go and where a plan's relative paths start.
#[derive(Clone, Copy)]
struct Places<'a> {
    base_dir: &'a Path,
    plan_dir: &'a Path,
}

/// Resolves `plan`'s `from_planner` tables as `acquire run` does, with the models its
/// forecast uses (the plan's simulated scene and camera): a capture's angles, a continuous
/// plan's frames per half turn, exposure and speed. Returns what the planners chose.
fn resolve_planners(plan: &mut Plan, plan_dir: &Path) -> Result<Vec<String>, String> {
    let wants_angles = plan
        .capture
        .as_ref()
        .is_some_and(|c| c.angles_deg.is_none() && c.from_planner.is_some());
    let wants_spin = plan
        .continuous
        .as_ref()
        .is_some_and(|c| c.from_planner.is_some());
    if !wants_angles && !wants_spin {
        return Ok(Vec::new());
    }
    let world = SimRig::world(plan, plan_dir).map_err(|e| e.to_string())?;
    let mut chosen = Vec::new();
    if let Some(c) = plan.capture.clone().filter(|_| wants_angles) {
        if let (Some(fp), Some(&first)) = (&c.from_planner, c.exposure_us.first()) {
            let (angles, _why) =
                forecast::planner_angles(&world.scene_file, &world.camera_model, fp, first)
                    .map_err(|e| e.to_string())?;
            chosen.push(format!("angles from the planner: {angles:.2?} deg"));
            plan.resolve_angles(angles).map_err(|e| e.to_string())?;
        }
    }
    if wants_spin {
        if let Some(choice) =
            polar_engine::continuous_planner::resolve(plan, &world.scene_file, &world.camera_model)
                .map_err(|e| e.to_string())?
        {
            chosen.push(polar_engine::continuous_planner::describe(&choice));
        }
    }
    Ok(chosen)
}

async fn run_one(
    mut plan: Plan,
    held: Option<Connected>,
    devices: &Devices,
    commands: &mut mpsc::Receiver<Command>,
    out: &std::rc::Rc<Out>,
    places: Places<'_>,
) {
    let Places { base_dir, plan_dir } = places;
    match resolve_planners(&mut plan, plan_dir) {
        Ok(chosen) => {
            for line in chosen {
                out.send(Reply::Log(line)).await;
            }
        }
        Err(e) => {
            out.send(Reply::Error(format!("from_planner: {e}"))).await;
            if let Some(c) = held {
                c.release().await;
            }
            return;
        }
    }
    let planned = plan.max_frames().unwrap_or(0);
    let run_dir = new_run_dir(base_dir, &plan);
    let Connected {
        sim,
        rig: engine_rig,
        link_dir,
        ..
    } = match held {
        Some(c) => {
            out.send(Reply::Log(format!(
                "running {:?} on the connected devices",
                plan.name
            )))
            .await;
            c
        }
        None => {
            out.send(Reply::Log(format!(
                "connecting the devices for {:?}",
                plan.name
            )))
            .await;
            match connect(devices, &plan, plan_dir, &run_dir.join(".sim")).await {
                Ok(c) => c,
                Err(e) => {
                    out.send(Reply::Error(e)).await;
                    return;
                }
            }
        }
    };
    out.send(Reply::Started {
        run_dir: run_dir.clone(),
        planned,
    })
    .await;
    let (ctl, link) = run::link();
    let Controller {
        control,
        mut state,
        mut events,
    } = ctl;

    // The state watch.
    let o = out.clone();
    let states = tokio::task::spawn_local(async move {
        loop {
            let s = state.borrow_and_update().clone();
            if !o.send(Reply::State(s)).await {
                break;
            }
            if state.changed().await.is_err() {
                break;
            }
        }
    });
    // Events, and the products of each accepted set.
    let o = out.clone();
    let dir = run_dir.clone();
    let forwarder = tokio::task::spawn_local(async move {
        while let Some(e) = events.recv().await {
            let accepted = matches!(&e, Event::Set { verdict, .. } if verdict.accepted);
            if !o.send(Reply::Event(e)).await {
                break;
            }
            if accepted {
                let d = dir.clone();
                match tokio::task::spawn_blocking(move || read_latest(&d)).await {
                    Ok(Ok(p)) => {
                        o.send(Reply::Products(Box::new(p))).await;
                    }
                    Ok(Err(e)) => {
                        o.send(Reply::Log(format!("reading products: {e}"))).await;
                    }
                    Err(e) => {
                        o.send(Reply::Log(format!("reading products: {e}"))).await;
                    }
                }
            }
        }
    });

    // A spinning plan runs through the continuous loop (the step loop refuses it).
    let mut fut: std::pin::Pin<Box<dyn std::future::Future<Output = _>>> =
        if plan.kind == polar_engine::plan::PlanKind::Continuous {
            Box::pin(run::run_continuous(
                &plan, engine_rig, &run_dir, false, link,
            ))
        } else {
            Box::pin(run::run(&plan, engine_rig, &run_dir, false, link))
        };
    let mut control = Some(control);
    let result = loop {
        tokio::select! {
            r = &mut fut => break r,
            cmd = commands.recv(), if control.is_some() => match cmd {
                Some(Command::Control(c)) => {
                    // Never wait here: the run is not polled while this branch runs.
                    if let Some(tx) = &control {
                        if let Err(e) = tx.try_send(c) {
                            out.note(Reply::Log(format!("{c:?}: not sent to the run: {e}")));
                        }
                    }
                }
                Some(Command::Start { .. }) => {
                    out.note(Reply::Log("a run is already in progress".into()));
                }
                Some(Command::PlanDir(_)) => {
                    out.note(Reply::Log("opening a plan: not while a run is in progress".into()));
                }
                Some(Command::Connect { .. } | Command::Disconnect | Command::Home
                    | Command::MoveAnalyzer { .. } | Command::SetExposure { .. }
                    | Command::SetGain { .. } | Command::Snapshot | Command::LiveStart { .. }
                    | Command::LiveStop) => {
                    out.note(Reply::Log("the run holds the devices: device commands wait until it ends".into()));
                }
                Some(Command::Forecast { .. }) => {
                    // The editor is locked while a run goes; do not hold the run up.
                    out.note(Reply::Forecast(Err("not while a run is in progress".into())));
                }
                None => {
                    // The UI is gone: drop the controller (a paused run detaches).
                    control = None;
                }
            },
        }
    };
    drop(control);
    let _ = forwarder.await;
    let _ = states.await;
    if let Some(sim) = sim {
        sim.shutdown().await;
    }
    if let Some(d) = link_dir {
        let _ = std::fs::remove_dir(d);
    }
    out.send(Reply::Finished(result.map_err(|e| e.to_string())))
        .await;
}
