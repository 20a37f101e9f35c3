//! The angle of a spinning stage against the host's clock, from its position samples: the
//! model behind `trigger = "timestamps"` (a camera the stage does not trigger).
//!
//! # Samples
//!
//! A position sample is a read of the stage's position while it spins
//! (`Rotator::spin_position_rad`) with the host's clock read just before the request and just
//! after the reply. The device latches the position somewhere inside that round trip, but not
//! while the request's bytes are still on a serial line nor once the reply's are: the driver
//! states both times (`Rotator::spin_read_wire`, the bytes' bits at the line's baud; a
//! K10CR1's position read spends 0.52 ms before its latch and 1.04 ms after it at 115200
//! baud), and the bracket is narrowed by them ([`PositionSample::bracketed`]). The sample's
//! time is the narrowed bracket's midpoint, `t = (t_request + t_reply) / 2`, and `rtt` below
//! its width. Where inside
//! the round trip the latch falls is a property of the controller that no number of samples
//! reveals, so its offset from the midpoint is a systematic error common to all samples,
//! uniform over `[-rtt / 2, rtt / 2]`: standard deviation `rtt / (2 sqrt 3)` in time, `omega`
//! times that in angle.
//!
//! # The line
//!
//! At constant speed the angle is a line in time, `theta(t) = a + omega (t - t_bar)`, with
//! `t_bar` the samples' mean time. Ordinary least squares over the `n` samples in the window
//! (angles unwrapped: each taken within half a turn of where the line, or the commanded speed
//! before there is a line, puts it) gives
//!
//! ```text
//! omega = sum (t_i - t_bar)(theta_i - theta_bar) / S_tt,   a = theta_bar,
//! S_tt  = sum (t_i - t_bar)^2,
//! s^2   = sum r_i^2 / (n - 2)          (r_i the residuals),
//! var theta(t) = s^2 (1 / n + (t - t_bar)^2 / S_tt)
//! ```
//!
//! (`a` and `omega` are uncorrelated because the time is centred.) `s` is floored at one
//! position count over `sqrt 12` (the quantisation of a read), so exact samples do not claim
//! an exact line. The residual scatter `s` carries the random part of each sample: the
//! controller's encoder noise and the spread of the latch inside the round trip from read to
//! read.
//!
//! # A frame's span and its uncertainty
//!
//! A frame whose exposure of length `T` ends at host time `t_end` spans
//! `[theta(t_end) - omega T, theta(t_end)]`. Its centre's standard uncertainty combines, as
//! independent terms,
//!
//! ```text
//! sigma_theta^2 = (omega sigma_t)^2 + max(var theta(t_c), s^2) + (omega rtt_bar / (2 sqrt 3))^2
//! ```
//!
//! with `sigma_t` the uncertainty of `t_end` on the host clock (the camera's stated timing
//! uncertainty, the plan's `timing_sigma_us`, widened where the end is only bracketed),
//! `t_c = t_end - T / 2` the span's centre and `rtt_bar` the window's mean round trip. The line
//! term is at least one read's scatter `s`: reads made while the host runs the reading task
//! late err together, so the window's average does not shrink their error as it would for
//! independent reads. This is
//! the `angle_sigma_rad` of `polar_model::span` (the spread of the span's centre), which enters
//! the products' rows and covariance.
//!
//! # The exposure's end on the host clock
//!
//! The host sees an exposure end (the camera's exposure-end event) some latency after it
//! happened, and that latency is at least a few microseconds and now and then milliseconds (a
//! thread that was not running). A camera that timestamps its frames on its own clock gives
//! the end without that jitter, on another clock: [`ClockMap`] maps the device's clock to the
//! host's from the pairs (device timestamp, host time of the event) of recent frames. The
//! host's time is the device's plus an offset and a rate error (crystal clocks differ by tens
//! of ppm), plus the latency, which is never negative. So every pair lies on or above the true
//! line, and the map is the line under all pairs that lies closest to them (the lower convex
//! hull's edge with the least sum of latencies, its rate within [`MAX_RATE_ERROR`] of 1, as
//! clock-skew estimation from one-way delays does): a late event lies above the line and does
//! not move it. The events bound the ends from above; each frame's software trigger plus its
//! exposure bounds its end from below (the camera cannot start before it is told to). A
//! frame's end is the middle of the tightest interval those bounds leave, each carried to the
//! frame's device time with the rate anywhere within [`MAX_RATE_ERROR`] of 1, and its
//! uncertainty the interval's (uniform) beside the plan's `timing_sigma_us`
//! ([`ClockMap::host_end_s`]): the line's rate is not trusted further than the rate bound, so
//! a bound from a frame seconds away is loosened by what the rate could add. A loaded host,
//! whose triggers leave late and whose events are seen late, widens the interval as it
//! happens.

use polar_hal::WireTimes;
use std::collections::VecDeque;
use std::f64::consts::{PI, TAU};

/// One read of a spinning stage's position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionSample {
    /// Host time of the request, seconds on the loop's clock.
    pub request_s: f64,
    /// Host time of the reply, seconds on the same clock.
    pub reply_s: f64,
    /// The position read, radians (unwrapped by the driver or not: the track unwraps).
    pub angle_rad: f64,
}

impl PositionSample {
    /// A read sent at `sent_s` and answered at `received_s` (host clock, seconds), its
    /// position `angle_rad`: the latch lies after the request's bytes reached the device and
    /// before the reply's left it ([`polar_hal::WireTimes`]). A round trip shorter than the
    /// line's share (a clock read late) keeps the line's proportion of it; a reply before its
    /// request is kept as it is, for [`SpinTrack::push`] to refuse.
    pub fn bracketed(sent_s: f64, received_s: f64, wire: WireTimes, angle_rad: f64) -> Self {
        if received_s < sent_s || received_s.is_nan() || sent_s.is_nan() {
            return PositionSample {
                request_s: sent_s,
                reply_s: received_s,
                angle_rad,
            };
        }
        let round_trip_s = received_s - sent_s;
        let on_line_s = wire.request_s.max(0.0) + wire.reply_s.max(0.0);
        let scale = if on_line_s > round_trip_s && on_line_s > 0.0 {
            round_trip_s / on_line_s
        } else {
            1.0
        };
        PositionSample {
            request_s: sent_s + scale * wire.request_s.max(0.0),
            reply_s: sent_s.max(received_s - scale * wire.reply_s.max(0.0)),
            angle_rad,
        }
    }

    /// The sample's time: the round trip's midpoint.
    pub fn time_s(&self) -> f64 {
        0.5 * (self.request_s + self.reply_s)
    }

    /// The round trip, seconds.
    pub fn round_trip_s(&self) -> f64 {
        self.reply_s - self.request_s
    }
}

/// Why samples give no line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// A field of a sample or of the track is out of range.
    #[error("{field} = {value}: allowed {allowed}")]
    OutOfRange {
        /// The field.
        field: &'static str,
        /// Its value.
        value: f64,
        /// What is allowed.
        allowed: &'static str,
    },
    /// Too few samples, or all at one time.
    #[error("position samples: {0}")]
    TooFew(String),
}

/// The fitted line `theta(t) = a + omega (t - t_bar)` and its uncertainty (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpinFit {
    /// The samples' mean time, s.
    pub t_bar_s: f64,
    /// The angle at `t_bar_s`, radians (unwrapped).
    pub a_rad: f64,
    /// The fitted speed, rad/s.
    pub omega_rad_per_s: f64,
    /// The residual scatter of a sample, radians (floored at a count over sqrt 12).
    pub residual_rad: f64,
    /// `S_tt`, s^2.
    pub s_tt_s2: f64,
    /// Samples in the fit.
    pub samples: usize,
    /// Their mean round trip, s.
    pub mean_round_trip_s: f64,
}

impl SpinFit {
    /// Fits the line to `samples` (angles already unwrapped); `resolution_rad` is one position
    /// count. Needs three samples at two times at least.
    pub fn fit(samples: &[PositionSample], resolution_rad: f64) -> Result<SpinFit, FitError> {
        let n = samples.len();
        if n < 3 {
            return Err(FitError::TooFew(format!(
                "{n} samples; a line with its scatter needs 3 at least"
            )));
        }
        let nf = n as f64;
        let t_bar = samples.iter().map(PositionSample::time_s).sum::<f64>() / nf;
        let y_bar = samples.iter().map(|s| s.angle_rad).sum::<f64>() / nf;
        let (mut s_tt, mut s_ty) = (0.0, 0.0);
        for s in samples {
            let dt = s.time_s() - t_bar;
            s_tt += dt * dt;
            s_ty += dt * (s.angle_rad - y_bar);
        }
        if !(s_tt > 0.0 && s_tt.is_finite()) {
            return Err(FitError::TooFew(format!(
                "{n} samples with no spread in time (S_tt = {s_tt} s^2)"
            )));
        }
        let omega = s_ty / s_tt;
        let rss: f64 = samples
            .iter()
            .map(|s| {
                let r = s.angle_rad - y_bar - omega * (s.time_s() - t_bar);
                r * r
            })
            .sum();
        let floor = resolution_rad / 12f64.sqrt();
        let residual = (rss / (nf - 2.0)).sqrt().max(floor);
        let mean_round_trip_s = samples.iter().map(|s| s.round_trip_s()).sum::<f64>() / nf;
        Ok(SpinFit {
            t_bar_s: t_bar,
            a_rad: y_bar,
            omega_rad_per_s: omega,
            residual_rad: residual,
            s_tt_s2: s_tt,
            samples: n,
            mean_round_trip_s,
        })
    }

    /// The line's angle at host time `t_s`, radians (unwrapped).
    pub fn angle_at(&self, t_s: f64) -> f64 {
        self.a_rad + self.omega_rad_per_s * (t_s - self.t_bar_s)
    }

    /// The host time at which the line reaches `angle_rad` (unwrapped), s.
    pub fn time_at(&self, angle_rad: f64) -> f64 {
        self.t_bar_s + (angle_rad - self.a_rad) / self.omega_rad_per_s
    }

    /// The standard error of the line at `t_s`, radians: `s sqrt(1/n + (t - t_bar)^2 / S_tt)`.
    pub fn line_sigma_rad(&self, t_s: f64) -> f64 {
        let dt = t_s - self.t_bar_s;
        self.residual_rad * (1.0 / self.samples as f64 + dt * dt / self.s_tt_s2).sqrt()
    }

    /// The latch's systematic uncertainty inside a read's round trip, radians: `omega
    /// rtt_bar / (2 sqrt 3)`.
    pub fn latch_sigma_rad(&self) -> f64 {
        self.omega_rad_per_s.abs() * self.mean_round_trip_s / (2.0 * 3f64.sqrt())
    }

    /// The span of a frame whose exposure of `exposure_s` ended at host time `end_s`, known
    /// to `timing_sigma_s` (module docs).
    pub fn span(&self, end_s: f64, exposure_s: f64, timing_sigma_s: f64) -> Span {
        let end_rad = self.angle_at(end_s);
        let start_rad = end_rad - self.omega_rad_per_s * exposure_s;
        let timing = self.omega_rad_per_s.abs() * timing_sigma_s;
        // At least one read's scatter: a host that runs the reading task late does so for a
        // while, so neighbouring reads err together and the window's average does not shrink
        // their error as independent reads would.
        let line = self
            .line_sigma_rad(end_s - 0.5 * exposure_s)
            .max(self.residual_rad);
        let latch = self.latch_sigma_rad();
        Span {
            start_rad,
            end_rad,
            sigma_rad: (timing * timing + line * line + latch * latch).sqrt(),
        }
    }
}

/// A frame's span on the stage's angle and the standard uncertainty of its centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Span {
    /// The angle at the exposure's start, radians (unwrapped).
    pub start_rad: f64,
    /// The angle at its end, radians (unwrapped).
    pub end_rad: f64,
    /// The standard uncertainty of the span (both ends move together), radians.
    pub sigma_rad: f64,
}

/// The samples of a spinning stage in a sliding window and the line through them.
#[derive(Debug, Clone)]
pub struct SpinTrack {
    samples: VecDeque<PositionSample>,
    window: usize,
    nominal_rad_per_s: f64,
    resolution_rad: f64,
    fit: Option<SpinFit>,
}

impl SpinTrack {
    /// An empty track: at most `window` samples (3..=100000) kept, the stage commanded at
    /// `nominal_rad_per_s` (finite, non-zero: the unwrapping's guess before there is a
    /// line), one position count `resolution_rad` (finite, > 0).
    pub fn new(
        window: usize,
        nominal_rad_per_s: f64,
        resolution_rad: f64,
    ) -> Result<SpinTrack, FitError> {
        if !(3..=100_000).contains(&window) {
            return Err(FitError::OutOfRange {
                field: "window",
                value: window as f64,
                allowed: "3..=100000 samples",
            });
        }
        if !(nominal_rad_per_s.is_finite() && nominal_rad_per_s != 0.0) {
            return Err(FitError::OutOfRange {
                field: "nominal speed",
                value: nominal_rad_per_s,
                allowed: "a finite non-zero rad/s",
            });
        }
        if !(resolution_rad.is_finite() && resolution_rad > 0.0) {
            return Err(FitError::OutOfRange {
                field: "resolution",
                value: resolution_rad,
                allowed: "a finite angle > 0 rad",
            });
        }
        Ok(SpinTrack {
            samples: VecDeque::with_capacity(window),
            window,
            nominal_rad_per_s,
            resolution_rad,
            fit: None,
        })
    }

    /// Adds a sample (its angle unwrapped to within half a turn of the line's, or of the last
    /// sample plus the nominal speed times the time between) and refits once there are three.
    /// The oldest sample leaves a full window.
    pub fn push(&mut self, sample: PositionSample) -> Result<(), FitError> {
        let finite = [sample.request_s, sample.reply_s, sample.angle_rad];
        if let Some(v) = finite.into_iter().find(|v| !v.is_finite()) {
            return Err(FitError::OutOfRange {
                field: "position sample",
                value: v,
                allowed: "finite times and angles",
            });
        }
        if sample.reply_s < sample.request_s {
            return Err(FitError::OutOfRange {
                field: "position sample round trip",
                value: sample.round_trip_s(),
                allowed: ">= 0 s (the reply after the request)",
            });
        }
        let t = sample.time_s();
        let expected = match (&self.fit, self.samples.back()) {
            (Some(f), _) => Some(f.angle_at(t)),
            (None, Some(last)) => {
                Some(last.angle_rad + self.nominal_rad_per_s * (t - last.time_s()))
            }
            (None, None) => None,
        };
        let mut s = sample;
        if let Some(e) = expected {
            s.angle_rad += TAU * ((e - s.angle_rad + PI) / TAU).floor();
        }
        if self.samples.len() == self.window {
            self.samples.pop_front();
        }
        self.samples.push_back(s);
        if self.samples.len() >= 3 {
            let v: Vec<PositionSample> = self.samples.iter().copied().collect();
            self.fit = Some(SpinFit::fit(&v, self.resolution_rad)?);
        }
        Ok(())
    }

    /// Forgets every sample (a new spin).
    pub fn clear(&mut self) {
        self.samples.clear();
        self.fit = None;
    }

    /// The line through the window's samples, once there are three.
    pub fn fit(&self) -> Option<&SpinFit> {
        self.fit.as_ref()
    }

    /// The window's samples, oldest first (angles unwrapped).
    pub fn samples(&self) -> impl Iterator<Item = &PositionSample> {
        self.samples.iter()
    }

    /// Samples in the window.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether the window is empty.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

/// The largest rate error between a camera's clock and the host's that [`ClockMap`] accepts
/// (two crystal clocks of 100 ppm each; a steeper line through two pairs is a late event).
pub const MAX_RATE_ERROR: f64 = 2e-4;

/// A camera clock mapped onto the host's from (device timestamp, host time of the event)
/// pairs (module docs).
#[derive(Debug, Clone)]
pub struct ClockMap {
    pairs: VecDeque<(f64, f64)>,
    /// (device time of an exposure's end, the earliest host time it can have ended: its
    /// trigger plus the exposure).
    earliest: VecDeque<(f64, f64)>,
    window: usize,
}

impl ClockMap {
    /// An empty map keeping the last `window` pairs (2..=1000).
    pub fn new(window: usize) -> Result<ClockMap, FitError> {
        if !(2..=1000).contains(&window) {
            return Err(FitError::OutOfRange {
                field: "clock map window",
                value: window as f64,
                allowed: "2..=1000 pairs",
            });
        }
        Ok(ClockMap {
            pairs: VecDeque::with_capacity(window),
            earliest: VecDeque::with_capacity(window),
            window,
        })
    }

    /// Adds the pair of a frame: its device timestamp and the host time its event was seen,
    /// both seconds. A device time not after the last one (a camera whose clock was reset)
    /// starts the map again.
    pub fn push(&mut self, device_s: f64, host_s: f64) -> Result<(), FitError> {
        for (field, value) in [("device timestamp", device_s), ("host time", host_s)] {
            if !value.is_finite() {
                return Err(FitError::OutOfRange {
                    field,
                    value,
                    allowed: "a finite time in seconds",
                });
            }
        }
        if self.pairs.back().is_some_and(|&(d, _)| device_s <= d) {
            self.pairs.clear();
            self.earliest.clear();
        }
        if self.pairs.len() == self.window {
            self.pairs.pop_front();
        }
        self.pairs.push_back((device_s, host_s));
        Ok(())
    }

    /// Adds the earliest host time the exposure that ended at `device_s` can have ended (its
    /// software trigger's host time plus the exposure: the camera cannot start before it is
    /// told to), both seconds.
    pub fn push_earliest(&mut self, device_s: f64, earliest_host_s: f64) -> Result<(), FitError> {
        if !(device_s.is_finite() && earliest_host_s.is_finite()) {
            return Err(FitError::OutOfRange {
                field: "earliest exposure end",
                value: if device_s.is_finite() {
                    earliest_host_s
                } else {
                    device_s
                },
                allowed: "finite times in seconds",
            });
        }
        if self.earliest.len() == self.window {
            self.earliest.pop_front();
        }
        self.earliest.push_back((device_s, earliest_host_s));
        Ok(())
    }

    /// The host time of device time `device_s` and its standard uncertainty, seconds, from
    /// bounds that hold whatever the rate within [`MAX_RATE_ERROR`] of 1: every event was seen
    /// at or after its end, so the end at `device_s` is at most an event's host time plus the
    /// device time since it, stretched by the rate bound; every trigger plus its exposure is
    /// at or before its end, so the end is at least that plus the device time since it,
    /// shrunk by the rate bound. The time is the middle of the tightest such interval and its
    /// uncertainty the interval's, uniform (`width / sqrt 12`): the frame just seen bounds its
    /// own end without a rate term, and a frame further off in device time bounds it less
    /// tightly, so a mapping carried across seconds owns the rate it does not know. A host
    /// that sees its events late and whose triggers leave late has a wide interval; the plan's
    /// `timing_sigma_us` comes on top. With no trigger bound the time is the upper bound and
    /// the uncertainty 0 (the plan's sigma alone); bounds that cross (a clock beyond the rate
    /// bound) give their middle and their crossing's width.
    pub fn host_end_s(&self, device_s: f64) -> Option<(f64, f64)> {
        let stretch = |d: f64| (device_s - d) + MAX_RATE_ERROR * (device_s - d).abs();
        let shrink = |d: f64| (device_s - d) - MAX_RATE_ERROR * (device_s - d).abs();
        let latest = self
            .pairs
            .iter()
            .map(|&(d, h)| h + stretch(d))
            .min_by(f64::total_cmp)?;
        let Some(earliest) = self
            .earliest
            .iter()
            .map(|&(d, lower)| lower + shrink(d))
            .max_by(f64::total_cmp)
        else {
            return Some((latest, 0.0));
        };
        let width = (latest - earliest).abs();
        Some((0.5 * (latest + earliest), width / 12f64.sqrt()))
    }

    /// The line `host = offset + rate x device` under every pair (no latency is negative)
    /// that lies closest to them (the least sum of latencies; the lower convex hull's edge),
    /// among lines through two pairs whose rate is within [`MAX_RATE_ERROR`] of 1. With fewer
    /// than three pairs, or none such, the rate is 1 (two pairs cannot tell a late event from
    /// a rate error) and the offset the lowest pair's. Returns `(offset, rate)`.
    pub fn line(&self) -> Option<(f64, f64)> {
        let p = &self.pairs;
        let lowest = |rate: f64| {
            p.iter()
                .map(|&(d, h)| h - rate * d)
                .min_by(f64::total_cmp)
                .map(|o| (o, rate))
        };
        if p.len() < 3 {
            return lowest(1.0);
        }
        let mut best: Option<(f64, (f64, f64))> = None;
        for (i, a) in p.iter().enumerate() {
            for b in p.iter().skip(i + 1) {
                let rate = (b.1 - a.1) / (b.0 - a.0);
                // (A NaN rate, two pairs at one device time, is not within it either.)
                let within = (rate - 1.0).abs() <= MAX_RATE_ERROR;
                if !within {
                    continue;
                }
                let offset = a.1 - rate * a.0;
                let mut sum = 0.0;
                let mut under = true;
                for &(d, h) in p {
                    let latency = h - (offset + rate * d);
                    // A nanosecond of rounding: the two pairs on the line.
                    if latency < -1e-9 {
                        under = false;
                        break;
                    }
                    sum += latency;
                }
                if under && best.is_none_or(|(s, _)| sum < s) {
                    best = Some((sum, (offset, rate)));
                }
            }
        }
        best.map(|(_, line)| line).or_else(|| lowest(1.0))
    }

    /// The rate of the host's clock against the device's ([`ClockMap::line`]).
    pub fn rate(&self) -> f64 {
        self.line().map_or(1.0, |(_, rate)| rate)
    }

    /// The host time of device time `device_s`, seconds, once there is a pair.
    pub fn host_s(&self, device_s: f64) -> Option<f64> {
        self.line().map(|(offset, rate)| offset + rate * device_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SplitMix64 and Box-Muller: a seeded standard normal stream for the tests.
    struct Normal(u64);
    impl Normal {
        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
        fn next(&mut self) -> f64 {
            let (u, v) = (self.uniform(), self.uniform());
            (-2.0 * u.ln()).sqrt() * (TAU * v).cos()
        }
    }

    fn sample(t: f64, angle: f64, rtt: f64) -> PositionSample {
        PositionSample {
            request_s: t - 0.5 * rtt,
            reply_s: t + 0.5 * rtt,
            angle_rad: angle,
        }
    }

    /// Exact samples of a known line (a = 1.3 rad at t = 0, 0.17 rad/s, 11 reads 0.1 s apart
    /// with 2 ms round trips) give the line back to 1e-12 (rounding of sums of 11 terms of
    /// order 1), `time_at` inverts `angle_at` to 1e-12 s, the scatter is the floor (one count
    /// over sqrt 12), and the span of a frame is `[theta(end) - omega T, theta(end)]` with the
    /// uncertainty of the module's formula computed by hand (to 1e-15 rad).
    #[test]
    fn exact_line_is_recovered() {
        let (a, omega, rtt) = (1.3, 0.17, 0.002);
        let resolution = TAU / 49_152_000.0;
        let samples: Vec<_> = (0..11)
            .map(|i| {
                let t = 5.0 + 0.1 * f64::from(i);
                sample(t, a + omega * t, rtt)
            })
            .collect();
        let f = SpinFit::fit(&samples, resolution).expect("fit");
        assert!((f.omega_rad_per_s - omega).abs() < 1e-12, "{f:?}");
        for t in [0.0, 5.5, 20.0] {
            assert!((f.angle_at(t) - (a + omega * t)).abs() < 1e-12, "{t}");
            assert!((f.time_at(f.angle_at(t)) - t).abs() < 1e-12);
        }
        let floor = resolution / 12f64.sqrt();
        assert_eq!(f.residual_rad, floor);
        assert!((f.mean_round_trip_s - rtt).abs() < 1e-15);
        // S_tt of 11 points 0.1 s apart: 0.01 * sum (i - 5)^2 = 1.1 s^2.
        assert!((f.s_tt_s2 - 1.1).abs() < 1e-12);
        let (end, exposure, timing) = (7.0, 0.004, 20e-6);
        let span = f.span(end, exposure, timing);
        assert!((span.end_rad - (a + omega * end)).abs() < 1e-12);
        assert!((span.end_rad - span.start_rad - omega * exposure).abs() < 1e-15);
        let tc = end - 0.5 * exposure;
        let line2 = floor * floor * (1.0 / 11.0 + (tc - 5.5).powi(2) / 1.1);
        let latch = omega * rtt / (2.0 * 3f64.sqrt());
        let expected = ((omega * timing).powi(2) + line2 + latch * latch).sqrt();
        assert!((span.sigma_rad - expected).abs() < 1e-15, "{span:?}");
    }

    /// Samples with Gaussian angle noise of known sigma (1e-3 rad, 20 reads over 1.9 s,
    /// 4000 seeded trials): the spread of the fitted angle at the samples' mean time is
    /// `sigma / sqrt n` and 1 s after the last sample `sigma sqrt(1/n + dt^2 / S_tt)`; the
    /// predicted line sigma (from each trial's residuals) agrees in rms. Tolerance 5 %: the
    /// standard error of an rms over 4000 trials is 1 / sqrt(2 x 4000) = 1.1 %, so 5 % is
    /// over 4 standard errors, and a wrong formula (say a missing 1/n or S_tt term) is off by
    /// a factor above 2 at one of the two times.
    #[test]
    fn noisy_line_has_the_predicted_spread() {
        let (a, omega, sigma, n) = (0.4, 3.0, 1e-3, 20);
        let mut rng = Normal(42);
        let times: Vec<f64> = (0..n).map(|i| 0.1 * f64::from(i)).collect();
        let t_bar = 0.95;
        let s_tt: f64 = times.iter().map(|t| (t - t_bar).powi(2)).sum();
        let t_far = 2.9;
        let trials = 4000;
        let (mut e_mid, mut e_far, mut p_mid, mut p_far) = (0.0, 0.0, 0.0, 0.0);
        for _ in 0..trials {
            let samples: Vec<_> = times
                .iter()
                .map(|&t| sample(t, a + omega * t + sigma * rng.next(), 1e-3))
                .collect();
            let f = SpinFit::fit(&samples, 1e-9).expect("fit");
            e_mid += (f.angle_at(t_bar) - (a + omega * t_bar)).powi(2);
            e_far += (f.angle_at(t_far) - (a + omega * t_far)).powi(2);
            p_mid += f.line_sigma_rad(t_bar).powi(2);
            p_far += f.line_sigma_rad(t_far).powi(2);
        }
        let rms = |s: f64| (s / f64::from(trials)).sqrt();
        let want_mid = sigma / f64::from(n).sqrt();
        let want_far = sigma * (1.0 / f64::from(n) + (t_far - t_bar).powi(2) / s_tt).sqrt();
        for (got, want, what) in [
            (rms(e_mid), want_mid, "error at t_bar"),
            (rms(e_far), want_far, "error at t_far"),
            (rms(p_mid), want_mid, "predicted at t_bar"),
            (rms(p_far), want_far, "predicted at t_far"),
        ] {
            assert!(
                (got / want - 1.0).abs() < 0.05,
                "{what}: {got:e} against {want:e}"
            );
        }
        assert!(
            want_far / want_mid > 2.0,
            "the two times test different terms"
        );
    }

    /// A driver that reports angles wrapped to `[0, 2 pi)` at 20 rad/s (a turn every 0.31 s,
    /// reads 0.05 s apart: one rad apart, less than half a turn): the track unwraps them and
    /// the line's speed is 20 rad/s to 1e-9 (exact samples); a sliding window keeps the last
    /// `window` samples.
    #[test]
    fn wrapped_reads_are_unwrapped() {
        let mut track = SpinTrack::new(8, 20.0, 1e-9).expect("track");
        for i in 0..40 {
            let t = 0.05 * f64::from(i);
            track
                .push(sample(t, (0.2 + 20.0 * t).rem_euclid(TAU), 5e-4))
                .expect("push");
        }
        assert_eq!(track.len(), 8);
        let f = track.fit().expect("fit");
        assert!((f.omega_rad_per_s - 20.0).abs() < 1e-9, "{f:?}");
        assert_eq!(f.samples, 8);
        let t = 1.5;
        let d = (f.angle_at(t) - (0.2 + 20.0 * t)).rem_euclid(TAU);
        assert!(d.min(TAU - d) < 1e-9);
    }

    /// A camera clock 40 ppm fast and 3.2 s ahead of the host's, its events seen 15 to 75 us
    /// late (uniform) and one 4 ms late (a thread that did not run), a frame every 0.5 s for 16
    /// frames: the mapped host time of a device time 1 s after the last frame is late by a
    /// latency of the ordinary pairs, 10 to 85 us (15 to 75 us, widened by the rate's error,
    /// asserted below 8 ppm: the hull's edge runs through two of the lowest pairs, several
    /// seconds apart), never by the outlier's 4 ms. Bad windows and non-finite times are
    /// refused by name; a device time that goes back restarts the map.
    #[test]
    fn clock_map_takes_the_least_latency() {
        let (rate, offset) = (1.0 - 40e-6, -3.2);
        let host_of = |device: f64| offset + rate * device;
        let mut map = ClockMap::new(32).expect("map");
        assert_eq!(map.host_s(1.0), None);
        let mut rng = Normal(7);
        for i in 0..16 {
            let device = 10.0 + 0.5 * f64::from(i);
            let latency = if i == 9 {
                4e-3
            } else {
                15e-6 + 60e-6 * rng.uniform()
            };
            map.push(device, host_of(device) + latency).expect("push");
        }
        let device = 10.0 + 0.5 * 15.0 + 1.0;
        let err = map.host_s(device).expect("mapped") - host_of(device);
        assert!((10e-6..85e-6).contains(&err), "error {err:e} s");
        assert!((map.rate() - rate).abs() < 8e-6, "rate {}", map.rate());
        map.push(1.0, 5.0).expect("reset");
        assert!((map.host_s(2.0).expect("one pair") - 6.0).abs() < 1e-12);
        let e = ClockMap::new(1).expect_err("window").to_string();
        assert!(e.contains("clock map window = 1"), "{e}");
        let e = map.push(f64::NAN, 0.0).expect_err("nan").to_string();
        assert!(e.contains("device timestamp"), "{e}");
    }

    /// A read's bracket is narrowed by the line's share: a K10CR1 read (6 bytes out, 12 back
    /// at 115200 baud 8N1: 0.52 and 1.04 ms) sent at 1 s and answered at 1.004 s latched in
    /// [1.00052, 1.00296] s (to 1e-12 s); no line leaves the round trip as it is; a round
    /// trip shorter than the line's share (a clock read late) keeps its proportion, so the
    /// bracket is one point, 1/3 of the way in, and never runs backwards.
    #[test]
    fn wire_times_narrow_the_bracket() {
        let wire = WireTimes::uart(6, 12, 115_200, 10);
        assert!((wire.request_s - 60.0 / 115_200.0).abs() < 1e-15);
        let s = PositionSample::bracketed(1.0, 1.004, wire, 0.5);
        assert!(
            (s.request_s - (1.0 + 60.0 / 115_200.0)).abs() < 1e-12,
            "{s:?}"
        );
        assert!(
            (s.reply_s - (1.004 - 120.0 / 115_200.0)).abs() < 1e-12,
            "{s:?}"
        );
        assert_eq!(s.angle_rad, 0.5);
        let none = PositionSample::bracketed(1.0, 1.004, WireTimes::default(), 0.5);
        assert_eq!((none.request_s, none.reply_s), (1.0, 1.004));
        let short = PositionSample::bracketed(1.0, 1.0009, wire, 0.5);
        assert!((short.round_trip_s()).abs() < 1e-12, "{short:?}");
        assert!((short.request_s - 1.0003).abs() < 1e-12, "{short:?}");
    }

    /// The events 100 us after each true end and the triggers' earliest ends 50 us before
    /// it (a camera clock equal to the host's). At the last frame's device time the interval
    /// is 150 us wide, the end is its middle, 25 us after the truth (within half the
    /// interval), with sigma 150 / sqrt 12 us (to 1e-12 s); without trigger bounds the end is
    /// the last event's, sigma 0. Carried 6.5 s past the last frame, each bound moves by up to
    /// the rate bound times 6.5 s, so the interval is 150 us + 2 x 2e-4 x 6.5 s wide and still
    /// holds the truth: the rate the map cannot know is in the sigma.
    #[test]
    fn triggers_bound_the_clock_map_from_below() {
        let mut map = ClockMap::new(16).expect("map");
        for i in 0..8 {
            let d = 10.0 + 0.5 * f64::from(i);
            map.push(d, d + 1e-4).expect("event");
        }
        let (host, sigma) = map.host_end_s(13.5).expect("mapped");
        assert!(
            (host - (13.5 + 1e-4)).abs() < 1e-12 && sigma == 0.0,
            "{host} {sigma}"
        );
        for i in 0..8 {
            let d = 10.0 + 0.5 * f64::from(i);
            map.push_earliest(d, d - 5e-5).expect("trigger");
        }
        let (host, sigma) = map.host_end_s(13.5).expect("mapped");
        assert!((host - (13.5 + 2.5e-5)).abs() < 1e-12, "{host}");
        assert!((sigma - 1.5e-4 / 12f64.sqrt()).abs() < 1e-12, "{sigma}");
        let (host, sigma) = map.host_end_s(20.0).expect("extrapolated");
        let width = 1.5e-4 + 2.0 * MAX_RATE_ERROR * 6.5;
        assert!((sigma - width / 12f64.sqrt()).abs() < 1e-12, "{sigma}");
        assert!((host - 20.0).abs() <= 0.5 * width, "{host}");
        let e = map
            .push_earliest(f64::NAN, 1.0)
            .expect_err("nan")
            .to_string();
        assert!(e.contains("earliest exposure end"), "{e}");
    }

    /// A camera clock 150 ppm fast (within the rate bound) with events seen 20-2000 us late
    /// and triggers leaving 10-500 us early of their bound: every end the map gives, at each
    /// frame's device time just after its pair is pushed, lies within half its interval
    /// (sqrt 3 sigma) of the truth, over 2000 frames at 50 Hz; the line's rate alone would not
    /// say how far off it extrapolates.
    #[test]
    fn the_interval_holds_the_true_end_under_a_rate_error() {
        let mut map = ClockMap::new(64).expect("map");
        let mut rng = Normal(7);
        let mut worst = 0.0f64;
        for i in 0..2000 {
            let true_host = 100.0 + 0.02 * f64::from(i);
            let device = (true_host - 100.0) * (1.0 + 1.5e-4);
            let late = 2e-5 + 2e-3 * rng.uniform().powi(4);
            let early = 1e-5 + 4.9e-4 * rng.uniform();
            map.push(device, true_host + late).expect("event");
            map.push_earliest(device, true_host - early)
                .expect("trigger");
            let (host, sigma) = map.host_end_s(device).expect("mapped");
            let z = (host - true_host).abs() / (sigma * 3f64.sqrt());
            worst = worst.max(z);
        }
        assert!(worst <= 1.0 + 1e-9, "worst |error| / half-width {worst}");
    }

    /// Bad input is refused with the field named: too few samples, no spread in time, a
    /// window below 3, a zero speed, a reply before its request, a non-finite angle.
    #[test]
    fn bad_input_is_named() {
        let two = [sample(0.0, 0.0, 1e-3), sample(1.0, 1.0, 1e-3)];
        let e = SpinFit::fit(&two, 1e-9).expect_err("two").to_string();
        assert!(e.contains("needs 3"), "{e}");
        let same = [sample(1.0, 0.0, 1e-3); 3];
        let e = SpinFit::fit(&same, 1e-9)
            .expect_err("same time")
            .to_string();
        assert!(e.contains("no spread in time"), "{e}");
        let e = SpinTrack::new(2, 1.0, 1e-9)
            .expect_err("window")
            .to_string();
        assert!(e.contains("window = 2"), "{e}");
        let e = SpinTrack::new(8, 0.0, 1e-9).expect_err("speed").to_string();
        assert!(e.contains("nominal speed"), "{e}");
        let mut track = SpinTrack::new(8, 1.0, 1e-9).expect("track");
        let e = track
            .push(PositionSample {
                request_s: 1.0,
                reply_s: 0.5,
                angle_rad: 0.0,
            })
            .expect_err("reply first")
            .to_string();
        assert!(e.contains("round trip"), "{e}");
        let e = track
            .push(sample(0.0, f64::NAN, 1e-3))
            .expect_err("nan")
            .to_string();
        assert!(e.contains("position sample"), "{e}");
        assert!(track.is_empty());
    }
}
