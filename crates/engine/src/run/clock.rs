//! The host's wall clock as the journal and the store record it.

use std::time::{SystemTime, UNIX_EPOCH};

/// `t` in nanoseconds since the Unix epoch (0 before it, saturating far after it).
pub(super) fn now_unix_ns(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}
