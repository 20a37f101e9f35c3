//! The run's link to its controller: what a controller can ask ([`Control`]), where the run
//! is ([`RunState`]), what happened ([`Event`]), and the two ends of the link.

use super::outcome::Verdict;
use serde_json::Value;
use tokio::sync::{mpsc, watch};

/// What a controller can ask of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Pause at the next safe point.
    Pause,
    /// Pause now: cancel the device operation in flight.
    PauseNow,
    /// Continue a paused run.
    Resume,
    /// Stop the run for good, paused or running (what was acquired stays).
    Abort,
    /// Leave a paused run to be resumed later (`polarimeter resume`).
    Detach,
}

/// Where a run is.
#[derive(Debug, Clone, PartialEq)]
pub enum RunState {
    /// Starting devices and storage.
    Starting,
    /// Acquiring.
    Running,
    /// A pause was asked; it happens at the next safe point.
    Pausing,
    /// Paused, with the reason.
    Paused(String),
    /// Finishing after an abort.
    Aborting,
    /// Every planned frame is stored and checked.
    Done,
    /// Aborted, with the reason.
    Aborted(String),
}

/// What happened, for progress bars, logs and the GUI.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The state changed.
    State(RunState),
    /// A frame is durable: `done` of at most `planned` frames.
    Progress {
        /// Frames that count so far, one per step (a frame superseded or in a rejected set
        /// does not).
        done: u64,
        /// Frames the plan takes (an adaptive plan: its budget).
        planned: u64,
        /// The step's label.
        label: String,
    },
    /// A set was checked.
    Set {
        /// The set.
        set: u64,
        /// Accepted or why not.
        verdict: Verdict,
        /// Mean S0, DoLP of the set (over finite pixels).
        mean_s0: f64,
        /// Mean DoLP.
        mean_dolp: f64,
    },
    /// The planner decided (adaptive runs).
    Decision(Value),
    /// A device operation failed and will be retried.
    Retry(String),
}

/// The controller's end: send [`Control`]s, watch the state, read [`Event`]s.
pub struct Controller {
    /// Commands to the run.
    pub control: mpsc::Sender<Control>,
    /// The run's state.
    pub state: watch::Receiver<RunState>,
    /// Events (bounded; the run never waits on a slow reader: events are dropped if full).
    pub events: mpsc::Receiver<Event>,
}

/// The run's end of the controller.
pub struct RunLink {
    pub(super) control: mpsc::Receiver<Control>,
    pub(super) state: watch::Sender<RunState>,
    pub(super) events: mpsc::Sender<Event>,
}

/// A connected controller and run link.
pub fn link() -> (Controller, RunLink) {
    let (ctx, crx) = mpsc::channel(16);
    let (stx, srx) = watch::channel(RunState::Starting);
    let (etx, erx) = mpsc::channel(1024);
    (
        Controller {
            control: ctx,
            state: srx,
            events: erx,
        },
        RunLink {
            control: crx,
            state: stx,
            events: etx,
        },
    )
}

impl RunLink {
    /// Publishes the run's state, on the state watch and as an event.
    pub(super) fn set_state(&self, s: RunState) {
        let _ = self.state.send(s.clone());
        let _ = self.events.try_send(Event::State(s));
    }
}
