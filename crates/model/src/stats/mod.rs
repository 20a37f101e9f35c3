//! Processing statistics (MODEL.md section 7): Stokes estimation with covariance, and the mean
//! and spread of the estimated DoLP and AoP, with a seeded Monte Carlo check at the Stokes level.
//!
//! * [`estimation`]: OLS and GLS Stokes estimators `S_hat = G I` and their covariance.
//! * [`dolp_aop`]: [`dolp_aop_stats`], the DoLP and AoP mean and spread of a Gaussian Stokes
//!   estimate with any 3 x 3 covariance.
//! * [`integral`]: the integration behind it, valid at every polarised SNR: polar coordinates in
//!   `(S1, S2)` with the radial integrals in closed form (truncated normal moments), the `S0`
//!   noise by a conditional series, an adaptive angular quadrature with an error estimate.
//! * [`approx`]: the closed-form delta-method ("Taylor") and isotropic Rice approximations, kept
//!   for comparison.
//! * [`special`]: Bessel, Laguerre and error functions, truncated normal moments, Gauss-Hermite.
//! * [`monte_carlo`]: the seeded Monte Carlo check.

pub mod approx;
pub mod dolp_aop;
pub mod estimation;
pub mod integral;
pub mod monte_carlo;
pub mod special;

pub use approx::{AOP_PHASE_SNR, AOP_STD_UNIFORM_RAD};
pub use dolp_aop::{
    dolp_aop_stats, PolarizationStats, Regime, RegimeChoice, StatsMethod, RICE_SNR_THRESHOLD,
};
pub use estimation::{
    estimate_stokes, estimate_stokes_from_matrix, stokes_cov_from_intensity_cov, Method,
    MethodChoice, StokesEstimate, StokesEstimator, SIGMA_COND_LIMIT, W_COND_WARN,
};
pub use integral::MAX_S0_ORDER;
pub(crate) use monte_carlo::SplitMix64;
pub use monte_carlo::{monte_carlo_dolp_aop, psd_factor, MonteCarloPolarization, MAX_MC_SAMPLES};
pub use special::{bessel_i0e, bessel_i1e};
