//! `report validation` on a tiny grid through the library: the analytic statistics agree with
//! the whole-chain Monte Carlo within the Monte Carlo's standard errors plus a stated bound on
//! the model's own bias, and the Markdown report carries the command, the summary and one row
//! per point.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_cli::validation::{self, GridSpec, Level};
use polar_model::stats::Regime;

/// The example CMOS (2.5 e- read noise, 10 000 e- full well) at 45 % of its full well, through
/// the two symmetric sets 0/60/120 and 0/45/90/135 (isotropic polarised noise), scene DoLP 0,
/// 0.02 and 0.3 at AoP 15 deg: 6 points, from SNR_p 0 (Rice) through about 1.6 (Rice) to about
/// 25 (Taylor), `S0 / sigma_S0` above 100.
fn tiny_grid() -> GridSpec {
    let mut g = GridSpec::report().unwrap();
    g.cameras.retain(|(label, _)| label == "CMOS");
    g.levels = vec![Level::FullWellFraction(0.45)];
    g.angle_sets_deg = vec![vec![0.0, 60.0, 120.0], vec![0.0, 45.0, 90.0, 135.0]];
    g.dolps = vec![0.0, 0.02, 0.3];
    g.aops_deg = vec![15.0];
    g
}

/// Every statistic of every point within `4 SE + bias`, the bias bound being the size of the
/// first term the analytic regime leaves out:
///
/// * Taylor: the first-order variances are exact to `1/(2 SNR^2)` relative
///   (`Var p_hat = sigma^2 (1 - 1/(2 SNR^2) + ...)`; the phase spread likewise); the second-order
///   mean to the Rice series' next term `1/(8 SNR^4)` relative;
/// * Rice (isotropic noise, as here): the DoLP of `p_hat / S0_hat` is treated to first order in
///   the `S0` noise, which leaves out terms of relative size `3 (sigma_S0/S0)^2`;
/// * both: rounding and Poisson skew change the shape, not the variance, of the Stokes noise;
///   at 4500 e-/frame and 23 DN of frame noise they are below the Monte Carlo's resolution, so
///   no allowance is made for them.
///
/// 20 000 sets per point; with 18 comparisons at 4 SE a failure by chance is about 1e-3 (and
/// the seeded run is deterministic).
#[test]
fn tiny_grid_agrees_within_standard_errors_and_stated_bias() {
    let points = tiny_grid().points().unwrap();
    assert_eq!(points.len(), 6);
    let rows = validation::run(&points, 20_000, 1).unwrap();
    let mut regimes = Vec::new();
    for (i, r) in rows.iter().enumerate() {
        let c = &r.result.comparison;
        let a = &r.result.analytic;
        let rho2 = c.polarised_snr * c.polarised_snr;
        let cs0_2 = a.estimator.cov[(0, 0)] / a.stokes_mean_w_m2_sr[0].powi(2);
        assert!(cs0_2 < 1e-4, "#{i}: S0 is known to better than 1 %");
        if c.regime == Regime::Rice {
            // Symmetric sets and a weakly polarised scene: the isotropy the Rice moments assume.
            assert!(!validation::anisotropic(r), "#{i}");
        }
        let (mean_rel, std_rel) = match c.regime {
            Regime::Taylor => (1.0 / (8.0 * rho2 * rho2), 1.0 / (2.0 * rho2)),
            Regime::Rice => (3.0 * cs0_2, 3.0 * cs0_2),
        };
        for (name, ag, rel) in [
            ("DoLP mean", c.dolp_mean, mean_rel),
            ("DoLP std", c.dolp_std, std_rel),
            ("AoP std", c.aop_std, std_rel),
        ] {
            let bound = 4.0 * ag.se + rel * ag.analytic.abs();
            assert!(
                (ag.analytic - ag.monte_carlo).abs() < bound,
                "#{i} {name} ({:?}, SNR_p {:.2}): {ag:?}, bound {bound:e}",
                c.regime,
                c.polarised_snr
            );
        }
        assert_eq!(r.result.monte_carlo.saturated_fraction, 0.0);
        regimes.push(c.regime);
    }
    assert!(regimes.contains(&Regime::Taylor) && regimes.contains(&Regime::Rice));

    let md = validation::markdown(&rows, 20_000, 1, "polarimeter report validation --tiny");
    assert!(md.contains("    polarimeter report validation --tiny"));
    assert!(md.contains("## Summary") && md.contains("### Findings"));
    assert!(md.contains("| Taylor, SNR_p >= 10 |"));
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
