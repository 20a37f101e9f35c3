//! When an analyzer set forms a Stokes image: the condition number of its measurement matrix.
//!
//! A set of `N >= 3` angles estimates the linear Stokes vector by least squares,
//! `S_hat = (W^T W)^-1 W^T I`, and the 2-norm condition number `kappa(W) = s_max / s_min` of
//! its measurement matrix bounds how much that estimate amplifies the frames' noise (Meng
//! (2012) Sec. 2.3 on the choice of analyzer sets; MODEL.md section 0). The rule used here:
//! a set is a **Stokes set** when `kappa(W) <= STOKES_MAX_CONDITION`, the worst `kappa` of a
//! 3-angle set whose angles are at least 30 degrees apart (0/30/60). So 3 angles need that
//! spread, and 4 to 6 angles may sit closer, as long as together they still see the three
//! Stokes components evenly.
//!
//! `W` is the **ideal** analyzer's, rows `[1, cos 2psi, sin 2psi]` (the factor 1/2 does not
//! change `kappa`). The rule is about the angles' geometry, the same for every camera: a
//! real analyzer with extinction ratio `e` multiplies the polarised columns by
//! `(1 - 1/e) / (1 + 1/e)`, which raises every set's `kappa` by about the same factor, so a
//! bound on the real rows would let a camera's polariser, not the set, decide what counts as a
//! Stokes set (and a weak polariser would allow none). The camera's own condition number is
//! reported beside it ([`crate::Contrast::condition_number`]).
//!
//! The smallest `kappa` any set reaches is `sqrt 2` (`W^T W` has `N` in its `S0` entry and
//! trace `2 N`, so its smallest eigenvalue is at most `N / 2` while its largest is at least
//! `N`); the equally spaced sets reach it.

use nalgebra::{Matrix3, Vector3};

/// The largest condition number of a Stokes set's ideal measurement matrix: that of 0/30/60
/// (6.2037), the worst 3-angle set whose angles are at least 30 degrees apart, rounded up.
/// (0/45/90 has 2.41, 0/60/120 1.41, the smallest possible.)
pub const STOKES_MAX_CONDITION: f64 = 6.21;

/// The smallest condition number any set reaches, `sqrt 2` (module docs).
pub const MIN_CONDITION: f64 = std::f64::consts::SQRT_2;

fn ideal_gram(angles_rad: &[f64]) -> Matrix3<f64> {
    angles_rad.iter().fold(Matrix3::zeros(), |acc, &p| {
        let (s, c) = (2.0 * p).sin_cos();
        let r = Vector3::new(1.0, c, s);
        acc + r * r.transpose()
    })
}

/// The ideal analyzer's measurement-matrix condition number `kappa(W)` of the set (infinite
/// for fewer than 3 independent rows).
pub fn stokes_condition(angles_rad: &[f64]) -> f64 {
    let e = ideal_gram(angles_rad).symmetric_eigenvalues();
    let (lo, hi) = (e.min(), e.max());
    if angles_rad.len() < 3 || lo <= hi * 1e-15 {
        f64::INFINITY
    } else {
        (hi / lo).sqrt()
    }
}

/// `ln kappa(W)` and, into `gradient`, its derivative per radian of each angle: with `v` the
/// unit eigenvectors of `W^T W` and `r_k`, `r'_k` a row and its derivative,
/// `d lambda / d psi_k = 2 (v . r_k) (v . r'_k)` and `d ln kappa = (d lambda_max / lambda_max
/// - d lambda_min / lambda_min) / 2`. Infinite (gradient 0) for a singular `W`.
pub fn log_condition_and_gradient(angles_rad: &[f64], gradient: &mut [f64]) -> f64 {
    let eig = ideal_gram(angles_rad).symmetric_eigen();
    let (mut imax, mut imin) = (0, 0);
    for k in 1..3 {
        if eig.eigenvalues[k] > eig.eigenvalues[imax] {
            imax = k;
        }
        if eig.eigenvalues[k] < eig.eigenvalues[imin] {
            imin = k;
        }
    }
    let (hi, lo) = (eig.eigenvalues[imax], eig.eigenvalues[imin]);
    gradient.iter_mut().for_each(|g| *g = 0.0);
    if angles_rad.len() < 3 || lo <= hi * 1e-15 {
        return f64::INFINITY;
    }
    let vmax = eig.eigenvectors.column(imax).into_owned();
    let vmin = eig.eigenvectors.column(imin).into_owned();
    for (g, &p) in gradient.iter_mut().zip(angles_rad) {
        let (s, c) = (2.0 * p).sin_cos();
        let r = Vector3::new(1.0, c, s);
        let dr = Vector3::new(0.0, -2.0 * s, 2.0 * c);
        let dhi = 2.0 * vmax.dot(&r) * vmax.dot(&dr);
        let dlo = 2.0 * vmin.dot(&r) * vmin.dot(&dr);
        *g = 0.5 * (dhi / hi - dlo / lo);
    }
    0.5 * (hi / lo).ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
    }

    /// The bound is 0/30/60's condition number rounded up by less than 0.01 (its definition),
    /// and no 3-angle set whose angles are at least 30 deg apart (modulo 180) exceeds it, on a
    /// 1-degree grid (the worst is 0/30/60 itself, found to the grid, hence the 1e-9 slack
    /// only for rounding). The conventional sets have their textbook values: 0/45/90
    /// `1 + sqrt 2`, 0/60/120 and 0/45/90/135 `sqrt 2` (to 1e-12: exact eigenvalues of
    /// diagonal and 2x2 Gram matrices, rounding only).
    #[test]
    fn the_bound_is_the_worst_thirty_degree_set() {
        let k = stokes_condition(&deg(&[0.0, 30.0, 60.0]));
        assert!(
            k <= STOKES_MAX_CONDITION && STOKES_MAX_CONDITION - k < 0.01,
            "{k}"
        );
        let mut worst: f64 = 0.0;
        for a in 30..=150 {
            for b in a + 30..=150 {
                if 180 - b >= 30 {
                    worst = worst.max(stokes_condition(&deg(&[0.0, a as f64, b as f64])));
                }
            }
        }
        assert!(worst <= k * (1.0 + 1e-9), "worst {worst} > 0/30/60's {k}");
        let k4590 = stokes_condition(&deg(&[0.0, 45.0, 90.0]));
        assert!((k4590 - (1.0 + MIN_CONDITION)).abs() < 1e-12, "{k4590}");
        for set in [&[0.0, 60.0, 120.0][..], &[0.0, 45.0, 90.0, 135.0]] {
            let k = stokes_condition(&deg(set));
            assert!((k - MIN_CONDITION).abs() < 1e-12, "{set:?}: {k}");
        }
        assert!(stokes_condition(&deg(&[0.0, 90.0])).is_infinite());
        assert!(stokes_condition(&deg(&[0.0, 0.0, 90.0])).is_infinite());
    }

    /// The analytic gradient of `ln kappa` matches central differences (step 1e-6 rad) to
    /// 1e-6 absolute: the difference's truncation error is O(h^2) times third derivatives of
    /// order 1 to 100 on these sets, and its rounding error ~1e-16 / 1e-6.
    #[test]
    fn gradient_matches_differences() {
        for set in [
            &[0.0, 30.0, 60.0][..],
            &[5.0, 20.0, 70.0, 100.0],
            &[1.0, 11.0, 33.0, 47.0, 90.0, 160.0],
        ] {
            let x = deg(set);
            let mut g = vec![0.0; x.len()];
            log_condition_and_gradient(&x, &mut g);
            let mut scratch = vec![0.0; x.len()];
            for k in 0..x.len() {
                let h = 1e-6;
                let (mut up, mut down) = (x.clone(), x.clone());
                up[k] += h;
                down[k] -= h;
                let fd = (log_condition_and_gradient(&up, &mut scratch)
                    - log_condition_and_gradient(&down, &mut scratch))
                    / (2.0 * h);
                assert!((fd - g[k]).abs() < 1e-6, "{set:?} k {k}: {fd} vs {}", g[k]);
            }
        }
    }
}
