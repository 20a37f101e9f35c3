//! The radiance of field points: the terms of one ray (direct, path, skylight), batches of
//! neighbouring rays accepted on level pairs, and the boresight's terms.

use super::band_sky::*;
use super::prepared::*;
use super::spec::*;
use crate::error::ModelError;
use crate::pbrdf::Surface;
use crate::polarization::{rotation_from_cos_sin_2eta, Stokes};
use crate::quadrature::Tolerance;
use crate::skylight::{
    batch_error, certified_level, level_pair, next_pair, pair_rule, reflected_skylight,
    reflected_skylight_at, Certificate, DIRECT_PRODUCT_MIN_COS_VIEW,
};
use crate::slope::{LevelPair, Start, StokesIntegral};
use crate::tiles::Tile;
use nalgebra::Vector3;
use rayon::prelude::*;
use std::sync::Arc;

/// What [`Prepared::point`] includes.
#[derive(Debug, Clone, Copy)]
pub(super) struct Include {
    pub(super) skylight: bool,
    pub(super) path: bool,
    /// Absolute tolerance of the skylight quadrature.
    pub(super) tol_abs: f64,
    /// Tabulated sky only: light the point with the half-resolution table.
    pub(super) coarse_table: bool,
    /// The lowest product-rule level that neighbouring rays, integrated to the same
    /// tolerance, were accepted at: this ray's skylight starts two levels below it (`ladder`:
    /// the error test is unchanged).
    pub(super) hint: Option<usize>,
    /// An accepted batch of level pairs around this batch, at the same tolerance: its rays
    /// take the batch's upper level alone, with its error ([`certified_level`]).
    pub(super) certified: Option<Certificate>,
}

/// One field point's radiance in the camera frame.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Point {
    pub(super) total: Vector3<f64>,
    pub(super) surface: Vector3<f64>,
    /// The reflected skylight alone (part of both the above).
    pub(super) sky: Vector3<f64>,
    pub(super) sky_error: f64,
    pub(super) evaluations: usize,
    /// The skylight's accepted product-rule level, if any.
    pub(super) level: Option<usize>,
    /// The batch of level pairs this point's skylight was accepted in, if any.
    pub(super) certificate: Option<Certificate>,
}

/// A field point's terms before its skylight, in the surface frame.
pub(super) struct PointBase {
    /// The direct part (Eq. 3.21) with its Lambertian term.
    pub(super) surface: Vector3<f64>,
    /// The path radiance (zero when not included).
    pub(super) path: Vector3<f64>,
    /// The sky irradiance per unit `f00_diffuse`, transmitted up.
    pub(super) e_sky: f64,
    /// The ray's material-independent terms (its band sky's coefficients and tables).
    pub(super) ray: Arc<RayTerms>,
}

/// The largest angle of a ray from the field's centre for [`Prepared::points_paired`]: the
/// validation (`field_pair_study`) spanned +-6 deg in view zenith and azimuth, rays up to 8.2
/// deg from the centre (6 deg for views near the normal, where azimuth moves a ray less).
pub(super) const PAIR_FIELD_DEG: f64 = 8.0;

impl Prepared {
    /// [`Prepared::point`] at each of `tiles`, in parallel (rayon's pool: `RAYON_NUM_THREADS`
    /// threads, by default one per core); the results in the order of `tiles`, the first
    /// error in that order if any. A batch that [`Prepared::pair_hint`] admits is integrated
    /// by [`Prepared::points_paired`].
    pub(super) fn points(
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
    pub(super) fn pair_hint(
        &self,
        surface: &Surface,
        tiles: &[Tile],
        inc: Include,
    ) -> Option<usize> {
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
    pub(super) fn points_paired(
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
    pub(super) fn point_base(
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
    pub(super) fn finish(
        &self,
        tile: &Tile,
        base: PointBase,
        sky: Option<&StokesIntegral>,
    ) -> Point {
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
    pub(super) fn point(
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
}
