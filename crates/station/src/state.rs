//! The station's state: the queue, the item running (or paused), the history of items that
//! left the station with their exit states, and whether the queue is taking items. Saved
//! whole and atomically ([`crate::atomic`]) on every change, so a SIGKILL or a power cut at
//! any moment leaves the state before or after the change.

use crate::error::StationError;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::path::Path;

/// A queued plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Item {
    /// Server-assigned, never reused.
    pub id: u64,
    /// The plan's name.
    pub name: String,
    /// The id of the key that added it.
    pub owner: String,
    /// Higher runs first; equal priorities keep their order.
    pub priority: i32,
    /// The plan file, relative to the data directory (`items/ID.toml`).
    pub plan_file: String,
    /// When it was added, Unix seconds.
    pub added_unix: u64,
    /// The forecast made when it was added: duration, frames, DoLP sigma, bytes.
    pub forecast: Value,
    /// When it may run (none: as soon as it is next).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub schedule: Option<crate::schedule::Schedule>,
    /// Runs started so far (a repeating item stays queued until its runs are used up).
    #[serde(default)]
    pub runs_done: u32,
    /// When its last run started, station time (Unix seconds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_start_unix: Option<u64>,
}

/// Where the current item is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Phase {
    /// Its run is going (after a restart: it was going when the station stopped).
    Running,
    /// Its run is paused, resumable; waiting for `run/resume` or `run/abort`.
    Paused,
}

/// The item the station is on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Current {
    /// The item.
    pub item: Item,
    /// Its run directory, relative to the data directory (`runs/ID-NAME`).
    pub run_dir: String,
    /// When its run started, Unix seconds.
    pub started_unix: u64,
    /// Running or paused.
    pub phase: Phase,
    /// Why it paused.
    pub pause_reason: Option<String>,
    /// How many times its run was resumed after the station died under it.
    pub crash_resumes: u32,
    /// A key asked to resume the paused run.
    pub resume_requested: bool,
    /// A key asked to abort the run.
    pub abort_requested: bool,
    /// The station paused it to stop (SIGTERM): resume when it starts again.
    pub resume_on_start: bool,
}

impl Current {
    /// An item whose run starts now in `run_dir`.
    pub fn new(item: Item, run_dir: String, now_unix: u64) -> Current {
        Current {
            item,
            run_dir,
            started_unix: now_unix,
            phase: Phase::Running,
            pause_reason: None,
            crash_resumes: 0,
            resume_requested: false,
            abort_requested: false,
            resume_on_start: false,
        }
    }
}

/// How an item left the station.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ExitState {
    /// Its run finished.
    Done,
    /// Its run could not start or failed (the message says why).
    Failed,
    /// A key aborted it; what was acquired stays.
    Aborted,
    /// It was paused and removed from the station; its run stays resumable with
    /// `polarimeter acquire resume`.
    Stopped,
}

/// An item that left the station.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryEntry {
    /// The item.
    pub item: Item,
    /// How it left.
    pub exit: ExitState,
    /// Its run directory, relative to the data directory (empty if no run started).
    pub run_dir: String,
    /// When its run started and when it left, Unix seconds.
    pub started_unix: u64,
    /// When it left, Unix seconds.
    pub ended_unix: u64,
    /// How many times its run was resumed after the station died under it
    /// (resumed-after-crash when above 0).
    pub crash_resumes: u32,
    /// Why (failed, aborted, stopped), or the run's warnings.
    pub message: String,
    /// The run's result, as `acquire run` prints it.
    pub result: Value,
    /// Its upload to the bucket (`None`: the station uploads nothing, or no run started).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub upload: Option<UploadState>,
    /// What retention removed of its run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub removed: Option<Removed>,
}

/// Where a finished run's upload stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UploadState {
    /// `pending` (waiting or being retried), `done`, or `failed` (no run directory to upload).
    pub state: String,
    /// Attempts so far.
    pub attempts: u32,
    /// The last attempt's error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Where it went (`s3://bucket/prefix/run`), once done.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
    /// When it completed, Unix seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub done_unix: Option<u64>,
}

impl UploadState {
    /// Waiting for its first attempt.
    pub fn pending() -> UploadState {
        UploadState {
            state: "pending".into(),
            attempts: 0,
            error: None,
            url: None,
            done_unix: None,
        }
    }

    /// Completed at `url` at `now`.
    pub fn done_now(url: String, now: u64) -> UploadState {
        UploadState {
            state: "done".into(),
            attempts: 1,
            error: None,
            url: Some(url),
            done_unix: Some(now),
        }
    }

    /// Whether the run is whole in the bucket (its completion marker written).
    pub fn done(&self) -> bool {
        self.state == "done"
    }
}

/// What retention removed of a finished run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Removed {
    /// Its raw frames (`run.zarr/frames/pixels`).
    Frames,
    /// The whole run directory.
    Run,
}

/// Everything the station keeps across restarts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// The next item's id.
    pub next_id: u64,
    /// Whether the queue takes items (start/stop).
    pub queue_running: bool,
    /// Waiting items, in order.
    pub queue: Vec<Item>,
    /// The item running or paused.
    pub current: Option<Current>,
    /// Items that left, oldest first.
    pub history: Vec<HistoryEntry>,
}

impl State {
    /// A new station's state.
    pub fn new(queue_running: bool) -> State {
        State {
            next_id: 1,
            queue_running,
            queue: Vec::new(),
            current: None,
            history: Vec::new(),
        }
    }

    /// The state saved in `path`, or a new one.
    pub fn load(path: &Path, autostart: bool) -> Result<State, StationError> {
        Ok(crate::atomic::read_json(path)?.unwrap_or_else(|| State::new(autostart)))
    }

    /// Saves the state atomically.
    pub fn save(&self, path: &Path) -> Result<(), StationError> {
        crate::atomic::write_json(path, self, false)
    }

    /// The current item leaves the station for the history (its run then waits for its
    /// upload when `uploads`).
    pub fn finish_current(
        &mut self,
        (exit, message): (ExitState, String),
        result: Value,
        now: u64,
        uploads: bool,
    ) {
        if let Some(c) = self.current.take() {
            let upload = (uploads && !c.run_dir.is_empty()).then(UploadState::pending);
            self.history.push(HistoryEntry {
                upload,
                removed: None,
                item: c.item,
                exit,
                run_dir: c.run_dir,
                started_unix: c.started_unix,
                ended_unix: now,
                crash_resumes: c.crash_resumes,
                message,
                result,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_round_trips_through_its_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("state.json");
        let mut s = State::new(true);
        s.queue.push(Item {
            id: 1,
            name: "a".into(),
            owner: "k".into(),
            priority: 0,
            plan_file: "items/1.toml".into(),
            added_unix: 5,
            forecast: Value::Null,
            schedule: None,
            runs_done: 0,
            last_start_unix: None,
        });
        s.next_id = 2;
        s.save(&p).unwrap();
        assert_eq!(State::load(&p, false).unwrap(), s);
        assert!(State::load(&dir.path().join("none.json"), false)
            .unwrap()
            .queue
            .is_empty());
    }
}
