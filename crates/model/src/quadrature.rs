//! Globally adaptive Gauss-Kronrod quadrature (7-point Gauss / 15-point Kronrod pair) with an
//! error estimate, in one and two (nested) dimensions.
//!
//! The rule's nodes and weights are the classic ones of Piessens et al., *QUADPACK* (Springer,
//! 1983), routine `QK15`, and so is the error estimate of an interval: `|K15 - G7|` rescaled by the
//! integrand's variation, `resasc * min(1, (200 |K15 - G7| / resasc)^1.5)`, floored at 50 eps times
//! the integral of `|f|`. It is an estimate, not a rigorous bound; the tests below and the
//! model's reference tests compare it with known integrals. The interval with the largest error
//! is bisected until the total error meets the tolerance or the subdivision budget is spent (then
//! `converged = false`).
//!
//! Hand-written because the model needs nested integration whose inner errors are propagated into
//! the outer estimate, without allocation per inner call; the crates available either do not
//! propagate inner errors or pull in thread pools.

/// Abscissae of the 15-point Kronrod rule on `[-1, 1]` (non-negative half, descending).
const XGK: [f64; 8] = [
    0.991_455_371_120_812_6,
    0.949_107_912_342_758_5,
    0.864_864_423_359_769_1,
    0.741_531_185_599_394_4,
    0.586_087_235_467_691_1,
    0.405_845_151_377_397_2,
    0.207_784_955_007_898_5,
    0.0,
];
/// Weights of the 15-point Kronrod rule for [`XGK`].
const WGK: [f64; 8] = [
    0.022_935_322_010_529_22,
    0.063_092_092_629_978_55,
    0.104_790_010_322_250_2,
    0.140_653_259_715_525_9,
    0.169_004_726_639_267_9,
    0.190_350_578_064_785_4,
    0.204_432_940_075_298_9,
    0.209_482_141_084_727_8,
];
/// Weights of the embedded 7-point Gauss rule, for `XGK[1], XGK[3], XGK[5], XGK[7]`.
const WG: [f64; 4] = [
    0.129_484_966_168_869_7,
    0.279_705_391_489_276_7,
    0.381_830_050_505_118_9,
    0.417_959_183_673_469_4,
];

/// Stopping rule of an adaptive integration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tolerance {
    /// Absolute error target.
    pub abs: f64,
    /// Relative error target (fraction of the integral's magnitude).
    pub rel: f64,
    /// Largest number of intervals (per dimension); past it the result is returned with
    /// `converged = false` and its honest error estimate.
    pub max_intervals: usize,
}

impl Tolerance {
    /// An absolute tolerance with a relative floor of 1e-12 and 200 intervals per dimension.
    pub fn absolute(abs: f64) -> Self {
        Tolerance {
            abs,
            rel: 1e-12,
            max_intervals: 200,
        }
    }

    pub(crate) fn target(&self, value: f64) -> f64 {
        self.abs.max(self.rel * value.abs())
    }
}

impl Tolerance {
    /// The same tolerance for an integral `factor` times larger.
    pub(crate) fn scaled(self, factor: f64) -> Tolerance {
        Tolerance {
            abs: self.abs * factor,
            ..self
        }
    }
}

impl Default for Tolerance {
    /// `1e-9` absolute: well below every figure the model reports with 6 significant digits.
    fn default() -> Self {
        Tolerance::absolute(1e-9)
    }
}

/// The result of an integration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Integral {
    /// The integral's estimate.
    pub value: f64,
    /// Conservative estimate of `|value - exact|`.
    pub error: f64,
    /// Number of integrand evaluations (innermost calls for nested integrals).
    pub evaluations: usize,
    /// Whether `error` met the tolerance within the interval budget.
    pub converged: bool,
}

#[derive(Debug, Clone, Copy)]
struct Piece<const N: usize> {
    a: f64,
    b: f64,
    value: [f64; N],
    error: f64,
}

/// QUADPACK's error estimate of one component: `|K - G|` rescaled by the integrand's variation
/// on the interval (resasc), which tracks the true error of K15 closely for smooth integrands
/// and falls back to `|K - G|` (or larger) where the integrand is rough.
fn component_error(fv: &[f64; 15], kronrod: f64, gauss: f64, half: f64) -> f64 {
    let fc = fv[14];
    let mean = 0.5 * kronrod;
    let mut resasc = WGK[7] * (fc - mean).abs();
    let mut abs_k = WGK[7] * fc.abs();
    for j in 0..7 {
        resasc += WGK[j] * ((fv[2 * j] - mean).abs() + (fv[2 * j + 1] - mean).abs());
        abs_k += WGK[j] * (fv[2 * j].abs() + fv[2 * j + 1].abs());
    }
    let h = half.abs();
    let (resasc, resabs) = (resasc * h, abs_k * h);
    let mut err = ((kronrod - gauss) * half).abs();
    if resasc != 0.0 && err != 0.0 {
        err = resasc * (200.0 * err / resasc).powf(1.5).min(1.0);
    }
    if resabs > f64::MIN_POSITIVE / (50.0 * f64::EPSILON) {
        err = err.max(50.0 * f64::EPSILON * resabs);
    }
    err
}

/// Applies the G7/K15 pair on `[a, b]` to an integrand with `N` components that returns
/// `(values, error_of_values)`; the pointwise errors (from an inner integration) are added to the
/// interval's error with the Kronrod weights. The interval's error is the largest component's.
fn gk15<const N: usize, F: FnMut(f64) -> ([f64; N], f64)>(f: &mut F, a: f64, b: f64) -> Piece<N> {
    let centre = 0.5 * (a + b);
    let half = 0.5 * (b - a);
    let mut fv = [[0.0f64; 15]; N];
    let mut inner = 0.0;
    let (vc, ec) = f(centre);
    for n in 0..N {
        fv[n][14] = vc[n];
    }
    inner += WGK[7] * ec;
    for j in 0..7 {
        let dx = half * XGK[j];
        let (v1, e1) = f(centre - dx);
        let (v2, e2) = f(centre + dx);
        for n in 0..N {
            fv[n][2 * j] = v1[n];
            fv[n][2 * j + 1] = v2[n];
        }
        inner += WGK[j] * (e1 + e2);
    }
    let mut value = [0.0; N];
    let mut error = 0.0f64;
    for n in 0..N {
        let v = &fv[n];
        let mut kronrod = WGK[7] * v[14];
        let mut gauss = WG[3] * v[14];
        for j in 0..7 {
            kronrod += WGK[j] * (v[2 * j] + v[2 * j + 1]);
            if j % 2 == 1 {
                gauss += WG[j / 2] * (v[2 * j] + v[2 * j + 1]);
            }
        }
        value[n] = kronrod * half;
        error = error.max(component_error(v, kronrod, gauss, half));
    }
    Piece {
        a,
        b,
        value,
        error: error + inner * half.abs(),
    }
}

/// The result of integrating an `N`-component integrand.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntegralN<const N: usize> {
    /// The integral of each component.
    pub value: [f64; N],
    /// Conservative estimate of the largest component's error.
    pub error: f64,
    /// Number of integrand evaluations (innermost calls for nested integrals).
    pub evaluations: usize,
    /// Whether `error` met the tolerance within the interval budget.
    pub converged: bool,
}

fn sum_pieces<const N: usize>(pieces: &[Piece<N>]) -> ([f64; N], f64) {
    let mut value = [0.0; N];
    let mut error = 0.0;
    for p in pieces {
        for (v, pv) in value.iter_mut().zip(&p.value) {
            *v += pv;
        }
        error += p.error;
    }
    (value, error)
}

pub(crate) fn max_abs<const N: usize>(v: &[f64; N]) -> f64 {
    v.iter().fold(0.0f64, |m, x| m.max(x.abs()))
}

/// Integrates an integrand that carries its own pointwise error over `[a, b]`.
fn adaptive<const N: usize, F: FnMut(f64) -> ([f64; N], f64)>(
    mut f: F,
    a: f64,
    b: f64,
    tol: Tolerance,
) -> IntegralN<N> {
    let mut pieces = vec![gk15(&mut f, a, b)];
    let mut evaluations = 15;
    loop {
        let (value, error) = sum_pieces(&pieces);
        let converged = error <= tol.target(max_abs(&value));
        if converged || pieces.len() >= tol.max_intervals.max(1) || !error.is_finite() {
            return IntegralN {
                value,
                error,
                evaluations,
                converged,
            };
        }
        let worst = pieces
            .iter()
            .enumerate()
            .max_by(|x, y| x.1.error.total_cmp(&y.1.error))
            .map(|(i, _)| i)
            .unwrap_or(0);
        let p = pieces.swap_remove(worst);
        let mid = 0.5 * (p.a + p.b);
        if mid <= p.a || mid >= p.b {
            // The interval cannot be split further in f64: report what we have.
            pieces.push(p);
            let (value, error) = sum_pieces(&pieces);
            return IntegralN {
                value,
                error,
                evaluations,
                converged: false,
            };
        }
        pieces.push(gk15(&mut f, p.a, mid));
        pieces.push(gk15(&mut f, mid, p.b));
        evaluations += 30;
    }
}

fn scalar(r: IntegralN<1>) -> Integral {
    Integral {
        value: r.value[0],
        error: r.error,
        evaluations: r.evaluations,
        converged: r.converged,
    }
}

/// [`gauss_legendre`]`(n)`, computed once per process for each `n` in `[1, 64]` when first
/// asked for (all 64 at once took about 2 ms of every process: 3 % of a one-shot rooftop
/// `model scene` at 1e-4, by `perf`).
pub(crate) fn gauss_legendre_table(n: usize) -> &'static [(f64, f64)] {
    static TABLE: [std::sync::OnceLock<Vec<(f64, f64)>>; 64] =
        [const { std::sync::OnceLock::new() }; 64];
    let n = n.clamp(1, 64);
    TABLE[n - 1].get_or_init(|| gauss_legendre(n))
}

/// Gauss-Legendre nodes and weights on `[-1, 1]` for `n` in `[1, 64]` (Newton's iteration on
/// the three-term recurrence; weights `2 / ((1 - x^2) P_n'(x)^2)`); exact for polynomials of
/// degree `2n - 1`.
pub fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    let n = n.clamp(1, 64);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        // Tricomi's initial guess, then Newton.
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=n {
                let kf = k as f64;
                let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
                p0 = p1;
                p1 = p2;
            }
            let pn = if n == 1 { x } else { p1 };
            let pm = if n == 1 { 1.0 } else { p0 };
            dp = n as f64 * (x * pn - pm) / (x * x - 1.0);
            let dx = pn / dp;
            x -= dx;
            if dx.abs() < 1e-16 {
                break;
            }
        }
        if n == 1 {
            out.push((0.0, 2.0));
            break;
        }
        out.push((x, 2.0 / ((1.0 - x * x) * dp * dp)));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    out
}

/// Integrates `f` over `[a, b]` to tolerance `tol`.
pub fn integrate<F: FnMut(f64) -> f64>(mut f: F, a: f64, b: f64, tol: Tolerance) -> Integral {
    scalar(adaptive(|x| ([f(x)], 0.0), a, b, tol))
}

/// [`integrate`] for an integrand with `N` components, all on the same adaptive partition; the
/// error is the largest component's.
pub fn integrate_n<const N: usize, F: FnMut(f64) -> [f64; N]>(
    mut f: F,
    a: f64,
    b: f64,
    tol: Tolerance,
) -> IntegralN<N> {
    adaptive(|x| (f(x), 0.0), a, b, tol)
}

/// Integrates `f(x, y)` over the rectangle `[ax, bx] x [ay, by]` by nested adaptive rules.
///
/// The inner integral over `y` runs at a tenth of the outer tolerance (scaled by the outer
/// interval length so the inner errors sum to at most that share), and its error estimates are
/// propagated into the outer one, so the reported error covers both.
pub fn integrate_2d<F: FnMut(f64, f64) -> f64>(
    f: F,
    x_range: (f64, f64),
    y_range: (f64, f64),
    tol: Tolerance,
) -> Integral {
    integrate_2d_split(f, x_range, y_range, |_, _| {}, tol)
}

/// [`integrate_2d`] with inner breakpoints: `breaks(x, &mut list)` pushes the `y` values where
/// `f(x, .)` has a kink or a jump, and the inner integral is split there, so that adaptivity is
/// not spent locating them. Breakpoints outside `(ay, by)` are ignored.
pub fn integrate_2d_split<F, B>(
    mut f: F,
    x_range: (f64, f64),
    y_range: (f64, f64),
    breaks: B,
    tol: Tolerance,
) -> Integral
where
    F: FnMut(f64, f64) -> f64,
    B: FnMut(f64, &mut Vec<f64>),
{
    scalar(integrate_2d_split_n(
        |x, y| [f(x, y)],
        x_range,
        y_range,
        breaks,
        tol,
    ))
}

/// The inner integral of a 2-D rule at outer point `x`: adaptive over `[ay, by]`, split at
/// `breaks(x)`, each piece to `0.3 tol / width / pieces` so that the outer sum of inner errors
/// stays below 0.3 of the tolerance. Returns the value and error, and adds to `evaluations` and
/// `converged`.
#[allow(clippy::too_many_arguments)]
fn inner_line<const N: usize, F, B>(
    f: &mut F,
    breaks: &mut B,
    points: &mut Vec<f64>,
    x: f64,
    (ay, by): (f64, f64),
    width: f64,
    tol: Tolerance,
    evaluations: &mut usize,
    converged: &mut bool,
) -> ([f64; N], f64)
where
    F: FnMut(f64, f64) -> [f64; N],
    B: FnMut(f64, &mut Vec<f64>),
{
    points.clear();
    breaks(x, points);
    points.retain(|&y| y.is_finite() && y > ay && y < by);
    points.push(ay);
    points.push(by);
    points.sort_by(f64::total_cmp);
    points.dedup();
    let pieces = (points.len() - 1) as f64;
    let inner_tol = Tolerance {
        abs: 0.3 * tol.abs / width / pieces,
        rel: 0.3 * tol.rel,
        max_intervals: tol.max_intervals,
    };
    let (mut value, mut error) = ([0.0; N], 0.0);
    for w in points.windows(2) {
        let inner = adaptive(|y| (f(x, y), 0.0), w[0], w[1], inner_tol);
        *evaluations += inner.evaluations;
        *converged &= inner.converged;
        for (v, iv) in value.iter_mut().zip(&inner.value) {
            *v += iv;
        }
        error += inner.error;
    }
    (value, error)
}

/// [`integrate_2d_split`] for an integrand with `N` components (a Stokes vector, say), all
/// integrated on the same adaptive partition; the error is the largest component's.
pub fn integrate_2d_split_n<const N: usize, F, B>(
    mut f: F,
    (ax, bx): (f64, f64),
    (ay, by): (f64, f64),
    mut breaks: B,
    tol: Tolerance,
) -> IntegralN<N>
where
    F: FnMut(f64, f64) -> [f64; N],
    B: FnMut(f64, &mut Vec<f64>),
{
    let width = (bx - ax).abs().max(f64::MIN_POSITIVE);
    let mut evaluations = 0usize;
    let mut all_inner_converged = true;
    let mut points = Vec::with_capacity(8);
    let outer = adaptive(
        |x| {
            inner_line(
                &mut f,
                &mut breaks,
                &mut points,
                x,
                (ay, by),
                width,
                tol,
                &mut evaluations,
                &mut all_inner_converged,
            )
        },
        ax,
        bx,
        tol,
    );
    IntegralN {
        evaluations,
        converged: outer.converged && all_inner_converged,
        ..outer
    }
}

/// A 2-D integral periodic in its outer variable: `int_{ax}^{ax + period} int_{ay}^{by} f dy dx`
/// with `f(x + period, y) = f(x, y)`. The outer integral is the trapezoid rule (spectrally
/// accurate for smooth periodic integrands; Trefethen & Weideman, SIAM Rev. 56, 385 (2014)) on
/// 8, 16, 32, ... points, each level reusing the last, until two levels differ by less than the
/// tolerance; the returned value is the finer level and the error the difference plus the inner
/// errors. The inner integrals are adaptive and split at `breaks` as in
/// [`integrate_2d_split_n`]. Much cheaper than nested adaptive rules when the outer integrand is
/// smooth, since the inner errors' noise does not drive outer subdivision.
pub fn integrate_periodic_split_n<const N: usize, F, B>(
    mut f: F,
    (ax, period): (f64, f64),
    (ay, by): (f64, f64),
    mut breaks: B,
    tol: Tolerance,
) -> IntegralN<N>
where
    F: FnMut(f64, f64) -> [f64; N],
    B: FnMut(f64, &mut Vec<f64>),
{
    let period = period.abs().max(f64::MIN_POSITIVE);
    let mut evaluations = 0usize;
    let mut all_inner_converged = true;
    let mut points = Vec::with_capacity(8);
    let mut line = |x: f64, evaluations: &mut usize, converged: &mut bool| {
        inner_line(
            &mut f,
            &mut breaks,
            &mut points,
            x,
            (ay, by),
            period,
            tol,
            evaluations,
            converged,
        )
    };
    let mut m = 8usize;
    let mut sum = [0.0; N];
    let mut inner_error = 0.0f64;
    for i in 0..m {
        let (v, e) = line(
            ax + period * i as f64 / m as f64,
            &mut evaluations,
            &mut all_inner_converged,
        );
        for (s, x) in sum.iter_mut().zip(&v) {
            *s += x;
        }
        inner_error = inner_error.max(e);
    }
    let mut coarse = sum.map(|s| s * period / m as f64);
    loop {
        for i in 0..m {
            let x = ax + period * (i as f64 + 0.5) / m as f64;
            let (v, e) = line(x, &mut evaluations, &mut all_inner_converged);
            for (s, x) in sum.iter_mut().zip(&v) {
                *s += x;
            }
            inner_error = inner_error.max(e);
        }
        m *= 2;
        let fine = sum.map(|s| s * period / m as f64);
        let change = fine
            .iter()
            .zip(&coarse)
            .fold(0.0f64, |a, (p, q)| a.max((p - q).abs()));
        let error = change + inner_error * period;
        let converged = error <= tol.target(max_abs(&fine));
        if converged || !error.is_finite() {
            return IntegralN {
                value: fine,
                error,
                evaluations,
                converged: converged && all_inner_converged,
            };
        }
        if m >= 512 {
            // Not smooth enough in x for the trapezoid rule (a breakpoint entering the range,
            // say): finish with nested adaptive rules and keep the better answer.
            let nested =
                integrate_2d_split_n(&mut f, (ax, ax + period), (ay, by), &mut breaks, tol);
            let evaluations = evaluations + nested.evaluations;
            return if nested.error < error {
                IntegralN {
                    evaluations,
                    ..nested
                }
            } else {
                IntegralN {
                    value: fine,
                    error,
                    evaluations,
                    converged: false,
                }
            };
        }
        coarse = fine;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polynomial_of_degree_22_is_exact_on_one_interval() {
        // K15 integrates polynomials up to degree 22 exactly: x^22 on [0, 1] is 1/23.
        let r = integrate(|x| x.powi(22), 0.0, 1.0, Tolerance::absolute(1e-14));
        assert!((r.value - 1.0 / 23.0).abs() < 1e-15, "{r:?}");
    }

    #[test]
    fn kink_converges_and_error_bounds_truth() {
        // |x - 0.3| on [0, 1]: a kink inside; exact 0.29.
        let r = integrate(|x| (x - 0.3).abs(), 0.0, 1.0, Tolerance::absolute(1e-10));
        assert!(r.converged);
        assert!((r.value - 0.29).abs() <= r.error.max(1e-15), "{r:?}");
        assert!((r.value - 0.29).abs() < 1e-10);
    }

    #[test]
    fn nested_gaussian_matches_closed_form_within_reported_error() {
        // int_0^1 int_0^2 exp(-x y) dy dx = int_0^1 (1 - exp(-2x)) / x dx = Ein(2)
        // Ein(2) = sum_{k>=1} (-1)^(k+1) 2^k / (k k!) = 1.3192633561695...; 1e-15 for rounding.
        let exact: f64 = (1..40)
            .map(|k| {
                let kf = k as f64;
                let fact: f64 = (1..=k).map(|j| j as f64).product();
                (-1f64).powi(k + 1) * 2f64.powi(k) / (kf * fact)
            })
            .sum();
        let r = integrate_2d(
            |x, y| (-x * y).exp(),
            (0.0, 1.0),
            (0.0, 2.0),
            Tolerance::absolute(1e-10),
        );
        assert!(r.converged);
        assert!(
            (r.value - exact).abs() <= r.error + 1e-15,
            "{r:?} vs {exact}"
        );
    }

    #[test]
    fn budget_exhaustion_is_reported() {
        // A discontinuity cannot be integrated to 1e-15 in 3 intervals.
        let r = integrate(
            |x| if x < 0.123 { 0.0 } else { 1.0 },
            0.0,
            1.0,
            Tolerance {
                abs: 1e-15,
                rel: 0.0,
                max_intervals: 3,
            },
        );
        assert!(!r.converged);
        assert!((r.value - 0.877).abs() <= r.error);
    }

    /// n-point Gauss-Legendre integrates x^(2n-2) exactly (2 / (2n - 1)) and its weights sum to 2.
    #[test]
    fn gauss_legendre_is_exact_to_degree_2n_minus_1() {
        for n in [1, 2, 3, 4, 6, 8, 12, 16] {
            let gl = gauss_legendre(n);
            assert_eq!(gl.len(), n);
            let sum: f64 = gl.iter().map(|p| p.1).sum();
            assert!((sum - 2.0).abs() < 1e-13, "n={n} sum={sum}");
            let d = 2 * n as i32 - 2;
            let m: f64 = gl.iter().map(|p| p.1 * p.0.powi(d)).sum();
            assert!((m - 2.0 / (d as f64 + 1.0)).abs() < 1e-13, "n={n} m={m}");
        }
    }

    /// The periodic rule integrates exp(cos x) y^2 over [0, 2 pi] x [0, 1] (= 2 pi I0(1) / 3)
    /// to the tolerance with few points, and reports an error that covers the truth.
    #[test]
    fn periodic_rule_is_accurate_and_cheap() {
        let exact = 2.0 * std::f64::consts::PI * 1.266_065_877_752_008_4 / 3.0;
        for tol in [1e-4, 1e-8, 1e-12] {
            let r = integrate_periodic_split_n(
                |x: f64, y: f64| [x.cos().exp() * y * y],
                (0.0, 2.0 * std::f64::consts::PI),
                (0.0, 1.0),
                |_, _| {},
                Tolerance::absolute(tol),
            );
            let actual = (r.value[0] - exact).abs();
            assert!(
                actual <= r.error.max(1e-15) && actual <= tol,
                "tol {tol}: {actual:e} vs {:e}",
                r.error
            );
            assert!(r.evaluations <= 32 * 15, "{} evaluations", r.evaluations);
        }
    }
}
