//! A seeded Monte Carlo of the whole sensor chain (MODEL.md section 7, "Monte Carlo
//! validation"), frame by frame as a camera produces them: the scene radiance drawn from its
//! mean and clutter covariance, Poisson photo-electrons and dark electrons, the full well,
//! Gaussian read noise, the gain, rounding to whole DN, the ADC's range, and (if asked) a
//! relative drift per frame. Its sample mean and covariance check [`SensorModel::signal`].
//!
//! Poisson deviates: inversion below a mean of 10, Hormann's transformed rejection (PTRS,
//! "The transformed rejection method for generating Poisson random variables", Insurance:
//! Mathematics and Economics 12, 1993) above.

use crate::error::ModelError;
use crate::sensor::{Exposure, SensorModel};
use crate::stats::SplitMix64;
use nalgebra::{DMatrix, DVector, Matrix3, SymmetricEigen};
use statrs::function::gamma::ln_gamma;

/// The most frame sets one run may draw.
pub const MAX_SETS: usize = 10_000_000;

/// Sample statistics of simulated frames.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    /// Frame sets drawn.
    pub sets: usize,
    /// Sample mean per frame, DN.
    pub mean_dn: DVector<f64>,
    /// Sample covariance (n - 1), DN^2.
    pub cov_dn: DMatrix<f64>,
    /// Fraction of draws per frame at the ADC's top code or the full well.
    pub saturated_fraction: Vec<f64>,
}

/// A Poisson deviate of mean `lambda >= 0`.
fn poisson(rng: &mut SplitMix64, lambda: f64) -> f64 {
    if lambda <= 0.0 {
        return 0.0;
    }
    if lambda < 10.0 {
        // Inversion by sequential search.
        let mut k = 0.0;
        let mut p = (-lambda).exp();
        let mut cdf = p;
        let u = rng.uniform_open();
        while u > cdf && k < 1000.0 {
            k += 1.0;
            p *= lambda / k;
            cdf += p;
        }
        return k;
    }
    // PTRS (Hormann 1993).
    let slam = lambda.sqrt();
    let loglam = lambda.ln();
    let b = 0.931 + 2.53 * slam;
    let a = -0.059 + 0.02483 * b;
    let invalpha = 1.1239 + 1.1328 / (b - 3.4);
    let vr = 0.9277 - 3.6224 / (b - 2.0);
    loop {
        let u = rng.uniform_open() - 0.5;
        let v = rng.uniform_open();
        let us = 0.5 - u.abs();
        let k = ((2.0 * a / us + b) * u + lambda + 0.43).floor();
        if us >= 0.07 && v <= vr {
            return k;
        }
        if k < 0.0 || (us < 0.013 && v > us) {
            continue;
        }
        if v.ln() + invalpha.ln() - (a / (us * us) + b).ln()
            <= -lambda + k * loglam - ln_gamma(k + 1.0)
        {
            return k;
        }
    }
}

/// Simulates `sets` sets of frames at `angles_rad` and returns their sample statistics. The
/// sensor noise factor must be 1 (a physical chain has no knob for it): anything else is an
/// error naming `noise_factor`.
pub fn simulate_frames(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    sets: usize,
    seed: u64,
) -> Result<FrameStats, ModelError> {
    if !(2..=MAX_SETS).contains(&sets) {
        return Err(ModelError::OutOfRange {
            field: "monte_carlo",
            value: sets as f64,
            allowed: "2 to 10 000 000",
        });
    }
    // Validates everything (and gives the analytic reference's shape).
    let reference = model.signal(angles_rad, exposure)?;
    if (reference.noise_variance_factor - 1.0).abs() > 1e-12 {
        return Err(ModelError::OutOfRange {
            field: "noise_factor",
            value: reference.noise_variance_factor,
            allowed: "1 in a Monte Carlo of the physical chain",
        });
    }
    let cam = model.camera();
    let w = &reference.intensities_from_stokes;
    let n = angles_rad.len();
    let g = reference.electrons_from_radiance;
    let dark = reference.dark_electrons;
    let k = cam.gain_dn_per_e;
    let top = cam.adc_max_dn();
    // Clutter factor: Sigma = Q diag(l) Q^T, draws Q sqrt(max(l, 0)) z.
    let sigma: Matrix3<f64> = exposure.radiance_cov_w2_m4_sr2;
    let eig = SymmetricEigen::new(0.5 * (sigma + sigma.transpose()));
    let factor =
        eig.eigenvectors * Matrix3::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt()));
    let l_mean = exposure.radiance_mean_w_m2_sr.0;
    let mut rng = SplitMix64(seed ^ 0x6d6f_6e74_6563_6172);
    let mut sum = DVector::<f64>::zeros(n);
    let mut sum_sq = DMatrix::<f64>::zeros(n, n);
    let mut saturated = vec![0usize; n];
    let mut y = DVector::<f64>::zeros(n);
    for _ in 0..sets {
        let (z0, z1) = rng.normal_pair();
        let (z2, _) = rng.normal_pair();
        let l = l_mean + factor * nalgebra::Vector3::new(z0, z1, z2);
        let intensity = w * l;
        for i in 0..n {
            let signal = poisson(&mut rng, (g * intensity[i]).max(0.0));
            let electrons = (signal + poisson(&mut rng, dark)).min(cam.full_well_e);
            let (read, drift) = rng.normal_pair();
            let analog = k * (electrons + cam.read_noise_e * read) + cam.offset_dn;
            let analog = analog * (1.0 + exposure.eps_cal * drift);
            let dn = analog.round().clamp(0.0, top);
            if dn >= top || electrons >= cam.full_well_e {
                saturated[i] += 1;
            }
            y[i] = dn;
        }
        sum += &y;
        sum_sq += &y * y.transpose();
    }
    let m = sets as f64;
    let mean_dn = &sum / m;
    let cov_dn = (sum_sq - &mean_dn * mean_dn.transpose() * m) / (m - 1.0);
    Ok(FrameStats {
        sets,
        mean_dn,
        cov_dn,
        saturated_fraction: saturated.iter().map(|&s| s as f64 / m).collect(),
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::atmosphere::Band;
    use crate::polarization::Stokes;
    use crate::sensor::Camera;

    fn cmos() -> SensorModel {
        let cam = Camera::from_toml_str(include_str!("../../../examples/cameras/cmos_modern.toml"))
            .unwrap();
        SensorModel::new(&cam, &Band::flat(500.0, 600.0).unwrap()).unwrap()
    }

    /// Poisson deviates: the mean and variance of 2e5 draws equal lambda within 5 standard
    /// errors (of the mean, sqrt(lambda / n); of the sample variance, sqrt((mu4 - sigma^4) / n)
    /// = sqrt((lambda + 2 lambda^2) / n)) for lambda = 0.5, 7 (inversion), 30 and 5000 (PTRS).
    #[test]
    fn poisson_moments() {
        let mut rng = SplitMix64(5);
        let n = 200_000;
        for lambda in [0.5, 7.0, 30.0, 5000.0] {
            let xs: Vec<f64> = (0..n).map(|_| poisson(&mut rng, lambda)).collect();
            let mean = xs.iter().sum::<f64>() / n as f64;
            let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            assert!(
                (mean - lambda).abs() < 5.0 * (lambda / n as f64).sqrt(),
                "{lambda}: {mean}"
            );
            let se_var = ((lambda + 2.0 * lambda * lambda) / n as f64).sqrt();
            assert!((var - lambda).abs() < 5.0 * se_var, "{lambda}: {var}");
        }
    }

    /// The chain against the analytic model on the shipped CMOS (about 4000 e- per frame, read
    /// noise 2.5 e-, K = 0.35): over 1e5 frame sets, each frame's mean is within 5 standard
    /// errors of the analytic mean, and each variance within 3 % (its standard error is
    /// sqrt(2/n) = 0.45 %); with clutter the off-diagonal covariances agree within 5 % of the
    /// diagonal scale.
    #[test]
    fn chain_matches_the_analytic_model() {
        let model = cmos();
        let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let mut exposure = Exposure::new(5e-3, Stokes::new(1.0, 0.2, 0.1));
        for clutter in [0.0, 1e-3] {
            exposure.radiance_cov_w2_m4_sr2 =
                Matrix3::new(1.0, 0.2, 0.0, 0.2, 0.5, 0.0, 0.0, 0.0, 0.5) * clutter;
            let a = model.signal(&angles, &exposure).unwrap();
            let mc = simulate_frames(&model, &angles, &exposure, 100_000, 9).unwrap();
            for i in 0..4 {
                let var = a.cov_dn[(i, i)];
                let se = (var / mc.sets as f64).sqrt();
                assert!(
                    (mc.mean_dn[i] - a.mean_dn[i]).abs() < 5.0 * se,
                    "{clutter} {i}: {} {}",
                    mc.mean_dn[i],
                    a.mean_dn[i]
                );
                assert!(
                    (mc.cov_dn[(i, i)] / var - 1.0).abs() < 0.03,
                    "{clutter} {i}: {} {var}",
                    mc.cov_dn[(i, i)]
                );
                for j in 0..i {
                    let scale = (var * a.cov_dn[(j, j)]).sqrt();
                    assert!(
                        (mc.cov_dn[(i, j)] - a.cov_dn[(i, j)]).abs() < 0.05 * scale,
                        "{clutter} {i} {j}"
                    );
                }
            }
        }
    }

    /// A scene far past the full well saturates every draw (the analytic model flags it), and a
    /// noise factor other than 1 or a bad sample count is an error naming its field.
    #[test]
    fn saturation_and_errors() {
        let model = cmos();
        let angles = [0.0, 1.0, 2.0];
        let exposure = Exposure::new(1.0, Stokes::new(100.0, 0.0, 0.0));
        let mc = simulate_frames(&model, &angles, &exposure, 100, 1).unwrap();
        assert!(mc.saturated_fraction.iter().all(|&f| f == 1.0));
        assert!(model
            .signal(&angles, &exposure)
            .unwrap()
            .saturated
            .iter()
            .all(|&s| s));
        let mut e = Exposure::new(1e-3, Stokes::new(1.0, 0.0, 0.0));
        e.noise_factor = crate::sensor::NoiseFactor::Variance(2.0);
        assert!(simulate_frames(&model, &angles, &e, 100, 1)
            .unwrap_err()
            .to_string()
            .contains("noise_factor"));
        let e = Exposure::new(1e-3, Stokes::new(1.0, 0.0, 0.0));
        assert!(simulate_frames(&model, &angles, &e, 1, 1)
            .unwrap_err()
            .to_string()
            .contains("monte_carlo"));
    }
}
