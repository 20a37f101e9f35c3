//! Scene statistics at the aperture (Meng (2012) Eqs. 3.21-3.31, MODEL.md sections 4, 5 and 11): the
//! Stokes radiance `L_S = T_up (Lr + Ld) + Lu` of each material seen through the camera, its mean
//! over the field of view and its covariance `Sigma_LS = Sigma_g + Sigma_v`, band-integrated, with
//! an error estimate, and with the fidelity chosen from a tolerance.
//!
//! # How it is fast
//!
//! * **Spectral**: product-rule nodes ([`Band::quadratic_nodes`]) integrate the spiky
//!   `R(l) E0(l)` exactly and interpolate only the smooth atmospheric factors; the node count
//!   doubles until the band-integrated direct beam and zenith sky change by less than `tol / 8`.
//! * **Sky**: single scattering separates into angular factors that do not depend on wavelength
//!   (the Rayleigh and Henyey-Greenstein phase functions, the E-vector direction) times
//!   functions of the view zenith cosine `mu` only. So the band-integrated sky of a field point is
//!   `P11_R(gamma) A(mu) + HG(gamma) B(mu)` with `A` and `B` sums over the spectral nodes,
//!   tabulated once on 257 points of `mu` (4x more while its error exceeds tol/8) and
//!   interpolated with 4-point Lagrange cubics; the
//!   table's error is measured against a half-resolution table and reported. The sky
//!   irradiance integrates the azimuth in closed form (Rayleigh: a polynomial; Henyey-Greenstein:
//!   a complete elliptic integral of the second kind by the AGM) and `mu` adaptively.
//! * **Field of view**: the mean and covariance over the image are integrals over the image
//!   plane, computed with tensor Gauss-Legendre rules of order 2, 3, 4, 6, 8, 12 until the mean
//!   and the covariance's scale change by less than the error budget leaves them (below; the
//!   last change is reported and added to the error). A probe of the field's corners decides
//!   whether one ray suffices (a 1-degree field of view: `Sigma_g` skipped); when the cheap
//!   terms (direct, path) alone vary by `tol / 4` it does not integrate the skylight.
//! * **Skylight over the field**: a polynomial through Chebyshev-Lobatto rays (a sparse grid
//!   grown from the cross up to 5 x 5; the probe's rays reused) replaces the
//!   hemisphere integral at every field ray once the four order-2 Gauss-Legendre rays show
//!   that the field mean and spread it gives are within its budget (below; to leading order,
//!   with a margin of 1.7-3.9; `fit_moment_errors`) and that it predicts them within four
//!   times that; the larger of the mean's and the spread's errors and its rays' quadrature
//!   errors are reported (`Prepared::lobatto_sky`). If it never does, every field ray
//!   integrates its own skylight. Once the cross's four edge rays are accepted as a
//!   batch of level pairs, every later ray (checks, corners, 5-point nodes) computes the
//!   batch's upper level only and carries its error (`skylight::certified_level`).
//! * **Error budget** (`SkyBudget`): the errors known before the field is sampled (spectral,
//!   `mu` table, albedo, a skipped path term) are taken from the tolerance; the rays'
//!   quadrature and the interpolant each get 0.45 of the rest, and the field's orders stop at
//!   what their measured errors leave, so the reported errors add up to at most `tol`.
//! * **Parallel**: the materials, and each material's independent ray integrals, run on
//!   rayon's pool (`RAYON_NUM_THREADS`, by default one thread per core); every sum runs in a
//!   fixed order, so the results do not depend on the thread count. A ray's product rule
//!   starts two levels below the lowest its neighbours at the same tolerance needed.
//!
//! # Fidelity
//!
//! Every decision is reported in [`Terms`], relative to the class's mean `S0`:
//!
//! * **path radiance** (Eq. 3.23): analytic and cheap; dropped when below `tol / 4` (a sensor
//!   a metre above the ground);
//! * **skylight** (Eq. 3.22): a coarse integral at the field centre, to `tol / 8` of the
//!   direct term, bounds the term; when the bound is below `tol / 4` the term is skipped for
//!   every field point (a metal's specular glint at a loose tolerance); otherwise integrated in
//!   facet-slope space, a lone ray to `tol / 4` and the field's rays to their share of the
//!   error budget;
//! * **geometry variation** `Sigma_g` and **texture** `Sigma_v` as above and in [`Texture`].
//!
//! The reported `error_estimate` adds the quadrature, spectral, `mu`-table and field errors, the
//! measured size of every skipped term, the Lambertian term's share of the specular albedo's
//! error, and, for a tabulated sky, its interpolation error floor (below).
//!
//! # Error floors
//!
//! An input's own error bounds the answer whatever the tolerance; integrating below it buys
//! nothing. A tabulated sky is such an input: before the field is integrated, each material's
//! floor is measured ([`Prepared::table_floor`]: the centre ray's skylight relit by the table's
//! half-resolution copy, the change halved, plus the probes' quadrature errors, the probes
//! tightened until that error is under a quarter of the change), and the material is
//! integrated to the larger of the tolerance and [`FLOOR_FRACTION`] (a quarter) of the floor.
//! The table's sky irradiance likewise: its full and half-resolution values at a loose
//! tolerance give its floor, and it is integrated to a quarter of that at most (its quadrature
//! error then added). The result carries the floor ([`ErrorFloor`]), its `error_estimate`
//! includes it, and [`ErrorFloor::below_floor`] says when the tolerance asked for is below it.
//! Skies from a model (single scattering, Berry) and the built-in materials have no floor:
//! their results do not change.
//!
//! # Sky
//!
//! [`SkyModel`]: single scattering (above), Berry-Dennis-Lee polarisation on single-scattering
//! radiance, or a table from a radiative-transfer code ([`crate::sky::table`]). The sun beam's
//! attenuation uses the pseudo-spherical cosine ([`crate::air_mass::slant_mu0`]), so a sun at
//! the horizon still lights the sky.
//!
//! # Modules
//!
//! * [`spec`]: the scene's inputs and the results;
//! * [`prepared`]: the prepared scene: spectral nodes, `mu` tables, sky irradiance;
//! * [`band_sky`]: the band-integrated sky of a field ray;
//! * [`points`]: the radiance of field points and of the boresight;
//! * [`fit`]: the skylight over the field as a Chebyshev-Lobatto polynomial;
//! * [`budget`]: the error budget;
//! * [`floor`]: a tabulated sky's error floor;
//! * [`evaluate`]: a material's mean and covariance over the field.

mod band_sky;
mod budget;
mod evaluate;
mod fit;
mod floor;
mod points;
mod prepared;
mod spec;

pub use evaluate::evaluate;
pub use prepared::Prepared;
pub use spec::{
    ErrorFloor, MaterialResult, SceneMaterial, SceneSpec, SkyModel, TermReport, Terms, Texture,
    FLOOR_FRACTION,
};

#[cfg(test)]
mod tests;
