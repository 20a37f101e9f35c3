//! One facet's reflection of a sky ray: the reflected ray's frame, and the facet's Fresnel
//! Mueller matrix applied to the incident Stokes vector, rotated into that frame.

use crate::fresnel::{amplitudes_eps, real_amplitudes};
use crate::polarization::Stokes;
use nalgebra::Vector3;

/// The (unnormalised) `x` axis of the reflected surface frame of a view `omega_view`,
/// `(omega_v.y, -omega_v.x, 0)`. At the zenith, where the view alone defines no frame, the
/// frame the field's tiles take ([`crate::geometry::reflected_frame_x`], the convention of
/// `Geometry::from_directions` at normal view) with the sky's `peak` as the sun (the zenith
/// without one): one frame for every incident ray, so that the hemisphere integral adds
/// Stokes vectors in the same frame. (`FacetGeometry::from_half_vector`'s frame at the zenith
/// follows each incident ray; integrated, it gave a glass plate seen at nadir under a zenith
/// sun a spurious DoLP of 4.7 %.)
pub(super) fn reflected_frame_x(
    omega_view: &Vector3<f64>,
    peak: Option<Vector3<f64>>,
) -> Vector3<f64> {
    if omega_view.x != 0.0 || omega_view.y != 0.0 {
        Vector3::new(omega_view.y, -omega_view.x, 0.0)
    } else {
        crate::geometry::reflected_frame_x(&peak.unwrap_or_else(Vector3::z), omega_view)
    }
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
pub(super) fn facet_reflection_cs(
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
pub(super) fn reflected_stokes(
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
