//! The band sky's `mu` tables: cubic interpolation on a uniform grid of `mu` (4-point Lagrange
//! stencils, and their cubics in the monomial basis), the sky irradiance by Simpson's rule on the
//! tables' points, and the table size an error asks for.

/// `int_0^1 (p_a A + p_b B) dmu` by Simpson's rule on the points of one node's tables `a` and
/// `b` (`mu = j / intervals`), `phases[j] = (p_a, p_b)` at the same points, and its error: the
/// change from the rule on every other point, which in the rule's fourth-order regime is 15
/// times the error (taken as it is: a factor 15 to spare), plus a bound of the sum's rounding
/// (`intervals` ulps of the sum of `|f|`). `None` unless the intervals are a
/// multiple of 4 (both rules need an even count). A term whose `B` is 0 is 0 (as the adaptive
/// rule's integrand has it, whatever the phase).
pub(crate) fn irradiance_on_table(
    phases: &[(f64, f64)],
    a: &[f64],
    b: &[f64],
) -> Option<(f64, f64)> {
    let intervals = phases.len().checked_sub(1)?;
    if intervals == 0 || intervals % 4 != 0 || a.len() != phases.len() || b.len() != phases.len() {
        return None;
    }
    let f: Vec<f64> = phases
        .iter()
        .zip(a.iter().zip(b))
        .map(|(&(pa, pb), (&a, &b))| pa * a + if b == 0.0 { 0.0 } else { pb * b })
        .collect();
    // Simpson's sums on step `step` (in points): ends once, odd points 4x, even inner 2x; and
    // the same of `|f|`, which bounds the sum's rounding.
    let simpson = |step: usize| {
        let (mut sum, mut abs) = (f[0] + f[intervals], f[0].abs() + f[intervals].abs());
        for (i, j) in (step..intervals).step_by(step).enumerate() {
            let (w, v) = (if i % 2 == 0 { 4.0 } else { 2.0 }, f[j]);
            sum += w * v;
            abs += w * v.abs();
        }
        let h = step as f64 / (3.0 * intervals as f64);
        (sum * h, abs * h)
    };
    let ((fine, abs), (half, _)) = (simpson(1), simpson(2));
    Some((
        fine,
        (fine - half).abs() + intervals as f64 * f64::EPSILON * abs,
    ))
}

/// The most intervals a `mu` table is refined to.
pub(crate) const TABLE_MAX_INTERVALS: usize = 4096;

/// The intervals a `mu` table needs for an error of `target` when it has `error` at
/// `intervals`: the fourth-order law `error ~ intervals^-4` with a factor 2 to spare, at
/// least 1.5 times as many, a multiple of 4 (the error probe takes every other point, and so
/// does the error of the sky irradiance's Simpson rule, [`irradiance_on_table`], on an even
/// count of intervals), at most [`TABLE_MAX_INTERVALS`].
pub(crate) fn table_intervals_for(intervals: usize, error: f64, target: f64) -> usize {
    let ratio = (2.0 * error / target.max(1e-300)).powf(0.25).max(1.5);
    let wanted = (intervals as f64 * ratio)
        .ceil()
        .min(TABLE_MAX_INTERVALS as f64) as usize;
    wanted.next_multiple_of(4).min(TABLE_MAX_INTERVALS)
}

/// 4-point Lagrange interpolation on a uniform grid over `[0, 1]` (`values.len() - 1` intervals).
#[cfg(test)]
pub(crate) fn lagrange4(values: &[f64], x: f64) -> f64 {
    let (j, w) = lagrange4_stencil(values.len(), x);
    stencil_dot(&w, &values[j - 1..j + 3])
}

/// [`lagrange4`] of two tables of the same length at the same `x`, sharing the stencil (the
/// reference [`BandTables`] is tested against).
#[cfg(test)]
pub(crate) fn lagrange4_pair(a: &[f64], b: &[f64], x: f64) -> (f64, f64) {
    let (j, w) = lagrange4_stencil(a.len(), x);
    (
        stencil_dot(&w, &a[j - 1..j + 3]),
        stencil_dot(&w, &b[j - 1..j + 3]),
    )
}

/// `w . v` for the four values of a stencil (one bounds check for the slice, not four).
#[inline]
pub(crate) fn stencil_dot(w: &[f64; 4], v: &[f64]) -> f64 {
    w[0] * v[0] + w[1] * v[1] + w[2] * v[2] + w[3] * v[3]
}

/// The stencil of [`lagrange4`] on a table of `len` values: the index `j` of its second point
/// (points `j - 1 ..= j + 2`) and the four weights at `x`.
pub(crate) fn lagrange4_stencil(len: usize, x: f64) -> (usize, [f64; 4]) {
    let m = len - 1;
    let t = x.clamp(0.0, 1.0) * m as f64;
    // t >= 0, so the truncating cast is the floor (a NaN gives 0, as NaN.floor() would) without
    // the software floor of the x86-64 baseline (2 % of a scene's instructions).
    let j = (t as usize).clamp(1, m.saturating_sub(2).max(1));
    let s = t - j as f64; // stencil j-1, j, j+1, j+2 at -1, 0, 1, 2
    (
        j,
        [
            -s * (s - 1.0) * (s - 2.0) / 6.0,
            (s + 1.0) * (s - 1.0) * (s - 2.0) / 2.0,
            -(s + 1.0) * s * (s - 2.0) / 2.0,
            (s + 1.0) * s * (s - 1.0) / 6.0,
        ],
    )
}

/// The band sky's `A(mu)` and `B(mu)` ([`crate::scene`] docs) for one set of per-node coefficients,
/// as [`lagrange4`] interpolates them on the `mu` table, one cubic per interval: the interval's
/// 4-point Lagrange cubic in the monomial basis of its own coordinate `s` in `[0, 1]`, `A`'s
/// coefficients (`s^0` to `s^3`) then `B`'s. The same polynomials to rounding (tested), at two
/// Horner evaluations per sky direction instead of the stencil's weights and two dot products (a
/// scene's most frequent call: the sky is asked once per integrand point). Empty for a tabulated
/// sky.
pub(crate) struct BandTables {
    pub(crate) cubics: Vec<[f64; 8]>,
}

impl BandTables {
    /// The cubics of the tables `a` and `b` (the same length, at least 4 values).
    pub(crate) fn new(a: &[f64], b: &[f64]) -> BandTables {
        let m = a.len().saturating_sub(1);
        if m < 3 || b.len() != a.len() {
            return BandTables { cubics: Vec::new() };
        }
        // The stencil cubic `v1 + c1 s + c2 s^2 + c3 s^3` through `v0..v3` at `s = -1, 0, 1,
        // 2` ([`lagrange4_stencil`]'s weights expanded), shifted to the interval's own
        // coordinate `s' = s - d` (`d = i - j`: the first and last intervals use the stencil
        // next to them).
        let stencil = |v: &[f64]| -> [f64; 4] {
            [
                v[1],
                -v[0] / 3.0 - v[1] / 2.0 + v[2] - v[3] / 6.0,
                v[0] / 2.0 - v[1] + v[2] / 2.0,
                (v[3] - v[0]) / 6.0 + (v[1] - v[2]) / 2.0,
            ]
        };
        let shifted = |v: &[f64], d: f64| -> [f64; 4] {
            let [c0, c1, c2, c3] = stencil(v);
            [
                c0 + d * (c1 + d * (c2 + d * c3)),
                c1 + d * (2.0 * c2 + 3.0 * d * c3),
                c2 + 3.0 * d * c3,
                c3,
            ]
        };
        let pack =
            |ca: [f64; 4], cb: [f64; 4]| [ca[0], ca[1], ca[2], ca[3], cb[0], cb[1], cb[2], cb[3]];
        // The first and last intervals take the stencil next to them (`d = -1`, `+1`); the
        // interior ones their own (`d = 0`: no shift).
        let mut cubics = Vec::with_capacity(m);
        cubics.push(pack(shifted(&a[0..4], -1.0), shifted(&b[0..4], -1.0)));
        cubics.extend(
            a.windows(4)
                .zip(b.windows(4))
                .take(m - 2)
                .map(|(va, vb)| pack(stencil(va), stencil(vb))),
        );
        cubics.push(pack(
            shifted(&a[m - 3..m + 1], 1.0),
            shifted(&b[m - 3..m + 1], 1.0),
        ));
        BandTables { cubics }
    }

    /// `(A(mu), B(mu))` for `mu` in `[0, 1]` (clamped); zero for empty tables.
    #[inline]
    pub(crate) fn at(&self, mu: f64) -> (f64, f64) {
        let Some(last) = self.cubics.len().checked_sub(1) else {
            return (0.0, 0.0);
        };
        self.at_in(mu, last)
    }

    /// [`BandTables::at`] for non-empty tables, `last` the index of the last interval: no check
    /// per call, so that a loop over rays ([`BandSky::stokes_in_frame_batch`]) takes the empty
    /// table once.
    #[inline(always)]
    pub(crate) fn at_in(&self, mu: f64, last: usize) -> (f64, f64) {
        let t = mu.clamp(0.0, 1.0) * (last + 1) as f64;
        // t >= 0, so the truncating cast is the floor (see `lagrange4_stencil`); through `u32`
        // (tables hold at most `TABLE_MAX_INTERVALS` intervals), whose saturating cast is half
        // the instructions of `usize`'s.
        let i = (t as u32 as usize).min(last);
        let c = &self.cubics[i];
        let s = t - i as f64;
        (
            c[0] + s * (c[1] + s * (c[2] + s * c[3])),
            c[4] + s * (c[5] + s * (c[6] + s * c[7])),
        )
    }
}
