//! The scattering geometry of the pBRDF, in the frames of [`crate::pbrdf`]'s module docs: a
//! validated pair of incident and view directions with their trigonometry, and the microfacet
//! that reflects one into the other (half angle, tilt, and the rotations of the two surface
//! frames into the facet frame).

use crate::angles::sin_cos_deg;
use crate::error::ModelError;
use crate::fresnel::amplitudes_eps;
use crate::polarization::cos_sin_2eta;
use nalgebra::{Matrix3, Vector3};
use num_complex::Complex64;
use std::f64::consts::{FRAC_PI_2, PI};

/// Smallest `cos theta` used anywhere: `cos(pi/2)` as f64 evaluates it.
pub const COS_FLOOR: f64 = 6.123_233_995_736_766e-17;

/// A validated scattering geometry with its trigonometry precomputed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geometry {
    pub(crate) cos_ti: f64,
    pub(crate) sin_ti: f64,
    pub(crate) cos_tr: f64,
    pub(crate) sin_tr: f64,
    pub(crate) cos_phi: f64,
    pub(crate) sin_phi: f64,
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
    /// Half vector, tilt and signed frame rotations for a geometry (see [`crate::pbrdf`]'s module docs).
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

/// The reflected ray's surface-frame `x` (s vector) in world coordinates, with the degenerate
/// cases resolved exactly as [`Geometry::from_directions`] does: at normal view the relative
/// azimuth is 0, so `s_r` is minus the turned frame's y axis (world `-y` turned by the sun's
/// horizontal direction; world `(0, -1, 0)` with the sun at the zenith too).
pub fn reflected_frame_x(omega_sun: &Vector3<f64>, omega_view: &Vector3<f64>) -> Vector3<f64> {
    let c = omega_view.cross(&Vector3::z());
    let n = c.norm();
    if n > 0.0 {
        return c / n;
    }
    // Normal view. from_directions turns the pair so omega_i has azimuth 0 about z, with
    // (ca, sa) the unit horizontal of omega_i (or (1, 0)), and uses phi = 0: s_r = (0, -1, 0) in
    // the turned frame, whose y axis in world coordinates is (-sa, ca, 0).
    let h = (omega_sun.x * omega_sun.x + omega_sun.y * omega_sun.y).sqrt();
    let (ca, sa) = if h > 0.0 {
        (omega_sun.x / h, omega_sun.y / h)
    } else {
        (1.0, 0.0)
    };
    Vector3::new(sa, -ca, 0.0)
}
