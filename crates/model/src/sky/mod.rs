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
//!
//! * [`radiance`]: the [`SkyRadiance`] trait and the surface-frame conventions;
//! * [`uniform`]: an unpolarised uniform sky;
//! * [`rayleigh`]: Rayleigh single scattering, and the sunlit Rayleigh sky;
//! * [`berry`]: the Berry-Dennis-Lee neutral-point form;
//! * [`band`]: a band sky's `mu` tables and their interpolation;
//! * [`clear`]: the clear sky of Rayleigh plus Henyey-Greenstein aerosol, and its phase
//!   functions integrated over azimuth;
//! * [`table`]: a sky tabulated by a radiative-transfer code.

pub mod band;
pub mod berry;
pub mod clear;
pub mod radiance;
pub mod rayleigh;
pub mod table;
pub mod uniform;

pub use crate::angles::direction_from_deg;
pub use berry::BerrySky;
pub use clear::ClearSky;
pub(crate) use radiance::stokes_in_frame_each;
pub use radiance::SkyRadiance;
pub use rayleigh::{rayleigh_optical_depth, RayleighSky, SunlitRayleigh, AIR_DEPOLARIZATION};
pub use table::{SkyTable, SkyTableError, StokesReference};
pub use uniform::UniformSky;

#[cfg(test)]
mod tests {
    use super::radiance::e_vector_in_frame;
    use super::*;
    use nalgebra::Vector3;

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
