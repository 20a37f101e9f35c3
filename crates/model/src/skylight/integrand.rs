//! The skylight's integrands over the hemisphere: the surface's specular Mueller matrix times
//! the sky, with the vegetation's facet frame taken directly, and the splits at the view's and
//! the sky peak's azimuth and zenith.

use crate::geometry::{Geometry, COS_FLOOR};
use crate::pbrdf::Surface;
use crate::sky::radiance::SkyRadiance;
use crate::slope::{facet_reflection, ReflectedFrame};
use nalgebra::Vector3;

/// The integrand of [`direct_skylight`] over `(phi, mu = cos theta)` of the incident direction:
/// the surface's specular Mueller matrix times the sky's Stokes vector times `mu`.
pub(super) fn hemisphere_integrand<'a, S: SkyRadiance + ?Sized>(
    surface: &'a Surface,
    sky: &'a S,
    omega_view: &'a Vector3<f64>,
) -> impl Fn(f64, f64) -> [f64; 3] + Copy + 'a {
    let f = direction_integrand(surface, sky, omega_view);
    move |phi: f64, mu: f64| f(&hemisphere_direction(phi.cos(), phi.sin(), mu))
}

/// The unit direction of azimuth `(cos phi, sin phi)` and `mu = cos theta`.
#[inline]
pub(super) fn hemisphere_direction(cos_phi: f64, sin_phi: f64, mu: f64) -> Vector3<f64> {
    let s = (1.0 - mu * mu).max(0.0).sqrt();
    Vector3::new(s * cos_phi, s * sin_phi, mu)
}

/// [`hemisphere_integrand`] of the incident direction `d` (unit, `z = mu`). For vegetation
/// (Eq. 3.19: `R(-eta_r) M(beta) R(eta_i) / (4 (cos ti + cos tr))`) seen off the zenith, the
/// sky's Stokes vector is asked for in the facet frame and `M(beta)` applied directly
/// ([`facet_reflection`]), as in the facet-slope integrand; otherwise the surface's own
/// Mueller matrix (`Surface::specular`) times the sky's Stokes vector.
pub(super) fn direction_integrand<'a, S: SkyRadiance + ?Sized>(
    surface: &'a Surface,
    sky: &'a S,
    omega_view: &'a Vector3<f64>,
) -> impl Fn(&Vector3<f64>) -> [f64; 3] + Copy + 'a {
    let s_r = ReflectedFrame::new(omega_view, sky.peak());
    let cos_tr = omega_view.z.clamp(COS_FLOOR, 1.0);
    let leaf_eps = match surface {
        Surface::Vegetation { lobe, .. } => Some(lobe.index().permittivity()),
        Surface::Microfacet { .. } => None,
    };
    // Inlined into the product rule's loop (asked once per integrand point); the general
    // path, taken off the vegetation's facet frame, is a call.
    #[inline(always)]
    move |d: &Vector3<f64>| {
        if let Some(eps) = leaf_eps {
            // `omega_r × omega_i`, the facet frame's x as in `FacetGeometry`.
            let (s_f_x, cos_beta, w) = leaf_facet(omega_view, d, cos_tr);
            if s_f_x.norm_squared() > 1e-200 {
                let s = sky.stokes_in_frame(d, &s_f_x);
                return facet_reflection(eps, cos_beta, &s, &s_f_x, &s_r, w);
            }
        }
        specular_times_sky(surface, sky, omega_view, d)
    }
}

/// Vegetation's facet for light from `d` seen from `omega_view` (Eq. 3.19): the facet frame's
/// `x`, `omega_r × omega_i` as in `FacetGeometry` (zero for light from the view's own
/// direction), `cos beta = |d + omega_view| / 2`, and the weight `mu / (4 (cos ti + cos tr))`
/// (`cos_tr` floored at [`COS_FLOOR`]). Shared by [`direction_integrand`] and
/// [`LeafColumns::column`]'s vector loop.
#[inline(always)]
pub(super) fn leaf_facet(
    omega_view: &Vector3<f64>,
    d: &Vector3<f64>,
    cos_tr: f64,
) -> (Vector3<f64>, f64, f64) {
    let mu = d.z;
    (
        omega_view.cross(d),
        0.5 * (d + omega_view).norm(),
        0.25 / (mu.clamp(COS_FLOOR, 1.0) + cos_tr) * mu,
    )
}

/// [`direction_integrand`] by the surface's own Mueller matrix: `Surface::specular` times the
/// sky's Stokes vector in the surface frame, times `mu`.
#[inline(never)]
pub(super) fn specular_times_sky<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    d: &Vector3<f64>,
) -> [f64; 3] {
    let Ok(g) = Geometry::from_directions(d, omega_view) else {
        return [0.0; 3];
    };
    let out = surface.specular(&g).0 * sky.stokes_from(d).0 * d.z;
    [out[0], out[1], out[2]]
}

/// The azimuths and `mu` at which [`hemisphere_gauss`] splits for `omega_view`: the
/// integrand is smooth but at two points, light from the sensor's own direction (the facet
/// frame is 0/0 there) and the sky's peak, and the product rule's lines pass through both.
pub(super) fn hemisphere_splits<S: SkyRadiance + ?Sized>(
    sky: &S,
    omega_view: &Vector3<f64>,
) -> (Vec<f64>, Vec<f64>) {
    let azimuth = |d: &Vector3<f64>| d.y.atan2(d.x);
    let mut phi_splits = vec![azimuth(omega_view)];
    let mut mu_splits = vec![omega_view.z];
    if let Some(p) = sky.peak().filter(|p| p.z > 0.0) {
        phi_splits.push(azimuth(&p));
        mu_splits.push(p.z);
    }
    (phi_splits, mu_splits)
}
