//! The noise model of the frames and the dark level subtracted from them.

use super::error::ProductsError;

/// The noise model of the frames, EMVA 1288 in DN (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseModel {
    /// System gain `K`, DN per electron; finite, in `[0, 1e6]`.
    pub gain_dn_per_e: f64,
    /// Offset (black level) `b`, DN; finite, in `[-1e6, 1e6]`. Shot noise counts from here.
    pub offset_dn: f64,
    /// Read plus quantisation variance, DN^2: `K^2 sigma_read_e^2 + 1/12`; finite, in
    /// `[0, 1e12]`.
    pub read_var_dn2: f64,
    /// A pixel with any frame value `>= saturation_dn` is saturated (all outputs NaN).
    pub saturation_dn: u16,
}

impl NoiseModel {
    /// The noise model of `camera`'s frames at `gain_db` of analogue gain: the gain scales
    /// `K` by `10^(gain_db / 20)`, and a pixel counts as saturated 3 read-noise sigma below the
    /// level a full well (or the ADC's top) reads, since a pixel there is clipped or
    /// nonlinear. The runs' products and the Python estimator both take it from here.
    pub fn from_camera(camera: &polar_model::sensor::Camera, gain_db: f64) -> NoiseModel {
        let k = camera.gain_dn_per_e * 10f64.powf(gain_db / 20.0);
        NoiseModel {
            gain_dn_per_e: k,
            offset_dn: camera.offset_dn,
            read_var_dn2: k * k * camera.read_noise_e * camera.read_noise_e + 1.0 / 12.0,
            saturation_dn: ((k * camera.full_well_e + camera.offset_dn).min(camera.adc_max_dn())
                - 3.0 * k * camera.read_noise_e)
                .clamp(0.0, 65535.0) as u16,
        }
    }

    /// The dark level of `camera`'s frames under this noise model's gain after
    /// `exposure_us`, DN: the offset plus `K` times the dark current's electrons (the level
    /// a run subtracts when it has too few dark frames for a map).
    pub fn dark_level_dn(&self, camera: &polar_model::sensor::Camera, exposure_us: f64) -> f64 {
        self.offset_dn + self.gain_dn_per_e * camera.dark_current_e_per_s * exposure_us * 1e-6
    }

    pub(super) fn validate(&self) -> Result<(), ProductsError> {
        let checks: [(&'static str, f64, f64, f64, &'static str); 3] = [
            (
                "gain_dn_per_e",
                self.gain_dn_per_e,
                0.0,
                1e6,
                "finite, in [0, 1e6] DN/e-",
            ),
            (
                "offset_dn",
                self.offset_dn,
                -1e6,
                1e6,
                "finite, in [-1e6, 1e6] DN",
            ),
            (
                "read_var_dn2",
                self.read_var_dn2,
                0.0,
                1e12,
                "finite, in [0, 1e12] DN^2",
            ),
        ];
        for (field, value, lo, hi, allowed) in checks {
            if !(value.is_finite() && value >= lo && value <= hi) {
                return Err(ProductsError::Noise {
                    field,
                    value,
                    allowed,
                });
            }
        }
        Ok(())
    }
}

/// The dark level subtracted from every frame, DN: `offset + K * dark electrons`.
#[derive(Debug, Clone, PartialEq)]
pub enum Dark {
    /// One value for every pixel (must be finite).
    Scalar(f32),
    /// A per-pixel dark map, row-major, `width * height` values (e.g. a mean of dark frames).
    /// A non-finite entry makes its pixel's outputs NaN.
    Map(Vec<f32>),
}
