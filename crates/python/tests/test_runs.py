"""Runs: ``open_run`` on a step-and-shoot, a continuous and a killed-then-resumed run (xarray
opens each whole, and the products it shows are the estimator's on the frames it shows); a
run driven from Python with its events; Ctrl-C pausing it; xarray alone on the store."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import polarimeter as pm
from conftest import BIN, EXAMPLES, cli


# A stored product is rounded to a multiple of a power of two at most half its pixel's sigma:
# within a quarter sigma, and the stored sigma is within 3.1 % (docs/DATASET.md): 0.258, plus
# float32 rounding (about 1e-4 sigma).
WITHIN_SIGMA = 0.26


def recompute_and_compare(ds) -> float:
    """Recomputes every set's products from the dataset's own frames, spans, camera and dark
    with ``pm.stokes``; the largest difference from the stored products in units of their
    predicted sigma. Both are the engine's kernel on the same inputs, so the difference is the
    store's rounding to the precision the sigma warrants (at most a quarter of the pixel's
    sigma, and the stored sigma is itself within 3.1 %) plus the dark map's float32 rounding.
    Planes the run did not store (S1 and S2 derived on read, or without a stored sigma) are
    not compared."""
    camera = ds.attrs["products_camera"]["model"]
    worst = 0.0
    for s in ds["set"].values:
        if s < 0:
            continue
        light = ds.isel(frame=(ds["frame_set"].values == s) & (ds["kind"].values == 0))
        rows = pm.analyzer_rows(light["angle_start_deg"].values, light["angle_end_deg"].values,
                                camera=camera)
        source = ds.attrs["dark_source"][str(int(s))]
        if "level_dn" in source:
            dark = dict(dark_dn=source["level_dn"])
        else:
            darks = ds.isel(frame=(ds["kind"].values == 1)
                            & (ds["exposure_us"].values == source["exposure_us"]))
            mean = darks["pixels"].values[: source["dark_frames"]].astype(np.float64).mean(0)
            dark = dict(dark_map=mean.astype(np.float32))
        got = pm.stokes(light["pixels"].values, rows, camera=camera,
                        gain_db=float(light["gain"].values[0]), threads=0, **dark)
        stored = ds.sel(set=s)
        for name in ["s0", "s1", "s2", "dolp"]:
            if "derived" in stored[name].attrs or "sigma_" + name not in stored:
                continue
            a, b = getattr(got, name), stored[name].values
            assert np.array_equal(np.isnan(a), np.isnan(b)), name
            sigma = stored["sigma_" + name].values
            ok = ~np.isnan(a)
            if ok.any():
                worst = max(worst, float(np.max(np.abs(a - b)[ok] / sigma[ok])))
        assert np.array_equal(got.flags, stored["flags"].values)
    return worst


def test_step_and_shoot_run_opens_whole(step_run: Path) -> None:
    ds = pm.open_run(step_run)
    assert set(ds.dims) >= {"frame", "y", "x", "set", "channel"}
    assert ds["pixels"].dtype == np.uint16
    assert np.issubdtype(ds["host_time_unix_ns"].dtype, np.datetime64)
    assert "conventions" in ds.attrs and ds.attrs["summary"]
    # capture.toml: 4 darks and 3 sets of 4 angles, every frame counting.
    assert ds.sizes["frame"] == 16 and ds.sizes["set"] == 3
    assert list(ds["set"].values) == [0, 1, 2]
    # Products within a quarter of their own predicted sigma of a recomputation (the store's
    # rounding, docs/DATASET.md), plus 1e-3 sigma of float32.
    assert recompute_and_compare(ds) < WITHIN_SIGMA


def test_continuous_run_opens_whole(continuous_run: Path) -> None:
    ds = pm.open_run(continuous_run)
    span = ds["angle_end_deg"].values - ds["angle_start_deg"].values
    light = ds["kind"].values == 0
    assert (span[light] > 0).all(), "a continuous run's frames each sweep a span"
    every = pm.open_run(continuous_run, accepted_only=False)
    superseded = int((every["accepted"].values == 0).sum())
    assert every.sizes["frame"] == ds.sizes["frame"] + superseded
    assert recompute_and_compare(ds) < WITHIN_SIGMA


def test_killed_run_opens_before_and_after_resume(tmp_path: Path) -> None:
    out = tmp_path / "killed"
    plan = EXAMPLES / "plans" / "capture.toml"
    proc = subprocess.Popen([str(BIN), "acquire", "run", str(plan), "--simulate", "--out",
                             str(out)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    journal = out / "journal.jsonl"
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline:
            if journal.is_file() and journal.read_text().count('"frame"') >= 7:
                break
            time.sleep(0.02)
        else:
            pytest.fail("the run wrote no 7 frames in 60 s")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    before = pm.open_run(out, accepted_only=False)
    # The journal had 7 frames when the kill came: the store holds them all, but for the one
    # being written when the process died.
    assert before.sizes["frame"] >= 6
    hashes = set(before["hash"].values.tolist())
    if "set" in before.dims and before.sizes["set"]:
        assert recompute_and_compare(pm.open_run(out)) < WITHIN_SIGMA
    p = cli("acquire", "resume", str(out))
    assert p.returncode == 0, p.stderr
    after = pm.open_run(out, accepted_only=False)
    # Nothing acquired before the kill is lost.
    assert hashes <= set(after["hash"].values.tolist())
    ds = pm.open_run(out)
    assert list(ds["set"].values) == [0, 1, 2], "every set of the plan, once"
    assert recompute_and_compare(ds) < WITHIN_SIGMA


def test_not_a_run_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        pm.open_run(tmp_path)


def test_xarray_alone_opens_the_frames_with_their_coordinates(step_run: Path) -> None:
    """Without the package: the store names the CF coordinates, so xarray sets the span,
    exposure, time and set of each frame, and the set of each product slot, as coordinates."""
    frames = xr.open_zarr(step_run / "run.zarr", group="frames", consolidated=False)
    for name in ("angle_start_deg", "angle_end_deg", "exposure_us", "host_time_unix_ns",
                 "set", "kind", "accepted"):
        assert name in frames.coords, name
    products = xr.open_zarr(step_run / "run.zarr", group="products", consolidated=False)
    assert "set" in products.coords and "angles_deg" in products.coords


def test_a_simulated_run_driven_from_python(tmp_path: Path) -> None:
    events: list[dict] = []
    result = pm.run(EXAMPLES / "plans" / "capture.toml", tmp_path / "py-run", simulate=True,
                    on_event=events.append)
    assert result.state == "done", result.data
    progress = [e for e in events if e["kind"] == "progress"]
    # One progress event per frame that counts, in order, up to the plan's frames.
    assert [e["done"] for e in progress] == list(range(1, len(progress) + 1))
    assert progress[-1]["done"] == progress[-1]["planned"] == result.summary["frames_accepted"]
    assert events[-1] == {"kind": "state", "state": "done", "reason": None}
    assert recompute_and_compare(result.open()) < WITHIN_SIGMA
    with pytest.raises(ValueError, match="give either simulate=True or the hardware"):
        pm.run(EXAMPLES / "plans" / "capture.toml", tmp_path / "neither")


CHILD = """
import sys
import polarimeter as pm

def on_event(e):
    if e["kind"] == "progress" and e["done"] == 3:
        print("frame 3", flush=True)

try:
    pm.run(sys.argv[1], sys.argv[2], simulate=True, on_event=on_event)
    print("finished", flush=True)
except KeyboardInterrupt as e:
    print("KeyboardInterrupt:", e, flush=True)
"""


def test_ctrl_c_pauses_the_run_and_raises_keyboard_interrupt(tmp_path: Path) -> None:
    """SIGINT to a Python process running a plan: the run pauses at its next safe point, the
    call raises KeyboardInterrupt naming the run, the store opens, and resume finishes it
    with every frame taken before the interrupt kept."""
    out = tmp_path / "interrupted"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(EXAMPLES / "plans" /
                                                               "capture.toml"), str(out)],
                             stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        line = child.stdout.readline()
        assert line.strip() == "frame 3", line + child.stderr.read()
        child.send_signal(signal.SIGINT)
        rest, err = child.communicate(timeout=60)
    finally:
        child.kill()
    assert "KeyboardInterrupt: the run paused at a safe point" in rest, rest + err
    assert f"polarimeter.resume({str(out)!r})" in rest.replace('"', "'"), rest
    before = pm.open_run(out, accepted_only=False)
    assert 3 <= before.sizes["frame"] < 16, "paused after frame 3, before the plan's 16"
    hashes = set(before["hash"].values.tolist())
    result = pm.resume(out)
    assert result.state == "done", result.data
    after = pm.open_run(out, accepted_only=False)
    assert hashes <= set(after["hash"].values.tolist())
    assert recompute_and_compare(pm.open_run(out)) < WITHIN_SIGMA
