//! Physical motion of a simulated axis: trapezoidal velocity profiles (or triangular when the
//! move is too short to reach the cruise velocity), gear backlash between motor and output,
//! and a noisy encoder on the motor.

/// One move: from `start` to `target` (motor counts), beginning at `t0_s`, with cruise velocity
/// `v` (counts/s) and acceleration `a` (counts/s^2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    /// Start position, counts.
    pub start: f64,
    /// End position, counts.
    pub target: f64,
    /// Start time, seconds.
    pub t0_s: f64,
    /// Cruise velocity, counts/s (> 0).
    pub v: f64,
    /// Acceleration, counts/s^2 (> 0).
    pub a: f64,
}

impl Profile {
    /// Time to accelerate and the peak velocity reached.
    fn shape(&self) -> (f64, f64, f64) {
        let d = (self.target - self.start).abs();
        let ta = self.v / self.a;
        if self.a * ta * ta >= d {
            // Triangular: accelerate to half way, decelerate.
            let ta = (d / self.a).sqrt();
            (ta, self.a * ta, 0.0)
        } else {
            (ta, self.v, (d - self.a * ta * ta) / self.v)
        }
    }

    /// Duration of the move, seconds.
    pub fn duration_s(&self) -> f64 {
        let (ta, _, tc) = self.shape();
        2.0 * ta + tc
    }

    /// Time the move ends, seconds.
    pub fn end_s(&self) -> f64 {
        self.t0_s + self.duration_s()
    }

    /// Direction: +1 or -1 (+1 for a null move).
    pub fn direction(&self) -> f64 {
        if self.target < self.start {
            -1.0
        } else {
            1.0
        }
    }

    /// Position at time `t_s`.
    pub fn position(&self, t_s: f64) -> f64 {
        let (ta, vp, tc) = self.shape();
        let t = (t_s - self.t0_s).clamp(0.0, 2.0 * ta + tc);
        let x = if t <= ta {
            0.5 * self.a * t * t
        } else if t <= ta + tc {
            0.5 * self.a * ta * ta + vp * (t - ta)
        } else {
            let td = 2.0 * ta + tc - t;
            (self.target - self.start).abs() - 0.5 * self.a * td * td
        };
        self.start + self.direction() * x
    }

    /// Velocity at time `t_s`, counts/s (signed).
    pub fn velocity(&self, t_s: f64) -> f64 {
        let (ta, vp, tc) = self.shape();
        let t = t_s - self.t0_s;
        let speed = if t <= 0.0 || t >= 2.0 * ta + tc {
            0.0
        } else if t <= ta {
            self.a * t
        } else if t <= ta + tc {
            vp
        } else {
            self.a * (2.0 * ta + tc - t)
        };
        self.direction() * speed
    }

    /// The profile that stops as soon as possible from time `t_s` (decelerating at `a`).
    pub fn stopped_at(&self, t_s: f64) -> Profile {
        let x = self.position(t_s);
        let v = self.velocity(t_s);
        let braking = v * v / (2.0 * self.a);
        let target = x + v.signum() * braking;
        // Past the original target's braking point the original profile already stops there.
        let target = if (target - self.start).abs() > (self.target - self.start).abs() {
            self.target
        } else {
            target
        };
        Profile {
            start: x,
            target,
            t0_s: t_s,
            v: v.abs().max(1e-9),
            a: self.a,
        }
    }
}

/// Velocity mode: from position `start` turning at `v0` (counts/s, signed) at time `t0_s`, the
/// axis changes speed at acceleration `a` (counts/s^2, > 0) to `v1` and holds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ramp {
    /// Position at `t0_s`, counts.
    pub start: f64,
    /// Velocity at `t0_s`, counts/s.
    pub v0: f64,
    /// Velocity held after the ramp, counts/s.
    pub v1: f64,
    /// Start time, seconds.
    pub t0_s: f64,
    /// Acceleration, counts/s^2 (> 0).
    pub a: f64,
}

impl Ramp {
    /// The time the ramp ends and the velocity `v1` is reached, seconds.
    pub fn settled_s(&self) -> f64 {
        self.t0_s + (self.v1 - self.v0).abs() / self.a
    }

    /// Velocity at `t_s` (signed).
    pub fn velocity(&self, t_s: f64) -> f64 {
        let t = (t_s - self.t0_s).max(0.0);
        let dv = self.v1 - self.v0;
        if t >= dv.abs() / self.a {
            self.v1
        } else {
            self.v0 + dv.signum() * self.a * t
        }
    }

    /// Position at `t_s`.
    pub fn position(&self, t_s: f64) -> f64 {
        let t = (t_s - self.t0_s).max(0.0);
        let dv = self.v1 - self.v0;
        let tr = dv.abs() / self.a;
        if t <= tr {
            self.start + self.v0 * t + 0.5 * dv.signum() * self.a * t * t
        } else {
            self.start + 0.5 * (self.v0 + self.v1) * tr + self.v1 * (t - tr)
        }
    }
}

/// The output shaft lags the motor by half the backlash against the last direction of motion:
/// output = motor - direction * backlash / 2.
pub fn output_from_motor(motor: f64, direction: f64, backlash: f64) -> f64 {
    motor - direction * 0.5 * backlash
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A long move reaches the cruise velocity; its duration is d/v + v/a; it starts and ends
    /// where asked, monotonic, with continuous velocity.
    #[test]
    fn trapezoid_kinematics() {
        let p = Profile {
            start: 100.0,
            target: -9_900.0,
            t0_s: 1.0,
            v: 2_000.0,
            a: 10_000.0,
        };
        assert!((p.duration_s() - (10_000.0 / 2_000.0 + 2_000.0 / 10_000.0)).abs() < 1e-12);
        assert_eq!(p.position(0.0), 100.0);
        assert!((p.position(p.end_s() + 1.0) + 9_900.0).abs() < 1e-9);
        let mut last = p.position(1.0);
        for k in 1..=1000 {
            let t = 1.0 + p.duration_s() * k as f64 / 1000.0;
            let x = p.position(t);
            assert!(x <= last + 1e-9);
            last = x;
        }
        assert!((p.velocity(3.0) + 2_000.0).abs() < 1e-9);
    }

    /// A ramp from rest reaches its velocity after v/a with position v^2/(2a), then turns at
    /// that velocity; a ramp down to 0 ends where v^2/(2a) says.
    #[test]
    fn ramp_kinematics() {
        let up = Ramp {
            start: 10.0,
            v0: 0.0,
            v1: -3_000.0,
            t0_s: 2.0,
            a: 12_000.0,
        };
        assert!((up.settled_s() - 2.25).abs() < 1e-12);
        assert!((up.position(2.25) - (10.0 - 3_000.0f64.powi(2) / 24_000.0)).abs() < 1e-9);
        assert!((up.position(3.25) - up.position(2.25) + 3_000.0).abs() < 1e-9);
        assert_eq!(up.velocity(5.0), -3_000.0);
        let down = Ramp {
            start: 0.0,
            v0: 3_000.0,
            v1: 0.0,
            t0_s: 0.0,
            a: 12_000.0,
        };
        assert!((down.position(10.0) - 375.0).abs() < 1e-9);
        assert_eq!(down.velocity(10.0), 0.0);
    }

    /// A short move is triangular: duration 2 sqrt(d/a), peak velocity below the cruise.
    #[test]
    fn triangle_kinematics() {
        let p = Profile {
            start: 0.0,
            target: 100.0,
            t0_s: 0.0,
            v: 2_000.0,
            a: 10_000.0,
        };
        assert!((p.duration_s() - 2.0 * (100.0f64 / 10_000.0).sqrt()).abs() < 1e-12);
        assert!((p.position(p.duration_s() / 2.0) - 50.0).abs() < 1e-9);
        // Stopping half way through acceleration ends before the target.
        let s = p.stopped_at(p.duration_s() / 4.0);
        assert!(s.target < 100.0 && s.target > s.start);
    }
}
