//! `polarimeter bench scene`: time per scene evaluation against its actual error, for the
//! example scenes, at tolerances 1e-2 .. 1e-8, against a reference computed in the same run at
//! a tighter tolerance.

use polar_model::scene::{MaterialResult, Prepared};
use polar_model::scene_file::Scene;
use std::time::{Duration, Instant};

/// The example scenes, embedded so that the benchmark runs from any directory.
pub const EXAMPLES: [(&str, &str); 3] = [
    ("bench", include_str!("../../../examples/bench.toml")),
    ("rooftop", include_str!("../../../examples/rooftop.toml")),
    ("airborne", include_str!("../../../examples/airborne.toml")),
];

/// One row of the table.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// Scene name.
    pub scene: String,
    /// Tolerance asked for.
    pub tolerance: f64,
    /// Median wall time of one whole-scene evaluation (all materials).
    pub time: Duration,
    /// Largest actual error of a material's mean (norm of the Stokes difference over the
    /// reference S0) against the reference.
    pub actual_error: f64,
    /// Largest reported error estimate.
    pub error_estimate: f64,
    /// Quadrature evaluations, all materials.
    pub evaluations: usize,
}

fn evaluate(scene: &Scene, tol: f64) -> anyhow::Result<Vec<MaterialResult>> {
    let p = Prepared::new(&scene.spec, tol)?;
    Ok(scene
        .materials
        .iter()
        .map(|m| p.evaluate(m))
        .collect::<Result<_, _>>()?)
}

/// Runs the benchmark: `tolerances` against a reference at `reference_tol`, each timing the
/// median of at least `min_runs` runs and at least `min_time`.
pub fn scene(
    scenes: &[(&str, &str)],
    tolerances: &[f64],
    reference_tol: f64,
    min_runs: usize,
    min_time: Duration,
) -> anyhow::Result<Vec<Row>> {
    let mut rows = Vec::new();
    for (name, text) in scenes {
        let scene = Scene::from_toml_str(text)?;
        let reference = evaluate(&scene, reference_tol)?;
        for &tol in tolerances {
            let mut times = Vec::new();
            let start = Instant::now();
            let mut last = None;
            while times.len() < min_runs || start.elapsed() < min_time {
                let t = Instant::now();
                let r = evaluate(&scene, tol)?;
                times.push(t.elapsed());
                last = Some(r);
                if times.len() >= 1000 {
                    break;
                }
            }
            times.sort();
            let r = last.unwrap_or_default();
            let actual_error = r
                .iter()
                .zip(&reference)
                .map(|(a, b)| (a.mean.0 - b.mean.0).norm() / b.mean.0[0].abs().max(1e-300))
                .fold(0.0, f64::max);
            rows.push(Row {
                scene: name.to_string(),
                tolerance: tol,
                time: times[times.len() / 2],
                actual_error,
                error_estimate: r.iter().map(|m| m.error_estimate).fold(0.0, f64::max),
                evaluations: r.iter().map(|m| m.evaluations).sum(),
            });
        }
    }
    Ok(rows)
}

/// The rows as a Markdown table.
pub fn markdown(rows: &[Row], reference_tol: f64) -> String {
    let mut out = format!(
        "| scene | tolerance | time per scene | actual error (vs {reference_tol:.0e}) | error estimate | evaluations |\n|---|---|---|---|---|---|\n"
    );
    for r in rows {
        out += &format!(
            "| {} | {:.0e} | {:.3} ms | {:.2e} | {:.2e} | {} |\n",
            r.scene,
            r.tolerance,
            r.time.as_secs_f64() * 1e3,
            r.actual_error,
            r.error_estimate,
            r.evaluations
        );
    }
    out
}
