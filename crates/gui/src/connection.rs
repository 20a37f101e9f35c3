//! Devices connected from the device panel (not held by a run): connecting them, their
//! status, the panel's device commands, and the worker's end of the reply channel.

use crate::messages::{Command, DeviceStatus, Devices, Reply, Snapshot};
use polar_drivers::any::AnyRotator;
use polar_engine::plan::Plan;
use polar_engine::run::Rig;
use polar_hal::camera::{Camera, TriggerMode};
use polar_hal::{Analyzer, DeviceError, OnRotator, Rotator};
use polar_rig::SimRig;
use polar_rig::{connect_hardware_for, HardwareRig};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::sync::mpsc;

/// The worker's end of the reply channel.
pub(crate) struct Out {
    pub(crate) tx: mpsc::Sender<Reply>,
    pub(crate) wake: Option<Box<dyn Fn() + Send>>,
}

impl Out {
    pub(crate) async fn send(&self, r: Reply) -> bool {
        let ok = self.tx.send(r).await.is_ok();
        if let Some(w) = &self.wake {
            w();
        }
        ok
    }

    /// Sends `r` if there is room, else drops it (for the run's loop, which must not wait).
    pub(crate) fn note(&self, r: Reply) {
        let _ = self.tx.try_send(r);
        if let Some(w) = &self.wake {
            w();
        }
    }
}

/// Devices connected from the device panel (not held by a run).
pub(crate) struct Connected {
    /// The simulated devices' servers (`None` on hardware).
    pub(crate) sim: Option<SimRig>,
    /// A hardware rig's simulated stage (its port `sim`).
    stage_sim: Option<polar_hil_mocks::serve::SimServer>,
    pub(crate) rig: HardwareRig,
    /// The `[simulation]` section and plan folder the simulated rig was built from.
    pub(crate) built_from: Option<(polar_engine::plan::Simulation, PathBuf)>,
    /// The folder of the simulated stage's pseudo-terminal link (removed on release).
    pub(crate) link_dir: Option<PathBuf>,
}

impl Connected {
    /// Lets the devices go (a simulated rig shuts down).
    pub(crate) async fn release(self) {
        drop(self.rig);
        if let Some(sim) = self.sim {
            sim.shutdown().await;
        }
        if let Some(stage) = self.stage_sim {
            stage.shutdown().await;
        }
        if let Some(d) = self.link_dir {
            // Only if empty: the link is gone with the server.
            let _ = std::fs::remove_dir(d);
        }
    }
}

impl Connected {
    /// The status, reading the stage's position.
    pub(crate) async fn status(&mut self, last: String) -> DeviceStatus {
        let info = self.rig.camera.info().clone();
        let mut st = DeviceStatus {
            connected: true,
            description: format!(
                "stage: {}; camera: {} {} ({}x{})",
                self.rig.analyzer.rotator.info().model,
                info.vendor,
                info.model,
                info.sensor_width,
                info.sensor_height
            ),
            exposure_range_us: Some(info.exposure_range_us),
            gain_range: Some(info.gain_range),
            last,
            ..DeviceStatus::default()
        };
        match self.rig.analyzer.rotator.position_rad().await {
            Ok(stage_rad) => {
                st.stage_deg = Some(stage_rad.to_degrees());
                let psi = (stage_rad - self.rig.analyzer.zero_offset_rad)
                    .rem_euclid(std::f64::consts::PI);
                st.analyzer_deg = Some(psi.to_degrees());
            }
            Err(e) => st.error = Some(e.to_string()),
        }
        st
    }
}

/// What the camera applied, and what was asked where it differs (a camera rounds to its
/// steps or keeps to its range): the panel then shows the applied value.
fn applied(what: &str, got: f64, asked: f64, unit: &str) -> String {
    if (got - asked).abs() <= 1e-9 * asked.abs().max(1.0) {
        format!("{what} {got:.1}{unit}")
    } else {
        format!("{what} {got:.1}{unit} (asked {asked:.1}{unit})")
    }
}

/// Carries out a device command on `c`; the status after it (with the error, if any).
pub(crate) async fn device_command(
    c: &mut Connected,
    cmd: &Command,
    settings: &mut (Option<f64>, Option<f64>),
) -> (DeviceStatus, Option<Snapshot>) {
    let mut snapshot = None;
    let r: Result<String, DeviceError> = async {
        match *cmd {
            Command::Home => {
                c.rig.analyzer.rotator.home().await?;
                Ok("homed".to_string())
            }
            Command::MoveAnalyzer { angle_deg } => {
                let got = c.rig.analyzer.set_angle(angle_deg.to_radians()).await?;
                Ok(format!(
                    "analyzer at {:.3} deg (asked {angle_deg:.3})",
                    got.to_degrees()
                ))
            }
            Command::SetExposure { exposure_us } => {
                let e = c.rig.camera.set_exposure_us(exposure_us).await?;
                settings.0 = Some(e);
                Ok(applied("exposure", e, exposure_us, " us"))
            }
            Command::SetGain { gain } => {
                let g = c.rig.camera.set_gain(gain).await?;
                settings.1 = Some(g);
                Ok(applied("gain", g, gain, ""))
            }
            Command::Snapshot => {
                let cam = &mut c.rig.camera;
                cam.set_trigger(TriggerMode::Software).await?;
                cam.start().await?;
                let grabbed = async {
                    cam.trigger().await?;
                    cam.grab(Duration::from_secs(5)).await
                }
                .await;
                let stopped = cam.stop().await;
                let f = grabbed?;
                stopped?;
                settings.0 = Some(f.exposure_us);
                settings.1 = Some(f.gain);
                let text = format!(
                    "frame {} ({}x{}), mean {:.1} DN",
                    f.frame_id,
                    f.width,
                    f.height,
                    f.mean()
                );
                snapshot = Some(Snapshot {
                    width: f.width,
                    height: f.height,
                    pixels: f.pixels,
                    exposure_us: f.exposure_us,
                    frame_id: f.frame_id,
                });
                Ok(text)
            }
            _ => Ok(String::new()),
        }
    }
    .await;
    let (last, err) = match r {
        Ok(l) => (l, None),
        Err(e) => (format!("{cmd:?} failed"), Some(e.to_string())),
    };
    let mut st = c.status(last).await;
    st.exposure_us = settings.0;
    st.gain = settings.1;
    if err.is_some() {
        st.error = err;
    }
    (st, snapshot)
}

/// Connects `devices`: on hardware the rig `polarimeter run` would use; simulated, the rig
/// of `plan`'s `[simulation]` section (its pseudo-terminal link under `link_dir`, its noise
/// stream `noise_stream`).
pub(crate) async fn connect(
    devices: &Devices,
    plan: &Plan,
    plan_dir: &Path,
    link_dir: &Path,
    noise_stream: u64,
) -> Result<Connected, String> {
    match devices {
        Devices::Hardware(hw) => {
            let c = connect_hardware_for(hw, plan)
                .await
                .map_err(|e| e.to_string())?;
            Ok(Connected {
                sim: None,
                stage_sim: c.simulator,
                rig: c.rig,
                built_from: None,
                link_dir: None,
            })
        }
        Devices::Simulated => {
            // Each connection draws its own noise stream, and one connection's frame ids
            // keep counting over its runs, so no draw repeats.
            let (sim, r) = SimRig::start_rig(plan, plan_dir, link_dir, noise_stream)
                .await
                .map_err(|e| format!("simulated rig: {e}"))?;
            let rig = Rig {
                analyzer: OnRotator {
                    rotator: AnyRotator::new(r.analyzer.rotator),
                    zero_offset_rad: r.analyzer.zero_offset_rad,
                    approach: r.analyzer.approach,
                    overshoot_rad: r.analyzer.overshoot_rad,
                },
                camera: r.camera,
                camera_model: r.camera_model,
                sensor: r.sensor,
                illumination: r.illumination,
                target_mask: r.target_mask,
                sun_deg: r.sun_deg,
                devices: r.devices,
                spin_acceleration_rad_per_s2: r.spin_acceleration_rad_per_s2,
            };
            Ok(Connected {
                sim: Some(sim),
                stage_sim: None,
                rig,
                built_from: Some((plan.simulation.clone(), plan_dir.to_path_buf())),
                link_dir: Some(link_dir.to_path_buf()),
            })
        }
    }
}

pub(crate) fn disconnected(description: &str, last: &str, error: Option<String>) -> DeviceStatus {
    DeviceStatus {
        description: description.into(),
        last: last.into(),
        error,
        ..DeviceStatus::default()
    }
}
