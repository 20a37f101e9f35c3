//! Seeded fault injection for the simulated devices. Each knob is a probability per event (a
//! reply, a move) in `[0, 1]`; the same seed gives the same faults.

use rand_core::{Rng, SeedableRng};
use rand_xorshift::XorShiftRng;
use serde::Deserialize;

/// Fault knobs (TOML: every field optional, 0 by default).
#[derive(Debug, Clone, Copy, PartialEq, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultProfile {
    /// A reply is never sent.
    pub drop_reply: f64,
    /// One byte of a reply is flipped.
    pub corrupt_reply: f64,
    /// A reply is sent twice.
    pub duplicate_reply: f64,
    /// A command is refused with Busy although the device is idle.
    pub spurious_busy: f64,
    /// A move stalls half way: the motor stops, the stalled flag is set, MotionDone reports
    /// where it stopped.
    pub stall: f64,
    /// After a command, the device resets on its own (Boot notice, position lost).
    pub spontaneous_reset: f64,
}

/// Errors in a fault profile: the field, the value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FaultError {
    /// The TOML does not parse or has an unknown key.
    #[error("fault profile: {0}")]
    Toml(String),
    /// A probability outside `[0, 1]`.
    #[error("fault profile: {field} = {value} is out of range: allowed [0, 1]")]
    Range {
        /// The knob.
        field: &'static str,
        /// The value.
        value: f64,
    },
}

impl FaultProfile {
    /// Parses and validates TOML.
    pub fn from_toml_str(text: &str) -> Result<Self, FaultError> {
        let p: FaultProfile = toml::from_str(text).map_err(|e| FaultError::Toml(e.to_string()))?;
        p.validate()?;
        Ok(p)
    }

    /// Checks every knob is a probability.
    pub fn validate(&self) -> Result<(), FaultError> {
        for (field, value) in [
            ("drop_reply", self.drop_reply),
            ("corrupt_reply", self.corrupt_reply),
            ("duplicate_reply", self.duplicate_reply),
            ("spurious_busy", self.spurious_busy),
            ("stall", self.stall),
            ("spontaneous_reset", self.spontaneous_reset),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(FaultError::Range { field, value });
            }
        }
        Ok(())
    }
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
        p > 0.0 && self.uniform() < p
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
}

#[cfg(test)]
mod tests {
    use super::*;

    /// TOML knobs parse, unknown keys and out-of-range values are errors naming the field.
    #[test]
    fn profile_parses_and_validates() {
        let p = FaultProfile::from_toml_str("drop_reply = 0.1\nstall = 0.5\n").unwrap();
        assert_eq!(p.drop_reply, 0.1);
        assert_eq!(p.corrupt_reply, 0.0);
        let e = FaultProfile::from_toml_str("drop_reply = 1.5").unwrap_err();
        assert!(e.to_string().contains("drop_reply = 1.5"), "{e}");
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
}
