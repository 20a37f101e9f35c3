//! The worker: one thread that takes the station's items one at a time. It starts the next
//! queued item when the queue runs, resumes a paused one when asked (or when the station
//! stopped it to shut down), resumes the run a crash or power cut interrupted, aborts a paused
//! run when asked, and pauses a going run when the disk reaches the reserve. Every change is
//! saved before the run call it leads to, so a restart knows where it was.

use crate::queue;
use crate::runner::{Request, RunControl, RunEnd};
use crate::shared::{EditError, Station};
use crate::state::{Current, ExitState, Phase, State};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// How often a going run's disk is checked against the reserve.
const DISK_POLL: Duration = Duration::from_secs(1);

/// What the worker does next.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Job {
    /// Start the queued item with this id (looked up again when taken: the queue may have
    /// changed since it was chosen).
    Start(u64),
    /// Resume the current item's run (`crashed`: it was going when the station died).
    Resume { crashed: bool },
    /// Abort the paused current item's run.
    AbortPaused,
}

fn next_job(s: &State, ready: impl Fn(&crate::state::Item) -> bool) -> Option<Job> {
    match &s.current {
        Some(c) if c.phase == Phase::Running => Some(Job::Resume { crashed: true }),
        Some(c) if c.abort_requested => Some(Job::AbortPaused),
        Some(c) if c.resume_requested || c.resume_on_start => Some(Job::Resume { crashed: false }),
        Some(_) => None,
        None if s.queue_running => queue::next(s, ready).map(|i| Job::Start(s.queue[i].id)),
        None => None,
    }
}

/// Starts the worker thread.
pub fn spawn(st: Arc<Station>) -> std::io::Result<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name("station-worker".into())
        .spawn(move || work(&st))
}

fn work(st: &Arc<Station>) {
    loop {
        let job = {
            let mut g = st.lock();
            loop {
                if st.stopping.load(Ordering::SeqCst) {
                    return;
                }
                let now = st.now();
                if let Some(j) = next_job(&g, |i| st.ready(i, now)) {
                    break j;
                }
                // A minute of station time at most (schedules open to the minute), 1 s at most.
                let poll = Duration::from_secs_f64((60.0 / st.clock.speed()).clamp(0.02, 1.0));
                g = st
                    .wake
                    .wait_timeout(g, poll)
                    .map_or_else(|p| p.into_inner().0, |r| r.0);
            }
        };
        if let Err(e) = take(st, job) {
            st.note_error(&e);
            // A state that cannot be saved is not retried at full speed.
            std::thread::sleep(Duration::from_secs(1));
        }
    }
}

/// The run directory of an item: `runs/ID-NAME` (the name's letters and digits only), with a
/// suffix when a directory of that name holds an earlier attempt.
fn run_dir_for(st: &Station, id: u64, name: &str) -> String {
    let slug: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '-'
            }
        })
        .take(48)
        .collect();
    let base = format!("runs/{id}-{slug}");
    let mut candidate = base.clone();
    let mut n = 2;
    while st.config.data_dir.join(&candidate).exists() {
        candidate = format!("{base}-{n}");
        n += 1;
    }
    candidate
}

fn save_err<E: std::fmt::Display>(e: EditError<E>) -> String {
    match e {
        EditError::Refused(e) => e.to_string(),
        EditError::Save(e) => format!("the station's state could not be saved: {e}"),
    }
}

/// The state change that begins `job`, made and saved before any run call: the current item
/// and whether its run starts fresh; `None` when an edit since the job was chosen took it away
/// (the item removed, or no longer ready).
fn begin(st: &Station, s: &mut State, job: Job, now: u64) -> Option<(Current, bool)> {
    let fresh = match job {
        Job::Start(id) => {
            let i = queue::index_of(s, id).ok()?;
            if s.current.is_some() || !st.ready(&s.queue[i], now) {
                return None;
            }
            // A repeating item stays queued until its runs are used up.
            let queued = &mut s.queue[i];
            queued.runs_done += 1;
            queued.last_start_unix = Some(now);
            let more = queued
                .schedule
                .as_ref()
                .is_some_and(|sc| sc.runs_left(queued.runs_done));
            let item = if more {
                queued.clone()
            } else {
                s.queue.remove(i)
            };
            let run_dir = run_dir_for(st, item.id, &item.name);
            s.current = Some(Current::new(item, run_dir, now));
            true
        }
        Job::Resume { .. } | Job::AbortPaused => {
            let c = s.current.as_mut()?;
            c.phase = Phase::Running;
            c.pause_reason = None;
            c.resume_requested = false;
            c.resume_on_start = false;
            false
        }
    };
    Some((s.current.clone()?, fresh))
}

fn take(st: &Arc<Station>, job: Job) -> Result<(), String> {
    let now = st.now();
    let begun = st
        .edit(|s| -> Result<_, String> { Ok(begin(st, s, job, now)) })
        .map_err(save_err)?;
    let Some((current, fresh)) = begun else {
        return Ok(());
    };
    let run_dir = st.config.data_dir.join(&current.run_dir);
    let plan_file = st.config.data_dir.join(&current.item.plan_file);
    // A run whose start a crash interrupted holds nothing: it starts again, in a new directory.
    let started = !fresh && st.runner.has_started(&run_dir);
    let run_dir = if !fresh && !started && run_dir.exists() {
        restart_dir(st, &current)?
    } else {
        run_dir
    };
    if started && job == (Job::Resume { crashed: true }) {
        st.edit(|s| -> Result<(), String> {
            if let Some(c) = s.current.as_mut() {
                c.crash_resumes += 1;
            }
            Ok(())
        })
        .map_err(save_err)?;
    }
    let abort_first = job == Job::AbortPaused;
    let end = execute(
        st,
        current.item.id,
        &plan_file,
        &run_dir,
        !started,
        abort_first,
    );
    conclude(st, end)?;
    archive_history(st)
}

/// A new run directory for an item whose first one never started; saved as the item's.
fn restart_dir(st: &Arc<Station>, current: &Current) -> Result<PathBuf, String> {
    let dir = run_dir_for(st, current.item.id, &current.item.name);
    st.edit(|s| -> Result<(), String> {
        if let Some(c) = s.current.as_mut() {
            c.run_dir = dir.clone();
        }
        Ok(())
    })
    .map_err(save_err)?;
    Ok(st.config.data_dir.join(dir))
}

/// Runs (or resumes) with a link the API can reach and a disk watch; how it ended, and
/// whether the disk watch paused it.
fn execute(
    st: &Arc<Station>,
    item_id: u64,
    plan_file: &std::path::Path,
    run_dir: &std::path::Path,
    fresh: bool,
    abort_first: bool,
) -> (Result<RunEnd, String>, bool) {
    let events = st.clone();
    let control = Arc::new(RunControl::new(move |e| run_event(&events, e)));
    if abort_first {
        control.request(Request::Abort);
    }
    if let Ok(mut c) = st.control.lock() {
        *c = Some((item_id, control.clone()));
    }
    // An abort asked before the link existed.
    if !abort_first && st.snapshot().current.is_some_and(|c| c.abort_requested) {
        control.request(Request::Abort);
    }
    let done = AtomicBool::new(false);
    let disk_full = AtomicBool::new(false);
    let end = std::thread::scope(|scope| {
        scope.spawn(|| {
            while !done.load(Ordering::SeqCst) {
                let low = crate::disk::free_bytes(&st.config.data_dir)
                    .is_some_and(|f| f < st.config.reserve_bytes);
                if low && !disk_full.swap(true, Ordering::SeqCst) {
                    st.note_error("free disk reached the station's reserve: pausing the run");
                    control.request(Request::Pause);
                }
                std::thread::sleep(DISK_POLL);
            }
        });
        let end = if fresh {
            st.runner.run(plan_file, run_dir, &control)
        } else {
            st.runner.resume(run_dir, &control)
        };
        done.store(true, Ordering::SeqCst);
        end
    });
    if let Ok(mut c) = st.control.lock() {
        *c = None;
    }
    (end, disk_full.load(Ordering::SeqCst))
}

/// History entries kept in the state (each edit saves the whole state); older ones move to
/// `history-archive.jsonl` in the data directory, one JSON line each.
const HISTORY_KEPT: usize = 1000;

/// Moves the history's oldest entries beyond [`HISTORY_KEPT`] to the archive (appended and
/// flushed before the state drops them: a crash between leaves them in both, never neither).
fn archive_history(st: &Station) -> Result<(), String> {
    let old: Vec<_> = {
        let s = st.lock();
        let excess = s.history.len().saturating_sub(HISTORY_KEPT);
        s.history[..excess].to_vec()
    };
    if old.is_empty() {
        return Ok(());
    }
    let path = st.config.data_dir.join("history-archive.jsonl");
    let mut text = String::new();
    for e in &old {
        text.push_str(&serde_json::to_string(e).map_err(|e| e.to_string())?);
        text.push('\n');
    }
    use std::io::Write;
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .and_then(|mut f| {
            f.write_all(text.as_bytes())?;
            f.sync_data()
        })
        .map_err(|e| format!("{}: {e}", path.display()))?;
    st.edit(|s| -> Result<(), String> {
        s.history.drain(..old.len().min(s.history.len()));
        Ok(())
    })
    .map_err(save_err)
}

/// A run's event: published, and kept as the latest progress or set.
fn run_event(st: &Station, e: Value) {
    let kind = e["kind"].as_str().unwrap_or("run").to_string();
    if kind == "progress" || kind == "set" {
        if let Ok(mut live) = st.live.lock() {
            live[kind.as_str()] = e.clone();
        }
    }
    st.hub.publish(&format!("run.{kind}"), e);
}

/// The current item after its run call: finished, aborted or failed items go to the history;
/// a paused one waits (resumed on start when the station paused it to stop).
fn conclude(
    st: &Arc<Station>,
    (end, disk_full): (Result<RunEnd, String>, bool),
) -> Result<(), String> {
    let now = st.now();
    let uploads = st.config.upload.is_some();
    let stopping = st.stopping.load(Ordering::SeqCst);
    if let Err(e) = &end {
        st.note_error(&format!("the item's run failed: {e}"));
    }
    if let Ok(mut live) = st.live.lock() {
        *live = json!({});
    }
    st.edit(|s| -> Result<(), String> {
        match end {
            Ok(RunEnd {
                state,
                reason,
                result,
            }) => match state.as_str() {
                "done" => {
                    let warnings = result["warnings"].as_array().map_or(String::new(), |w| {
                        w.iter()
                            .filter_map(Value::as_str)
                            .collect::<Vec<_>>()
                            .join("; ")
                    });
                    s.finish_current((ExitState::Done, warnings), result, now, uploads)
                }
                "aborted" => {
                    let why = reason.unwrap_or_default();
                    s.finish_current((ExitState::Aborted, why), result, now, uploads)
                }
                _ => {
                    if let Some(c) = s.current.as_mut() {
                        c.phase = Phase::Paused;
                        c.pause_reason = Some(if disk_full {
                            "free disk reached the station's reserve".to_string()
                        } else {
                            reason.unwrap_or_else(|| "paused".into())
                        });
                        c.resume_on_start = stopping && !disk_full && !c.abort_requested;
                    }
                }
            },
            Err(e) => s.finish_current((ExitState::Failed, e), Value::Null, now, uploads),
        }
        Ok(())
    })
    .map_err(save_err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state::Item;

    fn item(id: u64) -> Item {
        Item {
            id,
            name: "n".into(),
            owner: "k".into(),
            priority: 0,
            plan_file: String::new(),
            added_unix: 0,
            forecast: Value::Null,
            schedule: None,
            runs_done: 0,
            last_start_unix: None,
        }
    }

    #[test]
    fn a_run_going_at_start_is_resumed_before_anything_is_taken() {
        let mut s = State::new(true);
        s.queue.push(item(2));
        assert_eq!(next_job(&s, |_| true), Some(Job::Start(2)));
        s.current = Some(Current::new(item(1), "runs/1-n".into(), 0));
        assert_eq!(next_job(&s, |_| true), Some(Job::Resume { crashed: true }));
        let c = s.current.as_mut().unwrap();
        c.phase = Phase::Paused;
        assert_eq!(
            next_job(&s, |_| true),
            None,
            "a paused item waits; the queue does not pass it"
        );
        s.current.as_mut().unwrap().abort_requested = true;
        assert_eq!(next_job(&s, |_| true), Some(Job::AbortPaused));
        s.current = None;
        s.queue_running = false;
        assert_eq!(
            next_job(&s, |_| true),
            None,
            "a stopped queue takes nothing"
        );
    }
}
