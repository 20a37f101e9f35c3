//! How a material's tolerance is shared between the errors its result adds up, the Lambertian
//! term's share of the specular albedo's error, and the tabulated sky's floor probes.

use crate::error::ModelError;
use crate::pbrdf::Surface;
use crate::quadrature::Tolerance;

/// The loosest tolerance, relative to `S0`, of the probes that measure a tabulated sky's floor
/// ([`Prepared::table_floor`]): tightened by 8 while their quadrature error exceeds a quarter
/// of the change they measure.
pub(super) const FLOOR_PROBE_TOL: f64 = 1e-3 / 8.0;

/// How [`Prepared::evaluate`] shares a material's tolerance `tol` (relative to `S0`) between
/// the errors it adds up in `error_estimate`. Those known before the field is sampled (the
/// spectral nodes', the `mu` tables', the albedo's share and a skipped path term, each within
/// `tol / 8` or `tol / 4` by their own tests, together typically `tol / 10`) are taken from it,
/// and so is `tol / 4` for a tabulated sky's interpolation error (measured at the end). Of
/// what is left (`free`), the field rays' skylight quadrature may take
/// [`SkyBudget::RAY_SHARE`] and the sky interpolant's moment errors [`SkyBudget::FIT_SHARE`]
/// plus what the rays' measured errors leave of theirs ([`Prepared::lobatto_sky`]);
/// the field's Gauss-Legendre orders then stop at what those two measured errors leave of
/// `free`, and never below the remaining tenth of it, so that the errors add up to at most
/// `tol`. Before, the rays had a fixed `tol / 8`, the interpolant `tol / 8` and the orders
/// `tol / 4`, whatever the rest had used: on the rooftop at 1e-4 the estimates came to
/// 0.13-0.32 of `tol`, and the asphalt's rays took a product-rule level more than they needed.
#[derive(Debug, Clone, Copy)]
pub(super) struct SkyBudget {
    pub(super) free: f64,
}

impl SkyBudget {
    /// The field rays' share of `free`.
    pub(super) const RAY_SHARE: f64 = 0.45;
    /// The sky interpolant's share of `free`.
    pub(super) const FIT_SHARE: f64 = 0.45;

    /// The budget at tolerance `tol` with `known` already spent (relative to `S0`); a
    /// tabulated sky keeps `tol / 4` back. At least `tol / 8` is left to share: every known
    /// error is within `tol / 8` by its own test and a skipped path within `tol / 4`.
    pub(super) fn new(tol: f64, known: f64, tabulated: bool) -> SkyBudget {
        let reserve = if tabulated { tol / 4.0 } else { 0.0 };
        SkyBudget {
            free: (tol - reserve - known).max(tol / 8.0),
        }
    }

    /// Each field ray's skylight quadrature error (relative to `S0`); the probe of the field's
    /// corners integrates to half of it.
    pub(super) fn rays(&self) -> f64 {
        self.free * Self::RAY_SHARE
    }

    /// The sky interpolant's moment errors (relative to `S0`).
    pub(super) fn fit(&self) -> f64 {
        self.free * Self::FIT_SHARE
    }

    /// The field orders' change, given the rays' and interpolant's measured errors `spent`.
    pub(super) fn field(&self, spent: f64) -> f64 {
        (self.free - spent).max(self.free * (1.0 - Self::RAY_SHARE - Self::FIT_SHARE))
    }
}

/// A material's Lambertian term `f00_d` at the sun's incidence ([`Prepared::evaluate`]).
pub(super) struct Lambertian {
    pub(super) f00: f64,
    /// The specular albedo's quadrature error, which `f00_d` carries (over `pi`).
    pub(super) albedo_error: f64,
    pub(super) evaluations: usize,
}

impl Lambertian {
    /// A microfacet's `(DHR - specular albedo) / pi` (Eq. 3.18), the albedo to the absolute
    /// tolerance `tol_abs`; vegetation's is given, and its specular albedo, which does not
    /// enter it, is neither computed nor budgeted.
    pub(super) fn at(
        surface: &Surface,
        theta_i_rad: f64,
        tol_abs: f64,
    ) -> Result<Lambertian, ModelError> {
        match *surface {
            Surface::Vegetation { f00_diffuse, .. } => Ok(Lambertian {
                f00: f00_diffuse,
                albedo_error: 0.0,
                evaluations: 0,
            }),
            Surface::Microfacet { .. } => {
                let d = surface.diffuse(theta_i_rad, Tolerance::absolute(tol_abs))?;
                Ok(Lambertian {
                    f00: d.f00,
                    albedo_error: d.specular_albedo.error,
                    evaluations: d.specular_albedo.evaluations,
                })
            }
        }
    }
}

/// [`Prepared::table_floor`]'s measurement.
pub(super) struct FloorProbe {
    /// The floor, radiance (the Stokes norm of the reflected skylight's change).
    pub(super) floor: f64,
    /// The centre ray's `S0` it was measured at.
    pub(super) s0: f64,
    pub(super) evaluations: usize,
    /// The table's (zeniths, azimuths).
    pub(super) grid: (usize, usize),
}
