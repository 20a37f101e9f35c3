//! The per-pixel kernel: chunks of 512 pixels accumulated into an L1-resident block and
//! finished into the ten output images; bands of rows on scoped threads.

use super::error::ProductsError;
use super::fast_math::fast_aop;
use super::geometry::SetGeometry;
use super::noise::NoiseModel;
use super::planes::Products;
use std::sync::Mutex;

/// The weights of one frame in the hot loop: column `p` of `P`, and `kq`, the gain `K` times
/// the products `[p0 p0, 2 p0 p1, 2 p0 p2, p1 p1, 2 p1 p2, p2 p2]` (the factor 2 is the one
/// the quadratic forms of [`finalize`] need, folded in here).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(super) struct FrameWeights {
    pub(super) p: [f32; 3],
    pub(super) kq: [f32; 6],
}

/// Everything the hot loop needs, in f32, built once per call.
///
/// With `e_i = max(y_i - offset, 0)`, `C = P diag(K e + read_var) P^T
/// = read_var P P^T + sum_i e_i K p_i p_i^T`: the accumulators start at
/// `c_init = read_var P P^T` (same packing as `kq`) and each frame adds `kq_i e_i`. In a chunk
/// where no frame value is below the offset, `e_i = y_i - offset` and the offset term is
/// folded into the start value instead (`c_init_unclamped`).
#[derive(Debug, Clone)]
pub(super) struct Kernel {
    pub(super) w: Vec<FrameWeights>,
    /// `P 1`: `S = P y - dark P 1`, so the frames enter S undarkened and the dark level is
    /// subtracted once per pixel.
    pub(super) sigma: [f32; 3],
    /// `sigma[1] == sigma[2] == 0` (the usual case): only S0 needs the dark correction.
    pub(super) sigma12_zero: bool,
    pub(super) c_init: [f32; 6],
    /// `c_init - offset sum_i kq_i`: the start of `C` when no frame value of the chunk is
    /// below the offset, so that `C += kq_i y_i` needs no clamp.
    pub(super) c_init_unclamped: [f32; 6],
    pub(super) off: f32,
    pub(super) lo: u32,
    pub(super) sat: u16,
}

impl Kernel {
    pub(super) fn new(geometry: &SetGeometry, noise: &NoiseModel) -> Kernel {
        let k = noise.gain_dn_per_e;
        let pack = |p: &[f64; 3]| {
            [
                p[0] * p[0],
                2.0 * p[0] * p[1],
                2.0 * p[0] * p[2],
                p[1] * p[1],
                2.0 * p[1] * p[2],
                p[2] * p[2],
            ]
        };
        let mut m = [0.0f64; 6];
        let w = geometry
            .pinv
            .iter()
            .map(|p| {
                let q = pack(p);
                for (mi, qi) in m.iter_mut().zip(q) {
                    *mi += qi;
                }
                FrameWeights {
                    p: p.map(|v| v as f32),
                    kq: q.map(|v| (k * v) as f32),
                }
            })
            .collect();
        let off = noise.offset_dn;
        // sigma = P 1, the weight of a constant (the dark level) in S. For rows with a common
        // first entry (any analyzer whose transmittance does not depend on its angle),
        // sigma = [1 / a_0, 0, 0]: the zero entries are exact after the snapping of P.
        let sigma = geometry.pinv.iter().fold([0.0f64; 3], |acc, p| {
            [acc[0] + p[0], acc[1] + p[1], acc[2] + p[2]]
        });
        let p_max = geometry
            .pinv
            .iter()
            .flat_map(|c| c.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        let sigma = sigma.map(|v| if v.abs() < 1e-12 * p_max { 0.0 } else { v });
        Kernel {
            w,
            sigma: sigma.map(|v| v as f32),
            sigma12_zero: sigma[1] == 0.0 && sigma[2] == 0.0,
            c_init: m.map(|v| (noise.read_var_dn2 * v) as f32),
            c_init_unclamped: m.map(|v| ((noise.read_var_dn2 - k * off) * v) as f32),
            off: off as f32,
            // The smallest integer frame value with y - offset >= 0 (65536: none).
            lo: off.ceil().clamp(0.0, 65536.0) as u32,
            sat: noise.saturation_dn,
        }
    }
}

/// One pixel's accumulators: S and the covariance entries (`c01`, `c02`, `c12` doubled).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Acc {
    pub(super) s0: f32,
    pub(super) s1: f32,
    pub(super) s2: f32,
    pub(super) c00: f32,
    pub(super) c01x2: f32,
    pub(super) c02x2: f32,
    pub(super) c11: f32,
    pub(super) c12x2: f32,
    pub(super) c22: f32,
}

impl Acc {
    /// The accumulators before the first frame: `c` is [`Kernel::c_init`] or
    /// [`Kernel::c_init_unclamped`].
    #[inline(always)]
    pub(super) fn start(c: [f32; 6]) -> Acc {
        // -0.0 so that adding the first frame is exact and the compiler can drop the add.
        Acc {
            s0: -0.0,
            s1: -0.0,
            s2: -0.0,
            c00: c[0],
            c01x2: c[1],
            c02x2: c[2],
            c11: c[3],
            c12x2: c[4],
            c22: c[5],
        }
    }

    /// Subtracts the dark level from S once all frames are in: `S = P y - dark P 1`
    /// (`SIGMA12_ZERO`: only S0 has a non-zero `P 1` entry).
    #[inline(always)]
    pub(super) fn subtract_dark<const SIGMA12_ZERO: bool>(&mut self, dark: f32, sigma: &[f32; 3]) {
        self.s0 -= dark * sigma[0];
        if !SIGMA12_ZERO {
            self.s1 -= dark * sigma[1];
            self.s2 -= dark * sigma[2];
        }
    }

    /// Adds one frame value (S without the dark level, see [`Acc::subtract_dark`]).
    /// `CLAMP`: `e = max(y - offset, 0)` (start from `c_init`); otherwise `e = y` (start from
    /// `c_init_unclamped`; only when `y >= offset`).
    #[inline(always)]
    pub(super) fn add<const CLAMP: bool>(&mut self, y: u16, w: &FrameWeights, off: f32) {
        let yf = f32::from(y);
        let e = if CLAMP {
            let e = yf - off;
            if e > 0.0 {
                e
            } else {
                0.0
            }
        } else {
            yf
        };
        self.s0 += w.p[0] * yf;
        self.s1 += w.p[1] * yf;
        self.s2 += w.p[2] * yf;
        self.c00 += w.kq[0] * e;
        self.c01x2 += w.kq[1] * e;
        self.c02x2 += w.kq[2] * e;
        self.c11 += w.kq[3] * e;
        self.c12x2 += w.kq[4] * e;
        self.c22 += w.kq[5] * e;
    }
}

/// A pixel's ten outputs in [`Products::names`] order (saturation is handled by the caller,
/// [`fix_saturated`]).
///
/// Branch-free (every condition is a select or a bit operation), so that the pixel loops
/// vectorise. An undefined output gets a NaN added (`x + NaN = NaN`, `x + 0 = x`).
#[inline(always)]
pub(super) fn finalize(a: &Acc) -> [f32; 10] {
    let nan = f32::NAN;
    let (s0, s1, s2) = (a.s0, a.s1, a.s2);
    let (c00, c11, c22) = (a.c00, a.c11, a.c22);
    let sig0 = c00.sqrt();
    let sig1 = c11.sqrt();
    let sig2 = c22.sqrt();
    let s1s1 = s1 * s1;
    let s2s2 = s2 * s2;
    let l2 = s1s1 + s2s2;
    let l = l2.sqrt();
    let has_l = l2 >= f32::MIN_POSITIVE;
    // Unit direction (u, v) = (S1, S2) / L: uu = u^2, vv = v^2, uv = u v; at L = 0 the
    // direction is undefined and its average over directions is used (uu = vv = 1/2, uv = 0).
    let inv_l2 = if has_l { 1.0 / l2 } else { 0.0 };
    let z0 = if has_l { 0.0 } else { 0.5 };
    let uu = s1s1 * inv_l2 + z0;
    let vv = s2s2 * inv_l2 + z0;
    let uv = s1 * s2 * inv_l2;
    // Variance of the polarised intensity L along (u, v), and across: C_LL + C_TT = C11 + C22.
    let c_ll = uu * c11 + vv * c22 + uv * a.c12x2;
    let c_tt = (c11 + c22) - c_ll;
    let inv_s0 = 1.0 / s0;
    let p = l * inv_s0;
    // S0^2 var(p) = p^2 C00 - 2 (S1 C01 + S2 C02) / S0 + C_LL (the grad p of the module
    // doc times S0; the factors 2 are folded into the accumulators).
    let vp = inv_s0 * (inv_s0 * (l2 * c00) - (s1 * a.c01x2 + s2 * a.c02x2)) + c_ll;
    let vp = if vp > 0.0 { vp } else { 0.0 };
    let sig_p = vp.sqrt() * inv_s0;
    // 4 L^2 var(AoP) = u^2 C22 + v^2 C11 - 2 u v C12 = C_TT.
    let va = if c_tt > 0.0 { c_tt } else { 0.0 };
    let sig_a = va.sqrt() * (0.5 * l * inv_l2);
    let aop = fast_aop(s1, s2, l);
    // Only the divisions by S0 can overflow (an S0 below ~1e-30 DN, which integer frames do
    // not produce): such a value saturates at f32::MAX instead of becoming infinite.
    let p = if p < f32::MAX { p } else { f32::MAX };
    let sig_p = if sig_p < f32::MAX { sig_p } else { f32::MAX };
    let nan_p = if s0 >= f32::MIN_POSITIVE { 0.0 } else { nan };
    let nan_l = if has_l { 0.0 } else { nan };
    [
        s0,
        s1,
        s2,
        p + nan_p,
        aop + nan_l,
        sig0,
        sig1,
        sig2,
        sig_p + nan_p,
        sig_a + nan_l,
    ]
}

/// Whether every frame value over `start..start + len` is in `lo..sat` (at or above the
/// offset and not saturated): per value a wrapping subtraction, a saturating subtraction and
/// an OR (vectorised, 8 values per instruction).
pub(super) fn chunk_in_range(
    frames: &[&[u16]],
    start: usize,
    len: usize,
    lo: u32,
    sat: u16,
) -> bool {
    let sat = u32::from(sat);
    if lo >= sat {
        return false;
    }
    // With t = y - lo (mod 2^16): y < lo gives t >= 2^16 - lo > sat - lo, so "outside" is
    // exactly t >= sat - lo = span.
    let (lo, span_m1) = (lo as u16, (sat - lo - 1) as u16);
    let mut outside = 0u16;
    for f in frames.iter().filter_map(|f| f.get(start..start + len)) {
        outside |= f.iter().fold(0u16, |acc, &y| {
            acc | y.wrapping_sub(lo).saturating_sub(span_m1)
        });
    }
    outside == 0
}

/// The smallest and largest values of the frames over `start..start + len` (vectorised
/// reductions). They choose the chunk's accumulation (no clamp at the offset when the
/// smallest is at or above it) and whether it has saturated pixels to fix with
/// [`fix_saturated`] (the pixel loops do not test for saturation).
pub(super) fn chunk_range(frames: &[&[u16]], start: usize, len: usize) -> (u16, u16) {
    let mut lowest = u16::MAX;
    let mut highest = 0u16;
    for f in frames.iter().filter_map(|f| f.get(start..start + len)) {
        let (lo, hi) = f
            .iter()
            .fold((u16::MAX, 0u16), |(lo, hi), &y| (lo.min(y), hi.max(y)));
        lowest = lowest.min(lo);
        highest = highest.max(hi);
    }
    (lowest, highest)
}

/// Sets all ten outputs of the saturated pixels of a chunk (any frame value
/// `>= saturation_dn`) to NaN; returns their number.
pub(super) fn fix_saturated(
    frames: &[&[u16]],
    start: usize,
    chunk: OutSlices<'_>,
    saturation_dn: u16,
) -> u64 {
    let mut count = 0;
    let [o0, o1, o2, o3, o4, o5, o6, o7, o8, o9] = chunk.s;
    for j in 0..o0.len() {
        let sat = frames
            .iter()
            .any(|f| f.get(start + j).is_some_and(|&y| y >= saturation_dn));
        if sat {
            count += 1;
            for o in [
                &mut *o0, &mut *o1, &mut *o2, &mut *o3, &mut *o4, &mut *o5, &mut *o6, &mut *o7,
                &mut *o8, &mut *o9,
            ] {
                if let Some(v) = o.get_mut(j) {
                    *v = f32::NAN;
                }
            }
        }
    }
    count
}

/// The dark level of the pixels of a band: a constant or a slice.
pub(super) trait DarkSource: Copy + Send + Sync {
    /// Restricts to `start..start + len` (None when out of range).
    fn sub(self, start: usize, len: usize) -> Option<Self>;
    /// The dark level of pixel `j` (of the sub-range).
    fn at(&self, j: usize) -> f32;
}

#[derive(Clone, Copy)]
pub(super) struct ScalarDark(pub(super) f32);

impl DarkSource for ScalarDark {
    #[inline(always)]
    fn sub(self, _start: usize, _len: usize) -> Option<Self> {
        Some(self)
    }
    #[inline(always)]
    fn at(&self, _j: usize) -> f32 {
        self.0
    }
}

#[derive(Clone, Copy)]
pub(super) struct MapDark<'a>(pub(super) &'a [f32]);

impl DarkSource for MapDark<'_> {
    #[inline(always)]
    fn sub(self, start: usize, len: usize) -> Option<Self> {
        self.0.get(start..start.checked_add(len)?).map(MapDark)
    }
    #[inline(always)]
    fn at(&self, j: usize) -> f32 {
        self.0[j]
    }
}

/// The ten output slices of one band (or block), each of the same length.
pub(super) struct OutSlices<'a> {
    pub(super) s: [&'a mut [f32]; 10],
}

impl<'a> OutSlices<'a> {
    /// Splits off the first `len` pixels of every image.
    pub(super) fn split_first(self, len: usize) -> Option<(OutSlices<'a>, OutSlices<'a>)> {
        if self.s.iter().any(|s| s.len() < len) {
            return None;
        }
        let mut head: [&'a mut [f32]; 10] = Default::default();
        let mut tail: [&'a mut [f32]; 10] = Default::default();
        for ((s, h), t) in self.s.into_iter().zip(&mut head).zip(&mut tail) {
            let (a, b) = s.split_at_mut(len);
            *h = a;
            *t = b;
        }
        Some((OutSlices { s: head }, OutSlices { s: tail }))
    }
}

/// The internal invariant "all slices have the band's length" failed (unreachable after
/// validation; reported instead of panicking).
#[derive(Debug)]
pub(super) struct LengthMismatch;

/// Pixels per chunk: the accumulators of a chunk ([`AccBlock`], 9 x 4 x 512 B = 18 KiB)
/// stay in L1 between the accumulation and the output pass.
pub(super) const CHUNK: usize = 512;

/// Structure-of-arrays accumulators of one chunk.
pub(super) struct AccBlock {
    pub(super) s0: [f32; CHUNK],
    pub(super) s1: [f32; CHUNK],
    pub(super) s2: [f32; CHUNK],
    pub(super) c00: [f32; CHUNK],
    pub(super) c01x2: [f32; CHUNK],
    pub(super) c02x2: [f32; CHUNK],
    pub(super) c11: [f32; CHUNK],
    pub(super) c12x2: [f32; CHUNK],
    pub(super) c22: [f32; CHUNK],
}

impl AccBlock {
    pub(super) fn new() -> AccBlock {
        AccBlock {
            s0: [0.0; CHUNK],
            s1: [0.0; CHUNK],
            s2: [0.0; CHUNK],
            c00: [0.0; CHUNK],
            c01x2: [0.0; CHUNK],
            c02x2: [0.0; CHUNK],
            c11: [0.0; CHUNK],
            c12x2: [0.0; CHUNK],
            c22: [0.0; CHUNK],
        }
    }

    #[inline(always)]
    pub(super) fn load(&self, j: usize) -> Acc {
        Acc {
            s0: self.s0[j],
            s1: self.s1[j],
            s2: self.s2[j],
            c00: self.c00[j],
            c01x2: self.c01x2[j],
            c02x2: self.c02x2[j],
            c11: self.c11[j],
            c12x2: self.c12x2[j],
            c22: self.c22[j],
        }
    }

    #[inline(always)]
    pub(super) fn store(&mut self, j: usize, a: &Acc) {
        self.s0[j] = a.s0;
        self.s1[j] = a.s1;
        self.s2[j] = a.s2;
        self.c00[j] = a.c00;
        self.c01x2[j] = a.c01x2;
        self.c02x2[j] = a.c02x2;
        self.c11[j] = a.c11;
        self.c12x2[j] = a.c12x2;
        self.c22[j] = a.c22;
    }
}

/// Accumulation of a chunk, `G` frames fused in one pass (the frame loop is unrolled).
///
/// The pixel loops of the kernels index several slices of the same, hoisted length: the form
/// the vectoriser handles best (hence the `needless_range_loop` allowances).
#[allow(clippy::needless_range_loop)]
pub(super) fn accumulate_fused<
    const G: usize,
    const CLAMP: bool,
    const SIGMA12_ZERO: bool,
    D: DarkSource,
>(
    acc: &mut AccBlock,
    frames: &[&[u16]],
    start: usize,
    len: usize,
    dark: D,
    kernel: &Kernel,
) -> Result<(), LengthMismatch> {
    let len = len.min(CHUNK);
    let mut fr: [&[u16]; G] = [&[]; G];
    let mut w = [FrameWeights::default(); G];
    for i in 0..G {
        fr[i] = frames
            .get(i)
            .and_then(|f| f.get(start..start + len))
            .ok_or(LengthMismatch)?;
        w[i] = *kernel.w.get(i).ok_or(LengthMismatch)?;
    }
    let dk = dark.sub(start, len).ok_or(LengthMismatch)?;
    let off = kernel.off;
    let c = if CLAMP {
        kernel.c_init
    } else {
        kernel.c_init_unclamped
    };
    let sigma = kernel.sigma;
    for j in 0..len {
        let mut a = Acc::start(c);
        for i in 0..G {
            a.add::<CLAMP>(fr[i][j], &w[i], off);
        }
        a.subtract_dark::<SIGMA12_ZERO>(dk.at(j), &sigma);
        acc.store(j, &a);
    }
    Ok(())
}

/// Accumulation of a chunk, any number of frames: one pass per frame (always clamping, and
/// the dark level subtracted from all three of S). The same operations in the same order as
/// [`accumulate_fused`] with `CLAMP` and not `SIGMA12_ZERO` (so the same results).
#[allow(clippy::needless_range_loop)]
pub(super) fn accumulate_per_frame<D: DarkSource>(
    acc: &mut AccBlock,
    frames: &[&[u16]],
    start: usize,
    len: usize,
    dark: D,
    kernel: &Kernel,
) -> Result<(), LengthMismatch> {
    let len = len.min(CHUNK);
    let dk = dark.sub(start, len).ok_or(LengthMismatch)?;
    let init = Acc::start(kernel.c_init);
    for j in 0..len {
        acc.store(j, &init);
    }
    for (f, w) in frames.iter().zip(&kernel.w) {
        let y = f.get(start..start + len).ok_or(LengthMismatch)?;
        for j in 0..len {
            let mut a = acc.load(j);
            a.add::<true>(y[j], w, kernel.off);
            acc.store(j, &a);
        }
    }
    for j in 0..len {
        let mut a = acc.load(j);
        a.subtract_dark::<false>(dk.at(j), &kernel.sigma);
        acc.store(j, &a);
    }
    Ok(())
}

/// The output pass of a chunk: [`finalize`] of every pixel into the ten images.
pub(super) fn finalize_chunk(
    acc: &AccBlock,
    chunk: &mut OutSlices<'_>,
) -> Result<(), LengthMismatch> {
    let [o0, o1, o2, o3, o4, o5, o6, o7, o8, o9] = &mut chunk.s;
    let len = o0.len().min(CHUNK);
    let q0 = o0.get_mut(..len).ok_or(LengthMismatch)?;
    let q1 = o1.get_mut(..len).ok_or(LengthMismatch)?;
    let q2 = o2.get_mut(..len).ok_or(LengthMismatch)?;
    let q3 = o3.get_mut(..len).ok_or(LengthMismatch)?;
    let q4 = o4.get_mut(..len).ok_or(LengthMismatch)?;
    let q5 = o5.get_mut(..len).ok_or(LengthMismatch)?;
    let q6 = o6.get_mut(..len).ok_or(LengthMismatch)?;
    let q7 = o7.get_mut(..len).ok_or(LengthMismatch)?;
    let q8 = o8.get_mut(..len).ok_or(LengthMismatch)?;
    let q9 = o9.get_mut(..len).ok_or(LengthMismatch)?;
    for j in 0..len {
        let o = finalize(&acc.load(j));
        q0[j] = o[0];
        q1[j] = o[1];
        q2[j] = o[2];
        q3[j] = o[3];
        q4[j] = o[4];
        q5[j] = o[5];
        q6[j] = o[6];
        q7[j] = o[7];
        q8[j] = o[8];
        q9[j] = o[9];
    }
    Ok(())
}

/// One band (a contiguous range of pixels; `frames` and `dark` restricted to it), chunk by
/// chunk: accumulation (fused for 3, 4, 5, 6 and 8 frames), output pass, and the
/// saturated pixels of the rare chunks that have one. Returns the saturated count.
///
/// Splitting each chunk into an accumulation loop and an output loop (through the L1-resident
/// [`AccBlock`]) costs 18 loads and stores per 4 pixels but gives two shorter loops that the
/// processor overlaps better than one long one: 5 % faster in the benchmark.
pub(super) fn run_band<D: DarkSource>(
    out: OutSlices<'_>,
    frames: &[&[u16]],
    dark: D,
    kernel: &Kernel,
) -> Result<u64, LengthMismatch> {
    let n = out.s[0].len();
    let mut acc = Box::new(AccBlock::new());
    let mut saturated = 0u64;
    let mut rest = out;
    let mut start = 0;
    while start < n {
        let len = (n - start).min(CHUNK);
        let (mut chunk, tail) = rest.split_first(len).ok_or(LengthMismatch)?;
        rest = tail;
        // Usually every value is in [offset, saturation): one cheap test. Otherwise the
        // exact range decides the clamp and the saturation fix-up.
        let (lowest, highest) = if chunk_in_range(frames, start, len, kernel.lo, kernel.sat) {
            (u16::MAX, 0)
        } else {
            chunk_range(frames, start, len)
        };
        let clamp = u32::from(lowest) < kernel.lo;
        let a = &mut acc;
        macro_rules! fused {
            ($g:literal) => {
                match (clamp, kernel.sigma12_zero) {
                    (true, true) => {
                        accumulate_fused::<$g, true, true, D>(a, frames, start, len, dark, kernel)?
                    }
                    (true, false) => {
                        accumulate_fused::<$g, true, false, D>(a, frames, start, len, dark, kernel)?
                    }
                    (false, true) => {
                        accumulate_fused::<$g, false, true, D>(a, frames, start, len, dark, kernel)?
                    }
                    (false, false) => accumulate_fused::<$g, false, false, D>(
                        a, frames, start, len, dark, kernel,
                    )?,
                }
            };
        }
        match frames.len() {
            3 => fused!(3),
            4 => fused!(4),
            5 => fused!(5),
            6 => fused!(6),
            8 => fused!(8),
            _ => accumulate_per_frame(a, frames, start, len, dark, kernel)?,
        }
        finalize_chunk(&acc, &mut chunk)?;
        if highest >= kernel.sat {
            saturated += fix_saturated(frames, start, chunk, kernel.sat);
        }
        start += len;
    }
    Ok(saturated)
}

/// Bands per thread (at most; whole rows).
pub(super) const BANDS_PER_THREAD: usize = 8;

/// Below this many pixels per thread, extra threads cost more than they save.
pub(super) const MIN_PIXELS_PER_THREAD: usize = 16_384;

/// Splits the outputs into bands of `band_len` pixels and runs them on scoped threads (the
/// first on the calling thread).
pub(super) fn run_bands<D: DarkSource>(
    out: &mut Products,
    frames: &[&[u16]],
    dark: D,
    kernel: &Kernel,
    band_len: usize,
    threads: usize,
) -> Result<u64, ProductsError> {
    let n = out.pixel_count();
    let band_len = band_len.max(1);
    let mut chunks = out.images_mut().map(|v| v.chunks_mut(band_len));
    let mut jobs = Vec::new();
    let mut start = 0;
    while start < n {
        let s: [&mut [f32]; 10] = chunks.each_mut().map(|c| c.next().unwrap_or_default());
        let len = s[0].len();
        let band_frames: Option<Vec<&[u16]>> =
            frames.iter().map(|f| f.get(start..start + len)).collect();
        let band_frames = band_frames.ok_or(ProductsError::Worker)?;
        let band_dark = dark.sub(start, len).ok_or(ProductsError::Worker)?;
        jobs.push((OutSlices { s }, band_frames, band_dark));
        start += len;
    }
    // A shared queue of bands, taken in image order: every thread (the calling one
    // included) takes bands until none is left, so a slow thread (a shared core) or one that
    // cannot be spawned costs time, not a result.
    jobs.reverse();
    let queue = Mutex::new(jobs);
    let work = || -> Result<u64, LengthMismatch> {
        let mut total = 0u64;
        loop {
            let job = match queue.lock() {
                Ok(mut q) => q.pop(),
                Err(poisoned) => poisoned.into_inner().pop(),
            };
            let Some((o, f, d)) = job else {
                return Ok(total);
            };
            total += run_band(o, &f, d, kernel)?;
        }
    };
    let helpers = queue
        .lock()
        .map_or(0, |q| q.len().min(threads).saturating_sub(1));
    std::thread::scope(|scope| {
        let handles: Vec<_> = (0..helpers)
            .filter_map(|_| {
                std::thread::Builder::new()
                    .name("polar-products".into())
                    .spawn_scoped(scope, work)
                    .ok()
            })
            .collect();
        let mut total = work().map_err(|_| ProductsError::Worker)?;
        for h in handles {
            total += h
                .join()
                .map_err(|_| ProductsError::Worker)?
                .map_err(|_| ProductsError::Worker)?;
        }
        Ok(total)
    })
}
