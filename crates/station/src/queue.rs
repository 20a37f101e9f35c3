//! The queue's edits and its order: items run by priority (higher first), equal priorities in
//! the order they were added or moved to.

use crate::state::{Item, State};

/// Why an edit was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QueueError {
    /// No queued item has this id.
    #[error("no queued item has the id {0} (GET /api/v1/queue lists them)")]
    NoItem(u64),
    /// A position past the end.
    #[error("position {position} is out of range: 0 to {last} (the queue's length less one)")]
    Position {
        /// Asked.
        position: usize,
        /// The largest allowed.
        last: usize,
    },
}

/// Appends items in order, giving each the next id; their ids.
pub fn add(state: &mut State, items: Vec<Item>) -> Vec<u64> {
    let mut ids = Vec::with_capacity(items.len());
    for mut item in items {
        item.id = state.next_id;
        state.next_id += 1;
        ids.push(item.id);
        state.queue.push(item);
    }
    ids
}

/// The next id [`add`] will give (items' plan files are named by it before they are added).
pub fn peek_ids(state: &State, n: usize) -> std::ops::Range<u64> {
    state.next_id..state.next_id + n as u64
}

/// Moves item `id` to `position` (0: the front).
pub fn move_to(state: &mut State, id: u64, position: usize) -> Result<(), QueueError> {
    let from = index_of(state, id)?;
    let last = state.queue.len() - 1;
    if position > last {
        return Err(QueueError::Position { position, last });
    }
    let item = state.queue.remove(from);
    state.queue.insert(position, item);
    Ok(())
}

/// Removes item `id`.
pub fn remove(state: &mut State, id: u64) -> Result<Item, QueueError> {
    let i = index_of(state, id)?;
    Ok(state.queue.remove(i))
}

/// Where item `id` is in the queue.
pub fn index_of(state: &State, id: u64) -> Result<usize, QueueError> {
    state
        .queue
        .iter()
        .position(|i| i.id == id)
        .ok_or(QueueError::NoItem(id))
}

/// The index of the item to run next among those `ready` allows (their schedule's window
/// is open): the highest priority, the first of equals.
pub fn next(state: &State, ready: impl Fn(&Item) -> bool) -> Option<usize> {
    let mut best: Option<usize> = None;
    for (i, item) in state.queue.iter().enumerate() {
        if ready(item) && best.is_none_or(|b| item.priority > state.queue[b].priority) {
            best = Some(i);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn item(priority: i32) -> Item {
        Item {
            id: 0,
            name: String::new(),
            owner: String::new(),
            priority,
            plan_file: String::new(),
            added_unix: 0,
            forecast: serde_json::Value::Null,
            schedule: None,
            runs_done: 0,
            last_start_unix: None,
        }
    }

    #[test]
    fn ids_are_never_reused_and_priority_then_order_picks_the_next() {
        let mut s = State::new(true);
        assert_eq!(add(&mut s, vec![item(0), item(5), item(5)]), vec![1, 2, 3]);
        assert_eq!(
            s.queue[next(&s, |_| true).unwrap()].id,
            2,
            "the first of the highest priority"
        );
        remove(&mut s, 2).unwrap();
        assert_eq!(
            add(&mut s, vec![item(0)]),
            vec![4],
            "removed ids are not given again"
        );
        move_to(&mut s, 4, 0).unwrap();
        assert_eq!(
            s.queue.iter().map(|i| i.id).collect::<Vec<_>>(),
            vec![4, 1, 3]
        );
        assert_eq!(s.queue[next(&s, |_| true).unwrap()].id, 3);
        assert_eq!(
            move_to(&mut s, 4, 3).unwrap_err(),
            QueueError::Position {
                position: 3,
                last: 2
            }
        );
        assert_eq!(remove(&mut s, 9).unwrap_err(), QueueError::NoItem(9));
    }
}
