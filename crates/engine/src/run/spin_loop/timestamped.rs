//! The segments and half turns of `trigger = "timestamps"` (the parent's module docs): the
//! camera in software-trigger mode, each frame triggered when the line of
//! [`crate::run::timestamps`] through the stage's position reads puts the analyzer at its
//! grid angle, and its span from the exposure's end on the host clock.

use super::{run_up_s, SpinLine, SpinLoop};
use crate::run::timestamps::{ClockMap, FitError, PositionSample, SpinFit, SpinTrack};
use polar_hal::TURN_RAD;
use polar_hal::{Camera, DeviceError, ErrorKind, Rotator, TriggerMode};
use std::f64::consts::PI;
use std::time::{Duration, Instant};

/// Position reads that decide the stage is at speed, and the spacing between them.
const RUN_UP_SAMPLES: usize = 8;
/// Seconds between two reads while the stage comes up to speed.
const RUN_UP_GAP_S: f64 = 0.02;
/// The stage is at speed when the line through the last [`RUN_UP_SAMPLES`] reads turns
/// within this fraction of the commanded speed.
const SPEED_TOLERANCE: f64 = 0.02;
/// The longest wait for the stage to reach speed after the run-up ([`run_up_s`]), seconds.
const AT_SPEED_TIMEOUT_S: f64 = 10.0;
/// Reads in the line's sliding window (one per frame once running).
const WINDOW: usize = 32;
/// The longest the line is extrapolated while the loop waits for a frame's angle, seconds:
/// the position is read at least this often.
const READ_GAP_S: f64 = 0.1;
/// Frames whose (device timestamp, exposure-end event) pairs map the camera's clock.
const CLOCK_PAIRS: usize = 16;

fn fit_err(e: FitError) -> DeviceError {
    DeviceError::new(ErrorKind::Protocol, "continuous", e.to_string())
}

/// One position read of the spinning stage on `clock`, its bracket narrowed by the line's
/// share of the round trip ([`polar_hal::WireTimes`]: the device latches after the request's
/// last byte and before the reply's first).
async fn read<R: Rotator>(rotator: &mut R, clock: Instant) -> Result<PositionSample, DeviceError> {
    let wire = rotator.spin_read_wire();
    let sent_s = clock.elapsed().as_secs_f64();
    let angle_rad = rotator.spin_position_rad().await?;
    let received_s = clock.elapsed().as_secs_f64();
    Ok(PositionSample::bracketed(
        sent_s, received_s, wire, angle_rad,
    ))
}

/// The first stage angle at or after `angle_rad` that is a whole half turn of the analyzer
/// (whose zero is the stage's `zero_rad`).
fn whole_half_at_or_after(angle_rad: f64, zero_rad: f64) -> f64 {
    zero_rad + ((angle_rad - zero_rad) / PI).ceil() * PI
}

/// How far ahead of now a half turn's first frame must be: a position read (three mean round
/// trips) and 10 ms for the trigger.
fn lead_s(fit: &SpinFit) -> f64 {
    3.0 * fit.mean_round_trip_s + 0.01
}

impl<R: Rotator, C: Camera> SpinLoop<'_, R, C> {
    /// Configures and starts the camera in software-trigger mode, spins, waits the run-up
    /// ([`run_up_s`]), then reads the position until the line through the last reads turns at
    /// the commanded speed (within 2 %), and aims the first half turn at the next whole half
    /// turn.
    pub(super) async fn start_timestamps(&mut self) -> Result<(), DeviceError> {
        let t0 = Instant::now();
        let c = self.c;
        let cam = &mut self.rig.camera;
        cam.set_exposure_us(c.exposure_us).await?;
        cam.set_gain(c.gain_db).await?;
        cam.set_trigger(TriggerMode::Software).await?;
        cam.start().await?;
        // From here a failure stops the camera and the spin (stop_segment).
        self.spinning = true;
        self.line = None;
        let omega = c.speed_deg_per_s.to_radians();
        let rotator = &mut self.rig.analyzer.rotator;
        rotator.spin(omega).await?;
        let resolution = TURN_RAD / f64::from(rotator.info().counts_per_turn.max(1));
        let clock = Instant::now();
        let mut run_up = SpinTrack::new(RUN_UP_SAMPLES, omega, resolution).map_err(fit_err)?;
        let ramp_s = run_up_s(omega, self.rig.spin_acceleration_rad_per_s2);
        tokio::time::sleep(Duration::from_secs_f64(ramp_s)).await;
        let deadline = Instant::now() + Duration::from_secs_f64(AT_SPEED_TIMEOUT_S);
        loop {
            run_up.push(read(rotator, clock).await?).map_err(fit_err)?;
            let speed = run_up
                .fit()
                .filter(|_| run_up.len() == RUN_UP_SAMPLES)
                .map(|f| f.omega_rad_per_s);
            if speed.is_some_and(|s| (s / omega - 1.0).abs() <= SPEED_TOLERANCE) {
                break;
            }
            if Instant::now() > deadline {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    "continuous",
                    format!(
                        "the stage did not reach {} deg/s within {AT_SPEED_TIMEOUT_S} s: the \
                         line through its last {RUN_UP_SAMPLES} position reads turns at {} \
                         deg/s",
                        c.speed_deg_per_s,
                        speed.map_or("(no line)".to_string(), |s| format!(
                            "{:.3}",
                            s.to_degrees()
                        ))
                    ),
                ));
            }
            tokio::time::sleep(Duration::from_secs_f64(RUN_UP_GAP_S)).await;
        }
        let mut track = SpinTrack::new(WINDOW, omega, resolution).map_err(fit_err)?;
        for s in run_up.samples() {
            track.push(*s).map_err(fit_err)?;
        }
        let fit = *track
            .fit()
            .ok_or_else(|| fit_err(FitError::TooFew("no line after the run-up".into())))?;
        let zero = self.rig.analyzer.zero_offset_rad;
        let now_s = clock.elapsed().as_secs_f64();
        let next_half_rad = whole_half_at_or_after(fit.angle_at(now_s + lead_s(&fit)), zero);
        tracing::debug!(
            speed_deg_per_s = fit.omega_rad_per_s.to_degrees(),
            round_trip_ms = fit.mean_round_trip_s * 1e3,
            residual_deg = fit.residual_rad.to_degrees(),
            ms = t0.elapsed().as_secs_f64() * 1e3,
            "spinning; camera on software trigger, angles from timestamps"
        );
        self.line = Some(SpinLine {
            clock,
            track,
            clocks: ClockMap::new(CLOCK_PAIRS).map_err(fit_err)?,
            trigger_latency_s: 0.0,
            next_half_rad,
        });
        self.core.device_s += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Reads the position into the segment's line and returns the line.
    async fn sample_position(&mut self, clock: Instant) -> Result<SpinFit, DeviceError> {
        let sample = read(&mut self.rig.analyzer.rotator, clock).await?;
        let line = self.line.as_mut().ok_or_else(|| {
            DeviceError::new(ErrorKind::Protocol, "continuous", "no timestamps segment")
        })?;
        line.track.push(sample).map_err(fit_err)?;
        line.track
            .fit()
            .copied()
            .ok_or_else(|| fit_err(FitError::TooFew("no line".into())))
    }

    /// Takes half turn `h` with timestamps: for each frame the loop waits until the line puts
    /// the analyzer at the frame's grid angle (reading the position at least every
    /// [`READ_GAP_S`] meanwhile), triggers, takes the exposure's end on the host clock and the
    /// frame, reads the position once more (so the span is interpolated between reads, not
    /// extrapolated) and stores the span with its uncertainty; then the set goes to be checked
    /// with its span rows.
    pub(super) async fn half_turn_timestamps(&mut self, h: u64) -> Result<(), DeviceError> {
        let c = self.c;
        let n = u64::from(c.frames_per_half_turn);
        let interval = self.interval_rad();
        let interval_s = c.interval_deg() / c.speed_deg_per_s;
        let timing_s = c.timing_sigma_us * 1e-6;
        let zero = self.rig.analyzer.zero_offset_rad;
        let wait = self.wait();
        let no_line = || {
            DeviceError::new(
                ErrorKind::Protocol,
                "continuous",
                "no line through the stage's position reads (the segment did not start)",
            )
        };
        let (clock, base) = {
            let line = self.line.as_ref().ok_or_else(no_line)?;
            let fit = line.track.fit().ok_or_else(no_line)?;
            let now_s = line.clock.elapsed().as_secs_f64();
            let ahead = fit.angle_at(now_s + lead_s(fit));
            // Behind the planned half turn (a slow store, a retake): the next whole one.
            let base = if line.next_half_rad >= ahead {
                line.next_half_rad
            } else {
                whole_half_at_or_after(ahead, zero)
            };
            (line.clock, base)
        };
        let bad = |m: String| DeviceError::new(ErrorKind::Protocol, "continuous", m);
        let mut frames = Vec::with_capacity(n as usize);
        let mut spans_rad = Vec::with_capacity(n as usize);
        let mut sigma_rad: f64 = 0.0;
        for k in 0..n {
            let t0 = Instant::now();
            let target_rad = base + k as f64 * interval;
            // Wait for the frame's grid angle, reading the position every READ_GAP_S on the
            // way so the line is never extrapolated far.
            let latency_s = self.line.as_ref().map_or(0.0, |f| f.trigger_latency_s);
            let mut aim_s;
            loop {
                let fit = *self
                    .line
                    .as_ref()
                    .and_then(|f| f.track.fit())
                    .ok_or_else(no_line)?;
                aim_s = fit.time_at(target_rad) - latency_s;
                let wait_s = aim_s - clock.elapsed().as_secs_f64();
                if wait_s <= READ_GAP_S {
                    if wait_s > 0.0 {
                        tokio::time::sleep(Duration::from_secs_f64(wait_s)).await;
                    }
                    break;
                }
                tokio::time::sleep(
                    Duration::from_secs_f64(wait_s - READ_GAP_S)
                        .min(Duration::from_secs_f64(READ_GAP_S)),
                )
                .await;
                self.sample_position(clock).await?;
            }
            let cam = &mut self.rig.camera;
            let triggered_s = clock.elapsed().as_secs_f64();
            cam.trigger().await?;
            let ended = cam.exposure_end(wait).await?;
            let event_s = clock.elapsed().as_secs_f64();
            let frame = cam.grab(wait).await?;
            let arrived_s = clock.elapsed().as_secs_f64();
            // A read after the frame: its span is interpolated between reads.
            let fit = self.sample_position(clock).await?;
            self.core.device_s += t0.elapsed().as_secs_f64();
            let exposure_s = frame.exposure_us * 1e-6;
            // The exposure starts after its trigger, so it ends after trigger + exposure.
            let earliest_end_s = triggered_s + exposure_s;
            let (end_s, end_sigma_s) = match ended {
                Some(id) => {
                    if id != frame.frame_id {
                        return Err(bad(format!(
                            "frame {} is not the exposure that ended ({id})",
                            frame.frame_id
                        )));
                    }
                    // The end on the camera's clock, mapped to the host's past the events'
                    // latency (crate::run::timestamps::ClockMap); the event itself without a
                    // device timestamp.
                    // The map's own uncertainty (the room between the events and the triggers)
                    // comes on top of the plan's timing sigma.
                    let (end_s, map_sigma_s) = match frame.device_timestamp_ns {
                        Some(ns) => {
                            let device_s = ns as f64 * 1e-9;
                            let line = self.line.as_mut().ok_or_else(no_line)?;
                            line.clocks.push(device_s, event_s).map_err(fit_err)?;
                            line.clocks
                                .push_earliest(device_s, earliest_end_s)
                                .map_err(fit_err)?;
                            line.clocks.host_end_s(device_s).unwrap_or((event_s, 0.0))
                        }
                        None => (event_s, 0.0),
                    };
                    if end_s + 3.0 * timing_s < earliest_end_s {
                        return Err(bad(format!(
                            "frame {}'s exposure ended {:.1} us before its trigger plus the \
                             exposure: not this trigger's exposure",
                            frame.frame_id,
                            (earliest_end_s - end_s) * 1e6
                        )));
                    }
                    (end_s, timing_s.hypot(map_sigma_s))
                }
                None => {
                    // No exposure-end event: the end lies between trigger + exposure and the
                    // frame's arrival, uniformly for all we know.
                    let latest = arrived_s.max(earliest_end_s);
                    let width = latest - earliest_end_s;
                    (
                        0.5 * (earliest_end_s + latest),
                        (timing_s * timing_s + width * width / 12.0).sqrt(),
                    )
                }
            };
            let span = fit.span(end_s, exposure_s, end_sigma_s);
            let off_rad = span.start_rad - target_rad;
            if off_rad.abs() > 0.5 * interval {
                return Err(bad(format!(
                    "frame {k} of half turn {h} starts {:.4} deg from its grid angle {:.4} deg \
                     (more than half the {:.4} deg interval): triggered late or the stage's \
                     speed changed",
                    off_rad.to_degrees(),
                    (k as f64 * interval).to_degrees(),
                    interval.to_degrees()
                )));
            }
            // The delay from the time aimed at to the exposure's start (the timer's wake-up
            // and the trigger's latency), smoothed: the next trigger is aimed that much early.
            if let Some(line) = self.line.as_mut() {
                let latency = (end_s - exposure_s - aim_s).clamp(0.0, 0.25 * interval_s);
                line.trigger_latency_s = 0.7 * line.trigger_latency_s + 0.3 * latency;
            }
            let start_deg = (span.start_rad - zero).to_degrees().rem_euclid(180.0);
            let end_deg = start_deg + (span.end_rad - span.start_rad).to_degrees();
            sigma_rad = sigma_rad.max(span.sigma_rad);
            let index = self
                .store_frame(
                    h * n + k,
                    frame,
                    (start_deg, end_deg),
                    crate::AngleSource::Timestamps,
                    span.sigma_rad.to_degrees(),
                )
                .await?;
            frames.push(index);
            spans_rad.push((start_deg.to_radians(), end_deg.to_radians()));
        }
        if let Some(line) = self.line.as_mut() {
            line.next_half_rad = base + PI;
        }
        self.send_set(h, frames, &spans_rad, sigma_rad).await
    }
}
