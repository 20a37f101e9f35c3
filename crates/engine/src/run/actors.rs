//! The device actors: the analyzer and the camera, each owned by one local task that takes
//! commands from a bounded channel.

use polar_hal::{Analyzer, Camera, DeviceError, Frame, StreamStats, TriggerMode};
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};
use tracing::Instrument;
use tracing::{info_span, warn};

pub(super) enum StageCmd {
    SetAngle {
        psi_rad: f64,
        reply: oneshot::Sender<Result<f64, DeviceError>>,
    },
}

pub(super) enum CamCmd {
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
    /// The stream's counters.
    Stats { reply: oneshot::Sender<StreamStats> },
}

pub(super) fn spawn_stage<A: Analyzer + 'static>(mut analyzer: A) -> mpsc::Sender<StageCmd> {
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

pub(super) fn spawn_camera<C: Camera + 'static>(mut camera: C) -> mpsc::Sender<CamCmd> {
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
                    CamCmd::Stats { reply } => {
                        let _ = reply.send(camera.stats());
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
