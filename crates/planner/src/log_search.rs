//! One-dimensional minimisation on a logarithmic axis: a scan over the range, then
//! golden-section search between the best scan point's neighbours. The continuous planner's
//! speed per frame count and the step-and-shoot set's exposure are both found this way.

/// Minimises `f` over `[llo, lhi]` (the logarithm of the variable): `scan >= 2` equally spaced
/// points (the last exactly `lhi`), then `iterations` golden-section steps between the best
/// scan point's neighbours. `f` returns `f64::INFINITY` where the point is not allowed; a scan
/// with no allowed point is not refined. Returns the best `(log x, f)` of every evaluation, or
/// `None` when none was allowed. Callers that keep more than the value (the setting behind
/// it) keep it in `f`.
pub fn scan_then_golden<E>(
    llo: f64,
    lhi: f64,
    scan: usize,
    iterations: usize,
    mut f: impl FnMut(f64) -> Result<f64, E>,
) -> Result<Option<(f64, f64)>, E> {
    let step = (lhi - llo) / (scan.max(2) - 1) as f64;
    let mut best: Option<(f64, f64)> = None;
    let keep = |x: f64, v: f64, best: &mut Option<(f64, f64)>| {
        if v.is_finite() && best.is_none_or(|b| v < b.1) {
            *best = Some((x, v));
        }
    };
    let mut best_i = 0;
    let mut best_scan = f64::INFINITY;
    for i in 0..scan.max(2) {
        let x = if i + 1 == scan.max(2) {
            lhi
        } else {
            llo + step * i as f64
        };
        let v = f(x)?;
        if v < best_scan {
            best_scan = v;
            best_i = i;
        }
        keep(x, v, &mut best);
    }
    if best.is_none() {
        return Ok(None);
    }
    let (mut a, mut z) = (
        (llo + step * best_i.saturating_sub(1) as f64).max(llo),
        (llo + step * (best_i + 1) as f64).min(lhi),
    );
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut x1 = z - g * (z - a);
    let mut x2 = a + g * (z - a);
    let mut f1 = f(x1)?;
    keep(x1, f1, &mut best);
    let mut f2 = f(x2)?;
    keep(x2, f2, &mut best);
    for _ in 0..iterations {
        if f1 <= f2 {
            z = x2;
            x2 = x1;
            f2 = f1;
            x1 = z - g * (z - a);
            f1 = f(x1)?;
            keep(x1, f1, &mut best);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (z - a);
            f2 = f(x2)?;
            keep(x2, f2, &mut best);
        }
    }
    Ok(best)
}

/// The end of the region where `holds` is true, by `steps` bisections of `[lo, hi]` (logs):
/// `holds` is true at `lo` and false at `hi`, and changes once between them; returns the last
/// point known to hold.
pub fn bisect<E>(
    lo: f64,
    hi: f64,
    steps: usize,
    mut holds: impl FnMut(f64) -> Result<bool, E>,
) -> Result<f64, E> {
    let (mut lo, mut hi) = (lo, hi);
    for _ in 0..steps {
        let mid = 0.5 * (lo + hi);
        if holds(mid)? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(lo)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth minimum inside the range is found to 1e-9 in log x (70 golden steps shrink
    /// the bracket by 0.618^70 ~ 2e-15 of one scan step); a minimum at the end is that end
    /// exactly; a range with nothing allowed gives `None` without refining.
    #[test]
    fn finds_interior_and_end_minima() {
        let target = 0.3f64.ln();
        let (x, v) = scan_then_golden::<()>(1e-3f64.ln(), 10f64.ln(), 40, 70, |x| {
            Ok((x - target).powi(2))
        })
        .unwrap()
        .unwrap();
        assert!((x - target).abs() < 1e-9 && v < 1e-17, "{x} {v}");
        let (x, _) = scan_then_golden::<()>(0.0, 1.0, 10, 70, |x| Ok(-x))
            .unwrap()
            .unwrap();
        assert_eq!(x, 1.0);
        let mut calls = 0;
        let none = scan_then_golden::<()>(0.0, 1.0, 10, 70, |_| {
            calls += 1;
            Ok(f64::INFINITY)
        })
        .unwrap();
        assert!(none.is_none() && calls == 10);
    }
}
