"""The CLI's document commands from Python: keyword arguments become the command's flags,
the Rust side parses them with the CLI's own definitions and returns the CLI's JSON.

Nothing here computes a number; it spells flags, maps results onto arrays and rewrites the
CLI's flag names (``--target-dolp``) as the Python argument names (``target_dolp``) in errors.
"""

from __future__ import annotations

import json
import math
import os
import re
from typing import Any, Mapping

import numpy as np

from . import _native
from ._arrays import as_float

_FLAG = re.compile(r"--([a-z0-9][a-z0-9-]*)(?: <[A-Z0-9_]+>)?")


def _flag_value(value: Any) -> str:
    if isinstance(value, (bool, np.bool_)):
        raise TypeError("a boolean is a switch, not a value")
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        return ",".join(_flag_value(v) for v in np.ravel(np.asarray(value, dtype=object)))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


def argv(kwargs: Mapping[str, Any]) -> list[str]:
    """The CLI flags of ``kwargs``: ``name=value`` as ``--name=value`` (underscores become
    hyphens), ``True`` as a bare switch, ``None`` and ``False`` left out, sequences joined by
    commas."""
    out = []
    for name, value in kwargs.items():
        if value is None or value is False:
            continue
        flag = "--" + name.replace("_", "-")
        out.append(flag if value is True else f"{flag}={_flag_value(value)}")
    return out


def python_names(message: str) -> str:
    """A CLI message with its flag names written as the Python argument names."""
    return _FLAG.sub(lambda m: m.group(1).replace("-", "_"), message)


def run(name: str, kwargs: Mapping[str, Any]) -> dict:
    """The JSON result of command ``name`` with ``kwargs`` as its flags. A bad argument is a
    ``ValueError`` naming it, its value and the allowed range."""
    try:
        text = _native.command(name, argv(kwargs))
    except ValueError as e:
        raise ValueError(python_names(str(e))) from None
    return json.loads(text)


def _is_number(v: Any) -> bool:
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


def _numeric(values: list) -> np.ndarray | None:
    """``values`` (numbers, or equal-shaped nested lists of numbers; ``None`` is NaN) as one
    float array, or ``None`` when they are not all numeric or hold no number at all (a list of
    warnings that happens to be empty stays a list)."""
    numbers = 0

    def clean(v: Any) -> Any:
        nonlocal numbers
        if isinstance(v, list):
            return [clean(x) for x in v]
        if not _is_number(v):
            raise TypeError
        numbers += 1
        return math.nan if v is None else v
    try:
        cleaned = [clean(v) for v in values]
        if numbers == 0:
            return None
        arr = np.asarray(cleaned, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr


def mapped(name: str, fixed: Mapping[str, Any], arrays: Mapping[str, Any],
           inner: Mapping[str, int] | None = None) -> dict:
    """Runs ``name`` once per element of the broadcast ``arrays`` (scalars per call; an entry
    of ``inner`` names an argument whose last axis of that length is one vector per call), with
    ``fixed`` as the same flags every time. Numeric results become arrays of the broadcast
    shape (plus their own shape); others stay lists of that shape."""
    inner = dict(inner or {})
    shaped = {}
    for k, v in arrays.items():
        a = as_float(k, v)
        if k in inner:
            if a.ndim == 0 or a.shape[-1] != inner[k]:
                raise ValueError(
                    f"{k} has shape {a.shape}: allowed (..., {inner[k]}), "
                    f"{inner[k]} values per evaluation")
        shaped[k] = a
    shapes = {k: (a.shape[:-1] if k in inner else a.shape) for k, a in shaped.items()}
    try:
        shape = np.broadcast_shapes(*shapes.values())
    except ValueError:
        listed = ", ".join(f"{k} {s}" for k, s in shapes.items())
        raise ValueError(f"the inputs do not broadcast to one shape: {listed}") from None
    flat = {}
    for k, a in shaped.items():
        full = shape + ((inner[k],) if k in inner else ())
        flat[k] = np.broadcast_to(a, full).reshape((-1,) + full[len(shape):])
    count = int(np.prod(shape, dtype=np.int64))
    if count == 0:
        listed = ", ".join(f"{k} {s}" for k, s in shapes.items())
        raise ValueError(f"the inputs broadcast to an empty shape {shape}: {listed}")
    results = []
    for i in range(count):
        call = dict(fixed)
        for k, a in flat.items():
            call[k] = a[i].tolist() if k in inner else float(a[i])
        try:
            results.append(run(name, call))
        except ValueError as e:
            index = tuple(int(j) for j in np.unravel_index(i, shape))
            where = f" (at element {index} of the broadcast inputs)" if count > 1 else ""
            raise ValueError(f"{e}{where}") from None
    out: dict = {}
    for key in (results[0] if results else {}):
        values = [r.get(key) for r in results]
        arr = _numeric(values)
        if arr is not None:
            arr = arr.reshape(shape + arr.shape[1:])
            # One evaluation of a scalar field is a scalar, as the array functions give.
            out[key] = arr[()] if arr.ndim == 0 else arr
        elif shape == ():
            out[key] = values[0]
        else:
            out[key] = _nested(values, shape)
    return out


def _nested(values: list, shape: tuple) -> list:
    """A flat list as nested lists of ``shape``."""
    if len(shape) <= 1:
        return list(values)
    step = len(values) // shape[0]
    return [_nested(values[i * step:(i + 1) * step], shape[1:]) for i in range(shape[0])]
