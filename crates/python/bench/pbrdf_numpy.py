"""The microfacet pBRDF Mueller matrix written in numpy: the speed benchmark's baseline.

A vectorised, pure-numpy transcription of what the Rust model (crate ``polar-model``) computes
for Meng (2012)'s microfacet polarimetric BRDF, Sec. 3.1.1 (Eqs. 3.4-3.18):

* ``Geometry::from_deg`` (``geometry.rs``, ``angles.rs``): exact trigonometry at multiples of
  90 deg, ``cos theta`` floored at ``COS_FLOOR``;
* ``FacetGeometry::new`` / ``from_frames``: half vector (Eq. 3.6), facet tilt (Eq. 3.11) and the
  signed frame rotations of Eq. 3.7 from dot and cross products (``cos_sin_2eta``);
* ``amplitudes_eps`` / ``csqrt`` (``fresnel.rs``): Fresnel amplitudes for complex ``N = n + ik``
  (Meng (2012) Eqs. 2.27-2.28), with the real-arithmetic path of a dielectric below its
  critical angle;
* ``rotated_fresnel``: ``R(-eta_r) M(beta) R(eta_i)`` (Eq. 3.7) with the facet Mueller matrix
  of Eq. 3.5;
* ``slope_density`` (Eq. 3.12, zero below ``exp(-650)``), the shadowing term of Eq. 3.14 as
  ``G / (cos ti cos tr)``, and ``Microfacet::specular`` (Eq. 3.15);
* ``Surface::mueller_with``: the diffuse ``f00`` (Eqs. 3.16-3.18) added to element (0, 0).

Every floating-point operation is written in the order the Rust code performs it (including
nalgebra's and num-complex's operation order), so the two agree to the last bit wherever
numpy's ``sin``, ``cos`` and ``exp`` round as the C library that Rust calls does (numpy
builds with AVX-512 may use their own SIMD kernels, within an ulp or so; near retro-reflection
and the plane of incidence the frame rotations come from small cross products, which amplify
such input differences in the off-diagonal elements, so agreement there would be to some
1e-13 rather than to the bit; not measured);
comments mark the few places where a rewritten expression can differ, and then only in the
sign of a zero.

Run as a script, it checks itself against the Rust-backed ``polarimeter`` package.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

#: Smallest ``cos theta`` used anywhere: ``cos(pi/2)`` as f64 evaluates it (``COS_FLOOR``).
COS_FLOOR: float = 6.123_233_995_736_766e-17
#: The slope density is exactly 0 where its exponent is below this (``slope_density``).
EXPONENT_CUTOFF: float = -650.0
#: Roughness range accepted by ``Microfacet::new``.
SIGMA_MIN: float = 1e-6
SIGMA_MAX: float = 10.0
#: ``f64::to_radians``'s factor, ``PI / 180`` rounded once.
_RAD_PER_DEG: float = math.pi / 180.0
#: ``2.0 * PI`` (exact doubling), the first factor of the slope density's denominator.
_TWO_PI: float = 2.0 * math.pi


def _round_half_away(x: np.ndarray) -> np.ndarray:
    """Rust's ``f64::round`` (halves away from zero; ``np.round`` rounds them to even).

    ``x - trunc(x)`` is exact, so the comparison with 0.5 is too (unlike ``floor(x + 0.5)``,
    which rounds 0.49999999999999994 up).
    """
    t = np.trunc(x)
    return t + np.copysign((np.abs(x - t) >= 0.5).astype(np.float64), x)


def sin_cos_deg(x_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(sin, cos)`` of angles in degrees, exact at every multiple of 90 deg (``angles.rs``).

    The argument is reduced to ``[-45, 45]`` deg in degrees (exact in f64 for ``|x| <= 720``),
    converted to radians and the quadrant applied by swapping and negating.
    """
    q = _round_half_away(x_deg / 90.0)
    r = (x_deg - 90.0 * q) * _RAD_PER_DEG
    s, c = np.sin(r), np.cos(r)
    quadrant = np.mod(q.astype(np.int64), 4)
    sin = np.select([quadrant == 0, quadrant == 1, quadrant == 2], [s, c, -s], -c)
    cos = np.select([quadrant == 0, quadrant == 1, quadrant == 2], [c, -s, -c], s)
    return sin, cos


def _check_range(name: str, v: np.ndarray, lo: float, hi: float, allowed: str) -> None:
    """``ModelError::check_range`` on a whole array: finite and within ``[lo, hi]``."""
    bad = ~(np.isfinite(v) & (v >= lo) & (v <= hi))
    if np.any(bad):
        first = v[bad].flat[0]
        raise ValueError(f"{name} = {first} is out of range: allowed {allowed}")


def fresnel_mueller_terms(eps_re: float, eps_im: float, cos_beta: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(Rs, Rp, Re(rs rp*))`` at incidence cosine ``cos_beta`` for permittivity ``N^2``.

    ``amplitudes_eps`` of ``fresnel.rs``: ``rs = (c - w) / (c + w)``,
    ``rp = (N^2 c - w) / (N^2 c + w)``, ``w = sqrt(N^2 - sin^2)`` on the principal branch
    (Meng (2012) Eqs. 2.27-2.28 written for complex ``N``). A dielectric below its critical
    angle takes the real path, sharing one division between the two amplitudes as
    ``real_amplitudes`` does; everything else the complex path with ``csqrt``'s algebraic
    square root and num-complex's division. These three numbers make the facet Mueller matrix
    of Eq. 3.5.
    """
    c = np.clip(cos_beta, 0.0, 1.0)
    sin2 = np.fmax(1.0 - c * c, 0.0)
    rs2 = np.empty_like(c)
    rp2 = np.empty_like(c)
    d = np.empty_like(c)
    if eps_im == 0.0:
        real = eps_re >= sin2
    else:
        real = np.zeros(c.shape, dtype=bool)
    all_real = bool(np.all(real))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if np.any(real):
            cr = c if all_real else c[real]
            s2 = sin2 if all_real else sin2[real]
            w = np.sqrt(eps_re - s2)
            ds = cr + w
            dp = eps_re * cr + w
            den = ds * dp
            inv = 1.0 / den
            rs = (cr - w) * dp * inv
            rp = (eps_re * cr - w) * ds * inv
            ok = (den != 0.0) & np.isfinite(den)
            if not np.all(ok):
                rs = np.where(ok, rs, np.where(ds == 0.0, 0.0, (cr - w) / ds))
                rp = np.where(ok, rp, np.where(dp == 0.0, 0.0, (eps_re * cr - w) / dp))
            # |rs|^2 = rs^2 + 0^2 and Re(rs rp*) = rs rp - 0 (-0): equal up to the sign of a
            # zero result.
            if all_real:
                rs2[...] = rs * rs
                rp2[...] = rp * rp
                d[...] = rs * rp
            else:
                rs2[real] = rs * rs
                rp2[real] = rp * rp
                d[real] = rs * rp
        if not all_real:
            cplx = ~real
            cc = c[cplx]
            # csqrt(eps - sin2): Complex - f64 subtracts from the real part only.
            a = eps_re - sin2[cplx]
            b = eps_im
            t = np.sqrt(0.5 * (np.abs(a) + np.sqrt(a * a + b * b)))
            wr = np.where(a >= 0.0, t, abs(b) / (2.0 * t))
            wi = np.where(a >= 0.0, b / (2.0 * t), np.copysign(t, b))
            zero = (a == 0.0) & (b == 0.0)
            wr = np.where(zero, 0.0, wr)
            wi = np.where(zero, b, wi)
            # ds = c + w, dp = eps c + w; numerators c - w = (c - wr, 0 - wi), eps c - w.
            dsr, dsi = cc + wr, wi
            dpr, dpi = eps_re * cc + wr, eps_im * cc + wi
            nsr, nsi = cc - wr, 0.0 - wi
            npr, npi = eps_re * cc - wr, eps_im * cc - wi

            def cdiv(nr: np.ndarray, ni: np.ndarray, dr: np.ndarray, di: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
                """num-complex's ``Div``: ``((nr dr + ni di) + i (ni dr - nr di)) / |d|^2``,
                and 0 for a zero denominator (``amplitudes_eps``)."""
                norm = dr * dr + di * di
                re = (nr * dr + ni * di) / norm
                im = (ni * dr - nr * di) / norm
                dz = (dr == 0.0) & (di == 0.0)
                return np.where(dz, 0.0, re), np.where(dz, 0.0, im)

            rsr, rsi = cdiv(nsr, nsi, dsr, dsi)
            rpr, rpi = cdiv(npr, npi, dpr, dpi)
            rs2[cplx] = rsr * rsr + rsi * rsi
            rp2[cplx] = rpr * rpr + rpi * rpi
            # (rs * conj(rp)).re = rs.re rp.re - rs.im (-rp.im)
            d[cplx] = rsr * rpr - rsi * (-rpi)
    return rs2, rp2, d


def _cos_sin_2eta(c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cos_sin_2eta`` from ``cos eta = from . to`` and ``sin eta = (from x to) . k``:
    the double-angle identities, renormalised (the sign that Meng (2012)'s arc-cosine
    Eqs. 3.9-3.10 lose is kept)."""
    n2 = c * c + s * s
    return (c * c - s * s) / n2, 2.0 * c * s / n2


def pbrdf_numpy(theta_i_deg: np.ndarray | float, theta_r_deg: np.ndarray | float,
                phi_deg: np.ndarray | float, n: float, k: float, sigma: float,
                f00_diffuse: float) -> np.ndarray:
    """The microfacet pBRDF ``F = Fs + Fd`` (Meng (2012) Eqs. 3.4-3.18), sr^-1, shape ``(..., 3, 3)``.

    theta_i_deg, theta_r_deg: incidence and view zenith, degrees, ``[0, 90]``; phi_deg:
    relative azimuth, degrees, ``[-360, 360]`` (180 is specular, Eq. 3.6's convention); they
    broadcast against each other. ``n + ik``: refractive index of the surface; ``sigma``:
    facet-slope roughness (Eq. 3.13), ``[1e-6, 10]``; ``f00_diffuse``: the diffuse term's
    ``f00`` (Eq. 3.18, sr^-1), added to element (0, 0) as ``Surface::mueller_with`` does.

    The specular part is ``p(alpha) G / (4 cos ti cos tr) R(-eta_r) M(beta) R(eta_i)``
    (Eqs. 3.7, 3.12, 3.14, 3.15) in the incident and reflected surface frames of the Rust
    model (``pbrdf.rs`` module docs). Out-of-range inputs raise ``ValueError``.
    """
    ti_deg, tr_deg, ph_deg = np.broadcast_arrays(
        np.asarray(theta_i_deg, dtype=np.float64), np.asarray(theta_r_deg, dtype=np.float64),
        np.asarray(phi_deg, dtype=np.float64))
    shape = ti_deg.shape
    ti_deg, tr_deg, ph_deg = ti_deg.ravel(), tr_deg.ravel(), ph_deg.ravel()
    if not (math.isfinite(n) and 0.0 < n <= 100.0):
        raise ValueError(f"n = {n} is out of range: allowed (0, 100]")
    _check_range("k", np.asarray(k, dtype=np.float64), 0.0, 100.0, "[0, 100]")
    _check_range("sigma", np.asarray(sigma, dtype=np.float64), SIGMA_MIN, SIGMA_MAX,
                 "[1e-6, 10]")
    if not math.isfinite(f00_diffuse):
        raise ValueError(f"f00_diffuse = {f00_diffuse} is not finite")
    # Geometry::from_angles checks the radian values (then from_deg recomputes the trig).
    _check_range("theta_i_deg", ti_deg * _RAD_PER_DEG, 0.0, math.pi / 2, "[0, 90]")
    _check_range("theta_r_deg", tr_deg * _RAD_PER_DEG, 0.0, math.pi / 2, "[0, 90]")
    _check_range("phi_deg", ph_deg * _RAD_PER_DEG, -2.0 * math.pi, 2.0 * math.pi,
                 "[-360, 360]")

    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        # Geometry::from_deg.
        sti, cti = sin_cos_deg(ti_deg)
        s_tr, ctr = sin_cos_deg(tr_deg)
        sphi, cphi = sin_cos_deg(ph_deg)
        cti = np.fmax(cti, COS_FLOOR)
        ctr = np.fmax(ctr, COS_FLOOR)

        # omega_i = (sin ti, 0, cos ti), omega_r = (sin tr cos phi, sin tr sin phi, cos tr).
        ix, iz = sti, cti
        rx, ry, rz = s_tr * cphi, s_tr * sphi, ctr

        # FacetGeometry::from_frames: half vector h (Eq. 3.6), cos beta = |sum| / 2,
        # cos alpha = h.z (Eq. 3.11), tan^2 alpha from h's components. nalgebra's norm is
        # sqrt((x^2 + y^2) + z^2) and its vector / scalar divides each component.
        sx, sy, sz = ix + rx, ry, iz + rz  # sum.y = 0 + ry: ry up to the sign of zero
        length = np.sqrt(sx * sx + sy * sy + sz * sz)
        hx, hy, hz = sx / length, sy / length, sz / length
        cos_beta = np.fmin(0.5 * length, 1.0)
        cos_alpha = hz
        tan2_alpha = (hx * hx + hy * hy) / (hz * hz)

        # s_f = omega_r x omega_i / |.|, or s_i = (0, 1, 0) where the cross product is zero
        # (retro-reflection). nalgebra's cross: (ay bz - az by, az bx - ax bz, ax by - ay bx);
        # the terms multiplying omega_i.y = 0 are dropped (equal up to the sign of zero).
        c0 = ry * iz
        c1 = rz * ix - rx * iz
        c2 = -(ry * ix)
        cross_norm = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        has_plane = cross_norm > 0.0
        fx = np.where(has_plane, c0 / cross_norm, 0.0)
        fy = np.where(has_plane, c1 / cross_norm, 1.0)
        fz = np.where(has_plane, c2 / cross_norm, 0.0)

        # rot_i = cos_sin_2eta(s_i = (0, 1, 0), s_f, k_i = -omega_i):
        # s_i . s_f = fy, (s_i x s_f) . k_i = (fz, 0, -fx) . (-ix, -0, -iz).
        ci, si = _cos_sin_2eta(fy, -(fz * ix) + fx * iz)
        # rot_r = cos_sin_2eta(s_r = (sin phi, -cos phi, 0), s_f, k_r = omega_r):
        # s_r x s_f = (-cos phi fz, -sin phi fz, sin phi fy + cos phi fx).
        cr, sr = _cos_sin_2eta(
            sphi * fx - cphi * fy,
            -(cphi * fz) * rx + -(sphi * fz) * ry + (sphi * fy + cphi * fx) * rz)

        # Fresnel terms at the half angle (Eq. 3.5); eps = (n + ik)^2 as num-complex
        # multiplies.
        eps_re = n * n - k * k
        eps_im = n * k + k * n
        rs2, rp2, d = fresnel_mueller_terms(eps_re, eps_im, cos_beta)
        a = 0.5 * (rs2 + rp2)
        b = 0.5 * (rs2 - rp2)

        # slope_density (Eq. 3.12): exp(-tan^2 a / (2 s^2)) / (2 pi s^2 cos^3 a), 0 below
        # exp(-650).
        s2 = sigma * sigma
        cc = np.fmax(cos_alpha, COS_FLOOR)
        exponent = -tan2_alpha / (2.0 * s2)
        p = np.where(exponent < EXPONENT_CUTOFF, 0.0,
                     np.exp(exponent) / (_TWO_PI * s2 * cc * cc * cc))
        # G / (cos ti cos tr) (Eq. 3.14) without 0/0 at grazing; f64::min is fmin.
        t = 2.0 * cos_alpha / np.fmax(cos_beta, COS_FLOOR)
        g_over = np.fmin(np.fmin(1.0 / (cti * ctr), t / ctr), t / cti)
        scale = 0.25 * p * g_over  # Eq. 3.15: p G / (4 cos ti cos tr)

        # rotated_fresnel: R(-eta_r) M(beta) R(eta_i) (Eq. 3.7), then times the scale.
        out = np.empty(ti_deg.shape + (3, 3))
        out[:, 0, 0] = a * scale + f00_diffuse  # Surface::mueller_with adds f00 here
        out[:, 0, 1] = b * ci * scale
        out[:, 0, 2] = b * si * scale
        out[:, 1, 0] = cr * b * scale
        out[:, 1, 1] = (cr * a * ci + sr * d * si) * scale
        out[:, 1, 2] = (cr * a * si - sr * d * ci) * scale
        out[:, 2, 0] = sr * b * scale
        out[:, 2, 1] = (sr * a * ci - cr * d * si) * scale
        out[:, 2, 2] = (sr * a * si + cr * d * ci) * scale
    return out.reshape(shape + (3, 3))


def _rust_pbrdf(ti: np.ndarray, tr: np.ndarray, phi: np.ndarray, n: float, k: float,
                sigma: float, chunk: int = 4000) -> np.ndarray:
    """The Rust model's Mueller matrices with ``dhr = 0`` (so ``f00_d = 0``), in chunks.

    With ``dhr = 0``, ``Surface::diffuse`` computes ``(0 - albedo) / pi < 0`` and clamps it
    to exactly 0 for any positive albedo, so the albedo quadrature's tolerance does not
    matter: the loosest (1e-2) is used, because the binding integrates it once per distinct
    ``theta_i`` (every geometry here) and de-duplicates the resulting warnings with a linear
    search per warning, which chunking keeps short.
    """
    import polarimeter as pm

    out = np.empty(ti.shape + (3, 3))
    for lo in range(0, ti.size, chunk):
        sl = slice(lo, lo + chunk)
        r = pm.pbrdf(ti[sl], tr[sl], phi[sl], n=n, k=k, sigma=sigma, dhr=0.0, tolerance=1e-2)
        for w in r.warnings:
            assert "clamped to 0" in w or "did not reach tolerance" in w, w
        out[sl] = r.mueller
    return out


def _geometries(rng: np.random.Generator, count: int) -> tuple[np.ndarray, ...]:
    """``count`` random geometries (theta in [0, 89.9], phi in [-180, 180]) followed by the
    exact cases: theta 0, 90 (and near them), phi 0, +-90, +-180, specular and retro."""
    ti = rng.uniform(0.0, 89.9, count)
    tr = rng.uniform(0.0, 89.9, count)
    phi = rng.uniform(-180.0, 180.0, count)
    thetas = np.array([0.0, 1e-9, 30.0, 45.0, 60.0, 89.0, 89.9, 90.0 - 1e-9, 90.0])
    phis = np.array([0.0, 180.0, -180.0, 90.0, -90.0, 45.0, 1e-9, 180.0 - 1e-9, 360.0, -360.0])
    eti, etr, ephi = (g.ravel() for g in np.meshgrid(thetas, thetas, phis, indexing="ij"))
    # Specular (tr = ti, phi = 180) and retro-reflection (tr = ti, phi = 0) at random angles.
    u = rng.uniform(0.0, 90.0, 2000)
    sti = np.concatenate([u, u])
    sphi = np.concatenate([np.full(u.size, 180.0), np.zeros(u.size)])
    return (np.concatenate([ti, eti, sti]), np.concatenate([tr, etr, sti]),
            np.concatenate([phi, ephi, sphi]))


def _self_check() -> None:
    """Compare with the Rust-backed ``polarimeter.pbrdf`` and time one million geometries."""
    rng = np.random.default_rng(20120101)
    ti, tr, phi = _geometries(rng, 200_000)
    tiny = np.finfo(np.float64).tiny
    worst = 0.0
    for name, n, k, sigma in [("glass", 1.5, 0.0, 0.2), ("metal", 0.96, 6.69, 0.3)]:
        t0 = time.perf_counter()
        rust = _rust_pbrdf(ti, tr, phi, n, k, sigma)
        t_rust = time.perf_counter() - t0
        mine = pbrdf_numpy(ti, tr, phi, n, k, sigma, 0.0)
        assert mine.shape == rust.shape and np.all(np.isfinite(mine))
        big = np.abs(rust) > 1e-300
        rel = np.abs(mine - rust)[big] / np.maximum(np.abs(rust[big]), tiny)
        # Below 1e-300 (the slope density's cut-off makes most of these exactly 0) compare
        # absolutely.
        small_abs = float(np.max(np.abs(mine - rust)[~big], initial=0.0))
        identical = int(np.sum(mine == rust))
        i = int(np.argmax(rel)) if rel.size else 0
        at = np.argwhere(big)[i] if rel.size else None
        print(f"{name} (n={n}, k={k}, sigma={sigma}): {ti.size} geometries, "
              f"{big.sum()} elements > 1e-300, {identical}/{rust.size} bit-identical; "
              f"max rel diff {rel.max(initial=0.0):.3e}"
              + (f" at ti={ti[at[0]]!r} tr={tr[at[0]]!r} phi={phi[at[0]]!r} element "
                 f"({at[1]},{at[2]})" if at is not None and rel.max(initial=0.0) > 0 else "")
              + f"; max abs diff among the rest {small_abs:.3e} "
              f"(Rust call incl. albedo quadratures: {t_rust:.1f} s)")
        worst = max(worst, float(rel.max(initial=0.0)))
        assert small_abs <= 1e-300, small_abs
    print(f"largest relative difference |numpy - rust| / |rust|: {worst:.3e}")
    assert worst < 1e-9, worst

    m = 1_000_000
    bti = rng.uniform(0.0, 89.9, m)
    btr = rng.uniform(0.0, 89.9, m)
    bphi = rng.uniform(-180.0, 180.0, m)
    for name, n, k, sigma in [("glass", 1.5, 0.0, 0.2), ("metal", 0.96, 6.69, 0.3)]:
        times = []
        for _ in range(3):  # the first call also pays for first-touch page faults
            t0 = time.perf_counter()
            pbrdf_numpy(bti, btr, bphi, n, k, sigma, 0.0)
            times.append(time.perf_counter() - t0)
        print(f"numpy, {m} geometries, {name}: first {times[0]:.3f} s, best of 3 "
              f"{min(times):.3f} s ({min(times) / m * 1e9:.0f} ns each)")


if __name__ == "__main__":
    print(f"numpy {np.__version__}, Python {sys.version.split()[0]}")
    _self_check()
