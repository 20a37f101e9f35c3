"""Speed of the `polarimeter` package against the same work in numpy and polanalyser, in one
run, each timing the best of `--repeats` (the machine is noisy; ratios are within one run).

Usage: python crates/python/bench/bench_python.py [--directions N] [--size PIXELS] [--repeats R]

1. pBRDF Mueller matrices per second on N view directions under one sun (glass, sigma 0.2),
   from Python, against `pbrdf_numpy` (the same evaluation written in numpy, beside this file),
   with the largest relative difference between the two.
2. Stokes products per second on a 4-frame set of PIXELS x PIXELS uint16 frames: ours (S0, S1,
   S2, DoLP, AoP, their five predicted sigma and the flags; one thread and every core) against
   polanalyser's calcLinearStokes + cvtStokesToDoLP + cvtStokesToAoLP (S0-S2, DoLP, AoP only).
3. Two threads: the wall time of two equal pBRDF calls in two Python threads over one call
   (1.0 is perfect parallelism; 2.0 would be a held GIL).

Prints a Markdown table and a JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import polarimeter as pm  # noqa: E402
from pbrdf_numpy import pbrdf_numpy  # noqa: E402


def best(fn, repeats: int) -> float:
    """The shortest of `repeats` wall times of `fn()`, seconds."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bench_pbrdf(n: int, repeats: int) -> dict:
    rng = np.random.default_rng(1)
    ti = np.full(n, 35.0)
    tr = rng.uniform(0.0, 89.0, n)
    phi = rng.uniform(-180.0, 180.0, n)
    surface = dict(n=1.5, k=0.0, sigma=0.2, dhr=0.0)
    ours = pm.pbrdf(ti, tr, phi, **surface)
    ref = pbrdf_numpy(ti, tr, phi, 1.5, 0.0, 0.2, 0.0)
    scale = np.maximum(np.abs(ours.mueller), 1e-300)
    worst = float(np.max(np.abs(ref - ours.mueller)[np.abs(ours.mueller) > 1e-300]
                         / scale[np.abs(ours.mueller) > 1e-300]))
    t_ours = best(lambda: pm.pbrdf(ti, tr, phi, **surface), repeats)
    t_np = best(lambda: pbrdf_numpy(ti, tr, phi, 1.5, 0.0, 0.2, 0.0), repeats)
    return {"directions": n, "ours_per_s": n / t_ours, "numpy_per_s": n / t_np,
            "speedup": t_np / t_ours, "max_rel_diff": worst}


def bench_stokes(size: int, repeats: int) -> dict:
    import polanalyser
    rng = np.random.default_rng(2)
    angles = [0, 45, 90, 135]
    rows = pm.analyzer_rows(angles)
    s0 = rng.uniform(2e3, 2e4, (size, size))
    s1, s2 = 0.3 * s0 * rng.uniform(-1, 1, (2, size, size))
    frames = np.rint(np.einsum("nk,kyx->nyx", rows, np.stack([s0, s1, s2])) + 100)
    frames = frames.astype(np.uint16)
    noise = dict(gain_dn_per_e=0.5, offset_dn=100.0, read_var_dn2=4.0, saturation_dn=65000,
                 dark_dn=100.0)

    def theirs() -> None:
        st = polanalyser.calcLinearStokes(frames.astype(np.float64) - 100.0, np.radians(angles))
        polanalyser.cvtStokesToDoLP(st)
        polanalyser.cvtStokesToAoLP(st)

    pixels = size * size
    t1 = best(lambda: pm.stokes(frames, rows, threads=1, **noise), repeats)
    tn = best(lambda: pm.stokes(frames, rows, threads=0, **noise), repeats)
    tp = best(theirs, repeats)
    return {"pixels": pixels, "ours_1_thread_px_per_s": pixels / t1,
            "ours_all_cores_px_per_s": pixels / tn, "polanalyser_px_per_s": pixels / tp,
            "speedup_1_thread": tp / t1, "speedup_all_cores": tp / tn}


def bench_threads(n: int, repeats: int) -> dict:
    tr = np.linspace(0.0, 89.0, n)

    def one() -> None:
        pm.pbrdf(35.0, tr, 180.0, n=1.5, sigma=0.2, dhr=0.0)

    def two() -> None:
        ts = [threading.Thread(target=one) for _ in range(2)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()

    t1, t2 = best(one, repeats), best(two, repeats)
    return {"one_call_s": t1, "two_threads_s": t2, "ratio": t2 / t1}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--directions", type=int, default=1_000_000)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    for name, value, lo in (("--directions", a.directions, 1), ("--size", a.size, 2),
                            ("--repeats", a.repeats, 1)):
        if value < lo:
            ap.error(f"{name} = {value}: allowed {lo} or more")
    p = bench_pbrdf(a.directions, a.repeats)
    s = bench_stokes(a.size, a.repeats)
    t = bench_threads(a.directions // 2, a.repeats)
    print("| work | ours | baseline | ratio |")
    print("|---|---|---|---|")
    print(f"| pBRDF, {p['directions']:,} directions | {p['ours_per_s']:.3g} /s | numpy "
          f"{p['numpy_per_s']:.3g} /s | {p['speedup']:.1f}x (max rel. diff. "
          f"{p['max_rel_diff']:.1e}) |")
    print(f"| Stokes products, {s['pixels']:,} px, 1 thread | {s['ours_1_thread_px_per_s']:.3g}"
          f" px/s | polanalyser {s['polanalyser_px_per_s']:.3g} px/s | "
          f"{s['speedup_1_thread']:.1f}x |")
    print(f"| Stokes products, every core | {s['ours_all_cores_px_per_s']:.3g} px/s | "
          f"polanalyser {s['polanalyser_px_per_s']:.3g} px/s | {s['speedup_all_cores']:.1f}x |")
    print(f"| two pBRDF calls in two threads | {t['two_threads_s']:.3f} s | one call "
          f"{t['one_call_s']:.3f} s | {t['ratio']:.2f} |")
    print(json.dumps({"pbrdf": p, "stokes": s, "threads": t}))


if __name__ == "__main__":
    main()
