//! One rotator type and one wheel type for the dialects chosen at run time (`--dialect`, a rig
//! file's `[stage] dialect`): the [`Rotator`] and [`FilterWheel`] traits use `async fn`, so they
//! are not object-safe. [`AnyRotator`] and [`AnyWheel`] box any implementation behind an
//! object-safe twin of the trait whose methods return boxed futures, so a run, the CLI and the
//! GUI hold a stage of any dialect without being generic over it, and a new dialect needs no
//! change here (its registry line in [`crate::registry`] boxes its driver).

use polar_hal::{
    ContinuousSupport, DeviceError, FilterWheel, Rotator, RotatorInfo, TriggerPulse, WireTimes,
};
use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

/// A boxed future that may hold the device borrowed (drivers run on local tasks: not `Send`).
pub type LocalFuture<'a, T> = Pin<Box<dyn Future<Output = T> + 'a>>;

/// [`Rotator`] with boxed futures (object-safe).
trait DynRotator {
    fn info(&self) -> &RotatorInfo;
    fn home(&mut self) -> LocalFuture<'_, Result<(), DeviceError>>;
    fn move_to(&mut self, angle_rad: f64) -> LocalFuture<'_, Result<f64, DeviceError>>;
    fn position_rad(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>>;
    fn supports_velocity(&self) -> bool;
    fn set_velocity(&mut self, rad_per_s: f64) -> LocalFuture<'_, Result<(), DeviceError>>;
    fn continuous_support(&self) -> ContinuousSupport;
    fn spin(&mut self, rad_per_s: f64) -> LocalFuture<'_, Result<(), DeviceError>>;
    fn stop_spin(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>>;
    fn spin_position_rad(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>>;
    fn spin_read_wire(&self) -> WireTimes;
    fn arm_trigger(
        &mut self,
        first_rad: f64,
        interval_rad: f64,
        count: u32,
    ) -> LocalFuture<'_, Result<(), DeviceError>>;
    fn next_trigger(
        &mut self,
        timeout: Duration,
    ) -> LocalFuture<'_, Result<TriggerPulse, DeviceError>>;
}

impl<R: Rotator> DynRotator for R {
    fn info(&self) -> &RotatorInfo {
        Rotator::info(self)
    }
    fn home(&mut self) -> LocalFuture<'_, Result<(), DeviceError>> {
        Box::pin(Rotator::home(self))
    }
    fn move_to(&mut self, angle_rad: f64) -> LocalFuture<'_, Result<f64, DeviceError>> {
        Box::pin(Rotator::move_to(self, angle_rad))
    }
    fn position_rad(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>> {
        Box::pin(Rotator::position_rad(self))
    }
    fn supports_velocity(&self) -> bool {
        Rotator::supports_velocity(self)
    }
    fn set_velocity(&mut self, rad_per_s: f64) -> LocalFuture<'_, Result<(), DeviceError>> {
        Box::pin(Rotator::set_velocity(self, rad_per_s))
    }
    fn continuous_support(&self) -> ContinuousSupport {
        Rotator::continuous_support(self)
    }
    fn spin(&mut self, rad_per_s: f64) -> LocalFuture<'_, Result<(), DeviceError>> {
        Box::pin(Rotator::spin(self, rad_per_s))
    }
    fn stop_spin(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>> {
        Box::pin(Rotator::stop_spin(self))
    }
    fn spin_position_rad(&mut self) -> LocalFuture<'_, Result<f64, DeviceError>> {
        Box::pin(Rotator::spin_position_rad(self))
    }
    fn spin_read_wire(&self) -> WireTimes {
        Rotator::spin_read_wire(self)
    }
    fn arm_trigger(
        &mut self,
        first_rad: f64,
        interval_rad: f64,
        count: u32,
    ) -> LocalFuture<'_, Result<(), DeviceError>> {
        Box::pin(Rotator::arm_trigger(self, first_rad, interval_rad, count))
    }
    fn next_trigger(
        &mut self,
        timeout: Duration,
    ) -> LocalFuture<'_, Result<TriggerPulse, DeviceError>> {
        Box::pin(Rotator::next_trigger(self, timeout))
    }
}

/// A rotation stage of any dialect.
pub struct AnyRotator(Box<dyn DynRotator + Send>);

impl AnyRotator {
    /// Boxes a rotator.
    pub fn new<R: Rotator + Send + 'static>(rotator: R) -> AnyRotator {
        AnyRotator(Box::new(rotator))
    }
}

impl Rotator for AnyRotator {
    fn info(&self) -> &RotatorInfo {
        self.0.info()
    }

    async fn home(&mut self) -> Result<(), DeviceError> {
        self.0.home().await
    }

    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
        self.0.move_to(angle_rad).await
    }

    async fn position_rad(&mut self) -> Result<f64, DeviceError> {
        self.0.position_rad().await
    }

    fn supports_velocity(&self) -> bool {
        self.0.supports_velocity()
    }

    async fn set_velocity(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        self.0.set_velocity(rad_per_s).await
    }

    fn continuous_support(&self) -> ContinuousSupport {
        self.0.continuous_support()
    }

    async fn spin(&mut self, rad_per_s: f64) -> Result<(), DeviceError> {
        self.0.spin(rad_per_s).await
    }

    async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        self.0.stop_spin().await
    }

    async fn spin_position_rad(&mut self) -> Result<f64, DeviceError> {
        self.0.spin_position_rad().await
    }

    fn spin_read_wire(&self) -> WireTimes {
        self.0.spin_read_wire()
    }

    async fn arm_trigger(
        &mut self,
        first_rad: f64,
        interval_rad: f64,
        count: u32,
    ) -> Result<(), DeviceError> {
        self.0.arm_trigger(first_rad, interval_rad, count).await
    }

    async fn next_trigger(&mut self, timeout: Duration) -> Result<TriggerPulse, DeviceError> {
        self.0.next_trigger(timeout).await
    }
}

/// [`FilterWheel`] with boxed futures (object-safe).
trait DynWheel {
    fn slots(&self) -> &[String];
    fn select(&mut self, slot: usize) -> LocalFuture<'_, Result<usize, DeviceError>>;
    fn slot(&mut self) -> LocalFuture<'_, Result<Option<usize>, DeviceError>>;
}

impl<W: FilterWheel> DynWheel for W {
    fn slots(&self) -> &[String] {
        FilterWheel::slots(self)
    }
    fn select(&mut self, slot: usize) -> LocalFuture<'_, Result<usize, DeviceError>> {
        Box::pin(FilterWheel::select(self, slot))
    }
    fn slot(&mut self) -> LocalFuture<'_, Result<Option<usize>, DeviceError>> {
        Box::pin(FilterWheel::slot(self))
    }
}

/// A filter wheel or slider of any dialect.
pub struct AnyWheel(Box<dyn DynWheel + Send>);

impl AnyWheel {
    /// Boxes a wheel.
    pub fn new<W: FilterWheel + Send + 'static>(wheel: W) -> AnyWheel {
        AnyWheel(Box::new(wheel))
    }
}

impl FilterWheel for AnyWheel {
    fn slots(&self) -> &[String] {
        self.0.slots()
    }

    async fn select(&mut self, slot: usize) -> Result<usize, DeviceError> {
        self.0.select(slot).await
    }

    async fn slot(&mut self) -> Result<Option<usize>, DeviceError> {
        self.0.slot().await
    }
}
