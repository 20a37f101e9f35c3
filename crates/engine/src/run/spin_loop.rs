//! The spin loop, the strategy of `kind = "continuous"`: the analyzer spins at
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
//! trigger is armed from a whole half turn at least the run-up ([`run_up_s`]: the stage's ramp
//! to speed when its acceleration is known, else [`RUN_UP_S`]) ahead (one pulse before it,
//! the *go* pulse, starts the camera, so the camera sees only armed positions); with
//! timestamps the loop waits the run-up and reads the position until the line's speed is
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

use super::core::{drive, Checked, Core, Opening, Strategy};
use super::link::{Control, Event, RunLink, RunState};
use super::outcome::{CameraStream, Outcome, RunError};
use super::record::{frame_record, FrameSpan};
use super::rig::Rig;
use super::writer::{FromStore, SetJob, ToStore};
use crate::continuous::{Continuous, SpanEstimator, TriggerSource};
use crate::journal::Entry;
use crate::plan::{Plan, PlanError, StepSpec, SuspendAction};
use crate::run::timestamps::{ClockMap, SpinTrack};
use polar_hal::TriggerPulse;
use polar_hal::{Camera, DeviceError, ErrorKind, Frame, OnRotator, Rotator, TriggerMode};
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::f64::consts::PI;
use std::path::Path;
use std::time::{Duration, Instant};
use tracing::{info, warn};

mod timestamped;

/// The run-up when the stage's acceleration is not known: how far the stage turns at speed
/// before the first armed position, seconds of its speed (a stage's ramp is shorter).
pub const RUN_UP_S: f64 = 0.5;

/// Seconds added to a known ramp for the commands between `spin` and the arming (a position
/// read and the arming itself, a few serial round trips).
const RUN_UP_MARGIN_S: f64 = 0.05;

/// The run-up of a spin at `rad_per_s`: the stage's ramp to that speed (`|omega| / a`) plus
/// [`RUN_UP_MARGIN_S`] when its acceleration `a` is known, else [`RUN_UP_S`]. The first armed
/// position is at least this many seconds of travel at speed ahead, so the stage is at speed
/// there: it covers only half that distance while it ramps.
pub fn run_up_s(rad_per_s: f64, acceleration_rad_per_s2: Option<f64>) -> f64 {
    match acceleration_rad_per_s2 {
        Some(a) if a.is_finite() && a > 0.0 => rad_per_s.abs() / a + RUN_UP_MARGIN_S,
        _ => RUN_UP_S,
    }
}

/// What the products use the camera model for, with a spinning analyzer.
const USED_FOR: &str = "the analyzer span rows (transmittance, extinction ratio, angle \
                        offset), the noise and the scalar dark level of the products";

/// The last frame of a segment and its pulse: the pulse's controller time, us, and the
/// frame's camera timestamp, ns (the pairing check, module docs).
#[derive(Clone, Copy)]
struct Mark {
    pulse_us: u32,
    frame_ns: Option<u64>,
}

/// The state of a timestamps segment: the loop's clock, the line and the next half turn.
struct SpinLine {
    /// The host clock every sample and frame time is measured on.
    clock: Instant,
    /// The stage's reads and the line through them.
    track: SpinTrack,
    /// The camera's clock on the host's (frames with a device timestamp and an event).
    clocks: ClockMap,
    /// How long after the time a trigger is aimed at its exposure starts, smoothed over the
    /// frames, s: triggers are aimed this much before the line's time of the grid angle.
    trigger_latency_s: f64,
    /// The stage angle (unwrapped) of the next half turn's frame 0: a whole half turn of the
    /// analyzer from its zero.
    next_half_rad: f64,
}

/// The spin loop's state beside the [`Core`].
struct SpinLoop<'a, R: Rotator, C: Camera> {
    core: Core<'a>,
    c: &'a Continuous,
    rig: Rig<OnRotator<R>, C>,
    steps: Vec<StepSpec>,
    /// The half turns still to take, in order.
    todo: VecDeque<u64>,
    /// Sets sent for checking, by set: their frames.
    checking: BTreeMap<u64, Vec<u64>>,
    /// Sets to take again (rejected by the suspender).
    retake: VecDeque<u64>,
    spinning: bool,
    last: Option<Mark>,
    /// The line of a `trigger = "timestamps"` segment (module docs).
    line: Option<SpinLine>,
    /// Half turns taken again after a device error (a missed trigger, a late frame), by half
    /// turn: at most `policy.attempts` tries each before the run pauses.
    attempts: HashMap<u64, u32>,
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
/// (a rotator that spins, and for `trigger = "encoder"` fires position-compare pulses into the
/// camera's trigger line), reporting through `link` (module docs).
pub(super) async fn run<R, C>(
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
    let Some(c) = plan.continuous() else {
        return Err(plan_err(
            "continuous",
            "missing",
            "a [continuous] section for a continuous plan",
        ));
    };
    c.validate()?;
    let info = rig.camera.info().clone();
    let (width, height) = (info.sensor_width, info.sensor_height);
    plan.check_frame(width, height)?;
    check_trigger(c, &rig)?;
    let steps = plan.steps()?;
    let opening = Opening {
        width,
        height,
        devices: &rig.devices,
        sensor: &rig.sensor,
        camera_model: &rig.camera_model,
        used_for: USED_FOR,
    };
    let (mut core, replay) = Core::open(plan, run_dir, resume, link, opening)?;
    // A half turn counts once its SetDone is journaled, and stops counting when one of its
    // frames is found damaged (then it is taken again).
    let mut accepted = BTreeMap::new();
    for i in replay.sets_done.values().flatten() {
        if let Some(r) = core.records.get(i) {
            accepted.insert(r.step, r.index);
        }
    }
    core.count_accepted(accepted, steps.len() as u64);
    let settled = replay
        .rejected
        .iter()
        .chain(&core.damaged)
        .chain(replay.sets_done.values().flatten())
        .copied()
        .collect();
    let todo = (0..u64::from(c.half_turns))
        .filter(|h| !replay.sets_done.contains_key(h))
        .collect();
    let spin_loop = SpinLoop {
        core,
        c,
        rig,
        steps,
        todo,
        checking: BTreeMap::new(),
        retake: VecDeque::new(),
        spinning: false,
        last: None,
        line: None,
        attempts: HashMap::new(),
        settled,
    };
    spin_loop.core.set_state(RunState::Running);
    drive(spin_loop).await
}

/// Refuses a trigger the rig cannot give (module docs), naming `continuous.trigger`.
fn check_trigger<R: Rotator, C: Camera>(
    c: &Continuous,
    rig: &Rig<OnRotator<R>, C>,
) -> Result<(), RunError> {
    let support = rig.analyzer.rotator.continuous_support();
    let model = rig.analyzer.rotator.info().model.clone();
    let camera_id = rig.camera.info().id.clone();
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
                 native spins with \"encoder\" or \"timestamps\", apt and standa with \
                 \"timestamps\" (docs/DEVICES.md)"
            ),
        ));
    }
    let refuse = |device: String, message: String| {
        Err(RunError::Device(DeviceError::new(
            ErrorKind::OutOfRange,
            device,
            message,
        )))
    };
    match c.trigger {
        TriggerSource::Encoder if !support.can_trigger() => refuse(
            model.clone(),
            format!(
                "continuous.trigger = \"encoder\" needs a stage with velocity mode and a \
                 position-compare trigger output: stage {model} offers \"{support}\"; allowed \
                 on this stage: \"timestamps\""
            ),
        ),
        TriggerSource::Encoder if !rig.camera.supports_hardware_trigger() => refuse(
            camera_id,
            "continuous.trigger = \"encoder\" needs the camera's hardware trigger wired to \
             the stage's trigger output: this camera has no hardware trigger; allowed with \
             it: \"timestamps\""
                .into(),
        ),
        TriggerSource::Timestamps if !rig.camera.supports_software_trigger() => refuse(
            camera_id,
            "continuous.trigger = \"timestamps\" needs a camera with a software trigger: \
             this camera has none"
                .into(),
        ),
        _ => Ok(()),
    }
}

impl<'a, R: Rotator, C: Camera> Strategy<'a> for SpinLoop<'a, R, C> {
    fn core(&mut self) -> &mut Core<'a> {
        &mut self.core
    }

    async fn camera_stream(&mut self) -> Option<CameraStream> {
        Some(self.rig.camera.stats().into())
    }

    async fn acquire(&mut self) -> Result<Option<Outcome>, RunError> {
        loop {
            while let Ok(msg) = self.core.from_store.try_recv() {
                self.on_store(msg).map_err(RunError::Storage)?;
            }
            if let Some(o) = self.plan_retakes().await? {
                return Ok(Some(o));
            }
            let Some(&h) = self.todo.front() else {
                // No half turn left to take (unless a check rejects one): stop spinning.
                self.stop_segment().await;
                if self.checking.is_empty() && self.core.in_flight.is_empty() {
                    return Ok(None);
                }
                match self.core.from_store.recv().await {
                    Some(msg) => self.on_store(msg).map_err(RunError::Storage)?,
                    None => return Err(RunError::Storage("the storage thread stopped".into())),
                }
                continue;
            };
            if let Some(ending) = self.safe_point(h).await? {
                match ending {
                    Some(o) => return Ok(Some(o)),
                    None => continue,
                }
            }
            self.supersede_unfinished(h).await?;
            let taken = async {
                if !self.spinning {
                    let half_turns = self.todo.len() as u64;
                    self.start_segment(half_turns).await?;
                }
                self.half_turn(h).await
            }
            .await;
            match taken {
                Ok(()) => {
                    self.todo.pop_front();
                }
                Err(e) => {
                    if let Some(o) = self.after_error(h, e).await? {
                        return Ok(Some(o));
                    }
                }
            }
        }
    }

    async fn rest(&mut self) {
        self.stop_segment().await;
    }

    async fn drain(&mut self) -> Result<(), String> {
        while !self.core.in_flight.is_empty() || !self.checking.is_empty() {
            match self.core.from_store.recv().await {
                Some(msg) => self.on_store(msg)?,
                None => return Err("the storage thread stopped".into()),
            }
        }
        Ok(())
    }

    fn planned_steps(&self) -> BTreeSet<u64> {
        (0..self.steps.len() as u64).collect()
    }
}

impl<R: Rotator, C: Camera> SpinLoop<'_, R, C> {
    /// Takes a message of the storage thread; a checked half turn is settled, counted, and
    /// when rejected queued to be taken again.
    fn on_store(&mut self, msg: FromStore) -> Result<(), String> {
        if let Some(checked) = self.core.on_store(msg)? {
            self.on_checked(checked);
        }
        Ok(())
    }

    fn on_checked(&mut self, (set, verdict, mean_dolp): Checked) {
        let frames = self.checking.remove(&set).unwrap_or_default();
        self.settled.extend(frames.iter().copied());
        self.core.event(Event::Set {
            set,
            verdict: verdict.clone(),
            mean_s0: verdict.mean_s0_dn,
            mean_dolp,
        });
        if verdict.accepted {
            self.core.sets_accepted += 1;
            return;
        }
        self.core.sets_rejected += 1;
        warn!(set, reason = %verdict.reason, "half turn rejected");
        for i in &frames {
            if let Some(r) = self.core.records.get(i) {
                if self.core.accepted.get(&r.step) == Some(i) {
                    self.core.accepted.remove(&r.step);
                }
            }
        }
        *self.core.rejections.entry(set).or_default() += 1;
        self.retake.push_back(set);
    }

    /// Queues the rejected half turns again, or pauses when the plan says so (or a half turn
    /// was rejected too often).
    async fn plan_retakes(&mut self) -> Result<Option<Outcome>, RunError> {
        while let Some(set) = self.retake.pop_front() {
            let tries = self.core.rejections.get(&set).copied().unwrap_or(0);
            let cfg = &self.core.plan.suspender;
            if cfg.action == SuspendAction::Pause || tries > cfg.max_reacquire {
                self.todo.push_front(set);
                let reason = format!("half turn {set} rejected {tries} times");
                if let Some(o) = self.pause(reason, set).await? {
                    return Ok(Some(o));
                }
            } else {
                self.todo.push_back(set);
            }
        }
        Ok(None)
    }

    /// The safe point before half turn `h`: what the controller asked meanwhile. `None`: go
    /// on; `Some(None)`: paused and resumed (look again); `Some(Some(o))`: the run ends.
    async fn safe_point(&mut self, h: u64) -> Result<Option<Option<Outcome>>, RunError> {
        let mut asked = None;
        while let Ok(c) = self.core.link.control.try_recv() {
            asked = Some(c);
        }
        Ok(match asked {
            Some(Control::Pause | Control::PauseNow) => {
                self.core.set_state(RunState::Pausing);
                Some(self.pause("paused by the user".into(), h).await?)
            }
            Some(Control::Abort) => Some(Some(Outcome::Aborted("aborted by the user".into()))),
            Some(Control::Detach) => Some(Some(Outcome::Paused("detached by the user".into()))),
            Some(Control::Resume) | None => None,
        })
    }

    /// After a device error in half turn `h`: a trigger the camera missed (or a frame it took
    /// late) spoils only this half turn, taken again up to the plan's attempts; anything else
    /// pauses the run.
    async fn after_error(&mut self, h: u64, e: DeviceError) -> Result<Option<Outcome>, RunError> {
        let reason = format!("half turn {h}: {e}");
        let tries = self.attempts.entry(h).or_insert(0);
        *tries += 1;
        let retry = matches!(e.kind(), ErrorKind::Protocol | ErrorKind::Timeout)
            && *tries < self.core.plan.policy.attempts;
        if retry {
            warn!("{reason}; taking the half turn again (try {})", *tries + 1);
            self.core.retries += 1;
            self.core.event(Event::Retry(reason.clone()));
            self.stop_segment().await;
            if let Err(e) = Strategy::drain(self).await {
                warn!("while stopping: {e}");
            }
            return Ok(None);
        }
        warn!("{reason}");
        self.pause(reason, h).await
    }

    /// Names the frames half turn `h` already has outside a settled set (an earlier try cut
    /// off by a missed trigger, a pause or a crash) as superseded in the journal, before the
    /// half turn is taken again whole.
    async fn supersede_unfinished(&mut self, h: u64) -> Result<(), RunError> {
        let stale: Vec<u64> = self
            .core
            .records
            .values()
            .filter(|r| r.set == Some(h) && !self.settled.contains(&r.index))
            .map(|r| r.index)
            .collect();
        if stale.is_empty() {
            return Ok(());
        }
        for i in &stale {
            if let Some(r) = self.core.records.get(i) {
                if self.core.accepted.get(&r.step) == Some(i) {
                    self.core.accepted.remove(&r.step);
                }
            }
        }
        self.settled.extend(stale.iter().copied());
        info!(half_turn = h, frames = ?stale, "an unfinished half turn is taken again whole");
        self.core
            .send_store_async(ToStore::Entry(Entry::FramesSuperseded {
                set: h,
                frames: stale,
                reason: format!("half turn {h} did not finish; it is taken again whole"),
            }))
            .await
    }

    /// Stops everything and waits for the controller: `None` when the run resumes, or the
    /// outcome that ends it.
    async fn pause(&mut self, reason: String, half_turn: u64) -> Result<Option<Outcome>, RunError> {
        self.stop_segment().await;
        if let Err(e) = Strategy::drain(self).await {
            warn!("while pausing: {e}");
        }
        let next_step = half_turn * u64::from(self.c.frames_per_half_turn);
        Ok(self.core.hold(&reason, next_step).await?.ending())
    }

    fn interval_rad(&self) -> f64 {
        PI / f64::from(self.c.frames_per_half_turn)
    }

    fn wait(&self) -> Duration {
        let interval_s = self.c.interval_deg() / self.c.speed_deg_per_s;
        Duration::from_secs_f64(
            self.core.plan.policy.grab_timeout_s + 3.0 * interval_s + self.c.exposure_us * 1e-6,
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
        let run_up = run_up_s(omega, self.rig.spin_acceleration_rad_per_s2);
        let go_wait = self.wait() + Duration::from_secs_f64(2.0 * run_up + 1.0);
        let rotator = &mut self.rig.analyzer.rotator;
        rotator.spin(omega).await?;
        let zero = self.rig.analyzer.zero_offset_rad;
        let position = rotator.spin_position_rad().await?;
        // The first frame's position: a whole half turn of the analyzer, the run-up ahead; the
        // go pulse one interval before it.
        let ahead = position - zero + omega * run_up + interval;
        let first = zero + (ahead / PI).ceil() * PI - interval;
        let n = u64::from(c.frames_per_half_turn);
        let spare = u64::from(self.core.plan.suspender.max_reacquire) + 1;
        let pulses = u32::try_from(1 + n * half_turns * spare.min(4)).unwrap_or(u32::MAX);
        rotator.arm_trigger(first, interval, pulses).await?;
        let go = rotator.next_trigger(go_wait).await?;
        self.rig.camera.start().await?;
        tracing::debug!(
            go_deg = go.angle_rad.to_degrees(),
            ms = t0.elapsed().as_secs_f64() * 1e3,
            "spinning; camera on the line"
        );
        self.core.device_s += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Stops the camera and the spin and disarms the trigger (errors are logged: the run is
    /// ending or pausing anyway).
    async fn stop_segment(&mut self) {
        if !self.spinning {
            return;
        }
        self.spinning = false;
        self.line = None;
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
            self.core.device_s += t0.elapsed().as_secs_f64();
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
        let index = self.core.next_index;
        self.core.next_index += 1;
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
            self.core.plan.site.as_ref(),
        );
        self.core.records.insert(index, record.clone());
        self.core.accepted.insert(step, index);
        self.core.in_flight.insert(index);
        self.core
            .send_store_async(ToStore::Frame {
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
        self.core
            .send_store_async(ToStore::ProcessSet(job))
            .await
            .map_err(|e| DeviceError::new(ErrorKind::Other, "storage", e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The simulated stage reaches 360 deg/s in 1/8 s: the run-up is that ramp and the 50 ms
    /// margin, and the first armed position (the run-up's travel at speed ahead) lies beyond
    /// the ramp's travel (half of it, at constant acceleration), so the stage is at speed there.
    /// An unknown or nonsensical acceleration falls back to the fixed run-up.
    #[test]
    fn the_run_up_is_the_ramp_when_the_acceleration_is_known() {
        let omega = 360f64.to_radians();
        let a = omega * 8.0;
        let t = run_up_s(omega, Some(a));
        assert!((t - 0.175).abs() < 1e-12, "{t}");
        assert!(omega * t > omega * omega / (2.0 * a));
        assert_eq!(run_up_s(-omega, Some(a)), t, "either direction");
        for unknown in [None, Some(0.0), Some(f64::NAN), Some(-a)] {
            assert_eq!(run_up_s(omega, unknown), RUN_UP_S);
        }
        // A slow ramp (10 s) runs up for all of it, longer than the fixed run-up.
        assert!((run_up_s(omega, Some(omega / 10.0)) - 10.05).abs() < 1e-12);
    }
}
