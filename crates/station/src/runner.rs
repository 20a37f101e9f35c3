//! What the station asks of the instrument, and how it talks to a run while it goes. The
//! command line implements [`Runner`] with its own `plan check`, `acquire run` and `acquire
//! resume`, so a station's run is exactly a command-line run.

use serde_json::Value;
use std::collections::VecDeque;
use std::path::Path;
use std::sync::{Arc, Mutex};

/// A request to a going run, taken at its next poll.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request {
    /// Pause at the next safe point (a set boundary); the run stays resumable.
    Pause,
    /// Stop the run for good; what was acquired stays.
    Abort,
}

/// The link between the station and one going run: requests in, events out.
pub struct RunControl {
    requests: Mutex<VecDeque<Request>>,
    on_event: Box<dyn Fn(Value) + Send + Sync>,
}

impl RunControl {
    /// A link whose events go to `on_event` (as JSON: `{"kind": ...}`).
    pub fn new(on_event: impl Fn(Value) + Send + Sync + 'static) -> RunControl {
        RunControl {
            requests: Mutex::new(VecDeque::new()),
            on_event: Box::new(on_event),
        }
    }

    /// Asks the run for something.
    pub fn request(&self, r: Request) {
        if let Ok(mut q) = self.requests.lock() {
            q.push_back(r);
        }
    }

    /// The oldest request not yet taken (the run polls this).
    pub fn take(&self) -> Option<Request> {
        self.requests.lock().ok().and_then(|mut q| q.pop_front())
    }

    /// The run reports an event.
    pub fn event(&self, e: Value) {
        (self.on_event)(e)
    }
}

/// How a run call ended.
#[derive(Debug, Clone, PartialEq)]
pub struct RunEnd {
    /// `done`, `paused` or `aborted`.
    pub state: String,
    /// Why it paused or was aborted.
    pub reason: Option<String>,
    /// The command's JSON, as `acquire run` prints it.
    pub result: Value,
}

/// One product image of a run: row-major values, NaN where undefined.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// The angle set it was computed from.
    pub set: u64,
    /// The values (DN for S0, 0..1 for DoLP, radians for AoP).
    pub values: Vec<f32>,
}

/// The instrument, as the station uses it. Calls block; the station makes them from its
/// worker thread (runs) or a blocking task (checks).
pub trait Runner: Send + Sync + 'static {
    /// `plan check` of a plan file with the station's rig: the forecast (duration, frames,
    /// DoLP sigma per class, `bytes`), or the error naming the key.
    fn check(&self, plan_file: &Path) -> Result<Value, String>;
    /// Runs a plan file into `run_dir` (new or empty).
    fn run(
        &self,
        plan_file: &Path,
        run_dir: &Path,
        control: &Arc<RunControl>,
    ) -> Result<RunEnd, String>;
    /// Continues the paused or interrupted run in `run_dir` (a finished run: `done` at once).
    fn resume(&self, run_dir: &Path, control: &Arc<RunControl>) -> Result<RunEnd, String>;
    /// Whether a run in `run_dir` got far enough to be resumed (its start was recorded); a
    /// run dir without that holds nothing acquired.
    fn has_started(&self, run_dir: &Path) -> bool;
    /// The rig's site, for schedules' sun windows (`None`: the rig file has no `[site]`).
    fn site(&self) -> Option<crate::schedule::SunSite>;
    /// Whether the rig is simulated (a simulated clock is allowed only then).
    fn simulated(&self) -> bool;
    /// The latest written product image `name` (`s0`, `dolp`, `aop_rad`) of the run in
    /// `run_dir`.
    fn latest_product(&self, run_dir: &Path, name: &str) -> Result<Plane, String>;
    /// The devices: `{"ok": bool, ...}` with what was found (for `/healthz`). Called only
    /// while no run holds them.
    fn devices(&self) -> Value;
}
