//! The clear sky of Rayleigh plus aerosol single scattering (MODEL.md section 10), with the
//! Henyey-Greenstein phase function of its aerosol.

use crate::air_mass::slant_mu0;
use crate::polarization::Stokes;
use crate::sky::radiance::SkyRadiance;
use crate::sky::rayleigh::{downward_path, single_scattered, RayleighSky};
use nalgebra::Vector3;
use std::f64::consts::PI;

/// A clear sky of Rayleigh plus aerosol single scattering in a plane-parallel layer: molecules
/// scatter with the depolarised Rayleigh phase matrix, aerosol unpolarised with a
/// Henyey-Greenstein phase function (its polarisation, small in the visible, is neglected).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClearSky {
    /// Rayleigh optical depth.
    pub rayleigh: f64,
    /// Aerosol optical depth.
    pub aerosol: f64,
    /// Aerosol single-scattering albedo.
    pub ssa: f64,
    /// Aerosol asymmetry parameter.
    pub g: f64,
    /// Molecular depolarisation factor.
    pub depolarization: f64,
    /// Unit vector towards the sun.
    pub sun: Vector3<f64>,
}

impl ClearSky {
    /// Henyey-Greenstein phase function normalised to average 1 over the sphere.
    #[inline]
    pub fn henyey_greenstein(g: f64, cos_gamma: f64) -> f64 {
        let d = 1.0 + g * g - 2.0 * g * cos_gamma;
        (1.0 - g * g) / (d * d.sqrt())
    }

    /// Optical-depth-weighted source `(omega P11, -omega P12)` of the mixture, phase functions
    /// averaging 1 (so a conservative Rayleigh layer has `omega P11` averaging 1).
    pub fn source(&self, cos_gamma: f64) -> (f64, f64) {
        let tau = self.rayleigh + self.aerosol;
        if tau == 0.0 {
            return (0.0, 0.0);
        }
        let r = RayleighSky {
            optical_depth: self.rayleigh,
            depolarization: self.depolarization,
        };
        let (p11, p12) = r.phase(cos_gamma);
        let hg = ClearSky::henyey_greenstein(self.g, cos_gamma);
        (
            (self.rayleigh * p11 + self.ssa * self.aerosol * hg) / tau,
            self.rayleigh * p12 / tau,
        )
    }
}

impl SkyRadiance for ClearSky {
    /// Downwelling single-scattering radiance per unit TOA irradiance (the formula of
    /// [`RayleighSky::stokes`] with the mixture's source).
    fn stokes_from(&self, towards: &Vector3<f64>) -> Stokes {
        let path = downward_path(
            self.rayleigh + self.aerosol,
            slant_mu0(self.sun.z),
            towards.z.max(0.0),
        );
        let (p11, p12) = self.source(self.sun.dot(towards).clamp(-1.0, 1.0));
        single_scattered(p11, p12, path, &self.sun, towards)
    }
}

/// The sky irradiance's phase functions integrated over azimuth, for the sun at `mu0`: the
/// Rayleigh phase `P11 = alpha + beta cos^2 gamma` in closed form, Henyey-Greenstein's by
/// [`hg_azimuthal`].
pub(crate) struct AzimuthalPhase {
    pub(crate) alpha: f64,
    pub(crate) beta: f64,
    pub(crate) mu0: f64,
    pub(crate) g: f64,
}

impl AzimuthalPhase {
    pub(crate) fn new(rayleigh: &RayleighSky, g: f64, mu0: f64) -> AzimuthalPhase {
        let (p0, _) = rayleigh.phase(0.0);
        let (p1, _) = rayleigh.phase(1.0);
        AzimuthalPhase {
            alpha: p0,
            beta: p1 - p0,
            mu0,
            g,
        }
    }

    /// `int_0^{2 pi} P11 dphi` at `mu`: `cos gamma = mu mu0 + s s0 cos phi` averages
    /// `mu^2 mu0^2 + s^2 s0^2 / 2` in its square.
    pub(crate) fn rayleigh(&self, mu: f64) -> f64 {
        let (mu0, s0sq) = (self.mu0, 1.0 - self.mu0 * self.mu0);
        2.0 * PI * (self.alpha + self.beta * (mu * mu * mu0 * mu0 + 0.5 * (1.0 - mu * mu) * s0sq))
    }

    /// `int_0^{2 pi} P_HG dphi` at `mu`.
    pub(crate) fn hg(&self, mu: f64) -> f64 {
        hg_azimuthal(self.g, mu, self.mu0)
    }

    /// The width in `mu` of the HG term's peak at `mu0` (the sun's aureole), about
    /// `(1 - |g|) max(sin theta0, 1 - |g|)`: an angular width `1 - |g|` seen at `theta0`, or
    /// around the zenith sun.
    pub(crate) fn peak_width(&self) -> f64 {
        let forward = 1.0 - self.g.abs();
        forward * (1.0 - self.mu0 * self.mu0).max(0.0).sqrt().max(forward)
    }

    /// Whether Simpson's rule on `intervals` resolves the peak, with 8 points or more across
    /// it: its error test, a change between two grids, cannot see a peak both step over (with
    /// g 0.99 and the sun 5 deg from the zenith, 384 intervals claimed 6.1e-3 and were 1.6e-2
    /// off, `sky_irradiance_on_the_tables_meets_its_error`).
    pub(crate) fn resolves(&self, intervals: usize) -> bool {
        8.0 / intervals as f64 <= self.peak_width()
    }

    /// Breakpoints of `[0, 1]` for an adaptive rule: `0`, `mu0`, `1` and `mu0 +- w grading^k /
    /// grading` for the peak's width `w`, `k >= 0`, sorted. Over `[0, 1]` whole, the adaptive
    /// rule stepped over the peak at the zenith sun with g 0.95 and tol 1e-8: 1.1e-11 off with
    /// 1.4e-13 claimed.
    pub(crate) fn breaks(&self, grading: f64) -> Vec<f64> {
        let peak = self.mu0.clamp(0.0, 1.0);
        let mut breaks = vec![0.0, peak, 1.0];
        let mut step = self.peak_width() / grading;
        while step > 0.0 && step < 1.0 {
            breaks.extend(
                [peak - step, peak + step]
                    .into_iter()
                    .filter(|b| *b > 0.0 && *b < 1.0),
            );
            step *= grading;
        }
        breaks.sort_by(f64::total_cmp);
        breaks.dedup();
        breaks
    }

    /// `mu` times each, at `mu = j / intervals` ([`irradiance_on_table`]'s `phases`).
    pub(crate) fn on_grid(&self, intervals: usize) -> Vec<(f64, f64)> {
        (0..=intervals)
            .map(|j| {
                let mu = j as f64 / intervals as f64;
                (mu * self.rayleigh(mu), mu * self.hg(mu))
            })
            .collect()
    }
}

/// Complete elliptic integral of the second kind `E(m)`, `m = k^2` in `[0, 1]`, by the
/// arithmetic-geometric mean (Abramowitz & Stegun 17.6).
pub(crate) fn elliptic_e(m: f64) -> f64 {
    let m = m.clamp(0.0, 1.0);
    if m == 1.0 {
        return 1.0;
    }
    let (mut a, mut b) = (1.0, (1.0 - m).sqrt());
    let mut sum = 0.5 * m; // 2^(n-1) c_n^2 at n = 0, c0^2 = m
    let mut pow = 0.5;
    for _ in 0..40 {
        let c = 0.5 * (a - b);
        pow *= 2.0;
        sum += pow * c * c;
        let (an, bn) = (0.5 * (a + b), (a * b).sqrt());
        a = an;
        b = bn;
        if c.abs() < 1e-17 {
            break;
        }
    }
    PI / (2.0 * a) * (1.0 - sum)
}

/// `int_0^{2 pi} HG(g, cos gamma) dphi` for a view at `mu` and the sun at `mu0`
/// (`cos gamma = mu mu0 + s s0 cos phi`): with `A = 1 + g^2 - 2 g mu mu0`, `B = 2 g s s0`,
/// `int_0^pi (A - B cos phi)^{-3/2} dphi = 2 E(2B / (A + B)) / ((A - B) sqrt(A + B))`
/// (Gradshteyn & Ryzhik 2.575).
pub(crate) fn hg_azimuthal(g: f64, mu: f64, mu0: f64) -> f64 {
    let (s, s0) = (
        (1.0 - mu * mu).max(0.0).sqrt(),
        (1.0 - mu0 * mu0).max(0.0).sqrt(),
    );
    let a = 1.0 + g * g - 2.0 * g * mu * mu0;
    let b = (2.0 * g * s * s0).abs();
    (1.0 - g * g) * 4.0 * elliptic_e(2.0 * b / (a + b)) / ((a - b) * (a + b).sqrt())
}
