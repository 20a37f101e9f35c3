//! Independent oracles: Meng (2012)'s real-valued conductor formulas (Eqs. 2.31-2.36), its
//! arc-cosine rotation angles (Eqs. 3.9-3.10) in the interior of the domain, and a 3-D Jones
//! calculation of the facet reflection that shares no code with the Mueller path.

#![allow(clippy::unwrap_used)] // tests panic on failure by design

use nalgebra::{Matrix2, Matrix4, Vector3};
use num_complex::Complex64 as C;
use polar_model::fresnel::{amplitudes, amplitudes_eps, RefractiveIndex};
use polar_model::pbrdf::{FacetGeometry, Geometry};

/// Meng (2012) Eqs. 2.31-2.36 with the square root in 2.35, exactly as printed in MODEL.md section 2.
fn seed_conductor(n: f64, k: f64, ti: f64) -> (f64, f64) {
    let (s, c) = ti.sin_cos();
    let d = n * n - k * k - s * s;
    let cc = (4.0 * n * n * k * k + d * d).sqrt();
    let a = ((cc + d) / 2.0).sqrt();
    let b = ((cc - d) / 2.0).sqrt();
    let rs = ((a - c).powi(2) + b * b) / ((a + c).powi(2) + b * b);
    let st = s * ti.tan();
    let rp = rs * ((a - st).powi(2) + b * b) / ((a + st).powi(2) + b * b);
    (rs, rp)
}

#[test]
fn complex_fresnel_agrees_with_seed_real_formulas_to_1e12() {
    // Copper, gold, silver, aluminium, a dielectric through the k = 0 limit, and k up to 10.
    let materials = [
        (1.02, 2.577),
        (0.43, 2.455),
        (0.06, 3.586),
        (0.9671, 6.4617),
        (1.52, 0.0),
        (1.52, 1e-9),
        (0.3, 10.0),
        (5.0, 10.0),
    ];
    let mut worst = 0f64;
    for (n, k) in materials {
        let idx = RefractiveIndex::new(n, k).unwrap();
        for step in 0..=890 {
            // Up to 89 deg: beyond, Meng (2012)'s sin*tan form loses digits to cancellation (its
            // own weakness, which the complex form does not share).
            let ti = (step as f64 * 0.1).to_radians();
            let (rs, rp) = seed_conductor(n, k, ti);
            let a = amplitudes(&idx, ti).unwrap();
            worst = worst
                .max((a.rs_power() - rs).abs())
                .max((a.rp_power() - rp).abs());
        }
    }
    assert!(worst < 1e-12, "largest |complex - seed| = {worst:e}");
}

#[test]
fn dielectric_limit_of_conductor_is_continuous() {
    // k -> 0 must agree with the dielectric form: the change from k = 0 to k = 1e-12 is O(k).
    for ti_deg in [0.0, 30.0, 56.0, 80.0, 90.0] {
        let ti = f64::to_radians(ti_deg);
        let a = amplitudes(&RefractiveIndex::new(1.52, 0.0).unwrap(), ti).unwrap();
        let b = amplitudes(&RefractiveIndex::new(1.52, 1e-12).unwrap(), ti).unwrap();
        assert!(
            (a.rs - b.rs).norm() < 1e-11 && (a.rp - b.rp).norm() < 1e-11,
            "ti {ti_deg}"
        );
    }
}

/// Meng (2012)'s Eqs. 3.9-3.10 (3.10 with its denominator typo fixed), and Eq. 3.11.
fn seed_cos_eta(ti: f64, tr: f64, phi: f64) -> (f64, f64) {
    let cos_2b = ti.cos() * tr.cos() + ti.sin() * tr.sin() * phi.cos();
    let beta = 0.5 * cos_2b.acos();
    let cos_a = (ti.cos() + tr.cos()) / (2.0 * beta.cos());
    let ci = (cos_a - ti.cos() * beta.cos()) / (ti.sin() * beta.sin());
    let cr = (cos_a - tr.cos() * beta.cos()) / (tr.sin() * beta.sin());
    (ci, cr)
}

#[test]
fn vector_rotation_angles_match_seed_arccos_in_the_interior() {
    // Interior: away from ti, tr = 0, the specular plane and beta = 0, where Eqs. 3.9-3.10 are
    // well conditioned. They give |cos eta| only up to sign conventions of the angle itself, so
    // compare cos(2 eta) = 2 cos^2 eta - 1, which the sign does not affect.
    let mut worst = 0f64;
    for ti_deg in [10.0, 25.0, 40.0, 60.0, 75.0, 85.0] {
        for tr_deg in [5.0, 20.0, 45.0, 70.0, 88.0] {
            for phi_deg in [10.0, 45.0, 90.0, 135.0, 170.0, 200.0, 300.0] {
                let (ti, tr, phi) = (
                    f64::to_radians(ti_deg),
                    f64::to_radians(tr_deg),
                    f64::to_radians(phi_deg),
                );
                let fg = FacetGeometry::new(&Geometry::from_angles(ti, tr, phi).unwrap());
                let (ci, cr) = seed_cos_eta(ti, tr, phi);
                worst = worst
                    .max((fg.rot_i.0 - (2.0 * ci * ci - 1.0)).abs())
                    .max((fg.rot_r.0 - (2.0 * cr * cr - 1.0)).abs());
            }
        }
    }
    assert!(worst < 1e-9, "largest |cos 2eta| difference {worst:e}");
}

/// Mueller (3x3 linear part) of a Jones matrix, `M = A (J ⊗ J*) A^-1`.
fn mueller_of_jones(j: &Matrix2<C>) -> nalgebra::Matrix3<f64> {
    let i = C::new(0.0, 1.0);
    let (o, z) = (C::new(1.0, 0.0), C::new(0.0, 0.0));
    let a = Matrix4::new(o, z, z, o, o, z, z, -o, z, o, o, z, z, i, -i, z);
    let h = C::new(0.5, 0.0);
    let a_inv = Matrix4::new(o, o, z, z, z, z, o, -i, z, z, o, i, o, -o, z, z) * h;
    let kron = Matrix4::from_fn(|r, c| j[(r / 2, c / 2)] * j[(r % 2, c % 2)].conj());
    let m = a * kron * a_inv;
    nalgebra::Matrix3::from_fn(|r, c| m[(r, c)].re)
}

#[test]
fn mueller_path_matches_3d_jones_reflection() {
    // Fields in 3-D: incident basis (s_i, k_i × s_i), facet basis (s_f, k × s_f) on both rays,
    // reflected basis (s_r, k_r × s_r), all built here from k × n, independently of the library.
    let eps = C::new(1.02, 2.577).powi(2);
    let mut worst = 0f64;
    for ti_deg in [5.0, 30.0, 60.0, 85.0] {
        for tr_deg in [3.0, 30.0, 50.0, 89.0] {
            for phi_deg in [0.0, 37.0, 90.0, 150.0, 179.0, 181.0, 250.0, 359.0] {
                let (ti, tr, phi) = (
                    f64::to_radians(ti_deg),
                    f64::to_radians(tr_deg),
                    f64::to_radians(phi_deg),
                );
                let w_i = Vector3::new(ti.sin(), 0.0, ti.cos());
                let w_r = Vector3::new(tr.sin() * phi.cos(), tr.sin() * phi.sin(), tr.cos());
                let n = Vector3::z();
                let (k_i, k_r) = (-w_i, w_r);
                let h = (w_i + w_r).normalize();
                let s_i = k_i.cross(&n).normalize();
                let s_r = k_r.cross(&n).normalize();
                let s_f = k_i.cross(&h).normalize();
                let (p_i, p_r) = (k_i.cross(&s_i), k_r.cross(&s_r));
                let (pf_i, pf_r) = (k_i.cross(&s_f), k_r.cross(&s_f));
                let r = amplitudes_eps(eps, w_i.dot(&h));
                // Jones matrix, reflected surface frame <- incident surface frame.
                let jones = Matrix2::from_fn(|row, col| {
                    let e_in = if col == 0 { s_i } else { p_i };
                    let e_s = C::new(e_in.dot(&s_f), 0.0) * r.rs;
                    let e_p = C::new(e_in.dot(&pf_i), 0.0) * r.rp;
                    let basis = if row == 0 { s_r } else { p_r };
                    e_s * basis.dot(&s_f) + e_p * basis.dot(&pf_r)
                });
                let m_jones = mueller_of_jones(&jones);
                let fg = FacetGeometry::new(&Geometry::from_angles(ti, tr, phi).unwrap());
                let m = fg.rotated_fresnel(eps);
                worst = worst.max((m - m_jones).abs().max());
            }
        }
    }
    assert!(worst < 1e-12, "largest |Mueller - Jones| = {worst:e}");
}

/// The algebraic complex square root agrees with num-complex's polar-form `sqrt` on the branch
/// Fresnel needs (upper half plane and both real half-axes), to 4 ulp relative.
#[test]
fn algebraic_csqrt_matches_polar_sqrt() {
    use polar_model::fresnel::csqrt;
    let mut worst = 0f64;
    for i in -60..=60 {
        for j in 0..=60 {
            let z = C::new(i as f64 * 0.37 - 0.01, j as f64 * 0.29);
            let (a, b) = (csqrt(z), z.sqrt());
            worst = worst.max((a - b).norm() / b.norm().max(1e-300));
            assert!(a.re >= 0.0 && a.im >= 0.0);
        }
    }
    assert!(worst < 1e-15, "{worst:e}");
    assert_eq!(csqrt(C::new(-4.0, 0.0)), C::new(0.0, 2.0));
    assert_eq!(csqrt(C::new(0.0, 0.0)), C::new(0.0, 0.0));
}
