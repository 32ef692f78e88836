"""Cycle extraction: one clean closed loop from several imprecise performed loops.

The method is Ciccone 2019 (ETH Diss. 25792) §5.3, with the proposals and fixes of the project spec
(``cycles-and-puppet.md`` §1):

1. **Prepare** (§1.0): sort and de-duplicate the stamps, keep the longest stretch without a gap of
   more than ``gap_factor`` sample intervals, resample to a uniform grid when the stamps are irregular,
   unwrap Euler angles, and map quaternions to rotation vectors about the take's chordal mean (with
   hemisphere continuity), so that everything below works on plain vectors.
2. **Descriptor space**: channels are standardised for matching only; wide inputs (hundreds or
   thousands of channels) are projected on their principal subspace (a randomised range finder), which
   keeps the distances the descriptor sees and makes the cost independent of the channel count.
3. **Period candidates**: the peaks of the summed autocorrelation of the smoothed derivatives (blind
   to offsets and slow trends). It is only a prior: the descriptor decides.
4. **Chained matching** (replaces eq. 5.3's absolute grid, which fails on long real takes, §1.5): for
   random seeds, follow the performance loop by loop, searching each next occurrence of the seed's
   instant (minimum of the descriptor distance d_D, eq. 5.1-5.2) near the previous match plus the
   current tempo. A loop that does not match (a turn, a pause) is a miss, not the end; the tempo is
   tracked, so drift does not break it. Each seed gives cut points; the period is the median over seeds.
5. **Acceptance**: a candidate needs consistent loops (R >= ``min_consistency``, a little less with
   many loops; R is measured with the motion's drift over one period removed, so walking on in world
   coordinates still repeats while a ramp or a random walk does not), found in most loops
   (``min_hit_rate``) over most of the moving take (``min_coverage``), and agreed on by most seeds
   (``min_agreement``). The shortest such candidate wins if it repeats about as well as the best one
   or well enough with the drift left in: a multiple of the period repeats as well as the period, only
   a wrong sub-period alternates. So neither half nor double periods come out, and input that does not
   repeat raises :class:`NoPeriodFoundError`.
6. **Cut refinement, correspondence and averaging** (eq. 5.4): each cut is moved to where the data
   around it best fits the first average loop (a matched filter over half a loop, not a single
   instant). Anchors evenly spaced in a reference loop are matched by d_D in every loop; each loop is
   warped (monotone PCHIP) so the anchors share one time, and the loops are averaged; loops that
   deviate far more than the others (a turn, a stumble) are left out, and said so.
7. **Period** (refined, §1.2 "Bias"): with few loops, the take's duration over the number of loops it
   spans, counting the partial loops at both ends by their matched share of a loop (the mean loop
   duration); from ``median_from_loops`` loops on, the interquartile mean of the averaged loops'
   durations, each averaged over the seeds that cut it (robust to turns and stops).
8. **Stitching** (eq. 5.5): the end gap is spread linearly so the loop closes exactly; quaternions are
   mapped back. The :class:`~cycles.cycle.Cycle` evaluates it with a periodic cubic spline.

Deterministic for a given seed. No clock is read here: callers time it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from capture.errors import NoMotionError, NoPeriodFoundError
from cycles.cycle import Cycle
from cycles.descriptor import (
    K_RADIUS,
    descriptors,
    distance_rows,
    otsu_threshold,
    parabolic_offset,
    window_sums,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtractOptions:
    """Tuning of :func:`extract`. The defaults are the thesis's values and the spec's proposals.

    Attributes:
        k: descriptor radius (thesis: 5).
        seeds: random seed instants (thesis: 10, median kept).
        min_seeds: fewer seeds with a period than this raises :class:`NoPeriodFoundError`.
        min_consistency: smallest consistency R accepted (spec: 0.8).
        candidate_margin: a shorter candidate period wins over a better one if its R is within this.
        max_candidates: autocorrelation peaks tried as period candidates.
        max_components: descriptor dimensions kept for wide inputs.
        min_period_s, max_period_s: bounds on the period (default: 2k+2 samples .. half the take).
        search: half-width of the search window around each predicted occurrence, in periods.
        max_misses: consecutive loops that may fail to match before a chain ends.
        max_rate_hz, work_rate_hz: inputs sampled faster than ``max_rate_hz`` are matched at about
            ``work_rate_hz`` (low-passed and decimated); the loop keeps the input's rate.
        min_hit_rate: smallest share of loops (between the first and last match) that must match.
        min_coverage: smallest share of the moving part of the take the matched loops must span.
        min_agreement: smallest share of the seeds whose period agrees with the median.
        gap_factor: stamps further apart than this many median intervals split the take.
        period_estimate: ``"auto"``, ``"mean"`` (duration over loops spanned) or ``"median"``.
        median_from_loops: in ``"auto"``, use the robust (interquartile mean) loop duration from this
            many loops on, when some loops were left out or missed.
        keep_aligned: keep the time-aligned input loops in the result (the report draws them).
    """

    k: int = K_RADIUS
    seeds: int = 10
    min_seeds: int = 5
    min_consistency: float = 0.8
    candidate_margin: float = 0.1
    max_candidates: int = 4
    max_components: int = 32
    min_period_s: float | None = None
    max_period_s: float | None = None
    search: float = 0.15
    max_misses: int = 4
    max_rate_hz: float = 250.0
    work_rate_hz: float = 200.0
    min_hit_rate: float = 0.6
    min_coverage: float = 0.5
    min_agreement: float = 0.6
    gap_factor: float = 3.0
    period_estimate: str = "auto"
    median_from_loops: int = 8
    keep_aligned: bool = True

    def __post_init__(self) -> None:
        if self.k < 1 or self.seeds < 1 or not 1 <= self.min_seeds <= self.seeds:
            raise ValueError("k >= 1 and 1 <= min_seeds <= seeds are required")
        if not 0.0 < self.min_consistency < 1.0:
            raise ValueError("min_consistency must be in (0, 1)")
        if not 0.02 <= self.search <= 0.45:
            raise ValueError("search must be in [0.02, 0.45] periods")
        if self.period_estimate not in ("auto", "mean", "median"):
            raise ValueError("period_estimate must be 'auto', 'mean' or 'median'")
        if self.max_components < 2 or self.max_candidates < 1 or self.max_misses < 0 or self.gap_factor <= 1:
            raise ValueError("max_components >= 2, max_candidates >= 1, max_misses >= 0, gap_factor > 1")


# ---------------------------------------------------------------------------------------------- prepare


@dataclass
class _Work:
    t0: float
    dt: float
    x: np.ndarray                     # (n, W) working columns
    columns: list[tuple[str, list[int], list[int]]]  # (kind, input cols, working cols)
    q_refs: dict[int, Rotation]       # working col start -> reference rotation
    angle_scale: float
    notes: list[str]


def _prepare(t: np.ndarray, v: np.ndarray, quaternions: Sequence[Sequence[int]], angles: Sequence[int],
             angle_unit: str, gap_factor: float, min_gap_s: float = 0.1) -> _Work:
    c = v.shape[1]
    notes: list[str] = []
    finite = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    if not finite.all():
        notes.append(f"{int((~finite).sum())} sample(s) with a missing or non-finite value left out")
        t, v = t[finite], v[finite]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    if not keep.all():
        notes.append(f"{int((~keep).sum())} sample(s) with a repeated time stamp left out")
        t, v = t[keep], v[keep]
    if t.size < 8:
        raise NoPeriodFoundError(f"only {t.size} usable samples: a cycle needs several loops of motion")
    dt_all = np.diff(t)
    # A gap is an interval far beyond the usual ones: gap_factor times the median for a steady rate,
    # but measured against the 95th percentile when the stamps are irregular by nature (a phone's
    # sensor events), so ordinary long intervals do not split the take.
    med = float(np.median(dt_all))
    # Short holds (a mouse reports only changes, so it is silent while the hand turns round) are not
    # gaps: nothing shorter than min_gap_s splits the take; it is interpolated over.
    usual = max(med, float(np.percentile(dt_all, 95)) if np.percentile(dt_all, 95) > 1.5 * med else med)
    gap_at = max(gap_factor * usual, min_gap_s)
    gaps = np.flatnonzero(dt_all > gap_at)
    dt = med if usual == med else float(np.mean(dt_all[dt_all <= gap_factor * usual]))
    if gaps.size:
        bounds = np.concatenate([[0], gaps + 1, [t.size]])
        spans = t[bounds[1:] - 1] - t[bounds[:-1]]
        b = int(np.argmax(spans))
        lo, hi = int(bounds[b]), int(bounds[b + 1])
        notes.append(f"the take has {gaps.size} gap(s) longer than {gap_at:.3g} s (the longest"
                     f" {float(dt_all[gaps].max()):.3g} s); used the longest stretch without one,"
                     f" {float(t[lo]):.3f}-{float(t[hi - 1]):.3f} s")
        t, v = t[lo:hi], v[lo:hi]
        if t.size < 8:
            raise NoPeriodFoundError("no stretch of the take without a gap is long enough for a cycle")
        steps_in = np.diff(t)
        dt = float(np.median(steps_in)) if usual == med else float(np.mean(steps_in))

    qcols = [list(q) for q in quaternions]
    flat_q = [i for q in qcols for i in q]
    for q in qcols:
        if len(q) != 4 or len(set(q)) != 4:
            raise ValueError(f"a quaternion is 4 distinct columns (w, x, y, z), not {q}")
    angle_cols = list(angles)
    all_special = flat_q + angle_cols
    if len(set(all_special)) != len(all_special) or any(not 0 <= i < c for i in all_special):
        raise ValueError("quaternion and angle columns must be distinct, existing columns")
    if angle_unit not in ("rad", "deg"):
        raise ValueError("angle_unit must be 'rad' or 'deg'")
    angle_scale = math.pi / 180.0 if angle_unit == "deg" else 1.0

    columns: list[tuple[str, list[int], list[int]]] = []
    q_refs: dict[int, Rotation] = {}
    blocks: list[tuple[list[int], np.ndarray]] = []   # (working columns, values) of quats and angles
    lin_in: list[int] = []
    lin_w: list[int] = []
    w = 0
    qstart = {q[0]: q for q in qcols}
    flat_set, angle_set = set(flat_q), set(angle_cols)
    for i in range(c):
        if i in flat_set and i not in qstart:
            continue
        if i in qstart:
            q = qstart[i]
            quat = v[:, q].astype(np.float64)
            norm = np.linalg.norm(quat, axis=1)
            if np.any(norm < 1e-6):
                raise ValueError(f"quaternion columns {q} hold a zero quaternion")
            quat = quat / norm[:, None]
            # hemisphere continuity: q and -q are one rotation
            flips = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], axis=1) < 0, -1.0, 1.0))
            quat[1:] *= flips[:, None]
            m = quat.T @ quat
            ref = np.linalg.eigh(m)[1][:, -1]   # chordal mean
            r_ref = Rotation.from_quat(ref[[1, 2, 3, 0]])
            rv = (r_ref.inv() * Rotation.from_quat(quat[:, [1, 2, 3, 0]])).as_rotvec()
            blocks.append(([w, w + 1, w + 2], rv))
            columns.append(("quat", q, [w, w + 1, w + 2]))
            q_refs[w] = r_ref
            w += 3
        elif i in angle_set:
            blocks.append(([w], np.unwrap(v[:, i].astype(np.float64) * angle_scale)[:, None]))
            columns.append(("angle", [i], [w]))
            w += 1
        else:
            lin_in.append(i)
            lin_w.append(w)
            w += 1
    if lin_in:
        columns.append(("linear", lin_in, lin_w))
    x = np.empty((v.shape[0], w))
    x[:, lin_w] = v[:, lin_in]
    for wc, val in blocks:
        x[:, wc] = val

    steps = np.diff(t)
    if np.max(np.abs(steps - dt)) > 1e-3 * dt:
        m = math.floor((t[-1] - t[0]) / dt + 1e-9) + 1
        grid = t[0] + dt * np.arange(m)
        x = _interp_rows(t, x, grid)
    return _Work(t0=float(t[0]), dt=dt, x=np.ascontiguousarray(x), columns=columns, q_refs=q_refs,
                 angle_scale=angle_scale, notes=notes)


def _interp_rows(t: np.ndarray, x: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Linear interpolation of every column of ``x`` (sampled at ``t``) at times ``at``."""
    j = np.clip(np.searchsorted(t, at, side="right"), 1, t.size - 1)
    w = ((at - t[j - 1]) / (t[j] - t[j - 1]))[:, None]
    return x[j - 1] * (1.0 - w) + x[j] * w


def _at_positions(x: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Rows of ``x`` at fractional sample positions ``pos`` (linear interpolation)."""
    n = x.shape[0]
    p = np.clip(pos, 0.0, n - 1.0)
    j = np.minimum(p.astype(np.int64), n - 2)
    w = (p - j)[:, None]
    return x[j] * (1.0 - w) + x[j + 1] * w


# -------------------------------------------------------------------------------------- descriptor space


def _reduce(z: np.ndarray, r: int, rng: np.random.Generator) -> np.ndarray:
    """``z`` projected on (about) its top-``r`` principal subspace: same row distances up to the
    variance left out. A randomised range finder (Halko et al. 2011)."""
    d = z.shape[1]
    if d <= r:
        return z
    omega = rng.standard_normal((d, r + 8))
    q, _ = np.linalg.qr(z @ omega)
    b = q.T @ z
    ub, s, _ = np.linalg.svd(b, full_matrices=False)
    return (q @ ub[:, :r]) * s[:r]


def _acf_candidates(feat: np.ndarray, lo: int, hi: int, limit: int) -> list[float]:
    """Lags (samples, sub-sample refined) of the highest peaks of the summed autocorrelation of
    ``feat``, in increasing lag order."""
    n = feat.shape[0]
    f = feat - feat.mean(axis=0)
    nfft = 1 << math.ceil(math.log2(2 * n))
    spec = np.fft.rfft(f, nfft, axis=0)
    ac = np.fft.irfft(np.sum(spec.real ** 2 + spec.imag ** 2, axis=1), nfft)[:n]
    if not ac[0] > 0:
        return []
    ac = ac / ac[0]
    # unbias the lag taper so that later repetitions are not handicapped against the first
    ac_u = ac * n / np.maximum(n - np.arange(n), 1)
    hi = min(hi, n - 2)
    if hi <= lo:
        return []
    seg = ac_u[lo - 1:hi + 2]
    pk = np.flatnonzero((seg[1:-1] > seg[:-2]) & (seg[1:-1] >= seg[2:]) & (seg[1:-1] > 0.05)) + lo
    if pk.size == 0:
        return []
    # the earliest strong peaks (a long take has peaks at every multiple of the period, all about as
    # high), plus the highest one
    strong = pk[ac_u[pk] >= 0.5 * ac_u[pk].max()]
    top = np.union1d(strong[:limit], pk[np.argmax(ac_u[pk])])
    if top.size < limit:
        rest = np.setdiff1d(pk, top)
        top = np.union1d(top, rest[np.argsort(-ac_u[rest], kind="stable")][:limit - top.size])
    out = []
    for p in sorted(top.tolist()):
        out.append(p + parabolic_offset(-ac_u[p - 1], -ac_u[p], -ac_u[p + 1]))
    return out


# ------------------------------------------------------------------------------------------- matching


@dataclass
class _Chain:
    seed: int
    cuts: np.ndarray       # fractional positions, increasing
    ks: np.ndarray         # loop index of each cut (seed = 0)
    period: float          # samples, this seed's estimate
    thr: float

    @property
    def hit_rate(self) -> float:
        """Share of the loops between the first and last cut that were cut at both ends: loops must tile
        the take, so a 'period' that matches only one part of every real loop scores low."""
        return int(np.sum(np.diff(self.ks) == 1)) / max(1, int(self.ks[-1] - self.ks[0]))


def _seed_matches(dseed: np.ndarray, seeds: np.ndarray, k: int) -> list[tuple[np.ndarray, float]]:
    """Each seed's matches J_i (eq. 5.3): local minima of d_D(seed, .) outside the trivial neighbourhood,
    below the 25th percentile, with outliers pruned by Otsu's split of their log distances (the
    low class is kept); plus the distance threshold that pruning implies."""
    thr_all = np.percentile(dseed, 25.0, axis=1)
    pad = np.pad(dseed, ((0, 0), (2, 2)), constant_values=np.inf)
    is_min = dseed <= np.lib.stride_tricks.sliding_window_view(pad, 5, axis=1).min(axis=2)
    idx = np.arange(dseed.shape[1])
    return [_prune(dseed[i], np.flatnonzero(is_min[i] & (np.abs(idx - s) > k) & (dseed[i] <= thr_all[i])),
                   float(thr_all[i])) for i, s in enumerate(seeds)]


def _prune(d: np.ndarray, mins: np.ndarray, thr: float) -> tuple[np.ndarray, float]:
    if mins.size >= 4:
        # floored well below any real match: exact zeros of the product (a noise-free sine's mirror
        # instants) must not become a class of their own and leave the threshold at nothing
        floor = max(1e-6 * float(np.median(d)), 1e-300)
        logd = np.log(np.maximum(d[mins], floor))
        cut = otsu_threshold(logd)
        mins = mins[logd <= cut]
        thr = min(thr, float(np.exp(cut)))
    return mins, thr


def _chain(d: np.ndarray, seed: int, thr: float, tau: float, opts: ExtractOptions, margin: int) -> _Chain | None:
    n = d.shape[0]
    cuts = [float(seed)]
    ks = [0]
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
            half = max(2.0, opts.search * t_loc)
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
                if misses > opts.max_misses:
                    break
    order = np.argsort(ks)
    cuts_a = np.asarray(cuts)[order]
    ks_a = np.asarray(ks)[order]
    if cuts_a.size < 3:
        return None
    steps = np.diff(ks_a)
    per = np.diff(cuts_a) / steps
    one = per[steps == 1] if np.any(steps == 1) else per
    return _Chain(seed=seed, cuts=cuts_a, ks=ks_a, period=float(np.median(one)), thr=thr)


def _loops_of(chain: _Chain, tau: float) -> list[tuple[float, float]]:
    """Consecutive cut pairs (one loop apart) whose length is plausible."""
    out = []
    for a, b, ka, kb in zip(chain.cuts[:-1], chain.cuts[1:], chain.ks[:-1], chain.ks[1:], strict=True):
        if kb - ka == 1 and 0.7 * tau <= b - a <= 1.4 * tau:
            out.append((float(a), float(b)))
    return out


def _outliers(err: np.ndarray) -> np.ndarray:
    """Loops whose misfit is far above the others' (a turn or a stumble inside a take), as a mask; never
    more than 40% of the loops."""
    if err.size <= 2:
        return np.zeros(err.size, bool)
    med = float(np.median(err))
    bad = err > max(4.0 * med, med + 0.25)
    if bad.sum() > 0.4 * err.size:
        return np.zeros(err.size, bool)
    return bad


def _needed_r(opts: ExtractOptions, loops: int) -> float:
    """The consistency a candidate with ``loops`` loops needs: ``min_consistency`` up to 4 loops, then
    down to 0.2 less at 16 loops or more. Loops that do not repeat agree by chance about 1/p, so many
    loops that agree fairly well are as strong evidence as a few that agree very well (real takes,
    gait for one, are noisier than the spec's synthetic loops)."""
    return opts.min_consistency - 0.2 * min(1.0, max(0.0, (loops - 4) / 12.0))


def _loop_r(stack: np.ndarray) -> tuple[float, np.ndarray]:
    """Consistency R of time-aligned loops ``(p, m + 1, D)`` on standardised channels, and each loop's
    misfit: 1 - (mean squared deviation of the loops from their average) / (their variance), over the
    loops that are not outliers (:func:`_outliers`)."""
    s = stack - stack.mean(axis=(0, 1), keepdims=True)
    var = float(np.mean(np.sum(s * s, axis=2)))
    if not var > 0:
        return 0.0, np.ones(stack.shape[0])
    err = np.mean(np.sum((s - s.mean(axis=0)) ** 2, axis=2), axis=1) / var
    bad = _outliers(err)
    if bad.any():
        inl = s[~bad] - s[~bad].mean(axis=(0, 1), keepdims=True)
        var_i = float(np.mean(np.sum(inl * inl, axis=2)))
        if not var_i > 0:
            return 0.0, err
        err_i = np.mean(np.sum((inl - inl.mean(axis=0)) ** 2, axis=2), axis=1) / var_i
        return float(1.0 - err_i.mean()), err
    return float(1.0 - err.mean()), err


def _detrended(z: np.ndarray, tau: float) -> np.ndarray:
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


def _consistency_at(zv: np.ndarray, pos: np.ndarray) -> tuple[float, np.ndarray]:
    """:func:`_loop_r` of the loops of ``zv`` sampled at positions ``pos`` ``(p, m + 1)``."""
    p, m1 = pos.shape
    return _loop_r(_at_positions(zv, pos.reshape(-1)).reshape(p, m1, -1))


def _consistency(zv: np.ndarray, loops: list[tuple[float, float]], m: int) -> tuple[float, np.ndarray]:
    """:func:`_consistency_at` for loops resampled linearly (no warp) to ``m`` + 1 samples."""
    u = np.linspace(0.0, 1.0, m + 1)
    ab = np.asarray(loops)
    return _consistency_at(zv, ab[:, :1] + (ab[:, 1:] - ab[:, :1]) * u[None, :])


@dataclass
class _Candidate:
    tau: float
    chains: list[_Chain]
    best: _Chain
    loops: list[tuple[float, float]]
    consistency: float
    agreement: float
    period: float
    hit_rate: float
    alignment: _Alignment
    errors: np.ndarray
    plain: float = 0.0
    coverage: float = 0.0

    @property
    def score(self) -> float:
        return self.consistency * self.hit_rate


def _evaluate(h: np.ndarray, g: np.ndarray, dseed: np.ndarray, thrs: list[float], z: np.ndarray, tau: float, seeds: np.ndarray,
              opts: ExtractOptions, margin: int, total_var: float) -> _Candidate | None:
    chains = [c for c in (_chain(dseed[i], int(s), thrs[i], tau, opts, margin) for i, s in enumerate(seeds))
              if c is not None]
    if len(chains) < opts.min_seeds:
        return None
    periods = np.array([c.period for c in chains])
    med = float(np.median(periods))
    m_t = max(1.0, math.ceil(med / 8.0))
    agree = np.abs(periods - med) <= m_t
    agreement = float(np.mean(agree)) * len(chains) / len(seeds)
    good = [c for c, a in zip(chains, agree, strict=True) if a]
    if not good:
        return None
    # The seed whose cuts make the most consistent loops, among those cutting (nearly) the most loops.
    cut = [(c, _loops_of(c, med)) for c in good]
    most = max(len(lp) for _, lp in cut)
    if most < 2:
        return None
    m = max(8, round(med))
    zv = _detrended(z, med)
    # score a few: the chains cutting the most loops, closest to the median period first
    pick = sorted((e for e in cut if len(e[1]) >= max(2, most - 1)),
                  key=lambda e: (-len(e[1]), abs(e[0].period - med)))[:4]
    scored = [(_consistency(zv, lp, m)[0], len(lp), c, lp) for c, lp in pick]
    full = max((e for e in scored if e[1] == most), key=lambda e: e[0])
    short = [e for e in scored if e[1] < most]
    alt = max(short, key=lambda e: e[0]) if short else None
    r_lin, _, best, loops = alt if alt is not None and alt[0] > full[0] + 0.1 else full
    # loops differ in timing inside too (stance and swing): judge them once time-aligned
    al = _align(h, g, loops, med, opts.k)
    r_warp, errors = _warped_r(zv, al, m)
    # the same without the drift removal: at a wrong sub-period the loops alternate, which shows here
    r_plain = _warped_r(z, al, m)[0]
    r = max(r_lin, r_warp)
    hit = best.hit_rate
    return _Candidate(tau=tau, chains=chains, best=best, loops=loops, consistency=r, agreement=agreement, period=med,
                      hit_rate=hit, alignment=al, errors=errors, plain=r_plain)


# -------------------------------------------------------------------------------------------- eq. 5.3


def smallest_feasible_period(matches: np.ndarray, seed: float, first: float, last: float, t_min: int,
                             t_max: int) -> int | None:
    """Eq. 5.3 with the spec's bounds: the smallest integer period T (samples) such that for every k
    from ceil((first - seed) / T) to floor((last - seed) / T) some match lies within ceil(T / 8) of
    seed + kT. ``None`` if no T in ``[t_min, t_max]`` qualifies."""
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


def _raw_period(matches: list[np.ndarray], seeds: np.ndarray, n: int, margin: int, t_min: int, t_max: int) -> float:
    found = []
    for mins, s in zip(matches, seeds, strict=True):
        j = np.concatenate([mins, [s]]).astype(np.float64)
        T = smallest_feasible_period(j, float(s), float(margin), float(n - 1 - margin), t_min, t_max)
        if T is not None:
            found.append(T)
    return float(np.median(found)) if found else float("nan")


# ---------------------------------------------------------------------------------------------- extract


def extract(t_s: Sequence[float] | np.ndarray, values: Sequence[Sequence[float]] | np.ndarray, *,
            channels: Sequence[str] | None = None, quaternions: Sequence[Sequence[int]] = (),
            angles: Sequence[int] = (), angle_unit: str = "rad", seed: int = 0,
            options: ExtractOptions | None = None) -> Cycle:
    """One clean closed cycle from a take of several performed loops.

    Args:
        t_s: sample times in seconds, ``(n,)``; irregular stamps are fine.
        values: ``(n, C)`` (or ``(n,)`` for one channel) in any units.
        channels: channel names (default ``c0, c1, ...``).
        quaternions: column groups ``(w, x, y, z)`` holding rotations.
        angles: columns holding Euler angles (unwrapped before use).
        angle_unit: ``"rad"`` or ``"deg"`` for ``angles``.
        seed: seed of the random choices; equal seeds give bit-identical results.
        options: tuning; see :class:`ExtractOptions`.

    Returns:
        The cycle, with its period, cut points, loops used and confidence.

    Raises:
        NoMotionError: the input does not move.
        NoPeriodFoundError: no period repeats consistently over at least two loops.
        ValueError: malformed arguments (shapes, column groups, options).
    """
    opts = options or ExtractOptions()
    t = np.asarray(t_s, np.float64).reshape(-1)
    v = np.asarray(values, np.float64)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != t.size:
        raise ValueError(f"values must be (n, channels) with n = len(t_s) = {t.size}, not {v.shape}")
    if v.shape[1] == 0:
        raise ValueError("no channels")
    names = tuple(channels) if channels is not None else tuple(f"c{i}" for i in range(v.shape[1]))
    if len(names) != v.shape[1]:
        raise ValueError(f"{len(names)} channel names for {v.shape[1]} columns")
    work = _prepare(t, v, quaternions, angles, angle_unit, opts.gap_factor)
    try:
        return _extract(work, names, opts, seed)
    except NoPeriodFoundError as exc:
        if work.notes:   # say what was done to the input (a gap that cut it short, dropped samples)
            raise NoPeriodFoundError(f"{exc} (note: {'; '.join(work.notes)})") from None
        raise


def _extract(work: _Work, names: tuple[str, ...], opts: ExtractOptions, seed: int) -> Cycle:
    x_full = work.x
    # Matching works at up to ~250 samples/s: the descriptor's fixed radius (k samples) must span a
    # visible part of the motion, not sensor noise. Faster inputs are low-passed and decimated for
    # the matching (zero phase, so working sample i is input sample i * factor); the loop itself is
    # averaged from the full-rate data.
    factor = 1
    if 1.0 / work.dt > opts.max_rate_hz and x_full.shape[0] // 2 >= 64:
        factor = max(2, math.ceil(1.0 / (work.dt * opts.work_rate_hz)))
        if x_full.shape[0] // factor < 64:
            factor = max(2, x_full.shape[0] // 64)
        x = signal.decimate(x_full, factor, ftype="fir", axis=0, zero_phase=True)
        work = replace(work, dt=work.dt * factor)
    else:
        x = x_full
    n = x.shape[0]
    rng = np.random.default_rng(seed)

    mu = x.mean(axis=0)
    sd = x.std(axis=0)
    scale = np.maximum(np.abs(mu), 1.0)
    if not np.any(sd > 1e-12 * scale):
        raise NoMotionError("the input does not move: every channel is constant")
    active = sd >= 1e-9 * sd.max()
    z = (x[:, active] - mu[active]) / sd[active]
    z = _reduce(z, opts.max_components, rng)
    total_var = float(np.sum(z.var(axis=0)))

    k = opts.k
    h, g = descriptors(z, work.dt, k)
    margin = k + 2
    t_min = max(2 * k + 2, math.ceil(opts.min_period_s / work.dt) if opts.min_period_s else 0)
    t_max = (n - 1) // 2
    if opts.max_period_s:
        t_max = min(t_max, int(opts.max_period_s / work.dt))
    if t_max < t_min:
        raise NoPeriodFoundError(f"the take ({n * work.dt:.3g} s) is too short for two loops of at least"
                                 f" {t_min * work.dt:.3g} s")

    # seeds: interior instants where the curve moves (|h_i| at or above its 25th percentile)
    hn = np.linalg.norm(h, axis=1)
    inner = np.arange(margin, n - margin)
    pool = inner[hn[inner] >= np.percentile(hn[inner], 25.0)]
    if pool.size == 0:
        raise NoMotionError("the input barely moves")
    seeds = np.sort(rng.choice(pool, size=min(opts.seeds, pool.size), replace=False))

    # prior: autocorrelation of smoothed derivatives (offsets and slow trends do not count)
    feat = window_sums(np.diff(z, axis=0), k)[:, k * z.shape[1]:]
    cands = _acf_candidates(feat, t_min, t_max, opts.max_candidates)
    dz = h[:, k * z.shape[1]:]             # the radius-k smoothed derivative
    dseed = distance_rows(h, g, seeds)
    matched = _seed_matches(dseed, seeds, k)
    thrs = [thr for _, thr in matched]
    # the moving part of the take (a performer may stand still before and after looping)
    speed = np.linalg.norm(dz, axis=1)
    moving = np.flatnonzero(speed > 0.1 * np.percentile(speed, 95))
    extent = float(moving[-1] - moving[0]) if moving.size > 1 else float(n)

    def is_valid(c: _Candidate) -> bool:
        return (c.consistency >= _needed_r(opts, len(c.loops)) and c.hit_rate >= opts.min_hit_rate
                and c.coverage >= opts.min_coverage and c.agreement >= opts.min_agreement)

    # A period must explain the loops it cuts (R), be found in most of them (hit rate) over most of
    # the motion (coverage), and most seeds must agree on it. Candidates are tried shortest first; one
    # whose loops repeat even with the drift left in is the answer (longer candidates can only be its
    # multiples), so the rest need not be tried.
    evaluated: list[_Candidate] = []
    for tau in sorted(cands):
        c = _evaluate(h, g, dseed, thrs, z, tau, seeds, opts, margin, total_var)
        if c is None:
            continue
        c.coverage = float(c.best.cuts[-1] - c.best.cuts[0]) / max(extent, 1.0)
        evaluated.append(c)
        if is_valid(c) and c.plain >= _needed_r(opts, len(c.loops)):
            break
    if not evaluated:
        raise NoPeriodFoundError("no period: the motion does not repeat (a cycle needs about two and a half"
                                 " loops or more of one repeated motion"
                                 + (f"; tried {len(cands)} candidate period(s))" if cands else ")"))
    valid = [c for c in evaluated if is_valid(c)]
    if not valid:
        best = max(evaluated, key=lambda c: c.score)
        why = []
        if best.consistency < _needed_r(opts, len(best.loops)):
            why.append(f"its loops are too unlike (consistency R = {best.consistency:.2f},"
                       f" needs {_needed_r(opts, len(best.loops)):.2f})")
        if best.hit_rate < opts.min_hit_rate:
            why.append(f"only {best.hit_rate:.0%} of its loops could be cut (needs {opts.min_hit_rate:.0%})")
        if best.agreement < opts.min_agreement:
            why.append(f"only {best.agreement:.0%} of the random seeds agree on it (needs {opts.min_agreement:.0%})")
        if best.coverage < opts.min_coverage:
            why.append(f"its loops span only {best.coverage:.0%} of the motion (needs {opts.min_coverage:.0%})")
        raise NoPeriodFoundError(f"no consistent period: the best candidate ({best.period * work.dt:.3g} s) "
                                 + "; ".join(why))
    # The shortest valid candidate wins if it repeats about as well as the best one, or if its loops
    # repeat well enough even with the drift left in (a multiple of the period repeats as well as the
    # period; only a wrong sub-period alternates between loops, which drift removal can hide).
    best_r = max(c.consistency for c in valid)
    ok = [c for c in valid if c.consistency >= best_r - opts.candidate_margin
          or c.plain >= _needed_r(opts, len(c.loops))]
    cand = min(ok, key=lambda c: c.period)

    return _finish(work, x_full, factor, z, h, g, cand, seeds, [mm for mm, _ in matched], opts, names, margin,
                   total_var, t_min, t_max, sd, active)


@dataclass
class _Alignment:
    """Loops of the take and their correspondence: ``src[i]`` are positions (samples) in loop i of the
    anchors whose common place in the average loop is ``target`` (0..1, loop ends included)."""

    loops: list[tuple[float, float]]
    src: np.ndarray
    target: np.ndarray

    def positions(self, u: np.ndarray) -> np.ndarray:
        """``(loops, len(u))`` sample positions of the loop phases ``u`` (0..1) in every loop."""
        return self.warp(u)

    def warp(self, u: np.ndarray) -> np.ndarray:
        """As :meth:`positions`, from one monotone PCHIP over all loops (they share the knots)."""
        return PchipInterpolator(self.target, self.src.T, axis=0)(u).T


def _align(h: np.ndarray, g: np.ndarray, loops: list[tuple[float, float]], period: float, k: int) -> _Alignment:
    """Correspondence (spec §1.3): anchors evenly spaced in the reference loop (the one closest to the
    median length), each matched by d_D within ceil(T/8) of its proportional place in every other loop,
    kept monotone; the anchors' common place is their mean normalised position."""
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
    return _Alignment(loops=list(loops), src=src, target=target)


def _warped_r(zv: np.ndarray, al: _Alignment, m: int) -> tuple[float, np.ndarray]:
    """:func:`_consistency_at` of the loops warped onto the common timeline."""
    return _consistency_at(zv, al.positions(np.linspace(0.0, 1.0, m + 1)))


def _refine_cuts(z: np.ndarray, cuts: np.ndarray, mean0: np.ndarray, per: float) -> np.ndarray:
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


def _finish(work: _Work, x: np.ndarray, factor: int, z: np.ndarray, h: np.ndarray, g: np.ndarray, cand: _Candidate,
            seeds: np.ndarray, matches: list[np.ndarray], opts: ExtractOptions, names: tuple[str, ...],
            margin: int, total_var: float, t_min: int, t_max: int, sd: np.ndarray, active: np.ndarray) -> Cycle:
    notes = list(work.notes)
    # Refine the cut points against the first average loop (a matched filter over a quarter loop each
    # side, instead of the seed's single instant), then cut, align and judge again.
    m_r = max(16, round(cand.period))
    mean0 = _at_positions(z, cand.alignment.positions(np.linspace(0.0, 1.0, m_r + 1)).reshape(-1))
    mean0 = mean0.reshape(len(cand.alignment.loops), m_r + 1, -1).mean(axis=0)
    top = np.argsort(-z.var(axis=0), kind="stable")[:12]   # the strongest components carry the timing
    cand.best.cuts = _refine_cuts(z[:, top], cand.best.cuts, mean0[:, top], cand.period)
    loops0 = _loops_of(cand.best, cand.period)
    if len(loops0) >= 2:
        cand.loops = loops0
        cand.alignment = _align(h, g, loops0, cand.period, opts.k)
        cand.consistency, cand.errors = _warped_r(_detrended(z, cand.period), cand.alignment, m_r)
    al = cand.alignment
    consistency = cand.consistency
    # Leave out loops whose shape deviates far more than the others (a turn, a stumble).
    bad = _outliers(cand.errors)
    if bad.any():
        notes.append(f"{int(bad.sum())} loop(s) left out of the average: their shape differs from the others")
        kept = [lp for lp, b in zip(al.loops, bad, strict=True) if not b]
        al = _align(h, g, kept, cand.period, opts.k)
        consistency = _warped_r(_detrended(z, cand.period), al, max(8, round(cand.period)))[0]
    loops = al.loops
    # period: mean over the loops spanned, or median loop duration
    period_s = _period(work, z, cand, al, opts, total_var)
    m = max(8, round(period_s / (work.dt / factor)))   # the output at the input's rate
    u = np.linspace(0.0, 1.0, m + 1)
    positions = al.positions(u) * factor
    # average (eq. 5.4); rotation vectors about the take's mean rotation average as an approximate
    # Karcher mean
    stack = _at_positions(x, positions.reshape(-1)).reshape(len(loops), m + 1, -1)
    mean = stack.mean(axis=0)

    # stitching (eq. 5.5)
    d_ex = mean[0] - mean[-1]
    closure = float(np.sqrt(np.mean((d_ex[active] / sd[active]) ** 2)))
    mean = mean + (u - 0.5)[:, None] * d_ex[None, :]
    mean[-1] = mean[0]

    values = _to_input(work, mean, len(names))
    aligned = None
    if opts.keep_aligned:
        aligned = np.stack([_to_input(work, stack[li], len(names)) for li in range(len(loops))])
    to_s = work.dt
    cuts_s = work.t0 + cand.best.cuts * to_s
    spans = work.t0 + np.array(loops) * to_s
    raw = _raw_period(matches, seeds, z.shape[0], margin, t_min, t_max)
    confidence = float(np.clip(consistency, 0.0, 1.0) * cand.agreement)
    return Cycle(period_s=float(period_s), times_s=u * period_s, values=values, channels=names,
                 loops=len(loops), cuts_s=cuts_s, loop_spans_s=spans, confidence=confidence,
                 consistency=float(consistency), seed_agreement=float(cand.agreement),
                 raw_period_s=float(raw * to_s), closure_error=closure, aligned=aligned,
                 quaternions=tuple((c[0], c[1], c[2], c[3]) for kind, c, _ in work.columns if kind == "quat"),
                 notes=tuple(notes))


def _to_input(work: _Work, y: np.ndarray, c: int) -> np.ndarray:
    """Working columns back to the input's columns and units."""
    out = np.empty((y.shape[0], c))
    for kind, cols, wc in work.columns:
        if kind == "quat":
            r = work.q_refs[wc[0]] * Rotation.from_rotvec(y[:, wc])
            q = r.as_quat()[:, [3, 0, 1, 2]]
            # keep the hemisphere of the reference (w >= 0 relative to it) so loops stay continuous
            out[:, cols] = q
        elif kind == "angle":
            out[:, cols[0]] = y[:, wc[0]] / work.angle_scale
        else:
            out[:, cols] = y[:, wc]
    return out


def _period(work: _Work, z: np.ndarray, cand: _Candidate, al: _Alignment, opts: ExtractOptions,
            total_var: float) -> float:
    """The refined period in seconds (see the module docstring, step 7)."""
    loops = al.loops
    durations = np.array([b - a for a, b in loops])
    # The span estimate (the mean loop) is the most accurate when the loops run on without a break;
    # a long take with loops left out (a turn, a stumble) or missed gets the robust estimate.
    broken = len(loops) < len(cand.loops) or bool(np.any(np.diff(cand.best.ks) != 1))
    use_median = opts.period_estimate == "median" or (
        opts.period_estimate == "auto" and len(loops) >= opts.median_from_loops and broken)
    if use_median:
        # The typical duration of the loops that make the cycle (turns and stumbles left out). Each loop's
        # duration is averaged over the seeds that cut it, each at its own instant, which evens out the
        # jitter of single cut points.
        pairs = []
        for ch in cand.chains:
            one = np.flatnonzero(np.diff(ch.ks) == 1)
            pairs.append((ch.cuts[one], ch.cuts[one + 1] - ch.cuts[one]))
        avg = np.empty(durations.size)
        for i, (a, b) in enumerate(loops):
            got = [float(d[np.argmin(np.abs(st - a))]) for st, d in pairs
                   if st.size and np.min(np.abs(st - a)) < 0.5 * (b - a)]
            got = [d for d in got if 0.7 * (b - a) <= d <= 1.3 * (b - a)]
            avg[i] = float(np.mean(got)) if got else b - a
        lo_q, hi_q = np.percentile(avg, [25.0, 75.0])
        mid = avg[(avg >= lo_q) & (avg <= hi_q)]
        return float(np.mean(mid)) * work.dt   # the interquartile mean: robust, and less noisy than the median
    chain = cand.best
    cuts, ks = chain.cuts, chain.ks
    span_loops = float(ks[-1] - ks[0])
    first, last = float(cuts[0]), float(cuts[-1])
    per = (last - first) / span_loops
    # The partial loops at both ends count by the share of a loop they hold: the whole end segment is
    # matched against the average loop's last (head) or first (tail) part, stretched to fit.
    m0 = max(16, round(float(np.median(durations))))
    u0 = np.linspace(0.0, 1.0, m0 + 1)
    mean0 = _at_positions(z, al.positions(u0).reshape(-1)).reshape(len(al.loops), m0 + 1, -1).mean(axis=0)
    n = z.shape[0]
    extra = 0.0
    t_first, t_last = first, last
    for end in ("head", "tail"):
        seg = z[0:math.floor(first) + 1] if end == "head" else z[math.ceil(last):n]
        if seg.shape[0] < 4 or seg.shape[0] >= 1.3 * per:
            continue   # nothing there, or more than a loop of something else (a pause, a turn)
        s01 = np.linspace(0.0, 1.0, seg.shape[0])[None, :]

        def misfit(fr: np.ndarray, seg: np.ndarray = seg, s01: np.ndarray = s01, end: str = end) -> np.ndarray:
            ph = (1.0 - fr[:, None] * (1.0 - s01)) if end == "head" else fr[:, None] * s01
            fit = _at_positions(mean0, ph.reshape(-1) * m0).reshape(fr.size, seg.shape[0], -1)
            return np.mean(np.sum((fit - seg[None]) ** 2, axis=2), axis=1)

        # the share is near the segment's length over the period (tempo varies by some percent)
        f_exp = seg.shape[0] / per
        lo_f, hi_f = max(0.01, 0.8 * f_exp - 0.02), min(0.99, 1.2 * f_exp + 0.02)
        if hi_f <= lo_f:
            continue
        coarse_f = np.linspace(lo_f, hi_f, 25)
        coarse = misfit(coarse_f)
        step = float(coarse_f[1] - coarse_f[0])
        fine = np.clip(float(coarse_f[int(np.argmin(coarse))]) + np.linspace(-step, step, 17), lo_f, hi_f)
        err = misfit(fine)
        fi = int(np.argmin(err))
        f = float(fine[fi])
        if 0 < fi < fine.size - 1:
            f += parabolic_offset(err[fi - 1], err[fi], err[fi + 1]) * float(fine[1] - fine[0])
        log.debug("%s partial loop: %.3f of a loop, misfit %.3g", end, f, err[fi])
        # a stretch that does not follow the loop (a pause before the first loop) does not count
        if err[fi] > 0.1 * total_var or not 0.7 <= seg.shape[0] / (f * per) <= 1.4:
            continue
        extra += f
        if end == "head":
            t_first = 0.0
        else:
            t_last = float(n - 1)
    if extra > 0:
        per = (t_last - t_first) / (span_loops + extra)
    return per * work.dt
