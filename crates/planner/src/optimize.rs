//! The SCR-optimal analyzer set (MODEL.md section 9, "optimal multichannel combination").
//!
//! The search uses the problem's structure. The SCR depends on the set only through
//! `A = sum w_i w_i^T / v_i` ([`crate::scr`]). So it is invariant to the angles' order and to
//! 180-degree shifts of any angle, and the search covers **sorted** tuples in `[0, 180)` deg
//! only: `N!` times fewer points than the full torus.
//!
//! 1. **Coarse search**: without a separation, every nondecreasing tuple of a grid of `m`
//!    angles, `m` chosen per `N` so that at most [`GRID_BUDGET`] tuples are scored (tuples
//!    outside a range are left out). With a separation `s`, a lattice aligned with the
//!    constraints instead: every gap between neighbours is `s + h k`, so the sets on the
//!    boundary (angles exactly `s` apart, an angle at an end of the range), where the optimum
//!    of a binding constraint lies, are lattice points too. The conventional sets the
//!    constraints allow and the widest equally spaced set are added.
//! 2. **Refinement**: the best [`REFINED_STARTS`] points of distinct neighbourhoods (on the
//!    grid, no two within a grid step and a half: one start per basin) are refined by an active-set
//!    BFGS with the analytic gradient: the constraints of a sorted tuple are linear (gaps,
//!    wrap-around gap, range ends), a step is cut at the first one it meets, which becomes
//!    active, and the search goes on in the tangent space of the active ones, releasing one
//!    when its multiplier says the SCR rises into the interior. So an optimum on a boundary
//!    is found to the tolerance, not to the grid's spacing. Refinement only ascends, so the
//!    answer is never below a conventional set that the constraints allow.
//! 3. A filter wheel's fixed angles: every `N`-subset of its slots is scored (exact).
//!
//! The coarse spacing is much finer than the SCR's features, which vary on the scale of the
//! 45-degree period of `cos 4psi`. So the global maximum's basin holds a point among the
//! best. The tests check this against an exhaustive 1-degree grid for `N = 1..3`, against a
//! 0.1-degree grid on a binding separation, and against random multistarts for `N = 4..6`;
//! `tests/forecast_objective.rs` checks it with the forecast's objective over random cameras,
//! classes and constraints; `polarimeter bench planner` reports it each run.

use crate::scr::Contrast;
use crate::stokes::{log_condition_and_gradient, stokes_condition, MIN_CONDITION};
use crate::PlanError;
use std::f64::consts::PI;

/// Tuples scored by the coarse grid at most.
pub const GRID_BUDGET: usize = 20_000;
/// Grid points refined.
pub const REFINED_STARTS: usize = 12;
/// Channels allowed.
pub const MAX_CHANNELS: usize = 6;

/// What the set must respect.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Constraints {
    /// A rotator's travel `[lo, hi]`, radians, `0 <= hi - lo < pi`; `None` for a free rotator
    /// (any angle, 180-degree periodic).
    pub range_rad: Option<(f64, f64)>,
    /// Smallest separation between any two angles, radians, modulo pi (0: repeats allowed).
    pub min_separation_rad: f64,
    /// The stage's smallest step, radians (0: continuous); the answer is rounded to it.
    pub step_rad: f64,
    /// A filter wheel's fixed polarizer angles, radians: the set is the best `N`-subset.
    pub fixed_angles_rad: Option<Vec<f64>>,
    /// A Stokes set: the largest condition number of the ideal analyzer's measurement matrix
    /// ([`crate::stokes::stokes_condition`]; [`crate::stokes::STOKES_MAX_CONDITION`] for the
    /// rule of `plan --scene`), `>= sqrt 2`, 3 channels or more; `None`: any set.
    pub max_condition: Option<f64>,
}

/// The answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Optimum {
    /// The angles, radians, sorted, in `[0, pi)` (or in the range).
    pub angles_rad: Vec<f64>,
    /// Their SCR.
    pub scr: f64,
    /// SCR evaluations spent.
    pub evaluations: usize,
}

/// Circular distance modulo pi.
fn separation(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(PI);
    d.min(PI - d)
}

/// A Stokes bound is met to 1e-9 relative (rounding of a 3x3 eigenvalue problem; the
/// refinement lands on the bound to 1e-12).
const CONDITION_REL_TOL: f64 = 1e-9;

fn feasible(angles: &[f64], c: &Constraints) -> bool {
    if let Some(bound) = c.max_condition {
        if stokes_condition(angles) > bound * (1.0 + CONDITION_REL_TOL) {
            return false;
        }
    }
    if let Some((lo, hi)) = c.range_rad {
        if angles.iter().any(|&a| a < lo - 1e-12 || a > hi + 1e-12) {
            return false;
        }
    }
    if c.min_separation_rad > 0.0 {
        for i in 0..angles.len() {
            for j in i + 1..angles.len() {
                if separation(angles[i], angles[j]) < c.min_separation_rad - 1e-12 {
                    return false;
                }
            }
        }
    }
    true
}

/// `C(m + n - 1, n)`, saturating.
fn multisets(m: usize, n: usize) -> usize {
    let mut r: usize = 1;
    for k in 0..n {
        r = r.saturating_mul(m + k) / (k + 1);
    }
    r
}

/// Checks the constraints; errors name the field.
fn check(n: usize, c: &Constraints, tol_rad: f64) -> Result<(), PlanError> {
    if !(1..=MAX_CHANNELS).contains(&n) {
        return Err(PlanError::OutOfRange {
            field: "channels",
            value: n as f64,
            allowed: "1 to 6",
        });
    }
    if !(tol_rad.is_finite() && tol_rad > 0.0 && tol_rad <= 0.1) {
        return Err(PlanError::OutOfRange {
            field: "tolerance_deg",
            value: tol_rad.to_degrees(),
            allowed: "(0, 5.7] deg",
        });
    }
    if let Some((lo, hi)) = c.range_rad {
        if !(lo.is_finite() && hi.is_finite() && lo <= hi && hi - lo < PI) {
            return Err(PlanError::invalid(
                "angle_range_deg",
                format!(
                    "[{}, {}]: allowed lo <= hi, hi - lo < 180",
                    lo.to_degrees(),
                    hi.to_degrees()
                ),
            ));
        }
    }
    if !(c.min_separation_rad.is_finite() && (0.0..PI / 2.0).contains(&c.min_separation_rad)) {
        return Err(PlanError::OutOfRange {
            field: "min_separation_deg",
            value: c.min_separation_rad.to_degrees(),
            allowed: "[0, 90) deg",
        });
    }
    if c.min_separation_rad * n as f64 > PI + 1e-12 {
        return Err(PlanError::invalid(
            "min_separation_deg",
            format!(
                "{} deg between {n} angles does not fit in 180 deg",
                c.min_separation_rad.to_degrees()
            ),
        ));
    }
    if let Some(bound) = c.max_condition {
        if !(bound.is_finite() && bound >= MIN_CONDITION) {
            return Err(PlanError::OutOfRange {
                field: "max_condition",
                value: bound,
                allowed: "finite, >= sqrt 2 = 1.4142 (the smallest any set reaches)",
            });
        }
        if n < 3 {
            return Err(PlanError::invalid(
                "channels",
                format!(
                    "{n} channel(s) cannot form a Stokes set (max_condition = {bound}): allowed 3 \
                     to {MAX_CHANNELS}, a linear Stokes vector has 3 unknowns"
                ),
            ));
        }
    }
    if !(c.step_rad.is_finite() && (0.0..=0.2).contains(&c.step_rad)) {
        return Err(PlanError::OutOfRange {
            field: "step_deg",
            value: c.step_rad.to_degrees(),
            allowed: "[0, 11.5] deg",
        });
    }
    Ok(())
}

/// The SCR-optimal set of `n` angles under `constraints`, to `tol_rad` in each angle.
pub fn optimise(
    contrast: &Contrast,
    n: usize,
    constraints: &Constraints,
    tol_rad: f64,
) -> Result<Optimum, PlanError> {
    check(n, constraints, tol_rad)?;
    if let Some(fixed) = &constraints.fixed_angles_rad {
        return best_subset(contrast, n, fixed, constraints);
    }
    let (lo, span, periodic) = match constraints.range_rad {
        Some((lo, hi)) => (lo, hi - lo, false),
        None => (0.0, PI, true),
    };
    let mut best: Vec<(f64, Vec<f64>)> = Vec::new();
    let mut evaluations = 0usize;
    let sep = constraints.min_separation_rad;
    if sep > 0.0 && n > 1 {
        evaluations += separation_lattice(contrast, n, constraints, &mut best);
    } else {
        // The finest grid within the budget, at most 90 points (2 deg: the SCR's features are
        // on the 45-degree scale of cos 4psi, and the refinement does the rest).
        let mut m = 90usize;
        while m > 4 && multisets(m, n) > GRID_BUDGET {
            m -= 1;
        }
        let grid: Vec<f64> = (0..m)
            .map(|i| {
                if periodic {
                    lo + span * i as f64 / m as f64
                } else {
                    lo + span * i as f64 / (m - 1).max(1) as f64
                }
            })
            .collect();
        // Enumerate nondecreasing index tuples, keep the best of a few neighbourhoods.
        let radius_rad = 1.5 * span / m as f64;
        let mut idx = vec![0usize; n];
        let mut set = vec![0.0; n];
        loop {
            for (s, &i) in set.iter_mut().zip(&idx) {
                *s = grid[i];
            }
            if feasible(&set, constraints) {
                evaluations += 1;
                keep(&mut best, contrast.scr(&set), &set, periodic, radius_rad);
            }
            if !next_nondecreasing(&mut idx, m) {
                break;
            }
        }
    }
    // The widest equally spaced set: feasible whenever any set is (the grid can miss a thin
    // feasible region, e.g. a separation close to range / (N - 1)).
    let spread = if n > 1 {
        let room = if periodic {
            PI
        } else {
            span.min(PI - constraints.min_separation_rad)
        };
        let g = if periodic {
            PI / n as f64
        } else {
            room / (n - 1) as f64
        };
        (0..n).map(|i| lo + g * i as f64).collect()
    } else {
        vec![lo + 0.5 * span]
    };
    if feasible(&spread, constraints) {
        best.push((contrast.scr(&spread), spread));
        evaluations += 1;
    }
    if best.is_empty() {
        if let Some(bound) = constraints.max_condition {
            return Err(PlanError::invalid(
                "max_condition",
                format!(
                    "no set of {n} angles with a condition number <= {bound} fits the angle \
                     range (angle_range_deg) and the separation (min_separation_deg = {} deg): \
                     widen the range, lower the separation or raise the bound",
                    constraints.min_separation_rad.to_degrees()
                ),
            ));
        }
        return Err(PlanError::invalid(
            "min_separation_deg",
            format!(
                "{} deg between {n} angles does not fit in the angle range (angle_range_deg): \
                 no analyzer set satisfies both",
                constraints.min_separation_rad.to_degrees()
            ),
        ));
    }
    // The conventional sets of this N that the constraints allow start a refinement too, so
    // the answer is never below them (the refinement only ascends).
    for (_, deg) in CONVENTIONAL {
        let set: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
        if set.len() == n && feasible(&set, constraints) {
            best.push((contrast.scr(&set), set));
            evaluations += 1;
        }
    }
    let mut winner = (f64::NEG_INFINITY, Vec::new());
    for (_, start) in best {
        let (scr, angles, evals) = refine(contrast, start, constraints, tol_rad);
        evaluations += evals;
        if scr > winner.0 {
            winner = (scr, angles);
        }
    }
    let (mut scr, mut angles) = winner;
    if constraints.step_rad > 0.0 {
        let step = constraints.step_rad;
        let rounded: Vec<f64> = angles.iter().map(|a| (a / step).round() * step).collect();
        if feasible(&rounded, constraints) {
            scr = contrast.scr(&rounded);
            evaluations += 1;
            angles = rounded;
            // Rounding can lose a little: climb on the stage's lattice, one step of one angle
            // at a time, while that gains.
            let mut improved = true;
            while improved {
                improved = false;
                for k in 0..n {
                    for dir in [-1.0, 1.0] {
                        let mut trial = angles.clone();
                        trial[k] = ((trial[k] / step).round() + dir) * step;
                        if feasible(&trial, constraints) {
                            let f = contrast.scr(&trial);
                            evaluations += 1;
                            if f > scr {
                                (scr, angles, improved) = (f, trial, true);
                            }
                        }
                    }
                }
            }
        }
    }
    // The refinement's projection onto active constraints can end a rounding error (1e-12
    // rad) outside them: the answer is settled inside, and its SCR is the one of those angles.
    if settle(&mut angles, constraints) {
        scr = contrast.scr(&angles);
        evaluations += 1;
    }
    Ok(Optimum {
        angles_rad: canonical(angles, periodic),
        scr,
        evaluations,
    })
}

/// Moves a refined set onto its constraints where it ends a rounding error outside them:
/// sorted (a free rotator's angles modulo pi first), each gap to at least the separation
/// (pushing later angles up), a free rotator's wrap-around gap, then the range ends (pushing
/// earlier angles down from the top, then clamping). Returns whether anything moved.
fn settle(angles: &mut [f64], c: &Constraints) -> bool {
    let before = angles.to_vec();
    if c.range_rad.is_none() {
        // Directions: the gaps are those of the angles modulo pi, in that order.
        angles.iter_mut().for_each(|a| *a = a.rem_euclid(PI));
    }
    angles.sort_by(f64::total_cmp);
    let s = c.min_separation_rad;
    for i in 1..angles.len() {
        if angles[i] < angles[i - 1] + s {
            angles[i] = angles[i - 1] + s;
        }
    }
    let n = angles.len();
    if c.range_rad.is_none() && n > 1 && s > 0.0 {
        // The wrap-around gap, when a rounding error short of the separation.
        let wrap = angles[0] + PI - angles[n - 1];
        if wrap < s && s - wrap < 1e-9 {
            angles[n - 1] = angles[0] + PI - s;
        }
    }
    if let Some((lo, hi)) = c.range_rad {
        if n > 0 && angles[n - 1] > hi {
            angles[n - 1] = hi;
            for i in (0..n - 1).rev() {
                if angles[i] > angles[i + 1] - s {
                    angles[i] = angles[i + 1] - s;
                }
            }
        }
        angles.iter_mut().for_each(|a| *a = a.clamp(lo, hi));
    }
    angles.iter().zip(&before).any(|(a, b)| a != b)
}

/// Keeps `set` among the [`REFINED_STARTS`] best sets of distinct neighbourhoods: a set whose
/// angles (modulo pi and order) are all within `radius_rad` of a kept set's is that set's
/// neighbour, and only the better of the two is kept. So the starts spread over the SCR's
/// basins instead of crowding one: with a radius of a grid step and a half, the grid points
/// around one local optimum (which the refinement would all climb to the same answer) count
/// once, and a second basin's best point (say all four angles at one angle, where the best
/// set repeats one angle) gets its own start.
fn keep(best: &mut Vec<(f64, Vec<f64>)>, scr: f64, set: &[f64], periodic: bool, radius_rad: f64) {
    if best.len() >= REFINED_STARTS && scr <= best[best.len() - 1].0 {
        return;
    }
    let key = canonical(set.to_vec(), periodic);
    let near = |other: &Vec<f64>| {
        let o = canonical(other.clone(), periodic);
        o.iter().zip(&key).all(|(a, b)| (a - b).abs() <= radius_rad)
    };
    if let Some(i) = best.iter().position(|(_, other)| near(other)) {
        if scr <= best[i].0 {
            return;
        }
        best.remove(i);
    }
    best.push((scr, set.to_vec()));
    best.sort_by(|a, b| b.0.total_cmp(&a.0));
    best.truncate(REFINED_STARTS);
}

/// The coarse search with a separation `s > 0`: a lattice aligned with the constraints, so
/// that sets on the boundary (two angles exactly `s` apart, an angle at an end of the range)
/// are among its points. Every gap between neighbours is `s + h k` with `k >= 0`:
///
/// * a free rotator: the first angle on a grid over `[0, pi)`, then the `N` gaps (the last
///   one wrapping around) share the slack `pi - N s` in steps `h`;
/// * a range `[lo, hi]`: the distance from `lo` to the first angle, the `N - 1` gaps and the
///   distance from the last angle to `hi` share `hi - lo - (N - 1) s` in steps `h`.
///
/// `h` is the finest that keeps the points within [`GRID_BUDGET`]. Returns the evaluations.
fn separation_lattice(
    contrast: &Contrast,
    n: usize,
    constraints: &Constraints,
    best: &mut Vec<(f64, Vec<f64>)>,
) -> usize {
    let s = constraints.min_separation_rad;
    let (lo, periodic, free) = match constraints.range_rad {
        None => (0.0, true, (PI - n as f64 * s).max(0.0)),
        Some((lo, hi)) => (lo, false, (hi - lo - (n - 1) as f64 * s).max(0.0)),
    };
    // Slack parts: a free rotator's N gaps; a range's N - 1 gaps and its two ends.
    let parts = if periodic { n } else { n + 1 };
    let starts = |k: usize| -> usize {
        if !periodic {
            1
        } else if free <= 0.0 || k == 0 {
            90
        } else {
            ((PI * k as f64 / free).ceil() as usize).clamp(4, 90)
        }
    };
    let mut k = if free > 0.0 { 90usize } else { 0 };
    while k > 1 && starts(k).saturating_mul(multisets(k + 1, parts - 1)) > GRID_BUDGET {
        k -= 1;
    }
    let h = if k > 0 { free / k as f64 } else { 0.0 };
    let m0 = starts(k);
    let mut evaluations = 0;
    let mut set = vec![0.0; n];
    for i0 in 0..m0 {
        let x0 = if periodic {
            PI * i0 as f64 / m0 as f64
        } else {
            lo
        };
        // Bars c_1 <= .. <= c_{parts-1} in 0..=k: the parts are their differences.
        let mut bars = vec![0usize; parts - 1];
        loop {
            let part = |j: usize| -> usize {
                let hi = if j < bars.len() { bars[j] } else { k };
                let lo = if j == 0 { 0 } else { bars[j - 1] };
                hi - lo
            };
            // A range's first part is the distance from lo; a free rotator's parts are gaps.
            let (mut x, first_gap) = if periodic {
                (x0, 0)
            } else {
                (lo + h * part(0) as f64, 1)
            };
            set[0] = x;
            for (j, v) in set.iter_mut().enumerate().skip(1) {
                x += s + h * part(first_gap + j - 1) as f64;
                *v = x;
            }
            if feasible(&set, constraints) {
                evaluations += 1;
                keep(best, contrast.scr(&set), &set, periodic, 1e-9);
            }
            if !next_nondecreasing(&mut bars, k + 1) {
                break;
            }
        }
    }
    evaluations
}

/// Advances `idx` to the next nondecreasing tuple of indices below `m` (lexicographic order);
/// false after the last.
fn next_nondecreasing(idx: &mut [usize], m: usize) -> bool {
    let mut k = idx.len();
    while k > 0 {
        k -= 1;
        if idx[k] + 1 < m {
            idx[k] += 1;
            let v = idx[k];
            for j in idx.iter_mut().skip(k + 1) {
                *j = v;
            }
            return true;
        }
    }
    false
}

/// Sorted, and in `[0, pi)` when periodic.
fn canonical(mut angles: Vec<f64>, periodic: bool) -> Vec<f64> {
    if periodic {
        for a in angles.iter_mut() {
            *a = a.rem_euclid(PI);
            if *a >= PI {
                *a = 0.0;
            }
        }
    }
    angles.sort_by(f64::total_cmp);
    angles
}

/// The linear constraints of a sorted tuple `x_0 <= .. <= x_{n-1}`: `a_j . x >= b_j`.
///
/// * separation (or order, for a range without one): `x_{i+1} - x_i >= s`;
/// * with a separation: the wrap-around gap `x_0 + pi - x_{n-1} >= s` (angles are directions,
///   modulo pi, in a range too);
/// * a range: `x_0 >= lo` and `x_{n-1} <= hi`.
///
/// A free rotator without a separation has none (the SCR is symmetric in the angles, so the
/// tuple need not stay sorted).
fn linear_constraints(n: usize, c: &Constraints) -> Vec<(Vec<f64>, f64)> {
    let mut out = Vec::new();
    let periodic = c.range_rad.is_none();
    let s = c.min_separation_rad;
    if s > 0.0 || !periodic {
        for i in 0..n.saturating_sub(1) {
            let mut a = vec![0.0; n];
            a[i + 1] = 1.0;
            a[i] = -1.0;
            out.push((a, s));
        }
    }
    // Directions modulo pi: the first and the last angle are also neighbours, in a range too.
    if s > 0.0 && n >= 2 {
        let mut a = vec![0.0; n];
        a[0] = 1.0;
        a[n - 1] = -1.0;
        out.push((a, s - PI));
    }
    if let Some((lo, hi)) = c.range_rad {
        let mut a = vec![0.0; n];
        a[0] = 1.0;
        out.push((a, lo));
        let mut a = vec![0.0; n];
        a[n - 1] = -1.0;
        out.push((a, -hi));
    }
    out
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The tangent space of the active constraints: an orthonormal basis `Z` (`n x r`) of the
/// directions that keep them equalities, and the least-squares multipliers `mu` of
/// `g + N mu = 0` (`N` the active normals), one per active constraint.
fn tangent(
    n: usize,
    normals: &[&[f64]],
    g: &[f64],
) -> (nalgebra::DMatrix<f64>, nalgebra::DVector<f64>) {
    use nalgebra::{DMatrix, DVector};
    let m = normals.len();
    if m == 0 {
        return (DMatrix::identity(n, n), DVector::zeros(0));
    }
    let nn = DMatrix::from_fn(n, m, |i, j| normals[j][i]);
    let gram = nn.transpose() * &nn;
    // Dependent normals (all gaps of a free rotator at the separation, n s = pi): the
    // pseudo-inverse gives the least-squares multipliers and the right projector.
    let pinv = gram
        .clone()
        .pseudo_inverse(1e-10 * gram.amax().max(1.0))
        .unwrap_or_else(|_| DMatrix::zeros(m, m));
    let gv = DVector::from_column_slice(g);
    let mu = -(&pinv * (nn.transpose() * &gv));
    let projector = DMatrix::identity(n, n) - &nn * &pinv * nn.transpose();
    let eig = projector.symmetric_eigen();
    let cols: Vec<DVector<f64>> = (0..n)
        .filter(|&k| eig.eigenvalues[k] > 0.5)
        .map(|k| eig.eigenvectors.column(k).into_owned())
        .collect();
    let z = if cols.is_empty() {
        DMatrix::zeros(n, 0)
    } else {
        DMatrix::from_columns(&cols)
    };
    (z, mu)
}

/// Constrained ascent from a feasible `start`, an active-set method: quasi-Newton steps in the
/// tangent space of the active constraints. The linear ones ([`linear_constraints`]) and, for a
/// Stokes set, the condition bound `ln bound - ln kappa(x) >= 0` (nonlinear: its normal is its
/// gradient at the current point, and a step that leaves it, or that moves along it while it is
/// active, is brought back onto `kappa = bound` by Newton steps along its gradient within the
/// active linear constraints). A step is cut at the first constraint it meets, which becomes
/// active; an active constraint whose multiplier says that the SCR rises into the interior is
/// released. The curvature model is a full-space BFGS approximation of the Lagrangian's
/// Hessian (Powell-damped, so it stays positive definite), reduced to the tangent space at each
/// step (so it follows the boundary's curvature), and restarted when the active set changes.
/// It stops at a Karush-Kuhn-Tucker point (the projected gradient below 1e-10 of the SCR per
/// radian, every multiplier `>= 0`) or when a step is under `tol_rad / 100`. Returns the SCR,
/// the angles and the evaluations spent.
///
/// On a boundary (two angles exactly `min_separation` apart, an angle at the end of the range,
/// a condition number at its bound) the optimum is found as accurately as inside: the search
/// slides along the boundary rather than stopping where it met it.
fn refine(
    contrast: &Contrast,
    start: Vec<f64>,
    constraints: &Constraints,
    tol_rad: f64,
) -> (f64, Vec<f64>, usize) {
    use nalgebra::{DMatrix, DVector};
    let n = start.len();
    let cons = linear_constraints(n, constraints);
    let nl = cons.len();
    let log_bound = constraints.max_condition.map(f64::ln);
    let m_all = nl + usize::from(log_bound.is_some());
    let mut x = start;
    if !cons.is_empty() {
        x.sort_by(f64::total_cmp);
    }
    // The condition bound's slack and normal (gradient).
    let bound_slack = |x: &[f64], normal: &mut [f64]| -> f64 {
        let lb = log_bound.unwrap_or(f64::INFINITY);
        let lc = log_condition_and_gradient(x, normal);
        normal.iter_mut().for_each(|v| *v = -*v);
        lb - lc
    };
    let mut scratch = vec![0.0; n];
    let mut slack = |x: &[f64], j: usize| -> f64 {
        if j < nl {
            dot(&cons[j].0, x) - cons[j].1
        } else {
            bound_slack(x, &mut scratch)
        }
    };
    let mut active: Vec<bool> = (0..m_all).map(|j| slack(&x, j) <= 1e-10).collect();
    let linear_ok = |y: &[f64]| (0..nl).all(|j| dot(&cons[j].0, y) - cons[j].1 >= -1e-12);
    // Back onto the condition bound (`kappa = bound`), moving within the active linear
    // constraints: Newton on the slack along its projected gradient.
    let restore = |mut y: Vec<f64>, z_lin: &DMatrix<f64>| -> Option<Vec<f64>> {
        let mut normal = vec![0.0; n];
        for _ in 0..30 {
            let s = bound_slack(&y, &mut normal);
            if !s.is_finite() {
                return None;
            }
            if s.abs() <= 1e-13 {
                return Some(y);
            }
            let p = z_lin * (z_lin.transpose() * DVector::from_column_slice(&normal));
            let pp = p.norm_squared();
            if pp < 1e-300 {
                return None;
            }
            for (v, d) in y.iter_mut().zip(p.iter()) {
                *v -= s / pp * d;
            }
        }
        (bound_slack(&y, &mut normal) >= -1e-10).then_some(y)
    };
    let mut g = vec![0.0; n];
    let mut f = contrast.scr_and_gradient(&x, Some(&mut g));
    let mut evals = 1;
    let mut g_new = vec![0.0; n];
    // The Hessian model of -SCR (and of the bound's curvature), full space.
    let mut b: Option<DMatrix<f64>> = None;
    let mut bound_normal = vec![0.0; n];
    let mut trial_normal = vec![0.0; n];
    for _ in 0..400 {
        // The tangent space, releasing constraints whose multiplier is negative.
        let (z, gz, mu_bound) = loop {
            let idx: Vec<usize> = (0..m_all).filter(|&j| active[j]).collect();
            if log_bound.is_some() {
                bound_slack(&x, &mut bound_normal);
            }
            let normals: Vec<&[f64]> = idx
                .iter()
                .map(|&j| {
                    if j < nl {
                        cons[j].0.as_slice()
                    } else {
                        bound_normal.as_slice()
                    }
                })
                .collect();
            let (z, mu) = tangent(n, &normals, &g);
            let gnorm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
            let worst = (0..idx.len())
                .filter(|&k| mu[k] < -1e-12 * gnorm.max(1e-300))
                .min_by(|&a, &b| mu[a].total_cmp(&mu[b]));
            match worst {
                Some(k) => {
                    active[idx[k]] = false;
                    b = None;
                }
                None => {
                    let gz = z.transpose() * DVector::from_column_slice(&g);
                    let mu_bound = idx.iter().position(|&j| j == nl).map_or(0.0, |k| mu[k]);
                    break (z, gz, mu_bound);
                }
            }
        };
        let r = z.ncols();
        if r == 0 || gz.norm() <= 1e-10 * f.abs().max(1e-300) {
            break;
        }
        // Scaled so that the first step moves about 0.05 rad.
        let bm = b.get_or_insert_with(|| DMatrix::identity(n, n) * (gz.norm() / 0.05));
        let reduced = z.transpose() * &*bm * &z;
        let pz = match reduced.clone().cholesky() {
            Some(ch) => ch.solve(&gz),
            None => {
                *bm = DMatrix::identity(n, n) * (gz.norm() / 0.05);
                &gz * (0.05 / gz.norm())
            }
        };
        let slope = pz.dot(&gz);
        let p: Vec<f64> = (&z * &pz).iter().copied().collect();
        let pnorm = p.iter().map(|v| v.abs()).fold(0.0, f64::max);
        // The longest step that stays feasible (to first order for the bound), and the
        // constraint that blocks it.
        let mut t_max = f64::INFINITY;
        let mut blocking = None;
        for j in 0..m_all {
            if active[j] {
                continue;
            }
            let (ap, sl) = if j < nl {
                (dot(&cons[j].0, &p), slack(&x, j))
            } else {
                let s = bound_slack(&x, &mut bound_normal);
                (dot(&bound_normal, &p), s)
            };
            if ap < -1e-12 * pnorm {
                let t = sl.max(0.0) / -ap;
                if t < t_max {
                    t_max = t;
                    blocking = Some(j);
                }
            }
        }
        // The active linear constraints' tangent space, for the bound's restoration.
        let z_lin = if log_bound.is_some() {
            let normals: Vec<&[f64]> = (0..nl)
                .filter(|&j| active[j])
                .map(|j| cons[j].0.as_slice())
                .collect();
            tangent(n, &normals, &g).0
        } else {
            DMatrix::zeros(0, 0)
        };
        let mut t = t_max.min(1.0);
        let mut accepted = None;
        while t > 1e-14 {
            let mut trial: Vec<f64> = x.iter().zip(&p).map(|(a, b)| a + t * b).collect();
            let mut onto_bound = false;
            if log_bound.is_some()
                && (active.get(nl).copied().unwrap_or(false)
                    || bound_slack(&trial, &mut trial_normal) < 0.0)
            {
                match restore(trial, &z_lin) {
                    Some(y) => {
                        trial = y;
                        onto_bound = true;
                    }
                    None => {
                        t *= 0.5;
                        continue;
                    }
                }
            }
            if !linear_ok(&trial) {
                t *= 0.5;
                continue;
            }
            let ft = contrast.scr_and_gradient(&trial, Some(&mut g_new));
            evals += 1;
            if ft >= f + 1e-4 * t * slope {
                accepted = Some((trial, ft, t, onto_bound));
                break;
            }
            t *= 0.5;
        }
        let Some((x_new, f_new, t_used, onto_bound)) = accepted else {
            if let (Some(j), true) = (blocking, t_max <= 1e-14) {
                // Already on the blocking constraint: make it active and go on along it.
                active[j] = true;
                b = None;
                continue;
            }
            break;
        };
        let s: Vec<f64> = x_new.iter().zip(&x).map(|(a, b)| a - b).collect();
        let step = s.iter().map(|v| v.abs()).fold(0.0, f64::max);
        // The Lagrangian's gradient change (the bound's normal changes along the boundary).
        let mut y: Vec<f64> = g_new.iter().zip(&g).map(|(a, b)| -(a - b)).collect();
        if mu_bound != 0.0 {
            let mut before = vec![0.0; n];
            let mut after = vec![0.0; n];
            bound_slack(&x, &mut before);
            bound_slack(&x_new, &mut after);
            for k in 0..n {
                y[k] -= mu_bound * (after[k] - before[k]);
            }
        }
        x = x_new;
        f = f_new;
        g.copy_from_slice(&g_new);
        // A new active constraint restarts the curvature model (its scale along the new
        // tangent space is unknown), as when one is released.
        let mut changed = false;
        if onto_bound && !active[nl] {
            active[nl] = true;
            changed = true;
        }
        if let (Some(j), true) = (blocking, t_used >= t_max) {
            changed |= !active[j];
            active[j] = true;
        }
        if changed {
            b = None;
        }
        if let Some(bm) = b.as_mut() {
            // Powell-damped BFGS update of the Hessian model of -L.
            let sv = DVector::from_column_slice(&s);
            let mut yv = DVector::from_column_slice(&y);
            let bs = &*bm * &sv;
            let sbs = sv.dot(&bs);
            if sbs > 1e-300 {
                let sy = sv.dot(&yv);
                if sy < 0.2 * sbs {
                    let theta = 0.8 * sbs / (sbs - sy);
                    yv = &yv * theta + &bs * (1.0 - theta);
                }
                let sy = sv.dot(&yv);
                if sy > 1e-300 {
                    *bm += &yv * yv.transpose() / sy - &bs * bs.transpose() / sbs;
                }
            }
        }
        if step < tol_rad * 1e-2 && blocking.is_none_or(|_| t_used < t_max) {
            break;
        }
    }
    (f, x, evals)
}

/// The best `n`-subset of a wheel's fixed angles (every subset scored).
fn best_subset(
    contrast: &Contrast,
    n: usize,
    fixed: &[f64],
    constraints: &Constraints,
) -> Result<Optimum, PlanError> {
    if fixed.len() < n || fixed.len() > 24 || fixed.iter().any(|a| !a.is_finite()) {
        return Err(PlanError::invalid(
            "fixed_angles_deg",
            format!(
                "{} finite angles needed for {n} channels (at most 24 slots), got {}",
                n,
                fixed.len()
            ),
        ));
    }
    let mut pick: Vec<usize> = (0..n).collect();
    let mut best: Option<(f64, Vec<f64>)> = None;
    let mut evaluations = 0;
    loop {
        let set: Vec<f64> = pick.iter().map(|&i| fixed[i]).collect();
        if feasible(&set, constraints) {
            let scr = contrast.scr(&set);
            evaluations += 1;
            if best.as_ref().is_none_or(|(b, _)| scr > *b) {
                best = Some((scr, set));
            }
        }
        // Next combination.
        let mut k = n;
        let mut advanced = false;
        while k > 0 {
            k -= 1;
            if pick[k] < fixed.len() - n + k {
                pick[k] += 1;
                for j in k + 1..n {
                    pick[j] = pick[j - 1] + 1;
                }
                advanced = true;
                break;
            }
        }
        if !advanced {
            break;
        }
    }
    let (scr, angles) = best.ok_or_else(|| {
        PlanError::invalid(
            "fixed_angles_deg",
            "no subset satisfies the separation, range and condition (max_condition) constraints",
        )
    })?;
    Ok(Optimum {
        angles_rad: canonical(angles, false),
        scr,
        evaluations,
    })
}

/// An exhaustive search of sorted tuples on a grid of `step_rad` over `[0, pi)` (the baseline
/// `polarimeter bench planner` compares against).
pub fn grid_search(contrast: &Contrast, n: usize, step_rad: f64) -> Optimum {
    let m = ((PI / step_rad).round() as usize).max(1);
    let grid: Vec<f64> = (0..m).map(|i| i as f64 * PI / m as f64).collect();
    let mut idx = vec![0usize; n.max(1)];
    let mut set = vec![0.0; idx.len()];
    let mut best = (f64::NEG_INFINITY, Vec::new());
    let mut evaluations = 0;
    loop {
        for (s, &i) in set.iter_mut().zip(&idx) {
            *s = grid[i];
        }
        let scr = contrast.scr(&set);
        evaluations += 1;
        if scr > best.0 {
            best = (scr, set.clone());
        }
        if !next_nondecreasing(&mut idx, m) {
            break;
        }
    }
    Optimum {
        angles_rad: best.1,
        scr: best.0,
        evaluations,
    }
}

/// The conventional sets, degrees: Pickering 0/45/90, 0/60/120, and the modified Pickering
/// 0/45/90/135.
pub const CONVENTIONAL: [(&str, &[f64]); 3] = [
    ("0/45/90", &[0.0, 45.0, 90.0]),
    ("0/60/120", &[0.0, 60.0, 120.0]),
    ("0/45/90/135", &[0.0, 45.0, 90.0, 135.0]),
];

/// The conventional sets the planner is compared with ([`CONVENTIONAL`]), with their SCRs.
pub fn conventional(contrast: &Contrast) -> Vec<(&'static str, f64)> {
    CONVENTIONAL
        .iter()
        .map(|(name, deg)| {
            let rad: Vec<f64> = deg.iter().map(|d| d.to_radians()).collect();
            (*name, contrast.scr(&rad))
        })
        .collect()
}

/// Whether `angles_rad` satisfies `constraints` (range, separation modulo pi; a wheel's set
/// must also be a subset of its slots), to 1e-12 rad.
pub fn allowed(angles_rad: &[f64], constraints: &Constraints) -> bool {
    if let Some(slots) = &constraints.fixed_angles_rad {
        let on_slot = |a: &f64| slots.iter().any(|s| separation(*a, *s) < 1e-9);
        if !angles_rad.iter().all(on_slot) {
            return false;
        }
    }
    feasible(angles_rad, constraints)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Vector3};

    /// A contrast where the angles matter: strongly correlated clutter, noise comparable to it.
    fn contrast(seed: u64) -> Contrast {
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut r = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let l = Matrix3::new(r(), 0.0, 0.0, r(), r(), 0.0, r(), r(), r()) * 3.0;
        let sigma = l * l.transpose() + Matrix3::identity() * 0.05;
        let d = Vector3::new(r(), r(), r()) * 2.0;
        Contrast::new(d, sigma, 0.5 + r().abs()).expect("valid")
    }

    /// For N = 1, 2, 3 and several random problems, the optimiser's SCR is at least the best
    /// of an exhaustive 1-degree grid (less 1e-9 relative for rounding), and the optimum is
    /// stationary (gradient below 1e-6 of the SCR per radian) when unconstrained.
    #[test]
    fn beats_the_one_degree_grid() {
        for seed in 1..=6 {
            let c = contrast(seed);
            for n in 1..=3 {
                let opt = optimise(&c, n, &Constraints::default(), 1e-4f64.to_radians())
                    .expect("optimum");
                let grid = grid_search(&c, n, 1f64.to_radians());
                assert!(
                    opt.scr >= grid.scr * (1.0 - 1e-9),
                    "seed {seed} n {n}: {} < grid {}",
                    opt.scr,
                    grid.scr
                );
                let mut g = vec![0.0; n];
                c.scr_and_gradient(&opt.angles_rad, Some(&mut g));
                let gmax = g.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                assert!(
                    gmax <= 1e-6 * opt.scr.max(1e-12),
                    "seed {seed} n {n}: grad {g:?}"
                );
            }
        }
    }

    /// For N = 4..6, no one of 300 random starts refined locally does better (to 1e-7
    /// relative).
    #[test]
    fn global_against_random_multistart() {
        for seed in [3u64, 8] {
            let c = contrast(seed);
            for n in 4..=6 {
                let opt = optimise(&c, n, &Constraints::default(), 1e-3f64.to_radians())
                    .expect("optimum");
                let mut state = seed;
                for _ in 0..300 {
                    let start: Vec<f64> = (0..n)
                        .map(|_| {
                            state = state
                                .wrapping_mul(6364136223846793005)
                                .wrapping_add(1442695040888963407);
                            (state >> 11) as f64 / (1u64 << 53) as f64 * PI
                        })
                        .collect();
                    let (f, _, _) = refine(&c, start, &Constraints::default(), 1e-6);
                    assert!(
                        f <= opt.scr * (1.0 + 1e-7),
                        "seed {seed} n {n}: {f} > {}",
                        opt.scr
                    );
                }
            }
        }
    }

    /// Constraints hold: the range, the separation, the stage step (angles on its grid), and a
    /// wheel's best subset is the best of all subsets (checked by brute force over 3 of 6).
    #[test]
    fn constraints_are_respected() {
        let c = contrast(4);
        let range = (10f64.to_radians(), 100f64.to_radians());
        let cons = Constraints {
            range_rad: Some(range),
            min_separation_rad: 20f64.to_radians(),
            step_rad: 0.01f64.to_radians(),
            fixed_angles_rad: None,
            max_condition: None,
        };
        let opt = optimise(&c, 3, &cons, 1e-4).expect("optimum");
        assert!(feasible(&opt.angles_rad, &cons), "{:?}", opt.angles_rad);
        for a in &opt.angles_rad {
            let k = a / cons.step_rad;
            assert!((k - k.round()).abs() < 1e-6, "{a} not on the step grid");
        }
        let slots: Vec<f64> = [0.0f64, 30.0, 60.0, 90.0, 120.0, 150.0]
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let wheel = Constraints {
            fixed_angles_rad: Some(slots.clone()),
            ..Constraints::default()
        };
        let opt = optimise(&c, 3, &wheel, 1e-4).expect("subset");
        assert_eq!(opt.evaluations, 20, "C(6, 3) subsets");
        let mut brute = f64::NEG_INFINITY;
        for i in 0..6 {
            for j in i + 1..6 {
                for k in j + 1..6 {
                    brute = brute.max(c.scr(&[slots[i], slots[j], slots[k]]));
                }
            }
        }
        assert_eq!(opt.scr, brute);
    }

    /// On a boundary the optimum is found to the tolerance, not to the coarse grid: with a
    /// separation wider than the unconstrained optimum's, two channels end exactly the
    /// separation apart (to 1e-9 rad), and no point of an exhaustive 0.1-degree grid of the
    /// allowed pairs does better (to 1e-9 relative: the refinement stops within 1e-6 rad of
    /// the constrained optimum, where the SCR along the boundary is flat to second order).
    #[test]
    fn boundary_optimum_to_the_tolerance() {
        let mut checked = 0;
        for seed in 1..=6 {
            let c = contrast(seed);
            let free = optimise(&c, 2, &Constraints::default(), 1e-4).expect("optimum");
            let gap = separation(free.angles_rad[0], free.angles_rad[1]);
            // A separation the free optimum breaks, so that it binds.
            let sep = (gap + 0.3).min(1.4);
            if sep <= gap {
                continue;
            }
            let cons = Constraints {
                min_separation_rad: sep,
                ..Constraints::default()
            };
            let opt = optimise(&c, 2, &cons, 1e-4).expect("optimum");
            let got = separation(opt.angles_rad[0], opt.angles_rad[1]);
            let m = 1800;
            let mut best = f64::NEG_INFINITY;
            for i in 0..m {
                for j in i..m {
                    let set = [PI * i as f64 / m as f64, PI * j as f64 / m as f64];
                    if feasible(&set, &cons) {
                        best = best.max(c.scr(&set));
                    }
                }
            }
            assert!(
                opt.scr >= best * (1.0 - 1e-9),
                "seed {seed}: {} < grid {best}",
                opt.scr
            );
            if (got - sep).abs() < 1e-9 {
                checked += 1;
            }
        }
        assert!(checked >= 3, "the separation bound only {checked} times");
    }

    /// A Stokes bound on 4..6 channels: the answer keeps the ideal condition number within
    /// the bound, may place angles closer than 30 deg (the rule it replaces), and no feasible
    /// point of 400 random feasible starts refined under the same constraints, nor any
    /// feasible point of a 9-degree exhaustive grid, does better (to 1e-7 relative: the
    /// refinement stops within 1e-5 rad of a KKT point on the curved boundary, where the SCR
    /// is flat to second order). Where the bound binds, the answer sits on it (to 1e-6
    /// relative).
    #[test]
    fn stokes_bound_for_four_to_six_channels() {
        use crate::stokes::{stokes_condition, STOKES_MAX_CONDITION};
        let cons = Constraints {
            max_condition: Some(STOKES_MAX_CONDITION),
            ..Constraints::default()
        };
        let mut closer = 0;
        let mut binding = 0;
        for seed in [2u64, 5, 9] {
            let c = contrast(seed);
            for n in 4..=6 {
                let opt = optimise(&c, n, &cons, 1e-3f64.to_radians()).expect("optimum");
                let k = stokes_condition(&opt.angles_rad);
                assert!(k <= STOKES_MAX_CONDITION * (1.0 + 1e-9), "n {n}: {k}");
                if (k / STOKES_MAX_CONDITION - 1.0).abs() < 1e-6 {
                    binding += 1;
                }
                let min_gap = (0..n)
                    .flat_map(|i| (i + 1..n).map(move |j| (i, j)))
                    .map(|(i, j)| separation(opt.angles_rad[i], opt.angles_rad[j]))
                    .fold(PI, f64::min);
                if min_gap < 30f64.to_radians() - 1e-9 {
                    closer += 1;
                }
                let mut state = seed * 7 + n as u64;
                let mut tried = 0;
                while tried < 400 {
                    let start: Vec<f64> = (0..n)
                        .map(|_| {
                            state = state
                                .wrapping_mul(6364136223846793005)
                                .wrapping_add(1442695040888963407);
                            (state >> 11) as f64 / (1u64 << 53) as f64 * PI
                        })
                        .collect();
                    if !feasible(&start, &cons) {
                        continue;
                    }
                    tried += 1;
                    let (f, x, _) = refine(&c, start, &cons, 1e-6);
                    assert!(feasible(&x, &cons), "refinement left the bound: {x:?}");
                    assert!(
                        f <= opt.scr * (1.0 + 1e-7),
                        "seed {seed} n {n}: {f} > {}",
                        opt.scr
                    );
                }
                let m = 20;
                let mut idx = vec![0usize; n];
                let mut set = vec![0.0; n];
                loop {
                    for (s, &i) in set.iter_mut().zip(&idx) {
                        *s = PI * i as f64 / m as f64;
                    }
                    if feasible(&set, &cons) {
                        assert!(c.scr(&set) <= opt.scr * (1.0 + 1e-7), "grid {set:?}");
                    }
                    if !next_nondecreasing(&mut idx, m) {
                        break;
                    }
                }
            }
        }
        assert!(
            closer >= 3,
            "only {closer} answers use angles closer than 30 deg"
        );
        assert!(binding >= 3, "the bound binds only {binding} times");
    }

    /// Impossible or malformed requests are refused naming the field.
    #[test]
    fn bad_requests() {
        let c = contrast(1);
        let e = optimise(&c, 7, &Constraints::default(), 1e-4).expect_err("channels");
        assert!(e.to_string().contains("channels"), "{e}");
        let tight = Constraints {
            min_separation_rad: 70f64.to_radians(),
            ..Constraints::default()
        };
        let e = optimise(&c, 3, &tight, 1e-4).expect_err("separation");
        assert!(e.to_string().contains("min_separation_deg"), "{e}");
        let wheel = Constraints {
            fixed_angles_rad: Some(vec![0.0, 1.0]),
            ..Constraints::default()
        };
        let e = optimise(&c, 3, &wheel, 1e-4).expect_err("slots");
        assert!(e.to_string().contains("fixed_angles_deg"), "{e}");
        let stokes = |bound: f64| Constraints {
            max_condition: Some(bound),
            ..Constraints::default()
        };
        let e = optimise(&c, 2, &stokes(6.21), 1e-4).expect_err("two channels");
        assert!(e.to_string().contains("channels"), "{e}");
        let e = optimise(&c, 3, &stokes(1.2), 1e-4).expect_err("below sqrt 2");
        assert!(e.to_string().contains("max_condition"), "{e}");
        // 3 angles within 40 deg cannot see S1 and S2 evenly: no Stokes set fits.
        let narrow = Constraints {
            range_rad: Some((0.0, 40f64.to_radians())),
            ..stokes(6.21)
        };
        let e = optimise(&c, 3, &narrow, 1e-4).expect_err("narrow range");
        assert!(e.to_string().contains("max_condition"), "{e}");
    }
}
