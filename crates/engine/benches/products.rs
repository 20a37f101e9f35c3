//! Benchmark of the live Stokes products (`polar_engine::products`).
//!
//! One angle set of 4 frames of 2448 x 2048 u16 (0/45/90/135 deg, ideal analyzer) of a
//! synthetic scene: S0 about 4000 DN (frames about 2000 DN), DoLP 0 to 0.6 and AoP varying
//! across the image, shot and read noise from the noise model, a seeded generator.
//!
//! It times `compute_into` with every available thread (scalar dark and dark map), and the
//! plain single-threaded f64 reference `compute_reference` (std `atan2` and `sqrt`), prints
//! the speed-up and the largest difference of the fast path from the reference (absolute
//! and in units of the predicted sigma). Goal: <= 20 ms per set on 2 cores.
//!
//! Run with `cargo bench -p polar-engine --bench products`.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{criterion_main, Criterion};
use polar_engine::products::{
    compute_into, compute_reference, Dark, NoiseModel, Products, SetGeometry, AOP_MAX_ERROR_RAD,
    ATAN2_MAX_ERROR_RAD,
};

use polar_hil_mocks::faults::Dice;

const WIDTH: u32 = 2448;
const HEIGHT: u32 = 2048;

struct Scene {
    frames: Vec<Vec<u16>>,
    geometry: SetGeometry,
    dark_scalar: Dark,
    dark_map: Dark,
    noise: NoiseModel,
}

fn scene() -> Scene {
    let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|d| d.to_radians())
        .collect();
    let geometry = SetGeometry::ideal(&angles).expect("0/45/90/135 is well conditioned");
    let k = 0.25;
    let noise = NoiseModel {
        gain_dn_per_e: k,
        offset_dn: 64.0,
        read_var_dn2: k * k * 9.0 + 1.0 / 12.0,
        saturation_dn: 4095,
    };
    let (w, h) = (WIDTH as usize, HEIGHT as usize);
    let n = w * h;
    let dark_level = 70.0;
    let mut rng = Dice::new(0x00C0_FFEE);
    let map: Vec<f32> = (0..n)
        .map(|_| (dark_level + 0.5 * rng.normal()) as f32)
        .collect();
    let mut frames = vec![vec![0u16; n]; 4];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let fx = x as f64 / w as f64;
            let fy = y as f64 / h as f64;
            let s0 = 4000.0 * (0.8 + 0.4 * fy) + 300.0 * (13.0 * fx).sin();
            let dolp = 0.6 * fx;
            let aop = std::f64::consts::PI * (fy - 0.5) + 0.3 * (7.0 * fx).sin();
            let s = [
                s0,
                s0 * dolp * (2.0 * aop).cos(),
                s0 * dolp * (2.0 * aop).sin(),
            ];
            for (f, r) in frames.iter_mut().zip(geometry.rows()) {
                let mean = r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + f64::from(map[i]);
                let var = k * (mean - noise.offset_dn).max(0.0) + noise.read_var_dn2;
                let v = (mean + var.sqrt() * rng.normal()).round();
                f[i] = v.clamp(0.0, 65535.0) as u16;
            }
        }
    }
    // A few saturated pixels.
    for i in (0..n).step_by(100_003) {
        frames[1][i] = 4095;
    }
    Scene {
        frames,
        geometry,
        dark_scalar: Dark::Scalar(dark_level as f32),
        dark_map: Dark::Map(map),
        noise,
    }
}

/// Largest differences of `fast` from `reference`: per image, the max absolute difference
/// (AoP modulo pi) over pixels finite in both, the number of pixels finite in only one,
/// for S0..AoP the max difference in units of the reference's predicted sigma, and for the
/// sigmas the max relative difference.
fn report_differences(fast: &Products, reference: &Products) {
    let names = Products::names();
    let fi = fast.images();
    let ri = reference.images();
    println!("fast path vs f64 reference (same frames):");
    for k in 0..10 {
        let (mut max_abs, mut max_sig, mut max_rel, mut mismatch) = (0.0f64, 0.0f64, 0.0f64, 0u64);
        for j in 0..fi[k].len() {
            let (a, b) = (f64::from(fi[k][j]), f64::from(ri[k][j]));
            if a.is_finite() != b.is_finite() {
                mismatch += 1;
                continue;
            }
            if !a.is_finite() {
                continue;
            }
            let mut d = (a - b).abs();
            if names[k] == "aop_rad" {
                d = d.min(std::f64::consts::PI - d);
            }
            max_abs = max_abs.max(d);
            if k >= 5 && b != 0.0 {
                max_rel = max_rel.max(d / b.abs());
            }
            if k < 5 {
                let sig = f64::from(ri[k + 5][j]);
                if sig > 0.0 && sig.is_finite() {
                    max_sig = max_sig.max(d / sig);
                }
            }
        }
        if k < 5 {
            println!(
                "  {:<14} max |diff| {max_abs:.3e}  = {max_sig:.3e} sigma  \
                 finite-in-one-only {mismatch}",
                names[k]
            );
        } else {
            println!(
                "  {:<14} max |diff| {max_abs:.3e}  = {max_rel:.3e} relative  \
                 finite-in-one-only {mismatch}",
                names[k]
            );
        }
    }
    println!(
        "  saturated: fast {} reference {}; AoP approximation max error {AOP_MAX_ERROR_RAD:e} \
         rad (fast_atan2: {ATAN2_MAX_ERROR_RAD:e} rad)",
        fast.saturated, reference.saturated
    );
}

fn bench(c: &mut Criterion) {
    let sc = scene();
    let refs: Vec<&[u16]> = sc.frames.iter().map(Vec::as_slice).collect();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut out = Products::empty();
    let run = |out: &mut Products, dark: &Dark| {
        compute_into(
            out,
            &refs,
            WIDTH,
            HEIGHT,
            &sc.geometry,
            dark,
            &sc.noise,
            threads,
        )
        .expect("valid inputs")
    };
    run(&mut out, &sc.dark_map);
    let reference = compute_reference(&refs, WIDTH, HEIGHT, &sc.geometry, &sc.dark_map, &sc.noise)
        .expect("valid inputs");
    report_differences(&out, &reference);

    // Quick stand-alone timing for the ratio (criterion's numbers follow). The machine may
    // be shared: the minimum is the cost without interference, the median the typical one.
    let mut fast: Vec<Duration> = (0..30)
        .map(|_| {
            let t = Instant::now();
            run(&mut out, &sc.dark_map);
            t.elapsed()
        })
        .collect();
    let mut slow: Vec<Duration> = (0..3)
        .map(|_| {
            let t = Instant::now();
            black_box(
                compute_reference(&refs, WIDTH, HEIGHT, &sc.geometry, &sc.dark_map, &sc.noise)
                    .expect("valid inputs"),
            );
            t.elapsed()
        })
        .collect();
    fast.sort();
    slow.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let (f_min, f_med) = (fast[0], fast[fast.len() / 2]);
    let (s_min, s_med) = (slow[0], slow[slow.len() / 2]);
    println!(
        "4 x {WIDTH}x{HEIGHT}, dark map, {threads} threads: fast min {:.2} ms / median {:.2} ms; \
         f64 reference (1 thread) min {:.1} ms / median {:.1} ms; speed-up {:.1}x (min) / \
         {:.1}x (median)",
        ms(f_min),
        ms(f_med),
        ms(s_min),
        ms(s_med),
        ms(s_min) / ms(f_min),
        ms(s_med) / ms(f_med),
    );

    let mut g = c.benchmark_group("products_4x2448x2048");
    g.sample_size(30);
    g.measurement_time(Duration::from_secs(4));
    g.bench_function(format!("fast_f32_{threads}_threads_dark_map"), |b| {
        b.iter(|| run(&mut out, &sc.dark_map))
    });
    g.bench_function(format!("fast_f32_{threads}_threads_dark_scalar"), |b| {
        b.iter(|| run(&mut out, &sc.dark_scalar))
    });
    g.bench_function("fast_f32_1_thread_dark_map", |b| {
        b.iter(|| {
            compute_into(
                &mut out,
                &refs,
                WIDTH,
                HEIGHT,
                &sc.geometry,
                &sc.dark_map,
                &sc.noise,
                1,
            )
            .expect("valid inputs")
        })
    });
    g.sample_size(10);
    g.measurement_time(Duration::from_secs(8));
    g.bench_function("reference_f64_1_thread_dark_map", |b| {
        b.iter(|| {
            compute_reference(&refs, WIDTH, HEIGHT, &sc.geometry, &sc.dark_map, &sc.noise)
                .expect("valid inputs")
        })
    });
    g.finish();
}

/// The criterion group (the macro's `pub fn` has no doc of its own).
#[allow(missing_docs)]
mod group {
    criterion::criterion_group!(benches, super::bench);
}

criterion_main!(group::benches);
