//! The SCR-optimal analyzer set (MODEL.md section 9, "optimal multichannel combination").
//!
//! The search uses the problem's structure. The SCR depends on the set only through
//! `A = sum w_i w_i^T` ([`crate::scr`]). So it is invariant to the angles' order and to
//! 180-degree shifts of any angle, and the search covers **sorted** tuples in `[0, 180)` deg
//! only: `N!` times fewer points than the full torus.
//!
//! 1. **Coarse grid**: every nondecreasing tuple of a grid of `m` angles. `m` is chosen per `N`,
//!    so that at most [`GRID_BUDGET`] tuples are scored. Tuples that break the separation or
//!    range constraints are left out.
//! 2. **Refinement**: the best [`REFINED_STARTS`] distinct tuples are refined by BFGS with the
//!    analytic gradient and a backtracking line search. A step that would leave the feasible set
//!    is cut back. Refinement stops when the step is under `tol_rad`.
//! 3. A filter wheel's fixed angles: every `N`-subset of its slots is scored (exact).
//!
//! The grid's spacing is much finer than the SCR's features, which vary on the scale of the
//! 45-degree period of `cos 4psi`. So the global maximum's basin holds a grid point among the
//! best. The tests check this against an exhaustive 1-degree grid for `N = 1..3` and against
//! random multistarts for `N = 4..6`; `polarimeter bench planner` reports it each run.

use crate::scr::Contrast;
use crate::PlanError;
use std::f64::consts::PI;

/// Tuples scored by the coarse grid at most.
pub const GRID_BUDGET: usize = 20_000;
/// Grid points refined.
pub const REFINED_STARTS: usize = 8;
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

fn feasible(angles: &[f64], c: &Constraints) -> bool {
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
    // The finest grid within the budget, at most 90 points (2 deg: the SCR's features are on
    // the 45-degree scale of cos 4psi, and the refinement does the rest).
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

    // Enumerate nondecreasing index tuples, keep the best few distinct ones.
    let mut best: Vec<(f64, Vec<f64>)> = Vec::new();
    let mut idx = vec![0usize; n];
    let mut set = vec![0.0; n];
    let mut evaluations = 0usize;
    loop {
        for (s, &i) in set.iter_mut().zip(&idx) {
            *s = grid[i];
        }
        if feasible(&set, constraints) {
            let scr = contrast.scr(&set);
            evaluations += 1;
            if best.len() < REFINED_STARTS || scr > best[best.len() - 1].0 {
                best.push((scr, set.clone()));
                best.sort_by(|a, b| b.0.total_cmp(&a.0));
                best.truncate(REFINED_STARTS);
            }
        }
        if !next_nondecreasing(&mut idx, m) {
            break;
        }
    }
    if best.is_empty() {
        return Err(PlanError::invalid(
            "constraints",
            "no analyzer set satisfies the range and separation constraints",
        ));
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
        let rounded: Vec<f64> = angles
            .iter()
            .map(|a| (a / constraints.step_rad).round() * constraints.step_rad)
            .collect();
        if feasible(&rounded, constraints) {
            scr = contrast.scr(&rounded);
            evaluations += 1;
            angles = rounded;
        }
    }
    Ok(Optimum {
        angles_rad: canonical(angles, periodic),
        scr,
        evaluations,
    })
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

/// BFGS ascent from `start`; returns the SCR, the angles and the evaluations spent.
fn refine(
    contrast: &Contrast,
    start: Vec<f64>,
    constraints: &Constraints,
    tol_rad: f64,
) -> (f64, Vec<f64>, usize) {
    let n = start.len();
    let mut x = start;
    let mut g = vec![0.0; n];
    let mut f = contrast.scr_and_gradient(&x, Some(&mut g));
    let mut evals = 1;
    // Inverse Hessian approximation of -SCR, scaled to the first step.
    let gnorm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
    let scale = if gnorm > 0.0 { 0.05 / gnorm } else { 1.0 };
    let mut h: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..n).map(|j| if i == j { scale } else { 0.0 }).collect())
        .collect();
    let mut g_new = vec![0.0; n];
    for _ in 0..200 {
        // Ascent direction p = H g.
        let p: Vec<f64> = (0..n)
            .map(|i| (0..n).map(|j| h[i][j] * g[j]).sum())
            .collect();
        let slope: f64 = p.iter().zip(&g).map(|(a, b)| a * b).sum();
        if slope <= 0.0 {
            // Lost the ascent direction: restart from the gradient.
            for (i, row) in h.iter_mut().enumerate() {
                for (j, v) in row.iter_mut().enumerate() {
                    *v = if i == j { scale } else { 0.0 };
                }
            }
            continue;
        }
        let mut t = 1.0;
        let mut accepted = None;
        while t > 1e-12 {
            let trial: Vec<f64> = x.iter().zip(&p).map(|(a, b)| a + t * b).collect();
            if feasible(&trial, constraints) {
                let ft = contrast.scr_and_gradient(&trial, Some(&mut g_new));
                evals += 1;
                if ft >= f + 1e-4 * t * slope {
                    accepted = Some((trial, ft));
                    break;
                }
            }
            t *= 0.5;
        }
        let Some((x_new, f_new)) = accepted else {
            break;
        };
        let s: Vec<f64> = x_new.iter().zip(&x).map(|(a, b)| a - b).collect();
        let step = s.iter().map(|v| v.abs()).fold(0.0, f64::max);
        // BFGS update on -SCR: y = -(g_new - g).
        let y: Vec<f64> = g_new.iter().zip(&g).map(|(a, b)| -(a - b)).collect();
        let sy: f64 = s.iter().zip(&y).map(|(a, b)| a * b).sum();
        x = x_new;
        f = f_new;
        g.copy_from_slice(&g_new);
        if step < tol_rad * 1e-2 {
            break;
        }
        if sy > 1e-300 {
            let hy: Vec<f64> = (0..n)
                .map(|i| (0..n).map(|j| h[i][j] * y[j]).sum())
                .collect();
            let yhy: f64 = y.iter().zip(&hy).map(|(a, b)| a * b).sum();
            let rho = 1.0 / sy;
            for i in 0..n {
                for j in 0..n {
                    h[i][j] +=
                        (1.0 + yhy * rho) * rho * s[i] * s[j] - rho * (hy[i] * s[j] + s[i] * hy[j]);
                }
            }
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
            "no subset satisfies the separation and range constraints",
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

/// The conventional sets the planner is compared with: Pickering 0/45/90, 0/60/120, and the
/// modified Pickering 0/45/90/135, with their SCRs.
pub fn conventional(contrast: &Contrast) -> Vec<(&'static str, f64)> {
    [
        ("0/45/90", vec![0.0, 45.0, 90.0]),
        ("0/60/120", vec![0.0, 60.0, 120.0]),
        ("0/45/90/135", vec![0.0, 45.0, 90.0, 135.0]),
    ]
    .into_iter()
    .map(|(name, deg)| {
        let rad: Vec<f64> = deg.iter().map(|d: &f64| d.to_radians()).collect();
        (name, contrast.scr(&rad))
    })
    .collect()
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
    }
}
