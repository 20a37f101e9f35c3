//! Polarimetric BRDF: the microfacet model of Meng (2012) Sec. 3.1.1 (Eqs. 3.4-3.18) and the vegetation
//! model of Eq. 3.19 (MODEL.md section 3).
//!
//! # Geometry and frames
//!
//! The surface normal is `+z`. The towards-source direction is `omega_i = (sin ti, 0, cos ti)`
//! (incident azimuth 0) and the towards-sensor direction is
//! `omega_r = (sin tr cos phi, sin tr sin phi, cos tr)`, so the specular direction is
//! `tr = ti, phi = 180 deg` (Eq. 3.6's convention). Propagation vectors are `k_i = -omega_i` and
//! `k_r = omega_r`.
//!
//! Each ray's *surface frame* has `x = s`, the unit vector perpendicular to the plane containing
//! the ray and the surface normal (`s ∝ k × n`), and `y = k × x`. At exactly normal incidence or
//! view the plane is undefined and the frame is taken as the limit along the ray's azimuth
//! (`s_i = (0, 1, 0)`, `s_r = (sin phi, -cos phi, 0)`), so the Mueller matrix is continuous as the
//! angle goes to zero along a fixed azimuth. The *facet frame* has `x = s_f ∝ k_i × h` with `h`
//! the facet normal (half vector); it is the same for both rays because `k_r × h = k_i × h`.
//!
//! Eq. 3.7, `M'(beta) = R(-eta_r) M(beta) R(eta_i)`, is built from these vectors: `eta` is the
//! signed angle from the surface frame's `s` to `s_f` about the ray, from a dot and a cross
//! product. Meng (2012)'s arc-cosine forms (Eqs. 3.9-3.10) lose the sign and are 0/0 at normal
//! incidence, at `beta -> 0` and in the specular direction; they serve only as a test oracle.
//! At `beta = 0` (retro-reflection) `s_f` is undefined, but there `Rs = Rp` and `M'` does not
//! depend on the choice, so `s_f = s_i` is used.
//!
//! # Boundaries (MODEL.md section 12)
//!
//! * Zenith angles are in `[0, 90] deg`. `cos theta` is floored at `cos(pi/2)` evaluated in f64
//!   (`6.12e-17`), the value any angle input of 90 deg produces, so direction-based and
//!   angle-based inputs agree and every division is finite. Away from the grazing specular
//!   direction, the shadowing term is evaluated as `G / (cos ti cos tr) =
//!   min(1/(cos ti cos tr), 2 cos a / (cos b cos tr), 2 cos a / (cos b cos ti))`, whose limit at
//!   90 deg is finite. At exactly grazing specular (`ti = tr = 90, phi = 180 deg`) the BRDF of
//!   Eq. 3.15 diverges like `1 / cos^2`; the model returns the (finite, ~1e31 p(0)) value at the
//!   floor.
//! * `sigma -> 0`: the slope density tends to a delta function. For `sigma` down to
//!   [`SIGMA_MIN`] every value is finite: the lobe peak is `1/(2 pi sigma^2)` and outside it the
//!   Gaussian underflows to exactly 0. The specular albedo tends to the Fresnel reflectance
//!   `0.5 (Rs + Rp)(ti)` as `sigma -> 0` because it is integrated in slope space (below).

use crate::error::ModelError;
use crate::fresnel::{amplitudes_eps, RefractiveIndex};
pub use crate::geometry::{FacetGeometry, Geometry, COS_FLOOR};
use crate::polarization::Mueller;
use crate::quadrature::{integrate_2d, integrate_2d_split, Integral, Tolerance};
use num_complex::Complex64;
use std::f64::consts::{FRAC_PI_2, PI};

/// Smallest roughness accepted (slope standard deviation).
pub const SIGMA_MIN: f64 = 1e-6;
/// Largest roughness accepted.
pub const SIGMA_MAX: f64 = 10.0;

/// Beckmann facet-slope density per unit solid angle of facet normal (Eq. 3.12):
/// `exp(-tan^2 a / (2 sigma^2)) / (2 pi sigma^2 cos^3 a)`. Finite for `cos a >= COS_FLOOR`.
/// Exactly 0 where the exponential is below `exp(-650)` (1e-282 of the peak): there the
/// Mueller elements, products of it with factors down to 1e-25, would reach subnormal numbers
/// and lose their relative precision (a metal at grazing angles gave a DoLP of 1.0009 from
/// elements of 5e-321).
#[inline]
pub fn slope_density(tan2_alpha: f64, cos_alpha: f64, sigma: f64) -> f64 {
    let s2 = sigma * sigma;
    let c = cos_alpha.max(COS_FLOOR);
    let exponent = -tan2_alpha / (2.0 * s2);
    if exponent < -650.0 {
        return 0.0;
    }
    exponent.exp() / (2.0 * PI * s2 * c * c * c)
}

/// Shadowing/masking (Eq. 3.14), `min(1, 2 cos a cos ti / cos b, 2 cos a cos tr / cos b)`.
#[inline]
pub fn shadowing(cos_alpha: f64, cos_beta: f64, cos_ti: f64, cos_tr: f64) -> f64 {
    let t = 2.0 * cos_alpha / cos_beta.max(COS_FLOOR);
    1f64.min(t * cos_ti).min(t * cos_tr)
}

/// The specular lobe of the microfacet model (Eqs. 3.5-3.15): index and roughness.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Microfacet {
    index: RefractiveIndex,
    eps: Complex64,
    sigma: f64,
}

impl Microfacet {
    /// Validates roughness `sigma = sigma_h / l` (Eq. 3.13) in `[SIGMA_MIN, SIGMA_MAX]`.
    pub fn new(index: RefractiveIndex, sigma: f64) -> Result<Self, ModelError> {
        ModelError::check_range("sigma", sigma, SIGMA_MIN, SIGMA_MAX, "[1e-6, 10]")?;
        Ok(Microfacet {
            index,
            eps: index.permittivity(),
            sigma,
        })
    }

    /// The refractive index.
    pub fn index(&self) -> RefractiveIndex {
        self.index
    }

    /// The roughness.
    pub fn sigma(&self) -> f64 {
        self.sigma
    }

    /// The specular Mueller matrix `Fs` (Eq. 3.15), surface frames in and out, sr^-1.
    #[inline]
    pub fn specular(&self, g: &Geometry) -> Mueller {
        let fg = FacetGeometry::new(g);
        let p = slope_density(fg.tan2_alpha, fg.cos_alpha, self.sigma);
        // G / (cos ti cos tr) without 0/0 at grazing (see module docs).
        let t = 2.0 * fg.cos_alpha / fg.cos_beta.max(COS_FLOOR);
        let g_over = (1.0 / (g.cos_ti * g.cos_tr))
            .min(t / g.cos_tr)
            .min(t / g.cos_ti);
        Mueller(fg.rotated_fresnel(self.eps) * (0.25 * p * g_over))
    }

    /// Specular albedo `int f00_s cos tr dOmega_r` over the hemisphere (the integral of Eq. 3.18).
    ///
    /// Integrated in facet-slope space rather than over view directions: with
    /// `dOmega_r = 4 (omega_i . h) dOmega_h` and `p dOmega_h` the Gaussian slope measure,
    /// the albedo is `E_slope[M00(beta) G (omega_i . h) / cos ti]` over facets whose reflection
    /// leaves upwards. The integrand is bounded by 2 and continuous (G vanishes where the
    /// reflected ray or the facet reaches the horizon), and the narrow lobe of a smooth surface
    /// is absorbed into the Gaussian weight, so the cost does not grow as `sigma -> 0`.
    /// Polar slope coordinates `rho = sigma sqrt(2) t` make the weight `2 t exp(-t^2)`, integrated
    /// over `t in [0, 6.5]` (the neglected tail, `< 1e-18`, is added to the error).
    ///
    /// By reciprocity (`f(omega_i -> omega_r) = f(omega_r -> omega_i)`), the albedo is the
    /// radiance that a uniform sky of unit radiance reflects towards `omega_i`: the product
    /// rule of [`crate::slope::specular_skylight`] on this same slope-space integrand, whose
    /// levels converge geometrically: for lobes from [`ALBEDO_PRODUCT_MIN_SIGMA`] on, at
    /// incidence up to [`ALBEDO_PRODUCT_MAX_TI_RAD`], about a seventh of the adaptive rule's
    /// evaluations (376 k against 2.51 M in `albedo_product_rule_agrees_with_the_adaptive_rule`,
    /// which also found the adaptive rule drifting by 1.4e-8 of the albedo beyond its claimed
    /// error at sigma 1). Elsewhere, and when its ladder does not converge, the adaptive rule
    /// ([`Microfacet::specular_albedo_adaptive`]) answers.
    pub fn specular_albedo(
        &self,
        theta_i_rad: f64,
        tol: Tolerance,
    ) -> Result<Integral, ModelError> {
        let ti = ModelError::check_range("theta_i", theta_i_rad, 0.0, FRAC_PI_2, "[0, 90] deg")?;
        if ti > ALBEDO_PRODUCT_MAX_TI_RAD || self.sigma < ALBEDO_PRODUCT_MIN_SIGMA {
            return self.specular_albedo_adaptive(theta_i_rad, tol);
        }
        let omega_i = nalgebra::Vector3::new(ti.sin(), 0.0, ti.cos());
        let sky = crate::sky::UniformSky { radiance: 1.0 };
        let r = crate::slope::specular_skylight(self.eps, self.sigma, &sky, &omega_i, tol)?;
        if r.converged {
            return Ok(Integral {
                value: r.stokes.0[0],
                error: r.error,
                evaluations: r.evaluations,
                converged: true,
            });
        }
        let mut a = self.specular_albedo_adaptive(theta_i_rad, tol)?;
        a.evaluations += r.evaluations;
        Ok(a)
    }

    /// [`Microfacet::specular_albedo`] by the adaptive rule alone: Gauss-Kronrod over the
    /// slope's azimuth and along each line, split at the integrand's kinks; mirror symmetry
    /// about the plane of incidence halves the azimuth range.
    pub fn specular_albedo_adaptive(
        &self,
        theta_i_rad: f64,
        tol: Tolerance,
    ) -> Result<Integral, ModelError> {
        let ti = ModelError::check_range("theta_i", theta_i_rad, 0.0, FRAC_PI_2, "[0, 90] deg")?;
        let (sti, cti) = ti.sin_cos();
        let cti = cti.max(COS_FLOOR);
        let sigma = self.sigma;
        let eps = self.eps;
        // Polar slope coordinates rho = sigma sqrt(2) t: the Gaussian measure is 2 t exp(-t^2) dt
        // dpsi / (2 pi), smooth at t = 0 (a substitution through u = t^2 would leave a square-root
        // singularity there, since the integrand is linear in the slope near the origin).
        // Truncation at T: the neglected mass is exp(-T^2) and the integrand is at most 2.
        const T: f64 = 6.5;
        let truncation = 2.0 * (-T * T).exp();
        let f = |psi: f64, t: f64| -> f64 {
            let rho = sigma * std::f64::consts::SQRT_2 * t;
            let cp = psi.cos();
            // Facet normal h = (-x, -y, 1) / sqrt(1 + rho^2), slope (x, y) = rho (cos psi, sin psi).
            let inv = 1.0 / (1.0 + rho * rho).sqrt();
            let cos_alpha = inv;
            let cos_beta = (-rho * cp * sti + cti) * inv;
            if cos_beta <= 0.0 {
                return 0.0;
            }
            let cos_tr = 2.0 * cos_beta * cos_alpha - cti;
            if cos_tr <= 0.0 {
                return 0.0;
            }
            let r = amplitudes_eps(eps, cos_beta);
            let m00 = 0.5 * (r.rs_power() + r.rp_power());
            let g_cb_over_cti = (cos_beta / cti)
                .min(2.0 * cos_alpha)
                .min(2.0 * cos_alpha * cos_tr / cti);
            2.0 * t * (-t * t).exp() * m00 * g_cb_over_cti
        };
        // Kinks of the integrand along t at fixed psi, in slope rho (k = cos psi sin ti):
        // facet turning away (cos beta = 0): rho = cos ti / k; reflected ray at the horizon
        // (cos tr = 0): cos ti rho^2 + 2 k rho - cos ti = 0; the shadowing min switching
        // branches: rho = -cos ti / k (cos beta = 2 cos a cos ti) and rho = -k / cos ti
        // (cos tr = cos ti). The remaining switch (a cubic) is left to adaptivity.
        let breaks = |psi: f64, out: &mut Vec<f64>| {
            let k = psi.cos() * sti;
            let to_t = 1.0 / (sigma * std::f64::consts::SQRT_2);
            if k != 0.0 {
                out.push(cti / k * to_t);
                out.push(-cti / k * to_t);
            }
            out.push(-k / cti * to_t);
            out.push((-k + k.hypot(cti)) / cti * to_t);
        };
        let r = integrate_2d_split(f, (0.0, PI), (0.0, T), breaks, tol.scaled(PI));
        Ok(Integral {
            value: r.value / PI,
            error: r.error / PI + truncation,
            ..r
        })
    }
}

/// The polarising term of the vegetation model (Eq. 3.19, after Bréon et al. 1995 and
/// Maignan et al. 2009): leaves of uniformly distributed inclination reflect specularly at their
/// surface (index `n`), giving `rho_p = Fp / (4 (cos ti + cos tr))` with `Fp = 0.5 (Rs - Rp)` at the
/// scattering half angle. Meng (2012)'s text says the full pBRDF follows by replacing `Fp` with the
/// Mueller matrix of Eq. 3.5; that is what [`VegetationLobe::specular`] returns (rotated into the
/// surface frames like the microfacet term), so its `f10` in the facet frame is exactly `rho_p`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VegetationLobe {
    index: RefractiveIndex,
    eps: Complex64,
}

impl VegetationLobe {
    /// A vegetation lobe for the leaf-surface index (Meng (2012)'s Table 3.2 uses n = 1.5).
    pub fn new(index: RefractiveIndex) -> Self {
        VegetationLobe {
            index,
            eps: index.permittivity(),
        }
    }

    /// The refractive index.
    pub fn index(&self) -> RefractiveIndex {
        self.index
    }

    /// `R(-eta_r) M(beta) R(eta_i) / (4 (cos ti + cos tr))`, sr^-1.
    #[inline]
    pub fn specular(&self, g: &Geometry) -> Mueller {
        let fg = FacetGeometry::new(g);
        Mueller(fg.rotated_fresnel(self.eps) * (0.25 / (g.cos_ti + g.cos_tr)))
    }

    /// `int f00 cos tr dOmega_r` of the polarising term over the hemisphere, integrated over
    /// `(phi, cos tr)` (the integrand is smooth and bounded by 1/4).
    pub fn specular_albedo(
        &self,
        theta_i_rad: f64,
        tol: Tolerance,
    ) -> Result<Integral, ModelError> {
        let ti = ModelError::check_range("theta_i", theta_i_rad, 0.0, FRAC_PI_2, "[0, 90] deg")?;
        let (sti, cti) = ti.sin_cos();
        let cti = cti.max(COS_FLOOR);
        let eps = self.eps;
        let f = |phi: f64, mu: f64| -> f64 {
            let str_ = (1.0 - mu * mu).max(0.0).sqrt();
            let cos_2beta = cti * mu + sti * str_ * phi.cos();
            let cos_beta = (0.5 * (1.0 + cos_2beta)).max(0.0).sqrt();
            let r = amplitudes_eps(eps, cos_beta);
            0.5 * (r.rs_power() + r.rp_power()) * mu / (4.0 * (cti + mu))
        };
        let r = integrate_2d(f, (0.0, PI), (0.0, 1.0), tol.scaled(0.5 * PI));
        Ok(Integral {
            value: 2.0 * r.value,
            error: 2.0 * r.error,
            ..r
        })
    }
}

/// `80 deg`: incidence further from the normal than this takes the adaptive specular albedo.
/// At 85 deg and 1e-9 the product rule's ladder did not converge (its adaptive fallback took
/// 3.5x the adaptive rule's evaluations), and at 89.9 deg (sigma 0.3) that fallback and the
/// adaptive rule differed by 3x the sum of their errors (5e-9), which one off not settled.
pub const ALBEDO_PRODUCT_MAX_TI_RAD: f64 = 80.0 * std::f64::consts::PI / 180.0;

/// Lobes smoother than this take the adaptive specular albedo: the adaptive rule needs few
/// points on a narrow lobe (1125 evaluations at sigma 0.02, 0-60 deg, 1e-6 against the
/// product rule's 1016-7896), where the product rule's azimuth levels gain nothing.
pub const ALBEDO_PRODUCT_MIN_SIGMA: f64 = 0.2;

/// Warning raised when the specular lobe alone reflects more than the material's DHR, so the
/// diffuse term of Eq. 3.18 would be negative and is clamped to 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiffuseClamped {
    /// The material's directional-hemispherical reflectance.
    pub dhr: f64,
    /// The specular albedo that exceeded it.
    pub specular_albedo: f64,
}

impl std::fmt::Display for DiffuseClamped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "specular albedo {:.6} exceeds DHR {:.6}: diffuse term f00_d clamped to 0 (Eq. 3.18)",
            self.specular_albedo, self.dhr
        )
    }
}

/// The unpolarised diffuse term for one incidence angle (Eqs. 3.16-3.18).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiffuseTerm {
    /// `f00_d`, sr^-1 (the only non-zero element of `Fd`).
    pub f00: f64,
    /// The specular albedo and its quadrature error.
    pub specular_albedo: Integral,
    /// Set when `f00_d` was clamped at 0.
    pub clamped: Option<DiffuseClamped>,
}

/// A reflecting surface: one of Meng (2012)'s two pBRDF models.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Surface {
    /// Microfacet specular lobe plus a Lambertian term from the DHR (Eqs. 3.4-3.18).
    Microfacet {
        /// The specular lobe.
        lobe: Microfacet,
        /// Directional-hemispherical reflectance in `[0, 1]`, taken as independent of `ti`.
        dhr: f64,
    },
    /// Vegetation (Eq. 3.19) plus a given unpolarised diffuse `f00_d`.
    Vegetation {
        /// The leaf-surface polarising term.
        lobe: VegetationLobe,
        /// `f00_d` in sr^-1, `[0, 1/pi]` (Meng (2012)'s Table 3.2: `0.04/pi`).
        f00_diffuse: f64,
    },
}

/// A full evaluation: Mueller matrix, DoLP for unpolarised light, and the diffuse bookkeeping.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Evaluation {
    /// `F = Fs + Fd`, sr^-1, incident surface frame -> reflected surface frame.
    pub f: Mueller,
    /// DoLP of the reflected light for unpolarised illumination (Eq. 3.20).
    pub dolp: f64,
    /// The diffuse term used.
    pub diffuse: DiffuseTerm,
}

impl Surface {
    /// A microfacet surface; errors name `sigma` or `dhr`.
    pub fn microfacet(index: RefractiveIndex, sigma: f64, dhr: f64) -> Result<Self, ModelError> {
        let lobe = Microfacet::new(index, sigma)?;
        let dhr = ModelError::check_range("dhr", dhr, 0.0, 1.0, "[0, 1]")?;
        Ok(Surface::Microfacet { lobe, dhr })
    }

    /// A vegetation surface; errors name `f00_diffuse`.
    pub fn vegetation(index: RefractiveIndex, f00_diffuse: f64) -> Result<Self, ModelError> {
        let f00_diffuse =
            ModelError::check_range("f00_diffuse", f00_diffuse, 0.0, 1.0 / PI, "[0, 1/pi]")?;
        Ok(Surface::Vegetation {
            lobe: VegetationLobe::new(index),
            f00_diffuse,
        })
    }

    /// The specular (polarising) part, surface frames in and out.
    #[inline]
    pub fn specular(&self, g: &Geometry) -> Mueller {
        match self {
            Surface::Microfacet { lobe, .. } => lobe.specular(g),
            Surface::Vegetation { lobe, .. } => lobe.specular(g),
        }
    }

    /// The diffuse term at incidence `theta_i_rad`, with the specular albedo integrated to `tol`.
    pub fn diffuse(&self, theta_i_rad: f64, tol: Tolerance) -> Result<DiffuseTerm, ModelError> {
        match *self {
            Surface::Microfacet { lobe, dhr } => {
                let a = lobe.specular_albedo(theta_i_rad, tol)?;
                let raw = (dhr - a.value) / PI;
                Ok(DiffuseTerm {
                    f00: raw.max(0.0),
                    specular_albedo: a,
                    clamped: (raw < 0.0).then_some(DiffuseClamped {
                        dhr,
                        specular_albedo: a.value,
                    }),
                })
            }
            Surface::Vegetation { lobe, f00_diffuse } => Ok(DiffuseTerm {
                f00: f00_diffuse,
                specular_albedo: lobe.specular_albedo(theta_i_rad, tol)?,
                clamped: None,
            }),
        }
    }

    /// `F = Fs + Fd` with a precomputed diffuse term (the hot path: one diffuse term serves every
    /// view direction under the same illumination).
    #[inline]
    pub fn mueller_with(&self, g: &Geometry, diffuse: &DiffuseTerm) -> Mueller {
        let mut f = self.specular(g);
        f.0[(0, 0)] += diffuse.f00;
        f
    }

    /// Full evaluation at one geometry (integrates the diffuse term: use [`Surface::mueller_with`]
    /// in loops).
    pub fn evaluate(
        &self,
        theta_i_rad: f64,
        theta_r_rad: f64,
        phi_rad: f64,
        tol: Tolerance,
    ) -> Result<Evaluation, ModelError> {
        let g = Geometry::from_angles(theta_i_rad, theta_r_rad, phi_rad)?;
        let diffuse = self.diffuse(theta_i_rad, tol)?;
        let f = self.mueller_with(&g, &diffuse);
        // f00 > 0 always: the Fresnel M00 > 0 for Re N > 0 unless the lobe underflows and the
        // diffuse term is 0, in which case the light is reported unpolarised.
        let dolp = f.dolp_unpolarized().unwrap_or(0.0);
        Ok(Evaluation { f, dolp, diffuse })
    }
}
