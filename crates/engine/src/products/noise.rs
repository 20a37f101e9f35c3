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
