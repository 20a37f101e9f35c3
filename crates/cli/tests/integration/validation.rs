//! `report validation` on a tiny grid through the library: the analytic statistics agree with
//! the whole-chain Monte Carlo within the Monte Carlo's standard errors plus the analytic
//! method's own error estimate, and the Markdown report carries the command, the groups by
//! polarised-SNR band, the approximations for reference, the link to the accuracy-grid report
//! and one row per point.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_cli::validation::{self, GridSpec, Level};
use polar_model::stats::StatsMethod;

/// The example CMOS (2.5 e- read noise, 10 000 e- full well) at 45 % of its full well, through
/// the two symmetric sets 0/60/120 and 0/45/90/135 (isotropic polarised noise), scene DoLP 0,
/// 0.02 and 0.3 at AoP 15 deg: 6 points, at SNR_p 0, about 1.6 and about 25, `S0 / sigma_S0`
/// above 100.
fn tiny_grid() -> GridSpec {
    let mut g = GridSpec::report().unwrap();
    g.cameras.retain(|(label, _)| label == "CMOS");
    g.levels = vec![Level::FullWellFraction(0.45)];
    g.angle_sets_deg = vec![vec![0.0, 60.0, 120.0], vec![0.0, 45.0, 90.0, 135.0]];
    g.dolps = vec![0.0, 0.02, 0.3];
    g.aops_deg = vec![15.0];
    g
}

/// Every statistic of every point within `4 SE + est`, `est` the integration's own estimated
/// relative error: the analytic method is the exact statistics of Gaussian Stokes noise at every
/// polarised SNR, and at 4500 e-/frame and 23 DN of frame noise the chain's departure from
/// Gaussian Stokes noise (Poisson skew, rounding) is below the Monte Carlo's resolution, so no
/// allowance is made for it. The Taylor approximation is evaluated wherever `p > 0` and the
/// Rice approximation everywhere; at DoLP 0.02 (SNR_p about 1.6) the second-order Taylor DoLP
/// mean `p (1 + 1/(2 SNR^2))` is 1.9 % below the Rician mean `sigma sqrt(pi/2) L_1/2(-SNR^2/2)`
/// that the integration reproduces (its `sigma^2 / (2 p)` term is only the start of a series
/// that diverges as `p -> 0`: MODEL.md section 7), so they must differ by more than 1 %.
///
/// 20 000 sets per point; with 18 comparisons at 4 SE a failure by chance is about 1e-3 (and
/// the seeded run is deterministic).
#[test]
fn tiny_grid_agrees_within_standard_errors() {
    let points = tiny_grid().points().unwrap();
    assert_eq!(points.len(), 6);
    let rows = validation::run(&points, 20_000, 1).unwrap();
    let mut snrs = Vec::new();
    let mut taylor_low_snr_err: f64 = 0.0;
    for (i, r) in rows.iter().enumerate() {
        let c = &r.result.comparison;
        let a = &r.result.analytic;
        let cs0_2 = a.estimator.cov[(0, 0)] / a.stokes_mean_w_m2_sr[0].powi(2);
        assert!(cs0_2 < 1e-4, "#{i}: S0 is known to better than 1 %");
        assert_eq!(a.stats.method, StatsMethod::Integration, "#{i}");
        let est = a.stats.rel_error_estimate.unwrap();
        assert!(est < 1e-4, "#{i}: estimated error {est:e}");
        for (name, ag) in [
            ("DoLP mean", c.dolp_mean),
            ("DoLP std", c.dolp_std),
            ("AoP std", c.aop_std),
        ] {
            let bound = 4.0 * ag.se + est * ag.analytic.abs();
            assert!(
                (ag.analytic - ag.monte_carlo).abs() < bound,
                "#{i} {name} (SNR_p {:.2}): {ag:?}, bound {bound:e}",
                c.polarised_snr
            );
        }
        assert_eq!(r.taylor.is_some(), r.point.dolp > 0.0, "#{i}");
        if let Some(t) = &r.taylor {
            if c.polarised_snr < 3.0 {
                let d = (t.dolp_mean.analytic / c.dolp_mean.analytic - 1.0).abs();
                taylor_low_snr_err = taylor_low_snr_err.max(d);
            }
        }
        assert_eq!(r.result.monte_carlo.saturated_fraction, 0.0);
        snrs.push(c.polarised_snr);
    }
    assert!(snrs.iter().any(|&s| s >= 10.0) && snrs.iter().any(|&s| s < 3.0));
    assert!(taylor_low_snr_err > 0.01, "{taylor_low_snr_err}");

    let md = validation::markdown(&rows, 20_000, 1, "polarimeter report validation --tiny");
    assert!(md.contains("    polarimeter report validation --tiny"));
    assert!(md.contains("## Summary") && md.contains("### Findings"));
    let high_snr_points: usize = md
        .lines()
        .filter(|l| l.starts_with("| SNR_p >= 10, "))
        .filter_map(|l| l.split('|').nth(2)?.trim().parse::<usize>().ok())
        .sum();
    assert_eq!(high_snr_points, 2, "the two DoLP 0.3 points");
    assert!(md.contains("### Approximations, for reference"));
    assert!(md.contains("| Taylor, SNR_p < 3 | 2 |"));
    assert!(md.contains(&format!("[{0}]({0})", validation::GRID_REPORT_LINK)));
    assert!(md.contains(polar_cli::bench_stats::GRID_COMMAND));
    let table_rows = md
        .lines()
        .filter(|l| l.starts_with("| ") && l[2..].starts_with(|c: char| c.is_ascii_digit()))
        .count();
    assert_eq!(table_rows, 6, "one row per point");
}

/// The point seeds depend on the run's seed: another seed moves the Monte Carlo values but not
/// the analytic ones.
#[test]
fn seed_moves_only_the_monte_carlo() {
    let points = tiny_grid().points().unwrap();
    let a = validation::run(&points[..1], 2_000, 1).unwrap();
    let b = validation::run(&points[..1], 2_000, 2).unwrap();
    let (ca, cb) = (&a[0].result.comparison, &b[0].result.comparison);
    assert_eq!(ca.dolp_mean.analytic, cb.dolp_mean.analytic);
    assert_ne!(ca.dolp_mean.monte_carlo, cb.dolp_mean.monte_carlo);
    assert!(validation::run(&points[..1], 1, 1).is_err());
}

/// `bench stats --grid --out`: the accuracy-grid report is its own file, written into a
/// directory it creates, naming the command that regenerates it and linking back to the
/// whole-chain report; with the fewest draws allowed (4e5 per state) `dolp_aop_stats` agrees
/// with the Stokes-level Monte Carlo on all 324 comparisons within 5 standard errors (the
/// integration's estimated error is below 1e-6, far under the Monte Carlo's 0.1 %; a |z| of 5
/// among 324 normal deviates has a chance of about 2e-4, and the seeded run is deterministic),
/// and the report has one table row per state.
#[test]
fn grid_report_is_written_to_its_own_file() {
    use polar_cli::bench_stats::{self, GRID_MIN_SAMPLES};
    let dir = std::env::temp_dir().join(format!("polar-grid-report-{}", std::process::id()));
    let out = dir.join("validation").join("dolp-aop-grid.md");
    let command = "polarimeter bench stats --grid --test";
    let rows = bench_stats::write_grid_report(&out, GRID_MIN_SAMPLES, 1, command).unwrap();
    assert_eq!(rows.len(), 108);
    for r in &rows {
        assert!(r.predicted_error < 1e-6, "{r:?}");
        for z in r.z_scores() {
            assert!(z.abs() < 5.0, "{r:?}");
        }
    }
    let md = std::fs::read_to_string(&out).unwrap();
    assert!(md.contains(&format!("    {command}\n")));
    assert!(md.contains("[../VALIDATION.md](../VALIDATION.md)"));
    let table_rows = md.lines().filter(|l| l.starts_with("| 0/")).count();
    assert_eq!(table_rows, 108, "one row per state");
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(bench_stats::run_grid(GRID_MIN_SAMPLES - 1, 1).is_err());
}
