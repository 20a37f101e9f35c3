//! The run loop of `kind = "continuous"` ([`run_continuous`]): the analyzer spins at
//! `speed_deg_per_s` and the camera takes `frames_per_half_turn` frames per half turn, frame
//! `k` from the analyzer's grid angle `k * 180 / N`; a half turn is one set.
//!
//! **`trigger = "encoder"`.** The stage's position-compare output fires a pulse at every
//! `180 / N` degrees of the analyzer (whole multiples of the interval from the analyzer's
//! zero), and the camera, in hardware-trigger mode on that line, starts an exposure at each
//! pulse. Frame `k` of a half turn pairs with the pulse at `k * 180 / N`: its span starts at
//! the encoder angle the pulse latched and ends `speed x exposure` later
//! (`AngleSource::EncoderTrigger`, `angle_sigma_deg` 0: one encoder count is far below any
//! other error). Each frame's pairing with its pulse is checked: consecutive frames must be as
//! far apart on the camera's clock as their pulses on the stage's (within half an interval),
//! and each pulse must be at its frame's angle.
//!
//! **`trigger = "timestamps"`** (a stage without a trigger output, or one not wired to the
//! camera). The camera is in software-trigger mode and the analyzer's angle comes from the
//! stage's position samples against the host's clock ([`super::timestamps`]: a least-squares
//! line through reads of the spinning stage, read at least every 0.1 s while the loop waits
//! for a frame and once after each frame). Frame `k` is
//! triggered when the line puts the analyzer at its grid angle; its exposure's end is the
//! camera's exposure-end event on the host clock, taken through the frame's device timestamp
//! where the camera stamps its frames (the camera's clock mapped onto the host's past the
//! events' latency: [`super::timestamps::ClockMap`]), or, for a camera without that event, the
//! middle of the interval from trigger plus exposure to the frame's arrival, with that
//! interval's spread added to the timing uncertainty; its span ends at the line's angle then
//! and starts `speed x exposure` earlier (`AngleSource::Timestamps`, `angle_sigma_deg` the
//! span's standard uncertainty from the plan's `timing_sigma_us`, the line's standard error
//! and the reads' round trip). A frame whose span starts more than half an interval from its
//! grid angle is a protocol error (the half turn is taken again). The products of a half turn
//! use the span rows with the largest angle uncertainty of its frames as the jitter.
//!
//! A half turn's frames go through the same storage thread and journal as step-and-shoot
//! frames, and its products are computed there with the span rows of
//! [`crate::continuous::SpanEstimator`] (Malus's law averaged over each span) instead of the
//! still analyzer's rows; the suspender checks it as any set, and `SetDone` is journaled per
//! half turn.
//!
//! **Segments.** Spinning starts a segment: the camera is configured and started, the stage
//! spins, and half turns are taken until the run ends or pauses. With encoder triggers the
//! trigger is armed from a whole half turn at least [`RUN_UP_S`] ahead (one pulse before it,
//! the *go* pulse, starts the camera, so the camera sees only armed positions); with
//! timestamps the loop waits [`RUN_UP_S`] and reads the position until the line's speed is
//! the commanded one, and the first half turn is the next whole half turn of the analyzer.
//! Pausing (at a half-turn boundary: the safe point), a device error and the end stop the
//! camera and the spin (and disarm the trigger); resuming starts a new segment. So a pause, an
//! abort or a crash redoes at most the half turn in progress: a resumed run replays the
//! journal and takes every half turn without `SetDone` again (its earlier frames stay stored,
//! superseded).
//!
//! Refused at the start, naming `continuous.trigger`: either trigger on a stage that cannot
//! spin (Elliptec, filter wheels), `encoder` on a stage without a position-compare output or a
//! camera without a hardware trigger, `timestamps` with a camera without a software trigger.

use super::*;
use crate::continuous::{Continuous, SpanEstimator, TriggerSource};
use crate::plan::PlanError;
use polar_hal::{OnRotator, Rotator, TriggerPulse};
use std::f64::consts::PI;

mod timestamped;

/// How far the stage turns at speed before the first armed position, seconds of its speed
/// (its ramp to speed is shorter).
pub const RUN_UP_S: f64 = 0.5;

/// The last frame of a segment and its pulse: the pulse's controller time, us, and the
/// frame's camera timestamp, ns (the pairing check, module docs).
#[derive(Clone, Copy)]
struct Mark {
    pulse_us: u32,
    frame_ns: Option<u64>,
}

struct Cont<'a, R: Rotator, C: Camera> {
    plan: &'a Plan,
    c: &'a Continuous,
    rig: Rig<OnRotator<R>, C>,
    link: RunLink,
    to_store: std::sync::mpsc::SyncSender<ToStore>,
    from_store: mpsc::UnboundedReceiver<FromStore>,
    steps: Vec<StepSpec>,
    records: BTreeMap<u64, FrameRecord>,
    accepted: BTreeMap<u64, u64>,
    next_index: u64,
    in_flight: BTreeSet<u64>,
    done_frames: u64,
    planned_frames: u64,
    sets_accepted: u64,
    sets_rejected: u64,
    rejections: HashMap<u64, u32>,
    /// Sets sent for checking, by set: their frames.
    checking: BTreeMap<u64, Vec<u64>>,
    /// Sets to take again (rejected by the suspender).
    retake: VecDeque<u64>,
    pauses: u64,
    device_s: f64,
    spinning: bool,
    last: Option<Mark>,
    /// The line of a `trigger = "timestamps"` segment (module docs).
    free: Option<timestamped::Free>,
    /// Half turns taken again after a device error (a missed trigger, a late frame), by half
    /// turn: at most `policy.attempts` tries each before the run pauses.
    attempts: HashMap<u64, u32>,
    retries: u64,
    /// Frames found damaged and kept aside (recorded, neither counted nor verified).
    damaged: BTreeSet<u64>,
    /// Frames whose half turn is settled: done, rejected, superseded, or damaged. A recorded
    /// frame outside it belongs to a half turn that did not finish.
    settled: BTreeSet<u64>,
}

fn plan_err(field: &str, value: impl Into<String>, allowed: impl Into<String>) -> RunError {
    RunError::Plan(PlanError::Invalid {
        field: field.into(),
        value: value.into(),
        allowed: allowed.into(),
    })
}

/// Runs (or, with `resume`, continues) a `kind = "continuous"` plan into `run_dir` on `rig`
/// (a rotator that spins and fires position-compare pulses, a camera whose trigger line is
/// wired to them), reporting through `link` (module docs). Call it inside a
/// [`tokio::task::LocalSet`], as [`run`].
pub async fn run_continuous<R, C>(
    plan: &Plan,
    rig: Rig<OnRotator<R>, C>,
    run_dir: &Path,
    resume: bool,
    link: RunLink,
) -> Result<Outcome, RunError>
where
    R: Rotator,
    C: Camera,
{
    let started = Instant::now();
    let c = match (&plan.kind, &plan.continuous) {
        (PlanKind::Continuous, Some(c)) => c,
        _ => {
            return Err(plan_err(
                "kind",
                plan.kind.name(),
                "continuous (with a [continuous] section) for run_continuous",
            ))
        }
    };
    c.validate()?;
    let info = rig.camera.info().clone();
    let (width, height) = (info.sensor_width, info.sensor_height);
    plan.check_frame(width, height)?;
    let support = rig.analyzer.rotator.continuous_support();
    let model = rig.analyzer.rotator.info().model.clone();
    let trigger = match c.trigger {
        TriggerSource::Encoder => "encoder",
        TriggerSource::Timestamps => "timestamps",
    };
    if !support.can_spin() {
        return Err(plan_err(
            "continuous.trigger",
            trigger,
            format!(
                "a continuous plan needs a stage that spins (velocity mode), and stage \
                 {model} cannot spin (continuous-rotation support \"{support}\"); dialect \
                 native spins with \"encoder\" or \"timestamps\", apt with \"timestamps\" \
                 (docs/DEVICES.md)"
            ),
        ));
    }
    match c.trigger {
        TriggerSource::Encoder => {
            if !support.can_trigger() {
                return Err(RunError::Device(DeviceError::new(
                    ErrorKind::OutOfRange,
                    model.clone(),
                    format!(
                        "continuous.trigger = \"encoder\" needs a stage with velocity mode and \
                         a position-compare trigger output: stage {model} offers \"{support}\"; \
                         allowed on this stage: \"timestamps\""
                    ),
                )));
            }
            if !rig.camera.supports_hardware_trigger() {
                return Err(RunError::Device(DeviceError::new(
                    ErrorKind::OutOfRange,
                    info.id.clone(),
                    "continuous.trigger = \"encoder\" needs the camera's hardware trigger wired \
                     to the stage's trigger output: this camera has no hardware trigger; \
                     allowed with it: \"timestamps\"",
                )));
            }
        }
        TriggerSource::Timestamps => {
            if !rig.camera.supports_software_trigger() {
                return Err(RunError::Device(DeviceError::new(
                    ErrorKind::OutOfRange,
                    info.id.clone(),
                    "continuous.trigger = \"timestamps\" needs a camera with a software \
                     trigger: this camera has none",
                )));
            }
        }
    }
    let steps = plan.steps()?;
    let opened = open_run(plan, run_dir, resume, width, height, &rig.devices)?;
    let mut opened = opened;
    let entries = std::mem::take(&mut opened.entries);
    opened.store.set_attribute(
        "products_camera",
        json!({
            "model": rig.camera_model,
            "source": format!("{} devices", rig.devices["kind"].as_str().unwrap_or("unknown")),
            "used_for": "the analyzer span rows (transmittance, extinction ratio, angle \
                         offset), the noise and the scalar dark level of the products",
        }),
    )?;
    // Replay: a half turn counts once its SetDone is journaled, and stops counting when one
    // of its frames is found damaged (then it is taken again).
    let mut records: BTreeMap<u64, FrameRecord> = BTreeMap::new();
    let mut sets_done: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
    let mut rejections: HashMap<u64, u32> = HashMap::new();
    let mut rejected: BTreeSet<u64> = BTreeSet::new();
    let mut damaged: BTreeSet<u64> = BTreeSet::new();
    for e in &entries {
        match e {
            Entry::Frame(r) => {
                records.insert(r.index, r.clone());
            }
            Entry::SetDone { set, frames, .. } => {
                sets_done.insert(*set, frames.clone());
            }
            Entry::SetRejected { set, frames, .. } => {
                rejected.extend(frames.iter().copied());
                *rejections.entry(*set).or_default() += 1;
            }
            Entry::FramesSuperseded { frames, .. } => rejected.extend(frames.iter().copied()),
            Entry::FrameDamaged { index, .. } => {
                damaged.insert(*index);
                sets_done.retain(|_, frames| !frames.contains(index));
            }
            _ => {}
        }
    }
    if resume {
        // Every frame still on record is checked against its hash before the run goes on
        // (as step-and-shoot's resume does): a damaged chunk is kept aside and its half turn
        // taken again.
        rejected.extend(damaged.iter().copied());
        for index in set_aside_damaged(&mut opened, run_dir, &records, &rejected)? {
            damaged.insert(index);
            sets_done.retain(|_, frames| !frames.contains(&index));
        }
    }
    let mut accepted = BTreeMap::new();
    for frames in sets_done.values() {
        for i in frames {
            if let Some(r) = records.get(i) {
                accepted.insert(r.step, r.index);
            }
        }
    }
    let next_index = records.keys().next_back().map_or(0, |i| i + 1);
    let writer = Writer::new(
        opened.store,
        opened.journal,
        plan,
        &rig.sensor,
        &rig.camera_model,
        records.clone(),
        HashMap::new(),
    )?;
    let (to_store, from_store, writer_thread) = spawn_writer(writer)?;
    if resume {
        to_store
            .send(ToStore::Entry(Entry::Resumed {
                process_id: std::process::id(),
                at_unix_ns: now_unix_ns(SystemTime::now()),
            }))
            .map_err(|_| RunError::Storage("the storage thread stopped".into()))?;
    }
    let mut lp = Cont {
        plan,
        c,
        rig,
        link,
        to_store,
        from_store,
        planned_frames: steps.len() as u64,
        steps,
        done_frames: accepted.len() as u64,
        records,
        accepted,
        next_index,
        in_flight: BTreeSet::new(),
        sets_accepted: sets_done.len() as u64,
        sets_rejected: rejections.values().map(|n| u64::from(*n)).sum(),
        rejections,
        checking: BTreeMap::new(),
        retake: VecDeque::new(),
        pauses: 0,
        device_s: 0.0,
        spinning: false,
        last: None,
        free: None,
        attempts: HashMap::new(),
        retries: 0,
        settled: rejected
            .iter()
            .chain(&damaged)
            .chain(sets_done.values().flatten())
            .copied()
            .collect(),
        damaged,
    };
    lp.set_state(RunState::Running);
    let mut todo: VecDeque<u64> = (0..u64::from(c.half_turns))
        .filter(|h| !sets_done.contains_key(h))
        .collect();
    let outcome = lp.main(&mut todo).await;
    lp.stop_segment().await;
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => {
            drop(lp);
            let _ = tokio::task::spawn_blocking(move || writer_thread.join()).await;
            return Err(e);
        }
    };
    lp.drain().await.map_err(RunError::Storage)?;
    let summary = Summary {
        frames_stored: lp.next_index,
        frames_accepted: lp.accepted.len() as u64,
        sets_accepted: lp.sets_accepted,
        sets_rejected: lp.sets_rejected,
        retries: lp.retries,
        pauses: lp.pauses,
        elapsed_s: started.elapsed().as_secs_f64(),
        device_s: lp.device_s,
        final_angles_deg: None,
        saturation: Saturation::of(
            &RunStore::open(run_dir)?,
            plan.suspender.max_saturated_fraction,
        )?,
    };
    let result = match outcome {
        Some(Outcome::Aborted(reason)) => end_aborted(&lp.link, &lp.to_store, reason),
        Some(other) => Ok(other),
        None => {
            let summary_json =
                json!({ "run": serde_json::to_value(&summary).unwrap_or(Value::Null) });
            let checks = FinishChecks {
                planned_steps: (0..lp.steps.len() as u64).collect(),
                accepted: lp.accepted.clone(),
                damaged: lp.damaged.clone(),
            };
            end_done(&lp.link, &lp.to_store, summary_json, checks).await?;
            Ok(Outcome::Done(summary))
        }
    };
    drop(lp);
    let _ = tokio::task::spawn_blocking(move || writer_thread.join()).await;
    result
}

/// What to do after a pause.
enum After {
    Resume,
    End(Outcome),
}

impl<R: Rotator, C: Camera> Cont<'_, R, C> {
    fn set_state(&self, s: RunState) {
        self.link.set_state(s);
    }

    /// Sends without blocking the loop's thread (the channel holds two messages).
    async fn send_store_async(&self, msg: ToStore) -> Result<(), RunError> {
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

    fn on_store(&mut self, msg: FromStore) -> Result<(), RunError> {
        match msg {
            FromStore::Durable { index, label } => {
                self.in_flight.remove(&index);
                self.done_frames += 1;
                let _ = self.link.events.try_send(Event::Progress {
                    done: self.done_frames,
                    planned: self.planned_frames,
                    label,
                });
            }
            FromStore::SetChecked {
                set,
                verdict,
                mean_dolp,
            } => {
                let frames = self.checking.remove(&set).unwrap_or_default();
                self.settled.extend(frames.iter().copied());
                let _ = self.link.events.try_send(Event::Set {
                    set,
                    verdict: verdict.clone(),
                    mean_s0: verdict.mean_s0_dn,
                    mean_dolp,
                });
                if verdict.accepted {
                    self.sets_accepted += 1;
                } else {
                    self.sets_rejected += 1;
                    warn!(set, reason = %verdict.reason, "half turn rejected");
                    for i in &frames {
                        if let Some(r) = self.records.get(i) {
                            if self.accepted.get(&r.step) == Some(i) {
                                self.accepted.remove(&r.step);
                            }
                        }
                    }
                    *self.rejections.entry(set).or_default() += 1;
                    self.retake.push_back(set);
                }
            }
            FromStore::Failed(e) => return Err(RunError::Storage(e)),
        }
        Ok(())
    }

    async fn drain(&mut self) -> Result<(), String> {
        while !self.in_flight.is_empty() || !self.checking.is_empty() {
            match self.from_store.recv().await {
                Some(msg) => self.on_store(msg).map_err(|e| e.to_string())?,
                None => return Err("the storage thread stopped".into()),
            }
        }
        Ok(())
    }

    /// The half turns until the end, a pause that ends the run, or an abort.
    async fn main(&mut self, todo: &mut VecDeque<u64>) -> Result<Option<Outcome>, RunError> {
        loop {
            while let Ok(msg) = self.from_store.try_recv() {
                self.on_store(msg)?;
            }
            while let Some(set) = self.retake.pop_front() {
                let tries = self.rejections.get(&set).copied().unwrap_or(0);
                let cfg = &self.plan.suspender;
                if cfg.action == SuspendAction::Pause || tries > cfg.max_reacquire {
                    todo.push_front(set);
                    let reason = format!("half turn {set} rejected {tries} times");
                    match self.pause(reason, set).await? {
                        After::Resume => {}
                        After::End(o) => return Ok(Some(o)),
                    }
                } else {
                    todo.push_back(set);
                }
            }
            let Some(&h) = todo.front() else {
                // No half turn left to take (unless a check rejects one): stop spinning.
                self.stop_segment().await;
                if self.checking.is_empty() && self.in_flight.is_empty() {
                    return Ok(None);
                }
                match self.from_store.recv().await {
                    Some(msg) => self.on_store(msg)?,
                    None => return Err(RunError::Storage("the storage thread stopped".into())),
                }
                continue;
            };
            // The safe point: between half turns.
            let mut asked = None;
            while let Ok(c) = self.link.control.try_recv() {
                asked = Some(c);
            }
            match asked {
                Some(Control::Pause | Control::PauseNow) => {
                    self.set_state(RunState::Pausing);
                    match self.pause("paused by the user".into(), h).await? {
                        After::Resume => continue,
                        After::End(o) => return Ok(Some(o)),
                    }
                }
                Some(Control::Abort) => {
                    return Ok(Some(Outcome::Aborted("aborted by the user".into())))
                }
                Some(Control::Detach) => {
                    return Ok(Some(Outcome::Paused("detached by the user".into())))
                }
                Some(Control::Resume) | None => {}
            }
            self.supersede_unfinished(h).await?;
            let taken = async {
                if !self.spinning {
                    let half_turns = todo.len() as u64;
                    self.start_segment(half_turns).await?;
                }
                self.half_turn(h).await
            }
            .await;
            match taken {
                Ok(()) => {
                    todo.pop_front();
                }
                Err(e) => {
                    let reason = format!("half turn {h}: {e}");
                    let tries = self.attempts.entry(h).or_insert(0);
                    *tries += 1;
                    let retry = matches!(e.kind(), ErrorKind::Protocol | ErrorKind::Timeout)
                        && *tries < self.plan.policy.attempts;
                    if retry {
                        // A trigger the camera missed (or a frame it took late) spoils only
                        // this half turn: stop, spin up again and take it again.
                        warn!("{reason}; taking the half turn again (try {})", *tries + 1);
                        self.retries += 1;
                        let _ = self.link.events.try_send(Event::Retry(reason.clone()));
                        self.stop_segment().await;
                        if let Err(e) = self.drain().await {
                            warn!("while stopping: {e}");
                        }
                        continue;
                    }
                    warn!("{reason}");
                    match self.pause(reason, h).await? {
                        After::Resume => {}
                        After::End(o) => return Ok(Some(o)),
                    }
                }
            }
        }
    }

    /// Names the frames half turn `h` already has outside a settled set (an earlier try cut
    /// off by a missed trigger, a pause or a crash) as superseded in the journal, before the
    /// half turn is taken again whole.
    async fn supersede_unfinished(&mut self, h: u64) -> Result<(), RunError> {
        let stale: Vec<u64> = self
            .records
            .values()
            .filter(|r| r.set == Some(h) && !self.settled.contains(&r.index))
            .map(|r| r.index)
            .collect();
        if stale.is_empty() {
            return Ok(());
        }
        for i in &stale {
            if let Some(r) = self.records.get(i) {
                if self.accepted.get(&r.step) == Some(i) {
                    self.accepted.remove(&r.step);
                }
            }
        }
        self.settled.extend(stale.iter().copied());
        info!(half_turn = h, frames = ?stale, "an unfinished half turn is taken again whole");
        self.send_store_async(ToStore::Entry(Entry::FramesSuperseded {
            set: h,
            frames: stale,
            reason: format!("half turn {h} did not finish; it is taken again whole"),
        }))
        .await
    }

    /// Stops everything and waits for the controller.
    async fn pause(&mut self, reason: String, half_turn: u64) -> Result<After, RunError> {
        self.stop_segment().await;
        if let Err(e) = self.drain().await {
            warn!("while pausing: {e}");
        }
        self.pauses += 1;
        let next_step = half_turn * u64::from(self.c.frames_per_half_turn);
        Ok(
            match hold_paused(&mut self.link, &self.to_store, &reason, next_step).await? {
                AfterPause::Resume => After::Resume,
                AfterPause::Abort(r) => After::End(Outcome::Aborted(r)),
                AfterPause::Detach(r) => After::End(Outcome::Paused(r)),
            },
        )
    }

    fn interval_rad(&self) -> f64 {
        PI / f64::from(self.c.frames_per_half_turn)
    }

    fn wait(&self) -> Duration {
        let interval_s = self.c.interval_deg() / self.c.speed_deg_per_s;
        Duration::from_secs_f64(
            self.plan.policy.grab_timeout_s + 3.0 * interval_s + self.c.exposure_us * 1e-6,
        )
    }

    /// Starts a segment (module docs): with timestamps, see
    /// [`timestamped`]; with encoder triggers, configures and starts the camera on its line,
    /// spins, arms the trigger for `half_turns` half turns (and their retakes) and waits for
    /// the go pulse.
    async fn start_segment(&mut self, half_turns: u64) -> Result<(), DeviceError> {
        if self.c.trigger == TriggerSource::Timestamps {
            return self.start_timestamps().await;
        }
        let t0 = Instant::now();
        let c = self.c;
        let cam = &mut self.rig.camera;
        cam.set_exposure_us(c.exposure_us).await?;
        cam.set_gain(c.gain_db).await?;
        cam.set_trigger(TriggerMode::Hardware).await?;
        let omega = c.speed_deg_per_s.to_radians();
        self.spinning = true;
        self.last = None;
        let interval = self.interval_rad();
        let go_wait = self.wait() + Duration::from_secs_f64(2.0 * RUN_UP_S + 1.0);
        let rotator = &mut self.rig.analyzer.rotator;
        rotator.spin(omega).await?;
        let zero = self.rig.analyzer.zero_offset_rad;
        let position = rotator.spin_position_rad().await?;
        // The first frame's position: a whole half turn of the analyzer, RUN_UP_S ahead; the
        // go pulse one interval before it.
        let ahead = position - zero + omega * RUN_UP_S + interval;
        let first = zero + (ahead / PI).ceil() * PI - interval;
        let n = u64::from(c.frames_per_half_turn);
        let spare = u64::from(self.plan.suspender.max_reacquire) + 1;
        let pulses = u32::try_from(1 + n * half_turns * spare.min(4)).unwrap_or(u32::MAX);
        rotator.arm_trigger(first, interval, pulses).await?;
        let go = rotator.next_trigger(go_wait).await?;
        self.rig.camera.start().await?;
        tracing::debug!(
            go_deg = go.angle_rad.to_degrees(),
            ms = t0.elapsed().as_secs_f64() * 1e3,
            "spinning; camera on the line"
        );
        self.device_s += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Stops the camera and the spin and disarms the trigger (errors are logged: the run is
    /// ending or pausing anyway).
    async fn stop_segment(&mut self) {
        if !self.spinning {
            return;
        }
        self.spinning = false;
        self.free = None;
        if let Err(e) = self.rig.camera.stop().await {
            warn!("stopping the camera: {e}");
        }
        let rotator = &mut self.rig.analyzer.rotator;
        if let Err(e) = rotator.stop_spin().await {
            warn!("stopping the spin: {e}");
        }
        if self.c.trigger == TriggerSource::Encoder {
            if let Err(e) = rotator.arm_trigger(0.0, 0.0, 0).await {
                warn!("disarming the trigger: {e}");
            }
        }
    }

    /// Takes half turn `h` (with timestamps, see [`timestamped`]): `N` pulses, each with its
    /// frame, to storage, then the set to be checked with its span rows.
    async fn half_turn(&mut self, h: u64) -> Result<(), DeviceError> {
        if self.c.trigger == TriggerSource::Timestamps {
            return self.half_turn_timestamps(h).await;
        }
        let c = self.c;
        let n = u64::from(c.frames_per_half_turn);
        let interval_deg = c.interval_deg();
        let span_deg = c.span_deg();
        let zero = self.rig.analyzer.zero_offset_rad;
        let wait = self.wait();
        let mut frames = Vec::with_capacity(n as usize);
        let mut spans_rad = Vec::with_capacity(n as usize);
        for k in 0..n {
            let t0 = Instant::now();
            let pulse: TriggerPulse = self.rig.analyzer.rotator.next_trigger(wait).await?;
            let frame = self.rig.camera.grab(wait).await?;
            self.device_s += t0.elapsed().as_secs_f64();
            let bad = |m: String| DeviceError::new(ErrorKind::Protocol, "continuous", m);
            let start_deg = (pulse.angle_rad - zero).to_degrees().rem_euclid(180.0);
            let grid = (start_deg / interval_deg).round() as u64 % n;
            if grid != k {
                return Err(bad(format!(
                    "pulse {} at {start_deg:.4} deg is not at frame {k}'s angle {} deg",
                    pulse.index,
                    k as f64 * interval_deg
                )));
            }
            let mark = Mark {
                pulse_us: pulse.device_time_us,
                frame_ns: frame.device_timestamp_ns,
            };
            if let (Some(last), Some(now_ns)) = (self.last, mark.frame_ns) {
                if let Some(last_ns) = last.frame_ns {
                    let pulse_s = f64::from(mark.pulse_us.wrapping_sub(last.pulse_us)) * 1e-6;
                    let frame_s = now_ns.wrapping_sub(last_ns) as f64 * 1e-9;
                    let half_s = 0.5 * interval_deg / c.speed_deg_per_s;
                    if (pulse_s - frame_s).abs() > half_s {
                        return Err(bad(format!(
                            "frame {} came {frame_s:.4} s after the previous one but its pulse \
                             {} {pulse_s:.4} s after the previous pulse: the camera missed a \
                             trigger or took an extra one",
                            frame.frame_id, pulse.index
                        )));
                    }
                }
            }
            self.last = Some(mark);
            let span = (start_deg, start_deg + span_deg);
            let index = self
                .store_frame(
                    h * n + k,
                    frame,
                    span,
                    crate::AngleSource::EncoderTrigger,
                    0.0,
                )
                .await?;
            frames.push(index);
            spans_rad.push((span.0.to_radians(), span.1.to_radians()));
        }
        self.send_set(h, frames, &spans_rad, c.angle_sigma_rad())
            .await
    }

    /// Records frame `step` (its analyzer span `span_deg`, start and end from the analyzer's
    /// zero, measured by `source` to `sigma_deg`) and sends it to storage; returns its index.
    /// A frame of another size than the sensor's is a protocol error.
    async fn store_frame(
        &mut self,
        step: u64,
        frame: Frame,
        span_deg: (f64, f64),
        source: crate::AngleSource,
        sigma_deg: f64,
    ) -> Result<u64, DeviceError> {
        let (w, hgt) = (
            self.rig.camera.info().sensor_width,
            self.rig.camera.info().sensor_height,
        );
        if (frame.width, frame.height) != (w, hgt) || frame.pixels.len() != (w * hgt) as usize {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                "continuous",
                format!(
                    "frame {} of {}x{}; the run stores {w}x{hgt}",
                    frame.frame_id, frame.width, frame.height
                ),
            ));
        }
        let spec = self.steps[step as usize].clone();
        let index = self.next_index;
        self.next_index += 1;
        let record = frame_record(
            (index, step, &spec),
            &frame,
            FrameSpan {
                start_deg: span_deg.0,
                end_deg: span_deg.1,
                source,
                sigma_deg,
            },
            self.rig.sun_deg,
            self.plan.site.as_ref(),
        );
        self.records.insert(index, record.clone());
        self.accepted.insert(step, index);
        self.in_flight.insert(index);
        self.send_store_async(ToStore::Frame {
            record,
            pixels: frame.pixels,
        })
        .await
        .map_err(|e| DeviceError::new(ErrorKind::Other, "storage", e.to_string()))?;
        Ok(index)
    }

    /// Sends half turn `h` (its stored `frames` and their spans, radians from the analyzer's
    /// zero) to be checked, its products computed with the span rows at the centre-angle
    /// uncertainty `angle_sigma_rad`.
    async fn send_set(
        &mut self,
        h: u64,
        frames: Vec<u64>,
        spans_rad: &[(f64, f64)],
        angle_sigma_rad: f64,
    ) -> Result<(), DeviceError> {
        let c = self.c;
        let estimator = SpanEstimator::new(
            &self.rig.sensor,
            spans_rad,
            c.exposure_us * 1e-6,
            angle_sigma_rad,
        )
        .map_err(|e| DeviceError::new(ErrorKind::OutOfRange, "continuous", e.to_string()))?;
        let job = SetJob {
            set: h,
            measured_deg: spans_rad.iter().map(|s| s.0.to_degrees()).collect(),
            commanded_deg: c.trigger_angles_deg(),
            exposure_us: c.exposure_us,
            gain_db: c.gain_db,
            frames: frames.clone(),
            rows: Some(estimator.rows.iter().map(|r| [r[0], r[1], r[2]]).collect()),
        };
        self.checking.insert(h, frames);
        self.send_store_async(ToStore::ProcessSet(job))
            .await
            .map_err(|e| DeviceError::new(ErrorKind::Other, "storage", e.to_string()))
    }
}
