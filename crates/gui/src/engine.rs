//! The engine worker: a thread named `engine` with a current-thread tokio runtime and a
//! [`tokio::task::LocalSet`] (the engine's device actors are local tasks). The UI talks to it
//! through two bounded channels and never waits: commands go with `try_send`, replies are
//! read with `try_recv` once per frame.

use crate::connection::{connect, device_command, disconnected, Connected, Out};
pub use crate::forecast::forecast_text;
use crate::forecast::{compute_forecast, resolve_planners, Places};
pub use crate::messages::{Command, DeviceStatus, Devices, LiveProducts, Reply, Snapshot};
use polar_engine::plan::Plan;
use polar_engine::products::Products;
use polar_engine::run::{self, Control, Controller, Event};
use polar_engine::store::RunStore;
use std::path::{Path, PathBuf};
use tokio::sync::mpsc;

/// Capacity of the command channel (UI to engine).
const COMMANDS: usize = 16;
/// Capacity of the reply channel (engine to UI).
const REPLIES: usize = 256;

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
    // Connections made so far: each simulated one draws its own noise stream.
    let mut connections: u64 = 0;
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
                let kept = std::mem::take(&mut settings);
                run_one(plan.clone(), held, &devices, &mut commands, &out, places).await;
                if had {
                    // The run released the devices: connect them again with the panel's
                    // settings, so the user goes on where they were.
                    connections += 1;
                    let link_dir = base_dir.join(".polarimeter-gui-sim");
                    connected =
                        reconnect(&devices, &plan, places, &link_dir, connections, kept, &out)
                            .await;
                    settings = if connected.is_some() {
                        kept
                    } else {
                        (None, None)
                    };
                }
            }
            Command::Connect {
                plan_text,
                exposure_us,
                gain,
            } => {
                if connected.is_none() {
                    let plan = match connect_plan(&plan_text) {
                        Ok((p, note)) => {
                            if let Some(n) = note {
                                out.send(Reply::Log(n)).await;
                            }
                            p
                        }
                        Err(e) => {
                            out.send(Reply::Devices(disconnected(
                                "not connected",
                                "connect failed",
                                Some(e),
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
                    connections += 1;
                    match connect(&devices, &plan, &plan_dir, &link_dir, connections).await {
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

/// The plan Connect builds the devices from: the editor's plan when it parses; else the
/// default plan with the editor's `[simulation]` section, so an error elsewhere in the plan
/// (which Start and the forecast name) does not stop Connect, and a note saying so. An error
/// names the `[simulation]` key and its line.
pub fn connect_plan(plan_text: &str) -> Result<(Plan, Option<String>), String> {
    match Plan::from_toml_str(plan_text) {
        Ok(p) => Ok((p, None)),
        Err(plan_error) => {
            let simulation = Plan::simulation_from_toml_str(plan_text)
                .map_err(|e| format!("the plan's [simulation] section: {e}"))?;
            let mut p = Plan::from_toml_str(crate::DEFAULT_PLAN).map_err(|e| e.to_string())?;
            p.simulation = simulation;
            Ok((
                p,
                Some(format!(
                    "connecting from the plan's [simulation] section; the plan itself does not \
                     load yet: {plan_error}"
                )),
            ))
        }
    }
}

/// Connects `devices` again after a run released them and applies the panel's `kept`
/// exposure and gain; the status says so. `None` (with the error shown) if they do not
/// answer.
async fn reconnect(
    devices: &Devices,
    plan: &Plan,
    places: Places<'_>,
    link_dir: &Path,
    noise_stream: u64,
    kept: (Option<f64>, Option<f64>),
    out: &Out,
) -> Option<Connected> {
    let mut c = match connect(devices, plan, places.plan_dir, link_dir, noise_stream).await {
        Ok(c) => c,
        Err(e) => {
            out.send(Reply::Devices(disconnected(
                "not connected: the run released the devices and they did not answer again",
                "reconnect failed",
                Some(e),
            )))
            .await;
            return None;
        }
    };
    let mut settings = (None, None);
    let mut st = c.status("connected again after the run".into()).await;
    if let Some(exposure_us) = kept.0 {
        st = device_command(&mut c, &Command::SetExposure { exposure_us }, &mut settings)
            .await
            .0;
    }
    if let (Some(gain), None) = (kept.1, &st.error) {
        st = device_command(&mut c, &Command::SetGain { gain }, &mut settings)
            .await
            .0;
    }
    st.last = "connected again after the run, with the panel's settings".into();
    out.send(Reply::Devices(st)).await;
    Some(c)
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
    // A plane the run's `[storage]` did not keep (the essential set leaves out the sigmas of
    // S1, S2 and AoP) shows as NaN: not known from this store, rather than an error.
    let names = store.product_names().map_err(|e| e.to_string())?;
    let optional = |name: &str| {
        if names.iter().any(|n| n == name) {
            read(name)
        } else {
            Ok(vec![
                f32::NAN;
                store.width() as usize * store.height() as usize
            ])
        }
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
        sigma_s1: optional("sigma_s1")?,
        sigma_s2: optional("sigma_s2")?,
        sigma_dolp: read("sigma_dolp")?,
        sigma_aop_rad: optional("sigma_aop_rad")?,
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
            match connect(devices, &plan, plan_dir, &run_dir.join(".sim"), 0).await {
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

    let fut = run::run(&plan, engine_rig, &run_dir, false, link);
    tokio::pin!(fut);
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
