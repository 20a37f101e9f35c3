//! The planner's set is never beaten by any set of an exhaustive 1-degree grid under the same
//! constraints, for N = 1 to 6 channels (issue 42).
//!
//! Every nondecreasing tuple of whole degrees in `[0, 180)` (or in a rotator's range) that the
//! constraints allow is covered, without enumerating the C(185, 6) = 5e10 six-tuples: a set's
//! SCR depends on it only through the information its frames add up to, `A = sum w w^T / v`
//! ([`Contrast::frame_information`]), and rises with `A` in the Loewner order
//! ([`Contrast::scr_of_information`]). So a partial set with `k` frames still to choose can
//! reach at most the SCR of `A + k t I`, `t` the largest information any remaining grid angle
//! adds (a rank-one term `w w^T / v` is below `(|w|^2 / v) I`), and a branch whose bound
//! does not pass the planner's SCR is left out: no set in it can beat the planner. Everything
//! else is scored exactly. The search counts the leaves it scored, and the test checks the
//! bound's premise (the information sum gives the set's SCR) on every scored leaf to 1e-9.
//!
//! Cases: the CMOS example camera at random integration times, random class statistics and
//! random constraints (separation, a rotator's range, the Stokes rule), fresh on every run;
//! `POLAR_PLANNER_GRID_SEED` replays a run (the seed is printed).
#![allow(clippy::unwrap_used)]

use nalgebra::{Matrix3, Vector3};
use polar_model::atmosphere::Band;
use polar_model::sensor::{Camera, SensorModel};
use polar_planner::optimize::allowed;
use polar_planner::stokes::STOKES_MAX_CONDITION;
use polar_planner::{optimise, Constraints, Contrast};
use std::f64::consts::PI;

const CMOS: &str = include_str!("../../../examples/cameras/cmos_modern.toml");

/// The grid's step, degrees.
const STEP_DEG: f64 = 1.0;

/// A set beats the planner when its SCR passes the planner's by more than the optimiser's
/// refinement leaves (it stops within 1e-6 rad of a stationary point: ~1e-12 relative).
const BEATS: f64 = 1e-9;

/// How far the information route may stray from the direct SCR, relative: a 3x3 inverse of
/// `A Sigma + I` loses a few epsilon times its condition number where clutter dominates
/// (found: up to 2.5e-9). Bounds are inflated by it before they prune, and every scored leaf
/// checks it.
const PREMISE: f64 = 1e-6;

/// The branch-and-bound over the grid (module docs).
struct Search<'a> {
    contrast: &'a Contrast,
    cons: &'a Constraints,
    n: usize,
    grid: Vec<f64>,
    info: Vec<Matrix3<f64>>,
    /// The largest information (trace of the rank-one term) of grid angles `i..`.
    suffix_max: Vec<f64>,
    /// The mean information of grid angles `i..`.
    suffix_mean: Vec<Matrix3<f64>>,
    bar: f64,
    idx: Vec<usize>,
    leaves: u64,
    best: (f64, Vec<f64>),
    worst_premise: f64,
}

fn separation(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(PI);
    d.min(PI - d)
}

impl Search<'_> {
    /// An upper bound of the SCR of `a` plus the information of any `k` grid angles from
    /// `i` on (module docs): the tangent of the concave SCR at `Y0 = a + k mean(T)` bounds
    /// it from above, and over `a + k conv{T_j}` the tangent's largest value is at a vertex;
    /// the smaller of that and the isotropic bound `SCR(a + k t I)`.
    fn bound(&self, a: &Matrix3<f64>, k: usize, i: usize) -> f64 {
        let kf = k as f64;
        let iso = self
            .contrast
            .scr_of_information(&(a + Matrix3::identity() * (kf * self.suffix_max[i])));
        let y0 = a + self.suffix_mean[i] * kf;
        let Some(y0_inv) = y0.try_inverse() else {
            return iso;
        };
        let Some(p) = (self.contrast.sigma_b + y0_inv).try_inverse() else {
            return iso;
        };
        let pd = p * self.contrast.d;
        let g = y0_inv * pd;
        let f0 = self.contrast.d.dot(&pd);
        let lin = |m: &Matrix3<f64>| g.dot(&(m * g));
        let best_t = self.info[i..]
            .iter()
            .map(lin)
            .fold(f64::NEG_INFINITY, f64::max);
        let tangent = f0 + lin(&(a - y0)) + kf * best_t;
        tangent.min(iso)
    }

    fn visit(&mut self, depth: usize, start: usize, a: Matrix3<f64>) {
        if depth == self.n {
            let set: Vec<f64> = self.idx.iter().map(|&i| self.grid[i]).collect();
            if allowed(&set, self.cons) {
                self.leaves += 1;
                // Scored exactly (the planner's own SCR); the information route beside it.
                let f = self.contrast.scr(&set);
                let route = self.contrast.scr_of_information(&a);
                let premise = (route - f).abs() / f.abs().max(1e-300);
                self.worst_premise = self.worst_premise.max(premise);
                if f > self.best.0 {
                    self.best = (f, set);
                }
            }
            return;
        }
        let sep = self.cons.min_separation_rad;
        for i in start..self.grid.len() {
            let psi = self.grid[i];
            if sep > 0.0
                && self.idx[..depth]
                    .iter()
                    .any(|&c| separation(self.grid[c], psi) < sep - 1e-12)
            {
                continue;
            }
            let a2 = a + self.info[i];
            let k = self.n - depth - 1;
            if k > 0 && self.bound(&a2, k, i) * (1.0 + PREMISE) <= self.bar {
                continue;
            }
            self.idx[depth] = i;
            self.visit(depth + 1, i, a2);
        }
    }
}

/// The grid of whole degrees the constraints' range allows (all of `[0, 180)` without one).
fn grid(cons: &Constraints) -> Vec<f64> {
    let (lo, hi) = cons.range_rad.map_or((0.0, 180.0 - STEP_DEG), |(lo, hi)| {
        (lo.to_degrees().ceil(), hi.to_degrees().floor())
    });
    let mut g = Vec::new();
    let mut d = lo;
    while d <= hi + 1e-9 {
        g.push(d.to_radians());
        d += STEP_DEG;
    }
    g
}

/// Searches the grid for a set beating `bar`; the best allowed grid set above the bar (if any),
/// the leaves scored, and the worst relative difference between the information route and
/// the direct SCR on them.
fn search<'a>(contrast: &'a Contrast, n: usize, cons: &'a Constraints, bar: f64) -> Search<'a> {
    let grid = grid(cons);
    let info: Vec<Matrix3<f64>> = grid
        .iter()
        .map(|&p| contrast.frame_information(p))
        .collect();
    let mut suffix_max = vec![0.0f64; grid.len() + 1];
    let mut suffix_mean = vec![Matrix3::zeros(); grid.len() + 1];
    let mut sum = Matrix3::zeros();
    for i in (0..grid.len()).rev() {
        suffix_max[i] = suffix_max[i + 1].max(info[i].trace());
        sum += info[i];
        suffix_mean[i] = sum / (grid.len() - i) as f64;
    }
    let mut s = Search {
        contrast,
        cons,
        n,
        grid,
        info,
        suffix_max,
        suffix_mean,
        bar,
        idx: vec![0; n],
        leaves: 0,
        best: (f64::NEG_INFINITY, Vec::new()),
        worst_premise: 0.0,
    };
    s.visit(0, 0, Matrix3::zeros());
    s
}

/// A small deterministic generator (SplitMix64) for the cases.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

/// One case: the contrast at a random exposure and classes, and constraints for `n`.
fn case(rng: &mut Rng, sensor: &SensorModel, n: usize) -> (Contrast, Constraints) {
    let s0 = rng.range(5.0, 40.0);
    let pol = |rng: &mut Rng, p: f64| {
        let a = rng.range(0.0, PI);
        Vector3::new(s0, p * s0 * (2.0 * a).cos(), p * s0 * (2.0 * a).sin())
    };
    let (pb, pt) = (rng.range(0.0, 0.1), rng.range(0.05, 0.5));
    let mu_b = pol(rng, pb);
    let scale = rng.range(0.9, 1.1);
    let mu_t = pol(rng, pt) * scale;
    let c = Vector3::new(
        rng.range(0.01, 0.2),
        rng.range(0.0, 0.05),
        rng.range(0.0, 0.05),
    ) * s0;
    let r = Vector3::new(
        rng.range(-0.5, 0.5),
        rng.range(-0.5, 0.5),
        rng.range(-0.5, 0.5),
    );
    let mut cov = Matrix3::from_diagonal(&c.component_mul(&c));
    cov[(0, 1)] = r[0] * c[0] * c[1];
    cov[(0, 2)] = r[1] * c[0] * c[2];
    cov[(1, 2)] = r[2] * c[1] * c[2];
    cov = 0.5 * (cov + cov.transpose()) + Matrix3::identity() * 1e-9 * s0 * s0;
    let t_int_s = 10f64.powf(rng.range(-5.0, -2.5));
    let contrast = Contrast::from_sensor(sensor, t_int_s, &mu_t, &mu_b, &cov).unwrap();
    let stokes = n >= 3 && rng.next() < 0.5;
    let widest = (180.0 / n as f64 - 1.0).min(89.0);
    let sep_deg = if rng.next() < 0.5 {
        0.0
    } else {
        rng.range(0.0, widest) * if stokes { 0.25 } else { 1.0 }
    };
    let range_rad = (rng.next() < 0.3).then(|| {
        let lo = rng.range(0.0, 90.0);
        let span = rng
            .range(60.0, 179.0)
            .max(sep_deg * (n as f64 - 1.0) + 2.0)
            .min(179.0);
        (lo.to_radians(), (lo + span).to_radians())
    });
    let cons = Constraints {
        range_rad,
        min_separation_rad: sep_deg.to_radians(),
        max_condition: stokes.then_some(STOKES_MAX_CONDITION),
        ..Constraints::default()
    };
    (contrast, cons)
}

fn seed() -> u64 {
    const VAR: &str = "POLAR_PLANNER_GRID_SEED";
    let seed = std::env::var(VAR)
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(1, |d| d.as_nanos() as u64)
        });
    println!("grid seed {seed}: replay with {VAR}={seed}");
    seed
}

/// For N = 1 to 6, fresh cases each run: no allowed set of the 1-degree grid beats the
/// planner's SCR by more than 1e-9 relative, and the information route agrees with the
/// direct SCR to [`PREMISE`] on every leaf it scored (the premise of the bound).
#[test]
fn no_grid_set_beats_the_planner() {
    let cam = Camera::from_toml_str(CMOS).unwrap();
    let sensor = SensorModel::new(&cam, &Band::flat(450.0, 650.0).unwrap()).unwrap();
    let mut rng = Rng(seed());
    for n in 1..=6 {
        for _ in 0..2 {
            let (contrast, cons) = case(&mut rng, &sensor, n);
            let opt = match optimise(&contrast, n, &cons, 1e-3f64.to_radians()) {
                Ok(o) => o,
                Err(e) => {
                    assert!(e.to_string().contains("max_condition"), "{e}");
                    // Refused only when no set meets the Stokes bound in the range: the grid
                    // then has none either.
                    let s = search(&contrast, n, &cons, f64::NEG_INFINITY);
                    assert_eq!(s.leaves, 0, "{e}, yet the grid allows {:?}", s.best.1);
                    continue;
                }
            };
            let bar = opt.scr * (1.0 + BEATS);
            let t0 = std::time::Instant::now();
            let s = search(&contrast, n, &cons, bar);
            println!(
                "N = {n}: planner {:.6} at {:?} deg; {} leaves scored in {:.1} s (route {:.1e}); {cons:?}",
                opt.scr,
                opt.angles_rad
                    .iter()
                    .map(|a| (a.to_degrees() * 100.0).round() / 100.0)
                    .collect::<Vec<_>>(),
                s.leaves,
                t0.elapsed().as_secs_f64(),
                s.worst_premise
            );
            assert!(
                s.best.0 <= bar,
                "the grid set {:?} has SCR {} > the planner's {} at {:?}",
                s.best.1,
                s.best.0,
                opt.scr,
                opt.angles_rad
            );
            assert!(
                s.worst_premise < PREMISE,
                "premise off by {}",
                s.worst_premise
            );
        }
    }
}
