//! Skies as the reflection integrals see them: the [`SkyRadiance`] trait (the Stokes radiance
//! arriving from each direction of the upper hemisphere), an unpolarised uniform sky, and the
//! clear sky's polarised radiance by Rayleigh single scattering (MODEL.md section 10), with the
//! Berry neutral-point form.
//!
//! Directions on the sky are given by zenith angle and azimuth **clockwise from north** (x east,
//! y north, z up). The Stokes vector of light arriving from sky direction `d` is expressed in
//! that ray's surface frame (the convention of [`crate::pbrdf`]): propagation `k = -d`,
//! `x = s ∝ k × z` (horizontal, perpendicular to the vertical plane through `d`), `y = k × x`.
//! So `S1 > 0` is a horizontal E-vector, and the same Stokes vector is the incident state the
//! pBRDF expects for that direction.

pub use crate::angles::direction_from_deg;
use crate::error::ModelError;
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

    fn peak(&self) -> Option<Vector3<f64>> {
        Some(self.sun)
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

/// Rayleigh optical depth of the whole atmosphere at sea level (standard pressure),
/// `tau_R = 0.008569 l^-4 (1 + 0.0113 l^-2 + 0.00013 l^-4)`, `l` in micrometres
/// (Hansen & Travis, Space Sci. Rev. 16, 527 (1974), Eq. 2.30; MODEL.md section 10).
pub fn rayleigh_optical_depth(wavelength_um: f64) -> Result<f64, ModelError> {
    let l = ModelError::check_range(
        "wavelength_nm",
        wavelength_um * 1e3,
        200.0,
        3000.0,
        "[200, 3000]",
    )? * 1e-3;
    let l2 = 1.0 / (l * l);
    Ok(0.008569 * l2 * l2 * (1.0 + 0.0113 * l2 + 0.00013 * l2 * l2))
}

/// Molecular depolarisation factor of air (Young, Appl. Opt. 19, 3427 (1980); MODEL.md).
pub const AIR_DEPOLARIZATION: f64 = 0.0279;

/// A Rayleigh (molecular) single-scattering sky over a plane-parallel, homogeneous layer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayleighSky {
    /// Vertical optical depth of the layer.
    pub optical_depth: f64,
    /// Molecular depolarisation factor `rho_n` (0 for ideal dipoles).
    pub depolarization: f64,
}

impl RayleighSky {
    /// The sea-level Rayleigh sky at `wavelength_nm`, depolarisation 0.0279.
    pub fn at_wavelength(wavelength_nm: f64) -> Result<Self, ModelError> {
        Ok(RayleighSky {
            optical_depth: rayleigh_optical_depth(wavelength_nm * 1e-3)?,
            depolarization: AIR_DEPOLARIZATION,
        })
    }

    /// `Delta = (1 - rho) / (1 + rho / 2)`: the fraction of the phase matrix that is dipole-like
    /// (Hansen & Travis 1974, Eq. 2.15).
    fn delta(&self) -> f64 {
        (1.0 - self.depolarization) / (1.0 + 0.5 * self.depolarization)
    }

    /// Phase-matrix elements `(P11, -P12)` at scattering angle with cosine `cos_gamma`,
    /// normalised so that `P11` averages to 1 over the sphere.
    pub fn phase(&self, cos_gamma: f64) -> (f64, f64) {
        let d = self.delta();
        let c2 = cos_gamma * cos_gamma;
        (0.75 * d * (1.0 + c2) + (1.0 - d), 0.75 * d * (1.0 - c2))
    }

    /// Degree of linear polarisation of singly scattered light at scattering angle `gamma`:
    /// `-P12 / P11`; its maximum, at 90 deg, is `0.75 Delta / (1 - 0.25 Delta)` = 0.9457 for
    /// air. (MODEL.md's `d_max sin^2 / (1 + cos^2)` is the same curve to first order in `rho`.)
    pub fn dolp(&self, cos_gamma: f64) -> f64 {
        let (p11, p12) = self.phase(cos_gamma);
        p12 / p11
    }

    /// Sky Stokes radiance per unit top-of-atmosphere solar irradiance (sr^-1), for light arriving
    /// from `view` (unit, upward) with the sun towards `sun` (unit), single scattering at the
    /// bottom of the layer (Liou, *An Introduction to Atmospheric Radiation*, 2nd ed., Eq. 3.5.x
    /// for the diffuse downward intensity):
    /// `L = P11(gamma) / (4 pi) * mu0 / (mu0 - mu) * (exp(-tau/mu0) - exp(-tau/mu))`,
    /// evaluated with `expm1` so that `mu = mu0` and the horizon are exact limits.
    /// Errors name `sun_zenith_deg` or `zenith_deg` when a direction is below the horizon.
    pub fn stokes(&self, sun: &Vector3<f64>, view: &Vector3<f64>) -> Result<Stokes, ModelError> {
        if sun.z.is_nan() || sun.z < 0.0 {
            return Err(ModelError::OutOfRange {
                field: "sun_zenith_deg",
                value: sun.z.clamp(-1.0, 1.0).acos().to_degrees(),
                allowed: "[0, 90]",
            });
        }
        if view.z.is_nan() || view.z < 0.0 {
            return Err(ModelError::OutOfRange {
                field: "zenith_deg",
                value: view.z.clamp(-1.0, 1.0).acos().to_degrees(),
                allowed: "[0, 90]",
            });
        }
        let cos_gamma = sun.dot(view).clamp(-1.0, 1.0);
        let (p11, p12) = self.phase(cos_gamma);
        Ok(single_scattered(
            p11,
            p12,
            downward_path(
                self.optical_depth,
                crate::air_mass::slant_mu0(sun.z),
                view.z,
            ),
            sun,
            view,
        ))
    }
}

/// The geometric factor of downward single scattering at the bottom of a homogeneous layer of
/// optical depth `tau`, sun at `mu0 = cos`, view at `mu = cos` (Liou, *An Introduction to
/// Atmospheric Radiation*): `mu0 / (mu0 - mu) (e^{-tau/mu0} - e^{-tau/mu})`, evaluated with
/// `expm1` so that `mu = mu0` and the horizon are exact limits. `mu0` enters only through the
/// sun beam's attenuation, so callers pass the pseudo-spherical
/// [`crate::air_mass::slant_mu0`].
pub(crate) fn downward_path(tau: f64, mu0: f64, mu: f64) -> f64 {
    if mu0 <= 0.0 || tau == 0.0 {
        0.0
    } else {
        downward_path_beam(tau, mu0, mu, (-tau / mu0).exp())
    }
}

/// [`downward_path`] for `mu0 > 0` and `tau != 0` with the sun beam's attenuation
/// `beam = e^{-tau/mu0}` given, so that the points of one layer's `mu` table take it once (the
/// same values to the bit).
pub(crate) fn downward_path_beam(tau: f64, mu0: f64, mu: f64, beam: f64) -> f64 {
    if mu <= 0.0 {
        beam
    } else {
        // = e^{-tau/mu0} (tau/mu) (1 - e^{-x})/x, x = tau (mu0 - mu) / (mu mu0).
        let x = tau * (mu0 - mu) / (mu * mu0);
        let ratio = if x.abs() < 1e-12 {
            1.0 - 0.5 * x
        } else {
            -(-x).exp_m1() / x
        };
        beam * (tau / mu) * ratio
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
fn cos_sin_2chi(k: &Vector3<f64>, e: &Vector3<f64>) -> (f64, f64) {
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

/// Stokes radiance per unit TOA irradiance of singly scattered light arriving from `towards`,
/// from a source `(omega P11, -omega P12)` (phase functions averaging 1) and the geometric
/// `path` factor.
pub(crate) fn single_scattered(
    p11: f64,
    p12: f64,
    path: f64,
    sun: &Vector3<f64>,
    towards: &Vector3<f64>,
) -> Stokes {
    let radiance = p11 / (4.0 * std::f64::consts::PI) * path;
    if radiance == 0.0 {
        return Stokes::new(0.0, 0.0, 0.0);
    }
    let (c2, s2) = e_vector_in_frame(&-towards, sun);
    let p = radiance * p12 / p11;
    Stokes::new(radiance, p * c2, p * s2)
}

/// The Berry-Dennis-Lee sky (Berry, Dennis & Lee, New J. Phys. 6, 162 (2004)): the Rayleigh
/// pattern's one double neutral point at the sun (and one at the antisun) split into the
/// Babinet and Brewster points `separation` apart above and below the sun (and the Arago point
/// and its partner about the antisun), which is how the real sky, with multiple scattering,
/// looks. In the stereographic chart `zeta = tan(theta / 2) e^{i phi}` the polarisation is
/// `w = -4 (z - zBa)(z - zBr)(z + 1/zBr*)(z + 1/zBa*) / ((1 + |z|^2)^2 |zBa + 1/zBa*| |zBr + 1/zBr*|)`,
/// the DoLP `d_max |w| / (2 - |w|)` and the E-vector at `arg(w e^{-2i phi_sun}) / 2` in the chart. With zero
/// separation it is the Rayleigh pattern (tested).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BerrySky {
    /// Unit vector towards the sun.
    pub sun: Vector3<f64>,
    /// Angle between the Babinet and Brewster points, radians (about 0.5 in a clear sky).
    pub separation_rad: f64,
    /// Largest DoLP (at 90 deg from the sun when the separation is 0).
    pub max_dolp: f64,
}

impl BerrySky {
    /// Chart coordinate of a direction (x east, y north, z up).
    fn chart(d: &Vector3<f64>) -> num_complex::Complex64 {
        let theta = d.z.clamp(-1.0, 1.0).acos();
        let phi = d.y.atan2(d.x);
        num_complex::Complex64::from_polar((0.5 * theta).tan(), phi)
    }

    /// `(DoLP, cos 2chi, sin 2chi)` of light arriving from `towards` (unit, upward), `chi` the
    /// E-vector's angle in the frame of this module (x horizontal) for the ray `-towards`.
    pub fn polarization(&self, towards: &Vector3<f64>) -> (f64, f64, f64) {
        use num_complex::Complex64 as C;
        let theta_s = self.sun.z.clamp(-1.0, 1.0).acos();
        let phi_s = self.sun.y.atan2(self.sun.x);
        let half = 0.5 * self.separation_rad;
        let z_ba = C::from_polar((0.5 * (theta_s - half)).tan(), phi_s);
        let z_br = C::from_polar((0.5 * (theta_s + half)).tan(), phi_s);
        let z = Self::chart(towards);
        // (z + 1/z0*) / |z0 + 1/z0*| = (1 + z z0*) (z0/|z0|) / (1 + |z0|^2): finite at z0 = 0
        // (the sun at the zenith), where z0/|z0| is taken as the sun's azimuth.
        let factor = |z0: C| {
            let unit = if z0.norm() > 1e-12 {
                z0 / z0.norm()
            } else {
                C::from_polar(1.0, phi_s)
            };
            (1.0 + z * z0.conj()) * unit / (1.0 + z0.norm_sqr())
        };
        let w = -4.0 * (z - z_ba) * (z - z_br) * factor(z_ba) * factor(z_br)
            / (1.0 + z.norm_sqr()).powi(2);
        let m = w.norm().min(1.0);
        let dolp = self.max_dolp * m / (2.0 - m);
        let phi = towards.y.atan2(towards.x);
        // The E-vector's chart angle is arg(w e^{-2i phi_s}) / 2 (the inscribed-angle theorem on
        // the circles through the neutral points); on the sphere it is measured from the local
        // radial direction e_theta towards e_phi.
        let chi = 0.5 * w.arg() - phi_s;
        let a = chi - phi;
        let theta = towards.z.clamp(-1.0, 1.0).acos();
        let e_theta = Vector3::new(
            theta.cos() * phi.cos(),
            theta.cos() * phi.sin(),
            -theta.sin(),
        );
        let e_phi = Vector3::new(-phi.sin(), phi.cos(), 0.0);
        let e = e_theta * a.cos() + e_phi * a.sin();
        let (c2, s2) = cos_sin_2chi(&-towards, &e);
        (dolp, c2, s2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// REFERENCE_VALUES.md: 0.22129 (450 nm), 0.09728 (550 nm), 0.04932 (650 nm).
    #[test]
    fn rayleigh_optical_depth_reference_values() {
        for (nm, tau) in [(450.0, 0.22129), (550.0, 0.09728), (650.0, 0.04932)] {
            let t = rayleigh_optical_depth(nm * 1e-3).unwrap();
            assert!((t - tau).abs() < 6e-6, "{nm}: {t}");
        }
        assert!(rayleigh_optical_depth(0.1)
            .unwrap_err()
            .to_string()
            .contains("wavelength_nm"));
    }

    /// Maximum DoLP 0.9457 at 90 deg from the sun (REFERENCE_VALUES.md), 0 towards the sun.
    #[test]
    fn maximum_dolp_and_neutral_sun() {
        let sky = RayleighSky::at_wavelength(550.0).unwrap();
        assert!((sky.dolp(0.0) - 0.9457).abs() < 5e-5, "{}", sky.dolp(0.0));
        assert_eq!(sky.dolp(1.0), 0.0);
        let ideal = RayleighSky {
            optical_depth: 0.1,
            depolarization: 0.0,
        };
        assert!((ideal.dolp(0.0) - 1.0).abs() < 1e-15);
    }

    /// Sun at the zenith, view at 60 deg zenith: gamma = 60 deg, the E-vector is horizontal
    /// (perpendicular to the vertical plane containing sun and view), so S2 = 0 and S1 > 0;
    /// the radiance matches the closed form.
    #[test]
    fn sun_at_zenith_gives_horizontal_e_vector() {
        let sky = RayleighSky::at_wavelength(550.0).unwrap();
        for az in [0.0, 77.0, 200.0] {
            let s = sky
                .stokes(&Vector3::z(), &direction_from_deg(60.0, az))
                .unwrap();
            assert!(s.0[2].abs() < 1e-15 * s.0[0] && s.0[1] > 0.0, "{s:?}");
            assert!((s.dolp().unwrap() - sky.dolp(0.5)).abs() < 1e-14);
            let tau = sky.optical_depth;
            let closed = sky.phase(0.5).0 / (4.0 * std::f64::consts::PI) * 1.0 / (1.0 - 0.5)
                * ((-tau).exp() - (-tau / 0.5).exp());
            assert!((s.0[0] - closed).abs() < 1e-14, "{} vs {closed}", s.0[0]);
        }
    }

    /// Looking into the sun's own zenith angle (mu = mu0) is the exact limit tau/mu e^{-tau/mu},
    /// the horizon is finite, and a sun below the horizon is an error naming the field.
    #[test]
    fn limits_and_errors() {
        let sky = RayleighSky::at_wavelength(550.0).unwrap();
        let sun = direction_from_deg(50.0, 0.0);
        let same = sky.stokes(&sun, &direction_from_deg(50.0, 90.0)).unwrap();
        let near = sky
            .stokes(&sun, &direction_from_deg(50.0 + 1e-7, 90.0))
            .unwrap();
        assert!((same.0[0] - near.0[0]).abs() < 1e-8 * same.0[0]);
        let horizon = sky.stokes(&sun, &direction_from_deg(90.0, 90.0)).unwrap();
        assert!(horizon.0.iter().all(|v| v.is_finite()) && horizon.0[0] > 0.0);
        let e = sky
            .stokes(&direction_from_deg(95.0, 0.0), &Vector3::z())
            .unwrap_err()
            .to_string();
        assert!(e.contains("sun_zenith_deg"), "{e}");
    }

    /// With zero separation the Berry-Dennis-Lee sky is the Rayleigh pattern: DoLP
    /// `d_max sin^2 / (1 + cos^2)` and the same E-vector (1e-9), for suns from the zenith to
    /// near the horizon; with a separation, the DoLP vanishes at the Babinet and Brewster
    /// points, `separation / 2` above and below the sun on its vertical.
    #[test]
    fn berry_reduces_to_rayleigh_and_has_split_neutral_points() {
        for (sz, sa) in [(0.0, 0.0), (30.0, 40.0), (60.0, 200.0), (85.0, 300.0)] {
            let sun = direction_from_deg(sz, sa);
            let b = BerrySky {
                sun,
                separation_rad: 0.0,
                max_dolp: 1.0,
            };
            for (z, a) in [
                (10.0, 0.0),
                (45.0, 90.0),
                (70.0, 250.0),
                (89.0, 10.0),
                (0.0, 0.0),
            ] {
                let d = direction_from_deg(z, a);
                let cg: f64 = sun.dot(&d);
                if (1.0 - cg.abs()) < 1e-6 {
                    continue;
                }
                let (p, c2, s2) = b.polarization(&d);
                let want = (1.0 - cg * cg) / (1.0 + cg * cg);
                assert!(
                    (p - want).abs() < 1e-9,
                    "sun {sz},{sa} view {z},{a}: {p} vs {want}"
                );
                let (rc, rs) = e_vector_in_frame(&-d, &sun);
                assert!(
                    (c2 - rc).abs() < 1e-9 && (s2 - rs).abs() < 1e-9,
                    "sun {sz},{sa} view {z},{a}: ({c2},{s2}) vs ({rc},{rs})"
                );
            }
        }
        let sun = direction_from_deg(60.0, 90.0);
        let b = BerrySky {
            sun,
            separation_rad: 0.5,
            max_dolp: 0.8,
        };
        for zen in [60.0 - 0.25f64.to_degrees(), 60.0 + 0.25f64.to_degrees()] {
            let (p, _, _) = b.polarization(&direction_from_deg(zen, 90.0));
            assert!(p < 1e-12, "zenith {zen}: dolp {p}");
        }
        let (p, _, _) = b.polarization(&direction_from_deg(60.0, 90.0));
        assert!(
            p > 1e-3,
            "between the neutral points the light is polarised: {p}"
        );
    }
}
