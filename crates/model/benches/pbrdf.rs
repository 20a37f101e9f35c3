//! Throughput of full pBRDF Mueller evaluations over a realistic mix of materials (the eight
//! built-in ones) and geometries (sun zenith 0-85 deg, view zenith 0-89 deg, any azimuth), with a
//! baseline measured in the same run: the Fresnel amplitudes alone at the same facet angles.
//! Report the ratio, not the absolute figure; the machine is shared.
//!
//!     cargo bench -p polar-model --bench pbrdf

#![allow(missing_docs)] // criterion_group! generates undocumented items.

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use polar_model::fresnel::amplitudes_eps;
use polar_model::material::MaterialLibrary;
use polar_model::pbrdf::{DiffuseTerm, Geometry, Surface};
use polar_model::quadrature::Tolerance;

const N: usize = 4096;

/// A small deterministic generator (SplitMix64) so every run evaluates the same inputs.
fn uniform(state: &mut u64) -> f64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

struct Case {
    surface: Surface,
    angles_rad: (f64, f64, f64),
    directions: (nalgebra::Vector3<f64>, nalgebra::Vector3<f64>),
    geometry: Geometry,
    diffuse: DiffuseTerm,
}

fn cases() -> Vec<Case> {
    let lib = MaterialLibrary::builtin();
    let surfaces: Vec<Surface> = lib
        .materials
        .iter()
        .map(|m| m.surface().expect("built-in"))
        .collect();
    // A few sun positions per material, as in a scene: the diffuse term is per (material, sun).
    let suns = [10.0f64, 35.0, 60.0, 85.0];
    let diffuse: Vec<Vec<DiffuseTerm>> = surfaces
        .iter()
        .map(|s| {
            suns.iter()
                .map(|t| {
                    s.diffuse(t.to_radians(), Tolerance::absolute(1e-9))
                        .expect("in range")
                })
                .collect()
        })
        .collect();
    let mut state = 42u64;
    (0..N)
        .map(|_| {
            let m = (uniform(&mut state) * surfaces.len() as f64) as usize % surfaces.len();
            let k = (uniform(&mut state) * suns.len() as f64) as usize % suns.len();
            let ti = suns[k].to_radians();
            let tr = (uniform(&mut state) * 89.0).to_radians();
            let phi = (uniform(&mut state) * 360.0).to_radians();
            Case {
                surface: surfaces[m],
                angles_rad: (ti, tr, phi),
                directions: (
                    nalgebra::Vector3::new(ti.sin(), 0.0, ti.cos()),
                    nalgebra::Vector3::new(tr.sin() * phi.cos(), tr.sin() * phi.sin(), tr.cos()),
                ),
                geometry: Geometry::from_angles(ti, tr, phi).expect("in range"),
                diffuse: diffuse[m][k],
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let cases = cases();
    let mut group = c.benchmark_group("pbrdf");
    group.throughput(Throughput::Elements(N as u64));
    group.bench_function("baseline_fresnel_only", |b| {
        let eps = num_complex::Complex64::new(1.02, 2.577).powi(2);
        b.iter(|| {
            let mut acc = 0.0;
            for case in &cases {
                let a = amplitudes_eps(eps, case.geometry.cos_theta_r());
                acc += a.rs_power() + a.rp_power() + a.re_rs_rp_conj();
            }
            black_box(acc)
        })
    });
    group.bench_function("mueller_from_geometry", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for case in &cases {
                acc += case
                    .surface
                    .mueller_with(black_box(&case.geometry), &case.diffuse)
                    .0
                    .sum();
            }
            black_box(acc)
        })
    });
    group.bench_function("mueller_from_directions", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for case in &cases {
                let (wi, wr) = black_box(&case.directions);
                let g = Geometry::from_directions(wi, wr).expect("unit vectors");
                acc += case.surface.mueller_with(&g, &case.diffuse).0.sum();
            }
            black_box(acc)
        })
    });
    group.bench_function("mueller_from_angles", |b| {
        b.iter(|| {
            let mut acc = 0.0;
            for case in &cases {
                let (ti, tr, phi) = black_box(case.angles_rad);
                let g = Geometry::from_angles(ti, tr, phi).expect("in range");
                acc += case.surface.mueller_with(&g, &case.diffuse).0.sum();
            }
            black_box(acc)
        })
    });
    group.finish();

    // The diffuse term (specular-albedo quadrature) once per (material, sun), at two tolerances.
    let mut group = c.benchmark_group("diffuse_term");
    let glass = MaterialLibrary::builtin()
        .get("glass")
        .expect("built-in")
        .surface()
        .expect("valid");
    for tol in [1e-6, 1e-9] {
        group.bench_function(format!("glass_ti60_tol{tol:e}"), |b| {
            b.iter(|| {
                black_box(
                    glass
                        .diffuse(60f64.to_radians(), Tolerance::absolute(tol))
                        .expect("in range"),
                )
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
