//! The endpoints that read: health (no key), status, queue, history, the event stream and the
//! OpenAPI description.

use crate::auth::AppState;
use crate::keys::Scope;
use crate::reply::ApiError;
use crate::shared::{queue_summary, Station};
use axum::extract::{Query, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::IntoResponse;
use axum::Json;
use serde_json::{json, Value};
use std::time::Duration;
use tokio_stream::StreamExt;

/// The earliest time the station's clock may read (a clock before it is wrong: a board
/// without a real-time clock that has not synchronised yet).
const CLOCK_FLOOR_UNIX: u64 = 1_767_225_600; // 2026-01-01

/// `GET /healthz`: healthy only when the devices answer (or the going run has them), the disk
/// has more than the reserve free, the clock is plausible, and no item failed in the last
/// hour. 200 when healthy, 503 when not; the body says which part is wrong.
pub async fn healthz(State(app): State<AppState>) -> impl IntoResponse {
    let st = app.st.clone();
    let body = tokio::task::spawn_blocking(move || health(&st))
        .await
        .unwrap_or_else(|e| json!({"ok": false, "error": e.to_string()}));
    let code = if body["ok"].as_bool() == Some(true) {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    (code, Json(body))
}

fn health(st: &Station) -> Value {
    let state = st.snapshot();
    let going = st.control.lock().map(|c| c.is_some()).unwrap_or(false);
    let devices = if going {
        json!({"ok": true, "note": "a run holds the devices and is going"})
    } else {
        let d = st.runner.devices();
        if let Ok(mut h) = st.health.lock() {
            h.devices = d.clone();
        }
        d
    };
    let free = crate::disk::free_bytes(&st.config.data_dir);
    let disk_ok = free.is_some_and(|f| f >= st.config.reserve_bytes);
    let now = crate::now_unix();
    let clock_ok = now >= CLOCK_FLOOR_UNIX;
    let last_error = st.health.lock().ok().and_then(|h| h.last_error.clone());
    let recent_error = last_error
        .as_ref()
        .is_some_and(|(t, _)| now.saturating_sub(*t) < 3600);
    let devices_ok = devices["ok"].as_bool() == Some(true);
    json!({
        "ok": devices_ok && disk_ok && clock_ok && !recent_error,
        "devices": devices,
        "disk": {"ok": disk_ok, "free_bytes": free, "reserve_bytes": st.config.reserve_bytes,
                 "data_dir": st.config.data_dir.display().to_string()},
        "clock": {"ok": clock_ok, "now": crate::rfc3339(now)},
        "queue": queue_summary(&state),
        "last_error": last_error.map(|(t, m)| json!({"time": crate::rfc3339(t), "message": m})),
    })
}

/// `GET /api/v1/status`.
pub async fn status(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Read, "status").await?;
    let st = &app.st;
    let s = st.snapshot();
    let live = st.live.lock().map(|l| l.clone()).unwrap_or(Value::Null);
    Ok(Json(json!({
        "change_id": st.hub.last_id(),
        "queue_running": s.queue_running,
        "queued": s.queue.len(),
        "current": s.current,
        "live": live,
        "history": s.history.len(),
        "disk_free_bytes": crate::disk::free_bytes(&st.config.data_dir),
        "time": crate::rfc3339(crate::now_unix()),
    })))
}

/// `GET /api/v1/queue`.
pub async fn queue(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Read, "queue").await?;
    let s = app.st.snapshot();
    Ok(Json(
        json!({"queue_running": s.queue_running, "items": s.queue, "current": s.current}),
    ))
}

/// `?limit=N`: the newest N entries.
#[derive(serde::Deserialize)]
pub struct HistoryQuery {
    limit: Option<usize>,
}

/// `GET /api/v1/history[?limit=N]`: newest last.
pub async fn history(
    State(app): State<AppState>,
    headers: HeaderMap,
    query: Result<Query<HistoryQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Read, "history").await?;
    let Query(q) = query.map_err(|e| ApiError::field("limit", e.body_text()))?;
    let s = app.st.snapshot();
    let n = q.limit.unwrap_or(s.history.len()).min(s.history.len());
    Ok(Json(json!({"items": s.history[s.history.len() - n..]})))
}

/// `GET /api/v1/events`: server-sent events (`id:` the change id, `event:` the kind, `data:`
/// the JSON); a `Last-Event-ID` header replays the kept events after it.
pub async fn events(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<impl IntoResponse, ApiError> {
    app.key(&headers, Scope::Read, "events").await?;
    let after = headers
        .get("last-event-id")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    let (rx, missed) = app.st.hub.subscribe(after);
    let hello = app.st.hub.last_id();
    let first = tokio_stream::iter(
        std::iter::once(crate::events::StationEvent {
            id: hello,
            kind: "hello".into(),
            time: crate::rfc3339(crate::now_unix()),
            data: queue_summary(&app.st.snapshot()),
        })
        .chain(missed),
    );
    let live = tokio_stream::wrappers::BroadcastStream::new(rx).filter_map(Result::ok);
    let stream = first.chain(live).map(|e| {
        Ok::<_, std::convert::Infallible>(
            Event::default()
                .id(e.id.to_string())
                .event(e.kind.clone())
                .data(
                    json!({"id": e.id, "kind": e.kind, "time": e.time, "data": e.data}).to_string(),
                ),
        )
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

/// `GET /api/v1/openapi.json`.
pub async fn openapi() -> Json<Value> {
    Json(crate::openapi::document())
}
