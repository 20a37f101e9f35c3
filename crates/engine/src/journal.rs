//! The append-only journal: the run's source of truth.
//!
//! `RUN_DIR/journal.jsonl` holds one JSON object per line, each an [`Entry`] tagged by its
//! `"event"` field (`"run-started"`, `"frame"`, `"set-done"`, ...). [`Journal::append`] writes
//! the line and calls `sync_data` before it returns: that is the durability point of a step
//! ("flushed before a step counts"). A `frame` entry is written only after the frame's chunk is
//! durably stored, so every frame the journal names is on disk.
//!
//! A crash can tear the last line (a partial write, or a tail of zero bytes after a power
//! loss). [`replay`] drops a torn final line and says so in [`Replay::torn_tail`];
//! [`Journal::open_append`] truncates the file back to the last complete line before it
//! appends. A bad line anywhere else is corruption, an error naming the line number.
//!
//! Non-finite floats in a frame record (`measured_angle_deg` is NaN when the analyzer was not
//! read back) are written as `null` by JSON and read back as NaN.
//!
//! New fields may be added to entries: give them `#[serde(default)]` so that older journals
//! still replay. Unknown fields are ignored.

use crate::FrameRecord;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

/// The journal's file name inside a run directory.
pub const JOURNAL_FILE: &str = "journal.jsonl";

/// One line of the journal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum Entry {
    /// The first entry of a run.
    RunStarted {
        /// The plan, as data.
        plan: Value,
        /// The software that runs it ([`crate::software_version`]).
        software: Value,
        /// The devices (models, serial numbers, firmware).
        devices: Value,
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
        /// When the run started, nanoseconds since the Unix epoch.
        started_unix_ns: i64,
    },
    /// A frame whose pixels are durably stored (written only after its chunk is).
    Frame(#[serde(with = "frame_json")] FrameRecord),
    /// An angle set whose products were computed and accepted by the suspender.
    SetDone {
        /// The set number.
        set: u64,
        /// Its frames (indices).
        frames: Vec<u64>,
        /// The suspender's verdict.
        verdict: Value,
    },
    /// An angle set the suspender refused: its frames stay stored but are superseded; the set
    /// is taken again under a new set number.
    SetRejected {
        /// The set number.
        set: u64,
        /// Its frames (indices).
        frames: Vec<u64>,
        /// Why it was refused.
        reason: String,
    },
    /// The frames of a set that did not finish and is taken again whole (a continuous run's
    /// half turn cut by a missed trigger, a pause or a crash): they stay stored but are
    /// superseded, as a rejected set's are; the set keeps its number.
    FramesSuperseded {
        /// The set number.
        set: u64,
        /// Its frames taken so far (indices).
        frames: Vec<u64>,
        /// Why the set is taken again.
        reason: String,
    },
    /// A recorded frame found damaged (its chunk missing, unreadable or hashing to another
    /// value) when a run was resumed: the chunk is kept aside under `kept_as`, the frame no
    /// longer counts and its step is taken again (its set too, if it was done).
    FrameDamaged {
        /// The frame (index).
        index: u64,
        /// Its plan step.
        step: u64,
        /// The chunk file, relative to the run directory.
        chunk: String,
        /// Where the damaged chunk was moved (relative to the run directory); empty when
        /// there was no file to keep.
        kept_as: String,
        /// What was found.
        finding: String,
    },
    /// A time-lapse set that was late (its start time passed by more than half an interval)
    /// and what the plan's `late` policy did with it.
    SetLate {
        /// The set number.
        set: u64,
        /// When it was due, nanoseconds since the Unix epoch.
        due_unix_ns: i64,
        /// How late it was when its turn came, seconds.
        late_s: f64,
        /// `"taken"` (at once) or `"skipped"`.
        action: String,
    },
    /// One round of the planner's decision log.
    Decision {
        /// The planner's round.
        round: u64,
        /// What it decided and why.
        decision: Value,
    },
    /// A labelled checkpoint.
    Checkpoint {
        /// The label (e.g. `"set 3 done"`).
        label: String,
        /// The plan step to take next.
        next_step: u64,
    },
    /// The run paused.
    Paused {
        /// Why.
        reason: String,
        /// The plan step to take on resume.
        next_step: u64,
    },
    /// The run continued (in this process).
    Resumed {
        /// The process that continued it.
        process_id: u32,
        /// When, nanoseconds since the Unix epoch.
        at_unix_ns: i64,
    },
    /// A calibration result.
    Calibration {
        /// What was calibrated (e.g. `"analyzer"`, `"dark"`, `"photon-transfer"`).
        kind: String,
        /// The result.
        result: Value,
    },
    /// The run finished: every planned frame is stored and checked.
    Finished {
        /// Frames stored.
        frames: u64,
    },
    /// The run was aborted (what was acquired stays).
    Aborted {
        /// Why.
        reason: String,
    },
}

impl Entry {
    /// The entry's `"event"` tag (e.g. `"set-done"`).
    pub fn event(&self) -> &'static str {
        match self {
            Entry::RunStarted { .. } => "run-started",
            Entry::Frame(_) => "frame",
            Entry::SetDone { .. } => "set-done",
            Entry::SetRejected { .. } => "set-rejected",
            Entry::FramesSuperseded { .. } => "frames-superseded",
            Entry::FrameDamaged { .. } => "frame-damaged",
            Entry::SetLate { .. } => "set-late",
            Entry::Decision { .. } => "decision",
            Entry::Checkpoint { .. } => "checkpoint",
            Entry::Paused { .. } => "paused",
            Entry::Resumed { .. } => "resumed",
            Entry::Calibration { .. } => "calibration",
            Entry::Finished { .. } => "finished",
            Entry::Aborted { .. } => "aborted",
        }
    }
}

/// Frame records in JSON: NaN (written as `null`) reads back as NaN.
mod frame_json {
    use crate::{AngleSource, FrameKind, FrameRecord};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(r: &FrameRecord, s: S) -> Result<S::Ok, S::Error> {
        r.serialize(s)
    }

    #[derive(Deserialize)]
    struct Json {
        index: u64,
        #[serde(default)]
        step: u64,
        kind: FrameKind,
        set: Option<u64>,
        label: String,
        commanded_angle_deg: Option<f64>,
        measured_angle_deg: Option<f64>,
        // Absent in journals written before frames recorded their span: a step-and-shoot
        // frame, whose span is its settled reading.
        #[serde(default)]
        angle_start_deg: Option<f64>,
        #[serde(default)]
        angle_end_deg: Option<f64>,
        #[serde(default)]
        angle_source: Option<AngleSource>,
        #[serde(default)]
        angle_sigma_deg: Option<f64>,
        exposure_us: Option<f64>,
        gain: Option<f64>,
        host_time_unix_ns: i64,
        device_timestamp_ns: Option<u64>,
        frame_id: u64,
        sun_zenith_deg: Option<f64>,
        sun_azimuth_deg: Option<f64>,
        width: u32,
        height: u32,
        hash: u64,
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<FrameRecord, D::Error> {
        let j = Json::deserialize(d)?;
        let measured = j.measured_angle_deg.unwrap_or(f64::NAN);
        let source = j.angle_source.unwrap_or(AngleSource::Settled);
        let (start, end) = match j.angle_source {
            Some(_) => (
                j.angle_start_deg.unwrap_or(f64::NAN),
                j.angle_end_deg.unwrap_or(f64::NAN),
            ),
            None => (measured, measured),
        };
        Ok(FrameRecord {
            index: j.index,
            step: j.step,
            kind: j.kind,
            set: j.set,
            label: j.label,
            commanded_angle_deg: j.commanded_angle_deg.unwrap_or(f64::NAN),
            measured_angle_deg: measured,
            angle_start_deg: start,
            angle_end_deg: end,
            angle_source: source,
            angle_sigma_deg: j.angle_sigma_deg.unwrap_or(f64::NAN),
            exposure_us: j.exposure_us.unwrap_or(f64::NAN),
            gain: j.gain.unwrap_or(f64::NAN),
            host_time_unix_ns: j.host_time_unix_ns,
            device_timestamp_ns: j.device_timestamp_ns,
            frame_id: j.frame_id,
            sun_zenith_deg: j.sun_zenith_deg,
            sun_azimuth_deg: j.sun_azimuth_deg,
            width: j.width,
            height: j.height,
            hash: j.hash,
        })
    }
}

/// What can go wrong with a journal.
#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    /// [`Journal::create`] found a journal already there.
    #[error("{path}: a journal already exists (resume the run, or choose another directory)")]
    Exists {
        /// The journal file.
        path: PathBuf,
    },
    /// The journal file is not there.
    #[error("{path}: no journal (is this a run directory?)")]
    NotFound {
        /// The journal file.
        path: PathBuf,
    },
    /// Reading, writing or syncing failed.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What was being done (e.g. `"appending"`).
        action: &'static str,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line other than the last does not parse: the journal is corrupt.
    #[error("{path}: line {line} is corrupt: {message}")]
    Corrupt {
        /// The journal file.
        path: PathBuf,
        /// The line, counting from 1.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// An entry could not be serialized.
    #[error("{path}: cannot serialize a {event} entry: {message}")]
    Serialize {
        /// The journal file.
        path: PathBuf,
        /// The entry's event tag.
        event: &'static str,
        /// The serializer's message.
        message: String,
    },
}

fn io_err(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> JournalError {
    let path = path.to_path_buf();
    move |source| JournalError::Io {
        path,
        action,
        source,
    }
}

/// The journal of a run, open for appending.
#[derive(Debug)]
pub struct Journal {
    path: PathBuf,
    file: File,
    /// Bytes of complete lines in the file.
    len: u64,
}

impl Journal {
    /// Creates `dir/journal.jsonl`; fails if it exists. The directory must exist.
    pub fn create(dir: &Path) -> Result<Journal, JournalError> {
        let path = dir.join(JOURNAL_FILE);
        let file = OpenOptions::new()
            .append(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| {
                if e.kind() == std::io::ErrorKind::AlreadyExists {
                    JournalError::Exists { path: path.clone() }
                } else {
                    JournalError::Io {
                        path: path.clone(),
                        action: "creating",
                        source: e,
                    }
                }
            })?;
        sync_dir(dir).map_err(io_err(dir, "syncing the directory"))?;
        Ok(Journal { path, file, len: 0 })
    }

    /// Opens the journal of `dir` to continue a run: a torn last line is cut off first.
    pub fn open_append(dir: &Path) -> Result<Journal, JournalError> {
        let path = dir.join(JOURNAL_FILE);
        let bytes = read_journal(&path)?;
        let parsed = parse(&path, &bytes)?;
        let file = OpenOptions::new()
            .append(true)
            .open(&path)
            .map_err(io_err(&path, "opening for append"))?;
        if parsed.complete_len < bytes.len() as u64 {
            tracing::warn!(
                path = %path.display(),
                dropped_bytes = bytes.len() as u64 - parsed.complete_len,
                "cutting the journal's torn last line"
            );
            file.set_len(parsed.complete_len)
                .map_err(io_err(&path, "truncating the torn last line"))?;
            file.sync_all()
                .map_err(io_err(&path, "syncing after truncation"))?;
        }
        Ok(Journal {
            path,
            file,
            len: parsed.complete_len,
        })
    }

    /// The journal file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends `entry` as one line and syncs it to disk before returning.
    ///
    /// If the write fails, the file is cut back to its last complete line (when possible), so
    /// that a later append does not leave a torn line in the middle.
    pub fn append(&mut self, entry: &Entry) -> Result<(), JournalError> {
        let mut line = serde_json::to_vec(entry).map_err(|e| JournalError::Serialize {
            path: self.path.clone(),
            event: entry.event(),
            message: e.to_string(),
        })?;
        line.push(b'\n');
        let written = self
            .file
            .write_all(&line)
            .and_then(|()| self.file.sync_data());
        if let Err(e) = written {
            // Best effort: drop whatever part of the line reached the file.
            let _ = self.file.set_len(self.len);
            return Err(JournalError::Io {
                path: self.path.clone(),
                action: "appending",
                source: e,
            });
        }
        self.len += line.len() as u64;
        Ok(())
    }
}

fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

fn read_journal(path: &Path) -> Result<Vec<u8>, JournalError> {
    let mut file = File::open(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            JournalError::NotFound {
                path: path.to_path_buf(),
            }
        } else {
            JournalError::Io {
                path: path.to_path_buf(),
                action: "opening",
                source: e,
            }
        }
    })?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes)
        .map_err(io_err(path, "reading"))?;
    Ok(bytes)
}

struct Parsed {
    entries: Vec<Entry>,
    torn_tail: bool,
    complete_len: u64,
}

fn parse(path: &Path, bytes: &[u8]) -> Result<Parsed, JournalError> {
    let mut entries = Vec::new();
    let mut complete_len = 0u64;
    let mut torn_tail = false;
    let mut start = 0usize;
    let mut line_no = 0usize;
    while start < bytes.len() {
        line_no += 1;
        let (end, has_newline) = match bytes[start..].iter().position(|&b| b == b'\n') {
            Some(p) => (start + p, true),
            None => (bytes.len(), false),
        };
        let next = if has_newline { end + 1 } else { end };
        let is_last = next >= bytes.len();
        let line = &bytes[start..end];
        if !has_newline {
            // A partial write: the line never completed, whatever it holds.
            torn_tail = true;
            break;
        }
        if line.iter().all(u8::is_ascii_whitespace) {
            complete_len = next as u64;
            start = next;
            continue;
        }
        let parsed = std::str::from_utf8(line)
            .map_err(|e| e.to_string())
            .and_then(|s| serde_json::from_str::<Entry>(s).map_err(|e| e.to_string()));
        match parsed {
            Ok(entry) => {
                entries.push(entry);
                complete_len = next as u64;
            }
            Err(_) if is_last => {
                torn_tail = true;
                break;
            }
            Err(message) => {
                return Err(JournalError::Corrupt {
                    path: path.to_path_buf(),
                    line: line_no,
                    message,
                })
            }
        }
        start = next;
    }
    Ok(Parsed {
        entries,
        torn_tail,
        complete_len,
    })
}

/// Every entry of a journal, and views of them.
#[derive(Debug, Clone, PartialEq)]
pub struct Replay {
    /// Every entry, in order.
    pub entries: Vec<Entry>,
    /// The last line was torn by a crash and is dropped.
    pub torn_tail: bool,
}

/// The [`Entry::RunStarted`] entry's fields.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunStart<'a> {
    /// The plan.
    pub plan: &'a Value,
    /// The software.
    pub software: &'a Value,
    /// The devices.
    pub devices: &'a Value,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Start, nanoseconds since the Unix epoch.
    pub started_unix_ns: i64,
}

/// A set done or rejected.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SetOutcome<'a> {
    /// The set number.
    pub set: u64,
    /// Its frames.
    pub frames: &'a [u64],
    /// The verdict (sets done).
    pub verdict: Option<&'a Value>,
    /// Why it was refused (sets rejected).
    pub reason: Option<&'a str>,
}

impl Replay {
    /// The run-started entry (the first one, if there are several).
    pub fn run_started(&self) -> Option<RunStart<'_>> {
        self.entries.iter().find_map(|e| match e {
            Entry::RunStarted {
                plan,
                software,
                devices,
                width,
                height,
                started_unix_ns,
            } => Some(RunStart {
                plan,
                software,
                devices,
                width: *width,
                height: *height,
                started_unix_ns: *started_unix_ns,
            }),
            _ => None,
        })
    }

    /// The frames recorded, by index: a later entry for an index supersedes an earlier one
    /// (a frame taken again after a crash).
    pub fn frames(&self) -> BTreeMap<u64, &FrameRecord> {
        let mut frames = BTreeMap::new();
        for e in &self.entries {
            if let Entry::Frame(r) = e {
                frames.insert(r.index, r);
            }
        }
        frames
    }

    /// The frames recorded, sorted by index (what [`crate::store::RunStore::write_frame_metadata`]
    /// takes).
    pub fn frame_records(&self) -> Vec<FrameRecord> {
        self.frames().into_values().cloned().collect()
    }

    /// The index the next frame takes: one past the highest recorded.
    pub fn next_frame_index(&self) -> u64 {
        self.frames().keys().next_back().map_or(0, |i| i + 1)
    }

    /// Sets done, in journal order.
    pub fn sets_done(&self) -> Vec<SetOutcome<'_>> {
        self.entries
            .iter()
            .filter_map(|e| match e {
                Entry::SetDone {
                    set,
                    frames,
                    verdict,
                } => Some(SetOutcome {
                    set: *set,
                    frames,
                    verdict: Some(verdict),
                    reason: None,
                }),
                _ => None,
            })
            .collect()
    }

    /// Sets rejected, in journal order.
    pub fn sets_rejected(&self) -> Vec<SetOutcome<'_>> {
        self.entries
            .iter()
            .filter_map(|e| match e {
                Entry::SetRejected {
                    set,
                    frames,
                    reason,
                } => Some(SetOutcome {
                    set: *set,
                    frames,
                    verdict: None,
                    reason: Some(reason),
                }),
                _ => None,
            })
            .collect()
    }

    /// Frames found damaged on a resume (kept aside, superseded).
    pub fn damaged_frames(&self) -> BTreeSet<u64> {
        self.entries
            .iter()
            .filter_map(|e| match e {
                Entry::FrameDamaged { index, .. } => Some(*index),
                _ => None,
            })
            .collect()
    }

    /// Frames that no longer count though stored: those of rejected sets and of unfinished
    /// sets taken again ([`Entry::FramesSuperseded`]).
    pub fn rejected_frames(&self) -> BTreeSet<u64> {
        let mut frames: BTreeSet<u64> = self
            .sets_rejected()
            .iter()
            .flat_map(|s| s.frames.iter().copied())
            .collect();
        for e in &self.entries {
            if let Entry::FramesSuperseded { frames: f, .. } = e {
                frames.extend(f.iter().copied());
            }
        }
        frames
    }

    /// The planner's decisions, in order, with their round.
    pub fn decisions(&self) -> Vec<(u64, &Value)> {
        self.entries
            .iter()
            .filter_map(|e| match e {
                Entry::Decision { round, decision } => Some((*round, decision)),
                _ => None,
            })
            .collect()
    }

    /// Calibration results by kind (the latest of each kind).
    pub fn calibrations(&self) -> BTreeMap<&str, &Value> {
        let mut out = BTreeMap::new();
        for e in &self.entries {
            if let Entry::Calibration { kind, result } = e {
                out.insert(kind.as_str(), result);
            }
        }
        out
    }

    /// The last checkpoint: label and next step.
    pub fn last_checkpoint(&self) -> Option<(&str, u64)> {
        self.entries.iter().rev().find_map(|e| match e {
            Entry::Checkpoint { label, next_step } => Some((label.as_str(), *next_step)),
            _ => None,
        })
    }

    /// The last pause: reason and next step (whether or not it was resumed since).
    pub fn last_pause(&self) -> Option<(&str, u64)> {
        self.entries.iter().rev().find_map(|e| match e {
            Entry::Paused { reason, next_step } => Some((reason.as_str(), *next_step)),
            _ => None,
        })
    }

    /// The run's last pause was not followed by a resume.
    pub fn is_paused(&self) -> bool {
        for e in self.entries.iter().rev() {
            match e {
                Entry::Paused { .. } => return true,
                Entry::Resumed { .. } => return false,
                _ => {}
            }
        }
        false
    }

    /// The run finished.
    pub fn is_finished(&self) -> bool {
        self.entries
            .iter()
            .any(|e| matches!(e, Entry::Finished { .. }))
    }

    /// The run was aborted: the reason.
    pub fn aborted(&self) -> Option<&str> {
        self.entries.iter().find_map(|e| match e {
            Entry::Aborted { reason } => Some(reason.as_str()),
            _ => None,
        })
    }
}

/// The stored frames that do not count, by index, with their `frames/status` code
/// (`store::STATUS_CODES`): 1 a set the suspender rejected, 2 superseded (an unfinished set
/// taken again whole), 3 found damaged on a resume (a frame with two findings gets the
/// highest). Every other recorded frame counts.
pub fn frame_status(entries: &[Entry]) -> std::collections::BTreeMap<u64, u8> {
    let mut out = std::collections::BTreeMap::new();
    for e in entries {
        mark_frame_status(&mut out, e);
    }
    out
}

/// Adds what `entry` says of which frames count to `status` (see [`frame_status`]).
pub fn mark_frame_status(status: &mut std::collections::BTreeMap<u64, u8>, entry: &Entry) {
    let mut mark = |index: u64, code: u8| {
        let c = status.entry(index).or_insert(code);
        *c = (*c).max(code);
    };
    match entry {
        Entry::SetRejected { frames, .. } => frames.iter().for_each(|&i| mark(i, 1)),
        Entry::FramesSuperseded { frames, .. } => frames.iter().for_each(|&i| mark(i, 2)),
        Entry::FrameDamaged { index, .. } => mark(*index, 3),
        _ => {}
    }
}

/// Reads every entry of `dir/journal.jsonl`. A torn last line is dropped (and reported in
/// [`Replay::torn_tail`]); a bad line before it is an error naming its line number.
pub fn replay(dir: &Path) -> Result<Replay, JournalError> {
    let path = dir.join(JOURNAL_FILE);
    let bytes = read_journal(&path)?;
    let parsed = parse(&path, &bytes)?;
    Ok(Replay {
        entries: parsed.entries,
        torn_tail: parsed.torn_tail,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::FrameKind;
    use serde_json::json;

    fn temp_dir(name: &str) -> PathBuf {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos();
        let dir = std::env::temp_dir().join(format!(
            "polar-journal-{name}-{}-{nanos}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn record(index: u64, hash: u64) -> FrameRecord {
        FrameRecord {
            index,
            step: index,
            kind: FrameKind::Light,
            set: Some(0),
            label: format!("set 0 angle {}", index * 45),
            commanded_angle_deg: index as f64 * 45.0,
            measured_angle_deg: f64::NAN,
            angle_start_deg: index as f64 * 45.0,
            angle_end_deg: index as f64 * 45.0 + 2.5,
            angle_source: crate::AngleSource::EncoderTrigger,
            angle_sigma_deg: 0.01,
            exposure_us: 1000.0,
            gain: 0.0,
            host_time_unix_ns: 1_700_000_000_000_000_000 + index as i64,
            device_timestamp_ns: None,
            frame_id: index + 10,
            sun_zenith_deg: Some(40.0),
            sun_azimuth_deg: None,
            width: 4,
            height: 2,
            hash,
        }
    }

    fn entries() -> Vec<Entry> {
        vec![
            Entry::RunStarted {
                plan: json!({"name": "t"}),
                software: crate::software_version(),
                devices: json!({}),
                width: 4,
                height: 2,
                started_unix_ns: 5,
            },
            Entry::Frame(record(0, 11)),
            Entry::Frame(record(1, 12)),
            Entry::SetRejected {
                set: 0,
                frames: vec![0, 1],
                reason: "the light changed".into(),
            },
            Entry::Frame(record(1, 13)),
            Entry::SetDone {
                set: 1,
                frames: vec![0, 1],
                verdict: json!({"accepted": true}),
            },
            Entry::Decision {
                round: 0,
                decision: json!({"angles": [0, 60, 120]}),
            },
            Entry::Checkpoint {
                label: "set 1 done".into(),
                next_step: 2,
            },
            Entry::Calibration {
                kind: "analyzer".into(),
                result: json!({"offset_deg": 0.1}),
            },
            Entry::Paused {
                reason: "user".into(),
                next_step: 2,
            },
            Entry::Resumed {
                process_id: 7,
                at_unix_ns: 9,
            },
            Entry::Finished { frames: 2 },
        ]
    }

    /// NaN compares unequal; compare the JSON forms.
    fn same(a: &[Entry], b: &[Entry]) -> bool {
        serde_json::to_string(a).unwrap() == serde_json::to_string(b).unwrap()
    }

    #[test]
    fn round_trip() {
        let dir = temp_dir("round-trip");
        let mut j = Journal::create(&dir).unwrap();
        for e in entries() {
            j.append(&e).unwrap();
        }
        assert!(matches!(
            Journal::create(&dir),
            Err(JournalError::Exists { .. })
        ));
        let r = replay(&dir).unwrap();
        assert!(!r.torn_tail);
        assert!(same(&r.entries, &entries()));
        let text = std::fs::read_to_string(dir.join(JOURNAL_FILE)).unwrap();
        assert!(text
            .lines()
            .next()
            .unwrap()
            .contains("\"event\":\"run-started\""));
        assert!(text.contains("\"event\":\"frame\""));
        assert!(text.contains("\"event\":\"set-rejected\""));
        // Views.
        assert_eq!(r.run_started().unwrap().width, 4);
        let frames = r.frames();
        assert_eq!(frames.len(), 2);
        assert_eq!(frames[&1].hash, 13, "a later entry supersedes");
        assert!(frames[&0].measured_angle_deg.is_nan());
        assert_eq!(r.frame_records().len(), 2);
        assert_eq!(r.next_frame_index(), 2);
        assert_eq!(r.sets_done().len(), 1);
        assert_eq!(r.sets_rejected()[0].reason, Some("the light changed"));
        assert_eq!(r.rejected_frames().len(), 2);
        assert_eq!(r.decisions().len(), 1);
        assert_eq!(r.calibrations().len(), 1);
        assert_eq!(r.last_checkpoint(), Some(("set 1 done", 2)));
        assert_eq!(r.last_pause(), Some(("user", 2)));
        assert!(!r.is_paused());
        assert!(r.is_finished());
        assert_eq!(r.aborted(), None);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A frame entry written before frames recorded their span reads back as a step-and-shoot
    /// frame: start and end both the settled reading (exactly), source settled, sigma NaN;
    /// a frame entry with a span keeps it (the JSON round trip is exact for these values).
    #[test]
    fn frame_without_span_reads_as_settled() {
        let old = r#"{"index":3,"step":3,"kind":"light","set":0,"label":"set 0 angle 45",
            "commanded_angle_deg":45.0,"measured_angle_deg":44.99,"exposure_us":1000.0,
            "gain":0.0,"host_time_unix_ns":5,"device_timestamp_ns":null,"frame_id":3,
            "sun_zenith_deg":null,"sun_azimuth_deg":null,"width":4,"height":2,"hash":1}"#;
        let mut d = serde_json::Deserializer::from_str(old);
        let r = frame_json::deserialize(&mut d).unwrap();
        assert_eq!(r.angle_start_deg, 44.99);
        assert_eq!(r.angle_end_deg, 44.99);
        assert_eq!(r.angle_source, crate::AngleSource::Settled);
        assert!(r.angle_sigma_deg.is_nan());
        let text = serde_json::to_string(&record(2, 5)).unwrap();
        let mut d = serde_json::Deserializer::from_str(&text);
        let back = frame_json::deserialize(&mut d).unwrap();
        assert_eq!(back.angle_start_deg, 90.0);
        assert_eq!(back.angle_end_deg, 92.5);
        assert_eq!(back.angle_source, crate::AngleSource::EncoderTrigger);
        assert_eq!(back.angle_sigma_deg, 0.01);
    }

    #[test]
    fn torn_tail_is_dropped_and_truncated() {
        let dir = temp_dir("torn");
        let mut j = Journal::create(&dir).unwrap();
        let all = entries();
        for e in &all[..3] {
            j.append(e).unwrap();
        }
        drop(j);
        let path = dir.join(JOURNAL_FILE);
        let good_len = std::fs::metadata(&path).unwrap().len();
        // A partial line (no newline).
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(br#"{"event":"frame","index":3,"st"#).unwrap();
        drop(f);
        let r = replay(&dir).unwrap();
        assert!(r.torn_tail);
        assert!(same(&r.entries, &all[..3]));
        // Garbage on the last line, newline-terminated, also counts as torn.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"\0\0\0\n").unwrap();
        drop(f);
        let r = replay(&dir).unwrap();
        assert!(r.torn_tail, "a bad last line is a torn tail");
        let mut j = Journal::open_append(&dir).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), good_len);
        j.append(&all[3]).unwrap();
        let r = replay(&dir).unwrap();
        assert!(!r.torn_tail);
        assert!(same(&r.entries, &all[..4]));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn corruption_in_the_middle_names_the_line() {
        let dir = temp_dir("corrupt");
        let mut j = Journal::create(&dir).unwrap();
        for e in &entries()[..4] {
            j.append(e).unwrap();
        }
        drop(j);
        let path = dir.join(JOURNAL_FILE);
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines: Vec<String> = text.lines().map(String::from).collect();
        lines[2] = lines[2].replace("\"index\"", "\"ind");
        std::fs::write(&path, lines.join("\n") + "\n").unwrap();
        match replay(&dir) {
            Err(JournalError::Corrupt { line, .. }) => assert_eq!(line, 3),
            other => panic!("expected corruption at line 3, got {other:?}"),
        }
        let e = Journal::open_append(&dir).unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn append_after_reopen_continues() {
        let dir = temp_dir("reopen");
        let all = entries();
        let mut j = Journal::create(&dir).unwrap();
        for e in &all[..5] {
            j.append(e).unwrap();
        }
        drop(j);
        let mut j = Journal::open_append(&dir).unwrap();
        for e in &all[5..] {
            j.append(e).unwrap();
        }
        drop(j);
        let r = replay(&dir).unwrap();
        assert!(same(&r.entries, &all));
        assert!(matches!(
            replay(&dir.join("nope")),
            Err(JournalError::NotFound { .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
