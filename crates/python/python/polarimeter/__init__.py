"""Rotating-analyzer polarimetry from Python.

The end-to-end model of polarimetric imaging (Meng (2012), *Polarimetric imaging: an
end-to-end model*), the planner, the estimator and the runs of the ``polarimeter``
instrument controller, on numpy arrays. Every number comes from the project's Rust crates
(the same code as the ``polarimeter`` command); this package only shapes arrays and results.

* :mod:`polarimeter.model`: ``fresnel``, ``pbrdf``, ``sun_position``, ``sky``, ``scene``,
  ``sensor``, ``dolp_stats``, ``roc``, ``polarimeter``.
* :mod:`polarimeter.estimator`: ``analyzer_rows``, ``camera_noise``, ``stokes``.
* :mod:`polarimeter.planner`: ``plan_angles``, ``plan_scene``, ``plan_continuous``,
  ``check_plan``.
* :mod:`polarimeter.runs`: ``run`` and ``resume`` (plans on simulated or real devices, with
  progress events and Ctrl-C), ``open_run`` (needs xarray and zarr: ``pip install
  polarimeter[runs]``).
* :mod:`polarimeter.station`: ``Station``, a client of a station (``polarimeter station
  serve``): submit plans, control the run, read the history and the event stream.

Conventions (docs/MODEL.md): Stokes ``[S0, S1, S2]``, ``S1 > 0`` along the frame's x axis,
``S2 > 0`` at +45 deg; angles in degrees where a name ends in ``_deg``, radians in ``_rad``.
"""

from ._native import __version__
from .estimator import (AOP_UNDEFINED, DOLP_UNDEFINED, SATURATED, Products, analyzer_rows,
                        camera_noise, stokes)
from .model import (Fresnel, Pbrdf, SunPosition, dolp_stats, fresnel, pbrdf, polarimeter, roc,
                    scene, sensor, sky, sun_position)
from .planner import (AnglesPlan, ContinuousPlan, PlanCheck, ScenePlan, check_plan,
                      plan_angles, plan_continuous, plan_scene)
from .runs import RunResult, open_run, resume, run
from .station import Station, StationError

__all__ = [
    "__version__", "SATURATED", "DOLP_UNDEFINED", "AOP_UNDEFINED", "Products", "analyzer_rows", "camera_noise", "stokes", "Fresnel", "Pbrdf",
    "SunPosition", "dolp_stats", "fresnel", "pbrdf", "polarimeter", "roc", "scene", "sensor",
    "sky", "sun_position", "AnglesPlan", "ContinuousPlan", "PlanCheck", "ScenePlan",
    "check_plan", "plan_angles", "plan_continuous", "plan_scene", "RunResult", "open_run",
    "resume", "run", "Station", "StationError",
]
