//! Linear Stokes vectors and 3x3 Mueller matrices (MODEL.md section 0).
//!
//! The imaging chain is linear-polarisation only, so Stokes vectors have three components
//! `[S0, S1, S2]` and Mueller matrices are 3x3. A Stokes vector is always expressed in a
//! reference frame `(x, y)` transverse to the propagation direction `k` with `x × y = k`;
//! `S1 > 0` means polarised along `x`, `S2 > 0` along `+45 deg` (from `x` towards `y`).
//! Which frame a value is in is carried by its name (`stokes_facet`, `out_from_in`, ...).

use nalgebra::{Matrix3, Vector3};
use std::f64::consts::FRAC_PI_2;

/// A linear Stokes vector `[S0, S1, S2]` in some transverse frame (named by the variable).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stokes(pub Vector3<f64>);

impl Stokes {
    /// Builds a Stokes vector from its components.
    pub fn new(s0: f64, s1: f64, s2: f64) -> Self {
        Stokes(Vector3::new(s0, s1, s2))
    }

    /// Unpolarised light of intensity `s0`.
    pub fn unpolarized(s0: f64) -> Self {
        Stokes::new(s0, 0.0, 0.0)
    }

    /// Fully linearly polarised light of intensity `s0` at angle `aop_rad` from the x axis.
    pub fn linear(s0: f64, aop_rad: f64) -> Self {
        let (s, c) = (2.0 * aop_rad).sin_cos();
        Stokes::new(s0, s0 * c, s0 * s)
    }

    /// Total intensity `S0`.
    pub fn s0(&self) -> f64 {
        self.0[0]
    }

    /// Linearly polarised intensity `p = sqrt(S1^2 + S2^2)`, computed without overflow.
    pub fn polarized_intensity(&self) -> f64 {
        self.0[1].hypot(self.0[2])
    }

    /// Degree of linear polarisation `sqrt(S1^2 + S2^2) / S0` (Meng (2012) Eq. 2.14).
    ///
    /// `None` when `S0` is not positive and normal (below `f64::MIN_POSITIVE` a subnormal
    /// `S0` has lost its relative precision: effectively dark) or a component is not finite (a
    /// dark pixel has no DoLP). The value is not clamped to `[0, 1]`: a noisy reconstruction
    /// may exceed 1 and callers that estimate statistics need the raw estimator.
    pub fn dolp(&self) -> Option<f64> {
        let s0 = self.s0();
        let p = self.polarized_intensity();
        (s0 >= f64::MIN_POSITIVE && s0.is_finite() && p.is_finite()).then(|| p / s0)
    }

    /// Angle of linear polarisation `0.5 atan2(S2, S1)` in `(-pi/2, pi/2]` (Meng (2012) Eq. 2.15).
    ///
    /// `None` when `S1 = S2 = 0` (unpolarised light has no AoP) or a component is not finite.
    pub fn aop_rad(&self) -> Option<f64> {
        let (s1, s2) = (self.0[1], self.0[2]);
        if !(s1.is_finite() && s2.is_finite()) || (s1 == 0.0 && s2 == 0.0) {
            return None;
        }
        let a = 0.5 * s2.atan2(s1);
        // atan2(-0.0, negative) = -pi: fold the excluded end of the interval onto +pi/2.
        Some(if a <= -FRAC_PI_2 {
            a + std::f64::consts::PI
        } else {
            a
        })
    }
}

/// A 3x3 Mueller matrix acting on linear Stokes vectors, `S_out = M S_in`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mueller(pub Matrix3<f64>);

impl Mueller {
    /// The identity (free propagation).
    pub fn identity() -> Self {
        Mueller(Matrix3::identity())
    }

    /// Applies the matrix to a Stokes vector.
    pub fn apply(&self, s: &Stokes) -> Stokes {
        Stokes(self.0 * s.0)
    }

    /// Composition `self * rhs` (apply `rhs` first).
    pub fn then_after(&self, rhs: &Mueller) -> Mueller {
        Mueller(self.0 * rhs.0)
    }

    /// The Stokes vector this element produces from unpolarised light of unit intensity
    /// (its first column).
    pub fn response_to_unpolarized(&self) -> Stokes {
        Stokes(self.0.column(0).into_owned())
    }

    /// DoLP of the output for unpolarised input, `sqrt(M10^2 + M20^2) / M00` (Meng (2012) Eq. 3.20).
    /// `None` when `M00 <= 0`.
    pub fn dolp_unpolarized(&self) -> Option<f64> {
        self.response_to_unpolarized().dolp()
    }
}

/// The analyzer row `m(psi) = 0.5 [1, cos 2psi, sin 2psi]` of an ideal linear analyzer
/// (Meng (2012) Eq. 1.32 / 3.32): the transmitted intensity is `m^T S`.
pub fn analyzer_row(psi_rad: f64) -> Vector3<f64> {
    let (s, c) = (2.0 * psi_rad).sin_cos();
    Vector3::new(0.5, 0.5 * c, 0.5 * s)
}

/// Mueller matrix of an ideal linear polarizer with its axis at `psi` from the x axis
/// (Meng (2012) Eq. 2.17): `0.5 [[1, c, s], [c, c^2, cs], [s, cs, s^2]]`, `c = cos 2psi`, `s = sin 2psi`.
pub fn linear_polarizer(psi_rad: f64) -> Mueller {
    let (s, c) = (2.0 * psi_rad).sin_cos();
    Mueller(
        0.5 * Matrix3::new(
            1.0,
            c,
            s, //
            c,
            c * c,
            c * s, //
            s,
            c * s,
            s * s,
        ),
    )
}

/// Rotation of the reference frame by `eta` about the propagation direction (Meng (2012) Eq. 3.8 with the
/// sign typo fixed): `[[1, 0, 0], [0, cos 2eta, sin 2eta], [0, -sin 2eta, cos 2eta]]`.
///
/// If `S_old` is expressed in frame `(x, y)` and the new frame's x axis is `x` turned by `eta`
/// towards `y`, then `S_new = rotation(eta) S_old`.
pub fn rotation(eta_rad: f64) -> Mueller {
    let (s, c) = (2.0 * eta_rad).sin_cos();
    rotation_from_cos_sin_2eta(c, s)
}

/// [`rotation`] from `cos 2eta` and `sin 2eta` directly (no trigonometry; used on hot paths where
/// the angle comes from vector dot and cross products).
pub fn rotation_from_cos_sin_2eta(cos_2eta: f64, sin_2eta: f64) -> Mueller {
    Mueller(Matrix3::new(
        1.0, 0.0, 0.0, //
        0.0, cos_2eta, sin_2eta, //
        0.0, -sin_2eta, cos_2eta,
    ))
}

/// `(cos 2eta, sin 2eta)` of the signed angle `eta` that turns unit vector `from_x` into unit
/// vector `to_x` about the unit propagation direction `k` (both transverse to `k`).
///
/// Uses `cos eta = from·to`, `sin eta = (from × to)·k`, then the double-angle identities, so the
/// sign of the rotation is kept (Meng (2012)'s arc-cosine Eqs. 3.9-3.10 lose it).
pub fn cos_sin_2eta(from_x: &Vector3<f64>, to_x: &Vector3<f64>, k: &Vector3<f64>) -> (f64, f64) {
    let c = from_x.dot(to_x);
    let s = from_x.cross(to_x).dot(k);
    // Renormalise: (c, s) is a unit vector up to rounding; keep R exactly orthogonal.
    let n2 = c * c + s * s;
    ((c * c - s * s) / n2, 2.0 * c * s / n2)
}
