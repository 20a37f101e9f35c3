//! The band-integrated sky of one field ray ([`BandSky`]): single scattering from the `mu`
//! tables, the Berry pattern, or the table; and the prepared scene's per-ray terms and sky
//! accessors.

use super::prepared::*;
use crate::air_mass::slant_mu0;
use crate::atmosphere::OpticalDepths;
use crate::error::ModelError;
use crate::geometry::reflected_frame_x;
use crate::polarization::{cos_sin_2eta, rotation_from_cos_sin_2eta, Stokes};
use crate::sky::band::BandTables;
use crate::sky::clear::ClearSky;
use crate::sky::radiance::{e_vector_in_frame, surface_to_frame, SkyRadiance};
use crate::tiles::Tile;
use nalgebra::Vector3;
use std::f64::consts::PI;
use std::sync::{Arc, OnceLock};

/// The band-integrated single-scattering sky of one field point ([`crate::scene`] docs).
pub(super) struct BandSky<'a> {
    pub(super) prepared: &'a Prepared,
    /// The `A` and `B` tables, shared by every material's view of the same ray.
    pub(super) tables: Arc<BandTables>,
    /// Tabulated sky only: the band-mean transmittance `sum c_k / sum w_k`.
    pub(super) table_scale: f64,
    /// Tabulated sky only: use the half-resolution table (the interpolation-error probe).
    pub(super) coarse_table: bool,
}

impl BandSky<'_> {
    /// The band-integrated single-scattering radiance arriving from `towards` and its
    /// polarised part `P12 A(mu)` ([`crate::scene`] docs); `None` where the radiance is not
    /// positive.
    #[inline]
    pub(super) fn single_scattering(&self, towards: &Vector3<f64>) -> Option<(f64, f64)> {
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
pub(super) struct Scattering {
    pub(super) sun: Vector3<f64>,
    /// `RayleighSky::phase` with its depolarisation factor taken once.
    pub(super) rayleigh_phase: [f64; 2],
    pub(super) aerosol_g: f64,
}

impl Scattering {
    /// The radiance `P11 A(mu) + P_HG B(mu)` arriving from `towards` and its polarised part
    /// `P12 A(mu)` ([`crate::scene`] docs), from the tables' `(A, B)` at the ray's `mu`; the
    /// radiance may be `<= 0` (the callers take that as no light).
    #[inline(always)]
    pub(super) fn radiance(&self, (a, b): (f64, f64), towards: &Vector3<f64>) -> (f64, f64) {
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
    pub(super) fn in_frame(
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

impl Prepared {
    /// The single-scattering constants the band sky's per-ray arithmetic reads.
    #[inline(always)]
    pub(super) fn scattering(&self) -> Scattering {
        Scattering {
            sun: self.sun,
            rayleigh_phase: self.rayleigh_phase,
            aerosol_g: self.atmosphere.aerosol_g,
        }
    }

    /// A white Lambertian surface's radiance at the ground, direct sun plus sky (W m^-2 sr^-1):
    /// the scale below which a term cannot matter for any material.
    pub(super) fn white_radiance(&self) -> f64 {
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
    pub(super) fn band_sky(&self, coefficients: &[f64], coarse_table: bool) -> BandSky<'_> {
        self.band_sky_with(
            Arc::new(self.band_tables(coefficients)),
            coefficients,
            coarse_table,
        )
    }

    /// [`Prepared::band_sky`] of a field ray, its tables built once for every material.
    pub(super) fn ray_sky(&self, ray: &RayTerms, coarse_table: bool) -> BandSky<'_> {
        let tables = Arc::clone(
            ray.tables
                .get_or_init(|| Arc::new(self.band_tables(&ray.up))),
        );
        self.band_sky_with(tables, &ray.up, coarse_table)
    }

    pub(super) fn band_sky_with(
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
    pub(super) fn band_tables(&self, coefficients: &[f64]) -> BandTables {
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
    pub(super) fn ray_terms(&self, tile: &Tile) -> Result<Arc<RayTerms>, ModelError> {
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
}
