//! Live Stokes products with a per-pixel predicted sigma.
//!
//! From one angle set of `N >= 3` raw frames (u16, row-major, all `width x height`) taken
//! through a linear analyzer at known angles, [`compute_into`] computes per pixel, in
//! parallel over row bands, the f32 images
//! `S0, S1, S2` (DN, dark-subtracted), DoLP, AoP (radians, in `(-pi/2, pi/2)`) and their
//! predicted standard deviations `sigma_s0, sigma_s1, sigma_s2, sigma_dolp, sigma_aop_rad`
//! (see [`Products`]).
//!
//! # Model
//!
//! Conventions and statistics are those of `docs/MODEL.md` sections 0, 6 and 7.
//!
//! - **Measurement.** Frame `i`'s pixel value is `y_i = a_i . S + dark_dn + noise`, with `a_i`
//!   the analyzer's row (`A` is the `N x 3` matrix of rows). An ideal polarizer at `psi` has
//!   `a = 0.5 [1, cos 2psi, sin 2psi]` ([`SetGeometry::ideal`]); a real analyzer's rows
//!   (extinction, angle offset, fore-optics) are passed as they are ([`SetGeometry::new`]):
//!   nothing here assumes an ideal analyzer.
//! - **Estimate.** `S_hat = P (y - dark_dn)` with `P = (A^T A)^-1 A^T`, the `3 x N`
//!   pseudo-inverse (ordinary least squares), computed once per set in f64 with nalgebra.
//!   A set whose `A^T A` has a reciprocal condition number below [`MIN_RCOND`] (`1e-10`) is
//!   rejected with an error naming the angles (fewer than 3 distinct angles modulo 180 deg).
//!   `dark_dn` is `offset + K * dark electrons`, a scalar or a per-pixel map ([`Dark`]).
//! - **Frame noise** (EMVA 1288, in DN): `var(y) = K max(y - offset_dn, 0) + read_var_dn2`,
//!   `K` = [`NoiseModel::gain_dn_per_e`], `read_var_dn2 = K^2 sigma_read_e^2 + 1/12`
//!   (quantisation). The variance is evaluated at the measured `y` (the only estimate of its
//!   mean available live). Frames are independent in time.
//! - **Stokes covariance.** `Cov(S_hat) = P diag(var) P^T` (6 unique entries `C_kl`);
//!   `sigma_s_k = sqrt(C_kk)`.
//! - **DoLP and AoP.** `L = sqrt(S1^2 + S2^2)`, `p = L / S0`, `AoP = 0.5 atan2(S2, S1)`.
//!   Their sigma is first order (Taylor, delta method) from the full 3x3 covariance:
//!   `grad p = [-p/S0, S1/(S0 L), S2/(S0 L)]`, `var p = grad^T C grad`;
//!   `var AoP = (S1^2 C22 + S2^2 C11 - 2 S1 S2 C12) / (4 L^4)`.
//!   This is the **first-order regime**: it is valid when the polarised SNR `L / sigma_L` is
//!   about 10 or more. Below that the DoLP estimate is Rice-distributed and biased upwards
//!   (an unpolarised pixel does not give DoLP 0) and these sigmas are optimistic; the offline
//!   analysis has the Rice regime in `polar_model::stats`.
//!
//! # Special pixels (never a panic, never an infinity)
//!
//! - **Saturated**: any frame value `>= saturation_dn` makes all ten outputs NaN for that
//!   pixel; [`Products::saturated`] counts them.
//! - **`S0 <= 0`** (a dark pixel after dark subtraction; in f32 any `S0 < f32::MIN_POSITIVE`):
//!   DoLP and `sigma_dolp` are NaN (a ratio to a non-positive intensity is undefined); S,
//!   their sigmas, AoP and `sigma_aop_rad` stay defined.
//! - **`L == 0`** (exactly unpolarised; in f32 any `S1^2 + S2^2 < f32::MIN_POSITIVE`): DoLP is
//!   0, AoP and `sigma_aop_rad` are NaN (the angle is undefined), and `sigma_dolp` uses the
//!   gradient averaged over the undefined direction, `var p = (C11 + C22) / (2 S0^2)` (the
//!   first-order result is direction-dependent there).
//! - DoLP and `sigma_dolp` saturate at `f32::MAX` instead of overflowing (reachable only with
//!   a positive S0 below ~1e-30 DN, which integer frames do not produce).
//! - A non-finite entry in a dark map gives NaN outputs for its pixel.
//! - AoP lies in `[-1.5707962, 1.5707962]` (f32), strictly inside `(-pi/2, pi/2)`; both ends
//!   are the vertical direction.
//!
//! # Speed
//!
//! The benchmark (`cargo bench -p polar-engine --bench products`: 4 frames of 2448 x 2048)
//! compares [`compute_into`] with [`compute_reference`], a plain single-threaded f64 version
//! with `f64::atan2`, and prints the speed-up and the largest difference. On the 2-core
//! development VM (Xeon, SSE2 code): 17.5 to 19 ms per set with 2 threads (35 ms with one),
//! the reference 380 to 400 ms (a speed-up of about 21); the fast path is within 1.3e-5 of
//! the predicted sigma of the reference for S and 8e-5 for AoP. How the hot path is made
//! fast:
//!
//! - f32 throughout, structure of arrays, no allocation per pixel (one 18 KiB block per
//!   band), output buffers reused across calls ([`Products`] is resized only when the image
//!   size changes).
//! - Chunks of 512 pixels: an accumulation loop (the `N` frames fused and unrolled for `N` in
//!   3, 4, 5, 6, 8; one pass per frame otherwise) into an L1-resident block, then an output
//!   loop. Both are branch-free index loops over slices of hoisted length, which the compiler
//!   vectorises (checked in the disassembly: `mulps`, `sqrtps`, `divps` on 4 lanes, about
//!   135 + 130 instructions per 4 pixels for `N = 4`). The workspace forbids `unsafe`, so
//!   there is no run-time dispatch to AVX: the default x86-64 target gives SSE2.
//! - `C = read_var P P^T + K sum_i max(y_i - offset, 0) p_i p_i^T`: the constant part is
//!   computed once per call and each frame adds 6 products. A chunk whose frame values are
//!   all at or above the offset (the usual case) skips the clamp: `C` starts at
//!   `(read_var - K offset) P P^T` and each frame adds `K y_i p_i p_i^T`.
//! - `S = P (y - dark) = P y - dark P 1`: the frames enter undarkened and the dark level is
//!   subtracted once per pixel, from S0 alone when `P 1 = [1 / a_0, 0, 0]` (rows with a
//!   common first entry: any analyzer whose transmittance does not depend on its angle).
//! - AoP by the half-angle form [`fast_aop`] (one division, sign-bit operations, no octant
//!   branches, the minimax polynomial [`ATAN_COEFFS`] evaluated by Estrin's scheme);
//!   [`fast_atan2`] is the general-purpose form of the same polynomial.
//! - One vectorised test per chunk (every value in `[offset, saturation)`, 3 instructions
//!   per 8 values) chooses the accumulation; saturation is not tested in the pixel loops:
//!   only the rare chunks with a saturated pixel get a scalar fix-up pass.
//! - Bands of rows (8 per thread; row-major pixel ranges cut at chunk boundaries, not
//!   necessarily at row ends) on `std::thread::scope` threads that take them from a queue:
//!   threads = `available_parallelism`, capped by the caller's `threads`. The chunks are the
//!   same for every band split and each pixel's arithmetic depends only on its chunk, so the
//!   result is bit-identical for any thread count.
//!
//! # Precision of the f32 path
//!
//! Every per-pixel quantity is computed in f32 (relative rounding `6e-8` per operation).
//! For DN values up to 65535 the absolute error of S is a few `1e-3` DN, far below the
//! quantisation floor of the noise (`sqrt(1/12) = 0.29` DN per frame); the benchmark prints
//! the largest difference from the f64 reference in units of the predicted sigma (about
//! `1e-4` sigma). `sigma_dolp` loses more where its quadratic form cancels (DoLP near 1:
//! up to `1e-3` relative), irrelevant for a predicted sigma.
//!
//! The AoP error, [`AOP_MAX_ERROR_RAD`] = 6e-7 rad (measured), is far below any
//! `sigma_aop_rad` a real pixel can have: with an ideal analyzer, `var(S1) >= K S0` (shot
//! noise) and `L <= S0`, so `sigma_aop >= 0.5 sqrt(K / S0) = 0.5 / sqrt(S0 in electrons)`,
//! and `S0 <= 2 x full well`: `sigma_aop >= 0.35 / sqrt(full well)`, 1.1e-3 rad for
//! 1e5 e- and 3.5e-4 rad for 1e6 e- (over 500 times the error). Even without shot noise
//! (quantisation alone, the largest `L`) `sigma_aop >= 0.29 / (2 x 65535) = 2.2e-6` rad.

use std::f32::consts::{FRAC_PI_2 as FRAC_PI_2_F32, PI as PI_F32};
use std::sync::Mutex;

use nalgebra::{DMatrix, Matrix3};

/// Smallest reciprocal condition number of `A^T A` ([`SetGeometry`]) accepted:
/// `lambda_min / lambda_max = (s_min / s_max)^2` of the rows matrix `A`.
pub const MIN_RCOND: f64 = 1e-10;

/// Allowed range of the largest absolute entry of the analyzer rows (DN per Stokes unit;
/// an ideal polarizer's rows have 0.5). Outside it the f32 products could lose range.
pub const ROW_SCALE_RANGE: (f64, f64) = (1e-3, 1e3);

/// The maximum absolute error of [`fast_atan2`] against f64 `atan2` of the same f32 inputs,
/// in radians, including the f32 rounding of the result. Measured by the unit test
/// `atan2_error_is_measured_and_below_the_const` on a dense grid (2 million directions at 3
/// magnitudes, the reduced argument on `[0, 1]` in steps of 1e-6, the axes): 5.67e-7; a
/// search over 3e8 random f32 pairs found 5.88e-7. The const rounds up.
pub const ATAN2_MAX_ERROR_RAD: f64 = 7e-7;

/// The maximum absolute error of the AoP the products report ([`fast_aop`], the half-angle
/// form the hot loop uses) against f64 `0.5 atan2(S2, S1)` of the same f32 `S1, S2`, modulo
/// pi, in radians, including the f32 rounding of `L`. Measured by the unit test
/// `aop_error_is_measured_and_below_the_const` (2 million directions at 4 magnitudes, the
/// axes, signed zeros): 5.00e-7; a search over 3e8 random f32 pairs found 5.11e-7. The
/// const rounds up. See the module doc for how it compares with `sigma_aop_rad`.
pub const AOP_MAX_ERROR_RAD: f64 = 6e-7;

/// Coefficients `c0..c6` of `atan z ~ z (c0 + c1 z^2 + c2 z^4 + ... + c6 z^12)` for
/// `0 <= z <= 1` (odd, so also for `-1 <= z <= 0`): the minimax (equal-ripple) polynomial of
/// degree 13 for the absolute error, derived with the Remez exchange algorithm (8 reference
/// points, f64 solves, error extrema on a 2e5-point grid, iterated to convergence). Its
/// exact-arithmetic max error is 2.47e-7 rad; evaluated in f32 (Estrin's scheme, as
/// [`fast_atan2`] and [`fast_aop`] do) it is 3.8e-7 (1e8 points on `[0, 1]`). Check of the
/// derivation: the same procedure at degree 9 reproduces Abramowitz and Stegun, *Handbook
/// of Mathematical Functions* (1964), 4.4.47 (0.9998660, -0.3302995, 0.1801410, -0.0851330,
/// 0.0208351; error 1e-5), and each added degree divides the error by about
/// `(1 + sqrt 2)^2 = 5.8`, as expected from atan's poles at `±i`. Degree 13 is the smallest
/// whose exact error is below the f32 rounding of the result (degree 11: 1.7e-6).
pub const ATAN_COEFFS: [f64; 7] = [
    0.999_996_111_55,
    -0.333_173_680_53,
    0.198_078_155_51,
    -0.132_333_420_42,
    0.079_623_671_389,
    -0.033_604_219_717,
    0.006_811_793_010_9,
];

/// [`ATAN_COEFFS`] rounded to f32 (the test's measured error is of these).
const ATAN_COEFFS_F32: [f32; 7] = {
    let mut c = [0.0f32; 7];
    let mut i = 0;
    while i < 7 {
        c[i] = ATAN_COEFFS[i] as f32;
        i += 1;
    }
    c
};

/// Fast `atan2(y, x)` in f32, in `(-pi, pi]`, branch-free (vectorisable).
///
/// Octant reduction: `t = min(|x|, |y|) / max(|x|, |y|)` in `[0, 1]`, `atan t` from the
/// minimax polynomial [`ATAN_COEFFS`], then `pi/2 - r` when `|y| > |x|`,
/// `pi - r` when `x < 0`, and the sign of `y`. Max error [`ATAN2_MAX_ERROR_RAD`] for finite
/// inputs. Differences from `f32::atan2`: `y = -0.0` with `x < 0` gives `+pi` (not `-pi`),
/// so the result never leaves `(-pi, pi]`; `(±0, ±0)` gives 0; infinite inputs give NaN.
#[inline(always)]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    let ax = x.abs();
    let ay = y.abs();
    let swap = ay > ax;
    let num = if swap { ax } else { ay };
    let den = if swap { ay } else { ax };
    let t = num / den;
    let t = if den > 0.0 { t } else { 0.0 };
    let r = atan_unit(t);
    let r = if swap { FRAC_PI_2_F32 - r } else { r };
    let r = if x < 0.0 { PI_F32 - r } else { r };
    if y < 0.0 {
        -r
    } else {
        r
    }
}

/// The noise model of the frames, EMVA 1288 in DN (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseModel {
    /// System gain `K`, DN per electron; finite, in `[0, 1e6]`.
    pub gain_dn_per_e: f64,
    /// Offset (black level) `b`, DN; finite, in `[-1e6, 1e6]`. Shot noise counts from here.
    pub offset_dn: f64,
    /// Read plus quantisation variance, DN^2: `K^2 sigma_read_e^2 + 1/12`; finite, in
    /// `[0, 1e12]`.
    pub read_var_dn2: f64,
    /// A pixel with any frame value `>= saturation_dn` is saturated (all outputs NaN).
    pub saturation_dn: u16,
}

impl NoiseModel {
    fn validate(&self) -> Result<(), ProductsError> {
        let checks: [(&'static str, f64, f64, f64, &'static str); 3] = [
            (
                "gain_dn_per_e",
                self.gain_dn_per_e,
                0.0,
                1e6,
                "finite, in [0, 1e6] DN/e-",
            ),
            (
                "offset_dn",
                self.offset_dn,
                -1e6,
                1e6,
                "finite, in [-1e6, 1e6] DN",
            ),
            (
                "read_var_dn2",
                self.read_var_dn2,
                0.0,
                1e12,
                "finite, in [0, 1e12] DN^2",
            ),
        ];
        for (field, value, lo, hi, allowed) in checks {
            if !(value.is_finite() && value >= lo && value <= hi) {
                return Err(ProductsError::Noise {
                    field,
                    value,
                    allowed,
                });
            }
        }
        Ok(())
    }
}

/// The dark level subtracted from every frame, DN: `offset + K * dark electrons`.
#[derive(Debug, Clone, PartialEq)]
pub enum Dark {
    /// One value for every pixel (must be finite).
    Scalar(f32),
    /// A per-pixel dark map, row-major, `width * height` values (e.g. a mean of dark frames).
    /// A non-finite entry makes its pixel's outputs NaN.
    Map(Vec<f32>),
}

/// The analyzer rows of one angle set and their pseudo-inverse, computed once per set.
#[derive(Debug, Clone, PartialEq)]
pub struct SetGeometry {
    rows: Vec<[f64; 3]>,
    /// Column `i` of `P` (the weights of frame `i` in S0, S1, S2), f64.
    pinv: Vec<[f64; 3]>,
    condition_number: f64,
}

impl SetGeometry {
    /// The geometry of analyzer rows `a_i` (row `i` = frame `i`: `y_i = a_i . S + dark`).
    ///
    /// Errors: fewer than 3 rows, a non-finite entry, a largest `|entry|` outside
    /// [`ROW_SCALE_RANGE`], or `A^T A` singular or ill-conditioned (reciprocal condition
    /// number below [`MIN_RCOND`]; the error lists the analyzer angles the rows imply).
    pub fn new(rows: &[[f64; 3]]) -> Result<SetGeometry, ProductsError> {
        if rows.len() < 3 {
            return Err(ProductsError::TooFewRows { count: rows.len() });
        }
        for (index, row) in rows.iter().enumerate() {
            if row.iter().any(|v| !v.is_finite()) {
                return Err(ProductsError::NonFiniteRow { index, row: *row });
            }
        }
        let scale = rows
            .iter()
            .flat_map(|r| r.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        if !(scale >= ROW_SCALE_RANGE.0 && scale <= ROW_SCALE_RANGE.1) {
            return Err(ProductsError::RowScale { value: scale });
        }
        let singular = |rcond: f64| ProductsError::Singular {
            angles_deg: rows.iter().map(row_angle_deg).collect(),
            rcond,
            min: MIN_RCOND,
        };
        let a = DMatrix::from_fn(rows.len(), 3, |i, k| rows[i][k]);
        // Singular values only; a (never seen) failure to converge counts as singular.
        let sv = a
            .try_svd(false, false, 5.0 * f64::EPSILON, 10_000)
            .ok_or_else(|| singular(0.0))?
            .singular_values;
        let s_max = sv.iter().fold(0.0f64, |m, v| m.max(*v));
        let s_min = sv.iter().fold(f64::INFINITY, |m, v| m.min(*v));
        let rcond = if s_max > 0.0 {
            (s_min / s_max).powi(2)
        } else {
            0.0
        };
        if rcond.is_nan() || rcond < MIN_RCOND {
            return Err(singular(rcond));
        }
        let ata: Matrix3<f64> =
            Matrix3::from_fn(|r, c| rows.iter().map(|row| row[r] * row[c]).sum::<f64>());
        let inv = ata.try_inverse().ok_or_else(|| singular(rcond))?;
        let mut pinv: Vec<[f64; 3]> = rows
            .iter()
            .map(|row| {
                let mut col = [0.0; 3];
                for (k, c) in col.iter_mut().enumerate() {
                    *c = (0..3).map(|l| inv[(k, l)] * row[l]).sum();
                }
                col
            })
            .collect();
        // Entries that are rounding noise of an exact zero (e.g. cos 90 deg = 6e-17) are
        // snapped to 0, so that an ideal 0/45/90/135 set gives S1 = S2 = 0 exactly for equal
        // frames. The change (< 1e-12 of the largest entry) is far below f32 resolution.
        let p_max = pinv
            .iter()
            .flat_map(|c| c.iter())
            .fold(0.0f64, |m, v| m.max(v.abs()));
        for v in pinv.iter_mut().flat_map(|c| c.iter_mut()) {
            if v.abs() < 1e-12 * p_max {
                *v = 0.0;
            }
        }
        Ok(SetGeometry {
            rows: rows.to_vec(),
            pinv,
            condition_number: s_max / s_min,
        })
    }

    /// The geometry of an ideal linear polarizer at `angles_rad` (radians from the x axis):
    /// rows `0.5 [1, cos 2psi, sin 2psi]`. Errors as [`SetGeometry::new`], plus a
    /// non-finite angle.
    pub fn ideal(angles_rad: &[f64]) -> Result<SetGeometry, ProductsError> {
        let mut rows = Vec::with_capacity(angles_rad.len());
        for (index, &psi) in angles_rad.iter().enumerate() {
            if !psi.is_finite() {
                return Err(ProductsError::NonFiniteAngle { index, value: psi });
            }
            rows.push([0.5, 0.5 * (2.0 * psi).cos(), 0.5 * (2.0 * psi).sin()]);
        }
        SetGeometry::new(&rows)
    }

    /// The analyzer rows `a_i`, one per frame.
    pub fn rows(&self) -> &[[f64; 3]] {
        &self.rows
    }

    /// Number of frames (rows) of the set.
    pub fn frame_count(&self) -> usize {
        self.rows.len()
    }

    /// The `3 x N` pseudo-inverse `P = (A^T A)^-1 A^T` by columns: element `i` is column `i`,
    /// the weights of frame `i` in `(S0, S1, S2)`.
    pub fn pinv(&self) -> Vec<[f64; 3]> {
        self.pinv.clone()
    }

    /// The pseudo-inverse as a `3 x N` nalgebra matrix.
    pub fn pinv_matrix(&self) -> DMatrix<f64> {
        DMatrix::from_fn(3, self.pinv.len(), |k, i| self.pinv[i][k])
    }

    /// The 2-norm condition number of the rows matrix `A` (`s_max / s_min`; that of
    /// `A^T A` is its square). At most `1 / sqrt(MIN_RCOND) = 1e5` for an accepted set.
    pub fn condition_number(&self) -> f64 {
        self.condition_number
    }
}

/// The analyzer angle a row implies, degrees in `[0, 180)` (NaN for a row with no
/// polarising part).
fn row_angle_deg(row: &[f64; 3]) -> f64 {
    if row[1] == 0.0 && row[2] == 0.0 {
        return f64::NAN;
    }
    (0.5 * row[2].atan2(row[1])).to_degrees().rem_euclid(180.0)
}

/// Errors of the products. Each names the field, its value and what is allowed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProductsError {
    /// Fewer than 3 analyzer rows.
    #[error(
        "rows: {count} analyzer rows given; at least 3 are needed (S0, S1, S2 are 3 unknowns)"
    )]
    TooFewRows {
        /// Rows given.
        count: usize,
    },
    /// An analyzer row with a non-finite entry.
    #[error("rows[{index}] = {row:?}: every entry must be finite")]
    NonFiniteRow {
        /// Row index.
        index: usize,
        /// The row.
        row: [f64; 3],
    },
    /// A non-finite analyzer angle.
    #[error("angles_rad[{index}] = {value}: must be finite")]
    NonFiniteAngle {
        /// Angle index.
        index: usize,
        /// The angle.
        value: f64,
    },
    /// The rows' largest entry is outside [`ROW_SCALE_RANGE`].
    #[error(
        "rows: largest |entry| = {value:e}, allowed [1e-3, 1e3] (DN per Stokes unit; 0.5 for \
         an ideal polarizer)"
    )]
    RowScale {
        /// The largest absolute entry.
        value: f64,
    },
    /// `A^T A` singular or ill-conditioned.
    #[error(
        "analyzer set singular or ill-conditioned: reciprocal condition number of A^T A = \
         {rcond:e}, allowed >= {min:e}; analyzer angles (deg, from the rows) = {angles_deg:?}: \
         at least 3 distinct angles modulo 180 deg are needed"
    )]
    Singular {
        /// The analyzer angle of each row, degrees in `[0, 180)`.
        angles_deg: Vec<f64>,
        /// Reciprocal condition number of `A^T A`.
        rcond: f64,
        /// The smallest accepted, [`MIN_RCOND`].
        min: f64,
    },
    /// The number of frames differs from the number of analyzer rows.
    #[error("frames: {frames} frames given, the set geometry has {rows} analyzer rows; they must be equal")]
    FrameCount {
        /// Frames given.
        frames: usize,
        /// Rows of the geometry.
        rows: usize,
    },
    /// A frame's length differs from `width * height`.
    #[error(
        "frames[{index}]: length {len}, expected width * height = {width} * {height} = {expected}"
    )]
    FrameLength {
        /// Frame index.
        index: usize,
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// `width * height` does not fit in `usize`.
    #[error("size {width} x {height}: width * height must fit in usize")]
    Size {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// A dark map's length differs from `width * height`.
    #[error("dark map: length {len}, expected width * height = {expected}")]
    DarkMapLength {
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
    },
    /// A non-finite scalar dark level.
    #[error("dark: scalar value {value}: must be finite")]
    NonFiniteDark {
        /// The value.
        value: f32,
    },
    /// A noise parameter out of range.
    #[error("noise.{field} = {value}: allowed {allowed}")]
    Noise {
        /// The field of [`NoiseModel`].
        field: &'static str,
        /// Its value.
        value: f64,
        /// The allowed range.
        allowed: &'static str,
    },
    /// A summary mask whose length differs from the pixel count.
    #[error("mask: length {len}, expected width * height = {expected} (one entry per pixel)")]
    MaskLength {
        /// Its length.
        len: usize,
        /// `width * height`.
        expected: usize,
    },
    /// A worker thread panicked (a bug: the kernel has no panicking path).
    #[error("products: a worker thread panicked")]
    Worker,
}

/// The products of one angle set: ten f32 images, row-major, `width * height` each.
///
/// Reuse one value with [`compute_into`]: its buffers are resized only when the image size
/// changes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Products {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// S0, DN (dark-subtracted).
    pub s0: Vec<f32>,
    /// S1, DN (`> 0`: horizontal).
    pub s1: Vec<f32>,
    /// S2, DN (`> 0`: +45 deg).
    pub s2: Vec<f32>,
    /// Degree of linear polarisation `sqrt(S1^2 + S2^2) / S0`.
    pub dolp: Vec<f32>,
    /// Angle of polarisation `0.5 atan2(S2, S1)`, radians in `(-pi/2, pi/2)` (module doc).
    pub aop_rad: Vec<f32>,
    /// Predicted standard deviation of S0, DN.
    pub sigma_s0: Vec<f32>,
    /// Predicted standard deviation of S1, DN.
    pub sigma_s1: Vec<f32>,
    /// Predicted standard deviation of S2, DN.
    pub sigma_s2: Vec<f32>,
    /// Predicted (first-order) standard deviation of DoLP.
    pub sigma_dolp: Vec<f32>,
    /// Predicted (first-order) standard deviation of AoP, radians.
    pub sigma_aop_rad: Vec<f32>,
    /// Number of saturated pixels (all outputs NaN).
    pub saturated: u64,
}

/// The image names in storage order.
const NAMES: [&str; 10] = [
    "s0",
    "s1",
    "s2",
    "dolp",
    "aop_rad",
    "sigma_s0",
    "sigma_s1",
    "sigma_s2",
    "sigma_dolp",
    "sigma_aop_rad",
];

/// Means of the product images ([`Products::summary`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProductSummary {
    /// Mean over the finite (and masked-in) pixels of each image, in [`Products::names`]
    /// order; `None` when there is no such pixel.
    pub mean: [Option<f64>; 10],
    /// Number of finite (and masked-in) pixels of each image.
    pub count: [u64; 10],
}

impl ProductSummary {
    /// The mean of the image `name` (see [`Products::names`]).
    pub fn mean_of(&self, name: &str) -> Option<f64> {
        NAMES
            .iter()
            .position(|n| *n == name)
            .and_then(|i| self.mean[i])
    }
}

impl Products {
    /// No pixels.
    pub fn empty() -> Products {
        Products::default()
    }

    /// The image names in storage order: `"s0", "s1", "s2", "dolp", "aop_rad", "sigma_s0",
    /// "sigma_s1", "sigma_s2", "sigma_dolp", "sigma_aop_rad"`.
    pub fn names() -> [&'static str; 10] {
        NAMES
    }

    /// The images in [`Products::names`] order.
    pub fn images(&self) -> [&[f32]; 10] {
        [
            &self.s0,
            &self.s1,
            &self.s2,
            &self.dolp,
            &self.aop_rad,
            &self.sigma_s0,
            &self.sigma_s1,
            &self.sigma_s2,
            &self.sigma_dolp,
            &self.sigma_aop_rad,
        ]
    }

    fn images_mut(&mut self) -> [&mut Vec<f32>; 10] {
        [
            &mut self.s0,
            &mut self.s1,
            &mut self.s2,
            &mut self.dolp,
            &mut self.aop_rad,
            &mut self.sigma_s0,
            &mut self.sigma_s1,
            &mut self.sigma_s2,
            &mut self.sigma_dolp,
            &mut self.sigma_aop_rad,
        ]
    }

    /// The image called `name` (one of [`Products::names`]), or `None`.
    pub fn image(&self, name: &str) -> Option<&[f32]> {
        let i = NAMES.iter().position(|n| *n == name)?;
        self.images().get(i).copied()
    }

    /// Number of pixels, `width * height`.
    pub fn pixel_count(&self) -> usize {
        self.s0.len()
    }

    /// The mean of each image over its finite pixels, restricted to the pixels where `mask`
    /// is `true` when a mask is given (one entry per pixel, row-major). Accumulated in f64.
    pub fn summary(&self, mask: Option<&[bool]>) -> Result<ProductSummary, ProductsError> {
        let n = self.pixel_count();
        if let Some(m) = mask {
            if m.len() != n {
                return Err(ProductsError::MaskLength {
                    len: m.len(),
                    expected: n,
                });
            }
        }
        let mut mean = [None; 10];
        let mut count = [0u64; 10];
        for (k, img) in self.images().iter().enumerate() {
            let (mut sum, mut c) = (0.0f64, 0u64);
            for (i, v) in img.iter().enumerate() {
                let keep = mask.is_none_or(|m| m.get(i).copied().unwrap_or(false));
                if keep && v.is_finite() {
                    sum += f64::from(*v);
                    c += 1;
                }
            }
            count[k] = c;
            mean[k] = (c > 0).then(|| sum / c as f64);
        }
        Ok(ProductSummary { mean, count })
    }

    /// Sizes every image for `n` pixels (no reallocation when the size is unchanged).
    fn resize(&mut self, width: u32, height: u32, n: usize) {
        self.width = width;
        self.height = height;
        for img in self.images_mut() {
            if img.len() != n {
                img.resize(n, 0.0);
            }
        }
    }
}

/// The weights of one frame in the hot loop: column `p` of `P`, and `kq`, the gain `K` times
/// the products `[p0 p0, 2 p0 p1, 2 p0 p2, p1 p1, 2 p1 p2, p2 p2]` (the factor 2 is the one
/// the quadratic forms of [`finalize`] need, folded in here).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct FrameWeights {
    p: [f32; 3],
    kq: [f32; 6],
}

/// Everything the hot loop needs, in f32, built once per call.
///
/// With `e_i = max(y_i - offset, 0)`, `C = P diag(K e + read_var) P^T
/// = read_var P P^T + sum_i e_i K p_i p_i^T`: the accumulators start at
/// `c_init = read_var P P^T` (same packing as `kq`) and each frame adds `kq_i e_i`. In a chunk
/// where no frame value is below the offset, `e_i = y_i - offset` and the offset term is
/// folded into the start value instead (`c_init_unclamped`).
#[derive(Debug, Clone)]
struct Kernel {
    w: Vec<FrameWeights>,
    /// `P 1`: `S = P y - dark P 1`, so the frames enter S undarkened and the dark level is
    /// subtracted once per pixel.
    sigma: [f32; 3],
    /// `sigma[1] == sigma[2] == 0` (the usual case): only S0 needs the dark correction.
    sigma12_zero: bool,
    c_init: [f32; 6],
    /// `c_init - offset sum_i kq_i`: the start of `C` when no frame value of the chunk is
    /// below the offset, so that `C += kq_i y_i` needs no clamp.
    c_init_unclamped: [f32; 6],
    off: f32,
    lo: u32,
    sat: u16,
}

impl Kernel {
    fn new(geometry: &SetGeometry, noise: &NoiseModel) -> Kernel {
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
struct Acc {
    s0: f32,
    s1: f32,
    s2: f32,
    c00: f32,
    c01x2: f32,
    c02x2: f32,
    c11: f32,
    c12x2: f32,
    c22: f32,
}

impl Acc {
    /// The accumulators before the first frame: `c` is [`Kernel::c_init`] or
    /// [`Kernel::c_init_unclamped`].
    #[inline(always)]
    fn start(c: [f32; 6]) -> Acc {
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
    fn subtract_dark<const SIGMA12_ZERO: bool>(&mut self, dark: f32, sigma: &[f32; 3]) {
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
    fn add<const CLAMP: bool>(&mut self, y: u16, w: &FrameWeights, off: f32) {
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

/// The largest f32 below pi/2 (pi/2 = 1.5707963268; this is 1.5707962513): the AoP branch
/// constant, so that AoP stays inside `(-pi/2, pi/2)` in f32 (an error of 7.5e-8 rad,
/// included in [`AOP_MAX_ERROR_RAD`]).
const HALF_PI_BELOW: f32 = 1.570_796_2;

/// `atan z` for `|z| <= 1` with the degree-13 minimax polynomial [`ATAN_COEFFS`].
#[inline(always)]
fn atan_unit(z: f32) -> f32 {
    // Estrin's scheme: two more operations than Horner's, but a dependency chain of 4
    // multiply-adds instead of 6 (the pixel loop is partly latency-bound).
    let [c0, c1, c2, c3, c4, c5, c6] = ATAN_COEFFS_F32;
    let z2 = z * z;
    let z4 = z2 * z2;
    let z8 = z4 * z4;
    let p01 = c1 * z2 + c0;
    let p23 = c3 * z2 + c2;
    let p45 = c5 * z2 + c4;
    let q0 = p23 * z4 + p01;
    let q1 = c6 * z4 + p45;
    z * (q1 * z8 + q0)
}

/// AoP `= 0.5 atan2(S2, S1)` from `S1, S2` and `L = sqrt(S1^2 + S2^2)`, in `(-pi/2, pi/2)`,
/// by the half-angle identities (no octant reduction and one division, as `L` is already
/// known): for `S1 >= 0`, `tan AoP = S2 / (L + S1)`; for `S1 < 0`, `cot AoP = S2 / (L - S1)`.
/// Both ratios lie in `[-1, 1]`, where the polynomial applies:
/// `AoP = atan(z)` for `S1 >= 0` and `AoP = ±pi/2 - atan(z)` (the sign of `S2`) for `S1 < 0`,
/// `z = S2 / (L + |S1|)`. The branches are sign-bit operations (vectorisable). Max error
/// [`AOP_MAX_ERROR_RAD`] (measured by a unit test) for finite inputs; NaN when `L = 0`.
#[inline(always)]
pub fn fast_aop(s1: f32, s2: f32, l: f32) -> f32 {
    const SIGN: u32 = 0x8000_0000;
    let a = atan_unit(s2 / (l + s1.abs()));
    let b1 = s1.to_bits();
    // All ones when S1 is negative (or -0, where both branches agree), else zero.
    let neg1 = ((b1 as i32) >> 31) as u32;
    // -atan(z) when S1 < 0.
    let a = f32::from_bits(a.to_bits() ^ (b1 & SIGN));
    // ±pi/2 with the sign of S2, kept only when S1 < 0.
    let q = (HALF_PI_BELOW.to_bits() | (s2.to_bits() & SIGN)) & neg1;
    a + f32::from_bits(q)
}

/// A pixel's ten outputs in [`Products::names`] order (saturation is handled by the caller,
/// [`fix_saturated`]).
///
/// Branch-free (every condition is a select or a bit operation), so that the pixel loops
/// vectorise. An undefined output gets a NaN added (`x + NaN = NaN`, `x + 0 = x`).
#[inline(always)]
fn finalize(a: &Acc) -> [f32; 10] {
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
fn chunk_in_range(frames: &[&[u16]], start: usize, len: usize, lo: u32, sat: u16) -> bool {
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
fn chunk_range(frames: &[&[u16]], start: usize, len: usize) -> (u16, u16) {
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
fn fix_saturated(frames: &[&[u16]], start: usize, chunk: OutSlices<'_>, saturation_dn: u16) -> u64 {
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
trait DarkSource: Copy + Send + Sync {
    /// Restricts to `start..start + len` (None when out of range).
    fn sub(self, start: usize, len: usize) -> Option<Self>;
    /// The dark level of pixel `j` (of the sub-range).
    fn at(&self, j: usize) -> f32;
}

#[derive(Clone, Copy)]
struct ScalarDark(f32);

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
struct MapDark<'a>(&'a [f32]);

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
struct OutSlices<'a> {
    s: [&'a mut [f32]; 10],
}

impl<'a> OutSlices<'a> {
    /// Splits off the first `len` pixels of every image.
    fn split_first(self, len: usize) -> Option<(OutSlices<'a>, OutSlices<'a>)> {
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
struct LengthMismatch;

/// Pixels per chunk: the accumulators of a chunk ([`AccBlock`], 9 x 4 x 512 B = 18 KiB)
/// stay in L1 between the accumulation and the output pass.
const CHUNK: usize = 512;

/// Structure-of-arrays accumulators of one chunk.
struct AccBlock {
    s0: [f32; CHUNK],
    s1: [f32; CHUNK],
    s2: [f32; CHUNK],
    c00: [f32; CHUNK],
    c01x2: [f32; CHUNK],
    c02x2: [f32; CHUNK],
    c11: [f32; CHUNK],
    c12x2: [f32; CHUNK],
    c22: [f32; CHUNK],
}

impl AccBlock {
    fn new() -> AccBlock {
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
    fn load(&self, j: usize) -> Acc {
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
    fn store(&mut self, j: usize, a: &Acc) {
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
fn accumulate_fused<const G: usize, const CLAMP: bool, const SIGMA12_ZERO: bool, D: DarkSource>(
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
fn accumulate_per_frame<D: DarkSource>(
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
fn finalize_chunk(acc: &AccBlock, chunk: &mut OutSlices<'_>) -> Result<(), LengthMismatch> {
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
fn run_band<D: DarkSource>(
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
const BANDS_PER_THREAD: usize = 8;

/// Below this many pixels per thread, extra threads cost more than they save.
const MIN_PIXELS_PER_THREAD: usize = 16_384;

/// Checks the inputs; returns `width * height`.
fn validate(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
) -> Result<usize, ProductsError> {
    let n = usize::try_from(u64::from(width) * u64::from(height))
        .map_err(|_| ProductsError::Size { width, height })?;
    if frames.len() != geometry.rows.len() {
        return Err(ProductsError::FrameCount {
            frames: frames.len(),
            rows: geometry.rows.len(),
        });
    }
    for (index, f) in frames.iter().enumerate() {
        if f.len() != n {
            return Err(ProductsError::FrameLength {
                index,
                len: f.len(),
                expected: n,
                width,
                height,
            });
        }
    }
    match dark {
        Dark::Scalar(v) if !v.is_finite() => {
            return Err(ProductsError::NonFiniteDark { value: *v });
        }
        Dark::Map(m) if m.len() != n => {
            return Err(ProductsError::DarkMapLength {
                len: m.len(),
                expected: n,
            });
        }
        _ => {}
    }
    noise.validate()?;
    Ok(n)
}

/// Computes the products of one angle set into `out` (buffers reused; resized only when
/// the image size changes), in parallel over row bands.
///
/// `frames[i]` is frame `i` (row-major `width * height` values) taken with analyzer row
/// `geometry.rows()[i]`. `threads` caps the number of threads (`0`: no cap); at most
/// `std::thread::available_parallelism()` are used, and fewer for small images. The result
/// does not depend on the number of threads (bit for bit). On error `out` is unchanged.
#[allow(clippy::too_many_arguments)]
pub fn compute_into(
    out: &mut Products,
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
    threads: usize,
) -> Result<(), ProductsError> {
    let n = validate(frames, width, height, geometry, dark, noise)?;
    out.resize(width, height, n);
    out.saturated = 0;
    if n == 0 {
        return Ok(());
    }
    let available = std::thread::available_parallelism().map_or(1, |v| v.get());
    let cap = if threads == 0 {
        available
    } else {
        threads.min(available)
    };
    let threads = cap.min(n / MIN_PIXELS_PER_THREAD).max(1);
    // More bands than threads (BANDS_PER_THREAD each): the threads take them from a queue,
    // which balances the load when a core is shared with other work. A band is a range of
    // whole chunks (row-major pixels, not whole rows), so that the chunks, whose frame
    // values choose their accumulation (clamped or not), are the same for every band split:
    // the result does not depend on the number of threads.
    let bands = if threads == 1 {
        1
    } else {
        threads * BANDS_PER_THREAD
    };
    let band_len = n.div_ceil(bands).div_ceil(CHUNK) * CHUNK;
    let kernel = Kernel::new(geometry, noise);
    let saturated = match dark {
        Dark::Scalar(v) => run_bands(out, frames, ScalarDark(*v), &kernel, band_len, threads)?,
        Dark::Map(m) => run_bands(out, frames, MapDark(m), &kernel, band_len, threads)?,
    };
    out.saturated = saturated;
    Ok(())
}

/// Splits the outputs into bands of `band_len` pixels and runs them on scoped threads (the
/// first on the calling thread).
fn run_bands<D: DarkSource>(
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

/// [`compute_into`] into a new [`Products`].
pub fn compute(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
    threads: usize,
) -> Result<Products, ProductsError> {
    let mut out = Products::empty();
    compute_into(
        &mut out, frames, width, height, geometry, dark, noise, threads,
    )?;
    Ok(out)
}

/// The reference implementation: single-threaded, f64 throughout, `f64::atan2` and
/// `f64::sqrt`, the textbook formulas of the module doc (`var AoP` with `L^4`), the same
/// special-pixel rules (with `L == 0` exactly). Used by the tests and the benchmark to check
/// the fast path; results are rounded to f32 at the end.
#[doc(hidden)]
pub fn compute_reference(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
) -> Result<Products, ProductsError> {
    let n = validate(frames, width, height, geometry, dark, noise)?;
    let mut out = Products::empty();
    out.resize(width, height, n);
    let p = &geometry.pinv;
    let k = noise.gain_dn_per_e;
    let sat_dn = noise.saturation_dn;
    for j in 0..n {
        let dk = match dark {
            Dark::Scalar(v) => f64::from(*v),
            Dark::Map(m) => m.get(j).map_or(f64::NAN, |v| f64::from(*v)),
        };
        let mut s = [0.0f64; 3];
        let mut c = [[0.0f64; 3]; 3];
        let mut sat = false;
        for (f, pi) in frames.iter().zip(p) {
            let yv = f.get(j).copied().unwrap_or(0);
            sat |= yv >= sat_dn;
            let y = f64::from(yv);
            let var = k * (y - noise.offset_dn).max(0.0) + noise.read_var_dn2;
            for a in 0..3 {
                s[a] += pi[a] * (y - dk);
                for b in 0..3 {
                    c[a][b] += pi[a] * pi[b] * var;
                }
            }
        }
        let [s0, s1, s2] = s;
        let l = (s1 * s1 + s2 * s2).sqrt();
        let (dolp, sig_p) = if s0 <= 0.0 {
            (f64::NAN, f64::NAN)
        } else if l == 0.0 {
            (0.0, ((c[1][1] + c[2][2]) / 2.0).sqrt() / s0)
        } else {
            let p = l / s0;
            let g = [-p / s0, s1 / (s0 * l), s2 / (s0 * l)];
            let mut v = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    v += g[a] * c[a][b] * g[b];
                }
            }
            (p, v.max(0.0).sqrt())
        };
        let (aop, sig_a) = if l == 0.0 {
            (f64::NAN, f64::NAN)
        } else {
            let mut aop = 0.5 * s2.atan2(s1);
            if aop <= -std::f64::consts::FRAC_PI_2 {
                aop += std::f64::consts::PI;
            }
            let v = (s1 * s1 * c[2][2] + s2 * s2 * c[1][1] - 2.0 * s1 * s2 * c[1][2])
                / (4.0 * l.powi(4));
            (aop, v.max(0.0).sqrt())
        };
        let o = [
            s0,
            s1,
            s2,
            dolp,
            aop,
            c[0][0].sqrt(),
            c[1][1].sqrt(),
            c[2][2].sqrt(),
            sig_p,
            sig_a,
        ];
        if sat {
            out.saturated += 1;
        }
        for (img, v) in out.images_mut().into_iter().zip(o) {
            if let Some(x) = img.get_mut(j) {
                *x = if sat || !v.is_finite() {
                    f32::NAN
                } else {
                    v as f32
                };
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use polar_hil_mocks::faults::Dice;
    use std::f64::consts::PI;

    fn deg(a: &[f64]) -> Vec<f64> {
        a.iter().map(|d| d.to_radians()).collect()
    }

    /// The geometries of tests 1 and 2: ideal 0/45/90/135, ideal 0/60/120, a non-ideal
    /// analyzer (diattenuation 0.98, i.e. extinction ratio 99:1) at 0/45/90/135 plus a
    /// 1 deg zero offset, angle-dependent transmittance (fore-optics), and a 7-angle set (the
    /// per-frame kernel).
    fn geometries() -> Vec<(&'static str, SetGeometry)> {
        let nonideal: Vec<[f64; 3]> = [0.0f64, 45.0, 90.0, 135.0]
            .iter()
            .map(|d| {
                let psi = (d + 1.0).to_radians();
                [
                    0.5,
                    0.5 * 0.98 * (2.0 * psi).cos(),
                    0.5 * 0.98 * (2.0 * psi).sin(),
                ]
            })
            .collect();
        // Fore-optics whose transmittance depends on the analyzer angle (a diattenuating
        // window in front of the analyzer, 0/60/120/150 deg): the first entries of the rows
        // differ, so the dark level enters S1 and S2 too (P 1 has three non-zero entries).
        let diattenuating: Vec<[f64; 3]> = [0.0f64, 60.0, 120.0, 150.0]
            .iter()
            .map(|d| {
                let c = (2.0 * d.to_radians()).cos();
                let s = (2.0 * d.to_radians()).sin();
                [
                    0.5 * (1.0 + 0.08 * c),
                    0.5 * 0.97 * (c + 0.08),
                    0.5 * 0.97 * s,
                ]
            })
            .collect();
        vec![
            (
                "0/45/90/135",
                SetGeometry::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap(),
            ),
            (
                "0/60/120",
                SetGeometry::ideal(&deg(&[0.0, 60.0, 120.0])).unwrap(),
            ),
            ("non-ideal d=0.98", SetGeometry::new(&nonideal).unwrap()),
            (
                "diattenuating optics",
                SetGeometry::new(&diattenuating).unwrap(),
            ),
            (
                "7 angles",
                SetGeometry::ideal(&deg(&[0.0, 25.0, 50.0, 75.0, 100.0, 125.0, 150.0])).unwrap(),
            ),
        ]
    }

    fn noise() -> NoiseModel {
        NoiseModel {
            gain_dn_per_e: 0.5,
            offset_dn: 100.0,
            read_var_dn2: 0.25 * 4.0 + 1.0 / 12.0,
            saturation_dn: 65535,
        }
    }

    /// Noise-free frames of the Stokes vectors `s` (one per pixel), rounded to u16.
    fn synth(geom: &SetGeometry, s: &[[f64; 3]], dark: f64) -> Vec<Vec<u16>> {
        geom.rows()
            .iter()
            .map(|r| {
                s.iter()
                    .map(|s| {
                        let y = r[0] * s[0] + r[1] * s[1] + r[2] * s[2] + dark;
                        y.round().clamp(0.0, 65535.0) as u16
                    })
                    .collect()
            })
            .collect()
    }

    fn stokes(s0: f64, dolp: f64, aop_deg: f64) -> [f64; 3] {
        let a = 2.0 * aop_deg.to_radians();
        [s0, s0 * dolp * a.cos(), s0 * dolp * a.sin()]
    }

    /// Angle difference modulo pi (AoP is defined modulo pi).
    fn aop_diff(a: f64, b: f64) -> f64 {
        let d = (a - b).rem_euclid(PI);
        d.min(PI - d)
    }

    #[test]
    fn noise_free_frames_recover_stokes_dolp_aop() {
        // Large S0 (40000 DN) so that rounding the synthetic frames to u16 (|error| <= 0.5
        // DN per frame) is small; pixels: unpolarised, DoLP 0.3 at several AoP, DoLP 1, and
        // a small S0 (60 DN).
        let big = 40_000.0;
        let mut truth = vec![stokes(big, 0.0, 0.0)];
        for aop in [
            -89.0, -60.0, -30.0, -1.0, 0.0, 1.0, 22.5, 45.0, 67.0, 89.9, 90.0,
        ] {
            truth.push(stokes(big, 0.3, aop));
        }
        for aop in [-45.0, 0.0, 30.0, 90.0] {
            truth.push(stokes(big, 1.0, aop));
        }
        let small = truth.len();
        truth.push(stokes(60.0, 0.5, 30.0));
        let dark = 100.0;
        for (name, g) in geometries() {
            let frames = synth(&g, &truth, dark);
            let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
            let w = truth.len() as u32;
            let d = Dark::Scalar(dark as f32);
            let fast = compute(&refs, w, 1, &g, &d, &noise(), 1).unwrap();
            let reference = compute_reference(&refs, w, 1, &g, &d, &noise()).unwrap();
            let pinv = g.pinv();
            for (j, s) in truth.iter().enumerate() {
                // (a) Against the truth: rounding moves S_k by at most 0.5 sum_i |P_ki|
                // (exact bound), plus f32 arithmetic (a few ulp of 65535: 1e-2 DN).
                for k in 0..3 {
                    let bound: f64 = 0.5 * pinv.iter().map(|c| c[k].abs()).sum::<f64>() + 1e-2;
                    let got = f64::from([fast.s0[j], fast.s1[j], fast.s2[j]][k]);
                    assert!(
                        (got - s[k]).abs() <= bound,
                        "{name} pixel {j} S{k}: {got} vs {} (bound {bound})",
                        s[k]
                    );
                }
                let l = (s[1] * s[1] + s[2] * s[2]).sqrt();
                if j != small {
                    // With S0 = 40000 the rounding bound (~1 DN) is 2.5e-5 of S0: DoLP is
                    // within 2 * 2.5e-5 and AoP within 1 / (2 L) <= 4.2e-5 rad for DoLP >= 0.3.
                    let dolp = f64::from(fast.dolp[j]);
                    assert!(
                        (dolp - l / s[0]).abs() < 1e-4,
                        "{name} pixel {j} DoLP {dolp}"
                    );
                    if l > 0.0 {
                        let aop = f64::from(fast.aop_rad[j]);
                        let want = 0.5 * s[2].atan2(s[1]);
                        assert!(
                            aop_diff(aop, want) < 1e-4,
                            "{name} pixel {j} AoP {aop} vs {want}"
                        );
                        assert!(
                            aop > -PI / 2.0 && aop <= PI / 2.0 + 1e-7,
                            "AoP range: {aop}"
                        );
                    }
                }
                // (b) Against the f64 reference on the same rounded frames: only the f32
                // arithmetic differs (relative 6e-8 per operation on values up to 65535 DN,
                // ~20 operations): 1e-5 of S0 for S, 1e-5 absolute for DoLP, and for AoP
                // 1e-5 / DoLP plus the atan2 polynomial's error.
                let sc = f64::from(reference.s0[j]);
                for (a, b) in [
                    (fast.s0[j], reference.s0[j]),
                    (fast.s1[j], reference.s1[j]),
                    (fast.s2[j], reference.s2[j]),
                ] {
                    assert!((f64::from(a) - f64::from(b)).abs() <= 1e-5 * sc + 1e-3);
                }
                let (fd, rd) = (f64::from(fast.dolp[j]), f64::from(reference.dolp[j]));
                assert!(
                    (fd - rd).abs() <= 1e-5,
                    "{name} pixel {j}: DoLP {fd} vs {rd}"
                );
                if rd > 1e-3 {
                    let (fa, ra) = (f64::from(fast.aop_rad[j]), f64::from(reference.aop_rad[j]));
                    assert!(
                        aop_diff(fa, ra) <= 1e-5 / rd + AOP_MAX_ERROR_RAD,
                        "{name} pixel {j}: AoP {fa} vs {ra}"
                    );
                }
                // The sigmas agree with the reference to a few f32 ulps (1e-6 relative),
                // except sigma_dolp: at DoLP -> 1 its quadratic form g^T C g cancels to
                // ~1e-3 of its terms (the crossed analyzer frame is nearly dark), which
                // turns the f32 rounding (6e-8) into ~1e-4 relative (measured 4e-4 for
                // 0/60/120 at DoLP 1): 1e-3, irrelevant for a predicted sigma.
                let sigma_tol = [1e-6, 1e-6, 1e-6, 1e-3, 1e-6];
                for (k, (a, b)) in fast.images()[5..]
                    .iter()
                    .zip(&reference.images()[5..])
                    .enumerate()
                {
                    let (a, b) = (f64::from(a[j]), f64::from(b[j]));
                    if b.is_finite() && (rd > 1e-3 || k < 3) {
                        assert!(
                            (a - b).abs() <= sigma_tol[k] * b.abs(),
                            "{name} pixel {j} sigma {k}: {a} vs {b}"
                        );
                    }
                }
            }
            assert_eq!(fast.saturated, 0);
        }
    }

    #[test]
    fn predicted_sigma_matches_monte_carlo() {
        // A high-SNR pixel: S = (20000, 3000, -2000) DN, L = 3606 DN, sigma_L ~ 70 DN:
        // polarised SNR ~ 50, deep in the first-order regime (the second-order corrections
        // are ~1/SNR^2 = 0.04 %). Each draw is one pixel of a 1-row image; frame values are
        // Gaussian with the model's variance minus the 1/12 quantisation term, then rounded
        // (the rounding adds the 1/12 back). Sampling error of a std with n = 40000 draws:
        // 1 / sqrt(2 (n - 1)) = 0.35 %; tolerance 3 % (8.5 standard errors).
        let n = 40_000usize;
        let truth = [20_000.0, 3_000.0, -2_000.0];
        let nm = NoiseModel {
            gain_dn_per_e: 0.5,
            offset_dn: 100.0,
            read_var_dn2: 0.25 * 9.0 + 1.0 / 12.0,
            saturation_dn: 65535,
        };
        let dark = 130.0;
        for (name, g) in geometries() {
            let mut rng = Dice::new(0x5EED_0000 + g.frame_count() as u64);
            let frames: Vec<Vec<u16>> = g
                .rows()
                .iter()
                .map(|r| {
                    let mean = r[0] * truth[0] + r[1] * truth[1] + r[2] * truth[2] + dark;
                    let var =
                        nm.gain_dn_per_e * (mean - nm.offset_dn) + nm.read_var_dn2 - 1.0 / 12.0;
                    (0..n)
                        .map(|_| (mean + var.sqrt() * rng.normal()).round() as u16)
                        .collect()
                })
                .collect();
            let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
            let p = compute(&refs, n as u32, 1, &g, &Dark::Scalar(dark as f32), &nm, 2).unwrap();
            // AoP is far from the wrap (-16.8 deg): no unwrapping needed.
            let std_of = |v: &[f32]| -> f64 {
                let m = v.iter().map(|x| f64::from(*x)).sum::<f64>() / n as f64;
                let ss: f64 = v.iter().map(|x| (f64::from(*x) - m).powi(2)).sum();
                (ss / (n - 1) as f64).sqrt()
            };
            let mean_of = |v: &[f32]| v.iter().map(|x| f64::from(*x)).sum::<f64>() / n as f64;
            let pairs = [
                ("S0", &p.s0, &p.sigma_s0),
                ("S1", &p.s1, &p.sigma_s1),
                ("S2", &p.s2, &p.sigma_s2),
                ("DoLP", &p.dolp, &p.sigma_dolp),
                ("AoP", &p.aop_rad, &p.sigma_aop_rad),
            ];
            for (what, vals, sig) in pairs {
                let sample = std_of(vals);
                let predicted = mean_of(sig);
                let rel = (sample / predicted - 1.0).abs();
                eprintln!("{name} {what}: sample std {sample:.4e}, predicted {predicted:.4e}");
                assert!(
                    rel < 0.03,
                    "{name} {what}: sample std {sample} vs predicted {predicted} ({:.2} %)",
                    100.0 * rel
                );
            }
        }
    }

    #[test]
    fn saturated_dark_and_unpolarised_pixels_are_nan_or_finite_never_inf() {
        let g = SetGeometry::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap();
        let nm = NoiseModel {
            saturation_dn: 4095,
            ..noise()
        };
        // Pixels: 0 one frame saturated, 1 all saturated, 2 all at the dark level (S = 0),
        // 3 below the dark level (S0 < 0), 4 uniform above dark (unpolarised: L = 0
        // exactly with the snapped pseudo-inverse), 5 ordinary, 6 all zero, 7 just below
        // saturation.
        let px: [[u16; 4]; 8] = [
            [1000, 4095, 1000, 1000],
            [65535; 4],
            [200; 4],
            [150, 190, 120, 180],
            [3000; 4],
            [3000, 2000, 1000, 2000],
            [0; 4],
            [4094; 4],
        ];
        let frames: Vec<Vec<u16>> = (0..4).map(|i| px.iter().map(|p| p[i]).collect()).collect();
        let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
        for dark in [Dark::Scalar(200.0), Dark::Map(vec![200.0; 8])] {
            let p = compute(&refs, 8, 1, &g, &dark, &nm, 1).unwrap();
            assert_eq!(p.saturated, 2);
            for img in p.images() {
                assert!(img[0].is_nan() && img[1].is_nan());
                assert!(img.iter().all(|v| !v.is_infinite()), "an infinity: {img:?}");
            }
            for j in 2..8 {
                for k in [0, 1, 2, 5, 6, 7] {
                    assert!(p.images()[k][j].is_finite(), "pixel {j} image {k}");
                }
            }
            // S = 0 and S0 < 0: DoLP undefined (NaN), AoP undefined at S = 0.
            assert_eq!((p.s0[2], p.s1[2], p.s2[2]), (0.0, 0.0, 0.0));
            assert!(p.dolp[2].is_nan() && p.sigma_dolp[2].is_nan() && p.aop_rad[2].is_nan());
            assert!(p.s0[3] < 0.0 && p.dolp[3].is_nan() && p.aop_rad[3].is_finite());
            assert!(p.s0[6] < 0.0 && p.dolp[6].is_nan());
            // Unpolarised: DoLP exactly 0, AoP and its sigma NaN, sigma_dolp the
            // direction-averaged first-order value sqrt((C11 + C22) / 2) / S0.
            assert_eq!((p.s1[4], p.s2[4], p.dolp[4]), (0.0, 0.0, 0.0));
            assert!(p.aop_rad[4].is_nan() && p.sigma_aop_rad[4].is_nan());
            let want = ((p.sigma_s1[4].powi(2) + p.sigma_s2[4].powi(2)) / 2.0).sqrt() / p.s0[4];
            assert!((p.sigma_dolp[4] - want).abs() <= 1e-6 * want);
            // Ordinary pixel and just-below-saturation pixel: all ten finite.
            for img in p.images() {
                assert!(img[5].is_finite());
            }
            assert!(p.dolp[7] == 0.0 && p.s0[7] > 0.0);
        }
        // A tiny positive S0 with a large L (a negative dark map entry): no infinity.
        let frames2: Vec<Vec<u16>> = vec![vec![0], vec![0], vec![0], vec![0]];
        let refs2: Vec<&[u16]> = frames2.iter().map(Vec::as_slice).collect();
        for d in [-1e-38f32, -1e-30, f32::NAN, -1e30] {
            let p = compute(&refs2, 1, 1, &g, &Dark::Map(vec![d]), &nm, 1).unwrap();
            for img in p.images() {
                assert!(!img[0].is_infinite());
            }
        }
        let odd = Dark::Map(vec![1e-3, -1e-3, 2e-3, 0.0]);
        let frames3: Vec<Vec<u16>> = vec![vec![0; 4]; 4];
        let mut refs3: Vec<&[u16]> = frames3.iter().map(Vec::as_slice).collect();
        refs3.truncate(4);
        let p = compute(&refs3, 2, 2, &g, &odd, &nm, 1).unwrap();
        for img in p.images() {
            assert!(img.iter().all(|v| !v.is_infinite()));
        }
    }

    #[test]
    fn invalid_inputs_give_named_errors() {
        let g = SetGeometry::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap();
        let f = vec![100u16; 6];
        let nm = noise();
        let d = Dark::Scalar(10.0);
        // Frame count mismatch.
        let e = compute(&[&f, &f, &f], 3, 2, &g, &d, &nm, 1).unwrap_err();
        assert_eq!(e, ProductsError::FrameCount { frames: 3, rows: 4 });
        assert!(e.to_string().contains("3 frames") && e.to_string().contains("4 analyzer rows"));
        // Frame length.
        let short = vec![100u16; 5];
        let e = compute(&[&f, &f, &short, &f], 3, 2, &g, &d, &nm, 1).unwrap_err();
        assert!(matches!(
            e,
            ProductsError::FrameLength {
                index: 2,
                len: 5,
                expected: 6,
                ..
            }
        ));
        assert!(e.to_string().contains("frames[2]"));
        // Dark map length and non-finite dark.
        let e = compute(
            &[&f, &f, &f, &f],
            3,
            2,
            &g,
            &Dark::Map(vec![0.0; 5]),
            &nm,
            1,
        );
        assert_eq!(
            e.unwrap_err(),
            ProductsError::DarkMapLength {
                len: 5,
                expected: 6
            }
        );
        let e = compute(&[&f, &f, &f, &f], 3, 2, &g, &Dark::Scalar(f32::NAN), &nm, 1);
        assert!(matches!(
            e.unwrap_err(),
            ProductsError::NonFiniteDark { .. }
        ));
        // Non-finite and out-of-range noise parameters name the field.
        for (bad, field) in [
            (
                NoiseModel {
                    gain_dn_per_e: f64::NAN,
                    ..nm
                },
                "gain_dn_per_e",
            ),
            (
                NoiseModel {
                    offset_dn: f64::INFINITY,
                    ..nm
                },
                "offset_dn",
            ),
            (
                NoiseModel {
                    read_var_dn2: -1.0,
                    ..nm
                },
                "read_var_dn2",
            ),
        ] {
            let e = compute(&[&f, &f, &f, &f], 3, 2, &g, &d, &bad, 1).unwrap_err();
            assert!(matches!(e, ProductsError::Noise { field: fld, .. } if fld == field));
            assert!(e.to_string().contains(field));
        }
        // 0, 90, 180 deg: only two distinct analyzer angles modulo 180 -> singular.
        let e = SetGeometry::ideal(&deg(&[0.0, 90.0, 180.0])).unwrap_err();
        match &e {
            ProductsError::Singular {
                angles_deg, rcond, ..
            } => {
                assert!(*rcond < MIN_RCOND);
                let want = [0.0, 90.0, 0.0];
                for (a, w) in angles_deg.iter().zip(want) {
                    let diff = (a - w).rem_euclid(180.0);
                    assert!(diff.min(180.0 - diff) < 1e-9, "{angles_deg:?}");
                }
            }
            other => panic!("expected Singular, got {other:?}"),
        }
        assert!(e.to_string().contains("angles"));
        // Nearly repeated angles (0, 0.0001, 90 deg) are ill-conditioned too.
        assert!(matches!(
            SetGeometry::ideal(&deg(&[0.0, 1e-4, 90.0])).unwrap_err(),
            ProductsError::Singular { .. }
        ));
        // Too few rows, non-finite rows and angles, bad row scale.
        assert_eq!(
            SetGeometry::ideal(&deg(&[0.0, 60.0])).unwrap_err(),
            ProductsError::TooFewRows { count: 2 }
        );
        assert!(matches!(
            SetGeometry::new(&[[0.5, 0.5, 0.0], [0.5, f64::NAN, 0.0], [0.5, 0.0, 0.5]]),
            Err(ProductsError::NonFiniteRow { index: 1, .. })
        ));
        assert!(matches!(
            SetGeometry::ideal(&[0.0, f64::NAN, 1.0]),
            Err(ProductsError::NonFiniteAngle { index: 1, .. })
        ));
        assert!(matches!(
            SetGeometry::new(&[[5e3, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5]]),
            Err(ProductsError::RowScale { .. })
        ));
        // Summary mask length.
        let p = compute(&[&f, &f, &f, &f], 3, 2, &g, &d, &nm, 1).unwrap();
        assert_eq!(
            p.summary(Some(&[true; 5])).unwrap_err(),
            ProductsError::MaskLength {
                len: 5,
                expected: 6
            }
        );
    }

    #[test]
    fn atan2_error_is_measured_and_below_the_const() {
        // Dense grid: 2 million directions around the circle (every octant, both signs of
        // each coordinate) at several radii, plus the reduced argument t on [0, 1] in steps
        // of 1e-6 and the axes. The reference is f64 atan2 of the same f32 inputs.
        let mut max_err = 0.0f64;
        let mut check = |y: f32, x: f32| {
            let want = f64::from(y).atan2(f64::from(x));
            let got = f64::from(fast_atan2(y, x));
            let mut e = (got - want).abs();
            // fast_atan2 maps -pi to +pi (y = -0.0): the same direction.
            if e > 6.0 {
                e = (e - 2.0 * PI).abs();
            }
            max_err = max_err.max(e);
        };
        let m = 2_000_000;
        for i in 0..m {
            let th = -PI + 2.0 * PI * (i as f64 + 0.5) / m as f64;
            for r in [1e-3, 1.0, 3.7e4] {
                check((r * th.sin()) as f32, (r * th.cos()) as f32);
            }
        }
        for i in 0..=1_000_000 {
            let t = i as f32 * 1e-6;
            check(t, 1.0);
            check(1.0, t);
            check(-t, -1.0);
        }
        for (y, x) in [
            (0.0, 1.0),
            (1.0, 0.0),
            (0.0, -1.0),
            (-1.0, 0.0),
            (-0.0, -1.0),
            (0.0, 0.0),
        ] {
            check(y, x);
        }
        eprintln!("fast_atan2 max error over the grid: {max_err:.3e} rad");
        assert!(max_err <= ATAN2_MAX_ERROR_RAD, "measured {max_err:e}");
        const { assert!(ATAN2_MAX_ERROR_RAD < 1e-5) };
        // Range: (-pi, pi].
        assert_eq!(fast_atan2(-0.0, -1.0), std::f32::consts::PI);
        assert_eq!(fast_atan2(0.0, 0.0), 0.0);
    }

    #[test]
    fn aop_error_is_measured_and_below_the_const() {
        // The AoP of the hot loop (half-angle form, `L` computed in f32 as the kernel does)
        // against f64 0.5 atan2 of the same f32 S1, S2, compared modulo pi; 2 million
        // directions at several magnitudes, plus the axes and signed zeros. Every result must
        // lie strictly inside (-pi/2, pi/2).
        let mut max_err = 0.0f64;
        let mut check = |s1: f32, s2: f32| {
            let l = (s1 * s1 + s2 * s2).sqrt();
            let got = fast_aop(s1, s2, l);
            let want = 0.5 * f64::from(s2).atan2(f64::from(s1));
            assert!(
                f64::from(got).abs() < PI / 2.0,
                "AoP {got} out of range at ({s1}, {s2})"
            );
            max_err = max_err.max(aop_diff(f64::from(got), want));
        };
        let m = 2_000_000;
        for i in 0..m {
            let th = -PI + 2.0 * PI * (i as f64 + 0.5) / m as f64;
            for r in [1e-3, 1.0, 3.7e4, 1.3e5] {
                check((r * th.cos()) as f32, (r * th.sin()) as f32);
            }
        }
        for (s1, s2) in [
            (1.0, 0.0),
            (-1.0, 0.0),
            (-1.0, -0.0),
            (0.0, 1.0),
            (0.0, -1.0),
            (-0.0, 1.0),
            (-0.0, -1.0),
            (-1.0, 1e-30),
            (-1.0, -1e-30),
        ] {
            check(s1, s2);
        }
        eprintln!("fast_aop max error over the grid: {max_err:.3e} rad");
        assert!(max_err <= AOP_MAX_ERROR_RAD, "measured {max_err:e}");
        const { assert!(AOP_MAX_ERROR_RAD < 1e-5) };
        // Far below the smallest sigma_aop a shot-noise-limited pixel can have (module doc:
        // 0.35 / sqrt(full well), 3.5e-4 rad for a full well of 1e6 e-): 100 times.
        const { assert!(AOP_MAX_ERROR_RAD < 0.01 * 3.5e-4) };
        // Below even the quantisation-only floor (no shot noise, not a real sensor):
        // sqrt(1/12) / (2 * 65535) = 2.2e-6 rad.
        assert!(AOP_MAX_ERROR_RAD < (1.0f64 / 12.0).sqrt() / (2.0 * 65535.0));
        // L = 0: undefined (NaN), never a panic.
        assert!(fast_aop(0.0, 0.0, 0.0).is_nan());
    }

    #[test]
    fn thread_count_does_not_change_a_bit() {
        // An odd size (neither rows nor bands aligned with the 512-pixel chunks), random
        // frames of 1000 to 2000 DN, a few saturated pixels and a few below the offset (so
        // that chunks of all kinds occur: plain, clamped, with saturation), a dark map; 4
        // frames (fused kernel) and 7 frames (per-frame kernel). One thread (one band) must
        // give the same bits as several (16 bands: the threads are capped by the machine's
        // available parallelism).
        let (w, h) = (401u32, 307u32);
        let n = (w * h) as usize;
        let mut rng = Dice::new(42);
        for g in [
            SetGeometry::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap(),
            SetGeometry::ideal(&deg(&[0.0, 25.0, 50.0, 75.0, 100.0, 125.0, 150.0])).unwrap(),
        ] {
            let frames: Vec<Vec<u16>> = (0..g.frame_count())
                .map(|_| {
                    (0..n)
                        .map(|i| match i {
                            _ if i % 7919 == 11 => 4095,
                            _ if i % 5003 == 17 => 50,
                            _ => (1000 + rng.index(1000)) as u16,
                        })
                        .collect()
                })
                .collect();
            let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
            let dark = Dark::Map((0..n).map(|i| 100.0 + (i % 7) as f32).collect());
            let nm = NoiseModel {
                saturation_dn: 4095,
                ..noise()
            };
            let one = compute(&refs, w, h, &g, &dark, &nm, 1).unwrap();
            assert!(one.saturated > 0);
            let mut out = Products::empty();
            for t in [2, 3, 7, 0] {
                compute_into(&mut out, &refs, w, h, &g, &dark, &nm, t).unwrap();
                assert_eq!(out.saturated, one.saturated);
                for (a, b) in out.images().iter().zip(one.images()) {
                    assert!(a
                        .iter()
                        .zip(b)
                        .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan())));
                }
            }
        }
    }

    #[test]
    fn clamped_and_unclamped_chunks_agree() {
        // The same 511 pixels in a chunk whose values are all above the offset (C accumulated
        // from y with the offset folded into the start) and in a chunk with one more pixel
        // below the offset (C from max(y - offset, 0)): equal to f32 rounding (1e-6
        // relative, a few ulps of the accumulated sums).
        let g = SetGeometry::ideal(&deg(&[0.0, 45.0, 90.0, 135.0])).unwrap();
        let nm = noise();
        let mut rng = Dice::new(7);
        let frames: Vec<Vec<u16>> = (0..4)
            .map(|_| {
                (0..512)
                    .map(|i| {
                        if i == 0 {
                            200
                        } else {
                            (150 + rng.index(3000)) as u16
                        }
                    })
                    .collect()
            })
            .collect();
        let mut low = frames.clone();
        for f in &mut low {
            f[0] = 20;
        }
        let run = |fr: &Vec<Vec<u16>>| {
            let refs: Vec<&[u16]> = fr.iter().map(Vec::as_slice).collect();
            compute(&refs, 512, 1, &g, &Dark::Scalar(120.0), &nm, 1).unwrap()
        };
        let (a, b) = (run(&frames), run(&low));
        for (x, y) in a.images().iter().zip(b.images()) {
            for j in 1..512 {
                let (x, y) = (f64::from(x[j]), f64::from(y[j]));
                assert!((x - y).abs() <= 1e-6 * x.abs().max(1.0), "{x} vs {y}");
            }
        }
        // The clamp matters for the low pixel: its variance is the read variance alone.
        let p0 = g.pinv();
        let want: f64 = p0.iter().map(|c| c[0] * c[0] * nm.read_var_dn2).sum();
        assert!((f64::from(b.sigma_s0[0]).powi(2) - want).abs() <= 1e-5 * want);
    }

    #[test]
    fn buffers_are_reused_and_summary_averages_finite_pixels() {
        let g = SetGeometry::ideal(&deg(&[0.0, 60.0, 120.0])).unwrap();
        let f = vec![500u16; 12];
        let mut out = Products::empty();
        compute_into(
            &mut out,
            &[&f, &f, &f],
            4,
            3,
            &g,
            &Dark::Scalar(100.0),
            &noise(),
            0,
        )
        .unwrap();
        let ptr = out.s0.as_ptr();
        compute_into(
            &mut out,
            &[&f, &f, &f],
            3,
            4,
            &g,
            &Dark::Scalar(100.0),
            &noise(),
            0,
        )
        .unwrap();
        assert_eq!(out.s0.as_ptr(), ptr, "same size: no reallocation");
        assert_eq!((out.width, out.height), (3, 4));
        let s = out.summary(None).unwrap();
        assert!((s.mean_of("s0").unwrap() - 800.0).abs() < 1e-3);
        assert_eq!(
            s.mean_of("aop_rad"),
            None,
            "uniform frames: AoP undefined everywhere"
        );
        let mut mask = vec![false; 12];
        mask[0] = true;
        let s = out.summary(Some(&mask)).unwrap();
        assert_eq!(s.count[0], 1);
        assert_eq!(Products::names().len(), 10);
        for name in Products::names() {
            assert_eq!(out.image(name).map(<[f32]>::len), Some(12));
        }
        assert!(out.image("nope").is_none());
        assert!(g.condition_number() >= 1.0 && g.condition_number() < 10.0);
        assert_eq!(g.pinv_matrix().shape(), (3, 3));
    }
}
