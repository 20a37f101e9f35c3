//! Skylight reflected by a surface towards the sensor (seed Eq. 3.22, MODEL.md section 4):
//! `Ld = int_hemisphere F(omega_d -> omega_v) Lsky(omega_d) cos theta_d dOmega_d`, a Stokes vector in
//! the reflected ray's surface frame (the sky's Stokes vectors are already in each incident ray's
//! surface frame, see [`crate::sky`]), per unit of whatever the sky radiance is per.
//!
//! The specular lobe of a smooth surface is narrow, so its part is integrated in facet-slope
//! space, as the specular albedo is ([`crate::pbrdf::Microfacet::specular_albedo`]): for a fixed
//! view `omega_v`, each facet normal `h` reflects exactly one sky direction
//! `omega_d = 2 (omega_v . h) h - omega_v`, `dOmega_d = 4 (omega_v . h) dOmega_h`, and the
//! Gaussian slope measure absorbs the lobe, so the cost does not grow as `sigma -> 0`
//! (`sigma = 0.05` costs what `sigma = 0.5` does). The Lambertian part is `f00_d` times the sky
//! irradiance, and the vegetation lobe, which is broad, is integrated over the hemisphere
//! directly. Every result carries the quadrature's error estimate and evaluation count.

use crate::error::ModelError;
use crate::pbrdf::{FacetGeometry, Geometry, Surface, COS_FLOOR};
use crate::polarization::Stokes;
use crate::quadrature::{integrate_2d_split_n, integrate_periodic_split_n, Tolerance};
use crate::sky::RayleighSky;
use nalgebra::Vector3;
use std::f64::consts::PI;

/// A sky: the Stokes radiance arriving from each direction of the upper hemisphere, in that
/// ray's surface frame (`x ∝ k × z`, `k` the propagation direction; world `+y` at the zenith).
pub trait SkyRadiance {
    /// Stokes radiance arriving from unit direction `towards` (`z >= 0`).
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes;
}

/// A Rayleigh sky lit by the sun in a given direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SunlitRayleigh {
    /// The sky model.
    pub sky: RayleighSky,
    /// Unit vector towards the sun (`z >= 0`).
    pub sun: Vector3<f64>,
}

impl SkyRadiance for SunlitRayleigh {
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes {
        let t = Vector3::new(towards.x, towards.y, towards.z.max(0.0));
        self.sky
            .stokes(&self.sun, &t)
            .unwrap_or(Stokes::new(0.0, 0.0, 0.0))
    }
}

/// An unpolarised sky of uniform radiance (a test case with closed forms, and an overcast sky).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UniformSky {
    /// Radiance.
    pub radiance: f64,
}

impl SkyRadiance for UniformSky {
    fn stokes_from(&self, _towards: &Vector3<f64>) -> Stokes {
        Stokes::unpolarized(self.radiance)
    }
}

/// A hemisphere integral's result: a Stokes vector with its error estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StokesIntegral {
    /// The integral.
    pub stokes: Stokes,
    /// Estimated largest component error.
    pub error: f64,
    /// Integrand evaluations.
    pub evaluations: usize,
    /// Whether the tolerance was met.
    pub converged: bool,
}

/// Sky irradiance on a horizontal surface, `int S0 cos theta dOmega` (only `S0` is meaningful:
/// polarised components of different directions are in different frames).
pub fn sky_irradiance<S: SkyRadiance + ?Sized>(sky: &S, tol: Tolerance) -> StokesIntegral {
    let r = integrate_2d_split_n(
        |phi, mu: f64| {
            let s = (1.0 - mu * mu).max(0.0).sqrt();
            let d = Vector3::new(s * phi.cos(), s * phi.sin(), mu);
            [sky.stokes_from(&d).0[0] * mu]
        },
        (0.0, 2.0 * PI),
        (0.0, 1.0),
        |_, _| {},
        tol,
    );
    StokesIntegral {
        stokes: Stokes::unpolarized(r.value[0]),
        error: r.error,
        evaluations: r.evaluations,
        converged: r.converged,
    }
}

/// Checks a view direction: unit (to 1e-9) and not below the horizon. Errors name `omega_view`.
fn check_view(omega_view: &Vector3<f64>) -> Result<(), ModelError> {
    let n2 = omega_view.norm_squared();
    if n2.is_finite() && (n2 - 1.0).abs() <= 2e-9 && omega_view.z >= 0.0 {
        Ok(())
    } else {
        Err(ModelError::Invalid {
            field: "omega_view",
            reason: format!("{omega_view:?} must be a unit vector with z >= 0"),
        })
    }
}

/// The specular part of Eq. 3.22 for a microfacet surface of permittivity `eps` and roughness
/// `sigma`, integrated in facet-slope space (module docs). The result is in the reflected
/// surface frame of `omega_view`.
pub fn specular_skylight<S: SkyRadiance + ?Sized>(
    eps: num_complex::Complex64,
    sigma: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
) -> Result<StokesIntegral, ModelError> {
    check_view(omega_view)?;
    let cv = omega_view.z.max(COS_FLOOR);
    let sv = (omega_view.x * omega_view.x + omega_view.y * omega_view.y).sqrt();
    // Local horizontal basis: e1 towards the view's azimuth (x at nadir), e2 = z × e1.
    let e1 = if sv > 0.0 {
        Vector3::new(omega_view.x / sv, omega_view.y / sv, 0.0)
    } else {
        Vector3::x()
    };
    let e2 = Vector3::z().cross(&e1);
    const T: f64 = 6.5;
    let truncation = 2.0 * (-T * T).exp();
    let f = |psi: f64, t: f64| -> [f64; 3] {
        let rho = sigma * std::f64::consts::SQRT_2 * t;
        let (sp, cp) = psi.sin_cos();
        let hv = Vector3::z() - e1 * (rho * cp) - e2 * (rho * sp);
        let h = hv / hv.norm();
        let cos_beta = omega_view.dot(&h);
        if cos_beta <= 0.0 {
            return [0.0; 3];
        }
        let omega_d = h * (2.0 * cos_beta) - omega_view;
        let cos_d = omega_d.z;
        if cos_d <= 0.0 {
            return [0.0; 3];
        }
        let cos_alpha = h.z;
        let g_cb_over_cv = (cos_beta / cv)
            .min(2.0 * cos_alpha)
            .min(2.0 * cos_alpha * cos_d / cv);
        // omega_d is unit and above the horizon, omega_view checked: the world-frame facet
        // geometry, without the detour through the incident plane's frame.
        let m = FacetGeometry::from_world(&omega_d.normalize(), omega_view).rotated_fresnel(eps);
        let s = sky.stokes_from(&omega_d);
        let w = 2.0 * t * (-t * t).exp() * g_cb_over_cv / (2.0 * PI);
        let out = m * s.0 * w;
        [out[0], out[1], out[2]]
    };
    // Kinks along t at fixed psi, as for the albedo (k = cos psi sin theta_v).
    let breaks = |psi: f64, out: &mut Vec<f64>| {
        let k = psi.cos() * sv;
        let to_t = 1.0 / (sigma * std::f64::consts::SQRT_2);
        if k != 0.0 {
            out.push(cv / k * to_t);
            out.push(-cv / k * to_t);
        }
        out.push(-k / cv * to_t);
        out.push((-k + k.hypot(cv)) / cv * to_t);
    };
    let r = integrate_periodic_split_n(f, (0.0, 2.0 * PI), (0.0, T), breaks, tol);
    let scale = sky.stokes_from(&Vector3::z()).0[0].abs().max(1e-300);
    Ok(StokesIntegral {
        stokes: Stokes::new(r.value[0], r.value[1], r.value[2]),
        error: r.error + truncation * scale,
        evaluations: r.evaluations,
        converged: r.converged,
    })
}

/// The whole of Eq. 3.22 for a surface: specular (slope space or, for vegetation, direct) plus
/// `f00_d` times the sky irradiance `e_sky` (from [`sky_irradiance`]).
pub fn reflected_skylight<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    f00_diffuse: f64,
    e_sky: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
) -> Result<StokesIntegral, ModelError> {
    let mut r = match surface {
        Surface::Microfacet { lobe, .. } => specular_skylight(
            lobe.index().permittivity(),
            lobe.sigma(),
            sky,
            omega_view,
            tol,
        )?,
        Surface::Vegetation { .. } => direct_skylight(surface, sky, omega_view, tol)?,
    };
    r.stokes.0[0] += f00_diffuse * e_sky;
    Ok(r)
}

/// Eq. 3.22's specular part by direct integration over incident directions `(phi_d, cos theta_d)`,
/// using the surface's own Mueller matrix: right for broad lobes (vegetation, very rough
/// surfaces) and an independent check of [`specular_skylight`].
pub fn direct_skylight<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
) -> Result<StokesIntegral, ModelError> {
    check_view(omega_view)?;
    let f = |phi: f64, mu: f64| -> [f64; 3] {
        let s = (1.0 - mu * mu).max(0.0).sqrt();
        let d = Vector3::new(s * phi.cos(), s * phi.sin(), mu);
        let Ok(g) = Geometry::from_directions(&d, omega_view) else {
            return [0.0; 3];
        };
        let out = surface.specular(&g).0 * sky.stokes_from(&d).0 * mu;
        [out[0], out[1], out[2]]
    };
    let r = integrate_periodic_split_n(f, (0.0, 2.0 * PI), (0.0, 1.0), |_, _| {}, tol);
    Ok(StokesIntegral {
        stokes: Stokes::new(r.value[0], r.value[1], r.value[2]),
        error: r.error,
        evaluations: r.evaluations,
        converged: r.converged,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fresnel::{amplitudes_eps, RefractiveIndex};
    use crate::sky::direction_from_deg;

    fn glass(sigma: f64) -> Surface {
        Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), sigma, 0.1).unwrap()
    }

    /// A uniform unpolarised sky: by reciprocity the reflected S0 is L times the specular albedo
    /// at the view angle (1e-8: both integrals at 1e-10).
    #[test]
    fn uniform_sky_gives_the_albedo() {
        for (sigma, tv) in [(0.05, 30.0), (0.3, 60.0), (0.5, 80.0)] {
            let s = glass(sigma);
            let view = direction_from_deg(tv, 123.0);
            let r = reflected_skylight(
                &s,
                0.0,
                0.0,
                &UniformSky { radiance: 2.0 },
                &view,
                Tolerance::absolute(1e-10),
            )
            .unwrap();
            let a = s
                .diffuse(f64::to_radians(tv), Tolerance::absolute(1e-10))
                .unwrap()
                .specular_albedo
                .value;
            assert!(
                (r.stokes.0[0] - 2.0 * a).abs() < 1e-8,
                "sigma {sigma} tv {tv}: {r:?} vs {}",
                2.0 * a
            );
            assert!(r.converged, "sigma {sigma} tv {tv}: {r:?}");
        }
    }

    /// sigma -> 0: the surface is a mirror, so the reflected skylight is the Fresnel Mueller
    /// matrix at the view angle applied to the sky radiance from the mirror direction, in frames
    /// that coincide there (relative 2e-6: the lobe's O(sigma^2) width at sigma = 1e-4 averages
    /// the curvature of the sky and of the Fresnel terms, ~30 at 70 deg).
    #[test]
    fn smooth_surface_mirrors_the_polarised_sky() {
        let sky = SunlitRayleigh {
            sky: RayleighSky::at_wavelength(550.0).unwrap(),
            sun: direction_from_deg(40.0, 200.0),
        };
        for (tv, av) in [(30.0, 0.0), (55.0, 90.0), (70.0, 310.0)] {
            let view = direction_from_deg(tv, av);
            let r = specular_skylight(
                RefractiveIndex::new(1.52, 0.0).unwrap().permittivity(),
                1e-4,
                &sky,
                &view,
                Tolerance::absolute(1e-12),
            )
            .unwrap();
            let mirror = Vector3::new(-view.x, -view.y, view.z);
            let s_sky = sky.stokes_from(&mirror);
            let fr = amplitudes_eps(
                RefractiveIndex::new(1.52, 0.0).unwrap().permittivity(),
                view.z,
            );
            let (a, b, d) = (
                0.5 * (fr.rs_power() + fr.rp_power()),
                0.5 * (fr.rs_power() - fr.rp_power()),
                fr.re_rs_rp_conj(),
            );
            let want = Vector3::new(
                a * s_sky.0[0] + b * s_sky.0[1],
                b * s_sky.0[0] + a * s_sky.0[1],
                d * s_sky.0[2],
            );
            assert!(
                (r.stokes.0 - want).norm() < 2e-6 * want.norm(),
                "tv {tv}: {:?} vs {want:?}",
                r.stokes.0
            );
        }
    }

    /// The slope-space integral equals the direct hemisphere integral of the surface's own
    /// Mueller matrix (independent parametrisation and code path) for a moderately rough surface.
    #[test]
    fn slope_space_equals_direct_integration() {
        let sky = SunlitRayleigh {
            sky: RayleighSky::at_wavelength(550.0).unwrap(),
            sun: direction_from_deg(50.0, 10.0),
        };
        let s = glass(0.4);
        let Surface::Microfacet { lobe, .. } = s else {
            unreachable!()
        };
        let view = direction_from_deg(45.0, 170.0);
        let a = specular_skylight(
            lobe.index().permittivity(),
            lobe.sigma(),
            &sky,
            &view,
            Tolerance::absolute(1e-10),
        )
        .unwrap();
        let b = direct_skylight(
            &s,
            &sky,
            &view,
            Tolerance {
                abs: 1e-10,
                rel: 1e-12,
                max_intervals: 2000,
            },
        )
        .unwrap();
        assert!(
            (a.stokes.0 - b.stokes.0).norm() < 1e-7 * a.stokes.0.norm(),
            "{a:?} vs {b:?}"
        );
    }

    /// The narrow lobe (sigma = 0.05) costs no more than a broad one (0.5) at the same tolerance.
    #[test]
    fn narrow_lobe_is_not_more_expensive() {
        let sky = SunlitRayleigh {
            sky: RayleighSky::at_wavelength(550.0).unwrap(),
            sun: direction_from_deg(50.0, 10.0),
        };
        let view = direction_from_deg(45.0, 190.0);
        let eps = RefractiveIndex::new(1.52, 0.0).unwrap().permittivity();
        let narrow = specular_skylight(eps, 0.05, &sky, &view, Tolerance::absolute(1e-7)).unwrap();
        let broad = specular_skylight(eps, 0.5, &sky, &view, Tolerance::absolute(1e-7)).unwrap();
        assert!(narrow.converged && broad.converged);
        assert!(
            narrow.evaluations <= 2 * broad.evaluations,
            "{} vs {}",
            narrow.evaluations,
            broad.evaluations
        );
    }

    /// The world-frame facet geometry used by the slope-space integrand equals the one built
    /// through [`Geometry::from_directions`] (1e-12: rounding only) over a grid of directions
    /// that includes the zenith (both frames' defaults), the horizon's COS_FLOOR clamp and the
    /// specular direction. Exact retro-reflection (`omega_i = omega_r`) is left out: there the
    /// facet frame is `0/0` and the plane-frame path picks it from rounding noise in
    /// `omega_r x omega_i` (a set of measure zero for the integrand).
    #[test]
    fn world_frame_facet_geometry_equals_the_plane_frame_one() {
        let mut dirs = vec![Vector3::z(), Vector3::new(1.0, 0.0, 0.0)];
        for z in [0.0, 1e-3, 20.0, 45.0, 70.0, 89.9] {
            for a in [0.0, 37.0, 90.0, 181.0, 300.0] {
                dirs.push(direction_from_deg(z, a));
            }
        }
        for oi in &dirs {
            for or in dirs.iter().filter(|d| *d != oi) {
                let a = FacetGeometry::from_world(oi, or);
                let b = FacetGeometry::new(&Geometry::from_directions(oi, or).unwrap());
                let pairs = [
                    (a.cos_beta, b.cos_beta),
                    (a.cos_alpha, b.cos_alpha),
                    (a.tan2_alpha, b.tan2_alpha),
                    (a.rot_i.0, b.rot_i.0),
                    (a.rot_i.1, b.rot_i.1),
                    (a.rot_r.0, b.rot_r.0),
                    (a.rot_r.1, b.rot_r.1),
                ];
                for (x, y) in pairs {
                    assert!(
                        (x - y).abs() <= 1e-12 * (1.0 + y.abs()),
                        "{oi:?} {or:?}: {x} vs {y}"
                    );
                }
            }
        }
    }

    #[test]
    fn uniform_sky_irradiance_is_pi_l() {
        let e = sky_irradiance(&UniformSky { radiance: 3.0 }, Tolerance::absolute(1e-12));
        assert!((e.stokes.0[0] - 3.0 * PI).abs() < 1e-11);
    }
}
