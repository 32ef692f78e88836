"""From phone input to blend-space parameters: linear axes, the probe lookup table, smoothing.

This module owns the animation-blending mappings of Ciccone 2019, *Intuitive Control of Animated Scenes*
(ETH Diss. 25792), section 6.2.3 (the linear height mapping, the probe lookup table with inverse distance
weighting, eq. 6.1-6.2 with q = 7, and the speed-up for input beyond the feasible set). The grid size,
the log-space weights, the exact-hit tolerance, the 2-D border and the input smoothing are perfcap's
(``docs/design/puppet.md``):

* ``AxisMap``: the linear mapping ``p(u) = (u - a) / (b - a)`` clamped to [0, 1] (e.g. the phone's height
  to the crouch parameter ``p_height``; ``a`` and ``b`` are calibration values).
* ``idw``: inverse distance weighting, eq. 6.1-6.2, ``p(u) = sum w_k p*_k / sum w_k`` with
  ``w_k = d(u, u*_k)^-q``; a distance below 1e-12 is an exact hit and returns that probe (the mean of the
  probes hit when several share a ``u*``). The weights are computed in log space (``-q ln d`` minus its
  maximum), so ``d^-7`` cannot overflow or underflow to all zeros.
* ``ProbeTable``: the probe lookup table for the nonlinear speed axis. Probes ``p*_k`` sit on a grid over
  the blend space ``(p_vel, p_height)`` (21 x 21 by default); ``u*_k = (speed, p_height)`` where the speed
  is measured by a caller-supplied function (the root speed of the blended motion). The table lives in
  2-D u-space with the speed normalised by the largest measured speed ``v_max``. Inputs outside the
  feasible set are projected onto its border (the polyline of the ``p_vel = 1`` probes, plus the clamps of
  ``p_height`` to [0, 1]); the border point's parameters are known exactly (``p_vel = 1``, ``p_height`` the
  point's height), and the clip is played faster by ``u_vel / u'_vel`` (>= 1, exactly 1 inside).
* ``OneEuroFilter``: per-axis smoothing of the raw inputs (Casiez et al. 2012, the "1-euro filter"): a
  first-order low-pass whose cutoff rises with the input's speed of change, ``fc = min_cutoff +
  beta |dx/dt|``, so a still phone gives a steady parameter and a fast move little lag. Time comes from the
  caller; nothing here reads a clock.
* ``PuppetMapping``: the bundle the puppet uses each frame: smooth (speed, height), map the height with an
  ``AxisMap``, look the pair up in the ``ProbeTable``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from collections.abc import Callable

    from retarget._types import FloatArray

__all__ = [
    "EXACT_HIT",
    "AxisMap",
    "BlendQuery",
    "OneEuroFilter",
    "ProbeTable",
    "PuppetMapping",
    "idw",
]

#: Distances below this count as an exact hit of a probe.
EXACT_HIT = 1e-12
#: Inputs this close outside the border (normalised u-space) count as on it: rounding, not a projection.
_BORDER_TOL = 1e-12


@dataclass(frozen=True, slots=True)
class AxisMap:
    """The linear map ``p(u) = (u - a) / (b - a)``, clamped to [0, 1].

    ``a`` maps to 0 and ``b`` to 1; ``b < a`` gives a decreasing map.

    Args:
        a: the input value that maps to 0.
        b: the input value that maps to 1.

    Raises:
        ValueError: ``a == b`` or a non-finite bound.
    """

    a: float
    b: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.a) and math.isfinite(self.b)):
            raise ValueError(f"AxisMap bounds must be finite, got a={self.a!r}, b={self.b!r}")
        if self.a == self.b:
            raise ValueError(f"AxisMap needs a != b, got a = b = {self.a!r}")

    def __call__(self, u: float) -> float:
        """Map one input value to [0, 1].

        Raises:
            ValueError: ``u`` is NaN.
        """
        if math.isnan(u):
            raise ValueError("AxisMap input is NaN")
        p = (u - self.a) / (self.b - self.a)
        return 0.0 if p <= 0.0 else (1.0 if p >= 1.0 else float(p))

    def map_array(self, u: object) -> FloatArray:
        """Map an array of inputs to [0, 1] element-wise.

        Raises:
            ValueError: the array holds NaN.
        """
        arr = np.asarray(u, dtype=float)
        if np.any(np.isnan(arr)):
            raise ValueError("AxisMap input holds NaN")
        return np.clip((arr - self.a) / (self.b - self.a), 0.0, 1.0)


def idw(u: object, probes_u: object, probes_p: object, q: float = 7.0) -> FloatArray:
    """Inverse distance weighting of probe parameters (eq. 6.1-6.2), computed in log space.

    Args:
        u: one query ``(N,)`` or several ``(M, N)`` in the probes' u-space.
        probes_u: ``(K, N)`` probe positions ``u*_k`` in u-space.
        probes_p: ``(K, P)`` probe parameters ``p*_k``.
        q: the power (> 0); the thesis uses 7.

    Returns:
        ``(P,)`` for one query, ``(M, P)`` for several. An exact hit (``d < EXACT_HIT``) returns that probe's
        parameters (the mean over the probes hit); equidistant probes get equal weights, so their mean.

    Raises:
        ValueError: mismatched shapes, no probes, non-finite values or ``q <= 0``.
    """
    uu = np.asarray(u, dtype=float)
    pu = np.asarray(probes_u, dtype=float)
    pp = np.asarray(probes_p, dtype=float)
    if not (q > 0.0 and math.isfinite(q)):
        raise ValueError(f"q must be finite and > 0, got {q!r}")
    if pu.ndim != 2 or pp.ndim != 2 or pu.shape[0] != pp.shape[0] or pu.shape[0] == 0:
        raise ValueError(f"need probes_u (K, N) and probes_p (K, P) with K > 0, got {pu.shape}, {pp.shape}")
    single = uu.ndim == 1
    queries = uu[None, :] if single else uu
    if queries.ndim != 2 or queries.shape[1] != pu.shape[1]:
        raise ValueError(f"query shape {uu.shape} does not match probes of dimension {pu.shape[1]}")
    if not (np.all(np.isfinite(queries)) and np.all(np.isfinite(pu)) and np.all(np.isfinite(pp))):
        raise ValueError("idw inputs must be finite")
    out = _idw_rows(queries, pu, pp, float(q))
    return out[0] if single else out


def _idw_one(u: FloatArray, pu: FloatArray, pp: FloatArray, q: float) -> FloatArray:
    """IDW of one ``(N,)`` query without argument checks (the per-frame path; same result as ``_idw_rows``)."""
    diff = pu - u
    d2 = np.einsum("ij,ij->i", diff, diff)
    k = int(d2.argmin())
    if d2[k] < EXACT_HIT * EXACT_HIT:
        return np.asarray(pp[d2 < EXACT_HIT * EXACT_HIT].mean(axis=0), dtype=float)
    lw = np.log(d2)
    lw = (lw[k] - lw) * (0.5 * q)  # -q ln d_k minus its maximum (at the nearest probe)
    w = np.exp(lw)
    return np.asarray((w @ pp) / w.sum(), dtype=float)


def _idw_rows(queries: FloatArray, pu: FloatArray, pp: FloatArray, q: float) -> FloatArray:
    """IDW of ``(M, N)`` queries without argument checks (``w = d^-q`` as ``exp(-q/2 ln d^2)``)."""
    d2 = np.zeros((queries.shape[0], pu.shape[0]))
    for axis in range(pu.shape[1]):
        diff = pu[:, axis][None, :] - queries[:, axis][:, None]
        d2 += diff * diff
    exact = d2 < EXACT_HIT * EXACT_HIT
    lw = np.log(np.maximum(d2, EXACT_HIT * EXACT_HIT))
    lw *= -0.5 * q
    lw -= lw.max(axis=1, keepdims=True)
    w = np.exp(lw)
    hit_rows = exact.any(axis=1)
    if hit_rows.any():
        w[hit_rows] = exact[hit_rows].astype(float)
    return np.asarray((w @ pp) / w.sum(axis=1, keepdims=True), dtype=float)


@dataclass(frozen=True, slots=True)
class BlendQuery:
    """One lookup's result.

    Attributes:
        p_vel: blend parameter of the speed axis, in [0, 1].
        p_height: blend parameter of the height axis, in [0, 1].
        speedup: playback-rate factor ``u_vel / u'_vel`` (>= 1; exactly 1 inside the feasible set).
        speed: the speed looked up, m/s (after smoothing, when the mapping smooths).
        height: the height parameter looked up (clamped to [0, 1]).
        projected: True when the input was outside the feasible set and projected onto its border.
    """

    p_vel: float
    p_height: float
    speedup: float
    speed: float
    height: float
    projected: bool


class ProbeTable:
    """The probe lookup table from (speed, height parameter) to blend parameters ``(p_vel, p_height)``.

    Probe ``(i, j)`` sits at ``p* = (i / (n_vel - 1), j / (n_height - 1))``; its u-space point is
    ``u* = (speeds[i, j] / v_max, p_height)`` where ``v_max`` is the largest measured speed.

    Args:
        speeds: ``(n_vel, n_height)`` measured root speeds (m/s) of the blended motion at each probe.
        q: IDW power (the thesis uses 7).

    Raises:
        ValueError: fewer than 2 probes per axis, negative or non-finite speeds, no motion at all, or a
            ``p_vel = 1`` probe that does not move (the border must have a speed to scale by).
    """

    def __init__(self, speeds: object, *, q: float = 7.0) -> None:
        s = np.asarray(speeds, dtype=float)
        if s.ndim != 2 or s.shape[0] < 2 or s.shape[1] < 2:
            raise ValueError(f"speeds must be a (n_vel, n_height) grid with n >= 2, got shape {s.shape}")
        if not np.all(np.isfinite(s)) or np.any(s < 0.0):
            raise ValueError("probe speeds must be finite and >= 0")
        if not (q > 0.0 and math.isfinite(q)):
            raise ValueError(f"q must be finite and > 0, got {q!r}")
        if np.any(s[-1] <= 0.0):
            raise ValueError("every p_vel = 1 probe must move (speed > 0): the border is undefined otherwise")
        n_vel, n_height = s.shape
        self.q = float(q)
        self.speeds = s.copy()
        self.speeds.setflags(write=False)
        self.v_max = float(s.max())
        pv, ph = np.meshgrid(np.linspace(0.0, 1.0, n_vel), np.linspace(0.0, 1.0, n_height), indexing="ij")
        #: (K, 2) probe blend parameters p*_k, K = n_vel * n_height, row-major over (i, j).
        self.probes_p = np.column_stack([pv.ravel(), ph.ravel()])
        #: (K, 2) probe positions u*_k in normalised u-space (speed / v_max, p_height).
        self.probes_u = np.column_stack([s.ravel() / self.v_max, ph.ravel()])
        #: (n_height, 2) the border polyline: the p_vel = 1 probes in normalised u-space, by height.
        self.border = np.column_stack([s[-1] / self.v_max, np.linspace(0.0, 1.0, n_height)])
        self._seg_a = self.border[:-1]
        self._seg_d = self.border[1:] - self.border[:-1]
        self._seg_dd = np.einsum("kn,kn->k", self._seg_d, self._seg_d)
        for arr in (self.probes_p, self.probes_u, self.border):
            arr.setflags(write=False)

    @classmethod
    def measure(cls, speed_of: Callable[[float, float], float], *, n: int = 21, q: float = 7.0) -> ProbeTable:
        """Build the table by measuring each probe of an ``n x n`` grid.

        Args:
            speed_of: ``speed_of(p_vel, p_height)``: the root speed (m/s) of the motion blended at those
                parameters, e.g. measured by playing it.
            n: probes per axis (perfcap's default 21; the thesis asks only for a dense enough grid).
            q: IDW power.

        Returns:
            The table.

        Raises:
            ValueError: ``n < 2``, or bad measured speeds (see the class).
        """
        if n < 2:
            raise ValueError(f"need at least 2 probes per axis, got {n}")
        grid = np.linspace(0.0, 1.0, n)
        speeds = np.array([[float(speed_of(float(pv), float(ph))) for ph in grid] for pv in grid])
        return cls(speeds, q=q)

    def normalise(self, speed: float, height: float) -> tuple[float, float]:
        """The u-space point of an input: ``(speed / v_max, height clamped to [0, 1])``."""
        return speed / self.v_max, min(1.0, max(0.0, height))

    def border_speed(self, height: float) -> float:
        """The largest feasible speed (m/s) at a height parameter: the border polyline at that height."""
        h = min(1.0, max(0.0, height))
        return float(np.interp(h, self.border[:, 1], self.border[:, 0])) * self.v_max

    def lookup(self, speed: object, height: object) -> FloatArray:
        """Plain IDW lookup without projection (vectorised).

        Args:
            speed: speed(s) in m/s.
            height: height parameter(s), clamped to [0, 1].

        Returns:
            ``(2,)`` or ``(M, 2)`` blend parameters ``(p_vel, p_height)``.

        Raises:
            ValueError: non-finite inputs or mismatched shapes.
        """
        sp = np.asarray(speed, dtype=float)
        hp = np.clip(np.asarray(height, dtype=float), 0.0, 1.0)
        if sp.shape != hp.shape:
            raise ValueError(f"speed and height shapes differ: {sp.shape} vs {hp.shape}")
        u = np.stack([sp / self.v_max, hp], axis=-1)
        return idw(u, self.probes_u, self.probes_p, self.q)

    def project(self, speed: float, height: float) -> tuple[float, float, bool]:
        """Project an input onto the feasible set.

        Args:
            speed: m/s.
            height: height parameter (clamped to [0, 1]).

        Returns:
            ``(u'_vel, u'_height, projected)`` in normalised u-space; the input itself when it is inside.
        """
        uv, uh = self.normalise(speed, height)
        if uv <= float(np.interp(uh, self.border[:, 1], self.border[:, 0])) + _BORDER_TOL:
            return uv, uh, False
        rel = np.array([uv, uh]) - self._seg_a
        t = np.clip(np.einsum("kn,kn->k", rel, self._seg_d) / self._seg_dd, 0.0, 1.0)
        foot = self._seg_a + t[:, None] * self._seg_d
        off = foot - (uv, uh)
        k = int(np.argmin(np.einsum("kn,kn->k", off, off)))
        return float(foot[k, 0]), float(foot[k, 1]), True

    def query(self, speed: float, height: float) -> BlendQuery:
        """Blend parameters and playback factor for one input.

        Inside the feasible set: IDW over the probes, factor 1. Outside: the nearest point ``u'`` on the
        border, whose parameters are ``(1, u'_height)``, and the factor ``u_vel / u'_vel``.

        Args:
            speed: the input speed, m/s (>= 0).
            height: the height parameter (clamped to [0, 1]).

        Returns:
            The ``BlendQuery``.

        Raises:
            ValueError: a negative or non-finite speed or a non-finite height.
        """
        if not (math.isfinite(speed) and speed >= 0.0):
            raise ValueError(f"speed must be finite and >= 0, got {speed!r}")
        if not math.isfinite(height):
            raise ValueError(f"height must be finite, got {height!r}")
        pv, ph, projected = self.project(speed, height)
        h_in = min(1.0, max(0.0, height))
        if not projected:
            p = _idw_one(np.array([pv, ph]), self.probes_u, self.probes_p, self.q)
            return BlendQuery(float(p[0]), float(p[1]), 1.0, float(speed), h_in, False)
        # A border that bulges could put the nearest point at a higher speed; never slow the clip down.
        speedup = max(1.0, speed / (pv * self.v_max))
        return BlendQuery(1.0, ph, speedup, float(speed), h_in, True)


class OneEuroFilter:
    """The 1-euro filter (Casiez, Roussel, Vogel, CHI 2012) for one scalar axis.

    ``x_hat = x_hat_prev + alpha (x - x_hat_prev)`` with ``alpha = 1 / (1 + tau / dt)``, ``tau = 1 / (2 pi
    fc)`` and ``fc = min_cutoff + beta |dx_hat/dt|``, the derivative itself low-passed at ``d_cutoff``. Low
    speeds get a low cutoff (jitter removed), fast moves a high one (little lag).

    Args:
        min_cutoff: cutoff at rest, Hz (> 0).
        beta: how fast the cutoff rises with the speed of change (>= 0; 0 is a fixed low-pass).
        d_cutoff: cutoff of the derivative's low-pass, Hz (> 0).

    Raises:
        ValueError: a non-positive cutoff or a negative beta.
    """

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0) -> None:
        if not (min_cutoff > 0.0 and d_cutoff > 0.0 and math.isfinite(min_cutoff) and math.isfinite(d_cutoff)):
            raise ValueError(f"cutoffs must be finite and > 0, got {min_cutoff!r}, {d_cutoff!r}")
        if not (beta >= 0.0 and math.isfinite(beta)):
            raise ValueError(f"beta must be finite and >= 0, got {beta!r}")
        self.min_cutoff = float(min_cutoff)
        self.beta = float(beta)
        self.d_cutoff = float(d_cutoff)
        self._t: float | None = None
        self._x = 0.0
        self._dx = 0.0

    @staticmethod
    def _alpha(cutoff: float, dt: float) -> float:
        tau = 1.0 / (2.0 * math.pi * cutoff)
        return 1.0 / (1.0 + tau / dt)

    def reset(self) -> None:
        """Forget the history; the next sample passes through unchanged."""
        self._t = None
        self._dx = 0.0

    def __call__(self, t: float, x: float) -> float:
        """Filter one sample.

        Args:
            t: the sample's time, seconds (non-decreasing).
            x: the sample.

        Returns:
            The filtered value (the sample itself on the first call; the last output when ``dt = 0``).

        Raises:
            ValueError: time went backwards, or a non-finite sample or time.
        """
        if not (math.isfinite(t) and math.isfinite(x)):
            raise ValueError(f"time and sample must be finite, got t={t!r}, x={x!r}")
        if self._t is None:
            self._t, self._x, self._dx = t, float(x), 0.0
            return self._x
        dt = t - self._t
        if dt < 0.0:
            raise ValueError(f"time went backwards: {t} after {self._t}")
        if dt == 0.0:
            return self._x
        dx = (x - self._x) / dt
        self._dx += self._alpha(self.d_cutoff, dt) * (dx - self._dx)
        cutoff = self.min_cutoff + self.beta * abs(self._dx)
        self._x += self._alpha(cutoff, dt) * (x - self._x)
        self._t = t
        return self._x


class PuppetMapping:
    """Phone input to blend parameters, each frame: smooth, map the height, look up the speed.

    Args:
        table: the probe lookup table (speed axis; its height axis is ``p_height``).
        height: the linear map from the input height (e.g. the phone's height above the ground, m) to
            ``p_height``.
        smoothing: smooth the two raw inputs with one-euro filters (``update`` only; ``map`` never does).
        speed_filter: the speed filter; default ``OneEuroFilter(2.0, 0.3, 1.0)`` (our choice: steady at
            rest, about 3 Hz while accelerating at 3 m/s^2).
        height_filter: the height filter; default ``OneEuroFilter(2.0, 1.0, 1.0)``.
    """

    def __init__(self, table: ProbeTable, height: AxisMap, *, smoothing: bool = True,
                 speed_filter: OneEuroFilter | None = None, height_filter: OneEuroFilter | None = None) -> None:
        self.table = table
        self.height_map = height
        self.smoothing = smoothing
        self.speed_filter = speed_filter if speed_filter is not None else OneEuroFilter(2.0, 0.3, 1.0)
        self.height_filter = height_filter if height_filter is not None else OneEuroFilter(2.0, 1.0, 1.0)

    def reset(self) -> None:
        """Forget the smoothing history (e.g. on a new grab)."""
        self.speed_filter.reset()
        self.height_filter.reset()

    def map(self, speed: float, height: float) -> BlendQuery:
        """Map one raw input without smoothing.

        Args:
            speed: the stick end's horizontal speed, m/s (>= 0).
            height: the input height in the ``AxisMap``'s units.

        Returns:
            The ``BlendQuery``.

        Raises:
            ValueError: a negative or non-finite speed, or a non-finite height.
        """
        if not math.isfinite(height):
            raise ValueError(f"height must be finite, got {height!r}")
        return self.table.query(speed, self.height_map(height))

    def update(self, t: float, speed: float, height: float) -> BlendQuery:
        """Smooth one input frame (when enabled) and map it.

        Args:
            t: the frame's time, seconds (non-decreasing).
            speed: the stick end's horizontal speed, m/s (>= 0).
            height: the input height in the ``AxisMap``'s units.

        Returns:
            The ``BlendQuery`` of the smoothed input.

        Raises:
            ValueError: time went backwards, or bad inputs (see ``map``).
        """
        if not (math.isfinite(speed) and speed >= 0.0):
            raise ValueError(f"speed must be finite and >= 0, got {speed!r}")
        if self.smoothing:
            speed = max(0.0, self.speed_filter(t, speed))
            height = self.height_filter(t, height)
        return self.map(speed, height)
