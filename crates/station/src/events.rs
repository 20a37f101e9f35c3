//! Status and log events with change ids: each event the station publishes gets the next id,
//! and `GET /api/v1/status` reports the id of the last one, so a client that reconnects knows
//! what it missed (`Last-Event-ID` on the event stream replays the recent ones).

use serde::Serialize;
use serde_json::Value;
use std::collections::VecDeque;
use std::sync::Mutex;
use tokio::sync::broadcast;

/// Events kept for clients that reconnect.
const REPLAY: usize = 256;

/// One event: its change id, kind (`state`, `progress`, `set`, `queue`, `item`, `log`) and data.
#[derive(Debug, Clone, Serialize)]
pub struct StationEvent {
    /// The change id (increasing, from 1).
    pub id: u64,
    /// What changed.
    pub kind: String,
    /// When, RFC 3339.
    pub time: String,
    /// The details.
    pub data: Value,
}

/// Publishes events to every listener and keeps the recent ones.
pub struct Hub {
    tx: broadcast::Sender<StationEvent>,
    recent: Mutex<(u64, VecDeque<StationEvent>)>,
}

impl Default for Hub {
    fn default() -> Self {
        Hub::new()
    }
}

impl Hub {
    /// A hub with no listeners.
    pub fn new() -> Hub {
        let (tx, _) = broadcast::channel(1024);
        Hub {
            tx,
            recent: Mutex::new((0, VecDeque::new())),
        }
    }

    /// Publishes an event; its change id.
    pub fn publish(&self, kind: &str, data: Value) -> u64 {
        let Ok(mut recent) = self.recent.lock() else {
            return 0;
        };
        recent.0 += 1;
        let e = StationEvent {
            id: recent.0,
            kind: kind.to_string(),
            time: crate::rfc3339(crate::now_unix()),
            data,
        };
        if recent.1.len() == REPLAY {
            recent.1.pop_front();
        }
        recent.1.push_back(e.clone());
        // Sent under the lock, so listeners see ids in order.
        let _ = self.tx.send(e);
        recent.0
    }

    /// The last change id.
    pub fn last_id(&self) -> u64 {
        self.recent.lock().map_or(0, |r| r.0)
    }

    /// A new listener, and the kept events after `after` (for a reconnecting client).
    pub fn subscribe(
        &self,
        after: Option<u64>,
    ) -> (broadcast::Receiver<StationEvent>, Vec<StationEvent>) {
        let Ok(recent) = self.recent.lock() else {
            return (self.tx.subscribe(), Vec::new());
        };
        let missed = after.map_or_else(Vec::new, |a| {
            recent.1.iter().filter(|e| e.id > a).cloned().collect()
        });
        (self.tx.subscribe(), missed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_increase_and_a_reconnecting_listener_gets_what_it_missed() {
        let hub = Hub::new();
        hub.publish("a", Value::Null);
        let (mut rx, _) = hub.subscribe(None);
        assert_eq!(hub.publish("b", Value::Null), 2);
        assert_eq!(rx.try_recv().unwrap().kind, "b");
        let (_, missed) = hub.subscribe(Some(1));
        assert_eq!(missed.iter().map(|e| e.id).collect::<Vec<_>>(), vec![2]);
        assert_eq!(hub.last_id(), 2);
    }
}
