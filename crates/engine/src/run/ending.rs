//! How both run loops end: an abort journaled, or the storage thread's final checks passed and
//! the run done. A pause ends a loop too, with nothing more to journal ([`super::pause`]).

use super::link::{RunLink, RunState};
use super::outcome::{Outcome, RunError};
use super::pause::send_store;
use super::writer::{FinishChecks, ToStore};
use crate::journal::Entry;
use serde_json::Value;

/// Journals the abort (`reason`) and shows the aborting and aborted states.
pub(super) fn end_aborted(
    link: &RunLink,
    to_store: &std::sync::mpsc::SyncSender<ToStore>,
    reason: String,
) -> Result<Outcome, RunError> {
    link.set_state(RunState::Aborting);
    send_store(
        to_store,
        ToStore::Entry(Entry::Aborted {
            reason: reason.clone(),
        }),
    )?;
    link.set_state(RunState::Aborted(reason.clone()));
    Ok(Outcome::Aborted(reason))
}

/// Asks the storage thread to finish the run (its final `checks`, the `summary` attribute),
/// waits for its verdict and shows the done state.
pub(super) async fn end_done(
    link: &RunLink,
    to_store: &std::sync::mpsc::SyncSender<ToStore>,
    summary: Value,
    checks: FinishChecks,
) -> Result<(), RunError> {
    let (reply, rx) = std::sync::mpsc::channel();
    send_store(
        to_store,
        ToStore::Finish {
            reply,
            summary,
            checks,
        },
    )?;
    finish_verdict(rx).await?;
    link.set_state(RunState::Done);
    Ok(())
}

/// Waits for the storage thread's answer to `ToStore::Finish`: the run's final checks passed,
/// or the check that failed.
async fn finish_verdict(
    rx: std::sync::mpsc::Receiver<Result<Value, String>>,
) -> Result<(), RunError> {
    tokio::task::spawn_blocking(move || rx.recv())
        .await
        .map_err(|e| RunError::Storage(e.to_string()))?
        .map_err(|_| RunError::Storage("the storage thread stopped".into()))?
        .map(|_| ())
        .map_err(RunError::Check)
}
