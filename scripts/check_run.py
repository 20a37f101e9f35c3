#!/usr/bin/env python3
"""Check a run directory from the outside, with zarr-python 3, xarray and xxhash.

Usage: python3 scripts/check_run.py RUN_DIR [--finished]

What a reader of the dataset is promised, checked without any of our code:
- every array of RUN_DIR/run.zarr opens and reads whole (every chunk passes its crc32c; a
  frame the journal records as damaged was kept aside and reads as the fill value);
- `xarray.open_zarr` opens the `frames` and `products` groups with named dimensions, and
  every array carries a `long_name` (and `units` where it has one);
- the journal's frame records (RUN_DIR/journal.jsonl) are frames 0..N-1, each once, and the
  store holds the first M of them (M = N once the run is finished; a run that stopped without
  finishing, killed say, mirrors its journal up to its last metadata sync, at most about a
  second behind, and `acquire resume` catches up), each with its metadata (step, kind, hash)
  equal to the journal's and its pixels hashing (XXH3-64 of the little-endian bytes) to the
  recorded hash; every per-frame array holds M values, so xarray opens the group whole;
- which frames count (frames/accepted 1, frames/status 0) matches the journal: a rejected
  set's frames have status 1, an unfinished set's taken again whole 2, damaged frames 3;
- every frame's analyzer span (frames/angle_start_deg, angle_end_deg, angle_source,
  angle_sigma_deg) has one value per frame; the start is in [0, 180) and end - start (the
  span swept, unwrapped from the start) in [0, 180); step-and-shoot frames (source 0) have
  end == start; the source is a known code (0 settled, 1 encoder trigger, 2 timestamps).
  A run written before frames recorded spans has none of these arrays: that is not a problem;
- no set has two product slots, and every set the journal records as done has one;
  `products/flags`, a bit mask, is stored as unsigned integers;
- with --finished: the journal ends the run, every plan step between 0 and the last has
  exactly one accepted frame (but the steps of late time-lapse sets the plan skipped), and
  the summary counts the sets in the store.

Prints one JSON line {"ok": bool, "problems": [...], ...}; exits 0 when ok, 1 otherwise,
2 on a usage error or a missing package.
"""

import json
import sys


def main(argv):
    if len(argv) < 2 or argv[1].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    run_dir = argv[1]
    finished_required = "--finished" in argv[2:]
    try:
        import numpy as np
        import xarray as xr
        import xxhash
        import zarr
    except ImportError as e:
        print(f"check_run: {e}: run `bash scripts/test.sh`, which installs zarr, xarray and "
              "xxhash", file=sys.stderr)
        return 2

    problems = []
    journal = []
    with open(f"{run_dir}/journal.jsonl", "rb") as f:
        lines = f.read().split(b"\n")
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            journal.append(json.loads(line))
        except ValueError:
            # Only the last line may be torn by a crash.
            if i < len(lines) - 1 and any(x.strip() for x in lines[i + 1:]):
                problems.append(f"journal line {i + 1} does not parse")
    frames = {}
    for e in journal:
        if e.get("event") == "frame":
            if e["index"] in frames:
                problems.append(f"journal: frame {e['index']} recorded twice")
            frames[e["index"]] = e
    n = len(frames)
    if sorted(frames) != list(range(n)):
        problems.append(f"journal: frame indices are not 0..{n - 1}: {sorted(frames)[:10]}...")
    rejected = set()
    damaged = set()
    done_sets = set()
    skipped_sets = set()  # late time-lapse sets the plan's policy skipped: not planned
    for e in journal:
        if e.get("event") in ("set-rejected", "frames-superseded"):
            # A rejected set, or an unfinished one taken again whole: stored, superseded.
            rejected.update(e["frames"])
        if e.get("event") == "frame-damaged":
            # Kept aside on a resume and taken again: recorded, not stored.
            damaged.add(e["index"])
            rejected.add(e["index"])
        if e.get("event") == "set-done":
            done_sets.add(e["set"])
        if e.get("event") == "set-late" and e.get("action") == "skipped":
            skipped_sets.add(e["set"])
    finished = any(e.get("event") == "finished" for e in journal)

    root = zarr.open_group(f"{run_dir}/run.zarr", mode="r")
    arrays = {}

    def visit(group, prefix):
        for name, member in group.members():
            path = f"{prefix}{name}"
            if isinstance(member, zarr.Group):
                visit(member, path + "/")
            else:
                arrays[path] = member

    visit(root, "")
    values = {}
    for path, a in sorted(arrays.items()):
        try:
            values[path] = a[...]
        except Exception as e:  # noqa: BLE001 - any failure to read is the finding
            problems.append(f"{path}: unreadable: {type(e).__name__}: {e}")
        if "long_name" not in a.attrs:
            problems.append(f"{path}: no long_name attribute")
    for group in ("frames", "products"):
        try:
            ds = xr.open_zarr(f"{run_dir}/run.zarr", group=group, consolidated=False)
            for name, var in ds.data_vars.items():
                if any(d.startswith("dim_") for d in var.dims):
                    problems.append(f"xarray {group}/{name}: unnamed dimensions {var.dims}")
        except Exception as e:  # noqa: BLE001
            problems.append(f"xarray cannot open {group}: {type(e).__name__}: {e}")

    flags = arrays.get("products/flags")
    if flags is not None and flags.dtype.kind != "u":
        problems.append(f"products/flags is a bit mask stored as {flags.dtype}, not unsigned")

    pixels = values.get("frames/pixels")
    # The frames the store mirrors: all N once the run is finished, the first M <= N before.
    m = n
    if pixels is not None:
        m = min(n, pixels.shape[0])
        if pixels.shape[0] > n or (finished and pixels.shape[0] != n):
            problems.append(f"frames/pixels holds {pixels.shape[0]} frames; the journal {n}")
        for i in range(m):
            if i in damaged:
                continue
            h = xxhash.xxh3_64_intdigest(np.ascontiguousarray(pixels[i], dtype="<u2").tobytes())
            if h != frames[i]["hash"]:
                problems.append(f"frame {i}: pixels hash {h:#x}, journal {frames[i]['hash']:#x}")
    for name, key in (("hash", "hash"), ("step", "step"), ("frame_id", "frame_id")):
        v = values.get(f"frames/{name}")
        if v is None:
            problems.append(f"frames/{name} missing")
            continue
        if len(v) != m:
            problems.append(f"frames/{name} has {len(v)} values; frames/pixels {m} frames")
            continue
        bad = [i for i in range(m) if int(v[i]) != int(frames[i][key])]
        if bad:
            problems.append(f"frames/{name} differs from the journal at frames {bad[:10]}")
    kinds = values.get("frames/kind")
    if kinds is not None and len(kinds) == m:
        codes = {"light": 0, "dark": 1}
        bad = [i for i in range(m) if int(kinds[i]) != codes.get(frames[i]["kind"], -1)]
        if bad:
            problems.append(f"frames/kind differs from the journal at frames {bad[:10]}")

    # Which frames count, from the store alone (frames/accepted, frames/status) against the
    # journal: 0 counts, 1 a rejected set, 2 superseded (an unfinished set taken again), 3
    # damaged. A run written before frames recorded them has neither array. Before the run
    # finishes the store may not yet know of a frame superseded since its last sync, so
    # there only the two arrays' agreement is checked.
    accepted_flag, status = values.get("frames/accepted"), values.get("frames/status")
    if (accepted_flag is None) != (status is None):
        problems.append("frames: only one of accepted and status is stored")
    elif accepted_flag is not None and (len(accepted_flag) != m or len(status) != m):
        problems.append(f"frames/accepted and status hold {len(accepted_flag)} and "
                        f"{len(status)} values; frames/pixels {m} frames")
    elif accepted_flag is not None and not finished:
        bad = [i for i in range(m) if int(status[i]) not in (0, 1, 2, 3)
               or int(accepted_flag[i]) != int(status[i] == 0)]
        if bad:
            problems.append(f"frames/accepted and status disagree at frames {bad[:10]}")
    elif accepted_flag is not None:
        superseded = set()
        for e in journal:
            if e.get("event") == "frames-superseded":
                superseded.update(e["frames"])
        want = []
        for i in range(n):
            if i in damaged:
                want.append(3)
            elif i in superseded:
                want.append(2)
            elif i in rejected:
                want.append(1)
            else:
                want.append(0)
        bad = [i for i in range(n) if int(status[i]) != want[i]
               or int(accepted_flag[i]) != int(want[i] == 0)]
        if bad:
            problems.append(f"frames/accepted or status differ from the journal at frames "
                            f"{bad[:10]}")

    span_names = ("angle_start_deg", "angle_end_deg", "angle_source", "angle_sigma_deg")
    span = {name: values.get(f"frames/{name}") for name in span_names}
    present = [name for name in span_names if span[name] is not None]
    if present and len(present) != len(span_names):
        problems.append(f"frames: span arrays {present} present but not all of {span_names}")
    elif present:
        short = [name for name in span_names if len(span[name]) != m]
        if short:
            problems.append(f"frames/{short} do not hold one value per frame ({m} frames)")
        else:
            start = np.asarray(span["angle_start_deg"], dtype=float)
            end = np.asarray(span["angle_end_deg"], dtype=float)
            source = np.asarray(span["angle_source"])
            known = np.isin(source, (0, 1, 2))
            if not known.all():
                problems.append(f"frames/angle_source: unknown codes at frames "
                                f"{np.flatnonzero(~known)[:10].tolist()}")
            both = np.isfinite(start) & np.isfinite(end)
            swept = end - start
            bad = both & ((start < 0) | (start >= 180) | (swept < 0) | (swept >= 180))
            if bad.any():
                problems.append(f"frames: analyzer span outside start in [0, 180), end - start "
                                f"in [0, 180) at frames {np.flatnonzero(bad)[:10].tolist()}")
            settled_bad = both & (source == 0) & (swept != 0)
            if settled_bad.any():
                problems.append(f"frames: step-and-shoot frames with end != start at frames "
                                f"{np.flatnonzero(settled_bad)[:10].tolist()}")
            one_sided = np.isfinite(start) != np.isfinite(end)
            if one_sided.any():
                problems.append(f"frames: span with one end missing at frames "
                                f"{np.flatnonzero(one_sided)[:10].tolist()}")

    slot_sets = values.get("products/set")
    stored_sets = []
    if slot_sets is not None:
        stored_sets = [int(s) for s in slot_sets if s >= 0]
        dup = sorted({s for s in stored_sets if stored_sets.count(s) > 1})
        if dup:
            problems.append(f"products: sets {dup} have more than one slot")
        missing = sorted(done_sets - set(stored_sets))
        if missing:
            problems.append(f"products: sets {missing} are done in the journal but not stored")

    if finished_required and not finished:
        problems.append("the journal does not record the run as finished")
    if finished:
        accepted = [frames[i]["step"] for i in range(n) if i not in rejected]
        steps = sorted(accepted)
        dup = sorted({s for s in steps if steps.count(s) > 1})
        if dup:
            problems.append(f"steps {dup[:10]} have more than one accepted frame")
        if steps and not skipped_sets and sorted(set(steps)) != list(range(max(steps) + 1)):
            gaps = sorted(set(range(max(steps) + 1)) - set(steps))
            problems.append(f"steps {gaps[:10]} have no accepted frame")
        summary = root.attrs.get("summary", {}).get("run", {})
        if summary.get("sets_accepted") != len(set(stored_sets)):
            problems.append(
                f"summary sets_accepted {summary.get('sets_accepted')} but the store holds "
                f"{len(set(stored_sets))} sets")

    print(json.dumps({"ok": not problems, "frames": n, "sets": len(set(stored_sets)),
                      "finished": finished, "problems": problems}))
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
