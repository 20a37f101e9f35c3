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
//! [upload]                  # finished runs to an S3-compatible bucket
//! url = "s3://bucket/station-1"          # bucket and prefix (one prefix per station)
//! endpoint = "https://s3.example.org"    # omit for AWS
//! region = "us-east-1"
//! access_key_id = "..."                  # or AWS_ACCESS_KEY_ID in the environment
//! secret_access_key_file = "s3.secret"   # or AWS_SECRET_ACCESS_KEY
//! [retention]               # days after a run ended (uploaded runs only, with [upload])
//! frames_days = 7
//! runs_days = 30
//! ```

use crate::error::StationError;
use crate::retention::RetentionConfig;
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
    upload: Option<UploadFile>,
    #[serde(default)]
    retention: RetentionConfig,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct UploadFile {
    url: String,
    endpoint: Option<String>,
    #[serde(default = "default_region")]
    region: String,
    access_key_id: Option<String>,
    secret_access_key_file: Option<PathBuf>,
}

fn default_region() -> String {
    "us-east-1".into()
}

/// Where finished runs go (`[upload]`).
#[derive(Debug, Clone, PartialEq)]
pub struct UploadConfig {
    /// The bucket.
    pub bucket: String,
    /// The key prefix runs go under (`PREFIX/RUN/...`), without slashes at its ends.
    pub prefix: String,
    /// An S3-compatible server's URL (`None`: AWS).
    pub endpoint: Option<String>,
    /// The bucket's region.
    pub region: String,
    /// Plain HTTP to the endpoint: allowed for a loopback endpoint only.
    pub allow_http: bool,
    /// The access key id (else from the environment).
    pub access_key_id: Option<String>,
    /// A file holding the secret access key (else from the environment).
    pub secret_access_key_file: Option<PathBuf>,
}

impl UploadFile {
    /// Checks the URL and endpoint: `s3://BUCKET/PREFIX`, and plain HTTP only to loopback (a
    /// run's data must not cross a network in clear, nor the request signatures).
    fn resolve(self, dir: &Path) -> Result<UploadConfig, (&'static str, String)> {
        let rest = self.url.strip_prefix("s3://").ok_or((
            "upload.url",
            format!(
                "{:?} is not an s3:// URL: write s3://BUCKET/PREFIX",
                self.url
            ),
        ))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let prefix = prefix.trim_matches('/').to_string();
        let bucket_ok = (3..=63).contains(&bucket.len())
            && bucket
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.');
        if !bucket_ok || prefix.is_empty() || prefix.split('/').any(|p| p.is_empty() || p == "..") {
            return Err((
                "upload.url",
                format!(
                    "{:?}: write s3://BUCKET/PREFIX, a bucket of 3 to 63 of [a-z0-9.-] and a \
                     prefix (one per station, e.g. its name)",
                    self.url
                ),
            ));
        }
        let mut allow_http = false;
        if let Some(e) = &self.endpoint {
            let host = e
                .strip_prefix("http://")
                .map(|h| h.split(['/', ':']).next().unwrap_or(""));
            match host {
                Some(h) if ["127.0.0.1", "localhost", "[::1]", "::1"].contains(&h) => {
                    allow_http = true;
                }
                Some(_) => {
                    return Err((
                        "upload.endpoint",
                        format!(
                            "{e:?} is plain HTTP to another machine: use https:// (plain \
                             HTTP only to 127.0.0.1)"
                        ),
                    ))
                }
                None if e.starts_with("https://") => {}
                None => {
                    return Err((
                        "upload.endpoint",
                        format!("{e:?} is not a URL: write https://HOST[:PORT]"),
                    ))
                }
            }
        }
        Ok(UploadConfig {
            bucket: bucket.to_string(),
            prefix,
            endpoint: self.endpoint,
            region: self.region,
            allow_http,
            access_key_id: self.access_key_id,
            secret_access_key_file: self.secret_access_key_file.map(|f| dir.join(f)),
        })
    }
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
    /// Where finished runs are uploaded, if anywhere.
    pub upload: Option<UploadConfig>,
    /// What of a finished run is removed, and when.
    pub retention: RetentionConfig,
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
        let upload = match raw.upload {
            Some(u) => Some(u.resolve(dir).map_err(|(k, m)| bad(k, m))?),
            None => None,
        };
        raw.retention.check().map_err(|m| bad("retention", m))?;
        Ok(Config {
            upload,
            retention: raw.retention,
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

    #[test]
    fn uploads_need_a_bucket_a_prefix_and_tls_beyond_loopback() {
        let base = "data_dir = \"d\"\nrig = \"r\"\n[upload]\n";
        let c = load(&format!(
            "{base}url = \"s3://runs/roof-1/\"\nendpoint = \"http://127.0.0.1:9000\"\n"
        ))
        .unwrap();
        let u = c.upload.unwrap();
        assert_eq!((u.bucket.as_str(), u.prefix.as_str()), ("runs", "roof-1"));
        assert!(u.allow_http);
        for (text, key) in [
            ("url = \"runs/roof\"", "upload.url"),
            ("url = \"s3://runs\"", "upload.url"),
            ("url = \"s3://Runs/x\"", "upload.url"),
            ("url = \"s3://runs/../x\"", "upload.url"),
            (
                "url = \"s3://runs/x\"\nendpoint = \"http://10.0.0.5:9000\"",
                "upload.endpoint",
            ),
        ] {
            let e = load(&format!("{base}{text}\n")).unwrap_err().to_string();
            assert!(e.contains(key), "{text}: {e}");
        }
    }
}
