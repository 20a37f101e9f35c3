"""A tour of the `polarimeter` Python package, cell by cell (run it whole, or paste the cells
into a notebook). Install: `pip install ./crates/python` from a clone (docs/PYTHON.md).

Cells: the model on arrays; the estimator on frames; the planner; a run on simulated devices
with its progress, opened as an xarray Dataset, and its products recomputed from its own
frames. Writes into the working directory: tour-run/ and tour-dolp.png.
"""

# %% The model on arrays: Fresnel, the pBRDF, the sun
import shutil
from pathlib import Path

import numpy as np

import polarimeter as pm

EXAMPLES = Path(__file__).resolve().parents[1]

theta = np.linspace(0.0, 89.0, 90)
glass = pm.fresnel(1.52, theta)
brewster = theta[np.argmin(glass.Rp)]
print(f"glass: Rp is smallest at {brewster:.0f} deg (Brewster: atan 1.52 = 56.7 deg)")

# One sun, a fan of view directions: one (n, 3, 3) stack of Mueller matrices, sr^-1.
view = np.linspace(0.0, 80.0, 9)
copper = pm.pbrdf(45.0, view, 180.0, material="copper", sigma=0.2)
print("copper, sun at 45 deg, DoLP along the principal plane:", np.round(copper.dolp, 3))

times = np.arange("2026-06-21T10:00", "2026-06-21T20:00", np.timedelta64(2, "h"),
                  dtype="datetime64[ns]")
sun = pm.sun_position(times, 43.08, -77.67, 160.0)
print("sun elevation over the day, deg:", np.round(sun.elevation_deg, 1))

# %% DoLP statistics of the estimate over a grid of true DoLP (one call per element)
dolp = np.array([0.0, 0.02, 0.1, 0.5])
stokes = np.stack([np.full_like(dolp, 1000.0), 1000.0 * dolp, np.zeros_like(dolp)], axis=-1)
stats = pm.dolp_stats(stokes, [0, 60, 120], 10.0)
print("DoLP mean at true DoLP", dolp, "->", np.round(stats["mean"], 4))

# %% The estimator: frames of a known scene through 0/45/90/135, back to Stokes
rows = pm.analyzer_rows([0, 45, 90, 135], camera=EXAMPLES / "cameras" / "cmos_modern.toml")
y, x = np.mgrid[0:64, 0:64]
truth = np.stack([np.full(y.shape, 2000.0), 400.0 * np.cos(x / 10.0), 400.0 * np.sin(y / 10.0)])
noise = pm.camera_noise(EXAMPLES / "cameras" / "cmos_modern.toml", exposure_us=2000.0)
frames = np.rint(np.einsum("nk,kyx->nyx", rows, truth) + noise["dark_dn"]).astype(np.uint16)
products = pm.stokes(frames, rows, camera=EXAMPLES / "cameras" / "cmos_modern.toml",
                     exposure_us=2000.0)
err = np.max(np.abs(products.s1 - truth[1]))
print(f"S1 recovered to {err:.2f} DN (rounding to whole DN); predicted sigma "
      f"{float(np.median(products.sigma_s1)):.1f} DN")

# %% The planner: angles and a forecast for a target against a background
plan = pm.plan_scene(scene=EXAMPLES / "rooftop.toml",
                     camera=EXAMPLES / "cameras" / "cmos_modern.toml",
                     target="panel", background="asphalt", channels=3, min_separation_deg=30)
print(f"plan scene: angles {np.round(plan.angles_deg, 1)} deg, {plan.t_int_ms * 1000:.0f} us, "
      f"panel DoLP sigma {plan.forecast['dolp_sigma']['panel']:.3f}")
check = pm.check_plan(EXAMPLES / "plans" / "capture.toml")
print(f"plan check: {check.forecast['frames']} frames in {check.forecast['duration_s']:.1f} s")

# %% A run on simulated devices, with its progress; Ctrl-C would pause it (KeyboardInterrupt)
shutil.rmtree("tour-run", ignore_errors=True)


def progress(event: dict) -> None:
    if event["kind"] == "set":
        print(f"  set {event['set']}: mean DoLP {event['mean_dolp']:.3f}"
              f"{'' if event['accepted'] else ' (rejected: ' + event['reason'] + ')'}")


result = pm.run(EXAMPLES / "plans" / "capture.toml", "tour-run", simulate=True,
                on_event=progress)
print(f"run {result.state}: {result.summary['frames_accepted']} frames")
ds = pm.open_run("tour-run")
print(ds)

# Recompute the last set's products from the run's own frames, spans and camera model.
last = ds["set"].values[-1]
light = ds.isel(frame=(ds["frame_set"].values == last) & (ds["kind"].values == 0))
camera = ds.attrs["products_camera"]["model"]
rows = pm.analyzer_rows(light["angle_start_deg"].values, light["angle_end_deg"].values,
                        camera=camera)
# The dark each set subtracted: a level, or the mean of the first N dark frames at an exposure.
source = ds.attrs["dark_source"][str(int(last))]
if "level_dn" in source:
    dark = {"dark_dn": source["level_dn"]}
else:
    darks = ds.isel(frame=(ds["kind"].values == 1)
                    & (ds["exposure_us"].values == source["exposure_us"]))
    mean = darks["pixels"].values[: source["dark_frames"]].astype(np.float64).mean(axis=0)
    dark = {"dark_map": mean.astype(np.float32)}
again = pm.stokes(light["pixels"].values, rows, camera=camera,
                  gain_db=float(light["gain"].values[0]), **dark)
stored = ds["dolp"].sel(set=last).values
# The store keeps DoLP to a power of two at most half its sigma (docs/DATASET.md).
within = np.nanmax(np.abs(again.dolp - stored) / ds["sigma_dolp"].sel(set=last).values)
print(f"set {last}: DoLP recomputed in Python differs from the stored by at most "
      f"{np.nanmax(np.abs(again.dolp - stored)):.1e} ({within:.2f} of its sigma)")

# %% A picture of the DoLP (matplotlib, if installed)
try:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    print("matplotlib is not installed: no picture")
else:
    fig, ax = plt.subplots(figsize=(5, 4))
    im = ax.imshow(stored, vmin=0, vmax=1, cmap="viridis")
    fig.colorbar(im, label="DoLP")
    ax.set_title(f"tour-run, set {last}")
    fig.savefig("tour-dolp.png", dpi=80)
    print("wrote tour-dolp.png")
