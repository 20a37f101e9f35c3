//! Retention: what of a finished run the station removes, and when (`[retention]` in the
//! station file).
//!
//! * `frames_days`: a finished run's raw frames (`run.zarr/frames/pixels`) are removed this
//!   long after it ended; its products, per-frame metadata, journal and log stay, and the
//!   store's root attribute `retention` says when the frames went.
//! * `runs_days`: the whole run directory is removed this long after it ended.
//! * With `[upload]` configured, only runs whose upload completed are removed, by age or when
//!   the disk reaches the reserve (oldest first, until it is above). A run not uploaded is never
//!   removed then. Without `[upload]`, age alone decides, and the disk reserve removes nothing
//!   (the station pauses the going run instead).
//!
//! Each removal is recorded in the item's history entry (`removed`) and logged.

use crate::state::{HistoryEntry, Removed};
use serde::Deserialize;

/// `[retention]`.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RetentionConfig {
    /// Days after a run ended that its raw frames are removed.
    pub frames_days: Option<f64>,
    /// Days after a run ended that its whole directory is removed.
    pub runs_days: Option<f64>,
}

impl RetentionConfig {
    /// Refuses a negative or non-finite age, naming it.
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [
            ("frames_days", self.frames_days),
            ("runs_days", self.runs_days),
        ] {
            if let Some(d) = v {
                if !(d.is_finite() && d >= 0.0) {
                    return Err(format!(
                        "retention.{name} = {d} is invalid: allowed a number of days >= 0"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Whether `entry`'s run may be removed at all: it has a directory still there, and (with
/// uploads configured) its upload completed.
pub fn removable(entry: &HistoryEntry, uploads: bool) -> bool {
    !entry.run_dir.is_empty()
        && entry.removed != Some(Removed::Run)
        && (!uploads || entry.upload.as_ref().is_some_and(|u| u.done()))
}

/// What retention by age removes from `entry` at `now` (Unix seconds), if anything.
pub fn due_by_age(
    cfg: &RetentionConfig,
    entry: &HistoryEntry,
    uploads: bool,
    now: u64,
) -> Option<Removed> {
    if !removable(entry, uploads) {
        return None;
    }
    let age_days = now.saturating_sub(entry.ended_unix) as f64 / 86_400.0;
    if cfg.runs_days.is_some_and(|d| age_days >= d) {
        return Some(Removed::Run);
    }
    if entry.removed.is_none() && cfg.frames_days.is_some_and(|d| age_days >= d) {
        return Some(Removed::Frames);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state::{ExitState, Item, UploadState};
    use serde_json::Value;

    fn entry(ended_unix: u64, upload: Option<UploadState>) -> HistoryEntry {
        HistoryEntry {
            item: Item {
                id: 1,
                name: "a".into(),
                owner: "k".into(),
                priority: 0,
                plan_file: "items/1.toml".into(),
                added_unix: 0,
                forecast: Value::Null,
                schedule: None,
                runs_done: 1,
                last_start_unix: None,
            },
            exit: ExitState::Done,
            run_dir: "runs/1-a".into(),
            started_unix: 0,
            ended_unix,
            crash_resumes: 0,
            message: String::new(),
            result: Value::Null,
            upload,
            removed: None,
        }
    }

    #[test]
    fn ages_remove_frames_then_runs_and_uploads_come_first() {
        let day = 86_400;
        let cfg = RetentionConfig {
            frames_days: Some(2.0),
            runs_days: Some(10.0),
        };
        let done = Some(UploadState::done_now("s3://b/p/1-a".into(), 5));
        let e = entry(0, done.clone());
        assert_eq!(due_by_age(&cfg, &e, true, day), None, "1 day: nothing");
        assert_eq!(due_by_age(&cfg, &e, true, 3 * day), Some(Removed::Frames));
        let mut gone = e.clone();
        gone.removed = Some(Removed::Frames);
        assert_eq!(due_by_age(&cfg, &gone, true, 3 * day), None, "frames once");
        assert_eq!(due_by_age(&cfg, &gone, true, 11 * day), Some(Removed::Run));
        // Not uploaded yet: kept whatever its age while uploads are configured.
        let pending = entry(0, Some(UploadState::pending()));
        assert_eq!(due_by_age(&cfg, &pending, true, 11 * day), None);
        // Without uploads, age alone decides.
        assert_eq!(
            due_by_age(&cfg, &entry(0, None), false, 11 * day),
            Some(Removed::Run)
        );
        assert!(RetentionConfig {
            frames_days: Some(-1.0),
            runs_days: None
        }
        .check()
        .unwrap_err()
        .contains("retention.frames_days"));
    }
}
