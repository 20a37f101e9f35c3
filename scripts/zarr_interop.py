#!/usr/bin/env python3
"""Check that a run's Zarr store reads back in Python as the Rust writer says it should.

Usage: python3 scripts/zarr_interop.py RUN_DIR EXPECTED_JSON

Opens RUN_DIR/run.zarr with the `zarr` package (v3; `pip install 'zarr>=3'`), reads every
array and the root attributes, and compares them with EXPECTED_JSON (written by the Rust
integration test `crates/engine/tests/store.rs`):

    {
      "attributes": {"plan": ..., "software": ...},   # each key must be equal
      "arrays": {
        "frames/kind": {"shape": [6], "dtype": "uint8", "values": [0, 1, ...]},
        "frames/pixels": {"shape": [6, 48, 64], "dtype": "uint16",
                          "sum": 123.0, "min": 0.0, "max": 4095.0,
                          "samples": [{"index": [2, 10, 5], "value": 1234}, ...]},
        ...
      },
      "exact_members": true      # arrays in the store but not listed are a difference
    }

`values` are nested lists (NaN as null) compared exactly after conversion to the array's
dtype. `sum`, `min` and `max` are over the finite values, as float64 (relative tolerance
1e-9). Exits 0 when everything matches, 1 with one line per difference otherwise, 2 on a
usage error or when `zarr` is not installed.
"""

import json
import math
import sys


def fail_usage(message):
    print(f"zarr_interop: {message}", file=sys.stderr)
    sys.exit(2)


def to_expected_array(np, values, dtype):
    """Nested lists (null = NaN) to a numpy array of dtype."""

    def fix(v):
        if isinstance(v, list):
            return [fix(x) for x in v]
        return float("nan") if v is None else v

    return np.array(fix(values), dtype=dtype)


def close(a, b, rel=1e-9, abs_=1e-6):
    if a is None or b is None:
        return a is None and b is None
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return math.isclose(a, b, rel_tol=rel, abs_tol=abs_)


def first_differences(np, got, want, limit=5):
    """Up to `limit` (index, got, want) where the arrays differ (NaN equals NaN)."""
    if got.dtype.kind == "f":
        same = (got == want) | (np.isnan(got) & np.isnan(want))
    else:
        same = got == want
    bad = np.argwhere(~same)
    return [
        (tuple(int(i) for i in idx), got[tuple(idx)].item(), want[tuple(idx)].item())
        for idx in bad[:limit]
    ], int(bad.shape[0])


def check_array(np, name, arr, spec, diffs):
    shape = list(arr.shape)
    if "shape" in spec and shape != list(spec["shape"]):
        diffs.append(f"{name}: shape {shape}, expected {spec['shape']}")
        return
    dtype = str(arr.dtype)
    if "dtype" in spec and dtype != spec["dtype"]:
        diffs.append(f"{name}: dtype {dtype}, expected {spec['dtype']}")
        return
    data = arr[...]
    if "values" in spec:
        want = to_expected_array(np, spec["values"], arr.dtype)
        if list(want.shape) != shape:
            diffs.append(f"{name}: expected values have shape {list(want.shape)}, array {shape}")
        else:
            firsts, count = first_differences(np, data, want)
            if count:
                shown = "; ".join(f"at {i}: got {g!r}, expected {w!r}" for i, g, w in firsts)
                diffs.append(f"{name}: {count} values differ ({shown})")
    as64 = data.astype(np.float64)
    finite = as64[np.isfinite(as64)]
    for key, fn in (("sum", np.sum), ("min", np.min), ("max", np.max)):
        if key in spec:
            got = float(fn(finite)) if finite.size or key == "sum" else None
            if not close(got, spec[key]):
                diffs.append(f"{name}: {key} of finite values {got!r}, expected {spec[key]!r}")
    for sample in spec.get("samples", []):
        idx = tuple(sample["index"])
        try:
            got = data[idx].item()
        except IndexError:
            diffs.append(f"{name}[{list(idx)}]: out of bounds for shape {shape}")
            continue
        want = to_expected_array(np, sample["value"], arr.dtype).item()
        if not (got == want or (isinstance(got, float) and math.isnan(got) and math.isnan(want))):
            diffs.append(f"{name}[{list(idx)}]: got {got!r}, expected {want!r}")


def main(argv):
    if len(argv) != 3:
        fail_usage("usage: python3 scripts/zarr_interop.py RUN_DIR EXPECTED_JSON")
    run_dir, expected_path = argv[1], argv[2]
    try:
        import numpy as np
        import zarr
    except ImportError as e:
        fail_usage(f"{e}: install it with `pip install 'zarr>=3'` (or run `bash scripts/test.sh`)")
    if int(zarr.__version__.split(".")[0]) < 3:
        fail_usage(f"zarr {zarr.__version__} is too old: the store is Zarr v3; pip install 'zarr>=3'")
    with open(expected_path, encoding="utf-8") as f:
        expected = json.load(f)

    store_path = f"{run_dir.rstrip('/')}/run.zarr"
    diffs = []
    try:
        root = zarr.open_group(store_path, mode="r")
    except Exception as e:  # noqa: BLE001 - report any failure to open as a difference
        print(f"{store_path}: cannot open as a Zarr group: {e}")
        return 1

    attrs = dict(root.attrs)
    for key, want in expected.get("attributes", {}).items():
        if key not in attrs:
            diffs.append(f"attribute {key!r}: missing (present: {sorted(attrs)})")
        elif attrs[key] != want:
            diffs.append(
                f"attribute {key!r}: got {json.dumps(attrs[key], sort_keys=True)[:300]}, "
                f"expected {json.dumps(want, sort_keys=True)[:300]}"
            )

    arrays = {}
    for path, node in root.members(max_depth=None):
        if isinstance(node, zarr.Array):
            arrays[path] = node
    specs = expected.get("arrays", {})
    for name, spec in specs.items():
        if name not in arrays:
            diffs.append(f"{name}: missing (arrays: {sorted(arrays)})")
            continue
        try:
            check_array(np, name, arrays[name], spec, diffs)
        except Exception as e:  # noqa: BLE001 - a read failure is a difference
            diffs.append(f"{name}: cannot read: {type(e).__name__}: {e}")
    if expected.get("exact_members", False):
        for name in sorted(set(arrays) - set(specs)):
            diffs.append(f"{name}: in the store but not expected")

    if diffs:
        print(f"{store_path}: {len(diffs)} difference(s):")
        for d in diffs:
            print(f"  - {d}")
        return 1
    print(
        f"{store_path}: OK ({len(specs)} arrays, {len(expected.get('attributes', {}))} "
        f"attributes; zarr {zarr.__version__})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
