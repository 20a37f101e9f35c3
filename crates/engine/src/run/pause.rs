//! The paused state both run loops share: the pause is journaled with the step the run goes on
//! from, the run waits for its controller, and a resume is journaled before the loop goes on.
//! Each loop first brings its devices to their safe state and drains its storage thread.

use super::clock::now_unix_ns;
use super::link::{Control, RunLink, RunState};
use super::outcome::{Outcome, RunError};
use super::writer::ToStore;
use crate::journal::Entry;
use std::time::SystemTime;
use tracing::info;

/// The pause before dark frames on hardware (no simulated lens cap): the operator caps the
/// lens and resumes the run.
pub const CAP_LENS: &str = "cap the lens for the dark frames, then resume";
/// The pause after dark frames on hardware: the operator uncaps the lens and resumes.
pub const UNCAP_LENS: &str = "uncap the lens, then resume";

/// Outcome of waiting at a pause.
pub(super) enum AfterPause {
    Resume,
    Abort(String),
    Detach(String),
}

impl AfterPause {
    /// The outcome that ends the run (`None`: the run goes on).
    pub(super) fn ending(self) -> Option<Outcome> {
        match self {
            AfterPause::Resume => None,
            AfterPause::Abort(r) => Some(Outcome::Aborted(r)),
            AfterPause::Detach(r) => Some(Outcome::Paused(r)),
        }
    }
}

/// Sends `msg` to the storage thread (an error if it has stopped).
pub(super) fn send_store(
    to_store: &std::sync::mpsc::SyncSender<ToStore>,
    msg: ToStore,
) -> Result<(), RunError> {
    to_store
        .send(msg)
        .map_err(|_| RunError::Storage("the storage thread stopped".into()))
}

/// Syncs the metadata, journals the pause (`reason`, and `next_step`, where the run goes on),
/// shows the paused state and waits for the controller: a resume is journaled and the run is
/// running again; an abort, a detach or a dropped controller ends the wait.
pub(super) async fn hold_paused(
    link: &mut RunLink,
    to_store: &std::sync::mpsc::SyncSender<ToStore>,
    reason: &str,
    next_step: u64,
) -> Result<AfterPause, RunError> {
    send_store(to_store, ToStore::SyncMetadata)?;
    info!(reason = %reason, "paused");
    send_store(
        to_store,
        ToStore::Entry(Entry::Paused {
            reason: reason.to_string(),
            next_step,
        }),
    )?;
    link.set_state(RunState::Paused(reason.to_string()));
    loop {
        match link.control.recv().await {
            Some(Control::Resume) => {
                send_store(
                    to_store,
                    ToStore::Entry(Entry::Resumed {
                        process_id: std::process::id(),
                        at_unix_ns: now_unix_ns(SystemTime::now()),
                    }),
                )?;
                link.set_state(RunState::Running);
                return Ok(AfterPause::Resume);
            }
            Some(Control::Abort) => return Ok(AfterPause::Abort(reason.to_string())),
            Some(Control::Detach) | None => return Ok(AfterPause::Detach(reason.to_string())),
            Some(Control::Pause | Control::PauseNow) => {}
        }
    }
}
