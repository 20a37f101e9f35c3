//! Hard cases of MODEL.md section 12 that apply to the polarisation core: each boundary's answer
//! is stated and checked, not only "finite".

#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_model::analyzer::AnalyzerSet;
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::pbrdf::{Geometry, Surface, COS_FLOOR};
use polar_model::polarization::{Mueller, Stokes};
use polar_model::quadrature::Tolerance;
use polar_model::ModelError;

const ANGLES_DEG: [f64; 11] = [
    0.0,
    1e-9,
    1e-4,
    1.0,
    30.0,
    56.659293,
    60.0,
    89.0,
    89.9999,
    90.0 - 1e-9,
    90.0,
];
const PHI_DEG: [f64; 10] = [
    -180.0, 0.0, 1e-9, 45.0, 90.0, 179.999999, 180.0, 180.000001, 270.0, 360.0,
];
const SIGMAS: [f64; 6] = [1e-4, 1e-3, 0.01, 0.1, 0.5, 1.0];

fn surfaces() -> Vec<Surface> {
    let idx = |n, k| RefractiveIndex::new(n, k).unwrap();
    let mut v = Vec::new();
    for &sigma in &SIGMAS {
        for (n, k) in [
            (1.52, 0.0),
            (1.0001, 0.0),
            (0.5, 0.0),
            (1.02, 2.577),
            (0.06, 3.586),
            (0.1, 10.0),
            (3.0, 10.0),
        ] {
            v.push(Surface::microfacet(idx(n, k), sigma, 0.5).unwrap());
        }
    }
    v.push(Surface::vegetation(idx(1.5, 0.0), 0.04 / std::f64::consts::PI).unwrap());
    v
}

fn all_finite(m: &Mueller) -> bool {
    m.0.iter().all(|x| x.is_finite())
}

/// Dense grid: no NaN or infinity anywhere; f00 >= 0; DoLP <= 1 for unpolarised light.
#[test]
fn dense_grid_is_finite_and_physical() {
    let mut count = 0usize;
    for s in surfaces() {
        for &ti in &ANGLES_DEG {
            for &tr in &ANGLES_DEG {
                for &phi in &PHI_DEG {
                    let g = Geometry::from_deg(ti, tr, phi).unwrap();
                    let f = s.specular(&g);
                    assert!(all_finite(&f), "{s:?} {ti} {tr} {phi}: {f:?}");
                    assert!(f.0[(0, 0)] >= 0.0);
                    if let Some(d) = f.dolp_unpolarized() {
                        assert!(d <= 1.0 + 1e-12, "DoLP {d} at {ti} {tr} {phi}");
                    }
                    count += 1;
                }
            }
        }
    }
    assert_eq!(count, 43 * 11 * 11 * 10);
}

/// Normal incidence and normal view: the surface frame is the limit along the azimuth, so the
/// matrix at exactly 0 equals the one at 1e-7 deg to first order (relative 1e-8).
#[test]
fn normal_incidence_and_view_are_continuous_limits() {
    let s = Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.3, 0.1).unwrap();
    for &phi in &[0.0, 33.0, 90.0, 180.0, 300.0] {
        for &other in &[0.0, 20.0, 60.0] {
            let at0 = s.specular(&Geometry::from_deg(0.0, other, phi).unwrap()).0;
            let near = s.specular(&Geometry::from_deg(1e-7, other, phi).unwrap()).0;
            assert!(
                (at0 - near).abs().max() <= 1e-8 * at0.abs().max(),
                "ti=0 phi={phi} tr={other}"
            );
            let at0 = s.specular(&Geometry::from_deg(other, 0.0, phi).unwrap()).0;
            let near = s.specular(&Geometry::from_deg(other, 1e-7, phi).unwrap()).0;
            assert!(
                (at0 - near).abs().max() <= 1e-8 * at0.abs().max(),
                "tr=0 phi={phi} ti={other}"
            );
        }
    }
    // At ti = tr = 0 (retro-reflection along the normal, beta = 0) Rs = Rp: the matrix is
    // diag(R, R cos, R...) in the two azimuth-defined frames; its first column is unpolarised.
    let f = s.specular(&Geometry::from_deg(0.0, 0.0, 0.0).unwrap()).0;
    assert!(f[(1, 0)].abs() < 1e-15 * f[(0, 0)] && f[(2, 0)].abs() < 1e-15 * f[(0, 0)]);
    // And M22 = Re(rs rp*) = -R: the reflected frame is the mirror image of the incident one.
    assert!((f[(1, 1)] - f[(0, 0)]).abs() < 1e-12 * f[(0, 0)]);
    assert!((f[(2, 2)] + f[(0, 0)]).abs() < 1e-12 * f[(0, 0)]);
}

/// The exact specular direction: facet frame = surface frame, so S2 is not generated, the first
/// column is [f00, (Rs-Rp)/(Rs+Rp) f00, 0], and at Brewster incidence the light is fully s-polarised.
#[test]
fn specular_direction_and_brewster() {
    let idx = RefractiveIndex::new(1.52, 0.0).unwrap();
    let s = Surface::microfacet(idx, 0.1, 0.1).unwrap();
    for &t in &[1.0, 20.0, 45.0, 60.0, 80.0] {
        let f = s.specular(&Geometry::from_deg(t, t, 180.0).unwrap()).0;
        let a = amplitudes(&idx, f64::to_radians(t)).unwrap();
        let dop = (a.rs_power() - a.rp_power()) / (a.rs_power() + a.rp_power());
        assert!(f[(2, 0)].abs() <= 1e-15 * f[(0, 0)] && f[(0, 2)].abs() <= 1e-15 * f[(0, 0)]);
        assert!((f[(1, 0)] / f[(0, 0)] - dop).abs() < 1e-13, "t={t}");
    }
    let b = idx.brewster_angle_rad();
    let f = s.specular(&Geometry::from_angles(b, b, std::f64::consts::PI).unwrap());
    assert!((f.dolp_unpolarized().unwrap() - 1.0).abs() < 1e-12);
}

/// Mirror symmetry about the plane of incidence: phi -> -phi keeps f00, f01, f10, f11 and flips
/// the elements that couple S2 (the mirror reverses the sense of +45 deg).
#[test]
fn mirror_symmetry_flips_s2_coupling() {
    let s = Surface::microfacet(RefractiveIndex::new(1.02, 2.577).unwrap(), 0.3, 0.7).unwrap();
    for &(ti, tr, phi) in &[(30.0, 50.0, 40.0), (60.0, 10.0, 120.0), (80.0, 80.0, 170.0)] {
        let a = s.specular(&Geometry::from_deg(ti, tr, phi).unwrap()).0;
        let b = s.specular(&Geometry::from_deg(ti, tr, -phi).unwrap()).0;
        for (i, j, sign) in [
            (0, 0, 1.0),
            (0, 1, 1.0),
            (1, 0, 1.0),
            (1, 1, 1.0),
            (2, 2, 1.0),
            (0, 2, -1.0),
            (2, 0, -1.0),
            (1, 2, -1.0),
            (2, 1, -1.0),
        ] {
            assert!(
                (a[(i, j)] - sign * b[(i, j)]).abs() < 1e-12 * a.abs().max(),
                "({i},{j}) at {ti} {tr} {phi}"
            );
        }
        assert!(
            a[(2, 0)].abs() > 1e-6 * a[(0, 0)],
            "off-plane geometry must generate S2"
        );
    }
}

/// Grazing: away from grazing specular the value at 90 deg is the limit from below (relative
/// 1e-3 between 90 and 89.9999 deg, where the functions change by O(1e-6 rad) relative); at exact
/// grazing specular the BRDF diverges like 1/cos^2 and the model returns its value at the cos
/// floor, which is finite and enormous.
#[test]
fn grazing_limits() {
    let s = Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.5, 0.1).unwrap();
    let at = s
        .specular(&Geometry::from_deg(90.0, 40.0, 150.0).unwrap())
        .0;
    let near = s
        .specular(&Geometry::from_deg(89.9999, 40.0, 150.0).unwrap())
        .0;
    assert!(at[(0, 0)] > 0.0 && (at - near).abs().max() < 1e-3 * at.abs().max());
    // Grazing incidence: the surface frame's s is horizontal; Rs = Rp = 1 at the facet only in
    // the limit, so just require the documented divergent value at grazing specular.
    let gs = s
        .specular(&Geometry::from_deg(90.0, 90.0, 180.0).unwrap())
        .0;
    let p0 = 1.0 / (2.0 * std::f64::consts::PI * 0.25);
    let expect = p0 * 0.25 / (COS_FLOOR * COS_FLOOR);
    assert!(
        (gs[(0, 0)] / expect - 1.0).abs() < 1e-6,
        "{} vs {expect}",
        gs[(0, 0)]
    );
    // Both grazing, not specular: facets would have to be vertical; p(90 deg) = 0, so F = 0.
    let gn = s.specular(&Geometry::from_deg(90.0, 90.0, 90.0).unwrap()).0;
    assert_eq!(gn.abs().max(), 0.0);
}

/// sigma -> 0: the lobe is a delta function. Off the specular direction the Gaussian underflows to
/// exactly 0 (the pBRDF is then the diffuse term alone, unpolarised); on it the peak is
/// p(0) = 1/(2 pi sigma^2); the specular albedo tends to the Fresnel reflectance 0.5 (Rs + Rp)(ti).
#[test]
fn delta_lobe_limit() {
    let idx = RefractiveIndex::new(1.52, 0.0).unwrap();
    let s = Surface::microfacet(idx, 1e-4, 0.1).unwrap();
    let off = s
        .specular(&Geometry::from_deg(60.0, 59.0, 180.0).unwrap())
        .0;
    assert_eq!(off.abs().max(), 0.0);
    let e = s
        .evaluate(
            f64::to_radians(60.0),
            f64::to_radians(59.0),
            std::f64::consts::PI,
            Tolerance::default(),
        )
        .unwrap();
    assert_eq!(e.dolp, 0.0);
    let on = s
        .specular(&Geometry::from_deg(60.0, 60.0, 180.0).unwrap())
        .0;
    let a = amplitudes(&idx, f64::to_radians(60.0)).unwrap();
    let r = 0.5 * (a.rs_power() + a.rp_power());
    let expect = r / (2.0 * std::f64::consts::PI * 1e-8) / (4.0 * 0.25);
    assert!((on[(0, 0)] / expect - 1.0).abs() < 1e-12);
    for ti in [0.0, 30.0, 60.0, 85.0] {
        let a = amplitudes(&idx, f64::to_radians(ti)).unwrap();
        let albedo = s
            .diffuse(f64::to_radians(ti), Tolerance::absolute(1e-10))
            .unwrap()
            .specular_albedo;
        // The deviation from the Fresnel reflectance is O(sigma^2 |d2R/dtheta2|): sigma^2 = 1e-8
        // times a curvature that reaches ~30 at 85 deg; the quadrature adds < 1e-10.
        assert!(
            (albedo.value - 0.5 * (a.rs_power() + a.rp_power())).abs() < 1e-6,
            "ti {ti}: {albedo:?}"
        );
    }
}

/// Very rough surfaces and grazing illumination: the albedo stays a converged reflectance and the
/// diffuse clamp fires (with its warning) exactly when the lobe exceeds the DHR.
#[test]
fn albedo_quadrature_converges_everywhere_and_clamp_is_reported() {
    let cu = RefractiveIndex::new(1.02, 2.577).unwrap();
    for &sigma in &[1e-4, 0.01, 0.3, 1.0, 10.0] {
        for ti in [0.0, 45.0, 89.0, 90.0] {
            let s = Surface::microfacet(cu, sigma, 0.3).unwrap();
            let d = s
                .diffuse(f64::to_radians(ti), Tolerance::absolute(1e-8))
                .unwrap();
            assert!(
                d.specular_albedo.converged,
                "sigma {sigma} ti {ti}: {:?}",
                d.specular_albedo
            );
            assert!(d.specular_albedo.error <= 1e-8);
            let a = d.specular_albedo.value;
            assert!((0.0..=1.0).contains(&a), "albedo {a}");
            assert_eq!(
                d.clamped.is_some(),
                a > 0.3,
                "sigma {sigma} ti {ti} albedo {a}"
            );
            if let Some(w) = d.clamped {
                assert_eq!(d.f00, 0.0);
                assert!(w.to_string().contains("clamped"));
            }
        }
    }
}

/// Repeated or nearly repeated analyzer angles: rank-deficient sets are refused with an error
/// naming `angles_deg`; a nearly repeated set is accepted with its (large, finite) condition
/// number, which grows like 1/delta for two angles delta apart (the third far away): two nearly
/// equal rows leave a smallest singular value proportional to their difference.
#[test]
fn singular_and_ill_conditioned_analyzer_sets() {
    let deg = |v: &[f64]| v.iter().map(|a| a.to_radians()).collect::<Vec<_>>();
    for bad in [
        &[0.0, 0.0, 90.0][..],
        &[0.0, 180.0, 90.0],
        &[10.0, 10.0, 10.0, 190.0],
        &[0.0, 45.0],
    ] {
        let e = AnalyzerSet::ideal(&deg(bad)).unwrap_err();
        assert!(
            matches!(
                e,
                ModelError::Invalid {
                    field: "angles_deg",
                    ..
                }
            ),
            "{bad:?}: {e}"
        );
    }
    let c1 = AnalyzerSet::ideal(&deg(&[0.0, 1e-3, 90.0]))
        .unwrap()
        .cond2();
    let c2 = AnalyzerSet::ideal(&deg(&[0.0, 2e-3, 90.0]))
        .unwrap()
        .cond2();
    assert!(c1.is_finite() && c1 > 1e4);
    // Halving the separation doubles cond2 (first order in delta: relative 1e-6).
    assert!((c1 / c2 - 2.0).abs() < 1e-6, "ratio {}", c1 / c2);
}

/// DoLP and AoP at their singular points: dark pixel (S0 = 0), unpolarised (AoP undefined),
/// and the AoP interval's excluded end (-90 deg folds onto +90 deg).
#[test]
fn dolp_and_aop_at_singular_points() {
    assert_eq!(Stokes::new(0.0, 0.0, 0.0).dolp(), None);
    assert_eq!(Stokes::new(-1.0, 0.0, 0.0).dolp(), None);
    assert_eq!(Stokes::new(1.0, 0.0, 0.0).dolp(), Some(0.0));
    assert_eq!(Stokes::new(1.0, 0.0, 0.0).aop_rad(), None);
    let a = Stokes::new(1.0, -1.0, -0.0).aop_rad().unwrap();
    assert_eq!(a, std::f64::consts::FRAC_PI_2);
    // Just inside the interval: -90 deg + 0.5e-3 rad.
    let a = Stokes::new(1.0, -1.0, -1e-3).aop_rad().unwrap();
    assert!(
        (a + std::f64::consts::FRAC_PI_2 - 0.5e-3).abs() < 1e-9,
        "{a}"
    );
    // Overflow-safe polarised intensity.
    assert_eq!(Stokes::new(1e308, 1e308, 1e308).dolp(), Some(2f64.sqrt()));
}

/// Out-of-domain inputs are errors naming the field, never NaN.
#[test]
fn out_of_domain_inputs_name_the_field() {
    let e = Geometry::from_deg(91.0, 0.0, 0.0).unwrap_err().to_string();
    assert!(
        e.contains("theta_i_deg") && e.contains("91") && e.contains("[0, 90]"),
        "{e}"
    );
    let e = Geometry::from_deg(10.0, f64::NAN, 0.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("theta_r_deg"), "{e}");
    let e = Geometry::from_deg(10.0, 10.0, 400.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("phi_deg") && e.contains("400"), "{e}");
    let e = RefractiveIndex::new(0.0, 0.0).unwrap_err().to_string();
    assert!(e.contains("n = 0") && e.contains("(0, 100]"), "{e}");
    let e = RefractiveIndex::new(1.5, -1.0).unwrap_err().to_string();
    assert!(e.contains('k'), "{e}");
    let e = Surface::microfacet(RefractiveIndex::new(1.5, 0.0).unwrap(), 0.0, 0.1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sigma") && e.contains("[1e-6, 10]"), "{e}");
}

/// Degree trigonometry is exact at multiples of 90 deg and agrees with radians elsewhere (1e-15).
#[test]
fn degree_trigonometry_is_exact_at_quadrants() {
    use polar_model::angles::sin_cos_deg;
    for (d, s, c) in [
        (0.0, 0.0, 1.0),
        (90.0, 1.0, 0.0),
        (180.0, 0.0, -1.0),
        (270.0, -1.0, 0.0),
        (-90.0, -1.0, 0.0),
        (360.0, 0.0, 1.0),
        (-180.0, 0.0, -1.0),
    ] {
        let (gs, gc) = sin_cos_deg(d);
        assert!(gs == s && gc == c, "{d}: {gs} {gc}");
    }
    for i in -720..=720 {
        let d = i as f64 * 0.5 + 0.123;
        let (s, c) = sin_cos_deg(d);
        let (rs, rc) = d.to_radians().sin_cos();
        assert!((s - rs).abs() < 1e-15 && (c - rc).abs() < 1e-15, "{d}");
    }
}

/// The slope-space albedo (Eq. 3.18's integral) equals the direct hemisphere integral of the
/// specular Mueller element, `int f00_s cos tr dOmega_r` over `(cos tr, phi)`: two independent
/// parametrisations and code paths. Tolerance 1e-7: both quadratures run at 1e-9.
#[test]
fn slope_space_albedo_equals_direct_hemisphere_integral() {
    use polar_model::quadrature::integrate_2d;
    let idx = RefractiveIndex::new(1.52, 0.0).unwrap();
    for (sigma, ti_deg) in [
        (0.3, 30.0),
        (0.5, 60.0),
        (1.0, 80.0),
        (10.0, 89.0),
        (0.5, 0.0),
    ] {
        let s = Surface::microfacet(idx, sigma, 1.0).unwrap();
        let slope = s
            .diffuse(f64::to_radians(ti_deg), Tolerance::absolute(1e-10))
            .unwrap()
            .specular_albedo;
        let direct = integrate_2d(
            |phi, mu: f64| {
                let g =
                    Geometry::from_angles(f64::to_radians(ti_deg), mu.clamp(0.0, 1.0).acos(), phi)
                        .unwrap();
                s.specular(&g).0[(0, 0)] * mu
            },
            (0.0, std::f64::consts::PI),
            (0.0, 1.0),
            Tolerance {
                abs: 1e-10,
                rel: 1e-12,
                max_intervals: 2000,
            },
        );
        let direct_value = 2.0 * direct.value;
        assert!(
            (slope.value - direct_value).abs() < 1e-7,
            "sigma {sigma} ti {ti_deg}: slope {slope:?} direct {direct_value} ({direct:?})"
        );
    }
}

/// Direction-vector geometry equals angle geometry (1e-14 on every Mueller element relative to
/// the largest), including a rotated incident azimuth; bad vectors are refused by name.
#[test]
fn geometry_from_directions_matches_angles() {
    use nalgebra::Vector3;
    let s = Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.3, 0.1).unwrap();
    for &(ti, tr, phi) in &[
        (30.0f64, 50.0f64, 40.0f64),
        (60.0, 60.0, 180.0),
        (0.0, 20.0, 0.0),
        (80.0, 10.0, 300.0),
    ] {
        let a = s.specular(&Geometry::from_deg(ti, tr, phi).unwrap()).0;
        // At normal incidence the incident azimuth is lost in the vector (the frame limit then
        // uses azimuth 0), so only the unrotated pair is comparable there.
        let azimuths: &[f64] = if ti == 0.0 { &[0.0] } else { &[0.0, 1.0, 2.5] };
        for &az in azimuths {
            let (ti_r, tr_r, phi_r) = (ti.to_radians(), tr.to_radians(), phi.to_radians());
            let wi = Vector3::new(ti_r.sin() * az.cos(), ti_r.sin() * az.sin(), ti_r.cos());
            let wr = Vector3::new(
                tr_r.sin() * (az + phi_r).cos(),
                tr_r.sin() * (az + phi_r).sin(),
                tr_r.cos(),
            );
            let b = s.specular(&Geometry::from_directions(&wi, &wr).unwrap()).0;
            assert!(
                (a - b).abs().max() <= 1e-13 * a.abs().max(),
                "{ti} {tr} {phi} az {az}"
            );
        }
    }
    let e = Geometry::from_directions(&Vector3::new(0.0, 0.0, 2.0), &Vector3::z())
        .unwrap_err()
        .to_string();
    assert!(e.contains("omega_i") && e.contains("unit vector"), "{e}");
    let e = Geometry::from_directions(&Vector3::z(), &Vector3::new(0.0, 0.0, -1.0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("omega_r") && e.contains("z >= 0"), "{e}");
}

/// Far in a lobe's tail (a metal, sigma 0.15, incidence 83 deg, view 78 deg, 39 deg apart in
/// azimuth: the Beckmann exponent is -744) the pBRDF is exactly zero, not a subnormal
/// matrix whose rounding gave a DoLP of 1.0009 (found by `pbrdf_dolp_at_most_one`), and the
/// DoLP of the (dark) output is `None`. Inside the cut-off (sigma 0.17: exponent -576) the
/// elements are normal numbers and the DoLP is at most 1.
#[test]
fn lobe_tail_is_exactly_zero_not_subnormal() {
    let index = RefractiveIndex::new(5.827667356362288, 3.216050929487362).unwrap();
    let g =
        Geometry::from_angles(1.4562748059108699, 1.3611287499521858, -0.6759324494436122).unwrap();
    let s = Surface::microfacet(index, 0.14962291369287248, 0.0).unwrap();
    let m = s.specular(&g);
    assert!(m.0.iter().all(|&x| x == 0.0), "{}", m.0);
    assert_eq!(m.apply(&Stokes::linear(1.0, 0.78)).dolp(), None);
    let s = Surface::microfacet(index, 0.17, 0.0).unwrap();
    let m = s.specular(&g);
    let out = m.apply(&Stokes::linear(1.0, 0.78));
    assert!(out.s0() >= f64::MIN_POSITIVE, "{out:?}");
    let d = out.dolp().unwrap();
    assert!(d <= 1.0 + 1e-12, "DoLP {d}");
}
