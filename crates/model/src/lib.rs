//! End-to-end analytical model of polarimetric imaging.
//!
//! This crate is pure physics: no I/O, no async, no clock, no device types. It follows the
//! conventions of `docs/MODEL.md` section 0 (binding for the whole workspace):
//!
//! * linear Stokes vectors `S = [S0, S1, S2]`, `S1 > 0` along the frame's x axis, `S2 > 0` at +45 deg;
//! * an ideal analyzer at `psi` transmits `I = m(psi)^T S`, `m = 0.5 [1, cos 2psi, sin 2psi]`;
//! * angles are radians inside the code, degrees only at the user boundary (`_deg` names);
//! * zenith angles from the surface normal; relative azimuth `phi` between the towards-source and
//!   towards-sensor directions, so the specular direction is `theta_r = theta_i, phi = 180 deg`.
//!
//! Modules, in the order of the imaging chain:
//!
//! * [`angles`]: degree trigonometry exact at the quadrants, and directions from zenith and azimuth.
//! * [`polarization`]: Stokes and Mueller types, DoLP, AoP, polarizer, frame rotation.
//! * [`fresnel`]: dielectric and conductor Fresnel amplitudes and reflectances.
//! * [`geometry`]: the scattering geometry: ray pair, surface frames, the reflecting microfacet.
//! * [`pbrdf`]: the microfacet polarimetric BRDF (Meng (2012) Eqs. 3.4-3.18) and the vegetation model (Eq. 3.19).
//! * [`material`]: a small library of materials at 550 nm, TOML in and out.
//! * [`analyzer`]: measurement matrices of analyzer sets, reconstruction, conditioning and noise gains.
//! * [`air_mass`]: the relative air mass of the sun's slant path; the pseudo-spherical cosine.
//! * [`atmosphere`]: TOA spectrum, band, Beer-Lambert transmittance, the clear sky's optical depths, path radiance.
//! * [`sky`]: the skies: the trait, uniform, Rayleigh, Berry, the clear sky with aerosol, and a
//!   tabulated sky from a radiative-transfer code (CSV), interpolated with its error.
//! * [`slope`]: a microfacet's specular lobe against a sky, integrated in facet-slope space.
//! * [`skylight`]: skylight reflected by a surface (Eq. 3.22), with its error.
//! * [`span`]: the measurement row of an exposure while the analyzer turns, and angle jitter.
//! * [`sun`]: the sun's position from UTC time and site (NREL SPA).
//! * [`scene`]: a scene's mean and covariance at the aperture, to a tolerance, with its error and the terms it skipped.
//! * [`scene_file`]: the TOML scene format.
//! * [`tiles`]: per-tile viewing geometry of a sensor above flat ground (Appendix A).
//! * [`quadrature`]: the adaptive Gauss-Kronrod rule the model's integrals use, with error estimates.
#![warn(missing_docs)]

pub mod air_mass;
pub mod analyzer;
pub mod angles;
pub mod atmosphere;
pub mod calibration;
pub mod error;
pub mod fresnel;
pub mod geometry;
pub mod material;
pub mod metrics;
pub mod montecarlo;
pub mod pbrdf;
pub mod polarization;
pub mod quadrature;
pub mod scene;
pub mod scene_file;
pub mod sensor;
pub mod sky;
pub mod skylight;
pub mod slope;
pub mod span;
pub mod stats;
pub mod sun;
pub mod tiles;
pub mod validation;

pub use error::ModelError;
