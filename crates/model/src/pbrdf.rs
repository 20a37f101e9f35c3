//! Polarimetric BRDF: the microfacet model of seed Sec. 3.1.1 (Eqs. 3.4-3.18) and the vegetation
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
//! product. The seed's arc-cosine forms (Eqs. 3.9-3.10) lose the sign and are 0/0 at normal
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
use crate::polarization::{cos_sin_2eta, Mueller};
use crate::quadrature::{integrate_2d, integrate_2d_split, Integral, Tolerance};
use nalgebra::{Matrix3, Vector3};
use num_complex::Complex64;
use std::f64::consts::{FRAC_PI_2, PI};

/// Smallest `cos theta` used anywhere: `cos(pi/2)` as f64 evaluates it.
pub const COS_FLOOR: f64 = 6.123_233_995_736_766e-17;
/// Smallest roughness accepted (slope standard deviation).
pub const SIGMA_MIN: f64 = 1e-6;
/// Largest roughness accepted.
pub const SIGMA_MAX: f64 = 10.0;

/// A validated scattering geometry with its trigonometry precomputed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    cos_ti: f64,
    sin_ti: f64,
    cos_tr: f64,
    sin_tr: f64,
    cos_phi: f64,
    sin_phi: f64,
}

impl Geometry {
    /// Builds a geometry from incident zenith, view zenith (both `[0, pi/2]`) and relative azimuth
    /// (`[-2 pi, 2 pi]`), radians. Errors name `theta_i`, `theta_r` or `phi` with the range in
    /// degrees.
    pub fn from_angles(
        theta_i_rad: f64,
        theta_r_rad: f64,
        phi_rad: f64,
    ) -> Result<Self, ModelError> {
        let ti = ModelError::check_range("theta_i", theta_i_rad, 0.0, FRAC_PI_2, "[0, 90] deg")?;
        let tr = ModelError::check_range("theta_r", theta_r_rad, 0.0, FRAC_PI_2, "[0, 90] deg")?;
        let phi = ModelError::check_range("phi", phi_rad, -2.0 * PI, 2.0 * PI, "[-360, 360] deg")?;
        let (sin_ti, cos_ti) = ti.sin_cos();
        let (sin_tr, cos_tr) = tr.sin_cos();
        let (sin_phi, cos_phi) = phi.sin_cos();
        Ok(Geometry {
            cos_ti: cos_ti.max(COS_FLOOR),
            sin_ti,
            cos_tr: cos_tr.max(COS_FLOOR),
            sin_tr,
            cos_phi,
            sin_phi,
        })
    }

    /// [`Geometry::from_angles`] in degrees; errors name `theta_i_deg`, `theta_r_deg`, `phi_deg`.
    pub fn from_deg(theta_i_deg: f64, theta_r_deg: f64, phi_deg: f64) -> Result<Self, ModelError> {
        let rename = |e: ModelError, field: &'static str| match e {
            ModelError::OutOfRange { value, allowed, .. } => ModelError::OutOfRange {
                field,
                value: value.to_degrees(),
                allowed,
            },
            other => other,
        };
        for (field, v) in [
            ("theta_i_deg", theta_i_deg),
            ("theta_r_deg", theta_r_deg),
            ("phi_deg", phi_deg),
        ] {
            if !v.is_finite() {
                return Err(ModelError::OutOfRange {
                    field,
                    value: v,
                    allowed: if field == "phi_deg" {
                        "[-360, 360]"
                    } else {
                        "[0, 90]"
                    },
                });
            }
        }
        let mut g = Geometry::from_angles(
            theta_i_deg.to_radians(),
            theta_r_deg.to_radians(),
            phi_deg.to_radians(),
        )
        .map_err(|e| match &e {
            ModelError::OutOfRange {
                field: "theta_i", ..
            } => rename(e, "theta_i_deg"),
            ModelError::OutOfRange {
                field: "theta_r", ..
            } => rename(e, "theta_r_deg"),
            ModelError::OutOfRange { field: "phi", .. } => rename(e, "phi_deg"),
            _ => e,
        })?;
        // Exact trigonometry at multiples of 90 deg, so that 90 deg is exactly grazing and
        // 180 deg exactly in the plane of incidence (sin(pi) in radians is 1.2e-16, which at
        // grazing incidence is as large as cos theta itself).
        let (sin_ti, cos_ti) = sin_cos_deg(theta_i_deg);
        let (sin_tr, cos_tr) = sin_cos_deg(theta_r_deg);
        let (sin_phi, cos_phi) = sin_cos_deg(phi_deg);
        g.sin_ti = sin_ti;
        g.cos_ti = cos_ti.max(COS_FLOOR);
        g.sin_tr = sin_tr;
        g.cos_tr = cos_tr.max(COS_FLOOR);
        g.sin_phi = sin_phi;
        g.cos_phi = cos_phi;
        Ok(g)
    }

    /// Builds a geometry from unit direction vectors in the surface frame (normal `+z`), without
    /// trigonometry: the towards-source `omega_i` and towards-sensor `omega_r`. The pair is turned
    /// about the normal so that `omega_i` has azimuth 0. Both must be unit vectors (to 1e-9) with
    /// `z >= 0`; errors name `omega_i` or `omega_r`. At exactly normal incidence the incident
    /// azimuth is taken as 0, at exactly normal view the relative azimuth as 0 (the frame limits
    /// of the module docs).
    pub fn from_directions(
        omega_i: &Vector3<f64>,
        omega_r: &Vector3<f64>,
    ) -> Result<Self, ModelError> {
        for (field, v) in [("omega_i", omega_i), ("omega_r", omega_r)] {
            let n2 = v.norm_squared();
            if !(n2.is_finite() && (n2 - 1.0).abs() <= 2e-9 && v.z >= 0.0) {
                return Err(ModelError::Invalid {
                    field,
                    reason: format!(
                        "({}, {}, {}) must be a unit vector (|v| = 1 within 1e-9) with z >= 0",
                        v.x, v.y, v.z
                    ),
                });
            }
        }
        // Unit vectors: no overflow, so a plain square root (hypot is several times slower).
        let sin_ti = (omega_i.x * omega_i.x + omega_i.y * omega_i.y).sqrt();
        let (ca, sa) = if sin_ti > 0.0 {
            (omega_i.x / sin_ti, omega_i.y / sin_ti)
        } else {
            (1.0, 0.0)
        };
        let x = ca * omega_r.x + sa * omega_r.y;
        let y = -sa * omega_r.x + ca * omega_r.y;
        let sin_tr = (x * x + y * y).sqrt();
        let (cos_phi, sin_phi) = if sin_tr > 0.0 {
            (x / sin_tr, y / sin_tr)
        } else {
            (1.0, 0.0)
        };
        Ok(Geometry {
            cos_ti: omega_i.z.clamp(COS_FLOOR, 1.0),
            sin_ti: sin_ti.min(1.0),
            cos_tr: omega_r.z.clamp(COS_FLOOR, 1.0),
            sin_tr: sin_tr.min(1.0),
            cos_phi,
            sin_phi,
        })
    }

    /// The relative azimuth `phi` in `[0, 2 pi)` (0 at normal view, where it is undefined).
    pub fn relative_azimuth_rad(&self) -> f64 {
        self.sin_phi.atan2(self.cos_phi).rem_euclid(2.0 * PI)
    }

    /// `cos ti` (floored at [`COS_FLOOR`]).
    pub fn cos_theta_i(&self) -> f64 {
        self.cos_ti
    }

    /// `cos tr` (floored at [`COS_FLOOR`]).
    pub fn cos_theta_r(&self) -> f64 {
        self.cos_tr
    }

    /// Unit towards-source direction `omega_i`.
    pub fn omega_i(&self) -> Vector3<f64> {
        Vector3::new(self.sin_ti, 0.0, self.cos_ti)
    }

    /// Unit towards-sensor direction `omega_r`.
    pub fn omega_r(&self) -> Vector3<f64> {
        Vector3::new(
            self.sin_tr * self.cos_phi,
            self.sin_tr * self.sin_phi,
            self.cos_tr,
        )
    }
}

/// `(sin, cos)` of an angle in degrees, exact at every multiple of 90 deg: the argument is reduced
/// to `[-45, 45]` deg in degrees (exact in f64 for `|x| <= 720`) before converting to radians.
pub fn sin_cos_deg(x_deg: f64) -> (f64, f64) {
    let q = (x_deg / 90.0).round();
    let r = (x_deg - 90.0 * q).to_radians();
    let (s, c) = r.sin_cos();
    match (q as i64).rem_euclid(4) {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// The facet geometry of one evaluation: half angle, tilt and the two frame rotations.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FacetGeometry {
    /// `cos beta`, half the angle between `omega_i` and `omega_r` (Eq. 3.6).
    pub cos_beta: f64,
    /// `cos alpha`, tilt of the facet normal from the surface normal (Eq. 3.11).
    pub cos_alpha: f64,
    /// `tan^2 alpha`, computed from the half vector's components (accurate near `alpha = 0`).
    pub tan2_alpha: f64,
    /// `(cos 2 eta_i, sin 2 eta_i)`: incident surface frame -> facet frame.
    pub rot_i: (f64, f64),
    /// `(cos 2 eta_r, sin 2 eta_r)`: reflected surface frame -> facet frame.
    pub rot_r: (f64, f64),
}

impl FacetGeometry {
    /// Half vector, tilt and signed frame rotations for a geometry (see the module docs).
    pub fn new(g: &Geometry) -> Self {
        let s_i = Vector3::new(0.0, 1.0, 0.0);
        let s_r = Vector3::new(g.sin_phi, -g.cos_phi, 0.0);
        FacetGeometry::from_frames(&g.omega_i(), &g.omega_r(), &s_i, &s_r)
    }

    /// The facet geometry of unit directions `omega_i`, `omega_r` (`z > 0`) whose incident and
    /// reflected surface frames have the horizontal vectors `s_i` and `s_r`.
    fn from_frames(
        omega_i: &Vector3<f64>,
        omega_r: &Vector3<f64>,
        s_i: &Vector3<f64>,
        s_r: &Vector3<f64>,
    ) -> Self {
        let sum = omega_i + omega_r;
        // |sum| >= sum.z >= 2 COS_FLOOR > 0, so the half vector is always defined.
        let len = sum.norm();
        let h = sum / len;
        let cos_beta = (0.5 * len).min(1.0);
        let cos_alpha = h.z;
        let tan2_alpha = (h.x * h.x + h.y * h.y) / (h.z * h.z);
        let k_i = -omega_i;
        let k_r = *omega_r;
        // k_i × h is proportional to omega_r × omega_i.
        let cross = omega_r.cross(omega_i);
        let cross_norm = cross.norm();
        let s_f = if cross_norm > 0.0 {
            cross / cross_norm
        } else {
            *s_i
        };
        FacetGeometry {
            cos_beta,
            cos_alpha,
            tan2_alpha,
            rot_i: cos_sin_2eta(s_i, &s_f, &k_i),
            rot_r: cos_sin_2eta(s_r, &s_f, &k_r),
        }
    }

    /// [`FacetGeometry::new`] of `Geometry::from_directions(omega_i, omega_r)`, computed from
    /// the world-frame directions (unit, `z >= 0`, not checked) without the detour through the
    /// incident plane's frame: the half vector, tilt and cross product are invariant under the
    /// azimuthal rotation to that frame, and its frame vectors are, in the world frame,
    /// `s_i = (-sin a_i, cos a_i, 0)` and `s_r = (sin a_r, -cos a_r, 0)` (`a` the azimuths; at
    /// the zenith the same defaults as [`Geometry::from_directions`]). Equal to it up to
    /// rounding; for integrands that call it millions of times.
    pub fn from_world(omega_i: &Vector3<f64>, omega_r: &Vector3<f64>) -> Self {
        let oi = Vector3::new(omega_i.x, omega_i.y, omega_i.z.clamp(COS_FLOOR, 1.0));
        let or = Vector3::new(omega_r.x, omega_r.y, omega_r.z.clamp(COS_FLOOR, 1.0));
        let sin_ti = (oi.x * oi.x + oi.y * oi.y).sqrt();
        let (ca, sa) = if sin_ti > 0.0 {
            (oi.x / sin_ti, oi.y / sin_ti)
        } else {
            (1.0, 0.0)
        };
        let s_i = Vector3::new(-sa, ca, 0.0);
        let x = ca * or.x + sa * or.y;
        let y = -sa * or.x + ca * or.y;
        let sin_tr = (x * x + y * y).sqrt();
        let s_r = if sin_tr > 0.0 {
            Vector3::new(or.y / sin_tr, -or.x / sin_tr, 0.0)
        } else {
            Vector3::new(sa, -ca, 0.0)
        };
        FacetGeometry::from_frames(&oi, &or, &s_i, &s_r)
    }

    /// [`FacetGeometry::from_world`] for an integrand that already has the unit half vector
    /// `h` and `cos_beta = omega_r . h`: the frames' horizontal vectors are left unnormalised
    /// (`s_i ∝ (-omega_i.y, omega_i.x, 0)`, `s_r ∝ (omega_r.y, -omega_r.x, 0)`, the facet's
    /// `∝ omega_r × omega_i`), since [`cos_sin_2eta`] is invariant to their scale. That saves
    /// `from_world`'s three square roots and their divisions; the result equals it up to
    /// rounding (for `z >= COS_FLOOR`; tested).
    pub(crate) fn from_half_vector(
        omega_i: &Vector3<f64>,
        omega_r: &Vector3<f64>,
        h: &Vector3<f64>,
        cos_beta: f64,
    ) -> Self {
        let s_i = if omega_i.x != 0.0 || omega_i.y != 0.0 {
            Vector3::new(-omega_i.y, omega_i.x, 0.0)
        } else {
            Vector3::new(0.0, 1.0, 0.0)
        };
        let s_r = if omega_r.x != 0.0 || omega_r.y != 0.0 {
            Vector3::new(omega_r.y, -omega_r.x, 0.0)
        } else {
            // `from_world` at the zenith: from the incident frame's azimuth.
            -s_i
        };
        let cross = omega_r.cross(omega_i);
        // Tiny but non-zero, its squares would underflow in `cos_sin_2eta`.
        let s_f = if cross.norm_squared() > 1e-200 {
            cross
        } else {
            s_i
        };
        FacetGeometry {
            cos_beta: cos_beta.min(1.0),
            cos_alpha: h.z,
            tan2_alpha: (h.x * h.x + h.y * h.y) / (h.z * h.z),
            rot_i: cos_sin_2eta(&s_i, &s_f, &-omega_i),
            rot_r: cos_sin_2eta(&s_r, &s_f, omega_r),
        }
    }

    /// `R(-eta_r) M(beta) R(eta_i)` (Eq. 3.7) for the facet Mueller matrix of Eq. 3.5 with
    /// permittivity `eps`, expressed in the incident and reflected surface frames.
    pub fn rotated_fresnel(&self, eps: Complex64) -> Matrix3<f64> {
        let r = amplitudes_eps(eps, self.cos_beta);
        let (rs2, rp2) = (r.rs_power(), r.rp_power());
        let a = 0.5 * (rs2 + rp2);
        let b = 0.5 * (rs2 - rp2);
        let d = r.re_rs_rp_conj();
        let (ci, si) = self.rot_i;
        let (cr, sr) = self.rot_r;
        // M R(eta_i) = [[a, b ci, b si], [b, a ci, a si], [0, -d si, d ci]], then R(-eta_r) on the left.
        Matrix3::new(
            a,
            b * ci,
            b * si, //
            cr * b,
            cr * a * ci + sr * d * si,
            cr * a * si - sr * d * ci, //
            sr * b,
            sr * a * ci - cr * d * si,
            sr * a * si + cr * d * ci,
        )
    }
}

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
    /// rule of [`crate::skylight::specular_skylight`] on this same slope-space integrand, whose
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
        let sky = crate::skylight::UniformSky { radiance: 1.0 };
        let r = crate::skylight::specular_skylight(self.eps, self.sigma, &sky, &omega_i, tol)?;
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
/// scattering half angle. The seed's text says the full pBRDF follows by replacing `Fp` with the
/// Mueller matrix of Eq. 3.5; that is what [`VegetationLobe::specular`] returns (rotated into the
/// surface frames like the microfacet term), so its `f10` in the facet frame is exactly `rho_p`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VegetationLobe {
    index: RefractiveIndex,
    eps: Complex64,
}

impl VegetationLobe {
    /// A vegetation lobe for the leaf-surface index (the seed's Table 3.2 uses n = 1.5).
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

/// A reflecting surface: one of the seed's two pBRDF models.
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
        /// `f00_d` in sr^-1, `[0, 1/pi]` (the seed's Table 3.2: `0.04/pi`).
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
