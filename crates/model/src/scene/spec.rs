//! A scene's inputs and results: the sky model, the illumination and viewing, the materials and
//! their texture, and each material's statistics with its error, its terms and its floor.

use crate::atmosphere::{Atmosphere, Band};
use crate::pbrdf::Surface;
use crate::polarization::Stokes;
use crate::sky::table::SkyTable;
use crate::tiles::Pointing;
use nalgebra::Matrix3;
use std::sync::Arc;

/// The sky of a scene.
#[derive(Debug, Clone, PartialEq, Default)]
pub enum SkyModel {
    /// Single scattering in the plane-parallel layer of [`Atmosphere`] (Rayleigh with
    /// depolarisation plus Henyey-Greenstein aerosol), band-integrated.
    #[default]
    SingleScattering,
    /// Radiance from single scattering; DoLP and E-vector from the Berry-Dennis-Lee pattern
    /// ([`BerrySky`]), whose neutral points multiple scattering produces.
    Berry {
        /// Angle between the Babinet and Brewster points, degrees, `[0, 60]`.
        separation_deg: f64,
        /// The pattern's largest DoLP, `[0, 1]` (clear skies: 0.6-0.8).
        max_dolp: f64,
    },
    /// A band sky tabulated by a radiative-transfer code, in W m^-2 sr^-1 for this scene's band
    /// at the ground; transmitted to the sensor with the band-mean transmittance.
    Table(Arc<SkyTable>),
}

/// Illumination and viewing shared by every material of a scene.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneSpec {
    /// Sun zenith angle, degrees, `[0, 90]`.
    pub sun_zenith_deg: f64,
    /// Sun azimuth, degrees clockwise from north.
    pub sun_azimuth_deg: f64,
    /// The atmosphere.
    pub atmosphere: Atmosphere,
    /// Which sky lights the scene (the direct beam and path radiance always come from
    /// `atmosphere`).
    pub sky: SkyModel,
    /// The sensor's spectral band.
    pub band: Band,
    /// Where the sensor is and looks.
    pub pointing: Pointing,
}

/// A material's texture: the pixel-to-pixel variation of its reflectance (MODEL.md section 11).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Texture {
    /// No texture.
    None,
    /// A coefficient of variation of the reflectance, `[0, 1]`: `Sigma_v = diag((cv S_k)^2)` of
    /// the reflected (surface) part of the mean.
    Cv(f64),
    /// Measured over a uniform region: the standard deviation of each of `S0, S1, S2` divided by
    /// the region's mean surface-leaving `S0` (measure close to the surface, or subtract the
    /// path radiance first), each `[0, 1]`: `Sigma_v = diag((c_k S0_surface)^2)`, so that the
    /// texture does not grow with the path radiance of a higher sensor.
    Measured([f64; 3]),
}

/// One material of the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneMaterial {
    /// Its name in the scene.
    pub name: String,
    /// The reflection model.
    pub surface: Surface,
    /// Its texture.
    pub texture: Texture,
}

/// What was done about one term.
#[derive(Debug, Clone, PartialEq)]
pub struct TermReport {
    /// Whether the term is in the result.
    pub evaluated: bool,
    /// Its size (or, when skipped, the bound that justified skipping), relative to `S0`.
    pub relative_size: f64,
    /// Why, in words.
    pub reason: String,
}

/// The decisions and costs of one material's evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct Terms {
    /// Direct sunlight (Eq. 3.21): always evaluated.
    pub direct: TermReport,
    /// Reflected skylight (Eq. 3.22).
    pub skylight: TermReport,
    /// Path radiance (Eq. 3.23).
    pub path: TermReport,
    /// Geometry variation `Sigma_g`.
    pub geometry: TermReport,
    /// Texture variation `Sigma_v`.
    pub texture: TermReport,
    /// Gauss-Legendre order over the field of view in each direction (1: the centre ray only).
    pub field_order: usize,
    /// Spectral nodes used.
    pub spectral_nodes: usize,
}

/// A material's statistics at the aperture, in the camera frame (x along the image rows),
/// W m^-2 sr^-1 band-integrated (times the band's relative response).
#[derive(Debug, Clone, PartialEq)]
pub struct MaterialResult {
    /// The material's name.
    pub name: String,
    /// Mean Stokes radiance over the field of view.
    pub mean: Stokes,
    /// `Sigma_LS = Sigma_g + Sigma_v`.
    pub cov: Matrix3<f64>,
    /// `Sigma_g` alone.
    pub cov_geometry: Matrix3<f64>,
    /// Estimated error of the mean, relative to `S0`.
    pub error_estimate: f64,
    /// What was evaluated and skipped.
    pub terms: Terms,
    /// Integrand evaluations (quadrature points), all terms of this material.
    pub evaluations: usize,
    /// The error an input imposes whatever the tolerance, when one does (a tabulated sky's
    /// interpolation); `None` for scenes built from models alone.
    pub floor: Option<ErrorFloor>,
}

/// The part of a tolerance that integrating cannot buy: an input's own error bounds the answer
/// ([`Prepared::evaluate`]). Below it, the integration targets [`FLOOR_FRACTION`] of it.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorFloor {
    /// The floor, relative to the material's mean `S0`; part of its `error_estimate`.
    pub relative: f64,
    /// Which input sets it and how it was estimated, in words.
    pub source: String,
    /// The tolerance the material was integrated to: the larger of the one asked for and
    /// [`FLOOR_FRACTION`] of the floor.
    pub tolerance: f64,
    /// Whether the tolerance asked for is below the floor.
    pub below_floor: bool,
}

/// The share of an input's error floor the integration is held to when the tolerance asked
/// for is below the floor: the quadrature then adds at most a quarter of the floor to it.
pub const FLOOR_FRACTION: f64 = 0.25;
