//! The product rule's levels and when one is accepted: the ladder of levels with its adaptive
//! fallback, a pair of levels of one ray, and the result with its error estimate.

use crate::polarization::Stokes;
use crate::quadrature::{max_abs, IntegralN, Tolerance};
use std::f64::consts::PI;

/// A hemisphere integral's result: a Stokes vector with its error estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StokesIntegral {
    /// The integral.
    pub stokes: Stokes,
    /// Estimated largest component error.
    pub error: f64,
    /// Integrand evaluations.
    pub evaluations: usize,
    /// Whether the tolerance was met.
    pub converged: bool,
    /// The product rule's accepted level (an index into its levels, from 0), `None` when an
    /// adaptive rule gave the answer: where a ray next to this one may start
    /// ([`reflected_skylight`](crate::skylight::reflected_skylight)'s `start_level`).
    pub level: Option<usize>,
}

/// Where [`ladder`] starts.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Start<'p> {
    /// At this level of `GAUSS_LEVELS`.
    Level(usize),
    /// After the two levels of a [`LevelPair`] of the same ray, which are not computed again.
    After(&'p LevelPair),
}

/// One ray's specular skylight at two adjacent product-rule levels, not yet accepted: a
/// batch of neighbouring rays is accepted together on the largest of their changes
/// ([`level_pair`](crate::skylight::level_pair)), or each ray resumes its own ladder from here
/// ([`reflected_skylight_at`](crate::skylight::reflected_skylight_at)).
#[derive(Debug, Clone, Copy)]
pub(crate) struct LevelPair {
    /// The lower level (an index of `GAUSS_LEVELS`); the upper is the next.
    pub(crate) level: usize,
    pub(crate) lower: [f64; 3],
    pub(crate) upper: [f64; 3],
    /// The truncation error every result carries.
    pub(crate) floor: f64,
    /// The factor on the batch's largest change ([`PairRule::safety`](crate::skylight::PairRule::safety)).
    pub(crate) safety: f64,
    /// The change into `lower` from the level below it (a [`next_pair`](crate::skylight::next_pair)'s: the first pair's
    /// step), infinite for a first pair: with [`LevelPair::step`], the two changes the
    /// [`ladder`]'s own test takes.
    pub(crate) lower_change: f64,
    pub(crate) evaluations: usize,
}

impl LevelPair {
    /// The change between the two levels (largest component).
    pub(crate) fn step(&self) -> f64 {
        max_abs::<3>(&std::array::from_fn(|i| self.upper[i] - self.lower[i]))
    }

    /// [`LevelPair::step`] times the rule's safety factor, plus the truncation: the upper
    /// level's error, as the largest over a batch ([`level_pair`](crate::skylight::level_pair)).
    pub(crate) fn error(&self) -> f64 {
        self.safety * self.step() + self.floor
    }

    /// The largest component of the upper level's value.
    pub(crate) fn scale(&self) -> f64 {
        max_abs(&self.upper)
    }

    /// The upper level's index in `GAUSS_LEVELS`.
    pub(crate) fn upper_level(&self) -> usize {
        self.level + 1
    }

    /// The upper level accepted with `error` (the batch's largest change), plus the
    /// Lambertian term `f00_diffuse * e_sky` in S0, as [`reflected_skylight`](crate::skylight::reflected_skylight) returns it.
    pub(crate) fn accept(&self, error: f64, f00_diffuse: f64, e_sky: f64) -> StokesIntegral {
        accepted_level(self.upper, error, self.evaluations, f00_diffuse * e_sky)
    }
}

/// A product-rule level accepted with `error`, plus the Lambertian term `lambertian` in S0,
/// as [`reflected_skylight`](crate::skylight::reflected_skylight) returns it.
pub(crate) fn accepted_level(
    value: [f64; 3],
    error: f64,
    evaluations: usize,
    lambertian: f64,
) -> StokesIntegral {
    let mut r = StokesIntegral::from(IntegralN {
        value,
        error,
        evaluations,
        converged: true,
    });
    r.stokes.0[0] += lambertian;
    r
}
/// Runs a product rule `rule(n, q)` (value, evaluations) at each of [`GAUSS_LEVELS`] in turn,
/// from `start` (a level, at most the third last: a level's error needs the two before it; or
/// after a [`LevelPair`], whose two levels count as computed), until one is accepted; `floor`
/// is an error every result carries (a truncation). When none is (an integrand not smooth
/// enough on the rule's pieces: a sharp feature of the sky inside the lobe, say), `fallback`
/// (an adaptive rule) is run, and the better of its answer and the last level's is returned.
///
/// A later `start` skips levels, never the test: the accepted level passed it against the same
/// two levels below it as from 0, and is at least the level a start from 0 would accept unless
/// that one lies below `start + 2` (then the answer is a finer level's).
pub(crate) fn ladder(
    mut rule: impl FnMut(usize, usize) -> ([f64; 3], usize),
    fallback: impl FnOnce() -> IntegralN<3>,
    tol: Tolerance,
    floor: f64,
    start: Start,
) -> StokesIntegral {
    let accept = |value: [f64; 3], error: f64, evaluations: usize, level: usize| StokesIntegral {
        level: Some(level),
        ..StokesIntegral::from(IntegralN {
            value,
            error,
            evaluations,
            converged: true,
        })
    };
    let (first, mut previous, mut evaluations, mut last_change) = match start {
        Start::Level(level) => {
            let level = level.min(GAUSS_LEVELS.len() - 3);
            let (n, q) = GAUSS_LEVELS[level];
            let (value, e) = rule(n, q);
            (level, value, e, f64::INFINITY)
        }
        Start::After(pair) => {
            // The pair's upper level passes the ladder's own test when the two changes it
            // already has (into each of the pair's levels) are within the tolerance: a batch
            // that failed on its largest change (or its safety factor) takes no level more than
            // a ladder would at such a ray.
            let error = pair.step().max(pair.lower_change) + floor;
            if error <= tol.target(max_abs(&pair.upper)) {
                return accept(pair.upper, error, pair.evaluations, pair.level + 1);
            }
            (pair.level + 1, pair.upper, pair.evaluations, pair.step())
        }
    };
    let mut best = (previous, f64::INFINITY);
    for (level, &(n, q)) in GAUSS_LEVELS.iter().enumerate().skip(first + 1) {
        let (value, e) = rule(n, q);
        evaluations += e;
        let change = max_abs::<3>(&std::array::from_fn(|i| value[i] - previous[i]));
        // The larger of the last two changes: one change alone can be small by a coincidence
        // of two levels' errors (it is, in 6-8 % of 947 views and tolerances, by up to 11x;
        // the larger of two never is, see `product_rule_error_covers_the_actual_error`).
        let error = change.max(last_change) + floor;
        if error < best.1 {
            best = (value, error);
        }
        if error <= tol.target(max_abs(&value)) {
            return accept(value, error, evaluations, level);
        }
        previous = value;
        last_change = change;
    }
    let r = fallback();
    evaluations += r.evaluations;
    let (value, error, converged) = if r.error + floor <= best.1 {
        (r.value, r.error + floor, r.converged)
    } else {
        (best.0, best.1, false)
    };
    StokesIntegral::from(IntegralN {
        value,
        error,
        evaluations,
        converged,
    })
}

/// Points of the azimuth rule on an arc of length `len` at level `n` (points per half turn):
/// the arc's share by length, but at least `n / 2`, since the short arcs next to
/// `psi = +-pi/2` of a grazing view hold its fastest variation (on the scale
/// `cos theta_v / sin theta_v`).
pub(crate) fn arc_points(n: usize, len: f64) -> usize {
    ((n as f64 * len / PI).round() as usize)
        .max(n.div_ceil(2))
        .max(3)
}

/// `sum += v * w`, componentwise.
#[inline]
pub(crate) fn add_scaled(sum: &mut [f64; 3], v: &[f64; 3], w: f64) {
    for (s, x) in sum.iter_mut().zip(v) {
        *s += x * w;
    }
}

impl From<IntegralN<3>> for StokesIntegral {
    fn from(r: IntegralN<3>) -> Self {
        StokesIntegral {
            stokes: Stokes::new(r.value[0], r.value[1], r.value[2]),
            error: r.error,
            evaluations: r.evaluations,
            converged: r.converged,
            level: None,
        }
    }
}

/// The product rule's levels `(n, q)` for [`SlopeIntegrand::gauss`], each about 1.3-1.5 times
/// the last in both directions. A level is accepted when the larger of its change from the level
/// before and that level's change from the one before it is below the tolerance; that larger
/// change is its reported error.
pub(crate) const GAUSS_LEVELS: [(usize, usize); 9] = [
    (4, 4),
    (6, 5),
    (8, 6),
    (12, 8),
    (16, 10),
    (24, 12),
    (32, 16),
    (48, 20),
    (64, 24),
];
