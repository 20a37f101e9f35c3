//! Throughput of the JSON-lines batch path (parse, evaluate, serialise) for `model pbrdf` and
//! `model fresnel`, in memory (no process or pipe cost), against a baseline in the same run:
//! parsing and re-serialising the same lines without evaluating them.
//!
//!     cargo bench -p polar-cli --bench batch

#![allow(missing_docs)] // criterion_group! generates undocumented items.

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use polar_cli::batch::{run, Kind};

const LINES: usize = 2000;

fn pbrdf_lines() -> String {
    // One scene: two materials under one sun, many view directions (the diffuse term is shared).
    let mut s = String::new();
    for i in 0..LINES {
        let (n, k, sigma, dhr) = if i % 2 == 0 {
            (1.52, 0.0, 0.1, 0.1)
        } else {
            (1.02, 2.577, 0.3, 0.7)
        };
        let tr = (i * 7 % 89) as f64;
        let phi = (i * 13 % 360) as f64;
        s.push_str(&format!(
            "{{\"n\":{n},\"k\":{k},\"sigma\":{sigma},\"dhr\":{dhr},\"theta_i_deg\":45,\"theta_r_deg\":{tr},\"phi_deg\":{phi}}}\n"
        ));
    }
    s
}

fn fresnel_lines() -> String {
    (0..LINES)
        .map(|i| {
            format!(
                "{{\"n\":1.52,\"theta_i_deg\":{}}}\n",
                (i % 900) as f64 * 0.1
            )
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let pbrdf = pbrdf_lines();
    let fresnel = fresnel_lines();
    let mut group = c.benchmark_group("batch");
    group.throughput(Throughput::Elements(LINES as u64));
    group.bench_function("baseline_parse_and_serialise", |b| {
        b.iter(|| {
            let mut out = Vec::with_capacity(pbrdf.len() * 2);
            for line in pbrdf.lines() {
                let v: serde_json::Value = serde_json::from_str(line).expect("valid");
                serde_json::to_writer(&mut out, &v).expect("memory");
                out.push(b'\n');
            }
            black_box(out)
        })
    });
    group.bench_function("pbrdf", |b| {
        b.iter(|| {
            let mut out = Vec::with_capacity(pbrdf.len() * 4);
            black_box(run(Kind::Pbrdf, pbrdf.as_bytes(), &mut out).expect("memory"))
        })
    });
    group.bench_function("fresnel", |b| {
        b.iter(|| {
            let mut out = Vec::with_capacity(fresnel.len() * 4);
            black_box(run(Kind::Fresnel, fresnel.as_bytes(), &mut out).expect("memory"))
        })
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
