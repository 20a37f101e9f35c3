//! The step loop's state and its device operations: acquire a step (move, grab, record),
//! pause, drain the storage thread; the units of work between safe points.

use super::*;

// ---------------------------------------------------------------------------------------
// The main loop.

/// A set sent for checking: its steps and its frames.
pub(super) type Checking = (Vec<(u64, StepSpec)>, Vec<u64>);

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

pub(super) struct Loop<'a> {
    pub(super) plan: &'a Plan,
    pub(super) link: RunLink,
    pub(super) stage: mpsc::Sender<StageCmd>,
    pub(super) camera: mpsc::Sender<CamCmd>,
    pub(super) to_store: std::sync::mpsc::SyncSender<ToStore>,
    pub(super) from_store: mpsc::UnboundedReceiver<FromStore>,
    pub(super) illumination: Option<super::SceneLight>,
    pub(super) sun_deg: Option<(f64, f64)>,
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) next_index: u64,
    /// Accepted frame index per step.
    pub(super) accepted: BTreeMap<u64, u64>,
    /// Frame records by index (this process and replayed).
    pub(super) records: BTreeMap<u64, FrameRecord>,
    pub(super) in_flight: BTreeSet<u64>,
    pub(super) pausing: bool,
    pub(super) done_frames: u64,
    pub(super) planned_frames: u64,
    pub(super) configured: Option<(f64, f64)>,
    pub(super) retries: u64,
    pub(super) pauses: u64,
    pub(super) sets_accepted: u64,
    pub(super) sets_rejected: u64,
    pub(super) rejections: HashMap<u64, u32>,
    /// Pixels of accepted light frames by index (adaptive runs only).
    pub(super) keep_pixels: bool,
    pub(super) kept: HashMap<u64, Vec<u16>>,
    pub(super) lens_capped: Option<bool>,
    /// The simulated scene's illumination for light frames (1, or less under a cloud).
    pub(super) light_level: f64,
    /// Time spent in device operations (moves and grabs, as the engine waited for them).
    pub(super) device_s: f64,
    /// Suspender verdicts arrived and not yet acted on: set, verdict, mean DoLP.
    pub(super) verdicts: VecDeque<(u64, Verdict, f64)>,
    /// The move to the next step's angle, started when the last exposure ended.
    pub(super) pending_move: Option<PendingMove>,
    /// An abort or a detach asked while the run was going: the next safe point (reached at
    /// once, the operation in flight interrupted) ends the run that way instead of pausing.
    pub(super) ending: Option<Control>,
}

/// A move started ahead of its step (at the end of the previous step's exposure), so that it
/// overlaps that frame's readout, transfer and recording.
pub(super) struct PendingMove {
    /// The commanded angle, degrees as the plan gives it.
    pub(super) angle_deg: f64,
    pub(super) reply: oneshot::Receiver<Result<f64, DeviceError>>,
}

impl Loop<'_> {
    pub(super) fn set_state(&self, s: RunState) {
        self.link.set_state(s);
    }

    pub(super) fn event(&self, e: Event) {
        let _ = self.link.events.try_send(e);
    }

    pub(super) fn send_store(&self, msg: ToStore) -> Result<(), RunError> {
        send_store(&self.to_store, msg)
    }

    pub(super) fn handle_control(&mut self, c: Control) -> Option<OpError> {
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
                self.ending = Some(c);
                Some(OpError::Interrupted)
            }
            Control::Resume => None,
        }
    }

    /// Runs `fut`, watching the control channel: a pause request is noted, an immediate
    /// pause or an abort interrupts.
    pub(super) async fn watch<T, F>(&mut self, fut: F) -> Result<T, OpError>
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

    pub(super) fn on_store(&mut self, msg: FromStore) -> Result<(), String> {
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
    pub(super) async fn next_from_store(&mut self) -> Result<(), RunError> {
        match self.from_store.recv().await {
            Some(msg) => self.on_store(msg).map_err(RunError::Storage),
            None => Err(RunError::Storage("the storage thread stopped".into())),
        }
    }

    /// Waits until every frame sent is durable.
    pub(super) async fn drain(&mut self) -> Result<(), String> {
        while !self.in_flight.is_empty() {
            match self.from_store.recv().await {
                Some(msg) => self.on_store(msg)?,
                None => return Err("the storage thread stopped".into()),
            }
        }
        Ok(())
    }

    /// Pauses with `reason` and waits for the controller.
    pub(super) async fn pause(
        &mut self,
        reason: String,
        next_step: u64,
    ) -> Result<AfterPause, RunError> {
        // After a pause the stage is commanded afresh: whatever happened to it meanwhile, the
        // next step's angle is measured by its own move.
        self.pending_move = None;
        if let Err(e) = self.drain().await {
            warn!("while pausing: {e}");
        }
        self.pausing = false;
        match self.ending.take() {
            Some(Control::Abort) => return Ok(AfterPause::Abort("aborted by the user".into())),
            Some(Control::Detach) => return Ok(AfterPause::Detach("detached by the user".into())),
            _ => {}
        }
        self.pauses += 1;
        hold_paused(&mut self.link, &self.to_store, &reason, next_step).await
    }

    /// Takes one step's frame (with the plan's retries); the frame goes to storage. `next_deg`
    /// is the angle of the step that will follow, if known: the stage starts moving there as
    /// soon as the camera reports this step's exposure ended.
    pub(super) async fn acquire(
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
            light(if spec.kind == FrameKind::Dark {
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

    pub(super) async fn try_acquire(
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

    pub(super) fn record(
        &self,
        index: u64,
        step: u64,
        spec: &StepSpec,
        measured_deg: f64,
        frame: &Frame,
    ) -> FrameRecord {
        frame_record(
            (index, step, spec),
            frame,
            FrameSpan::settled(measured_deg),
            self.sun_deg,
            self.plan.site.as_ref(),
        )
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
