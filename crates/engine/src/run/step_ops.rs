//! The step loop's device operations: a step's move, the camera's configuration and its
//! grab (with the plan's retries), each watching the controller and the storage thread; the
//! step loop's pause.

use super::actors::{CamCmd, StageCmd};
use super::link::{Control, Event, RunState};
use super::outcome::RunError;
use super::pause::AfterPause;
use super::record::{frame_record, FrameSpan};
use super::step_loop::{OpError, PendingMove, StepLoop};
use super::writer::{FromStore, ToStore};
use crate::plan::StepSpec;
use crate::{FrameKind, FrameRecord};
use polar_hal::{DeviceError, ErrorKind, Frame};
use std::time::{Duration, Instant};
use tokio::sync::oneshot;
use tracing::{info, warn};

impl StepLoop<'_> {
    pub(super) fn handle_control(&mut self, c: Control) -> Option<OpError> {
        match c {
            Control::Pause => {
                if !self.pausing {
                    self.pausing = true;
                    self.core.set_state(RunState::Pausing);
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
                c = self.core.link.control.recv() => {
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
                Some(msg) = self.core.from_store.recv() => {
                    if let Err(e) = self.on_store(msg) {
                        return Err(OpError::Device(DeviceError::new(ErrorKind::Other, "storage", e)));
                    }
                }
            }
        }
    }

    /// Takes a message of the storage thread (a checked set waits in `verdicts`).
    pub(super) fn on_store(&mut self, msg: FromStore) -> Result<(), String> {
        if let Some(checked) = self.core.on_store(msg)? {
            self.verdicts.push_back(checked);
        }
        Ok(())
    }

    /// Waits for the next message from the storage thread.
    pub(super) async fn next_from_store(&mut self) -> Result<(), RunError> {
        match self.core.from_store.recv().await {
            Some(msg) => self.on_store(msg).map_err(RunError::Storage),
            None => Err(RunError::Storage("the storage thread stopped".into())),
        }
    }

    /// Waits until every frame sent is durable.
    pub(super) async fn drain_frames(&mut self) -> Result<(), String> {
        while !self.core.in_flight.is_empty() {
            match self.core.from_store.recv().await {
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
        if let Err(e) = self.drain_frames().await {
            warn!("while pausing: {e}");
        }
        self.pausing = false;
        match self.ending.take() {
            Some(Control::Abort) => return Ok(AfterPause::Abort("aborted by the user".into())),
            Some(Control::Detach) => return Ok(AfterPause::Detach("detached by the user".into())),
            _ => {}
        }
        self.core.hold(&reason, next_step).await
    }

    /// Takes one step's frame (with the plan's retries); the frame goes to storage. `next_deg`
    /// is the angle of the step that will follow, if known: the stage starts moving there as
    /// soon as the camera reports this step's exposure ended.
    pub(super) async fn acquire_step(
        &mut self,
        step: u64,
        spec: &StepSpec,
        next_deg: Option<f64>,
    ) -> Result<u64, OpError> {
        let policy = &self.core.plan.policy;
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
                    let index = self.core.next_index;
                    self.core.next_index += 1;
                    let record = self.record(index, step, spec, measured_deg, &frame);
                    self.core.records.insert(index, record.clone());
                    self.core.accepted.insert(step, index);
                    if self.keep_pixels && spec.kind == FrameKind::Light {
                        self.kept.insert(index, frame.pixels.clone());
                    }
                    self.core.in_flight.insert(index);
                    let msg = ToStore::Frame {
                        record,
                        pixels: frame.pixels,
                    };
                    // The bounded channel: waits (off the loop's thread) only when two frames
                    // are already queued.
                    if self.core.send_store_async(msg).await.is_err() {
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
                    self.core.retries += 1;
                    let msg = format!("{} (attempt {attempt} of {attempts}): {e}", spec.label);
                    warn!("{msg}");
                    self.core.event(Event::Retry(msg));
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

    /// One attempt at a step: the move (with its readback), the camera's exposure and gain
    /// if they change, and the grab; returns the measured angle, degrees in `[0, 180)`, and
    /// the frame.
    pub(super) async fn try_acquire(
        &mut self,
        spec: &StepSpec,
        next_deg: Option<f64>,
        move_deadline: Duration,
        grab_deadline: Duration,
    ) -> Result<(f64, Frame), OpError> {
        let t0 = Instant::now();
        let measured = self.move_to(spec, move_deadline).await?;
        self.configure(spec).await?;
        let t1 = Instant::now();
        let frame = self.grab(next_deg, grab_deadline, t1).await?;
        let (move_s, grab_s) = ((t1 - t0).as_secs_f64(), t1.elapsed().as_secs_f64());
        self.core.device_s += move_s + grab_s;
        tracing::debug!(
            move_ms = move_s * 1e3,
            grab_ms = grab_s * 1e3,
            "step timing"
        );
        Ok((measured.to_degrees().rem_euclid(180.0), frame))
    }

    /// Moves the analyzer to the step's angle (or takes the move started ahead to it) and
    /// returns the angle read back, radians.
    async fn move_to(&mut self, spec: &StepSpec, move_deadline: Duration) -> Result<f64, OpError> {
        let stage = self.stage.clone();
        let psi = spec.angle_deg.to_radians();
        // A move started ahead to this angle is this step's move; one to another angle (a retry
        // of the previous step, a set taken again) is left to finish, and the stage actor
        // runs this step's move after it.
        let ahead = self
            .pending_move
            .take()
            .filter(|p| p.angle_deg == spec.angle_deg)
            .map(|p| p.reply);
        self.watch(async move {
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
        .await
    }

    /// Sets the camera's exposure and gain to the step's, when they differ from the last.
    async fn configure(&mut self, spec: &StepSpec) -> Result<(), OpError> {
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
        Ok(())
    }

    /// Grabs the step's frame (of the store's size). When the camera reports the exposure's
    /// end and `next_deg` is known, the next step's move starts then, overlapping this frame's
    /// readout, transfer and recording.
    async fn grab(
        &mut self,
        next_deg: Option<f64>,
        grab_deadline: Duration,
        t1: Instant,
    ) -> Result<Frame, OpError> {
        let cam = self.camera.clone();
        let (w, h) = (self.core.width, self.core.height);
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
        self.watch(async move {
            let f = frame_rx
                .await
                .map_err(|_| DeviceError::new(ErrorKind::Disconnected, "camera", "actor gone"))??;
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
        .await
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
            self.core.plan.site.as_ref(),
        )
    }
}
