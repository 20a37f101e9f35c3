"""The GIL is released while the Rust side computes, and bad inputs are ValueErrors that
name the argument, the value and the allowed range."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import polarimeter as pm


def test_python_runs_while_a_long_evaluation_computes() -> None:
    """While one thread evaluates a million pBRDF geometries (about a second), the main
    thread keeps running Python. Were the GIL held, it could not take a single step until
    the evaluation ended."""
    ti = np.full(1_000_000, 35.0)
    tr = np.linspace(0.0, 89.0, ti.size)
    done = threading.Event()
    steps_during = 0

    def work() -> None:
        pm.pbrdf(ti, tr, 180.0, material="glass")
        done.set()

    t = threading.Thread(target=work)
    t.start()
    while not done.is_set():
        steps_during += 1
        done.wait(0.001)
    t.join()
    assert steps_during >= 10, f"only {steps_during} steps of Python ran during the call"


@pytest.mark.parametrize("call,message", [
    (lambda: pm.fresnel(-1.0, 30.0), r"n = -1 is out of range: allowed \(0, 100\]"),
    (lambda: pm.fresnel(1.5, [10.0, 95.0]),
     r"theta_i_deg = 95 is out of range: allowed \[0, 90\] \(at element 1"),
    (lambda: pm.fresnel(1.5, np.zeros(3), k=np.zeros(4)),
     r"do not broadcast.*n \(\), k \(4,\), theta_i_deg \(3,\)"),
    (lambda: pm.fresnel("glass", 30.0), "n must be numeric"),
    (lambda: pm.pbrdf(30.0, 30.0, 180.0, material="unobtainium"), "unobtainium"),
    (lambda: pm.pbrdf(30.0, 30.0, 180.0, n=1.5, sigma=0.2), "dhr"),
    (lambda: pm.pbrdf(30.0, 30.0, 180.0, material="glass", tolerance=1.0),
     r"tolerance = 1 is out of range"),
    (lambda: pm.sun_position("yesterday", 40.0, -105.0), r"time = \"yesterday\" is invalid"),
    (lambda: pm.sun_position(np.datetime64("2026-06-21T12:00"), 95.0, 0.0),
     r"lat_deg = 95 is out of range"),
    (lambda: pm.dolp_stats([1.0, 2.0], [0, 60, 120], 1.0), r"stokes has shape \(2,\)"),
    (lambda: pm.dolp_stats([100.0, 1.0, 1.0], [0, 60, 120], -1.0), "sigma_i"),
])
def test_bad_inputs_are_value_errors_naming_the_argument(call, message) -> None:
    with pytest.raises(ValueError, match=message):
        call()
