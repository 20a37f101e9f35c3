//! The station's upkeep: one task that uploads finished runs to the bucket ([`crate::upload`])
//! and applies retention ([`crate::retention`]), every [`POLL`], recording each outcome in the
//! item's history entry (saved as any edit) and in the event stream and audit log.

use crate::retention::{due_by_age, removable};
use crate::shared::Station;
use crate::state::{Removed, UploadState};
use crate::upload;
use object_store::ObjectStore;
use serde_json::json;
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How often the upkeep looks for work.
pub const POLL: Duration = Duration::from_secs(2);

/// The longest wait before a failed upload is tried again.
pub const MAX_BACKOFF: Duration = Duration::from_secs(600);

/// Runs until the station stops.
pub async fn run(st: Arc<Station>) {
    let mut stop = st.shutdown.subscribe();
    let bucket = match &st.config.upload {
        Some(c) => match upload::bucket(c) {
            Ok(b) => Some(b),
            Err(e) => {
                st.note_error(&format!("uploads are off: {e}"));
                None
            }
        },
        None => None,
    };
    let mut retry_at: HashMap<String, Instant> = HashMap::new();
    loop {
        if let Some(b) = &bucket {
            upload_next(&st, b, &mut retry_at).await;
        }
        let st2 = Arc::clone(&st);
        let _ = tokio::task::spawn_blocking(move || apply_retention(&st2)).await;
        tokio::select! {
            _ = tokio::time::sleep(POLL) => {}
            _ = stop.changed() => return,
        }
    }
}

/// Uploads the oldest run waiting for its upload (whose retry time has come).
async fn upload_next(
    st: &Arc<Station>,
    bucket: &Arc<dyn ObjectStore>,
    retry_at: &mut HashMap<String, Instant>,
) {
    let Some(cfg) = &st.config.upload else {
        return;
    };
    let next = st.lock().history.iter().find_map(|e| {
        let waiting = e.upload.as_ref().is_some_and(|u| u.state == "pending");
        let due = retry_at
            .get(&e.run_dir)
            .is_none_or(|t| *t <= Instant::now());
        (waiting && due).then(|| {
            (
                e.run_dir.clone(),
                e.upload.as_ref().map_or(0, |u| u.attempts),
            )
        })
    });
    let Some((run_dir, before)) = next else {
        return;
    };
    // The attempt is counted before it starts, so one a kill cut short still counts.
    let attempts = before + 1;
    set_upload(st, &run_dir, |u| u.attempts = attempts);
    let dir = st.config.data_dir.join(&run_dir);
    if !dir.is_dir() {
        // A run that failed before it wrote anything, or a directory removed by hand: nothing
        // to upload, and no retry.
        set_upload(st, &run_dir, |u| {
            u.state = "failed".into();
            u.error = Some(format!("{}: no run directory to upload", dir.display()));
        });
        return;
    }
    let name = Path::new(&run_dir)
        .file_name()
        .map_or_else(|| run_dir.clone(), |n| n.to_string_lossy().into_owned());
    let outcome = upload::upload_run(bucket, cfg, &dir, &name).await;
    let now = st.now();
    let update = match &outcome {
        Ok(u) => {
            retry_at.remove(&run_dir);
            st.hub
                .publish("upload", json!({"run_dir": run_dir, "done": u}));
            st.audit.record(
                "station",
                "upload",
                &run_dir,
                true,
                &format!("{} files, {} sent, to {}", u.files, u.sent, u.url),
            );
            let mut done = UploadState::done_now(u.url.clone(), now);
            done.attempts = attempts;
            done
        }
        Err(e) => {
            let wait = Duration::from_secs(5u64 << (attempts - 1).min(7)).min(MAX_BACKOFF);
            retry_at.insert(run_dir.clone(), Instant::now() + wait);
            st.note_error(&format!(
                "{e} (tried {attempts} times; next in {} s)",
                wait.as_secs()
            ));
            st.audit
                .record("station", "upload", &run_dir, false, &e.to_string());
            UploadState {
                attempts,
                error: Some(e.to_string()),
                ..UploadState::pending()
            }
        }
    };
    set_upload(st, &run_dir, |u| *u = update);
}

/// Changes the upload state of `run_dir`'s history entry, saved.
fn set_upload(st: &Station, run_dir: &str, f: impl FnOnce(&mut UploadState)) {
    let saved = st.edit(|s| -> Result<(), ()> {
        if let Some(u) = s
            .history
            .iter_mut()
            .find(|e| e.run_dir == run_dir)
            .and_then(|e| e.upload.as_mut())
        {
            f(u);
        }
        Ok(())
    });
    if saved.is_err() {
        st.note_error(&format!(
            "{run_dir}: the station's state could not be saved for its upload"
        ));
    }
}

/// Bytes of the files under `dir`.
fn bytes_under(dir: &Path) -> u64 {
    std::fs::read_dir(dir).map_or(0, |rd| {
        rd.flatten()
            .map(|e| match e.file_type() {
                Ok(t) if t.is_dir() => bytes_under(&e.path()),
                _ => e.metadata().map_or(0, |m| m.len()),
            })
            .sum()
    })
}

/// What retention removes now: by age, then (with uploads) the oldest uploaded runs while the
/// disk is below the reserve.
fn removals(st: &Station) -> Vec<(String, Removed)> {
    let uploads = st.config.upload.is_some();
    let now = st.now();
    let s = st.lock();
    let mut out: Vec<(String, Removed)> = s
        .history
        .iter()
        .filter_map(|e| {
            due_by_age(&st.config.retention, e, uploads, now).map(|r| (e.run_dir.clone(), r))
        })
        .collect();
    if uploads {
        let free = crate::disk::free_bytes(&st.config.data_dir).unwrap_or(u64::MAX);
        let mut short = st.config.reserve_bytes.saturating_sub(free);
        for e in s.history.iter().filter(|e| removable(e, true)) {
            if short == 0 {
                break;
            }
            if out
                .iter()
                .any(|(d, r)| d == &e.run_dir && *r == Removed::Run)
            {
                continue;
            }
            short = short.saturating_sub(bytes_under(&st.config.data_dir.join(&e.run_dir)));
            out.retain(|(d, _)| d != &e.run_dir);
            out.push((e.run_dir.clone(), Removed::Run));
        }
    }
    out
}

/// Removes what [`removals`] says, recording each in the item's history entry.
fn apply_retention(st: &Station) {
    for (run_dir, what) in removals(st) {
        let dir = st.config.data_dir.join(&run_dir);
        let done =
            match what {
                Removed::Run => std::fs::remove_dir_all(&dir).or_else(|e| {
                    if dir.exists() {
                        Err(e)
                    } else {
                        Ok(())
                    }
                }),
                Removed::Frames => remove_frames(&dir, st.now()),
            };
        let what_name = match what {
            Removed::Run => "run",
            Removed::Frames => "frames",
        };
        match done {
            Ok(()) => {
                st.audit.record(
                    "station",
                    "retention",
                    &run_dir,
                    true,
                    &format!("removed its {what_name}"),
                );
                st.hub
                    .publish("retention", json!({"run_dir": run_dir, "removed": what}));
                let _ = st.edit(|s| -> Result<(), ()> {
                    if let Some(e) = s.history.iter_mut().find(|e| e.run_dir == run_dir) {
                        e.removed = Some(what);
                    }
                    Ok(())
                });
            }
            Err(e) => st.note_error(&format!("retention: {}: {e}", dir.display())),
        }
    }
}

/// Removes a run's raw frames (`run.zarr/frames/pixels`), saying so in the store's root
/// attribute `retention` first (a crash between the two leaves the note and the frames).
fn remove_frames(run_dir: &Path, now: u64) -> std::io::Result<()> {
    let root = run_dir.join("run.zarr/zarr.json");
    let text = std::fs::read_to_string(&root)?;
    let mut meta: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))?;
    if let Some(attrs) = meta["attributes"].as_object_mut() {
        attrs.insert(
            "retention".into(),
            json!({
                "frames_removed_unix": now,
                "note": "the raw frames (frames/pixels) were removed by the station's retention \
                         (frames_days); products, per-frame metadata and the journal remain",
            }),
        );
    }
    let bytes = serde_json::to_vec_pretty(&meta).unwrap_or_default();
    crate::atomic::write(&root, &bytes, false).map_err(std::io::Error::other)?;
    let pixels = run_dir.join("run.zarr/frames/pixels");
    match std::fs::remove_dir_all(&pixels) {
        Err(e) if pixels.exists() => Err(e),
        _ => Ok(()),
    }
}
