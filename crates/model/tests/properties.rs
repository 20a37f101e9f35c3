//! Property tests (proptest) of physical identities that must hold for every input in the domain.

#![allow(clippy::unwrap_used)] // tests panic on failure by design

use nalgebra::Vector3;
use polar_model::analyzer::AnalyzerSet;
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::pbrdf::{Geometry, Surface};
use polar_model::polarization::{cos_sin_2eta, linear_polarizer, rotation, Stokes};
use polar_model::quadrature::Tolerance;
use proptest::prelude::*;
use std::f64::consts::{FRAC_PI_2, PI};

fn index() -> impl Strategy<Value = RefractiveIndex> {
    (0.05f64..10.0, 0.0f64..10.0).prop_map(|(n, k)| RefractiveIndex::new(n, k).unwrap())
}

fn surface() -> impl Strategy<Value = Surface> {
    prop_oneof![
        (index(), 1e-3f64..1.0, 0.0f64..1.0)
            .prop_map(|(i, s, d)| Surface::microfacet(i, s, d).unwrap()),
        (index(), 0.0f64..0.3).prop_map(|(i, f)| Surface::vegetation(i, f).unwrap()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// At 45 deg, rp = rs (cos - sin) ... squared: Rp = Rs^2 exactly for any complex index
    /// (Azzam's identity). Relative tolerance 1e-12: a few roundings of O(1) quantities.
    #[test]
    fn rp_equals_rs_squared_at_45_deg(idx in index()) {
        let a = amplitudes(&idx, std::f64::consts::FRAC_PI_4).unwrap();
        let (rs, rp) = (a.rs_power(), a.rp_power());
        prop_assert!((rp - rs * rs).abs() <= 1e-12 * rs.max(1e-300), "Rs {rs} Rp {rp}");
    }

    /// Rp vanishes at Brewster's angle atan(n) for every dielectric (n > 1 or n < 1).
    /// |rp| there is a difference of two equal O(n^2) terms: tolerance 1e-26 on Rp = |rp|^2.
    #[test]
    fn rp_vanishes_at_brewster(n in 0.2f64..10.0) {
        let idx = RefractiveIndex::new(n, 0.0).unwrap();
        let rp = amplitudes(&idx, idx.brewster_angle_rad()).unwrap().rp_power();
        prop_assert!(rp < 1e-26, "Rp(Brewster) = {rp} for n = {n}");
    }

    /// Helmholtz reciprocity of the intensity element: f00(ti, tr, phi) = f00(tr, ti, phi).
    /// Every factor of Eqs. 3.6-3.15 and 3.19 is symmetric in (ti, tr); relative 1e-11 allows
    /// for the different rounding of the two half-vector computations.
    #[test]
    fn f00_is_reciprocal(s in surface(), ti in 0.0f64..FRAC_PI_2, tr in 0.0f64..FRAC_PI_2, phi in -PI..PI) {
        let a = s.specular(&Geometry::from_angles(ti, tr, phi).unwrap()).0[(0, 0)];
        let b = s.specular(&Geometry::from_angles(tr, ti, phi).unwrap()).0[(0, 0)];
        prop_assert!((a - b).abs() <= 1e-11 * a.abs().max(b.abs()) + 1e-300, "{a} vs {b}");
    }

    /// The pBRDF never produces light more than fully polarised: DoLP <= 1 for unpolarised
    /// illumination and for any fully polarised illumination (1e-12 for rounding).
    #[test]
    fn pbrdf_dolp_at_most_one(s in surface(), ti in 0.0f64..FRAC_PI_2, tr in 0.0f64..FRAC_PI_2,
                              phi in -PI..PI, aop in -FRAC_PI_2..FRAC_PI_2) {
        let g = Geometry::from_angles(ti, tr, phi).unwrap();
        let f = s.specular(&g);
        for input in [Stokes::unpolarized(1.0), Stokes::linear(1.0, aop)] {
            let out = f.apply(&input);
            if let Some(d) = out.dolp() {
                prop_assert!(d <= 1.0 + 1e-12, "DoLP {d}");
            }
        }
    }

    /// An ideal polarizer is a projector: P P = P (elementwise 1e-15).
    #[test]
    fn polarizer_is_idempotent(psi in -10.0f64..10.0) {
        let p = linear_polarizer(psi);
        let pp = p.then_after(&p);
        prop_assert!((pp.0 - p.0).abs().max() < 1e-15);
    }

    /// Noise-free data through >= 3 distinct analyzer angles reconstructs S exactly (relative
    /// 1e-9: the reconstruction error is cond(W) * eps * |S|, and angles closer than 2 deg are
    /// excluded so cond(W) < 1e4).
    #[test]
    fn reconstruction_is_exact_without_noise(
        s0 in 0.1f64..1e4, dolp in 0.0f64..1.0, aop in -FRAC_PI_2..FRAC_PI_2,
        mut angles in prop::collection::vec(0.0f64..180.0, 3..9),
    ) {
        angles.sort_by(f64::total_cmp);
        let distinct = angles.windows(2).filter(|w| w[1] - w[0] > 2.0).count() + 1;
        let wraps = angles[0] + 180.0 - angles[angles.len() - 1] > 2.0;
        prop_assume!(distinct >= 3 && wraps);
        let rad: Vec<f64> = angles.iter().map(|a| a.to_radians()).collect();
        let set = AnalyzerSet::ideal(&rad).unwrap();
        let s = Stokes::new(s0, s0 * dolp * (2.0 * aop).cos(), s0 * dolp * (2.0 * aop).sin());
        let i: Vec<f64> = set.intensities(&s).iter().copied().collect();
        let back = set.reconstruct(&i).unwrap();
        prop_assert!((back.0 - s.0).norm() <= 1e-9 * s0 * set.cond2(), "{back:?} vs {s:?}");
    }

    /// Frame rotation round trip: R(-eta) R(eta) = I, and the vector form of the rotation angle
    /// agrees with R(eta) built from the angle (1e-12).
    #[test]
    fn frame_rotation_round_trip(eta in -10.0f64..10.0, theta in 0.0f64..PI, az in -PI..PI) {
        let back = rotation(-eta).then_after(&rotation(eta));
        prop_assert!((back.0 - nalgebra::Matrix3::identity()).abs().max() < 1e-14);
        // A random propagation direction k, a transverse x, and x turned by eta about k.
        let k = Vector3::new(theta.sin() * az.cos(), theta.sin() * az.sin(), theta.cos());
        let helper = if k.z.abs() < 0.9 { Vector3::z() } else { Vector3::x() };
        let x = k.cross(&helper).normalize();
        let y = k.cross(&x);
        let x2 = x * eta.cos() + y * eta.sin();
        let (c2, s2) = cos_sin_2eta(&x, &x2, &k);
        prop_assert!((c2 - (2.0 * eta).cos()).abs() < 1e-12 && (s2 - (2.0 * eta).sin()).abs() < 1e-12);
        // A Stokes vector polarised along x reads AoP = -eta in the turned frame.
        let s_new = rotation(eta).apply(&Stokes::linear(1.0, 0.0));
        let expect = Stokes::linear(1.0, -eta);
        prop_assert!((s_new.0 - expect.0).norm() < 1e-12);
    }

    /// The diffuse term never goes negative and the albedo is a reflectance (in [0, 1]).
    #[test]
    fn diffuse_term_is_non_negative(idx in index(), sigma in 1e-3f64..1.0, dhr in 0.0f64..1.0, ti in 0.0f64..FRAC_PI_2) {
        let s = Surface::microfacet(idx, sigma, dhr).unwrap();
        let d = s.diffuse(ti, Tolerance::absolute(1e-7)).unwrap();
        prop_assert!(d.f00 >= 0.0);
        prop_assert!(d.specular_albedo.value >= 0.0 && d.specular_albedo.value <= 1.0 + 1e-7);
        prop_assert_eq!(d.clamped.is_some(), d.specular_albedo.value > dhr);
    }
}
