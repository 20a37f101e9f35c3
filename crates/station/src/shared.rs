//! The station as the API and the worker share it: its settings, its state (saved on every
//! edit), the link to the going run, the keys, the event hub and what health knows.

use crate::audit::Audit;
use crate::clock::Clock;
use crate::config::Config;
use crate::error::StationError;
use crate::events::Hub;
use crate::keys::KeyStore;
use crate::runner::{RunControl, Runner};
use crate::schedule::SunSite;
use crate::state::Item;
use crate::state::State;
use serde_json::{json, Value};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::SystemTime;

/// The keys as last read, reloaded when `station key create` or `revoke` changes the file.
pub struct KeyCache {
    /// The keys.
    pub store: KeyStore,
    seen: Option<(SystemTime, u64)>,
}

/// The station (module docs).
pub struct Station {
    /// Its settings.
    pub config: Config,
    state: Mutex<State>,
    /// Wakes the worker after an edit.
    pub wake: Condvar,
    /// Status and log events.
    pub hub: Hub,
    /// The instrument.
    pub runner: Arc<dyn Runner>,
    /// The going run's link and its item's id, while one goes.
    pub control: Mutex<Option<(u64, Arc<RunControl>)>>,
    /// The keys.
    pub keys: Mutex<KeyCache>,
    /// The audit log.
    pub audit: Audit,
    /// The last error (a failed item, a full disk), with its time, for `/healthz`.
    pub last_error: Mutex<Option<(u64, String)>>,
    /// The going run's latest progress and set (`{"progress": ..., "set": ...}`).
    pub live: Mutex<Value>,
    /// Set when the station is stopping: the worker takes nothing new.
    pub stopping: AtomicBool,
    /// Station time for schedules and the history.
    pub clock: Clock,
    /// The rig's site, for sun windows.
    pub site: Option<SunSite>,
    /// Becomes true when the station stops (ends the event streams).
    pub shutdown: tokio::sync::watch::Sender<bool>,
    /// The data directory's lock, held while the station lives: one station per directory.
    _lock: std::fs::File,
}

impl Station {
    /// Opens the station's data directory (made if missing), its state and keys.
    pub fn open(config: Config, runner: Arc<dyn Runner>) -> Result<Arc<Station>, StationError> {
        for d in [
            config.data_dir.clone(),
            config.items_dir(),
            config.runs_dir(),
        ] {
            std::fs::create_dir_all(&d).map_err(|e| StationError::io(&d, e))?;
        }
        let lock_path = config.data_dir.join(".lock");
        let lock = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .map_err(|e| StationError::io(&lock_path, e))?;
        if lock.try_lock().is_err() {
            return Err(StationError::Config {
                file: config.path.display().to_string(),
                key: "data_dir".into(),
                message: format!(
                    "{} is in use by another station (one station per data directory)",
                    config.data_dir.display()
                ),
            });
        }
        let state = State::load(&config.state_file(), config.autostart)?;
        let clock = match config.sim_clock {
            None => Clock::system(),
            Some(_) if !runner.simulated() => {
                return Err(StationError::Config {
                    file: config.path.display().to_string(),
                    key: "simulation".into(),
                    message: "a simulated clock needs a simulated rig (the rig file's stage \
                              port \"sim\"): a real instrument runs on the real clock"
                        .into(),
                })
            }
            Some((start, speed)) => Clock::simulated(start, speed),
        };
        let site = runner.site();
        let store = KeyStore::load(&config.keys_file())?;
        Ok(Arc::new(Station {
            audit: Audit::new(config.audit_file()),
            state: Mutex::new(state),
            wake: Condvar::new(),
            hub: Hub::new(),
            runner,
            control: Mutex::new(None),
            keys: Mutex::new(KeyCache { store, seen: None }),
            last_error: Mutex::new(None),
            live: Mutex::new(json!({})),
            stopping: AtomicBool::new(false),
            clock,
            site,
            shutdown: tokio::sync::watch::channel(false).0,
            _lock: lock,
            config,
        }))
    }

    /// The state, locked (for the worker's waits; edits go through [`Station::edit`]).
    pub fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Station time, Unix seconds.
    pub fn now(&self) -> u64 {
        self.clock.now_unix()
    }

    /// When `item` may next start (station time; `None`: never again, or not within the
    /// schedule's horizon).
    pub fn next_start(&self, item: &Item, now: u64) -> Option<u64> {
        match &item.schedule {
            None => Some(now),
            Some(s) => s.next_start(
                now,
                item.last_start_unix,
                item.runs_done,
                self.site.as_ref(),
                self.config.utc_offset_s,
            ),
        }
    }

    /// Whether `item` may start now.
    pub fn ready(&self, item: &Item, now: u64) -> bool {
        item.schedule.as_ref().is_none_or(|s| {
            s.ready_at(
                now,
                item.last_start_unix,
                item.runs_done,
                self.site.as_ref(),
                self.config.utc_offset_s,
            )
        })
    }

    /// A copy of the state.
    pub fn snapshot(&self) -> State {
        self.lock().clone()
    }

    /// Applies `f` to a copy of the state, saves the copy, and only then makes it the state
    /// (a save that fails changes nothing); wakes the worker and publishes a `queue` event.
    pub fn edit<T, E>(
        &self,
        f: impl FnOnce(&mut State) -> Result<T, E>,
    ) -> Result<T, EditError<E>> {
        let mut guard = self.lock();
        let mut next = guard.clone();
        let out = f(&mut next).map_err(EditError::Refused)?;
        if next != *guard {
            next.save(&self.config.state_file())
                .map_err(EditError::Save)?;
            *guard = next;
            // Published under the state lock, so the events' order is the edits' (the hub
            // takes no other lock).
            self.hub.publish("queue", queue_summary(&guard));
            drop(guard);
            self.wake.notify_all();
        }
        Ok(out)
    }

    /// The keys, reloaded if their file changed since last read.
    pub fn key_store(&self) -> Result<MutexGuard<'_, KeyCache>, StationError> {
        let mut cache = self.keys.lock().unwrap_or_else(|p| p.into_inner());
        let path = self.config.keys_file();
        let seen = std::fs::metadata(&path)
            .ok()
            .and_then(|m| Some((m.modified().ok()?, m.len())));
        if seen != cache.seen {
            cache.store = KeyStore::load(&path)?;
            cache.seen = seen;
        }
        Ok(cache)
    }

    /// Records an error for `/healthz` and the event stream.
    pub fn note_error(&self, message: &str) {
        tracing::warn!("{message}");
        if let Ok(mut e) = self.last_error.lock() {
            *e = Some((crate::now_unix(), message.to_string()));
        }
        self.hub
            .publish("log", json!({"level": "error", "message": message}));
    }
}

/// Why [`Station::edit`] changed nothing.
#[derive(Debug)]
pub enum EditError<E> {
    /// `f` refused the edit.
    Refused(E),
    /// The new state could not be saved.
    Save(StationError),
}

/// The queue in brief, for events.
pub fn queue_summary(s: &State) -> Value {
    json!({
        "queue_running": s.queue_running,
        "queued": s.queue.iter().map(|i| i.id).collect::<Vec<_>>(),
        "current": s.current.as_ref().map(|c| json!({"id": c.item.id, "phase": c.phase})),
        "history": s.history.len(),
    })
}
