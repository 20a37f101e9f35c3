//! A run: the state machine that turns a plan into stored frames and products.
//!
//! **States.** Running; pausing at the next safe point (between angle sets, or between
//! single frames outside sets); paused (with the reason: the user, a device error after the
//! plan's retries, a storage error, the suspender, a dark series that needs the lens capped);
//! aborting; done. [`Control::Pause`] asks for the next safe point; [`Control::PauseNow`]
//! cancels the device operation in flight (its step is taken again on resume);
//! [`Control::Resume`] continues a paused run; [`Control::Abort`] ends a paused or a running
//! run (a running one at once: the device operation in flight is cancelled);
//! [`Control::Detach`] (or dropping the controller) leaves the run to `polarimeter resume`.
//!
//! **Actors.** The analyzer and the camera are each owned by one task
//! ([`tokio::task::spawn_local`]) that takes commands from a bounded channel; nothing else
//! touches them. The storage thread owns the journal and the Zarr store, and computes the
//! products and the suspender's verdict of each set. The next move starts as soon as a frame
//! is grabbed, so it overlaps the frame's write, and the first move of the next set
//! overlaps the products of the last.
//!
//! **Durability.** A step counts when its frame's chunk is fsynced and its journal line is
//! flushed (`journal::Journal::append`). A crash loses at most the frame in flight; the
//! resumed run (a new process, [`run`] with `resume = true`) takes that step again, into the
//! same frame index, so there is no duplicate and no gap. At the end every planned step must
//! have exactly one accepted frame whose stored pixels hash to the journaled hash; anything
//! else is an error.
//!
//! **Suspender.** Every set is checked against the model before it counts: the mean reduced
//! chi-square of the per-pixel Malus fit (sets of 4 or more angles), the change of the mean S0
//! from the last accepted set (sets of 3), the analyzer's readback against the command, and
//! frames repeated bit for bit (a stuck camera). A failing set is recorded with the reason and
//! taken again, or pauses the run, as the plan says.

use crate::journal::{Entry, Journal};
use crate::plan::{Plan, PlanKind, StepSpec, SuspendAction};
use crate::products::{self, Dark, NoiseModel, Products, SetGeometry};
use crate::store::{RunStore, STORE_DIR};
use crate::{pixel_hash, FrameKind, FrameRecord};
use polar_hal::{Analyzer, Camera, DeviceError, ErrorKind, Frame, TriggerMode};
use polar_model::sensor::{Camera as CameraModel, SensorModel};
use polar_planner::aptd::{Aptd, AptdConfig, AptdFrame, Step as AptdStep, TargetSpec};
use polar_planner::Constraints;
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{info, info_span, warn, Instrument};

/// The pause before dark frames on hardware (no simulated lens cap): the operator caps the
/// lens and resumes the run.
pub const CAP_LENS: &str = "cap the lens for the dark frames, then resume";
/// The pause after dark frames on hardware: the operator uncaps the lens and resumes.
pub const UNCAP_LENS: &str = "uncap the lens, then resume";

/// What a controller can ask of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Pause at the next safe point.
    Pause,
    /// Pause now: cancel the device operation in flight.
    PauseNow,
    /// Continue a paused run.
    Resume,
    /// Stop the run for good, paused or running (what was acquired stays).
    Abort,
    /// Leave a paused run to be resumed later (`polarimeter resume`).
    Detach,
}

/// Where a run is.
#[derive(Debug, Clone, PartialEq)]
pub enum RunState {
    /// Starting devices and storage.
    Starting,
    /// Acquiring.
    Running,
    /// A pause was asked; it happens at the next safe point.
    Pausing,
    /// Paused, with the reason.
    Paused(String),
    /// Finishing after an abort.
    Aborting,
    /// Every planned frame is stored and checked.
    Done,
    /// Aborted, with the reason.
    Aborted(String),
}

/// What happened, for progress bars, logs and the GUI.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The state changed.
    State(RunState),
    /// A frame is durable: `done` of at most `planned` frames.
    Progress {
        /// Frames stored and counted.
        done: u64,
        /// Frames the plan takes (an adaptive plan: its budget).
        planned: u64,
        /// The step's label.
        label: String,
    },
    /// A set was checked.
    Set {
        /// The set.
        set: u64,
        /// Accepted or why not.
        verdict: Verdict,
        /// Mean S0, DoLP of the set (over finite pixels).
        mean_s0: f64,
        /// Mean DoLP.
        mean_dolp: f64,
    },
    /// The planner decided (adaptive runs).
    Decision(Value),
    /// A device operation failed and will be retried.
    Retry(String),
}

/// The suspender's verdict on a set.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Verdict {
    /// The set counts.
    pub accepted: bool,
    /// Why not (empty when accepted).
    pub reason: String,
    /// Mean reduced chi-square of the per-pixel Malus fit (NaN for 3 angles).
    pub reduced_chi2: f64,
    /// Mean S0 of the set, DN.
    pub mean_s0_dn: f64,
    /// Largest |commanded - measured| analyzer angle, degrees.
    pub max_angle_error_deg: f64,
    /// The share of the set's pixels where a frame saturated (their products are NaN).
    #[serde(default)]
    pub saturated_fraction: f64,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Every planned frame stored and verified.
    Done(Summary),
    /// Paused and detached: `polarimeter resume` continues it.
    Paused(String),
    /// Aborted.
    Aborted(String),
}

/// What a finished run did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Frames stored (accepted and superseded).
    pub frames_stored: u64,
    /// Frames that count.
    pub frames_accepted: u64,
    /// Sets accepted.
    pub sets_accepted: u64,
    /// Sets the suspender rejected (and took again).
    pub sets_rejected: u64,
    /// Device operations retried.
    pub retries: u64,
    /// Pauses (any reason).
    pub pauses: u64,
    /// Wall time of this process's part of the run, seconds.
    pub elapsed_s: f64,
    /// Of which the engine waited on device operations (moves with their readback, grabs),
    /// seconds: the rest is the engine's own time that did not overlap a device.
    pub device_s: f64,
    /// The planner's last set, degrees (adaptive runs).
    pub final_angles_deg: Option<Vec<f64>>,
    /// The sets (of the whole run, every process's) whose saturated share of pixels is over
    /// the plan's `suspender.max_saturated_fraction`.
    pub saturation: Saturation,
}

/// Saturated pixels over a run, from the store's per-set record.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
pub struct Saturation {
    /// The plan's limit, a share of a set's pixels.
    pub max_fraction: f64,
    /// The largest share of any set.
    pub worst_fraction: f64,
    /// The sets over the limit and their shares.
    pub sets_over: Vec<(u64, f64)>,
    /// What to do about it (empty when no set is over the limit).
    pub warning: String,
}

impl Saturation {
    /// The run's saturation from the store's per-set shares and the plan's limit.
    pub fn of(store: &RunStore, max_fraction: f64) -> Result<Saturation, RunError> {
        let shares = store.product_saturation()?;
        let worst_fraction = shares.values().copied().fold(0.0, f64::max);
        let sets_over: Vec<(u64, f64)> = shares
            .into_iter()
            .filter(|(_, f)| *f > max_fraction)
            .collect();
        let warning = if sets_over.is_empty() {
            String::new()
        } else {
            format!(
                "{} set(s) saturate more than {:.1} % of their pixels (the worst {:.1} %; \
                 suspender.max_saturated_fraction): their products are NaN there. Shorten the \
                 exposure or lower the gain (plan check shows the saturation margin)",
                sets_over.len(),
                100.0 * max_fraction,
                100.0 * worst_fraction
            )
        };
        Ok(Saturation {
            max_fraction,
            worst_fraction,
            sets_over,
            warning,
        })
    }
}

/// Why a run could not go on at all (as opposed to pausing).
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The plan cannot run.
    #[error(transparent)]
    Plan(#[from] crate::plan::PlanError),
    /// The run directory.
    #[error("run directory {path}: {message}")]
    Dir {
        /// The directory.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// The journal.
    #[error(transparent)]
    Journal(#[from] crate::journal::JournalError),
    /// The store.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// The frames written do not match the frames planned, or a stored frame does not match
    /// its journaled hash.
    #[error("run check failed: {0}")]
    Check(String),
    /// The planner.
    #[error("planner: {0}")]
    Planner(String),
    /// A device could not be set up.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The storage thread went away.
    #[error("storage thread: {0}")]
    Storage(String),
}

/// The light of a simulated scene, as the run sets it: the fraction of the scene's light that
/// reaches the sensor, 0 (the lens capped, for darks) to 1 (a passing cloud in between).
pub type SceneLight = std::sync::Arc<dyn Fn(f64) + Send + Sync>;

/// What a run drives and knows about its devices.
pub struct Rig<A, C> {
    /// The analyzer (a rotator or a wheel of polarizers).
    pub analyzer: A,
    /// The camera.
    pub camera: C,
    /// The camera's noise model (the calibrated camera file).
    pub camera_model: CameraModel,
    /// The sensor model (camera, analyzer and band): the analyzer rows of the products.
    pub sensor: SensorModel,
    /// The simulated scene's lens cap and clouds; `None` on real hardware (dark series then
    /// pause for the operator to cap the lens).
    pub illumination: Option<SceneLight>,
    /// The adaptive loop's target pixels, when known as a mask.
    pub target_mask: Option<Vec<bool>>,
    /// The sun every frame records, zenith and azimuth in degrees: a simulated scene's own
    /// sun; `None` on real devices, where each frame records the real sun at the plan's
    /// site and the frame's time.
    pub sun_deg: Option<(f64, f64)>,
    /// A description of the devices for the store.
    pub devices: Value,
}

/// The controller's end: send [`Control`]s, watch the state, read [`Event`]s.
pub struct Controller {
    /// Commands to the run.
    pub control: mpsc::Sender<Control>,
    /// The run's state.
    pub state: watch::Receiver<RunState>,
    /// Events (bounded; the run never waits on a slow reader: events are dropped if full).
    pub events: mpsc::Receiver<Event>,
}

/// The run's end of the controller.
pub struct RunLink {
    control: mpsc::Receiver<Control>,
    state: watch::Sender<RunState>,
    events: mpsc::Sender<Event>,
}

/// A connected controller and run link.
pub fn link() -> (Controller, RunLink) {
    let (ctx, crx) = mpsc::channel(16);
    let (stx, srx) = watch::channel(RunState::Starting);
    let (etx, erx) = mpsc::channel(1024);
    (
        Controller {
            control: ctx,
            state: srx,
            events: erx,
        },
        RunLink {
            control: crx,
            state: stx,
            events: etx,
        },
    )
}

fn now_unix_ns(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

// ---------------------------------------------------------------------------------------
// Device actors.

mod actors;
mod adaptive;
mod calibration;
mod continuous_loop;
mod ending;
mod pause;
mod record;
mod run_dir;
mod simulated;
mod step_loop;
pub mod timestamps;
mod writer;

use actors::*;
pub use adaptive::replayed_decisions;
use adaptive::*;
use calibration::*;
pub use continuous_loop::{run_continuous, RUN_UP_S};
use ending::*;
use pause::*;
use record::*;
use run_dir::*;
pub use run_dir::{default_run_dir, is_finished, noise_stream, plan_of, run_parts};
pub use simulated::{run_simulated, SimRunError};
use step_loop::*;
use writer::*;

/// Runs (or, with `resume`, continues) `plan` into `run_dir` on `rig`, reporting through
/// `link`. Call it inside a [`tokio::task::LocalSet`] (the device actors are local tasks).
/// Pauses wait for the controller; errors that leave nothing to resume are returned.
pub async fn run<A, C>(
    plan: &Plan,
    rig: Rig<A, C>,
    run_dir: &Path,
    resume: bool,
    link: RunLink,
) -> Result<Outcome, RunError>
where
    A: Analyzer + 'static,
    C: Camera + 'static,
{
    let started = Instant::now();
    let info = rig.camera.info().clone();
    let (width, height) = (info.sensor_width, info.sensor_height);
    plan.check_frame(width, height)?;
    if plan.kind == PlanKind::Continuous {
        // The step loop moves, settles and shoots: it must not run a spinning plan.
        return Err(crate::plan::PlanError::Invalid {
            field: "kind".into(),
            value: "continuous".into(),
            allowed: "capture, calibrate-noise, calibrate-analyzer, time-lapse or adaptive \
                      for `run` (the step loop does not spin the analyzer: a continuous plan \
                      runs through `run_continuous` or `run_simulated`)"
                .into(),
        }
        .into());
    }
    let stage = spawn_stage(rig.analyzer);
    // A new run that starts with a set: the stage goes to its first angle while the store is
    // created (about 30 fsyncs).
    let mut first_move = None;
    if !resume && plan.adaptive.is_none() {
        let first = plan.steps().ok().and_then(|steps| steps.into_iter().next());
        if let Some(first) = first.filter(|s| s.set.is_some() && s.not_before_s.is_none()) {
            let (tx, reply) = oneshot::channel();
            let sent = stage.try_send(StageCmd::SetAngle {
                psi_rad: first.angle_deg.to_radians(),
                reply: tx,
            });
            if sent.is_ok() {
                first_move = Some(PendingMove {
                    angle_deg: first.angle_deg,
                    reply,
                });
            }
        }
    }
    let opened = open_run(plan, run_dir, resume, width, height, &rig.devices)?;
    tracing::debug!(ms = started.elapsed().as_secs_f64() * 1e3, "store opened");
    let run_start_unix_ns = opened.run_start_unix_ns;
    let mut opened = opened;
    let entries = std::mem::take(&mut opened.entries);
    // The model the products are computed with, and where it came from (written by every
    // process, the same values: a resume uses the camera file the run started with).
    let source = rig.devices["camera_file"].as_str().map_or_else(
        || {
            format!(
                "{} devices",
                rig.devices["kind"].as_str().unwrap_or("unknown")
            )
        },
        String::from,
    );
    opened.store.set_attribute(
        "products_camera",
        json!({
            "model": rig.camera_model,
            "source": source,
            "used_for": "the analyzer rows (transmittance, extinction ratio, angle offset), \
                         the noise (gain K in DN per electron, offset, read noise) and the \
                         scalar dark level of the products",
        }),
    )?;

    // Replay.
    let mut records: BTreeMap<u64, FrameRecord> = BTreeMap::new();
    let mut rejected: BTreeSet<u64> = BTreeSet::new();
    let mut sets_done: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    let mut rejections: HashMap<u64, u32> = HashMap::new();
    let mut decisions: Vec<Value> = Vec::new();
    // Frames found damaged (kept aside): they stay recorded but neither count nor verify.
    let mut damaged: BTreeSet<u64> = BTreeSet::new();
    // Late time-lapse sets the plan's policy skipped: neither taken nor planned.
    let mut skipped_sets: BTreeSet<u64> = BTreeSet::new();
    // The lens as the operator left it: a run resumed from a lens-cap pause was resumed by
    // the operator who did what the pause asked (in a new process, or at the prompt).
    let mut lens_capped = None;
    for e in &entries {
        match e {
            Entry::Paused { reason, .. } if reason == CAP_LENS => lens_capped = Some(true),
            Entry::Paused { reason, .. } if reason == UNCAP_LENS => lens_capped = Some(false),
            Entry::Frame(r) => {
                records.insert(r.index, r.clone());
            }
            Entry::SetRejected { set, frames, .. } => {
                rejected.extend(frames.iter().copied());
                *rejections.entry(*set).or_default() += 1;
            }
            Entry::SetDone { set, frames, .. } => {
                sets_done.insert(*set, frames.clone());
            }
            Entry::SetLate { set, action, .. } if action == "skipped" => {
                skipped_sets.insert(*set);
            }
            Entry::FrameDamaged { index, .. } => {
                rejected.insert(*index);
                damaged.insert(*index);
                sets_done.retain(|_, frames| !frames.contains(index));
            }
            Entry::Decision { decision, .. } => decisions.push(decision.clone()),
            _ => {}
        }
    }
    if resume {
        for index in set_aside_damaged(&mut opened, run_dir, &records, &rejected)? {
            rejected.insert(index);
            damaged.insert(index);
            sets_done.retain(|_, frames| !frames.contains(&index));
        }
    }
    let mut accepted: BTreeMap<u64, u64> = BTreeMap::new();
    for r in records.values() {
        if !rejected.contains(&r.index) {
            accepted.insert(r.step, r.index);
        }
    }
    let next_index = records.keys().next_back().map_or(0, |i| i + 1);
    if resume {
        info!(
            frames = records.len(),
            accepted = accepted.len(),
            sets_done = sets_done.len(),
            "resuming"
        );
    }

    // The darks earlier processes took count towards this process's dark maps: the products
    // of a resumed run subtract what they would have subtracted without the interruption.
    let mut darks: HashMap<u64, (Vec<f64>, u32)> = HashMap::new();
    for r in records.values() {
        if r.kind != FrameKind::Dark || rejected.contains(&r.index) {
            continue;
        }
        let pixels = opened.store.read_frame(r.index)?;
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
    let writer = Writer::new(
        opened.store,
        opened.journal,
        plan,
        &rig.sensor,
        &rig.camera_model,
        records.clone(),
        darks,
    )?;
    let reader = RunStore::open(run_dir)?;
    let (to_store, from_store, writer_thread) = spawn_writer(writer)?;
    if resume {
        to_store
            .send(ToStore::Entry(Entry::Resumed {
                process_id: std::process::id(),
                at_unix_ns: now_unix_ns(SystemTime::now()),
            }))
            .map_err(|_| RunError::Storage("the storage thread stopped".into()))?;
    }

    let camera = spawn_camera(rig.camera);
    let done_frames = accepted.len() as u64;
    let mut lp = Loop {
        plan,
        link,
        stage,
        camera,
        to_store,
        from_store,
        illumination: rig.illumination.clone(),
        sun_deg: rig.sun_deg,
        width,
        height,
        next_index,
        accepted,
        records,
        in_flight: BTreeSet::new(),
        pausing: false,
        done_frames,
        planned_frames: plan.max_frames()?,
        configured: None,
        retries: 0,
        pauses: 0,
        sets_accepted: sets_done.len() as u64,
        sets_rejected: rejections.values().map(|n| u64::from(*n)).sum(),
        rejections,
        keep_pixels: plan.kind == PlanKind::Adaptive,
        kept: HashMap::new(),
        lens_capped,
        light_level: 1.0,
        device_s: 0.0,
        verdicts: VecDeque::new(),
        pending_move: first_move,
        ending: None,
    };
    lp.set_state(RunState::Running);

    // The work list.
    let steps = plan.steps()?;
    // A set the journal records as done keeps its frames and products: a resumed run does
    // not check it (nor write its products) again.
    let mut units: VecDeque<Unit> = units_of(&steps, 0)
        .into_iter()
        .filter(|u| {
            !matches!(u, Unit::Set(set, _) if sets_done.contains_key(set) || skipped_sets.contains(set))
        })
        .collect();
    let mut planned_steps: BTreeSet<u64> = steps
        .iter()
        .enumerate()
        .filter(|(_, s)| !s.set.is_some_and(|set| skipped_sets.contains(&set)))
        .map(|(i, _)| i as u64)
        .collect();
    let mut aptd: Option<Aptd> = None;
    let mut final_angles: Option<Vec<f64>> = None;
    let mut aptd_next_step = steps.len() as u64;
    let mut aptd_set = 0u64;
    if let Some(a) = &plan.adaptive {
        let (machine, planned, next) = adaptive_start(
            plan,
            a,
            &rig.target_mask,
            &lp.records,
            &lp.accepted,
            &sets_done,
            &reader,
            &steps,
            width,
            height,
            &rig.camera_model,
        )?;
        // Replace the static first set with the replayed state.
        units = units_of(&steps, 0)
            .into_iter()
            .filter(|u| matches!(u, Unit::Single(..)))
            .collect();
        planned_steps = planned;
        match next {
            AdaptiveNext::Acquire(set, members) => {
                aptd_set = set;
                aptd_next_step = members.last().map_or(aptd_next_step, |(s, _)| s + 1);
                final_angles = Some(members.iter().map(|(_, s)| s.angle_deg).collect());
                units.push_back(Unit::Set(set, members));
            }
            AdaptiveNext::Done(angles) => final_angles = Some(angles),
        }
        aptd = Some(machine);
    }

    // Sets sent to the storage thread for their products and verdict: their steps and frames.
    let mut checking: BTreeMap<u64, Checking> = BTreeMap::new();
    let outcome = 'run: loop {
        // Verdicts that arrived: a static plan's sets are checked behind the acquisition of
        // the next ones; an adaptive plan waits for each (its next set depends on it).
        while let Some((set, verdict, mean_dolp)) = lp.verdicts.pop_front() {
            let Some((members, frames)) = checking.remove(&set) else {
                continue;
            };
            lp.event(Event::Set {
                set,
                verdict: verdict.clone(),
                mean_s0: verdict.mean_s0_dn,
                mean_dolp,
            });
            if verdict.accepted {
                lp.sets_accepted += 1;
                lp.send_store(ToStore::Entry(Entry::Checkpoint {
                    label: format!("set {set} done"),
                    next_step: members.last().map_or(0, |(s, _)| s + 1),
                }))?;
                if let Some(machine) = aptd.as_mut() {
                    // Every frame of the set, those an earlier process took (read back from
                    // the store) included: the planner sees exactly the set's frames.
                    let mut aptd_frames: Vec<AptdFrame> = Vec::with_capacity(frames.len());
                    for i in &frames {
                        let r = lp.records.get(i).ok_or_else(|| {
                            RunError::Check(format!("frame {i} of set {set} has no record"))
                        })?;
                        let px = match lp.kept.remove(i) {
                            Some(px) => px,
                            None => reader.read_frame(*i)?,
                        };
                        aptd_frames.push(aptd_frame(r, &px, &rig.camera_model, plan));
                    }
                    let step = machine
                        .on_frames(aptd_frames)
                        .map_err(|e| RunError::Planner(e.to_string()))?;
                    if let Some(d) = machine.decisions().last() {
                        let v = decision_json(d);
                        lp.send_store(ToStore::Entry(Entry::Decision {
                            round: d.round as u64,
                            decision: v.clone(),
                        }))?;
                        decisions.push(v.clone());
                        lp.event(Event::Decision(v));
                    }
                    if let AptdStep::Acquire(angles) = step {
                        aptd_set += 1;
                        let members = adaptive_set(plan, aptd_set, aptd_next_step, &angles);
                        aptd_next_step += members.len() as u64;
                        planned_steps.extend(members.iter().map(|(s, _)| *s));
                        final_angles = Some(members.iter().map(|(_, s)| s.angle_deg).collect());
                        units.push_back(Unit::Set(aptd_set, members));
                    }
                }
            } else {
                lp.sets_rejected += 1;
                let n = lp.rejections.entry(set).or_default();
                *n += 1;
                let tries = *n;
                warn!(set, reason = %verdict.reason, "set rejected");
                for (s, _) in &members {
                    lp.accepted.remove(s);
                }
                let cfg = &plan.suspender;
                let first = members[0].0;
                units.push_front(Unit::Set(set, members));
                if cfg.action == SuspendAction::Pause || tries > cfg.max_reacquire {
                    let reason = format!("set {set} rejected {tries} times: {}", verdict.reason);
                    match lp.pause(reason, first).await? {
                        AfterPause::Resume => {}
                        AfterPause::Abort(r) => break 'run Some(Outcome::Aborted(r)),
                        AfterPause::Detach(r) => break 'run Some(Outcome::Paused(r)),
                    }
                }
            }
        }
        let Some(unit) = units.pop_front() else {
            if checking.is_empty() {
                break None;
            }
            lp.next_from_store().await?;
            continue;
        };
        // Safe point.
        if lp.pausing {
            let next = unit_first_step(&unit);
            match lp.pause("paused by the user".into(), next).await? {
                AfterPause::Resume => {}
                AfterPause::Abort(r) => break Some(Outcome::Aborted(r)),
                AfterPause::Detach(r) => break Some(Outcome::Paused(r)),
            }
        }
        // A unit an earlier process finished has nothing to take (and asks nothing of the
        // operator).
        let finished = match &unit {
            Unit::Single(step, _) => lp.accepted.contains_key(step),
            Unit::Set(_, members) => members.iter().all(|(s, _)| lp.accepted.contains_key(s)),
        };
        if finished && !matches!(unit, Unit::Set(..)) {
            continue;
        }
        // Darks on hardware: the operator caps the lens at a pause.
        if lp.illumination.is_none() && !finished {
            let wants_dark = match &unit {
                Unit::Single(_, s) => s.kind == FrameKind::Dark,
                Unit::Set(..) => false,
            };
            if lp.lens_capped != Some(wants_dark) && (wants_dark || lp.lens_capped.is_some()) {
                let reason = if wants_dark { CAP_LENS } else { UNCAP_LENS };
                match lp.pause(reason.into(), unit_first_step(&unit)).await? {
                    AfterPause::Resume => lp.lens_capped = Some(wants_dark),
                    AfterPause::Abort(r) => break Some(Outcome::Aborted(r)),
                    AfterPause::Detach(r) => {
                        units.push_front(unit);
                        break Some(Outcome::Paused(r));
                    }
                }
            }
        }
        // Time-lapse: wait for the set's time; a set late by more than half an interval
        // follows the plan's policy, said in the journal and the store.
        if let (Some(t), Some(tl), Unit::Set(set, members)) =
            (unit_not_before(&unit), plan.time_lapse.as_ref(), &unit)
        {
            let due_ns = run_start_unix_ns + (t * 1e9) as i64;
            let late_s = (now_unix_ns(SystemTime::now()) - due_ns) as f64 * 1e-9;
            if late_s > 0.5 * tl.interval_s {
                let skip = tl.late == crate::plan::LatePolicy::Skip;
                warn!(
                    set,
                    late_s,
                    "time-lapse set {set} is {late_s:.1} s late: {}",
                    if skip { "skipped" } else { "taken at once" }
                );
                lp.send_store(ToStore::Entry(Entry::SetLate {
                    set: *set,
                    due_unix_ns: due_ns,
                    late_s,
                    action: if skip { "skipped" } else { "taken" }.into(),
                }))?;
                if skip {
                    for (s, _) in members {
                        planned_steps.remove(s);
                    }
                    continue;
                }
            }
        }
        if let Some(t) = unit_not_before(&unit) {
            let due_ns = run_start_unix_ns + (t * 1e9) as i64;
            let wait_ns = due_ns - now_unix_ns(SystemTime::now());
            if wait_ns > 0 {
                let sleep = tokio::time::sleep(Duration::from_nanos(wait_ns as u64));
                tokio::pin!(sleep);
                let mut interrupted = false;
                let mut controller_gone = false;
                loop {
                    if controller_gone {
                        (&mut sleep).await;
                        break;
                    }
                    tokio::select! {
                        _ = &mut sleep => break,
                        c = lp.link.control.recv() => {
                            let Some(c) = c else {
                                controller_gone = true;
                                continue;
                            };
                            if lp.handle_control(c).is_some() || lp.pausing {
                                interrupted = true;
                                break;
                            }
                        }
                    }
                }
                if interrupted {
                    units.push_front(unit);
                    continue;
                }
            }
        }
        match unit {
            Unit::Single(step, spec) => {
                if lp.accepted.contains_key(&step) {
                    continue;
                }
                let span = info_span!("step", step, label = %spec.label);
                match lp.acquire(step, &spec, None).instrument(span).await {
                    Ok(_) => {}
                    Err(e) => {
                        let reason = match e {
                            OpError::Interrupted => "paused by the user (immediately)".to_string(),
                            OpError::Device(e) => format!("{}: {e}", spec.label),
                        };
                        units.push_front(Unit::Single(step, spec));
                        match lp.pause(reason, step).await? {
                            AfterPause::Resume => continue,
                            AfterPause::Abort(r) => break Some(Outcome::Aborted(r)),
                            AfterPause::Detach(r) => break Some(Outcome::Paused(r)),
                        }
                    }
                }
            }
            Unit::Set(set, members) => {
                let mut failed = None;
                // After the set's last frame the stage may go ahead to the next set's first
                // angle, unless a pause or a wait for the set's time comes first.
                let next_set_deg = match units.front() {
                    Some(u @ Unit::Set(_, next)) if unit_not_before(u).is_none() => next
                        .iter()
                        .find(|(s, _)| !lp.accepted.contains_key(s))
                        .map(|(_, s)| s.angle_deg),
                    _ => None,
                };
                for (i, (step, spec)) in members.iter().enumerate() {
                    if lp.accepted.contains_key(step) {
                        continue;
                    }
                    let next_deg = members[i + 1..]
                        .iter()
                        .find(|(s, _)| !lp.accepted.contains_key(s))
                        .map(|(_, s)| s.angle_deg)
                        .or(if lp.pausing { None } else { next_set_deg });
                    let span = info_span!("step", step, label = %spec.label);
                    // A passing cloud in the middle of a set (simulation).
                    if let (Some(_), Some(cloud_set)) =
                        (&lp.illumination, plan.simulation.cloud_at_set)
                    {
                        let first_try = !lp.rejections.contains_key(&set);
                        let mid = members.len() / 2;
                        if set == cloud_set && first_try && members[mid].0 == *step {
                            warn!(set, "simulation: a cloud passes");
                            lp.light_level = 1.0 - plan.simulation.cloud_depth;
                        }
                    }
                    let r = lp.acquire(*step, spec, next_deg).instrument(span).await;
                    if let Err(e) = r {
                        failed = Some((*step, e));
                        break;
                    }
                }
                lp.light_level = 1.0;
                if let Some(light) = &lp.illumination {
                    light(1.0);
                }
                if let Some((step, e)) = failed {
                    let reason = match e {
                        OpError::Interrupted => "paused by the user (immediately)".to_string(),
                        OpError::Device(e) => format!("set {set}: {e}"),
                    };
                    units.push_front(Unit::Set(set, members));
                    match lp.pause(reason, step).await? {
                        AfterPause::Resume => continue,
                        AfterPause::Abort(r) => break Some(Outcome::Aborted(r)),
                        AfterPause::Detach(r) => break Some(Outcome::Paused(r)),
                    }
                }
                // Check the set (the storage thread), overlapping the next set's first move.
                let frames: Vec<u64> = members
                    .iter()
                    .filter_map(|(s, _)| lp.accepted.get(s).copied())
                    .collect();
                let job = SetJob {
                    set,
                    measured_deg: frames
                        .iter()
                        .map(|i| lp.records.get(i).map_or(f64::NAN, |r| r.measured_angle_deg))
                        .collect(),
                    commanded_deg: members.iter().map(|(_, s)| s.angle_deg).collect(),
                    exposure_us: members[0].1.exposure_us,
                    gain_db: members[0].1.gain_db,
                    frames: frames.clone(),
                    rows: None,
                };
                lp.send_store(ToStore::ProcessSet(job))?;
                checking.insert(set, (members, frames));
                if aptd.is_some() {
                    while !lp.verdicts.iter().any(|v| v.0 == set) {
                        lp.next_from_store().await?;
                    }
                }
            }
        }
    };

    // Let the writer finish what it has.
    tracing::debug!(
        ms = started.elapsed().as_secs_f64() * 1e3,
        "steps done; draining"
    );
    if let Err(e) = lp.drain().await {
        return Err(RunError::Storage(e));
    }
    tracing::debug!(ms = started.elapsed().as_secs_f64() * 1e3, "drained");
    let summary = Summary {
        frames_stored: lp.next_index,
        frames_accepted: lp.accepted.len() as u64,
        sets_accepted: lp.sets_accepted,
        sets_rejected: lp.sets_rejected,
        retries: lp.retries,
        pauses: lp.pauses,
        elapsed_s: started.elapsed().as_secs_f64(),
        device_s: lp.device_s,
        final_angles_deg: final_angles.clone(),
        saturation: Saturation::of(&reader, plan.suspender.max_saturated_fraction)?,
    };
    let result = match outcome {
        Some(Outcome::Aborted(reason)) => end_aborted(&lp.link, &lp.to_store, reason),
        Some(Outcome::Paused(reason)) => Ok(Outcome::Paused(reason)),
        Some(Outcome::Done(s)) => Ok(Outcome::Done(s)),
        None => {
            if let Err(e) = lp.drain().await {
                return Err(RunError::Storage(e));
            }
            if let Some((kind, result)) = calibrate(plan, &reader, &lp.records, &lp.accepted)? {
                info!(kind = %kind, "calibration: {result}");
                lp.send_store(ToStore::Entry(Entry::Calibration {
                    kind: kind.clone(),
                    result: result.clone(),
                }))?;
                let (tx, rx) = std::sync::mpsc::channel();
                lp.send_store(ToStore::Attribute {
                    key: "calibration".into(),
                    value: json!({ kind: result }),
                    reply: tx,
                })?;
                let r = tokio::task::spawn_blocking(move || rx.recv())
                    .await
                    .map_err(|e| RunError::Storage(e.to_string()))?
                    .map_err(|_| RunError::Storage("the storage thread stopped".into()))?;
                r.map_err(RunError::Storage)?;
            }
            let summary_json = json!({
                "run": serde_json::to_value(&summary).unwrap_or(Value::Null),
                "decisions": decisions,
            });
            let checks = FinishChecks {
                planned_steps,
                accepted: lp.accepted.clone(),
                damaged: damaged.clone(),
            };
            end_done(&lp.link, &lp.to_store, summary_json, checks).await?;
            Ok(Outcome::Done(summary))
        }
    };
    if !decisions.is_empty() {
        if let Ok(store) = RunStore::open(run_dir) {
            let _ = store.set_attribute("decisions", Value::Array(decisions));
        }
    }
    drop(lp);
    let _ = tokio::task::spawn_blocking(move || writer_thread.join()).await;
    result
}
