//! `devices list`, `stage` and `sim stage`: serial ports, one-shot stage and wheel commands in
//! every dialect, and simulated devices on pseudo-terminals.

use polar_drivers::elliptec::{self, ElliptecRotator, ElliptecSlider};
use polar_drivers::fw102c::{self, Fw102c};
use polar_drivers::link::{Connector, Policy, SerialPath};
use polar_drivers::native::{self, NativeRotator, NativeWheel};
use polar_hal::{angle_from_counts, DeviceError, FilterWheel, Rotator};
use polar_hil_mocks::elliptec::{ElliptecConfig, ElliptecDevice};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::fw102c::{Fw102cConfig, Fw102cDevice};
use polar_hil_mocks::native::{NativeConfig, NativeDevice};
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Simulator;
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

/// The serial dialects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Dialect {
    /// Our firmware (`firmware-protocol/SPEC.md`), 115200 baud.
    Native,
    /// Thorlabs Elliptec ELL14/ELL18 rotation mounts, ELL6/ELL9 sliders, 9600 baud.
    Elliptec,
    /// Thorlabs FW102C/FW212C filter wheels, 115200 baud.
    Fw102c,
}

impl Dialect {
    /// The line rate.
    pub fn baud(self) -> u32 {
        match self {
            Dialect::Elliptec => 9600,
            Dialect::Native | Dialect::Fw102c => 115_200,
        }
    }

    /// The dialect the CLI spells `name` (`native`, `elliptec`, `fw102c`).
    pub fn from_name(name: &str) -> Option<Dialect> {
        [Dialect::Native, Dialect::Elliptec, Dialect::Fw102c]
            .into_iter()
            .find(|d| d.name() == name)
    }

    /// The dialect's name as the CLI spells it.
    pub fn name(self) -> &'static str {
        match self {
            Dialect::Native => "native",
            Dialect::Elliptec => "elliptec",
            Dialect::Fw102c => "fw102c",
        }
    }

    /// The driver policy (deadlines, retries) for the dialect.
    pub fn policy(self) -> Policy {
        match self {
            Dialect::Native => native::default_policy(),
            Dialect::Elliptec => elliptec::default_policy(),
            Dialect::Fw102c => fw102c::default_policy(),
        }
    }
}

/// What `stage` does.
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
        out["simulated"] = json!({
            "running": running,
            "offered": [
                { "dialect": "native", "models": ["rotator", "wheel"], "start": "polarimeter sim stage --dialect native" },
                { "dialect": "elliptec", "models": ["ell14", "ell18", "ell6", "ell9"], "start": "polarimeter sim stage --dialect elliptec" },
                { "dialect": "fw102c", "models": ["fw102c", "fw212c"], "start": "polarimeter sim stage --dialect fw102c" },
            ],
        });
    }
    let cameras = crate::camera::list(simulate);
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

fn running_simulators() -> Vec<(String, PathBuf)> {
    let Ok(entries) = std::fs::read_dir(sim_root()) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with("polarimeter-sim-")
        })
        .flat_map(|e| stable_names(&e.path()))
        .collect()
}

/// The serial connector of a port in a dialect (its baud rate).
pub fn connector(port: &str, dialect: Dialect) -> Box<dyn Connector> {
    Box::new(SerialPath {
        path: port.to_string(),
        baud: dialect.baud(),
    })
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
    dialect: Dialect,
    address: u8,
    action: &StageAction,
) -> Result<Value, DevicesError> {
    if let StageAction::Move { angle_deg } = action {
        check_angle(*angle_deg)?;
    }
    runtime()?.block_on(stage_async(port, dialect, address, action))
}

/// The angles `stage move` takes, degrees: one turn either way.
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

async fn stage_async(
    port: &str,
    dialect: Dialect,
    address: u8,
    action: &StageAction,
) -> Result<Value, DevicesError> {
    let policy = dialect.policy();
    let started = std::time::Instant::now();
    // Info and position: read without moving. The rest: connect (which homes), then act.
    let rotator = match (dialect, action) {
        (Dialect::Fw102c, StageAction::Move { .. }) => {
            return Err(DevicesError(
                "an FW102C is a filter wheel: use `slot --slot N`".into(),
            ))
        }
        (Dialect::Fw102c, _) => false,
        (Dialect::Native, StageAction::Info | StageAction::Position) => {
            let p = native::probe(connector(port, dialect), policy).await?;
            let id = p.identity;
            let rotator = id.device == polar_firmware_protocol::DeviceKind::Rotator;
            let mut v = json!({
                "port": port, "dialect": dialect.name(),
                "device": format!("{:?}", id.device),
                "serial": format!("{:08x}", id.serial),
                "firmware": format!("{}.{}.{}", id.firmware[0], id.firmware[1], id.firmware[2]),
                "counts_per_turn": id.counts_per_turn,
                "slots": id.slots,
                "homed": p.homed,
                "position_counts": p.position_counts,
            });
            if rotator {
                let angle = angle_from_counts(i64::from(p.position_counts), id.counts_per_turn);
                v["position_deg"] = json!(angle.to_degrees());
            } else {
                v["slot"] = json!(p.slot);
            }
            return Ok(v);
        }
        (Dialect::Elliptec, StageAction::Info | StageAction::Position) => {
            let (info, counts) = elliptec::probe(connector(port, dialect), address, policy).await?;
            let mut v = json!({
                "port": port, "dialect": dialect.name(), "address": address,
                "model": info.model(), "serial": info.serial, "year": info.year,
                "firmware": info.firmware, "travel": info.travel, "pulses": info.pulses,
                "position_counts": counts,
            });
            if elliptec::is_rotator(info.model_code) {
                v["position_deg"] =
                    json!(angle_from_counts(i64::from(counts), info.pulses).to_degrees());
            } else if let Some(slots) = elliptec::slider_positions(info.model_code) {
                v["slot"] = json!(slots.iter().position(|&p| (p - counts).abs() <= 5));
            }
            return Ok(v);
        }
        (_, StageAction::Move { .. }) => true,
        (_, StageAction::Slot { .. }) => false,
        (Dialect::Native, _) => {
            let p = native::probe(connector(port, dialect), policy).await?;
            p.identity.device == polar_firmware_protocol::DeviceKind::Rotator
        }
        (Dialect::Elliptec, _) => {
            let (info, _) = elliptec::probe(connector(port, dialect), address, policy).await?;
            elliptec::is_rotator(info.model_code)
        }
    };
    let mut out = if rotator {
        let c = connector(port, dialect);
        match dialect {
            Dialect::Native => {
                rotator_action(NativeRotator::connect(c, policy).await?, action).await?
            }
            _ => {
                let tolerance_rad = 0.05f64.to_radians();
                let r = ElliptecRotator::connect(c, address, policy, tolerance_rad).await?;
                rotator_action(r, action).await?
            }
        }
    } else {
        let c = connector(port, dialect);
        match dialect {
            Dialect::Native => {
                wheel_action(NativeWheel::connect(c, policy, None).await?, action).await?
            }
            Dialect::Elliptec => {
                wheel_action(ElliptecSlider::connect(c, address, policy).await?, action).await?
            }
            Dialect::Fw102c => {
                let w = Fw102c::connect(c, policy).await?;
                let identity = w.identity().to_string();
                let mut v = wheel_action(w, action).await?;
                v["model"] = json!(identity);
                v
            }
        }
    };
    out["port"] = json!(port);
    out["dialect"] = json!(dialect.name());
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

/// The simulated models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimModel {
    /// Our firmware's rotation stage.
    Rotator,
    /// Our firmware's six-slot wheel.
    Wheel,
    /// Elliptec ELL14 rotation mount.
    Ell14,
    /// Elliptec ELL18 rotation mount.
    Ell18,
    /// Elliptec ELL6 two-position slider.
    Ell6,
    /// Elliptec ELL9 four-position slider.
    Ell9,
    /// Thorlabs FW102C six-position wheel.
    Fw102c,
    /// Thorlabs FW212C twelve-position wheel.
    Fw212c,
}

/// The simulator of `dialect` (model `model`, or the dialect's first), with device faults.
pub fn simulator(
    dialect: Dialect,
    model: Option<SimModel>,
    faults: FaultProfile,
    seed: u64,
) -> Result<Box<dyn Simulator>, DevicesError> {
    use SimModel as M;
    let sim: Box<dyn Simulator> = match (dialect, model) {
        (Dialect::Native, None | Some(M::Rotator)) => {
            Box::new(NativeDevice::new(NativeConfig::rotator(), faults, seed))
        }
        (Dialect::Native, Some(M::Wheel)) => {
            Box::new(NativeDevice::new(NativeConfig::wheel(), faults, seed))
        }
        (Dialect::Elliptec, None | Some(M::Ell14)) => {
            Box::new(ElliptecDevice::new(ElliptecConfig::ell14(), faults, seed))
        }
        (Dialect::Elliptec, Some(M::Ell18)) => {
            Box::new(ElliptecDevice::new(ElliptecConfig::ell18(), faults, seed))
        }
        (Dialect::Elliptec, Some(M::Ell6)) => {
            Box::new(ElliptecDevice::new(ElliptecConfig::ell6(), faults, seed))
        }
        (Dialect::Elliptec, Some(M::Ell9)) => {
            Box::new(ElliptecDevice::new(ElliptecConfig::ell9(), faults, seed))
        }
        (Dialect::Fw102c, None | Some(M::Fw102c)) => {
            Box::new(Fw102cDevice::new(Fw102cConfig::fw102c(), faults, seed))
        }
        (Dialect::Fw102c, Some(M::Fw212c)) => {
            Box::new(Fw102cDevice::new(Fw102cConfig::fw212c(), faults, seed))
        }
        (d, Some(m)) => {
            return Err(DevicesError(format!(
                "--model = {m:?} is not a {} device: allowed {}",
                d.name(),
                match d {
                    Dialect::Native => "rotator, wheel",
                    Dialect::Elliptec => "ell14, ell18, ell6, ell9",
                    Dialect::Fw102c => "fw102c, fw212c",
                }
            )))
        }
    };
    Ok(sim)
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
    dialect: Dialect,
    model: Option<SimModel>,
    faults: FaultProfile,
    seed: u64,
) -> Result<(), DevicesError> {
    let sim = simulator(dialect, model, faults, seed)?;
    let dir = sim_root().join(format!("polarimeter-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .map_err(|e| DevicesError(format!("cannot create {}: {e}", dir.display())))?;
    let link = dir.join(format!("{}-{seed}", dialect.name()));
    let rt = runtime()?;
    let result = rt.block_on(async {
        let server = SimServer::pty(sim, faults, seed, &link)
            .map_err(|e| DevicesError(format!("cannot open a pseudo-terminal: {e}")))?;
        let line = json!({
            "port": link,
            "pty": server.port(),
            "dialect": dialect.name(),
            "device": server.describe(),
            "baud": dialect.baud(),
            "seed": seed,
        });
        println!("{line}");
        use std::io::Write;
        let _ = std::io::stdout().flush();
        let _ = tokio::signal::ctrl_c().await;
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
