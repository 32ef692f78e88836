"""Correspondence, warping and consistency of the loops of a take (Ciccone 2019, section 5.3, "Average
cycle"; step 6 of :func:`cycles.extract`, and the consistency R its acceptance uses).

This module owns ``Alignment`` and ``align`` (anchors evenly spaced in a reference loop, matched by the
descriptor distance d_D in every other loop, kept monotone; each loop is warped by one monotone PCHIP so
the anchors share one time), ``refine_cuts`` (each cut moved to where the data around it best fits the
average loop), and the consistency of time-aligned loops: ``loop_consistency`` (R = 1 - mean squared
deviation from the average over the variance, outlier loops left out), ``outliers``, ``detrended`` (drift
over one period removed), ``consistency_at``, ``linear_consistency`` and ``warped_consistency``. The
consistency test and the anchor count are perfcap's own (the thesis gives neither), see
``docs/design/cycles.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.interpolate import PchipInterpolator

from cycles.descriptor import distance_rows, parabolic_offset
from cycles.prepare import at_positions

if TYPE_CHECKING:
    from cycles._types import BoolArray, FloatArray

__all__ = [
    "Alignment",
    "align",
    "alternation",
    "consistency_at",
    "detrended",
    "linear_consistency",
    "loop_consistency",
    "outliers",
    "refine_cuts",
    "warped_consistency",
]


def outliers(err: FloatArray) -> BoolArray:
    """Loops whose misfit is far above the others' (a turn or a stumble inside a take), as a mask; never
    more than 40% of the loops."""
    if err.size <= 2:
        return np.zeros(err.size, bool)
    med = float(np.median(err))
    bad = err > max(4.0 * med, med + 0.25)
    if bad.sum() > 0.4 * err.size:
        return np.zeros(err.size, bool)
    return bad


def loop_consistency(stack: FloatArray) -> tuple[float, FloatArray]:
    """Consistency R of time-aligned loops ``(p, m + 1, D)`` on standardised channels, and each loop's
    misfit: 1 - (mean squared deviation of the loops from their average) / (their variance), over the
    loops that are not outliers (:func:`outliers`)."""
    s = stack - stack.mean(axis=(0, 1), keepdims=True)
    var = float(np.mean(np.sum(s * s, axis=2)))
    if not var > 0:
        return 0.0, np.ones(stack.shape[0])
    err = np.mean(np.sum((s - s.mean(axis=0)) ** 2, axis=2), axis=1) / var
    bad = outliers(err)
    if bad.any():
        inl = s[~bad] - s[~bad].mean(axis=(0, 1), keepdims=True)
        var_i = float(np.mean(np.sum(inl * inl, axis=2)))
        if not var_i > 0:
            return 0.0, err
        err_i = np.mean(np.sum((inl - inl.mean(axis=0)) ** 2, axis=2), axis=1) / var_i
        return float(1.0 - err_i.mean()), err
    return float(1.0 - err.mean()), err


def detrended(z: FloatArray, tau: float) -> FloatArray:
    """``z`` minus its moving average over one candidate period. A motion that repeats every ``tau``
    is unchanged (its average over a period is constant) while drift is removed: a performer who walks
    on in world coordinates still repeats, a ramp or a random walk is left with nothing that does, and
    at a wrong (half) period the slower part of the motion stays in and keeps the loops unlike."""
    n = z.shape[0]
    w = max(1, round(tau))
    c = np.zeros((n + 1, z.shape[1]))
    np.cumsum(z, axis=0, out=c[1:])
    i = np.arange(n)
    lo = np.clip(i - w // 2, 0, n - w if n > w else 0)
    hi = np.minimum(lo + w, n)
    return z - (c[hi] - c[lo]) / (hi - lo)[:, None]


def consistency_at(zv: FloatArray, pos: FloatArray) -> tuple[float, FloatArray]:
    """:func:`loop_consistency` of the loops of ``zv`` sampled at positions ``pos`` ``(p, m + 1)``."""
    p, m1 = pos.shape
    return loop_consistency(at_positions(zv, pos.reshape(-1)).reshape(p, m1, -1))


def linear_consistency(zv: FloatArray, loops: list[tuple[float, float]], m: int) -> tuple[float, FloatArray]:
    """:func:`consistency_at` for loops resampled linearly (no warp) to ``m`` + 1 samples."""
    u = np.linspace(0.0, 1.0, m + 1)
    ab = np.asarray(loops)
    return consistency_at(zv, ab[:, :1] + (ab[:, 1:] - ab[:, :1]) * u[None, :])


@dataclass
class Alignment:
    """Loops of the take and their correspondence: ``src[i]`` are positions (samples) in loop i of the
    anchors whose common place in the average loop is ``target`` (0..1, loop ends included)."""

    loops: list[tuple[float, float]]
    src: FloatArray
    target: FloatArray
    _pchip: PchipInterpolator | None = field(default=None, init=False, repr=False, compare=False)

    def positions(self, u: FloatArray) -> FloatArray:
        """``(loops, len(u))`` sample positions of the loop phases ``u`` (0..1) in every loop."""
        return self.warp(u)

    def warp(self, u: FloatArray) -> FloatArray:
        """As :meth:`positions`, from one monotone PCHIP over all loops (they share the knots), built
        once per alignment (``src`` and ``target`` are not changed after :func:`align`)."""
        if self._pchip is None:
            self._pchip = PchipInterpolator(self.target, self.src.T, axis=0)
        pos: FloatArray = self._pchip(u).T
        return pos


def align(h: FloatArray, g: FloatArray, loops: list[tuple[float, float]], period: float, k: int) -> Alignment:
    """Correspondence (Ciccone 2019, section 5.3, "Average cycle"; the details are perfcap's): anchors
    evenly spaced in the reference loop (the one closest to the median length), each matched by d_D within
    ceil(T/8) of its proportional place in every other loop, kept monotone; the anchors' common place is
    their mean normalised position."""
    n = h.shape[0]
    lengths = np.array([b - a for a, b in loops])
    ref = int(np.argmin(np.abs(lengths - np.median(lengths))))
    n_anchor = int(min(16, max(4, math.floor(period / (2 * k + 1)))))
    ra, rb = loops[ref]
    frac = np.arange(1, n_anchor + 1) / (n_anchor + 1)
    anchor_pos = ra + frac * (rb - ra)
    anchor_idx = np.clip(np.rint(anchor_pos).astype(np.int64), 0, n - 1)
    m_t = max(2, math.ceil(period / 8.0))
    src = np.empty((len(loops), n_anchor + 2))
    eps = 1e-3
    for li, (a, b) in enumerate(loops):
        src[li, 0], src[li, -1] = a, b
        if li == ref:
            src[li, 1:-1] = anchor_pos
            continue
        prop = a + frac * (b - a)
        a_lo, a_hi = math.ceil(a) + 1, min(math.floor(b) - 1, n - 2)
        dl = distance_rows(h, g, anchor_idx, slice(a_lo, a_hi + 1)) if a_hi > a_lo else None
        if dl is None:
            src[li, 1:-1] = prop
        else:
            floor = 0.02 * np.percentile(dl, 25.0, axis=1)
            cols = np.arange(a_lo, a_hi + 1)
            lo = np.maximum(np.floor(prop) - m_t, a_lo)
            hi = np.minimum(np.ceil(prop) + m_t, a_hi)
            inside = (cols[None, :] >= lo[:, None]) & (cols[None, :] <= hi[:, None])
            # the deepest minimum, mildly preferring the proportional place; the additive part breaks
            # the descriptor product's exact ties (it is 0 where either factor is)
            off = (cols[None, :] - prop[:, None]) / m_t
            cost = np.where(inside, dl * (1.0 + 0.5 * off * off) + floor[:, None] * off * off, np.inf)
            j = np.argmin(cost, axis=1)
            q = np.arange(n_anchor)
            jm, jp = np.maximum(j - 1, 0), np.minimum(j + 1, cols.size - 1)
            y0, y1, y2 = dl[q, jm], dl[q, j], dl[q, jp]
            den = y0 - 2.0 * y1 + y2
            interior = inside[q, jm] & inside[q, jp] & (jm < j) & (jp > j) & (den > 0)
            sub = np.where(interior, np.clip(0.5 * (y0 - y2) / np.where(den > 0, den, 1.0), -0.5, 0.5), 0.0)
            found = cols[j] + sub + (anchor_pos - anchor_idx)
            src[li, 1:-1] = np.where(hi > lo, found, prop)
        # monotone, strictly inside the loop
        inner = np.clip(np.maximum.accumulate(src[li, 1:-1]), a + eps, b - eps)
        src[li, 1:-1] = inner + eps * 1e-3 * np.arange(n_anchor)
    norm = (src - src[:, :1]) / (src[:, -1:] - src[:, :1])
    target = np.maximum.accumulate(norm.mean(axis=0))
    target[0], target[-1] = 0.0, 1.0
    target[1:-1] = np.clip(target[1:-1], 1e-6, 1 - 1e-6)
    if np.any(np.diff(target) <= 0):
        target = np.linspace(0.0, 1.0, n_anchor + 2)
    return Alignment(loops=list(loops), src=src, target=target)


def alternation(zv: FloatArray, al: Alignment, ks: list[int], m: int, j: int) -> tuple[float, float]:
    """Whether loops alternate with ``j`` parts: the loops, warped onto the common timeline, grouped by
    their index in the performance modulo ``j`` (``ks``: a missed loop leaves a hole, so groups follow
    the loops performed, not their places in the list), and compared as a one-way analysis of variance.

    Returns ``(F, effect)``: F is the variance between the groups' average loops over the variance
    inside the groups, each per degree of freedom, so about 1 when every loop is the same motion
    (the loop-to-loop differences of tempo and noise fall inside the groups as much as between them)
    and far above 1 at a wrong sub-period of ``j`` parts; effect is the between-group part as a share
    of the loops' variance (a large F of a negligible difference is no alternation). ``(nan, 0)`` when
    a group has fewer than two loops."""
    g = np.mod(np.asarray(ks), j)
    count = np.bincount(g, minlength=j)
    if count.min() < 2:
        return float("nan"), 0.0
    u = np.linspace(0.0, 1.0, m + 1)
    pos = al.positions(u)
    stack = at_positions(zv, pos.reshape(-1)).reshape(pos.shape[0], m + 1, -1)
    grand = stack.mean(axis=0)
    var = float(np.mean(np.sum((stack - stack.mean(axis=(0, 1))) ** 2, axis=2)))
    means = np.stack([stack[g == q].mean(axis=0) for q in range(j)])
    between = float(np.sum(count[:, None, None] * (means - grand) ** 2))
    within = float(sum(np.sum((stack[g == q] - means[q]) ** 2) for q in range(j)))
    effect = between / (len(ks) * (m + 1)) / var if var > 0 else 0.0
    if not within > 0:
        return (float("inf") if between > 0 else float("nan")), effect
    return (between / (j - 1)) / (within / (len(ks) - j)), effect


def warped_consistency(zv: FloatArray, al: Alignment, m: int) -> tuple[float, FloatArray]:
    """:func:`consistency_at` of the loops warped onto the common timeline."""
    return consistency_at(zv, al.positions(np.linspace(0.0, 1.0, m + 1)))


def refine_cuts(z: FloatArray, cuts: FloatArray, mean0: FloatArray, per: float) -> FloatArray:
    """Each cut moved to where the data around it best fits the average loop around its start (least
    squares over +-T/4, offsets removed, shifts up to +-T/8, sub-sample by a parabola)."""
    n = z.shape[0]
    m0 = mean0.shape[0] - 1
    loop = mean0[:-1]
    w = max(3, round(per / 4.0))
    s_max = max(2, math.ceil(per / 8.0))
    shifts = np.arange(-s_max, s_max + 1, dtype=np.float64)
    rel = np.arange(-w, w + 1)
    out = cuts.astype(np.float64).copy()
    for i, c in enumerate(cuts):
        ci = round(c)
        idx = ci + rel
        if idx[0] < 0 or idx[-1] > n - 1:
            continue
        data = z[idx]
        data = data - data.mean(axis=0)
        ph = np.mod((idx[None, :] - (c + shifts[:, None])) / per, 1.0) * m0
        j0 = np.floor(ph).astype(np.int64) % m0
        fr = (ph - np.floor(ph))[..., None]
        tmpl = loop[j0] * (1.0 - fr) + loop[(j0 + 1) % m0] * fr
        tmpl = tmpl - tmpl.mean(axis=1, keepdims=True)
        err = np.sum((tmpl - data[None]) ** 2, axis=(1, 2))
        b = int(np.argmin(err))
        if 0 < b < shifts.size - 1:
            out[i] = c + shifts[b] + parabolic_offset(err[b - 1], err[b], err[b + 1])
    order = np.argsort(out)
    if np.any(order != np.arange(out.size)) or np.any(np.diff(out) <= 0):
        return cuts   # refinement would reorder cuts: keep the matches as they were
    return out

