//! The endpoints that edit the queue: add (one plan or a batch, all or nothing), validate
//! without queuing, remove, clear, move, start and stop. A plan is checked exactly as
//! `polarimeter plan check --rig RIG` checks it, and its forecast bytes must fit on the disk
//! above the station's reserve. Every edit is audited with its key's id.

use crate::auth::AppState;
use crate::keys::{KeyRecord, Scope};
use crate::queue;
use crate::reply::{audited, body, parse_body, ApiError};
use crate::schedule::Schedule;
use crate::shared::{EditError, Station};
use crate::state::{ExitState, Item, Phase};
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::Json;
use serde::Deserialize;
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::Arc;

/// Priorities allowed.
const PRIORITY: std::ops::RangeInclusive<i32> = -1000..=1000;
/// Items in one batch.
const MAX_BATCH: usize = 100;
/// Items the queue holds (each edit saves the whole queue).
const MAX_QUEUE: usize = 1000;

/// One plan to queue.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct NewItem {
    /// The plan file's text.
    plan: String,
    /// `toml` (default) or `yaml`.
    #[serde(default)]
    format: Option<String>,
    /// Higher runs first.
    #[serde(default)]
    priority: i32,
    /// When it may run.
    #[serde(default)]
    schedule: Option<Schedule>,
}

/// One item or `{"items": [...]}`, with the field path of what is wrong.
fn new_items(bytes: &[u8]) -> Result<Vec<NewItem>, ApiError> {
    let v: Value = parse_body(bytes)?;
    let batch = v.get("items").is_some();
    let items: Vec<NewItem> = if batch {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Batch {
            items: Vec<NewItem>,
        }
        parse_body::<Batch>(bytes)?.items
    } else {
        vec![parse_body(bytes)?]
    };
    if items.is_empty() || items.len() > MAX_BATCH {
        return Err(ApiError::field(
            "items",
            format!("{} items: a batch holds 1 to {MAX_BATCH}", items.len()),
        ));
    }
    Ok(items)
}

/// A checked plan waiting to be queued: its file (under a pending name) and forecast.
struct Checked {
    pending: PathBuf,
    ext: &'static str,
    name: String,
    priority: i32,
    schedule: Option<Schedule>,
    forecast: Value,
}

fn random_hex() -> String {
    let mut b = [0u8; 8];
    let _ = getrandom::fill(&mut b);
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// Writes the plan under a pending name and checks it; `at` names the item in a batch.
fn check_one(st: &Station, n: &NewItem, at: &str) -> Result<Checked, ApiError> {
    let ext = match n.format.as_deref().unwrap_or("toml") {
        "toml" => "toml",
        "yaml" | "yml" => "yaml",
        other => {
            return Err(ApiError::field(
                format!("{at}format"),
                format!("{other:?} is not a plan format: toml or yaml"),
            ))
        }
    };
    if !PRIORITY.contains(&n.priority) {
        return Err(ApiError::field(
            format!("{at}priority"),
            format!("{} is out of range: -1000 to 1000", n.priority),
        ));
    }
    if let Some(s) = &n.schedule {
        s.validate(st.site.as_ref())
            .map_err(|(field, m)| ApiError::field(format!("{at}{field}"), m))?;
        let now = st.now();
        if s.next_start(now, None, 0, st.site.as_ref(), st.config.utc_offset_s)
            .is_none()
        {
            return Err(ApiError::field(
                format!("{at}schedule"),
                "the window does not open within 3 days of its start: it could never run as \
                 written (check the sun limits against the site's latitude and the season)",
            ));
        }
    }
    let pending = st
        .config
        .items_dir()
        .join(format!(".pending-{}.{ext}", random_hex()));
    crate::atomic::write(&pending, n.plan.as_bytes(), false).map_err(ApiError::internal)?;
    let checked = st.runner.check(&pending);
    let forecast = match checked {
        Ok(f) => f,
        Err(e) => {
            let _ = std::fs::remove_file(&pending);
            // The pending file's path means nothing to the client and shows the data directory.
            let e = e.replace(&pending.display().to_string(), "the plan");
            return Err(ApiError::field(format!("{at}plan"), e));
        }
    };
    Ok(Checked {
        pending,
        ext,
        name: forecast["plan"].as_str().unwrap_or("plan").to_string(),
        priority: n.priority,
        schedule: n.schedule.clone(),
        forecast: summary(&forecast),
    })
}

/// What an item keeps of its forecast: duration, frames, sets, bytes, the worst DoLP sigma
/// per set and the notes.
fn summary(check: &Value) -> Value {
    let f = &check["forecast"];
    let worst = f["classes"].as_array().and_then(|c| {
        c.iter()
            .filter_map(|x| x["sigma_dolp"].as_f64())
            .reduce(f64::max)
    });
    json!({
        "kind": check["kind"], "duration_s": f["duration_s"], "frames": f["frames"],
        "sets": f["sets"], "bytes": check["bytes"], "sigma_dolp_max": worst, "notes": f["notes"],
    })
}

/// Checks every item and the disk; all or nothing.
fn check_all(st: &Station, items: &[NewItem]) -> Result<Vec<Checked>, ApiError> {
    let batch = items.len() > 1;
    let mut done: Vec<Checked> = Vec::new();
    for (i, n) in items.iter().enumerate() {
        let at = if batch {
            format!("items[{i}].")
        } else {
            String::new()
        };
        match check_one(st, n, &at) {
            Ok(c) => done.push(c),
            Err(e) => {
                discard(&done);
                return Err(e);
            }
        }
    }
    let bytes: u64 = done
        .iter()
        .filter_map(|c| c.forecast["bytes"].as_u64())
        .sum();
    if let Err(m) = crate::disk::fits(&st.config.data_dir, bytes, st.config.reserve_bytes) {
        discard(&done);
        return Err(ApiError::new(StatusCode::INSUFFICIENT_STORAGE, m));
    }
    Ok(done)
}

fn discard(checked: &[Checked]) {
    for c in checked {
        let _ = std::fs::remove_file(&c.pending);
    }
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(ApiError::internal)?
}

/// `POST /api/v1/queue`: `{"plan": TEXT, "format": "toml"|"yaml", "priority": N}` or
/// `{"items": [...]}`; answers `{"ids": [...]}` (201).
pub async fn submit(
    State(app): State<AppState>,
    headers: HeaderMap,
    b: Result<Bytes, BytesRejection>,
) -> Result<(StatusCode, Json<Value>), ApiError> {
    let key = app.key(&headers, Scope::Queue, "queue.add").await?;
    let bytes = body(b)?;
    let st = app.st.clone();
    let owner = key.id.clone();
    let result = blocking(move || {
        let items = new_items(&bytes)?;
        let checked = check_all(&st, &items)?;
        add_checked(&st, checked, &owner)
    })
    .await;
    let r = result.map_err(EditError::Refused);
    let ids = audited(&app.st, &key.id, "queue.add", |ids| format!("{ids:?}"), r)?;
    Ok((StatusCode::CREATED, Json(json!({ "ids": ids }))))
}

/// Gives checked plans their ids and files and queues them, in one saved edit.
fn add_checked(
    st: &Arc<Station>,
    checked: Vec<Checked>,
    owner: &str,
) -> Result<Vec<u64>, ApiError> {
    let now = st.now();
    let outcome = st.edit(|s| -> Result<Vec<u64>, ApiError> {
        if s.queue.len() + checked.len() > MAX_QUEUE {
            return Err(ApiError::field(
                "items",
                format!(
                    "the queue holds {} items and takes at most {MAX_QUEUE}: remove some first",
                    s.queue.len()
                ),
            ));
        }
        let ids = queue::peek_ids(s, checked.len());
        let mut items = Vec::new();
        for (id, c) in ids.zip(&checked) {
            let file = format!("items/{id}.{}", c.ext);
            let to = st.config.data_dir.join(&file);
            std::fs::rename(&c.pending, &to).map_err(|e| {
                ApiError::internal(format!("cannot keep the plan as {}: {e}", to.display()))
            })?;
            items.push(Item {
                id,
                name: c.name.clone(),
                owner: owner.to_string(),
                priority: c.priority,
                plan_file: file,
                added_unix: now,
                forecast: c.forecast.clone(),
                schedule: c.schedule.clone(),
                runs_done: 0,
                last_start_unix: None,
            });
        }
        // The renames reach the disk before the state that names the files.
        let dir = st.config.items_dir();
        std::fs::File::open(&dir)
            .and_then(|d| d.sync_all())
            .map_err(|e| ApiError::internal(format!("{}: {e}", dir.display())))?;
        Ok(queue::add(s, items))
    });
    if outcome.is_err() {
        discard(&checked);
    }
    outcome.map_err(|e| match e {
        EditError::Refused(e) => e,
        EditError::Save(e) => {
            ApiError::internal(format!("the station's state could not be saved: {e}"))
        }
    })
}

/// `POST /api/v1/queue/validate`: the same body as adding; answers each item's forecast and
/// whether the batch fits on the disk, queuing nothing.
pub async fn validate(
    State(app): State<AppState>,
    headers: HeaderMap,
    b: Result<Bytes, BytesRejection>,
) -> Result<Json<Value>, ApiError> {
    app.key(&headers, Scope::Queue, "queue.validate").await?;
    let bytes = body(b)?;
    let st = app.st.clone();
    blocking(move || {
        let items = new_items(&bytes)?;
        let checked = check_all(&st, &items)?;
        discard(&checked);
        let free = crate::disk::free_bytes(&st.config.data_dir);
        Ok(Json(json!({
            "ok": true,
            "items": checked.iter().map(|c| json!({"name": c.name, "forecast": c.forecast})).collect::<Vec<_>>(),
            "disk_free_bytes": free, "reserve_bytes": st.config.reserve_bytes,
        })))
    })
    .await
}

fn parse_id(text: &str) -> Result<u64, ApiError> {
    text.parse().map_err(|_| {
        ApiError::field(
            "id",
            format!("{text:?} is not an item id: a whole number from 1"),
        )
    })
}

fn may_edit(key: &KeyRecord, owner: &str) -> Result<(), ApiError> {
    if key.id == owner || key.allows(Scope::Admin) {
        return Ok(());
    }
    Err(ApiError::new(
        StatusCode::FORBIDDEN,
        format!("the item belongs to key {owner}: only its owner or an admin key may change it"),
    ))
}

/// Whether `key` may change the queued item `id` (404 when no item has it).
fn may_edit_queued(s: &crate::state::State, key: &KeyRecord, id: u64) -> Result<(), ApiError> {
    let i =
        queue::index_of(s, id).map_err(|e| ApiError::new(StatusCode::NOT_FOUND, e.to_string()))?;
    may_edit(key, &s.queue[i].owner)
}

/// `DELETE /api/v1/queue/{id}`: a queued item (a repeating one: its later runs), or the
/// current item while paused (it leaves as `stopped`, its run resumable with `polarimeter
/// acquire resume`).
pub async fn remove(
    State(app): State<AppState>,
    headers: HeaderMap,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Queue, "queue.remove").await?;
    let id = parse_id(&id)?;
    let r = app.st.edit(|s| -> Result<(), ApiError> {
        // A repeating item is queued while one of its runs is current: removing it ends its
        // repeats and lets the current run go on.
        if queue::index_of(s, id).is_ok() {
            may_edit_queued(s, &key, id)?;
            return queue::remove(s, id)
                .map(|_| ())
                .map_err(|e| ApiError::field("id", e.to_string()));
        }
        if let Some(c) = s.current.as_ref().filter(|c| c.item.id == id) {
            may_edit(&key, &c.item.owner)?;
            if c.phase != Phase::Paused {
                return Err(ApiError::conflict(
                    "the item is running: pause or abort it first (POST /api/v1/run/pause)",
                ));
            }
            let message = "removed while paused; the run stays resumable".to_string();
            let uploads = app.st.config.upload.is_some();
            s.finish_current(
                (ExitState::Stopped, message),
                Value::Null,
                app.st.now(),
                uploads,
            );
            return Ok(());
        }
        Err(ApiError::new(
            StatusCode::NOT_FOUND,
            queue::QueueError::NoItem(id).to_string(),
        ))
    });
    finish_edit(&app.st, &key, "queue.remove", &id.to_string(), r)
}

/// Audits an edit and answers `{"ok": true}`.
fn finish_edit(
    st: &Station,
    key: &KeyRecord,
    action: &str,
    target: &str,
    r: Result<(), EditError<ApiError>>,
) -> Result<Json<Value>, ApiError> {
    audited(st, &key.id, action, |()| target.to_string(), r).map(|()| Json(json!({"ok": true})))
}

/// `DELETE /api/v1/queue`: removes the key's own queued items (an admin key: all).
pub async fn clear(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Queue, "queue.clear").await?;
    let admin = key.allows(Scope::Admin);
    let r = app.st.edit(|s| -> Result<(), ApiError> {
        s.queue.retain(|i| !(admin || i.owner == key.id));
        Ok(())
    });
    finish_edit(
        &app.st,
        &key,
        "queue.clear",
        if admin { "all" } else { "own" },
        r,
    )
}

/// `{"position": N}`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MoveBody {
    position: usize,
}

/// `POST /api/v1/queue/{id}/move`.
pub async fn move_item(
    State(app): State<AppState>,
    headers: HeaderMap,
    Path(id): Path<String>,
    b: Result<Bytes, BytesRejection>,
) -> Result<Json<Value>, ApiError> {
    let key = app.key(&headers, Scope::Queue, "queue.move").await?;
    let id = parse_id(&id)?;
    let m: MoveBody = parse_body(&body(b)?)?;
    let r = app.st.edit(|s| -> Result<(), ApiError> {
        may_edit_queued(s, &key, id)?;
        queue::move_to(s, id, m.position).map_err(|e| ApiError::field("position", e.to_string()))
    });
    finish_edit(
        &app.st,
        &key,
        "queue.move",
        &format!("{id} to {}", m.position),
        r,
    )
}

async fn set_running(app: AppState, headers: HeaderMap, on: bool) -> Result<Json<Value>, ApiError> {
    let action = if on { "queue.start" } else { "queue.stop" };
    let key = app.key(&headers, Scope::Control, action).await?;
    let r = app.st.edit(|s| -> Result<(), ApiError> {
        s.queue_running = on;
        Ok(())
    });
    finish_edit(&app.st, &key, action, "", r)
}

/// `POST /api/v1/queue/start`: take items (the current one, if any, goes on regardless).
pub async fn start(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    set_running(app, headers, true).await
}

/// `POST /api/v1/queue/stop`: take no new item after the current one.
pub async fn stop(
    State(app): State<AppState>,
    headers: HeaderMap,
) -> Result<Json<Value>, ApiError> {
    set_running(app, headers, false).await
}
