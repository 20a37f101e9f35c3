//! Whole-chain validation of the analytic statistics (MODEL.md section 7, "Monte Carlo
//! validation", Meng (2012)'s Sec. 3.3.2 *reconstructed*): a seeded, parallel Monte Carlo of the
//! processed products (Stokes estimate, DoLP, AoP) drawn frame by frame through the sensor chain
//! of [`crate::montecarlo`], the analytic counterpart in one call, and their comparison.
//!
//! # The Monte Carlo
//!
//! Each *set* is `N` frames drawn by the chain of [`crate::montecarlo::simulate_frames`] (scene
//! radiance from its mean and clutter covariance, Poisson photo-electrons and dark electrons,
//! full well, Gaussian read noise, gain and offset, drift, rounding, the ADC's range). Each set
//! is processed as a real pipeline would (MODEL.md section 7): dark-subtracted and scaled,
//! `I_hat = (y - K mu_I t_int - b) / (K G)`, then `S_hat = G_est I_hat` with the estimator
//! `G_est` (OLS or GLS) built from the *analytic* intensity covariance, the same estimator the
//! analytic path propagates. Per set: `DoLP = |(S1, S2)| / S0` (sets with `S0_hat <= 0` have no
//! DoLP and are counted apart, as in [`crate::stats::monte_carlo_dolp_aop`]) and
//! `AoP = 0.5 atan2(S2, S1)`.
//!
//! Sample statistics are streamed, so memory does not grow with the number of sets:
//!
//! * DoLP: power sums of `d = DoLP - c` up to the fourth, `c` the DoLP of the mean Stokes vector
//!   (the "shifted data" algorithm: T. F. Chan, G. H. Golub and R. J. LeVeque, "Algorithms for
//!   computing the sample variance", *The American Statistician* 37(3), 242-247, 1983). Mean,
//!   standard deviation (`n - 1`), and their Monte Carlo standard errors: `s / sqrt(n)` for the
//!   mean and, by the delta method on `Var(s^2) = (mu_4 - sigma^4) / n`,
//!   `sqrt((m_4 - m_2^2) / n) / (2 s)` for the standard deviation (`s / sqrt(2n)` for a normal
//!   variable).
//! * AoP: deviations from the AoP of the mean Stokes vector, each wrapped into `(-pi/2, pi/2]`,
//!   and their root-mean-square: exactly the quantity [`PolarizationStats::aop_std_rad`] is
//!   defined as (its standard deviation about `aop_mean_rad`, the AoP of the mean Stokes vector).
//!   [`crate::stats::monte_carlo_dolp_aop`] centres on the sample's circular mean instead, which
//!   needs a second pass over stored draws; for an unbiased AoP the two centres differ by about
//!   one standard error and the RMS by its square. The circular mean direction and circular
//!   standard deviation `sqrt(-2 ln R) / 2` of `2 AoP` (K. V. Mardia and P. E. Jupp, *Directional
//!   Statistics*, Wiley 2000, Sec. 2.3.4) are reported too. The RMS's standard error is
//!   `sqrt((E d^4 - (E d^2)^2) / n) / (2 rms)` (delta method).
//! * Stokes: sample mean and covariance of `S_hat`, which check the linear part of the chain
//!   (exact in the analytic model up to saturation).
//!
//! [`McSource::GaussianStokes`] draws the Stokes estimates from `N(mean, Sigma_S)` of the
//! analytic path instead and summarises them the same way: the gap between the analytic values
//! and that Monte Carlo is the error of the DoLP/AoP formulas alone, the gap between it and the
//! chain's is the chain's departure from Gaussian Stokes noise (Poisson counts, rounding).
//!
//! # Seeds and threads
//!
//! The sets are split into chunks of [`CHUNK_SETS`]; chunk `j` draws from its own SplitMix64
//! stream seeded by hashing `(seed, j)` (the "split" of G. L. Steele, D. Lea and C. H. Flood,
//! "Fast splittable pseudorandom number generators", OOPSLA 2014). Chunks run on
//! `std::thread::scope` workers (as many as `std::thread::available_parallelism`, or as asked)
//! and their sums are added in chunk order, so the answer is bit-for-bit the same for any number
//! of threads.

use crate::error::ModelError;
use crate::montecarlo::FrameChain;
use crate::sensor::{Exposure, SensorModel, SensorSignal};
use crate::stats::{
    dolp_aop_stats, Method, MethodChoice, PolarizationStats, Regime, RegimeChoice, SplitMix64,
    StokesEstimator,
};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Frame sets per chunk: the unit of seeding and of parallel work.
pub const CHUNK_SETS: usize = 1024;

/// The most frame sets one [`simulate_products`] run may draw.
pub const MAX_PRODUCT_SETS: usize = 100_000_000;

/// The most frame sets [`sample_products`] returns (it keeps every set).
pub const MAX_SAMPLE_SETS: usize = 2_000_000;

/// The most worker threads one run may use.
pub const MAX_THREADS: usize = 256;

/// Options of the whole-chain Monte Carlo.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct McConfig {
    /// Frame sets to draw, `2 ..= MAX_PRODUCT_SETS`.
    pub sets: usize,
    /// Seed of the run; chunk `j` draws from a stream seeded by `(seed, j)`.
    pub seed: u64,
    /// Worker threads: 0 for `std::thread::available_parallelism`, else `1 ..= MAX_THREADS`.
    /// The answer does not depend on it.
    pub threads: usize,
    /// The Stokes estimator (built from the analytic intensity covariance, as in
    /// [`analytic_products`]).
    pub method: MethodChoice,
    /// What is drawn: the whole chain, or Gaussian Stokes estimates.
    pub source: McSource,
}

/// What a Monte Carlo draws.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum McSource {
    /// Frame sets through the whole sensor chain, processed into Stokes estimates.
    #[default]
    Chain,
    /// Stokes estimates drawn from `N(mean, Sigma_S)` of the analytic path (the model's own
    /// Gaussian assumption, as [`crate::stats::monte_carlo_dolp_aop`]), summarised with the
    /// same statistics as the chain: it separates the error of the DoLP/AoP formulas from the
    /// chain's departure from Gaussian Stokes noise.
    GaussianStokes,
}

impl McConfig {
    /// `sets` sets with `seed`, all available threads, the automatic estimator (OLS for
    /// isotropic intensity noise, GLS otherwise).
    pub fn new(sets: usize, seed: u64) -> Self {
        McConfig {
            sets,
            seed,
            threads: 0,
            method: MethodChoice::Auto,
            source: McSource::Chain,
        }
    }
}

/// The analytic statistics of the processed products, from [`analytic_products`].
#[derive(Debug, Clone, PartialEq)]
pub struct AnalyticProducts {
    /// The frames' statistics in DN ([`SensorModel::signal`]).
    pub signal: SensorSignal,
    /// `K G`, DN per W m^-2 sr^-1 of transmitted intensity.
    pub dn_per_radiance: f64,
    /// `K mu_I t_int + b`, the DN subtracted before scaling.
    pub dark_dn: f64,
    /// Mean of the dark-subtracted, scaled intensities `I_hat`, W m^-2 sr^-1 (N).
    pub intensity_mean_w_m2_sr: DVector<f64>,
    /// Their covariance `Sigma_y / (K G)^2`, (W m^-2 sr^-1)^2 (N x N).
    pub intensity_cov_w2_m4_sr2: DMatrix<f64>,
    /// The Stokes estimator (gain, `Sigma_S`, method).
    pub estimator: StokesEstimator,
    /// Mean of the Stokes estimate, W m^-2 sr^-1: `L_mean` (exact, since `G_est W = I`), or
    /// `G_est E[I_hat]` when the sensor model clamped a negative transmitted intensity.
    pub stokes_mean_w_m2_sr: Vector3<f64>,
    /// DoLP and AoP statistics ([`dolp_aop_stats`] of the Stokes mean and covariance).
    pub stats: PolarizationStats,
    /// Warnings of every stage (sensor, estimator, statistics).
    pub warnings: Vec<String>,
}

/// Sample statistics of the processed products of a whole-chain Monte Carlo, with their Monte
/// Carlo standard errors.
#[derive(Debug, Clone, PartialEq)]
pub struct McProducts {
    /// Frame sets drawn.
    pub sets: usize,
    /// The run's seed.
    pub seed: u64,
    /// Chunks of [`CHUNK_SETS`] the sets were split into.
    pub chunks: usize,
    /// Worker threads used (does not change the answer).
    pub threads: usize,
    /// The Stokes estimator used.
    pub method: Method,
    /// Sample mean of the Stokes estimate, W m^-2 sr^-1.
    pub stokes_mean_w_m2_sr: Vector3<f64>,
    /// Sample covariance (`n - 1`) of the Stokes estimate, (W m^-2 sr^-1)^2.
    pub stokes_cov_w2_m4_sr2: Matrix3<f64>,
    /// Sample mean of the DoLP over the sets with `S0_hat > 0`.
    pub dolp_mean: f64,
    /// Its standard error `s / sqrt(n)`.
    pub dolp_mean_se: f64,
    /// Sample standard deviation (`n - 1`) of the DoLP.
    pub dolp_std: f64,
    /// Its standard error `sqrt((m4 - m2^2) / n) / (2 s)` (delta method).
    pub dolp_std_se: f64,
    /// The AoP the deviations are taken from: that of the analytic mean Stokes vector (0 when
    /// it has no linear polarisation), radians.
    pub aop_center_rad: f64,
    /// Root-mean-square of the AoP's deviations from `aop_center_rad`, each wrapped into
    /// `(-pi/2, pi/2]`, radians (comparable with [`PolarizationStats::aop_std_rad`]).
    pub aop_std_rad: f64,
    /// Its standard error (delta method), radians.
    pub aop_std_se_rad: f64,
    /// Circular mean direction of `2 AoP`, halved, in `(-pi/2, pi/2]`, radians.
    pub aop_circular_mean_rad: f64,
    /// Circular standard deviation `sqrt(-2 ln R) / 2` of the AoP, radians (`R` floored at
    /// 1e-300).
    pub aop_circular_std_rad: f64,
    /// Sets with a DoLP (`S0_hat > 0`).
    pub samples_used: usize,
    /// Sets with `S0_hat <= 0`, left out of the DoLP.
    pub samples_dark: usize,
    /// Sets with `S1_hat = S2_hat = 0` (no AoP), left out of the AoP.
    pub samples_no_aop: usize,
    /// Fraction of all frames at the ADC's top code or the full well.
    pub saturated_fraction: f64,
}

/// One processed frame set of [`sample_products`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProductSample {
    /// The Stokes estimate, W m^-2 sr^-1.
    pub stokes_w_m2_sr: Vector3<f64>,
    /// Its DoLP, `None` when `S0_hat <= 0`.
    pub dolp: Option<f64>,
    /// Its AoP in `(-pi/2, pi/2]`, radians; `None` when `S1_hat = S2_hat = 0`.
    pub aop_rad: Option<f64>,
    /// Frames of the set at the ADC's top code or the full well.
    pub saturated_frames: usize,
}

/// One statistic, analytic against Monte Carlo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Agreement {
    /// The analytic value.
    pub analytic: f64,
    /// The Monte Carlo value.
    pub monte_carlo: f64,
    /// The Monte Carlo standard error.
    pub se: f64,
    /// `(analytic - monte_carlo) / |monte_carlo|` (the denominator floored at 1e-300).
    pub rel_error: f64,
    /// `(analytic - monte_carlo) / se`, the difference in standard errors (0 when both are 0,
    /// `f64::MAX` with the sign of the difference when `se = 0` and they differ).
    pub z: f64,
}

impl Agreement {
    /// The agreement of `analytic` with `monte_carlo` of standard error `se`.
    pub fn new(analytic: f64, monte_carlo: f64, se: f64) -> Self {
        let diff = analytic - monte_carlo;
        let z = if se > 0.0 {
            diff / se
        } else if diff == 0.0 {
            0.0
        } else {
            f64::MAX.copysign(diff)
        };
        Agreement {
            analytic,
            monte_carlo,
            se,
            rel_error: diff / monte_carlo.abs().max(1e-300),
            z,
        }
    }
}

/// The analytic DoLP and AoP statistics against the Monte Carlo's.
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    /// The regime the analytic answer came from.
    pub regime: Regime,
    /// Polarised SNR `p / sigma_p` of the analytic Stokes statistics.
    pub polarised_snr: f64,
    /// DoLP mean.
    pub dolp_mean: Agreement,
    /// DoLP standard deviation.
    pub dolp_std: Agreement,
    /// AoP standard deviation (radians).
    pub aop_std: Agreement,
    /// Largest `|C_analytic - C_mc|_ij / sqrt(C_ii C_jj)` over the Stokes covariance (analytic
    /// diagonal): the linear part of the chain; its Monte Carlo noise is about `sqrt(2 / n)`.
    pub stokes_cov_error: f64,
}

/// Analytic against Monte Carlo at one point: both answers and their comparison.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidationPoint {
    /// The analytic path.
    pub analytic: AnalyticProducts,
    /// The Monte Carlo.
    pub monte_carlo: McProducts,
    /// The comparison.
    pub comparison: Comparison,
}

/// The analytic statistics of the processed products in one call (MODEL.md sections 6 and 7):
/// [`SensorModel::signal`] gives the frames' mean and covariance in DN; dark subtraction and
/// scaling by `1 / (K G)` give the intensities' `E[I_hat] = W L_mean` and
/// `Sigma_I = Sigma_y / (K G)^2`; [`StokesEstimator::new`] gives the estimator (OLS or GLS per
/// `method`) and `Sigma_S`; [`dolp_aop_stats`] the DoLP and AoP statistics in the `regime`.
///
/// Errors: those of [`SensorModel::signal`] (`angles_deg`, `t_int_s`, `radiance_mean_w_m2_sr`,
/// `radiance_cov_w2_m4_sr2`, `eps_cal`, `noise_factor`); `band` when the camera has no
/// responsivity in the band (`K G = 0`); those of [`StokesEstimator::new`] (fewer than 3
/// distinct angles name `angles_deg`) and of [`dolp_aop_stats`] (`S0` when the mean Stokes
/// vector is dark).
pub fn analytic_products(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    method: MethodChoice,
    regime: RegimeChoice,
) -> Result<AnalyticProducts, ModelError> {
    let signal = model.signal(angles_rad, exposure)?;
    analytic_from_signal(model, exposure, signal, method, regime)
}

/// The rest of [`analytic_products`] once the frames' statistics are known.
fn analytic_from_signal(
    model: &SensorModel,
    exposure: &Exposure,
    signal: SensorSignal,
    method: MethodChoice,
    regime: RegimeChoice,
) -> Result<AnalyticProducts, ModelError> {
    let n = signal.intensities_from_stokes.nrows();
    if n < 3 {
        return Err(ModelError::Invalid {
            field: "angles_deg",
            reason: format!(
                "{n} angles; allowed at least 3, distinct modulo 180 deg, for a linear Stokes \
                 estimate"
            ),
        });
    }
    let cam = model.camera();
    let dn_per_radiance = cam.gain_dn_per_e * signal.electrons_from_radiance;
    if !(dn_per_radiance.is_finite() && dn_per_radiance > 0.0) {
        return Err(ModelError::OutOfRange {
            field: "band",
            value: dn_per_radiance,
            allowed: "a band where the camera responds (K G > 0 DN per W m^-2 sr^-1)",
        });
    }
    let dark_dn = cam.gain_dn_per_e * signal.dark_electrons + cam.offset_dn;
    let intensity_mean_w_m2_sr = signal.mean_dn.map(|y| (y - dark_dn) / dn_per_radiance);
    let intensity_cov_w2_m4_sr2 = &signal.cov_dn / (dn_per_radiance * dn_per_radiance);
    let estimator = StokesEstimator::new(
        &signal.intensities_from_stokes,
        &intensity_cov_w2_m4_sr2,
        method,
    )?;
    // G_est W = I for any unbiased linear estimator, so E[S_hat] = L_mean exactly unless the
    // sensor clamped a negative transmitted intensity; taken as such rather than as
    // G_est E[I_hat], whose rounding would give an unpolarised scene a DoLP of 1e-17.
    let l_mean = exposure.radiance_mean_w_m2_sr.0;
    let unclamped = (&signal.intensities_from_stokes * l_mean)
        .iter()
        .all(|v| *v >= 0.0);
    let stokes_mean_w_m2_sr = if unclamped {
        l_mean
    } else {
        let g = &estimator.stokes_from_intensities;
        Vector3::from_fn(|r, _| {
            (0..g.ncols())
                .map(|i| g[(r, i)] * intensity_mean_w_m2_sr[i])
                .sum()
        })
    };
    let stats = dolp_aop_stats(&stokes_mean_w_m2_sr, &estimator.cov, regime)?;
    let mut warnings = signal.warnings.clone();
    warnings.extend(estimator.warnings.iter().cloned());
    warnings.extend(stats.warnings.iter().cloned());
    Ok(AnalyticProducts {
        signal,
        dn_per_radiance,
        dark_dn,
        intensity_mean_w_m2_sr,
        intensity_cov_w2_m4_sr2,
        estimator,
        stokes_mean_w_m2_sr,
        stats,
        warnings,
    })
}

/// Wraps an angle into `(-pi/2, pi/2]`.
fn wrap_half_pi(a: f64) -> f64 {
    let r = a - PI * (a / PI).round();
    if r <= -FRAC_PI_2 {
        r + PI
    } else {
        r
    }
}

/// The seed of chunk `chunk` of a run seeded `seed`: two SplitMix64 finalisations, so that
/// neighbouring chunks start far apart on the generator's cycle (seeding chunk `j` with
/// `seed + j` would make the streams shifted copies of each other).
fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    let base = SplitMix64(seed).next_u64();
    SplitMix64(base ^ (chunk as u64).wrapping_mul(0xD1B5_4A32_D192_ED03)).next_u64()
}

/// The chain and the processing of one run, shared by the workers.
struct Pipeline {
    chain: FrameChain,
    /// `F` with `F F^T = Sigma_S`, for [`McSource::GaussianStokes`].
    stokes_factor: Matrix3<f64>,
    /// `G_est / (K G)`, per frame the column `[g0, g1, g2]`.
    stokes_from_dn: Vec<[f64; 3]>,
    dark_dn: f64,
    method: Method,
    stokes_center: Vector3<f64>,
    dolp_center: f64,
    aop_center_rad: f64,
}

impl Pipeline {
    fn new(chain: FrameChain, analytic: &AnalyticProducts) -> Pipeline {
        let g = &analytic.estimator.stokes_from_intensities;
        let k = analytic.dn_per_radiance;
        let stokes_from_dn = (0..g.ncols())
            .map(|i| [g[(0, i)] / k, g[(1, i)] / k, g[(2, i)] / k])
            .collect();
        let s = analytic.stokes_mean_w_m2_sr;
        let cov = analytic.estimator.cov;
        let stokes_factor = crate::stats::psd_factor(&cov);
        Pipeline {
            chain,
            stokes_factor,
            stokes_from_dn,
            dark_dn: analytic.dark_dn,
            method: analytic.estimator.method,
            stokes_center: s,
            dolp_center: s[1].hypot(s[2]) / s[0],
            aop_center_rad: if s[1] != 0.0 || s[2] != 0.0 {
                0.5 * s[2].atan2(s[1])
            } else {
                0.0
            },
        }
    }

    /// Draws the `len` sets of chunk `chunk` and hands each processed set to `visit`.
    fn run_chunk(
        &self,
        source: McSource,
        seed: u64,
        chunk: usize,
        len: usize,
        mut visit: impl FnMut(&Vector3<f64>, usize),
    ) {
        let mut rng = SplitMix64(chunk_seed(seed, chunk));
        if source == McSource::GaussianStokes {
            for _ in 0..len {
                let (z0, z1) = rng.normal_pair();
                let (z2, _) = rng.normal_pair();
                let s = self.stokes_center + self.stokes_factor * Vector3::new(z0, z1, z2);
                visit(&s, 0);
            }
            return;
        }
        let mut y = vec![0.0; self.stokes_from_dn.len()];
        for _ in 0..len {
            let mut saturated = 0usize;
            self.chain.draw(&mut rng, &mut y, |_| saturated += 1);
            let mut s = Vector3::zeros();
            for (col, &dn) in self.stokes_from_dn.iter().zip(&y) {
                let v = dn - self.dark_dn;
                s[0] += col[0] * v;
                s[1] += col[1] * v;
                s[2] += col[2] * v;
            }
            visit(&s, saturated);
        }
    }

    fn dolp(s: &Vector3<f64>) -> Option<f64> {
        (s[0] > 0.0).then(|| s[1].hypot(s[2]) / s[0])
    }

    fn aop(s: &Vector3<f64>) -> Option<f64> {
        (s[1] != 0.0 || s[2] != 0.0).then(|| 0.5 * s[2].atan2(s[1]))
    }

    /// The streamed sums of one chunk.
    fn chunk_sums(&self, source: McSource, seed: u64, chunk: usize, len: usize) -> Sums {
        let mut t = Sums::default();
        self.run_chunk(source, seed, chunk, len, |s, saturated| {
            t.sets += 1;
            t.saturated_frames += saturated;
            let ds = s - self.stokes_center;
            t.stokes += ds;
            t.stokes_sq += ds * ds.transpose();
            if let Some(d) = Pipeline::dolp(s) {
                let x = d - self.dolp_center;
                let x2 = x * x;
                t.dolp_n += 1;
                t.dolp[0] += x;
                t.dolp[1] += x2;
                t.dolp[2] += x2 * x;
                t.dolp[3] += x2 * x2;
            }
            if let Some(a) = Pipeline::aop(s) {
                let dev = wrap_half_pi(a - self.aop_center_rad);
                let dev2 = dev * dev;
                let (sin, cos) = (2.0 * a).sin_cos();
                t.aop_n += 1;
                t.aop[0] += dev2;
                t.aop[1] += dev2 * dev2;
                t.aop[2] += cos;
                t.aop[3] += sin;
            }
        });
        t
    }
}

/// Streamed sums of one chunk (module docs).
#[derive(Debug, Clone, Default)]
struct Sums {
    sets: usize,
    saturated_frames: usize,
    stokes: Vector3<f64>,
    stokes_sq: Matrix3<f64>,
    dolp_n: usize,
    /// Sums of `d, d^2, d^3, d^4`, `d = DoLP - c`.
    dolp: [f64; 4],
    aop_n: usize,
    /// Sums of `dev^2, dev^4, cos 2AoP, sin 2AoP`.
    aop: [f64; 4],
}

impl Sums {
    fn add(&mut self, o: &Sums) {
        self.sets += o.sets;
        self.saturated_frames += o.saturated_frames;
        self.stokes += o.stokes;
        self.stokes_sq += o.stokes_sq;
        self.dolp_n += o.dolp_n;
        self.aop_n += o.aop_n;
        for k in 0..4 {
            self.dolp[k] += o.dolp[k];
            self.aop[k] += o.aop[k];
        }
    }
}

fn check_config(cfg: &McConfig, max_sets: usize, allowed: &'static str) -> Result<(), ModelError> {
    if !(2..=max_sets).contains(&cfg.sets) {
        return Err(ModelError::OutOfRange {
            field: "sets",
            value: cfg.sets as f64,
            allowed,
        });
    }
    if cfg.threads > MAX_THREADS {
        return Err(ModelError::OutOfRange {
            field: "threads",
            value: cfg.threads as f64,
            allowed: "0 (all available) to 256",
        });
    }
    Ok(())
}

/// The chain, the analytic answer and the processing of a run.
fn prepare(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    method: MethodChoice,
    regime: RegimeChoice,
) -> Result<(Pipeline, AnalyticProducts), ModelError> {
    let (chain, signal) = FrameChain::new(model, angles_rad, exposure)?;
    let analytic = analytic_from_signal(model, exposure, signal, method, regime)?;
    Ok((Pipeline::new(chain, &analytic), analytic))
}

/// Runs every chunk of `sets` on `threads` workers and returns the per-chunk results in chunk
/// order. A worker that panics (it cannot: the chain does not panic) is an error naming
/// `threads`.
fn run_chunks<T: Send>(
    sets: usize,
    threads: usize,
    work: impl Fn(usize, usize) -> T + Sync,
) -> Result<Vec<T>, ModelError> {
    let chunks = sets.div_ceil(CHUNK_SETS);
    let len = |c: usize| CHUNK_SETS.min(sets - c * CHUNK_SETS);
    if threads <= 1 || chunks <= 1 {
        return Ok((0..chunks).map(|c| work(c, len(c))).collect());
    }
    let next = AtomicUsize::new(0);
    let mut done: Vec<(usize, T)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads.min(chunks))
            .map(|_| {
                scope.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let c = next.fetch_add(1, Ordering::Relaxed);
                        if c >= chunks {
                            break;
                        }
                        out.push((c, work(c, len(c))));
                    }
                    out
                })
            })
            .collect();
        let mut all = Vec::with_capacity(chunks);
        for h in handles {
            match h.join() {
                Ok(part) => all.extend(part),
                Err(_) => return Err(()),
            }
        }
        Ok(all)
    })
    .map_err(|()| ModelError::Invalid {
        field: "threads",
        reason: "a Monte Carlo worker thread panicked".into(),
    })?;
    done.sort_by_key(|(c, _)| *c);
    Ok(done.into_iter().map(|(_, t)| t).collect())
}

fn resolve_threads(threads: usize) -> usize {
    if threads == 0 {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
            .min(MAX_THREADS)
    } else {
        threads
    }
}

/// The whole-chain Monte Carlo of the processed products (module docs): `cfg.sets` frame sets
/// of `model` at `angles_rad` and `exposure`, each processed into a Stokes estimate, DoLP and
/// AoP, summarised with standard errors. Seeded and parallel; the answer does not depend on
/// `cfg.threads`.
///
/// Errors: those of [`analytic_products`] (the estimator and the centres come from it); a sensor
/// noise factor other than 1 names `noise_factor`; `sets` outside `2 ..= MAX_PRODUCT_SETS`;
/// `threads` above [`MAX_THREADS`]; `S0` when fewer than 2 sets have `S0_hat > 0` or none has an
/// AoP (a scene too dark for its noise).
pub fn simulate_products(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    cfg: &McConfig,
) -> Result<McProducts, ModelError> {
    check_config(cfg, MAX_PRODUCT_SETS, "2 to 100 000 000")?;
    let (pipeline, _) = prepare(model, angles_rad, exposure, cfg.method, RegimeChoice::Auto)?;
    simulate_with(&pipeline, cfg)
}

fn simulate_with(pipeline: &Pipeline, cfg: &McConfig) -> Result<McProducts, ModelError> {
    let threads = resolve_threads(cfg.threads);
    let parts = run_chunks(cfg.sets, threads, |c, len| {
        pipeline.chunk_sums(cfg.source, cfg.seed, c, len)
    })?;
    let chunks = parts.len();
    let mut t = Sums::default();
    for p in &parts {
        t.add(p);
    }
    summarise(pipeline, &t, cfg, chunks, threads.min(chunks).max(1))
}

fn summarise(
    p: &Pipeline,
    t: &Sums,
    cfg: &McConfig,
    chunks: usize,
    threads: usize,
) -> Result<McProducts, ModelError> {
    if t.dolp_n < 2 || t.aop_n < 1 {
        return Err(ModelError::Invalid {
            field: "S0",
            reason: format!(
                "only {} of {} frame sets have S0 > 0 and {} an AoP: the scene is too dark for \
                 the sensor's noise",
                t.dolp_n, t.sets, t.aop_n
            ),
        });
    }
    let n = t.sets as f64;
    let ds = t.stokes / n;
    let stokes_mean_w_m2_sr = p.stokes_center + ds;
    let stokes_cov_w2_m4_sr2 = (t.stokes_sq - ds * ds.transpose() * n) / (n - 1.0);
    // DoLP moments about the sample mean from the power sums about the centre.
    let nd = t.dolp_n as f64;
    let [e1, e2, e3, e4] = t.dolp.map(|v| v / nd);
    let m2 = (e2 - e1 * e1).max(0.0);
    let m4 = (e4 - 4.0 * e1 * e3 + 6.0 * e1 * e1 * e2 - 3.0 * e1.powi(4)).max(0.0);
    let dolp_std = (m2 * nd / (nd - 1.0)).sqrt();
    let dolp_std_se = if dolp_std > 0.0 {
        ((m4 - m2 * m2).max(0.0) / nd).sqrt() / (2.0 * dolp_std)
    } else {
        0.0
    };
    let na = t.aop_n as f64;
    let (a2, a4) = (t.aop[0] / na, t.aop[1] / na);
    let aop_std_rad = a2.sqrt();
    let aop_std_se_rad = if aop_std_rad > 0.0 {
        ((a4 - a2 * a2).max(0.0) / na).sqrt() / (2.0 * aop_std_rad)
    } else {
        0.0
    };
    let (c_bar, s_bar) = (t.aop[2] / na, t.aop[3] / na);
    let r = c_bar.hypot(s_bar);
    let frames = p.stokes_from_dn.len().max(1) as f64;
    Ok(McProducts {
        sets: t.sets,
        seed: cfg.seed,
        chunks,
        threads,
        method: p.method,
        stokes_mean_w_m2_sr,
        stokes_cov_w2_m4_sr2,
        dolp_mean: p.dolp_center + e1,
        dolp_mean_se: dolp_std / nd.sqrt(),
        dolp_std,
        dolp_std_se,
        aop_center_rad: p.aop_center_rad,
        aop_std_rad,
        aop_std_se_rad,
        aop_circular_mean_rad: wrap_half_pi(0.5 * s_bar.atan2(c_bar)),
        aop_circular_std_rad: 0.5 * (-2.0 * r.max(1e-300).ln()).sqrt(),
        samples_used: t.dolp_n,
        samples_dark: t.sets - t.dolp_n,
        samples_no_aop: t.sets - t.aop_n,
        saturated_fraction: t.saturated_frames as f64 / (n * frames),
    })
}

/// Every processed frame set of a whole-chain Monte Carlo (the same draws, set for set, as
/// [`simulate_products`] with the same `sets` and `seed`), for checks that need the samples
/// themselves (ROC curves, histograms). Single-threaded.
///
/// Errors as [`simulate_products`], with `sets` in `2 ..= MAX_SAMPLE_SETS`.
pub fn sample_products(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    cfg: &McConfig,
) -> Result<Vec<ProductSample>, ModelError> {
    check_config(cfg, MAX_SAMPLE_SETS, "2 to 2 000 000")?;
    let (pipeline, _) = prepare(model, angles_rad, exposure, cfg.method, RegimeChoice::Auto)?;
    let mut out = Vec::with_capacity(cfg.sets);
    let chunks = cfg.sets.div_ceil(CHUNK_SETS);
    for c in 0..chunks {
        let len = CHUNK_SETS.min(cfg.sets - c * CHUNK_SETS);
        pipeline.run_chunk(cfg.source, cfg.seed, c, len, |s, saturated_frames| {
            out.push(ProductSample {
                stokes_w_m2_sr: *s,
                dolp: Pipeline::dolp(s),
                aop_rad: Pipeline::aop(s).map(wrap_half_pi),
                saturated_frames,
            })
        });
    }
    Ok(out)
}

/// The analytic DoLP and AoP statistics against a Monte Carlo's (relative errors and
/// differences in standard errors), and the Stokes covariance's largest normalised difference.
pub fn compare(
    stats: &PolarizationStats,
    stokes_cov: &Matrix3<f64>,
    mc: &McProducts,
) -> Comparison {
    let mut cov_err: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let scale = (stokes_cov[(i, i)] * stokes_cov[(j, j)]).max(0.0).sqrt();
            let d = (stokes_cov[(i, j)] - mc.stokes_cov_w2_m4_sr2[(i, j)]).abs();
            if scale > 0.0 {
                cov_err = cov_err.max(d / scale);
            }
        }
    }
    Comparison {
        regime: stats.regime,
        polarised_snr: stats.polarised_snr,
        dolp_mean: Agreement::new(stats.dolp_mean, mc.dolp_mean, mc.dolp_mean_se),
        dolp_std: Agreement::new(stats.dolp_std, mc.dolp_std, mc.dolp_std_se),
        aop_std: Agreement::new(stats.aop_std_rad, mc.aop_std_rad, mc.aop_std_se_rad),
        stokes_cov_error: cov_err,
    }
}

/// One validation point: the analytic statistics in `regime` and the whole-chain Monte Carlo
/// with `cfg`, from the same chain and estimator, and their comparison. Errors as
/// [`simulate_products`].
pub fn validate_point(
    model: &SensorModel,
    angles_rad: &[f64],
    exposure: &Exposure,
    regime: RegimeChoice,
    cfg: &McConfig,
) -> Result<ValidationPoint, ModelError> {
    check_config(cfg, MAX_PRODUCT_SETS, "2 to 100 000 000")?;
    let (pipeline, analytic) = prepare(model, angles_rad, exposure, cfg.method, regime)?;
    let monte_carlo = simulate_with(&pipeline, cfg)?;
    let comparison = compare(&analytic.stats, &analytic.estimator.cov, &monte_carlo);
    Ok(ValidationPoint {
        analytic,
        monte_carlo,
        comparison,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::atmosphere::Band;
    use crate::polarization::Stokes;
    use crate::sensor::{Camera, NoiseFactor};

    fn cmos() -> SensorModel {
        let cam = Camera::from_toml_str(include_str!("../../../examples/cameras/cmos_modern.toml"))
            .unwrap();
        SensorModel::new(&cam, &Band::flat(500.0, 600.0).unwrap()).unwrap()
    }

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
    }

    /// An exposure of `electrons` mean photo-electrons per frame (unpolarised part) for a scene
    /// of DoLP `dolp` at AoP `aop_deg`.
    fn exposure(
        model: &SensorModel,
        angles: &[f64],
        electrons: f64,
        dolp: f64,
        aop_deg: f64,
    ) -> Exposure {
        let w = model.intensities_from_stokes(angles).unwrap();
        let s0 = 0.1;
        let t = electrons / (model.responsivity_e_per_s() * w.column(0).mean() * s0);
        let a = 2.0 * aop_deg.to_radians();
        Exposure::new(t, Stokes::new(s0, s0 * dolp * a.cos(), s0 * dolp * a.sin()))
    }

    /// The answer is bit-for-bit the same on 1, 2 and 3 threads (chunks seeded by index, summed
    /// in order), and on the Gaussian source too; another seed gives another answer.
    #[test]
    fn thread_count_does_not_change_the_answer() {
        let model = cmos();
        let angles = deg(&[0.0, 60.0, 120.0]);
        let ex = exposure(&model, &angles, 500.0, 0.1, 20.0);
        for source in [McSource::Chain, McSource::GaussianStokes] {
            let run = |threads: usize, seed: u64| {
                let cfg = McConfig {
                    threads,
                    source,
                    ..McConfig::new(5 * CHUNK_SETS + 17, seed)
                };
                let mut r = simulate_products(&model, &angles, &ex, &cfg).unwrap();
                r.threads = 0;
                r
            };
            let one = run(1, 3);
            assert_eq!(one.chunks, 6);
            assert_eq!(one, run(2, 3));
            assert_eq!(one, run(3, 3));
            assert_eq!(one, run(0, 3));
            assert_ne!(one.dolp_mean, run(1, 4).dolp_mean);
        }
    }

    /// `sample_products` returns the very draws `simulate_products` summarises: the mean DoLP of
    /// the samples equals the summary's to rounding (1e-12 relative).
    #[test]
    fn samples_are_the_summarised_draws() {
        let model = cmos();
        let angles = deg(&[0.0, 45.0, 90.0, 135.0]);
        let ex = exposure(&model, &angles, 1000.0, 0.3, 40.0);
        let cfg = McConfig::new(3000, 11);
        let summary = simulate_products(&model, &angles, &ex, &cfg).unwrap();
        let samples = sample_products(&model, &angles, &ex, &cfg).unwrap();
        assert_eq!(samples.len(), 3000);
        let mean = samples.iter().map(|s| s.dolp.unwrap()).sum::<f64>() / 3000.0;
        assert!((mean / summary.dolp_mean - 1.0).abs() < 1e-12);
        assert!(samples
            .iter()
            .all(|s| s.aop_rad.unwrap().abs() <= FRAC_PI_2));
    }

    /// The linear part is exact in the analytic model: over 1e5 sets of the CMOS at 2000
    /// e-/frame (GLS, since shot noise differs between frames) the sample Stokes mean is within
    /// 4 standard errors (`sqrt(Sigma_ii / n)`) of `L_mean`, and every covariance entry within
    /// `5 sqrt(2 / n)` = 2.2 % of the diagonal scale (the standard error of a sample
    /// (co)variance is at most `sqrt(2 / n)` of it for Gaussian data).
    #[test]
    fn stokes_mean_and_covariance_are_exact() {
        let model = cmos();
        let angles = deg(&[0.0, 45.0, 90.0, 135.0]);
        let ex = exposure(&model, &angles, 2000.0, 0.3, 40.0);
        let n = 100_000;
        let v = validate_point(
            &model,
            &angles,
            &ex,
            RegimeChoice::Auto,
            &McConfig::new(n, 2),
        )
        .unwrap();
        assert_eq!(v.analytic.estimator.method, Method::Gls);
        assert_eq!(v.monte_carlo.method, Method::Gls);
        let cov = v.analytic.estimator.cov;
        for i in 0..3 {
            let se = (cov[(i, i)] / n as f64).sqrt();
            let d = v.monte_carlo.stokes_mean_w_m2_sr[i] - v.analytic.stokes_mean_w_m2_sr[i];
            assert!(d.abs() < 4.0 * se, "S{i}: {d:e} against SE {se:e}");
        }
        let tol = 5.0 * (2.0 / n as f64).sqrt();
        assert!(
            v.comparison.stokes_cov_error < tol,
            "{}",
            v.comparison.stokes_cov_error
        );
        assert_eq!(v.monte_carlo.saturated_fraction, 0.0);
    }

    /// High polarised SNR (DoLP 0.3 at 4500 e-/frame through 0/45/90/135: SNR_p about 28): the
    /// Taylor regime; DoLP mean, DoLP std and AoP std within 4 Monte Carlo standard errors plus
    /// the size of the first neglected term: `1/(2 SNR^2)` of the standard deviations
    /// (first-order variance, `Var p_hat = sigma^2 (1 - 1/(2 SNR^2))`), and for the mean the
    /// Rice series' next term `sigma_p^4 / (8 p^3)` plus the second-order `S0` term
    /// `3 (sigma_S0/S0)^4` of the mean's size.
    #[test]
    fn taylor_agrees_at_high_snr() {
        let model = cmos();
        let angles = deg(&[0.0, 45.0, 90.0, 135.0]);
        let ex = exposure(&model, &angles, 4500.0, 0.3, 15.0);
        let v = validate_point(
            &model,
            &angles,
            &ex,
            RegimeChoice::Auto,
            &McConfig::new(50_000, 5),
        )
        .unwrap();
        let c = &v.comparison;
        assert_eq!(c.regime, Regime::Taylor);
        assert!(c.polarised_snr > 20.0, "{}", c.polarised_snr);
        let rho2 = c.polarised_snr * c.polarised_snr;
        let s = &v.analytic.stokes_mean_w_m2_sr;
        let cs0 = v.analytic.estimator.cov[(0, 0)].sqrt() / s[0];
        let mean_bias = c.dolp_mean.analytic * (1.0 / (8.0 * rho2 * rho2) + 3.0 * cs0.powi(4));
        assert!(
            (c.dolp_mean.analytic - c.dolp_mean.monte_carlo).abs()
                < 4.0 * c.dolp_mean.se + mean_bias,
            "{:?}",
            c.dolp_mean
        );
        for a in [c.dolp_std, c.aop_std] {
            let bias = a.analytic / (2.0 * rho2);
            assert!(
                (a.analytic - a.monte_carlo).abs() < 4.0 * a.se + bias,
                "{a:?}"
            );
        }
    }

    /// Low polarised SNR (DoLP 0.02 at 4500 e-/frame through 0/60/120: SNR_p about 1.6,
    /// isotropic (S1, S2) noise): the Rice regime; all three statistics within 4 standard errors
    /// plus `3 (sigma_S0/S0)^2` relative (the first-order treatment of the `S0` noise; 0.02 %
    /// here), while the Taylor mean forced on the same point is low by the Rice series' next
    /// terms (1.7 %, about 9 standard errors).
    #[test]
    fn rice_agrees_at_low_snr() {
        let model = cmos();
        let angles = deg(&[0.0, 60.0, 120.0]);
        let ex = exposure(&model, &angles, 4500.0, 0.02, 15.0);
        let v = validate_point(
            &model,
            &angles,
            &ex,
            RegimeChoice::Auto,
            &McConfig::new(50_000, 6),
        )
        .unwrap();
        let c = &v.comparison;
        assert_eq!(c.regime, Regime::Rice);
        assert!(
            c.polarised_snr > 1.0 && c.polarised_snr < 2.5,
            "{}",
            c.polarised_snr
        );
        let s0 = v.analytic.stokes_mean_w_m2_sr[0];
        let cs0_2 = v.analytic.estimator.cov[(0, 0)] / (s0 * s0);
        for a in [c.dolp_mean, c.dolp_std, c.aop_std] {
            let bias = 3.0 * cs0_2 * a.analytic.abs();
            assert!(
                (a.analytic - a.monte_carlo).abs() < 4.0 * a.se + bias,
                "{a:?}"
            );
        }
        let taylor = dolp_aop_stats(
            &v.analytic.stokes_mean_w_m2_sr,
            &v.analytic.estimator.cov,
            RegimeChoice::Taylor,
        )
        .unwrap();
        let forced = compare(&taylor, &v.analytic.estimator.cov, &v.monte_carlo);
        // E[p_hat] = p (1 + 1/(2 rho^2) + 1/(8 rho^4) + 1/(16 rho^6) + ...) (the Rice mean's
        // large-SNR series); the second-order Taylor mean stops after 1/(2 rho^2), so it is low
        // by about (1/(8 rho^4) + 1/(16 rho^6)) / (1 + 1/(2 rho^2)) = 1.7 % at rho = 1.63.
        let rho2 = c.polarised_snr * c.polarised_snr;
        let missing =
            (1.0 / (8.0 * rho2 * rho2) + 1.0 / (16.0 * rho2 * rho2 * rho2)) / (1.0 + 0.5 / rho2);
        assert!(forced.dolp_mean.z < -5.0, "{:?}", forced.dolp_mean);
        assert!(
            (forced.dolp_mean.rel_error + missing).abs()
                < 4.0 * forced.dolp_mean.se / forced.dolp_mean.monte_carlo + 0.5 * missing,
            "{:?} {missing}",
            forced.dolp_mean
        );
    }

    /// An unpolarised scene: the analytic mean Stokes vector is exactly unpolarised (no 1e-17
    /// residue from the estimator), the AoP spread is the uniform `pi/sqrt(12)` and the MC's
    /// is within 4 standard errors of it.
    #[test]
    fn unpolarised_scene() {
        let model = cmos();
        let angles = deg(&[0.0, 45.0, 90.0, 135.0]);
        let ex = exposure(&model, &angles, 4500.0, 0.0, 0.0);
        let v = validate_point(
            &model,
            &angles,
            &ex,
            RegimeChoice::Auto,
            &McConfig::new(20_000, 8),
        )
        .unwrap();
        let s = v.analytic.stokes_mean_w_m2_sr;
        assert_eq!((s[1], s[2]), (0.0, 0.0));
        let a = v.comparison.aop_std;
        assert!((a.analytic - crate::stats::AOP_STD_UNIFORM_RAD).abs() < 1e-12);
        assert!(a.z.abs() < 4.0, "{a:?}");
    }

    /// Inputs outside the domain are errors naming the field: sets, threads, a noise factor
    /// other than 1, two angles (W singular), a dark scene (S0 = 0), more samples than kept.
    #[test]
    fn errors_name_the_field() {
        let model = cmos();
        let angles = deg(&[0.0, 60.0, 120.0]);
        let ex = exposure(&model, &angles, 500.0, 0.1, 0.0);
        let err = |r: Result<McProducts, ModelError>| r.unwrap_err().to_string();
        assert!(err(simulate_products(
            &model,
            &angles,
            &ex,
            &McConfig::new(1, 1)
        ))
        .contains("sets"));
        let cfg = McConfig {
            threads: 1000,
            ..McConfig::new(10, 1)
        };
        assert!(err(simulate_products(&model, &angles, &ex, &cfg)).contains("threads"));
        let mut e = ex;
        e.noise_factor = NoiseFactor::Variance(2.0);
        assert!(err(simulate_products(
            &model,
            &angles,
            &e,
            &McConfig::new(10, 1)
        ))
        .contains("noise_factor"));
        let two = deg(&[0.0, 90.0]);
        assert!(
            err(simulate_products(&model, &two, &ex, &McConfig::new(10, 1))).contains("angles_deg")
        );
        let dark = Exposure::new(1e-3, Stokes::new(0.0, 0.0, 0.0));
        assert!(err(simulate_products(
            &model,
            &angles,
            &dark,
            &McConfig::new(10, 1)
        ))
        .contains("S0"));
        let big = McConfig::new(MAX_SAMPLE_SETS + 1, 1);
        assert!(sample_products(&model, &angles, &ex, &big)
            .unwrap_err()
            .to_string()
            .contains("sets"));
    }
}
