#!/usr/bin/env python3
"""Status requests per second on loopback while a continuous run goes, against the same run
unloaded: the run's frames lost (0) and its set rate under load.

Usage: python3 scripts/bench_station_load.py [--bin target/release/polarimeter]
       [--clients 4] [--half-turns 60] [--out target/station-load]

Starts `polarimeter station serve` on the simulated rig (loopback, a free port), runs one
continuous plan unloaded, then the same plan while `--clients` threads send `GET
/api/v1/status` back to back (loopback only, bounded by the run's duration and at most 120 s),
and prints JSON: requests, requests per second, the error count, latency percentiles, each
run's sets per second (sets over the run's own first-to-last frame time) and its ratio, and
whether every frame counted (the run check and the plan's frame count). Needs httpx (the
station tests' venv: tests/station/requirements.txt).
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def plan(half_turns):
    return (f'name = "load"\nkind = "continuous"\n[continuous]\nframes_per_half_turn = 4\n'
            f'exposure_us = 1000\nspeed_deg_per_s = 360\nhalf_turns = {half_turns}\n'
            f'trigger = "encoder"\n')


def run_item(c, text, data):
    ids = c.post("/api/v1/queue", json={"plan": text}).json()["ids"]
    while True:
        h = [e for e in c.get("/api/v1/history").json()["items"] if e["item"]["id"] in ids]
        if h:
            return h[0]
        time.sleep(0.2)


def set_rate(binary, run_dir):
    """Sets per second over the run's frame times (first to last frame that counts)."""
    import numpy as np
    import zarr
    g = zarr.open_group(str(run_dir / "run.zarr"), mode="r")
    t = np.asarray(g["frames/host_time_unix_ns"][:], dtype=np.int64)
    ok = np.asarray(g["frames/accepted"][:]) == 1
    sets = np.asarray(g["frames/set"][:])[ok]
    t = t[ok]
    n = len(set(int(s) for s in sets if s >= 0))
    return (n - 1) / ((t.max() - t.min()) * 1e-9), int(ok.sum())


def hammer(url, key, stop, out):
    lat = []
    errors = 0
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=10) as c:
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                ok = c.get("/api/v1/status").status_code == 200
            except httpx.HTTPError:
                ok = False
            lat.append(time.perf_counter() - t0)
            errors += not ok
    out.append((lat, errors))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "polarimeter"))
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--half-turns", type=int, default=60)
    ap.add_argument("--out", default=str(ROOT / "target" / "station-load"))
    a = ap.parse_args()
    out = Path(a.out)
    shutil.rmtree(out, ignore_errors=True)
    (out / "tmp").mkdir(parents=True)
    cfg = out / "station.toml"
    cfg.write_text(f'listen = "127.0.0.1:0"\ndata_dir = "data"\n'
                   f'rig = "{ROOT / "examples" / "rigs" / "sim.toml"}"\nreserve_mb = 64\n')
    key = json.loads(subprocess.run([a.bin, "station", "key", "create", "--config", str(cfg),
                                     "--scope", "admin"], capture_output=True, text=True,
                                    check=True).stdout)["key"]
    env = dict(os.environ, TMPDIR=str(out / "tmp"))
    p = subprocess.Popen([a.bin, "station", "serve", "--config", str(cfg)], env=env,
                         stdout=subprocess.PIPE, stderr=open(out / "serve.err", "w"), text=True,
                         stdin=subprocess.DEVNULL)
    try:
        url = json.loads(p.stdout.readline())["listening"]
        text = plan(a.half_turns)
        with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"},
                          timeout=60) as c:
            quiet = run_item(c, text, out)
            stop, results = threading.Event(), []
            threads = [threading.Thread(target=hammer, args=(url, key, stop, results))
                       for _ in range(a.clients)]
            t0 = time.monotonic()
            for t in threads:
                t.start()
            ids = c.post("/api/v1/queue", json={"plan": text}).json()["ids"]
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                h = [e for e in c.get("/api/v1/history").json()["items"] if e["item"]["id"] in ids]
                if h:
                    break
                time.sleep(0.2)
            stop.set()
            for t in threads:
                t.join()
            elapsed = time.monotonic() - t0
            loaded = h[0]
    finally:
        p.terminate()
        p.wait(timeout=60)
    lat = sorted(x for r in results for x in r[0])
    errors = sum(r[1] for r in results)
    report = {"clients": a.clients, "requests": len(lat), "errors": errors,
              "requests_per_s": round(len(lat) / elapsed, 1),
              "latency_ms": {"p50": round(1e3 * lat[len(lat) // 2], 2),
                             "p99": round(1e3 * lat[int(len(lat) * 0.99)], 2)}}
    for name, entry in (("unloaded", quiet), ("loaded", loaded)):
        run = out / "data" / entry["run_dir"]
        check = json.loads(subprocess.run([a.bin, "acquire", "check", str(run)],
                                          capture_output=True, text=True).stdout)
        rate, counted = set_rate(a.bin, run)
        report[name] = {"exit": entry["exit"], "check_ok": check["ok"],
                        "frames_counted": counted, "frames_planned": entry["item"]["forecast"]["frames"],
                        "frames_lost": entry["item"]["forecast"]["frames"] - counted,
                        "sets_per_s": round(rate, 2)}
    report["set_rate_ratio_loaded_to_unloaded"] = round(
        report["loaded"]["sets_per_s"] / report["unloaded"]["sets_per_s"], 3)
    print(json.dumps(report))
    return 0 if report["loaded"]["frames_lost"] == 0 and errors == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
