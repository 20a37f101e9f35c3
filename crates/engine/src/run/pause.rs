//! The paused state both run loops share: the pause is journaled with the step the run goes on
//! from, the run waits for its controller, and a resume is journaled before the loop goes on.
//! Each loop first brings its devices to their safe state and drains its storage thread.

use super::*;

/// Outcome of waiting at a pause.
pub(super) enum AfterPause {
    Resume,
    Abort(String),
    Detach(String),
}

impl RunLink {
    /// Publishes the run's state, on the state watch and as an event.
    pub(super) fn set_state(&self, s: RunState) {
        let _ = self.state.send(s.clone());
        let _ = self.events.try_send(Event::State(s));
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
