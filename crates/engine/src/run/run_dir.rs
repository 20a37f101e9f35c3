//! The run directory: opening a new or resumed run (refusing to overwrite one), damage
//! found on resume, and what a directory says about its run.

use super::clock::now_unix_ns;
use super::outcome::RunError;
use crate::journal::{Entry, Journal};
use crate::plan::Plan;
use crate::store::RunStore;
use crate::store::STORE_DIR;
use crate::FrameRecord;
use serde_json::json;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::path::PathBuf;
use std::time::{SystemTime, UNIX_EPOCH};
use tracing::warn;

/// Opens (or creates) the run directory and its journal and store; replays a journal.
pub(super) struct Opened {
    pub(super) journal: Journal,
    pub(super) store: RunStore,
    pub(super) entries: Vec<Entry>,
    pub(super) run_start_unix_ns: i64,
}

pub(super) fn open_run(
    plan: &Plan,
    run_dir: &Path,
    resume: bool,
    width: u32,
    height: u32,
    devices: &Value,
) -> Result<Opened, RunError> {
    let dir_err = |m: String| RunError::Dir {
        path: run_dir.display().to_string(),
        message: m,
    };
    if resume {
        let replay = crate::journal::replay(run_dir)?;
        if replay.torn_tail {
            warn!("the journal's last line was torn by a crash; it is dropped");
        }
        let entries = replay.entries;
        let start = entries
            .iter()
            .find_map(|e| match e {
                Entry::RunStarted {
                    started_unix_ns, ..
                } => Some(*started_unix_ns),
                _ => None,
            })
            .ok_or_else(|| dir_err("the journal has no run-started entry".into()))?;
        if entries.iter().any(|e| matches!(e, Entry::Finished { .. })) {
            return Err(dir_err("the run is already finished".into()));
        }
        if entries.iter().any(|e| matches!(e, Entry::Aborted { .. })) {
            return Err(dir_err("the run was aborted; start a new run".into()));
        }
        let journal = Journal::open_append(run_dir)?;
        let store = RunStore::open(run_dir)?;
        if (store.width(), store.height()) != (width, height) {
            return Err(dir_err(format!(
                "the store holds {}x{} frames; the camera gives {width}x{height}",
                store.width(),
                store.height()
            )));
        }
        Ok(Opened {
            journal,
            store,
            entries,
            run_start_unix_ns: start,
        })
    } else {
        // Nothing stored is ever deleted: a directory holding a run (its journal started it,
        // or its store holds a frame, whatever its journal says) is refused. What a start
        // that crashed before its first journal entry leaves (a store without frames) holds
        // nothing acquired: it is moved aside and the run starts in its place.
        let parts = run_parts(run_dir);
        if !parts.is_empty() {
            let journal = run_dir.join(crate::journal::JOURNAL_FILE);
            let started = journal.exists()
                && crate::journal::replay(run_dir)
                    .map(|r| r.run_started().is_some())
                    .unwrap_or(true);
            if started || holds_frames(run_dir) {
                return Err(dir_err(format!(
                    "already holds a run ({}): continue it with `polarimeter resume {}`, or \
                     choose another --out directory; nothing was changed",
                    parts.join(", "),
                    run_dir.display()
                )));
            }
            for name in [crate::journal::JOURNAL_FILE, STORE_DIR] {
                let from = run_dir.join(name);
                if from.exists() {
                    let to = (0u32..)
                        .map(|n| run_dir.join(format!("{name}.crashed-start-{n}")))
                        .find(|p| !p.exists())
                        .unwrap_or_else(|| run_dir.join(format!("{name}.crashed-start")));
                    warn!(
                        "{} is what a start that crashed before its first frame left; \
                         moved to {}",
                        from.display(),
                        to.display()
                    );
                    std::fs::rename(&from, &to)
                        .map_err(|e| dir_err(format!("{}: {e}", from.display())))?;
                }
            }
        }
        std::fs::create_dir_all(run_dir).map_err(|e| dir_err(e.to_string()))?;
        let plan_json = serde_json::to_value(plan).unwrap_or(Value::Null);
        let started = now_unix_ns(SystemTime::now());
        let mut attrs = serde_json::Map::new();
        attrs.insert("plan".into(), plan_json.clone());
        attrs.insert("software".into(), crate::software_version());
        attrs.insert("devices".into(), devices.clone());
        attrs.insert("state".into(), json!("running"));
        attrs.insert(
            "storage".into(),
            serde_json::to_value(plan.storage).unwrap_or(Value::Null),
        );
        let store = RunStore::create(run_dir, width, height, attrs)?;
        std::fs::write(
            run_dir.join("plan.toml"),
            toml::to_string(plan).unwrap_or_default(),
        )
        .map_err(|e| dir_err(format!("plan.toml: {e}")))?;
        // The run exists from its journal's first entry on.
        let mut journal = Journal::create(run_dir)?;
        journal.append(&Entry::RunStarted {
            plan: plan_json,
            software: crate::software_version(),
            devices: devices.clone(),
            width,
            height,
            started_unix_ns: started,
        })?;
        Ok(Opened {
            journal,
            store,
            entries: Vec::new(),
            run_start_unix_ns: started,
        })
    }
}

/// Checks every frame that still counts (recorded, not superseded) against its recorded hash
/// before a resumed run goes on: a chunk that is missing, fails its checksum or hashes to
/// another value is named (file, frame, step), kept aside ([`RunStore::set_aside_frame`])
/// and journaled as [`Entry::FrameDamaged`]. Returns the damaged frames; the caller takes
/// their steps (and their sets) again.
pub(super) fn set_aside_damaged(
    opened: &mut Opened,
    run_dir: &Path,
    records: &BTreeMap<u64, FrameRecord>,
    superseded: &BTreeSet<u64>,
) -> Result<Vec<u64>, RunError> {
    let counting: Vec<FrameRecord> = records
        .values()
        .filter(|r| !superseded.contains(&r.index))
        .cloned()
        .collect();
    let v = opened.store.verify(&counting)?;
    let mut damaged: Vec<u64> = v.missing.iter().chain(&v.mismatched).copied().collect();
    damaged.sort_unstable();
    let relative = |p: &Path| p.strip_prefix(run_dir).unwrap_or(p).display().to_string();
    for &index in &damaged {
        let step = records.get(&index).map_or(0, |r| r.step);
        let chunk = opened.store.frame_chunk_path(index);
        let finding = v.finding(index);
        let kept = opened.store.set_aside_frame(index)?;
        let kept_as = kept.as_deref().map(relative).unwrap_or_default();
        tracing::error!(
            frame = index,
            step,
            chunk = %chunk.display(),
            kept_as = %kept_as,
            "damaged frame: {finding}; the chunk is kept aside and the step is taken again"
        );
        opened.journal.append(&Entry::FrameDamaged {
            index,
            step,
            chunk: relative(&chunk),
            kept_as,
            finding,
        })?;
    }
    Ok(damaged)
}

/// `run_dir`'s store holds at least one frame chunk (a file under `frames/pixels/c/`).
pub(super) fn holds_frames(run_dir: &Path) -> bool {
    pub(super) fn any_file(dir: &Path) -> bool {
        std::fs::read_dir(dir).is_ok_and(|entries| {
            entries.flatten().any(|e| {
                let p = e.path();
                if p.is_dir() {
                    any_file(&p)
                } else {
                    true
                }
            })
        })
    }
    any_file(&run_dir.join(STORE_DIR).join("frames/pixels/c"))
}

/// The parts of a run that `run_dir` holds (its journal, store, plan copy), by file name.
pub fn run_parts(run_dir: &Path) -> Vec<String> {
    [crate::journal::JOURNAL_FILE, STORE_DIR, "plan.toml"]
        .into_iter()
        .filter(|name| run_dir.join(name).exists())
        .map(String::from)
        .collect()
}

/// The run directory's journal says the run is finished.
pub fn is_finished(run_dir: &Path) -> bool {
    crate::journal::replay(run_dir)
        .map(|r| {
            r.entries
                .iter()
                .any(|e| matches!(e, Entry::Finished { .. }))
        })
        .unwrap_or(false)
}

/// The simulated camera's noise stream for the next process on `run_dir`: the number of
/// processes that have run it so far (its run-started and resumed entries; 0 for a new
/// directory), so no process draws the noise an earlier one drew.
pub fn noise_stream(run_dir: &Path) -> u64 {
    crate::journal::replay(run_dir).map_or(0, |r| {
        r.entries
            .iter()
            .filter(|e| matches!(e, Entry::RunStarted { .. } | Entry::Resumed { .. }))
            .count() as u64
    })
}

/// The plan a run directory was started with (from its journal).
pub fn plan_of(run_dir: &Path) -> Result<Plan, RunError> {
    let replay = crate::journal::replay(run_dir)?;
    let plan = replay
        .entries
        .iter()
        .find_map(|e| match e {
            Entry::RunStarted { plan, .. } => Some(plan.clone()),
            _ => None,
        })
        .ok_or_else(|| RunError::Dir {
            path: run_dir.display().to_string(),
            message: "the journal has no run-started entry: the run's start was interrupted \
                      before any frame was taken, so nothing was acquired; start the plan again \
                      with `polarimeter run` into another directory"
                .into(),
        })?;
    serde_json::from_value(plan).map_err(|e| RunError::Dir {
        path: run_dir.display().to_string(),
        message: format!("the journal's plan does not parse: {e}"),
    })
}

/// The default run directory name for a plan started now.
pub fn default_run_dir(base: &Path, plan: &Plan) -> PathBuf {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let name: String = plan
        .name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    base.join(format!(
        "run-{}-{secs}",
        if name.is_empty() { "plan" } else { &name }
    ))
}
