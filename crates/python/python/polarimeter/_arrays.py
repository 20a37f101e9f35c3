"""Broadcasting for the array functions: the inputs as equal-length float64 vectors for the
Rust side, and the shape to give the outputs back."""

from __future__ import annotations

from typing import Any

import numpy as np


def as_float(name: str, value: Any) -> np.ndarray:
    """``value`` as a float64 array; a value that is not numeric is a ``ValueError`` naming
    ``name``."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric (a number or an array of numbers), "
                         f"got {type(value).__name__}") from None


def broadcast(**named: Any) -> tuple[tuple[int, ...], dict[str, np.ndarray]]:
    """The broadcast shape of the named inputs and each as a contiguous float64 vector of
    that many elements. A shape mismatch is a ``ValueError`` listing every input's shape;
    an input that is not numeric is one naming it."""
    arrays = {name: as_float(name, value) for name, value in named.items()}
    try:
        shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
    except ValueError:
        listed = ", ".join(f"{k} {a.shape}" for k, a in arrays.items())
        raise ValueError(f"the inputs do not broadcast to one shape: {listed}") from None
    flat = {k: np.ascontiguousarray(np.broadcast_to(a, shape)).reshape(-1)
            for k, a in arrays.items()}
    return shape, flat


def shaped(value: np.ndarray, shape: tuple[int, ...]) -> Any:
    """A flat result in the inputs' shape; a 0-d result as a scalar."""
    out = value.reshape(shape + value.shape[1:])
    return out[()] if out.ndim == 0 else out
