//! A run: the state machine that turns a plan into stored frames and products.
//!
//! **States.** Running; pausing at the next safe point (between angle sets, or between
//! single frames outside sets); paused (with the reason: the user, a device error after the
//! plan's retries, a storage error, the suspender, a dark series that needs the lens capped);
//! aborting; done. [`Control::Pause`] asks for the next safe point; [`Control::PauseNow`]
//! cancels the device operation in flight (its step is taken again on resume);
//! [`Control::Resume`] and [`Control::Abort`] act on a paused run; [`Control::Detach`] (or
//! dropping the controller) leaves a paused run to `polarimeter resume`.
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
use crate::store::RunStore;
use crate::{pixel_hash, FrameKind, FrameRecord};
use polar_hal::{Analyzer, Camera, DeviceError, ErrorKind, Frame, TriggerMode};
use polar_hil_mocks::camera::Illumination;
use polar_model::sensor::{Camera as CameraModel, SensorModel};
use polar_planner::aptd::{Aptd, AptdConfig, AptdFrame, Step as AptdStep, TargetSpec};
use polar_planner::Constraints;
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{info, info_span, warn, Instrument};

/// What a controller can ask of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Control {
    /// Pause at the next safe point.
    Pause,
    /// Pause now: cancel the device operation in flight.
    PauseNow,
    /// Continue a paused run.
    Resume,
    /// Stop a paused run for good (what was acquired stays).
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
    pub illumination: Option<Illumination>,
    /// The adaptive loop's target pixels, when known as a mask.
    pub target_mask: Option<Vec<bool>>,
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

enum StageCmd {
    SetAngle {
        psi_rad: f64,
        reply: oneshot::Sender<Result<f64, DeviceError>>,
    },
}

enum CamCmd {
    Configure {
        exposure_us: f64,
        gain: f64,
        reply: oneshot::Sender<Result<(f64, f64), DeviceError>>,
    },
    Acquire {
        deadline: Duration,
        /// Told the frame id when the exposure ends, if the camera reports it (the sender is
        /// dropped otherwise).
        exposed: Option<oneshot::Sender<u64>>,
        reply: oneshot::Sender<Result<Frame, DeviceError>>,
    },
}

fn spawn_stage<A: Analyzer + 'static>(mut analyzer: A) -> mpsc::Sender<StageCmd> {
    let (tx, mut rx) = mpsc::channel::<StageCmd>(4);
    tokio::task::spawn_local(
        async move {
            while let Some(cmd) = rx.recv().await {
                match cmd {
                    StageCmd::SetAngle { psi_rad, reply } => {
                        let r = analyzer
                            .set_angle(psi_rad)
                            .instrument(info_span!("move", deg = psi_rad.to_degrees()))
                            .await;
                        let _ = reply.send(r);
                    }
                }
            }
        }
        .instrument(info_span!("stage actor")),
    );
    tx
}

fn spawn_camera<C: Camera + 'static>(mut camera: C) -> mpsc::Sender<CamCmd> {
    let (tx, mut rx) = mpsc::channel::<CamCmd>(4);
    tokio::task::spawn_local(
        async move {
            let mut started = false;
            while let Some(cmd) = rx.recv().await {
                match cmd {
                    CamCmd::Configure {
                        exposure_us,
                        gain,
                        reply,
                    } => {
                        let r = async {
                            if started {
                                camera.stop().await?;
                                started = false;
                            }
                            let e = camera.set_exposure_us(exposure_us).await?;
                            let g = camera.set_gain(gain).await?;
                            Ok((e, g))
                        }
                        .await;
                        let _ = reply.send(r);
                    }
                    CamCmd::Acquire {
                        deadline,
                        exposed,
                        reply,
                    } => {
                        let r = async {
                            if !started {
                                camera.set_trigger(TriggerMode::Software).await?;
                                camera.start().await?;
                                started = true;
                            }
                            // A frame from an earlier, timed-out trigger must not stand in
                            // for this one.
                            while let Ok(stale) = camera.grab(Duration::ZERO).await {
                                warn!(frame_id = stale.frame_id, "discarded a late frame");
                            }
                            let until = tokio::time::Instant::now() + deadline;
                            camera.trigger().await?;
                            if let Some(exposed) = exposed {
                                if let Some(frame_id) = camera.exposure_end(deadline).await? {
                                    let _ = exposed.send(frame_id);
                                }
                            }
                            camera
                                .grab(until.saturating_duration_since(tokio::time::Instant::now()))
                                .await
                        }
                        .instrument(info_span!("grab"))
                        .await;
                        let _ = reply.send(r);
                    }
                }
            }
            if started {
                let _ = camera.stop().await;
            }
        }
        .instrument(info_span!("camera actor")),
    );
    tx
}

// ---------------------------------------------------------------------------------------
// The storage thread.

enum ToStore {
    Frame {
        record: FrameRecord,
        pixels: Vec<u16>,
    },
    Entry(Entry),
    ProcessSet(SetJob),
    /// Mirror the journal's frame records into the store's metadata arrays (at pauses and
    /// the end; the journal is the truth in between).
    SyncMetadata,
    Attribute {
        key: String,
        value: Value,
        reply: std::sync::mpsc::Sender<Result<(), String>>,
    },
    Finish {
        reply: std::sync::mpsc::Sender<Result<Value, String>>,
        summary: Value,
        checks: FinishChecks,
    },
}

struct SetJob {
    set: u64,
    /// Frame indices in step order.
    frames: Vec<u64>,
    measured_deg: Vec<f64>,
    commanded_deg: Vec<f64>,
    exposure_us: f64,
    gain_db: f64,
}

struct FinishChecks {
    /// Planned steps that must each have an accepted frame.
    planned_steps: BTreeSet<u64>,
    /// Accepted frame per step.
    accepted: BTreeMap<u64, u64>,
}

enum FromStore {
    Durable {
        index: u64,
        label: String,
    },
    SetChecked {
        set: u64,
        verdict: Verdict,
        mean_dolp: f64,
    },
    Failed(String),
}

struct Writer {
    store: RunStore,
    journal: Journal,
    sensor: SensorModel,
    camera_model: CameraModel,
    suspender: crate::plan::Suspender,
    records: BTreeMap<u64, FrameRecord>,
    cache: HashMap<u64, Vec<u16>>,
    products: Products,
    product_slot: u64,
    last_s0: Option<f64>,
    threads: usize,
    /// Sum and count of dark frames by exposure (bits of the f64).
    darks: HashMap<u64, (Vec<f64>, u32)>,
}

impl Writer {
    fn pixels(&mut self, index: u64) -> Result<Vec<u16>, String> {
        if let Some(p) = self.cache.get(&index) {
            return Ok(p.clone());
        }
        self.store.read_frame(index).map_err(|e| e.to_string())
    }

    fn frame(&mut self, record: FrameRecord, pixels: Vec<u16>) -> Result<(), String> {
        self.store
            .write_frame(record.index, &pixels)
            .map_err(|e| format!("writing frame {}: {e}", record.index))?;
        self.journal
            .append(&Entry::Frame(record.clone()))
            .map_err(|e| format!("journal: {e}"))?;
        if record.kind == FrameKind::Dark {
            let (sum, n) = self
                .darks
                .entry(record.exposure_us.to_bits())
                .or_insert_with(|| (vec![0.0; pixels.len()], 0));
            if sum.len() == pixels.len() {
                sum.iter_mut()
                    .zip(&pixels)
                    .for_each(|(s, &p)| *s += f64::from(p));
                *n += 1;
            }
        } else {
            self.cache.insert(record.index, pixels);
        }
        self.records.insert(record.index, record);
        Ok(())
    }

    fn noise(&self, gain_db: f64) -> (NoiseModel, f64) {
        let c = &self.camera_model;
        let k = c.gain_dn_per_e * 10f64.powf(gain_db / 20.0);
        let noise = NoiseModel {
            gain_dn_per_e: k,
            offset_dn: c.offset_dn,
            read_var_dn2: k * k * c.read_noise_e * c.read_noise_e + 1.0 / 12.0,
            // A full pixel reads the full well plus read noise: 3 sigma below the level
            // counts as saturated (a pixel there is clipped or nonlinear).
            saturation_dn: ((k * c.full_well_e + c.offset_dn).min(c.adc_max_dn())
                - 3.0 * k * c.read_noise_e)
                .clamp(0.0, 65535.0) as u16,
        };
        (noise, k)
    }

    fn process(&mut self, job: SetJob) -> Result<(Verdict, f64), String> {
        let mut frames = Vec::with_capacity(job.frames.len());
        for &i in &job.frames {
            frames.push(self.pixels(i)?);
        }
        let (w, h) = (self.store.width(), self.store.height());
        let angles_rad: Vec<f64> = job.measured_deg.iter().map(|d| d.to_radians()).collect();
        let rows_m = self
            .sensor
            .intensities_from_stokes(&angles_rad)
            .map_err(|e| format!("analyzer rows: {e}"))?;
        let rows: Vec<[f64; 3]> = (0..rows_m.nrows())
            .map(|i| [rows_m[(i, 0)], rows_m[(i, 1)], rows_m[(i, 2)]])
            .collect();
        let geometry = SetGeometry::new(&rows).map_err(|e| e.to_string())?;
        let (noise, k) = self.noise(job.gain_db);
        let dark_scalar = self.camera_model.offset_dn
            + k * self.camera_model.dark_current_e_per_s * job.exposure_us * 1e-6;
        let dark = match self.darks.get(&job.exposure_us.to_bits()) {
            // A dark map only from enough darks that its own noise is small (16 frames:
            // a quarter of one frame's temporal noise); otherwise the calibrated level.
            Some((sum, n)) if *n >= 16 && sum.len() == (w as usize * h as usize) => {
                Dark::Map(sum.iter().map(|s| (s / f64::from(*n)) as f32).collect())
            }
            _ => Dark::Scalar(dark_scalar as f32),
        };
        let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
        products::compute_into(
            &mut self.products,
            &refs,
            w,
            h,
            &geometry,
            &dark,
            &noise,
            self.threads,
        )
        .map_err(|e| e.to_string())?;
        let verdict = self.verdict(&job, &refs, &rows, &dark, &noise);
        let mean_dolp = finite_mean(&self.products.dolp);
        if verdict.accepted {
            let names = Products::names();
            let images: Vec<(&str, &[f32])> = names
                .iter()
                .filter_map(|n| self.products.image(n).map(|img| (*n, img)))
                .collect();
            self.store
                .write_products(self.product_slot, job.set, &job.measured_deg, &images)
                .map_err(|e| format!("products of set {}: {e}", job.set))?;
            self.product_slot += 1;
            self.last_s0 = Some(verdict.mean_s0_dn);
            self.journal
                .append(&Entry::SetDone {
                    set: job.set,
                    frames: job.frames.clone(),
                    verdict: serde_json::to_value(&verdict).unwrap_or(Value::Null),
                })
                .map_err(|e| format!("journal: {e}"))?;
        } else {
            self.journal
                .append(&Entry::SetRejected {
                    set: job.set,
                    frames: job.frames.clone(),
                    reason: verdict.reason.clone(),
                })
                .map_err(|e| format!("journal: {e}"))?;
        }
        for i in &job.frames {
            self.cache.remove(i);
        }
        Ok((verdict, mean_dolp))
    }

    /// The suspender (module doc): Malus residuals, S0 drift, analyzer readback, repeats.
    fn verdict(
        &self,
        job: &SetJob,
        frames: &[&[u16]],
        rows: &[[f64; 3]],
        dark: &Dark,
        noise: &NoiseModel,
    ) -> Verdict {
        let p = &self.products;
        let mean_s0 = finite_mean(&p.s0);
        let max_angle_error_deg = job
            .commanded_deg
            .iter()
            .zip(&job.measured_deg)
            .map(|(c, m)| {
                let d = (c - m).rem_euclid(180.0);
                d.min(180.0 - d)
            })
            .fold(0.0, f64::max);
        // Mean reduced chi-square over unsaturated pixels (every 1 in `stride`).
        let n = frames.len();
        let mut chi2 = f64::NAN;
        if n > 3 {
            let px = p.s0.len();
            let stride = (px / 200_000).max(1);
            let (mut sum, mut count) = (0.0f64, 0u64);
            let mut i = 0;
            while i < px {
                if p.s0[i].is_finite() {
                    let s = [f64::from(p.s0[i]), f64::from(p.s1[i]), f64::from(p.s2[i])];
                    let d = match dark {
                        Dark::Scalar(v) => f64::from(*v),
                        Dark::Map(m) => f64::from(m[i]),
                    };
                    let mut c = 0.0;
                    for (f, r) in frames.iter().zip(rows) {
                        let y = f64::from(f[i]);
                        let model = r[0] * s[0] + r[1] * s[1] + r[2] * s[2];
                        let var = noise.gain_dn_per_e * (y - noise.offset_dn).max(0.0)
                            + noise.read_var_dn2;
                        c += (y - d - model).powi(2) / var;
                    }
                    sum += c / (n - 3) as f64;
                    count += 1;
                }
                i += stride;
            }
            if count > 0 {
                chi2 = sum / count as f64;
            }
        }
        let cfg = &self.suspender;
        let mut reasons = Vec::new();
        for a in 0..frames.len() {
            for b in a + 1..frames.len() {
                if frames[a] == frames[b] {
                    reasons.push(format!(
                        "frames {} and {} are identical (a stuck camera)",
                        job.frames[a], job.frames[b]
                    ));
                }
            }
        }
        if max_angle_error_deg > cfg.max_angle_error_deg {
            reasons.push(format!(
                "the analyzer is {max_angle_error_deg:.3} deg from where it was commanded \
                 (allowed {} deg): an analyzer slip",
                cfg.max_angle_error_deg
            ));
        }
        if chi2.is_finite() && chi2 > cfg.max_reduced_chi2 {
            reasons.push(format!(
                "the intensities do not follow Malus's law: mean reduced chi-square {chi2:.2} \
                 (allowed {}); the light changed during the set (a cloud?) or a frame is bad",
                cfg.max_reduced_chi2
            ));
        }
        if n == 3 {
            if let Some(last) = self.last_s0 {
                let change = (mean_s0 - last).abs() / last.abs().max(1e-9);
                if change > cfg.max_s0_change {
                    reasons.push(format!(
                        "the mean S0 changed by {:.1} % from the last set (allowed {:.1} %): \
                         the light changed",
                        100.0 * change,
                        100.0 * cfg.max_s0_change
                    ));
                }
            }
        }
        if !mean_s0.is_finite() {
            reasons.push("every pixel of the set is saturated or dark".into());
        }
        let accepted = !cfg.enabled || reasons.is_empty();
        Verdict {
            accepted,
            reason: reasons.join("; "),
            reduced_chi2: chi2,
            mean_s0_dn: mean_s0,
            max_angle_error_deg,
        }
    }

    fn finish(&mut self, summary: Value, checks: &FinishChecks) -> Result<Value, String> {
        let records: Vec<FrameRecord> = self.records.values().cloned().collect();
        self.store
            .write_frame_metadata(&records)
            .map_err(|e| format!("frame metadata: {e}"))?;
        // Planned against written.
        let missing: Vec<u64> = checks
            .planned_steps
            .iter()
            .filter(|s| !checks.accepted.contains_key(s))
            .copied()
            .collect();
        let extra: Vec<u64> = checks
            .accepted
            .keys()
            .filter(|s| !checks.planned_steps.contains(s))
            .copied()
            .collect();
        if !missing.is_empty() || !extra.is_empty() {
            return Err(format!(
                "frames written do not match frames planned: steps missing {missing:?}, \
                 steps not planned {extra:?}"
            ));
        }
        let v = self
            .store
            .verify(&records)
            .map_err(|e| format!("verify: {e}"))?;
        let v = serde_json::to_value(&v).unwrap_or(Value::Null);
        let bad = ["missing", "mismatched"].iter().any(|k| {
            v.get(*k)
                .and_then(Value::as_array)
                .is_some_and(|a| !a.is_empty())
        });
        if bad {
            return Err(format!("stored frames do not match the journal: {v}"));
        }
        // Dark means.
        if let Some((sum, n)) = self.darks.values().next() {
            if *n > 0 {
                let mean: Vec<f32> = sum.iter().map(|s| (s / f64::from(*n)) as f32).collect();
                self.store
                    .write_dark_mean(&mean)
                    .map_err(|e| format!("dark mean: {e}"))?;
            }
        }
        self.store
            .set_attribute("summary", summary.clone())
            .map_err(|e| format!("summary: {e}"))?;
        self.store
            .set_attribute("state", json!("done"))
            .map_err(|e| format!("state: {e}"))?;
        let frames = records.len() as u64;
        self.journal
            .append(&Entry::Finished { frames })
            .map_err(|e| format!("journal: {e}"))?;
        Ok(json!({ "verification": v, "frames": frames }))
    }
}

fn finite_mean(v: &[f32]) -> f64 {
    let (mut s, mut n) = (0.0f64, 0u64);
    for x in v {
        if x.is_finite() {
            s += f64::from(*x);
            n += 1;
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// The storage thread's ends: commands in, results out, and its handle.
type WriterEnds = (
    std::sync::mpsc::SyncSender<ToStore>,
    mpsc::UnboundedReceiver<FromStore>,
    std::thread::JoinHandle<()>,
);

fn spawn_writer(mut writer: Writer) -> Result<WriterEnds, RunError> {
    // Two frames in flight at most: the grab loop never runs far ahead of the disk.
    let (tx, rx) = std::sync::mpsc::sync_channel::<ToStore>(2);
    let (back, back_rx) = mpsc::unbounded_channel();
    let handle = std::thread::Builder::new()
        .name("run-storage".into())
        .spawn(move || {
            let _span = info_span!("storage").entered();
            while let Ok(msg) = rx.recv() {
                match msg {
                    ToStore::Frame { record, pixels } => {
                        let (index, label) = (record.index, record.label.clone());
                        match writer.frame(record, pixels) {
                            Ok(()) => {
                                let _ = back.send(FromStore::Durable { index, label });
                            }
                            Err(e) => {
                                let _ = back.send(FromStore::Failed(e));
                            }
                        }
                    }
                    ToStore::Entry(e) => {
                        if let Err(e) = writer.journal.append(&e) {
                            let _ = back.send(FromStore::Failed(format!("journal: {e}")));
                        }
                    }
                    ToStore::ProcessSet(job) => {
                        let set = job.set;
                        let _s = info_span!("products", set).entered();
                        match writer.process(job) {
                            Ok((verdict, mean_dolp)) => {
                                let _ = back.send(FromStore::SetChecked {
                                    set,
                                    verdict,
                                    mean_dolp,
                                });
                            }
                            Err(e) => {
                                let _ = back.send(FromStore::Failed(e));
                            }
                        }
                    }
                    ToStore::SyncMetadata => {
                        let records: Vec<FrameRecord> = writer.records.values().cloned().collect();
                        if let Err(e) = writer.store.write_frame_metadata(&records) {
                            let _ = back.send(FromStore::Failed(format!("frame metadata: {e}")));
                        }
                    }
                    ToStore::Attribute { key, value, reply } => {
                        let _ = reply.send(
                            writer
                                .store
                                .set_attribute(&key, value)
                                .map_err(|e| format!("attribute {key}: {e}")),
                        );
                    }
                    ToStore::Finish {
                        reply,
                        summary,
                        checks,
                    } => {
                        let _ = reply.send(writer.finish(summary, &checks));
                    }
                }
            }
        })
        .map_err(|e| RunError::Storage(format!("cannot start the storage thread: {e}")))?;
    Ok((tx, back_rx, handle))
}

// ---------------------------------------------------------------------------------------
// The main loop.

/// A set sent for checking: its steps and its frames.
type Checking = (Vec<(u64, StepSpec)>, Vec<u64>);

/// A unit of work between two safe points.
#[derive(Debug, Clone)]
enum Unit {
    Single(u64, StepSpec),
    Set(u64, Vec<(u64, StepSpec)>),
}

/// Why a device operation did not give its value.
enum OpError {
    Device(DeviceError),
    /// Immediate pause or abort asked while in flight.
    Interrupted,
}

struct Loop<'a> {
    plan: &'a Plan,
    link: RunLink,
    stage: mpsc::Sender<StageCmd>,
    camera: mpsc::Sender<CamCmd>,
    to_store: std::sync::mpsc::SyncSender<ToStore>,
    from_store: mpsc::UnboundedReceiver<FromStore>,
    illumination: Option<Illumination>,
    width: u32,
    height: u32,
    next_index: u64,
    /// Accepted frame index per step.
    accepted: BTreeMap<u64, u64>,
    /// Frame records by index (this process and replayed).
    records: BTreeMap<u64, FrameRecord>,
    in_flight: BTreeSet<u64>,
    pausing: bool,
    done_frames: u64,
    planned_frames: u64,
    configured: Option<(f64, f64)>,
    retries: u64,
    pauses: u64,
    sets_accepted: u64,
    sets_rejected: u64,
    rejections: HashMap<u64, u32>,
    /// Pixels of accepted light frames by index (adaptive runs only).
    keep_pixels: bool,
    kept: HashMap<u64, Vec<u16>>,
    lens_capped: Option<bool>,
    /// The simulated scene's illumination for light frames (1, or less under a cloud).
    light_level: f64,
    /// Time spent in device operations (moves and grabs, as the engine waited for them).
    device_s: f64,
    /// Suspender verdicts arrived and not yet acted on: set, verdict, mean DoLP.
    verdicts: VecDeque<(u64, Verdict, f64)>,
    /// The move to the next step's angle, started when the last exposure ended.
    pending_move: Option<PendingMove>,
}

/// A move started ahead of its step (at the end of the previous step's exposure), so that it
/// overlaps that frame's readout, transfer and recording.
struct PendingMove {
    /// The commanded angle, degrees as the plan gives it.
    angle_deg: f64,
    reply: oneshot::Receiver<Result<f64, DeviceError>>,
}

/// Outcome of waiting at a pause.
enum AfterPause {
    Resume,
    Abort(String),
    Detach(String),
}

impl Loop<'_> {
    fn set_state(&self, s: RunState) {
        let _ = self.link.state.send(s.clone());
        let _ = self.link.events.try_send(Event::State(s));
    }

    fn event(&self, e: Event) {
        let _ = self.link.events.try_send(e);
    }

    fn send_store(&self, msg: ToStore) -> Result<(), RunError> {
        self.to_store
            .send(msg)
            .map_err(|_| RunError::Storage("the storage thread stopped".into()))
    }

    fn handle_control(&mut self, c: Control) -> Option<OpError> {
        match c {
            Control::Pause => {
                if !self.pausing {
                    self.pausing = true;
                    self.set_state(RunState::Pausing);
                }
                None
            }
            Control::PauseNow => {
                self.pausing = true;
                Some(OpError::Interrupted)
            }
            Control::Abort | Control::Detach => {
                self.pausing = true;
                Some(OpError::Interrupted)
            }
            Control::Resume => None,
        }
    }

    /// Runs `fut`, watching the control channel: a pause request is noted, an immediate
    /// pause or an abort interrupts.
    async fn watch<T, F>(&mut self, fut: F) -> Result<T, OpError>
    where
        F: std::future::Future<Output = Result<T, DeviceError>>,
    {
        tokio::pin!(fut);
        loop {
            tokio::select! {
                r = &mut fut => return r.map_err(OpError::Device),
                c = self.link.control.recv() => {
                    match c {
                        Some(c) => {
                            if let Some(e) = self.handle_control(c) {
                                return Err(e);
                            }
                        }
                        None => {
                            // The controller is gone: finish the operation.
                            return (&mut fut).await.map_err(OpError::Device);
                        }
                    }
                }
                Some(msg) = self.from_store.recv() => {
                    if let Err(e) = self.on_store(msg) {
                        return Err(OpError::Device(DeviceError::new(ErrorKind::Other, "storage", e)));
                    }
                }
            }
        }
    }

    fn on_store(&mut self, msg: FromStore) -> Result<(), String> {
        match msg {
            FromStore::Durable { index, label } => {
                self.in_flight.remove(&index);
                self.done_frames += 1;
                self.event(Event::Progress {
                    done: self.done_frames,
                    planned: self.planned_frames,
                    label,
                });
                Ok(())
            }
            FromStore::SetChecked {
                set,
                verdict,
                mean_dolp,
            } => {
                self.verdicts.push_back((set, verdict, mean_dolp));
                Ok(())
            }
            FromStore::Failed(e) => Err(e),
        }
    }

    /// Waits for the next message from the storage thread.
    async fn next_from_store(&mut self) -> Result<(), RunError> {
        match self.from_store.recv().await {
            Some(msg) => self.on_store(msg).map_err(RunError::Storage),
            None => Err(RunError::Storage("the storage thread stopped".into())),
        }
    }

    /// Waits until every frame sent is durable.
    async fn drain(&mut self) -> Result<(), String> {
        while !self.in_flight.is_empty() {
            match self.from_store.recv().await {
                Some(msg) => self.on_store(msg)?,
                None => return Err("the storage thread stopped".into()),
            }
        }
        Ok(())
    }

    /// Pauses with `reason` and waits for the controller.
    async fn pause(&mut self, reason: String, next_step: u64) -> Result<AfterPause, RunError> {
        // After a pause the stage is commanded afresh: whatever happened to it meanwhile, the
        // next step's angle is measured by its own move.
        self.pending_move = None;
        if let Err(e) = self.drain().await {
            warn!("while pausing: {e}");
        }
        self.pauses += 1;
        self.pausing = false;
        self.send_store(ToStore::SyncMetadata)?;
        info!(reason = %reason, "paused");
        self.send_store(ToStore::Entry(Entry::Paused {
            reason: reason.clone(),
            next_step,
        }))?;
        self.set_state(RunState::Paused(reason.clone()));
        loop {
            match self.link.control.recv().await {
                Some(Control::Resume) => {
                    self.send_store(ToStore::Entry(Entry::Resumed {
                        process_id: std::process::id(),
                        at_unix_ns: now_unix_ns(SystemTime::now()),
                    }))?;
                    self.set_state(RunState::Running);
                    return Ok(AfterPause::Resume);
                }
                Some(Control::Abort) => return Ok(AfterPause::Abort(reason)),
                Some(Control::Detach) | None => return Ok(AfterPause::Detach(reason)),
                Some(Control::Pause | Control::PauseNow) => {}
            }
        }
    }

    /// Takes one step's frame (with the plan's retries); the frame goes to storage. `next_deg`
    /// is the angle of the step that will follow, if known: the stage starts moving there as
    /// soon as the camera reports this step's exposure ended.
    async fn acquire(
        &mut self,
        step: u64,
        spec: &StepSpec,
        next_deg: Option<f64>,
    ) -> Result<u64, OpError> {
        let policy = &self.plan.policy;
        let attempts = policy.attempts.max(1);
        let backoff = Duration::from_millis(policy.retry_backoff_ms);
        let move_deadline = Duration::from_secs_f64(policy.move_timeout_s);
        let grab_deadline =
            Duration::from_secs_f64(policy.grab_timeout_s + spec.exposure_us * 1e-6);
        // The lens cap (simulated) for darks; on hardware the operator caps it at a pause.
        if let Some(light) = &self.illumination {
            light.set(if spec.kind == FrameKind::Dark {
                0.0
            } else {
                self.light_level
            });
        }
        let mut last_err = None;
        for attempt in 1..=attempts {
            if attempt > 1 {
                tokio::time::sleep(backoff).await;
            }
            match self
                .try_acquire(spec, next_deg, move_deadline, grab_deadline)
                .await
            {
                Ok((measured_deg, frame)) => {
                    let index = self.next_index;
                    self.next_index += 1;
                    let record = self.record(index, step, spec, measured_deg, &frame);
                    self.records.insert(index, record.clone());
                    self.accepted.insert(step, index);
                    if self.keep_pixels && spec.kind == FrameKind::Light {
                        self.kept.insert(index, frame.pixels.clone());
                    }
                    self.in_flight.insert(index);
                    let msg = ToStore::Frame {
                        record,
                        pixels: frame.pixels,
                    };
                    // The bounded channel: blocks only when two frames are already queued.
                    let tx = self.to_store.clone();
                    let sent = tokio::task::spawn_blocking(move || tx.send(msg).is_ok())
                        .await
                        .unwrap_or(false);
                    if !sent {
                        return Err(OpError::Device(DeviceError::new(
                            ErrorKind::Other,
                            "storage",
                            "the storage thread stopped",
                        )));
                    }
                    return Ok(index);
                }
                Err(OpError::Interrupted) => return Err(OpError::Interrupted),
                Err(OpError::Device(e)) => {
                    self.retries += 1;
                    let msg = format!("{} (attempt {attempt} of {attempts}): {e}", spec.label);
                    warn!("{msg}");
                    self.event(Event::Retry(msg));
                    let permanent = matches!(e.kind(), ErrorKind::OutOfRange);
                    last_err = Some(e);
                    if permanent {
                        break;
                    }
                }
            }
        }
        Err(OpError::Device(last_err.unwrap_or_else(|| {
            DeviceError::new(ErrorKind::Other, "run", "no attempt was made")
        })))
    }

    async fn try_acquire(
        &mut self,
        spec: &StepSpec,
        next_deg: Option<f64>,
        move_deadline: Duration,
        grab_deadline: Duration,
    ) -> Result<(f64, Frame), OpError> {
        let stage = self.stage.clone();
        let psi = spec.angle_deg.to_radians();
        let t0 = Instant::now();
        // A move started ahead to this angle is this step's move; one to another angle (a retry
        // of the previous step, a set taken again) is left to finish, and the stage actor
        // runs this step's move after it.
        let ahead = self
            .pending_move
            .take()
            .filter(|p| p.angle_deg == spec.angle_deg)
            .map(|p| p.reply);
        let measured = self
            .watch(async move {
                let rx = match ahead {
                    Some(rx) => rx,
                    None => {
                        let (tx, rx) = oneshot::channel();
                        stage
                            .send(StageCmd::SetAngle {
                                psi_rad: psi,
                                reply: tx,
                            })
                            .await
                            .map_err(|_| {
                                DeviceError::new(ErrorKind::Disconnected, "stage", "actor gone")
                            })?;
                        rx
                    }
                };
                match tokio::time::timeout(move_deadline, rx).await {
                    Ok(Ok(r)) => r,
                    Ok(Err(_)) => Err(DeviceError::new(
                        ErrorKind::Disconnected,
                        "stage",
                        "actor gone",
                    )),
                    Err(_) => Err(DeviceError::new(
                        ErrorKind::Timeout,
                        "stage",
                        format!("no answer to a move within {move_deadline:?}"),
                    )),
                }
            })
            .await?;
        let gain = spec.gain_db;
        if self.configured != Some((spec.exposure_us, gain)) {
            let cam = self.camera.clone();
            let exposure_us = spec.exposure_us;
            let applied = self
                .watch(async move {
                    let (tx, rx) = oneshot::channel();
                    cam.send(CamCmd::Configure {
                        exposure_us,
                        gain,
                        reply: tx,
                    })
                    .await
                    .map_err(|_| {
                        DeviceError::new(ErrorKind::Disconnected, "camera", "actor gone")
                    })?;
                    rx.await.map_err(|_| {
                        DeviceError::new(ErrorKind::Disconnected, "camera", "actor gone")
                    })?
                })
                .await?;
            info!(
                exposure_us = applied.0,
                gain = applied.1,
                "camera configured"
            );
            self.configured = Some((spec.exposure_us, gain));
        }
        let t1 = Instant::now();
        let cam = self.camera.clone();
        let (w, h) = (self.width, self.height);
        let (frame_tx, frame_rx) = oneshot::channel();
        let (exposed_tx, exposed_rx) = next_deg.map(|_| oneshot::channel()).unzip();
        self.watch(async move {
            cam.send(CamCmd::Acquire {
                deadline: grab_deadline,
                exposed: exposed_tx,
                reply: frame_tx,
            })
            .await
            .map_err(|_| DeviceError::new(ErrorKind::Disconnected, "camera", "actor gone"))
        })
        .await?;
        // The exposure's end (if the camera reports it) starts the next step's move, which then
        // overlaps this frame's readout, transfer and recording. Without the report (or when the
        // grab fails first), the sender is dropped and the next move waits for its step.
        let mut exposure_frame_id = None;
        if let (Some(rx), Some(next)) = (exposed_rx, next_deg) {
            if let Some(frame_id) = self.watch(async move { Ok(rx.await.ok()) }).await? {
                let (tx, reply) = oneshot::channel();
                let sent = self.stage.try_send(StageCmd::SetAngle {
                    psi_rad: next.to_radians(),
                    reply: tx,
                });
                if sent.is_ok() {
                    tracing::debug!(
                        frame_id,
                        next_deg = next,
                        after_ms = t1.elapsed().as_secs_f64() * 1e3,
                        "exposure ended; moving ahead"
                    );
                    self.pending_move = Some(PendingMove {
                        angle_deg: next,
                        reply,
                    });
                    exposure_frame_id = Some(frame_id);
                }
            }
        }
        let frame = self
            .watch(async move {
                let f = frame_rx.await.map_err(|_| {
                    DeviceError::new(ErrorKind::Disconnected, "camera", "actor gone")
                })??;
                if (f.width, f.height) != (w, h) || f.pixels.len() != w as usize * h as usize {
                    return Err(DeviceError::new(
                        ErrorKind::Protocol,
                        "camera",
                        format!(
                            "frame of {}x{} ({} pixels); the run stores {w}x{h}",
                            f.width,
                            f.height,
                            f.pixels.len()
                        ),
                    ));
                }
                if let Some(id) = exposure_frame_id {
                    // The stage left when exposure `id` ended: any other frame may have been
                    // exposed while it moved.
                    if f.frame_id != id {
                        return Err(DeviceError::new(
                            ErrorKind::Protocol,
                            "camera",
                            format!(
                                "frame {} arrived for the exposure that ended as frame {id}",
                                f.frame_id
                            ),
                        ));
                    }
                }
                Ok(f)
            })
            .await?;
        let (move_s, grab_s) = ((t1 - t0).as_secs_f64(), t1.elapsed().as_secs_f64());
        self.device_s += move_s + grab_s;
        tracing::debug!(
            move_ms = move_s * 1e3,
            grab_ms = grab_s * 1e3,
            "step timing"
        );
        Ok((measured.to_degrees().rem_euclid(180.0), frame))
    }

    fn record(
        &self,
        index: u64,
        step: u64,
        spec: &StepSpec,
        measured_deg: f64,
        frame: &Frame,
    ) -> FrameRecord {
        let host_ns = now_unix_ns(frame.host_time);
        let (zen, az) = self
            .plan
            .site
            .as_ref()
            .and_then(|s| sun_at(host_ns, s))
            .map_or((None, None), |(z, a)| (Some(z), Some(a)));
        FrameRecord {
            index,
            step,
            kind: spec.kind,
            set: spec.set,
            label: spec.label.clone(),
            commanded_angle_deg: spec.angle_deg.rem_euclid(180.0),
            measured_angle_deg: measured_deg,
            exposure_us: frame.exposure_us,
            gain: frame.gain,
            host_time_unix_ns: host_ns,
            device_timestamp_ns: frame.device_timestamp_ns,
            frame_id: frame.frame_id,
            sun_zenith_deg: zen,
            sun_azimuth_deg: az,
            width: frame.width,
            height: frame.height,
            hash: pixel_hash(&frame.pixels),
        }
    }
}

/// The sun's zenith and azimuth at a Unix time (ns) for a site (NREL SPA, geometric).
fn sun_at(unix_ns: i64, site: &crate::plan::Site) -> Option<(f64, f64)> {
    use chrono::{Datelike, Timelike};
    let t = chrono::DateTime::from_timestamp(
        unix_ns.div_euclid(1_000_000_000),
        u32::try_from(unix_ns.rem_euclid(1_000_000_000)).ok()?,
    )?;
    let time = polar_model::sun::UtcTime {
        year: t.year(),
        month: t.month(),
        day: t.day(),
        hour: t.hour(),
        minute: t.minute(),
        second: f64::from(t.second()) + f64::from(t.nanosecond()) * 1e-9,
    };
    let s = polar_model::sun::Site::new(site.latitude_deg, site.longitude_deg, site.elevation_m)
        .ok()?;
    let p = polar_model::sun::sun_position(&time, &s, None, None).ok()?;
    Some((p.zenith_deg, p.azimuth_deg))
}

/// The units of work of a static plan's steps (consecutive steps of a set form one unit).
fn units_of(steps: &[StepSpec], first_step: u64) -> VecDeque<Unit> {
    let mut units = VecDeque::new();
    let mut i = 0;
    while i < steps.len() {
        let step = first_step + i as u64;
        match steps[i].set {
            None => {
                units.push_back(Unit::Single(step, steps[i].clone()));
                i += 1;
            }
            Some(set) => {
                let mut members = Vec::new();
                while i < steps.len() && steps[i].set == Some(set) {
                    members.push((first_step + i as u64, steps[i].clone()));
                    i += 1;
                }
                units.push_back(Unit::Set(set, members));
            }
        }
    }
    units
}

/// Opens (or creates) the run directory and its journal and store; replays a journal.
struct Opened {
    journal: Journal,
    store: RunStore,
    entries: Vec<Entry>,
    run_start_unix_ns: i64,
}

fn open_run(
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
        let journal_path = run_dir.join(crate::journal::JOURNAL_FILE);
        if journal_path.exists() {
            // A journal without its run-started entry is a start that crashed before any
            // step could count: start again. Anything else is a run to resume.
            let started = crate::journal::replay(run_dir)
                .map(|r| r.run_started().is_some())
                .unwrap_or(true);
            if started {
                return Err(dir_err(
                    "a run already exists here: resume it with `polarimeter resume`, or \
                     choose another directory"
                        .into(),
                ));
            }
            std::fs::remove_file(&journal_path).map_err(|e| dir_err(e.to_string()))?;
        }
        std::fs::create_dir_all(run_dir).map_err(|e| dir_err(e.to_string()))?;
        // No journal: nothing was counted, so a store left by a crashed start is stale.
        let stale = run_dir.join("run.zarr");
        if stale.exists() {
            std::fs::remove_dir_all(&stale)
                .map_err(|e| dir_err(format!("{}: {e}", stale.display())))?;
        }
        let plan_json = serde_json::to_value(plan).unwrap_or(Value::Null);
        let started = now_unix_ns(SystemTime::now());
        let mut attrs = serde_json::Map::new();
        attrs.insert("plan".into(), plan_json.clone());
        attrs.insert("software".into(), crate::software_version());
        attrs.insert("devices".into(), devices.clone());
        attrs.insert("state".into(), json!("running"));
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
    let entries = opened.entries;

    // Replay.
    let mut records: BTreeMap<u64, FrameRecord> = BTreeMap::new();
    let mut rejected: BTreeSet<u64> = BTreeSet::new();
    let mut sets_done: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    let mut rejections: HashMap<u64, u32> = HashMap::new();
    let mut decisions: Vec<Value> = Vec::new();
    for e in &entries {
        match e {
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
            Entry::Decision { decision, .. } => decisions.push(decision.clone()),
            _ => {}
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

    let writer = Writer {
        store: opened.store,
        journal: opened.journal,
        sensor: rig.sensor.clone(),
        camera_model: rig.camera_model.clone(),
        suspender: plan.suspender.clone(),
        records: records.clone(),
        cache: HashMap::new(),
        products: Products::empty(),
        product_slot: sets_done.len() as u64,
        last_s0: None,
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        darks: HashMap::new(),
    };
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
        lens_capped: None,
        light_level: 1.0,
        device_s: 0.0,
        verdicts: VecDeque::new(),
        pending_move: first_move,
    };
    lp.set_state(RunState::Running);

    // The work list.
    let steps = plan.steps()?;
    let mut units = units_of(&steps, 0);
    let mut planned_steps: BTreeSet<u64> = (0..steps.len() as u64).collect();
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
                    let aptd_frames: Vec<AptdFrame> = frames
                        .iter()
                        .filter_map(|i| {
                            let r = lp.records.get(i)?;
                            let px = lp.kept.remove(i)?;
                            Some(aptd_frame(r, &px, &rig.camera_model, plan))
                        })
                        .collect();
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
        // Darks on hardware: the operator caps the lens at a pause.
        if lp.illumination.is_none() {
            let wants_dark = match &unit {
                Unit::Single(_, s) => s.kind == FrameKind::Dark,
                Unit::Set(..) => false,
            };
            if lp.lens_capped != Some(wants_dark) && (wants_dark || lp.lens_capped.is_some()) {
                let reason = if wants_dark {
                    "cap the lens for the dark frames, then resume"
                } else {
                    "uncap the lens, then resume"
                };
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
        // Time-lapse: wait for the set's time.
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
                    light.set(1.0);
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
    };
    let result = match outcome {
        Some(Outcome::Aborted(reason)) => {
            lp.set_state(RunState::Aborting);
            lp.send_store(ToStore::Entry(Entry::Aborted {
                reason: reason.clone(),
            }))?;
            lp.set_state(RunState::Aborted(reason.clone()));
            Ok(Outcome::Aborted(reason))
        }
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
            let (tx, rx) = std::sync::mpsc::channel();
            let summary_json = json!({
                "run": serde_json::to_value(&summary).unwrap_or(Value::Null),
                "decisions": decisions,
            });
            lp.send_store(ToStore::Finish {
                reply: tx,
                summary: summary_json,
                checks: FinishChecks {
                    planned_steps,
                    accepted: lp.accepted.clone(),
                },
            })?;
            let r = tokio::task::spawn_blocking(move || rx.recv())
                .await
                .map_err(|e| RunError::Storage(e.to_string()))?
                .map_err(|_| RunError::Storage("the storage thread stopped".into()))?;
            match r {
                Ok(_) => {
                    lp.set_state(RunState::Done);
                    Ok(Outcome::Done(summary))
                }
                Err(e) => Err(RunError::Check(e)),
            }
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

/// The calibration a plan computes from its frames: the EMVA 1288 photon transfer
/// (calibrate-noise) or the analyzer's Malus fit (calibrate-analyzer).
fn calibrate(
    plan: &Plan,
    reader: &RunStore,
    records: &BTreeMap<u64, FrameRecord>,
    accepted: &BTreeMap<u64, u64>,
) -> Result<Option<(String, Value)>, RunError> {
    let frames_of = |kind: FrameKind| -> Vec<&FrameRecord> {
        accepted
            .values()
            .filter_map(|i| records.get(i))
            .filter(|r| r.kind == kind)
            .collect()
    };
    let bad = |e: String| RunError::Check(format!("calibration: {e}"));
    match plan.kind {
        PlanKind::CalibrateNoise => {
            let c = plan
                .calibrate_noise
                .as_ref()
                .ok_or_else(|| bad("no [calibrate-noise] section".into()))?;
            let mut points = Vec::new();
            for &e in &c.exposure_us {
                let pick = |kind| -> Vec<&FrameRecord> {
                    frames_of(kind)
                        .into_iter()
                        .filter(|r| (r.exposure_us - e).abs() <= 1e-6 * e.max(1.0) + 0.5)
                        .collect()
                };
                let stats = |rs: Vec<&FrameRecord>| -> Result<(f64, f64, usize), RunError> {
                    let (mut m, mut v, mut n, mut pairs) = (0.0, 0.0, 0usize, 0usize);
                    for pair in rs.chunks_exact(2) {
                        let a = reader.read_frame(pair[0].index)?;
                        let b = reader.read_frame(pair[1].index)?;
                        let st = polar_model::calibration::pair_statistics(&a, &b)
                            .map_err(|e| bad(e.to_string()))?;
                        m += st.mean_dn;
                        v += st.temporal_var_dn2;
                        n += st.pixels;
                        pairs += 1;
                    }
                    if pairs == 0 {
                        return Err(bad(format!("no frame pair at {e} us")));
                    }
                    Ok((m / pairs as f64, v / pairs as f64, n))
                };
                let (dm, dv, _) = stats(pick(FrameKind::Dark))?;
                let (fm, fv, n) = stats(pick(FrameKind::Light))?;
                points.push(polar_model::calibration::ExposurePoint {
                    exposure_us: e,
                    photons_per_pixel: None,
                    dark_mean_dn: dm,
                    dark_var_dn2: dv,
                    flat_mean_dn: fm,
                    flat_var_dn2: fv,
                    pixels: n,
                });
            }
            let pt = polar_model::calibration::photon_transfer(&points)
                .map_err(|e| bad(e.to_string()))?;
            Ok(Some((
                "noise".into(),
                serde_json::to_value(&pt).unwrap_or(Value::Null),
            )))
        }
        PlanKind::CalibrateAnalyzer => {
            let c = plan
                .calibrate_analyzer
                .as_ref()
                .ok_or_else(|| bad("no [calibrate-analyzer] section".into()))?;
            let mean = |r: &FrameRecord| -> Result<f64, RunError> {
                let px = reader.read_frame(r.index)?;
                Ok(px.iter().map(|&p| f64::from(p)).sum::<f64>() / px.len().max(1) as f64)
            };
            let darks = frames_of(FrameKind::Dark);
            if darks.is_empty() {
                return Err(bad("the extinction ratio needs dark frames".into()));
            }
            let mut dark = 0.0;
            for r in &darks {
                dark += mean(r)?;
            }
            let dark = dark / darks.len() as f64;
            let mut points = Vec::new();
            for r in frames_of(FrameKind::Light) {
                let m = mean(r)?;
                points.push(crate::analyzer_cal::MalusPoint {
                    angle_deg: r.measured_angle_deg,
                    signal: m - dark,
                    variance: None,
                });
            }
            let fit = crate::analyzer_cal::fit_malus(&points, c.reference_angle_deg)
                .map_err(|e| bad(e.to_string()))?;
            Ok(Some((
                "analyzer".into(),
                serde_json::to_value(&fit).unwrap_or(Value::Null),
            )))
        }
        _ => Ok(None),
    }
}

fn unit_first_step(u: &Unit) -> u64 {
    match u {
        Unit::Single(s, _) => *s,
        Unit::Set(_, m) => m.first().map_or(0, |(s, _)| *s),
    }
}

fn unit_not_before(u: &Unit) -> Option<f64> {
    match u {
        Unit::Single(_, s) => s.not_before_s,
        Unit::Set(_, m) => m.first().and_then(|(_, s)| s.not_before_s),
    }
}

/// The steps of adaptive set `set` at `angles_rad`, numbered from `first_step`.
fn adaptive_set(
    plan: &Plan,
    set: u64,
    first_step: u64,
    angles_rad: &[f64],
) -> Vec<(u64, StepSpec)> {
    let (exposure_us, gain_db) = plan
        .adaptive
        .as_ref()
        .map_or((1000.0, 0.0), |a| (a.exposure_us, a.gain_db));
    angles_rad
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let deg = a.to_degrees().rem_euclid(180.0);
            (
                first_step + i as u64,
                StepSpec {
                    kind: FrameKind::Light,
                    set: Some(set),
                    angle_deg: deg,
                    exposure_us,
                    gain_db,
                    label: format!("round {} {deg:.3} deg", set + 1),
                    not_before_s: None,
                },
            )
        })
        .collect()
}

/// A stored light frame as APTD sees it: dark-subtracted DN at the measured angle.
fn aptd_frame(r: &FrameRecord, pixels: &[u16], camera: &CameraModel, plan: &Plan) -> AptdFrame {
    let gain_db = plan.adaptive.as_ref().map_or(0.0, |a| a.gain_db);
    let k = camera.gain_dn_per_e * 10f64.powf(gain_db / 20.0);
    let dark = camera.offset_dn + k * camera.dark_current_e_per_s * r.exposure_us * 1e-6;
    AptdFrame {
        angle_rad: r.measured_angle_deg.to_radians(),
        pixels: pixels.iter().map(|&p| f64::from(p) - dark).collect(),
    }
}

fn decision_json(d: &polar_planner::aptd::Decision) -> Value {
    json!({
        "round": d.round,
        "frames_used": d.frames_used,
        "target_pixels": d.target_pixels,
        "d": d.d,
        "clutter_cov": d.clutter_cov,
        "scr_last_set": d.scr_last_set,
        "next_angles_deg": d.next_angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "scr_next": d.scr_next,
        "angle_change_deg": d.angle_change_rad.to_degrees(),
        "reason": d.reason,
    })
}

enum AdaptiveNext {
    Acquire(u64, Vec<(u64, StepSpec)>),
    Done(Vec<f64>),
}

/// The APTD machine, rebuilt from the sets already accepted (a resumed run replays them; the
/// machine is deterministic, so it decides what it decided before), and the set to take next.
#[allow(clippy::too_many_arguments)]
fn adaptive_start(
    plan: &Plan,
    a: &crate::plan::Adaptive,
    target_mask: &Option<Vec<bool>>,
    records: &BTreeMap<u64, FrameRecord>,
    accepted: &BTreeMap<u64, u64>,
    sets_done: &BTreeMap<u64, Vec<u64>>,
    reader: &RunStore,
    steps: &[StepSpec],
    width: u32,
    height: u32,
    camera: &CameraModel,
) -> Result<(Aptd, BTreeSet<u64>, AdaptiveNext), RunError> {
    let n_px = width as usize * height as usize;
    let target = if let Some(f) = a.target.anomalies {
        TargetSpec::Anomalies { fraction: f }
    } else if let Some([x0, y0, x1, y1]) = a.target.rect {
        if x1 > width || y1 > height {
            return Err(RunError::Plan(crate::plan::PlanError::Invalid {
                field: "adaptive.target.rect".into(),
                value: format!("[{x0}, {y0}, {x1}, {y1}]"),
                allowed: format!("inside the {width}x{height} frame"),
            }));
        }
        let mut m = vec![false; n_px];
        for y in y0..y1 {
            for x in x0..x1 {
                m[(y * width + x) as usize] = true;
            }
        }
        TargetSpec::Region(m)
    } else {
        match target_mask {
            Some(m) if m.len() == n_px => TargetSpec::Region(m.clone()),
            _ => {
                return Err(RunError::Plan(crate::plan::PlanError::Invalid {
                    field: "adaptive.target.material".into(),
                    value: format!("{:?}", a.target.material),
                    allowed: "a material of the simulated scene (or use rect or anomalies \
                              on hardware)"
                        .into(),
                }))
            }
        }
    };
    // Sensor noise per frame, DN^2, at the mid-level of the camera's range.
    let k = camera.gain_dn_per_e * 10f64.powf(a.gain_db / 20.0);
    let mid_e = 0.25 * camera.full_well_e;
    let noise_var = k * k * (mid_e + camera.read_noise_e.powi(2)) + 1.0 / 12.0;
    let config = AptdConfig {
        channels: a.channels,
        initial_angles_rad: a
            .initial_angles_deg
            .iter()
            .map(|d| d.to_radians())
            .collect(),
        noise_var,
        target,
        constraints: Constraints {
            min_separation_rad: a.min_separation_deg.to_radians(),
            ..Constraints::default()
        },
        angle_tol_rad: a.angle_tol_deg.to_radians(),
        scr_rel_tol: a.scr_rel_tol,
        frame_budget: a.frame_budget,
    };
    let (mut machine, mut next) =
        Aptd::new(config).map_err(|e| RunError::Planner(e.to_string()))?;
    let darks = steps.iter().filter(|s| s.kind == FrameKind::Dark).count() as u64;
    let mut planned: BTreeSet<u64> = (0..darks).collect();
    let mut set = 0u64;
    let mut first_step = darks;
    loop {
        let angles = match &next {
            AptdStep::Acquire(angles) => angles.clone(),
            AptdStep::Done(_) => {
                let last = machine
                    .decisions()
                    .last()
                    .map(|d| d.next_angles_rad.iter().map(|r| r.to_degrees()).collect())
                    .unwrap_or_default();
                return Ok((machine, planned, AdaptiveNext::Done(last)));
            }
        };
        let members = adaptive_set(plan, set, first_step, &angles);
        planned.extend(members.iter().map(|(s, _)| *s));
        if !sets_done.contains_key(&set) {
            return Ok((machine, planned, AdaptiveNext::Acquire(set, members)));
        }
        // Replay this set from the store.
        let mut frames = Vec::new();
        for (s, _) in &members {
            let idx = accepted.get(s).ok_or_else(|| {
                RunError::Check(format!("set {set} is done but step {s} has no frame"))
            })?;
            let r = records
                .get(idx)
                .ok_or_else(|| RunError::Check(format!("frame {idx} has no record")))?;
            let px = reader.read_frame(*idx)?;
            frames.push(aptd_frame(r, &px, camera, plan));
        }
        next = machine
            .on_frames(frames)
            .map_err(|e| RunError::Planner(e.to_string()))?;
        first_step += members.len() as u64;
        set += 1;
    }
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
            message: "the journal has no run-started entry".into(),
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
