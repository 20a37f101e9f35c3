//! `bench serial`: what a command round trip costs through a real pseudo-terminal, against the
//! same driver and simulator over an in-memory pipe and against the simulated device's own
//! time (the bytes on the wire at its baud rate), for each dialect in the registry (every
//! simulator line of `polar_hil_mocks::sim::SIMULATORS`, its first model, driven through the
//! driver registry's constructor).
//!
//! The query is a position read that always asks the device: a rotator's
//! `spin_position_rad` where the driver has one (it never answers from a cache), else its
//! `position_rad`; a wheel's `slot`. The simulated devices act on a request once its last byte
//! is in and send their reply at their line's rate (`Simulator::seconds_per_byte`), so
//! everything above the request's and the reply's time on the line is overhead: the driver,
//! tokio (whose timers round each wake up to the next millisecond, and the simulator's pacing
//! uses them), the kernel's pty and the server. The pty row against the memory row isolates
//! the pseudo-terminal's share.

use crate::devices::DevicesError;
use polar_drivers::link::{BoxIo, Connector, FnConnector, SerialPath};
use polar_drivers::registry::{self, Dialect};
use polar_hal::{FilterWheel, Rotator};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::{SimDialect, Simulator, SIMULATORS};
use std::time::Instant;

/// One measured row.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialRow {
    /// The dialect and device.
    pub device: String,
    /// `pty` or `memory`.
    pub transport: &'static str,
    /// Baud rate of the simulated line.
    pub baud: u32,
    /// The simulated line's time for one query: its request and reply bytes at the line's
    /// rate, ms.
    pub wire_ms: f64,
    /// Median round trip, ms.
    pub median_ms: f64,
    /// 90th percentile, ms.
    pub p90_ms: f64,
    /// Median minus wire time, ms.
    pub overhead_ms: f64,
}

/// The speed of the rotators whose simulators can be built at one, degrees per second: the
/// driver's connect homes the stage, and the slowest real homings (the 8MPR16-1's 1.25 deg/s,
/// the AG-PR100P's 1.5) would take minutes; a position query does not depend on it.
pub const BENCH_SPEED_DEG_S: f64 = 360.0;

/// The simulator of a dialect's first model (at [`BENCH_SPEED_DEG_S`] where it can be built at
/// a speed).
fn sim(entry: &SimDialect) -> Result<Box<dyn Simulator>, DevicesError> {
    let model = entry.models[0];
    let faults = FaultProfile::default();
    entry
        .at_speed
        .and_then(|build| build(model, BENCH_SPEED_DEG_S, faults, 1))
        .or_else(|| (entry.build)(model, faults, 1))
        .ok_or_else(|| DevicesError(format!("{}: no simulator of {model}", entry.dialect)))
}

/// Times `n` position queries through `connector` with the dialect's driver; returns the
/// times and the request and reply bytes per query.
async fn queries(
    dialect: &Dialect,
    connector: Box<dyn Connector>,
    server: &SimServer,
    n: usize,
) -> Result<(Vec<f64>, f64), DevicesError> {
    let mut times = Vec::with_capacity(n);
    let policy = (dialect.policy)();
    let bytes_before;
    if let Some(connect) = dialect.rotator {
        let mut r = connect(connector, dialect.default_address(), policy).await?;
        // The read that never answers from a cache, where the driver has it.
        let fresh = r.spin_position_rad().await.is_ok();
        bytes_before = line_bytes(server);
        for _ in 0..n {
            let t = Instant::now();
            if fresh {
                r.spin_position_rad().await?;
            } else {
                r.position_rad().await?;
            }
            times.push(t.elapsed().as_secs_f64());
        }
    } else if let Some(connect) = dialect.wheel {
        let mut w = connect(connector, dialect.default_address(), policy).await?;
        bytes_before = line_bytes(server);
        for _ in 0..n {
            let t = Instant::now();
            w.slot().await?;
            times.push(t.elapsed().as_secs_f64());
        }
    } else {
        return Err(DevicesError(format!("{} has no device", dialect.name)));
    }
    let bytes_per_query = (line_bytes(server) - bytes_before) as f64 / n as f64;
    Ok((times, bytes_per_query))
}

/// The bytes the server has carried both ways.
fn line_bytes(server: &SimServer) -> u64 {
    let s = server.stats();
    s.bytes_in + s.bytes_out
}

fn row(
    device: &str,
    transport: &'static str,
    (baud, seconds_per_byte): (u32, f64),
    mut times: Vec<f64>,
    bytes: f64,
) -> SerialRow {
    times.sort_by(f64::total_cmp);
    let q = |p: f64| times[((times.len() - 1) as f64 * p).round() as usize] * 1e3;
    let wire_ms = bytes * seconds_per_byte * 1e3;
    SerialRow {
        device: device.to_string(),
        transport,
        baud,
        wire_ms,
        median_ms: q(0.5),
        p90_ms: q(0.9),
        overhead_ms: q(0.5) - wire_ms,
    }
}

/// Measures `n` position queries per dialect and transport.
pub fn serial(n: usize) -> Result<Vec<SerialRow>, DevicesError> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| DevicesError(format!("cannot start the async runtime: {e}")))?;
    let dir = std::env::temp_dir().join(format!("polarimeter-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .map_err(|e| DevicesError(format!("cannot create {}: {e}", dir.display())))?;
    let result = rt.block_on(async {
        let mut rows = Vec::new();
        for entry in SIMULATORS {
            let dialect = registry::find(entry.dialect).ok_or_else(|| {
                DevicesError(format!("{}: no driver in the registry", entry.dialect))
            })?;
            let name = format!("{} {}", entry.dialect, entry.models[0]);
            let (baud, per_byte) = {
                let s = sim(entry)?;
                (s.baud(), s.seconds_per_byte())
            };
            // Through a pseudo-terminal.
            let link = dir.join(name.replace(' ', "-"));
            let server = SimServer::pty(sim(entry)?, FaultProfile::default(), 1, &link)
                .map_err(|e| DevicesError(format!("cannot open a pseudo-terminal: {e}")))?;
            let connector = Box::new(SerialPath {
                path: link.to_string_lossy().into_owned(),
                baud,
            });
            let (times, bytes) = queries(dialect, connector, &server, n).await?;
            rows.push(row(&name, "pty", (baud, per_byte), times, bytes));
            server.shutdown().await;
            // In memory.
            let server = SimServer::memory(sim(entry)?, FaultProfile::default(), 1);
            let port = server
                .memory_port()
                .ok_or_else(|| DevicesError("no memory port".into()))?;
            let connector = Box::new(FnConnector::new("memory", move || {
                let port = port.clone();
                async move { port.open().await.map(|io| Box::new(io) as BoxIo) }
            }));
            let (times, bytes) = queries(dialect, connector, &server, n).await?;
            rows.push(row(&name, "memory", (baud, per_byte), times, bytes));
            server.shutdown().await;
        }
        Ok(rows)
    });
    let _ = std::fs::remove_dir_all(&dir);
    result
}

/// The rows as a Markdown table, with the pty's extra cost over memory per dialect.
pub fn markdown(rows: &[SerialRow], n: usize) -> String {
    let mut out = format!(
        "Position query round trip, {n} queries per row (median and 90th percentile).\n\n\
         | device | transport | baud | device time: reply on the wire (ms) | median (ms) | p90 (ms) | overhead over wire (ms) |\n\
         |---|---|---:|---:|---:|---:|---:|\n"
    );
    for r in rows {
        out.push_str(&format!(
            "| {} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
            r.device, r.transport, r.baud, r.wire_ms, r.median_ms, r.p90_ms, r.overhead_ms
        ));
    }
    out.push('\n');
    for pair in rows.chunks(2) {
        if let [pty, mem] = pair {
            out.push_str(&format!(
                "- {}: the pty adds {:.2} ms per round trip over memory ({:.2}x the in-memory median); the device's wire time is {:.1} % of the pty median.\n",
                pty.device,
                pty.median_ms - mem.median_ms,
                pty.median_ms / mem.median_ms.max(1e-9),
                100.0 * pty.wire_ms / pty.median_ms.max(1e-9),
            ));
        }
    }
    out
}
