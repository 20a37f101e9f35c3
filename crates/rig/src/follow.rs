//! A simulated camera behind a stage the rig does not simulate (a `simulate stage` started
//! apart, or a real stage): the camera cannot read that stage's true angle, so it renders
//! through the position the stage last reported. [`ReadBack`] wraps the stage's driver and
//! publishes every position it reads (after homing, after each move, on each position read);
//! the camera's angle source reads that value. A step-and-shoot run reads the stage back after
//! every move and before every frame's exposure, so each frame renders at the angle the run
//! records for it. A spinning analyzer cannot be followed this way: [`ReadBack`] offers no
//! continuous rotation, and the rig refuses a continuous plan on such a pair before it starts.

use polar_hal::{DeviceError, Rotator, RotatorInfo};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

/// The last position a stage reported, radians, shared with the camera that follows it.
#[derive(Debug, Clone, Default)]
pub struct ReportedAngle(Arc<AtomicU64>);

impl ReportedAngle {
    /// The last reported position, radians (0 before the first report).
    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(Ordering::Acquire))
    }

    fn set(&self, angle_rad: f64) {
        self.0.store(angle_rad.to_bits(), Ordering::Release);
    }
}

/// A stage's driver that publishes every position it reads to a [`ReportedAngle`].
pub struct ReadBack<R> {
    inner: R,
    angle: ReportedAngle,
}

impl<R: Rotator> ReadBack<R> {
    /// Wraps `inner`; its positions go to `angle`.
    pub fn new(inner: R, angle: ReportedAngle) -> ReadBack<R> {
        ReadBack { inner, angle }
    }
}

impl<R: Rotator> Rotator for ReadBack<R> {
    fn info(&self) -> &RotatorInfo {
        self.inner.info()
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.inner.home().await?;
        let at = self.inner.position_rad().await?;
        self.angle.set(at);
        Ok(())
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        let at = self.inner.move_to(angle_rad).await?;
        self.angle.set(at);
        Ok(at)
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        let at = self.inner.position_rad().await?;
        self.angle.set(at);
        Ok(at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use polar_hal::ErrorKind;

    /// A stage that is wherever it was last sent, exactly.
    struct Exact {
        info: RotatorInfo,
        at: f64,
    }

    impl Rotator for Exact {
        fn info(&self) -> &RotatorInfo {
            &self.info
        }
        async fn home(&mut self) -> Result<(), DeviceError> {
            self.at = 0.0;
            Ok(())
        }
        async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
            if !angle_rad.is_finite() {
                return Err(DeviceError::new(
                    ErrorKind::OutOfRange,
                    "exact",
                    "not finite",
                ));
            }
            self.at = angle_rad;
            Ok(angle_rad)
        }
        async fn position_rad(&mut self) -> Result<f64, DeviceError> {
            Ok(self.at)
        }
    }

    /// Every reported position reaches the camera's side bit for bit, a failed move leaves the
    /// last good one, and the wrapper offers no continuous rotation (so a spinning plan is
    /// refused rather than rendered at stale angles).
    #[test]
    fn positions_reach_the_follower() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let angle = ReportedAngle::default();
        let mut stage = ReadBack::new(
            Exact {
                info: RotatorInfo {
                    model: "exact".into(),
                    counts_per_turn: 360,
                    tolerance_rad: 1e-9,
                },
                at: 1.0,
            },
            angle.clone(),
        );
        rt.block_on(async {
            stage.home().await.expect("home");
            assert_eq!(angle.get(), 0.0);
            let at = stage.move_to(0.785).await.expect("move");
            assert_eq!(angle.get().to_bits(), at.to_bits());
            assert!(stage.move_to(f64::NAN).await.is_err());
            assert_eq!(angle.get(), 0.785);
            assert!(stage.spin(1.0).await.is_err());
        });
        assert_eq!(
            stage.continuous_support(),
            polar_hal::ContinuousSupport::None
        );
    }
}
