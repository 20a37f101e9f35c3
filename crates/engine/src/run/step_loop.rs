//! The step loop: the strategy of every plan kind but `continuous`. The analyzer moves to each
//! step's angle and the camera takes the step's frame there; consecutive steps of a set form a
//! unit between two safe points, whose frames go to the storage thread to be checked (behind
//! the next set's acquisition for a static plan; an adaptive plan's planner waits for each
//! verdict and chooses the next set). Dark series on hardware pause for the lens cap; a
//! time-lapse set waits for its time.

use super::actors::{spawn_camera, spawn_stage, CamCmd, StageCmd};
use super::adaptive::{adaptive_set, adaptive_start, aptd_frame, decision_json, AdaptiveNext};
use super::clock::now_unix_ns;
use super::core::{drive, Checked, Core, Opening, Replay, Strategy};
use super::link::{Control, Event, RunLink, RunState};
use super::outcome::{CameraStream, Outcome, RunError};
use super::pause::AfterPause;
use super::pause::{CAP_LENS, UNCAP_LENS};
use super::rig::{Rig, SceneLight};
use super::writer::{SetJob, ToStore};
use crate::journal::Entry;
use crate::plan::{Plan, PlanKind, StepSpec, SuspendAction};
use crate::FrameKind;
use polar_hal::{Analyzer, Camera, DeviceError};
use polar_model::sensor::Camera as CameraModel;
use polar_planner::aptd::{Aptd, AptdFrame, Step as AptdStep};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::Path;
use std::time::{Duration, SystemTime};
use tokio::sync::{mpsc, oneshot};
use tracing::{info_span, warn, Instrument};

/// What the products use the camera model for, with a still analyzer.
const USED_FOR: &str = "the analyzer rows (transmittance, extinction ratio, angle offset), the \
                        noise (gain K in DN per electron, offset, read noise) and the scalar \
                        dark level of the products";

/// A set sent for checking: its steps and its frames.
type Checking = (Vec<(u64, StepSpec)>, Vec<u64>);

/// A unit of work between two safe points.
#[derive(Debug, Clone)]
pub(super) enum Unit {
    Single(u64, StepSpec),
    Set(u64, Vec<(u64, StepSpec)>),
}

/// Why a device operation did not give its value.
pub(super) enum OpError {
    Device(DeviceError),
    /// Immediate pause or abort asked while in flight.
    Interrupted,
}

/// Where the loop goes after a unit's safe point.
enum Flow {
    /// Take the unit.
    Take(Unit),
    /// Nothing to take (done by an earlier process, skipped, or put back): the next unit.
    Next,
    /// The run ends.
    End(Outcome),
}

/// The step loop's state beside the [`Core`].
pub(super) struct StepLoop<'a> {
    pub(super) core: Core<'a>,
    pub(super) stage: mpsc::Sender<StageCmd>,
    pub(super) camera: mpsc::Sender<CamCmd>,
    /// The simulated scene's lens cap and clouds (`None` on hardware).
    pub(super) illumination: Option<SceneLight>,
    pub(super) sun_deg: Option<(f64, f64)>,
    /// The camera's noise model (the adaptive planner's dark level).
    camera_model: CameraModel,
    pub(super) pausing: bool,
    /// The exposure and gain the camera is set to.
    pub(super) configured: Option<(f64, f64)>,
    /// Pixels of accepted light frames by index (adaptive runs only).
    pub(super) keep_pixels: bool,
    pub(super) kept: HashMap<u64, Vec<u16>>,
    lens_capped: Option<bool>,
    /// The simulated scene's illumination for light frames (1, or less under a cloud).
    pub(super) light_level: f64,
    /// Suspender verdicts arrived and not yet acted on.
    pub(super) verdicts: VecDeque<Checked>,
    /// The move to the next step's angle, started when the last exposure ended.
    pub(super) pending_move: Option<PendingMove>,
    /// An abort or a detach asked while the run was going: the next safe point (reached at
    /// once, the operation in flight interrupted) ends the run that way instead of pausing.
    pub(super) ending: Option<Control>,
    /// The work list.
    units: VecDeque<Unit>,
    /// Sets sent to the storage thread for their products and verdict.
    checking: BTreeMap<u64, Checking>,
    /// The steps the finished run must have.
    planned_steps: BTreeSet<u64>,
    /// The adaptive planner, its next set and step, and its last set's angles.
    aptd: Option<Aptd>,
    aptd_set: u64,
    aptd_next_step: u64,
    final_angles: Option<Vec<f64>>,
    /// The planner's decisions (replayed and this process's).
    decisions: Vec<Value>,
}

/// A move started ahead of its step (at the end of the previous step's exposure), so that it
/// overlaps that frame's readout, transfer and recording.
pub(super) struct PendingMove {
    /// The commanded angle, degrees as the plan gives it.
    pub(super) angle_deg: f64,
    pub(super) reply: oneshot::Receiver<Result<f64, DeviceError>>,
}

/// Runs (or, with `resume`, continues) a plan that is not `continuous` (module docs).
pub(super) async fn run<A, C>(
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
    let info = rig.camera.info().clone();
    let (width, height) = (info.sensor_width, info.sensor_height);
    plan.check_frame(width, height)?;
    let stage = spawn_stage(rig.analyzer);
    // A new run that starts with a set: the stage goes to its first angle while the store is
    // created (about 30 fsyncs).
    let first_move = if resume || plan.adaptive().is_some() {
        None
    } else {
        first_move(plan, &stage)
    };
    let opening = Opening {
        width,
        height,
        devices: &rig.devices,
        sensor: &rig.sensor,
        camera_model: &rig.camera_model,
        used_for: USED_FOR,
    };
    let (mut core, replay) = Core::open(plan, run_dir, resume, link, opening)?;
    let accepted = core
        .records
        .values()
        .filter(|r| !replay.rejected.contains(&r.index))
        .map(|r| (r.step, r.index))
        .collect();
    core.count_accepted(accepted, plan.max_frames()?);
    let camera = spawn_camera(rig.camera);
    let mut step_loop = StepLoop {
        core,
        stage,
        camera,
        illumination: rig.illumination.clone(),
        sun_deg: rig.sun_deg,
        camera_model: rig.camera_model.clone(),
        pausing: false,
        configured: None,
        keep_pixels: plan.kind() == PlanKind::Adaptive,
        kept: HashMap::new(),
        lens_capped: replay.lens_capped,
        light_level: 1.0,
        verdicts: VecDeque::new(),
        pending_move: first_move,
        ending: None,
        units: VecDeque::new(),
        checking: BTreeMap::new(),
        planned_steps: BTreeSet::new(),
        aptd: None,
        aptd_set: 0,
        aptd_next_step: 0,
        final_angles: None,
        decisions: Vec::new(),
    };
    step_loop.core.set_state(RunState::Running);
    step_loop.plan_work(replay, &rig.target_mask)?;
    drive(step_loop).await
}

/// Sends the stage to a new plan's first angle, if the plan starts with a set taken at once.
fn first_move(plan: &Plan, stage: &mpsc::Sender<StageCmd>) -> Option<PendingMove> {
    let first = plan.steps().ok()?.into_iter().next()?;
    if first.set.is_none() || first.not_before_s.is_some() {
        return None;
    }
    let (tx, reply) = oneshot::channel();
    let cmd = StageCmd::SetAngle {
        psi_rad: first.angle_deg.to_radians(),
        reply: tx,
    };
    stage.try_send(cmd).ok().map(|()| PendingMove {
        angle_deg: first.angle_deg,
        reply,
    })
}

impl<'a> Strategy<'a> for StepLoop<'a> {
    fn core(&mut self) -> &mut Core<'a> {
        &mut self.core
    }

    async fn camera_stream(&mut self) -> Option<CameraStream> {
        let (reply, rx) = oneshot::channel();
        self.camera.send(CamCmd::Stats { reply }).await.ok()?;
        rx.await.ok().map(CameraStream::from)
    }

    async fn acquire(&mut self) -> Result<Option<Outcome>, RunError> {
        loop {
            if let Some(o) = self.take_verdicts().await? {
                return Ok(Some(o));
            }
            let Some(unit) = self.units.pop_front() else {
                if self.checking.is_empty() {
                    return Ok(None);
                }
                self.next_from_store().await?;
                continue;
            };
            let unit = match self.safe_point(unit).await? {
                Flow::Take(unit) => unit,
                Flow::Next => continue,
                Flow::End(o) => return Ok(Some(o)),
            };
            let unit = match self.wait_for_time(unit).await? {
                Flow::Take(unit) => unit,
                Flow::Next => continue,
                Flow::End(o) => return Ok(Some(o)),
            };
            let ended = match unit {
                Unit::Single(step, spec) => self.take_single(step, spec).await?,
                Unit::Set(set, members) => self.take_set(set, members).await?,
            };
            if let Some(o) = ended {
                return Ok(Some(o));
            }
        }
    }

    async fn drain(&mut self) -> Result<(), String> {
        self.drain_frames().await
    }

    fn planned_steps(&self) -> BTreeSet<u64> {
        self.planned_steps.clone()
    }

    fn final_angles(&self) -> Option<Vec<f64>> {
        self.final_angles.clone()
    }

    fn decisions(&self) -> Option<&[Value]> {
        Some(&self.decisions)
    }
}

impl StepLoop<'_> {
    /// The work list from the plan's steps and what the journal says: a set the journal
    /// records as done keeps its frames and products (a resumed run does not check it, nor
    /// write its products, again); an adaptive plan's planner replays its rounds.
    fn plan_work(
        &mut self,
        replay: Replay,
        target_mask: &Option<Vec<bool>>,
    ) -> Result<(), RunError> {
        let plan = self.core.plan;
        let steps = plan.steps()?;
        let skipped = &replay.skipped_sets;
        self.units = units_of(&steps, 0)
            .into_iter()
            .filter(|u| {
                !matches!(u, Unit::Set(set, _) if replay.sets_done.contains_key(set) || skipped.contains(set))
            })
            .collect();
        self.planned_steps = steps
            .iter()
            .enumerate()
            .filter(|(_, s)| !s.set.is_some_and(|set| skipped.contains(&set)))
            .map(|(i, _)| i as u64)
            .collect();
        self.aptd_next_step = steps.len() as u64;
        self.decisions = replay.decisions;
        let Some(a) = plan.adaptive() else {
            return Ok(());
        };
        let core = &self.core;
        let (machine, planned, next) = adaptive_start(
            plan,
            a,
            target_mask,
            &core.records,
            &core.accepted,
            &replay.sets_done,
            &core.reader,
            &steps,
            core.width,
            core.height,
            &self.camera_model,
        )?;
        // Replace the static first set with the replayed state.
        self.units.retain(|u| matches!(u, Unit::Single(..)));
        self.planned_steps = planned;
        match next {
            AdaptiveNext::Acquire(set, members) => {
                self.aptd_set = set;
                self.aptd_next_step = members.last().map_or(self.aptd_next_step, |(s, _)| s + 1);
                self.final_angles = Some(members.iter().map(|(_, s)| s.angle_deg).collect());
                self.units.push_back(Unit::Set(set, members));
            }
            AdaptiveNext::Done(angles) => self.final_angles = Some(angles),
        }
        self.aptd = Some(machine);
        Ok(())
    }

    /// Acts on the verdicts that arrived: a static plan's sets are checked behind the
    /// acquisition of the next ones; an adaptive plan waits for each (its next set depends on
    /// it). A rejected set is taken again, or pauses the run, as the plan says.
    async fn take_verdicts(&mut self) -> Result<Option<Outcome>, RunError> {
        while let Some((set, verdict, mean_dolp)) = self.verdicts.pop_front() {
            let Some((members, frames)) = self.checking.remove(&set) else {
                continue;
            };
            self.core.event(Event::Set {
                set,
                verdict: verdict.clone(),
                mean_s0: verdict.mean_s0_dn,
                mean_dolp,
            });
            if verdict.accepted {
                self.core.sets_accepted += 1;
                self.core.send_store(ToStore::Entry(Entry::Checkpoint {
                    label: format!("set {set} done"),
                    next_step: members.last().map_or(0, |(s, _)| s + 1),
                }))?;
                self.next_adaptive_set(set, &frames)?;
                continue;
            }
            self.core.sets_rejected += 1;
            let n = self.core.rejections.entry(set).or_default();
            *n += 1;
            let tries = *n;
            warn!(set, reason = %verdict.reason, "set rejected");
            for (s, _) in &members {
                self.core.accepted.remove(s);
            }
            let cfg = &self.core.plan.suspender;
            let first = members[0].0;
            self.units.push_front(Unit::Set(set, members));
            if cfg.action == SuspendAction::Pause || tries > cfg.max_reacquire {
                let reason = format!("set {set} rejected {tries} times: {}", verdict.reason);
                if let Some(o) = self.pause(reason, first).await?.ending() {
                    return Ok(Some(o));
                }
            }
        }
        Ok(None)
    }

    /// An adaptive run's planner takes accepted set `set` (its `frames`) and decides: the
    /// next set to take, or done.
    fn next_adaptive_set(&mut self, set: u64, frames: &[u64]) -> Result<(), RunError> {
        let Some(machine) = self.aptd.as_mut() else {
            return Ok(());
        };
        let plan = self.core.plan;
        // Every frame of the set, those an earlier process took (read back from the store)
        // included: the planner sees exactly the set's frames.
        let mut aptd_frames: Vec<AptdFrame> = Vec::with_capacity(frames.len());
        for i in frames {
            let r =
                self.core.records.get(i).ok_or_else(|| {
                    RunError::Check(format!("frame {i} of set {set} has no record"))
                })?;
            let px = match self.kept.remove(i) {
                Some(px) => px,
                None => self.core.reader.read_frame(*i)?,
            };
            aptd_frames.push(aptd_frame(r, &px, &self.camera_model, plan));
        }
        let step = machine
            .on_frames(aptd_frames)
            .map_err(|e| RunError::Planner(e.to_string()))?;
        if let Some(d) = machine.decisions().last() {
            let v = decision_json(d);
            self.core.send_store(ToStore::Entry(Entry::Decision {
                round: d.round as u64,
                decision: v.clone(),
            }))?;
            self.decisions.push(v.clone());
            self.core.event(Event::Decision(v));
        }
        if let AptdStep::Acquire(angles) = step {
            self.aptd_set += 1;
            let members = adaptive_set(plan, self.aptd_set, self.aptd_next_step, &angles);
            self.aptd_next_step += members.len() as u64;
            self.planned_steps.extend(members.iter().map(|(s, _)| *s));
            self.final_angles = Some(members.iter().map(|(_, s)| s.angle_deg).collect());
            self.units.push_back(Unit::Set(self.aptd_set, members));
        }
        Ok(())
    }

    /// The safe point before `unit`: a pause the user asked for; a unit an earlier process
    /// finished has nothing to take (and asks nothing of the operator); darks on hardware
    /// pause for the operator to cap the lens (and light frames after them to uncap it).
    async fn safe_point(&mut self, unit: Unit) -> Result<Flow, RunError> {
        if self.pausing {
            let next = unit_first_step(&unit);
            if let Some(o) = self
                .pause("paused by the user".into(), next)
                .await?
                .ending()
            {
                return Ok(Flow::End(o));
            }
        }
        let finished = match &unit {
            Unit::Single(step, _) => self.core.accepted.contains_key(step),
            Unit::Set(_, members) => members
                .iter()
                .all(|(s, _)| self.core.accepted.contains_key(s)),
        };
        if finished && !matches!(unit, Unit::Set(..)) {
            return Ok(Flow::Next);
        }
        if self.illumination.is_some() || finished {
            return Ok(Flow::Take(unit));
        }
        let wants_dark = matches!(&unit, Unit::Single(_, s) if s.kind == FrameKind::Dark);
        if self.lens_capped == Some(wants_dark) || !(wants_dark || self.lens_capped.is_some()) {
            return Ok(Flow::Take(unit));
        }
        let reason = if wants_dark { CAP_LENS } else { UNCAP_LENS };
        match self.pause(reason.into(), unit_first_step(&unit)).await? {
            AfterPause::Resume => {
                self.lens_capped = Some(wants_dark);
                Ok(Flow::Take(unit))
            }
            AfterPause::Abort(r) => Ok(Flow::End(Outcome::Aborted(r))),
            AfterPause::Detach(r) => {
                self.units.push_front(unit);
                Ok(Flow::End(Outcome::Paused(r)))
            }
        }
    }

    /// Time-lapse: waits for the set's time; a set late by more than half an interval
    /// follows the plan's policy, said in the journal and the store. A pause or an abort
    /// asked during the wait puts the unit back.
    async fn wait_for_time(&mut self, unit: Unit) -> Result<Flow, RunError> {
        let Some(t) = unit_not_before(&unit) else {
            return Ok(Flow::Take(unit));
        };
        let due_ns = self.core.run_start_unix_ns + (t * 1e9) as i64;
        if let (Some(tl), Unit::Set(set, members)) = (self.core.plan.time_lapse(), &unit) {
            let late_s = (now_unix_ns(SystemTime::now()) - due_ns) as f64 * 1e-9;
            if late_s > 0.5 * tl.interval_s {
                let skip = tl.late == crate::plan::LatePolicy::Skip;
                let action = if skip { "skipped" } else { "taken at once" };
                warn!(
                    set,
                    late_s, "time-lapse set {set} is {late_s:.1} s late: {action}"
                );
                self.core.send_store(ToStore::Entry(Entry::SetLate {
                    set: *set,
                    due_unix_ns: due_ns,
                    late_s,
                    action: if skip { "skipped" } else { "taken" }.into(),
                }))?;
                if skip {
                    for (s, _) in members {
                        self.planned_steps.remove(s);
                    }
                    return Ok(Flow::Next);
                }
            }
        }
        let wait_ns = due_ns - now_unix_ns(SystemTime::now());
        if wait_ns <= 0 {
            return Ok(Flow::Take(unit));
        }
        let sleep = tokio::time::sleep(Duration::from_nanos(wait_ns as u64));
        tokio::pin!(sleep);
        loop {
            tokio::select! {
                _ = &mut sleep => return Ok(Flow::Take(unit)),
                c = self.core.link.control.recv() => {
                    let Some(c) = c else {
                        // The controller is gone: nothing can interrupt the wait.
                        (&mut sleep).await;
                        return Ok(Flow::Take(unit));
                    };
                    if self.handle_control(c).is_some() || self.pausing {
                        self.units.push_front(unit);
                        return Ok(Flow::Next);
                    }
                }
            }
        }
    }

    /// Takes a single step's frame; a device error pauses the run.
    async fn take_single(
        &mut self,
        step: u64,
        spec: StepSpec,
    ) -> Result<Option<Outcome>, RunError> {
        if self.core.accepted.contains_key(&step) {
            return Ok(None);
        }
        let span = info_span!("step", step, label = %spec.label);
        let Err(e) = self.acquire_step(step, &spec, None).instrument(span).await else {
            return Ok(None);
        };
        let reason = match e {
            OpError::Interrupted => "paused by the user (immediately)".to_string(),
            OpError::Device(e) => format!("{}: {e}", spec.label),
        };
        self.units.push_front(Unit::Single(step, spec));
        Ok(self.pause(reason, step).await?.ending())
    }

    /// Takes a set's frames (those not taken yet) and sends the set to be checked; a device
    /// error pauses the run and the set is taken again.
    async fn take_set(
        &mut self,
        set: u64,
        members: Vec<(u64, StepSpec)>,
    ) -> Result<Option<Outcome>, RunError> {
        let plan = self.core.plan;
        let mut failed = None;
        // After the set's last frame the stage may go ahead to the next set's first angle,
        // unless a pause or a wait for the set's time comes first.
        let next_set_deg = match self.units.front() {
            Some(u @ Unit::Set(_, next)) if unit_not_before(u).is_none() => next
                .iter()
                .find(|(s, _)| !self.core.accepted.contains_key(s))
                .map(|(_, s)| s.angle_deg),
            _ => None,
        };
        for (i, (step, spec)) in members.iter().enumerate() {
            if self.core.accepted.contains_key(step) {
                continue;
            }
            let next_deg = members[i + 1..]
                .iter()
                .find(|(s, _)| !self.core.accepted.contains_key(s))
                .map(|(_, s)| s.angle_deg)
                .or(if self.pausing { None } else { next_set_deg });
            let span = info_span!("step", step, label = %spec.label);
            // A passing cloud in the middle of a set (simulation).
            if let (Some(_), Some(cloud_set)) = (&self.illumination, plan.simulation.cloud_at_set) {
                let first_try = !self.core.rejections.contains_key(&set);
                let mid = members.len() / 2;
                if set == cloud_set && first_try && members[mid].0 == *step {
                    warn!(set, "simulation: a cloud passes");
                    self.light_level = 1.0 - plan.simulation.cloud_depth;
                }
            }
            let r = self
                .acquire_step(*step, spec, next_deg)
                .instrument(span)
                .await;
            if let Err(e) = r {
                failed = Some((*step, e));
                break;
            }
        }
        self.light_level = 1.0;
        if let Some(light) = &self.illumination {
            light(1.0);
        }
        if let Some((step, e)) = failed {
            let reason = match e {
                OpError::Interrupted => "paused by the user (immediately)".to_string(),
                OpError::Device(e) => format!("set {set}: {e}"),
            };
            self.units.push_front(Unit::Set(set, members));
            return Ok(self.pause(reason, step).await?.ending());
        }
        self.check_set(set, members).await?;
        Ok(None)
    }

    /// Sends a taken set to the storage thread to be checked (overlapping the next set's first
    /// move); an adaptive run waits for the verdict.
    async fn check_set(&mut self, set: u64, members: Vec<(u64, StepSpec)>) -> Result<(), RunError> {
        let frames: Vec<u64> = members
            .iter()
            .filter_map(|(s, _)| self.core.accepted.get(s).copied())
            .collect();
        let job = SetJob {
            set,
            measured_deg: frames
                .iter()
                .map(|i| {
                    self.core
                        .records
                        .get(i)
                        .map_or(f64::NAN, |r| r.measured_angle_deg)
                })
                .collect(),
            commanded_deg: members.iter().map(|(_, s)| s.angle_deg).collect(),
            exposure_us: members[0].1.exposure_us,
            gain_db: members[0].1.gain_db,
            frames: frames.clone(),
            rows: None,
        };
        self.core.send_store(ToStore::ProcessSet(job))?;
        self.checking.insert(set, (members, frames));
        if self.aptd.is_some() {
            while !self.verdicts.iter().any(|v| v.0 == set) {
                self.next_from_store().await?;
            }
        }
        Ok(())
    }
}

/// The units of work of a static plan's steps (consecutive steps of a set form one unit).
pub(super) fn units_of(steps: &[StepSpec], first_step: u64) -> VecDeque<Unit> {
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

pub(super) fn unit_first_step(u: &Unit) -> u64 {
    match u {
        Unit::Single(s, _) => *s,
        Unit::Set(_, m) => m.first().map_or(0, |(s, _)| *s),
    }
}

pub(super) fn unit_not_before(u: &Unit) -> Option<f64> {
    match u {
        Unit::Single(_, s) => s.not_before_s,
        Unit::Set(_, m) => m.first().and_then(|(_, s)| s.not_before_s),
    }
}
