"""The estimator of the runs on numpy arrays: Stokes, DoLP, AoP, their predicted sigma and
the quality flags of one angle set, computed by the same kernel as ``acquire run``'s products
(``polar_engine::products``), reading the frames where numpy holds them."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import _native

__all__ = ["SATURATED", "DOLP_UNDEFINED", "AOP_UNDEFINED", "Products", "analyzer_rows",
           "camera_noise", "stokes"]

#: Flag value 1 (bit 0): a frame saturated at the pixel (every product is NaN there).
SATURATED = 1
#: Flag value 2 (bit 1): DoLP undefined (S0 <= 0 after the dark).
DOLP_UNDEFINED = 2
#: Flag value 4 (bit 2): the AoP carries no information (undefined, or its sigma above
#: pi/sqrt(12)).
AOP_UNDEFINED = 4


def analyzer_rows(start_deg: Any, end_deg: Any = None, *,
                  camera: Any = None, extinction_ratio: float | None = None,
                  offset_deg: float | None = None) -> np.ndarray:
    """Measurement rows ``(count, 3)`` of frames whose analyzer turned from ``start_deg`` to
    ``end_deg`` during the exposure (``end_deg`` omitted: step-and-shoot frames), degrees:
    ``0.5 [1, cos 2psi, sin 2psi]`` averaged over the span (the ``sin D / D`` factor). The
    analyzer is a ``camera`` file's (its polarizer's transmittance, extinction ratio and
    offset, and its fore-optics, as a run's products take them), or an analyzer of
    ``extinction_ratio`` (default: ideal) whose axis is ``offset_deg`` (default 0) from the
    stage's angle. A run's ``angle_start_deg`` and ``angle_end_deg`` go here as they are."""
    if end_deg is None:
        end_deg = start_deg
    try:
        start, end = np.broadcast_arrays(np.asarray(start_deg, dtype=np.float64),
                                         np.asarray(end_deg, dtype=np.float64))
    except ValueError:
        raise ValueError(f"start_deg {np.shape(start_deg)} and end_deg {np.shape(end_deg)} do "
                         "not broadcast to one shape") from None
    start = np.ascontiguousarray(start).reshape(-1)
    end = np.ascontiguousarray(end).reshape(-1)
    text = None if camera is None else _camera_text(camera)
    return _native.analyzer_rows(
        start, end, camera_toml=text,
        extinction_ratio=None if extinction_ratio is None else float(extinction_ratio),
        offset_deg=None if offset_deg is None else float(offset_deg))


def _camera_text(camera: Any) -> str:
    """A camera file's text, or a camera model given as a mapping (a run's
    ``products_camera["model"]``) as JSON."""
    if isinstance(camera, dict):
        import json
        return json.dumps(camera)
    return Path(camera).read_text()


def camera_noise(camera: Any, *, gain_db: float = 0.0,
                 exposure_us: float = 0.0) -> dict:
    """A camera file's noise model as the runs use it: ``gain_dn_per_e``, ``offset_dn``,
    ``read_var_dn2`` (DN^2), ``saturation_dn`` and ``dark_dn`` (the dark level at
    ``exposure_us``)."""
    return _native.camera_noise(_camera_text(camera), gain_db=float(gain_db),
                                exposure_us=float(exposure_us))


@dataclass(frozen=True)
class Products:
    """The products of one angle set, images of the frames' shape."""

    s0: np.ndarray
    """S0, DN above the dark (float32)."""
    s1: np.ndarray
    """S1, DN (> 0 along the frame's x axis)."""
    s2: np.ndarray
    """S2, DN (> 0 at +45 deg)."""
    dolp: np.ndarray
    """Degree of linear polarisation."""
    aop_rad: np.ndarray
    """Angle of polarisation, radians in (-pi/2, pi/2], from x towards y."""
    sigma_s0: np.ndarray
    """Predicted standard deviation of S0, DN."""
    sigma_s1: np.ndarray
    """Predicted standard deviation of S1, DN."""
    sigma_s2: np.ndarray
    """Predicted standard deviation of S2, DN."""
    sigma_dolp: np.ndarray
    """Predicted (first-order) standard deviation of DoLP."""
    sigma_aop_rad: np.ndarray
    """Predicted (first-order) standard deviation of AoP, radians."""
    flags: np.ndarray
    """uint8 bit mask: SATURATED, DOLP_UNDEFINED, AOP_UNDEFINED."""
    saturated: int
    """Number of saturated pixels."""


def stokes(frames: np.ndarray, rows: Any, *, camera: Any = None,
           gain_db: float = 0.0, exposure_us: float | None = None, dark_dn: float | None = None,
           dark_map: np.ndarray | None = None, gain_dn_per_e: float | None = None,
           offset_dn: float | None = None, read_var_dn2: float | None = None,
           saturation_dn: int | None = None, threads: int = 1) -> Products:
    """Stokes, DoLP, AoP, their predicted sigma and flags of one angle set.

    frames: ``(count, height, width)`` uint16 (C-contiguous arrays are read in place); rows:
    ``(count, 3)`` measurement rows (``analyzer_rows``). The noise model comes from a
    ``camera`` file or model (at ``gain_db``; the dark is its level after ``exposure_us``,
    offset plus dark current, unless ``dark_dn`` or ``dark_map`` is given) or from
    ``gain_dn_per_e``, ``offset_dn``, ``read_var_dn2`` (DN^2) and ``saturation_dn`` (DN, up
    to 65535) with a dark. ``threads`` caps the threads (0: all cores).
    """
    frames = np.asarray(frames)
    if frames.dtype != np.uint16:
        raise ValueError(f"frames has dtype {frames.dtype}: allowed uint16 (the cameras' DN)")
    if frames.ndim != 3:
        raise ValueError(f"frames has shape {frames.shape}: allowed (count, height, width)")
    noise = {"gain_dn_per_e": gain_dn_per_e, "offset_dn": offset_dn,
             "read_var_dn2": read_var_dn2, "saturation_dn": saturation_dn}
    if camera is not None:
        if dark_dn is None and dark_map is None and exposure_us is None:
            raise ValueError("give exposure_us (the camera's dark level depends on it), or "
                             "dark_dn or dark_map")
        model = camera_noise(camera, gain_db=gain_db, exposure_us=exposure_us or 0.0)
        noise = {k: (model[k] if v is None else v) for k, v in noise.items()}
        if dark_dn is None and dark_map is None:
            dark_dn = model["dark_dn"]
    missing = [k for k, v in noise.items() if v is None]
    if missing:
        raise ValueError(f"give camera=PATH or {', '.join(missing)}")
    if not 0 <= int(noise["saturation_dn"]) <= 65535:
        raise ValueError(f"saturation_dn = {noise['saturation_dn']} is out of range: allowed "
                         "[0, 65535] DN")
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    if rows.ndim != 2:
        raise ValueError(f"rows has shape {rows.shape}: allowed ({frames.shape[0]}, 3)")
    if dark_map is not None:
        dark_map = np.ascontiguousarray(dark_map, dtype=np.float32)
    if threads < 0:
        raise ValueError(f"threads = {threads}: allowed 0 (all cores) or more")
    out = _native.stokes_products(
        np.ascontiguousarray(frames), rows, dark_dn=None if dark_dn is None else float(dark_dn),
        dark_map=dark_map, gain_dn_per_e=float(noise["gain_dn_per_e"]),
        offset_dn=float(noise["offset_dn"]), read_var_dn2=float(noise["read_var_dn2"]),
        saturation_dn=int(noise["saturation_dn"]), threads=int(threads))
    return Products(**out)
