#!/usr/bin/env python3
"""Recompute a run's products from its store alone, with the reference in docs/DATASET.md.

Usage: python3 scripts/recompute_products.py RUN_DIR

Runs the Python block under "Recomputing the products from the store" in docs/DATASET.md (so
the documented reference is the code tested) and compares S0, S1, S2 and DoLP of every stored
set with the run's `products/`. The products are stored as float32 and computed with
float32 sums over the frames, so the two differ by float32 rounding: up to about 4e-7 (of the
set's largest |S0| for Stokes, absolute for DoLP) in CI's runs. The tolerance, 2e-6, is five
times that; what a reader could get wrong is far larger (a dark level rounded to a thousandth
of a DN moves DoLP by 4e-6; leaving out the span factor of a 14 degree span, 1 %). DoLP is
compared where S0 is above 1 % of that largest value (below it DoLP divides float32 noise by
a small S0). NaN must fall on the same pixels in both (saturation, undefined DoLP).

A run stored at `precision = "sigma"` (the default, docs/DATASET.md) rounds each stored value
to a multiple of a power of two at most half its pixel's sigma: such a plane (its `precision`
attribute says so) may also differ by a quarter of its stored sigma, which is itself within
3.1 %: 0.26 sigma. A plane the run did not store (S1 and S2 of `products = "essential"`) is
not compared.

Prints one JSON line {"ok": bool, "sets": N, "worst": {...}, "problems": [...]}; exits 0 when
ok, 1 otherwise, 2 on a usage error or a missing package.
"""

import json
import pathlib
import re
import sys

STOKES_TOL = 2e-6
DOLP_TOL = 2e-6
ROUNDING_SIGMA = 0.26


def reference():
    """The `recompute` function of docs/DATASET.md's reference block."""
    doc = pathlib.Path(__file__).resolve().parent.parent / "docs" / "DATASET.md"
    text = doc.read_text()
    m = re.search(r"<!-- reference: [^>]*-->\n```python\n(.*?)```", text, re.S)
    if not m:
        raise SystemExit(f"{doc}: no reference block")
    scope = {}
    exec(compile(m.group(1), f"{doc} (reference block)", "exec"), scope)  # noqa: S102
    return scope["recompute"]


def main(argv):
    if len(argv) != 2 or argv[1].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    try:
        import numpy as np
        import zarr
    except ImportError as e:
        print(f"missing package: {e}", file=sys.stderr)
        return 2
    run_dir = argv[1]
    recomputed = reference()(run_dir)
    products = zarr.open_group(f"{run_dir}/run.zarr", mode="r")["products"]
    problems, worst = [], {"s0": 0.0, "s1": 0.0, "s2": 0.0, "dolp": 0.0}
    for slot, s in enumerate(products["set"][...]):
        if s < 0:
            continue
        mine = recomputed[int(s)]
        s0 = products["s0"][slot].astype(np.float64)
        scale = float(np.nanmax(np.abs(s0))) if np.isfinite(s0).any() else 1.0
        for name in worst:
            if name not in products.array_keys():
                continue
            stored = products[name][slot].astype(np.float64)
            rounded = "precision" in products[name].attrs
            sigma = (products["sigma_" + name][slot].astype(np.float64)
                     if rounded else np.zeros_like(stored))
            nan_differs = np.isfinite(stored) != np.isfinite(mine[name])
            if nan_differs.any():
                problems.append(f"set {s} {name}: NaN at {int(nan_differs.sum())} pixels in "
                                f"one but not the other")
            both = np.isfinite(stored) & np.isfinite(mine[name])
            # The difference past what the store's rounding allows, in the float32 tolerance's
            # units.
            excess = np.maximum(np.abs(stored - mine[name]) - ROUNDING_SIGMA * sigma, 0.0)
            if name == "dolp":
                both &= np.abs(s0) > 0.01 * scale
                diff = excess[both]
                tol = DOLP_TOL
            else:
                diff = excess[both] / scale
                tol = STOKES_TOL
            err = float(diff.max()) if diff.size else 0.0
            worst[name] = max(worst[name], err)
            if err > tol:
                problems.append(f"set {s} {name}: differs by {err:.3g} (allowed {tol:g})")
    print(json.dumps({"ok": not problems, "sets": len(recomputed), "worst": worst,
                      "problems": problems[:20]}))
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
