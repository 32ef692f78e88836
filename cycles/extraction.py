"""Cycle extraction: one clean closed loop from several imprecise performed loops.

The method is Ciccone 2019, *Intuitive Control of Animated Scenes* (ETH Diss. 25792), chapter 5,
section 5.3 "Cycle Specification", with perfcap's own additions where the thesis is silent or where its
plain method fails on long real takes; ``docs/design/cycles.md`` says which is which. This module owns
the pipeline (``extract``), its tuning (``ExtractOptions``), the acceptance of a candidate period, the
averaging and stitching, and the refined period; the steps it calls live in their own modules:

1. **Prepare** (:mod:`cycles.prepare`): sort and de-duplicate the stamps, keep the longest stretch
   without a gap of more than ``gap_factor`` sample intervals, resample to a uniform grid when the stamps
   are irregular, unwrap Euler angles, and map quaternions to rotation vectors about the take's chordal
   mean (with hemisphere continuity), so that everything below works on plain vectors.
2. **Descriptor space** (:mod:`cycles.candidates`): channels are standardised for matching only; wide
   inputs (hundreds or thousands of channels) are projected on their principal subspace (a randomised
   range finder), which keeps the distances the descriptor sees and makes the cost independent of the
   channel count. The descriptor itself (eq. 5.1-5.2) is :mod:`cycles.descriptor`.
3. **Period candidates** (:mod:`cycles.candidates`): the peaks of the summed autocorrelation of the
   smoothed derivatives (blind to offsets and slow trends). It is only a prior: the descriptor decides.
4. **Chained matching** (:mod:`cycles.matching`; it replaces eq. 5.3's absolute grid, which fails on long
   real takes): for random seeds, follow the performance loop by loop, searching each next occurrence of
   the seed's instant (minimum of the descriptor distance d_D, eq. 5.2) near the previous match plus the
   current tempo. A loop that does not match (a turn, a pause) is a miss, not the end; the tempo is
   tracked, so drift does not break it. Each seed gives cut points; the period is the median over seeds.
5. **Acceptance** (here, with the consistency of :mod:`cycles.alignment`): a candidate needs consistent
   loops (R >= ``min_consistency``, a little less with many loops; R is measured with the motion's drift
   over one period removed, so walking on in world coordinates still repeats while a ramp or a random
   walk does not), found in most loops (``min_hit_rate``) over most of the moving take (``min_coverage``),
   and agreed on by most seeds (``min_agreement``). The shortest such candidate wins if it repeats about
   as well as the best one or well enough with the drift left in: a multiple of the period repeats as
   well as the period, only a wrong sub-period alternates. So neither half nor double periods come out,
   and input that does not repeat raises :class:`NoPeriodFoundError`.
6. **Cut refinement, correspondence and averaging** (:mod:`cycles.alignment`, eq. 5.4): each cut is moved
   to where the data around it best fits the first average loop (a matched filter over half a loop, not
   a single instant). Anchors evenly spaced in a reference loop are matched by d_D in every loop; each
   loop is warped (monotone PCHIP) so the anchors share one time, and the loops are averaged; loops that
   deviate far more than the others (a turn, a stumble) are left out, and said so.
7. **Period** (here; the thesis reports eq. 5.3's integer T, perfcap refines it): with few loops, the
   take's duration over the number of loops it spans, counting the partial loops at both ends by their
   matched share of a loop (the mean loop duration); from ``median_from_loops`` loops on, the
   interquartile mean of the averaged loops' durations, each averaged over the seeds that cut it (robust
   to turns and stops).
8. **Stitching** (here, eq. 5.5): the end gap is spread linearly so the loop closes exactly; quaternions
   are mapped back. The :class:`~cycles.cycle.Cycle` evaluates it with a periodic cubic spline.

Deterministic for a given seed. No clock is read here: callers time it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy import signal

from capture.errors import NoMotionError, NoPeriodFoundError
from cycles.alignment import (
    Alignment,
    align,
    detrended,
    linear_consistency,
    outliers,
    refine_cuts,
    warped_consistency,
)
from cycles.candidates import acf_candidates, principal_subspace
from cycles.cycle import Cycle
from cycles.descriptor import K_RADIUS, descriptors, distance_rows, parabolic_offset, window_sums
from cycles.matching import Chain, follow_chain, loops_of, raw_period, seed_matches
from cycles.prepare import Prepared, at_positions, prepare, to_input

if TYPE_CHECKING:
    from collections.abc import Sequence

    from numpy.typing import ArrayLike

    from cycles._types import BoolArray, FloatArray, IntArray

__all__ = ["ExtractOptions", "extract"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtractOptions:
    """Tuning of :func:`extract`. ``k`` and ``seeds`` default to Ciccone 2019's values (section 5.3); the
    rest are perfcap's (the thesis has no such settings), explained in ``docs/design/cycles.md``.

    Attributes:
        k: descriptor radius (the thesis uses 5).
        seeds: random seed instants (the thesis uses 10 and keeps the median period).
        min_seeds: fewer seeds with a period than this raises :class:`NoPeriodFoundError`.
        min_consistency: smallest consistency R accepted (perfcap's acceptance test; 0.8).
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


def _needed_r(opts: ExtractOptions, loops: int) -> float:
    """The consistency a candidate with ``loops`` loops needs: ``min_consistency`` up to 4 loops, then
    down to 0.2 less at 16 loops or more. Loops that do not repeat agree by chance about 1/p, so many
    loops that agree fairly well are as strong evidence as a few that agree very well (real takes,
    gait for one, are noisier than synthetic loops)."""
    return opts.min_consistency - 0.2 * min(1.0, max(0.0, (loops - 4) / 12.0))


@dataclass
class _Candidate:
    tau: float
    chains: list[Chain]
    best: Chain
    loops: list[tuple[float, float]]
    consistency: float
    agreement: float
    period: float
    hit_rate: float
    alignment: Alignment
    errors: FloatArray
    plain: float = 0.0
    coverage: float = 0.0

    @property
    def score(self) -> float:
        return self.consistency * self.hit_rate


def _evaluate(h: FloatArray, g: FloatArray, dseed: FloatArray, thrs: list[float], z: FloatArray, tau: float,
              seeds: IntArray, opts: ExtractOptions, margin: int, total_var: float) -> _Candidate | None:
    followed = (follow_chain(dseed[i], int(s), thrs[i], tau, opts.search, opts.max_misses, margin)
                for i, s in enumerate(seeds))
    chains = [c for c in followed if c is not None]
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
    cut = [(c, loops_of(c, med)) for c in good]
    most = max(len(lp) for _, lp in cut)
    if most < 2:
        return None
    m = max(8, round(med))
    zv = detrended(z, med)
    # score a few: the chains cutting the most loops, closest to the median period first
    pick = sorted((e for e in cut if len(e[1]) >= max(2, most - 1)),
                  key=lambda e: (-len(e[1]), abs(e[0].period - med)))[:4]
    scored = [(linear_consistency(zv, lp, m)[0], len(lp), c, lp) for c, lp in pick]
    full = max((e for e in scored if e[1] == most), key=lambda e: e[0])
    short = [e for e in scored if e[1] < most]
    alt = max(short, key=lambda e: e[0]) if short else None
    r_lin, _, best, loops = alt if alt is not None and alt[0] > full[0] + 0.1 else full
    # loops differ in timing inside too (stance and swing): judge them once time-aligned
    al = align(h, g, loops, med, opts.k)
    r_warp, errors = warped_consistency(zv, al, m)
    # the same without the drift removal: at a wrong sub-period the loops alternate, which shows here
    r_plain = warped_consistency(z, al, m)[0]
    r = max(r_lin, r_warp)
    hit = best.hit_rate
    return _Candidate(tau=tau, chains=chains, best=best, loops=loops, consistency=r, agreement=agreement, period=med,
                      hit_rate=hit, alignment=al, errors=errors, plain=r_plain)


def extract(t_s: ArrayLike, values: ArrayLike, *,
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
    work = prepare(t, v, quaternions, angles, angle_unit, opts.gap_factor)
    try:
        return _extract(work, names, opts, seed)
    except NoPeriodFoundError as exc:
        if work.notes:   # say what was done to the input (a gap that cut it short, dropped samples)
            raise NoPeriodFoundError(f"{exc} (note: {'; '.join(work.notes)})") from None
        raise


def _extract(work: Prepared, names: tuple[str, ...], opts: ExtractOptions, seed: int) -> Cycle:
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
    z = principal_subspace(z, opts.max_components, rng)
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
    cands = acf_candidates(feat, t_min, t_max, opts.max_candidates)
    dz = h[:, k * z.shape[1]:]             # the radius-k smoothed derivative
    dseed = distance_rows(h, g, seeds)
    matched = seed_matches(dseed, seeds, k)
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


def _finish(work: Prepared, x: FloatArray, factor: int, z: FloatArray, h: FloatArray, g: FloatArray, cand: _Candidate,
            seeds: IntArray, matches: list[IntArray], opts: ExtractOptions, names: tuple[str, ...],
            margin: int, total_var: float, t_min: int, t_max: int, sd: FloatArray, active: BoolArray) -> Cycle:
    notes = list(work.notes)
    # Refine the cut points against the first average loop (a matched filter over a quarter loop each
    # side, instead of the seed's single instant), then cut, align and judge again.
    m_r = max(16, round(cand.period))
    mean0 = at_positions(z, cand.alignment.positions(np.linspace(0.0, 1.0, m_r + 1)).reshape(-1))
    mean0 = mean0.reshape(len(cand.alignment.loops), m_r + 1, -1).mean(axis=0)
    top = np.argsort(-z.var(axis=0), kind="stable")[:12]   # the strongest components carry the timing
    cand.best.cuts = refine_cuts(z[:, top], cand.best.cuts, mean0[:, top], cand.period)
    loops0 = loops_of(cand.best, cand.period)
    if len(loops0) >= 2:
        cand.loops = loops0
        cand.alignment = align(h, g, loops0, cand.period, opts.k)
        cand.consistency, cand.errors = warped_consistency(detrended(z, cand.period), cand.alignment, m_r)
    al = cand.alignment
    consistency = cand.consistency
    # Leave out loops whose shape deviates far more than the others (a turn, a stumble).
    bad = outliers(cand.errors)
    if bad.any():
        notes.append(f"{int(bad.sum())} loop(s) left out of the average: their shape differs from the others")
        kept = [lp for lp, b in zip(al.loops, bad, strict=True) if not b]
        al = align(h, g, kept, cand.period, opts.k)
        consistency = warped_consistency(detrended(z, cand.period), al, max(8, round(cand.period)))[0]
    loops = al.loops
    # period: mean over the loops spanned, or median loop duration
    period_s = _period(work, z, cand, al, opts, total_var)
    m = max(8, round(period_s / (work.dt / factor)))   # the output at the input's rate
    u = np.linspace(0.0, 1.0, m + 1)
    positions = al.positions(u) * factor
    # average (eq. 5.4); rotation vectors about the take's mean rotation average as an approximate
    # Karcher mean
    stack = at_positions(x, positions.reshape(-1)).reshape(len(loops), m + 1, -1)
    mean = stack.mean(axis=0)

    # stitching (eq. 5.5)
    d_ex = mean[0] - mean[-1]
    closure = float(np.sqrt(np.mean((d_ex[active] / sd[active]) ** 2)))
    mean = mean + (u - 0.5)[:, None] * d_ex[None, :]
    mean[-1] = mean[0]

    values = to_input(work, mean, len(names))
    aligned = None
    if opts.keep_aligned:
        aligned = np.stack([to_input(work, stack[li], len(names)) for li in range(len(loops))])
    to_s = work.dt
    cuts_s = work.t0 + cand.best.cuts * to_s
    spans = work.t0 + np.array(loops) * to_s
    raw = raw_period(matches, seeds, z.shape[0], margin, t_min, t_max)
    confidence = float(np.clip(consistency, 0.0, 1.0) * cand.agreement)
    return Cycle(period_s=float(period_s), times_s=u * period_s, values=values, channels=names,
                 loops=len(loops), cuts_s=cuts_s, loop_spans_s=spans, confidence=confidence,
                 consistency=float(consistency), seed_agreement=float(cand.agreement),
                 raw_period_s=float(raw * to_s), closure_error=closure, aligned=aligned,
                 quaternions=tuple((c[0], c[1], c[2], c[3]) for kind, c, _ in work.columns if kind == "quat"),
                 notes=tuple(notes))


def _period(work: Prepared, z: FloatArray, cand: _Candidate, al: Alignment, opts: ExtractOptions,
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
    mean0 = at_positions(z, al.positions(u0).reshape(-1)).reshape(len(al.loops), m0 + 1, -1).mean(axis=0)
    n = z.shape[0]
    extra = 0.0
    t_first, t_last = first, last
    for end in ("head", "tail"):
        seg = z[0:math.floor(first) + 1] if end == "head" else z[math.ceil(last):n]
        if seg.shape[0] < 4 or seg.shape[0] >= 1.3 * per:
            continue   # nothing there, or more than a loop of something else (a pause, a turn)
        s01 = np.linspace(0.0, 1.0, seg.shape[0])[None, :]

        def misfit(fr: FloatArray, seg: FloatArray = seg, s01: FloatArray = s01, end: str = end) -> FloatArray:
            ph = (1.0 - fr[:, None] * (1.0 - s01)) if end == "head" else fr[:, None] * s01
            fit = at_positions(mean0, ph.reshape(-1) * m0).reshape(fr.size, seg.shape[0], -1)
            out: FloatArray = np.mean(np.sum((fit - seg[None]) ** 2, axis=2), axis=1)
            return out

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
