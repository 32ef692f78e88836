"""Array types for annotations in ``cycles``: what an array holds, not just that it is one."""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

#: Real values (positions, angles, times, weights, ...).
FloatArray: TypeAlias = NDArray[np.float64]
#: Indices and counts.
IntArray: TypeAlias = NDArray[np.intp]
#: Masks.
BoolArray: TypeAlias = NDArray[np.bool_]

__all__ = ["BoolArray", "FloatArray", "IntArray"]
