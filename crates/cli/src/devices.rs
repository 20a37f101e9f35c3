//! `devices list`, `devices stage` and `simulate stage`: serial ports, one-shot stage and wheel
//! commands in every dialect of the registry (`polar_drivers::registry`), and the simulators of the
//! simulators' registry (`polar_hil_mocks::sim::SIMULATORS`) on pseudo-terminals.

use crate::commands::CommandError;
use polar_drivers::registry::{self, DeviceKind, Dialect, Identity, Position, DIALECTS};
use polar_hal::{DeviceError, FilterWheel, Rotator};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::{Simulator, SIMULATORS};
use polar_rig::file::{starting_rig, CameraEntry, StageEntry};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// An error of a device command, already worded for the user.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct DevicesError(pub String);

impl From<DeviceError> for DevicesError {
    fn from(e: DeviceError) -> Self {
        DevicesError(format!("{e} [{:?}]", e.kind()))
    }
}

/// The registry's dialect named `name`, or an error naming `--dialect`, the value and the
/// dialects allowed.
pub fn dialect(name: &str) -> Result<&'static Dialect, DevicesError> {
    registry::find(name).ok_or_else(|| {
        DevicesError(format!(
            "--dialect = {name:?} is invalid: allowed {}",
            registry::names()
        ))
    })
}

/// What `devices stage` does.
#[derive(Debug, Clone, PartialEq)]
pub enum StageAction {
    /// Identify (without homing).
    Info,
    /// Home.
    Home,
    /// Move a rotator to an angle, degrees.
    Move {
        /// The angle, degrees.
        angle_deg: f64,
    },
    /// Select a wheel's or slider's slot (from 0).
    Slot {
        /// The slot.
        slot: usize,
    },
    /// Read the position (rotator: degrees; wheel: slot).
    Position,
}

/// The serial ports the system has, with their stable `/dev/serial/by-id` names, and (with
/// `simulate`) the simulated devices running and on offer.
pub fn list(simulate: bool) -> Result<Value, DevicesError> {
    let by_id = stable_names(Path::new("/dev/serial/by-id"));
    let ports = tokio_serial::available_ports()
        .map_err(|e| DevicesError(format!("cannot list serial ports: {e}")))?;
    let ports: Vec<Value> = ports
        .into_iter()
        .map(|p| {
            let usb = match &p.port_type {
                tokio_serial::SerialPortType::UsbPort(u) => json!({
                    "vid": format!("{:04x}", u.vid),
                    "pid": format!("{:04x}", u.pid),
                    "serial_number": u.serial_number,
                    "manufacturer": u.manufacturer,
                    "product": u.product,
                }),
                _ => Value::Null,
            };
            let stable: Vec<&String> = by_id
                .iter()
                .filter(|(_, target)| target.as_os_str() == p.port_name.as_str())
                .map(|(link, _)| link)
                .collect();
            json!({ "port": p.port_name, "stable": stable, "usb": usb })
        })
        .collect();
    let mut out = json!({ "ports": ports });
    if simulate {
        let running: Vec<Value> = running_simulators()
            .into_iter()
            .map(|(link, target)| json!({ "port": link, "pty": target }))
            .collect();
        let offered: Vec<Value> = SIMULATORS
            .iter()
            .map(|sim| {
                json!({
                    "dialect": sim.dialect,
                    "models": sim.models,
                    "start": format!("polarimeter simulate stage --dialect {}", sim.dialect),
                })
            })
            .collect();
        out["simulated"] = json!({ "running": running, "offered": offered });
    }
    out["dialects"] = DIALECTS
        .iter()
        .map(|d| {
            json!({
                "dialect": d.name,
                "description": d.description,
                "kinds": d.kinds.iter().map(|k| k.name()).collect::<Vec<_>>(),
                "models": d.models,
                "baud": d.baud,
                "addressed": d.addressed(),
                "addresses": d.bus.map(|b| format!("{}..={}", b.first, b.last)),
            })
        })
        .collect();
    let cameras = polar_rig::camera::list(simulate);
    out["cameras"] = cameras["cameras"].clone();
    out["camera_backends"] = cameras["backends"].clone();
    Ok(out)
}

/// Symbolic links in `dir` and the devices they point to.
fn stable_names(dir: &Path) -> Vec<(String, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| {
            let path = e.path();
            let target = std::fs::canonicalize(&path).ok()?;
            Some((path.to_string_lossy().into_owned(), target))
        })
        .collect()
}

/// Where simulators put their links.
fn sim_root() -> PathBuf {
    std::env::temp_dir()
}

/// The prefix of a `simulate stage` process's folder of links in [`sim_root`], followed by
/// its process id.
const SIM_DIR_PREFIX: &str = "polarimeter-sim-";

/// Whether `port` is a link a `simulate stage` process made.
pub fn is_simulator_link(port: &str) -> bool {
    Path::new(port)
        .parent()
        .and_then(|d| d.file_name())
        .is_some_and(|n| n.to_string_lossy().starts_with(SIM_DIR_PREFIX))
}

/// The links of the `simulate stage` processes that are running. A folder whose process is
/// gone (killed before it could clean up) is removed, so a stopped simulator is never listed.
fn running_simulators() -> Vec<(String, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(sim_root()) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix(SIM_DIR_PREFIX) else {
            continue;
        };
        let alive = pid
            .parse::<u32>()
            .is_ok_and(|pid| Path::new(&format!("/proc/{pid}")).exists());
        if alive || !Path::new("/proc/self").exists() {
            out.extend(stable_names(&e.path()));
        } else {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
    out
}

fn runtime() -> Result<tokio::runtime::Runtime, DevicesError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| DevicesError(format!("cannot start the async runtime: {e}")))
}

/// One command to a stage or wheel on `port`.
pub fn stage(
    port: &str,
    dialect: &'static Dialect,
    address: u8,
    action: &StageAction,
) -> Result<Value, DevicesError> {
    if let StageAction::Move { angle_deg } = action {
        check_angle(*angle_deg)?;
    }
    dialect
        .check_address(address)
        .map_err(|e| DevicesError(format!("--{e}")))?;
    runtime()?.block_on(stage_async(port, dialect, address, action))
}

/// The angles `devices stage move` takes, degrees: one turn either way.
pub const MOVE_RANGE_DEG: f64 = 360.0;

/// Refuses a `--angle-deg` that is not finite or beyond one turn, before anything moves.
pub fn check_angle(angle_deg: f64) -> Result<(), DevicesError> {
    if angle_deg.is_finite() && angle_deg.abs() <= MOVE_RANGE_DEG {
        Ok(())
    } else {
        Err(DevicesError(format!(
            "--angle-deg = {} is out of range: allowed a finite angle in [-360, 360] degrees",
            crate::commands::compact(angle_deg)
        )))
    }
}

/// Checks where a move ended: within the stage's tolerance of the target (modulo a turn),
/// plus one count of the stage's resolution (the target is rounded to counts), or an error
/// naming the target, the position reached and the tolerance.
pub fn check_reached(
    target_deg: f64,
    reached_deg: f64,
    tolerance_deg: f64,
    counts_per_turn: u32,
) -> Result<(), DevicesError> {
    let d = (reached_deg - target_deg).rem_euclid(360.0);
    let off = d.min(360.0 - d);
    let allowed = tolerance_deg + 360.0 / f64::from(counts_per_turn.max(1));
    if off.is_finite() && off <= allowed {
        Ok(())
    } else {
        Err(DevicesError(format!(
            "the move to --angle-deg = {} ended at {} deg, {} deg off: allowed within {} deg \
             (the stage's tolerance)",
            crate::commands::compact(target_deg),
            crate::commands::compact(reached_deg),
            crate::commands::compact(off),
            crate::commands::compact(allowed)
        )))
    }
}

/// A device's identity as JSON.
pub fn identity_json(id: &Identity) -> Value {
    let mut v = json!({
        "kind": id.kind.name(),
        "model": id.model,
        "serial": id.serial,
        "firmware": id.firmware,
    });
    if let Some(c) = id.counts_per_turn {
        v["counts_per_turn"] = json!(c);
    }
    if let Some(n) = id.slots {
        v["slots"] = json!(n);
    }
    if let Some(h) = id.homed {
        v["homed"] = json!(h);
    }
    match id.position {
        Position::Angle { deg } => v["position_deg"] = json!(deg),
        Position::Slot(slot) => v["slot"] = json!(slot),
    }
    v
}

async fn stage_async(
    port: &str,
    d: &'static Dialect,
    address: u8,
    action: &StageAction,
) -> Result<Value, DevicesError> {
    let policy = (d.policy)();
    let started = std::time::Instant::now();
    // Info and position: read without moving. The rest: connect (which homes), then act.
    let kind = match action {
        StageAction::Info | StageAction::Position => {
            let id = (d.identify)(d.connector(port), address, policy).await?;
            let mut v = identity_json(&id);
            v["port"] = json!(port);
            v["dialect"] = json!(d.name);
            if d.addressed() {
                v["address"] = json!(address);
            }
            return Ok(v);
        }
        StageAction::Move { .. } => DeviceKind::Rotator,
        StageAction::Slot { .. } => DeviceKind::Wheel,
        StageAction::Home => match d.kinds {
            [only] => *only,
            _ => (d.identify)(d.connector(port), address, policy).await?.kind,
        },
    };
    let mut out = match (kind, d.rotator, d.wheel) {
        (DeviceKind::Rotator, Some(connect), _) => {
            rotator_action(connect(d.connector(port), address, policy).await?, action).await?
        }
        (DeviceKind::Wheel, _, Some(connect)) => {
            wheel_action(connect(d.connector(port), address, policy).await?, action).await?
        }
        (kind, _, _) => {
            let hint = match kind {
                DeviceKind::Rotator => "use `slot --slot N`",
                DeviceKind::Wheel => "use `move --angle-deg X`",
            };
            return Err(DevicesError(format!(
                "{}: {hint}",
                registry::not_provided(d, kind)
            )));
        }
    };
    out["port"] = json!(port);
    out["dialect"] = json!(d.name);
    out["elapsed_s"] = json!(started.elapsed().as_secs_f64());
    Ok(out)
}

async fn rotator_action<R: Rotator>(mut r: R, action: &StageAction) -> Result<Value, DevicesError> {
    let info = r.info().clone();
    let mut v = json!({
        "model": info.model,
        "counts_per_turn": info.counts_per_turn,
        "tolerance_deg": info.tolerance_rad.to_degrees(),
    });
    match action {
        StageAction::Move { angle_deg } => {
            check_angle(*angle_deg)?;
            let reached = r.move_to(angle_deg.to_radians()).await?;
            let target = angle_deg.rem_euclid(360.0);
            check_reached(
                target,
                reached.to_degrees(),
                info.tolerance_rad.to_degrees(),
                info.counts_per_turn,
            )?;
            v["target_deg"] = json!(target);
            v["position_deg"] = json!(reached.to_degrees());
        }
        StageAction::Home => {
            r.home().await?;
            v["position_deg"] = json!(r.position_rad().await?.to_degrees());
        }
        StageAction::Position | StageAction::Info => {
            v["position_deg"] = json!(r.position_rad().await?.to_degrees());
        }
        StageAction::Slot { .. } => {
            return Err(DevicesError(
                "this device is a rotator: use `move --angle-deg X`".into(),
            ))
        }
    }
    Ok(v)
}

async fn wheel_action<W: FilterWheel>(
    mut w: W,
    action: &StageAction,
) -> Result<Value, DevicesError> {
    let slots = w.slots().len();
    let mut v = json!({ "slots": slots });
    match action {
        StageAction::Slot { slot } => {
            if *slot >= slots {
                return Err(DevicesError(format!(
                    "--slot = {slot} is out of range: allowed 0..={}",
                    slots.saturating_sub(1)
                )));
            }
            v["slot"] = json!(w.select(*slot).await?);
        }
        StageAction::Home | StageAction::Position | StageAction::Info => {
            v["slot"] = json!(w.slot().await?);
        }
        StageAction::Move { .. } => {
            return Err(DevicesError(
                "this device is a wheel or slider: use `slot --slot N`".into(),
            ))
        }
    }
    Ok(v)
}

/// The simulator of dialect `dialect` (model `model`, or the dialect's first) with device
/// faults, from the simulators' registry; errors name `--dialect` or `--model` and what is
/// allowed.
pub fn simulator(
    dialect: &str,
    model: Option<&str>,
    faults: FaultProfile,
    seed: u64,
) -> Result<Box<dyn Simulator>, DevicesError> {
    polar_hil_mocks::sim::simulator(
        dialect,
        model.map(str::to_lowercase).as_deref(),
        faults,
        seed,
    )
    .map_err(|e| DevicesError(format!("--{e}")))
}

/// Reads a fault profile file.
pub fn load_faults(path: &Path) -> Result<FaultProfile, DevicesError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| DevicesError(format!("--faults {}: cannot read: {e}", path.display())))?;
    FaultProfile::from_toml_str(&text)
        .map_err(|e| DevicesError(format!("--faults {}: {e}", path.display())))
}

/// Starts a simulator on a pseudo-terminal, prints `{"port": LINK, ...}` on one line, and
/// serves until Ctrl-C (or until `stop` resolves).
pub fn sim_stage(
    dialect: &'static Dialect,
    model: Option<&str>,
    addresses: &[u8],
    faults: FaultProfile,
    seed: u64,
) -> Result<(), DevicesError> {
    let sim = match addresses {
        [] => simulator(dialect.name, model, faults, seed)?,
        _ => sim_on_bus(dialect, model, addresses, faults, seed)?,
    };
    let dir = sim_root().join(format!("{SIM_DIR_PREFIX}{}", std::process::id()));
    // A folder with this process's id is a dead process's (ids are reused): not ours to keep.
    let _ = std::fs::remove_dir_all(&dir);
    let name = format!("{}-{seed}", dialect.name);
    let link = dir.join(&name);
    let rt = runtime()?;
    let result = rt.block_on(async {
        let server = SimServer::pty_in_new_dir(sim, faults, seed, &dir, &name).map_err(|e| {
            DevicesError(format!(
                "cannot open a pseudo-terminal in {}: {e}",
                dir.display()
            ))
        })?;
        let line = json!({
            "port": link,
            "pty": server.port(),
            "dialect": dialect.name,
            "device": server.describe(),
            "baud": dialect.baud,
            "seed": seed,
        });
        println!("{line}");
        use std::io::Write;
        let _ = std::io::stdout().flush();
        stop_signal().await;
        let stats = server.stats();
        eprintln!(
            "simulator stopped: {} connections, {} bytes in, {} bytes out, {} unplugs",
            stats.connections, stats.bytes_in, stats.bytes_out, stats.unplugs
        );
        server.shutdown().await;
        Ok(())
    });
    let _ = std::fs::remove_dir_all(&dir);
    result
}

/// The simulated devices of `dialect` at `addresses` on one port; an address outside the
/// dialect's bus, or a dialect whose simulator has no bus, is refused naming what is allowed.
fn sim_on_bus(
    dialect: &'static Dialect,
    model: Option<&str>,
    addresses: &[u8],
    faults: FaultProfile,
    seed: u64,
) -> Result<Box<dyn polar_hil_mocks::sim::Simulator>, DevicesError> {
    let entry = SIMULATORS.iter().find(|s| s.dialect == dialect.name);
    let Some(on_bus) = entry.and_then(|s| s.on_bus) else {
        return Err(DevicesError(format!(
            "--address: the {} simulator puts one device on a port (give no --address)",
            dialect.name
        )));
    };
    for &a in addresses {
        dialect
            .check_address(a)
            .map_err(|e| DevicesError(format!("--{e}")))?;
    }
    // The model is checked as for one device.
    simulator(dialect.name, model, faults, seed)?;
    let model = model.unwrap_or(dialect.models[0]);
    on_bus(model, addresses, faults, seed).ok_or_else(|| {
        DevicesError(format!(
            "--model = {model:?} is not a {} device: allowed {}",
            dialect.name,
            dialect.model_list()
        ))
    })
}

/// Ctrl-C, or (on Unix) SIGTERM as a service manager or `kill` sends: the simulator then
/// removes its links before it exits.
async fn stop_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    let _ = tokio::signal::ctrl_c().await;
}

/// Tries each dialect's identify on `port`, each given `deadline`, in registry order; the
/// first that answers. Each try sends that dialect's identify request, which a device of
/// another dialect ignores or rejects as noise.
pub fn identify_any(
    port: &str,
    deadline: std::time::Duration,
) -> Result<Option<(&'static Dialect, Identity)>, DevicesError> {
    runtime()?.block_on(async {
        for d in DIALECTS {
            let mut policy = (d.policy)();
            policy.attempts = 1;
            let id = (d.identify)(d.connector(port), d.default_address(), policy);
            if let Ok(Ok(id)) = tokio::time::timeout(deadline, id).await {
                return Ok(Some((d, id)));
            }
        }
        Ok(None)
    })
}

/// The ports `devices list` found (stable names first, then the ports), and the running
/// simulators' links.
pub fn candidate_ports(listed: &Value) -> Vec<String> {
    let mut out = Vec::new();
    for p in listed["ports"].as_array().into_iter().flatten() {
        match p["stable"]
            .as_array()
            .and_then(|s| s.first())
            .and_then(Value::as_str)
        {
            Some(stable) => out.push(stable.to_string()),
            None => out.extend(p["port"].as_str().map(String::from)),
        }
    }
    for r in listed["simulated"]["running"]
        .as_array()
        .into_iter()
        .flatten()
    {
        out.extend(r["port"].as_str().map(String::from));
    }
    out
}

/// How long `devices list` gives each dialect to identify a device.
pub const IDENTIFY_DEADLINE: std::time::Duration = std::time::Duration::from_millis(1500);

/// `devices list [--simulate] [--rig RIG] [--write-rig FILE]`: [`list`]; with a rig, its stage
/// identified and whether its camera was found; with `--write-rig`, a starting rig file.
pub fn list_cmd(
    simulate: bool,
    rig: Option<&Path>,
    write_rig: Option<&Path>,
) -> Result<Value, DevicesError> {
    let mut out = list(simulate)?;
    if let Some(path) = rig {
        let rig = crate::rig::load(path).map_err(|e| DevicesError(e.to_string()))?;
        let stage = match &rig.file.stage {
            None => Value::Null,
            Some(s) if s.is_simulated() => json!({ "simulated": s.dialect }),
            Some(s) => match dialect(&s.dialect).and_then(|d| {
                let address = s.address.unwrap_or(d.default_address());
                stage(&s.port, d, address, &StageAction::Info)
            }) {
                Ok(v) => v,
                Err(e) => json!({ "port": s.port, "dialect": s.dialect, "error": e.0 }),
            },
        };
        let camera = rig.camera_name();
        let found = camera.as_deref().is_some_and(|c| {
            c == "sim"
                || out["cameras"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .any(|f| f["camera"] == c)
        });
        out["rig"] = json!({
            "file": path.display().to_string(),
            "stage": stage,
            "camera": camera,
            "camera_found": found,
        });
    }
    if let Some(path) = write_rig {
        let mut found = None;
        for port in candidate_ports(&out) {
            if let Some((d, id)) = identify_any(&port, IDENTIFY_DEADLINE)? {
                found = Some(polar_rig::file::StageEntry {
                    dialect: d.name.to_string(),
                    port,
                    address: None,
                    model: Some(id.model.to_lowercase()).filter(|m| d.models.contains(&m.as_str())),
                });
                break;
            }
        }
        if simulate && found.is_none() {
            // The simulated devices `--simulate` offers: the default simulated stage (our
            // firmware's rotator), simulated by the rig itself (port "sim").
            let (dialect, model) = polar_rig::sim_stage::default_stage();
            found = Some(polar_rig::file::StageEntry {
                dialect: dialect.into(),
                port: polar_rig::SIM_PORT.into(),
                address: None,
                model: Some(model.into()),
            });
        }
        out["rig_written"] = write_starting_rig(path, found, &out["cameras"])
            .map_err(|e| DevicesError(e.to_string()))?;
    }
    Ok(out)
}

/// The port, dialect and address of `devices stage`: flags override the rig file's `[stage]`;
/// errors name the missing flag or key.
pub fn stage_target(
    rig: Option<&Path>,
    port: Option<String>,
    dialect_name: Option<String>,
    address: Option<u8>,
) -> Result<(String, &'static Dialect, u8), DevicesError> {
    let rig = rig
        .map(crate::rig::load)
        .transpose()
        .map_err(|e| DevicesError(e.to_string()))?;
    let entry = rig.as_ref().and_then(|r| r.file.stage.clone());
    let missing = |key: &str, flag: &str| match &rig {
        Some(r) => DevicesError(format!(
            "rig {}: {key} is missing (or give {flag})",
            r.path.display()
        )),
        None => DevicesError(format!("give {flag} (or --rig)")),
    };
    let port = port
        .or_else(|| entry.as_ref().map(|s| s.port.clone()))
        .ok_or_else(|| missing("stage.port", "--port"))?;
    if port == polar_rig::SIM_PORT {
        return Err(DevicesError(
            "stage.port = \"sim\": a one-shot command needs a port; start a simulator with \
             `polarimeter simulate stage --dialect D` and give its port"
                .into(),
        ));
    }
    let name = dialect_name
        .or_else(|| entry.as_ref().map(|s| s.dialect.clone()))
        .ok_or_else(|| missing("stage.dialect", "--dialect"))?;
    let d = dialect(&name)?;
    let address = address
        .or(entry.and_then(|s| s.address))
        .unwrap_or(d.default_address());
    Ok((port, d, address))
}

/// Human-readable rendering of a result: `key: value` lines.
pub fn text(v: &Value) -> String {
    match v {
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| match v {
                Value::String(s) => format!("{k}: {s}\n"),
                Value::Array(items) if items.iter().all(Value::is_object) && !items.is_empty() => {
                    let rows: String = items.iter().map(|i| format!("  {i}\n")).collect();
                    format!("{k}:\n{rows}")
                }
                other => format!("{k}: {other}\n"),
            })
            .collect(),
        other => format!("{other}\n"),
    }
}

/// A starting rig's simulated camera made usable: it needs a camera file (the simulated rig's
/// default camera, written beside the rig as `STEM.camera.toml`, never over an existing file)
/// and a stage it can follow (it renders through the true angle of a stage simulator the rig
/// starts itself, so a stage found on a running simulator's link is written as `port =
/// "sim"`, the same dialect and model). Returns the entries and a comment saying what was done.
fn simulated_bench(
    rig_path: &Path,
    stage: Option<StageEntry>,
    camera: Option<CameraEntry>,
) -> Result<(Option<StageEntry>, Option<CameraEntry>, String), CommandError> {
    let camera = camera.unwrap_or(CameraEntry {
        backend: "sim".into(),
        id: None,
        file: None,
    });
    if camera.backend != "sim" {
        return Ok((stage, Some(camera), String::new()));
    }
    let mut note = String::new();
    let stage = stage.map(|mut s| {
        if !s.is_simulated() && is_simulator_link(&s.port) {
            note.push_str(&format!(
                "# The stage was found on a simulator's link ({}); the simulated camera follows\n\
                 # only a stage the rig simulates itself, so the rig names port = \"sim\".\n",
                s.port
            ));
            s.port = polar_rig::SIM_PORT.to_string();
        }
        s
    });
    let stem = rig_path
        .file_stem()
        .map_or_else(|| "rig".into(), |s| s.to_string_lossy().into_owned());
    let name = format!("{stem}.camera.toml");
    let camera_path = rig_path.parent().unwrap_or(Path::new(".")).join(&name);
    polar_rig::file::write_new(&camera_path, polar_rig::simulated::DEFAULT_CAMERA).map_err(
        |e| {
            CommandError::input(
                "--write-rig",
                format!(" {}: the camera file: {e}", rig_path.display()),
            )
        },
    )?;
    note.push_str(&format!(
        "# The simulated camera's noise model is {name} (the modern CMOS example); edit it or\n\
         # point camera.file at a calibrated camera file.\n\n"
    ));
    Ok((
        stage,
        Some(CameraEntry {
            file: Some(name.into()),
            ..camera
        }),
        note,
    ))
}

/// `devices list --write-rig FILE`: a starting rig file from what was found (the first stage
/// that identified, the first camera listed), refusing to overwrite an existing file.
pub fn write_starting_rig(
    path: &Path,
    stage: Option<StageEntry>,
    cameras: &Value,
) -> Result<Value, CommandError> {
    let camera = cameras
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|c| c["camera"].as_str())
        .map(|name| match name.split_once(':') {
            Some((backend, id)) => CameraEntry {
                backend: backend.to_string(),
                id: Some(id.to_string()),
                file: None,
            },
            None => CameraEntry {
                backend: name.to_string(),
                id: None,
                file: None,
            },
        })
        .next();
    let (stage, camera, note) = simulated_bench(path, stage, camera)?;
    let text = format!("{note}{}", starting_rig(stage.clone(), camera.clone()));
    use std::io::Write;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(|e| {
            CommandError::input(
                "--write-rig",
                format!(
                    " {}: {}",
                    path.display(),
                    if e.kind() == std::io::ErrorKind::AlreadyExists {
                        "the file exists: allowed a new file (a rig file is never overwritten)"
                            .to_string()
                    } else {
                        format!("cannot create: {e}")
                    }
                ),
            )
        })?;
    f.write_all(text.as_bytes()).map_err(|e| {
        CommandError::input(
            "--write-rig",
            format!(" {}: cannot write: {e}", path.display()),
        )
    })?;
    Ok(json!({
        "written": path.display().to_string(),
        "stage": stage.map(|s| json!({ "dialect": s.dialect, "port": s.port, "model": s.model })),
        "camera": camera.map(|c| json!({ "backend": c.backend, "id": c.id })),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn absurd_angles_are_refused_naming_flag_value_and_range() {
        for bad in [1e300, -1e300, f64::NAN, f64::INFINITY, 360.5, -361.0] {
            let e = check_angle(bad).unwrap_err().0;
            assert!(
                e.contains("--angle-deg") && e.contains("[-360, 360]") && e.len() < 120,
                "{e}"
            );
        }
        assert!(check_angle(1e300).unwrap_err().0.contains("= 1e300 "));
        for ok in [-360.0, -33.3, 0.0, 359.99, 360.0] {
            check_angle(ok).unwrap();
        }
    }

    #[test]
    fn a_move_that_ends_outside_the_tolerance_is_an_error() {
        // 1/100 deg counts: the tolerance plus one count is allowed, across 0/360 too.
        check_reached(10.0, 10.05, 0.05, 36_000).unwrap();
        check_reached(359.99, 0.02, 0.05, 36_000).unwrap();
        let e = check_reached(10.0, 10.2, 0.05, 36_000).unwrap_err().0;
        assert!(
            e.contains("--angle-deg = 10") && e.contains("ended at 10.2") && e.contains("allowed"),
            "{e}"
        );
        assert!(check_reached(10.0, f64::NAN, 0.05, 36_000).is_err());
    }
}
