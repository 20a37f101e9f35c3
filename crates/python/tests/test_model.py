"""Every model function against the command line's output for the same inputs: exact where
both evaluate a closed form with the same code (Fresnel, the pBRDF, the sun, the analyzer
set), and the same JSON for the document commands."""

from __future__ import annotations

import numpy as np
import pytest

import polarimeter as pm
from conftest import EXAMPLES, cli_json


@pytest.mark.parametrize("n,k", [(1.5, 0.0), (1.33, 0.0), (0.96, 6.69), (0.2, 3.4)])
def test_fresnel_is_the_clis_to_the_bit(n: float, k: float) -> None:
    angles = np.array([0.0, 12.5, 45.0, 56.3, 80.0, 89.9])
    got = pm.fresnel(n, angles, k=k)
    for i, t in enumerate(angles):
        ref = cli_json("model", "fresnel", f"--n={n!r}", f"--k={k!r}", f"--theta-i-deg={float(t)!r}")
        assert got.rs[i] == complex(*ref["rs"])
        assert got.rp[i] == complex(*ref["rp"])
        assert got.Rs[i] == ref["Rs"] and got.Rp[i] == ref["Rp"]


def test_fresnel_broadcasts_and_takes_float32() -> None:
    n = np.array([[1.3], [1.5], [1.7]], dtype=np.float32)
    t = np.linspace(0, 89, 5, dtype=np.float32)
    got = pm.fresnel(n, t)
    assert got.Rs.shape == (3, 5) and got.rp.dtype == np.complex128
    # float32 inputs are widened exactly, so they give the float64 answer of the same values.
    ref = pm.fresnel(n.astype(np.float64), t.astype(np.float64))
    assert np.array_equal(got.Rp, ref.Rp)
    # A scalar call gives a scalar.
    assert np.ndim(pm.fresnel(1.5, 30.0).Rs) == 0


@pytest.mark.parametrize("material", ["glass", "black_paint", "asphalt", "vegetation", "gold"])
def test_pbrdf_is_the_clis_to_the_bit(material: str) -> None:
    ti, tr, phi = np.array([20.0, 20.0, 55.0]), np.array([20.0, 60.0, 10.0]), \
        np.array([180.0, 90.0, -30.0])
    got = pm.pbrdf(ti, tr, phi, material=material)
    for i in range(3):
        ref = cli_json("model", "pbrdf", f"--material={material}", f"--theta-i-deg={float(ti[i])!r}",
                       f"--theta-r-deg={float(tr[i])!r}", f"--phi-deg={float(phi[i])!r}")
        assert np.array_equal(got.mueller[i], np.array(ref["f"]))
        assert got.dolp[i] == ref["dolp"]


def test_sun_is_the_clis_to_the_bit() -> None:
    times = np.array(["2026-06-21T15:00:00", "2026-12-21T08:30:15.5", "2027-03-20T23:59:59"],
                     dtype="datetime64[ns]")
    got = pm.sun_position(times, 39.742476, -105.1786, 1830.14)
    for i, t in enumerate(["2026-06-21T15:00:00Z", "2026-12-21T08:30:15.5Z",
                           "2027-03-20T23:59:59Z"]):
        ref = cli_json("model", "sun", f"--time={t}", "--lat-deg=39.742476",
                       "--lon-deg=-105.1786", "--elevation-m=1830.14")
        assert got.zenith_deg[i] == ref["zenith_deg"]
        assert got.azimuth_deg[i] == ref["azimuth_deg"]


def test_sky_dolp_stats_polarimeter_roc_scene_and_sensor_are_the_clis() -> None:
    sky = pm.sky([30.0, 60.0], 300.0, sun_zenith_deg=40.0, sun_azimuth_deg=120.0)
    ref = cli_json("model", "sky", "--zenith-deg=60.0", "--azimuth-deg=300.0",
                   "--sun-zenith-deg=40.0", "--sun-azimuth-deg=120.0")
    assert sky["s"].shape == (2, 3)
    assert np.array_equal(sky["s"][1], ref["s"]) and sky["dolp"][1] == ref["dolp"]

    stokes = np.array([[1000.0, 50.0, 20.0], [1000.0, 0.0, 300.0]])
    stats = pm.dolp_stats(stokes, [0, 45, 90, 135], 10.0)
    ref = cli_json("model", "dolp-stats", "--angles-deg=0,45,90,135",
                   "--stokes=1000.0,0.0,300.0", "--sigma-i=10.0")
    assert stats["std"].shape == (2,) and stats["std"][1] == ref["std"]
    assert np.array_equal(stats["stokes_cov"][1], ref["stokes_cov"])

    assert pm.polarimeter([0, 60, 120]) == cli_json("model", "polarimeter",
                                                    "--angles-deg=0,60,120")
    roc_flags = dict(detector="mf", target_mean=[1040, 30, -12], background_mean=[1000, 0, 0],
                     target_cov=[400, 30, -20, 30, 60, 12, -20, 12, 45],
                     background_cov=[400, 30, -20, 30, 60, 12, -20, 12, 45],
                     angles_deg=[0, 60, 120])
    assert pm.roc(**roc_flags) == cli_json(
        "model", "roc", "--detector=mf", "--target-mean=1040,30,-12", "--background-mean=1000,0,0",
        "--target-cov=400,30,-20,30,60,12,-20,12,45",
        "--background-cov=400,30,-20,30,60,12,-20,12,45", "--angles-deg=0,60,120")

    scene = EXAMPLES / "rooftop.toml"
    got = pm.scene(scene)
    ref = cli_json("model", "scene", f"--scene={scene}")
    # Elapsed times differ between two evaluations; everything else is the same.
    for d in (got, ref):
        d.pop("elapsed_ms", None)
    assert got == ref


def test_sensor_is_the_clis() -> None:
    camera = EXAMPLES / "cameras" / "cmos_modern.toml"
    flags = dict(camera=camera, angles_deg=[0, 45, 90, 135], radiance_mean=[10.0, 1.0, 0.5],
                 t_int_ms=5.0)
    got = pm.sensor(**flags)
    ref = cli_json("model", "sensor", f"--camera={camera}", "--angles-deg=0,45,90,135",
                   "--radiance-mean=10.0,1.0,0.5", "--t-int-ms=5.0")
    assert got == ref
