//! The run core every plan kind shares, and the strategy trait each run loop implements.
//!
//! The core opens the run directory (or a resumed run's journal and store), replays the
//! journal, writes what the products are computed with, starts the storage thread, counts
//! frames and sets, holds a pause, and ends the run: the summary, the calibration a plan
//! computes from its frames, an abort journaled or the storage thread's final checks. A
//! strategy ([`Strategy`]) is how frames are taken: the step loop moves, settles and shoots
//! ([`super::step_loop`]), the spin loop takes frames from a spinning analyzer
//! ([`super::spin_loop`]). [`drive`] runs a strategy from its first frame to its ending.

use super::calibration::calibrate;
use super::clock::now_unix_ns;
use super::ending::{end_aborted, end_done};
use super::link::{Event, RunLink, RunState};
use super::outcome::{CameraStream, Outcome, RunError, Saturation, Summary, Verdict};
use super::pause::{hold_paused, send_store, AfterPause};
use super::pause::{CAP_LENS, UNCAP_LENS};
use super::run_dir::{open_run, set_aside_damaged};
use super::writer::{spawn_writer, FinishChecks, FromStore, ToStore, Writer};
use crate::journal::Entry;
use crate::plan::Plan;
use crate::store::RunStore;
use crate::{FrameKind, FrameRecord};
use polar_model::sensor::{Camera as CameraModel, SensorModel};
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime};
use tokio::sync::mpsc;
use tracing::info;

/// What the core needs to know of the rig to open a run.
pub(super) struct Opening<'r> {
    /// The sensor's width and height, pixels: the store's frame shape.
    pub(super) width: u32,
    /// See `width`.
    pub(super) height: u32,
    /// The devices' description (the store's `devices` attribute).
    pub(super) devices: &'r Value,
    /// The sensor model: the analyzer rows of the products.
    pub(super) sensor: &'r SensorModel,
    /// The camera's noise model.
    pub(super) camera_model: &'r CameraModel,
    /// What the products use the camera model for (the store's `products_camera.used_for`).
    pub(super) used_for: &'static str,
}

/// What the journal of a resumed run says, beyond the frames the core keeps.
#[derive(Default)]
pub(super) struct Replay {
    /// Frames that do not count: in a rejected set, superseded, or damaged.
    pub(super) rejected: BTreeSet<u64>,
    /// Sets journaled as done, with their frames.
    pub(super) sets_done: BTreeMap<u64, Vec<u64>>,
    /// The adaptive planner's decisions, in order.
    pub(super) decisions: Vec<Value>,
    /// Late time-lapse sets the plan's policy skipped: neither taken nor planned.
    pub(super) skipped_sets: BTreeSet<u64>,
    /// The lens as the operator left it at a lens-cap pause (`Some(true)`: capped).
    pub(super) lens_capped: Option<bool>,
}

/// A set the storage thread checked: the set, the suspender's verdict and its mean DoLP.
pub(super) type Checked = (u64, Verdict, f64);

/// The state every run loop shares: the plan, the controller's link, the storage thread's
/// ends, the frames and sets counted, and the run's timings.
pub(super) struct Core<'a> {
    pub(super) plan: &'a Plan,
    pub(super) run_dir: PathBuf,
    pub(super) link: RunLink,
    pub(super) to_store: std::sync::mpsc::SyncSender<ToStore>,
    pub(super) from_store: mpsc::UnboundedReceiver<FromStore>,
    /// The run's store, for reading frames back (the storage thread writes it).
    pub(super) reader: RunStore,
    /// The store's frame shape, pixels.
    pub(super) width: u32,
    /// See `width`.
    pub(super) height: u32,
    /// When the run started (its first process), Unix ns: time-lapse sets are due from it.
    pub(super) run_start_unix_ns: i64,
    /// Frame records by index (this process and replayed).
    pub(super) records: BTreeMap<u64, FrameRecord>,
    /// The accepted frame of each step.
    pub(super) accepted: BTreeMap<u64, u64>,
    /// The next frame's index.
    pub(super) next_index: u64,
    /// Frames sent to the storage thread and not yet durable.
    pub(super) in_flight: BTreeSet<u64>,
    /// Frames the plan takes (an adaptive plan: its budget).
    pub(super) planned_frames: u64,
    pub(super) sets_accepted: u64,
    pub(super) sets_rejected: u64,
    /// Suspender rejections by set.
    pub(super) rejections: HashMap<u64, u32>,
    /// Device operations retried.
    pub(super) retries: u64,
    pub(super) pauses: u64,
    /// Time spent in device operations (as the engine waited for them), seconds.
    pub(super) device_s: f64,
    /// Frames found damaged (kept aside): recorded, neither counted nor verified.
    pub(super) damaged: BTreeSet<u64>,
    started: Instant,
    writer_thread: Option<std::thread::JoinHandle<()>>,
}

impl<'a> Core<'a> {
    /// Opens (or, with `resume`, reopens) `run_dir` for `plan`, replays its journal, writes
    /// the products' camera model and starts the storage thread. The accepted frames and the
    /// planned count are the strategy's to set ([`Core::count_accepted`]).
    pub(super) fn open(
        plan: &'a Plan,
        run_dir: &Path,
        resume: bool,
        link: RunLink,
        rig: Opening<'_>,
    ) -> Result<(Core<'a>, Replay), RunError> {
        let started = Instant::now();
        let (width, height) = (rig.width, rig.height);
        let mut opened = open_run(plan, run_dir, resume, width, height, rig.devices)?;
        tracing::debug!(ms = started.elapsed().as_secs_f64() * 1e3, "store opened");
        // The model the products are computed with, and where it came from (written by every
        // process, the same values: a resume uses the camera file the run started with).
        let kind = rig.devices["kind"].as_str().unwrap_or("unknown");
        let source = rig.devices["camera_file"]
            .as_str()
            .map_or_else(|| format!("{kind} devices"), String::from);
        opened.store.set_attribute(
            "products_camera",
            json!({ "model": rig.camera_model, "source": source, "used_for": rig.used_for }),
        )?;
        let entries = std::mem::take(&mut opened.entries);
        let (mut records, mut rejections, mut damaged) =
            (BTreeMap::new(), HashMap::new(), BTreeSet::new());
        let mut replay = Replay::default();
        for e in &entries {
            replay_entry(e, &mut replay, &mut records, &mut rejections, &mut damaged);
        }
        if resume {
            for index in set_aside_damaged(&mut opened, run_dir, &records, &replay.rejected)? {
                replay.rejected.insert(index);
                damaged.insert(index);
                replay
                    .sets_done
                    .retain(|_, frames| !frames.contains(&index));
            }
        }
        let next_index = records.keys().next_back().map_or(0, |i| i + 1);
        if resume {
            info!(
                frames = records.len(),
                sets_done = replay.sets_done.len(),
                "resuming"
            );
        }
        let darks = dark_sums(&opened.store, &records, &replay.rejected)?;
        let writer = Writer::new(
            opened.store,
            opened.journal,
            plan,
            rig.sensor,
            rig.camera_model,
            records.clone(),
            darks,
        )?;
        let reader = RunStore::open(run_dir)?;
        let (to_store, from_store, writer_thread) = spawn_writer(writer)?;
        if resume {
            send_store(
                &to_store,
                ToStore::Entry(Entry::Resumed {
                    process_id: std::process::id(),
                    at_unix_ns: now_unix_ns(SystemTime::now()),
                }),
            )?;
        }
        let core = Core {
            plan,
            run_dir: run_dir.to_path_buf(),
            link,
            to_store,
            from_store,
            reader,
            width,
            height,
            run_start_unix_ns: opened.run_start_unix_ns,
            records,
            accepted: BTreeMap::new(),
            next_index,
            in_flight: BTreeSet::new(),
            planned_frames: 0,
            sets_accepted: replay.sets_done.len() as u64,
            sets_rejected: rejections.values().map(|n| u64::from(*n)).sum(),
            rejections,
            retries: 0,
            pauses: 0,
            device_s: 0.0,
            damaged,
            started,
            writer_thread: Some(writer_thread),
        };
        Ok((core, replay))
    }

    /// Sets the frames that already count (one per step) and the plan's frame count.
    pub(super) fn count_accepted(&mut self, accepted: BTreeMap<u64, u64>, planned_frames: u64) {
        self.accepted = accepted;
        self.planned_frames = planned_frames;
    }

    /// Publishes the run's state.
    pub(super) fn set_state(&self, s: RunState) {
        self.link.set_state(s);
    }

    /// Sends an event (dropped when the controller's queue is full: the run never waits).
    pub(super) fn event(&self, e: Event) {
        let _ = self.link.events.try_send(e);
    }

    /// Sends `msg` to the storage thread, blocking while two messages are queued.
    pub(super) fn send_store(&self, msg: ToStore) -> Result<(), RunError> {
        send_store(&self.to_store, msg)
    }

    /// Sends `msg` to the storage thread without blocking the loop's thread.
    pub(super) async fn send_store_async(&self, msg: ToStore) -> Result<(), RunError> {
        let tx = self.to_store.clone();
        let sent = tokio::task::spawn_blocking(move || tx.send(msg).is_ok())
            .await
            .unwrap_or(false);
        if sent {
            Ok(())
        } else {
            Err(RunError::Storage("the storage thread stopped".into()))
        }
    }

    /// Takes a message of the storage thread: a durable frame is reported with the durable
    /// frames that count so far (one per step: a superseded or rejected frame no longer counts,
    /// so the progress never passes the plan; a frame still on its way to the store does not
    /// count yet, so each durable frame adds one even when the store lags the loop); a checked
    /// set is returned for the strategy to act on; a storage failure is an error.
    pub(super) fn on_store(&mut self, msg: FromStore) -> Result<Option<Checked>, String> {
        match msg {
            FromStore::Durable { index, label } => {
                self.in_flight.remove(&index);
                // Every frame in flight was counted as accepted when it was taken.
                let pending = self.in_flight.len().min(self.accepted.len());
                self.event(Event::Progress {
                    done: (self.accepted.len() - pending) as u64,
                    planned: self.planned_frames,
                    label,
                });
                Ok(None)
            }
            FromStore::SetChecked {
                set,
                verdict,
                mean_dolp,
            } => Ok(Some((set, verdict, mean_dolp))),
            FromStore::Failed(e) => Err(e),
        }
    }

    /// Journals a pause (`reason`; the run goes on from `next_step`) and waits for the
    /// controller. The strategy has brought its devices to rest and drained the storage
    /// thread first.
    pub(super) async fn hold(
        &mut self,
        reason: &str,
        next_step: u64,
    ) -> Result<AfterPause, RunError> {
        self.pauses += 1;
        hold_paused(&mut self.link, &self.to_store, reason, next_step).await
    }
}

/// Takes one journal entry into the replayed state.
fn replay_entry(
    e: &Entry,
    replay: &mut Replay,
    records: &mut BTreeMap<u64, FrameRecord>,
    rejections: &mut HashMap<u64, u32>,
    damaged: &mut BTreeSet<u64>,
) {
    match e {
        // A run resumed from a lens-cap pause was resumed by the operator who did what the
        // pause asked (in a new process, or at the prompt).
        Entry::Paused { reason, .. } if reason == CAP_LENS => replay.lens_capped = Some(true),
        Entry::Paused { reason, .. } if reason == UNCAP_LENS => replay.lens_capped = Some(false),
        Entry::Frame(r) => {
            records.insert(r.index, r.clone());
        }
        Entry::SetRejected { set, frames, .. } => {
            replay.rejected.extend(frames.iter().copied());
            *rejections.entry(*set).or_default() += 1;
        }
        Entry::SetDone { set, frames, .. } => {
            replay.sets_done.insert(*set, frames.clone());
        }
        Entry::SetLate { set, action, .. } if action == "skipped" => {
            replay.skipped_sets.insert(*set);
        }
        Entry::FramesSuperseded { frames, .. } => replay.rejected.extend(frames.iter().copied()),
        // A set counts until one of its frames is found damaged; then it is taken again.
        Entry::FrameDamaged { index, .. } => {
            replay.rejected.insert(*index);
            damaged.insert(*index);
            replay.sets_done.retain(|_, frames| !frames.contains(index));
        }
        Entry::Decision { decision, .. } => replay.decisions.push(decision.clone()),
        _ => {}
    }
}

/// The sums of the dark frames earlier processes took, by exposure (its bits): a resumed
/// run's products subtract what they would have subtracted without the interruption.
fn dark_sums(
    store: &RunStore,
    records: &BTreeMap<u64, FrameRecord>,
    rejected: &BTreeSet<u64>,
) -> Result<HashMap<u64, (Vec<f64>, u32)>, RunError> {
    let mut darks: HashMap<u64, (Vec<f64>, u32)> = HashMap::new();
    for r in records.values() {
        if r.kind != FrameKind::Dark || rejected.contains(&r.index) {
            continue;
        }
        let pixels = store.read_frame(r.index)?;
        let (sum, n) = darks
            .entry(r.exposure_us.to_bits())
            .or_insert_with(|| (vec![0.0; pixels.len()], 0));
        if sum.len() == pixels.len() {
            sum.iter_mut()
                .zip(&pixels)
                .for_each(|(s, &p)| *s += f64::from(p));
            *n += 1;
        }
    }
    Ok(darks)
}

/// How a run loop takes its frames; the [`Core`] does the rest.
pub(super) trait Strategy<'a> {
    /// The shared state.
    fn core(&mut self) -> &mut Core<'a>;
    /// Takes the plan's frames: `None` when every one is taken, or the outcome (a detach,
    /// an abort) that ends the run first.
    async fn acquire(&mut self) -> Result<Option<Outcome>, RunError>;
    /// Brings the devices to rest after [`Strategy::acquire`] (errors are logged).
    async fn rest(&mut self) {}
    /// Waits until everything sent to the storage thread is done.
    async fn drain(&mut self) -> Result<(), String>;
    /// The steps a finished run must have, each with exactly one accepted frame.
    fn planned_steps(&self) -> BTreeSet<u64>;
    /// The planner's last set, degrees (adaptive runs).
    fn final_angles(&self) -> Option<Vec<f64>> {
        None
    }
    /// The planner's decisions (adaptive runs; `None` where a strategy has no planner).
    fn decisions(&self) -> Option<&[Value]> {
        None
    }
    /// The camera's stream counters (`None`: the camera could not be asked).
    async fn camera_stream(&mut self) -> Option<CameraStream>;
}

/// Runs `strategy` to its ending: the frames, then the summary, the plan's calibration and the
/// storage thread's final checks (or the abort journaled), and the storage thread joined.
pub(super) async fn drive<'a, S: Strategy<'a>>(mut strategy: S) -> Result<Outcome, RunError> {
    let outcome = strategy.acquire().await;
    strategy.rest().await;
    let result = match outcome {
        Ok(outcome) => end(&mut strategy, outcome).await,
        Err(e) => Err(e),
    };
    let writer_thread = strategy.core().writer_thread.take();
    drop(strategy);
    if let Some(handle) = writer_thread {
        let _ = tokio::task::spawn_blocking(move || handle.join()).await;
    }
    result
}

/// The ending of a loop that returned `outcome` (`None`: every frame taken).
async fn end<'a, S: Strategy<'a>>(
    strategy: &mut S,
    outcome: Option<Outcome>,
) -> Result<Outcome, RunError> {
    tracing::debug!("steps done; draining");
    strategy.drain().await.map_err(RunError::Storage)?;
    let final_angles_deg = strategy.final_angles();
    let planned_steps = strategy.planned_steps();
    let decisions = strategy.decisions().map(<[Value]>::to_vec);
    let camera_stream = strategy.camera_stream().await;
    let core = strategy.core();
    let plan = core.plan;
    let summary = Summary {
        frames_stored: core.next_index,
        frames_accepted: core.accepted.len() as u64,
        sets_accepted: core.sets_accepted,
        sets_rejected: core.sets_rejected,
        retries: core.retries,
        pauses: core.pauses,
        elapsed_s: core.started.elapsed().as_secs_f64(),
        device_s: core.device_s,
        final_angles_deg,
        saturation: Saturation::of(&core.reader, plan.suspender.max_saturated_fraction)?,
        camera_stream: camera_stream.map(Box::new),
    };
    let result = match outcome {
        Some(Outcome::Aborted(reason)) => end_aborted(&core.link, &core.to_store, reason),
        Some(other) => Ok(other),
        None => {
            if let Some((kind, result)) =
                calibrate(plan, &core.reader, &core.records, &core.accepted)?
            {
                record_calibration(core, kind, result).await?;
            }
            let mut summary_json = json!({
                "run": serde_json::to_value(&summary).unwrap_or(Value::Null),
            });
            if let Some(d) = &decisions {
                summary_json["decisions"] = Value::Array(d.clone());
            }
            let checks = FinishChecks {
                planned_steps,
                accepted: core.accepted.clone(),
                damaged: core.damaged.clone(),
            };
            end_done(&core.link, &core.to_store, summary_json, checks).await?;
            Ok(Outcome::Done(summary))
        }
    };
    if let Some(d) = decisions.filter(|d| !d.is_empty()) {
        if let Ok(store) = RunStore::open(&core.run_dir) {
            let _ = store.set_attribute("decisions", Value::Array(d));
        }
    }
    result
}

/// Journals the plan's calibration result and writes it as the store's `calibration`
/// attribute (through the storage thread, which owns the store).
async fn record_calibration(core: &Core<'_>, kind: String, result: Value) -> Result<(), RunError> {
    info!(kind = %kind, "calibration: {result}");
    core.send_store(ToStore::Entry(Entry::Calibration {
        kind: kind.clone(),
        result: result.clone(),
    }))?;
    let (tx, rx) = std::sync::mpsc::channel();
    core.send_store(ToStore::Attribute {
        key: "calibration".into(),
        value: json!({ kind: result }),
        reply: tx,
    })?;
    let r = tokio::task::spawn_blocking(move || rx.recv())
        .await
        .map_err(|e| RunError::Storage(e.to_string()))?
        .map_err(|_| RunError::Storage("the storage thread stopped".into()))?;
    r.map_err(RunError::Storage)
}
