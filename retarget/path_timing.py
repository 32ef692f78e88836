"""The timewarp of path editing (``docs/design/path-editing.md`` section 1.6): new key times after the path
was edited, so a longer stride is taken faster and the walk's timing follows the edit as a walker's would.

* **Stride law.** Froude number ``Fr = v^2 / (g L)`` and Alexander's stride law ``lambda / L = 2.3 Fr^0.3``
  give, for stride lengths scaled by ``sigma``, the speed ``v_Fr = sigma^(5/3) v``. The speed a key is
  given combines it with the turning law's (``v_kappa``, from the turns step, 1 when there is none) as
  ``v_new = v_Fr^0.5 v_kappa^0.5``: a speed ratio ``rho = sigma^(5/6) kappa_ratio^(1/2)``.
* **Stride ratio per key.** Each segment's scale (from the horizontal solve) is placed at its midpoint in
  original arclength and interpolated over the keys with a natural cubic spline, held beyond the first
  and last midpoints and floored at ``SIGMA_MIN``.
* **New times.** Each key's central time span becomes ``c_i = (t_{i+1} - t_{i-1}) g_i / rho_i`` with
  ``g_i`` the ratio of the edited to the original central distance (so a key moved twice as far at the
  same speed takes twice as long). The new time steps are the least squares fit of their central sums to
  ``c`` with a small smoothness term (``MU``) against the odd/even mode central sums leave free; keys
  slower than ``V_MIN`` keep their timing, and no step falls below ``STEP_MIN`` of the original. The
  matrix depends only on the original times (factored once); unchanged spans give the original times.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import splu

if TYPE_CHECKING:
    from collections.abc import Sequence

    from retarget._types import FloatArray

#: the combination weights of the stride and turning laws (the thesis's beta, 0.5 each)
BETA = 0.5
#: Alexander's exponent makes speed go as stride^(5/3)
STRIDE_SPEED_EXP = 5.0 / 3.0
SIGMA_MIN = 0.05
#: keys slower than this (m/s) keep their timing, blended in below it
V_MIN = 0.05
#: no new time step is shorter than this part of the original one
STEP_MIN = 0.05
MU = 1e-3


def froude(v: float, leg: float, g: float = 9.81) -> float:
    """The Froude number of walking at ``v`` m/s on legs ``leg`` m long."""
    return v * v / (g * leg)


def alexander_stride(v: float, leg: float, g: float = 9.81) -> float:
    """Alexander's stride length at speed ``v``: ``2.3 L Fr^0.3`` (m)."""
    return float(2.3 * leg * froude(v, leg, g) ** 0.3)


def stride_ratio_per_key(arclength: FloatArray, keys: Sequence[int], scales: Sequence[float]) -> FloatArray:
    """``(n+1,)``: each segment's scale at its midpoint in the original arclength ``arclength``, between
    consecutive handle ``keys``, interpolated over every key (natural cubic spline, held at the ends,
    floored at ``SIGMA_MIN``).

    Raises:
        ValueError: a scale per segment is not given, or the arclength is not non-decreasing.
    """
    a = np.asarray(arclength, np.float64)
    ks = list(keys)
    if len(scales) != len(ks) - 1:
        raise ValueError(f"{len(ks) - 1} segments but {len(scales)} scales")
    if np.any(np.diff(a) < 0):
        raise ValueError("the arclength must not decrease")
    mids = np.array([(a[i] + a[j]) / 2 for i, j in itertools.pairwise(ks)])
    s = np.asarray(scales, np.float64)
    keep = np.concatenate([[True], np.diff(mids) > 1e-9])   # segments of no length share a knot
    mids, s = mids[keep], s[keep]
    if len(mids) < 2:
        return np.full(len(a), max(float(s[0]), SIGMA_MIN))
    spline = CubicSpline(mids, s, bc_type="natural")
    out = spline(np.clip(a, mids[0], mids[-1]))
    result: FloatArray = np.maximum(out, SIGMA_MIN)
    return result


@dataclass(frozen=True)
class Warped:
    """New key times (``times[0] = 0``), and how many steps the floor ``STEP_MIN`` held."""

    times: FloatArray
    clamped: int


class TimeWarp:
    """The time solve of a clip with key times ``t`` ``(n+1,)`` (increasing), factored once.

    Raises:
        ValueError: fewer than three keys or times that do not increase.
    """

    def __init__(self, t: FloatArray) -> None:
        self.t = np.asarray(t, np.float64)
        n1 = len(self.t)
        dt = np.diff(self.t)
        if n1 < 3 or np.any(dt <= 0) or not np.isfinite(self.t).all():
            raise ValueError("key times must be finite and increase, at least three of them")
        self.dt = dt
        n = n1 - 1
        rows: list[int] = []
        cols: list[int] = []
        vals: list[float] = []
        r = 0
        rows += [0]
        cols += [0]
        vals += [1.0]           # the first step, one-sided
        r = 1
        for i in range(1, n):   # central sums: dth_{i-1} + dth_i = c_i
            rows += [r, r]
            cols += [i - 1, i]
            vals += [1.0, 1.0]
            r += 1
        rows += [r]
        cols += [n - 1]
        vals += [1.0]           # the last step, one-sided
        r += 1
        w = np.sqrt(MU) * float(dt.mean())
        for i in range(1, n):   # smoothness of the steps relative to the original ones
            rows += [r, r]
            cols += [i, i - 1]
            vals += [w / dt[i], -w / dt[i - 1]]
            r += 1
        self._m = coo_matrix((vals, (rows, cols)), shape=(r, n)).tocsc()
        self._normal = (self._m.T @ self._m).tocsc()
        self._lu = splu(self._normal)
        self._n = n

    def solve(self, p: FloatArray, ph: FloatArray, rho: FloatArray) -> Warped:
        """New times for a path edited from ``p`` to ``ph`` (``(n+1, d)``, horizontal positions) with speed
        ratios ``rho`` ``(n+1,)`` per key.

        Raises:
            ValueError: shapes that do not match the times, or speed ratios that are not finite and > 0.
        """
        p, ph, rho = (np.asarray(x, np.float64) for x in (p, ph, rho))
        n = self._n
        if len(p) != n + 1 or ph.shape != p.shape or rho.shape != (n + 1,):
            raise ValueError("the paths and ratios must have one row per key")
        if not (np.isfinite(rho).all() and (rho > 0).all()):
            raise ValueError("speed ratios must be finite and > 0")
        t, dt = self.t, self.dt
        d_old = np.linalg.norm(p[2:] - p[:-2], axis=1)
        d_new = np.linalg.norm(ph[2:] - ph[:-2], axis=1)
        span = t[2:] - t[:-2]
        v_old = d_old / span
        g = np.where(d_old > 1e-12, d_new / np.maximum(d_old, 1e-12), 1.0)
        c = span * g / rho[1:-1]
        lam = np.clip(v_old / V_MIN, 0.0, 1.0)          # slow keys keep their timing
        c = lam * c + (1 - lam) * span
        e0 = _end_step(dt[0], p[0], p[1], ph[0], ph[1], float(rho[0]))
        e1 = _end_step(dt[-1], p[-2], p[-1], ph[-2], ph[-1], float(rho[-1]))
        rhs = np.concatenate([[e0], c, [e1], np.zeros(n - 1)])
        b = self._m.T @ rhs
        step = self._lu.solve(b)
        for _ in range(3):
            res = b - self._normal @ step
            if not np.abs(res).max() > 1e-15 * max(float(np.abs(b).max()), 1e-300):
                break
            step += self._lu.solve(res)
        floor = STEP_MIN * dt
        clamped = int(np.sum(step < floor))
        step = np.maximum(step, floor)
        out: FloatArray = np.concatenate([[0.0], np.cumsum(step)])
        return Warped(out, clamped)


def _end_step(dt: float, a: FloatArray, b: FloatArray, ah: FloatArray, bh: FloatArray, rho: float) -> float:
    """The target of a clip's first or last time step, as for a central span: stretched with its step,
    divided by its speed ratio, kept as it was where the key is slow."""
    d = float(np.linalg.norm(b - a))
    stretch = float(np.linalg.norm(bh - ah)) / d if d > 1e-12 else 1.0
    lam = min(max(d / dt / V_MIN, 0.0), 1.0)
    return lam * dt * stretch / rho + (1 - lam) * dt


def speed_ratio(sigma: FloatArray, kappa_ratio: FloatArray | None = None) -> FloatArray:
    """``rho = (sigma^(5/3))^BETA * kappa_ratio^BETA``: the speed ratio of keys whose stride is scaled by
    ``sigma``, on a path whose turning law asks ``kappa_ratio`` (1 without turns)."""
    s = np.asarray(sigma, np.float64)
    k = np.ones_like(s) if kappa_ratio is None else np.asarray(kappa_ratio, np.float64)
    out: FloatArray = (s ** STRIDE_SPEED_EXP) ** BETA * k ** BETA
    return out


__all__ = ["BETA", "TimeWarp", "Warped", "alexander_stride", "froude", "speed_ratio", "stride_ratio_per_key"]
