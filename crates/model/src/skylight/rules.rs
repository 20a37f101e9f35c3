//! The hemisphere's product rules: Gauss-Legendre in `mu` on each azimuth arc, and the
//! vegetation lobe's columns in batches the widest instruction set the CPU has evaluates
//! ([`pulp::Arch::dispatch`]).

use super::integrand::*;
use crate::geometry::COS_FLOOR;
use crate::pbrdf::Surface;
use crate::quadrature::gauss_legendre_table;
use crate::sky::radiance::SkyRadiance;
use crate::slope::{
    add_scaled, arc_points, reflect_batch, FacetBatch, ReflectedFrame, FACET_BATCH,
};
use nalgebra::Vector3;
use std::f64::consts::PI;

/// [`vegetation_gauss`]'s rule for [`pulp::Arch::dispatch`], as [`SlopeRule`](crate::slope::SlopeRule): its column
/// closure is made inside `with_simd`, so that it too has a copy per instruction set.
pub(super) struct VegetationRule<'r, 'a, S: SkyRadiance + ?Sized> {
    pub(super) leaf: &'r LeafColumns<'a, S>,
    pub(super) level: (usize, usize),
    pub(super) splits: (&'r [f64], &'r [f64]),
}

impl<S: SkyRadiance + ?Sized> pulp::WithSimd for VegetationRule<'_, '_, S> {
    type Output = ([f64; 3], usize);

    #[inline(always)]
    fn with_simd<Simd: pulp::Simd>(self, _simd: Simd) -> Self::Output {
        let mut b = FacetBatch::new();
        let leaf = self.leaf;
        let ((n, q), (phi_splits, mu_splits)) = (self.level, self.splits);
        hemisphere_gauss_columns(
            #[inline(always)]
            |c: f64, s: f64, nodes: &[(f64, f64, f64)], wphi: f64, sum: &mut [f64; 3]| {
                leaf.column((c, s), nodes, wphi, &mut b, sum)
            },
            n,
            q,
            phi_splits,
            mu_splits,
        )
    }
}

/// A product Gauss-Legendre rule over the hemisphere in `(phi, mu = cos theta)`: the azimuth
/// split at `phi_splits` (any order; none: one arc of `2 pi`) into arcs of `n`-per-`pi` points
/// (at least `n / 2` each), `mu` split at `mu_splits` (inside `(0, 1)`) into pieces of `q`
/// points. Returns the integral of `f` and the evaluations.
pub(super) fn hemisphere_gauss<F: Fn(&Vector3<f64>) -> [f64; 3]>(
    f: &F,
    n: usize,
    q: usize,
    phi_splits: &[f64],
    mu_splits: &[f64],
) -> ([f64; 3], usize) {
    let column =
        |cos_phi: f64, sin_phi: f64, nodes: &[(f64, f64, f64)], wphi: f64, sum: &mut [f64; 3]| {
            for &(mu, s, wmu) in nodes {
                let v = f(&Vector3::new(s * cos_phi, s * sin_phi, mu));
                add_scaled(sum, &v, wphi * wmu);
            }
        };
    hemisphere_gauss_columns(column, n, q, phi_splits, mu_splits)
}

/// [`hemisphere_gauss`] by columns: `column(cos phi, sin phi, nodes, w_phi, sum)` adds `w_phi
/// w_mu f(d)` over the azimuth line's `nodes` `(mu, sin theta, w_mu)` to `sum` (a whole line
/// at once, so that it may be computed in vector loops: [`LeafColumns`]).
#[inline(always)]
pub(super) fn hemisphere_gauss_columns(
    mut column: impl FnMut(f64, f64, &[(f64, f64, f64)], f64, &mut [f64; 3]),
    n: usize,
    q: usize,
    phi_splits: &[f64],
    mu_splits: &[f64],
) -> ([f64; 3], usize) {
    let mut phis: Vec<f64> = phi_splits.iter().map(|p| p.rem_euclid(2.0 * PI)).collect();
    phis.sort_by(f64::total_cmp);
    phis.dedup();
    let arcs: Vec<(f64, f64)> = match phis.len() {
        0 => vec![(0.0, 2.0 * PI)],
        k => (0..k)
            .map(|i| {
                let b = if i + 1 < k {
                    phis[i + 1]
                } else {
                    phis[0] + 2.0 * PI
                };
                (phis[i], b)
            })
            .filter(|(a, b)| b > a)
            .collect(),
    };
    let mut mus: Vec<f64> = mu_splits
        .iter()
        .copied()
        .filter(|m| *m > 0.0 && *m < 1.0)
        .chain([0.0, 1.0])
        .collect();
    mus.sort_by(f64::total_cmp);
    mus.dedup();
    let gq = gauss_legendre_table(q);
    // The `mu` nodes, their `sin theta` and weights, the same on every azimuth line.
    let nodes: Vec<(f64, f64, f64)> = mus
        .windows(2)
        .flat_map(|w| {
            let (mid, h) = (0.5 * (w[0] + w[1]), 0.5 * (w[1] - w[0]));
            gq.iter().map(move |&(y, wy)| {
                let mu = mid + h * y;
                (mu, (1.0 - mu * mu).max(0.0).sqrt(), h * wy)
            })
        })
        .collect();
    let mut sum = [0.0; 3];
    let mut evaluations = 0;
    for (a, b) in arcs {
        let m = arc_points(n, b - a);
        let (centre, half) = (0.5 * (a + b), 0.5 * (b - a));
        for &(x, wx) in gauss_legendre_table(m) {
            let phi = centre + half * x;
            column(phi.cos(), phi.sin(), &nodes, half * wx, &mut sum);
            evaluations += nodes.len();
        }
    }
    (sum, evaluations)
}

/// Vegetation's [`direction_integrand`] (its facet-frame path) over whole azimuth lines of
/// [`hemisphere_gauss_columns`], in vector loops: the directions, facet frames and weights,
/// then [`reflect_batch`]. The same values as the direction integrand to rounding (tested).
pub(super) struct LeafColumns<'a, S: SkyRadiance + ?Sized> {
    pub(super) surface: &'a Surface,
    pub(super) sky: &'a S,
    pub(super) omega_view: Vector3<f64>,
    pub(super) s_r: ReflectedFrame,
    pub(super) cos_tr: f64,
    pub(super) eps: num_complex::Complex64,
    /// As [`SlopeIntegrand`]'s.
    pub(super) real_eps: Option<f64>,
}

impl<'a, S: SkyRadiance + ?Sized> LeafColumns<'a, S> {
    /// `None` for a surface other than vegetation.
    pub(super) fn new(surface: &'a Surface, sky: &'a S, omega_view: &Vector3<f64>) -> Option<Self> {
        let Surface::Vegetation { lobe, .. } = surface else {
            return None;
        };
        let eps = lobe.index().permittivity();
        Some(LeafColumns {
            surface,
            sky,
            omega_view: *omega_view,
            s_r: ReflectedFrame::new(omega_view, sky.peak()),
            cos_tr: omega_view.z.clamp(COS_FLOOR, 1.0),
            eps,
            real_eps: (eps.im == 0.0 && eps.re >= 1.0).then_some(eps.re),
        })
    }

    /// One azimuth line: [`hemisphere_gauss_columns`]' `column`.
    #[inline(always)]
    pub(super) fn column(
        &self,
        (cos_phi, sin_phi): (f64, f64),
        nodes: &[(f64, f64, f64)],
        wphi: f64,
        b: &mut FacetBatch,
        sum: &mut [f64; 3],
    ) {
        let v = &self.omega_view;
        let (rx, ry) = (&self.s_r.x, &self.s_r.y);
        for chunk in nodes.chunks(FACET_BATCH) {
            let n = chunk.len();
            for (i, &(mu, s, wmu)) in chunk.iter().enumerate() {
                let d = Vector3::new(s * cos_phi, s * sin_phi, mu);
                let (f, cos_beta, w) = leaf_facet(v, &d, self.cos_tr);
                (b.dx[i], b.dy[i], b.dz[i]) = (d.x, d.y, d.z);
                (b.fx[i], b.fy[i], b.fz[i]) = (f.x, f.y, f.z);
                b.f2[i] = f.x * f.x + f.y * f.y + f.z * f.z;
                b.cos_beta[i] = cos_beta;
                b.w[i] = w * (wphi * wmu);
                b.c[i] = rx.dot(&f);
                b.sn[i] = ry.dot(&f);
            }
            // The facet frame is 0/0 (light from the view's own direction): the surface's
            // Mueller matrix, one point.
            for (i, &(_, _, wmu)) in chunk.iter().enumerate() {
                if b.f2[i] <= 1e-200 {
                    let d = Vector3::new(b.dx[i], b.dy[i], b.dz[i]);
                    let value = specular_times_sky(self.surface, self.sky, v, &d);
                    add_scaled(sum, &value, wphi * wmu);
                    b.set_idle(i);
                }
            }
            reflect_batch(self.sky, self.eps, self.real_eps, b, n, sum);
        }
    }
}

/// Vegetation's product rule at `(n, q)`: [`hemisphere_gauss`] of [`direction_integrand`], by
/// [`LeafColumns`].
pub(super) fn vegetation_gauss<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    (n, q): (usize, usize),
    (phi_splits, mu_splits): (&[f64], &[f64]),
) -> ([f64; 3], usize) {
    match LeafColumns::new(surface, sky, omega_view) {
        // As `SlopeIntegrand::gauss`: the widest instruction set the CPU has.
        Some(leaf) => pulp::Arch::new().dispatch(VegetationRule {
            leaf: &leaf,
            level: (n, q),
            splits: (phi_splits, mu_splits),
        }),
        None => {
            let g = direction_integrand(surface, sky, omega_view);
            hemisphere_gauss(&g, n, q, phi_splits, mu_splits)
        }
    }
}
