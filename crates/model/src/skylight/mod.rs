//! Skylight reflected by a surface towards the sensor (Meng (2012) Eq. 3.22, MODEL.md section 4):
//! `Ld = int_hemisphere F(omega_d -> omega_v) Lsky(omega_d) cos theta_d dOmega_d`, a Stokes vector in
//! the reflected ray's surface frame (the sky's Stokes vectors are already in each incident ray's
//! surface frame, see [`crate::sky`]), per unit of whatever the sky radiance is per.
//!
//! The specular part is integrated in facet-slope space ([`crate::slope`]), which makes the cost
//! independent of the roughness; a batch of neighbouring rays may be accepted on two levels of
//! its product rule each, with the largest change over the batch as every ray's error
//! (`level_pair`, validated by `field_pair_study`), which halves the cost of the scene's field
//! rays; vegetation's batches likewise, on twice that change (`vegetation_pair_study`). Rays
//! around an accepted batch then take its upper level alone, with its error
//! (`certified_level`, validated by `certificate_study`).
//!
//! The Lambertian part is `f00_d` times the sky irradiance, and the vegetation lobe, which is
//! broad, is integrated over the hemisphere directly, by the same kind of product rule. Every
//! result carries the quadrature's error estimate and evaluation count.
//!
//! * [`reflected`]: the entry points: reflected and direct skylight, sky irradiance;
//! * [`integrand`]: the integrands over the hemisphere;
//! * [`rules`]: the hemisphere's product rules;
//! * [`acceptance`]: level pairs over a batch of rays, and certified levels.

mod acceptance;
mod integrand;
mod reflected;
mod rules;

pub use crate::sky::{SkyRadiance, SunlitRayleigh, UniformSky};
pub use crate::slope::{specular_skylight, StokesIntegral};
pub(crate) use acceptance::{
    batch_error, certified_level, level_pair, next_pair, pair_rule, Certificate,
};
pub use reflected::{direct_skylight, reflected_skylight, sky_irradiance};
pub(crate) use reflected::{reflected_skylight_at, DIRECT_PRODUCT_MIN_COS_VIEW};

#[cfg(test)]
mod tests;
