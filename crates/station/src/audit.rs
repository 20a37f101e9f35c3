//! The audit log: every write action (and every refused one) with the key's id, one JSON line
//! each, appended and flushed, in the data directory's `audit.log`.

use serde_json::json;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Mutex;

/// Appends audit lines.
pub struct Audit {
    path: PathBuf,
    lock: Mutex<()>,
}

impl Audit {
    /// The log at `path`.
    pub fn new(path: PathBuf) -> Audit {
        Audit {
            path,
            lock: Mutex::new(()),
        }
    }

    /// Records that key `key` did (or was refused) `action` on `target`.
    pub fn record(&self, key: &str, action: &str, target: &str, ok: bool, message: &str) {
        let line = json!({
            "time": crate::rfc3339(crate::now_unix()),
            "key": key, "action": action, "target": target, "ok": ok, "message": message,
        });
        tracing::info!(target: "audit", "{line}");
        let _guard = self.lock.lock();
        let written = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)
            .and_then(|mut f| {
                writeln!(f, "{line}")?;
                f.sync_data()
            });
        if let Err(e) = written {
            tracing::error!("audit log {}: {e}", self.path.display());
        }
    }
}
