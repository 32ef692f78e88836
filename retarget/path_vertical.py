"""The vertical deformation of path editing (``docs/design/path-editing.md`` section 1.7): the root's height
along the edited path, bent to the handles' new heights as rigidly as the shear frame allows.

Each interior key is written in the frame of its neighbours over the horizontal arclength ``a`` (fixed by
the horizontal solve): ``y_i = y_{i-1} + u_i (y_{i+1} - y_{i-1}) + v_i`` with ``u_i`` the arclength fraction;
the edited heights keep the ``v_i`` in least squares (weights ``1 / |d_i|`` of the original neighbours'
distance in ``(a, y)``), with the handles' heights fixed and, at every handle that is a contact period's
lowest key, the tangent kept: ``y_{h+1} - y_{h-1}`` as it was, so a step's lowest point stays a low point
(unless a neighbouring key is itself a handle, whose height then decides).
The solve is for the displacement from the original heights; its matrix depends only on the original and
the handle set (factored once, each lift one re-solve). A constant lift moves the curve exactly so, and so
does one growing linearly along the arclength where no tangent is kept; unmoved handles give the original
exactly.

Ballistic spans (one shear and the apex lift per flight) are the design note's next step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import splu

from retarget.path_arap import STILL_M, frame_keys

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray, IntArray

REFINE_STEPS = 3


class VerticalPath:
    """Root heights ``y`` ``(n+1,)`` over horizontal arclength ``a`` ``(n+1,)`` (non-decreasing), with
    handles at ``keys`` (the first and last among them) and tangents kept at ``tangent_keys`` (a subset of
    the interior handle keys).

    Raises:
        ValueError: shapes or values that break the above.
    """

    def __init__(self, a: FloatArray, y: FloatArray, keys: Sequence[int], tangent_keys: Sequence[int] = ()) -> None:
        self.a = np.asarray(a, np.float64)
        self.y = np.asarray(y, np.float64)
        n1 = len(self.y)
        ks = np.asarray(keys, np.intp)
        if n1 < 2 or self.a.shape != (n1,) or self.y.shape != (n1,) or not (
                np.isfinite(self.a).all() and np.isfinite(self.y).all()) or np.any(np.diff(self.a) < 0):
            raise ValueError("heights and arclengths are (n+1,) finite values, the arclength non-decreasing")
        if len(ks) < 2 or ks[0] != 0 or ks[-1] != n1 - 1 or np.any(np.diff(ks) <= 0):
            raise ValueError("handle keys must increase from the first key to the last")
        tk = sorted({int(k) for k in tangent_keys})
        if any(k not in set(ks.tolist()) or k in (0, n1 - 1) for k in tk):
            raise ValueError("tangent keys must be interior handle keys")
        self.keys: IntArray = ks
        handles = set(ks.tolist())
        tk = [h for h in tk if h - 1 not in handles and h + 1 not in handles]   # a neighbour handle decides
        # variables: one per key, except that a kept tangent ties key h+1 to key h-1
        var = np.arange(n1)
        for h in tk:
            var[h + 1] = var[h - 1]
        self._var = var
        self._tangents = tk
        self._factor(n1)

    def _factor(self, n1: int) -> None:
        a, y = self.a, self.y
        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        r = 0
        for i in range(1, n1 - 1):
            lo, hi = frame_keys(a[:, None], i)
            da = a[hi] - a[lo]
            dist = max(float(np.hypot(da, y[hi] - y[lo])), STILL_M)
            u = (a[i] - a[lo]) / da if da > 0 else 0.5
            w = 1.0 / np.sqrt(dist)
            rows += [r, r, r]
            cols += [int(self._var[i]), int(self._var[lo]), int(self._var[hi])]
            vals += [w, -(1 - u) * w, -u * w]
            r += 1
        m = coo_matrix((vals, (rows, cols)), shape=(max(r, 1), n1)).tocsc()   # duplicates are summed
        fixed = np.zeros(n1, bool)
        fixed[self._var[self.keys]] = True
        used = np.zeros(n1, bool)
        used[self._var] = True
        self._free = np.flatnonzero(used & ~fixed)
        self._fixed = np.flatnonzero(used & fixed)
        mf, mh = m[:, self._free], m[:, self._fixed]
        self._coupling = (mf.T @ mh).tocsc()
        self._normal = (mf.T @ mf).tocsc()
        self._lu = splu(self._normal) if len(self._free) else None

    def solve(self, lifts: FloatArray) -> FloatArray:
        """The edited heights with each handle lifted by ``lifts`` ``(len(keys),)`` (metres, from its
        original height)."""
        d = np.asarray(lifts, np.float64)
        if d.shape != (len(self.keys),) or not np.isfinite(d).all():
            raise ValueError(f"lifts are {len(self.keys)} finite values, one per handle")
        x = np.zeros(len(self.y))
        x[self._var[self.keys]] = d
        dh = x[self._fixed]
        if self._lu is not None and np.any(dh):
            rhs = -(self._coupling @ dh)
            z = self._lu.solve(rhs)
            for _ in range(REFINE_STEPS):
                res = rhs - self._normal @ z
                if not np.abs(res).max() > 1e-15 * max(float(np.abs(rhs).max()), 1e-300):
                    break
                z += self._lu.solve(res)
            x[self._free] = z
        out: FloatArray = self.y + x[self._var]
        return out


__all__ = ["VerticalPath"]
