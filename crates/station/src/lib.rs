//! An unattended polarimeter station: one long-lived process that owns a rig, a data
//! directory, a persistent plan queue and its history, and serves them over HTTP + JSON.
//!
//! * [`config`]: the station file (`STATION.toml`), checked key by key.
//! * [`keys`]: scoped API keys, shown once and stored only as SHA-256 hashes.
//! * [`state`]: the queue, the running item and the history, saved atomically on every change.
//! * [`queue`]: the queue's edits (add, move, remove, clear) and which item runs next.
//! * [`schedule`], [`clock`]: when an item may run (sun, local time, intervals) on the
//!   station's clock (the system's, or a fast one in simulation).
//! * [`runner`]: what the station asks of the instrument (check, run, resume a plan); the
//!   command line implements it with `acquire run` and `acquire resume`.
//! * [`worker`]: the thread that takes items one at a time and survives restarts.
//! * [`events`]: status and log events with change ids, for the event stream.
//! * [`auth`], [`reply`], [`routes`], [`api`], [`openapi`]: the HTTP API (who asks, how it
//!   answers, its endpoints) and its description.
//! * [`serve`]: binding (loopback unless TLS), start-up recovery and shutdown.
//! * [`picture`], [`page`]: the latest products as PNG and the status page at `/`.
//! * [`client`]: the command line's client of a station.
//! * [`upload`], [`retention`], [`upkeep`]: finished runs pushed to an S3-compatible bucket
//!   (`object_store`), what of them is removed and when, and the task that does both.
//!
//! Bluesky's queue server, DLS blueapi and all-sky camera stations (indi-allsky) are the
//! anchors: item ids, a history with exit states, queue control apart from run control,
//! change ids on pushed status, keys stored as hashes with scopes, a health endpoint.

pub mod api;
pub mod atomic;
pub mod audit;
pub mod auth;
pub mod client;
pub mod clock;
pub mod config;
pub mod disk;
pub mod error;
pub mod events;
pub mod keys;
pub mod openapi;
pub mod page;
pub mod picture;
pub mod queue;
pub mod reply;
pub mod retention;
pub mod routes;
pub mod runner;
pub mod schedule;
pub mod serve;
pub mod shared;
pub mod state;
pub mod upkeep;
pub mod upload;
pub mod worker;

pub use config::Config;
pub use error::StationError;
pub use runner::{Plane, Request, RunControl, RunEnd, Runner};

/// Seconds since the Unix epoch, now.
pub fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// A Unix time as RFC 3339 (UTC, seconds).
pub fn rfc3339(unix: u64) -> String {
    humantime::format_rfc3339_seconds(std::time::UNIX_EPOCH + std::time::Duration::from_secs(unix))
        .to_string()
}
