"""The estimator against polanalyser (Maeda's polarisation-image library) on the same
frames, and against itself on edge cases: saturated pixels, spans, bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

import polarimeter as pm
from conftest import EXAMPLES

import polanalyser

NOISE = dict(gain_dn_per_e=0.5, offset_dn=100.0, read_var_dn2=4.0, saturation_dn=60000)


def synthetic_frames(rows: np.ndarray, shape=(24, 32), seed=3) -> tuple[np.ndarray, np.ndarray]:
    """Frames of a scene of known Stokes (S0 2e3..2e4 DN, every DoLP and AoP) through
    ``rows``, with a 100 DN dark, noiseless but for rounding to whole DN."""
    rng = np.random.default_rng(seed)
    s0 = rng.uniform(2e3, 2e4, shape)
    dolp = rng.uniform(0.0, 1.0, shape)
    aop = rng.uniform(-np.pi / 2, np.pi / 2, shape)
    stokes = np.stack([s0, s0 * dolp * np.cos(2 * aop), s0 * dolp * np.sin(2 * aop)])
    frames = np.einsum("nk,kyx->nyx", rows, stokes) + NOISE["offset_dn"]
    return np.rint(frames).astype(np.uint16), stokes


@pytest.mark.parametrize("angles", [[0, 45, 90, 135], [0, 60, 120], [10, 50, 95, 140, 170]])
def test_stokes_matches_polanalyser_step_and_shoot(angles: list) -> None:
    rows = pm.analyzer_rows(angles)
    frames, _ = synthetic_frames(rows)
    got = pm.stokes(frames, rows, dark_dn=NOISE["offset_dn"], **NOISE)
    ref = polanalyser.calcLinearStokes(frames.astype(np.float64) - NOISE["offset_dn"],
                                       np.radians(angles))
    # Our products are float32 (a run stores them so): 2e-7 of S0 is a few float32 ulps.
    scale = np.abs(ref[..., 0])
    for i, name in enumerate(["s0", "s1", "s2"]):
        assert np.max(np.abs(getattr(got, name) - ref[..., i]) / scale) < 2e-7, name
    dolp = polanalyser.cvtStokesToDoLP(ref)
    assert np.max(np.abs(got.dolp - dolp)) < 1e-6
    # AoP: polanalyser's is in [0, pi), ours in (-pi/2, pi/2]; the same angle modulo pi, to
    # the kernel's arctangent (6e-7 rad) plus the float32 Stokes error (2e-7 S0) over the
    # polarised part (DoLP S0), which grows as the DoLP falls.
    aolp = polanalyser.cvtStokesToAoLP(ref)
    diff = np.abs(np.angle(np.exp(2j * (got.aop_rad - aolp))) / 2)
    assert np.all(diff <= 6e-7 + 4e-7 / np.maximum(dolp, 1e-12))


def test_stokes_matches_polanalyser_with_span_rows() -> None:
    """A spinning analyzer's frames: each row averages Malus's law over a 30-degree span.
    polanalyser takes measurement rows as they are; both invert the same rows."""
    start = np.arange(6) * 30.0
    rows = pm.analyzer_rows(start, start + 30.0, extinction_ratio=300.0)
    # The mean of cos 2psi over a span D is cos 2c sin D / D: D = 30 deg damps the polarised
    # terms by 0.955, beside the analyzer's (1 - 1/300) / (1 + 1/300).
    damp = np.sin(np.pi / 6) / (np.pi / 6)
    assert np.allclose(np.hypot(rows[:, 1], rows[:, 2]),
                       rows[:, 0] * (1 - 1 / 300) / (1 + 1 / 300) * damp, rtol=1e-12)
    frames, _ = synthetic_frames(rows)
    got = pm.stokes(frames, rows, dark_dn=NOISE["offset_dn"], **NOISE)
    ref = polanalyser.calcStokes(frames.astype(np.float64) - NOISE["offset_dn"], rows)
    scale = np.abs(ref[..., 0])
    for i, name in enumerate(["s0", "s1", "s2"]):
        assert np.max(np.abs(getattr(got, name) - ref[..., i]) / scale) < 2e-7, name


def test_saturated_pixels_are_nan_and_flagged() -> None:
    rows = pm.analyzer_rows([0, 45, 90, 135])
    frames, _ = synthetic_frames(rows, shape=(8, 8))
    frames[2, 3, 4] = 65535
    got = pm.stokes(frames, rows, dark_dn=100.0, **NOISE)
    assert got.saturated == 1
    assert np.isnan(got.s0[3, 4]) and got.flags[3, 4] & pm.SATURATED
    assert np.count_nonzero(got.flags & pm.SATURATED) == 1


def test_camera_file_gives_the_runs_noise_model() -> None:
    """The camera file's noise model, against EMVA 1288 written out here from the file's own
    values: K scaled by 10^(gain/20), read variance K^2 sigma_read^2 + 1/12 (quantisation),
    saturation three read-noise sigma below the full well (or the ADC's top), and the dark
    level offset + K dark current t. The same double arithmetic: to 1e-12 relative."""
    import tomllib
    path = EXAMPLES / "cameras" / "cmos_modern.toml"
    cam = tomllib.loads(path.read_text())
    noise = pm.camera_noise(path, gain_db=6.0, exposure_us=1000.0)
    k = cam["gain_dn_per_e"] * 10 ** (6.0 / 20)
    assert noise["gain_dn_per_e"] == pytest.approx(k, rel=1e-12)
    assert noise["read_var_dn2"] == pytest.approx(k * k * cam["read_noise_e"] ** 2 + 1 / 12,
                                                  rel=1e-12)
    top = min(k * cam["full_well_e"] + cam["offset_dn"], 2.0 ** cam["bit_depth"] - 1)
    assert noise["saturation_dn"] == int(top - 3 * k * cam["read_noise_e"])
    assert noise["dark_dn"] == pytest.approx(
        cam["offset_dn"] + k * cam["dark_current_e_per_s"] * 1e-3, rel=1e-12)
    rows = pm.analyzer_rows([0, 60, 120], camera=path)
    frames = np.full((3, 4, 4), 500, dtype=np.uint16)
    got = pm.stokes(frames, rows, camera=path, gain_db=6.0, exposure_us=1000.0)
    # A uniform 500 DN through three equally spaced analyzers is unpolarised light.
    assert np.allclose(got.dolp, 0.0, atol=1e-6) and np.all(got.sigma_s0 > 0)
    with pytest.raises(ValueError, match="give exposure_us"):
        pm.stokes(frames, rows, camera=path)


def test_bad_inputs_name_the_argument() -> None:
    rows = pm.analyzer_rows([0, 45, 90, 135])
    frames = np.zeros((4, 8, 8), dtype=np.uint16)
    with pytest.raises(ValueError, match="frames has dtype float64"):
        pm.stokes(frames.astype(float), rows, dark_dn=0.0, **NOISE)
    with pytest.raises(ValueError, match=r"rows has shape \(3, 3\)"):
        pm.stokes(frames, rows[:3], dark_dn=0.0, **NOISE)
    with pytest.raises(ValueError, match="dark_map has shape"):
        pm.stokes(frames, rows, dark_map=np.zeros((4, 4)), **NOISE)
    with pytest.raises(ValueError, match="give exactly one of dark_dn"):
        pm.stokes(frames, rows, **NOISE)
    with pytest.raises(ValueError, match="read_var_dn2"):
        pm.stokes(frames, rows, dark_dn=0.0, **{**NOISE, "read_var_dn2": -1.0})
    with pytest.raises(ValueError, match="extinction_ratio"):
        pm.analyzer_rows([0, 45], extinction_ratio=0.5)
    with pytest.raises(ValueError, match="give camera=PATH or gain_dn_per_e"):
        pm.stokes(frames, rows, dark_dn=0.0)
    with pytest.raises(ValueError, match=r"saturation_dn = 70000 is out of range"):
        pm.stokes(frames, rows, dark_dn=0.0, **{**NOISE, "saturation_dn": 70000})
    # A scalar end broadcasts against the starts (every frame ends at 180).
    assert pm.analyzer_rows([0, 45, 90], 180.0).shape == (3, 3)
