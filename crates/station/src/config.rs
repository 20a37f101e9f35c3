//! The station file (`STATION.toml`): where the station listens, its data directory and rig
//! file (relative to the station file), the disk reserve, request limits and TLS.
//!
//! ```toml
//! listen = "127.0.0.1:8750"
//! data_dir = "station-data"
//! rig = "../rigs/sim.toml"
//! autostart = true          # take queued items as soon as the station starts
//! reserve_mb = 1024         # free space kept on the data directory's disk
//! max_body_kb = 256         # request bodies larger than this are refused (413)
//! auto_resume = 3           # resumes of a device-error pause before the item waits
//! utc_offset_h = -5         # local time for schedules' local_from / local_to
//! [tls]                     # required to listen on anything but loopback
//! cert = "cert.pem"
//! key = "key.pem"
//! [simulation]              # a fast clock for schedules (a simulated rig only)
//! clock_start = "2026-06-21T04:00:00Z"
//! clock_speed = 600
//! ```

use crate::error::StationError;
use serde::Deserialize;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

/// The default address: loopback only.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:8750";

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ConfigFile {
    listen: Option<String>,
    data_dir: PathBuf,
    rig: PathBuf,
    #[serde(default = "default_true")]
    autostart: bool,
    #[serde(default = "default_reserve_mb")]
    reserve_mb: u64,
    #[serde(default = "default_max_body_kb")]
    max_body_kb: u64,
    #[serde(default = "default_auto_resume")]
    auto_resume: u32,
    tls: Option<TlsFile>,
    #[serde(default)]
    utc_offset_h: f64,
    simulation: Option<SimulationFile>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SimulationFile {
    clock_start: String,
    #[serde(default = "default_speed")]
    clock_speed: f64,
}

fn default_speed() -> f64 {
    1.0
}

fn default_true() -> bool {
    true
}
fn default_reserve_mb() -> u64 {
    1024
}
fn default_max_body_kb() -> u64 {
    256
}
fn default_auto_resume() -> u32 {
    3
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TlsFile {
    cert: PathBuf,
    key: PathBuf,
}

/// TLS for a station reachable from other machines: PEM files.
#[derive(Debug, Clone)]
pub struct Tls {
    /// The certificate chain (PEM).
    pub cert: PathBuf,
    /// The private key (PEM).
    pub key: PathBuf,
}

/// The station's settings, paths resolved against the station file's directory.
#[derive(Debug, Clone)]
pub struct Config {
    /// The station file.
    pub path: PathBuf,
    /// Where the API listens.
    pub listen: SocketAddr,
    /// The data directory: state, keys, audit log, item plans and runs.
    pub data_dir: PathBuf,
    /// The rig file the station runs on.
    pub rig: PathBuf,
    /// Take queued items as soon as the station starts.
    pub autostart: bool,
    /// Free space kept on the data directory's file system, bytes.
    pub reserve_bytes: u64,
    /// The largest request body accepted, bytes.
    pub max_body_bytes: usize,
    /// Automatic resumes of a device-error pause before the item waits for a person.
    pub auto_resume: u32,
    /// TLS, when configured.
    pub tls: Option<Tls>,
    /// Local time's offset from UTC, seconds (schedules' `local_from`, `local_to`).
    pub utc_offset_s: i64,
    /// A simulated clock: its start (Unix seconds) and speed (simulated rigs only).
    pub sim_clock: Option<(u64, f64)>,
}

impl Config {
    /// Reads and checks the station file; errors name the key, the value and what is allowed.
    pub fn load(path: &Path) -> Result<Config, StationError> {
        let text = std::fs::read_to_string(path).map_err(|e| StationError::io(path, e))?;
        let file = path.display().to_string();
        let bad = |key: &str, message: String| StationError::Config {
            file: file.clone(),
            key: key.to_string(),
            message,
        };
        let de = toml::Deserializer::new(&text);
        let raw: ConfigFile = serde_path_to_error::deserialize(de).map_err(|e| {
            let key = e.path().to_string();
            bad(&key, e.into_inner().message().trim().to_string())
        })?;
        // Absolute, so the station's paths do not depend on where it was started from.
        let path = &std::fs::canonicalize(path).map_err(|e| StationError::io(path, e))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let listen_text = raw.listen.unwrap_or_else(|| DEFAULT_LISTEN.to_string());
        let listen = parse_listen(&listen_text).map_err(|m| bad("listen", m))?;
        if raw.max_body_kb == 0 || raw.max_body_kb > 16 * 1024 {
            return Err(bad(
                "max_body_kb",
                format!("{} is out of range: 1 to 16384 (KiB)", raw.max_body_kb),
            ));
        }
        if raw.auto_resume > 100 {
            return Err(bad(
                "auto_resume",
                format!("{} is out of range: 0 to 100", raw.auto_resume),
            ));
        }
        if !(-14.0..=14.0).contains(&raw.utc_offset_h) {
            return Err(bad(
                "utc_offset_h",
                format!("{} is out of range: -14 to 14 (hours)", raw.utc_offset_h),
            ));
        }
        let sim_clock = match raw.simulation {
            None => None,
            Some(s) => {
                let start = humantime::parse_rfc3339_weak(&s.clock_start).map_err(|_| {
                    bad(
                        "simulation.clock_start",
                        format!(
                            "{:?} is not a time: write e.g. 2026-06-21T04:00:00Z",
                            s.clock_start
                        ),
                    )
                })?;
                if !(s.clock_speed.is_finite() && (1.0..=100_000.0).contains(&s.clock_speed)) {
                    return Err(bad(
                        "simulation.clock_speed",
                        format!(
                            "{} is out of range: 1 to 100000 (times real time)",
                            s.clock_speed
                        ),
                    ));
                }
                let start = start
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_secs());
                Some((start, s.clock_speed))
            }
        };
        Ok(Config {
            path: path.to_path_buf(),
            utc_offset_s: (raw.utc_offset_h * 3600.0).round() as i64,
            sim_clock,
            listen,
            data_dir: dir.join(raw.data_dir),
            rig: dir.join(raw.rig),
            autostart: raw.autostart,
            reserve_bytes: raw.reserve_mb.saturating_mul(1 << 20),
            max_body_bytes: (raw.max_body_kb * 1024) as usize,
            auto_resume: raw.auto_resume,
            tls: raw.tls.map(|t| Tls {
                cert: dir.join(t.cert),
                key: dir.join(t.key),
            }),
        })
    }

    /// Refuses to listen beyond loopback without TLS: a station on the network takes keys,
    /// which must not cross it in clear.
    pub fn check_bind(&self) -> Result<(), StationError> {
        if self.listen.ip().is_loopback() || self.tls.is_some() {
            return Ok(());
        }
        Err(StationError::Config {
            file: self.path.display().to_string(),
            key: "listen".into(),
            message: format!(
                "{} is reachable from other machines, which needs TLS (API keys must not \
                 cross a network in clear): give [tls] cert and key (PEM files), or listen on \
                 127.0.0.1",
                self.listen
            ),
        })
    }

    /// The station's state file (queue, running item, history).
    pub fn state_file(&self) -> PathBuf {
        self.data_dir.join("state.json")
    }

    /// The API keys (hashes only).
    pub fn keys_file(&self) -> PathBuf {
        self.data_dir.join("keys.json")
    }

    /// The audit log: every write action with its key id.
    pub fn audit_file(&self) -> PathBuf {
        self.data_dir.join("audit.log")
    }

    /// Where queued plans are kept, one file per item.
    pub fn items_dir(&self) -> PathBuf {
        self.data_dir.join("items")
    }

    /// Where runs are written, one directory per item.
    pub fn runs_dir(&self) -> PathBuf {
        self.data_dir.join("runs")
    }
}

/// `ADDR:PORT`, e.g. `127.0.0.1:8750` or `[::1]:8750`.
pub fn parse_listen(text: &str) -> Result<SocketAddr, String> {
    text.parse().map_err(|_| {
        format!("{text:?} is not an address and port: write e.g. \"127.0.0.1:8750\" (port 1 to 65535; 0 picks a free one)")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(text: &str) -> Result<Config, StationError> {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("station.toml");
        std::fs::write(&p, text).unwrap();
        Config::load(&p)
    }

    #[test]
    fn defaults_listen_on_loopback_and_paths_resolve_beside_the_file() {
        let c = load("data_dir = \"d\"\nrig = \"r.toml\"\n").unwrap();
        assert!(c.listen.ip().is_loopback());
        assert!(c.data_dir.ends_with("d") && c.rig.ends_with("r.toml"));
        assert_eq!(c.reserve_bytes, 1024 << 20);
        c.check_bind().unwrap();
    }

    #[test]
    fn a_network_bind_without_tls_is_refused_naming_the_key() {
        let c = load("listen = \"0.0.0.0:8750\"\ndata_dir = \"d\"\nrig = \"r\"\n").unwrap();
        let e = c.check_bind().unwrap_err().to_string();
        assert!(e.contains("listen") && e.contains("TLS"), "{e}");
    }

    #[test]
    fn bad_keys_are_named() {
        let e = load("data_dir = \"d\"\nrig = \"r\"\nreserve_mb = -1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("reserve_mb"), "{e}");
        let e = load("data_dir = \"d\"\nrig = \"r\"\nlisten = \"here\"\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("listen") && e.contains("here"), "{e}");
        let e = load("data_dir = \"d\"\nrig = \"r\"\ncolour = 1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("colour"), "{e}");
    }
}
