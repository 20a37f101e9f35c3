//! The Rayleigh (molecular) single-scattering sky over a plane-parallel layer (MODEL.md
//! section 10): its optical depth, phase matrix and radiance, the geometric factor of downward
//! single scattering, and the sunlit sky the reflection integrals take.

use crate::error::ModelError;
use crate::polarization::Stokes;
use crate::sky::radiance::{e_vector_in_frame, SkyRadiance};
use nalgebra::Vector3;

/// A Rayleigh sky lit by the sun in a given direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SunlitRayleigh {
    /// The sky model.
    pub sky: RayleighSky,
    /// Unit vector towards the sun (`z >= 0`).
    pub sun: Vector3<f64>,
}

impl SkyRadiance for SunlitRayleigh {
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes {
        let t = Vector3::new(towards.x, towards.y, towards.z.max(0.0));
        self.sky
            .stokes(&self.sun, &t)
            .unwrap_or(Stokes::new(0.0, 0.0, 0.0))
    }

    fn peak(&self) -> Option<Vector3<f64>> {
        Some(self.sun)
    }
}

/// Rayleigh optical depth of the whole atmosphere at sea level (standard pressure),
/// `tau_R = 0.008569 l^-4 (1 + 0.0113 l^-2 + 0.00013 l^-4)`, `l` in micrometres
/// (Hansen & Travis, Space Sci. Rev. 16, 527 (1974), Eq. 2.30; MODEL.md section 10).
pub fn rayleigh_optical_depth(wavelength_um: f64) -> Result<f64, ModelError> {
    let l = ModelError::check_range(
        "wavelength_nm",
        wavelength_um * 1e3,
        200.0,
        3000.0,
        "[200, 3000]",
    )? * 1e-3;
    let l2 = 1.0 / (l * l);
    Ok(0.008569 * l2 * l2 * (1.0 + 0.0113 * l2 + 0.00013 * l2 * l2))
}

/// Molecular depolarisation factor of air (Young, Appl. Opt. 19, 3427 (1980); MODEL.md).
pub const AIR_DEPOLARIZATION: f64 = 0.0279;

/// A Rayleigh (molecular) single-scattering sky over a plane-parallel, homogeneous layer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayleighSky {
    /// Vertical optical depth of the layer.
    pub optical_depth: f64,
    /// Molecular depolarisation factor `rho_n` (0 for ideal dipoles).
    pub depolarization: f64,
}

impl RayleighSky {
    /// The sea-level Rayleigh sky at `wavelength_nm`, depolarisation 0.0279.
    pub fn at_wavelength(wavelength_nm: f64) -> Result<Self, ModelError> {
        Ok(RayleighSky {
            optical_depth: rayleigh_optical_depth(wavelength_nm * 1e-3)?,
            depolarization: AIR_DEPOLARIZATION,
        })
    }

    /// `Delta = (1 - rho) / (1 + rho / 2)`: the fraction of the phase matrix that is dipole-like
    /// (Hansen & Travis 1974, Eq. 2.15).
    fn delta(&self) -> f64 {
        (1.0 - self.depolarization) / (1.0 + 0.5 * self.depolarization)
    }

    /// Phase-matrix elements `(P11, -P12)` at scattering angle with cosine `cos_gamma`,
    /// normalised so that `P11` averages to 1 over the sphere.
    pub fn phase(&self, cos_gamma: f64) -> (f64, f64) {
        let d = self.delta();
        let c2 = cos_gamma * cos_gamma;
        (0.75 * d * (1.0 + c2) + (1.0 - d), 0.75 * d * (1.0 - c2))
    }

    /// Degree of linear polarisation of singly scattered light at scattering angle `gamma`:
    /// `-P12 / P11`; its maximum, at 90 deg, is `0.75 Delta / (1 - 0.25 Delta)` = 0.9457 for
    /// air. (MODEL.md's `d_max sin^2 / (1 + cos^2)` is the same curve to first order in `rho`.)
    pub fn dolp(&self, cos_gamma: f64) -> f64 {
        let (p11, p12) = self.phase(cos_gamma);
        p12 / p11
    }

    /// Sky Stokes radiance per unit top-of-atmosphere solar irradiance (sr^-1), for light arriving
    /// from `view` (unit, upward) with the sun towards `sun` (unit), single scattering at the
    /// bottom of the layer (Liou, *An Introduction to Atmospheric Radiation*, 2nd ed., Eq. 3.5.x
    /// for the diffuse downward intensity):
    /// `L = P11(gamma) / (4 pi) * mu0 / (mu0 - mu) * (exp(-tau/mu0) - exp(-tau/mu))`,
    /// evaluated with `expm1` so that `mu = mu0` and the horizon are exact limits.
    /// Errors name `sun_zenith_deg` or `zenith_deg` when a direction is below the horizon.
    pub fn stokes(&self, sun: &Vector3<f64>, view: &Vector3<f64>) -> Result<Stokes, ModelError> {
        if sun.z.is_nan() || sun.z < 0.0 {
            return Err(ModelError::OutOfRange {
                field: "sun_zenith_deg",
                value: sun.z.clamp(-1.0, 1.0).acos().to_degrees(),
                allowed: "[0, 90]",
            });
        }
        if view.z.is_nan() || view.z < 0.0 {
            return Err(ModelError::OutOfRange {
                field: "zenith_deg",
                value: view.z.clamp(-1.0, 1.0).acos().to_degrees(),
                allowed: "[0, 90]",
            });
        }
        let cos_gamma = sun.dot(view).clamp(-1.0, 1.0);
        let (p11, p12) = self.phase(cos_gamma);
        Ok(single_scattered(
            p11,
            p12,
            downward_path(
                self.optical_depth,
                crate::air_mass::slant_mu0(sun.z),
                view.z,
            ),
            sun,
            view,
        ))
    }
}

/// The geometric factor of downward single scattering at the bottom of a homogeneous layer of
/// optical depth `tau`, sun at `mu0 = cos`, view at `mu = cos` (Liou, *An Introduction to
/// Atmospheric Radiation*): `mu0 / (mu0 - mu) (e^{-tau/mu0} - e^{-tau/mu})`, evaluated with
/// `expm1` so that `mu = mu0` and the horizon are exact limits. `mu0` enters only through the
/// sun beam's attenuation, so callers pass the pseudo-spherical
/// [`crate::air_mass::slant_mu0`].
pub(crate) fn downward_path(tau: f64, mu0: f64, mu: f64) -> f64 {
    if mu0 <= 0.0 || tau == 0.0 {
        0.0
    } else {
        downward_path_beam(tau, mu0, mu, (-tau / mu0).exp())
    }
}

/// [`downward_path`] for `mu0 > 0` and `tau != 0` with the sun beam's attenuation
/// `beam = e^{-tau/mu0}` given, so that the points of one layer's `mu` table take it once (the
/// same values to the bit).
pub(crate) fn downward_path_beam(tau: f64, mu0: f64, mu: f64, beam: f64) -> f64 {
    if mu <= 0.0 {
        beam
    } else {
        // = e^{-tau/mu0} (tau/mu) (1 - e^{-x})/x, x = tau (mu0 - mu) / (mu mu0).
        let x = tau * (mu0 - mu) / (mu * mu0);
        let ratio = if x.abs() < 1e-12 {
            1.0 - 0.5 * x
        } else {
            -(-x).exp_m1() / x
        };
        beam * (tau / mu) * ratio
    }
}

/// Stokes radiance per unit TOA irradiance of singly scattered light arriving from `towards`,
/// from a source `(omega P11, -omega P12)` (phase functions averaging 1) and the geometric
/// `path` factor.
pub(crate) fn single_scattered(
    p11: f64,
    p12: f64,
    path: f64,
    sun: &Vector3<f64>,
    towards: &Vector3<f64>,
) -> Stokes {
    let radiance = p11 / (4.0 * std::f64::consts::PI) * path;
    if radiance == 0.0 {
        return Stokes::new(0.0, 0.0, 0.0);
    }
    let (c2, s2) = e_vector_in_frame(&-towards, sun);
    let p = radiance * p12 / p11;
    Stokes::new(radiance, p * c2, p * s2)
}
