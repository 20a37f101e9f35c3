"""The planner from Python gives the command line's answer for the same problem."""

from __future__ import annotations

import pytest

import polarimeter as pm
from conftest import EXAMPLES, cli_json

ANGLES = dict(channels=3, target_mean=[1040, 30, -12], background_mean=[1000, 0, 0],
              background_cov=[400, 30, -20, 30, 60, 12, -20, 12, 45], noise_var=80)
ANGLES_CLI = ["--channels=3", "--target-mean=1040,30,-12", "--background-mean=1000,0,0",
              "--background-cov=400,30,-20,30,60,12,-20,12,45", "--noise-var=80"]


def _without_timing(d: dict) -> dict:
    return {k: v for k, v in d.items() if k not in ("elapsed_ms", "evaluations")}


def test_plan_angles_is_the_clis() -> None:
    got = pm.plan_angles(**ANGLES)
    ref = cli_json("plan", "angles", *ANGLES_CLI)
    assert _without_timing(got.data) == _without_timing(ref)
    assert got.angles_deg == ref["angles_deg"] and got.scr == ref["scr"]
    # Three channels that form a Stokes image: three distinct angles modulo 180.
    assert len({round(a % 180, 6) for a in got.angles_deg}) == 3


def test_plan_scene_is_the_clis() -> None:
    flags = dict(scene=EXAMPLES / "rooftop.toml", camera=EXAMPLES / "cameras" /
                 "cmos_modern.toml", target="panel", background="asphalt", channels=3,
                 min_separation_deg=30)
    got = pm.plan_scene(**flags)
    ref = cli_json("plan", "scene", f"--scene={flags['scene']}", f"--camera={flags['camera']}",
                   "--target=panel", "--background=asphalt", "--channels=3",
                   "--min-separation-deg=30")
    assert got.data == ref
    assert got.t_int_ms > 0 and got.forecast["frames"] >= 3


def test_plan_continuous_is_the_clis() -> None:
    scene, camera = EXAMPLES / "rooftop.toml", EXAMPLES / "cameras" / "cmos_modern.toml"
    got = pm.plan_continuous(scene=scene, camera=camera, target="panel", background="asphalt")
    ref = cli_json("plan", "continuous", f"--scene={scene}", f"--camera={camera}",
                   "--target=panel", "--background=asphalt", "--json")
    assert got.data == ref
    assert got.continuous["binds"] and got.time_to_target_ratio > 0


def test_check_plan_from_a_path_and_from_text(tmp_path, monkeypatch) -> None:
    plan = EXAMPLES / "plans" / "capture.toml"
    got = pm.check_plan(plan)
    ref = cli_json("plan", "check", str(plan))
    assert got.data == ref and got.kind == "capture"
    # The same plan as text, its relative paths taken from the working directory.
    monkeypatch.chdir(plan.parent)
    assert pm.check_plan(plan.read_text()).data == ref
    assert not list(plan.parent.glob(".polarimeter-plan-*")), "a temporary file was left"


def test_planner_errors_name_the_python_argument() -> None:
    """Errors name the Python keyword (``noise_var``), never the CLI's flag (``--noise-var``)."""
    with pytest.raises(ValueError, match="channels") as e:
        pm.plan_angles(**{**ANGLES, "channels": 0})
    assert "--" not in str(e.value)
    with pytest.raises(ValueError, match="noise_var") as e:
        pm.plan_angles(**{**ANGLES, "noise_var": "lots"})
    assert "--" not in str(e.value)
    with pytest.raises(ValueError, match="unexpected argument 'no_such_flag'") as e:
        pm.plan_angles(**ANGLES, no_such_flag=1)
    assert "--" not in str(e.value)
    with pytest.raises(ValueError, match="no-such-material"):
        pm.plan_scene(scene=EXAMPLES / "rooftop.toml",
                      camera=EXAMPLES / "cameras" / "cmos_modern.toml",
                      target="no-such-material", background="asphalt")
