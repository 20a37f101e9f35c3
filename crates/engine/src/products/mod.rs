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
//!   pseudo-inverse (ordinary least squares), computed once per set in f64 by the model's
//!   estimator ([`polar_model::analyzer::stokes_from_intensities`], from the SVD of `A`).
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

mod error;
mod fast_math;
mod geometry;
mod inputs;
mod kernel;
mod noise;
mod planes;
mod reference;

pub use error::ProductsError;
pub use fast_math::{fast_aop, fast_atan2, AOP_MAX_ERROR_RAD, ATAN2_MAX_ERROR_RAD, ATAN_COEFFS};
pub use geometry::{SetGeometry, MIN_RCOND, ROW_SCALE_RANGE};
use inputs::validate;
use kernel::*;
pub use noise::{Dark, NoiseModel};
pub use planes::{ProductSummary, Products};
pub use reference::compute_reference;
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::geometry::*;
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
