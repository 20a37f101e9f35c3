//! The [`SkyRadiance`] trait and the frame conventions every sky shares: the Stokes radiance
//! arriving from each direction of the upper hemisphere, in that ray's surface frame, and the
//! E-vector angle of singly scattered light in that frame.

use crate::polarization::{cos_sin_2eta, Stokes};
use nalgebra::Vector3;

/// A sky: the Stokes radiance arriving from each direction of the upper hemisphere, in that
/// ray's surface frame (`x ∝ k × z`, `k` the propagation direction; world `+y` at the zenith).
pub trait SkyRadiance {
    /// Stokes radiance arriving from unit direction `towards` (`z >= 0`).
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes;

    /// A direction near which the radiance varies fastest, if there is one (the sun, whose
    /// aureole the aerosol's forward scattering makes): quadrature rules split there.
    fn peak(&self) -> Option<Vector3<f64>> {
        None
    }

    /// [`SkyRadiance::stokes_from`] in another transverse frame of the same ray: `frame_x`
    /// (non-zero, perpendicular to `towards`, any length) and `y = k × frame_x`, `k = -towards`
    /// the propagation direction. By default the surface frame's Stokes vector rotated by
    /// [`cos_sin_2eta`] (the rotation [`FacetGeometry`](crate::geometry::FacetGeometry) applies into a facet frame); a sky that
    /// knows its E-vector may compute the angle in `frame_x` directly, which is what the
    /// facet-slope integrand asks for.
    fn stokes_in_frame(&self, towards: &Vector3<f64>, frame_x: &Vector3<f64>) -> Stokes {
        surface_to_frame(self.stokes_from(towards), towards, frame_x)
    }

    /// [`SkyRadiance::stokes_in_frame`] for a batch of rays in structure-of-arrays form: ray
    /// `i` arrives from `(towards[0][i], towards[1][i], towards[2][i])` and its frame is
    /// `frame_x[..][i]`; its Stokes vector goes to `out[..][i]`, for `i < out[0].len()` (every
    /// slice at least that long). By default one [`SkyRadiance::stokes_in_frame`] per ray; a
    /// sky whose radiance is arithmetic may compute the batch in vector loops, which the
    /// facet-slope integrand's product rule asks for, one piece of a line at a time.
    fn stokes_in_frame_batch(
        &self,
        towards: [&[f64]; 3],
        frame_x: [&[f64]; 3],
        out: [&mut [f64]; 3],
    ) {
        stokes_in_frame_each(self, towards, frame_x, out);
    }
}

/// [`SkyRadiance::stokes_in_frame_batch`] one ray at a time.
pub(crate) fn stokes_in_frame_each<S: SkyRadiance + ?Sized>(
    sky: &S,
    towards: [&[f64]; 3],
    frame_x: [&[f64]; 3],
    out: [&mut [f64]; 3],
) {
    let [o0, o1, o2] = out;
    for (i, ((o0, o1), o2)) in o0.iter_mut().zip(o1.iter_mut()).zip(o2).enumerate() {
        let k = Vector3::new(towards[0][i], towards[1][i], towards[2][i]);
        let f = Vector3::new(frame_x[0][i], frame_x[1][i], frame_x[2][i]);
        let s = sky.stokes_in_frame(&k, &f);
        (*o0, *o1, *o2) = (s.0[0], s.0[1], s.0[2]);
    }
}

/// A Stokes vector of a ray arriving from `towards`, given in its surface frame
/// ([`surface_frame_x`]), in the transverse frame `frame_x` instead (the rotation
/// [`FacetGeometry`](crate::geometry::FacetGeometry) applies into a facet frame).
#[inline]
pub(crate) fn surface_to_frame(
    s: Stokes,
    towards: &Vector3<f64>,
    frame_x: &Vector3<f64>,
) -> Stokes {
    let (c, sn) = cos_sin_2eta(&surface_frame_x(towards), frame_x, &-towards);
    Stokes::new(s.0[0], c * s.0[1] + sn * s.0[2], c * s.0[2] - sn * s.0[1])
}

/// The (unnormalised) `x` axis of the surface frame of a ray arriving from `towards`: `k × z`
/// for `k = -towards`, world `+y` when the ray is vertical (as [`FacetGeometry`](crate::geometry::FacetGeometry) takes it).
#[inline]
fn surface_frame_x(towards: &Vector3<f64>) -> Vector3<f64> {
    if towards.x != 0.0 || towards.y != 0.0 {
        Vector3::new(-towards.y, towards.x, 0.0)
    } else {
        Vector3::new(0.0, 1.0, 0.0)
    }
}

/// `(cos 2chi, sin 2chi)` of an E-vector perpendicular to the scattering plane of a ray
/// propagating along `k` (unit) and the sun direction, in the ray's surface frame `x ∝ k × z`
/// (world `+y` when `k` is vertical: the pBRDF's normal-incidence limit). Towards or away from
/// the sun the plane is undefined and `(1, 0)` is returned (the light is unpolarised there).
pub(crate) fn e_vector_in_frame(k: &Vector3<f64>, sun: &Vector3<f64>) -> (f64, f64) {
    let e = k.cross(sun);
    if e.norm_squared() == 0.0 {
        return (1.0, 0.0);
    }
    if k.x != 0.0 || k.y != 0.0 {
        // The unnormalised frame x = k × z = (k.y, -k.x, 0), y = k × x = k k.z - z for unit k:
        // e.x = e.x k.y - e.y k.x, e.y = -e.z (e ⊥ k). The scale of x cancels in the ratios.
        let (c, s) = (e.x * k.y - e.y * k.x, -e.z);
        let n2 = c * c + s * s;
        if n2 > 0.0 {
            return ((c * c - s * s) / n2, 2.0 * c * s / n2);
        }
    }
    cos_sin_2chi(k, &e)
}

/// `(cos 2chi, sin 2chi)` of a (non-zero, transverse) E-vector `e` of a ray propagating along
/// `k`, in the ray's surface frame `x ∝ k × z` (world `+y` when `k` is vertical), `y = k × x`.
pub(crate) fn cos_sin_2chi(k: &Vector3<f64>, e: &Vector3<f64>) -> (f64, f64) {
    let x = k.cross(&Vector3::z());
    let x = if x.norm() > 0.0 {
        x.normalize()
    } else {
        Vector3::new(0.0, 1.0, 0.0)
    };
    let y = k.cross(&x);
    let (c, s) = (e.dot(&x), e.dot(&y));
    let n2 = (c * c + s * s).max(1e-300);
    ((c * c - s * s) / n2, 2.0 * c * s / n2)
}
