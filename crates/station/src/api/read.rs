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
        st.runner.devices()
    };
    let free = crate::disk::free_bytes(&st.config.data_dir);
    let disk_ok = free.is_some_and(|f| f >= st.config.reserve_bytes);
    let now = crate::now_unix();
    let clock_ok = now >= CLOCK_FLOOR_UNIX;
    let last_error = st.last_error.lock().ok().and_then(|e| e.clone());
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

/// `GET /api/v1/status`: the queue in brief, the current item and its live progress, the
/// next scheduled start, the station's time and the sun's elevation at the rig's site.
pub async fn status(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Read, "status").await?;
    let st = &app.st;
    let s = st.snapshot();
    let now = st.now();
    // The queue's next start: the earliest of its items' (the queue's order breaks ties).
    let next = s
        .queue
        .iter()
        .filter_map(|i| st.next_start(i, now).map(|t| (i.id, t)))
        .min_by_key(|(_, t)| *t);
    let live = st.live.lock().map(|l| l.clone()).unwrap_or(Value::Null);
    let sun = st
        .site
        .as_ref()
        .and_then(|site| crate::schedule::sun_elevation_deg(site, now));
    Ok(Json(json!({
        "change_id": st.hub.last_id(),
        "queue_running": s.queue_running,
        "queued": s.queue.len(),
        "current": s.current,
        "live": live,
        "history": s.history.len(),
        "disk_free_bytes": crate::disk::free_bytes(&st.config.data_dir),
        "time": crate::rfc3339(now),
        "clock": {"simulated": !st.clock.is_system(), "speed": st.clock.speed()},
        "next_start": next.map(|(id, t)| json!({"id": id, "time": crate::rfc3339(t)})),
        "sun_elevation_deg": sun,
    })))
}

/// `GET /api/v1/queue`: the items in order, each with its next start (station time).
pub async fn queue(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Read, "queue").await?;
    let s = app.st.snapshot();
    let now = app.st.now();
    let items: Vec<Value> = s
        .queue
        .iter()
        .map(|i| {
            let mut v = json!(i);
            v["next_start"] = json!(app.st.next_start(i, now).map(crate::rfc3339));
            v
        })
        .collect();
    Ok(Json(
        json!({"queue_running": s.queue_running, "items": items,
                   "current": s.current, "time": crate::rfc3339(now)}),
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
    // `hello` carries no id: a client that reconnects after it asks from the id it last saw.
    let hello = Event::default().event("hello").data(
        json!({"kind": "hello", "time": crate::rfc3339(crate::now_unix()),
               "data": queue_summary(&app.st.snapshot())})
        .to_string(),
    );
    let events = tokio_stream::iter(missed)
        .chain(tokio_stream::wrappers::BroadcastStream::new(rx).filter_map(Result::ok))
        .map(|e| {
            Event::default()
                .id(e.id.to_string())
                .event(e.kind.clone())
                .data(
                    json!({"id": e.id, "kind": e.kind, "time": e.time, "data": e.data}).to_string(),
                )
        });
    // The stream ends when the station stops.
    let ended = tokio_stream::wrappers::WatchStream::new(app.st.shutdown.subscribe())
        .filter(|stopping| *stopping)
        .map(|_| None);
    let stream = tokio_stream::once(hello)
        .chain(events)
        .map(Some)
        .merge(ended)
        .take_while(Option::is_some)
        .filter_map(|e| e.map(Ok::<_, std::convert::Infallible>));
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}

/// `GET /api/v1/products/latest/{name}`: a PNG of the latest set's `s0`, `dolp` or `aop`, from
/// the current item's run, else the last finished one's (404 while none has a set).
pub async fn product(
    State(app): State<AppState>,
    headers: HeaderMap,
    axum::extract::Path(name): axum::extract::Path<String>,
) -> Result<impl IntoResponse, ApiError> {
    app.key(&headers, Scope::Read, "product").await?;
    let stem = name.strip_suffix(".png").unwrap_or(&name).to_string();
    let Some((_, stored)) = crate::picture::PRODUCTS.iter().find(|(n, _)| *n == stem) else {
        return Err(ApiError::field(
            "name",
            format!("{name:?} is not a product: s0, dolp or aop"),
        ));
    };
    let st = app.st.clone();
    let png = tokio::task::spawn_blocking(move || {
        let s = st.snapshot();
        let dirs = s.current.iter().map(|c| c.run_dir.clone()).chain(
            s.history
                .iter()
                .rev()
                .map(|h| h.run_dir.clone())
                .filter(|d| !d.is_empty()),
        );
        for dir in dirs.take(3) {
            if let Ok(plane) = st
                .runner
                .latest_product(&st.config.data_dir.join(&dir), stored)
            {
                return crate::picture::render(&stem, &plane).map_err(ApiError::internal);
            }
        }
        Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "no run has a product image yet",
        ))
    })
    .await
    .map_err(ApiError::internal)??;
    Ok(([(axum::http::header::CONTENT_TYPE, "image/png")], png))
}

/// `GET /api/v1/openapi.json`.
pub async fn openapi() -> Json<Value> {
    Json(crate::openapi::document())
}
