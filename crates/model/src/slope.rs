//! The specular lobe of a microfacet surface against a sky, integrated in facet-slope space: the
//! quadrature that the specular albedo ([`crate::pbrdf::Microfacet::specular_albedo`], a uniform
//! sky) and the reflected skylight ([`crate::skylight`], Meng (2012) Eq. 3.22) share.
//!
//! The specular lobe of a smooth surface is narrow, so it is integrated over facet slopes rather
//! than over sky directions: for a fixed view `omega_v`, each facet normal `h` reflects exactly
//! one sky direction `omega_d = 2 (omega_v . h) h - omega_v`, `dOmega_d = 4 (omega_v . h)
//! dOmega_h`, and the Gaussian slope measure absorbs the lobe, so the cost does not grow as
//! `sigma -> 0` (`sigma = 0.05` costs what `sigma = 0.5` does).
//!
//! In polar slope coordinates `(psi, t)` the integrand is smooth between known curves: the
//! reflected ray's horizon (the support ends there), the shadowing term's branch switches (a
//! line, a circle and a cubic that `rho = tan x` turns into `tan 3x = cos theta_v / k`), and
//! the azimuths where `k = cos psi sin theta_v` is `0` or `-cos theta_v` (where the switches
//! enter a line or meet). A product Gauss-Legendre rule on the smooth pieces converges
//! geometrically; the sky's peak (the sun's aureole) is one more split in both directions. It
//! needs a fraction of the adaptive rule's evaluations, and the adaptive rule remains the
//! fallback (docs/design/scene-quadrature.md). The rule's levels (`ladder`) may start above
//! the first, for rays next to one whose level is known, or after a `LevelPair` of the same
//! ray. Every result carries the quadrature's error estimate and evaluation count.

use crate::error::ModelError;
use crate::fresnel::{amplitudes_eps, real_amplitudes};
use crate::geometry::{FacetGeometry, COS_FLOOR};
use crate::polarization::Stokes;
use crate::quadrature::{
    gauss_legendre_table, integrate_periodic_split_n, max_abs, IntegralN, Tolerance,
};
use crate::sky::SkyRadiance;
use nalgebra::Vector3;
use std::f64::consts::PI;

/// The (unnormalised) `x` axis of the reflected surface frame of a view `omega_view`,
/// `(omega_v.y, -omega_v.x, 0)`. At the zenith, where the view alone defines no frame, the
/// frame the field's tiles take ([`crate::geometry::reflected_frame_x`], the convention of
/// `Geometry::from_directions` at normal view) with the sky's `peak` as the sun (the zenith
/// without one): one frame for every incident ray, so that the hemisphere integral adds
/// Stokes vectors in the same frame. (`FacetGeometry::from_half_vector`'s frame at the zenith
/// follows each incident ray; integrated, it gave a glass plate seen at nadir under a zenith
/// sun a spurious DoLP of 4.7 %.)
fn reflected_frame_x(omega_view: &Vector3<f64>, peak: Option<Vector3<f64>>) -> Vector3<f64> {
    if omega_view.x != 0.0 || omega_view.y != 0.0 {
        Vector3::new(omega_view.y, -omega_view.x, 0.0)
    } else {
        crate::geometry::reflected_frame_x(&peak.unwrap_or_else(Vector3::z), omega_view)
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
    /// The product rule's accepted level (an index into its levels, from 0), `None` when an
    /// adaptive rule gave the answer: where a ray next to this one may start
    /// ([`reflected_skylight`](crate::skylight::reflected_skylight)'s `start_level`).
    pub level: Option<usize>,
}

/// Checks a view direction: unit (to 1e-9) and not below the horizon. Errors name `omega_view`.
pub(crate) fn check_view(omega_view: &Vector3<f64>) -> Result<(), ModelError> {
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

/// The slope-space integrand of [`specular_skylight`] for one view: `value(psi, t)` is the
/// reflected Stokes vector's density over the facet slope `rho (cos psi, sin psi)`,
/// `rho = sigma sqrt(2) t`, in the measure `dpsi dt` (the Gaussian slope weight
/// `2 t exp(-t^2) / (2 pi)` included).
pub(crate) struct SlopeIntegrand<'a, S: SkyRadiance + ?Sized> {
    eps: num_complex::Complex64,
    sky: &'a S,
    omega_view: Vector3<f64>,
    /// `cos theta_v`, floored at [`COS_FLOOR`].
    cv: f64,
    /// `1 / cv`.
    inv_cv: f64,
    /// `sin theta_v`.
    sv: f64,
    /// Unit horizontal vector towards the view's azimuth (x at nadir); `e2 = z x e1`.
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    /// The facet slope that reflects the sky's peak into the view, as `(psi, t)`.
    peak: Option<(f64, f64)>,
    /// The view's reflected surface frame.
    s_r: ReflectedFrame,
    /// `rho / t = sigma sqrt(2)`.
    rho_per_t: f64,
    /// `omega_view × z` and its components along the reflected frame's `x` and `y`: the
    /// facet frame's `x` is `omega_view × h ∝ omega_view × z - rho omega_view × along`
    /// ([`SlopeLine`]).
    view_cross_z: Vector3<f64>,
    view_cross_z_r: (f64, f64),
    /// `Re eps` of a dielectric with `eps >= 1` (no total internal reflection at any angle:
    /// [`real_amplitudes`] holds for every facet), whose Fresnel terms the batch computes in
    /// vector loops; `None` for any other surface.
    real_eps: Option<f64>,
}

/// [`SlopeIntegrand::point`]: one point's geometry. On the integrand's support when
/// `cos_beta > 0` and `cos_d > 0`.
pub(crate) struct SlopePoint {
    /// `1 / sqrt(1 + rho^2)`, the half vector's `z`.
    inv_n: f64,
    cos_beta: f64,
    /// `omega_d.z`.
    cos_d: f64,
    /// The reflected (incident sky) direction.
    omega_d: Vector3<f64>,
    /// The shadowing term times `cos beta / cos theta_v`.
    g: f64,
    /// The facet frame's `x` (unnormalised) and its components along the reflected frame's `x`
    /// and `y`.
    s_f: Vector3<f64>,
    c: f64,
    sn: f64,
}

/// The terms of one line of [`SlopeIntegrand`] (slope azimuth `psi`) that do not change along
/// it: with `along` the line's unit horizontal direction and `rho` the slope, the unnormalised
/// half vector is `z - rho along` (of squared length `1 + rho^2`), so `cos beta =
/// (cos theta_v - rho omega_view . along) / sqrt(1 + rho^2)` and the facet frame's `x`,
/// `omega_view × omega_d = 2 cos beta / sqrt(1 + rho^2) (omega_view × z - rho omega_view ×
/// along)`, is a linear function of `rho` up to a positive scale, which no frame rotation sees.
pub(crate) struct SlopeLine {
    pub(crate) along: Vector3<f64>,
    /// `omega_view . along`.
    pub(crate) view_along: f64,
    /// `omega_view × along` and its components along the reflected frame's `x` and `y`.
    pub(crate) view_cross_along: Vector3<f64>,
    pub(crate) view_cross_along_r: (f64, f64),
}

/// `w R(-eta_r) M(beta) S_f` (Eqs. 3.5 and 3.7) for a sky Stokes vector `s_f` already in the
/// facet frame (`x ∝ s_f_x = omega_r × omega_i`, from [`SkyRadiance::stokes_in_frame`]), out
/// in the reflected surface frame `r` ([`ReflectedFrame`]), `M(beta)` applied by its four
/// distinct entries: what `FacetGeometry::rotated_fresnel(eps) * stokes_from(..) * w`
/// computes, without the incident surface frame, `R(eta_i)` or the 3 x 3 product (equal up to
/// rounding; tested).
#[inline]
pub(crate) fn facet_reflection(
    eps: num_complex::Complex64,
    cos_beta: f64,
    s_f: &Stokes,
    s_f_x: &Vector3<f64>,
    r: &ReflectedFrame,
    w: f64,
) -> [f64; 3] {
    // `cos_sin_2eta(s_r, s_f_x, omega_r)` with one division, its scale folded into `w`'s:
    // `(s_r × s_f_x) . omega_r = s_f_x . (omega_r × s_r)`, the frame's `y` computed once.
    facet_reflection_cs(eps, cos_beta, s_f, r.x.dot(s_f_x), r.y.dot(s_f_x), w)
}

/// [`facet_reflection`] with the facet frame's `x` given by its components `(c, sn)` along the
/// reflected frame's `x` and `y` (of any common scale): the slope integrand has them as linear
/// functions of the slope along each line ([`SlopeLine`]).
#[inline(always)]
fn facet_reflection_cs(
    eps: num_complex::Complex64,
    cos_beta: f64,
    s_f: &Stokes,
    c: f64,
    sn: f64,
    w: f64,
) -> [f64; 3] {
    let (rs2, rp2, d) = match real_amplitudes(eps, cos_beta.min(1.0)) {
        Some((rs, rp)) => (rs * rs, rp * rp, rs * rp),
        None => {
            let f = amplitudes_eps(eps, cos_beta.min(1.0));
            (f.rs_power(), f.rp_power(), f.re_rs_rp_conj())
        }
    };
    reflected_stokes((rs2, rp2, d), &s_f.0.into(), c, sn, w)
}

/// `w R(-eta_r) M(beta) S_f` from the Fresnel terms `(|rs|^2, |rp|^2, Re(rs rp*))`: `M(beta)`
/// (Eq. 3.5) by its four distinct entries, then the rotation from the facet frame `(c, sn)`
/// ([`facet_reflection_cs`]) into the reflected frame with one division, its scale folded into
/// `w`'s. Branch-free (a zero frame gives zero polarisation), so that [`reflect_batch`]'s loop
/// vectorises.
#[inline(always)]
fn reflected_stokes(
    (rs2, rp2, d): (f64, f64, f64),
    s: &[f64; 3],
    c: f64,
    sn: f64,
    w: f64,
) -> [f64; 3] {
    let (a, b) = (0.5 * (rs2 + rp2), 0.5 * (rs2 - rp2));
    let (y0, y1, y2) = (a * s[0] + b * s[1], b * s[0] + a * s[1], d * s[2]);
    let r2 = c * c + sn * sn;
    let scale = if r2 > 0.0 { w / r2 } else { 0.0 };
    let (cr, sr) = (c * c - sn * sn, 2.0 * c * sn);
    [
        y0 * w,
        (cr * y1 - sr * y2) * scale,
        (sr * y1 + cr * y2) * scale,
    ]
}

/// The reflected surface frame of a view `omega_r`: `x` from [`reflected_frame_x`] and
/// `y = omega_r × x` (both of the same length), fixed for every incident ray of the view.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ReflectedFrame {
    pub(crate) x: Vector3<f64>,
    pub(crate) y: Vector3<f64>,
}

impl ReflectedFrame {
    pub(crate) fn new(omega_view: &Vector3<f64>, peak: Option<Vector3<f64>>) -> ReflectedFrame {
        let x = reflected_frame_x(omega_view, peak);
        ReflectedFrame {
            x,
            y: omega_view.cross(&x),
        }
    }
}

/// Fixed splits of every line in `t`, so that no piece spans more than the Gaussian weight's
/// scale where it matters.
const SLOPE_SPLITS: [f64; 2] = [1.5, 3.0];

/// Truncation of the slope measure: `t <= T`, leaving out `exp(-T^2)` of it.
pub(crate) const SLOPE_T: f64 = 6.5;

impl<'a, S: SkyRadiance + ?Sized> SlopeIntegrand<'a, S> {
    pub(crate) fn new(
        eps: num_complex::Complex64,
        sigma: f64,
        sky: &'a S,
        omega_view: &Vector3<f64>,
    ) -> Self {
        let cv = omega_view.z.max(COS_FLOOR);
        let sv = (omega_view.x * omega_view.x + omega_view.y * omega_view.y).sqrt();
        let e1 = if sv > 0.0 {
            Vector3::new(omega_view.x / sv, omega_view.y / sv, 0.0)
        } else {
            Vector3::x()
        };
        let e2 = Vector3::z().cross(&e1);
        // h ∝ z - rho (cos psi e1 + sin psi e2), so the slope is -(h.e1, h.e2) / h.z.
        let peak = sky.peak().and_then(|d| {
            let h = d + omega_view;
            if d.z <= 0.0 || h.z <= 0.0 {
                return None;
            }
            let (p, q) = (-h.dot(&e1) / h.z, -h.dot(&e2) / h.z);
            let t = p.hypot(q) / (sigma * std::f64::consts::SQRT_2);
            let psi = q.atan2(p);
            let psi = if psi < -std::f64::consts::FRAC_PI_2 {
                psi + 2.0 * PI
            } else {
                psi
            };
            (t < SLOPE_T).then_some((psi, t))
        });
        let s_r = ReflectedFrame::new(omega_view, sky.peak());
        let view_cross_z = omega_view.cross(&Vector3::z());
        SlopeIntegrand {
            eps,
            sky,
            omega_view: *omega_view,
            cv,
            inv_cv: 1.0 / cv,
            sv,
            e1,
            e2,
            peak,
            s_r,
            rho_per_t: sigma * std::f64::consts::SQRT_2,
            view_cross_z,
            view_cross_z_r: (s_r.x.dot(&view_cross_z), s_r.y.dot(&view_cross_z)),
            real_eps: (eps.im == 0.0 && eps.re >= 1.0).then_some(eps.re),
        }
    }

    /// The line of slope azimuth `psi`'s constant terms.
    #[inline]
    pub(crate) fn line(&self, psi: f64) -> SlopeLine {
        self.line_at(psi.sin_cos())
    }

    /// [`SlopeIntegrand::line`] from `(sin psi, cos psi)`.
    #[inline]
    pub(crate) fn line_at(&self, (sp, cp): (f64, f64)) -> SlopeLine {
        let along = self.e1 * cp + self.e2 * sp;
        let view_cross_along = self.omega_view.cross(&along);
        SlopeLine {
            along,
            view_along: self.omega_view.dot(&along),
            view_cross_along,
            view_cross_along_r: (
                self.s_r.x.dot(&view_cross_along),
                self.s_r.y.dot(&view_cross_along),
            ),
        }
    }

    #[inline]
    pub(crate) fn value(&self, psi: f64, t: f64) -> [f64; 3] {
        self.value_on(&self.line(psi), t, slope_weight(t))
    }

    /// [`SlopeIntegrand::value`] on the line `line` (from [`SlopeIntegrand::line`]). `weight`
    /// is [`slope_weight`]`(t)`. The adaptive rule's point, and the product rule's at a
    /// degenerate facet frame; the product rule's pieces compute the same in vector loops
    /// ([`SlopeIntegrand::piece`], tested against this).
    #[inline(always)]
    pub(crate) fn value_on(&self, line: &SlopeLine, t: f64, weight: f64) -> [f64; 3] {
        let rho = self.rho_per_t * t;
        let p = self.point(line, rho);
        if p.cos_beta <= 0.0 || p.cos_d <= 0.0 {
            return [0.0; 3];
        }
        let w = weight * p.g;
        if p.s_f.norm_squared() > 1e-200 {
            // `R(-eta_r) M(beta) R(eta_i) S` (Eq. 3.7) with the sky's Stokes vector asked for
            // in the facet frame, so that neither the incident surface frame nor `R(eta_i)` is
            // formed, and `M(beta)` (Eq. 3.5) applied by its four distinct entries: the same
            // product as `rotated_fresnel(..) * stokes_from(..)` up to rounding (tested).
            let s = self.sky.stokes_in_frame(&p.omega_d, &p.s_f);
            return facet_reflection_cs(self.eps, p.cos_beta, &s, p.c, p.sn, w);
        }
        // omega_d is unit (to rounding) and above the horizon, omega_view checked, h and
        // cos beta known: the world-frame facet geometry without normalising its frames.
        let h = Vector3::new(
            -rho * p.inv_n * line.along.x,
            -rho * p.inv_n * line.along.y,
            p.inv_n,
        );
        let m = FacetGeometry::from_half_vector(&p.omega_d, &self.omega_view, &h, p.cos_beta)
            .rotated_fresnel(self.eps);
        let s = self.sky.stokes_from(&p.omega_d);
        let out = m * s.0 * w;
        [out[0], out[1], out[2]]
    }

    /// The geometry of the point of slope `rho` on `line` ([`SlopeLine`]): shared by
    /// [`SlopeIntegrand::value_on`] and the product rule's vector loop
    /// ([`SlopeIntegrand::piece`]), branch-free so that the loop vectorises.
    #[inline(always)]
    pub(crate) fn point(&self, line: &SlopeLine, rho: f64) -> SlopePoint {
        // `h = (z - rho along) / n`, `n = sqrt(1 + rho^2)` (`along` is unit and horizontal).
        let inv_n = 1.0 / (1.0 + rho * rho).sqrt();
        let omega_view = &self.omega_view;
        let cos_beta = (omega_view.z - rho * line.view_along) * inv_n;
        // `omega_d = 2 cos beta h - omega_view`.
        let twice_cb_inv_n = 2.0 * cos_beta * inv_n;
        let cos_d = twice_cb_inv_n - omega_view.z;
        let out_of_plane = twice_cb_inv_n * rho;
        let omega_d = Vector3::new(
            -out_of_plane * line.along.x - omega_view.x,
            -out_of_plane * line.along.y - omega_view.y,
            cos_d,
        );
        // `G cos beta / cos theta_v` (`cos alpha = 1 / n`).
        let g = less(
            less(cos_beta * self.inv_cv, 2.0 * inv_n),
            2.0 * inv_n * cos_d * self.inv_cv,
        );
        // The facet frame's x, `omega_r × omega_i` as in `FacetGeometry::from_half_vector`, up
        // to its positive scale `2 cos beta / n`, and its components in the reflected frame.
        let q = &line.view_cross_along;
        SlopePoint {
            inv_n,
            cos_beta,
            cos_d,
            omega_d,
            g,
            s_f: Vector3::new(
                self.view_cross_z.x - rho * q.x,
                self.view_cross_z.y - rho * q.y,
                -rho * q.z,
            ),
            c: self.view_cross_z_r.0 - rho * line.view_cross_along_r.0,
            sn: self.view_cross_z_r.1 - rho * line.view_cross_along_r.1,
        }
    }

    /// The integrand's kinks along `t` at azimuth `psi` (`k = cos psi sin theta_v`), in slope
    /// `rho`: facet turning away (`cos beta = 0`): `rho = cos theta_v / k`; reflected ray at the
    /// horizon (`cos theta_d = 0`): `cos theta_v rho^2 + 2 k rho - cos theta_v = 0`; the
    /// shadowing min switching branches: `rho = -cos theta_v / k` and `rho = -k / cos theta_v`.
    pub(crate) fn kinks(&self, psi: f64, out: &mut Vec<f64>) {
        let (k, cv) = (psi.cos() * self.sv, self.cv);
        let to_t = 1.0 / self.rho_per_t;
        if k != 0.0 {
            out.push(cv / k * to_t);
            out.push(-cv / k * to_t);
        }
        out.push(-k / cv * to_t);
        out.push((-k + k.hypot(cv)) / cv * to_t);
    }

    /// The smooth pieces of the line at azimuth `psi` (given as `cos_psi`), as `t` from 0 to
    /// the end of the integrand's support: the line ends where the reflected ray reaches the
    /// horizon (`cos theta_v rho^2 + 2 k rho - cos theta_v = 0`, `k = cos psi sin theta_v`;
    /// beyond it the integrand is 0) or at `T`, and breaks where the shadowing `min(A, B, C)`
    /// (`A = cos beta / cos theta_v`, `B = 2 cos alpha`, `C = 2 cos alpha cos theta_d / cos
    /// theta_v`) switches branches: `A = B` at `rho = -cos theta_v / k`, `B = C` at
    /// `rho = -k / cos theta_v`, and `A = C` on the cubic
    /// `k rho^3 - 3 cos theta_v rho^2 - 3 k rho + cos theta_v = 0`, which with `rho = tan x` is
    /// `tan 3x = cos theta_v / k`. A switch is a break only where its two branches are the
    /// minimum.
    pub(crate) fn pieces(&self, cos_psi: f64, out: &mut Vec<f64>) {
        out.clear();
        let (k, cv) = (cos_psi * self.sv, self.cv);
        let to_t = 1.0 / self.rho_per_t;
        let end = ((-k + k.hypot(cv)) / cv * to_t).min(SLOPE_T);
        let abc = |rho: f64| {
            let c = 1.0 / (1.0 + rho * rho).sqrt();
            (
                (cv - k * rho) * c / cv,
                2.0 * c,
                2.0 * c * c * c * (cv - 2.0 * k * rho - cv * rho * rho) / cv,
            )
        };
        out.push(0.0);
        let mut push = |rho: f64, active: bool| {
            let t = rho * to_t;
            if active && t > 0.0 && t < end {
                out.push(t);
            }
        };
        let slack = 1.0 + 1e-9;
        if k < 0.0 {
            let r = -cv / k;
            let (a, _, c) = abc(r);
            push(r, a <= c * slack);
            let r = -k / cv;
            let (a, b, _) = abc(r);
            push(r, b <= a * slack);
        }
        // The roots `tan x` at `x = phi0 / 3` and `x + pi / 3` (below pi / 2), the second by
        // the addition formula: one `tan` for both.
        let x = cv.atan2(k) / 3.0;
        let r = x.tan();
        let (_, b, c) = abc(r);
        push(r, c <= b * slack);
        if x + std::f64::consts::FRAC_PI_3 < std::f64::consts::FRAC_PI_2 {
            let sqrt3 = 3f64.sqrt();
            let r = (r + sqrt3) / (1.0 - sqrt3 * r);
            let (_, b, c) = abc(r);
            push(r, c <= b * slack);
        }
        for t in SLOPE_SPLITS.into_iter().chain(self.peak.map(|p| p.1)) {
            if t > 0.0 && t < end {
                out.push(t);
            }
        }
        out.push(end.max(0.0));
        out.sort_by(f64::total_cmp);
        out.dedup();
    }

    /// The integral by the adaptive rule: periodic trapezoid in `psi`, adaptive Gauss-Kronrod
    /// along each line, split at [`SlopeIntegrand::kinks`].
    pub(crate) fn adaptive(&self, tol: Tolerance) -> IntegralN<3> {
        integrate_periodic_split_n(
            |psi, t| self.value(psi, t),
            (0.0, 2.0 * PI),
            (0.0, SLOPE_T),
            |psi, out: &mut Vec<f64>| self.kinks(psi, out),
            tol,
        )
    }

    /// The azimuth arcs on which the line integrals are smooth: split where `k = 0` (`psi =
    /// +-pi/2`, where the `B = C` break enters the line at `t = 0`) and, for views more than
    /// 45 deg off the normal, where `k = -cos theta_v` (`A = B = C` at one point of the line:
    /// there the kinks change which branches they join). Returns how many of `out` are set.
    pub(crate) fn arcs(&self, out: &mut [(f64, f64); 5]) -> usize {
        let h = std::f64::consts::FRAC_PI_2;
        out[0] = (-h, h);
        let mut count = if self.sv > self.cv {
            let star = (-self.cv / self.sv).acos();
            out[1] = (h, star);
            out[2] = (star, 2.0 * PI - star);
            out[3] = (2.0 * PI - star, 3.0 * h);
            4
        } else {
            out[1] = (h, 3.0 * h);
            2
        };
        if let Some((psi, _)) = self.peak {
            if let Some(i) = out[..count].iter().position(|&(a, b)| a < psi && psi < b) {
                let (a, b) = out[i];
                out[i] = (a, psi);
                out[count] = (psi, b);
                count += 1;
            }
        }
        count
    }

    /// The integral by a product Gauss-Legendre rule: `n` azimuths per half turn over the arcs
    /// of [`SlopeIntegrand::arcs`] (at least `n / 2` per arc, at most 64), `q` points on each
    /// smooth piece of each line from [`SlopeIntegrand::pieces`] (about half as many beyond the
    /// last fixed split).
    pub(crate) fn gauss(&self, n: usize, q: usize, pieces: &mut Vec<f64>) -> ([f64; 3], usize) {
        // Compiled once per instruction set pulp knows (SSE2, AVX2 with FMA) and run in the
        // widest the CPU has: the same operations in the same order on every path (Rust forms
        // no fused multiply-adds), so the same result to the bit.
        pulp::Arch::new().dispatch(SlopeRule {
            integrand: self,
            n,
            q,
            pieces,
        })
    }

    /// [`SlopeIntegrand::gauss`] in whichever instruction set it is dispatched to.
    #[inline(always)]
    pub(crate) fn gauss_rule(
        &self,
        n: usize,
        q: usize,
        pieces: &mut Vec<f64>,
    ) -> ([f64; 3], usize) {
        let mut sum = [0.0; 3];
        let mut evaluations = 0;
        let mut shared = SharedWeights::new(self.peak.map(|p| p.1));
        let mut batch = FacetBatch::new();
        let mut arcs = [(0.0, 0.0); 5];
        let count = self.arcs(&mut arcs);
        for &(a, b) in &arcs[..count] {
            let gn = gauss_legendre_table(arc_points(n, b - a));
            let (centre, half) = (0.5 * (a + b), 0.5 * (b - a));
            for &(x, wx) in gn {
                let psi = centre + half * x;
                let wpsi = half * wx;
                let (sp, cp) = psi.sin_cos();
                self.pieces(cp, pieces);
                let line = self.line_at((sp, cp));
                for w in pieces.windows(2) {
                    let (mid, half) = (0.5 * (w[0] + w[1]), 0.5 * (w[1] - w[0]));
                    if half <= 0.0 {
                        continue;
                    }
                    // Beyond the last fixed split the Gaussian weight is below exp(-9) of its
                    // peak: about half the points, still growing with every level.
                    let gq = gauss_legendre_table(if w[0] >= SLOPE_SPLITS[1] {
                        q.div_ceil(2) + 1
                    } else {
                        q
                    });
                    let weights = shared.get(w[0], w[1], gq);
                    self.piece(&line, gq, (mid, half, wpsi), weights, &mut batch, &mut sum);
                    evaluations += gq.len();
                }
            }
        }
        (sum, evaluations)
    }
}

impl<'a, S: SkyRadiance + ?Sized> SlopeIntegrand<'a, S> {
    /// One smooth piece of a line of the product rule: `sum += wpsi half wy value(psi, t)` over
    /// its Gauss nodes `(y, wy)`, `t = mid + half y`, with `weights` the slope weights at the
    /// nodes when every line shares the piece ([`SharedWeights`]).
    ///
    /// [`SlopeIntegrand::value_on`]'s arithmetic, reordered into loops over the piece's nodes
    /// (structure of arrays, no branches: a point off the integrand's support gets weight 0),
    /// which the compiler vectorises: the geometry, the sky ([`SkyRadiance::
    /// stokes_in_frame_batch`]) and, for a dielectric, the Fresnel terms and the rotation into
    /// the reflected frame. The same values as `value_on` to rounding (tested); a point whose
    /// facet frame is degenerate (the facet normal along the view) takes `value_on` itself.
    #[inline(always)]
    pub(crate) fn piece(
        &self,
        line: &SlopeLine,
        nodes: &[(f64, f64)],
        rule: (f64, f64, f64),
        weights: Option<&[f64]>,
        b: &mut FacetBatch,
        sum: &mut [f64; 3],
    ) {
        for start in (0..nodes.len()).step_by(FACET_BATCH) {
            let end = (start + FACET_BATCH).min(nodes.len());
            let weights = weights.map(|ws| &ws[start..end]);
            self.piece_batch(line, &nodes[start..end], rule, weights, b, sum);
        }
    }

    /// [`SlopeIntegrand::piece`] for at most [`FACET_BATCH`] nodes.
    #[inline(always)]
    pub(crate) fn piece_batch(
        &self,
        line: &SlopeLine,
        nodes: &[(f64, f64)],
        (mid, half, wpsi): (f64, f64, f64),
        weights: Option<&[f64]>,
        b: &mut FacetBatch,
        sum: &mut [f64; 3],
    ) {
        let n = nodes.len().min(FACET_BATCH);
        // The slope weights times the quadrature weights.
        match weights {
            Some(ws) => {
                for (i, &(y, wy)) in nodes[..n].iter().enumerate() {
                    b.rho[i] = self.rho_per_t * (mid + half * y);
                    b.w[i] = ws[i] * (wpsi * half * wy);
                }
            }
            None => {
                for (i, &(y, wy)) in nodes[..n].iter().enumerate() {
                    let t = mid + half * y;
                    b.rho[i] = self.rho_per_t * t;
                    b.w[i] = slope_weight(t) * (wpsi * half * wy);
                }
            }
        }
        let mut idle = false;
        for i in 0..n {
            let p = self.point(line, b.rho[i]);
            (b.dx[i], b.dy[i], b.dz[i]) = (p.omega_d.x, p.omega_d.y, p.omega_d.z);
            b.cos_beta[i] = p.cos_beta;
            (b.fx[i], b.fy[i], b.fz[i]) = (p.s_f.x, p.s_f.y, p.s_f.z);
            b.f2[i] = p.s_f.x * p.s_f.x + p.s_f.y * p.s_f.y + p.s_f.z * p.s_f.z;
            (b.c[i], b.sn[i]) = (p.c, p.sn);
            let on = p.cos_beta > 0.0 && p.cos_d > 0.0;
            b.w[i] = if on { b.w[i] * p.g } else { 0.0 };
            // A point to set aside below (a vectorised OR: most pieces have none).
            idle |= !on | (b.f2[i] <= 1e-200) | (b.w[i] == 0.0);
        }
        // A degenerate facet frame: the general product, one point. That point, and those off
        // the support, then ask the sky for the zenith in a valid frame (weight 0: only so
        // that every sky's value there is finite).
        for i in 0..if idle { n } else { 0 } {
            let degenerate = b.f2[i] <= 1e-200;
            if b.w[i] == 0.0 || degenerate {
                if b.w[i] != 0.0 {
                    let t = b.rho[i] / self.rho_per_t;
                    let g = weights.map_or_else(|| slope_weight(t), |ws| ws[i]);
                    let v = self.value_on(line, t, g);
                    add_scaled(sum, &v, wpsi * half * nodes[i].1);
                }
                b.set_idle(i);
            }
        }
        reflect_batch(self.sky, self.eps, self.real_eps, b, n, sum);
    }
}

/// [`SlopeIntegrand::gauss_rule`] for [`pulp::Arch::dispatch`]. `with_simd` is generic over
/// the instruction set, so each set gets its own copy of the rule, inlined into pulp's entry
/// point compiled for that set. (A closure handed to `dispatch` would be one function whatever
/// the set, so the AVX2 entry point would run SSE2 code; and pulp's `x86-v3` feature must be
/// on, or `Arch` never detects AVX2.)
pub(crate) struct SlopeRule<'r, 'a, S: SkyRadiance + ?Sized> {
    integrand: &'r SlopeIntegrand<'a, S>,
    n: usize,
    q: usize,
    pieces: &'r mut Vec<f64>,
}

impl<S: SkyRadiance + ?Sized> pulp::WithSimd for SlopeRule<'_, '_, S> {
    type Output = ([f64; 3], usize);

    #[inline(always)]
    fn with_simd<Simd: pulp::Simd>(self, _simd: Simd) -> Self::Output {
        self.integrand.gauss_rule(self.n, self.q, self.pieces)
    }
}

/// The smaller of `a` and `b` for operands that are not NaN: one vector instruction, where
/// `f64::min`'s NaN rule costs several.
#[inline(always)]
fn less(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// The second half of a batch of facet reflections ([`SlopeIntegrand::piece`], and
/// `LeafColumns::column` in [`crate::skylight`]): with the points' incident directions, facet
/// frames, `cos beta` and whole weights set in `b` (a point that contributes nothing set by
/// [`FacetBatch::set_idle`]: weight 0 and a ray every sky is finite for), the sky in
/// the facet frames ([`SkyRadiance::stokes_in_frame_batch`]) and [`facet_reflection_cs`],
/// summed into `sum`. `real_eps` is `Re eps` of a dielectric with `eps >= 1`, whose Fresnel
/// terms (`real_amplitudes`' one division) and frame rotation run in a vector loop; other
/// surfaces take `facet_reflection_cs` point by point.
#[inline(always)]
pub(crate) fn reflect_batch<S: SkyRadiance + ?Sized>(
    sky: &S,
    eps: num_complex::Complex64,
    real_eps: Option<f64>,
    b: &mut FacetBatch,
    n: usize,
    sum: &mut [f64; 3],
) {
    sky.stokes_in_frame_batch(
        [&b.dx[..n], &b.dy[..n], &b.dz[..n]],
        [&b.fx[..n], &b.fy[..n], &b.fz[..n]],
        [&mut b.s0[..n], &mut b.s1[..n], &mut b.s2[..n]],
    );
    let Some(er) = real_eps else {
        for i in 0..n {
            if b.w[i] != 0.0 {
                let s = Stokes::new(b.s0[i], b.s1[i], b.s2[i]);
                let v = facet_reflection_cs(eps, b.cos_beta[i], &s, b.c[i], b.sn[i], b.w[i]);
                add_scaled(sum, &v, 1.0);
            }
        }
        return;
    };
    // `facet_reflection_cs` with `real_amplitudes`' one division, for `eps >= 1`.
    for i in 0..n {
        let c = b.cos_beta[i].clamp(0.0, 1.0);
        let sin2 = 1.0 - c * c;
        let root = (er - sin2).sqrt();
        let (ds, dp) = (c + root, er * c + root);
        let den = ds * dp;
        let inv = if den > 0.0 { 1.0 / den } else { 0.0 };
        let (rs, rp) = ((c - root) * dp * inv, (er * c - root) * ds * inv);
        let s = [b.s0[i], b.s1[i], b.s2[i]];
        let r = reflected_stokes((rs * rs, rp * rp, rs * rp), &s, b.c[i], b.sn[i], b.w[i]);
        (b.s0[i], b.s1[i], b.s2[i]) = (r[0], r[1], r[2]);
    }
    for i in 0..n {
        sum[0] += b.s0[i];
        sum[1] += b.s1[i];
        sum[2] += b.s2[i];
    }
}

/// The most points of one [`SlopeIntegrand::piece`]: a piece's Gauss nodes.
pub(crate) const FACET_BATCH: usize = SHARED_MAX_NODES;

/// [`SlopeIntegrand::piece`]'s working arrays, one entry per node.
pub(crate) struct FacetBatch {
    pub(crate) rho: [f64; FACET_BATCH],
    /// The point's whole weight (slope, shadowing, quadrature); 0 off the support.
    pub(crate) w: [f64; FACET_BATCH],
    pub(crate) cos_beta: [f64; FACET_BATCH],
    /// The reflected (incident sky) direction `omega_d`.
    pub(crate) dx: [f64; FACET_BATCH],
    pub(crate) dy: [f64; FACET_BATCH],
    pub(crate) dz: [f64; FACET_BATCH],
    /// The facet frame's `x` (unnormalised, [`SlopeLine`]), its squared length, and its
    /// components along the reflected frame's `x` and `y`.
    pub(crate) fx: [f64; FACET_BATCH],
    pub(crate) fy: [f64; FACET_BATCH],
    pub(crate) fz: [f64; FACET_BATCH],
    pub(crate) f2: [f64; FACET_BATCH],
    pub(crate) c: [f64; FACET_BATCH],
    pub(crate) sn: [f64; FACET_BATCH],
    /// The sky's Stokes vector in the facet frame, then the weighted reflected one.
    pub(crate) s0: [f64; FACET_BATCH],
    pub(crate) s1: [f64; FACET_BATCH],
    pub(crate) s2: [f64; FACET_BATCH],
}

impl FacetBatch {
    /// Point `i` adds nothing (weight 0) and asks the sky for the zenith in the frame `x`: a
    /// ray every sky gives a finite value for, so that the vector loops need no select.
    #[inline(always)]
    pub(crate) fn set_idle(&mut self, i: usize) {
        self.w[i] = 0.0;
        (self.dx[i], self.dy[i], self.dz[i]) = (0.0, 0.0, 1.0);
        (self.fx[i], self.fy[i], self.fz[i]) = (1.0, 0.0, 0.0);
    }

    pub(crate) fn new() -> FacetBatch {
        let z = [0.0; FACET_BATCH];
        FacetBatch {
            rho: z,
            w: z,
            cos_beta: z,
            dx: z,
            dy: z,
            dz: z,
            fx: z,
            fy: z,
            fz: z,
            f2: z,
            c: z,
            sn: z,
            s0: z,
            s1: z,
            s2: z,
        }
    }
}

/// The slope weight `2 t exp(-t^2) / (2 pi)` of [`SlopeIntegrand`]'s measure `dpsi dt`.
#[inline(always)]
pub(crate) fn slope_weight(t: f64) -> f64 {
    t * exp_nonpositive(-t * t) * std::f64::consts::FRAC_1_PI
}

/// `exp(x)` for `x` in `[-708, 0]` (a smaller `x` gives `exp(-708)`), within 2 ulps of libm's
/// (tested over the slope weight's range and beyond), in arithmetic that a loop can vectorise
/// (libm's `exp` is a call). Cody and Waite's reduction `x = k ln 2 + r`, `|r| <= ln 2 / 2`
/// (W. J. Cody and W. Waite, Software Manual for the Elementary Functions, 1980, ch. 6), with
/// `k` rounded by adding `1.5 * 2^52` (its bits then hold `k`), `exp(r)` by its Taylor
/// polynomial to degree 13 (truncation below `(ln 2 / 2)^14 / 14! = 4e-18`; Estrin's split
/// into even and odd parts), and `2^k` put into the exponent field.
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f64) -> f64 {
    // 1.5 * 2^52.
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    // ln 2 in two parts, the first with its low 32 bits zero, so that `k * LN2_HI` is exact for
    // `|k| < 2^20` (fdlibm's split).
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    // Taylor coefficients 1/j!: even j from 12 down to 2, odd j from 13 down to 3.
    const EVEN: [f64; 6] = [
        1.0 / 479_001_600.0,
        1.0 / 3_628_800.0,
        1.0 / 40_320.0,
        1.0 / 720.0,
        1.0 / 24.0,
        0.5,
    ];
    const ODD: [f64; 6] = [
        1.0 / 6_227_020_800.0,
        1.0 / 39_916_800.0,
        1.0 / 362_880.0,
        1.0 / 5_040.0,
        1.0 / 120.0,
        1.0 / 6.0,
    ];
    let x = x.clamp(-708.0, 0.0);
    let shifted = x * std::f64::consts::LOG2_E + SHIFT;
    let k = shifted - SHIFT;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    // `exp(r) - 1 = r + r^2 (E(r^2) + r O(r^2))`: the even and odd parts as two Horner
    // chains in `r^2` that run side by side (half the latency of one chain in `r`).
    let r2 = r * r;
    let (mut even, mut odd) = (EVEN[0], ODD[0]);
    for (e, o) in EVEN[1..].iter().zip(&ODD[1..]) {
        even = even * r2 + e;
        odd = odd * r2 + o;
    }
    let expm1_r = r + r2 * (even + r * odd);
    // `shifted`'s low bits are `k` (two's complement, `-1022 <= k <= 0`); `2^k` is the
    // double of exponent field `k + 1023`.
    let k_bits = shifted.to_bits().wrapping_sub(SHIFT.to_bits());
    let two_k = f64::from_bits(k_bits.wrapping_add(1023) << 52);
    (1.0 + expm1_r) * two_k
}

/// [`slope_weight`] at the Gauss nodes of the pieces that every line of a product rule shares:
/// those between the fixed splits, the sky peak's split, `0` and [`SLOPE_T`] (the line's
/// kinks and horizon end move with its azimuth). Computed once per rule instead of once per
/// line: the same values to the bit, since a piece's nodes come from its ends alone.
pub(crate) struct SharedWeights {
    /// The splits every line has: `0`, [`SLOPE_SPLITS`], the peak's and [`SLOPE_T`].
    pub(crate) fixed: [f64; 5],
    /// Per piece met so far: its ends and its nodes' weights (at most [`SHARED_MAX_NODES`]).
    pub(crate) pieces: Vec<(f64, f64, usize, [f64; SHARED_MAX_NODES])>,
}

/// The most Gauss nodes a piece's shared weights hold (`GAUSS_LEVELS`' largest `q`).
const SHARED_MAX_NODES: usize = 24;

impl SharedWeights {
    pub(crate) fn new(peak_t: Option<f64>) -> SharedWeights {
        SharedWeights {
            fixed: [
                0.0,
                SLOPE_SPLITS[0],
                SLOPE_SPLITS[1],
                peak_t.unwrap_or(0.0),
                SLOPE_T,
            ],
            pieces: Vec::new(),
        }
    }

    /// The weights at the nodes `gq` of the piece `[a, b]` when every line shares it (`None`
    /// otherwise: the caller computes its own).
    #[inline]
    pub(crate) fn get(&mut self, a: f64, b: f64, gq: &[(f64, f64)]) -> Option<&[f64]> {
        let shared = |x: f64| self.fixed.contains(&x);
        if gq.len() > SHARED_MAX_NODES || !shared(a) || !shared(b) {
            return None;
        }
        let found = self
            .pieces
            .iter()
            .position(|p| p.0 == a && p.1 == b && p.2 == gq.len());
        let i = match found {
            Some(i) => i,
            None => {
                let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
                let mut weights = [0.0; SHARED_MAX_NODES];
                for (w, &(y, _)) in weights.iter_mut().zip(gq) {
                    *w = slope_weight(mid + half * y);
                }
                self.pieces.push((a, b, gq.len(), weights));
                self.pieces.len() - 1
            }
        };
        let p = &self.pieces[i];
        Some(&p.3[..p.2])
    }
}

/// The specular part of Eq. 3.22 for a microfacet surface of permittivity `eps` and roughness
/// `sigma`, integrated in facet-slope space (module docs). The result is in the reflected
/// surface frame of `omega_view`.
///
/// The rule is a product Gauss-Legendre rule on the integrand's smooth pieces
/// (`SlopeIntegrand::gauss`) at increasing levels (`GAUSS_LEVELS`); if the last level does
/// not meet `tol` (a sky with a sharp feature inside the lobe), the adaptive rule takes over and
/// the better of the two is returned.
pub fn specular_skylight<S: SkyRadiance + ?Sized>(
    eps: num_complex::Complex64,
    sigma: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
) -> Result<StokesIntegral, ModelError> {
    specular_skylight_from(eps, sigma, sky, omega_view, tol, Start::Level(0))
}

/// [`specular_skylight`] with the product rule's levels from `start` (`ladder`).
pub(crate) fn specular_skylight_from<S: SkyRadiance + ?Sized>(
    eps: num_complex::Complex64,
    sigma: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
    start: Start,
) -> Result<StokesIntegral, ModelError> {
    check_view(omega_view)?;
    let integrand = SlopeIntegrand::new(eps, sigma, sky, omega_view);
    let mut pieces = Vec::with_capacity(8);
    Ok(ladder(
        |n, q| integrand.gauss(n, q, &mut pieces),
        || integrand.adaptive(tol),
        tol,
        slope_truncation(sky),
        start,
    ))
}

/// The error of leaving out the slope measure beyond `SLOPE_T`: its weight `exp(-T^2)`
/// times twice the zenith sky (a bound of the integrand's scale).
pub(crate) fn slope_truncation<S: SkyRadiance + ?Sized>(sky: &S) -> f64 {
    2.0 * (-SLOPE_T * SLOPE_T).exp() * sky.stokes_from(&Vector3::z()).0[0].abs()
}

/// Where [`ladder`] starts.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Start<'p> {
    /// At this level of `GAUSS_LEVELS`.
    Level(usize),
    /// After the two levels of a [`LevelPair`] of the same ray, which are not computed again.
    After(&'p LevelPair),
}

/// One ray's specular skylight at two adjacent product-rule levels, not yet accepted: a
/// batch of neighbouring rays is accepted together on the largest of their changes
/// ([`level_pair`](crate::skylight::level_pair)), or each ray resumes its own ladder from here
/// ([`reflected_skylight_at`](crate::skylight::reflected_skylight_at)).
#[derive(Debug, Clone, Copy)]
pub(crate) struct LevelPair {
    /// The lower level (an index of `GAUSS_LEVELS`); the upper is the next.
    pub(crate) level: usize,
    pub(crate) lower: [f64; 3],
    pub(crate) upper: [f64; 3],
    /// The truncation error every result carries.
    pub(crate) floor: f64,
    /// The factor on the batch's largest change ([`PairRule::safety`](crate::skylight::PairRule::safety)).
    pub(crate) safety: f64,
    /// The change into `lower` from the level below it (a [`next_pair`](crate::skylight::next_pair)'s: the first pair's
    /// step), infinite for a first pair: with [`LevelPair::step`], the two changes the
    /// [`ladder`]'s own test takes.
    pub(crate) lower_change: f64,
    pub(crate) evaluations: usize,
}

impl LevelPair {
    /// The change between the two levels (largest component).
    pub(crate) fn step(&self) -> f64 {
        max_abs::<3>(&std::array::from_fn(|i| self.upper[i] - self.lower[i]))
    }

    /// [`LevelPair::step`] times the rule's safety factor, plus the truncation: the upper
    /// level's error, as the largest over a batch ([`level_pair`](crate::skylight::level_pair)).
    pub(crate) fn error(&self) -> f64 {
        self.safety * self.step() + self.floor
    }

    /// The largest component of the upper level's value.
    pub(crate) fn scale(&self) -> f64 {
        max_abs(&self.upper)
    }

    /// The upper level's index in `GAUSS_LEVELS`.
    pub(crate) fn upper_level(&self) -> usize {
        self.level + 1
    }

    /// The upper level accepted with `error` (the batch's largest change), plus the
    /// Lambertian term `f00_diffuse * e_sky` in S0, as [`reflected_skylight`](crate::skylight::reflected_skylight) returns it.
    pub(crate) fn accept(&self, error: f64, f00_diffuse: f64, e_sky: f64) -> StokesIntegral {
        accepted_level(self.upper, error, self.evaluations, f00_diffuse * e_sky)
    }
}

/// A product-rule level accepted with `error`, plus the Lambertian term `lambertian` in S0,
/// as [`reflected_skylight`](crate::skylight::reflected_skylight) returns it.
pub(crate) fn accepted_level(
    value: [f64; 3],
    error: f64,
    evaluations: usize,
    lambertian: f64,
) -> StokesIntegral {
    let mut r = StokesIntegral::from(IntegralN {
        value,
        error,
        evaluations,
        converged: true,
    });
    r.stokes.0[0] += lambertian;
    r
}
/// Runs a product rule `rule(n, q)` (value, evaluations) at each of [`GAUSS_LEVELS`] in turn,
/// from `start` (a level, at most the third last: a level's error needs the two before it; or
/// after a [`LevelPair`], whose two levels count as computed), until one is accepted; `floor`
/// is an error every result carries (a truncation). When none is (an integrand not smooth
/// enough on the rule's pieces: a sharp feature of the sky inside the lobe, say), `fallback`
/// (an adaptive rule) is run, and the better of its answer and the last level's is returned.
///
/// A later `start` skips levels, never the test: the accepted level passed it against the same
/// two levels below it as from 0, and is at least the level a start from 0 would accept unless
/// that one lies below `start + 2` (then the answer is a finer level's).
pub(crate) fn ladder(
    mut rule: impl FnMut(usize, usize) -> ([f64; 3], usize),
    fallback: impl FnOnce() -> IntegralN<3>,
    tol: Tolerance,
    floor: f64,
    start: Start,
) -> StokesIntegral {
    let accept = |value: [f64; 3], error: f64, evaluations: usize, level: usize| StokesIntegral {
        level: Some(level),
        ..StokesIntegral::from(IntegralN {
            value,
            error,
            evaluations,
            converged: true,
        })
    };
    let (first, mut previous, mut evaluations, mut last_change) = match start {
        Start::Level(level) => {
            let level = level.min(GAUSS_LEVELS.len() - 3);
            let (n, q) = GAUSS_LEVELS[level];
            let (value, e) = rule(n, q);
            (level, value, e, f64::INFINITY)
        }
        Start::After(pair) => {
            // The pair's upper level passes the ladder's own test when the two changes it
            // already has (into each of the pair's levels) are within the tolerance: a batch
            // that failed on its largest change (or its safety factor) takes no level more than
            // a ladder would at such a ray.
            let error = pair.step().max(pair.lower_change) + floor;
            if error <= tol.target(max_abs(&pair.upper)) {
                return accept(pair.upper, error, pair.evaluations, pair.level + 1);
            }
            (pair.level + 1, pair.upper, pair.evaluations, pair.step())
        }
    };
    let mut best = (previous, f64::INFINITY);
    for (level, &(n, q)) in GAUSS_LEVELS.iter().enumerate().skip(first + 1) {
        let (value, e) = rule(n, q);
        evaluations += e;
        let change = max_abs::<3>(&std::array::from_fn(|i| value[i] - previous[i]));
        // The larger of the last two changes: one change alone can be small by a coincidence
        // of two levels' errors (it is, in 6-8 % of 947 views and tolerances, by up to 11x;
        // the larger of two never is, see `product_rule_error_covers_the_actual_error`).
        let error = change.max(last_change) + floor;
        if error < best.1 {
            best = (value, error);
        }
        if error <= tol.target(max_abs(&value)) {
            return accept(value, error, evaluations, level);
        }
        previous = value;
        last_change = change;
    }
    let r = fallback();
    evaluations += r.evaluations;
    let (value, error, converged) = if r.error + floor <= best.1 {
        (r.value, r.error + floor, r.converged)
    } else {
        (best.0, best.1, false)
    };
    StokesIntegral::from(IntegralN {
        value,
        error,
        evaluations,
        converged,
    })
}

/// Points of the azimuth rule on an arc of length `len` at level `n` (points per half turn):
/// the arc's share by length, but at least `n / 2`, since the short arcs next to
/// `psi = +-pi/2` of a grazing view hold its fastest variation (on the scale
/// `cos theta_v / sin theta_v`).
pub(crate) fn arc_points(n: usize, len: f64) -> usize {
    ((n as f64 * len / PI).round() as usize)
        .max(n.div_ceil(2))
        .max(3)
}

/// `sum += v * w`, componentwise.
#[inline]
pub(crate) fn add_scaled(sum: &mut [f64; 3], v: &[f64; 3], w: f64) {
    for (s, x) in sum.iter_mut().zip(v) {
        *s += x * w;
    }
}

impl From<IntegralN<3>> for StokesIntegral {
    fn from(r: IntegralN<3>) -> Self {
        StokesIntegral {
            stokes: Stokes::new(r.value[0], r.value[1], r.value[2]),
            error: r.error,
            evaluations: r.evaluations,
            converged: r.converged,
            level: None,
        }
    }
}

/// The product rule's levels `(n, q)` for [`SlopeIntegrand::gauss`], each about 1.3-1.5 times
/// the last in both directions. A level is accepted when the larger of its change from the level
/// before and that level's change from the one before it is below the tolerance; that larger
/// change is its reported error.
pub(crate) const GAUSS_LEVELS: [(usize, usize); 9] = [
    (4, 4),
    (6, 5),
    (8, 6),
    (12, 8),
    (16, 10),
    (24, 12),
    (32, 16),
    (48, 20),
    (64, 24),
];
