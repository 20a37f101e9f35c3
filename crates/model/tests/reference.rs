//! Every value of `shared/reference/REFERENCE_VALUES.md`'s Fresnel, pBRDF and polarimeter
//! sections. Tolerances follow the digits printed there (half a unit of the last digit, plus
//! float slack), so each assertion fails if the physics or a convention changes.

// The table values are the printed digits of REFERENCE_VALUES.md, kept as printed on purpose.
#![allow(clippy::approx_constant, clippy::type_complexity)]
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_model::analyzer::AnalyzerSet;
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::pbrdf::{Geometry, Surface};
use polar_model::quadrature::Tolerance;

fn rad(d: f64) -> f64 {
    d.to_radians()
}

#[test]
fn glass_fresnel_table() {
    let glass = RefractiveIndex::new(1.52, 0.0).unwrap();
    // theta_i, Rs, Rp, (Rs-Rp)/(Rs+Rp); printed to 6 decimals -> tolerance 6e-7.
    let rows = [
        (0.0, 0.042580, 0.042580, 0.0),
        (20.0, 0.050007, 0.035700, 0.166928),
        (45.0, 0.096733, 0.009357, 0.823598),
        (60.0, 0.183438, 0.001527, 0.983487),
        (80.0, 0.546363, 0.235537, 0.397526),
        (89.0, 0.940841, 0.868543, 0.039957),
    ];
    for (ti, rs, rp, dop) in rows {
        let a = amplitudes(&glass, rad(ti)).unwrap();
        let (s, p) = (a.rs_power(), a.rp_power());
        assert!((s - rs).abs() < 6e-7, "Rs({ti}) = {s}, table {rs}");
        assert!((p - rp).abs() < 6e-7, "Rp({ti}) = {p}, table {rp}");
        assert!(((s - p) / (s + p) - dop).abs() < 6e-7, "DoP({ti})");
    }
    // Brewster angle atan(1.52) = 56.659293 deg, where Rp vanishes.
    let b = glass.brewster_angle_rad();
    assert!((b.to_degrees() - 56.659293).abs() < 6e-7);
    assert!(amplitudes(&glass, b).unwrap().rp_power() < 1e-30);
}

#[test]
fn copper_fresnel_table_and_pseudo_brewster() {
    let cu = RefractiveIndex::new(1.02, 2.577).unwrap();
    let rows = [
        (0.0, 0.619450, 0.619450),
        (45.0, 0.719137, 0.517159),
        (60.0, 0.794439, 0.448652),
        (80.0, 0.924017, 0.530191),
    ];
    for (ti, rs, rp) in rows {
        let a = amplitudes(&cu, rad(ti)).unwrap();
        assert!(
            (a.rs_power() - rs).abs() < 6e-7,
            "Rs({ti}) = {}",
            a.rs_power()
        );
        assert!(
            (a.rp_power() - rp).abs() < 6e-7,
            "Rp({ti}) = {}",
            a.rp_power()
        );
    }
    // Pseudo-Brewster angle (minimum of Rp) 68.454 deg: golden-section search to 1e-6 deg.
    let rp = |t: f64| amplitudes(&cu, rad(t)).unwrap().rp_power();
    let (mut lo, mut hi) = (60.0, 80.0);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    while hi - lo > 1e-7 {
        let (a, b) = (hi - g * (hi - lo), lo + g * (hi - lo));
        if rp(a) < rp(b) {
            hi = b
        } else {
            lo = a
        }
    }
    assert!(
        (0.5 * (lo + hi) - 68.454).abs() < 6e-4,
        "pseudo-Brewster {lo}"
    );
}

#[test]
fn glass_pbrdf_reference_at_sigma_0_1() {
    let glass = Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.1, 0.1).unwrap();
    let ti = rad(60.0);
    let d = glass.diffuse(ti, Tolerance::absolute(1e-10)).unwrap();
    assert!(d.specular_albedo.converged);
    assert!(d.specular_albedo.error < 1e-9, "{:?}", d.specular_albedo);
    // Specular albedo 0.09275 (5 decimals), f00_d 0.002309 (6 decimals).
    assert!(
        (d.specular_albedo.value - 0.09275).abs() < 6e-6,
        "{:?}",
        d.specular_albedo
    );
    assert!((d.f00 - 0.002309).abs() < 6e-7, "f00_d = {}", d.f00);
    assert!(d.clamped.is_none());

    let g = Geometry::from_deg(60.0, 60.0, 180.0).unwrap();
    let fs = glass.specular(&g);
    assert!(
        (fs.0[(0, 0)] - 1.47191).abs() < 6e-6,
        "f00_s = {}",
        fs.0[(0, 0)]
    );
    let pol = fs.0[(1, 0)].hypot(fs.0[(2, 0)]);
    assert!((pol - 1.44760).abs() < 6e-6, "polarised = {pol}");
    let f = glass.mueller_with(&g, &d);
    let dolp = f.dolp_unpolarized().unwrap();
    assert!((dolp - 0.98195).abs() < 6e-6, "DoLP = {dolp}");
    // In the specular plane the facet frame is the surface frame: S2 stays 0 and S1 > 0 (s-polarised).
    assert!(fs.0[(2, 0)].abs() < 1e-12 && fs.0[(1, 0)] > 0.0);
}

#[test]
fn polarimeter_matrix_table() {
    // angles, singular values (6 decimals, empty when not printed), cond2, trace((W^T W)^-1)
    let rows: [(&[f64], &[f64], f64, f64, f64); 4] = [
        (
            &[0.0, 45.0, 90.0],
            &[0.923880, 0.707107, 0.382683],
            2.414214,
            10.0,
            6e-7,
        ),
        (
            &[0.0, 60.0, 120.0],
            &[0.866025, 0.612372, 0.612372],
            1.414214,
            6.666667,
            6e-7,
        ),
        (
            &[0.0, 45.0, 90.0, 135.0],
            &[1.0, 0.707107, 0.707107],
            1.414214,
            5.0,
            6e-7,
        ),
        (&[0.0, 20.0, 40.0], &[], 15.5726, 193.88, 6e-3),
    ];
    for (angles, sv, cond, ewv, tol) in rows {
        let rad: Vec<f64> = angles.iter().map(|a| a.to_radians()).collect();
        let set = AnalyzerSet::ideal(&rad).unwrap();
        for (got, want) in set.singular_values().iter().zip(sv) {
            assert!((got - want).abs() < 6e-7, "{angles:?}: sv {got} vs {want}");
        }
        assert!(
            (set.cond2() - cond).abs() < tol.max(6e-5),
            "{angles:?}: cond {}",
            set.cond2()
        );
        assert!(
            (set.ewv() - ewv).abs() < tol * 10.0,
            "{angles:?}: ewv {}",
            set.ewv()
        );
    }
    // N equally spaced angles: W^T W = (N/4) diag(1, 1/2, 1/2), cond2 = sqrt(2).
    for n in 3..12 {
        let rad: Vec<f64> = (0..n)
            .map(|k| std::f64::consts::PI * k as f64 / n as f64)
            .collect();
        let set = AnalyzerSet::ideal(&rad).unwrap();
        let wtw = set.intensities_from_stokes().transpose() * set.intensities_from_stokes();
        let q = n as f64 / 4.0;
        let want = [q, q / 2.0, q / 2.0];
        for i in 0..3 {
            for j in 0..3 {
                let w = if i == j { want[i] } else { 0.0 };
                assert!((wtw[(i, j)] - w).abs() < 1e-13, "N={n} WtW[{i},{j}]");
            }
        }
        assert!((set.cond2() - 2f64.sqrt()).abs() < 1e-12);
    }
}
