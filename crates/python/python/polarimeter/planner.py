"""The planner from Python: the same problems, defaults, checks and answers as
``polarimeter plan angles``, ``plan scene``, ``plan continuous`` and ``plan check``.

Keyword arguments are the command's flags with underscores (``target_mean=[1040, 30, -12]``
for ``--target-mean 1040,30,-12``; ``True`` for a switch); ``polarimeter plan scene --help``
lists them with their units. Each result keeps the command's whole JSON in ``data``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields
from typing import Any

from . import _commands

__all__ = ["AnglesPlan", "ScenePlan", "ContinuousPlan", "PlanCheck", "plan_angles", "plan_scene",
           "plan_continuous", "check_plan"]


def _build(cls: type, data: dict) -> Any:
    named = {f.name: data.get(f.name) for f in fields(cls) if f.name != "data"}
    return cls(**named, data=data)


@dataclass(frozen=True)
class AnglesPlan:
    """``plan angles``: the SCR-optimal analyzer angles for a target against a background."""

    angles_deg: list
    """The chosen angles, degrees."""
    scr: float
    """Signal-to-clutter ratio of the matched filter at those angles."""
    pd: float
    """Its probability of detection at ``pfa``."""
    pfa: float
    """The false-alarm probability."""
    scr_conventional: dict
    """SCR of the conventional sets, for comparison."""
    notes: list
    """What the planner says about the answer."""
    data: dict
    """The command's whole JSON."""


@dataclass(frozen=True)
class ScenePlan:
    """``plan scene``: angles, integration time and a forecast for a scene and a camera."""

    angles_deg: list
    """The chosen angles, degrees."""
    t_int_ms: float
    """Integration time, ms."""
    exposure: dict
    """The exposure (us), the rule that chose it and the saturation limit (us)."""
    objective: dict
    """The objective (``plan continuous``'s): its goal, the set's time, DoLP sigma, SCR per set
    and per second, and the time to the goal."""
    stage: dict
    """The stage's limits used (top speed, acceleration) and where they came from."""
    set: dict
    """The set: kind, rule, conditioning and what the Stokes image costs in SCR."""
    forecast: dict
    """SCR, Pd at Pfa, DoLP sigma, saturation margin (sigma), frames and duration (s)."""
    notes: list
    """What the planner says about the answer."""
    warnings: list
    """Warnings of the model's evaluation."""
    data: dict
    """The command's whole JSON."""


@dataclass(frozen=True)
class ContinuousPlan:
    """``plan continuous``: frames per half turn, exposure and speed of a spinning analyzer,
    and the step-and-shoot set beside it."""

    continuous: dict
    """The spinning choice: frames_per_half_turn, exposure_us, speed_deg_per_s,
    time_to_target_s, peak_fraction_of_saturation and ``binds`` (the limits that bind)."""
    step_and_shoot: dict
    """The step-and-shoot set on the same rig, its exposure chosen as ``plan_scene`` chooses."""
    exposure_comparison: str
    """Why the spinning exposure differs from the still one (or that they agree)."""
    stage: dict
    """The stage's limits used and where they came from."""
    time_to_target_ratio: float
    """Step-and-shoot's time to the goal over the spinning analyzer's."""
    data: dict
    """The command's whole JSON."""


@dataclass(frozen=True)
class PlanCheck:
    """``plan check``: a plan file's forecast, without running it."""

    plan: str
    """The plan's name."""
    kind: str
    """The plan's kind."""
    forecast: dict
    """Frames, sets, darks, duration (s), angles, per-class predicted sigma and notes."""
    data: dict
    """The command's whole JSON."""


def plan_angles(**flags: Any) -> AnglesPlan:
    """The SCR-optimal analyzer angles (``polarimeter plan angles``), e.g.
    ``plan_angles(channels=3, target_mean=[1040, 30, -12], background_mean=[1000, 0, 0],
    background_cov=[...9 values...], noise_var=80)``."""
    return _build(AnglesPlan, _commands.run("plan_angles", flags))


def plan_scene(**flags: Any) -> ScenePlan:
    """Angles, integration time and forecast (``polarimeter plan scene``), e.g.
    ``plan_scene(scene="examples/rooftop.toml", camera="examples/cameras/cmos_modern.toml",
    target="panel", background="asphalt", channels=3)``."""
    return _build(ScenePlan, _commands.run("plan_scene", flags))


def plan_continuous(**flags: Any) -> ContinuousPlan:
    """A spinning analyzer's settings (``polarimeter plan continuous``), e.g.
    ``plan_continuous(scene=..., camera=..., target="panel", background="asphalt")``."""
    return _build(ContinuousPlan, _commands.run("plan_continuous", flags))


def check_plan(plan: str | os.PathLike, *, rig: str | os.PathLike | None = None) -> PlanCheck:
    """A plan's forecast (``polarimeter plan check``): ``plan`` is a plan file's path, or the
    plan's TOML text (relative paths in it are then relative to the working directory, where
    the text is written for a moment as a hidden ``.polarimeter-plan-*.toml``)."""
    if isinstance(plan, str) and "\n" in plan:
        import tempfile
        fd, name = tempfile.mkstemp(suffix=".toml", prefix=".polarimeter-plan-", dir=os.getcwd())
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(plan)
            return _build(PlanCheck, _commands.run("plan_check", {"file": name, "rig": rig}))
        finally:
            os.unlink(name)
    return _build(PlanCheck, _commands.run("plan_check", {"file": plan, "rig": rig}))
