//! Run control, apart from queue control: pause the running item at its next set boundary,
//! resume it, abort it (its owner, or an admin key for another key's item; logged either way).

use crate::auth::AppState;
use crate::keys::Scope;
use crate::reply::{audited, ApiError};
use crate::runner::Request;
use crate::shared::EditError;
use crate::state::Phase;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::Json;
use serde_json::{json, Value};

fn answer(
    app: &AppState,
    key: &str,
    action: &str,
    r: Result<u64, EditError<ApiError>>,
) -> Result<Json<Value>, ApiError> {
    audited(&app.st, key, action, u64::to_string, r).map(|id| Json(json!({"ok": true, "id": id})))
}

fn nothing() -> ApiError {
    ApiError::conflict("no item is running or paused (GET /api/v1/status)")
}

/// Sends `r` to item `id`'s going run; whether it was going.
fn send(app: &AppState, id: u64, r: Request) -> bool {
    let link = app.st.control.lock().ok().and_then(|c| c.clone());
    match link {
        Some((going, l)) if going == id => {
            l.request(r);
            true
        }
        _ => false,
    }
}

/// `POST /api/v1/run/pause`: the running item pauses at its next set boundary (its run stays
/// resumable); the answer comes at once, the pause when it happens (events: `run.state`).
pub async fn pause(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Control, "run.pause").await?;
    let s = app.st.snapshot();
    let r = match &s.current {
        Some(c) if c.phase == Phase::Running => {
            if send(&app, c.item.id, Request::Pause) {
                Ok(c.item.id)
            } else {
                Err(EditError::Refused(ApiError::conflict(
                    "the item's run is starting or ending: try again",
                )))
            }
        }
        Some(_) => Err(EditError::Refused(ApiError::conflict(
            "the item is already paused",
        ))),
        None => Err(EditError::Refused(nothing())),
    };
    answer(&app, &key.id, "run.pause", r)
}

/// `POST /api/v1/run/resume`: the paused item goes on.
pub async fn resume(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Control, "run.resume").await?;
    let r = app.st.edit(|s| -> Result<u64, ApiError> {
        let c = s.current.as_mut().ok_or_else(nothing)?;
        if c.phase != Phase::Paused {
            return Err(ApiError::conflict("the item is running, not paused"));
        }
        c.resume_requested = true;
        Ok(c.item.id)
    });
    answer(&app, &key.id, "run.resume", r)
}

/// `POST /api/v1/run/abort`: the current item stops for good, running or paused; what was
/// acquired stays. Another key's item needs the admin scope.
pub async fn abort(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Control, "run.abort").await?;
    let admin = key.allows(Scope::Admin);
    let r = app.st.edit(|s| -> Result<(u64, bool), ApiError> {
        let c = s.current.as_mut().ok_or_else(nothing)?;
        if c.item.owner != key.id && !admin {
            return Err(ApiError::new(
                StatusCode::FORBIDDEN,
                format!(
                    "the item belongs to key {}: aborting another key's item needs the admin scope",
                    c.item.owner
                ),
            ));
        }
        c.abort_requested = true;
        Ok((c.item.id, c.phase == Phase::Running))
    });
    // A run that is not going yet takes the abort from the state when its link is made.
    let r = r.map(|(id, running)| {
        if running {
            send(&app, id, Request::Abort);
        }
        id
    });
    answer(&app, &key.id, "run.abort", r)
}
