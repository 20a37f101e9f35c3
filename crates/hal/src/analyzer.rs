//! The analyzer view: plans set the analyzer's transmission-axis angle `psi` in `[0, pi)` (in
//! the camera frame) and this module turns it into stage angles or wheel slots.

use crate::{signed_difference, wrap, DeviceError, ErrorKind, FilterWheel, Rotator, TURN_RAD};
use std::f64::consts::PI;

/// Which side a rotator approaches its target from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Approach {
    /// Always finish with a move in the positive direction (backlash taken up the same way).
    Positive,
    /// Always finish with a move in the negative direction.
    Negative,
    /// The short way (for direct-drive stages without backlash).
    Either,
}

/// A polarizer fitted in a wheel slot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SlotAngle {
    /// The slot index.
    pub slot: usize,
    /// Its polarizer's transmission axis in the camera frame, radians.
    pub angle_rad: f64,
}

/// An analyzer: a polarizer whose angle can be set.
#[allow(async_fn_in_trait)]
pub trait Analyzer {
    /// The angles it can take, radians in `[0, pi)`, or `None` for any angle (a rotator).
    fn available_angles_rad(&self) -> Option<Vec<f64>>;
    /// Sets the transmission axis to `psi_rad` (any real; taken modulo pi) and returns the
    /// angle reached, radians in `[0, pi)`.
    async fn set_angle(&mut self, psi_rad: f64) -> Result<f64, DeviceError>;
}

/// An analyzer on a rotation stage: stage angle = `psi + zero_offset_rad` (modulo pi).
#[derive(Debug)]
pub struct OnRotator<R> {
    /// The stage.
    pub rotator: R,
    /// Stage angle at which the analyzer's axis is along the camera's x axis, radians.
    pub zero_offset_rad: f64,
    /// Approach direction.
    pub approach: Approach,
    /// How far before the target an approaching move starts, radians (> the backlash).
    pub overshoot_rad: f64,
}

impl<R: Rotator> OnRotator<R> {
    /// The stage's moves for target `t` from `current`: (total travel, waypoints).
    fn plan(&self, current: f64, t: f64) -> (f64, Vec<f64>) {
        let d = signed_difference(t, current, TURN_RAD);
        let o = self.overshoot_rad.abs();
        match self.approach {
            Approach::Either => (d.abs(), vec![t]),
            Approach::Positive | Approach::Negative => {
                let sign = if self.approach == Approach::Positive {
                    1.0
                } else {
                    -1.0
                };
                if d * sign >= o {
                    (d.abs(), vec![t])
                } else {
                    let pre = wrap(t - sign * o, TURN_RAD);
                    (
                        signed_difference(pre, current, TURN_RAD).abs() + o,
                        vec![pre, t],
                    )
                }
            }
        }
    }
}

impl<R: Rotator> Analyzer for OnRotator<R> {
    fn available_angles_rad(&self) -> Option<Vec<f64>> {
        None
    }

    async fn set_angle(&mut self, psi_rad: f64) -> Result<f64, DeviceError> {
        if !psi_rad.is_finite() {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                self.rotator.info().model.clone(),
                format!("analyzer angle {psi_rad} rad is not finite"),
            ));
        }
        let current = self.rotator.position_rad().await?;
        // The polarizer repeats every pi: two stage angles give the same analyzer angle.
        let t0 = wrap(psi_rad + self.zero_offset_rad, TURN_RAD);
        let t1 = wrap(t0 + PI, TURN_RAD);
        let (p0, p1) = (self.plan(current, t0), self.plan(current, t1));
        let (_, waypoints) = if p1.0 < p0.0 { p1 } else { p0 };
        let mut reached = current;
        for w in waypoints {
            reached = self.rotator.move_to(w).await?;
        }
        Ok(wrap(reached - self.zero_offset_rad, PI))
    }
}

/// An analyzer made of fixed polarizers in a wheel.
#[derive(Debug)]
pub struct OnWheel<W> {
    /// The wheel.
    pub wheel: W,
    /// The polarizers fitted.
    pub fitted: Vec<SlotAngle>,
    /// How far a requested angle may be from a fitted one, radians.
    pub tolerance_rad: f64,
}

impl<W: FilterWheel> Analyzer for OnWheel<W> {
    fn available_angles_rad(&self) -> Option<Vec<f64>> {
        Some(self.fitted.iter().map(|s| wrap(s.angle_rad, PI)).collect())
    }

    async fn set_angle(&mut self, psi_rad: f64) -> Result<f64, DeviceError> {
        let best = self
            .fitted
            .iter()
            .map(|s| (signed_difference(s.angle_rad, psi_rad, PI).abs(), *s))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let name = self.wheel.slots().join(", ");
        let Some((_, slot)) = best.filter(|(d, _)| *d <= self.tolerance_rad) else {
            let fitted: Vec<String> = self
                .fitted
                .iter()
                .map(|s| format!("{:.2}", wrap(s.angle_rad, PI).to_degrees()))
                .collect();
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                format!("wheel [{name}]"),
                format!(
                    "analyzer angle {:.2} deg is not fitted: allowed {} deg (within {:.2} deg)",
                    wrap(psi_rad, PI).to_degrees(),
                    fitted.join(", "),
                    self.tolerance_rad.to_degrees()
                ),
            ));
        };
        let got = self.wheel.select(slot.slot).await?;
        if got != slot.slot {
            return Err(DeviceError::new(
                ErrorKind::Stalled,
                format!("wheel [{name}]"),
                format!("asked for slot {}, read back slot {got}", slot.slot),
            ));
        }
        Ok(wrap(slot.angle_rad, PI))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::RotatorInfo;
    use std::future::Future;
    use std::pin::pin;
    use std::task::{Context, Poll, Waker};

    /// Runs a future that never waits (the fakes below answer at once).
    fn run<F: Future>(f: F) -> F::Output {
        let mut f = pin!(f);
        let mut cx = Context::from_waker(Waker::noop());
        match f.as_mut().poll(&mut cx) {
            Poll::Ready(v) => v,
            Poll::Pending => panic!("the fake devices never wait"),
        }
    }

    /// A stage that goes the short way and records every move's signed travel.
    struct FakeStage {
        info: RotatorInfo,
        at: f64,
        moves: Vec<f64>,
    }

    impl FakeStage {
        fn new(at_deg: f64) -> Self {
            FakeStage {
                info: RotatorInfo {
                    model: "fake".into(),
                    counts_per_turn: 262_144,
                    tolerance_rad: 1e-4,
                },
                at: at_deg.to_radians(),
                moves: Vec::new(),
            }
        }
    }

    impl Rotator for FakeStage {
        fn info(&self) -> &RotatorInfo {
            &self.info
        }
        async fn home(&mut self) -> Result<(), DeviceError> {
            self.at = 0.0;
            Ok(())
        }
        async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
            self.moves
                .push(signed_difference(angle_rad, self.at, TURN_RAD));
            self.at = wrap(angle_rad, TURN_RAD);
            Ok(self.at)
        }
        async fn position_rad(&mut self) -> Result<f64, DeviceError> {
            Ok(self.at)
        }
    }

    fn analyzer(at_deg: f64, approach: Approach) -> OnRotator<FakeStage> {
        OnRotator {
            rotator: FakeStage::new(at_deg),
            zero_offset_rad: 10f64.to_radians(),
            approach,
            overshoot_rad: 5f64.to_radians(),
        }
    }

    fn close(a: f64, b: f64) -> bool {
        signed_difference(a, b, PI).abs() < 1e-12
    }

    /// With a positive approach the last move is always positive and at least the overshoot,
    /// whatever the start; the angle reached is the one asked (modulo pi), offset removed.
    #[test]
    fn positive_approach_ends_with_a_positive_move() {
        for start in [0.0, 30.0, 54.0, 56.0, 100.0, 200.0, 359.0] {
            for psi in [0.0, 45.0, 90.0, 135.0, 179.9] {
                let mut a = analyzer(start, Approach::Positive);
                let got = run(a.set_angle(f64::to_radians(psi))).unwrap();
                assert!(close(got, psi.to_radians()), "{start} -> {psi}: {got}");
                let last = *a.rotator.moves.last().unwrap();
                assert!(
                    last >= 5f64.to_radians() - 1e-12,
                    "{start} -> {psi}: last move {last}"
                );
                // The polarizer's period is used: no move longer than half a turn plus the
                // overshoot.
                let travel: f64 = a.rotator.moves.iter().map(|m| m.abs()).sum();
                assert!(
                    travel <= PI / 2.0 + 2.0 * 5f64.to_radians() + 1e-9,
                    "{travel}"
                );
            }
        }
        // Negative approach mirrors it.
        let mut a = analyzer(0.0, Approach::Negative);
        run(a.set_angle(0.3)).unwrap();
        assert!(*a.rotator.moves.last().unwrap() <= -5f64.to_radians() + 1e-12);
    }

    /// The short way: one move, at most a quarter turn (the analyzer's period is half a turn).
    #[test]
    fn either_takes_the_short_way() {
        let mut a = analyzer(350.0, Approach::Either);
        let got = run(a.set_angle(f64::to_radians(170.0))).unwrap();
        assert!(close(got, f64::to_radians(170.0)));
        assert_eq!(a.rotator.moves.len(), 1);
        assert!(a.rotator.moves[0].abs() <= PI / 2.0 + 1e-12);
        let bad = run(a.set_angle(f64::NAN)).unwrap_err();
        assert_eq!(bad.kind(), ErrorKind::OutOfRange);
    }

    struct FakeWheel {
        labels: Vec<String>,
        at: Option<usize>,
        stuck: bool,
    }

    impl FilterWheel for FakeWheel {
        fn slots(&self) -> &[String] {
            &self.labels
        }
        async fn select(&mut self, slot: usize) -> Result<usize, DeviceError> {
            if slot >= self.labels.len() {
                return Err(DeviceError::new(ErrorKind::OutOfRange, "fake", "slot"));
            }
            if !self.stuck {
                self.at = Some(slot);
            }
            Ok(self.at.unwrap_or(0))
        }
        async fn slot(&mut self) -> Result<Option<usize>, DeviceError> {
            Ok(self.at)
        }
    }

    fn wheel(stuck: bool) -> OnWheel<FakeWheel> {
        OnWheel {
            wheel: FakeWheel {
                labels: (0..6).map(|i| format!("P{i}")).collect(),
                at: Some(0),
                stuck,
            },
            fitted: [0.0, 45.0, 90.0, 135.0]
                .iter()
                .enumerate()
                .map(|(i, d)| SlotAngle {
                    slot: i + 1,
                    angle_rad: f64::to_radians(*d),
                })
                .collect(),
            tolerance_rad: 0.5f64.to_radians(),
        }
    }

    /// A wheel maps angles (modulo pi) to the fitted slots; an angle not fitted is an
    /// OutOfRange error listing what is; a slot not reached is Stalled.
    #[test]
    fn wheel_maps_angles_to_slots() {
        let mut w = wheel(false);
        let got = run(w.set_angle(f64::to_radians(225.2))).unwrap();
        assert!(close(got, f64::to_radians(45.0)));
        assert_eq!(w.wheel.at, Some(2));
        let e = run(w.set_angle(f64::to_radians(60.0))).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(
            e.to_string().contains("60.00 deg") && e.to_string().contains("135.00"),
            "{e}"
        );
        assert_eq!(w.available_angles_rad().unwrap().len(), 4);
        let mut stuck = wheel(true);
        let e = run(stuck.set_angle(f64::to_radians(90.0))).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Stalled);
    }

    /// Wrapping helpers: wrap into [0, period), signed difference into (-period/2, period/2].
    #[test]
    fn wrapping() {
        assert!((wrap(-0.1, PI) - (PI - 0.1)).abs() < 1e-15);
        assert_eq!(wrap(PI, PI), 0.0);
        assert!((signed_difference(0.1, TURN_RAD - 0.1, TURN_RAD) - 0.2).abs() < 1e-12);
        assert!((signed_difference(PI, 0.0, TURN_RAD) - PI).abs() < 1e-15);
        assert!(ErrorKind::Timeout.is_transient() && !ErrorKind::Disconnected.is_transient());
    }
}
