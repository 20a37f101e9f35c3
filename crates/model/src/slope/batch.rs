//! Batches of facet reflections, in arrays that the widest instruction set the CPU has
//! evaluates: the working arrays, the slope weight and a vectorisable exponential.

use super::facet::*;
use super::ladder::*;
use crate::polarization::Stokes;
use crate::sky::SkyRadiance;

/// The smaller of `a` and `b` for operands that are not NaN: one vector instruction, where
/// `f64::min`'s NaN rule costs several.
#[inline(always)]
pub(super) fn less(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// The second half of a batch of facet reflections ([`SlopeIntegrand::piece`], and
/// `LeafColumns::column` in [`crate::skylight`]): with the points' incident directions, facet
/// frames, `cos beta` and whole weights set in `b` (a point that contributes nothing set by
/// [`FacetBatch::set_idle`]: weight 0 and a ray every sky is finite for), the sky in
/// the facet frames ([`SkyRadiance::stokes_in_frame_batch`]) and [`facet_reflection_cs`],
/// summed into `sum`. `real_eps` is `Re eps` of a dielectric with `eps >= 1`, whose Fresnel
/// terms (`real_amplitudes`' one division) and frame rotation run in a vector loop; other
/// surfaces take `facet_reflection_cs` point by point.
#[inline(always)]
pub(crate) fn reflect_batch<S: SkyRadiance + ?Sized>(
    sky: &S,
    eps: num_complex::Complex64,
    real_eps: Option<f64>,
    b: &mut FacetBatch,
    n: usize,
    sum: &mut [f64; 3],
) {
    sky.stokes_in_frame_batch(
        [&b.dx[..n], &b.dy[..n], &b.dz[..n]],
        [&b.fx[..n], &b.fy[..n], &b.fz[..n]],
        [&mut b.s0[..n], &mut b.s1[..n], &mut b.s2[..n]],
    );
    let Some(er) = real_eps else {
        for i in 0..n {
            if b.w[i] != 0.0 {
                let s = Stokes::new(b.s0[i], b.s1[i], b.s2[i]);
                let v = facet_reflection_cs(eps, b.cos_beta[i], &s, b.c[i], b.sn[i], b.w[i]);
                add_scaled(sum, &v, 1.0);
            }
        }
        return;
    };
    // `facet_reflection_cs` with `real_amplitudes`' one division, for `eps >= 1`.
    for i in 0..n {
        let c = b.cos_beta[i].clamp(0.0, 1.0);
        let sin2 = 1.0 - c * c;
        let root = (er - sin2).sqrt();
        let (ds, dp) = (c + root, er * c + root);
        let den = ds * dp;
        let inv = if den > 0.0 { 1.0 / den } else { 0.0 };
        let (rs, rp) = ((c - root) * dp * inv, (er * c - root) * ds * inv);
        let s = [b.s0[i], b.s1[i], b.s2[i]];
        let r = reflected_stokes((rs * rs, rp * rp, rs * rp), &s, b.c[i], b.sn[i], b.w[i]);
        (b.s0[i], b.s1[i], b.s2[i]) = (r[0], r[1], r[2]);
    }
    for i in 0..n {
        sum[0] += b.s0[i];
        sum[1] += b.s1[i];
        sum[2] += b.s2[i];
    }
}

/// The most points of one [`SlopeIntegrand::piece`]: a piece's Gauss nodes.
pub(crate) const FACET_BATCH: usize = SHARED_MAX_NODES;

/// [`SlopeIntegrand::piece`]'s working arrays, one entry per node.
pub(crate) struct FacetBatch {
    pub(crate) rho: [f64; FACET_BATCH],
    /// The point's whole weight (slope, shadowing, quadrature); 0 off the support.
    pub(crate) w: [f64; FACET_BATCH],
    pub(crate) cos_beta: [f64; FACET_BATCH],
    /// The reflected (incident sky) direction `omega_d`.
    pub(crate) dx: [f64; FACET_BATCH],
    pub(crate) dy: [f64; FACET_BATCH],
    pub(crate) dz: [f64; FACET_BATCH],
    /// The facet frame's `x` (unnormalised, [`SlopeLine`]), its squared length, and its
    /// components along the reflected frame's `x` and `y`.
    pub(crate) fx: [f64; FACET_BATCH],
    pub(crate) fy: [f64; FACET_BATCH],
    pub(crate) fz: [f64; FACET_BATCH],
    pub(crate) f2: [f64; FACET_BATCH],
    pub(crate) c: [f64; FACET_BATCH],
    pub(crate) sn: [f64; FACET_BATCH],
    /// The sky's Stokes vector in the facet frame, then the weighted reflected one.
    pub(crate) s0: [f64; FACET_BATCH],
    pub(crate) s1: [f64; FACET_BATCH],
    pub(crate) s2: [f64; FACET_BATCH],
}

impl FacetBatch {
    /// Point `i` adds nothing (weight 0) and asks the sky for the zenith in the frame `x`: a
    /// ray every sky gives a finite value for, so that the vector loops need no select.
    #[inline(always)]
    pub(crate) fn set_idle(&mut self, i: usize) {
        self.w[i] = 0.0;
        (self.dx[i], self.dy[i], self.dz[i]) = (0.0, 0.0, 1.0);
        (self.fx[i], self.fy[i], self.fz[i]) = (1.0, 0.0, 0.0);
    }

    pub(crate) fn new() -> FacetBatch {
        let z = [0.0; FACET_BATCH];
        FacetBatch {
            rho: z,
            w: z,
            cos_beta: z,
            dx: z,
            dy: z,
            dz: z,
            fx: z,
            fy: z,
            fz: z,
            f2: z,
            c: z,
            sn: z,
            s0: z,
            s1: z,
            s2: z,
        }
    }
}

/// The slope weight `2 t exp(-t^2) / (2 pi)` of [`SlopeIntegrand`]'s measure `dpsi dt`.
#[inline(always)]
pub(crate) fn slope_weight(t: f64) -> f64 {
    t * exp_nonpositive(-t * t) * std::f64::consts::FRAC_1_PI
}

/// `exp(x)` for `x` in `[-708, 0]` (a smaller `x` gives `exp(-708)`), within 2 ulps of libm's
/// (tested over the slope weight's range and beyond), in arithmetic that a loop can vectorise
/// (libm's `exp` is a call). Cody and Waite's reduction `x = k ln 2 + r`, `|r| <= ln 2 / 2`
/// (W. J. Cody and W. Waite, Software Manual for the Elementary Functions, 1980, ch. 6), with
/// `k` rounded by adding `1.5 * 2^52` (its bits then hold `k`), `exp(r)` by its Taylor
/// polynomial to degree 13 (truncation below `(ln 2 / 2)^14 / 14! = 4e-18`; Estrin's split
/// into even and odd parts), and `2^k` put into the exponent field.
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f64) -> f64 {
    // 1.5 * 2^52.
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    // ln 2 in two parts, the first with its low 32 bits zero, so that `k * LN2_HI` is exact for
    // `|k| < 2^20` (fdlibm's split).
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    // Taylor coefficients 1/j!: even j from 12 down to 2, odd j from 13 down to 3.
    const EVEN: [f64; 6] = [
        1.0 / 479_001_600.0,
        1.0 / 3_628_800.0,
        1.0 / 40_320.0,
        1.0 / 720.0,
        1.0 / 24.0,
        0.5,
    ];
    const ODD: [f64; 6] = [
        1.0 / 6_227_020_800.0,
        1.0 / 39_916_800.0,
        1.0 / 362_880.0,
        1.0 / 5_040.0,
        1.0 / 120.0,
        1.0 / 6.0,
    ];
    let x = x.clamp(-708.0, 0.0);
    let shifted = x * std::f64::consts::LOG2_E + SHIFT;
    let k = shifted - SHIFT;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    // `exp(r) - 1 = r + r^2 (E(r^2) + r O(r^2))`: the even and odd parts as two Horner
    // chains in `r^2` that run side by side (half the latency of one chain in `r`).
    let r2 = r * r;
    let (mut even, mut odd) = (EVEN[0], ODD[0]);
    for (e, o) in EVEN[1..].iter().zip(&ODD[1..]) {
        even = even * r2 + e;
        odd = odd * r2 + o;
    }
    let expm1_r = r + r2 * (even + r * odd);
    // `shifted`'s low bits are `k` (two's complement, `-1022 <= k <= 0`); `2^k` is the
    // double of exponent field `k + 1023`.
    let k_bits = shifted.to_bits().wrapping_sub(SHIFT.to_bits());
    let two_k = f64::from_bits(k_bits.wrapping_add(1023) << 52);
    (1.0 + expm1_r) * two_k
}

/// The most Gauss nodes a piece's shared weights hold (`GAUSS_LEVELS`' largest `q`).
pub(super) const SHARED_MAX_NODES: usize = 24;
