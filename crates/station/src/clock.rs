//! The station's clock for schedules: the system's, or in simulation one that starts at a
//! chosen instant and runs `speed` times fast, so a whole day of sun-driven items runs in
//! minutes on the simulated rig.

use std::time::Instant;

/// Station time, Unix seconds.
#[derive(Debug, Clone)]
pub struct Clock {
    simulated: bool,
    speed: f64,
    origin_unix: f64,
    origin: Instant,
}

impl Clock {
    /// The system's clock.
    pub fn system() -> Clock {
        Clock {
            simulated: false,
            speed: 1.0,
            origin_unix: crate::now_unix() as f64,
            origin: Instant::now(),
        }
    }

    /// A simulated clock: `start_unix` now, running `speed` times fast.
    pub fn simulated(start_unix: u64, speed: f64) -> Clock {
        Clock {
            simulated: true,
            speed,
            origin_unix: start_unix as f64,
            origin: Instant::now(),
        }
    }

    /// Whether this is the system's clock.
    pub fn is_system(&self) -> bool {
        !self.simulated
    }

    /// Now, Unix seconds.
    pub fn now_unix(&self) -> u64 {
        if !self.simulated {
            return crate::now_unix();
        }
        (self.origin_unix + self.origin.elapsed().as_secs_f64() * self.speed).max(0.0) as u64
    }

    /// How many times fast it runs.
    pub fn speed(&self) -> f64 {
        self.speed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_simulated_clock_starts_where_asked_and_runs_fast() {
        let c = Clock::simulated(1_000_000, 1000.0);
        let t0 = c.now_unix();
        assert!((1_000_000..1_000_100).contains(&t0), "{t0}");
        std::thread::sleep(std::time::Duration::from_millis(50));
        let t1 = c.now_unix();
        assert!(t1 >= t0 + 40, "50 ms at 1000x is about 50 s: {t0} -> {t1}");
        assert!(Clock::system().is_system());
    }
}
