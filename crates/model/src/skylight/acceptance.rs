//! When a ray's skylight is accepted: a batch of neighbouring rays on two levels of their
//! product rule ([`level_pair`], [`next_pair`], [`batch_error`]), and the rays around an
//! accepted batch on its upper level alone, with its error ([`certified_level`]).

use super::integrand::*;
use super::rules::*;
use crate::error::ModelError;
use crate::pbrdf::Surface;
use crate::quadrature::Tolerance;
use crate::sky::radiance::SkyRadiance;
use crate::slope::{
    accepted_level, check_view, slope_truncation, LevelPair, SlopeIntegrand, StokesIntegral,
    GAUSS_LEVELS,
};
use nalgebra::Vector3;

/// When a batch of a surface's rays may be accepted on level pairs ([`level_pair`]): the
/// lowest and highest level the neighbours' [`ladder`]s must have been accepted at (`hint`),
/// and the factor on the batch's largest change that is then every ray's error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct PairRule {
    /// The lowest admissible hint.
    pub(crate) min_hint: usize,
    /// The highest admissible hint.
    pub(crate) max_hint: usize,
    /// The factor on the batch's largest change.
    pub(crate) safety: f64,
}

/// The [`PairRule`] of `surface`, each validated by a study over fields of +-4 and +-6 deg
/// (5 skies with an aureole, views 8-68 deg from the normal, tolerances 1e-2 to 1e-8 of S0):
///
/// - A microfacet (`field_pair_study`: a dielectric and a metal, sigma 0.02-1): hints from
///   [`PAIR_MIN_HINT`] on, the largest change as it is. None of 132 624 rays in accepted
///   batches was further from the truth than that change (the worst at 0.89 of it); below
///   that hint rays were, by up to 81x.
/// - Vegetation's hemisphere rule (`vegetation_pair_study`: leaf indices 1.4-1.6): hints 2-7,
///   twice the largest change. With the change as it is, rays were short of it by up to 1.28x
///   at hints 5-6; twice it, none of 18 132 rays in admitted batches was, the worst at 0.67 of
///   the claim. At hint 8 (the top level) rays were short by up to 28x even so (one sun, views
///   8-25 deg: level 7's change into level 8 far below its error), so such batches keep their
///   ladders.
pub(crate) fn pair_rule(surface: &Surface) -> PairRule {
    match surface {
        Surface::Microfacet { .. } => PairRule {
            min_hint: PAIR_MIN_HINT,
            max_hint: GAUSS_LEVELS.len() - 1,
            safety: 1.0,
        },
        Surface::Vegetation { .. } => PairRule {
            min_hint: 2,
            max_hint: GAUSS_LEVELS.len() - 2,
            safety: 2.0,
        },
    }
}

/// The error every ray of a batch of [`LevelPair`]s is accepted with, the largest of their
/// [`LevelPair::error`]s, when it meets the tolerance at every ray; `None` when it does not.
pub(crate) fn batch_error<'p>(
    mut pairs: impl Iterator<Item = &'p LevelPair> + Clone,
    tol: Tolerance,
) -> Option<f64> {
    let error = pairs.clone().fold(0.0f64, |m, p| m.max(p.error()));
    pairs
        .all(|p| error <= tol.target(p.scale()))
        .then_some(error)
}

/// The lowest level a batch's microfacet [`ladder`]s must have been accepted at (`hint`)
/// before its neighbours may be accepted on one change ([`pair_rule`]).
pub(crate) const PAIR_MIN_HINT: usize = 4;

/// The skylight of `surface`'s polarising lobe (without the Lambertian term) at product-rule
/// levels `hint - 2` and `hint - 1`, for a batch of rays near rays whose ladders were accepted
/// at level `hint` (admitted by [`pair_rule`]) to the batch's tolerance.
///
/// One change alone is not an honest error (`ladder`: it fell short in 6-8 % of single rays,
/// by up to 11x). For a batch it is taken as the largest change over the batch (times the
/// rule's safety factor), once the neighbours' ladders showed that levels from `hint - 2` on
/// converge: a change small by a coincidence of two levels' errors at one ray is not small at
/// all of its neighbours, whose errors vary smoothly with the view (the rule's pieces move
/// continuously with it). The validation is [`pair_rule`]'s.
pub(crate) fn level_pair<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    hint: usize,
) -> Result<LevelPair, ModelError> {
    let level = hint.clamp(2, GAUSS_LEVELS.len() - 1) - 2;
    let (lower, e0) = rule_level(surface, sky, omega_view, level)?;
    let (upper, e1) = rule_level(surface, sky, omega_view, level + 1)?;
    Ok(LevelPair {
        level,
        lower,
        upper,
        floor: match surface {
            Surface::Microfacet { .. } => slope_truncation(sky),
            Surface::Vegetation { .. } => 0.0,
        },
        safety: pair_rule(surface).safety,
        lower_change: f64::INFINITY,
        evaluations: e0 + e1,
    })
}

/// The batch's next pair for one ray: `pair`'s upper level and the level above it (same
/// surface, sky and view as `pair`), when a batch's first pairs fell short of its tolerance;
/// `None` when no level is left above (or none after it for a ladder to resume on).
/// Validated as the first pairs are (`field_pair_study`, `vegetation_pair_study`: one such
/// step).
pub(crate) fn next_pair<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    pair: &LevelPair,
) -> Result<Option<LevelPair>, ModelError> {
    let level = pair.level + 1;
    if level + 2 >= GAUSS_LEVELS.len() {
        return Ok(None);
    }
    let (upper, e) = rule_level(surface, sky, omega_view, level + 1)?;
    Ok(Some(LevelPair {
        level,
        lower: pair.upper,
        upper,
        lower_change: pair.step(),
        evaluations: pair.evaluations + e,
        ..*pair
    }))
}

/// What an accepted batch of [`LevelPair`]s shows for the rays around it: its upper level
/// and the error every one of its rays was accepted with ([`batch_error`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Certificate {
    /// The batch's upper level (an index of `GAUSS_LEVELS`).
    pub(crate) level: usize,
    /// The batch's error (its largest change times the rule's safety, plus the truncation).
    pub(crate) error: f64,
}

/// The skylight of a ray among the rays of an accepted batch (the sky interpolant's later
/// rays: its checks, corners and 5-point nodes, around the batch of the cross's four edges),
/// at the batch's upper level alone and with its error, plus the Lambertian term
/// `f00_diffuse * e_sky` in S0.
///
/// A batch's largest change bounds the errors of the rays around it as well as its own
/// (`certificate_study`): of 83 136 such rays around 6 928 accepted batches of microfacet
/// edges, and 18 180 around 1 515 of vegetation, none was further from the truth than the
/// batch's error (the worst at 0.91 and 0.71 of it). A pair costs its lower level as well:
/// the upper alone is about 0.6 of it.
pub(crate) fn certified_level<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    certificate: Certificate,
    f00_diffuse: f64,
    e_sky: f64,
) -> Result<StokesIntegral, ModelError> {
    let level = certificate.level.min(GAUSS_LEVELS.len() - 1);
    let (value, evaluations) = rule_level(surface, sky, omega_view, level)?;
    Ok(accepted_level(
        value,
        certificate.error,
        evaluations,
        f00_diffuse * e_sky,
    ))
}

/// The skylight of `surface`'s polarising lobe by the product rule at `GAUSS_LEVELS[level]`,
/// (value, evaluations): in facet-slope space for a microfacet ([`SlopeIntegrand::gauss`]),
/// over the hemisphere for vegetation ([`direct_skylight`]'s rule; the adaptive rule it takes
/// at views within 15 deg of the horizon is not a level, and [`pair_rule`]'s validation
/// stopped at 68 deg).
pub(super) fn rule_level<S: SkyRadiance + ?Sized>(
    surface: &Surface,
    sky: &S,
    omega_view: &Vector3<f64>,
    level: usize,
) -> Result<([f64; 3], usize), ModelError> {
    check_view(omega_view)?;
    let (n, q) = GAUSS_LEVELS[level];
    Ok(match surface {
        Surface::Microfacet { lobe, .. } => {
            SlopeIntegrand::new(lobe.index().permittivity(), lobe.sigma(), sky, omega_view).gauss(
                n,
                q,
                &mut Vec::with_capacity(8),
            )
        }
        Surface::Vegetation { .. } => {
            let (phi_splits, mu_splits) = hemisphere_splits(sky, omega_view);
            vegetation_gauss(surface, sky, omega_view, (n, q), (&phi_splits, &mu_splits))
        }
    })
}
