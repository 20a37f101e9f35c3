"""The model on arrays (Meng (2012), the dissertation the project follows): Fresnel, the
polarimetric BRDF, the sun, the skies, a scene's material Stokes vectors, the sensor model,
DoLP/AoP statistics and ROC.

Angles are degrees (``_deg``), as on the command line; Stokes vectors are ``[S0, S1, S2]``
with ``S1 > 0`` along the frame's x axis and ``S2 > 0`` at +45 deg (docs/MODEL.md). Inputs
broadcast against each other like numpy's; float32 is accepted and computed in float64.
Every function releases the GIL while the Rust side computes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import _commands, _native
from ._arrays import broadcast, shaped

__all__ = ["Fresnel", "Pbrdf", "SunPosition", "fresnel", "pbrdf", "sun_position", "sky", "scene",
           "sensor", "dolp_stats", "roc", "polarimeter"]


@dataclass(frozen=True)
class Fresnel:
    """Fresnel reflection at a surface of index ``n + ik``."""

    rs: Any
    """s amplitude (complex)."""
    rp: Any
    """p amplitude (complex)."""
    Rs: Any
    """s reflectance, ``|rs|^2``."""
    Rp: Any
    """p reflectance, ``|rp|^2``."""


def fresnel(n: Any, theta_i_deg: Any, k: Any = 0.0) -> Fresnel:
    """Fresnel amplitudes and reflectances (``polarimeter model fresnel``).

    n: real part of the refractive index, (0, 100]; k: extinction coefficient, [0, 100] (0 for
    a dielectric); theta_i_deg: angle of incidence from the normal, degrees, [0, 90].
    """
    shape, a = broadcast(n=n, k=k, theta_i_deg=theta_i_deg)
    rs, rp, big_rs, big_rp = _native.fresnel(a["n"], a["k"], a["theta_i_deg"])
    return Fresnel(shaped(rs, shape), shaped(rp, shape), shaped(big_rs, shape),
                   shaped(big_rp, shape))


@dataclass(frozen=True)
class Pbrdf:
    """The polarimetric BRDF at each geometry."""

    mueller: np.ndarray
    """Mueller matrices, sr^-1, shape ``(..., 3, 3)`` (linear Stokes)."""
    dolp: Any
    """DoLP of the light reflected from unpolarised light."""
    aop_deg: Any
    """Its AoP, degrees (NaN where the DoLP is 0)."""
    warnings: list[str]
    """The diffuse terms' warnings (a clamped albedo, a quadrature short of its tolerance)."""


def pbrdf(theta_i_deg: Any, theta_r_deg: Any, phi_deg: Any, *, material: str | None = None,
          n: float | None = None, k: float | None = None, sigma: float | None = None,
          dhr: float | None = None, vegetation: bool = False,
          tolerance: float = 1e-9) -> Pbrdf:
    """The pBRDF Mueller matrix (Meng (2012) Eqs. 3.4-3.19; ``polarimeter model pbrdf``).

    theta_i_deg, theta_r_deg: incidence (sun) and view zenith, degrees, [0, 90]; phi_deg:
    relative azimuth between the source and view directions, degrees, [-360, 360] (180 is
    specular). The surface: a built-in ``material`` (``polarimeter model materials``) or
    ``n``, ``k``, ``sigma`` (facet-slope roughness, [1e-6, 10]) and ``dhr``
    (directional-hemispherical reflectance, [0, 1]); given values override the material's.
    ``vegetation`` selects Meng (2012) Eq. 3.19. ``tolerance``: absolute error target of the
    specular-albedo quadrature, [1e-14, 1e-2], integrated once per distinct incidence angle.
    """
    shape, a = broadcast(theta_i_deg=theta_i_deg, theta_r_deg=theta_r_deg, phi_deg=phi_deg)
    m, dolp, aop, warnings = _native.pbrdf_mueller(
        a["theta_i_deg"], a["theta_r_deg"], a["phi_deg"], n=n, k=k, material=material,
        sigma=sigma, dhr=dhr, vegetation=vegetation, tolerance=tolerance)
    return Pbrdf(m.reshape(shape + (3, 3)), shaped(dolp, shape), shaped(aop, shape),
                 list(warnings))


@dataclass(frozen=True)
class SunPosition:
    """The sun's topocentric position (NREL SPA)."""

    zenith_deg: Any
    """Zenith angle, degrees (refraction-corrected unless ``refraction=False``)."""
    azimuth_deg: Any
    """Azimuth, degrees clockwise from north, [0, 360)."""

    @property
    def elevation_deg(self) -> Any:
        """Elevation above the horizon, degrees (90 - zenith)."""
        return 90.0 - self.zenith_deg


def _rfc3339(time: Any) -> tuple[tuple[int, ...], list[str]]:
    """Instants (numpy datetime64, datetime, or RFC 3339 text) as RFC 3339 UTC text."""
    arr = np.asarray(time)
    if arr.dtype.kind == "M":
        # Whole seconds at least (RFC 3339), finer units as they are: a cast to nanoseconds
        # would wrap dates outside 1678-2262.
        unit = np.datetime_data(arr.dtype)[0]
        if unit in ("Y", "M", "W", "D", "h", "m", "generic"):
            arr = arr.astype("datetime64[s]")
        text = np.datetime_as_string(arr, timezone="UTC")
        return arr.shape, [str(t) for t in np.ravel(text)]
    if arr.dtype.kind == "O":
        import datetime as dt
        flat = []
        for t in np.ravel(arr):
            if isinstance(t, dt.datetime):
                if t.tzinfo is None:
                    raise ValueError(f"time = {t!r} has no time zone: allowed an aware "
                                     "datetime, a numpy datetime64 (UTC) or RFC 3339 text")
                t = t.isoformat()
            flat.append(str(t))
        return arr.shape, flat
    return arr.shape, [str(t) for t in np.ravel(arr)]


def sun_position(time: Any, lat_deg: Any, lon_deg: Any, elevation_m: Any = 0.0, *,
                 pressure_hpa: float | None = None, temperature_c: float = 15.0,
                 delta_t_s: float | None = None, refraction: bool = True) -> SunPosition:
    """The sun's position for UTC instants and sites (``polarimeter model sun``).

    time: numpy datetime64 (UTC), aware datetimes or RFC 3339 text; lat_deg [-90, 90] north,
    lon_deg [-180, 180] east, elevation_m [-500, 9000]. Refraction uses ``pressure_hpa``
    (default: the standard atmosphere at the elevation) and ``temperature_c``; ``delta_t_s``
    is TT - UT (default: the Espenak-Meeus estimate).
    """
    tshape, times = _rfc3339(time)
    shape, a = broadcast(time=np.zeros(tshape), lat_deg=lat_deg, lon_deg=lon_deg,
                         elevation_m=elevation_m)
    times = list(np.broadcast_to(np.asarray(times, dtype=object).reshape(tshape), shape).ravel())
    zen, az = _native.sun_position(times, a["lat_deg"], a["lon_deg"], a["elevation_m"],
                                   pressure_hpa=pressure_hpa, temperature_c=temperature_c,
                                   delta_t_s=delta_t_s, refraction=refraction)
    return SunPosition(shaped(zen, shape), shaped(az, shape))


def sky(zenith_deg: Any, azimuth_deg: Any, *, sun_zenith_deg: Any, sun_azimuth_deg: Any,
        model: str = "rayleigh", **flags: Any) -> dict:
    """Sky Stokes radiance, DoLP and AoP of sky directions (``polarimeter model sky``):
    ``s`` (shape ``(..., 3)``, sr^-1 per unit top-of-atmosphere solar irradiance, S1 > 0 a
    horizontal E-vector), ``dolp``, ``aop_deg``. Azimuths clockwise from north, degrees.
    model: ``rayleigh``, ``berry`` or ``table`` (with ``table=PATH``); other flags as the
    command takes them (``wavelength_nm``, ``separation_deg``, ``reference``)."""
    return _commands.mapped("model_sky", {"model": model, **flags},
                            {"zenith_deg": zenith_deg, "azimuth_deg": azimuth_deg,
                             "sun_zenith_deg": sun_zenith_deg,
                             "sun_azimuth_deg": sun_azimuth_deg})


def scene(path: str | os.PathLike, **flags: Any) -> dict:
    """Each material's mean Stokes radiance and covariance over the field of view of a TOML
    scene (``polarimeter model scene``; W m^-2 sr^-1, camera frame), with the error estimate
    and the terms evaluated and skipped."""
    return _commands.run("model_scene", {"scene": path, **flags})


def sensor(**flags: Any) -> dict:
    """The frames' mean and covariance (DN) for a scene radiance through a camera behind
    analyzers (``polarimeter model sensor``; EMVA 1288 linear camera). Flags as the command
    takes them, e.g. ``camera="examples/cameras/cmos_modern.toml"``, ``angles_deg=[0, 60,
    120]``, ``stokes=[...]`` (W m^-2 sr^-1), ``t_int_ms``."""
    return _commands.run("model_sensor", flags)


def dolp_stats(stokes: Any, angles_deg: Any, sigma_i: Any, *, regime: str = "auto",
               monte_carlo: int = 0, seed: int = 1) -> dict:
    """DoLP and AoP mean, spread and AoP bias of the Stokes estimate from analyzer angles
    with intensity noise ``sigma_i`` (``polarimeter model dolp-stats``): ``stokes`` has shape
    ``(..., 3)``, one true Stokes vector per evaluation, broadcast against ``sigma_i``."""
    return _commands.mapped(
        "model_dolp_stats",
        {"angles_deg": list(np.ravel(angles_deg)), "regime": regime,
         "monte_carlo": monte_carlo, "seed": seed},
        {"stokes": stokes, "sigma_i": sigma_i}, inner={"stokes": 3})


def roc(**flags: Any) -> dict:
    """Analytic ROC of a detector (matched filter, RX) for a target against a background
    (``polarimeter model roc``): Pd at a Pfa, SCR and the curve. Flags as the command takes
    them (``target_mean``, ``background_mean``, ``background_cov``, ``angles_deg``, ...)."""
    return _commands.run("model_roc", flags)


def polarimeter(angles_deg: Any, **flags: Any) -> dict:
    """Condition number, EWV, singular values and pseudo-inverse of an analyzer set
    (``polarimeter model polarimeter``)."""
    return _commands.run("model_polarimeter", {"angles_deg": list(np.ravel(angles_deg)),
                                                **flags})
