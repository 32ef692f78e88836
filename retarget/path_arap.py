"""The horizontal path deformation of path editing (``docs/design/path-editing.md`` sections 1.3-1.4): the
modified two-stage as-rigid-as-possible solve that bends a root path to its handles, so strides bend rather
than stretch, and the per-segment scale that keeps each segment's arclength.

* **Stage 1, scale-free.** Every interior key is written in the frame of its two neighbours,
  ``p_i = p_{i-1} + u_i d_i + v_i R90 d_i`` with ``d_i = p_{i+1} - p_{i-1}``; the edited path keeps those
  coordinates as well as it can, in least squares weighted ``1 / |d_i|``, with the handles fixed. The
  solve is for the displacement from the original path, so unmoved handles give exactly the original.
  Its normal matrix depends only on the path and the handle keys: factored once (``scipy``'s sparse LU),
  each handle move is one re-solve.
* **Stage 2, scale-adjusted.** Between two consecutive handles the edges take the stage-1 directions at
  the original lengths times a scale ``s``, and the chord's mismatch is spread along the segment in
  proportion to the original edge lengths (the closed form of the weighted least squares with the
  handles fixed, weights ``1 / |e_i|`` of the original edges).
* **The scale** of each segment is found so that its edited arclength equals ``s`` times its original
  one (so ``s = 1`` for an untouched or rigidly moved segment): a safeguarded Newton search from
  ``s = 1``, floored at ``S_MIN``.

Where the path stands still (neighbours closer than ``STILL_M``), a key is framed by the nearest keys on
either side that are that far apart, so standing frames neither blow up the weights nor break the
solve's invariance to rotating and moving the whole path.
Ballistic spans (flights) are not yet given their similarity constraint here (the design note's next step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import splu

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray, IntArray

#: below this, a key's neighbours are too close to give it a frame, m
STILL_M = 1e-3
#: framing keys closer than this are one point: the key keeps their midpoint's displacement instead, m
DEGENERATE_M = 1e-6
#: the smallest scale a segment is given (handles dragged onto each other)
S_MIN = 0.05
#: the scale search stops when the arclength is this close, in parts of the segment's length
S_TOL = 1e-9
MAX_ITER = 50
#: iterative refinement of the stage-1 solve (the normal matrix of a long path is ill-conditioned)
REFINE_STEPS = 3


@dataclass(frozen=True)
class Solved:
    """A deformed path: ``path`` ``(n+1, 2)``, the scale and search iterations of each segment between
    consecutive handles, and whether a segment's scale hit ``S_MIN``."""

    path: FloatArray
    scales: tuple[float, ...]
    iterations: tuple[int, ...]
    floored: tuple[bool, ...]


def _rot90(a: FloatArray) -> FloatArray:
    """``R90 a`` with ``R90 = [[0, 1], [-1, 0]]``, row-wise."""
    return np.stack([a[..., 1], -a[..., 0]], axis=-1)


def frame_keys(points: FloatArray, i: int) -> tuple[int, int]:
    """The keys that frame key ``i`` of ``points`` ``(n+1, d)``: its neighbours, or, where the path stands
    still, on each side the nearest key at least ``STILL_M / 2`` from it (clipped to the path's ends), so no
    two keys are ever framed as the same point (which would leave them tied to each other only)."""
    n = len(points) - 1
    lo = i - 1
    while lo > 0 and float(np.linalg.norm(points[i] - points[lo])) < STILL_M / 2:
        lo -= 1
    hi = i + 1
    while hi < n and float(np.linalg.norm(points[hi] - points[i])) < STILL_M / 2:
        hi += 1
    return lo, hi


class HorizontalPath:
    """A root path ``p`` ``(n+1, 2)`` (x, z) with handles at ``keys``, prepared for repeated solves.

    Raises:
        ValueError: fewer than two keys, handle keys not strictly increasing within the path, or the
            first and last keys not among them.
    """

    def __init__(self, p: FloatArray, keys: Sequence[int]) -> None:
        self.p = np.asarray(p, np.float64)
        n1 = len(self.p)
        ks = np.asarray(keys, np.intp)
        if n1 < 2 or self.p.shape != (n1, 2) or not np.isfinite(self.p).all():
            raise ValueError("a path is (n+1, 2) finite points, at least two")
        if len(ks) < 2 or ks[0] != 0 or ks[-1] != n1 - 1 or np.any(np.diff(ks) <= 0):
            raise ValueError("handle keys must increase from the first key to the last")
        self.keys: IntArray = ks
        self._factor(n1)

    def _factor(self, n1: int) -> None:
        p = self.p
        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        r = 0
        for i in range(1, n1 - 1):
            lo, hi = frame_keys(p, i)
            d = p[hi] - p[lo]
            dn = float(np.hypot(*d))
            if dn < DEGENERATE_M:   # its framing keys coincide (all of the path still): their midpoint
                w = 1.0 / np.sqrt(STILL_M)
                for c in (0, 1):
                    rows += [r + c] * 3
                    cols += [2 * i + c, 2 * lo + c, 2 * hi + c]
                    vals += [w, -0.5 * w, -0.5 * w]
                r += 2
                continue
            e = p[i] - p[lo]
            u = float(e @ d) / dn**2
            v = float(e @ _rot90(d)) / dn**2
            w = 1.0 / np.sqrt(max(dn, STILL_M))
            # r_x = x_i - (1-u) x_lo - u x_hi - v (z_hi - z_lo)
            # r_z = z_i - (1-u) z_lo - u z_hi + v (x_hi - x_lo)
            ix, iz, ax, az, bx, bz = 2 * i, 2 * i + 1, 2 * lo, 2 * lo + 1, 2 * hi, 2 * hi + 1
            rows += [r] * 5
            cols += [ix, ax, bx, bz, az]
            vals += [w, -(1 - u) * w, -u * w, -v * w, v * w]
            rows += [r + 1] * 5
            cols += [iz, az, bz, bx, ax]
            vals += [w, -(1 - u) * w, -u * w, v * w, -v * w]
            r += 2
        m = coo_matrix((vals, (rows, cols)), shape=(max(r, 1), 2 * n1)).tocsc()
        fixed = np.zeros(2 * n1, bool)
        fixed[2 * self.keys] = True
        fixed[2 * self.keys + 1] = True
        self._free = np.flatnonzero(~fixed)
        self._fixed = np.flatnonzero(fixed)
        mf, mh = m[:, self._free], m[:, self._fixed]
        self._coupling = (mf.T @ mh).tocsc()
        self._normal = (mf.T @ mf).tocsc()
        self._lu = splu(self._normal) if len(self._free) else None

    def stage1(self, targets: FloatArray) -> FloatArray:
        """The scale-free path with the handles at ``targets`` ``(len(keys), 2)``."""
        t = np.asarray(targets, np.float64)
        delta = np.zeros(self.p.size)
        dh = (t - self.p[self.keys]).reshape(-1)
        delta[self._fixed] = dh
        if self._lu is not None and np.any(dh):
            rhs = -(self._coupling @ dh)
            z = self._lu.solve(rhs)
            for _ in range(REFINE_STEPS):   # the normal matrix of a long chain is ill-conditioned
                res = rhs - self._normal @ z
                if not np.abs(res).max() > 1e-15 * max(float(np.abs(rhs).max()), 1e-300):
                    break
                z += self._lu.solve(res)
            delta[self._free] = z
        out: FloatArray = self.p + delta.reshape(self.p.shape)
        return out

    def solve(self, targets: FloatArray, scales: Sequence[float | None] | None = None) -> Solved:
        """The deformed path with the handles at ``targets``: stage 1, then stage 2 per segment at its
        automatic scale (or at the scale given for it in ``scales``, ``None`` meaning automatic)."""
        t = np.asarray(targets, np.float64)
        pb = self.stage1(t)
        out = np.empty_like(self.p)
        out[self.keys] = t
        ss, its, floors = [], [], []
        for k, (a, b) in enumerate(zip(self.keys[:-1].tolist(), self.keys[1:].tolist(), strict=True)):
            seg = _Segment(self.p[a:b + 1], pb[a:b + 1], t[k + 1] - t[k])
            given = scales[k] if scales is not None else None
            s, it = (float(given), 0) if given is not None else seg.scale()
            floored = s < S_MIN
            s = max(s, S_MIN)
            out[a + 1:b] = t[k] + np.cumsum(seg.edges(s), axis=0)[:-1]
            ss.append(s)
            its.append(it)
            floors.append(floored)
        return Solved(out, tuple(ss), tuple(its), tuple(floors))


class _Segment:
    """Stage 2 on the keys between two handles: ``x_i(s) = s eb_i + |e_i| (C - s sum eb) / L0``."""

    def __init__(self, p: FloatArray, pb: FloatArray, chord: FloatArray) -> None:
        e = np.diff(p, axis=0)
        self.len = np.hypot(e[:, 0], e[:, 1])
        self.l0 = float(self.len.sum())
        eb = np.diff(pb, axis=0)
        nb = np.hypot(eb[:, 0], eb[:, 1])
        unit = np.where(nb[:, None] > 1e-12, eb / np.maximum(nb, 1e-300)[:, None],
                        e / np.maximum(self.len, 1e-300)[:, None])
        self.eb = unit * self.len[:, None]
        self.chord = np.asarray(chord, np.float64)
        w = self.len / self.l0 if self.l0 > 0 else np.full(len(self.len), 1.0 / max(len(self.len), 1))
        self.w = w
        self.base = w[:, None] * self.chord                     # x at s = 0
        self.slope = self.eb - w[:, None] * self.eb.sum(axis=0)  # dx/ds

    def edges(self, s: float) -> FloatArray:
        out: FloatArray = self.base + s * self.slope
        return out

    def f(self, s: float) -> tuple[float, float]:
        x = self.edges(s)
        nx = np.hypot(x[:, 0], x[:, 1])
        fs = float(nx.sum()) - s * self.l0
        with np.errstate(invalid="ignore", divide="ignore"):
            df = float(np.sum(np.where(nx > 0, np.einsum("ij,ij->i", x, self.slope) / nx, 0.0))) - self.l0
        return fs, df

    def scale(self) -> tuple[float, int]:
        """The ``s`` with edited arclength ``s L0`` (Newton from 1 inside a bisection bracket), iterations."""
        if self.l0 <= 0:
            return 1.0, 0
        tol = S_TOL * self.l0
        f1, d1 = self.f(1.0)
        if abs(f1) <= tol:
            return 1.0, 0
        lo, hi = 0.0, 1.0   # f(0) = |C| >= 0 and f is convex: the root is past the last point where f >= 0
        if f1 > 0:
            lo = 1.0
            hi = 2.0
            while self.f(hi)[0] > 0 and hi < 1e6:
                hi *= 2
        s, fs, ds = 1.0, f1, d1
        for it in range(1, MAX_ITER + 1):
            step = s - fs / ds if ds < 0 else 0.5 * (lo + hi)
            s = step if lo < step < hi else 0.5 * (lo + hi)
            fs, ds = self.f(s)
            if abs(fs) <= tol:
                return s, it
            if fs > 0:
                lo = s
            else:
                hi = s
        return s, MAX_ITER


__all__ = ["STILL_M", "S_MIN", "HorizontalPath", "Solved", "frame_keys"]
