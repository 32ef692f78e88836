"""Matching a seed instant through the take (step 4 of :func:`cycles.extract`), and the thesis's own
period test.

This module owns ``seed_matches`` (each seed's candidate matches J_i of Ciccone 2019, section 5.3: local
minima of the descriptor distance d_D of eq. 5.2 below a loose threshold, outliers pruned), ``follow_chain``
(perfcap's chained matching, which follows the performance loop by loop from the previous match and the
current tempo, so that drift, a missed loop or a turn do not break it), ``Chain`` and ``loops_of`` (the cut
points one seed gives and the loops between them), and ``smallest_feasible_period`` / ``raw_period``
(eq. 5.3 itself on an absolute grid, reported beside the result). Why chained matching replaces eq. 5.3's
grid, and the bounds used for eq. 5.3, are in ``docs/design/cycles.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from cycles.descriptor import otsu_threshold, parabolic_offset

if TYPE_CHECKING:
    from collections.abc import Sequence

    from cycles._types import BoolArray, FloatArray, IntArray

__all__ = ["Chain", "follow_chain", "loops_of", "numbered_loops", "raw_period", "seed_matches",
           "smallest_feasible_period"]


#: the ratio of the typical distances of the two classes of matches below which they are one class
MIN_SPLIT = 2.5


@dataclass
class Chain:
    seed: int
    cuts: FloatArray       # fractional positions, increasing
    ks: IntArray           # loop index of each cut (seed = 0)
    period: float          # samples, this seed's estimate
    thr: float
    # per cut: the stretch from the previous cut crosses a break (a pause or a gap), so it is no loop
    across: BoolArray = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        if self.across.size != self.cuts.size:
            self.across = np.zeros(self.cuts.size, bool)

    def steps(self) -> tuple[FloatArray, IntArray]:
        """Length (samples) and loop count of each stretch between consecutive cuts that crosses no
        break."""
        keep = ~self.across[1:]
        return np.diff(self.cuts)[keep], np.diff(self.ks)[keep]

    @property
    def hit_rate(self) -> float:
        """Share of the loops between the first and last cut (breaks left out) that were cut at both
        ends: loops must tile the take, so a 'period' that matches only one part of every real loop
        scores low."""
        _, dk = self.steps()
        return int(np.sum(dk == 1)) / max(1, int(dk.sum()))


def seed_matches(dseed: FloatArray, seeds: IntArray, k: int) -> list[tuple[IntArray, float]]:
    """Each seed's matches J_i (eq. 5.3): local minima of d_D(seed, .) outside the trivial neighbourhood,
    below the 25th percentile, with outliers pruned by Otsu's split of their log distances (the
    low class is kept); plus the distance threshold that pruning implies."""
    thr_all = np.percentile(dseed, 25.0, axis=1)
    pad = np.pad(dseed, ((0, 0), (2, 2)), constant_values=np.inf)
    is_min = dseed <= np.lib.stride_tricks.sliding_window_view(pad, 5, axis=1).min(axis=2)
    idx = np.arange(dseed.shape[1])
    return [_prune(dseed[i], np.flatnonzero(is_min[i] & (np.abs(idx - s) > k) & (dseed[i] <= thr_all[i])),
                   float(thr_all[i])) for i, s in enumerate(seeds)]


def _prune(d: FloatArray, mins: IntArray, thr: float) -> tuple[IntArray, float]:
    if mins.size >= 4:
        # floored well below any real match: exact zeros of the product (a noise-free sine's mirror
        # instants) must not become a class of their own and leave the threshold at nothing
        floor = max(1e-6 * float(np.median(d)), 1e-300)
        logd = np.log(np.maximum(d[mins], floor))
        cut = otsu_threshold(logd)
        low = logd <= cut
        # only a real split prunes: true matches of loops at varying tempo differ by some tens of
        # percent among themselves, and Otsu would halve them; false matches lie far above
        if low.all() or float(logd[~low].mean() - logd[low].mean()) >= math.log(MIN_SPLIT):
            mins = mins[low]
            thr = min(thr, float(np.exp(cut)))
    return mins, thr


def follow_chain(d: FloatArray, seed: int, thr: float, tau: float, search: float, max_misses: int,
                 margin: int, breaks: Sequence[tuple[float, float]] = (),
                 moving: BoolArray | None = None) -> Chain | None:
    """Follow the seed's instant through the take loop by loop (perfcap's chained matching; see the
    module docstring). ``breaks`` are intervals ``(a, b)`` of samples that hold no loop (a pause, or
    the joint of two stretches between a gap, where ``a == b``): the next loop past one is searched
    afresh in the loop after it, where the take moves (``moving``, a mask of samples; default all),
    and the stretch across it counts as no loop."""
    n = d.shape[0]
    cuts = [float(seed)]
    ks = [0]
    crossed: set[int] = set()     # ks of the later cut of each pair across a break
    for direction in (1, -1):
        pos = float(seed)
        last = float(seed)
        last_k = 0
        k = 0
        t_loc = tau
        misses = 0
        while True:
            k += direction
            pred = pos + direction * t_loc
            half = max(2.0, search * t_loc)
            brk = _break_ahead(breaks, pos, pred + direction * half, direction)
            if brk is not None:
                jf = _reacquire(d, brk, direction, t_loc, thr, margin, moving)
                if jf is None:
                    break
                cuts.append(jf)
                ks.append(k)
                crossed.add(k if direction > 0 else last_k)
                pos = last = jf
                last_k = k
                misses = 0
                continue
            lo = math.floor(pred - half)
            hi = math.ceil(pred + half)
            if lo < margin or hi > n - 1 - margin:
                lo, hi = max(lo, margin), min(hi, n - 1 - margin)
                if hi - lo < half:      # most of the window is off the take
                    break
            # the deepest minimum, mildly preferring the predicted place (tempo changes slowly)
            off = (np.arange(lo, hi + 1) - pred) / half
            # (the additive term also breaks exact ties, e.g. a noise-free sine's mirror instant, where
            # the descriptor product is 0 as well)
            j = lo + int(np.argmin(d[lo:hi + 1] * (1.0 + 0.5 * off * off) + thr * 0.02 * off * off))
            # the preference may stop a sample or two short of the minimum it points at: go down to it
            a, b = max(j - 2, lo), min(j + 2, hi)
            j = a + int(np.argmin(d[a:b + 1]))
            is_min = d[j] <= d[max(j - 2, 0):j + 3].min()
            if is_min and d[j] <= thr:
                jf = j + (parabolic_offset(d[j - 1], d[j], d[j + 1]) if 0 < j < n - 1 else 0.0)
                gap = abs(jf - last) / abs(k - last_k)
                if 0.7 * tau <= gap <= 1.3 * tau:
                    t_loc = 0.6 * t_loc + 0.4 * gap
                cuts.append(jf)
                ks.append(k)
                pos = last = jf
                last_k = k
                misses = 0
            else:
                pos = pred
                misses += 1
                if misses > max_misses:
                    break
    order = np.argsort(ks)
    cuts_a = np.asarray(cuts)[order]
    ks_a = np.asarray(ks)[order]
    if cuts_a.size < 3:
        return None
    across = np.isin(ks_a, list(crossed))
    keep = ~across[1:]
    if not keep.any():
        return None
    steps = np.diff(ks_a)[keep]
    per = np.diff(cuts_a)[keep] / steps
    one = per[steps == 1] if np.any(steps == 1) else per
    return Chain(seed=seed, cuts=cuts_a, ks=ks_a, period=float(np.median(one)), thr=thr, across=across)


def _break_ahead(breaks: Sequence[tuple[float, float]], pos: float, reach: float,
                 direction: int) -> tuple[float, float] | None:
    """The first break between ``pos`` and ``reach`` in ``direction``, if any."""
    if direction > 0:
        ahead = [br for br in breaks if pos < br[0] <= reach]
        return min(ahead) if ahead else None
    behind = [br for br in breaks if reach <= br[1] < pos]
    return max(behind, key=lambda br: br[1]) if behind else None


def _reacquire(d: FloatArray, brk: tuple[float, float], direction: int, t_loc: float, thr: float,
               margin: int, moving: BoolArray | None) -> float | None:
    """The deepest match (a local minimum of ``d`` under ``thr`` where the take moves) within a loop and
    a fifth past the break, or None."""
    n = d.shape[0]
    if direction > 0:
        lo, hi = math.ceil(brk[1]) + margin, math.ceil(brk[1]) + margin + math.ceil(1.2 * t_loc)
    else:
        lo, hi = math.floor(brk[0]) - margin - math.ceil(1.2 * t_loc), math.floor(brk[0]) - margin
    lo, hi = max(lo, margin), min(hi, n - 1 - margin)
    if hi - lo < 2:
        return None
    seg = d[lo:hi + 1]
    ok = (seg[1:-1] <= seg[:-2]) & (seg[1:-1] <= seg[2:]) & (seg[1:-1] <= thr)
    if moving is not None:
        ok &= moving[lo + 1:hi]
    inner = np.flatnonzero(ok) + 1
    if inner.size == 0:
        return None
    j = lo + int(inner[np.argmin(seg[inner])])
    return j + parabolic_offset(d[j - 1], d[j], d[j + 1])


def loops_of(chain: Chain, tau: float) -> list[tuple[float, float]]:
    """Consecutive cut pairs (one loop apart) whose length is plausible."""
    return [lp for lp, _ in numbered_loops(chain, tau)]


def numbered_loops(chain: Chain, tau: float) -> list[tuple[tuple[float, float], int]]:
    """:func:`loops_of` with each loop's index in the performance (its first cut's ``ks``)."""
    out = []
    for a, b, ka, kb, x in zip(chain.cuts[:-1], chain.cuts[1:], chain.ks[:-1], chain.ks[1:], chain.across[1:],
                               strict=True):
        if kb - ka == 1 and not x and 0.7 * tau <= b - a <= 1.4 * tau:
            out.append(((float(a), float(b)), int(ka)))
    return out


def smallest_feasible_period(matches: FloatArray, seed: float, first: float, last: float, t_min: int,
                             t_max: int) -> int | None:
    """Eq. 5.3 of Ciccone 2019 (section 5.3), with perfcap's bounds on k: the smallest integer period T
    (samples) such that for every k from ceil((first - seed) / T) to floor((last - seed) / T) some match
    lies within ceil(T / 8) of seed + kT. The thesis writes the upper bound as a ceiling, which asks for a
    match past the end of the take; ``docs/design/cycles.md``. ``None`` if no T in ``[t_min, t_max]``
    qualifies."""
    j = np.sort(np.asarray(matches, np.float64))
    t_min = max(1, t_min)
    if j.size == 0 or t_max < t_min:
        return None
    periods = np.arange(t_min, t_max + 1)
    k_lo = np.ceil((first - seed) / periods).astype(np.int64)
    k_hi = np.floor((last - seed) / periods).astype(np.int64)
    counts = np.maximum(k_hi - k_lo + 1, 0)
    total = int(counts.sum())
    if total == 0:
        return None
    owner = np.repeat(np.arange(periods.size), counts)
    start = np.cumsum(counts) - counts
    k = k_lo[owner] + (np.arange(total) - start[owner])
    target = seed + k * periods[owner]
    idx = np.searchsorted(j, target)
    lo = j[np.clip(idx - 1, 0, j.size - 1)]
    hi = j[np.clip(idx, 0, j.size - 1)]
    near = np.minimum(np.abs(lo - target), np.abs(hi - target))
    miss = near >= np.ceil(periods[owner] / 8.0)
    misses = np.bincount(owner, weights=miss, minlength=periods.size)
    ok = (counts >= 2) & (misses == 0)
    if not ok.any():
        return None
    return int(periods[int(np.argmax(ok))])


def raw_period(matches: list[IntArray], seeds: IntArray, n: int, margin: int, t_min: int, t_max: int) -> float:
    found = []
    for mins, s in zip(matches, seeds, strict=True):
        j = np.concatenate([mins, [s]]).astype(np.float64)
        T = smallest_feasible_period(j, float(s), float(margin), float(n - 1 - margin), t_min, t_max)
        if T is not None:
            found.append(T)
    return float(np.median(found)) if found else float("nan")

