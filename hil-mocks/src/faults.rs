//! Seeded fault injection for the simulated devices. Probabilities are per event (a reply, a
//! command, a move) in `[0, 1]`; durations are seconds in `[0, 60]`; the same seed gives the same
//! faults.
//!
//! Two layers use the knobs: the device simulators (replies dropped, corrupted, duplicated;
//! busy; stall; reset; thermal cut-out) and the transport server in [`crate::serve`] (chunked
//! and coalesced reads, latency, late replies, garbage, stale bytes at open, unplug and replug).

use rand_core::{Rng, SeedableRng};
use rand_xorshift::XorShiftRng;
use serde::Deserialize;

/// Fault knobs (TOML: every field optional; all off by default, so a simulated device behaves as
/// the healthy real one).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultProfile {
    /// Device: a reply is never sent.
    pub drop_reply: f64,
    /// Device: one bit of a reply is flipped.
    pub corrupt_reply: f64,
    /// Device: a reply is sent twice.
    pub duplicate_reply: f64,
    /// Device: a motion command is refused as busy although the device is idle.
    pub spurious_busy: f64,
    /// Device: a move stalls half way (position frozen there, the dialect's stall report).
    pub stall: f64,
    /// Device: after a command, the device resets on its own (position and datum lost).
    pub spontaneous_reset: f64,
    /// Device: the motor's duty cycle over the last [`THERMAL_WINDOW_S`] above which moves are
    /// refused with the dialect's thermal error until it cools; 0 = never.
    pub thermal_duty: f64,
    /// Device (Elliptec): a move command (`ma`, `mr`, `fw`, `bw`) arriving less than
    /// [`crate::elliptec::QUICK_MOVE_S`] after the previous motion ended goes to position 0
    /// instead, and is still answered `PO` with no error. pylablib's driver notes a real module
    /// "can" do this when commanded too soon (it waits 0.1 s before every move); most public
    /// clients send moves back to back and work on real modules, so it is a sometime fault, not
    /// the device's normal behaviour. Default 0 (never).
    pub quick_move_to_zero: f64,
    /// Transport: a reply is delivered in random small pieces with short gaps between them.
    pub chunk_reads: f64,
    /// Transport: a reply is held back up to 50 ms and delivered together with what follows.
    pub coalesce_replies: f64,
    /// Transport: fixed delay added to every reply, seconds.
    pub latency_s: f64,
    /// Transport: a reply arrives `late_by_s` late (after a driver's deadline, so it is stale
    /// for the next request).
    pub late_reply: f64,
    /// Transport: how late a late reply is, seconds (default 4).
    pub late_by_s: f64,
    /// Transport: 1 to 8 random bytes precede a reply (line noise).
    pub garbage: f64,
    /// Transport: this many stale bytes wait in the port when it is opened.
    pub stale_bytes_at_open: u32,
    /// Transport: after a command, the device is unplugged; it comes back power-cycled at a
    /// new port after `replug_s`.
    pub unplug: f64,
    /// Transport: how long an unplugged device stays away, seconds (default 0.5).
    pub replug_s: f64,
}

impl Default for FaultProfile {
    fn default() -> Self {
        FaultProfile {
            drop_reply: 0.0,
            corrupt_reply: 0.0,
            duplicate_reply: 0.0,
            spurious_busy: 0.0,
            stall: 0.0,
            spontaneous_reset: 0.0,
            thermal_duty: 0.0,
            quick_move_to_zero: 0.0,
            chunk_reads: 0.0,
            coalesce_replies: 0.0,
            latency_s: 0.0,
            late_reply: 0.0,
            late_by_s: 4.0,
            garbage: 0.0,
            stale_bytes_at_open: 0,
            unplug: 0.0,
            replug_s: 0.5,
        }
    }
}

/// The window over which the thermal duty cycle is measured, seconds.
pub const THERMAL_WINDOW_S: f64 = 10.0;

/// Errors in a fault profile: the field, the value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FaultError {
    /// The TOML does not parse or has an unknown key.
    #[error("fault profile: {0}")]
    Toml(String),
    /// A knob outside its range.
    #[error("fault profile: {field} = {value} is out of range: allowed {range}")]
    Range {
        /// The knob.
        field: &'static str,
        /// The value.
        value: f64,
        /// The allowed range.
        range: &'static str,
    },
}

impl FaultProfile {
    /// Parses and validates TOML.
    pub fn from_toml_str(text: &str) -> Result<Self, FaultError> {
        let p: FaultProfile = toml::from_str(text).map_err(|e| FaultError::Toml(e.to_string()))?;
        p.validate()?;
        Ok(p)
    }

    /// Checks every probability is in `[0, 1]` and every duration in `[0, 60]` s.
    pub fn validate(&self) -> Result<(), FaultError> {
        for (field, value) in [
            ("drop_reply", self.drop_reply),
            ("corrupt_reply", self.corrupt_reply),
            ("duplicate_reply", self.duplicate_reply),
            ("spurious_busy", self.spurious_busy),
            ("stall", self.stall),
            ("spontaneous_reset", self.spontaneous_reset),
            ("thermal_duty", self.thermal_duty),
            ("quick_move_to_zero", self.quick_move_to_zero),
            ("chunk_reads", self.chunk_reads),
            ("coalesce_replies", self.coalesce_replies),
            ("late_reply", self.late_reply),
            ("garbage", self.garbage),
            ("unplug", self.unplug),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(FaultError::Range {
                    field,
                    value,
                    range: "[0, 1]",
                });
            }
        }
        for (field, value) in [
            ("latency_s", self.latency_s),
            ("late_by_s", self.late_by_s),
            ("replug_s", self.replug_s),
        ] {
            if !(0.0..=60.0).contains(&value) {
                return Err(FaultError::Range {
                    field,
                    value,
                    range: "[0, 60] s",
                });
            }
        }
        if self.stale_bytes_at_open > 4096 {
            return Err(FaultError::Range {
                field: "stale_bytes_at_open",
                value: self.stale_bytes_at_open as f64,
                range: "[0, 4096]",
            });
        }
        Ok(())
    }
}

/// Chances that came up, in this process, across every simulator (for fault campaigns: the
/// fault decisions are the chances; see [`faults_fired`]).
static FIRED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// How many [`Dice::chance`] calls with a nonzero probability came up in this process: the
/// faults every simulator injected (plus the Elliptec simulator's unsolicited status reports).
pub fn faults_fired() -> u64 {
    FIRED.load(std::sync::atomic::Ordering::Relaxed)
}

/// A seeded source of fault decisions and noise.
#[derive(Debug, Clone)]
pub struct Dice {
    rng: XorShiftRng,
}

impl Dice {
    /// Seeded.
    pub fn new(seed: u64) -> Self {
        Dice {
            rng: XorShiftRng::seed_from_u64(seed),
        }
    }

    /// Uniform in `[0, 1)` (53 random bits).
    pub fn uniform(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        let hit = p > 0.0 && self.uniform() < p;
        if hit {
            FIRED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        hit
    }

    /// A standard normal deviate (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }

    /// An index in `0..n` (`n > 0`).
    pub fn index(&mut self, n: usize) -> usize {
        ((self.uniform() * n as f64) as usize).min(n.saturating_sub(1))
    }

    /// A random byte.
    pub fn byte(&mut self) -> u8 {
        (self.rng.next_u32() >> 24) as u8
    }

    /// A reply through the device-level reply faults: dropped (empty), one bit flipped
    /// (never in the last byte, so a frame or line still ends), or sent twice.
    pub fn reply_faults(&mut self, faults: &FaultProfile, mut bytes: Vec<u8>) -> Vec<u8> {
        if self.chance(faults.drop_reply) {
            return Vec::new();
        }
        if self.chance(faults.corrupt_reply) && bytes.len() > 1 {
            let i = self.index(bytes.len() - 1);
            bytes[i] ^= 1 << self.index(8);
        }
        if self.chance(faults.duplicate_reply) {
            let again = bytes.clone();
            bytes.extend(again);
        }
        bytes
    }
}

/// The motor's recent running time, for the thermal cut-out.
#[derive(Debug, Clone, Default)]
pub struct DutyCycle {
    /// (start, end) of recent moves, seconds.
    runs: Vec<(f64, f64)>,
}

impl DutyCycle {
    /// Records that the motor runs from `start_s` to `end_s`.
    pub fn record(&mut self, start_s: f64, end_s: f64) {
        self.runs.retain(|&(_, e)| e > start_s - THERMAL_WINDOW_S);
        self.runs.push((start_s, end_s));
    }

    /// The fraction of the window `[now - W, now]` the motor ran.
    pub fn duty(&self, now_s: f64) -> f64 {
        let from = now_s - THERMAL_WINDOW_S;
        let on: f64 = self
            .runs
            .iter()
            .map(|&(s, e)| (e.min(now_s) - s.max(from)).max(0.0))
            .sum();
        on / THERMAL_WINDOW_S
    }

    /// Whether a move must be refused at `now_s` under `faults.thermal_duty`.
    pub fn too_hot(&self, faults: &FaultProfile, now_s: f64) -> bool {
        faults.thermal_duty > 0.0 && self.duty(now_s) > faults.thermal_duty
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// TOML knobs parse (the quick-move fault off unless set), unknown keys and out-of-range
    /// values are errors naming the field.
    #[test]
    fn profile_parses_and_validates() {
        let p = FaultProfile::from_toml_str("drop_reply = 0.1\nstall = 0.5\n").unwrap();
        assert_eq!(p.drop_reply, 0.1);
        assert_eq!(p.corrupt_reply, 0.0);
        assert_eq!(p.late_by_s, 4.0);
        let e = FaultProfile::from_toml_str("drop_reply = 1.5").unwrap_err();
        assert!(e.to_string().contains("drop_reply = 1.5"), "{e}");
        let e = FaultProfile::from_toml_str("latency_s = -1").unwrap_err();
        assert!(e.to_string().contains("latency_s = -1"), "{e}");
        assert_eq!(p.quick_move_to_zero, 0.0, "off by default");
        let q = FaultProfile::from_toml_str("quick_move_to_zero = 0.25").unwrap();
        assert_eq!(q.quick_move_to_zero, 0.25);
        let e = FaultProfile::from_toml_str("quick_move_to_zero = 2").unwrap_err();
        assert!(e.to_string().contains("quick_move_to_zero = 2"), "{e}");
        let e = FaultProfile::from_toml_str("explode = 1").unwrap_err();
        assert!(e.to_string().contains("explode"), "{e}");
    }

    /// The dice are reproducible and roughly fair: 10^5 draws of chance(0.3) give 0.3 within
    /// 5 sigma (sigma = sqrt(0.21 / 1e5) = 1.45e-3); normals have mean 0 and variance 1 within
    /// 5 sigma.
    #[test]
    fn dice_are_seeded_and_fair() {
        let (mut a, mut b) = (Dice::new(7), Dice::new(7));
        assert!((0..100).all(|_| a.uniform() == b.uniform()));
        let mut d = Dice::new(1);
        let n = 100_000;
        let hits = (0..n).filter(|_| d.chance(0.3)).count() as f64 / n as f64;
        assert!((hits - 0.3).abs() < 5.0 * 1.45e-3, "{hits}");
        let xs: Vec<f64> = (0..n).map(|_| d.normal()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 5.0 / (n as f64).sqrt(), "{mean}");
        assert!((var - 1.0).abs() < 5.0 * (2.0 / n as f64).sqrt(), "{var}");
    }

    /// Two 3 s moves in the last 10 s are a duty of 0.6; at 13 s only the second is in the window.
    #[test]
    fn duty_cycle_over_the_window() {
        let mut d = DutyCycle::default();
        d.record(0.0, 3.0);
        d.record(5.0, 8.0);
        assert!((d.duty(8.0) - 0.6).abs() < 1e-12);
        assert!((d.duty(13.0) - 0.3).abs() < 1e-12);
        let hot = FaultProfile {
            thermal_duty: 0.5,
            ..Default::default()
        };
        assert!(d.too_hot(&hot, 8.0) && !d.too_hot(&hot, 13.0));
        assert!(!d.too_hot(&FaultProfile::default(), 8.0));
    }
}
