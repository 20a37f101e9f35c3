//! The reflected skylight over the field as a polynomial through Chebyshev-Lobatto rays (sparse
//! grids by the combination technique), and the errors of the field moments it gives.

use super::points::*;
use super::prepared::*;
use crate::error::ModelError;
use crate::pbrdf::Surface;
use crate::tiles::Tile;
use nalgebra::{Matrix3, Vector3};

/// A tensor Lagrange polynomial through rays on a grid of the field.
pub(super) struct TensorFit {
    /// Nodes in `u`.
    pub(super) nodes_u: Vec<f64>,
    /// Nodes in `v`.
    pub(super) nodes_v: Vec<f64>,
    /// `values[i * nodes_v.len() + j]` at `(nodes_u[i], nodes_v[j])`.
    pub(super) values: Vec<Vector3<f64>>,
}

impl TensorFit {
    pub(super) fn at(&self, u: f64, v: f64) -> Vector3<f64> {
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
pub(super) struct SkyFit {
    pub(super) parts: Vec<(f64, TensorFit)>,
    /// The largest quadrature error of the fitted values.
    pub(super) error: f64,
}

impl SkyFit {
    /// The polynomial through a full grid of rays.
    pub(super) fn tensor(
        nodes_u: Vec<f64>,
        nodes_v: Vec<f64>,
        values: Vec<Vector3<f64>>,
        error: f64,
    ) -> Self {
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
    pub(super) fn sparse(
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

    pub(super) fn at(&self, u: f64, v: f64) -> Vector3<f64> {
        self.parts
            .iter()
            .map(|(c, t)| t.at(u, v) * *c)
            .sum::<Vector3<f64>>()
    }
}

/// The Lagrange basis polynomial of node `i` of `nodes` at `x`.
pub(super) fn lagrange_basis(nodes: &[f64], x: f64, i: usize) -> f64 {
    nodes
        .iter()
        .enumerate()
        .filter(|&(k, _)| k != i)
        .map(|(_, &xk)| (x - xk) / (nodes[i] - xk))
        .product()
}

/// The nested Chebyshev-Lobatto node sets of [`Prepared::lobatto_sky`]'s sparse grids, by
/// level: the centre; the edges and centre; five points.
pub(super) const LOBATTO_LEVELS: [&[f64]; 3] = [
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
pub(super) fn grid(nodes_u: &[f64], nodes_v: &[f64]) -> Vec<(f64, f64)> {
    nodes_u
        .iter()
        .flat_map(|&u| nodes_v.iter().map(move |&v| (u, v)))
        .collect()
}

/// The largest level in direction `axis` (0: `u`, 1: `v`) of a set's pairs on that axis.
pub(super) fn set_max(set: &[(usize, usize)], axis: usize) -> usize {
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
pub(super) fn combination_coefficients(set: &[(usize, usize)]) -> Vec<((usize, usize), f64)> {
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
pub(super) struct MomentErrors {
    /// Of the field mean, `|E[delta]|`, `delta` the interpolant's error.
    pub(super) mean: f64,
    /// Of the field spread `sqrt(|Cov|_F)` (what [`Prepared::evaluate`]'s field orders test).
    pub(super) spread: f64,
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
pub(super) fn fit_moment_errors(
    fit: &SkyFit,
    checks: &[((f64, f64), Point)],
    noise: f64,
) -> MomentErrors {
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

/// [`Prepared::lobatto_sky`]'s result: the interpolant with its interpolation error, if it
/// predicts its check rays, and the integrand evaluations spent.
pub(super) struct LobattoSky {
    pub(super) fit: Option<(SkyFit, f64)>,
    pub(super) evaluations: usize,
    /// The lowest product-rule level its own rays were accepted at.
    pub(super) level: Option<usize>,
}

impl Prepared {
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
    pub(super) fn lobatto_sky(
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
}
