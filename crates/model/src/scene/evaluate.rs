//! Evaluating materials on a prepared scene: the field's Gauss-Legendre orders, the skylight over
//! the field, the error estimate and the terms reported.

use super::budget::*;
use super::fit::*;
use super::points::*;
use super::prepared::*;
use super::spec::*;
use crate::error::ModelError;
use crate::polarization::Stokes;
use crate::quadrature::gauss_legendre_table;
use crate::skylight::pair_rule;
use crate::tiles::Tile;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

impl Prepared {
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

    /// [`Prepared::evaluate`] at tolerance `tol` (at least the scene's), a tabulated sky's
    /// measured floor `table_floor` (radiance) added to the error estimate.
    pub(super) fn evaluate_to(
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

/// Evaluates every material of a scene at relative tolerance `tol` (of each material's mean
/// `S0`). Errors name the field.
pub fn evaluate(
    spec: &SceneSpec,
    materials: &[SceneMaterial],
    tol: f64,
) -> Result<Vec<MaterialResult>, ModelError> {
    Prepared::new(spec, tol)?.evaluate_all(materials)
}
