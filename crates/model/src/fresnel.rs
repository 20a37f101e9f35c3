//! Fresnel reflection at a planar interface (Meng (2012) Sec. 2.5, MODEL.md section 2).
//!
//! The incidence medium is air (index 1). The second medium has complex index `N = n + ik`
//! (`k = 0` for a dielectric). Amplitudes follow the convention of MODEL.md:
//!
//! * `rs = (cos ti - w) / (cos ti + w)`, `rp = (N^2 cos ti - w) / (N^2 cos ti + w)`,
//!   `w = sqrt(N^2 - sin^2 ti)` (principal branch, `Re w >= 0`, `Im w >= 0`), Meng (2012) Eqs. 2.27-2.28
//!   written for complex `N`;
//! * at normal incidence `rp = -rs`: the p basis vector of each ray is `k × s`, so it flips with
//!   the propagation direction. The Mueller element `M22 = Re(rs rp*)` is then `-R` at normal
//!   incidence, consistent with the mirror-image frame of the reflected ray.
//!
//! The complex form has no `tan ti` and is exact at grazing incidence (`rs = rp = -1`). Meng (2012)'s
//! real-valued conductor formulas (Eqs. 2.31-2.36) are used only as a test oracle.

use crate::error::ModelError;
use num_complex::Complex64;
use serde::{Deserialize, Serialize};

/// Complex refractive index `n + ik` of the reflecting medium, relative to the incidence medium.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RefractiveIndex {
    /// Real part `n`, in `(0, 100]`.
    pub n: f64,
    /// Extinction coefficient `k`, in `[0, 100]` (0 for a dielectric).
    #[serde(default)]
    pub k: f64,
}

impl RefractiveIndex {
    /// Largest `n` and `k` accepted; far beyond any optical material, small enough that `N^2` and
    /// every intermediate stay well inside f64.
    pub const MAX: f64 = 100.0;

    /// Validates and builds an index. Errors name `n` or `k` and the allowed range.
    pub fn new(n: f64, k: f64) -> Result<Self, ModelError> {
        if !(n.is_finite() && n > 0.0 && n <= Self::MAX) {
            return Err(ModelError::OutOfRange {
                field: "n",
                value: n,
                allowed: "(0, 100]",
            });
        }
        ModelError::check_range("k", k, 0.0, Self::MAX, "[0, 100]")?;
        Ok(RefractiveIndex { n, k })
    }

    /// `N^2 = (n + ik)^2`, the relative permittivity.
    pub fn permittivity(&self) -> Complex64 {
        let nn = Complex64::new(self.n, self.k);
        nn * nn
    }

    /// Brewster angle `atan(n)` of a dielectric (where `Rp = 0`). An absorbing medium (`k > 0`)
    /// has no angle where `Rp` vanishes: use [`RefractiveIndex::pseudo_brewster`].
    pub fn brewster_angle_rad(&self) -> f64 {
        self.n.atan()
    }

    /// The pseudo-Brewster angle: where `Rp` is smallest on `[0, 90]` deg, and that `Rp`.
    /// `Rp` falls from normal incidence to one minimum and rises to 1 at grazing incidence, so
    /// a golden-section search over `[0, pi/2]` finds it, to [`PSEUDO_BREWSTER_TOL_RAD`]. For
    /// `k = 0` it is the Brewster angle `atan(n)` with `Rp = 0`; for `k -> 0` it tends to it.
    pub fn pseudo_brewster(&self) -> PseudoBrewster {
        if self.k == 0.0 {
            return PseudoBrewster {
                angle_rad: self.brewster_angle_rad(),
                rp_min: 0.0,
            };
        }
        let eps = self.permittivity();
        let rp = |t: f64| amplitudes_eps(eps, t.cos()).rp_power();
        let g = (5f64.sqrt() - 1.0) / 2.0;
        let (mut lo, mut hi) = (0.0, std::f64::consts::FRAC_PI_2);
        let (mut a, mut b) = (hi - g * (hi - lo), lo + g * (hi - lo));
        let (mut fa, mut fb) = (rp(a), rp(b));
        // The bracket shrinks by g per step; stop at a tenth of the stated tolerance (below
        // it, Rp's differences near the minimum are at its rounding, ~1e-8 rad).
        while hi - lo > PSEUDO_BREWSTER_TOL_RAD / 10.0 {
            if fa < fb {
                (hi, b, fb) = (b, a, fa);
                a = hi - g * (hi - lo);
                fa = rp(a);
            } else {
                (lo, a, fa) = (a, b, fb);
                b = lo + g * (hi - lo);
                fb = rp(b);
            }
        }
        let angle_rad = 0.5 * (lo + hi);
        PseudoBrewster {
            angle_rad,
            rp_min: rp(angle_rad),
        }
    }
}

/// Accuracy of [`RefractiveIndex::pseudo_brewster`]'s angle, radians (5.7e-6 deg).
pub const PSEUDO_BREWSTER_TOL_RAD: f64 = 1e-7;

/// The minimum of `Rp` over the angle of incidence ([`RefractiveIndex::pseudo_brewster`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PseudoBrewster {
    /// The angle of incidence of the minimum, radians.
    pub angle_rad: f64,
    /// `Rp` there.
    pub rp_min: f64,
}

/// Complex Fresnel amplitude reflection coefficients for one angle of incidence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FresnelAmplitudes {
    /// s (TE, perpendicular) amplitude coefficient.
    pub rs: Complex64,
    /// p (TM, parallel) amplitude coefficient, basis `k × s` on both rays.
    pub rp: Complex64,
}

impl FresnelAmplitudes {
    /// Power reflectance `Rs = |rs|^2`.
    pub fn rs_power(&self) -> f64 {
        self.rs.norm_sqr()
    }

    /// Power reflectance `Rp = |rp|^2`.
    pub fn rp_power(&self) -> f64 {
        self.rp.norm_sqr()
    }

    /// `Re(rs rp*)`, the retardance-carrying Mueller element `M22` of Eq. 3.5.
    pub fn re_rs_rp_conj(&self) -> f64 {
        (self.rs * self.rp.conj()).re
    }
}

/// Principal square root `sqrt(z)` (`Re >= 0`, and `Im` with the sign of `Im z`), in algebraic
/// form: one `hypot` and one `sqrt`, no trigonometry (num-complex's `sqrt` goes through polar
/// form). Exact for `z = 0`; on the negative real axis returns `+i sqrt(|z|)` for `Im z = +0`.
/// `|z|` is formed without `hypot`: the model's permittivities (`|N| <= 100 sqrt(2)`) cannot
/// overflow it.
#[inline]
pub fn csqrt(z: Complex64) -> Complex64 {
    let (a, b) = (z.re, z.im);
    if a == 0.0 && b == 0.0 {
        return Complex64::new(0.0, b);
    }
    let t = (0.5 * (a.abs() + (a * a + b * b).sqrt())).sqrt();
    if a >= 0.0 {
        Complex64::new(t, b / (2.0 * t))
    } else {
        Complex64::new(b.abs() / (2.0 * t), t.copysign(b))
    }
}

/// Fresnel amplitudes for a precomputed permittivity `eps = N^2` and `cos ti`.
///
/// `cos_ti` is clamped to `[0, 1]`; the result is finite for every `eps` with `Re N > 0`
/// (see the module documentation for why neither denominator can vanish then). The only
/// 0/0 is `N = 1` at exact grazing incidence (no interface), which returns zero amplitudes.
/// A dielectric below its critical angle takes a real-arithmetic path.
#[inline]
pub fn amplitudes_eps(eps: Complex64, cos_ti: f64) -> FresnelAmplitudes {
    if let Some((rs, rp)) = real_amplitudes(eps, cos_ti) {
        return FresnelAmplitudes {
            rs: Complex64::new(rs, 0.0),
            rp: Complex64::new(rp, 0.0),
        };
    }
    let c = cos_ti.clamp(0.0, 1.0);
    let sin2 = (1.0 - c * c).max(0.0);
    let zero = Complex64::new(0.0, 0.0);
    let w = csqrt(eps - sin2);
    let ds = c + w;
    let dp = eps * c + w;
    FresnelAmplitudes {
        rs: if ds == zero { zero } else { (c - w) / ds },
        rp: if dp == zero { zero } else { (eps * c - w) / dp },
    }
}

/// [`amplitudes_eps`]'s real-arithmetic path: the real `(rs, rp)` of a dielectric (`eps` real)
/// below its critical angle, `None` otherwise. A caller that needs only `|rs|^2`, `|rp|^2` and
/// `Re(rs rp*)` takes them as `rs^2`, `rp^2` and `rs rp` from here, equal to the bit and
/// without the complex products on zero imaginary parts. Both amplitudes share one division
/// (to a few ulps of the two quotients).
#[inline]
pub(crate) fn real_amplitudes(eps: Complex64, cos_ti: f64) -> Option<(f64, f64)> {
    let c = cos_ti.clamp(0.0, 1.0);
    let sin2 = (1.0 - c * c).max(0.0);
    if !(eps.im == 0.0 && eps.re >= sin2) {
        return None;
    }
    let w = (eps.re - sin2).sqrt();
    let (ds, dp) = (c + w, eps.re * c + w);
    let den = ds * dp;
    if den != 0.0 && den.is_finite() {
        // One division for both (it costs several multiplications' time).
        let inv = 1.0 / den;
        return Some(((c - w) * dp * inv, (eps.re * c - w) * ds * inv));
    }
    let rs = if ds == 0.0 { 0.0 } else { (c - w) / ds };
    let rp = if dp == 0.0 {
        0.0
    } else {
        (eps.re * c - w) / dp
    };
    Some((rs, rp))
}

/// Fresnel amplitudes at incidence angle `theta_i_rad` in `[0, pi/2]`.
pub fn amplitudes(
    index: &RefractiveIndex,
    theta_i_rad: f64,
) -> Result<FresnelAmplitudes, ModelError> {
    let ti = ModelError::check_range(
        "theta_i",
        theta_i_rad,
        0.0,
        std::f64::consts::FRAC_PI_2,
        "[0, 90] deg",
    )?;
    Ok(amplitudes_eps(index.permittivity(), ti.cos()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Copper (n = 1.02, k = 2.577): the pseudo-Brewster angle 68.454 deg of the published
    /// table in `tests/reference.rs` (3 decimals, so 6e-4 deg), with `Rp` there below `Rp` at
    /// 1e-4 rad either side (a minimum) and above zero (a metal never extinguishes p).
    #[test]
    fn copper_pseudo_brewster_is_the_minimum_of_rp() {
        let cu = RefractiveIndex::new(1.02, 2.577).unwrap();
        let pb = cu.pseudo_brewster();
        assert!(
            (pb.angle_rad.to_degrees() - 68.454).abs() < 6e-4,
            "{}",
            pb.angle_rad.to_degrees()
        );
        let rp = |t: f64| amplitudes(&cu, t).unwrap().rp_power();
        assert!((rp(pb.angle_rad) - pb.rp_min).abs() < 1e-15);
        assert!(rp(pb.angle_rad - 1e-4) > pb.rp_min && rp(pb.angle_rad + 1e-4) > pb.rp_min);
        assert!(pb.rp_min > 0.4, "{}", pb.rp_min);
        // Not the dielectric formula: atan(1.02) = 45.57 deg is 23 deg off.
        assert!((cu.brewster_angle_rad() - pb.angle_rad).to_degrees().abs() > 20.0);
    }

    /// Against an independent search: a 0.001-deg scan of `Rp` refined by the parabola through
    /// the best point and its neighbours, for metals, a semiconductor and strong absorbers;
    /// the two agree to 2e-6 rad (the scan's parabola is exact to O(h^3) = 1e-15 of curvature
    /// terms, so the tolerance is the search's 1e-7 plus the parabola's rounding).
    #[test]
    fn pseudo_brewster_agrees_with_a_scan() {
        for (n, k) in [
            (1.02, 2.577),
            (0.43, 2.455),
            (0.06, 3.586),
            (3.85, 0.02),
            (5.0, 10.0),
        ] {
            let idx = RefractiveIndex::new(n, k).unwrap();
            let rp = |t: f64| amplitudes(&idx, t).unwrap().rp_power();
            let h = 1e-3f64.to_radians();
            let steps = (std::f64::consts::FRAC_PI_2 / h) as usize;
            let best = (1..steps)
                .min_by(|&i, &j| rp(i as f64 * h).total_cmp(&rp(j as f64 * h)))
                .unwrap();
            let (ym, y0, yp) = (
                rp((best - 1) as f64 * h),
                rp(best as f64 * h),
                rp((best + 1) as f64 * h),
            );
            let scan = best as f64 * h + 0.5 * h * (ym - yp) / (ym - 2.0 * y0 + yp);
            let pb = idx.pseudo_brewster();
            assert!(
                (pb.angle_rad - scan).abs() < 2e-6,
                "n {n} k {k}: {} vs {scan}",
                pb.angle_rad
            );
        }
    }

    /// As `k -> 0` the pseudo-Brewster angle tends to atan(n) and `Rp` there to 0: at
    /// `k = 1e-4` both move by O(k^2) ~ 1e-8, so within the search's 1e-7 rad and 1e-6 in Rp.
    #[test]
    fn pseudo_brewster_tends_to_brewster_as_k_vanishes() {
        for n in [1.33, 1.52, 2.4] {
            let idx = RefractiveIndex::new(n, 1e-4).unwrap();
            let pb = idx.pseudo_brewster();
            assert!(
                (pb.angle_rad - n.atan()).abs() < 2e-7,
                "n {n}: {} vs {}",
                pb.angle_rad,
                n.atan()
            );
            assert!(pb.rp_min < 1e-6, "n {n}: {}", pb.rp_min);
            let dielectric = RefractiveIndex::new(n, 0.0).unwrap().pseudo_brewster();
            assert_eq!(dielectric.angle_rad, n.atan());
        }
    }
}
