//! The specular lobe of a microfacet surface against a sky, integrated in facet-slope space: the
//! quadrature that the specular albedo ([`crate::pbrdf::Microfacet::specular_albedo`], a uniform
//! sky) and the reflected skylight ([`crate::skylight`], Meng (2012) Eq. 3.22) share.
//!
//! The specular lobe of a smooth surface is narrow, so it is integrated over facet slopes rather
//! than over sky directions: for a fixed view `omega_v`, each facet normal `h` reflects exactly
//! one sky direction `omega_d = 2 (omega_v . h) h - omega_v`, `dOmega_d = 4 (omega_v . h)
//! dOmega_h`, and the Gaussian slope measure absorbs the lobe, so the cost does not grow as
//! `sigma -> 0` (`sigma = 0.05` costs what `sigma = 0.5` does).
//!
//! In polar slope coordinates `(psi, t)` the integrand is smooth between known curves: the
//! reflected ray's horizon (the support ends there), the shadowing term's branch switches (a
//! line, a circle and a cubic that `rho = tan x` turns into `tan 3x = cos theta_v / k`), and
//! the azimuths where `k = cos psi sin theta_v` is `0` or `-cos theta_v` (where the switches
//! enter a line or meet). A product Gauss-Legendre rule on the smooth pieces converges
//! geometrically; the sky's peak (the sun's aureole) is one more split in both directions. It
//! needs a fraction of the adaptive rule's evaluations, and the adaptive rule remains the
//! fallback (docs/design/scene-quadrature.md). The rule's levels (`ladder`) may start above
//! the first, for rays next to one whose level is known, or after a `LevelPair` of the same
//! ray. Every result carries the quadrature's error estimate and evaluation count.
//!
//! * [`integrand`]: the integrand in slope coordinates and its product rule;
//! * [`facet`]: one facet's reflection of a sky ray;
//! * [`batch`]: batches of facet reflections;
//! * [`ladder`]: the rule's levels, their acceptance and the result with its error.

pub(crate) mod batch;
pub(crate) mod facet;
pub(crate) mod integrand;
pub(crate) mod ladder;

pub(crate) use batch::{reflect_batch, FacetBatch, FACET_BATCH};
pub(crate) use facet::{facet_reflection, ReflectedFrame};
pub use integrand::specular_skylight;
pub(crate) use integrand::{check_view, slope_truncation, specular_skylight_from, SlopeIntegrand};
pub use ladder::StokesIntegral;
pub(crate) use ladder::{
    accepted_level, add_scaled, arc_points, ladder, LevelPair, Start, GAUSS_LEVELS,
};
