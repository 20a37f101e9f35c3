//! The live modes' device loop, on the engine's worker thread (the UI only ever reads its
//! replies).
//!
//! * Live: the camera runs free; every frame counts towards the frame rate, and at most about
//!   25 a second go to the UI with their histogram ([`crate::live::frame_stats`]). Exposure
//!   and gain may be changed while it streams.
//! * Live polarimetry: the stage spins at the set speed and its position-compare trigger fires
//!   `frames_per_half_turn` pulses per half turn, at stage angles that are whole multiples of
//!   the pulse interval from the datum (so every half turn has its frames at the same
//!   angles). Each pulse reports its latched encoder angle and the controller's clock. The
//!   camera exposes on each pulse: wired (hardware trigger), the exposure starts at the
//!   pulse, so its span is `[pulse, pulse + speed x exposure]`; otherwise it is triggered in
//!   software and its end is the camera's exposure-end event. The controller's clock is
//!   mapped onto the host's by the smallest host-minus-controller difference seen over the
//!   pulses (the pulse that reached the host quickest), and the speed is measured between
//!   consecutive pulses, so the span's end is `pulse angle + speed x (end - pulse time)`. A
//!   stage with velocity mode but no trigger output is read for its position before each
//!   exposure instead (the read's midpoint taken as its time). Every half turn with all its
//!   frames is estimated ([`crate::live::estimate_half_turn`]); one missing a frame is
//!   dropped.

use crate::connection::{Connected, Out};
use crate::forecast::compute_forecast;
use crate::live::{
    estimate_half_turn, frame_stats, noise_and_dark, HalfTurn, LiveFrame, LiveMode, LiveUpdate,
    RateMeter, SpinSettings, LIVE_HIST_BINS,
};
use crate::messages::{Command, DeviceStatus, Reply};
use polar_hal::camera::{Camera, TriggerMode};
use polar_hal::{ErrorKind, Rotator};
use std::collections::VecDeque;
use std::path::Path;
use std::rc::Rc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// Least time between two frames sent to the UI (about 25 a second).
const SHOW_EVERY: Duration = Duration::from_millis(40);

/// How long the stage spins before the first exposure, seconds (its ramp to speed is shorter).
const RUN_UP_S: f64 = 1.0;

/// Half turns one arming of the trigger covers.
const ARMED_HALF_TURNS: u32 = 10_000;

/// What arrived while a live mode ran.
struct Incoming {
    /// Stop the mode.
    stop: bool,
    /// A camera setting to apply now (live camera mode).
    apply: Vec<Command>,
}

/// Takes the commands waiting (never waits). Stop ends the mode; Start, Connect and
/// Disconnect end it too and are left for the worker's main loop (in `deferred`, with a plan
/// folder change); device commands that would move the stage or need the camera are refused.
fn take_commands(
    commands: &mut mpsc::Receiver<Command>,
    out: &Rc<Out>,
    deferred: &mut VecDeque<Command>,
    plan_dir: &Path,
    mode: LiveMode,
    status: &DeviceStatus,
) -> Incoming {
    let mut inc = Incoming {
        stop: false,
        apply: Vec::new(),
    };
    loop {
        let cmd = match commands.try_recv() {
            Ok(c) => c,
            Err(mpsc::error::TryRecvError::Empty) => break,
            Err(mpsc::error::TryRecvError::Disconnected) => {
                // The UI is gone.
                inc.stop = true;
                break;
            }
        };
        match cmd {
            Command::LiveStop => inc.stop = true,
            Command::LiveStart { .. } => {
                out.note(Reply::Log(format!("{} is already running", mode.label())));
            }
            Command::Forecast { plan_text } => {
                let (o, dir) = (out.clone(), plan_dir.to_path_buf());
                tokio::task::spawn_local(async move {
                    let f = compute_forecast(plan_text, dir).await;
                    o.send(Reply::Forecast(f)).await;
                });
            }
            Command::Control(c) => out.note(Reply::Log(format!("{c:?}: no run in progress"))),
            Command::PlanDir(_) => deferred.push_back(cmd),
            Command::Start { .. } | Command::Connect { .. } | Command::Disconnect => {
                inc.stop = true;
                deferred.push_back(cmd);
            }
            Command::SetExposure { .. } | Command::SetGain { .. } if mode == LiveMode::Camera => {
                inc.apply.push(cmd);
            }
            Command::Home
            | Command::MoveAnalyzer { .. }
            | Command::Snapshot
            | Command::SetExposure { .. }
            | Command::SetGain { .. } => {
                out.note(Reply::Devices(DeviceStatus {
                    error: Some(format!("{cmd:?}: stop {} first", mode.label())),
                    last: String::new(),
                    ..status.clone()
                }));
            }
        }
    }
    inc
}

/// Runs `mode` on `c` until Stop (or a command that ends it, or an error); returns the
/// commands left for the main loop, in order. `settings` are the exposure and gain last
/// applied.
pub(crate) async fn run_live(
    c: &mut Connected,
    mode: LiveMode,
    spin: SpinSettings,
    commands: &mut mpsc::Receiver<Command>,
    out: &Rc<Out>,
    settings: &mut (Option<f64>, Option<f64>),
    plan_dir: &Path,
) -> VecDeque<Command> {
    let mut deferred = VecDeque::new();
    let mut status = c.status(String::new()).await;
    status.exposure_us = settings.0;
    status.gain = settings.1;
    let io = Io {
        commands,
        out,
        deferred: &mut deferred,
        plan_dir,
        status: &status,
    };
    let r = match mode {
        LiveMode::Camera => camera_loop(c, io, settings).await,
        LiveMode::Polarimetry => polarimetry_loop(c, io, spin, settings).await,
    };
    out.send(Reply::Live(LiveUpdate::Stopped {
        mode,
        error: r.err(),
    }))
    .await;
    deferred
}

/// The worker's channels while a mode runs.
struct Io<'a> {
    commands: &'a mut mpsc::Receiver<Command>,
    out: &'a Rc<Out>,
    deferred: &'a mut VecDeque<Command>,
    plan_dir: &'a Path,
    status: &'a DeviceStatus,
}

impl Io<'_> {
    fn take(&mut self, mode: LiveMode) -> Incoming {
        take_commands(
            self.commands,
            self.out,
            self.deferred,
            self.plan_dir,
            mode,
            self.status,
        )
    }
}

async fn camera_loop(
    c: &mut Connected,
    mut io: Io<'_>,
    settings: &mut (Option<f64>, Option<f64>),
) -> Result<(), String> {
    let cam = &mut c.rig.camera;
    cam.set_trigger(TriggerMode::FreeRun)
        .await
        .map_err(|e| e.to_string())?;
    cam.start().await.map_err(|e| e.to_string())?;
    io.out
        .send(Reply::Live(LiveUpdate::Started {
            mode: LiveMode::Camera,
            note: "Live: the camera runs free, the analyzer stays still".into(),
        }))
        .await;
    let t0 = Instant::now();
    let mut meter = RateMeter::default();
    let mut frames = 0u64;
    let mut shown: Option<Instant> = None;
    let result = loop {
        let inc = io.take(LiveMode::Camera);
        if inc.stop {
            break Ok(());
        }
        if !inc.apply.is_empty() {
            let cam = &mut c.rig.camera;
            let applied: Result<String, String> = async {
                cam.stop().await.map_err(|e| e.to_string())?;
                let mut last = String::new();
                for cmd in &inc.apply {
                    match *cmd {
                        Command::SetExposure { exposure_us } => {
                            let e = cam
                                .set_exposure_us(exposure_us)
                                .await
                                .map_err(|e| e.to_string())?;
                            settings.0 = Some(e);
                            last = format!("exposure {e:.1} us");
                        }
                        Command::SetGain { gain } => {
                            let g = cam.set_gain(gain).await.map_err(|e| e.to_string())?;
                            settings.1 = Some(g);
                            last = format!("gain {g:.2}");
                        }
                        _ => {}
                    }
                }
                cam.start().await.map_err(|e| e.to_string())?;
                Ok(last)
            }
            .await;
            let (last, error) = match applied {
                Ok(l) => (l, None),
                Err(e) => ("setting the camera failed".to_string(), Some(e)),
            };
            io.out
                .send(Reply::Devices(DeviceStatus {
                    exposure_us: settings.0,
                    gain: settings.1,
                    last,
                    error: error.clone(),
                    ..io.status.clone()
                }))
                .await;
            if let Some(e) = error {
                break Err(e);
            }
        }
        let cam = &mut c.rig.camera;
        let wait = Duration::from_secs_f64((2e-6 * settings.0.unwrap_or(0.0)).max(0.2));
        match cam.grab(wait).await {
            Ok(f) => {
                frames += 1;
                meter.push(t0.elapsed().as_secs_f64());
                if shown.is_none_or(|t| t.elapsed() >= SHOW_EVERY) {
                    shown = Some(Instant::now());
                    let (noise, _) = noise_and_dark(&c.rig.camera_model, f.gain, f.exposure_us);
                    let stats = frame_stats(
                        &f.pixels,
                        f.format.max_value(),
                        noise.saturation_dn,
                        LIVE_HIST_BINS,
                    );
                    io.out
                        .note(Reply::Live(LiveUpdate::Frame(Box::new(LiveFrame {
                            width: f.width,
                            height: f.height,
                            pixels: f.pixels,
                            frame_id: f.frame_id,
                            exposure_us: f.exposure_us,
                            stats,
                            rate_hz: meter.rate_hz(),
                            frames,
                        }))));
                }
            }
            Err(e) if e.kind() == ErrorKind::Timeout => {}
            Err(e) => break Err(e.to_string()),
        }
    };
    let stopped = c.rig.camera.stop().await.map_err(|e| e.to_string());
    result.and(stopped)
}

/// Where the stage was at a host time: a pulse (or a position read) and the speed.
#[derive(Debug, Clone, Copy)]
struct Anchor {
    /// Stage angle, radians, unwrapped.
    angle_rad: f64,
    /// Host time, seconds from the loop's start.
    host_s: f64,
    /// The pulse's index (trigger) or the frame's count (position reads).
    index: u64,
}

/// Maps the controller's clock onto the host's from the pulses (module doc).
#[derive(Debug, Default)]
struct PulseClock {
    /// The first pulse's controller time, microseconds.
    first_us: Option<u32>,
    /// The smallest host-minus-controller time seen, seconds.
    offset_s: f64,
    /// The last pulse: controller seconds since the first, angle.
    last: Option<(f64, f64)>,
}

impl PulseClock {
    /// A pulse latched at `angle_rad`, controller time `device_us`, read on the host at
    /// `host_s`: its host time and the speed since the previous pulse (if measurable).
    fn pulse(&mut self, device_us: u32, angle_rad: f64, host_s: f64) -> (f64, Option<f64>) {
        let first = *self.first_us.get_or_insert(device_us);
        let dev_s = f64::from(device_us.wrapping_sub(first)) * 1e-6;
        if self.last.is_none() {
            self.offset_s = host_s - dev_s;
        }
        self.offset_s = self.offset_s.min(host_s - dev_s);
        let speed = self.last.and_then(|(t, a)| {
            let dt = dev_s - t;
            (dt > 0.0).then(|| (angle_rad - a) / dt)
        });
        self.last = Some((dev_s, angle_rad));
        (dev_s + self.offset_s, speed)
    }
}

async fn polarimetry_loop(
    c: &mut Connected,
    mut io: Io<'_>,
    spin: SpinSettings,
    settings: &mut (Option<f64>, Option<f64>),
) -> Result<(), String> {
    let exposure_us = settings
        .0
        .ok_or("exposure_us: not set yet: set the exposure first (Set exposure)")?;
    spin.check(exposure_us)?;
    let gain_db = settings.1.unwrap_or(0.0);
    let rig = &mut c.rig;
    let support = rig.analyzer.rotator.continuous_support();
    if !support.can_spin() {
        return Err(format!(
            "live polarimetry needs a stage that spins: {} offers continuous rotation \
             \"{support}\"",
            rig.analyzer.rotator.info().model
        ));
    }
    let hardware = spin.hardware_trigger;
    if hardware && !(support.can_trigger() && rig.camera.supports_hardware_trigger()) {
        return Err(format!(
            "camera trigger wired to stage: needs the stage's trigger output (it offers \
             \"{support}\") and the camera's hardware trigger (offered: {})",
            rig.camera.supports_hardware_trigger()
        ));
    }
    let mode = if hardware {
        TriggerMode::Hardware
    } else {
        TriggerMode::Software
    };
    rig.camera
        .set_trigger(mode)
        .await
        .map_err(|e| e.to_string())?;
    rig.camera.start().await.map_err(|e| e.to_string())?;
    let omega = spin.speed_deg_per_s.to_radians();
    let started = match rig.analyzer.rotator.spin(omega).await {
        Ok(()) => spin_and_estimate(c, &mut io, spin, exposure_us, gain_db).await,
        Err(e) => Err(e.to_string()),
    };
    let rig = &mut c.rig;
    let cam = rig.camera.stop().await.map_err(|e| e.to_string());
    let stage = rig
        .analyzer
        .rotator
        .stop_spin()
        .await
        .map(|_| ())
        .map_err(|e| e.to_string());
    if support.can_trigger() {
        // Disarm (no pulses left over for the next arming).
        let _ = rig.analyzer.rotator.arm_trigger(0.0, 0.0, 0).await;
    }
    started.and(cam).and(stage)
}

async fn spin_and_estimate(
    c: &mut Connected,
    io: &mut Io<'_>,
    spin: SpinSettings,
    exposure_us: f64,
    gain_db: f64,
) -> Result<(), String> {
    let n = u64::from(spin.frames_per_half_turn);
    let commanded = spin.speed_deg_per_s.to_radians();
    let step = std::f64::consts::PI / n as f64;
    let exposure_s = exposure_us * 1e-6;
    let rig = &mut c.rig;
    let trigger = rig.analyzer.rotator.continuous_support().can_trigger();
    let hardware = spin.hardware_trigger;
    let t0 = Instant::now();
    let now_s = move || t0.elapsed().as_secs_f64();
    let position = rig
        .analyzer
        .rotator
        .spin_position_rad()
        .await
        .map_err(|e| e.to_string())?;
    if trigger {
        let first = ((position + commanded * RUN_UP_S) / step).ceil() * step;
        rig.analyzer
            .rotator
            .arm_trigger(first, step, spin.frames_per_half_turn * ARMED_HALF_TURNS)
            .await
            .map_err(|e| e.to_string())?;
    } else {
        tokio::time::sleep(Duration::from_secs_f64(RUN_UP_S)).await;
    }
    let timing = match (trigger, hardware) {
        (true, true) => "hardware trigger at each encoder pulse; span from the pulse",
        (true, false) => {
            "software trigger on each encoder pulse; span end from the exposure-end event \
             against the pulse clock"
        }
        (false, _) => {
            "no trigger output: software trigger; span end from the exposure-end event \
             against a position read (timestamps)"
        }
    };
    io.out
        .send(Reply::Live(LiveUpdate::Started {
            mode: LiveMode::Polarimetry,
            note: format!(
                "Live polarimetry: {:.1} deg/s, {} frames per half turn, exposure {exposure_us:.1} \
                 us; {timing}",
                spin.speed_deg_per_s, spin.frames_per_half_turn
            ),
        }))
        .await;
    let zero = rig.analyzer.zero_offset_rad;
    let (width, height) = (
        rig.camera.info().sensor_width,
        rig.camera.info().sensor_height,
    );
    let mut clock = PulseClock::default();
    let mut speed = commanded;
    let mut group: Vec<(Vec<u16>, (f64, f64))> = Vec::with_capacity(n as usize);
    let mut group_half: Option<u64> = None;
    let mut estimated = 0u64;
    let mut meter = RateMeter::default();
    let mut counter = 0u64;
    let mut next_s = now_s();
    let interval_s = spin.frame_interval_s();
    let wait = Duration::from_secs_f64(3.0 * interval_s + exposure_s + RUN_UP_S + 2.0);
    loop {
        if io.take(LiveMode::Polarimetry).stop {
            return Ok(());
        }
        let rig = &mut c.rig;
        let anchor = if trigger {
            let p = rig
                .analyzer
                .rotator
                .next_trigger(wait)
                .await
                .map_err(|e| e.to_string())?;
            let (host_s, measured) = clock.pulse(p.device_time_us, p.angle_rad, now_s());
            if let Some(s) = measured {
                speed = s;
            }
            Anchor {
                angle_rad: p.angle_rad,
                host_s,
                index: u64::from(p.index),
            }
        } else {
            next_s += interval_s;
            tokio::time::sleep(Duration::from_secs_f64((next_s - now_s()).max(0.0))).await;
            let a = now_s();
            let angle_rad = rig
                .analyzer
                .rotator
                .spin_position_rad()
                .await
                .map_err(|e| e.to_string())?;
            let b = now_s();
            counter += 1;
            Anchor {
                angle_rad,
                host_s: 0.5 * (a + b),
                index: counter - 1,
            }
        };
        let cam = &mut rig.camera;
        let ended = if hardware {
            None
        } else {
            cam.trigger().await.map_err(|e| e.to_string())?;
            cam.exposure_end(wait).await.map_err(|e| e.to_string())?
        };
        let end_s = now_s();
        let frame = cam.grab(wait).await.map_err(|e| e.to_string())?;
        let arrived_s = now_s();
        let stage_span = if hardware {
            (anchor.angle_rad, anchor.angle_rad + speed * exposure_s)
        } else {
            let end_host = if ended.is_some() { end_s } else { arrived_s };
            let end = anchor.angle_rad + speed * (end_host - anchor.host_s);
            (end - speed * exposure_s, end)
        };
        let half = anchor.index / n;
        if group_half != Some(half) {
            group.clear();
            group_half = Some(half);
        }
        if ended.is_some_and(|id| id != frame.frame_id) {
            io.out.note(Reply::Log(format!(
                "live polarimetry: frame {} is not the exposure that ended ({ended:?}); half \
                 turn {half} dropped",
                frame.frame_id
            )));
            group_half = None;
            continue;
        }
        if frame.width != width || frame.height != height {
            return Err(format!(
                "frame {}: {}x{}, expected the sensor's {width}x{height}",
                frame.frame_id, frame.width, frame.height
            ));
        }
        group.push((frame.pixels, (stage_span.0 - zero, stage_span.1 - zero)));
        if group.len() as u64 == n {
            let frames: Vec<&[u16]> = group.iter().map(|(f, _)| f.as_slice()).collect();
            let spans: Vec<(f64, f64)> = group.iter().map(|(_, s)| *s).collect();
            let products = estimate_half_turn(
                &frames,
                width,
                height,
                &spans,
                &c.rig.sensor,
                &c.rig.camera_model,
                exposure_us,
                gain_db,
            )?;
            meter.push(now_s());
            let last_frame = group.last().map(|(f, _)| f.clone()).unwrap_or_default();
            io.out
                .send(Reply::Live(LiveUpdate::HalfTurn(Box::new(HalfTurn {
                    index: estimated,
                    products,
                    spans_deg: spans
                        .iter()
                        .map(|(a, b)| (a.to_degrees(), b.to_degrees()))
                        .collect(),
                    speed_deg_per_s: speed.to_degrees(),
                    rate_hz: meter.rate_hz(),
                    timing: timing.to_string(),
                    last_frame,
                }))))
                .await;
            estimated += 1;
            group.clear();
            group_half = None;
        }
        if trigger && anchor.index + 1 >= n * u64::from(ARMED_HALF_TURNS) {
            io.out.note(Reply::Log(format!(
                "live polarimetry: the trigger's arming of {ARMED_HALF_TURNS} half turns is \
                 used up; start again for more"
            )));
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The pulse clock: pulses 0.1 s apart on the controller, read on the host with
    /// latencies 3, 1 and 2 ms. The offset is the smallest difference (the 1 ms read), so
    /// the third pulse's host time is its controller time plus that offset (1e-12: float
    /// rounding), and the speed is the angle step over the controller interval.
    #[test]
    fn pulse_clock_takes_the_quickest_read() {
        let mut c = PulseClock::default();
        let base = 10.0;
        let (h0, s0) = c.pulse(4_000_000, 1.0, base + 0.003);
        assert!((h0 - (base + 0.003)).abs() < 1e-12);
        assert_eq!(s0, None);
        let (_, s1) = c.pulse(4_100_000, 1.2, base + 0.1 + 0.001);
        assert!((s1.unwrap() - 2.0).abs() < 1e-9);
        let (h2, _) = c.pulse(4_200_000, 1.4, base + 0.2 + 0.002);
        assert!((h2 - (base + 0.2 + 0.001)).abs() < 1e-12, "{h2}");
    }
}
