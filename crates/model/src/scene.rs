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
//! radiance, or a table from a radiative-transfer code ([`crate::sky_table`]). The sun beam's
//! attenuation uses the pseudo-spherical cosine ([`crate::air_mass::slant_mu0`]), so a sun at
//! the horizon still lights the sky.

use crate::air_mass::{air_mass, slant_mu0};
use crate::atmosphere::{Atmosphere, Band, ClearSky, OpticalDepths};
use crate::error::ModelError;
use crate::geometry::reflected_frame_x;
use crate::pbrdf::Surface;
use crate::polarization::{cos_sin_2eta, rotation_from_cos_sin_2eta, Stokes};
use crate::quadrature::{gauss_legendre_table, integrate, Tolerance};
use crate::sky::{
    downward_path, downward_path_beam, e_vector_in_frame, surface_to_frame, BerrySky, RayleighSky,
    SkyRadiance, AIR_DEPOLARIZATION,
};
use crate::sky_table::SkyTable;
use crate::skylight::{
    batch_error, certified_level, level_pair, next_pair, pair_rule, reflected_skylight,
    reflected_skylight_at, sky_irradiance, Certificate, DIRECT_PRODUCT_MIN_COS_VIEW,
};
use crate::slope::{LevelPair, Start, StokesIntegral};
use crate::tiles::{Field, Pointing, Tile};
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock};

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

/// The loosest tolerance, relative to `S0`, of the probes that measure a tabulated sky's floor
/// ([`Prepared::table_floor`]): tightened by 8 while their quadrature error exceeds a quarter
/// of the change they measure.
const FLOOR_PROBE_TOL: f64 = 1e-3 / 8.0;

/// One spectral node: centre, product-rule weight `int R E0 L_i` (W m^-2), optical depths and the
/// direct transmittance to the ground.
#[derive(Debug, Clone, Copy)]
struct Node {
    /// The wavelength (nm); the optical depths below are its, and the model needs no more of
    /// it (tests rebuild a node's sky from it).
    #[cfg_attr(not(test), allow(dead_code))]
    nm: f64,
    weight: f64,
    rayleigh: f64,
    aerosol: f64,
    t_sun: f64,
    /// Sky irradiance on the ground per unit weight (W m^-2 per W m^-2).
    e_sky: f64,
}

/// Intervals of the `mu` table at first (refined while its error exceeds tol/8,
/// [`table_intervals_for`]).
const TABLE_INTERVALS: usize = 256;

/// One spectral node's `mu` tables ([`Prepared::new`]): `A` and `B` per unit node weight at
/// `mu = j / intervals`, and their interpolation error relative to their peaks.
struct NodeTables {
    intervals: usize,
    a: Vec<f64>,
    b: Vec<f64>,
    error: f64,
}

/// The sky irradiance's phase functions integrated over azimuth, for the sun at `mu0`: the
/// Rayleigh phase `P11 = alpha + beta cos^2 gamma` in closed form, Henyey-Greenstein's by
/// [`hg_azimuthal`].
struct AzimuthalPhase {
    alpha: f64,
    beta: f64,
    mu0: f64,
    g: f64,
}

impl AzimuthalPhase {
    fn new(rayleigh: &RayleighSky, g: f64, mu0: f64) -> AzimuthalPhase {
        let (p0, _) = rayleigh.phase(0.0);
        let (p1, _) = rayleigh.phase(1.0);
        AzimuthalPhase {
            alpha: p0,
            beta: p1 - p0,
            mu0,
            g,
        }
    }

    /// `int_0^{2 pi} P11 dphi` at `mu`: `cos gamma = mu mu0 + s s0 cos phi` averages
    /// `mu^2 mu0^2 + s^2 s0^2 / 2` in its square.
    fn rayleigh(&self, mu: f64) -> f64 {
        let (mu0, s0sq) = (self.mu0, 1.0 - self.mu0 * self.mu0);
        2.0 * PI * (self.alpha + self.beta * (mu * mu * mu0 * mu0 + 0.5 * (1.0 - mu * mu) * s0sq))
    }

    /// `int_0^{2 pi} P_HG dphi` at `mu`.
    fn hg(&self, mu: f64) -> f64 {
        hg_azimuthal(self.g, mu, self.mu0)
    }

    /// The width in `mu` of the HG term's peak at `mu0` (the sun's aureole), about
    /// `(1 - |g|) max(sin theta0, 1 - |g|)`: an angular width `1 - |g|` seen at `theta0`, or
    /// around the zenith sun.
    fn peak_width(&self) -> f64 {
        let forward = 1.0 - self.g.abs();
        forward * (1.0 - self.mu0 * self.mu0).max(0.0).sqrt().max(forward)
    }

    /// Whether Simpson's rule on `intervals` resolves the peak, with 8 points or more across
    /// it: its error test, a change between two grids, cannot see a peak both step over (with
    /// g 0.99 and the sun 5 deg from the zenith, 384 intervals claimed 6.1e-3 and were 1.6e-2
    /// off, `sky_irradiance_on_the_tables_meets_its_error`).
    fn resolves(&self, intervals: usize) -> bool {
        8.0 / intervals as f64 <= self.peak_width()
    }

    /// Breakpoints of `[0, 1]` for an adaptive rule: `0`, `mu0`, `1` and `mu0 +- w grading^k /
    /// grading` for the peak's width `w`, `k >= 0`, sorted. Over `[0, 1]` whole, the adaptive
    /// rule stepped over the peak at the zenith sun with g 0.95 and tol 1e-8: 1.1e-11 off with
    /// 1.4e-13 claimed.
    fn breaks(&self, grading: f64) -> Vec<f64> {
        let peak = self.mu0.clamp(0.0, 1.0);
        let mut breaks = vec![0.0, peak, 1.0];
        let mut step = self.peak_width() / grading;
        while step > 0.0 && step < 1.0 {
            breaks.extend(
                [peak - step, peak + step]
                    .into_iter()
                    .filter(|b| *b > 0.0 && *b < 1.0),
            );
            step *= grading;
        }
        breaks.sort_by(f64::total_cmp);
        breaks.dedup();
        breaks
    }

    /// `mu` times each, at `mu = j / intervals` ([`irradiance_on_table`]'s `phases`).
    fn on_grid(&self, intervals: usize) -> Vec<(f64, f64)> {
        (0..=intervals)
            .map(|j| {
                let mu = j as f64 / intervals as f64;
                (mu * self.rayleigh(mu), mu * self.hg(mu))
            })
            .collect()
    }
}

/// `int_0^1 (p_a A + p_b B) dmu` by Simpson's rule on the points of one node's tables `a` and
/// `b` (`mu = j / intervals`), `phases[j] = (p_a, p_b)` at the same points, and its error: the
/// change from the rule on every other point, which in the rule's fourth-order regime is 15
/// times the error (taken as it is: a factor 15 to spare), plus a bound of the sum's rounding
/// (`intervals` ulps of the sum of `|f|`). `None` unless the intervals are a
/// multiple of 4 (both rules need an even count). A term whose `B` is 0 is 0 (as the adaptive
/// rule's integrand has it, whatever the phase).
fn irradiance_on_table(phases: &[(f64, f64)], a: &[f64], b: &[f64]) -> Option<(f64, f64)> {
    let intervals = phases.len().checked_sub(1)?;
    if intervals == 0 || intervals % 4 != 0 || a.len() != phases.len() || b.len() != phases.len() {
        return None;
    }
    let f: Vec<f64> = phases
        .iter()
        .zip(a.iter().zip(b))
        .map(|(&(pa, pb), (&a, &b))| pa * a + if b == 0.0 { 0.0 } else { pb * b })
        .collect();
    // Simpson's sums on step `step` (in points): ends once, odd points 4x, even inner 2x; and
    // the same of `|f|`, which bounds the sum's rounding.
    let simpson = |step: usize| {
        let (mut sum, mut abs) = (f[0] + f[intervals], f[0].abs() + f[intervals].abs());
        for (i, j) in (step..intervals).step_by(step).enumerate() {
            let (w, v) = (if i % 2 == 0 { 4.0 } else { 2.0 }, f[j]);
            sum += w * v;
            abs += w * v.abs();
        }
        let h = step as f64 / (3.0 * intervals as f64);
        (sum * h, abs * h)
    };
    let ((fine, abs), (half, _)) = (simpson(1), simpson(2));
    Some((
        fine,
        (fine - half).abs() + intervals as f64 * f64::EPSILON * abs,
    ))
}

/// The most intervals a `mu` table is refined to.
const TABLE_MAX_INTERVALS: usize = 4096;

/// The intervals a `mu` table needs for an error of `target` when it has `error` at
/// `intervals`: the fourth-order law `error ~ intervals^-4` with a factor 2 to spare, at
/// least 1.5 times as many, a multiple of 4 (the error probe takes every other point, and so
/// does the error of the sky irradiance's Simpson rule, [`irradiance_on_table`], on an even
/// count of intervals), at most [`TABLE_MAX_INTERVALS`].
fn table_intervals_for(intervals: usize, error: f64, target: f64) -> usize {
    let ratio = (2.0 * error / target.max(1e-300)).powf(0.25).max(1.5);
    let wanted = (intervals as f64 * ratio)
        .ceil()
        .min(TABLE_MAX_INTERVALS as f64) as usize;
    wanted.next_multiple_of(4).min(TABLE_MAX_INTERVALS)
}

/// 4-point Lagrange interpolation on a uniform grid over `[0, 1]` (`values.len() - 1` intervals).
#[cfg(test)]
fn lagrange4(values: &[f64], x: f64) -> f64 {
    let (j, w) = lagrange4_stencil(values.len(), x);
    stencil_dot(&w, &values[j - 1..j + 3])
}

/// [`lagrange4`] of two tables of the same length at the same `x`, sharing the stencil (the
/// reference [`BandTables`] is tested against).
#[cfg(test)]
fn lagrange4_pair(a: &[f64], b: &[f64], x: f64) -> (f64, f64) {
    let (j, w) = lagrange4_stencil(a.len(), x);
    (
        stencil_dot(&w, &a[j - 1..j + 3]),
        stencil_dot(&w, &b[j - 1..j + 3]),
    )
}

/// `w . v` for the four values of a stencil (one bounds check for the slice, not four).
#[inline]
fn stencil_dot(w: &[f64; 4], v: &[f64]) -> f64 {
    w[0] * v[0] + w[1] * v[1] + w[2] * v[2] + w[3] * v[3]
}

/// The stencil of [`lagrange4`] on a table of `len` values: the index `j` of its second point
/// (points `j - 1 ..= j + 2`) and the four weights at `x`.
fn lagrange4_stencil(len: usize, x: f64) -> (usize, [f64; 4]) {
    let m = len - 1;
    let t = x.clamp(0.0, 1.0) * m as f64;
    // t >= 0, so the truncating cast is the floor (a NaN gives 0, as NaN.floor() would) without
    // the software floor of the x86-64 baseline (2 % of a scene's instructions).
    let j = (t as usize).clamp(1, m.saturating_sub(2).max(1));
    let s = t - j as f64; // stencil j-1, j, j+1, j+2 at -1, 0, 1, 2
    (
        j,
        [
            -s * (s - 1.0) * (s - 2.0) / 6.0,
            (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0,
            -(s + 1.0) * s * (s - 2.0) / 2.0,
            (s + 1.0) * s * (s - 1.0) / 6.0,
        ],
    )
}

/// Complete elliptic integral of the second kind `E(m)`, `m = k^2` in `[0, 1]`, by the
/// arithmetic-geometric mean (Abramowitz & Stegun 17.6).
fn elliptic_e(m: f64) -> f64 {
    let m = m.clamp(0.0, 1.0);
    if m == 1.0 {
        return 1.0;
    }
    let (mut a, mut b) = (1.0, (1.0 - m).sqrt());
    let mut sum = 0.5 * m; // 2^(n-1) c_n^2 at n = 0, c0^2 = m
    let mut pow = 0.5;
    for _ in 0..40 {
        let c = 0.5 * (a - b);
        pow *= 2.0;
        sum += pow * c * c;
        let (an, bn) = (0.5 * (a + b), (a * b).sqrt());
        a = an;
        b = bn;
        if c.abs() < 1e-17 {
            break;
        }
    }
    PI / (2.0 * a) * (1.0 - sum)
}

/// `int_0^{2 pi} HG(g, cos gamma) dphi` for a view at `mu` and the sun at `mu0`
/// (`cos gamma = mu mu0 + s s0 cos phi`): with `A = 1 + g^2 - 2 g mu mu0`, `B = 2 g s s0`,
/// `int_0^pi (A - B cos phi)^{-3/2} dphi = 2 E(2B / (A + B)) / ((A - B) sqrt(A + B))`
/// (Gradshteyn & Ryzhik 2.575).
fn hg_azimuthal(g: f64, mu: f64, mu0: f64) -> f64 {
    let (s, s0) = (
        (1.0 - mu * mu).max(0.0).sqrt(),
        (1.0 - mu0 * mu0).max(0.0).sqrt(),
    );
    let a = 1.0 + g * g - 2.0 * g * mu * mu0;
    let b = (2.0 * g * s * s0).abs();
    (1.0 - g * g) * 4.0 * elliptic_e(2.0 * b / (a + b)) / ((a - b) * (a + b).sqrt())
}

/// The band sky's `A(mu)` and `B(mu)` (module docs) for one set of per-node coefficients, as
/// [`lagrange4`] interpolates them on the `mu` table, one cubic per interval: the interval's
/// 4-point Lagrange cubic in the monomial basis of its own coordinate `s` in `[0, 1]`, `A`'s
/// coefficients (`s^0` to `s^3`) then `B`'s. The same polynomials to rounding (tested), at
/// two Horner evaluations per sky direction instead of the stencil's weights and two dot
/// products (a scene's most frequent call: the sky is asked once per integrand point). Empty
/// for a tabulated sky.
struct BandTables {
    cubics: Vec<[f64; 8]>,
}

impl BandTables {
    /// The cubics of the tables `a` and `b` (the same length, at least 4 values).
    fn new(a: &[f64], b: &[f64]) -> BandTables {
        let m = a.len().saturating_sub(1);
        if m < 3 || b.len() != a.len() {
            return BandTables { cubics: Vec::new() };
        }
        // The stencil cubic `v1 + c1 s + c2 s^2 + c3 s^3` through `v0..v3` at `s = -1, 0, 1,
        // 2` ([`lagrange4_stencil`]'s weights expanded), shifted to the interval's own
        // coordinate `s' = s - d` (`d = i - j`: the first and last intervals use the stencil
        // next to them).
        let stencil = |v: &[f64]| -> [f64; 4] {
            [
                v[1],
                -v[0] / 3.0 - v[1] / 2.0 + v[2] - v[3] / 6.0,
                v[0] / 2.0 - v[1] + v[2] / 2.0,
                (v[3] - v[0]) / 6.0 + (v[1] - v[2]) / 2.0,
            ]
        };
        let shifted = |v: &[f64], d: f64| -> [f64; 4] {
            let [c0, c1, c2, c3] = stencil(v);
            [
                c0 + d * (c1 + d * (c2 + d * c3)),
                c1 + d * (2.0 * c2 + 3.0 * d * c3),
                c2 + 3.0 * d * c3,
                c3,
            ]
        };
        let pack =
            |ca: [f64; 4], cb: [f64; 4]| [ca[0], ca[1], ca[2], ca[3], cb[0], cb[1], cb[2], cb[3]];
        // The first and last intervals take the stencil next to them (`d = -1`, `+1`); the
        // interior ones their own (`d = 0`: no shift).
        let mut cubics = Vec::with_capacity(m);
        cubics.push(pack(shifted(&a[0..4], -1.0), shifted(&b[0..4], -1.0)));
        cubics.extend(
            a.windows(4)
                .zip(b.windows(4))
                .take(m - 2)
                .map(|(va, vb)| pack(stencil(va), stencil(vb))),
        );
        cubics.push(pack(
            shifted(&a[m - 3..m + 1], 1.0),
            shifted(&b[m - 3..m + 1], 1.0),
        ));
        BandTables { cubics }
    }

    /// `(A(mu), B(mu))` for `mu` in `[0, 1]` (clamped); zero for empty tables.
    #[inline]
    fn at(&self, mu: f64) -> (f64, f64) {
        let Some(last) = self.cubics.len().checked_sub(1) else {
            return (0.0, 0.0);
        };
        self.at_in(mu, last)
    }

    /// [`BandTables::at`] for non-empty tables, `last` the index of the last interval: no check
    /// per call, so that a loop over rays ([`BandSky::stokes_in_frame_batch`]) takes the empty
    /// table once.
    #[inline(always)]
    fn at_in(&self, mu: f64, last: usize) -> (f64, f64) {
        let t = mu.clamp(0.0, 1.0) * (last + 1) as f64;
        // t >= 0, so the truncating cast is the floor (see `lagrange4_stencil`); through `u32`
        // (tables hold at most `TABLE_MAX_INTERVALS` intervals), whose saturating cast is half
        // the instructions of `usize`'s.
        let i = (t as u32 as usize).min(last);
        let c = &self.cubics[i];
        let s = t - i as f64;
        (
            c[0] + s * (c[1] + s * (c[2] + s * c[3])),
            c[4] + s * (c[5] + s * (c[6] + s * c[7])),
        )
    }
}

/// The band-integrated single-scattering sky of one field point (module docs).
struct BandSky<'a> {
    prepared: &'a Prepared,
    /// The `A` and `B` tables, shared by every material's view of the same ray.
    tables: Arc<BandTables>,
    /// Tabulated sky only: the band-mean transmittance `sum c_k / sum w_k`.
    table_scale: f64,
    /// Tabulated sky only: use the half-resolution table (the interpolation-error probe).
    coarse_table: bool,
}

/// The material-independent terms of one field ray, computed once per scene and shared by
/// every material that looks along it ([`Prepared::ray_terms`]).
struct RayTerms {
    /// Per spectral node, the node weight times the ground-to-sensor transmittance.
    up: Vec<f64>,
    /// The direct irradiance `sum up_k t_sun,k mu0`.
    e_dir: f64,
    /// The sky irradiance per unit `f00_diffuse`, transmitted up (the full table's, for a
    /// tabulated sky).
    e_sky: f64,
    /// The path radiance.
    path: Vector3<f64>,
    /// The band sky's tables for `up`, built on first use.
    tables: OnceLock<Arc<BandTables>>,
}

impl BandSky<'_> {
    /// The band-integrated single-scattering radiance arriving from `towards` and its
    /// polarised part `P12 A(mu)` (module docs); `None` where the radiance is not positive.
    #[inline]
    fn single_scattering(&self, towards: &Vector3<f64>) -> Option<(f64, f64)> {
        let (intensity, pol) = self
            .prepared
            .scattering()
            .radiance(self.tables.at(towards.z.max(0.0)), towards);
        (intensity > 0.0).then_some((intensity, pol))
    }
}

/// The band sky's single-scattering constants, copied out of [`Prepared`] so that a loop over
/// rays ([`BandSky::stokes_in_frame_batch`]) holds them in registers.
#[derive(Debug, Clone, Copy)]
struct Scattering {
    sun: Vector3<f64>,
    /// `RayleighSky::phase` with its depolarisation factor taken once.
    rayleigh_phase: [f64; 2],
    aerosol_g: f64,
}

impl Scattering {
    /// The radiance `P11 A(mu) + P_HG B(mu)` arriving from `towards` and its polarised part
    /// `P12 A(mu)` (module docs), from the tables' `(A, B)` at the ray's `mu`; the radiance
    /// may be `<= 0` (the callers take that as no light).
    #[inline(always)]
    fn radiance(&self, (a, b): (f64, f64), towards: &Vector3<f64>) -> (f64, f64) {
        let c = self.sun.dot(towards).clamp(-1.0, 1.0);
        let [k0, k1] = self.rayleigh_phase;
        let c2 = c * c;
        let (p11, p12) = (k0 * (1.0 + c2) + k1, k0 * (1.0 - c2));
        let hg = ClearSky::henyey_greenstein(self.aerosol_g, c);
        (p11 * a + hg * b, p12 * a)
    }

    /// [`BandSky::stokes_in_frame`] from [`Scattering::radiance`]'s `(intensity, pol)`: the
    /// E-vector (`e = k × sun`, `k = -towards`) angle taken in `frame_x` directly, one division
    /// instead of the surface frame's and the rotation's. With `frame_x` perpendicular to `k`,
    /// `e . (k × frame_x) = frame_x . (e × k) = frame_x . sun`, since `e × k = sun - k (k .
    /// sun)`. Zero where the radiance is not positive. Branch-free (selects), so that the
    /// batch's loop vectorises.
    #[inline(always)]
    fn in_frame(
        &self,
        (intensity, pol): (f64, f64),
        towards: &Vector3<f64>,
        frame_x: &Vector3<f64>,
    ) -> Stokes {
        let k = -towards;
        let e = k.cross(&self.sun);
        let (c, s) = (e.dot(frame_x), frame_x.dot(&self.sun));
        let n2 = c * c + s * s;
        // `n2 = 0`: towards or away from the sun, no scattering plane and no polarisation.
        let (q1, q2) = if n2 == 0.0 {
            (pol, 0.0)
        } else {
            let pol = pol / n2;
            (pol * (c * c - s * s), pol * 2.0 * c * s)
        };
        let on = intensity > 0.0;
        Stokes::new(
            if on { intensity } else { 0.0 },
            if on { q1 } else { 0.0 },
            if on { q2 } else { 0.0 },
        )
    }
}

impl SkyRadiance for BandSky<'_> {
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes {
        let p = self.prepared;
        if let Sky::Table(t) = &p.sky {
            let t = match (&t.coarse, self.coarse_table) {
                (Some(c), true) => c,
                _ => &t.full,
            };
            return Stokes(t.stokes_from(towards).0 * self.table_scale);
        }
        let Some((intensity, pol)) = self.single_scattering(towards) else {
            return Stokes::new(0.0, 0.0, 0.0);
        };
        if let Sky::Berry(b) = &p.sky {
            let (dolp, c2, s2) = b.polarization(towards);
            let pol = intensity * dolp;
            return Stokes::new(intensity, pol * c2, pol * s2);
        }
        let (c2, s2) = e_vector_in_frame(&-towards, &p.sun);
        Stokes::new(intensity, pol * c2, pol * s2)
    }

    /// The single-scattering sky's E-vector angle taken in `frame_x` directly
    /// ([`Scattering::in_frame`]). Inlined into the integrands' loops: it is asked once per
    /// integrand point.
    #[inline(always)]
    fn stokes_in_frame(&self, towards: &Vector3<f64>, frame_x: &Vector3<f64>) -> Stokes {
        if !matches!(self.prepared.sky, Sky::SingleScattering) {
            return surface_to_frame(self.stokes_from(towards), towards, frame_x);
        }
        let scattering = self.prepared.scattering();
        let radiance = scattering.radiance(self.tables.at(towards.z.max(0.0)), towards);
        scattering.in_frame(radiance, towards, frame_x)
    }

    fn peak(&self) -> Option<Vector3<f64>> {
        Some(self.prepared.sun)
    }

    /// [`BandSky::stokes_in_frame`] over a batch: the tables looked up one ray at a time, the
    /// rest ([`Scattering`]) in a loop the compiler vectorises (the same values to the bit as
    /// one ray at a time, tested). Inlined into the product rules' loops, so that it is
    /// compiled for the instruction set they are dispatched to.
    #[inline(always)]
    fn stokes_in_frame_batch(
        &self,
        towards: [&[f64]; 3],
        frame_x: [&[f64]; 3],
        out: [&mut [f64]; 3],
    ) {
        if !matches!(self.prepared.sky, Sky::SingleScattering) {
            crate::sky::stokes_in_frame_each(self, towards, frame_x, out);
            return;
        }
        let scattering = self.prepared.scattering();
        let [o0, o1, o2] = out;
        let n = o0.len().min(o1.len()).min(o2.len());
        let (tx, ty, tz) = (&towards[0][..n], &towards[1][..n], &towards[2][..n]);
        let (fx, fy, fz) = (&frame_x[0][..n], &frame_x[1][..n], &frame_x[2][..n]);
        let (o0, o1, o2) = (&mut o0[..n], &mut o1[..n], &mut o2[..n]);
        // The tables' `(A, B)` go through the first two outputs, which the second loop then
        // overwrites point by point (no scratch arrays to clear).
        if let Some(last) = self.tables.cubics.len().checked_sub(1) {
            for i in 0..n {
                (o0[i], o1[i]) = self.tables.at_in(tz[i], last);
            }
        } else {
            o0.fill(0.0);
            o1.fill(0.0);
        }
        for i in 0..n {
            let towards = Vector3::new(tx[i], ty[i], tz[i]);
            let frame = Vector3::new(fx[i], fy[i], fz[i]);
            let radiance = scattering.radiance((o0[i], o1[i]), &towards);
            let s = scattering.in_frame(radiance, &towards, &frame).0;
            (o0[i], o1[i], o2[i]) = (s[0], s[1], s[2]);
        }
    }
}

/// What [`Prepared::point`] includes.
#[derive(Debug, Clone, Copy)]
struct Include {
    skylight: bool,
    path: bool,
    /// Absolute tolerance of the skylight quadrature.
    tol_abs: f64,
    /// Tabulated sky only: light the point with the half-resolution table.
    coarse_table: bool,
    /// The lowest product-rule level that neighbouring rays, integrated to the same
    /// tolerance, were accepted at: this ray's skylight starts two levels below it (`ladder`:
    /// the error test is unchanged).
    hint: Option<usize>,
    /// An accepted batch of level pairs around this batch, at the same tolerance: its rays
    /// take the batch's upper level alone, with its error ([`certified_level`]).
    certified: Option<Certificate>,
}

/// One field point's radiance in the camera frame.
#[derive(Debug, Clone, Copy, Default)]
struct Point {
    total: Vector3<f64>,
    surface: Vector3<f64>,
    /// The reflected skylight alone (part of both the above).
    sky: Vector3<f64>,
    sky_error: f64,
    evaluations: usize,
    /// The skylight's accepted product-rule level, if any.
    level: Option<usize>,
    /// The batch of level pairs this point's skylight was accepted in, if any.
    certificate: Option<Certificate>,
}

/// A field point's terms before its skylight, in the surface frame.
struct PointBase {
    /// The direct part (Eq. 3.21) with its Lambertian term.
    surface: Vector3<f64>,
    /// The path radiance (zero when not included).
    path: Vector3<f64>,
    /// The sky irradiance per unit `f00_diffuse`, transmitted up.
    e_sky: f64,
    /// The ray's material-independent terms (its band sky's coefficients and tables).
    ray: Arc<RayTerms>,
}

/// The largest angle of a ray from the field's centre for [`Prepared::points_paired`]: the
/// validation (`field_pair_study`) spanned +-6 deg in view zenith and azimuth, rays up to 8.2
/// deg from the centre (6 deg for views near the normal, where azimuth moves a ray less).
const PAIR_FIELD_DEG: f64 = 8.0;

/// A tensor Lagrange polynomial through rays on a grid of the field.
struct TensorFit {
    /// Nodes in `u`.
    nodes_u: Vec<f64>,
    /// Nodes in `v`.
    nodes_v: Vec<f64>,
    /// `values[i * nodes_v.len() + j]` at `(nodes_u[i], nodes_v[j])`.
    values: Vec<Vector3<f64>>,
}

impl TensorFit {
    fn at(&self, u: f64, v: f64) -> Vector3<f64> {
        let mv = self.nodes_v.len();
        let mut out = Vector3::zeros();
        for i in 0..self.nodes_u.len() {
            let bu = lagrange_basis(&self.nodes_u, u, i);
            for j in 0..mv {
                out += self.values[i * mv + j] * (bu * lagrange_basis(&self.nodes_v, v, j));
            }
        }
        out
    }
}

/// The reflected skylight over the field, in the camera frame: a sum of tensor Lagrange
/// polynomials with integer coefficients (one of coefficient 1 for a full grid; the
/// combination technique's for a sparse one, [`Prepared::lobatto_sky`]).
struct SkyFit {
    parts: Vec<(f64, TensorFit)>,
    /// The largest quadrature error of the fitted values.
    error: f64,
}

impl SkyFit {
    /// The polynomial through a full grid of rays.
    fn tensor(nodes_u: Vec<f64>, nodes_v: Vec<f64>, values: Vec<Vector3<f64>>, error: f64) -> Self {
        SkyFit {
            parts: vec![(
                1.0,
                TensorFit {
                    nodes_u,
                    nodes_v,
                    values,
                },
            )],
            error,
        }
    }

    /// The combination technique's interpolant for a downward-closed `set` of level pairs of
    /// [`LOBATTO_LEVELS`], from the values at its rays.
    fn sparse(
        set: &[(usize, usize)],
        value_at: impl Fn(f64, f64) -> Vector3<f64>,
        error: f64,
    ) -> Self {
        let parts = combination_coefficients(set)
            .into_iter()
            .map(|((i, j), c)| {
                let (nodes_u, nodes_v) = (LOBATTO_LEVELS[i], LOBATTO_LEVELS[j]);
                let values = grid(nodes_u, nodes_v)
                    .into_iter()
                    .map(|(u, v)| value_at(u, v))
                    .collect();
                let t = TensorFit {
                    nodes_u: nodes_u.to_vec(),
                    nodes_v: nodes_v.to_vec(),
                    values,
                };
                (c, t)
            })
            .collect();
        SkyFit { parts, error }
    }

    fn at(&self, u: f64, v: f64) -> Vector3<f64> {
        self.parts
            .iter()
            .map(|(c, t)| t.at(u, v) * *c)
            .sum::<Vector3<f64>>()
    }
}

/// The Lagrange basis polynomial of node `i` of `nodes` at `x`.
fn lagrange_basis(nodes: &[f64], x: f64, i: usize) -> f64 {
    nodes
        .iter()
        .enumerate()
        .filter(|&(k, _)| k != i)
        .map(|(_, &xk)| (x - xk) / (nodes[i] - xk))
        .product()
}

/// The nested Chebyshev-Lobatto node sets of [`Prepared::lobatto_sky`]'s sparse grids, by
/// level: the centre; the edges and centre; five points.
const LOBATTO_LEVELS: [&[f64]; 3] = [
    &[0.0],
    &[-1.0, 0.0, 1.0],
    &[
        -1.0,
        -std::f64::consts::FRAC_1_SQRT_2,
        0.0,
        std::f64::consts::FRAC_1_SQRT_2,
        1.0,
    ],
];

/// The rays `(u, v)` of the grid `nodes_u x nodes_v`, `v` fastest (the order of
/// [`TensorFit::values`]).
fn grid(nodes_u: &[f64], nodes_v: &[f64]) -> Vec<(f64, f64)> {
    nodes_u
        .iter()
        .flat_map(|&u| nodes_v.iter().map(move |&v| (u, v)))
        .collect()
}

/// The largest level in direction `axis` (0: `u`, 1: `v`) of a set's pairs on that axis.
fn set_max(set: &[(usize, usize)], axis: usize) -> usize {
    set.iter()
        .filter(|k| if axis == 0 { k.1 == 0 } else { k.0 == 0 })
        .map(|k| if axis == 0 { k.0 } else { k.1 })
        .max()
        .unwrap_or(0)
}

/// The combination technique's coefficients (Griebel, Schneider & Zenger 1992) for a
/// downward-closed set of level pairs: `c(i, j) = sum over z in {0, 1}^2 of (-1)^|z|` for
/// `(i, j) + z` in the set. The sum of `c(i, j)` times the tensor interpolant on levels
/// `(i, j)` interpolates at every ray of the set's grids.
fn combination_coefficients(set: &[(usize, usize)]) -> Vec<((usize, usize), f64)> {
    let has = |k: (usize, usize)| set.contains(&k);
    set.iter()
        .map(|&(i, j)| {
            let c = [(0, 0, 1.0), (1, 0, -1.0), (0, 1, -1.0), (1, 1, 1.0)]
                .iter()
                .filter(|(a, b, _)| has((i + a, j + b)))
                .map(|(_, _, s)| s)
                .sum::<f64>();
            ((i, j), c)
        })
        .filter(|(_, c)| *c != 0.0)
        .collect()
}

/// The leading-order errors of an interpolant's field moments (absolute).
struct MomentErrors {
    /// Of the field mean, `|E[delta]|`, `delta` the interpolant's error.
    mean: f64,
    /// Of the field spread `sqrt(|Cov|_F)` (what [`Prepared::evaluate`]'s field orders test).
    spread: f64,
}

/// Estimates the errors of the field moments of `fit` from its residuals `r_i` at the 2 x 2
/// Gauss-Legendre rays `checks` (their skylight integrated, `total` their whole radiance),
/// less `noise`, the quadrature error in each residual.
///
/// The interpolant's error `delta` is 0 at its nodes, and the 2 x 2 rule over the checks
/// estimates its field mean. To leading order, in a direction with 3 nodes,
/// `delta = c x (x^2 - 1) + e x^2 (x^2 - 1)`: its mean over `[-1, 1]` is `-2e/15`, the rule's
/// `-2e/9`; with 5 nodes, `e x^2 (x^2 - 1) (x^2 - 1/2)` has mean `e/105` and the rule `e/27`.
/// So the rule over-states the mean error by 1.67 and 3.9 times. The covariance changes by
/// `E[delta d^T] + E[d delta^T]` (`d` the radiance's deviation from its mean;
/// `E[delta delta^T]` is of second order), and the rule over the checks, `mean_i r_i d_i^T`,
/// over-states that by the same factors for the terms odd in a direction against a linear `d`
/// (`c x (x^2 - 1) x` has mean `-2c/15`, the rule `-2c/9`); the spread moves by at most
/// `|dCov|_F / (2 spread)`, and never by more than `sqrt(|dCov|_F)`.
fn fit_moment_errors(fit: &SkyFit, checks: &[((f64, f64), Point)], noise: f64) -> MomentErrors {
    let n = checks.len().max(1) as f64;
    let mean_total = checks.iter().map(|c| c.1.total).sum::<Vector3<f64>>() / n;
    let mut mean = Vector3::zeros();
    let mut cross = Matrix3::zeros();
    let mut cov = Matrix3::zeros();
    let mut d_mean = 0.0;
    for ((u, v), p) in checks {
        let r = fit.at(*u, *v) - p.sky;
        let d = p.total - mean_total;
        mean += r / n;
        cross += r * d.transpose() / n;
        cov += d * d.transpose() / n;
        d_mean += d.norm() / n;
    }
    let d_cov = ((cross + cross.transpose()).norm() - 2.0 * noise * d_mean).max(0.0);
    let spread = cov.norm().sqrt();
    MomentErrors {
        mean: (mean.norm() - noise).max(0.0),
        spread: if spread > 0.0 {
            (d_cov / (2.0 * spread)).min(d_cov.sqrt())
        } else {
            d_cov.sqrt()
        },
    }
}

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
struct SkyBudget {
    free: f64,
}

impl SkyBudget {
    /// The field rays' share of `free`.
    const RAY_SHARE: f64 = 0.45;
    /// The sky interpolant's share of `free`.
    const FIT_SHARE: f64 = 0.45;

    /// The budget at tolerance `tol` with `known` already spent (relative to `S0`); a
    /// tabulated sky keeps `tol / 4` back. At least `tol / 8` is left to share: every known
    /// error is within `tol / 8` by its own test and a skipped path within `tol / 4`.
    fn new(tol: f64, known: f64, tabulated: bool) -> SkyBudget {
        let reserve = if tabulated { tol / 4.0 } else { 0.0 };
        SkyBudget {
            free: (tol - reserve - known).max(tol / 8.0),
        }
    }

    /// Each field ray's skylight quadrature error (relative to `S0`); the probe of the field's
    /// corners integrates to half of it.
    fn rays(&self) -> f64 {
        self.free * Self::RAY_SHARE
    }

    /// The sky interpolant's moment errors (relative to `S0`).
    fn fit(&self) -> f64 {
        self.free * Self::FIT_SHARE
    }

    /// The field orders' change, given the rays' and interpolant's measured errors `spent`.
    fn field(&self, spent: f64) -> f64 {
        (self.free - spent).max(self.free * (1.0 - Self::RAY_SHARE - Self::FIT_SHARE))
    }
}

/// A material's Lambertian term `f00_d` at the sun's incidence ([`Prepared::evaluate`]).
struct Lambertian {
    f00: f64,
    /// The specular albedo's quadrature error, which `f00_d` carries (over `pi`).
    albedo_error: f64,
    evaluations: usize,
}

impl Lambertian {
    /// A microfacet's `(DHR - specular albedo) / pi` (Eq. 3.18), the albedo to the absolute
    /// tolerance `tol_abs`; vegetation's is given, and its specular albedo, which does not
    /// enter it, is neither computed nor budgeted.
    fn at(surface: &Surface, theta_i_rad: f64, tol_abs: f64) -> Result<Lambertian, ModelError> {
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

/// [`Prepared::lobatto_sky`]'s result: the interpolant with its interpolation error, if it
/// predicts its check rays, and the integrand evaluations spent.
struct LobattoSky {
    fit: Option<(SkyFit, f64)>,
    evaluations: usize,
    /// The lowest product-rule level its own rays were accepted at.
    level: Option<usize>,
}

/// The sky, resolved.
enum Sky {
    SingleScattering,
    Berry(BerrySky),
    Table(TableSky),
}

/// A tabulated sky with its half-resolution copy and their irradiances per unit band weight.
struct TableSky {
    full: Arc<SkyTable>,
    coarse: Option<SkyTable>,
    e_full: f64,
    e_coarse: f64,
}

/// The material-independent part of a scene, computed once: spectral nodes, the sky's `mu`
/// tables per node and their sky irradiances, the field geometry.
pub struct Prepared {
    spec: SceneSpec,
    sky: Sky,
    atmosphere: Atmosphere,
    /// `(k0, k1)` of the Rayleigh phase `P11 = k0 (1 + c^2) + k1`, `-P12 = k0 (1 - c^2)`
    /// ([`RayleighSky::phase`]: `k0 = 3 Delta / 4`, `k1 = 1 - Delta`).
    rayleigh_phase: [f64; 2],
    sun: Vector3<f64>,
    field: Field,
    nodes: Vec<Node>,
    /// Per node: `A_k(mu_j)`, `B_k(mu_j)` (module docs), per unit node weight.
    table_a: Vec<Vec<f64>>,
    table_b: Vec<Vec<f64>>,
    spectral_change: f64,
    table_error: f64,
    /// A tabulated sky's irradiance quadrature error relative to the irradiance, when its
    /// floor let it be integrated above the tolerance (else 0: within the tolerance's budget).
    irradiance_error: f64,
    tol: f64,
    evaluations: usize,
    /// [`Prepared::ray_terms`]' rays so far.
    rays: Mutex<HashMap<[u64; 3], Arc<RayTerms>>>,
}

impl Prepared {
    /// The single-scattering constants the band sky's per-ray arithmetic reads.
    #[inline(always)]
    fn scattering(&self) -> Scattering {
        Scattering {
            sun: self.sun,
            rayleigh_phase: self.rayleigh_phase,
            aerosol_g: self.atmosphere.aerosol_g,
        }
    }

    /// Prepares `spec` for evaluation at relative tolerance `tol` in `[1e-10, 0.1]`. Errors
    /// name the field.
    pub fn new(spec: &SceneSpec, tol: f64) -> Result<Prepared, ModelError> {
        ModelError::check_range("tolerance", tol, 1e-10, 0.1, "[1e-10, 0.1]")?;
        spec.atmosphere.validate()?;
        let field = Field::new(&spec.pointing, spec.sun_zenith_deg, spec.sun_azimuth_deg)?;
        let sun = field.omega_sun();
        let am = air_mass(spec.sun_zenith_deg);
        let atm = spec.atmosphere;
        let build = |pairs: usize| -> Result<Vec<Node>, ModelError> {
            spec.band
                .quadratic_nodes(pairs)
                .into_iter()
                .map(|(nm, weight)| {
                    let t = atm.optical_depths(nm)?;
                    Ok(Node {
                        nm,
                        weight,
                        rayleigh: t.rayleigh,
                        aerosol: t.aerosol,
                        t_sun: (-(t.rayleigh + t.aerosol) * am).exp(),
                        e_sky: 0.0,
                    })
                })
                .collect()
        };
        // Spectral refinement on the band-integrated direct beam and zenith sky.
        let probe = |nodes: &[Node]| -> (f64, f64) {
            let direct: f64 = nodes.iter().map(|n| n.weight * n.t_sun).sum();
            let zenith: f64 = nodes
                .iter()
                .map(|n| {
                    let tau = n.rayleigh + n.aerosol;
                    n.weight * downward_path(tau, slant_mu0(sun.z), 1.0)
                })
                .sum();
            (direct, zenith)
        };
        let rel = |a: f64, b: f64| {
            if a == b {
                0.0
            } else {
                ((a - b) / b.abs().max(1e-300)).abs()
            }
        };
        let mut pairs = 1;
        let mut nodes = build(pairs)?;
        let spectral_change = loop {
            let finer = build(2 * pairs)?;
            let (a, b) = (probe(&nodes), probe(&finer));
            let change = rel(a.0, b.0).max(rel(a.1, b.1));
            nodes = finer;
            pairs *= 2;
            if change < tol / 8.0 || pairs >= 256 {
                break change;
            }
        };
        let rayleigh = RayleighSky {
            optical_depth: 0.0,
            depolarization: AIR_DEPOLARIZATION,
        };
        let mu0 = sun.z;
        let mu0_slant = slant_mu0(mu0);
        // The mu tables per unit node weight: A = tau_R / tau * path / (4 pi), B likewise with
        // ssa tau_A.
        // One node's pair as a function of `mu`, the sun beam's attenuation taken once.
        let ssa = atm.aerosol_ssa;
        let factors = |n: &Node| {
            let tau = n.rayleigh + n.aerosol;
            let lit = tau != 0.0 && mu0_slant > 0.0;
            let beam = (-tau / mu0_slant).exp();
            let (rayleigh, aerosol) = (n.rayleigh, n.aerosol);
            move |mu: f64| -> (f64, f64) {
                if !lit {
                    return (0.0, 0.0);
                }
                let path = downward_path_beam(tau, mu0_slant, mu, beam) / (4.0 * PI * tau);
                (rayleigh * path, ssa * aerosol * path)
            }
        };
        // One node's tables on `intervals` intervals (`factors` at `mu = j / intervals`; the
        // points a `previous` table on `p` intervals holds,
        // where `j p / intervals` is whole, copied from it: the same rational `mu` rounds to the
        // same `f64`, so the values are the same to the bit), and their error: a
        // half-resolution table's error at the odd points, divided by 8, relative to the
        // table's peak. Fourth-order interpolation gains 16 from halving, but the largest error
        // lies between the odd points: over 20 001 values of `mu` the rooftop's tables were off
        // by up to 1.08x the odd points' error / 16 (`sized_mu_tables_meet_their_error`).
        let node_tables = |n: &Node, intervals: usize, previous: Option<&NodeTables>| {
            let fresh = factors(n);
            let mut ta = Vec::with_capacity(intervals + 1);
            let mut tb = Vec::with_capacity(intervals + 1);
            for j in 0..=intervals {
                let (a, b) = match previous {
                    Some(p) if (j * p.intervals) % intervals == 0 => {
                        let k = j * p.intervals / intervals;
                        (p.a[k], p.b[k])
                    }
                    _ => fresh(j as f64 / intervals as f64),
                };
                ta.push(a);
                tb.push(b);
            }
            let coarse_a: Vec<f64> = ta.iter().step_by(2).copied().collect();
            let coarse_b: Vec<f64> = tb.iter().step_by(2).copied().collect();
            let peak = |t: &[f64]| t.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let (peak_a, peak_b) = (peak(&ta), peak(&tb));
            let mut error = 0.0f64;
            for j in (1..intervals).step_by(2) {
                let (i, w) = lagrange4_stencil(coarse_a.len(), j as f64 / intervals as f64);
                for (coarse, t, peak) in [(&coarse_a, &ta, peak_a), (&coarse_b, &tb, peak_b)] {
                    if peak > 0.0 {
                        let e = (stencil_dot(&w, &coarse[i - 1..i + 3]) - t[j]).abs() / 8.0 / peak;
                        error = error.max(e);
                    }
                }
            }
            NodeTables {
                intervals,
                a: ta,
                b: tb,
                error,
            }
        };
        // The tables: 256 intervals, refined until their error is below tol/8. The nodes are
        // independent: built in parallel, collected in their order (the result does not depend
        // on the thread count).
        let build_tables = |nodes: &[Node], intervals: usize, previous: &[Option<NodeTables>]| {
            nodes
                .par_iter()
                .enumerate()
                .map(|(k, n)| node_tables(n, intervals, previous.get(k).and_then(Option::as_ref)))
                .collect::<Vec<NodeTables>>()
        };
        // From 256 intervals on, the table's error falls as the fourth power of the interval
        // (fourth-order interpolation; measured on the rooftop: a factor 4 in intervals gives
        // about 230x, against 4^4 = 256, while below 256 intervals the error falls more slowly):
        // a table short of tol/8 is rebuilt at the size that law asks for with a
        // factor 2 to spare, and checked again. The first size is probed on the nodes of least
        // and greatest optical depth alone, where the error is largest (the horizon's
        // transition lies at `mu ~ tau`: sharpest for the least, and the greatest has the
        // deepest attenuation), and every node's tables are built at the size their error asks
        // for and checked there; were another node's error larger, the check refines again.
        let mut intervals = TABLE_INTERVALS;
        let tau = |k: usize| nodes[k].rayleigh + nodes[k].aerosol;
        let by_tau = |a: &usize, b: &usize| tau(*a).total_cmp(&tau(*b));
        let mut probes: Vec<usize> = [
            (0..nodes.len()).min_by(by_tau),
            (0..nodes.len()).max_by(by_tau),
        ]
        .into_iter()
        .flatten()
        .collect();
        probes.dedup();
        let mut previous: Vec<Option<NodeTables>> = (0..nodes.len()).map(|_| None).collect();
        let probed: Vec<NodeTables> = probes
            .par_iter()
            .map(|&k| node_tables(&nodes[k], intervals, None))
            .collect();
        let probe_error = probed.iter().fold(0.0f64, |m, t| m.max(t.error));
        if probe_error > tol / 8.0 {
            intervals = table_intervals_for(intervals, probe_error, tol / 8.0);
        }
        for (k, t) in probes.into_iter().zip(probed) {
            previous[k] = Some(t);
        }
        let (tables, table_error) = loop {
            let tables = build_tables(&nodes, intervals, &previous);
            let error = tables.iter().fold(0.0f64, |m, t| m.max(t.error));
            if error <= tol / 8.0 || intervals >= TABLE_MAX_INTERVALS {
                break (tables, error);
            }
            intervals = table_intervals_for(intervals, error, tol / 8.0);
            previous = tables.into_iter().map(Some).collect();
        };
        // Sky irradiance per unit weight, `int_0^1 mu (P_R(mu) A(mu) + P_HG(mu) B(mu)) dmu` with
        // the phase functions integrated over azimuth in closed form: by Simpson's rule on the
        // tables' points, where `A` and `B` are already known and the phase functions, the same
        // for every node, are evaluated once (`irradiance_on_table`); a node whose rule does
        // not meet tol/64 of its zenith radiance is integrated adaptively instead.
        let phase = AzimuthalPhase::new(&rayleigh, atm.aerosol_g, mu0);
        let phases = phase.on_grid(intervals);
        // Simpson's rule where it resolves the HG term's peak ([`AzimuthalPhase::resolves`]);
        // the adaptive rule on pieces graded towards it ([`AzimuthalPhase::breaks`]).
        let on_grid = phase.resolves(intervals);
        let breaks = phase.breaks(4.0);
        let irradiances: Vec<(f64, usize)> = nodes
            .par_iter()
            .zip(&tables)
            .map(|(n, t)| {
                let scale = t.a[intervals].max(t.b[intervals]).max(1e-300);
                let target = tol / 64.0 * scale;
                if let Some((e, error)) = irradiance_on_table(&phases, &t.a, &t.b) {
                    if on_grid && error <= target {
                        return (e, 0);
                    }
                }
                let factors = factors(n);
                let f = |mu: f64| {
                    let (fa, fb) = factors(mu);
                    let hg = if fb == 0.0 { 0.0 } else { phase.hg(mu) };
                    mu * (phase.rayleigh(mu) * fa + hg * fb)
                };
                let pieces = (breaks.len() - 1) as f64;
                breaks
                    .windows(2)
                    .fold((0.0, 0), |(value, evaluations), ab| {
                        let e = integrate(f, ab[0], ab[1], Tolerance::absolute(target / pieces));
                        (value + e.value, evaluations + e.evaluations)
                    })
            })
            .collect();
        let mut evaluations = phases.len();
        for (n, (e_sky, e)) in nodes.iter_mut().zip(irradiances) {
            n.e_sky = e_sky;
            evaluations += e;
        }
        let (table_a, table_b): (Vec<Vec<f64>>, Vec<Vec<f64>>) =
            tables.into_iter().map(|t| (t.a, t.b)).unzip();
        let mut irradiance_error = 0.0;
        let sky = match &spec.sky {
            SkyModel::SingleScattering => Sky::SingleScattering,
            SkyModel::Berry {
                separation_deg,
                max_dolp,
            } => {
                let sep = ModelError::check_range(
                    "sky.separation_deg",
                    *separation_deg,
                    0.0,
                    60.0,
                    "[0, 60]",
                )?;
                let d = ModelError::check_range("sky.max_dolp", *max_dolp, 0.0, 1.0, "[0, 1]")?;
                let b = BerrySky {
                    sun,
                    separation_rad: sep.to_radians(),
                    max_dolp: d,
                };
                Sky::Berry(b)
            }
            SkyModel::Table(t) => {
                // The table replaces the sky: its irradiance, per unit band weight, on every node.
                // The table's own irradiance floor first: the full and half-resolution tables'
                // irradiances at a loose tolerance, the change halved plus their quadrature
                // errors. Integrating further than a quarter of it buys nothing (the module
                // docs, "Error floors"): only a tolerance above that is met, and the irradiance's
                // quadrature error is then carried in `irradiance_error`.
                let w: f64 = nodes.iter().map(|n| n.weight).sum();
                let peak = t.peak_radiance().max(1e-300);
                let coarse = t.half_resolution();
                let both = |tol_rel: f64| {
                    let tol_e = Tolerance::absolute(tol_rel / 64.0 * peak);
                    let e = sky_irradiance(t.as_ref(), tol_e);
                    let c = coarse.as_ref().map(|c| sky_irradiance(c, tol_e));
                    (e, c)
                };
                let loose = tol.max(FLOOR_PROBE_TOL);
                let (mut e, mut c) = both(loose);
                evaluations += e.evaluations + c.as_ref().map_or(0, |c| c.evaluations);
                let tol_e = match &c {
                    Some(c) => {
                        let change = (e.stokes.0[0] - c.stokes.0[0]).abs() + e.error + c.error;
                        tol.max(FLOOR_FRACTION * change / 2.0 / e.stokes.0[0].abs().max(1e-300))
                    }
                    None => tol,
                };
                if tol_e < loose {
                    (e, c) = both(tol_e);
                    evaluations += e.evaluations + c.as_ref().map_or(0, |c| c.evaluations);
                }
                if tol_e > tol {
                    irradiance_error = e.error / e.stokes.0[0].abs().max(1e-300);
                }
                let e_coarse = c.map_or(e.stokes.0[0], |c| c.stokes.0[0]);
                for n in &mut nodes {
                    n.e_sky = e.stokes.0[0] / w;
                }
                Sky::Table(TableSky {
                    full: Arc::clone(t),
                    coarse,
                    e_full: e.stokes.0[0] / w,
                    e_coarse: e_coarse / w,
                })
            }
        };
        Ok(Prepared {
            spec: spec.clone(),
            sky,
            atmosphere: atm,
            rayleigh_phase: {
                let (p11, p12) = rayleigh.phase(0.0);
                [p12, p11 - p12]
            },
            sun,
            field,
            nodes,
            table_a,
            table_b,
            spectral_change,
            table_error,
            irradiance_error,
            tol,
            evaluations,
            rays: Mutex::new(HashMap::new()),
        })
    }

    /// A white Lambertian surface's radiance at the ground, direct sun plus sky (W m^-2 sr^-1):
    /// the scale below which a term cannot matter for any material.
    fn white_radiance(&self) -> f64 {
        self.nodes
            .iter()
            .map(|n| n.weight * (n.t_sun * self.sun.z + n.e_sky))
            .sum::<f64>()
            / PI
    }

    /// Spectral nodes in use.
    pub fn spectral_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// The band sky at the ground (W m^-2 sr^-1 in the band), each direction's Stokes vector in
    /// the frame of [`crate::sky`]: what a sky table of this scene would hold.
    pub fn ground_sky(&self) -> Box<dyn SkyRadiance + '_> {
        let weights: Vec<f64> = self.nodes.iter().map(|n| n.weight).collect();
        Box::new(self.band_sky(&weights, false))
    }

    /// The sky model's tabulation error, relative to the sky's peak.
    pub fn table_error(&self) -> f64 {
        self.table_error
    }

    /// The band sky `sum_k c_k (A_k, B_k)` for per-node coefficients `c_k` (node weight times
    /// the ground-to-sensor transmittance).
    fn band_sky(&self, coefficients: &[f64], coarse_table: bool) -> BandSky<'_> {
        self.band_sky_with(
            Arc::new(self.band_tables(coefficients)),
            coefficients,
            coarse_table,
        )
    }

    /// [`Prepared::band_sky`] of a field ray, its tables built once for every material.
    fn ray_sky(&self, ray: &RayTerms, coarse_table: bool) -> BandSky<'_> {
        let tables = Arc::clone(
            ray.tables
                .get_or_init(|| Arc::new(self.band_tables(&ray.up))),
        );
        self.band_sky_with(tables, &ray.up, coarse_table)
    }

    fn band_sky_with(
        &self,
        tables: Arc<BandTables>,
        coefficients: &[f64],
        coarse_table: bool,
    ) -> BandSky<'_> {
        let w: f64 = self.nodes.iter().map(|n| n.weight).sum();
        BandSky {
            prepared: self,
            tables,
            table_scale: coefficients.iter().sum::<f64>() / w,
            coarse_table,
        }
    }

    /// The tables `sum_k c_k A_k` and `sum_k c_k B_k` (none for a tabulated sky, which
    /// replaces the single-scattering tables).
    fn band_tables(&self, coefficients: &[f64]) -> BandTables {
        if matches!(self.sky, Sky::Table(_)) {
            return BandTables { cubics: Vec::new() };
        }
        let combine = |tables: &[Vec<f64>]| -> Vec<f64> {
            let mut out = vec![0.0; tables[0].len()];
            for (t, c) in tables.iter().zip(coefficients) {
                for (o, v) in out.iter_mut().zip(t) {
                    *o += c * v;
                }
            }
            out
        };
        BandTables::new(&combine(&self.table_a), &combine(&self.table_b))
    }

    /// The material-independent terms of the ray of `tile`: computed on the first request and
    /// kept (keyed by the exact view direction, which [`Field::ray`] gives every material
    /// alike), so that the materials of a scene share each ray's transmittances, path radiance
    /// and band-sky tables. A scene has at most a few hundred distinct rays (the field's
    /// Gauss-Legendre orders up to 12 x 12, the interpolant's and the probes'), each with the
    /// band sky's cubics when its skylight is integrated: 64 bytes per interval of the `mu`
    /// table, at most 4096 intervals (256 KB, from tolerances near 1e-8: the rooftop at 1e-8
    /// peaks at 52 MB resident, 26 MB when the tables held values), freed with the
    /// `Prepared`. Errors name the field as [`Atmosphere::path`] does.
    fn ray_terms(&self, tile: &Tile) -> Result<Arc<RayTerms>, ModelError> {
        let view = tile.omega_view;
        let key = [view.x.to_bits(), view.y.to_bits(), view.z.to_bits()];
        let lock = || self.rays.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(r) = lock().get(&key) {
            return Ok(Arc::clone(r));
        }
        let mu0 = self.sun.z;
        let altitude = self.spec.pointing.altitude_m;
        let mut e_dir = 0.0;
        let mut e_sky = 0.0;
        let mut path = Vector3::zeros();
        let mut up = Vec::with_capacity(self.nodes.len());
        let below = self.atmosphere.fractions_below(altitude)?;
        let mu0_slant = slant_mu0(self.sun.z);
        for n in &self.nodes {
            let depths = OpticalDepths {
                rayleigh: n.rayleigh,
                aerosol: n.aerosol,
            };
            let p = self
                .atmosphere
                .path_through(depths, below, mu0_slant, &self.sun, &view);
            let t = p.transmittance * n.weight;
            up.push(t);
            e_dir += t * n.t_sun * mu0;
            e_sky += t * n.e_sky;
            path += p.radiance.0 * n.weight;
        }
        // The path radiance comes in the frame of `crate::sky` (x along k × z), the surface
        // terms in the pBRDF's (`reflected_frame_x`, the same x for a slanted ray). Straight
        // down, k × z vanishes and the two fall back to different axes (world +y; the sun's
        // horizontal turned by -90 deg), which flipped the path's S1 against the surface
        // terms' at exact nadir alone: the path is turned into the surface terms' frame there,
        // so that the camera rotation applies to one frame and a point at nadir is the limit
        // of its neighbours.
        if view.x == 0.0 && view.y == 0.0 {
            let s_r = reflected_frame_x(&self.sun, &view);
            let (c, s) = cos_sin_2eta(&Vector3::y(), &s_r, &view);
            path = rotation_from_cos_sin_2eta(c, s).0 * path;
        }
        let terms = Arc::new(RayTerms {
            up,
            e_dir,
            e_sky,
            path,
            tables: OnceLock::new(),
        });
        // Another thread may have computed the same ray meanwhile: the first one kept is
        // everyone's (the two are equal to the bit).
        Ok(Arc::clone(lock().entry(key).or_insert(terms)))
    }

    /// [`Prepared::point`] at each of `tiles`, in parallel (rayon's pool: `RAYON_NUM_THREADS`
    /// threads, by default one per core); the results in the order of `tiles`, the first
    /// error in that order if any. A batch that [`Prepared::pair_hint`] admits is integrated
    /// by [`Prepared::points_paired`].
    fn points(
        &self,
        surface: &Surface,
        f00_diffuse: f64,
        tiles: &[Tile],
        inc: Include,
    ) -> Result<Vec<Point>, ModelError> {
        if let Some(hint) = self.pair_hint(surface, tiles, inc) {
            return self.points_paired(surface, f00_diffuse, tiles, inc, hint);
        }
        let results: Vec<Result<Point, ModelError>> = tiles
            .par_iter()
            .map(|t| self.point(surface, f00_diffuse, t, inc))
            .collect();
        results.into_iter().collect()
    }

    /// The level `hint` at which `tiles`' skylight may be integrated as a batch of
    /// [`LevelPair`]s (`level_pair`): an analytic sky (a tabulated one is only C1),
    /// neighbours' ladders accepted to the same tolerance at a level the surface's
    /// [`pair_rule`] admits, at least two rays, every view within 75 deg of the normal and
    /// within [`PAIR_FIELD_DEG`] of the field's centre: the conditions it was validated under.
    fn pair_hint(&self, surface: &Surface, tiles: &[Tile], inc: Include) -> Option<usize> {
        let rule = pair_rule(surface);
        let hint = inc
            .hint
            .filter(|&h| (rule.min_hint..=rule.max_hint).contains(&h))?;
        let analytic = !matches!(self.sky, Sky::Table(_));
        if !inc.skylight || !analytic || tiles.len() < 2 {
            return None;
        }
        let centre = self.field.ray(0.0, 0.0, (0, 0)).ok()?.omega_view;
        let near = PAIR_FIELD_DEG.to_radians().cos();
        let views_ok = tiles.iter().all(|t| {
            t.omega_view.z >= DIRECT_PRODUCT_MIN_COS_VIEW && t.omega_view.dot(&centre) >= near
        });
        views_ok.then_some(hint)
    }

    /// [`Prepared::points`] for a batch admitted by [`Prepared::pair_hint`]: every ray's
    /// skylight at product-rule levels `hint - 2` and `hint - 1`; when the largest change over
    /// the batch meets the tolerance at every ray, each takes its upper level with that change
    /// as its error (and no level of its own, so that it hints no later batch). When it does
    /// not, the batch tries once more one level up (`next_pair`); then each ray
    /// resumes its own ladder from its last pair (`reflected_skylight_at`), nothing
    /// recomputed.
    fn points_paired(
        &self,
        surface: &Surface,
        f00_diffuse: f64,
        tiles: &[Tile],
        inc: Include,
        hint: usize,
    ) -> Result<Vec<Point>, ModelError> {
        if let Some(c) = inc.certified.filter(|c| c.error <= inc.tol_abs) {
            // Rays around an accepted batch: its upper level alone, with its error.
            let results: Vec<Result<Point, ModelError>> = tiles
                .par_iter()
                .map(|t| {
                    let base = self.point_base(surface, f00_diffuse, t, inc)?;
                    let sky = self.ray_sky(&base.ray, inc.coarse_table);
                    let r =
                        certified_level(surface, &sky, &t.omega_view, c, f00_diffuse, base.e_sky)?;
                    Ok(self.finish(t, base, Some(&r)))
                })
                .collect();
            return results.into_iter().collect();
        }
        // Each ray's terms, band sky and first pair, in parallel (the first error in the order
        // of `tiles`, as in `points`).
        let parts: Vec<Result<(PointBase, BandSky<'_>, LevelPair), ModelError>> = tiles
            .par_iter()
            .map(|t| {
                let base = self.point_base(surface, f00_diffuse, t, inc)?;
                let sky = self.ray_sky(&base.ray, inc.coarse_table);
                let pair = level_pair(surface, &sky, &t.omega_view, hint)?;
                Ok((base, sky, pair))
            })
            .collect();
        let mut parts: Vec<(PointBase, BandSky<'_>, LevelPair)> =
            parts.into_iter().collect::<Result<_, _>>()?;
        let tol = Tolerance::absolute(inc.tol_abs);
        let mut accepted = None;
        for step in 0..2 {
            accepted = batch_error(parts.iter().map(|(_, _, p)| p), tol);
            if accepted.is_some() {
                break;
            }
            if step == 1 {
                break;
            }
            let next: Vec<Result<Option<LevelPair>, ModelError>> = parts
                .par_iter()
                .zip(tiles)
                .map(|((_, sky, pair), t)| next_pair(surface, sky, &t.omega_view, pair))
                .collect();
            let next: Vec<Option<LevelPair>> = next.into_iter().collect::<Result<_, _>>()?;
            if next.iter().any(Option::is_none) {
                break;
            }
            for ((_, _, pair), n) in parts.iter_mut().zip(next.into_iter().flatten()) {
                *pair = n;
            }
        }
        let results: Vec<Result<Point, ModelError>> = parts
            .into_par_iter()
            .zip(tiles)
            .map(|((base, sky, pair), tile)| {
                let certificate = accepted.map(|error| Certificate {
                    level: pair.upper_level(),
                    error,
                });
                let r = match accepted {
                    Some(error) => pair.accept(error, f00_diffuse, base.e_sky),
                    None => reflected_skylight_at(
                        surface,
                        f00_diffuse,
                        base.e_sky,
                        &sky,
                        &tile.omega_view,
                        tol,
                        Start::After(&pair),
                    )?,
                };
                Ok(Point {
                    certificate,
                    ..self.finish(tile, base, Some(&r))
                })
            })
            .collect();
        results.into_iter().collect()
    }

    /// One field point's terms but its skylight.
    fn point_base(
        &self,
        surface: &Surface,
        f00_diffuse: f64,
        tile: &Tile,
        inc: Include,
    ) -> Result<PointBase, ModelError> {
        let ray = self.ray_terms(tile)?;
        let f = surface.specular(&tile.geometry);
        let e_dir = ray.e_dir;
        let mut e_sky = ray.e_sky;
        if inc.coarse_table {
            if let Sky::Table(t) = &self.sky {
                e_sky *= t.e_coarse / t.e_full.max(1e-300);
            }
        }
        // Direct (Eq. 3.21): E cos(ti) F [1, 0, 0], transmitted up.
        let mut surface_part = f.0.column(0).into_owned() * e_dir;
        surface_part[0] += f00_diffuse * e_dir;
        Ok(PointBase {
            surface: surface_part,
            path: if inc.path { ray.path } else { Vector3::zeros() },
            e_sky,
            ray,
        })
    }

    /// A field point from its terms and its reflected skylight, if integrated: rotated into
    /// the camera frame.
    fn finish(&self, tile: &Tile, base: PointBase, sky: Option<&StokesIntegral>) -> Point {
        let sky_part = sky.map_or(Vector3::zeros(), |r| r.stokes.0);
        let surface_part = base.surface + sky_part;
        let (c, s) = tile.camera_from_surface;
        let rot = rotation_from_cos_sin_2eta(c, s).0;
        Point {
            total: rot * (surface_part + base.path),
            surface: rot * surface_part,
            sky: rot * sky_part,
            sky_error: sky.map_or(0.0, |r| r.error),
            evaluations: sky.map_or(0, |r| r.evaluations),
            level: sky.and_then(|r| r.level),
            certificate: None,
        }
    }

    /// One field point: camera-frame total and surface part.
    fn point(
        &self,
        surface: &Surface,
        f00_diffuse: f64,
        tile: &Tile,
        inc: Include,
    ) -> Result<Point, ModelError> {
        let base = self.point_base(surface, f00_diffuse, tile, inc)?;
        let sky = if inc.skylight {
            let sky = self.ray_sky(&base.ray, inc.coarse_table);
            let start_level = inc.hint.map_or(0, |level| level.saturating_sub(2));
            Some(reflected_skylight(
                surface,
                f00_diffuse,
                base.e_sky,
                &sky,
                &tile.omega_view,
                Tolerance::absolute(inc.tol_abs),
                start_level,
            )?)
        } else {
            None
        };
        Ok(self.finish(tile, base, sky.as_ref()))
    }

    /// The three radiance terms of Eq. 3.24 for `material` along the boresight, band-integrated,
    /// in the camera frame (W m^-2 sr^-1): the direct sun (Eq. 3.21, transmitted up), the
    /// reflected skylight (Eq. 3.22, transmitted up) and the path radiance (Eq. 3.23). Nothing
    /// is skipped; the skylight is integrated to the scene's tolerance of the largest term.
    pub fn boresight_terms(&self, material: &SceneMaterial) -> Result<[Stokes; 3], ModelError> {
        let surface = &material.surface;
        let diffuse = surface.diffuse(
            self.spec.sun_zenith_deg.to_radians(),
            Tolerance::absolute(self.tol / 64.0),
        )?;
        let centre = self.field.ray(0.0, 0.0, (0, 0))?;
        let base = Include {
            skylight: false,
            path: true,
            tol_abs: 0.0,
            coarse_table: false,
            hint: None,
            certified: None,
        };
        let no_sky = self.point(surface, diffuse.f00, &centre, base)?;
        let white = self.white_radiance();
        let scale = no_sky.total[0].abs().max(1e-3 * white).max(1e-300);
        let all = self.point(
            surface,
            diffuse.f00,
            &centre,
            Include {
                skylight: true,
                tol_abs: self.tol * scale,
                ..base
            },
        )?;
        Ok([
            Stokes(no_sky.surface),
            Stokes(all.sky),
            Stokes(all.total - all.surface),
        ])
    }

    /// The reflected skylight over the field as a sparse-grid polynomial through
    /// Chebyshev-Lobatto rays (the combination technique, [`SkyFit::sparse`], on nested levels
    /// [`LOBATTO_LEVELS`]), checked at the four rays `(+-1/sqrt 3, +-1/sqrt 3)`. It starts as
    /// the cross `{-1, 0, 1} x {0} + {0} x {-1, 0, 1}` (five rays: the centre and corners may
    /// come from `probed`, the others are integrated with `inc`; when the cross's edges are
    /// accepted as a batch of level pairs, the checks and every later ray take the batch's
    /// upper level alone, `skylight::certified_level`); while it fails the check, it
    /// adds one level pair at a time, reusing every ray before: the mixed `(1, 1)` (the
    /// corners: the 3 x 3 grid) when the checks' residual is largest in its part odd in both
    /// directions (the `u v` term nothing else resolves), else 5 points
    /// (`{-1, -1/sqrt 2, 0, 1/sqrt 2, 1}`) in the direction whose odd part is the larger; up to
    /// the 5 x 5 grid. A field whose skylight is nearly additive in `u` and `v` then needs 5
    /// or 7 rays instead of the tensor grid's 9 or 15.
    ///
    /// The interpolant serves the field's mean and covariance, so it is checked on their
    /// errors ([`fit_moment_errors`]): both below `target`. It must also predict the check rays
    /// pointwise to `4 target`. The check rays are where a 3-point interpolant's leading error
    /// term, `f''' / 6 x (x^2 - 1)` in each direction, is largest, and the four signs combine
    /// the two directions' terms in every way, so the largest miss there is the interpolant's
    /// largest error to leading order. For 5 points, `x (x^2 - 1) (x^2 - 1/2)` is 1.81 times
    /// larger at its extremum (`x = 0.36`) than at `1/sqrt 3`, so a pointwise miss of a level
    /// with 5 points in a direction is doubled; without the corners (no `(1, 1)`), the `u v`
    /// term left out is 3 times larger at the field's corners than at the checks, so the miss
    /// is tripled. The misses are net of the quadrature errors of
    /// the rays involved; those (the fitted rays' and the check rays') are reported as the fit's
    /// `error`. Returns the interpolant and the estimated error of the field mean it gives
    /// (absolute), or `None`.
    fn lobatto_sky(
        &self,
        surface: &Surface,
        f00: f64,
        inc: Include,
        probed: &[((f64, f64), Point)],
        target: f64,
    ) -> Result<LobattoSky, ModelError> {
        let mut evaluations = 0;
        let mut rays: Vec<((f64, f64), Point)> = probed.to_vec();
        let find = |rays: &[((f64, f64), Point)], u: f64, v: f64| {
            rays.iter()
                .find(|((a, b), _)| (a - u).abs() < 1e-12 && (b - v).abs() < 1e-12)
                .map(|(_, p)| *p)
        };
        // The rays at `coords`: those not integrated yet are, in parallel.
        let mut fetch = |coords: &[(f64, f64)],
                         rays: &mut Vec<((f64, f64), Point)>,
                         inc: Include|
         -> Result<Vec<Point>, ModelError> {
            let mut out = Vec::with_capacity(coords.len());
            let mut missing = Vec::new();
            for (i, &(u, v)) in coords.iter().enumerate() {
                let known = find(rays, u, v);
                if known.is_none() {
                    missing.push((i, self.field.ray(u, v, (0, 0))?));
                }
                out.push(known.unwrap_or_default());
            }
            let tiles: Vec<Tile> = missing.iter().map(|m| m.1).collect();
            for ((i, _), p) in missing.iter().zip(self.points(surface, f00, &tiles, inc)?) {
                evaluations += p.evaluations;
                rays.push((coords[*i], p));
                out[*i] = p;
            }
            Ok(out)
        };
        let g = 1.0 / 3f64.sqrt();
        let check_coords = [(-g, -g), (g, -g), (-g, g), (g, g)];
        // The rays of a set of level pairs, each once, in the order of the set.
        let set_rays = |set: &[(usize, usize)]| -> Vec<(f64, f64)> {
            let mut out: Vec<(f64, f64)> = Vec::new();
            for &(i, j) in set {
                for c in grid(LOBATTO_LEVELS[i], LOBATTO_LEVELS[j]) {
                    if !out.contains(&c) {
                        out.push(c);
                    }
                }
            }
            out
        };
        // The sparse grid starts as the cross `{-1, 0, 1} x {0} + {0} x {-1, 0, 1}`.
        let mut set = vec![(0, 0), (1, 0), (0, 1)];
        let points = fetch(&set_rays(&set), &mut rays, inc)?;
        // The later rays (the checks, then every later level's) start two product-rule levels
        // below the lowest level of these neighbours, integrated to the same tolerance
        // (`reflected_skylight`). (Rays accepted as a batch of level pairs have no level of
        // their own: then the hint that admitted them stands.) When the cross's edges were
        // accepted as such a batch, the later rays, which lie around them, take its upper
        // level alone, with its error (`certified_level`).
        let level = points.iter().filter_map(|p| p.level).chain(inc.hint).min();
        let later = Include {
            hint: level,
            certified: points.iter().find_map(|p| p.certificate),
            ..inc
        };
        let check_points = fetch(&check_coords, &mut rays, later)?;
        let checks: Vec<((f64, f64), Point)> = check_coords.into_iter().zip(check_points).collect();
        let check_error = checks.iter().fold(0.0f64, |m, c| m.max(c.1.sky_error));
        loop {
            let coords = set_rays(&set);
            let points = fetch(&coords, &mut rays, later)?;
            let value_at = |u: f64, v: f64| {
                coords
                    .iter()
                    .zip(&points)
                    .find(|((a, b), _)| *a == u && *b == v)
                    .map_or(Vector3::zeros(), |(_, p)| p.sky)
            };
            let error = points.iter().fold(0.0f64, |m, p| m.max(p.sky_error));
            let fit = SkyFit::sparse(&set, value_at, error);
            let noise = fit.error + check_error;
            // The residuals at the checks, less their quadrature errors, and their parts odd
            // in `u` and `v` and in both.
            let mut miss = 0.0f64;
            let (mut odd_u, mut odd_v, mut odd_uv) =
                (Vector3::zeros(), Vector3::zeros(), Vector3::zeros());
            for ((u, v), p) in &checks {
                let r = fit.at(*u, *v) - p.sky;
                miss = miss.max(r.norm() - p.sky_error - fit.error);
                odd_u += r * u.signum();
                odd_v += r * v.signum();
                odd_uv += r * (u * v).signum();
            }
            // A pointwise miss at the checks bounds the interpolant's error elsewhere to
            // leading order (see above), doubled where a direction has 5 points; without the
            // mixed level (1, 1), the `u v` term it leaves out is 3 times larger at the
            // field's corners than at the checks (`g^2 = 1/3`).
            let has = |k: (usize, usize)| set.contains(&k);
            let factor = if has((2, 0)) || has((0, 2)) { 2.0 } else { 1.0 }
                * if has((1, 1)) { 1.0 } else { 3.0 };
            let pointwise = factor * miss.max(0.0);
            let moments = fit_moment_errors(&fit, &checks, noise);
            // What the rays left of their budget (`inc.tol_abs`, the largest error any of them
            // may carry) goes to the moments: the two errors together stay within the rays'
            // and the interpolant's shares of `SkyBudget`, and the field's orders keep theirs.
            // (Rooftop glass at 1e-4: rays at 0.28 of their budget, the spread's error at 1.04
            // of the interpolant's, which took two rays more.)
            let moment_target = target + (inc.tol_abs - error.max(check_error)).max(0.0);
            if moments.mean.max(moments.spread) < moment_target && pointwise < 4.0 * target {
                let fit = SkyFit {
                    error: fit.error.max(check_error),
                    ..fit
                };
                return Ok(LobattoSky {
                    fit: Some((fit, moments.mean.max(moments.spread))),
                    evaluations,
                    level,
                });
            }
            // The next level pair: the mixed one when the residual's part odd in both
            // directions (the `u v` term only it resolves) is the largest, else the direction
            // whose odd part is the larger gets its 5 points first; every admissible pair in
            // turn until the 5 x 5 grid.
            let admissible = |k: (usize, usize)| {
                k.0 <= 2
                    && k.1 <= 2
                    && !has(k)
                    && (k.0 == 0 || has((k.0 - 1, k.1)))
                    && (k.1 == 0 || has((k.0, k.1 - 1)))
            };
            let (u_next, v_next) = ((set_max(&set, 0) + 1, 0), (0, set_max(&set, 1) + 1));
            let mut order = if odd_uv.norm() >= odd_u.norm().max(odd_v.norm()) {
                vec![(1, 1), u_next, v_next]
            } else if odd_u.norm() >= odd_v.norm() {
                vec![u_next, v_next, (1, 1)]
            } else {
                vec![v_next, u_next, (1, 1)]
            };
            order.extend([(2, 1), (1, 2), (2, 2)]);
            match order.into_iter().find(|&k| admissible(k)) {
                Some(k) => set.push(k),
                None => break,
            }
        }
        Ok(LobattoSky {
            fit: None,
            evaluations,
            level,
        })
    }

    /// [`Prepared::evaluate`] for each of `materials`, in parallel; the results in the order
    /// of `materials`, the first error in that order if any. The results are the same, to the
    /// bit, as one at a time: every sum runs in a fixed order.
    pub fn evaluate_all(
        &self,
        materials: &[SceneMaterial],
    ) -> Result<Vec<MaterialResult>, ModelError> {
        let results: Vec<Result<MaterialResult, ModelError>> =
            materials.par_iter().map(|m| self.evaluate(m)).collect();
        results.into_iter().collect()
    }

    /// Evaluates one material over the field of view. Its independent ray integrals run in
    /// parallel (rayon's pool: `RAYON_NUM_THREADS` threads, by default one per core).
    ///
    /// A tabulated sky bounds the answer's error by its interpolation error whatever the
    /// tolerance: that floor is measured first ([`Prepared::table_floor`]), the material is
    /// integrated to the larger of the tolerance and [`FLOOR_FRACTION`] of the floor, and the
    /// floor is part of the error estimate and reported in [`MaterialResult::floor`].
    pub fn evaluate(&self, material: &SceneMaterial) -> Result<MaterialResult, ModelError> {
        match material.texture {
            Texture::None => {}
            Texture::Cv(cv) => {
                ModelError::check_range("texture_cv", cv, 0.0, 1.0, "[0, 1]")?;
            }
            Texture::Measured(c) => {
                for v in c {
                    ModelError::check_range("texture_stokes_cv", v, 0.0, 1.0, "[0, 1] each")?;
                }
            }
        }
        let Some(probe) = self.table_floor(&material.surface)? else {
            return self.evaluate_to(material, self.tol, None);
        };
        let probed = (probe.floor / probe.s0).min(1.0);
        let tol = self.tol.max(FLOOR_FRACTION * probed).min(0.1);
        let mut result = self.evaluate_to(material, tol, Some(probe.floor))?;
        result.evaluations += probe.evaluations;
        let relative = probe.floor / result.mean.0[0].abs().max(1e-300);
        let (nz, na) = probe.grid;
        result.floor = Some(ErrorFloor {
            relative,
            source: format!(
                "sky table interpolation ({nz} zeniths x {na} azimuths): the centre ray's skylight \
                 relit by the table's half-resolution copy, the change halved, its quadrature \
                 error added"
            ),
            tolerance: tol,
            below_floor: self.tol < relative,
        });
        Ok(result)
    }

    /// A tabulated sky's error floor for `surface`, before the field is integrated: the
    /// centre ray's reflected skylight with the table and with its half-resolution copy, the
    /// change halved (the least a convergent interpolant gains from halving its step) plus
    /// both integrals' quadrature errors halved. The probes start at [`FLOOR_PROBE_TOL`] of
    /// `S0` (or the scene's tolerance / 8 if looser) and are tightened by 8, down to the scene's
    /// tolerance / 8, while their quadrature errors exceed a quarter of the change: so the floor
    /// is the table's, not the probes'. `None` for a sky that is not a table, or a table too
    /// coarse to halve.
    fn table_floor(&self, surface: &Surface) -> Result<Option<FloorProbe>, ModelError> {
        let Sky::Table(t) = &self.sky else {
            return Ok(None);
        };
        if t.coarse.is_none() {
            return Ok(None);
        }
        let theta_sun = self.spec.sun_zenith_deg.to_radians();
        let centre = self.field.ray(0.0, 0.0, (0, 0))?;
        let mut tol_probe = (self.tol / 8.0).max(FLOOR_PROBE_TOL);
        let diffuse = Lambertian::at(surface, theta_sun, tol_probe / 64.0)?;
        let mut evaluations = diffuse.evaluations;
        let base = Include {
            skylight: false,
            path: true,
            tol_abs: 0.0,
            coarse_table: false,
            hint: None,
            certified: None,
        };
        let cheap = self.point(surface, diffuse.f00, &centre, base)?;
        let mut scale = cheap.total[0]
            .abs()
            .max(1e-2 * self.white_radiance())
            .max(1e-300);
        loop {
            let full = Include {
                skylight: true,
                tol_abs: tol_probe * scale,
                ..base
            };
            let half = Include {
                coarse_table: true,
                ..full
            };
            let (h, f) = rayon::join(
                || self.point(surface, diffuse.f00, &centre, half),
                || self.point(surface, diffuse.f00, &centre, full),
            );
            let (h, f) = (h?, f?);
            evaluations += h.evaluations + f.evaluations;
            let change = (h.sky - f.sky).norm();
            let quadrature = h.sky_error + f.sky_error;
            let s0 = f.total[0].abs().max(1e-300);
            if quadrature <= change / 4.0 || tol_probe <= self.tol / 8.0 {
                return Ok(Some(FloorProbe {
                    floor: (change + quadrature) / 2.0,
                    s0,
                    evaluations,
                    grid: t.full.grid(),
                }));
            }
            tol_probe = (tol_probe / 8.0).max(self.tol / 8.0);
            scale = s0;
        }
    }

    /// [`Prepared::evaluate`] at tolerance `tol` (at least the scene's), a tabulated sky's
    /// measured floor `table_floor` (radiance) added to the error estimate.
    fn evaluate_to(
        &self,
        material: &SceneMaterial,
        tol: f64,
        table_floor: Option<f64>,
    ) -> Result<MaterialResult, ModelError> {
        let surface = &material.surface;
        let theta_sun = self.spec.sun_zenith_deg.to_radians();
        let mut diffuse = Lambertian::at(surface, theta_sun, tol / 64.0)?;
        let mut evaluations = diffuse.evaluations;
        let mut f00 = diffuse.f00;
        let coarse_f00 = f00;
        let centre = self.field.ray(0.0, 0.0, (0, 0))?;
        let direct_only = Include {
            skylight: false,
            path: false,
            tol_abs: 0.0,
            coarse_table: false,
            hint: None,
            certified: None,
        };
        // Scale of every decision: the centre's direct term, floored by the band's TOA
        // irradiance times 1e-15 (the sun at the horizon gives no direct light at all).
        let floor = 1e-15 * self.nodes.iter().map(|n| n.weight).sum::<f64>().abs();
        let d0 = self.point(surface, f00, &centre, direct_only)?;
        let s0_direct = d0.total[0].abs().max(floor).max(1e-300);

        // A white Lambertian surface's radiance: the floor of the first skylight estimate's
        // scale, so that a dark material seen away from the sun (skylight >> direct) does not
        // buy a needlessly tight coarse integral.
        let white = self.white_radiance();
        let with_path = self.point(
            surface,
            f00,
            &centre,
            Include {
                path: true,
                ..direct_only
            },
        )?;
        // Skylight: a coarse integral at the centre bounds the term; its tolerance is tol/8 of
        // the estimated S0 (redone once if the first scale was too loose).
        let mut coarse_scale = s0_direct.max(1e-2 * white);
        let (coarse, s0_est) = loop {
            let coarse = self.point(
                surface,
                f00,
                &centre,
                Include {
                    skylight: true,
                    tol_abs: tol / 8.0 * coarse_scale,
                    ..direct_only
                },
            )?;
            evaluations += coarse.evaluations;
            let s0_est = (coarse.total + with_path.total - d0.total)[0]
                .abs()
                .max(s0_direct);
            if coarse.sky_error <= tol / 8.0 * s0_est || coarse_scale <= s0_est {
                break (coarse, s0_est);
            }
            coarse_scale = s0_est;
        };
        let sky_bound = ((coarse.total - d0.total).norm() + coarse.sky_error) / s0_est;
        let skylight = sky_bound >= tol / 4.0;
        let skylight_report = TermReport {
            evaluated: skylight,
            relative_size: sky_bound,
            reason: if skylight {
                "integrated over the hemisphere (facet-slope space for microfacets)".into()
            } else {
                format!(
                    "a coarse integral plus its error is {sky_bound:.2e} of S0, below tol/4 ({} evaluations)",
                    coarse.evaluations
                )
            },
        };
        let path_rel = (with_path.total - d0.total).norm() / s0_est;
        let path = path_rel >= tol / 4.0;
        let altitude = self.spec.pointing.altitude_m;
        let path_report = TermReport {
            evaluated: path,
            relative_size: path_rel,
            reason: if path {
                format!("{path_rel:.2e} of S0 at {altitude} m")
            } else {
                format!("{path_rel:.2e} of S0 at {altitude} m, below tol/4")
            },
        };
        // The Lambertian term f00_d = (DHR - specular albedo) / pi carries the albedo's error
        // times the irradiance: `error * white` of radiance. A dark material (S0 << white) needs
        // the albedo tighter than tol/64: redone to tol/16 of S0 when above tol/8.
        let albedo_target = tol / 8.0 * s0_est / white.max(1e-300);
        if diffuse.albedo_error > albedo_target {
            diffuse = Lambertian::at(surface, theta_sun, albedo_target / 2.0)?;
            evaluations += diffuse.evaluations;
            f00 = diffuse.f00;
        }
        // The coarse integral's skylight with the current Lambertian term: the point is linear
        // in `f00_d`, whose term is unpolarised, so only its S0 moves, by the change times the
        // sky irradiance (the same in the camera frame). Its quadrature error is the specular
        // part's and does not change; the albedo's error is in the budget below.
        let coarse_sky =
            coarse.sky + Vector3::x() * ((f00 - coarse_f00) * self.ray_terms(&centre)?.e_sky);
        // Every tolerance from here on is relative to the estimated S0.
        let s0_direct = s0_est;
        let inc = Include {
            skylight,
            path,
            tol_abs: tol / 4.0 * s0_direct,
            coarse_table: false,
            hint: None,
            certified: None,
        };

        // Geometry: the field's corners decide whether one ray is enough: the field's mean then
        // differs from the centre by less than the largest corner difference. The cheap terms
        // (direct and path) first: when they alone vary by tol/4 or more the field is sampled
        // whatever the skylight does, and the corners' skylight is not integrated here (it is
        // at most a needless sampling when the skylight's variation cancels theirs). Otherwise
        // every included term (skylight at half the rays' budget, its error added).
        //
        // The error budget of the field (`SkyBudget`): what the errors known by now leave of
        // the tolerance, shared by the rays' quadrature and the sky's interpolant, the field's
        // orders taking what their measured errors leave.
        let budget = SkyBudget::new(
            tol,
            self.spectral_change
                + self.table_error
                + diffuse.albedo_error * white / s0_direct
                + if path { 0.0 } else { path_rel },
            matches!(self.sky, Sky::Table(_)),
        );
        let (ray_tol, fit_tol) = (budget.rays(), budget.fit());
        let corners = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)];
        let cheap = Include {
            skylight: false,
            ..inc
        };
        let cheap_centre = self.point(surface, f00, &centre, cheap)?;
        // The centre with the coarse integral's skylight, when that is tight enough (below).
        let coarse_centre = Point {
            total: cheap_centre.total + coarse_sky,
            surface: cheap_centre.surface + coarse_sky,
            sky: coarse_sky,
            sky_error: coarse.sky_error,
            evaluations: 0,
            level: coarse.level,
            certificate: None,
        };
        let mut cheap_spread = 0.0f64;
        let mut corner_tiles = Vec::with_capacity(4);
        for (u, v) in corners {
            let t = self.field.ray(u, v, (0, 0))?;
            let p = self.point(surface, f00, &t, cheap)?;
            cheap_spread = cheap_spread.max((p.total - cheap_centre.total).norm() / s0_direct);
            corner_tiles.push(((u, v), t));
        }
        // Rays whose skylight is already integrated, to the rays' budget or tighter: with the
        // centre they are rays of the sky's field interpolant below.
        let mut probed: Vec<((f64, f64), Point)> = Vec::new();
        let probe = Include {
            tol_abs: ray_tol / 2.0 * s0_direct,
            ..inc
        };
        let (spread, c0) = if cheap_spread >= tol / 4.0 {
            (cheap_spread, None)
        } else {
            // The centre: the coarse integral's skylight on the cheap terms when it already
            // meets the probe's tolerance (the point is linear in its terms), else integrated.
            let c0 = if skylight && coarse.sky_error <= ray_tol / 2.0 * s0_direct {
                coarse_centre
            } else {
                let c0 = self.point(surface, f00, &centre, probe)?;
                evaluations += c0.evaluations;
                c0
            };
            let mut spread = 0.0f64;
            probed.push(((0.0, 0.0), c0));
            let tiles: Vec<Tile> = corner_tiles.iter().map(|c| c.1).collect();
            let points = self.points(surface, f00, &tiles, probe)?;
            for (((u, v), _), p) in corner_tiles.iter().zip(points) {
                evaluations += p.evaluations;
                let diff = (p.total - c0.total).norm() + p.sky_error + c0.sky_error;
                spread = spread.max(diff / s0_direct);
                probed.push(((*u, *v), p));
            }
            (spread, Some(c0))
        };
        // The coarse integral is the centre's skylight when it is tight enough.
        if skylight && probed.is_empty() && coarse.sky_error <= ray_tol * s0_direct {
            probed.push(((0.0, 0.0), coarse_centre));
        }
        let mut sky_fit_error = 0.0;
        // The sky over the field as an interpolant through Chebyshev-Lobatto rays (the probe's
        // reused), checked at rays it was not built from; `None` when it does not predict them
        // to the interpolant's budget and every field ray integrates its own skylight (below).
        // The lowest product-rule level of the field rays integrated so far at the rays' budget:
        // where the next ones start (`reflected_skylight`).
        let mut ray_level = None;
        let lobatto = if skylight && spread >= tol / 4.0 {
            // The coarse integral is the centre ray at this tolerance or tighter (its error is
            // within the rays' budget): its level hints the first rays, which are then integrated
            // as batches of level pairs where the surface's `pair_rule` admits that level. On
            // vegetation a level it does not admit hints nothing: the centre ray, in the sun's
            // plane there, can need three levels more than its neighbours, whose own ladders
            // would then start needlessly high (up to 2.1x the cost). As pairs, the first rays
            // cost less even so (docs/design/scene-quadrature.md).
            let coarse_hint = coarse.level.filter(|&l| {
                l <= pair_rule(surface).max_hint && coarse.sky_error <= ray_tol * s0_direct
            });
            let per_ray = Include {
                tol_abs: ray_tol * s0_direct,
                hint: coarse_hint,
                ..inc
            };
            let l = self.lobatto_sky(surface, f00, per_ray, &probed, fit_tol * s0_direct)?;
            evaluations += l.evaluations;
            ray_level = l.level;
            l.fit
        } else {
            None
        };
        let (mean, cov_g, surface_mean, field_change, sky_error, order) = if spread < tol / 4.0 {
            // One ray: the probe's centre is it, with every included term and its skylight at
            // half the rays' budget (at most 0.23 tol), tighter than the tol/4 a lone ray needs.
            let p = match c0 {
                Some(p) => p,
                None => {
                    let p = self.point(surface, f00, &centre, inc)?;
                    evaluations += p.evaluations;
                    p
                }
            };
            (p.total, Matrix3::zeros(), p.surface, spread, p.sky_error, 1)
        } else {
            // The skylight varies slowly over the field: once the polynomial through the last
            // order's rays predicts this order's rays to the interpolant's budget (their
            // quadrature errors allowed for), the polynomial through this order's rays replaces
            // the hemisphere integrals at every higher order, and its last prediction error is
            // reported.
            let per_ray = Include {
                tol_abs: ray_tol * s0_direct,
                ..inc
            };
            let mut fit_final = !skylight;
            let mut fit: Option<SkyFit> = None;
            // The sky's quadrature error at the fitted rays, carried by every field point.
            let mut fit_quadrature_error = 0.0;
            if let Some((f, interpolation_error)) = lobatto {
                sky_fit_error = interpolation_error / s0_direct;
                fit_quadrature_error = f.error;
                fit = Some(f);
                fit_final = true;
            }
            let mut previous: Option<(Vector3<f64>, f64)> = None;
            let mut last_change = f64::INFINITY;
            let orders = [2, 3, 4, 6, 8, 12];
            let mut k = 0;
            loop {
                let n = orders[k];
                let gl = gauss_legendre_table(n);
                let mut mean = Vector3::zeros();
                let mut second = Matrix3::zeros();
                let mut surf = Vector3::zeros();
                let mut sky_error = 0.0;
                let mut values = Vec::with_capacity(n * n);
                let mut worst_prediction = 0.0f64;
                let mut worst_sky_error = 0.0f64;
                let integrate_sky = skylight && !fit_final;
                let mut tiles = Vec::with_capacity(n * n);
                for (i, &(u, _)) in gl.iter().enumerate() {
                    for (j, &(v, _)) in gl.iter().enumerate() {
                        tiles.push(self.field.ray(u, v, (i, j))?);
                    }
                }
                let ray_inc = Include {
                    skylight: integrate_sky,
                    hint: ray_level,
                    ..per_ray
                };
                let points = self.points(surface, f00, &tiles, ray_inc)?;
                ray_level = points.iter().filter_map(|p| p.level).chain(ray_level).min();
                let nodes = gl.iter().flat_map(|&a| gl.iter().map(move |&b| (a, b)));
                for (((u, wu), (v, wv)), mut p) in nodes.zip(points) {
                    evaluations += p.evaluations;
                    if integrate_sky {
                        values.push(p.sky);
                        worst_sky_error = worst_sky_error.max(p.sky_error);
                        if let Some(f) = &fit {
                            let d = (f.at(u, v) - p.sky).norm() - p.sky_error - f.error;
                            worst_prediction = worst_prediction.max(d);
                        }
                    } else if let Some(f) = &fit {
                        let sky = f.at(u, v);
                        p.total += sky;
                        p.surface += sky;
                        p.sky_error = fit_quadrature_error;
                    }
                    let w = wu * wv / 4.0;
                    mean += p.total * w;
                    second += p.total * p.total.transpose() * w;
                    surf += p.surface * w;
                    sky_error += p.sky_error * w;
                }
                if skylight && !fit_final {
                    let predicted = fit.is_some() && worst_prediction < fit_tol * s0_direct;
                    if predicted {
                        fit_final = true;
                        sky_fit_error = worst_prediction.max(0.0) / s0_direct;
                        fit_quadrature_error = worst_sky_error;
                    }
                    let nodes: Vec<f64> = gl.iter().map(|p| p.0).collect();
                    fit = Some(SkyFit::tensor(
                        nodes.clone(),
                        nodes,
                        values,
                        worst_sky_error,
                    ));
                }
                let cov = second - mean * mean.transpose();
                let cov = 0.5 * (cov + cov.transpose());
                let scale = mean[0].abs().max(1e-300);
                let spread_now = cov.norm().max(0.0).sqrt();
                let change = previous.map_or(f64::INFINITY, |(pm, ps)| {
                    ((mean - pm).norm() / scale).max((spread_now - ps).abs() / scale)
                });
                // The larger of the last two changes, as in the hemisphere rule's ladder: across
                // a kink of the direct term over the field (the shadowing function's branches)
                // the orders converge algebraically, their errors change sign, and one change
                // alone fell short of the error by up to 3.8x
                // (`error_estimate_covers_the_truth_on_kinked_fields`).
                let error = change.max(last_change);
                if error < budget.field(sky_error / s0_direct + sky_fit_error)
                    || k + 1 == orders.len()
                {
                    break (mean, cov, surf, error, sky_error, n);
                }
                last_change = change;
                previous = Some((mean, spread_now));
                k += 1;
            }
        };
        let s0 = mean[0].abs().max(floor).max(1e-300);
        let geometry_report = TermReport {
            evaluated: order > 1,
            relative_size: if order > 1 {
                cov_g.norm().sqrt() / s0
            } else {
                spread
            },
            reason: if order > 1 {
                format!("{order}x{order} Gauss-Legendre rays over the field; the last two refinements changed the result by at most {field_change:.2e} of S0")
            } else {
                format!("corner probe: the field varies by {spread:.2e} of the direct term, below tol/4; one ray")
            },
        };
        let cov_v = match material.texture {
            Texture::None => Matrix3::zeros(),
            Texture::Cv(cv) => Matrix3::from_diagonal(&surface_mean.map(|x| (cv * x).powi(2))),
            // Texture is a property of the surface: scaled by the surface-leaving S0, so path
            // radiance (which grows with altitude) does not inflate it.
            Texture::Measured(c) => Matrix3::from_diagonal(
                &Vector3::new(c[0], c[1], c[2]).map(|x| (x * surface_mean[0]).powi(2)),
            ),
        };
        let texture_report = TermReport {
            evaluated: cov_v != Matrix3::zeros(),
            relative_size: cov_v.norm().sqrt() / s0,
            reason: match material.texture {
                Texture::None => "no texture given".into(),
                Texture::Cv(cv) => format!("coefficient of variation {cv}"),
                Texture::Measured(c) => format!("measured Stokes variation {c:?} of S0"),
            },
        };
        // A tabulated sky's interpolation error, measured before the field ([`table_floor`]);
        // a skipped skylight's whole size is in `skipped` below.
        let table_error = match (table_floor, skylight) {
            (Some(floor), true) => floor / s0,
            _ => 0.0,
        };
        // A skipped term's measured size is an error the answer carries.
        let skipped = if skylight {
            0.0
        } else {
            sky_bound * s0_direct / s0
        } + if path { 0.0 } else { path_rel * s0_direct / s0 };
        let error_estimate = sky_error / s0
            + skipped
            + table_error
            + sky_fit_error * (s0_direct / s0)
            + diffuse.albedo_error * white / s0
            + self.spectral_change
            + self.table_error
            + self.irradiance_error
            + field_change.min(1.0);
        Ok(MaterialResult {
            name: material.name.clone(),
            mean: Stokes(mean),
            cov: cov_g + cov_v,
            cov_geometry: cov_g,
            error_estimate,
            terms: Terms {
                direct: TermReport {
                    evaluated: true,
                    relative_size: d0.total[0] / s0,
                    reason: "analytic".into(),
                },
                skylight: skylight_report,
                path: path_report,
                geometry: geometry_report,
                texture: texture_report,
                field_order: order,
                spectral_nodes: self.nodes.len(),
            },
            evaluations: evaluations + self.evaluations,
            floor: None,
        })
    }
}

/// [`Prepared::table_floor`]'s measurement.
struct FloorProbe {
    /// The floor, radiance (the Stokes norm of the reflected skylight's change).
    floor: f64,
    /// The centre ray's `S0` it was measured at.
    s0: f64,
    evaluations: usize,
    /// The table's (zeniths, azimuths).
    grid: (usize, usize),
}

/// Evaluates every material of a scene at relative tolerance `tol` (of each material's mean
/// `S0`). Errors name the field.
pub fn evaluate(
    spec: &SceneSpec,
    materials: &[SceneMaterial],
    tol: f64,
) -> Result<Vec<MaterialResult>, ModelError> {
    Prepared::new(spec, tol)?.evaluate_all(materials)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fresnel::RefractiveIndex;
    use crate::skylight::sky_irradiance;

    fn spec(altitude_m: f64, off_nadir: f64, look: f64, fov: f64) -> SceneSpec {
        SceneSpec {
            sun_zenith_deg: 40.0,
            sun_azimuth_deg: 180.0,
            atmosphere: Atmosphere::default(),
            sky: SkyModel::SingleScattering,
            band: Band::flat(450.0, 650.0).unwrap(),
            pointing: Pointing {
                altitude_m,
                off_nadir_deg: off_nadir,
                look_azimuth_deg: look,
                fov_deg: (fov, fov),
            },
        }
    }

    fn glass(sigma: f64) -> SceneMaterial {
        SceneMaterial {
            name: "glass".into(),
            surface: Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), sigma, 0.1)
                .unwrap(),
            texture: Texture::Cv(0.05),
        }
    }

    /// E(0) = pi/2, E(1) = 1, E(1/2) = 1.3506438810476755 (A&S Table 17.1).
    #[test]
    fn elliptic_e_reference_values() {
        assert!((elliptic_e(0.0) - PI / 2.0).abs() < 1e-15);
        assert!((elliptic_e(1.0) - 1.0).abs() < 1e-15);
        assert!((elliptic_e(0.5) - 1.350_643_881_047_675_5).abs() < 1e-14);
    }

    /// The closed-form azimuthal HG integral equals adaptive quadrature (to 1e-10) across g and
    /// geometries including mu = mu0 with a strong forward peak.
    #[test]
    fn hg_azimuthal_matches_quadrature() {
        for g in [0.0, 0.3, 0.7, 0.95] {
            for (mu, mu0) in [(0.2f64, 0.8f64), (0.5, 0.5), (1.0, 0.3), (0.05, 0.9)] {
                let q = integrate(
                    |phi| {
                        let s = ((1.0 - mu * mu) * (1.0 - mu0 * mu0)).sqrt();
                        ClearSky::henyey_greenstein(g, mu * mu0 + s * phi.cos())
                    },
                    0.0,
                    2.0 * PI,
                    Tolerance::absolute(1e-12),
                );
                let c = hg_azimuthal(g, mu, mu0);
                assert!(
                    (c - q.value).abs() < 1e-10 * q.value.max(1.0),
                    "g={g} mu={mu} mu0={mu0}: {c} vs {}",
                    q.value
                );
            }
        }
    }

    /// The `mu` tables sized by the fourth-order law (`table_intervals_for`) meet tol/8 and
    /// interpolate the exact `A(mu)` and `B(mu)` within their reported error (relative to the
    /// table's peak) at 20 001 values of `mu`, including the last interval before the horizon,
    /// where `exp(-tau / mu)` bends fastest: at 1e-4 (one refinement from 256 intervals), 1e-6
    /// and 1e-8 (one each, where the 4x steps took one and two).
    /// The band tables' cubics are `lagrange4`'s polynomials: on a smooth table and on a
    /// rough one (every value independent), at every interval's ends and inside, they agree to
    /// rounding (1e-13 of the table's peak: a few ulps of the Taylor shift's terms).
    #[test]
    fn band_table_cubics_are_the_lagrange_interpolant() {
        for intervals in [3usize, 4, 7, 256] {
            let smooth: Vec<f64> = (0..=intervals)
                .map(|j| (1.0 + 3.0 * j as f64 / intervals as f64).ln())
                .collect();
            let rough: Vec<f64> = (0..=intervals)
                .map(|j| ((j * 7919) % 101) as f64 - 50.0)
                .collect();
            let tables = BandTables::new(&smooth, &rough);
            assert_eq!(tables.cubics.len(), intervals);
            for k in 0..=20 * intervals {
                let mu = k as f64 / (20 * intervals) as f64;
                let (a, b) = tables.at(mu);
                let (ra, rb) = lagrange4_pair(&smooth, &rough, mu);
                assert!(
                    (a - ra).abs() <= 1e-13 * 4f64.ln(),
                    "{intervals} {mu}: {a} {ra}"
                );
                assert!((b - rb).abs() <= 1e-13 * 50.0, "{intervals} {mu}: {b} {rb}");
            }
        }
        // Fewer than 4 values: no cubic, and zero radiance rather than a panic.
        let short = BandTables::new(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]);
        assert_eq!(short.at(0.5), (0.0, 0.0));
    }

    #[test]
    fn sized_mu_tables_meet_their_error() {
        let scene =
            crate::scene_file::Scene::from_toml_str(include_str!("../../../examples/rooftop.toml"))
                .unwrap();
        for tol in [1e-4, 1e-6, 1e-8] {
            let p = Prepared::new(&scene.spec, tol).unwrap();
            assert!(
                p.table_error() <= tol / 8.0,
                "tol {tol}: {:e}",
                p.table_error()
            );
            let mu0_slant = slant_mu0(p.sun.z);
            for (k, n) in p.nodes.iter().enumerate() {
                let tau = n.rayleigh + n.aerosol;
                let exact = |mu: f64| {
                    let path = downward_path(tau, mu0_slant, mu) / (4.0 * PI * tau);
                    (
                        n.rayleigh * path,
                        scene.spec.atmosphere.aerosol_ssa * n.aerosol * path,
                    )
                };
                for (table, pick) in [(&p.table_a[k], 0), (&p.table_b[k], 1)] {
                    let peak = table.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    let mut worst = 0.0f64;
                    for j in 0..=20_000 {
                        let mu = j as f64 / 20_000.0;
                        let (a, b) = exact(mu);
                        let want = if pick == 0 { a } else { b };
                        worst = worst.max((lagrange4(table, mu) - want).abs() / peak);
                    }
                    assert!(
                        worst <= p.table_error(),
                        "tol {tol}, node {k}, table {pick}: {worst:e} > {:e} ({} intervals)",
                        p.table_error(),
                        table.len() - 1
                    );
                }
            }
        }
    }

    /// The sky irradiance by Simpson's rule on the `mu` tables' points is within the error it
    /// claims of the integral of the same integrand to 1e-14 of the zenith radiance, wherever
    /// it is admitted, and every node's irradiance in a scene within tol/64 of its zenith
    /// radiance (the target of the adaptive rule it replaced), for suns from the zenith to the
    /// horizon, aerosol asymmetry -0.9 to 0.99 (0.99 is the sharpest forward peak the
    /// atmosphere admits) and tolerances 1e-2 to 1e-8. The rule must serve most nodes, or it
    /// saves nothing.
    #[test]
    fn sky_irradiance_on_the_tables_meets_its_error() {
        let base =
            crate::scene_file::Scene::from_toml_str(include_str!("../../../examples/rooftop.toml"))
                .unwrap()
                .spec;
        let rayleigh = RayleighSky {
            optical_depth: 0.0,
            depolarization: AIR_DEPOLARIZATION,
        };
        let (mut on_table, mut nodes) = (0, 0);
        for zenith in [0.0, 5.0, 30.0, 60.0, 85.0, 90.0] {
            for g in [-0.9, 0.0, 0.7, 0.95, 0.99] {
                for tol in [1e-2, 1e-4, 1e-6, 1e-8] {
                    let mut s = with_sun(base.clone(), zenith);
                    s.atmosphere.aerosol_g = g;
                    let p = Prepared::new(&s, tol).unwrap();
                    let phase = AzimuthalPhase::new(&rayleigh, g, p.sun.z);
                    let intervals = p.table_a[0].len() - 1;
                    let phases = phase.on_grid(intervals);
                    let mu0_slant = slant_mu0(p.sun.z);
                    let ssa = s.atmosphere.aerosol_ssa;
                    for (k, n) in p.nodes.iter().enumerate() {
                        let tau = n.rayleigh + n.aerosol;
                        let integrand = |mu: f64| {
                            let path = downward_path(tau, mu0_slant, mu) / (4.0 * PI * tau);
                            let (fa, fb) = (n.rayleigh * path, ssa * n.aerosol * path);
                            let hg = if fb == 0.0 { 0.0 } else { phase.hg(mu) };
                            mu * (phase.rayleigh(mu) * fa + hg * fb)
                        };
                        let scale = p.table_a[k][intervals]
                            .max(p.table_b[k][intervals])
                            .max(1e-300);
                        // The reference: graded towards the HG peak twice as finely as the
                        // scene's adaptive rule is.
                        let breaks = phase.breaks(2.0);
                        let (mut exact, mut exact_error) = (0.0, 0.0);
                        for ab in breaks.windows(2) {
                            let e = integrate(
                                integrand,
                                ab[0],
                                ab[1],
                                Tolerance::absolute(1e-14 * scale / breaks.len() as f64),
                            );
                            assert!(e.converged, "zenith {zenith}, g {g}");
                            exact += e.value;
                            exact_error += e.error;
                        }
                        let case = format!("zenith {zenith}, g {g}, tol {tol}, node {k}");
                        let off = (n.e_sky - exact).abs();
                        assert!(
                            off <= tol / 64.0 * scale + exact_error,
                            "{case}: {off:e} > {:e}",
                            tol / 64.0 * scale
                        );
                        let (e, error) =
                            irradiance_on_table(&phases, &p.table_a[k], &p.table_b[k]).unwrap();
                        nodes += 1;
                        if phase.resolves(intervals) {
                            let off = (e - exact).abs();
                            assert!(
                                off <= error + exact_error,
                                "{case}: rule {off:e} > {error:e}"
                            );
                            on_table += usize::from(error <= tol / 64.0 * scale);
                        }
                    }
                }
            }
        }
        assert!(
            2 * on_table > nodes,
            "{on_table} of {nodes} nodes on the tables"
        );
        eprintln!("{on_table} of {nodes} nodes on the tables");
    }

    /// The tabulated band sky equals the spectral sum of the exact single-scattering skies, and
    /// its sky irradiance equals brute-force hemisphere quadrature, to 1e-6 relative.
    #[test]
    fn band_sky_equals_sum_of_exact_skies() {
        let s = spec(2.0, 0.0, 0.0, 1.0);
        let p = Prepared::new(&s, 1e-6).unwrap();
        let weights: Vec<f64> = p.nodes.iter().map(|n| n.weight).collect();
        let band = p.band_sky(&weights, false);
        for (z, az) in [
            (0.0, 0.0),
            (30.0, 90.0),
            (60.0, 200.0),
            (85.0, 10.0),
            (89.5, 180.0),
        ] {
            let d = crate::angles::direction_from_deg(z, az);
            let mut exact = Vector3::zeros();
            for n in &p.nodes {
                let sky = s.atmosphere.sky(n.nm, p.sun).unwrap();
                exact += sky.stokes_from(&d).0 * n.weight;
            }
            let got = band.stokes_from(&d).0;
            // Within the table's reported error (relative to the sky's peak, a few times the
            // zenith radiance), and that error is small.
            let peak = 10.0 * exact[0].max(band.stokes_from(&Vector3::z()).0[0]);
            assert!(
                (got - exact).norm() <= p.table_error() * peak,
                "z={z}: {got:?} vs {exact:?}"
            );
        }
        let e_exact = sky_irradiance(&band, Tolerance::absolute(1e-9)).stokes.0[0];
        let e: f64 = p.nodes.iter().map(|n| n.weight * n.e_sky).sum();
        assert!((e - e_exact).abs() < 1e-6 * e_exact, "{e} vs {e_exact}");
    }

    /// The band sky's E-vector taken in any transverse frame (`stokes_in_frame`, what the
    /// facet-slope integrand asks for) equals its surface-frame Stokes vector rotated into that
    /// frame (the trait's default), to rounding (1e-14 of S0), for the sun at 40 deg and rays
    /// from the zenith, the horizon, towards and away from the sun's azimuth, in frames at any
    /// angle; a sign slip would show as an O(1) error in S1 or S2.
    #[test]
    fn band_sky_in_a_facet_frame_equals_the_rotated_surface_frame() {
        let s = spec(30.0, 0.0, 0.0, 1.0);
        let p = Prepared::new(&s, 1e-4).unwrap();
        let weights: Vec<f64> = p.nodes.iter().map(|n| n.weight).collect();
        let band = p.band_sky(&weights, false);
        let mut checked = 0;
        for (z, az) in [
            (0.0, 0.0),
            (10.0, 180.0),
            (40.0, 0.0),
            (60.0, 250.0),
            (89.9, 75.0),
        ] {
            let d = crate::angles::direction_from_deg(z, az);
            let k = -d;
            // A transverse basis of the ray, then frames at 36 angles (and two lengths).
            let u = k.cross(&Vector3::new(0.3, -0.2, 0.9)).normalize();
            let v = k.cross(&u);
            for i in 0..36 {
                let a = i as f64 * 10f64.to_radians() + 0.01;
                let x = (u * a.cos() + v * a.sin()) * (1.0 + i as f64);
                let fast = band.stokes_in_frame(&d, &x).0;
                let surface = band.stokes_from(&d);
                let slow = surface_to_frame(surface, &d, &x).0;
                assert!(
                    (fast - slow).amax() <= 1e-14 * surface.0[0],
                    "z={z} az={az} frame {i}: {fast:?} vs {slow:?}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 180);
    }

    /// The band sky's batch (`stokes_in_frame_batch`, vector loops with selects) is its
    /// one-ray `stokes_in_frame` to the bit: the same operations in the same order. Rays over
    /// the hemisphere and at and below the horizon (the integrand's off-support points, whose
    /// weight is 0 but whose values must stay finite), frames of several lengths, a ray
    /// towards the sun (no scattering plane), a zero frame, and more rays than one chunk.
    #[test]
    fn band_sky_batch_equals_one_ray_at_a_time() {
        let s = spec(30.0, 0.0, 0.0, 1.0);
        let p = Prepared::new(&s, 1e-4).unwrap();
        let weights: Vec<f64> = p.nodes.iter().map(|n| n.weight).collect();
        let band = p.band_sky(&weights, false);
        let (mut towards, mut frame) = (Vec::new(), Vec::new());
        for i in 0..61 {
            let z = -5.0 + i as f64 * 1.6;
            let d = crate::angles::direction_from_deg(z, i as f64 * 37.0);
            let u = d.cross(&Vector3::new(0.3, -0.2, 0.9)) * (0.5 + i as f64);
            towards.push(d);
            frame.push(u);
        }
        towards.push(p.sun);
        frame.push(p.sun.cross(&Vector3::x()));
        towards.push(Vector3::z());
        frame.push(Vector3::zeros());
        let n = towards.len();
        let col = |v: &[Vector3<f64>], k: usize| v.iter().map(|x| x[k]).collect::<Vec<_>>();
        let (t, f) = (
            [col(&towards, 0), col(&towards, 1), col(&towards, 2)],
            [col(&frame, 0), col(&frame, 1), col(&frame, 2)],
        );
        let mut out = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
        let [o0, o1, o2] = &mut out;
        band.stokes_in_frame_batch([&t[0], &t[1], &t[2]], [&f[0], &f[1], &f[2]], [o0, o1, o2]);
        for i in 0..n {
            let one = band.stokes_in_frame(&towards[i], &frame[i]).0;
            let batch = [out[0][i], out[1][i], out[2][i]];
            assert_eq!(batch, [one[0], one[1], one[2]], "ray {i}: {:?}", towards[i]);
            assert!(batch.iter().all(|x| x.is_finite()), "ray {i}: {batch:?}");
        }
    }

    /// At 2 m, path radiance is negligible and a 1-degree field has no geometry variation.
    #[test]
    fn bench_skips_path_and_geometry() {
        let r = evaluate(&spec(2.0, 30.0, 0.0, 1.0), &[glass(0.2)], 1e-2).unwrap();
        let t = &r[0].terms;
        assert!(!t.path.evaluated, "{:?}", t.path);
        assert!(t.path.relative_size < 1e-3, "{:?}", t.path);
        assert!(!t.geometry.evaluated, "{:?}", t.geometry);
        assert!(t.skylight.evaluated);
        assert_eq!(t.field_order, 1);
    }

    /// The parallel evaluation is deterministic: on one thread and on four, the results of a
    /// scene whose field is sampled (8 deg at 60 deg off nadir, so the skylight's field
    /// interpolant and the field rays run in parallel) are equal to the bit, because every
    /// sum runs in a fixed order whatever thread computed its terms.
    #[test]
    fn parallel_evaluation_equals_one_thread() {
        let s = spec(30.0, 60.0, 300.0, 8.0);
        let materials = [glass(0.1), asphalt(), glass(0.4)];
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| evaluate(&s, &materials, 1e-4).unwrap())
        };
        let one = run(1);
        assert!(one.iter().all(|r| r.terms.field_order > 1), "{one:?}");
        assert_eq!(one, run(4));
    }

    /// Materials evaluated together share each field ray's atmosphere terms and band-sky tables
    /// (`Prepared::ray_terms`); each one's result is equal to the bit to its result alone.
    #[test]
    fn shared_ray_terms_change_nothing() {
        let s = spec(30.0, 60.0, 300.0, 8.0);
        let materials = [glass(0.1), asphalt(), glass(0.4)];
        let together = evaluate(&s, &materials, 1e-4).unwrap();
        for (m, t) in materials.iter().zip(&together) {
            let alone = evaluate(&s, std::slice::from_ref(m), 1e-4).unwrap();
            assert_eq!(&alone[0], t);
        }
    }

    /// From 10 km, path radiance is a large part of the signal.
    #[test]
    fn airborne_path_radiance_matters() {
        let r = evaluate(&spec(10_000.0, 20.0, 0.0, 5.0), &[glass(0.2)], 1e-3).unwrap();
        let t = &r[0].terms;
        assert!(t.path.evaluated);
        assert!(t.path.relative_size > 0.05, "{:?}", t.path);
    }

    /// A measured texture scales with the surface-leaving S0, not with the total: from 10 km,
    /// where path radiance is over 5 % of the signal, the texture variance of S0 is
    /// `(c0 (S0 - S0_path))^2` to 2 % (the field's spread of the path term over a 1-degree field
    /// is far smaller), and clearly below `(c0 S0)^2`.
    #[test]
    fn measured_texture_ignores_path_radiance() {
        let sp = spec(10_000.0, 20.0, 0.0, 1.0);
        let mut textured = glass(0.2);
        textured.texture = Texture::Measured([0.1, 0.01, 0.01]);
        let mut plain = glass(0.2);
        plain.texture = Texture::None;
        let r = evaluate(&sp, &[textured.clone(), plain], 1e-4).unwrap();
        let var_v = r[0].cov[(0, 0)] - r[1].cov[(0, 0)];
        let path = Prepared::new(&sp, 1e-4)
            .unwrap()
            .boresight_terms(&textured)
            .unwrap()[2];
        let s0 = r[0].mean.0[0];
        assert!(path.0[0] > 0.05 * s0, "path {} of S0 {s0}", path.0[0]);
        let want = (0.1 * (s0 - path.0[0])).powi(2);
        assert!((var_v / want - 1.0).abs() < 0.02, "{var_v} vs {want}");
        assert!(var_v < 0.95 * (0.1 * s0).powi(2));
    }

    /// Looking into a smooth metal's glint, the skylight is orders of magnitude below the
    /// direct term and skipped at a loose tolerance, but included at a tight one.
    #[test]
    fn glint_skips_skylight_at_loose_tolerance() {
        let aluminium = SceneMaterial {
            name: "al".into(),
            surface: Surface::microfacet(RefractiveIndex::new(0.96, 6.69).unwrap(), 0.02, 0.9)
                .unwrap(),
            texture: Texture::None,
        };
        // Sun at zenith 40 in the south; the sensor looks south, 40 deg off nadir: the glint.
        let s = spec(2.0, 40.0, 180.0, 1.0);
        let loose = evaluate(&s, std::slice::from_ref(&aluminium), 1e-2).unwrap();
        assert!(
            !loose[0].terms.skylight.evaluated,
            "{:?}",
            loose[0].terms.skylight
        );
        let tight = evaluate(&s, &[aluminium], 1e-6).unwrap();
        assert!(tight[0].terms.skylight.evaluated);
        let diff = (tight[0].mean.0 - loose[0].mean.0).norm() / tight[0].mean.0[0];
        assert!(diff < 1e-2, "skipping changed the answer by {diff:e}");
    }

    /// The error estimate at each tolerance covers the difference from a tight reference.
    #[test]
    fn error_estimate_covers_the_truth() {
        let s = spec(30.0, 45.0, 0.0, 10.0);
        let m = glass(0.15);
        let reference = evaluate(&s, std::slice::from_ref(&m), 1e-8).unwrap()[0].clone();
        for tol in [1e-2, 1e-3, 1e-4, 1e-5] {
            let r = evaluate(&s, std::slice::from_ref(&m), tol).unwrap()[0].clone();
            let actual = (r.mean.0 - reference.mean.0).norm() / reference.mean.0[0];
            assert!(
                actual <= r.error_estimate.max(1e-12),
                "tol {tol}: actual {actual:e} > estimate {:e}\n{r:#?}\n{reference:#?}",
                r.error_estimate
            );
            assert!(actual <= tol, "tol {tol}: actual {actual:e}");
        }
    }

    /// The budget's parts add up to at most the tolerance whatever the rays and the
    /// interpolant measure within their shares (the known errors are at most 5/8 of it: three
    /// within tol/8 and a skipped path within tol/4), and the field's orders keep at least a
    /// tenth of what is left.
    #[test]
    fn sky_budget_adds_up_to_the_tolerance() {
        for tol in [1e-2, 1e-4, 1e-8] {
            for tabulated in [false, true] {
                for known in [0.0, 0.1, 0.3, 0.625].map(|k| k * tol) {
                    let b = SkyBudget::new(tol, known, tabulated);
                    let reserve = if tabulated { tol / 4.0 } else { 0.0 };
                    for (ray, fit) in [(0.0, 0.0), (1.0, 0.0), (0.5, 1.0), (1.0, 1.0)] {
                        let spent = ray * b.rays() + fit * b.fit();
                        let total = known + reserve + spent + b.field(spent);
                        assert!(
                            total <= tol * (1.0 + 1e-12),
                            "tol {tol} known {known:e} tabulated {tabulated}: {total:e}"
                        );
                        assert!(b.field(spent) >= 0.1 * b.free * (1.0 - 1e-12));
                    }
                    assert!(b.rays() >= tol / 32.0, "rays {:e} at tol {tol}", b.rays());
                }
            }
        }
    }

    /// The example scenes' error estimates (the tabulated sky's included) are within their
    /// tolerances at 1e-2, 1e-4 and 1e-6: the budget (`SkyBudget`) shares out the tolerance,
    /// not more.
    #[test]
    fn example_scenes_are_within_their_tolerance() {
        for text in [
            include_str!("../../../examples/bench.toml"),
            include_str!("../../../examples/rooftop.toml"),
            include_str!("../../../examples/airborne.toml"),
            include_str!("../../../examples/rooftop_panels.toml"),
        ] {
            let scene = crate::scene_file::Scene::from_toml_str(text).unwrap();
            for tol in [1e-2, 1e-4, 1e-6] {
                for r in evaluate(&scene.spec, &scene.materials, tol).unwrap() {
                    assert!(
                        r.error_estimate <= tol,
                        "{} at {tol}: estimate {:e}",
                        r.name,
                        r.error_estimate
                    );
                }
            }
        }
    }

    /// The error estimate covers the difference from a reference at 1e-8 where the direct
    /// term has a kink over the field (the shadowing function's branch switch: the field's
    /// Gauss-Legendre means then converge algebraically, and one change between orders can be
    /// small by a coincidence of two orders' errors). Three fields found by a sweep of 40
    /// random scenes and five materials, where an estimate from one change between orders
    /// falls short by up to 1.5x; the field's orders are accepted on the larger of the last
    /// two changes, as the hemisphere rule's levels are.
    #[test]
    fn error_estimate_covers_the_truth_on_kinked_fields() {
        let cases = [
            // (altitude, off nadir, look, fov, sun zenith, sun azimuth, tolerance)
            (30.0, 57.1, 68.0, (19.8, 19.7), 21.3, 297.0, 1e-3),
            (2.0, 42.8, 342.0, (14.1, 4.8), 59.1, 73.0, 1e-4),
            (2.0, 59.6, 180.0, (2.1, 13.6), 57.0, 347.0, 1e-4),
        ];
        for (altitude, off, look, fov, sun_zenith, sun_azimuth, tol) in cases {
            let mut s = spec(altitude, off, look, 1.0);
            s.pointing.fov_deg = fov;
            s.sun_zenith_deg = sun_zenith;
            s.sun_azimuth_deg = sun_azimuth;
            let m = [asphalt()];
            let reference = evaluate(&s, &m, 1e-8).unwrap();
            let r = evaluate(&s, &m, tol).unwrap();
            let actual = (r[0].mean.0 - reference[0].mean.0).norm() / reference[0].mean.0[0];
            assert!(
                actual <= r[0].error_estimate,
                "{s:?} at {tol}: actual {actual:e} > estimate {:e}",
                r[0].error_estimate
            );
        }
    }

    fn with_sun(mut s: SceneSpec, zenith_deg: f64) -> SceneSpec {
        s.sun_zenith_deg = zenith_deg;
        s
    }

    fn asphalt() -> SceneMaterial {
        SceneMaterial {
            name: "asphalt".into(),
            surface: Surface::microfacet(RefractiveIndex::new(1.6, 0.0).unwrap(), 0.5, 0.08)
                .unwrap(),
            texture: Texture::None,
        }
    }

    /// `s` lit by its own band sky exported as a table on a 10-degree grid (zenith 0..90,
    /// azimuth 0..350), read back as a tabulated sky.
    fn lit_by_own_sky_table(s: &SceneSpec) -> SceneSpec {
        let p = Prepared::new(s, 1e-6).unwrap();
        let sky = p.ground_sky();
        let mut csv = String::from("zenith_deg,azimuth_deg,S0,S1,S2\n");
        for i in 0..=9 {
            for j in 0..36 {
                let (z, a) = (i as f64 * 10.0, j as f64 * 10.0);
                let v = sky
                    .stokes_from(&crate::angles::direction_from_deg(z.max(1e-7), a))
                    .0;
                csv += &format!("{z},{a},{:e},{:e},{:e}\n", v[0], v[1], v[2]);
            }
        }
        let table =
            SkyTable::from_csv_str(&csv, crate::sky_table::StokesReference::Horizontal).unwrap();
        SceneSpec {
            sky: SkyModel::Table(Arc::new(table)),
            ..s.clone()
        }
    }

    /// A scene lit by its own band sky exported as a 10-degree table (Meng (2012)'s MODTRAN-P
    /// grid) agrees with the analytic scene within the table's reported interpolation error,
    /// and that error is reported (below 2 %: the grid is coarse, not wrong).
    #[test]
    fn own_sky_as_a_table_reproduces_the_scene() {
        let s = spec(30.0, 50.0, 300.0, 4.0);
        let tabled = lit_by_own_sky_table(&s);
        let materials = [glass(0.1), asphalt()];
        let analytic = evaluate(&s, &materials, 1e-4).unwrap();
        let from_table = evaluate(&tabled, &materials, 1e-3).unwrap();
        for (a, t) in analytic.iter().zip(&from_table) {
            let diff = (a.mean.0 - t.mean.0).norm() / a.mean.0[0];
            assert!(
                diff <= t.error_estimate,
                "{}: {diff:e} > {:e}",
                a.name,
                t.error_estimate
            );
            assert!(
                t.error_estimate < 2e-2,
                "{}: {:e}",
                a.name,
                t.error_estimate
            );
        }
    }

    /// A tabulated sky's interpolation error bounds the answer at any tolerance: asked for
    /// 1e-9, each material is integrated to a quarter of its measured floor instead, its
    /// error estimate includes the floor and still covers the difference from the analytic
    /// sky the table was written from (integrated to 1e-7), and it costs at most 4x the
    /// evaluations of a 1e-3 run (at 1e-9 proper, the hemisphere integrals alone would cost
    /// orders of magnitude more). A sky from a model has no floor.
    #[test]
    fn tabulated_sky_floor_bounds_the_effort() {
        let s = spec(30.0, 50.0, 300.0, 4.0);
        let tabled = lit_by_own_sky_table(&s);
        let materials = [glass(0.1), asphalt()];
        let analytic = evaluate(&s, &materials, 1e-7).unwrap();
        assert!(analytic.iter().all(|r| r.floor.is_none()));
        let loose = evaluate(&tabled, &materials, 1e-3).unwrap();
        let tight = evaluate(&tabled, &materials, 1e-9).unwrap();
        for ((a, l), t) in analytic.iter().zip(&loose).zip(&tight) {
            let floor = t.floor.as_ref().expect("a tabulated sky has a floor");
            let diff = (a.mean.0 - t.mean.0).norm() / a.mean.0[0];
            eprintln!(
                "{}: floor {:.2e}, integrated to {:.2e}, error {:.2e}, diff {diff:.2e}, evaluations {} (1e-3: {})",
                a.name, floor.relative, floor.tolerance, t.error_estimate, t.evaluations, l.evaluations
            );
            assert!(floor.below_floor, "{}: {floor:?}", a.name);
            assert!(floor.relative > 1e-5, "{}: {floor:?}", a.name);
            // Integrated to a quarter of the floor measured at the centre's S0 (within 10 %
            // of the field mean's).
            assert!(
                floor.tolerance >= 0.9 * FLOOR_FRACTION * floor.relative
                    && floor.tolerance <= 1.1 * FLOOR_FRACTION * floor.relative,
                "{}: {floor:?}",
                a.name
            );
            assert!(t.error_estimate >= floor.relative, "{}", a.name);
            assert!(
                diff <= t.error_estimate,
                "{}: {diff:e} > {:e}",
                a.name,
                t.error_estimate
            );
            assert!(
                t.evaluations <= 4 * l.evaluations,
                "{}: {} evaluations at 1e-9, {} at 1e-3",
                a.name,
                t.evaluations,
                l.evaluations
            );
        }
    }

    /// Straight down (Figs. 4.1-4.2's geometry: 1 km, sun at 46 deg zenith in the south, the
    /// library's glass), the boresight's Stokes vector is the limit of its neighbours: within
    /// 1e-3 of S0 of the mean of the rays 0.5 deg either side in the sun's plane (the terms
    /// vary by 4e-5 of S0 per degree squared there, and are integrated to 1e-5 of it), and
    /// the field mean over a 1-degree field at nadir agrees with the boresight's terms summed
    /// within 1e-3 of S0 (the field's curvature over +-0.5 deg and the tolerance). With the
    /// path radiance in another frame than the surface terms at exact nadir, both missed by
    /// 5 % of S0 (polarised radiance 0.060 against 0.137).
    #[test]
    fn nadir_is_the_limit_of_its_neighbours() {
        let glass = crate::material::MaterialLibrary::builtin()
            .get("glass")
            .unwrap()
            .surface()
            .unwrap();
        let material = SceneMaterial {
            name: "glass".into(),
            surface: glass,
            texture: Texture::None,
        };
        let at = |view_deg: f64| {
            let spec = SceneSpec {
                sun_zenith_deg: 46.0,
                sun_azimuth_deg: 180.0,
                atmosphere: Atmosphere::default(),
                sky: SkyModel::SingleScattering,
                band: Band::flat(450.0, 650.0).unwrap(),
                pointing: Pointing {
                    altitude_m: 1000.0,
                    off_nadir_deg: view_deg.abs(),
                    look_azimuth_deg: if view_deg >= 0.0 { 180.0 } else { 0.0 },
                    fov_deg: (1.0, 1.0),
                },
            };
            let p = Prepared::new(&spec, 1e-5).unwrap();
            let t = p.boresight_terms(&material).unwrap();
            let total = t[0].0 + t[1].0 + t[2].0;
            (total, p.evaluate(&material).unwrap().mean.0)
        };
        let (nadir, field) = at(0.0);
        let (plus, _) = at(0.5);
        let (minus, _) = at(-0.5);
        let s0 = nadir[0];
        let limit = (plus + minus) / 2.0;
        assert!(
            (nadir - limit).norm() <= 1e-3 * s0,
            "nadir {nadir:?}, neighbours' mean {limit:?}"
        );
        assert!(
            (field - nadir).norm() <= 1e-3 * s0,
            "field mean {field:?}, boresight {nadir:?}"
        );
    }

    /// Zero aerosol: the band sky's DoLP is the Rayleigh phase matrix's `-P12 / P11` at every
    /// scattering angle (1e-9), and the scene evaluates.
    #[test]
    fn zero_aerosol_sky_is_rayleigh() {
        let mut s = spec(30.0, 45.0, 0.0, 4.0);
        s.atmosphere.aerosol_optical_depth_550 = 0.0;
        let p = Prepared::new(&s, 1e-5).unwrap();
        let sky = p.ground_sky();
        for (z, az) in [(10.0, 0.0), (50.0, 90.0), (80.0, 270.0), (40.0, 180.0)] {
            let d = crate::angles::direction_from_deg(z, az);
            let air = RayleighSky {
                optical_depth: 0.0,
                depolarization: AIR_DEPOLARIZATION,
            };
            let want = air.dolp(p.sun.dot(&d));
            let got = sky.stokes_from(&d).dolp().unwrap_or(0.0);
            assert!((got - want).abs() < 1e-9, "{z},{az}: {got} vs {want}");
        }
        let r = evaluate(&s, &[glass(0.2)], 1e-3).unwrap();
        assert!(r[0].mean.0.iter().all(|v| v.is_finite()) && r[0].mean.0[0] > 0.0);
    }

    /// The Berry sky in a scene: its radiance is the single-scattering sky's, with zero
    /// separation its E-vector is the Rayleigh one (1e-9), and with a 30-degree separation the
    /// Babinet and Brewster points, 15 degrees above and below the sun, are unpolarised.
    #[test]
    fn berry_sky_in_a_scene() {
        let s = spec(30.0, 45.0, 0.0, 4.0);
        let berry = |sep: f64| SceneSpec {
            sky: SkyModel::Berry {
                separation_deg: sep,
                max_dolp: 0.7,
            },
            ..s.clone()
        };
        let ss = Prepared::new(&s, 1e-5).unwrap();
        let b0 = Prepared::new(&berry(0.0), 1e-5).unwrap();
        let b30 = Prepared::new(&berry(30.0), 1e-5).unwrap();
        let (sky_ss, sky_b0, sky_b30) = (ss.ground_sky(), b0.ground_sky(), b30.ground_sky());
        for (z, az) in [(10.0, 0.0), (50.0, 90.0), (80.0, 270.0), (60.0, 10.0)] {
            let d = crate::angles::direction_from_deg(z, az);
            let (a, b) = (sky_ss.stokes_from(&d).0, sky_b0.stokes_from(&d).0);
            assert!((a[0] - b[0]).abs() < 1e-12 * a[0], "{z},{az}");
            let (pa, pb) = (a[1].hypot(a[2]), b[1].hypot(b[2]));
            let cross = (a[1] * b[2] - a[2] * b[1]) / (pa * pb);
            assert!(
                cross.abs() < 1e-9 && a[1] * b[1] + a[2] * b[2] > 0.0,
                "{z},{az}"
            );
        }
        // Sun at zenith 40, azimuth 180: the neutral points are at zenith 25 and 55.
        for z in [25.0, 55.0] {
            let d = crate::angles::direction_from_deg(z, 180.0);
            let dolp = sky_b30.stokes_from(&d).dolp().unwrap_or(0.0);
            assert!(dolp < 1e-6, "zenith {z}: {dolp}");
        }
        let r = evaluate(&berry(30.0), &[glass(0.2)], 1e-3).unwrap();
        assert!(r[0].terms.skylight.evaluated);
    }

    /// Sun at the horizon: no direct light (its reported size is below 1e-6 of S0), the
    /// skylight carries the signal, and the answer is finite with DoLP in [0, 1].
    #[test]
    fn sun_at_the_horizon() {
        let s = with_sun(spec(30.0, 45.0, 0.0, 4.0), 90.0);
        let r = evaluate(&s, &[glass(0.2), asphalt()], 1e-3).unwrap();
        for m in &r {
            assert!(
                m.terms.direct.relative_size.abs() < 1e-6,
                "{:?}",
                m.terms.direct
            );
            assert!(m.terms.skylight.evaluated);
            assert!(m.mean.0[0] > 0.0 && m.mean.0.iter().all(|v| v.is_finite()));
            let d = m.mean.dolp().unwrap_or(0.0);
            assert!((0.0..=1.0).contains(&d), "{d}");
        }
    }

    /// Sun at the zenith, view at nadir: sky, surface and path are all symmetric about the
    /// vertical, so the light is unpolarised (DoLP below the tolerance).
    #[test]
    fn sun_at_zenith_seen_at_nadir_is_unpolarised() {
        let s = with_sun(spec(30.0, 0.0, 0.0, 1.0), 0.0);
        let r = evaluate(&s, &[glass(0.2), asphalt()], 1e-4).unwrap();
        for m in &r {
            let d = m.mean.dolp().unwrap_or(0.0);
            assert!(d < 1e-4, "{}: DoLP {d:e}", m.name);
        }
    }

    /// A near-grazing view (85 deg off nadir): the error estimate still covers the difference
    /// from a tight reference.
    #[test]
    fn grazing_view_error_is_covered() {
        let s = spec(30.0, 85.0, 90.0, 2.0);
        let m = [glass(0.1)];
        let reference = evaluate(&s, &m, 1e-6).unwrap();
        let r = evaluate(&s, &m, 1e-3).unwrap();
        let actual = (r[0].mean.0 - reference[0].mean.0).norm() / reference[0].mean.0[0];
        assert!(
            actual <= r[0].error_estimate,
            "{actual:e} vs {:e}",
            r[0].error_estimate
        );
    }

    /// sigma -> small: a near-mirror (0.02) costs no more than three times a rough glass (0.2)
    /// in the same scene, at the same tolerance (slope-space quadrature, not brute force).
    #[test]
    fn smooth_surface_costs_what_a_rough_one_does() {
        let s = spec(30.0, 50.0, 0.0, 4.0);
        let smooth = evaluate(&s, &[glass(0.02)], 1e-4).unwrap();
        let rough = evaluate(&s, &[glass(0.2)], 1e-4).unwrap();
        assert!(
            smooth[0].evaluations <= 3 * rough[0].evaluations,
            "{} vs {}",
            smooth[0].evaluations,
            rough[0].evaluations
        );
    }

    /// The sky's field interpolant through Chebyshev-Lobatto rays, for every material of the
    /// rooftop example (60 deg off nadir, an 8 x 6 deg field; the microfacets' rays integrated
    /// as batches of level pairs, hinted by the centre; the panel's is accepted at 5 x 3
    /// on its moments while its pointwise miss is twice `target`), gives the field's mean
    /// within its reported error, and its spread `sqrt(|Cov|_F)` within `target` (tol/8 of
    /// S0), against 8 x 8 Gauss-Legendre rays each integrated to 1e-9 of S0 (exact for the
    /// interpolant, and far past the 5-point interpolant's error for the sky); each plus the
    /// quadrature errors involved. Pointwise, it predicts every one of those rays within
    /// tol/2 of S0, its check's bound. (Measured: the panel's spread is off by 1.6e-6 against
    /// a target of 8.9e-6; its 3 x 3 interpolant's estimated spread error is 1.7e-4, and
    /// accepting that interpolant fails this test.)
    #[test]
    fn lobatto_sky_moments_are_within_their_error() {
        let tol = 1e-4;
        let scene =
            crate::scene_file::Scene::from_toml_str(include_str!("../../../examples/rooftop.toml"))
                .unwrap();
        let p = Prepared::new(&scene.spec, tol).unwrap();
        let gl = gauss_legendre_table(8);
        for m in &scene.materials {
            let f00 = m
                .surface
                .diffuse(
                    scene.spec.sun_zenith_deg.to_radians(),
                    Tolerance::absolute(1e-10),
                )
                .unwrap()
                .f00;
            let centre = p.field.ray(0.0, 0.0, (0, 0)).unwrap();
            let inc = Include {
                skylight: true,
                path: true,
                tol_abs: 0.0,
                coarse_table: false,
                hint: None,
                certified: None,
            };
            let s0 = p
                .point(
                    &m.surface,
                    f00,
                    &centre,
                    Include {
                        tol_abs: 1e-6,
                        ..inc
                    },
                )
                .unwrap()
                .total[0];
            let target = tol / 8.0 * s0;
            let per_ray = Include {
                tol_abs: target,
                ..inc
            };
            // As in `evaluate`: the centre ray first, its level hinting the rays (which are
            // then integrated as batches of level pairs where `pair_rule` admits it).
            let c = p.point(&m.surface, f00, &centre, per_ray).unwrap();
            let per_ray = Include {
                hint: c.level.filter(|&l| l <= pair_rule(&m.surface).max_hint),
                ..per_ray
            };
            let l = p
                .lobatto_sky(&m.surface, f00, per_ray, &[((0.0, 0.0), c)], target)
                .unwrap();
            let (fit, mean_error) = l.fit.expect("the interpolant passes its check");
            let tiles: Vec<Tile> = gl
                .iter()
                .flat_map(|&(u, _)| gl.iter().map(move |&(v, _)| (u, v)))
                .map(|(u, v)| p.field.ray(u, v, (0, 0)).unwrap())
                .collect();
            let exact = p
                .points(
                    &m.surface,
                    f00,
                    &tiles,
                    Include {
                        tol_abs: 1e-9 * s0,
                        ..inc
                    },
                )
                .unwrap();
            let moments = |values: &[Vector3<f64>]| {
                let mut mean = Vector3::zeros();
                let mut second = Matrix3::zeros();
                let nodes = gl.iter().flat_map(|&a| gl.iter().map(move |&b| (a, b)));
                for (((_, wu), (_, wv)), x) in nodes.zip(values) {
                    mean += x * (wu * wv / 4.0);
                    second += x * x.transpose() * (wu * wv / 4.0);
                }
                (mean, (second - mean * mean.transpose()).norm().sqrt())
            };
            let nodes = gl.iter().flat_map(|&a| gl.iter().map(move |&b| (a, b)));
            let mut worst = 0.0f64;
            let mut quadrature = fit.error;
            let fitted: Vec<Vector3<f64>> = nodes
                .zip(&exact)
                .map(|(((u, _), (v, _)), e)| {
                    let sky = fit.at(u, v);
                    worst = worst.max((sky - e.sky).norm());
                    quadrature = quadrature.max(e.sky_error);
                    e.total - e.sky + sky
                })
                .collect();
            let totals: Vec<Vector3<f64>> = exact.iter().map(|e| e.total).collect();
            let (mean_fit, spread_fit) = moments(&fitted);
            let (mean_true, spread_true) = moments(&totals);
            let name = &m.name;
            let d_mean = (mean_fit - mean_true).norm();
            let d_spread = (spread_fit - spread_true).abs();
            assert!(
                d_mean <= mean_error + quadrature,
                "{name}: mean off by {d_mean:e}, reported {mean_error:e} + {quadrature:e}"
            );
            assert!(
                d_spread <= target + quadrature,
                "{name}: spread off by {d_spread:e}, target {target:e} + {quadrature:e}"
            );
            assert!(
                worst <= tol / 2.0 * s0 + quadrature,
                "{name}: pointwise {:e} of S0",
                worst / s0
            );
        }
    }

    /// The combination technique's interpolant on each set `lobatto_sky` can reach takes the
    /// values at every ray of the set's grids (to 1e-13: rounding of Lagrange weights of
    /// order 1), and reproduces the polynomials its tensor parts span: on the cross plus
    /// `(2, 0)` and `(1, 1)`, `u^4 + u^2 v + u v^2 + v^2` everywhere (1e-12), but not `u^3 v`,
    /// which only `(2, 1)` spans (off by more than 0.01 at a point off the rays).
    #[test]
    fn sparse_fit_interpolates_its_rays() {
        let f = |u: f64, v: f64| Vector3::new((0.3 * u + 0.2 * v + 0.1 * u * v).exp(), u * v, v);
        let sets: [&[(usize, usize)]; 4] = [
            &[(0, 0), (1, 0), (0, 1)],
            &[(0, 0), (1, 0), (0, 1), (2, 0)],
            &[(0, 0), (1, 0), (0, 1), (1, 1), (2, 0)],
            &[
                (0, 0),
                (1, 0),
                (0, 1),
                (1, 1),
                (2, 0),
                (0, 2),
                (2, 1),
                (1, 2),
                (2, 2),
            ],
        ];
        for set in sets {
            let fit = SkyFit::sparse(set, f, 0.0);
            for &(i, j) in set {
                for &u in LOBATTO_LEVELS[i] {
                    for &v in LOBATTO_LEVELS[j] {
                        let d = (fit.at(u, v) - f(u, v)).norm();
                        assert!(d < 1e-13, "{set:?} at ({u}, {v}): {d:e}");
                    }
                }
            }
        }
        let p =
            |u: f64, v: f64| Vector3::new(u.powi(4) + u * u * v + u * v * v + v * v, u * v, 1.0);
        let fit = SkyFit::sparse(sets[2], p, 0.0);
        for (u, v) in [(0.3, -0.7), (-0.9, 0.45), (0.577, 0.577)] {
            let d = (fit.at(u, v) - p(u, v)).norm();
            assert!(d < 1e-12, "({u}, {v}): {d:e}");
        }
        let q = |u: f64, v: f64| Vector3::new(u.powi(3) * v, 0.0, 0.0);
        let fit = SkyFit::sparse(sets[2], q, 0.0);
        let d = (fit.at(0.5, 0.5) - q(0.5, 0.5)).norm();
        assert!(d > 0.01, "u^3 v reproduced without (2, 1): {d:e}");
    }

    /// Studies: slow, run on demand
    /// (`cargo test --release -p polar-model --lib scene::tests::studies -- --ignored --nocapture`).
    mod studies {
        use super::*;

        /// The error estimate against a reference at 1e-8 over 40 random scenes (a fixed seed:
        /// altitude 2 m, 30 m or 1 km, 0-70 deg off nadir, any look azimuth, fields of 2-20
        /// deg each way, sun zenith 10-80 deg at any azimuth) and five materials (glass,
        /// paint, asphalt, aluminium, vegetation), at 1e-3 and 1e-4: the mean's actual error
        /// never exceeds its estimate. Prints the largest ratio of actual error to estimate,
        /// for the mean and for the spread `sqrt |Cov|_F` (not part of the estimate's
        /// contract), and the evaluations per tolerance. About 80 s; it reports a mean ratio
        /// of 0.84 at worst and a spread ratio of 1.06 (one glass field at 1 km).
        #[test]
        #[ignore]
        fn estimate_sweep() {
            let mut seed: u64 = 12345;
            let mut rnd = || {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (seed >> 11) as f64 / (1u64 << 53) as f64
            };
            let surfaces = [
                Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.1, 0.1),
                Surface::microfacet(RefractiveIndex::new(1.49, 0.0).unwrap(), 0.3, 0.04),
                Surface::microfacet(RefractiveIndex::new(1.6, 0.0).unwrap(), 0.5, 0.08),
                Surface::microfacet(RefractiveIndex::new(1.02, 6.6).unwrap(), 0.1, 0.93),
                Surface::vegetation(RefractiveIndex::new(1.5, 0.0).unwrap(), 0.0127),
            ];
            let materials: Vec<SceneMaterial> = surfaces
                .into_iter()
                .zip(["glass", "paint", "asphalt", "aluminium", "vegetation"])
                .map(|(s, name)| SceneMaterial {
                    name: name.into(),
                    surface: s.unwrap(),
                    texture: Texture::None,
                })
                .collect();
            let (mut worst, mut worst_spread) = (0.0f64, 0.0f64);
            let mut evaluations = [0usize; 2];
            for case in 0..40 {
                let altitude = [2.0, 30.0, 1000.0][(rnd() * 3.0) as usize];
                let mut s = spec(altitude, rnd() * 70.0, rnd() * 360.0, 1.0);
                s.pointing.fov_deg = (2.0 + rnd() * 18.0, 2.0 + rnd() * 18.0);
                s.sun_zenith_deg = 10.0 + rnd() * 70.0;
                s.sun_azimuth_deg = rnd() * 360.0;
                let Ok(reference) = evaluate(&s, &materials, 1e-8) else {
                    continue;
                };
                for (k, tol) in [1e-3, 1e-4].into_iter().enumerate() {
                    let r = evaluate(&s, &materials, tol).unwrap();
                    for (a, b) in r.iter().zip(&reference) {
                        evaluations[k] += a.evaluations;
                        let s0 = b.mean.0[0];
                        let actual = (a.mean.0 - b.mean.0).norm() / s0;
                        let spread = (a.cov.norm().sqrt() - b.cov.norm().sqrt()).abs() / s0;
                        worst = worst.max(actual / a.error_estimate);
                        worst_spread = worst_spread.max(spread / a.error_estimate);
                        assert!(
                            actual <= a.error_estimate,
                            "case {case}, {} at {tol}: actual {actual:e} > estimate {:e}: {s:?}",
                            a.name,
                            a.error_estimate
                        );
                    }
                }
            }
            println!(
                "actual / estimate at worst: mean {worst:.3}, spread {worst_spread:.3}; \
                 evaluations at 1e-3 and 1e-4: {evaluations:?}"
            );
        }
    }

    #[test]
    fn bad_tolerance_is_an_error() {
        let e = evaluate(&spec(2.0, 0.0, 0.0, 1.0), &[glass(0.2)], 0.5).unwrap_err();
        assert!(e.to_string().contains("tolerance"), "{e}");
    }
}
