//! Checking a run directory after the fact (`polarimeter check RUN_DIR`): every frame the
//! journal counts is stored and hashes as recorded, frames found damaged on a resume are
//! reported with where their chunk was kept, and no angle set has two product slots. A
//! finished run with damage says so here; nothing is changed on disk.

use crate::journal::{replay, Entry};
use crate::store::RunStore;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// What [`check_run`] found.
#[derive(Debug, Clone, Serialize)]
pub struct RunCheck {
    /// Every counted frame is intact and the products are keyed by set.
    pub ok: bool,
    /// The journal records the run as finished.
    pub finished: bool,
    /// Frames the journal records.
    pub frames_recorded: u64,
    /// Recorded frames whose stored pixels hash as recorded.
    pub frames_intact: u64,
    /// Damage found now: one line per frame (chunk file, frame, step, what is wrong).
    pub damaged: Vec<String>,
    /// Damage found earlier, on a resume: the frame, its step, and where its chunk was kept.
    pub kept_aside: Vec<String>,
    /// Other findings (stored frames no record describes, product slots).
    pub findings: Vec<String>,
}

/// Checks `run_dir` (see the module doc). Errors only when the journal or the store cannot
/// be opened at all.
pub fn check_run(run_dir: &Path) -> Result<RunCheck, crate::run::RunError> {
    let r = replay(run_dir)?;
    let store = RunStore::open(run_dir)?;
    let frames = r.frames();
    let mut kept_aside = Vec::new();
    let mut earlier = std::collections::BTreeSet::new();
    for e in &r.entries {
        if let Entry::FrameDamaged {
            index,
            step,
            chunk,
            kept_as,
            finding,
        } = e
        {
            earlier.insert(*index);
            kept_aside.push(format!(
                "frame {index} (step {step}): {finding}; {chunk} kept as {kept_as}"
            ));
        }
    }
    let counted: Vec<_> = frames
        .values()
        .filter(|f| !earlier.contains(&f.index))
        .map(|f| (*f).clone())
        .collect();
    let v = store.verify(&counted)?;
    let mut damaged = Vec::new();
    for index in v.missing.iter().chain(&v.mismatched) {
        let step = frames.get(index).map_or(0, |f| f.step);
        let what = v.finding(*index);
        damaged.push(format!(
            "{} (step {step}): {what}",
            store.frame_chunk_path(*index).display()
        ));
    }
    let mut findings: Vec<String> = v
        .unrecorded
        .iter()
        .map(|i| format!("frame {i}: stored but not recorded (written by a process that stopped before its journal entry; ignored by readers of the journal)"))
        .collect();
    let mut slots_of: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    for s in store.product_slots()? {
        if let Some(set) = s.set {
            slots_of.entry(set).or_default().push(s.slot);
        }
    }
    for (set, slots) in &slots_of {
        if slots.len() > 1 {
            findings.push(format!("products: set {set} is in slots {slots:?}"));
        }
    }
    let products_ok = slots_of.values().all(|s| s.len() == 1);
    Ok(RunCheck {
        ok: damaged.is_empty() && products_ok,
        finished: r.is_finished(),
        frames_recorded: frames.len() as u64,
        frames_intact: v.ok,
        damaged,
        kept_aside,
        findings,
    })
}
