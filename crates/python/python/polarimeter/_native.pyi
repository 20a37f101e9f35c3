"""Type stubs of the Rust extension module (``polarimeter._native``). The public API is the
package's Python layer; these are its building blocks, on flat float64 arrays."""

from typing import Any, Callable

import numpy as np
import numpy.typing as npt

__version__: str

def fresnel(
    n: npt.NDArray[np.float64],
    k: npt.NDArray[np.float64],
    theta_i_deg: npt.NDArray[np.float64],
) -> tuple[
    npt.NDArray[np.complex128],
    npt.NDArray[np.complex128],
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
]: ...
def pbrdf_mueller(
    theta_i_deg: npt.NDArray[np.float64],
    theta_r_deg: npt.NDArray[np.float64],
    phi_deg: npt.NDArray[np.float64],
    *,
    n: float | None = None,
    k: float | None = None,
    material: str | None = None,
    sigma: float | None = None,
    dhr: float | None = None,
    vegetation: bool = False,
    tolerance: float = 1e-9,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64], list[str]]: ...
def sun_position(
    time: list[str],
    lat_deg: npt.NDArray[np.float64],
    lon_deg: npt.NDArray[np.float64],
    elevation_m: npt.NDArray[np.float64],
    *,
    pressure_hpa: float | None = None,
    temperature_c: float = 15.0,
    delta_t_s: float | None = None,
    refraction: bool = True,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def analyzer_rows(
    start_deg: npt.NDArray[np.float64],
    end_deg: npt.NDArray[np.float64],
    *,
    camera_toml: str | None = None,
    extinction_ratio: float | None = None,
    offset_deg: float | None = None,
) -> npt.NDArray[np.float64]: ...
def camera_noise(camera_toml: str, *, gain_db: float = 0.0, exposure_us: float = 0.0) -> dict[str, float]: ...
def stokes_products(
    frames: npt.NDArray[np.uint16],
    rows: npt.NDArray[np.float64],
    *,
    gain_dn_per_e: float,
    offset_dn: float,
    read_var_dn2: float,
    saturation_dn: int,
    dark_dn: float | None = None,
    dark_map: npt.NDArray[np.float32] | None = None,
    threads: int = 1,
) -> dict[str, Any]: ...
def command(name: str, argv: list[str]) -> str: ...
def run_plan(
    plan: str,
    out: str | None = None,
    *,
    simulate: bool = False,
    rig: str | None = None,
    on_event: Callable[[str], Any] | None = None,
) -> str: ...
def resume_run(run_dir: str, *, on_event: Callable[[str], Any] | None = None) -> str: ...
