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
    /// Median wall time of one whole-scene evaluation (all materials) on rayon's pool.
    pub time: Duration,
    /// The same on one thread, measured in the same run: the baseline of the speed-up.
    pub time_one_thread: Duration,
    /// Largest actual error of a material's mean (norm of the Stokes difference over the
    /// reference S0) against the reference.
    pub actual_error: f64,
    /// Largest reported error estimate.
    pub error_estimate: f64,
    /// Quadrature evaluations, all materials.
    pub evaluations: usize,
}

fn evaluate(scene: &Scene, tol: f64) -> anyhow::Result<Vec<MaterialResult>> {
    Ok(Prepared::new(&scene.spec, tol)?.evaluate_all(&scene.materials)?)
}

/// The median wall time of `scene` at `tol` over at least `min_runs` runs and `min_time`, and
/// the last run's results.
fn median_time(
    scene: &Scene,
    tol: f64,
    min_runs: usize,
    min_time: Duration,
) -> anyhow::Result<(Duration, Vec<MaterialResult>)> {
    let mut times = Vec::new();
    let start = Instant::now();
    let mut last = Vec::new();
    while times.len() < min_runs || start.elapsed() < min_time {
        let t = Instant::now();
        last = evaluate(scene, tol)?;
        times.push(t.elapsed());
        if times.len() >= 1000 {
            break;
        }
    }
    times.sort();
    Ok((times[times.len() / 2], last))
}

/// Threads of rayon's pool, which the scene model's parallel loops use.
pub fn threads() -> usize {
    rayon::current_num_threads()
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
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    for (name, text) in scenes {
        let scene = Scene::from_toml_str(text)?;
        let reference = evaluate(&scene, reference_tol)?;
        for &tol in tolerances {
            let (time, r) = median_time(&scene, tol, min_runs, min_time)?;
            let (time_one_thread, _) =
                one_thread.install(|| median_time(&scene, tol, min_runs, min_time))?;
            let actual_error = r
                .iter()
                .zip(&reference)
                .map(|(a, b)| (a.mean.0 - b.mean.0).norm() / b.mean.0[0].abs().max(1e-300))
                .fold(0.0, f64::max);
            rows.push(Row {
                scene: name.to_string(),
                tolerance: tol,
                time,
                time_one_thread,
                actual_error,
                error_estimate: r.iter().map(|m| m.error_estimate).fold(0.0, f64::max),
                evaluations: r.iter().map(|m| m.evaluations).sum(),
            });
        }
    }
    Ok(rows)
}

/// The rows as a Markdown table; `threads` is the size of the pool the first time column ran on.
pub fn markdown(rows: &[Row], reference_tol: f64, threads: usize) -> String {
    let mut out = format!(
        "| scene | tolerance | time per scene ({threads} threads) | 1 thread | speed-up | actual error (vs {reference_tol:.0e}) | error estimate | evaluations |\n|---|---|---|---|---|---|---|---|\n"
    );
    for r in rows {
        out += &format!(
            "| {} | {:.0e} | {:.3} ms | {:.3} ms | {:.2}x | {:.2e} | {:.2e} | {} |\n",
            r.scene,
            r.tolerance,
            r.time.as_secs_f64() * 1e3,
            r.time_one_thread.as_secs_f64() * 1e3,
            r.time_one_thread.as_secs_f64() / r.time.as_secs_f64().max(1e-12),
            r.actual_error,
            r.error_estimate,
            r.evaluations
        );
    }
    out
}
