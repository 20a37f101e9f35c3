//! The sensor model (MODEL.md section 6, Meng (2012)'s Sec. 3.2 *reconstructed*): a camera file,
//! the camera equation from band radiance to electrons, and the EMVA 1288 linear model from
//! electrons to digital numbers, with the mean and covariance of `N` frames taken through a
//! rotating analyzer.
//!
//! # Chain and units
//!
//! * Radiance: **band radiance** in W m^-2 sr^-1, a linear Stokes vector `L = [S0, S1, S2]`
//!   band-integrated as the scene module produces it (`int R(l) L_l(l) dl`, `R` the band's relative
//!   response, see [`crate::scene`]).
//! * Analyzer and fore-optics: frame `i` at commanded angle `psi_i` transmits `m_i^T L` with
//!   `m_i^T = a(psi_i)^T M_opt`, `a = 0.5 [k1 + k2, (k1 - k2) cos 2(psi + dpsi), (k1 - k2) sin 2(psi + dpsi)]`
//!   ([`AnalyzerModel::row`]) and `M_opt` the 3x3 linear-polarisation part of the fore-optics'
//!   Mueller matrix (light goes through the fore-optics first, then the analyzer). The rows stack
//!   into `W` (`N x 3`, `intensities_from_stokes`).
//! * Camera equation (MODEL.md section 6): on-axis focal-plane irradiance
//!   `E = pi tau_o L / (1 + 4 F#^2)` (no `cos^4` fall-off, no vignetting), photons per pixel
//!   `A_pixel E t_int lambda / (h c)` (EMVA 1288 Release 4.0, the mean number of photons
//!   `mu_p = A E t_exp lambda / (h c)`), electrons `eta(lambda)` times that. Spectrally,
//!   `mu_e,i = g t_int m_i^T L` with the **responsivity**
//!   `g = pi tau_o A_pixel / ((1 + 4 F#^2) h c) * int R w eta lambda dl / int R w dl`
//!   (electrons per second per W m^-2 sr^-1), where `R` is the band's relative response and `w` a
//!   spectral weight: the spectral radiance within the band is assumed to have the shape
//!   `R(l) w(l)`; [`SensorModel::new`] takes `w = 1` (radiance spread flat in wavelength over the
//!   band), [`SensorModel::with_spectral_weight`] any `w` (for instance
//!   [`crate::atmosphere::toa_irradiance`] for a sunlit scene). MODEL.md's `G`, electrons per unit
//!   radiance in one frame, is `g t_int` ([`SensorSignal::electrons_from_radiance`]).
//! * Electrons to DN (EMVA 1288 Release 4.0 linear model, MODEL.md section 6):
//!   `mu_y = K (mu_e + mu_I t_int) + b`, `sigma_y^2 = K^2 (sigma_d^2 + mu_I t_int + mu_e) + 1/12`.
//!   `sigma_d` is the read noise without dark-current shot noise (which is the separate
//!   `mu_I t_int` term; EMVA's temporal dark noise lumps the two).
//! * Frames (independent in time): `y_mean = K G W L_mean + (K mu_I t_int + b) 1`,
//!   `Sigma_y = K^2 G^2 W Sigma_LS W^T + F_n Sigma_n + diag((eps_cal y_i)^2)`,
//!   `Sigma_n = diag_i[K^2 (sigma_d^2 + mu_I t_int + G m_i^T L_mean) + 1/12]`.
//!
//! The model is linear up to saturation: means are not clipped. A frame is flagged saturated
//! when `y_i + 3 sigma_i` exceeds `min(K full_well + b, 2^bit_depth - 1)` (see
//! [`SensorSignal::saturated`]).

use crate::analyzer::{AnalyzerModel, MAX_ANGLES};
use crate::atmosphere::Band;
use crate::error::ModelError;
use crate::polarization::{Mueller, Stokes};
use nalgebra::{DMatrix, DVector, Matrix3, RowVector3, Vector3};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Planck constant, J s (exact, SI 2019).
const PLANCK_J_S: f64 = 6.626_070_15e-34;
/// Speed of light in vacuum, m s^-1 (exact).
const SPEED_OF_LIGHT_M_PER_S: f64 = 299_792_458.0;
/// Relative tolerance for the symmetry and positive-semidefiniteness of `Sigma_LS`.
pub const COVARIANCE_REL_TOL: f64 = 1e-9;
/// Largest magnitude accepted for a radiance component, W m^-2 sr^-1 (the sun's disc is ~2e7).
pub const MAX_RADIANCE_W_M2_SR: f64 = 1e12;
/// Longest integration time accepted, s.
pub const MAX_T_INT_S: f64 = 1e5;

/// The rotating analyzer of a camera file (`[polarizer]` table; absent means ideal).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Polarizer {
    /// Extinction ratio `k1 / k2`, `> 1`; absent (or `inf`, which TOML can carry) means ideal
    /// (`k2 = 0`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extinction_ratio: Option<f64>,
    /// Major principal transmittance `k1`, in `(0, 1]`; default 1.
    #[serde(default = "one")]
    pub transmittance: f64,
    /// Angle offset `dpsi` added to every commanded angle, degrees, in `[-180, 180]`; default 0.
    #[serde(default)]
    pub offset_deg: f64,
}

fn one() -> f64 {
    1.0
}

impl Default for Polarizer {
    fn default() -> Self {
        Polarizer {
            extinction_ratio: None,
            transmittance: 1.0,
            offset_deg: 0.0,
        }
    }
}

impl Polarizer {
    /// The analyzer model: `k1 = transmittance`, `k2 = k1 / extinction_ratio` (0 if ideal),
    /// offset in radians. Errors name `polarizer.<field>`.
    pub fn analyzer(&self) -> Result<AnalyzerModel, ModelError> {
        let k1 = positive_at_most("polarizer.transmittance", self.transmittance, 1.0, "(0, 1]")?;
        let k2 = match self.extinction_ratio {
            None => 0.0,
            Some(er) if er.is_nan() || er <= 1.0 => {
                return Err(ModelError::OutOfRange {
                    field: "polarizer.extinction_ratio",
                    value: er,
                    allowed: "> 1 (inf, or the field absent, for an ideal analyzer)",
                })
            }
            Some(er) => k1 / er,
        };
        let offset_deg = ModelError::check_range(
            "polarizer.offset_deg",
            self.offset_deg,
            -180.0,
            180.0,
            "[-180, 180]",
        )?;
        Ok(AnalyzerModel {
            k1,
            k2,
            offset_rad: offset_deg.to_radians(),
        })
    }
}

/// A camera: optics, detector (EMVA 1288 parameters), analyzer and fore-optics.
///
/// TOML (every field required unless marked optional; see `examples/cameras/`):
///
/// ```toml
/// name = "typical cooled CCD"
/// pixel_pitch_um = 7.4
/// f_number = 4.0
/// optics_transmittance = 0.9
/// qe = [[400, 0.30], [500, 0.52], [600, 0.45], [700, 0.30]]   # [wavelength_nm, QE]
/// gain_dn_per_e = 0.1          # K
/// read_noise_e = 10.0          # sigma_d
/// dark_current_e_per_s = 1.0   # mu_I
/// offset_dn = 100.0            # b
/// bit_depth = 12
/// full_well_e = 40000.0
/// fore_optics = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]   # optional, default identity
/// [polarizer]                  # optional, default ideal
/// extinction_ratio = 1000.0    # optional (absent or inf: ideal)
/// transmittance = 0.85         # k1, default 1
/// offset_deg = 0.0             # default 0
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// A name for reports.
    pub name: String,
    /// Pixel pitch, micrometres, in `(0, 1000]`; the pixel area is `pitch^2` (fill factor and
    /// microlens gain are folded into the QE, as EMVA 1288 does).
    pub pixel_pitch_um: f64,
    /// Working f-number `F#`, in `[0.5, 100]`.
    pub f_number: f64,
    /// Transmittance of the lens (and any window or filter not in the band response), `(0, 1]`.
    pub optics_transmittance: f64,
    /// Quantum efficiency curve: `[wavelength_nm, qe]` pairs, wavelengths strictly increasing in
    /// `[200, 2500]` nm, QE in `[0, 1]`, at least 2 points, not all zero; linearly interpolated,
    /// zero outside the tabulated range.
    pub qe: Vec<[f64; 2]>,
    /// System gain `K`, DN per electron, in `(0, 1000]`.
    pub gain_dn_per_e: f64,
    /// Read noise `sigma_d`, electrons rms, in `[0, 1e5]` (without dark-current shot noise).
    pub read_noise_e: f64,
    /// Dark current `mu_I`, electrons per second, in `[0, 1e9]`.
    pub dark_current_e_per_s: f64,
    /// Offset (black level) `b`, DN, in `[0, 2^bit_depth - 1)`.
    pub offset_dn: f64,
    /// ADC bit depth, `8..=16`.
    pub bit_depth: u32,
    /// Full-well (saturation) capacity, electrons, in `[1, 1e9]`.
    pub full_well_e: f64,
    /// The rotating analyzer; optional, default ideal.
    #[serde(default)]
    pub polarizer: Polarizer,
    /// Fore-optics Mueller matrix in front of the analyzer: its **3x3 linear-polarisation part**
    /// (rows and columns `S0, S1, S2`; the circular row and column of the 4x4 matrix are dropped,
    /// as V is ignored by the passive model), as three rows. Optional, default identity. Entries
    /// finite, `M00 > 0` and `M00 >= sqrt(M01^2 + M02^2)` (unpolarised-to-polarised input never
    /// gives negative intensity).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fore_optics: Option<[[f64; 3]; 3]>,
}

/// `value` finite and in `(0, hi]`.
fn positive_at_most(
    field: &'static str,
    value: f64,
    hi: f64,
    allowed: &'static str,
) -> Result<f64, ModelError> {
    if value.is_finite() && value > 0.0 && value <= hi {
        Ok(value)
    } else {
        Err(ModelError::OutOfRange {
            field,
            value,
            allowed,
        })
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        field,
        reason: reason.into(),
    }
}

impl Camera {
    /// Parses and validates a camera file. TOML syntax errors and unknown keys name `camera`
    /// (with line and column); range errors name the field, the value and the allowed range.
    pub fn from_toml_str(text: &str) -> Result<Camera, ModelError> {
        let camera: Camera = toml::from_str(text)
            .map_err(|e| invalid("camera", crate::error::toml_message(text, &e)))?;
        camera.validate()?;
        Ok(camera)
    }

    /// The camera as TOML text (parses back to an equal camera).
    pub fn to_toml_string(&self) -> Result<String, ModelError> {
        toml::to_string(self).map_err(|e| invalid("camera", e.to_string()))
    }

    /// Checks every field (ranges in the field docs). Errors name the field.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.name.trim().is_empty() {
            return Err(invalid("name", "empty; allowed any non-empty text"));
        }
        positive_at_most("pixel_pitch_um", self.pixel_pitch_um, 1000.0, "(0, 1000]")?;
        ModelError::check_range("f_number", self.f_number, 0.5, 100.0, "[0.5, 100]")?;
        positive_at_most(
            "optics_transmittance",
            self.optics_transmittance,
            1.0,
            "(0, 1]",
        )?;
        self.validate_qe()?;
        positive_at_most("gain_dn_per_e", self.gain_dn_per_e, 1000.0, "(0, 1000]")?;
        ModelError::check_range("read_noise_e", self.read_noise_e, 0.0, 1e5, "[0, 1e5]")?;
        ModelError::check_range(
            "dark_current_e_per_s",
            self.dark_current_e_per_s,
            0.0,
            1e9,
            "[0, 1e9]",
        )?;
        if !(8..=16).contains(&self.bit_depth) {
            return Err(ModelError::OutOfRange {
                field: "bit_depth",
                value: f64::from(self.bit_depth),
                allowed: "an integer in [8, 16]",
            });
        }
        let adc_max = self.adc_max_dn();
        if !(self.offset_dn.is_finite() && self.offset_dn >= 0.0 && self.offset_dn < adc_max) {
            return Err(ModelError::OutOfRange {
                field: "offset_dn",
                value: self.offset_dn,
                allowed: "[0, 2^bit_depth - 1)",
            });
        }
        ModelError::check_range("full_well_e", self.full_well_e, 1.0, 1e9, "[1, 1e9]")?;
        self.polarizer.analyzer()?;
        if let Some(m) = &self.fore_optics {
            if let Some(bad) = m.iter().flatten().find(|v| !v.is_finite() || v.abs() > 1e3) {
                return Err(ModelError::OutOfRange {
                    field: "fore_optics",
                    value: *bad,
                    allowed: "finite entries with |entry| <= 1000",
                });
            }
            let row0 = m[0][1].hypot(m[0][2]);
            if !(m[0][0] > 0.0 && m[0][0] >= row0) {
                return Err(invalid(
                    "fore_optics",
                    format!(
                        "M00 = {}, sqrt(M01^2 + M02^2) = {row0}: allowed M00 > 0 and \
                         M00 >= sqrt(M01^2 + M02^2)",
                        m[0][0]
                    ),
                ));
            }
        }
        Ok(())
    }

    fn validate_qe(&self) -> Result<(), ModelError> {
        if self.qe.len() < 2 {
            return Err(invalid(
                "qe",
                format!(
                    "{} points; allowed at least 2 [wavelength_nm, qe] pairs",
                    self.qe.len()
                ),
            ));
        }
        for (i, &[nm, q]) in self.qe.iter().enumerate() {
            if !(nm.is_finite() && (200.0..=2500.0).contains(&nm)) {
                return Err(invalid(
                    "qe",
                    format!("point {i}: wavelength_nm = {nm}; allowed [200, 2500]"),
                ));
            }
            if !(q.is_finite() && (0.0..=1.0).contains(&q)) {
                return Err(invalid(
                    "qe",
                    format!("point {i}: qe = {q}; allowed [0, 1]"),
                ));
            }
        }
        for (i, w) in self.qe.windows(2).enumerate() {
            if w[1][0] <= w[0][0] {
                return Err(invalid(
                    "qe",
                    format!(
                        "points {i} and {}: wavelengths {} then {} nm; allowed strictly increasing",
                        i + 1,
                        w[0][0],
                        w[1][0]
                    ),
                ));
            }
        }
        if self.qe.iter().all(|p| p[1] == 0.0) {
            return Err(invalid(
                "qe",
                "zero at every wavelength; allowed some QE > 0",
            ));
        }
        Ok(())
    }

    /// The quantum efficiency at `nm`, linearly interpolated; 0 outside the tabulated range.
    pub fn qe_at(&self, nm: f64) -> f64 {
        let q = &self.qe;
        if q.is_empty() || !(nm >= q[0][0] && nm <= q[q.len() - 1][0]) {
            return 0.0;
        }
        let i = q.partition_point(|p| p[0] <= nm).clamp(1, q.len() - 1);
        let (a, b) = (q[i - 1], q[i]);
        if b[0] == a[0] {
            return a[1];
        }
        a[1] + (b[1] - a[1]) * (nm - a[0]) / (b[0] - a[0])
    }

    /// The largest ADC output, `2^bit_depth - 1` DN.
    pub fn adc_max_dn(&self) -> f64 {
        f64::from(2u32.pow(self.bit_depth.min(31))) - 1.0
    }

    /// The saturation level `min(K full_well + b, 2^bit_depth - 1)`, DN.
    pub fn saturation_dn(&self) -> f64 {
        (self.gain_dn_per_e * self.full_well_e + self.offset_dn).min(self.adc_max_dn())
    }

    /// The fore-optics (3x3 linear part), identity if absent.
    pub fn fore_optics(&self) -> Mueller {
        match &self.fore_optics {
            None => Mueller::identity(),
            Some(m) => Mueller(Matrix3::from_fn(|i, j| m[i][j])),
        }
    }

    /// The geometric factor `pi tau_o A_pixel / ((1 + 4 F#^2) h c)`, electrons per second per
    /// W m^-2 sr^-1 per metre of wavelength at QE 1 (multiply by `eta lambda`).
    fn etendue_factor(&self) -> f64 {
        let area_m2 = (self.pixel_pitch_um * 1e-6).powi(2);
        PI * self.optics_transmittance * area_m2
            / ((1.0 + 4.0 * self.f_number * self.f_number) * PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S)
    }

    /// Band responsivity `g`, electrons per second per W m^-2 sr^-1 of band radiance, with the
    /// spectral radiance spread flat in wavelength over the band (times its response):
    /// `g = pi tau_o A / ((1 + 4 F#^2) h c) * int R eta lambda dl / int R dl` (module docs,
    /// MODEL.md section 6). Errors name `band` if the QE is zero over the whole band.
    pub fn responsivity_e_per_s(&self, band: &Band) -> Result<f64, ModelError> {
        self.responsivity_e_per_s_weighted(band, |_| 1.0)
    }

    /// As [`Camera::responsivity_e_per_s`], with the spectral radiance in the band shaped as
    /// `R(l) weight(l)` (`weight` finite and `>= 0`; errors name `spectral_weight`).
    ///
    /// Quadrature: 3-point Gauss-Legendre on pieces split at every integer nanometre and at the
    /// QE knots, so the integral is exact for the piecewise-linear QE and flat weight with any
    /// band whose knots are whole nanometres (and for a piecewise-linear weight with such knots,
    /// such as the TOA spectrum: the integrand is then a quartic on each piece).
    pub fn responsivity_e_per_s_weighted<F: Fn(f64) -> f64>(
        &self,
        band: &Band,
        weight: F,
    ) -> Result<f64, ModelError> {
        let (signal, norm) = self.band_integrals(band, &weight)?;
        if norm.is_nan() || norm <= 0.0 {
            return Err(invalid(
                "spectral_weight",
                "the weighted band response integrates to 0; allowed a weight > 0 somewhere in the band",
            ));
        }
        let g = self.etendue_factor() * signal / norm;
        if g.is_nan() || g <= 0.0 {
            let (lo, hi) = band.range_nm();
            return Err(invalid(
                "band",
                format!(
                    "[{lo}, {hi}] nm: the camera's QE (tabulated over [{}, {}] nm) is zero over \
                     the whole band; allowed a band where the QE is > 0",
                    self.qe[0][0],
                    self.qe[self.qe.len() - 1][0]
                ),
            ));
        }
        Ok(g)
    }

    /// `(int R w eta lambda_m dl, int R w dl)` over the band (module docs).
    fn band_integrals(
        &self,
        band: &Band,
        weight: &dyn Fn(f64) -> f64,
    ) -> Result<(f64, f64), ModelError> {
        let (lo, hi) = band.range_nm();
        let mut knots: Vec<f64> = vec![lo, hi];
        let mut k = lo.floor() + 1.0;
        while k < hi {
            knots.push(k);
            k += 1.0;
        }
        knots.extend(self.qe.iter().map(|p| p[0]).filter(|&l| l > lo && l < hi));
        knots.sort_by(f64::total_cmp);
        knots.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        let x3 = (0.6f64).sqrt();
        let gl = [(-x3, 5.0 / 9.0), (0.0, 8.0 / 9.0), (x3, 5.0 / 9.0)];
        let (mut signal, mut norm) = (0.0, 0.0);
        for seg in knots.windows(2) {
            let (mid, half) = (0.5 * (seg[0] + seg[1]), 0.5 * (seg[1] - seg[0]));
            for (t, w) in gl {
                let l = mid + half * t;
                let wl = weight(l);
                if !(wl.is_finite() && wl >= 0.0) {
                    return Err(ModelError::OutOfRange {
                        field: "spectral_weight",
                        value: wl,
                        allowed: "finite and >= 0 at every wavelength of the band",
                    });
                }
                let rw = band.response(l) * wl * w * half;
                norm += rw;
                signal += rw * self.qe_at(l) * l * 1e-9;
            }
        }
        Ok((signal, norm))
    }
}

/// Meng (2012)'s sensor noise factor `F_n` (its Ch. 4 sweeps it). Whether it scaled the variance
/// or the standard deviation of the sensor noise is not recoverable from Meng (2012) (MODEL.md
/// section 6), so both are offered: `Variance(f)` multiplies `Sigma_n` by `f`, `StdDev(f)`
/// multiplies every sensor-noise standard deviation by `f`, that is `Sigma_n` by `f^2`. Scene
/// clutter and drift are not scaled. Default `Variance(1.0)` (the plain EMVA 1288 model).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NoiseFactor {
    /// Multiplies the sensor-noise variance by this factor (`>= 0`).
    Variance(f64),
    /// Multiplies the sensor-noise standard deviation by this factor (`>= 0`).
    StdDev(f64),
}

impl Default for NoiseFactor {
    fn default() -> Self {
        NoiseFactor::Variance(1.0)
    }
}

impl NoiseFactor {
    /// The factor applied to `Sigma_n`: `f` for `Variance(f)`, `f^2` for `StdDev(f)`.
    pub fn variance_multiplier(&self) -> f64 {
        match *self {
            NoiseFactor::Variance(f) => f,
            NoiseFactor::StdDev(f) => f * f,
        }
    }

    fn validate(&self) -> Result<f64, ModelError> {
        let f = match *self {
            NoiseFactor::Variance(f) | NoiseFactor::StdDev(f) => f,
        };
        ModelError::check_range("noise_factor", f, 0.0, 1e6, "finite, in [0, 1e6]")?;
        Ok(self.variance_multiplier())
    }
}

/// One acquisition's inputs besides the angles: integration time, the scene's band Stokes
/// radiance statistics at the aperture, the noise factor and the frame-to-frame drift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exposure {
    /// Integration time, s, in `(0, 1e5]`.
    pub t_int_s: f64,
    /// Mean band Stokes radiance `L_mean`, W m^-2 sr^-1 (each component `|.| <= 1e12`).
    pub radiance_mean_w_m2_sr: Stokes,
    /// Its covariance `Sigma_LS` (scene clutter), (W m^-2 sr^-1)^2: symmetric and positive
    /// semidefinite to [`COVARIANCE_REL_TOL`] relative to its largest eigenvalue magnitude.
    pub radiance_cov_w2_m4_sr2: Matrix3<f64>,
    /// The sensor noise factor `F_n`.
    pub noise_factor: NoiseFactor,
    /// Relative calibration/illumination drift between frames `eps_cal`, in `[0, 1]`: adds
    /// `diag((eps_cal y_i)^2)` with `y_i` the frame's mean DN (offset and dark signal included,
    /// as MODEL.md section 6 writes it).
    pub eps_cal: f64,
}

impl Exposure {
    /// An exposure with no clutter, `F_n = Variance(1)` and no drift.
    pub fn new(t_int_s: f64, radiance_mean_w_m2_sr: Stokes) -> Self {
        Exposure {
            t_int_s,
            radiance_mean_w_m2_sr,
            radiance_cov_w2_m4_sr2: Matrix3::zeros(),
            noise_factor: NoiseFactor::default(),
            eps_cal: 0.0,
        }
    }

    fn validate(&self) -> Result<f64, ModelError> {
        positive_at_most("t_int_s", self.t_int_s, MAX_T_INT_S, "> 0 and <= 1e5 s")?;
        for v in self.radiance_mean_w_m2_sr.0.iter() {
            ModelError::check_range(
                "radiance_mean_w_m2_sr",
                *v,
                -MAX_RADIANCE_W_M2_SR,
                MAX_RADIANCE_W_M2_SR,
                "finite, |component| <= 1e12 W m^-2 sr^-1",
            )?;
        }
        validate_covariance(&self.radiance_cov_w2_m4_sr2)?;
        ModelError::check_range("eps_cal", self.eps_cal, 0.0, 1.0, "[0, 1]")?;
        self.noise_factor.validate()
    }
}

/// `Sigma_LS` finite, symmetric and positive semidefinite, all relative to its scale.
fn validate_covariance(c: &Matrix3<f64>) -> Result<(), ModelError> {
    const FIELD: &str = "radiance_cov_w2_m4_sr2";
    let max_sq = MAX_RADIANCE_W_M2_SR * MAX_RADIANCE_W_M2_SR;
    for v in c.iter() {
        ModelError::check_range(
            FIELD,
            *v,
            -max_sq,
            max_sq,
            "finite, |entry| <= 1e24 (W m^-2 sr^-1)^2",
        )?;
    }
    let scale = c.amax();
    let asym = (c - c.transpose()).amax();
    if asym > COVARIANCE_REL_TOL * scale {
        return Err(invalid(
            FIELD,
            format!(
                "not symmetric: max |C_ij - C_ji| = {asym:e} against largest entry {scale:e}; \
                 allowed asymmetry <= {COVARIANCE_REL_TOL:e} relative"
            ),
        ));
    }
    let eig = (0.5 * (c + c.transpose())).symmetric_eigenvalues();
    let lam_min = eig.min();
    let lam_absmax = eig.amax();
    if lam_min < -COVARIANCE_REL_TOL * lam_absmax {
        return Err(invalid(
            FIELD,
            format!(
                "not positive semidefinite: eigenvalues {:e}, {:e}, {:e} (smallest {lam_min:e}); \
                 allowed smallest >= -{COVARIANCE_REL_TOL:e} times the largest magnitude \
                 ({lam_absmax:e})",
                eig[0], eig[1], eig[2]
            ),
        ));
    }
    Ok(())
}

/// A camera looking through its band: the responsivity is integrated once, then
/// [`SensorModel::signal`] gives the frames' statistics for any angles and exposure.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorModel {
    camera: Camera,
    analyzer: AnalyzerModel,
    fore_optics: Mueller,
    responsivity_e_per_s: f64,
    warnings: Vec<String>,
}

impl SensorModel {
    /// The camera through `band`, radiance spread flat in wavelength over the band (see
    /// [`Camera::responsivity_e_per_s`]). Errors: the camera's field, or `band`.
    pub fn new(camera: &Camera, band: &Band) -> Result<Self, ModelError> {
        SensorModel::with_spectral_weight(camera, band, |_| 1.0)
    }

    /// As [`SensorModel::new`] with the in-band spectral shape `R(l) weight(l)` (see
    /// [`Camera::responsivity_e_per_s_weighted`]).
    pub fn with_spectral_weight<F: Fn(f64) -> f64>(
        camera: &Camera,
        band: &Band,
        weight: F,
    ) -> Result<Self, ModelError> {
        camera.validate()?;
        let responsivity_e_per_s = camera.responsivity_e_per_s_weighted(band, weight)?;
        let mut warnings = Vec::new();
        let (lo, hi) = band.range_nm();
        let (q_lo, q_hi) = (camera.qe[0][0], camera.qe[camera.qe.len() - 1][0]);
        if lo < q_lo || hi > q_hi {
            warnings.push(format!(
                "the band [{lo}, {hi}] nm extends beyond the QE curve [{q_lo}, {q_hi}] nm of \
                 camera {:?}: QE taken as 0 there",
                camera.name
            ));
        }
        Ok(SensorModel {
            analyzer: camera.polarizer.analyzer()?,
            fore_optics: camera.fore_optics(),
            camera: camera.clone(),
            responsivity_e_per_s,
            warnings,
        })
    }

    /// The camera.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The analyzer model built from the camera's `[polarizer]`.
    pub fn analyzer(&self) -> AnalyzerModel {
        self.analyzer
    }

    /// Band responsivity `g`, electrons per second per W m^-2 sr^-1 (`G = g t_int`).
    pub fn responsivity_e_per_s(&self) -> f64 {
        self.responsivity_e_per_s
    }

    /// Warnings from construction (band beyond the QE curve).
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// The measurement matrix `W` (`N x 3`): rows `a(psi_i)^T M_opt` with the camera's real
    /// analyzer (`k1`, `k2`, offset) and fore-optics. Errors name `angles_deg` (values in
    /// degrees): empty list, more than [`MAX_ANGLES`], or a non-finite or huge angle.
    pub fn intensities_from_stokes(&self, angles_rad: &[f64]) -> Result<DMatrix<f64>, ModelError> {
        let n = angles_rad.len();
        if !(1..=MAX_ANGLES).contains(&n) {
            return Err(invalid(
                "angles_deg",
                format!("{n} angles given; allowed 1 to {MAX_ANGLES}"),
            ));
        }
        if let Some(bad) = angles_rad.iter().find(|a| !a.is_finite() || a.abs() > 1e6) {
            return Err(ModelError::OutOfRange {
                field: "angles_deg",
                value: bad.to_degrees(),
                allowed: "finite, |angle| <= 1e6 rad",
            });
        }
        let m_opt = self.fore_optics.0;
        let mut w = DMatrix::zeros(n, 3);
        for (i, &psi) in angles_rad.iter().enumerate() {
            let row: RowVector3<f64> = self.analyzer.row(psi).transpose() * m_opt;
            w.row_mut(i).copy_from(&row);
        }
        Ok(w)
    }

    /// Mean and covariance of the `N` frames' digital numbers (module docs, MODEL.md section 6).
    ///
    /// Negative transmitted intensities `m_i^T L_mean` (possible with an unphysical Stokes mean or
    /// fore-optics) are clamped to 0 electrons, with a warning. Errors name the field:
    /// `angles_deg`, `t_int_s`, `radiance_mean_w_m2_sr`, `radiance_cov_w2_m4_sr2` (also when not
    /// symmetric or not positive semidefinite, to [`COVARIANCE_REL_TOL`]), `eps_cal`,
    /// `noise_factor`.
    pub fn signal(
        &self,
        angles_rad: &[f64],
        exposure: &Exposure,
    ) -> Result<SensorSignal, ModelError> {
        let noise_variance_factor = exposure.validate()?;
        let w = self.intensities_from_stokes(angles_rad)?;
        let n = angles_rad.len();
        let cam = &self.camera;
        let t = exposure.t_int_s;
        let k = cam.gain_dn_per_e;
        let big_g = self.responsivity_e_per_s * t;
        let mut warnings = self.warnings.clone();

        let l_mean: Vector3<f64> = exposure.radiance_mean_w_m2_sr.0;
        let intensity = &w * l_mean;
        let mut clamped = Vec::new();
        let electrons = DVector::from_fn(n, |i, _| {
            let e = big_g * intensity[i];
            if e < 0.0 {
                clamped.push(i);
                0.0
            } else {
                e
            }
        });
        if !clamped.is_empty() {
            warnings.push(format!(
                "negative transmitted intensity m_i^T L_mean in frame(s) {clamped:?} (unphysical \
                 Stokes mean or fore-optics): electrons clamped to 0"
            ));
        }
        let dark_electrons = cam.dark_current_e_per_s * t;
        let mean_dn = electrons.map(|e| k * (e + dark_electrons) + cam.offset_dn);

        let sigma =
            0.5 * (exposure.radiance_cov_w2_m4_sr2 + exposure.radiance_cov_w2_m4_sr2.transpose());
        let sigma_d = DMatrix::from_fn(3, 3, |i, j| sigma[(i, j)]);
        let kg2 = (k * big_g) * (k * big_g);
        let clutter = &w * sigma_d * w.transpose() * kg2;
        let clutter = 0.5 * (&clutter + clutter.transpose());

        let f = noise_variance_factor;
        let k2 = k * k;
        let variance = VarianceBreakdown {
            shot_dn2: electrons.map(|e| f * k2 * e),
            dark_dn2: DVector::from_element(n, f * k2 * dark_electrons),
            read_dn2: DVector::from_element(n, f * k2 * cam.read_noise_e * cam.read_noise_e),
            quantization_dn2: DVector::from_element(n, f / 12.0),
            clutter_dn2: clutter.diagonal(),
            drift_dn2: mean_dn.map(|y| (exposure.eps_cal * y).powi(2)),
        };
        let mut cov_dn = clutter;
        for i in 0..n {
            cov_dn[(i, i)] += variance.shot_dn2[i]
                + variance.dark_dn2[i]
                + variance.read_dn2[i]
                + variance.quantization_dn2[i]
                + variance.drift_dn2[i];
        }

        let saturation_dn = cam.saturation_dn();
        let saturated: Vec<bool> = (0..n)
            .map(|i| mean_dn[i] + 3.0 * cov_dn[(i, i)].max(0.0).sqrt() > saturation_dn)
            .collect();
        let flagged: Vec<usize> = (0..n).filter(|&i| saturated[i]).collect();
        if !flagged.is_empty() {
            warnings.push(format!(
                "frame(s) {flagged:?} within 3 sigma of saturation ({saturation_dn} DN): the \
                 linear model over-states their mean and variance"
            ));
        }

        Ok(SensorSignal {
            dn_from_radiance: &w * (k * big_g),
            mean_dn,
            cov_dn,
            saturated,
            saturation_dn,
            electrons,
            dark_electrons,
            electrons_from_radiance: big_g,
            intensities_from_stokes: w,
            variance,
            noise_variance_factor,
            warnings,
        })
    }
}

/// Per-frame variance terms, DN^2, each as it enters `cov_dn`'s diagonal (the sensor terms
/// already multiplied by `F_n`'s variance multiplier); they sum to `diag(cov_dn)`.
#[derive(Debug, Clone, PartialEq)]
pub struct VarianceBreakdown {
    /// Photon shot noise `F K^2 G m_i^T L_mean`.
    pub shot_dn2: DVector<f64>,
    /// Dark-current shot noise `F K^2 mu_I t_int`.
    pub dark_dn2: DVector<f64>,
    /// Read noise `F K^2 sigma_d^2`.
    pub read_dn2: DVector<f64>,
    /// Quantisation `F / 12`.
    pub quantization_dn2: DVector<f64>,
    /// Scene clutter `diag(K^2 G^2 W Sigma_LS W^T)` (the only term correlated across frames).
    pub clutter_dn2: DVector<f64>,
    /// Drift `(eps_cal y_i)^2`.
    pub drift_dn2: DVector<f64>,
}

/// The frames' statistics from [`SensorModel::signal`].
#[derive(Debug, Clone, PartialEq)]
pub struct SensorSignal {
    /// `y_mean`, DN (N).
    pub mean_dn: DVector<f64>,
    /// `Sigma_y`, DN^2 (N x N).
    pub cov_dn: DMatrix<f64>,
    /// Per frame: `y_i + 3 sqrt(Sigma_y,ii) > saturation_dn`, i.e. more than about 0.1 % of the
    /// frame's values (Gaussian approximation) would clip at the full well or the ADC ceiling.
    pub saturated: Vec<bool>,
    /// `min(K full_well + b, 2^bit_depth - 1)`, DN.
    pub saturation_dn: f64,
    /// Photo-electrons per frame `G m_i^T L_mean` (clamped at 0), N.
    pub electrons: DVector<f64>,
    /// Dark electrons per frame `mu_I t_int`.
    pub dark_electrons: f64,
    /// `G = g t_int`, electrons per W m^-2 sr^-1 in one frame.
    pub electrons_from_radiance: f64,
    /// The measurement matrix `W` used (real analyzer and fore-optics), `N x 3`.
    pub intensities_from_stokes: DMatrix<f64>,
    /// `K G W`, DN per W m^-2 sr^-1, `N x 3`.
    pub dn_from_radiance: DMatrix<f64>,
    /// The variance terms per frame.
    pub variance: VarianceBreakdown,
    /// The factor applied to `Sigma_n` (`F_n` or `F_n^2`, see [`NoiseFactor`]).
    pub noise_variance_factor: f64,
    /// What was clamped, approximated or flagged.
    pub warnings: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::polarization::analyzer_row;

    const CCD_SEED: &str = include_str!("../../../examples/cameras/ccd_seed.toml");
    const CMOS_MODERN: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

    /// A simple camera for hand computation: 10 um pixels (A = 1e-10 m^2), F/0.5
    /// (1 + 4 F^2 = 2), tau = 1, flat QE 0.5 over [300, 1100] nm, K = 0.5 DN/e-,
    /// sigma_d = 3 e-, mu_I = 10 e-/s, b = 100 DN, 16 bit, full well 1e6 e-, ideal analyzer.
    fn hand_camera() -> Camera {
        Camera {
            name: "hand".into(),
            pixel_pitch_um: 10.0,
            f_number: 0.5,
            optics_transmittance: 1.0,
            qe: vec![[300.0, 0.5], [1100.0, 0.5]],
            gain_dn_per_e: 0.5,
            read_noise_e: 3.0,
            dark_current_e_per_s: 10.0,
            offset_dn: 100.0,
            bit_depth: 16,
            full_well_e: 1e6,
            polarizer: Polarizer::default(),
            fore_optics: None,
        }
    }

    fn band(lo: f64, hi: f64) -> Band {
        Band::flat(lo, hi).unwrap()
    }

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs().max(1e-300)
    }

    const ANGLES_4: [f64; 4] = [
        0.0,
        std::f64::consts::FRAC_PI_4,
        std::f64::consts::FRAC_PI_2,
        3.0 * std::f64::consts::FRAC_PI_4,
    ];

    /// Hand-computed case. Band [400, 600] nm flat, QE 0.5: `g = pi * 1 * 1e-10 / 2 * 0.5 *
    /// 500e-9 / (h c) = 1.97689e8` e-/s per W m^-2 sr^-1. With `t = 1 ms`, `L = (1e-3, 5e-4, 0)`
    /// and the frame at 0 deg: `m^T L = 0.5 (1e-3 + 5e-4) = 7.5e-4`, electrons
    /// `= 1.97689e5 * 7.5e-4 = 148.27`; dark 0.01 e-; mean `0.5 (148.27 + 0.01) + 100 = 174.14`
    /// DN; variance `0.25 (9 + 0.01 + 148.27) + 1/12 = 39.40` DN^2. The code and this test use
    /// the same closed form, so they agree to rounding (1e-12 relative); the stated numbers are
    /// checked to their printed digits.
    #[test]
    fn hand_computed_case() {
        let cam = hand_camera();
        let model = SensorModel::new(&cam, &band(400.0, 600.0)).unwrap();
        let hc = PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S;
        let g = PI * 1.0 * 1e-10 / 2.0 * 0.5 * 500e-9 / hc;
        assert!(rel(model.responsivity_e_per_s(), g) < 1e-12);
        assert!(rel(g, 1.97689e8) < 1e-5, "{g}");
        let mut exp = Exposure::new(1e-3, Stokes::new(1e-3, 5e-4, 0.0));
        exp.radiance_cov_w2_m4_sr2 = Matrix3::from_diagonal(&Vector3::new(1e-8, 4e-9, 4e-9));
        let s = model.signal(&ANGLES_4, &exp).unwrap();
        let big_g = g * 1e-3;
        for (i, &psi) in ANGLES_4.iter().enumerate() {
            let m = analyzer_row(psi);
            let e = big_g * (m[0] * 1e-3 + m[1] * 5e-4);
            let mean = 0.5 * (e + 0.01) + 100.0;
            let clutter =
                0.25 * big_g * big_g * (m[0] * m[0] * 1e-8 + (m[1] * m[1] + m[2] * m[2]) * 4e-9);
            let var = 0.25 * (9.0 + 0.01 + e) + 1.0 / 12.0 + clutter;
            assert!(rel(s.electrons[i], e) < 1e-12);
            assert!(rel(s.mean_dn[i], mean) < 1e-12);
            assert!(rel(s.cov_dn[(i, i)], var) < 1e-12);
            for (j, &psi_j) in ANGLES_4.iter().enumerate() {
                let mj = analyzer_row(psi_j);
                let c = 0.25
                    * big_g
                    * big_g
                    * (m[0] * mj[0] * 1e-8 + (m[1] * mj[1] + m[2] * mj[2]) * 4e-9);
                if i != j {
                    assert!((s.cov_dn[(i, j)] - c).abs() <= 1e-12 * var);
                }
            }
        }
        assert!((s.electrons[0] - 148.27).abs() < 0.01, "{}", s.electrons[0]);
        assert!((s.mean_dn[0] - 174.14).abs() < 0.01, "{}", s.mean_dn[0]);
        let sensor_var0 = s.cov_dn[(0, 0)] - s.variance.clutter_dn2[0];
        assert!((sensor_var0 - 39.40).abs() < 0.01, "{sensor_var0}");
        assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        assert!(s.saturated.iter().all(|x| !x));
    }

    /// A QE rising linearly from 0.4 at 400 nm to 0.6 at 600 nm over the flat band [400, 600]:
    /// `int QE l dl / 200 = 253.333... nm` analytically, so `g` equals the geometric factor times
    /// 253.333e-9 m. The quadrature is exact for this quadratic integrand: 1e-13 relative.
    #[test]
    fn linear_qe_band_integral_is_exact() {
        let mut cam = hand_camera();
        cam.qe = vec![[400.0, 0.4], [600.0, 0.6]];
        let g = cam.responsivity_e_per_s(&band(400.0, 600.0)).unwrap();
        let expect = cam.etendue_factor() * (50_666.666_666_666_67 / 200.0) * 1e-9;
        assert!(rel(g, expect) < 1e-13, "{g} vs {expect}");
        // A flat spectral weight is the default; a constant weight changes nothing (1e-13).
        let g2 = cam
            .responsivity_e_per_s_weighted(&band(400.0, 600.0), |_| 7.0)
            .unwrap();
        assert!(rel(g2, g) < 1e-13);
        // A weight concentrated towards 600 nm raises g (QE and lambda both grow).
        let g3 = cam
            .responsivity_e_per_s_weighted(&band(400.0, 600.0), |l| l - 400.0)
            .unwrap();
        assert!(g3 > g);
    }

    /// The mean minus the dark level is linear in `t_int` and in `L` (the model is linear below
    /// saturation): doubling either doubles it, to rounding (1e-12 relative).
    #[test]
    fn mean_is_linear_in_time_and_radiance() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let l = Stokes::new(2e-3, 3e-4, -5e-4);
        let dark = |t: f64| 0.5 * 10.0 * t + 100.0;
        let a = model.signal(&ANGLES_4, &Exposure::new(1e-3, l)).unwrap();
        let b = model.signal(&ANGLES_4, &Exposure::new(2e-3, l)).unwrap();
        let c = model
            .signal(&ANGLES_4, &Exposure::new(1e-3, Stokes(l.0 * 2.0)))
            .unwrap();
        let d = model
            .signal(
                &ANGLES_4,
                &Exposure::new(1e-3, Stokes(l.0 * 0.5 + Vector3::new(1e-3, 0.0, 2e-4))),
            )
            .unwrap();
        let e = model
            .signal(
                &ANGLES_4,
                &Exposure::new(1e-3, Stokes(Vector3::new(1e-3, 0.0, 2e-4))),
            )
            .unwrap();
        for i in 0..4 {
            let sa = a.mean_dn[i] - dark(1e-3);
            assert!(rel(b.mean_dn[i] - dark(2e-3), 2.0 * sa) < 1e-12);
            assert!(rel(c.mean_dn[i] - dark(1e-3), 2.0 * sa) < 1e-12);
            // Superposition: y(0.5 L + L2) - dark = 0.5 (y(L) - dark) + (y(L2) - dark).
            let sum = 0.5 * sa + (e.mean_dn[i] - dark(1e-3));
            assert!(rel(d.mean_dn[i] - dark(1e-3), sum) < 1e-12);
        }
    }

    /// A pure shot-noise camera (no read noise, no dark current, no clutter): the variance
    /// minus the fixed quantisation 1/12 DN^2 is `K^2` times the electrons, to rounding (1e-12).
    #[test]
    fn pure_shot_noise_variance() {
        let mut cam = hand_camera();
        cam.read_noise_e = 0.0;
        cam.dark_current_e_per_s = 0.0;
        cam.gain_dn_per_e = 0.37;
        let model = SensorModel::new(&cam, &band(500.0, 600.0)).unwrap();
        let s = model
            .signal(
                &ANGLES_4,
                &Exposure::new(2e-3, Stokes::new(3e-3, 1e-3, 1e-3)),
            )
            .unwrap();
        for i in 0..4 {
            let shot = s.cov_dn[(i, i)] - 1.0 / 12.0;
            assert!(rel(shot, 0.37 * 0.37 * s.electrons[i]) < 1e-12);
            assert!(s.electrons[i] > 100.0);
        }
    }

    /// `F_n = Variance(2)` doubles the sensor-noise variance, `StdDev(2)` quadruples it; scene
    /// clutter and drift are untouched (1e-12 relative: only rounding).
    #[test]
    fn noise_factor_semantics() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let mut exp = Exposure::new(1e-3, Stokes::new(2e-3, 4e-4, 1e-4));
        exp.radiance_cov_w2_m4_sr2 = Matrix3::from_diagonal(&Vector3::new(1e-8, 1e-9, 1e-9));
        exp.eps_cal = 0.01;
        let base = model.signal(&ANGLES_4, &exp).unwrap();
        let sensor = |s: &SensorSignal, i: usize| {
            s.cov_dn[(i, i)] - s.variance.clutter_dn2[i] - s.variance.drift_dn2[i]
        };
        for (nf, mult) in [
            (NoiseFactor::Variance(2.0), 2.0),
            (NoiseFactor::StdDev(2.0), 4.0),
        ] {
            exp.noise_factor = nf;
            let s = model.signal(&ANGLES_4, &exp).unwrap();
            assert_eq!(s.noise_variance_factor, mult);
            for i in 0..4 {
                assert!(rel(sensor(&s, i), mult * sensor(&base, i)) < 1e-12);
                assert!(rel(s.variance.clutter_dn2[i], base.variance.clutter_dn2[i]) < 1e-12);
                assert!(rel(s.variance.drift_dn2[i], base.variance.drift_dn2[i]) < 1e-12);
                for j in 0..4 {
                    if i != j {
                        assert!(
                            (s.cov_dn[(i, j)] - base.cov_dn[(i, j)]).abs()
                                < 1e-12 * base.cov_dn[(i, i)]
                        );
                    }
                }
            }
        }
        assert_eq!(NoiseFactor::default(), NoiseFactor::Variance(1.0));
    }

    /// The drift adds `(eps y_i)^2` with `y_i` the mean DN, exactly (1e-12 relative).
    #[test]
    fn drift_term() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let mut exp = Exposure::new(1e-3, Stokes::new(2e-3, 4e-4, 1e-4));
        let a = model.signal(&ANGLES_4, &exp).unwrap();
        exp.eps_cal = 0.02;
        let b = model.signal(&ANGLES_4, &exp).unwrap();
        for i in 0..4 {
            let d = (0.02 * a.mean_dn[i]).powi(2);
            assert!(rel(b.cov_dn[(i, i)] - a.cov_dn[(i, i)], d) < 1e-9);
            assert!(rel(b.variance.drift_dn2[i], d) < 1e-12);
        }
    }

    /// Drives a pure shot-noise camera (K = 1, b = 0, no read or dark noise) to a given number
    /// of electrons in the frame at 0 deg (unpolarised light, ideal analyzer).
    fn at_electrons(cam: &Camera, electrons: f64) -> SensorSignal {
        let model = SensorModel::new(cam, &band(500.0, 600.0)).unwrap();
        let t = 1e-3;
        let s0 = electrons / (model.responsivity_e_per_s() * t * 0.5);
        model
            .signal(&[0.0], &Exposure::new(t, Stokes::unpolarized(s0)))
            .unwrap()
    }

    /// Saturation: with K = 1, b = 0, full well 1000 e- and 12 bits the level is 1000 DN;
    /// 900 e- (900 + 3 sqrt(900.08) = 990.0) is not flagged, 920 e- (920 + 3 * 30.33 = 1011) is.
    /// With 8 bits the ADC ceiling 255 DN rules: 200 e- (242.4) no, 215 e- (259.0) yes. The
    /// margins (about 10 DN) are far above rounding.
    #[test]
    fn saturation_flag_level() {
        let mut cam = hand_camera();
        cam.gain_dn_per_e = 1.0;
        cam.offset_dn = 0.0;
        cam.read_noise_e = 0.0;
        cam.dark_current_e_per_s = 0.0;
        cam.full_well_e = 1000.0;
        cam.bit_depth = 12;
        assert_eq!(cam.saturation_dn(), 1000.0);
        let a = at_electrons(&cam, 900.0);
        assert!(rel(a.electrons[0], 900.0) < 1e-12);
        assert!(!a.saturated[0]);
        assert!(a.warnings.is_empty());
        let b = at_electrons(&cam, 920.0);
        assert!(b.saturated[0]);
        assert!(b.warnings.iter().any(|w| w.contains("saturation")));
        cam.bit_depth = 8;
        assert_eq!(cam.saturation_dn(), 255.0);
        assert!(!at_electrons(&cam, 200.0).saturated[0]);
        assert!(at_electrons(&cam, 215.0).saturated[0]);
    }

    /// An identity fore-optics matrix changes nothing (bit-for-bit equal W); a half-wave plate
    /// with its fast axis along x (linear part diag(1, 1, -1)) flips the sign of S2: the frames
    /// for `(S0, S1, S2)` with the plate equal those for `(S0, S1, -S2)` without (1e-12).
    #[test]
    fn fore_optics_identity_and_half_wave_plate() {
        let mut cam = hand_camera();
        let b = band(450.0, 650.0);
        let plain = SensorModel::new(&cam, &b).unwrap();
        cam.fore_optics = Some([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let ident = SensorModel::new(&cam, &b).unwrap();
        let exp = Exposure::new(1e-3, Stokes::new(2e-3, 3e-4, 8e-4));
        let (p, q) = (
            plain.signal(&ANGLES_4, &exp).unwrap(),
            ident.signal(&ANGLES_4, &exp).unwrap(),
        );
        assert_eq!(p, q);
        cam.fore_optics = Some([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]);
        let hwp = SensorModel::new(&cam, &b).unwrap();
        let h = hwp.signal(&ANGLES_4, &exp).unwrap();
        let flipped = plain
            .signal(
                &ANGLES_4,
                &Exposure::new(1e-3, Stokes::new(2e-3, 3e-4, -8e-4)),
            )
            .unwrap();
        for i in 0..4 {
            assert!(rel(h.mean_dn[i], flipped.mean_dn[i]) < 1e-12);
        }
        // The 45 deg frame sees S0/2 + S2/2 without the plate and S0/2 - S2/2 with it.
        assert!(h.mean_dn[1] < p.mean_dn[1]);
    }

    /// Analyzer rows: no `[polarizer]` gives the ideal row `0.5 [1, cos 2psi, sin 2psi]`
    /// exactly; an extinction ratio 100 with `k1 = 0.9` and a 2 deg offset gives
    /// `0.5 [k1 + k2, (k1 - k2) cos 2(psi + 2 deg), ...]` with `k2 = 0.009` (1e-15 absolute,
    /// rounding of numbers of order 1).
    #[test]
    fn ideal_and_extinction_ratio_rows() {
        let mut cam = hand_camera();
        let b = band(450.0, 650.0);
        let w = SensorModel::new(&cam, &b)
            .unwrap()
            .intensities_from_stokes(&ANGLES_4)
            .unwrap();
        for (i, &psi) in ANGLES_4.iter().enumerate() {
            let m = analyzer_row(psi);
            for (j, mj) in m.iter().enumerate() {
                assert_eq!(w[(i, j)], *mj);
            }
        }
        cam.polarizer = Polarizer {
            extinction_ratio: Some(100.0),
            transmittance: 0.9,
            offset_deg: 2.0,
        };
        let model = SensorModel::new(&cam, &b).unwrap();
        let w = model.intensities_from_stokes(&ANGLES_4).unwrap();
        let (k1, k2) = (0.9, 0.009);
        for (i, &psi) in ANGLES_4.iter().enumerate() {
            let a = 2.0 * (psi + 2f64.to_radians());
            let expect = [
                0.5 * (k1 + k2),
                0.5 * (k1 - k2) * a.cos(),
                0.5 * (k1 - k2) * a.sin(),
            ];
            for (j, e) in expect.iter().enumerate() {
                assert!((w[(i, j)] - e).abs() < 1e-15);
            }
        }
        // `inf` in TOML is the ideal analyzer too.
        cam.polarizer.extinction_ratio = Some(f64::INFINITY);
        assert_eq!(cam.polarizer.analyzer().unwrap().k2, 0.0);
        let text = cam.to_toml_string().unwrap();
        assert!(text.contains("extinction_ratio = inf"), "{text}");
        assert_eq!(Camera::from_toml_str(&text).unwrap(), cam);
    }

    /// Both example cameras parse, round-trip through TOML, and give plausible electrons: a
    /// 1 W m^-2 sr^-1 unpolarised scene (10 mW m^-2 sr^-1 nm^-1, a dim daylight surface) in the
    /// flat band [500, 600] nm at 10 ms. Independent estimate: `pi tau / (1 + 4 F^2) * A * t *
    /// QE(550) * 550 nm / (h c)` times the analyzer's 0.5 (k1 + k2); the computed value must be
    /// within 10 % of it (the QE curve is not flat over the band, and the band-mean of QE times
    /// lambda differs from the centre values by a few percent), and in [1e3, 1e5] electrons,
    /// the range in which these cameras are designed to work (above read noise squared, below
    /// or near full well). Neither camera warns for this band.
    #[test]
    fn example_cameras_parse_and_are_plausible() {
        for text in [CCD_SEED, CMOS_MODERN] {
            let cam = Camera::from_toml_str(text).unwrap();
            let back = Camera::from_toml_str(&cam.to_toml_string().unwrap()).unwrap();
            assert_eq!(back, cam);
            let model = SensorModel::new(&cam, &band(500.0, 600.0)).unwrap();
            let s = model
                .signal(&[0.0, 1.0], &Exposure::new(0.01, Stokes::unpolarized(1.0)))
                .unwrap();
            let a = cam.polarizer.analyzer().unwrap();
            let estimate = PI * cam.optics_transmittance / (1.0 + 4.0 * cam.f_number.powi(2))
                * (cam.pixel_pitch_um * 1e-6).powi(2)
                * 0.01
                * cam.qe_at(550.0)
                * 550e-9
                / (PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S)
                * 0.5
                * (a.k1 + a.k2);
            let e = s.electrons[0];
            assert!(rel(e, estimate) < 0.1, "{}: {e} vs {estimate}", cam.name);
            assert!((1e3..=1e5).contains(&e), "{}: {e}", cam.name);
            assert!(
                rel(s.electrons[1], e) < 1e-12,
                "unpolarised: same in every frame"
            );
            assert!(s.warnings.is_empty(), "{:?}", s.warnings);
            assert!(s.mean_dn.iter().all(|y| y.is_finite()));
        }
    }

    /// Each camera-file error names its field (the TOML key, or `polarizer.<key>`), and range
    /// errors carry the offending value.
    #[test]
    fn camera_errors_name_their_field() {
        let base = CCD_SEED;
        let cases: [(&str, &str, &str); 16] = [
            ("pixel_pitch_um", "pixel_pitch_um = 0", "pixel_pitch_um"),
            ("f_number", "f_number = 0.2", "f_number"),
            (
                "optics_transmittance",
                "optics_transmittance = 1.5",
                "optics_transmittance",
            ),
            ("qe", "qe = [[500, 0.5], [400, 0.5]]", "qe"),
            ("qe", "qe = [[400, 0.5], [500, 1.2]]", "qe"),
            ("qe", "qe = [[400, 0.5]]", "qe"),
            ("gain_dn_per_e", "gain_dn_per_e = -0.1", "gain_dn_per_e"),
            ("read_noise_e", "read_noise_e = nan", "read_noise_e"),
            (
                "dark_current_e_per_s",
                "dark_current_e_per_s = -1",
                "dark_current_e_per_s",
            ),
            ("offset_dn", "offset_dn = 5000", "offset_dn"),
            ("bit_depth", "bit_depth = 20", "bit_depth"),
            ("full_well_e", "full_well_e = inf", "full_well_e"),
            (
                "extinction_ratio",
                "extinction_ratio = 0.5",
                "polarizer.extinction_ratio",
            ),
            (
                "transmittance",
                "transmittance = 0",
                "polarizer.transmittance",
            ),
            ("offset_deg", "offset_deg = 400", "polarizer.offset_deg"),
            ("name", "name = \" \"", "name"),
        ];
        for (key, replacement, field) in cases {
            let text: String = base
                .lines()
                .map(|l| {
                    if l.trim_start().starts_with(&format!("{key} ")) {
                        replacement.to_string()
                    } else {
                        l.to_string()
                    }
                })
                .collect::<Vec<_>>()
                .join("\n");
            assert_ne!(text, base, "{key} not found in the example");
            let err = Camera::from_toml_str(&text).unwrap_err();
            let msg = err.to_string();
            assert!(msg.starts_with(field), "{key}: {msg}");
        }
        let with_fore = format!("fore_optics = [[0, 1, 0], [0, 1, 0], [0, 0, 1]]\n{base}");
        let err = Camera::from_toml_str(&with_fore).unwrap_err();
        assert!(err.to_string().starts_with("fore_optics"), "{err}");
        let unknown = format!("colour = 1\n{base}");
        let err = Camera::from_toml_str(&unknown).unwrap_err();
        assert!(
            err.to_string().starts_with("camera") && err.to_string().contains("colour"),
            "{err}"
        );
    }

    /// Signal errors name their field: zero, negative and NaN integration time; empty and NaN
    /// angle lists; NaN radiance; NaN drift and noise factor; a band where the QE is zero.
    #[test]
    fn signal_errors_name_their_field() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let ok = Exposure::new(1e-3, Stokes::new(1e-3, 0.0, 0.0));
        let field = |r: Result<SensorSignal, ModelError>| match r.unwrap_err() {
            ModelError::OutOfRange { field, .. } | ModelError::Invalid { field, .. } => field,
        };
        for t in [0.0, -1e-3, f64::NAN, f64::INFINITY] {
            let e = Exposure { t_int_s: t, ..ok };
            assert_eq!(field(model.signal(&ANGLES_4, &e)), "t_int_s");
        }
        assert_eq!(field(model.signal(&[], &ok)), "angles_deg");
        assert_eq!(field(model.signal(&[0.0, f64::NAN], &ok)), "angles_deg");
        let e = Exposure {
            radiance_mean_w_m2_sr: Stokes::new(1.0, f64::NAN, 0.0),
            ..ok
        };
        assert_eq!(field(model.signal(&ANGLES_4, &e)), "radiance_mean_w_m2_sr");
        let mut c = Matrix3::identity();
        c[(2, 1)] = f64::NAN;
        let e = Exposure {
            radiance_cov_w2_m4_sr2: c,
            ..ok
        };
        assert_eq!(field(model.signal(&ANGLES_4, &e)), "radiance_cov_w2_m4_sr2");
        let e = Exposure {
            eps_cal: f64::NAN,
            ..ok
        };
        assert_eq!(field(model.signal(&ANGLES_4, &e)), "eps_cal");
        let e = Exposure {
            noise_factor: NoiseFactor::StdDev(f64::NAN),
            ..ok
        };
        assert_eq!(field(model.signal(&ANGLES_4, &e)), "noise_factor");
        let e = Exposure {
            noise_factor: NoiseFactor::Variance(-1.0),
            ..ok
        };
        assert_eq!(field(model.signal(&ANGLES_4, &e)), "noise_factor");
        let mut cam = hand_camera();
        cam.qe = vec![[800.0, 0.0], [900.0, 0.5], [1000.0, 0.0]];
        let err = SensorModel::new(&cam, &band(400.0, 700.0)).unwrap_err();
        assert!(err.to_string().starts_with("band"), "{err}");
        let err =
            SensorModel::with_spectral_weight(&hand_camera(), &band(400.0, 700.0), |_| f64::NAN)
                .unwrap_err();
        assert!(err.to_string().starts_with("spectral_weight"), "{err}");
    }

    /// `Sigma_LS` must be symmetric and positive semidefinite: an asymmetric matrix and one with
    /// eigenvalue -0.1 (of largest 1.1) are rejected and the message says which test failed; a
    /// PSD matrix with a roundoff-sized negative eigenvalue (-1e-14 relative, under the 1e-9
    /// tolerance) and the zero matrix are accepted.
    #[test]
    fn non_psd_covariance_rejected() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let ok = Exposure::new(1e-3, Stokes::new(1e-3, 0.0, 0.0));
        let mut asym = Matrix3::identity();
        asym[(0, 1)] = 0.1;
        let err = model
            .signal(
                &ANGLES_4,
                &Exposure {
                    radiance_cov_w2_m4_sr2: asym,
                    ..ok
                },
            )
            .unwrap_err();
        assert!(err.to_string().contains("not symmetric"), "{err}");
        // Eigenvalues 1.1, 1, -0.1 (off-diagonal 0.6 between the first two at 0.5 each).
        let mut indefinite = Matrix3::from_diagonal(&Vector3::new(0.5, 0.5, 1.0));
        indefinite[(0, 1)] = 0.6;
        indefinite[(1, 0)] = 0.6;
        let err = model
            .signal(
                &ANGLES_4,
                &Exposure {
                    radiance_cov_w2_m4_sr2: indefinite,
                    ..ok
                },
            )
            .unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.starts_with("radiance_cov_w2_m4_sr2") && msg.contains("positive semidefinite"),
            "{msg}"
        );
        let mut nearly = Matrix3::from_diagonal(&Vector3::new(1e-6, 1e-6, -1e-20));
        nearly[(0, 1)] = 1e-7;
        nearly[(1, 0)] = 1e-7;
        assert!(model
            .signal(
                &ANGLES_4,
                &Exposure {
                    radiance_cov_w2_m4_sr2: nearly,
                    ..ok
                }
            )
            .is_ok());
        assert!(model.signal(&ANGLES_4, &ok).is_ok());
    }

    /// Zero radiance gives the dark level, finite everywhere, no clamping warning; an
    /// unphysical mean (S1 = -3 S0) gives negative intensity in the 0 deg frame, which is
    /// clamped to 0 electrons with a warning and no NaN.
    #[test]
    fn zero_and_negative_radiance_give_no_nan() {
        let model = SensorModel::new(&hand_camera(), &band(450.0, 650.0)).unwrap();
        let s = model
            .signal(&ANGLES_4, &Exposure::new(1e-3, Stokes::new(0.0, 0.0, 0.0)))
            .unwrap();
        assert!(s
            .mean_dn
            .iter()
            .chain(s.cov_dn.iter())
            .all(|v| v.is_finite()));
        assert!(s.electrons.iter().all(|&e| e == 0.0));
        assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        assert!(rel(s.mean_dn[0], 0.5 * 10.0 * 1e-3 + 100.0) < 1e-12);
        let s = model
            .signal(
                &ANGLES_4,
                &Exposure::new(1e-3, Stokes::new(1e-3, -3e-3, 0.0)),
            )
            .unwrap();
        assert!(s
            .mean_dn
            .iter()
            .chain(s.cov_dn.iter())
            .all(|v| v.is_finite()));
        assert_eq!(s.electrons[0], 0.0);
        assert!(s.electrons[2] > 0.0);
        assert!(
            s.warnings.iter().any(|w| w.contains("clamped")),
            "{:?}",
            s.warnings
        );
    }

    /// A band beyond the QE table warns that QE is taken as 0 there.
    #[test]
    fn band_beyond_qe_warns() {
        let mut cam = hand_camera();
        cam.qe = vec![[400.0, 0.5], [700.0, 0.5]];
        let model = SensorModel::new(&cam, &band(350.0, 650.0)).unwrap();
        assert_eq!(model.warnings().len(), 1);
        let s = model
            .signal(&ANGLES_4, &Exposure::new(1e-3, Stokes::unpolarized(1e-3)))
            .unwrap();
        assert!(s.warnings[0].contains("QE taken as 0"));
    }
}
