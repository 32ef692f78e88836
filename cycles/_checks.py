"""Argument checks shared by the cycle-editing modules (:mod:`cycles.edit`, :mod:`cycles.retiming`,
:mod:`cycles.contacts`): integers that are really integers, finite arrays of the right rank, positive
numbers, unit vectors, and the frame count of an open or closed loop curve. Each raises ``ValueError``
naming the argument."""

from __future__ import annotations

import math
import operator
from typing import TYPE_CHECKING, SupportsIndex

import numpy as np

if TYPE_CHECKING:
    from cycles._types import FloatArray


def as_int(value: object, name: str) -> int:
    """``value`` as a Python int; bools, floats and other non-integers are refused with ValueError."""
    if isinstance(value, bool) or not isinstance(value, SupportsIndex):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return operator.index(value)


def finite_array(values: object, name: str, ndim: tuple[int, ...]) -> FloatArray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim not in ndim:
        raise ValueError(f"{name} must have {' or '.join(map(str, ndim))} dimensions, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def positive_finite(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return v


def unit_vector(vector: object, name: str) -> FloatArray:
    v = finite_array(vector, name, (1,))
    if v.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {v.shape}")
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise ValueError(f"{name} must not be the zero vector")
    return v / norm


def loop_frames(values: FloatArray, closed: bool, name: str, *, quaternion: bool = False) -> int:
    """The number of distinct frames ``m`` in ``values``, checking the closing row if ``closed``."""
    rows = int(values.shape[0])
    if not closed:
        if rows < 1:
            raise ValueError(f"{name} has no frames")
        return rows
    if rows < 2:
        raise ValueError(f"a closed {name} needs at least 2 rows (frames 0..m with m >= 1)")
    first, last = values[0], values[-1]
    scale = max(1.0, float(np.max(np.abs(values))))
    tol = 1e-9 * scale
    same = bool(np.all(np.abs(last - first) <= tol))
    if quaternion and not same:
        same = bool(np.all(np.abs(last + first) <= tol))
    if not same:
        raise ValueError(f"closed=True but the last row of {name} differs from the first")
    return rows - 1
