//! The specular lobe's integrand in polar slope coordinates `(psi, t)`, its smooth pieces and
//! their product Gauss-Legendre rule, and the specular skylight it integrates.

use super::batch::*;
use super::facet::*;
use super::ladder::*;
use crate::error::ModelError;
use crate::geometry::{FacetGeometry, COS_FLOOR};
use crate::quadrature::{gauss_legendre_table, integrate_periodic_split_n, IntegralN, Tolerance};
use crate::sky::SkyRadiance;
use nalgebra::Vector3;
use std::f64::consts::PI;

/// Checks a view direction: unit (to 1e-9) and not below the horizon. Errors name `omega_view`.
pub(crate) fn check_view(omega_view: &Vector3<f64>) -> Result<(), ModelError> {
    let n2 = omega_view.norm_squared();
    if n2.is_finite() && (n2 - 1.0).abs() <= 2e-9 && omega_view.z >= 0.0 {
        Ok(())
    } else {
        Err(ModelError::Invalid {
            field: "omega_view",
            reason: format!("{omega_view:?} must be a unit vector with z >= 0"),
        })
    }
}

/// The slope-space integrand of [`specular_skylight`] for one view: `value(psi, t)` is the
/// reflected Stokes vector's density over the facet slope `rho (cos psi, sin psi)`,
/// `rho = sigma sqrt(2) t`, in the measure `dpsi dt` (the Gaussian slope weight
/// `2 t exp(-t^2) / (2 pi)` included).
pub(crate) struct SlopeIntegrand<'a, S: SkyRadiance + ?Sized> {
    pub(super) eps: num_complex::Complex64,
    pub(super) sky: &'a S,
    pub(super) omega_view: Vector3<f64>,
    /// `cos theta_v`, floored at [`COS_FLOOR`].
    pub(super) cv: f64,
    /// `1 / cv`.
    pub(super) inv_cv: f64,
    /// `sin theta_v`.
    pub(super) sv: f64,
    /// Unit horizontal vector towards the view's azimuth (x at nadir); `e2 = z x e1`.
    pub(super) e1: Vector3<f64>,
    pub(super) e2: Vector3<f64>,
    /// The facet slope that reflects the sky's peak into the view, as `(psi, t)`.
    pub(super) peak: Option<(f64, f64)>,
    /// The view's reflected surface frame.
    pub(super) s_r: ReflectedFrame,
    /// `rho / t = sigma sqrt(2)`.
    pub(super) rho_per_t: f64,
    /// `omega_view × z` and its components along the reflected frame's `x` and `y`: the
    /// facet frame's `x` is `omega_view × h ∝ omega_view × z - rho omega_view × along`
    /// ([`SlopeLine`]).
    pub(super) view_cross_z: Vector3<f64>,
    pub(super) view_cross_z_r: (f64, f64),
    /// `Re eps` of a dielectric with `eps >= 1` (no total internal reflection at any angle:
    /// [`real_amplitudes`] holds for every facet), whose Fresnel terms the batch computes in
    /// vector loops; `None` for any other surface.
    pub(super) real_eps: Option<f64>,
}

/// [`SlopeIntegrand::point`]: one point's geometry. On the integrand's support when
/// `cos_beta > 0` and `cos_d > 0`.
pub(crate) struct SlopePoint {
    /// `1 / sqrt(1 + rho^2)`, the half vector's `z`.
    pub(super) inv_n: f64,
    pub(super) cos_beta: f64,
    /// `omega_d.z`.
    pub(super) cos_d: f64,
    /// The reflected (incident sky) direction.
    pub(super) omega_d: Vector3<f64>,
    /// The shadowing term times `cos beta / cos theta_v`.
    pub(super) g: f64,
    /// The facet frame's `x` (unnormalised) and its components along the reflected frame's `x`
    /// and `y`.
    pub(super) s_f: Vector3<f64>,
    pub(super) c: f64,
    pub(super) sn: f64,
}

/// The terms of one line of [`SlopeIntegrand`] (slope azimuth `psi`) that do not change along
/// it: with `along` the line's unit horizontal direction and `rho` the slope, the unnormalised
/// half vector is `z - rho along` (of squared length `1 + rho^2`), so `cos beta =
/// (cos theta_v - rho omega_view . along) / sqrt(1 + rho^2)` and the facet frame's `x`,
/// `omega_view × omega_d = 2 cos beta / sqrt(1 + rho^2) (omega_view × z - rho omega_view ×
/// along)`, is a linear function of `rho` up to a positive scale, which no frame rotation sees.
pub(crate) struct SlopeLine {
    pub(crate) along: Vector3<f64>,
    /// `omega_view . along`.
    pub(crate) view_along: f64,
    /// `omega_view × along` and its components along the reflected frame's `x` and `y`.
    pub(crate) view_cross_along: Vector3<f64>,
    pub(crate) view_cross_along_r: (f64, f64),
}

/// Fixed splits of every line in `t`, so that no piece spans more than the Gaussian weight's
/// scale where it matters.
pub(super) const SLOPE_SPLITS: [f64; 2] = [1.5, 3.0];

/// Truncation of the slope measure: `t <= T`, leaving out `exp(-T^2)` of it.
pub(crate) const SLOPE_T: f64 = 6.5;

impl<'a, S: SkyRadiance + ?Sized> SlopeIntegrand<'a, S> {
    pub(crate) fn new(
        eps: num_complex::Complex64,
        sigma: f64,
        sky: &'a S,
        omega_view: &Vector3<f64>,
    ) -> Self {
        let cv = omega_view.z.max(COS_FLOOR);
        let sv = (omega_view.x * omega_view.x + omega_view.y * omega_view.y).sqrt();
        let e1 = if sv > 0.0 {
            Vector3::new(omega_view.x / sv, omega_view.y / sv, 0.0)
        } else {
            Vector3::x()
        };
        let e2 = Vector3::z().cross(&e1);
        // h ∝ z - rho (cos psi e1 + sin psi e2), so the slope is -(h.e1, h.e2) / h.z.
        let peak = sky.peak().and_then(|d| {
            let h = d + omega_view;
            if d.z <= 0.0 || h.z <= 0.0 {
                return None;
            }
            let (p, q) = (-h.dot(&e1) / h.z, -h.dot(&e2) / h.z);
            let t = p.hypot(q) / (sigma * std::f64::consts::SQRT_2);
            let psi = q.atan2(p);
            let psi = if psi < -std::f64::consts::FRAC_PI_2 {
                psi + 2.0 * PI
            } else {
                psi
            };
            (t < SLOPE_T).then_some((psi, t))
        });
        let s_r = ReflectedFrame::new(omega_view, sky.peak());
        let view_cross_z = omega_view.cross(&Vector3::z());
        SlopeIntegrand {
            eps,
            sky,
            omega_view: *omega_view,
            cv,
            inv_cv: 1.0 / cv,
            sv,
            e1,
            e2,
            peak,
            s_r,
            rho_per_t: sigma * std::f64::consts::SQRT_2,
            view_cross_z,
            view_cross_z_r: (s_r.x.dot(&view_cross_z), s_r.y.dot(&view_cross_z)),
            real_eps: (eps.im == 0.0 && eps.re >= 1.0).then_some(eps.re),
        }
    }

    /// The line of slope azimuth `psi`'s constant terms.
    #[inline]
    pub(crate) fn line(&self, psi: f64) -> SlopeLine {
        self.line_at(psi.sin_cos())
    }

    /// [`SlopeIntegrand::line`] from `(sin psi, cos psi)`.
    #[inline]
    pub(crate) fn line_at(&self, (sp, cp): (f64, f64)) -> SlopeLine {
        let along = self.e1 * cp + self.e2 * sp;
        let view_cross_along = self.omega_view.cross(&along);
        SlopeLine {
            along,
            view_along: self.omega_view.dot(&along),
            view_cross_along,
            view_cross_along_r: (
                self.s_r.x.dot(&view_cross_along),
                self.s_r.y.dot(&view_cross_along),
            ),
        }
    }

    #[inline]
    pub(crate) fn value(&self, psi: f64, t: f64) -> [f64; 3] {
        self.value_on(&self.line(psi), t, slope_weight(t))
    }

    /// [`SlopeIntegrand::value`] on the line `line` (from [`SlopeIntegrand::line`]). `weight`
    /// is [`slope_weight`]`(t)`. The adaptive rule's point, and the product rule's at a
    /// degenerate facet frame; the product rule's pieces compute the same in vector loops
    /// ([`SlopeIntegrand::piece`], tested against this).
    #[inline(always)]
    pub(crate) fn value_on(&self, line: &SlopeLine, t: f64, weight: f64) -> [f64; 3] {
        let rho = self.rho_per_t * t;
        let p = self.point(line, rho);
        if p.cos_beta <= 0.0 || p.cos_d <= 0.0 {
            return [0.0; 3];
        }
        let w = weight * p.g;
        if p.s_f.norm_squared() > 1e-200 {
            // `R(-eta_r) M(beta) R(eta_i) S` (Eq. 3.7) with the sky's Stokes vector asked for
            // in the facet frame, so that neither the incident surface frame nor `R(eta_i)` is
            // formed, and `M(beta)` (Eq. 3.5) applied by its four distinct entries: the same
            // product as `rotated_fresnel(..) * stokes_from(..)` up to rounding (tested).
            let s = self.sky.stokes_in_frame(&p.omega_d, &p.s_f);
            return facet_reflection_cs(self.eps, p.cos_beta, &s, p.c, p.sn, w);
        }
        // omega_d is unit (to rounding) and above the horizon, omega_view checked, h and
        // cos beta known: the world-frame facet geometry without normalising its frames.
        let h = Vector3::new(
            -rho * p.inv_n * line.along.x,
            -rho * p.inv_n * line.along.y,
            p.inv_n,
        );
        let m = FacetGeometry::from_half_vector(&p.omega_d, &self.omega_view, &h, p.cos_beta)
            .rotated_fresnel(self.eps);
        let s = self.sky.stokes_from(&p.omega_d);
        let out = m * s.0 * w;
        [out[0], out[1], out[2]]
    }

    /// The geometry of the point of slope `rho` on `line` ([`SlopeLine`]): shared by
    /// [`SlopeIntegrand::value_on`] and the product rule's vector loop
    /// ([`SlopeIntegrand::piece`]), branch-free so that the loop vectorises.
    #[inline(always)]
    pub(crate) fn point(&self, line: &SlopeLine, rho: f64) -> SlopePoint {
        // `h = (z - rho along) / n`, `n = sqrt(1 + rho^2)` (`along` is unit and horizontal).
        let inv_n = 1.0 / (1.0 + rho * rho).sqrt();
        let omega_view = &self.omega_view;
        let cos_beta = (omega_view.z - rho * line.view_along) * inv_n;
        // `omega_d = 2 cos beta h - omega_view`.
        let twice_cb_inv_n = 2.0 * cos_beta * inv_n;
        let cos_d = twice_cb_inv_n - omega_view.z;
        let out_of_plane = twice_cb_inv_n * rho;
        let omega_d = Vector3::new(
            -out_of_plane * line.along.x - omega_view.x,
            -out_of_plane * line.along.y - omega_view.y,
            cos_d,
        );
        // `G cos beta / cos theta_v` (`cos alpha = 1 / n`).
        let g = less(
            less(cos_beta * self.inv_cv, 2.0 * inv_n),
            2.0 * inv_n * cos_d * self.inv_cv,
        );
        // The facet frame's x, `omega_r × omega_i` as in `FacetGeometry::from_half_vector`, up
        // to its positive scale `2 cos beta / n`, and its components in the reflected frame.
        let q = &line.view_cross_along;
        SlopePoint {
            inv_n,
            cos_beta,
            cos_d,
            omega_d,
            g,
            s_f: Vector3::new(
                self.view_cross_z.x - rho * q.x,
                self.view_cross_z.y - rho * q.y,
                -rho * q.z,
            ),
            c: self.view_cross_z_r.0 - rho * line.view_cross_along_r.0,
            sn: self.view_cross_z_r.1 - rho * line.view_cross_along_r.1,
        }
    }

    /// The integrand's kinks along `t` at azimuth `psi` (`k = cos psi sin theta_v`), in slope
    /// `rho`: facet turning away (`cos beta = 0`): `rho = cos theta_v / k`; reflected ray at the
    /// horizon (`cos theta_d = 0`): `cos theta_v rho^2 + 2 k rho - cos theta_v = 0`; the
    /// shadowing min switching branches: `rho = -cos theta_v / k` and `rho = -k / cos theta_v`.
    pub(crate) fn kinks(&self, psi: f64, out: &mut Vec<f64>) {
        let (k, cv) = (psi.cos() * self.sv, self.cv);
        let to_t = 1.0 / self.rho_per_t;
        if k != 0.0 {
            out.push(cv / k * to_t);
            out.push(-cv / k * to_t);
        }
        out.push(-k / cv * to_t);
        out.push((-k + k.hypot(cv)) / cv * to_t);
    }

    /// The smooth pieces of the line at azimuth `psi` (given as `cos_psi`), as `t` from 0 to
    /// the end of the integrand's support: the line ends where the reflected ray reaches the
    /// horizon (`cos theta_v rho^2 + 2 k rho - cos theta_v = 0`, `k = cos psi sin theta_v`;
    /// beyond it the integrand is 0) or at `T`, and breaks where the shadowing `min(A, B, C)`
    /// (`A = cos beta / cos theta_v`, `B = 2 cos alpha`, `C = 2 cos alpha cos theta_d / cos
    /// theta_v`) switches branches: `A = B` at `rho = -cos theta_v / k`, `B = C` at
    /// `rho = -k / cos theta_v`, and `A = C` on the cubic
    /// `k rho^3 - 3 cos theta_v rho^2 - 3 k rho + cos theta_v = 0`, which with `rho = tan x` is
    /// `tan 3x = cos theta_v / k`. A switch is a break only where its two branches are the
    /// minimum.
    pub(crate) fn pieces(&self, cos_psi: f64, out: &mut Vec<f64>) {
        out.clear();
        let (k, cv) = (cos_psi * self.sv, self.cv);
        let to_t = 1.0 / self.rho_per_t;
        let end = ((-k + k.hypot(cv)) / cv * to_t).min(SLOPE_T);
        let abc = |rho: f64| {
            let c = 1.0 / (1.0 + rho * rho).sqrt();
            (
                (cv - k * rho) * c / cv,
                2.0 * c,
                2.0 * c * c * c * (cv - 2.0 * k * rho - cv * rho * rho) / cv,
            )
        };
        out.push(0.0);
        let mut push = |rho: f64, active: bool| {
            let t = rho * to_t;
            if active && t > 0.0 && t < end {
                out.push(t);
            }
        };
        let slack = 1.0 + 1e-9;
        if k < 0.0 {
            let r = -cv / k;
            let (a, _, c) = abc(r);
            push(r, a <= c * slack);
            let r = -k / cv;
            let (a, b, _) = abc(r);
            push(r, b <= a * slack);
        }
        // The roots `tan x` at `x = phi0 / 3` and `x + pi / 3` (below pi / 2), the second by
        // the addition formula: one `tan` for both.
        let x = cv.atan2(k) / 3.0;
        let r = x.tan();
        let (_, b, c) = abc(r);
        push(r, c <= b * slack);
        if x + std::f64::consts::FRAC_PI_3 < std::f64::consts::FRAC_PI_2 {
            let sqrt3 = 3f64.sqrt();
            let r = (r + sqrt3) / (1.0 - sqrt3 * r);
            let (_, b, c) = abc(r);
            push(r, c <= b * slack);
        }
        for t in SLOPE_SPLITS.into_iter().chain(self.peak.map(|p| p.1)) {
            if t > 0.0 && t < end {
                out.push(t);
            }
        }
        out.push(end.max(0.0));
        out.sort_by(f64::total_cmp);
        out.dedup();
    }

    /// The integral by the adaptive rule: periodic trapezoid in `psi`, adaptive Gauss-Kronrod
    /// along each line, split at [`SlopeIntegrand::kinks`].
    pub(crate) fn adaptive(&self, tol: Tolerance) -> IntegralN<3> {
        integrate_periodic_split_n(
            |psi, t| self.value(psi, t),
            (0.0, 2.0 * PI),
            (0.0, SLOPE_T),
            |psi, out: &mut Vec<f64>| self.kinks(psi, out),
            tol,
        )
    }

    /// The azimuth arcs on which the line integrals are smooth: split where `k = 0` (`psi =
    /// +-pi/2`, where the `B = C` break enters the line at `t = 0`) and, for views more than
    /// 45 deg off the normal, where `k = -cos theta_v` (`A = B = C` at one point of the line:
    /// there the kinks change which branches they join). Returns how many of `out` are set.
    pub(crate) fn arcs(&self, out: &mut [(f64, f64); 5]) -> usize {
        let h = std::f64::consts::FRAC_PI_2;
        out[0] = (-h, h);
        let mut count = if self.sv > self.cv {
            let star = (-self.cv / self.sv).acos();
            out[1] = (h, star);
            out[2] = (star, 2.0 * PI - star);
            out[3] = (2.0 * PI - star, 3.0 * h);
            4
        } else {
            out[1] = (h, 3.0 * h);
            2
        };
        if let Some((psi, _)) = self.peak {
            if let Some(i) = out[..count].iter().position(|&(a, b)| a < psi && psi < b) {
                let (a, b) = out[i];
                out[i] = (a, psi);
                out[count] = (psi, b);
                count += 1;
            }
        }
        count
    }

    /// The integral by a product Gauss-Legendre rule: `n` azimuths per half turn over the arcs
    /// of [`SlopeIntegrand::arcs`] (at least `n / 2` per arc, at most 64), `q` points on each
    /// smooth piece of each line from [`SlopeIntegrand::pieces`] (about half as many beyond the
    /// last fixed split).
    pub(crate) fn gauss(&self, n: usize, q: usize, pieces: &mut Vec<f64>) -> ([f64; 3], usize) {
        // Compiled once per instruction set pulp knows (SSE2, AVX2 with FMA) and run in the
        // widest the CPU has: the same operations in the same order on every path (Rust forms
        // no fused multiply-adds), so the same result to the bit.
        pulp::Arch::new().dispatch(SlopeRule {
            integrand: self,
            n,
            q,
            pieces,
        })
    }

    /// [`SlopeIntegrand::gauss`] in whichever instruction set it is dispatched to.
    #[inline(always)]
    pub(crate) fn gauss_rule(
        &self,
        n: usize,
        q: usize,
        pieces: &mut Vec<f64>,
    ) -> ([f64; 3], usize) {
        let mut sum = [0.0; 3];
        let mut evaluations = 0;
        let mut shared = SharedWeights::new(self.peak.map(|p| p.1));
        let mut batch = FacetBatch::new();
        let mut arcs = [(0.0, 0.0); 5];
        let count = self.arcs(&mut arcs);
        for &(a, b) in &arcs[..count] {
            let gn = gauss_legendre_table(arc_points(n, b - a));
            let (centre, half) = (0.5 * (a + b), 0.5 * (b - a));
            for &(x, wx) in gn {
                let psi = centre + half * x;
                let wpsi = half * wx;
                let (sp, cp) = psi.sin_cos();
                self.pieces(cp, pieces);
                let line = self.line_at((sp, cp));
                for w in pieces.windows(2) {
                    let (mid, half) = (0.5 * (w[0] + w[1]), 0.5 * (w[1] - w[0]));
                    if half <= 0.0 {
                        continue;
                    }
                    // Beyond the last fixed split the Gaussian weight is below exp(-9) of its
                    // peak: about half the points, still growing with every level.
                    let gq = gauss_legendre_table(if w[0] >= SLOPE_SPLITS[1] {
                        q.div_ceil(2) + 1
                    } else {
                        q
                    });
                    let weights = shared.get(w[0], w[1], gq);
                    self.piece(&line, gq, (mid, half, wpsi), weights, &mut batch, &mut sum);
                    evaluations += gq.len();
                }
            }
        }
        (sum, evaluations)
    }
}

impl<'a, S: SkyRadiance + ?Sized> SlopeIntegrand<'a, S> {
    /// One smooth piece of a line of the product rule: `sum += wpsi half wy value(psi, t)` over
    /// its Gauss nodes `(y, wy)`, `t = mid + half y`, with `weights` the slope weights at the
    /// nodes when every line shares the piece ([`SharedWeights`]).
    ///
    /// [`SlopeIntegrand::value_on`]'s arithmetic, reordered into loops over the piece's nodes
    /// (structure of arrays, no branches: a point off the integrand's support gets weight 0),
    /// which the compiler vectorises: the geometry, the sky ([`SkyRadiance::
    /// stokes_in_frame_batch`]) and, for a dielectric, the Fresnel terms and the rotation into
    /// the reflected frame. The same values as `value_on` to rounding (tested); a point whose
    /// facet frame is degenerate (the facet normal along the view) takes `value_on` itself.
    #[inline(always)]
    pub(crate) fn piece(
        &self,
        line: &SlopeLine,
        nodes: &[(f64, f64)],
        rule: (f64, f64, f64),
        weights: Option<&[f64]>,
        b: &mut FacetBatch,
        sum: &mut [f64; 3],
    ) {
        for start in (0..nodes.len()).step_by(FACET_BATCH) {
            let end = (start + FACET_BATCH).min(nodes.len());
            let weights = weights.map(|ws| &ws[start..end]);
            self.piece_batch(line, &nodes[start..end], rule, weights, b, sum);
        }
    }

    /// [`SlopeIntegrand::piece`] for at most [`FACET_BATCH`] nodes.
    #[inline(always)]
    pub(crate) fn piece_batch(
        &self,
        line: &SlopeLine,
        nodes: &[(f64, f64)],
        (mid, half, wpsi): (f64, f64, f64),
        weights: Option<&[f64]>,
        b: &mut FacetBatch,
        sum: &mut [f64; 3],
    ) {
        let n = nodes.len().min(FACET_BATCH);
        // The slope weights times the quadrature weights.
        match weights {
            Some(ws) => {
                for (i, &(y, wy)) in nodes[..n].iter().enumerate() {
                    b.rho[i] = self.rho_per_t * (mid + half * y);
                    b.w[i] = ws[i] * (wpsi * half * wy);
                }
            }
            None => {
                for (i, &(y, wy)) in nodes[..n].iter().enumerate() {
                    let t = mid + half * y;
                    b.rho[i] = self.rho_per_t * t;
                    b.w[i] = slope_weight(t) * (wpsi * half * wy);
                }
            }
        }
        let mut idle = false;
        for i in 0..n {
            let p = self.point(line, b.rho[i]);
            (b.dx[i], b.dy[i], b.dz[i]) = (p.omega_d.x, p.omega_d.y, p.omega_d.z);
            b.cos_beta[i] = p.cos_beta;
            (b.fx[i], b.fy[i], b.fz[i]) = (p.s_f.x, p.s_f.y, p.s_f.z);
            b.f2[i] = p.s_f.x * p.s_f.x + p.s_f.y * p.s_f.y + p.s_f.z * p.s_f.z;
            (b.c[i], b.sn[i]) = (p.c, p.sn);
            let on = p.cos_beta > 0.0 && p.cos_d > 0.0;
            b.w[i] = if on { b.w[i] * p.g } else { 0.0 };
            // A point to set aside below (a vectorised OR: most pieces have none).
            idle |= !on | (b.f2[i] <= 1e-200) | (b.w[i] == 0.0);
        }
        // A degenerate facet frame: the general product, one point. That point, and those off
        // the support, then ask the sky for the zenith in a valid frame (weight 0: only so
        // that every sky's value there is finite).
        for i in 0..if idle { n } else { 0 } {
            let degenerate = b.f2[i] <= 1e-200;
            if b.w[i] == 0.0 || degenerate {
                if b.w[i] != 0.0 {
                    let t = b.rho[i] / self.rho_per_t;
                    let g = weights.map_or_else(|| slope_weight(t), |ws| ws[i]);
                    let v = self.value_on(line, t, g);
                    add_scaled(sum, &v, wpsi * half * nodes[i].1);
                }
                b.set_idle(i);
            }
        }
        reflect_batch(self.sky, self.eps, self.real_eps, b, n, sum);
    }
}

/// [`SlopeIntegrand::gauss_rule`] for [`pulp::Arch::dispatch`]. `with_simd` is generic over
/// the instruction set, so each set gets its own copy of the rule, inlined into pulp's entry
/// point compiled for that set. (A closure handed to `dispatch` would be one function whatever
/// the set, so the AVX2 entry point would run SSE2 code; and pulp's `x86-v3` feature must be
/// on, or `Arch` never detects AVX2.)
pub(crate) struct SlopeRule<'r, 'a, S: SkyRadiance + ?Sized> {
    pub(super) integrand: &'r SlopeIntegrand<'a, S>,
    pub(super) n: usize,
    pub(super) q: usize,
    pub(super) pieces: &'r mut Vec<f64>,
}

impl<S: SkyRadiance + ?Sized> pulp::WithSimd for SlopeRule<'_, '_, S> {
    type Output = ([f64; 3], usize);

    #[inline(always)]
    fn with_simd<Simd: pulp::Simd>(self, _simd: Simd) -> Self::Output {
        self.integrand.gauss_rule(self.n, self.q, self.pieces)
    }
}

/// [`slope_weight`] at the Gauss nodes of the pieces that every line of a product rule shares:
/// those between the fixed splits, the sky peak's split, `0` and [`SLOPE_T`] (the line's
/// kinks and horizon end move with its azimuth). Computed once per rule instead of once per
/// line: the same values to the bit, since a piece's nodes come from its ends alone.
pub(crate) struct SharedWeights {
    /// The splits every line has: `0`, [`SLOPE_SPLITS`], the peak's and [`SLOPE_T`].
    pub(crate) fixed: [f64; 5],
    /// Per piece met so far: its ends and its nodes' weights (at most [`SHARED_MAX_NODES`]).
    pub(crate) pieces: Vec<(f64, f64, usize, [f64; SHARED_MAX_NODES])>,
}

impl SharedWeights {
    pub(crate) fn new(peak_t: Option<f64>) -> SharedWeights {
        SharedWeights {
            fixed: [
                0.0,
                SLOPE_SPLITS[0],
                SLOPE_SPLITS[1],
                peak_t.unwrap_or(0.0),
                SLOPE_T,
            ],
            pieces: Vec::new(),
        }
    }

    /// The weights at the nodes `gq` of the piece `[a, b]` when every line shares it (`None`
    /// otherwise: the caller computes its own).
    #[inline]
    pub(crate) fn get(&mut self, a: f64, b: f64, gq: &[(f64, f64)]) -> Option<&[f64]> {
        let shared = |x: f64| self.fixed.contains(&x);
        if gq.len() > SHARED_MAX_NODES || !shared(a) || !shared(b) {
            return None;
        }
        let found = self
            .pieces
            .iter()
            .position(|p| p.0 == a && p.1 == b && p.2 == gq.len());
        let i = match found {
            Some(i) => i,
            None => {
                let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
                let mut weights = [0.0; SHARED_MAX_NODES];
                for (w, &(y, _)) in weights.iter_mut().zip(gq) {
                    *w = slope_weight(mid + half * y);
                }
                self.pieces.push((a, b, gq.len(), weights));
                self.pieces.len() - 1
            }
        };
        let p = &self.pieces[i];
        Some(&p.3[..p.2])
    }
}

/// The specular part of Eq. 3.22 for a microfacet surface of permittivity `eps` and roughness
/// `sigma`, integrated in facet-slope space ([`crate::slope`] docs). The result is in the reflected
/// surface frame of `omega_view`.
///
/// The rule is a product Gauss-Legendre rule on the integrand's smooth pieces
/// (`SlopeIntegrand::gauss`) at increasing levels (`GAUSS_LEVELS`); if the last level does
/// not meet `tol` (a sky with a sharp feature inside the lobe), the adaptive rule takes over and
/// the better of the two is returned.
pub fn specular_skylight<S: SkyRadiance + ?Sized>(
    eps: num_complex::Complex64,
    sigma: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
) -> Result<StokesIntegral, ModelError> {
    specular_skylight_from(eps, sigma, sky, omega_view, tol, Start::Level(0))
}

/// [`specular_skylight`] with the product rule's levels from `start` (`ladder`).
pub(crate) fn specular_skylight_from<S: SkyRadiance + ?Sized>(
    eps: num_complex::Complex64,
    sigma: f64,
    sky: &S,
    omega_view: &Vector3<f64>,
    tol: Tolerance,
    start: Start,
) -> Result<StokesIntegral, ModelError> {
    check_view(omega_view)?;
    let integrand = SlopeIntegrand::new(eps, sigma, sky, omega_view);
    let mut pieces = Vec::with_capacity(8);
    Ok(ladder(
        |n, q| integrand.gauss(n, q, &mut pieces),
        || integrand.adaptive(tol),
        tol,
        slope_truncation(sky),
        start,
    ))
}

/// The error of leaving out the slope measure beyond `SLOPE_T`: its weight `exp(-T^2)`
/// times twice the zenith sky (a bound of the integrand's scale).
pub(crate) fn slope_truncation<S: SkyRadiance + ?Sized>(sky: &S) -> f64 {
    2.0 * (-SLOPE_T * SLOPE_T).exp() * sky.stokes_from(&Vector3::z()).0[0].abs()
}
