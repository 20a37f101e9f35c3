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
use crate::sensor::{Exposure, SensorModel, SensorSignal};
use crate::stats::SplitMix64;
use nalgebra::{DMatrix, DVector, Matrix3, SymmetricEigen, Vector3};
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
pub(crate) fn poisson(rng: &mut SplitMix64, lambda: f64) -> f64 {
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

/// One exposure's sensor chain, validated and ready to draw frame sets: the per-set draw shared
/// by [`simulate_frames`] and [`crate::validation`], so that both simulate the same camera.
#[derive(Debug, Clone)]
pub(crate) struct FrameChain {
    /// The measurement matrix `W` (`N x 3`).
    w: DMatrix<f64>,
    /// `G`, electrons per W m^-2 sr^-1 in one frame.
    electrons_from_radiance: f64,
    /// Mean dark electrons per frame.
    dark_electrons: f64,
    /// `K`, DN per electron.
    gain_dn_per_e: f64,
    /// `sigma_d`, electrons.
    read_noise_e: f64,
    /// `b`, DN.
    offset_dn: f64,
    /// Full well, electrons.
    full_well_e: f64,
    /// The ADC's top code, DN.
    adc_max_dn: f64,
    /// Relative drift per frame.
    eps_cal: f64,
    /// `Q sqrt(max(lambda, 0))` of the clutter covariance `Sigma_LS = Q diag(lambda) Q^T`.
    clutter_factor: Matrix3<f64>,
    /// `L_mean`, W m^-2 sr^-1.
    l_mean: Vector3<f64>,
}

impl FrameChain {
    /// The chain of `model` at `angles_rad` and `exposure`, with the analytic frame statistics
    /// ([`SensorModel::signal`], which validates every input). The sensor noise factor must be 1
    /// (a physical chain has no knob for it): anything else is an error naming `noise_factor`.
    pub(crate) fn new(
        model: &SensorModel,
        angles_rad: &[f64],
        exposure: &Exposure,
    ) -> Result<(FrameChain, SensorSignal), ModelError> {
        let reference = model.signal(angles_rad, exposure)?;
        if (reference.noise_variance_factor - 1.0).abs() > 1e-12 {
            return Err(ModelError::OutOfRange {
                field: "noise_factor",
                value: reference.noise_variance_factor,
                allowed: "1 in a Monte Carlo of the physical chain",
            });
        }
        let cam = model.camera();
        // Clutter factor: Sigma = Q diag(l) Q^T, draws Q sqrt(max(l, 0)) z.
        let sigma: Matrix3<f64> = exposure.radiance_cov_w2_m4_sr2;
        let eig = SymmetricEigen::new(0.5 * (sigma + sigma.transpose()));
        let clutter_factor =
            eig.eigenvectors * Matrix3::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt()));
        let chain = FrameChain {
            w: reference.intensities_from_stokes.clone(),
            electrons_from_radiance: reference.electrons_from_radiance,
            dark_electrons: reference.dark_electrons,
            gain_dn_per_e: cam.gain_dn_per_e,
            read_noise_e: cam.read_noise_e,
            offset_dn: cam.offset_dn,
            full_well_e: cam.full_well_e,
            adc_max_dn: cam.adc_max_dn(),
            eps_cal: exposure.eps_cal,
            clutter_factor,
            l_mean: exposure.radiance_mean_w_m2_sr.0,
        };
        Ok((chain, reference))
    }

    /// Frames per set, `N`.
    pub(crate) fn frames(&self) -> usize {
        self.w.nrows()
    }

    /// Draws one set of `N` frames into `y` (DN; `y.len()` must be `N`, extra entries are left
    /// alone) and calls `on_saturated(i)` for each frame `i` at the ADC's top code or the full
    /// well: the radiance from its mean and clutter covariance, then per frame Poisson
    /// photo-electrons and dark electrons, the full well, Gaussian read noise, the gain and
    /// offset, the drift, rounding and the ADC's range.
    pub(crate) fn draw(
        &self,
        rng: &mut SplitMix64,
        y: &mut [f64],
        mut on_saturated: impl FnMut(usize),
    ) {
        let (z0, z1) = rng.normal_pair();
        let (z2, _) = rng.normal_pair();
        let l = self.l_mean + self.clutter_factor * Vector3::new(z0, z1, z2);
        let (g, k, top) = (
            self.electrons_from_radiance,
            self.gain_dn_per_e,
            self.adc_max_dn,
        );
        for (i, dn_out) in y.iter_mut().enumerate().take(self.w.nrows()) {
            let intensity = self.w[(i, 0)] * l[0] + self.w[(i, 1)] * l[1] + self.w[(i, 2)] * l[2];
            let signal = poisson(rng, (g * intensity).max(0.0));
            let electrons = (signal + poisson(rng, self.dark_electrons)).min(self.full_well_e);
            let (read, drift) = rng.normal_pair();
            let analog = k * (electrons + self.read_noise_e * read) + self.offset_dn;
            let analog = analog * (1.0 + self.eps_cal * drift);
            let dn = analog.round().clamp(0.0, top);
            if dn >= top || electrons >= self.full_well_e {
                on_saturated(i);
            }
            *dn_out = dn;
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
    let (chain, _reference) = FrameChain::new(model, angles_rad, exposure)?;
    let n = chain.frames();
    let mut rng = SplitMix64(seed ^ 0x6d6f_6e74_6563_6172);
    let mut sum = DVector::<f64>::zeros(n);
    let mut sum_sq = DMatrix::<f64>::zeros(n, n);
    let mut saturated = vec![0usize; n];
    let mut y = DVector::<f64>::zeros(n);
    for _ in 0..sets {
        chain.draw(&mut rng, y.as_mut_slice(), |i| saturated[i] += 1);
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

/// Largest mean photo-electron count per pixel accepted by [`expose_pixels`] (far past any full
/// well: the camera file allows at most 1e9 e-).
pub const MAX_MEAN_PHOTOELECTRONS: f64 = 1e12;

/// Most pixels in one frame accepted by [`expose_pixels`] and [`fixed_pattern`] (2^28, a
/// 16384 x 16384 sensor).
pub const MAX_FRAME_PIXELS: usize = 1 << 28;

/// Salt mixed into the seed of [`expose_pixels`], so a frame never repeats the draws of
/// [`simulate_frames`] or [`fixed_pattern`] with the same seed.
const EXPOSE_SALT: u64 = 0x6578_706f_7365_7078;
/// Salt mixed into the seed of [`fixed_pattern`].
const PATTERN_SALT: u64 = 0x7061_7474_6572_6e73;

fn check_frame_len(field: &'static str, pixels: usize) -> Result<(), ModelError> {
    if pixels == 0 || pixels > MAX_FRAME_PIXELS {
        return Err(ModelError::Invalid {
            field,
            reason: format!("{pixels} pixels; allowed 1 to {MAX_FRAME_PIXELS}"),
        });
    }
    Ok(())
}

/// One frame of a camera, pixel by pixel, as the sensor chain of [`simulate_frames`] draws it
/// (EMVA 1288 Release 4.0 Linear, Sec. 2: the linear signal and noise model) for a simulated
/// camera: for pixel `i` with mean photo-electrons `mu_i`,
///
/// `y_i = clamp(round(K (min(P(mu_i) + P(mu_I t_int), full_well) + sigma_d z_i) + b), 0, 2^bits - 1)`
///
/// with `P` a Poisson deviate, `z_i` a standard normal, `K`, `sigma_d`, `mu_I`, `b`, the full
/// well and the bit depth from `camera`. Photo-electrons are the caller's: the mean photon
/// count times the QE, times a PRNU pattern if wanted; a DSNU pattern is added by the caller.
/// Pixels are independent; the same `seed` gives the same frame (SplitMix64, see
/// [`crate::stats`]), and different seeds independent frames. The two Poisson terms are drawn
/// as one, `P(mu_i + mu_I t_int)`: the sum of independent Poisson variables is Poisson with the
/// summed mean, so the distribution is exactly the formula's, at one draw per pixel instead of
/// two (half the time of a simulated camera's frame).
///
/// Errors name the field: the camera's (see [`crate::sensor::Camera::validate`]), `t_int_s` outside
/// `[0, 1e5]` s, `mean_photoelectrons` empty, longer than [`MAX_FRAME_PIXELS`], or with an
/// entry not finite or outside `[0, MAX_MEAN_PHOTOELECTRONS]` (the message gives its index).
pub fn expose_pixels(
    camera: &crate::sensor::Camera,
    mean_photoelectrons: &[f64],
    t_int_s: f64,
    seed: u64,
) -> Result<Vec<u16>, ModelError> {
    camera.validate()?;
    ModelError::check_range(
        "t_int_s",
        t_int_s,
        0.0,
        crate::sensor::MAX_T_INT_S,
        "[0, 1e5] s",
    )?;
    check_frame_len("mean_photoelectrons", mean_photoelectrons.len())?;
    if let Some((i, m)) = mean_photoelectrons
        .iter()
        .enumerate()
        .find(|(_, m)| !(m.is_finite() && (0.0..=MAX_MEAN_PHOTOELECTRONS).contains(*m)))
    {
        return Err(ModelError::Invalid {
            field: "mean_photoelectrons",
            reason: format!("pixel {i}: {m}; allowed finite, in [0, 1e12] e-"),
        });
    }
    let dark_e = camera.dark_current_e_per_s * t_int_s;
    let k = camera.gain_dn_per_e;
    let top = camera.adc_max_dn();
    let mut rng = SplitMix64(seed ^ EXPOSE_SALT);
    let mut spare: Option<f64> = None;
    let mut frame = Vec::with_capacity(mean_photoelectrons.len());
    for &mu in mean_photoelectrons {
        let electrons = poisson(&mut rng, mu + dark_e).min(camera.full_well_e);
        let z = match spare.take() {
            Some(z) => z,
            None => {
                let (a, b) = rng.normal_pair();
                spare = Some(b);
                a
            }
        };
        let dn = (k * (electrons + camera.read_noise_e * z) + camera.offset_dn)
            .round()
            .clamp(0.0, top);
        // In [0, 2^bit_depth - 1] with bit_depth <= 16: exact in u16.
        frame.push(dn as u16);
    }
    Ok(frame)
}

/// A fixed (frame-to-frame constant) pattern of `pixels` values for simulating PRNU (relative
/// gain) or DSNU (offset): Gaussian with standard deviation `rms`, and **exactly zero mean**:
/// value `n - 1 - i` is minus value `i` (the middle one is 0 when `n` is odd), so the pattern
/// changes no frame's mean (in an image, pixel `(r, c)` mirrors `(h - 1 - r, w - 1 - c)`). The
/// same `seed` gives the same pattern.
///
/// Errors: `pixels` 0 or above [`MAX_FRAME_PIXELS`], `rms` not finite or outside `[0, 1e6]`.
pub fn fixed_pattern(pixels: usize, rms: f64, seed: u64) -> Result<Vec<f64>, ModelError> {
    check_frame_len("pixels", pixels)?;
    ModelError::check_range("rms", rms, 0.0, 1e6, "[0, 1e6]")?;
    let mut rng = SplitMix64(seed ^ PATTERN_SALT);
    let mut pattern = vec![0.0; pixels];
    let half = pixels / 2;
    let mut i = 0;
    while i < half {
        let (a, b) = rng.normal_pair();
        for z in [a, b] {
            if i < half {
                pattern[i] = rms * z;
                pattern[pixels - 1 - i] = -rms * z;
                i += 1;
            }
        }
    }
    Ok(pattern)
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
