"""Runs from Python: ``run`` and ``resume`` (``polarimeter acquire run`` and ``acquire resume``,
the same code, with progress events and Ctrl-C), and ``open_run``, which reads a run
directory's Zarr store (the frames, their analyzer spans and times, the products of every set
and the store's conventions) with zarr-python and xarray, before or after a resume, whatever
interrupted it."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from . import _native


@dataclass(frozen=True)
class RunResult:
    """How a run (or a resume) ended."""

    state: str
    """``done``, ``paused`` (a device fault its retries did not clear: ``resume`` it) or
    ``aborted``."""
    run_dir: str
    """The run directory."""
    summary: dict | None
    """A finished run's summary: frames, sets, rejections, retries, timings, saturation."""
    data: dict
    """The command's whole JSON (``reason``, ``warnings``, ``forecast_warnings``, ...)."""

    def open(self, **kwargs: Any) -> Any:
        """The run as an xarray Dataset (``open_run``)."""
        return open_run(self.run_dir, **kwargs)


def _result(text: str) -> RunResult:
    data = json.loads(text)
    return RunResult(state=data.get("state", ""), run_dir=data.get("run_dir", ""),
                     summary=data.get("summary"), data=data)


def _events(on_event: Callable[[dict], Any] | None) -> Callable[[str], Any] | None:
    if on_event is None:
        return None
    return lambda text: on_event(json.loads(text))


def run(plan: str | os.PathLike, out: str | os.PathLike | None = None, *,
        simulate: bool = False, rig: str | os.PathLike | None = None,
        on_event: Callable[[dict], Any] | None = None) -> RunResult:
    """Runs a plan file into ``out`` (a new or empty directory; default
    ``./run-NAME-UNIXTIME``) on the simulated devices (``simulate=True``) or on the hardware
    a rig file names (``rig=PATH``), as ``polarimeter acquire run``.

    ``on_event`` is called with each event as a dict: ``{"kind": "progress", "done",
    "planned", "label"}``, ``{"kind": "set", "set", "accepted", "reason", "mean_s0_dn",
    "mean_dolp"}``, ``{"kind": "state", "state", "reason"}``, ``{"kind": "retry",
    "message"}``, ``{"kind": "decision", ...}``. Ctrl-C (on the main thread) or an exception
    ``on_event`` raises pauses the run at its next safe point (a second Ctrl-C: at once; a
    third leaves it); then ``KeyboardInterrupt`` (or that exception) is raised with the run
    directory as its ``run_dir`` attribute, and ``resume(run_dir)`` continues the run. The GIL
    is released while it runs; one run at a time per process.
    """
    return _result(_native.run_plan(os.fspath(plan), None if out is None else os.fspath(out),
                                    simulate=simulate,
                                    rig=None if rig is None else os.fspath(rig),
                                    on_event=_events(on_event)))


def resume(run_dir: str | os.PathLike, *,
           on_event: Callable[[dict], Any] | None = None) -> RunResult:
    """Continues a paused or interrupted run on the devices it was started on, as
    ``polarimeter acquire resume`` (a finished run: nothing to do, state ``done``)."""
    return _result(_native.resume_run(os.fspath(run_dir), on_event=_events(on_event)))

__all__ = ["RunResult", "run", "resume", "open_run", "FRAME_COORDS"]

#: Per-frame arrays that describe a frame rather than measure it (every one but its hash),
#: coordinates on ``frame``: the store's ``frames/pixels`` CF ``coordinates``, with the
#: frame's ``set`` named ``frame_set`` (``set`` is the products' dimension). Runs written
#: before the store named them get the same coordinates here.
FRAME_COORDS = ("angle_start_deg", "angle_end_deg", "angle_sigma_deg", "angle_source",
                "measured_angle_deg", "commanded_angle_deg", "exposure_us", "gain",
                "host_time_unix_ns", "device_timestamp_ns", "frame_set", "step", "kind",
                "accepted", "status", "frame_id", "sun_zenith_deg", "sun_azimuth_deg")


def _store(path: str | os.PathLike) -> Path:
    p = Path(path)
    store = p / "run.zarr" if (p / "run.zarr").is_dir() else p
    if not (store / "zarr.json").is_file():
        raise FileNotFoundError(f"{path}: not a run directory (no run.zarr/zarr.json in it)")
    return store


def _derive_stokes(products: Any) -> Any:
    """Adds S1 and S2 derived from S0, DoLP and AoP where the store did not keep them."""
    import numpy as np

    have = set(products.data_vars)
    if not {"s0", "dolp", "aop_rad"} <= have:
        return products
    for name, trig in (("s1", np.cos), ("s2", np.sin)):
        if name in have:
            continue
        v = products["s0"] * products["dolp"] * trig(2 * products["aop_rad"])
        v.attrs = {
            "units": "DN",
            "long_name": f"Stokes {name.upper()}",
            "derived": f"s0 * dolp * {trig.__name__}(2 aop_rad): not stored by the run",
        }
        products[name] = v.astype(np.float32)
    return products


def open_run(path: str | os.PathLike, *, accepted_only: bool = True) -> Any:
    """A run as one ``xarray.Dataset``.

    Dimensions: ``frame`` (the stored frames; with ``accepted_only`` only those whose set's
    products use them and the dark frames, as ``frames/accepted == 1``), ``y``, ``x``,
    ``set`` (one per finished set: the products) and ``channel`` (its angles).

    Variables: ``pixels`` (frame, y, x; uint16 DN, read lazily), the products the run stored
    and ``flags`` (set, y, x) (a run's ``[storage] products = "essential"``, the default,
    stores ``s0``, ``dolp``, ``aop_rad``, ``sigma_s0`` and ``sigma_dolp``; ``s1`` and ``s2``
    are then derived here from them, marked by a ``derived`` attribute, and the other sigmas
    come from :func:`stokes` on the frames), and ``dark_mean`` (y, x, the mean of every dark frame) when the run
    took dark frames; ``angles_deg`` (set, channel) is a coordinate. Coordinates on ``frame``: the analyzer span (``angle_start_deg``,
    ``angle_end_deg``), ``exposure_us``, the host time ``host_time_unix_ns``
    (datetime64), ``frame_set`` (the set the frame belongs to), ``kind`` and the rest of
    ``FRAME_COORDS``. Attributes: the store's root attributes (``conventions``,
    ``products_camera``, ``plan``, ``summary``, ...) and the products' (``dark_source``,
    ``saturated_fraction``).
    """
    import xarray as xr
    import zarr

    store = _store(path)
    root = zarr.open_group(str(store), mode="r")
    frames = xr.open_zarr(str(store), group="frames", consolidated=False)
    frames = frames.rename({"set": "frame_set"})
    frames = frames.set_coords([c for c in FRAME_COORDS if c in frames.variables])
    if accepted_only and "accepted" in frames.variables:
        keep = frames["accepted"].values == 1
        frames = frames.isel(frame=keep)
    parts = [frames]
    groups = set(root.group_keys())
    attrs = dict(root.attrs)
    if "products" in groups:
        products = xr.open_zarr(str(store), group="products", consolidated=False)
        attrs.update({k: v for k, v in products.attrs.items() if k != "names"})
        # Slots not written yet (a killed run's, set -1) hold no set's products.
        products = products.isel(slot=products["set"].values >= 0)
        products = products.set_coords("set").swap_dims({"slot": "set"})
        parts.append(_derive_stokes(products))
    if "darks" in groups and "mean" in root["darks"].array_keys():
        darks = xr.open_zarr(str(store), group="darks", consolidated=False)
        parts.append(darks.rename({"mean": "dark_mean"}))
    ds = xr.merge(parts, combine_attrs="drop", compat="override", join="outer")
    ds.attrs = attrs
    ds.attrs["run_dir"] = str(store.parent if store.name == "run.zarr" else store)
    return ds
