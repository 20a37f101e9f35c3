//! Monte Carlo check of the DoLP-threshold ROC ([`polar_model::metrics::dolp_threshold`]), the
//! one ROC of MODEL.md section 8 that `metrics.rs`'s own `rocs_match_monte_carlo` (matched
//! filter and RX) does not cover: synthetic pixels drawn through the whole sensor chain
//! ([`polar_model::validation::sample_products`]), thresholded where the analytic ROC puts its
//! threshold, against the analytic false-alarm and detection rates.
#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_model::atmosphere::Band;
use polar_model::metrics::{dolp_threshold, q_inv};
use polar_model::polarization::Stokes;
use polar_model::sensor::{Camera, Exposure, SensorModel};
use polar_model::stats::{MethodChoice, Regime, RegimeChoice};
use polar_model::validation::{analytic_products, sample_products, McConfig};

const SETS: usize = 200_000;

fn cmos() -> SensorModel {
    let cam =
        Camera::from_toml_str(include_str!("../../../examples/cameras/cmos_modern.toml")).unwrap();
    SensorModel::new(&cam, &Band::flat(500.0, 600.0).unwrap()).unwrap()
}

fn angles() -> Vec<f64> {
    [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|d| d.to_radians())
        .collect()
}

/// A pixel class: mean photo-electrons per frame `electrons` (unpolarised part) of a scene of
/// DoLP `dolp` at AoP 30 deg.
fn class(model: &SensorModel, electrons: f64, dolp: f64) -> Exposure {
    let w = model.intensities_from_stokes(&angles()).unwrap();
    let s0 = 0.1;
    let t = electrons / (model.responsivity_e_per_s() * w.column(0).mean() * s0);
    let a = 60f64.to_radians();
    Exposure::new(t, Stokes::new(s0, s0 * dolp * a.cos(), s0 * dolp * a.sin()))
}

/// DoLPs of `SETS` synthetic pixels of a class.
fn dolps(model: &SensorModel, ex: &Exposure, seed: u64) -> Vec<f64> {
    sample_products(model, &angles(), ex, &McConfig::new(SETS, seed))
        .unwrap()
        .iter()
        .map(|s| s.dolp.unwrap())
        .collect()
}

fn rate_above(xs: &[f64], eta: f64) -> f64 {
    xs.iter().filter(|&&x| x > eta).count() as f64 / xs.len() as f64
}

fn binomial_se(p: f64) -> f64 {
    (p * (1.0 - p) / SETS as f64).sqrt()
}

/// Sample skewness.
fn skewness(xs: &[f64]) -> f64 {
    let n = xs.len() as f64;
    let m = xs.iter().sum::<f64>() / n;
    let m2 = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    let m3 = xs.iter().map(|x| (x - m).powi(3)).sum::<f64>() / n;
    m3 / m2.powf(1.5)
}

/// First Edgeworth correction to a Gaussian tail at `z` standard deviations for skewness `g`:
/// `|g| / 6 |z^2 - 1| phi(z)` (the leading error of treating a skewed variable as Gaussian).
fn edgeworth(g: f64, z: f64) -> f64 {
    g.abs() / 6.0 * (z * z - 1.0).abs() * (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Taylor regime, where `dolp_threshold` says its Gaussian treatment holds: background DoLP
/// 0.30, target 0.32, 4500 e-/frame through 0/45/90/135 (polarised SNR about 28, DoLP standard
/// deviation about 0.011, so the classes overlap: Pd 0.1 to 0.8). At Pfa = 1e-3, 1e-2 and 0.1
/// the threshold the analytic ROC implies (`m_b + s_b Q^-1(Pfa)`) gives, on 2e5 whole-chain
/// pixels per class, a false-alarm and a detection rate within 4 binomial standard errors plus
/// the first Edgeworth term of the measured skewness (the Gaussian approximation's own error)
/// of the analytic values.
#[test]
fn dolp_threshold_roc_matches_monte_carlo_in_the_taylor_regime() {
    let model = cmos();
    let (b_ex, t_ex) = (class(&model, 4500.0, 0.30), class(&model, 4500.0, 0.32));
    let stats = |ex: &Exposure| {
        analytic_products(
            &model,
            &angles(),
            ex,
            MethodChoice::Auto,
            RegimeChoice::Auto,
        )
        .unwrap()
        .stats
    };
    let (b, t) = (stats(&b_ex), stats(&t_ex));
    assert_eq!((b.regime, t.regime), (Regime::Taylor, Regime::Taylor));
    assert!(b.polarised_snr > 20.0, "{}", b.polarised_snr);
    let xb = dolps(&model, &b_ex, 21);
    let xt = dolps(&model, &t_ex, 22);
    let (gb, gt) = (skewness(&xb), skewness(&xt));
    for pfa in [1e-3, 1e-2, 0.1] {
        let roc =
            dolp_threshold((t.dolp_mean, t.dolp_std), (b.dolp_mean, b.dolp_std), pfa).unwrap();
        let eta = b.dolp_mean + b.dolp_std * q_inv(pfa);
        let zt = (eta - t.dolp_mean) / t.dolp_std;
        let (fa, pd) = (rate_above(&xb, eta), rate_above(&xt, eta));
        let tol_fa = 4.0 * binomial_se(pfa) + edgeworth(gb, q_inv(pfa));
        let tol_pd = 4.0 * binomial_se(roc.pd) + edgeworth(gt, zt);
        eprintln!(
            "Pfa {pfa}: MC {fa:.5} (tol {tol_fa:.1e}); Pd analytic {:.5} MC {pd:.5} (tol \
             {tol_pd:.1e}); skewness {gb:.3} {gt:.3}",
            roc.pd
        );
        assert!(
            (fa - pfa).abs() < tol_fa,
            "Pfa {pfa}: MC {fa}, tolerance {tol_fa:e}"
        );
        assert!(
            (pd - roc.pd).abs() < tol_pd,
            "Pfa {pfa}: Pd MC {pd} analytic {}, tolerance {tol_pd:e}",
            roc.pd
        );
        assert!(
            roc.pd > 0.05 && roc.pd < 0.95,
            "a discriminating point: {}",
            roc.pd
        );
    }
}

/// Rice regime, where the Gaussian treatment is known to fail, and the right answer there: an
/// unpolarised background (4500 e-/frame, 0/45/90/135: isotropic polarised noise, `S0` known to
/// 0.8 %) has a Rayleigh-distributed DoLP, `P(DoLP > eta) = exp(-eta^2 / (2 s^2))` with
/// `s = sigma_p / S0`. On 2e5 whole-chain pixels the false-alarm rate at the Gaussian threshold
/// for Pfa = 1e-2 is far from 1e-2 (more than 10 binomial standard errors), and within 4 of the
/// Rayleigh tail (plus its change from the `S0` noise, relative `2 a^2 (sigma_S0/S0)^2` with
/// `a = eta^2 / (2 s^2)`, 0.5 % here); `dolp_threshold` warns that it assumed Gaussian DoLPs.
#[test]
fn dolp_threshold_gaussian_tail_fails_for_an_unpolarised_background() {
    let model = cmos();
    let b_ex = class(&model, 4500.0, 0.0);
    let a = analytic_products(
        &model,
        &angles(),
        &b_ex,
        MethodChoice::Auto,
        RegimeChoice::Auto,
    )
    .unwrap();
    let b = &a.stats;
    assert_eq!(b.regime, Regime::Rice);
    let s0 = a.stokes_mean_w_m2_sr[0];
    let c2 = a.estimator.cov[(0, 0)] / (s0 * s0);
    assert!(c2 < 1e-4);
    let s = b.sigma_p / s0;
    let xb = dolps(&model, &b_ex, 31);
    let pfa = 1e-2;
    let roc = dolp_threshold(
        (b.dolp_mean * 1.5, b.dolp_std),
        (b.dolp_mean, b.dolp_std),
        pfa,
    )
    .unwrap();
    assert!(roc.warnings.iter().any(|w| w.contains("Gaussian")));
    let eta = b.dolp_mean + b.dolp_std * q_inv(pfa);
    let fa = rate_above(&xb, eta);
    assert!(
        (fa - pfa).abs() > 10.0 * binomial_se(pfa),
        "the Gaussian tail should fail here: MC {fa}"
    );
    let arg = eta * eta / (2.0 * s * s);
    let rayleigh = (-arg).exp();
    let tol = 4.0 * binomial_se(rayleigh) + 2.0 * arg * arg * c2 * rayleigh;
    eprintln!("Gaussian Pfa {pfa}: MC {fa:.5}, Rayleigh {rayleigh:.5} (tol {tol:.1e})");
    assert!(
        (fa - rayleigh).abs() < tol,
        "MC {fa}, Rayleigh {rayleigh}, tolerance {tol:e}"
    );
}
