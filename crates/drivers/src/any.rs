//! One rotator type for the dialects chosen at run time (`--dialect native|elliptec`): the
//! [`Rotator`] trait uses `async fn`, so it is not object-safe, and an enum that delegates lets a
//! run, the CLI and the GUI hold either stage without being generic over it.

use crate::elliptec::ElliptecRotator;
use crate::native::NativeRotator;
use polar_hal::{DeviceError, Rotator, RotatorInfo};

/// A rotation stage of one of the supported dialects.
pub enum AnyRotator {
    /// Our firmware's stage.
    Native(NativeRotator),
    /// A Thorlabs Elliptec rotation mount (ELL14/ELL18).
    Elliptec(ElliptecRotator),
}

impl From<NativeRotator> for AnyRotator {
    fn from(r: NativeRotator) -> Self {
        AnyRotator::Native(r)
    }
}

impl From<ElliptecRotator> for AnyRotator {
    fn from(r: ElliptecRotator) -> Self {
        AnyRotator::Elliptec(r)
    }
}

impl Rotator for AnyRotator {
    fn info(&self) -> &RotatorInfo {
        match self {
            AnyRotator::Native(r) => r.info(),
            AnyRotator::Elliptec(r) => r.info(),
        }
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        match self {
            AnyRotator::Native(r) => r.home().await,
            AnyRotator::Elliptec(r) => r.home().await,
        }
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        match self {
            AnyRotator::Native(r) => r.move_to(angle_rad).await,
            AnyRotator::Elliptec(r) => r.move_to(angle_rad).await,
        }
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        match self {
            AnyRotator::Native(r) => r.position_rad().await,
            AnyRotator::Elliptec(r) => r.position_rad().await,
        }
    }

    fn supports_velocity(&self) -> bool {
        match self {
            AnyRotator::Native(r) => r.supports_velocity(),
            AnyRotator::Elliptec(r) => r.supports_velocity(),
        }
    }

    async fn set_velocity(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        match self {
            AnyRotator::Native(r) => r.set_velocity(rad_per_s).await,
            AnyRotator::Elliptec(r) => r.set_velocity(rad_per_s).await,
        }
    }
}
