//! What a run drives: the analyzer, the camera and what is known about them.

use polar_model::sensor::{Camera as CameraModel, SensorModel};
use serde_json::Value;

/// The light of a simulated scene, as the run sets it: the fraction of the scene's light that
/// reaches the sensor, 0 (the lens capped, for darks) to 1 (a passing cloud in between).
pub type SceneLight = std::sync::Arc<dyn Fn(f64) + Send + Sync>;

/// What a run drives and knows about its devices.
pub struct Rig<A, C> {
    /// The analyzer (a rotator or a wheel of polarizers).
    pub analyzer: A,
    /// The camera.
    pub camera: C,
    /// The camera's noise model (the calibrated camera file).
    pub camera_model: CameraModel,
    /// The sensor model (camera, analyzer and band): the analyzer rows of the products.
    pub sensor: SensorModel,
    /// The simulated scene's lens cap and clouds; `None` on real hardware (dark series then
    /// pause for the operator to cap the lens).
    pub illumination: Option<SceneLight>,
    /// The adaptive loop's target pixels, when known as a mask.
    pub target_mask: Option<Vec<bool>>,
    /// The sun every frame records, zenith and azimuth in degrees: a simulated scene's own
    /// sun; `None` on real devices, where each frame records the real sun at the plan's
    /// site and the frame's time.
    pub sun_deg: Option<(f64, f64)>,
    /// A description of the devices for the store.
    pub devices: Value,
    /// The stage's acceleration in velocity mode, rad/s^2, when known (the simulated rig's
    /// stage): a continuous run's run-up is then its ramp to speed
    /// ([`crate::run::run_up_s`]); `None` runs up for a fixed [`crate::run::RUN_UP_S`].
    pub spin_acceleration_rad_per_s2: Option<f64>,
}
