"""Cycle extraction: one clean closed loop from several imprecise performed loops.

The method is Ciccone 2019, *Intuitive Control of Animated Scenes* (ETH Diss. 25792), chapter 5,
section 5.3 "Cycle Specification", with perfcap's own additions where the thesis is silent or where its
plain method fails on long real takes; ``docs/design/cycles.md`` says which is which. This module owns
the pipeline (``extract``), its tuning (``ExtractOptions``), the acceptance of a candidate period, the
averaging and stitching, and the refined period; the steps it calls live in their own modules:

1. **Prepare** (:mod:`cycles.prepare`): sort and de-duplicate the stamps, keep every stretch between
   gaps of more than ``gap_factor`` sample intervals (one after the other, with breaks between them),
   resample to a uniform grid when the stamps are irregular, unwrap Euler angles, and map quaternions to
   rotation vectors about the take's chordal mean (with hemisphere continuity), so that everything below
   works on plain vectors.
2. **Descriptor space** (:mod:`cycles.candidates`): channels are standardised for matching only; wide
   inputs (hundreds or thousands of channels) are projected on their principal subspace (a randomised
   range finder), which keeps the distances the descriptor sees and makes the cost independent of the
   channel count. A coarse take is matched on a finer grid. The descriptor itself (eq. 5.1-5.2) is
   :mod:`cycles.descriptor`.
3. **Period candidates** (:mod:`cycles.candidates`): the prominent peaks of the summed autocorrelation of
   the smoothed derivatives (blind to offsets and slow trends) and of the values (where a higher
   harmonic dominates). It is only a prior: the descriptor decides.
4. **Chained matching** (:mod:`cycles.matching`; it replaces eq. 5.3's absolute grid, which fails on long
   real takes): for random seeds, follow the performance loop by loop, searching each next occurrence of
   the seed's instant (minimum of the descriptor distance d_D, eq. 5.2) near the previous match plus the
   current tempo. A loop that does not match (a turn) is a miss, not the end; the tempo is tracked, so
   drift does not break it; a long pause or a gap is jumped, and the loops after it are picked up. Each
   seed gives cut points; the period is the median over seeds.
5. **Acceptance** (here, with the consistency of :mod:`cycles.alignment`): a candidate needs consistent
   loops (R >= ``min_consistency``, a little less with many loops; R is measured with the motion's drift
   over one period removed, so walking on in world coordinates still repeats while a ramp or a random
   walk does not), found in most loops (``min_hit_rate``) over most of the moving take (``min_coverage``),
   and agreed on by most seeds (``min_agreement``). A wrong sub-period alternates: its loops, grouped by
   index modulo j, differ between the groups (an analysis of variance); then j times it is tried. The
   shortest accepted candidate that does not alternate wins unless another explains the motion clearly
   better (a multiple of the period never does). So neither half nor double periods come out, and input
   that does not repeat raises :class:`NoPeriodFoundError`. ``docs/design/cycles.md`` has the rules.
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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy import signal

from capture.errors import NoMotionError, NoPeriodFoundError
from cycles.alignment import (
    Alignment,
    align,
    alternation,
    detrended,
    linear_consistency,
    outliers,
    refine_cuts,
    warped_consistency,
)
from cycles.candidates import acf_candidates, principal_subspace
from cycles.cycle import Cycle
from cycles.descriptor import K_RADIUS, descriptors, distance_rows, parabolic_offset, window_sums
from cycles.matching import Chain, follow_chain, loops_of, numbered_loops, raw_period, seed_matches
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
        candidate_margin: a shorter candidate period wins over one whose loops explain the motion better
            if the share it leaves unexplained (the misfit 1 - R, unbiased for the number of loops,
            inside the loops it cut, and the loops it could not cut) is at most 1.5 times the better
            one's plus this.
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
    candidate_margin: float = 0.02
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


#: the extra consistency a candidate of only two loops needs
TWO_LOOPS_R = 0.1


def _needed_r(opts: ExtractOptions, loops: int) -> float:
    """The consistency a candidate with ``loops`` loops needs: ``min_consistency`` from 3 to 4 loops,
    then down to 0.2 less at 16 loops or more; with only two, TWO_LOOPS_R more (at most 0.95). Loops
    that do not repeat agree by chance about 1/p, so many loops that agree fairly well are as strong
    evidence as a few that agree very well (real takes, gait for one, are noisier than synthetic
    loops), and two stretches of a wandering signal agree fairly well quite often."""
    if loops <= 2:
        return min(0.95, opts.min_consistency + TWO_LOOPS_R)
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
    multiple: int = 0     # j > 1: the loops alternate with j parts, so this is 1/j of a longer loop
    doubt: dict[int, float] = field(default_factory=dict)   # parts j it may be 1/j of (and their F)

    @property
    def misfit(self) -> float:
        """1 - R, unbiased for the number of loops: p loops deviate from their own average by (p - 1)/p
        of what they deviate from the motion's true loop, so a candidate with fewer (longer) loops does
        not look better for that alone."""
        p = max(2, len(self.loops))
        return (1.0 - self.consistency) * p / (p - 1)

    @property
    def unexplained(self) -> float:
        """The share of the motion between the first and last cut that the loops do not explain: the
        misfit inside the loops that were cut, and all of the loops that could not be. A 'period' whose
        loops fit only where they were cut (a part of the loop that recurs, cut between holes) explains
        less than the true period, and a multiple of the period no more."""
        return self.hit_rate * self.misfit + (1.0 - self.hit_rate)

    @property
    def score(self) -> float:
        return self.consistency * self.hit_rate


#: loops a candidate needs when only the drift removal makes them alike (walking on in world
#: coordinates): two or three oscillations of a random walk, its drift removed, agree by chance
MIN_DRIFT_LOOPS = 4
#: a candidate is 1/j of the loop when its loops grouped by index modulo j differ more between the
#: groups than inside them: an F statistic (about 1 when every loop is the same motion) above
#: ALTERNATION_F, with an effect (the between-group share of the variance) of at least
#: ALTERNATION_EVIDENCE / F and never under ALTERNATION_EFFECT: a clear difference may be small, a
#: small F needs a large one (few loops make F noisy)
ALTERNATION_F = 3.0
ALTERNATION_EVIDENCE = 0.12
ALTERNATION_EFFECT = 0.01
#: an F above this (with at least ALTERNATION_EFFECT) is a hint: the longer loop is tried as well
ALTERNATION_HINT = 1.5
#: the most parts a loop is tested for (a loop whose j-th harmonic dominates looks like 1/j of it)
ALTERNATION_MAX_PARTS = 8


def _alternation(z: FloatArray, al: Alignment, ks: list[int], tau: float, m: int,
                 t_max: int) -> tuple[int, dict[int, float]]:
    """Whether the loops alternate (:func:`~cycles.alignment.alternation`, for ``j`` from 2 to
    ``ALTERNATION_MAX_PARTS``, on the take with the drift over ``j`` loops removed, which keeps a
    motion of period ``j * tau`` whole). Returns the smallest ``j`` for which they clearly do (0 if
    none), and the ``j`` worth trying as the loop too, with their F: those with a hint of alternation,
    and (F = NaN) those that could not be tested (too few loops cut for two in each group) though
    ``j * tau`` fits the take twice."""
    doubt: dict[int, float] = {}
    for j in range(2, ALTERNATION_MAX_PARTS + 1):
        if j * tau > t_max:
            break
        f, effect = alternation(detrended(z, j * tau), al, ks, m, j)
        if not math.isfinite(f):
            doubt[j] = float("nan")
        elif f > ALTERNATION_F and effect >= max(ALTERNATION_EFFECT, ALTERNATION_EVIDENCE / f):
            return j, doubt
        elif f > ALTERNATION_HINT and effect >= ALTERNATION_EFFECT:
            doubt[j] = f
    return 0, doubt


#: a stillness is a pause (no loop holds it; the chains pick the loops up after it) when it lasts
#: this many candidate periods: a hold inside a loop is shorter than the loop
PAUSE_LOOPS = 2.0
#: ... with the change over a quarter loop, averaged over half a loop, under this share of its median
#: over the moving samples
PAUSE_SPEED = 0.2
#: the matching wants at least this many times the descriptor radius k samples per loop
UPSAMPLE_BELOW = 8
#: the fewest input samples a loop may have
MIN_LOOP_SAMPLES = 6


def _upsampling(lags: list[float], k: int) -> int:
    """How many times finer than the input the matching should sample the take (1 to 4): enough for
    the shortest repetition the autocorrelation of the values shows (``lags``, samples) to span
    ``UPSAMPLE_BELOW * k`` samples."""
    if not lags or min(lags) >= UPSAMPLE_BELOW * k:
        return 1
    return int(min(4, math.ceil(UPSAMPLE_BELOW * k / min(lags))))


#: candidates whose loops repeat less well than this have their cuts refined before they are judged
REFINE_BELOW = 0.98


def _refined(z: FloatArray, chain: Chain, al: Alignment, tau: float, m: int) -> Chain | None:
    """A copy of ``chain`` with its cuts refined against the average of the loops ``al`` aligns
    (:func:`~cycles.alignment.refine_cuts`), or None when nothing moved."""
    mean0 = at_positions(z, al.positions(np.linspace(0.0, 1.0, m + 1)).reshape(-1))
    mean0 = mean0.reshape(len(al.loops), m + 1, -1).mean(axis=0)
    top = np.argsort(-z.var(axis=0), kind="stable")[:12]   # the strongest components carry the timing
    cuts = refine_cuts(z[:, top], chain.cuts, mean0[:, top], tau)
    if np.array_equal(cuts, chain.cuts):
        return None
    return replace(chain, cuts=cuts)


def _runs(mask: BoolArray) -> list[tuple[float, float]]:
    """The runs of True in ``mask`` as ``(first, last)`` rows."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return [(float(a), float(b)) for a, b in zip(starts, ends, strict=True)]


def _speed(z: FloatArray, lag: int) -> FloatArray:
    """How far the take moves around each sample: ``|z[i + lag] - z[i - lag]|`` (clamped at the ends)."""
    n = z.shape[0]
    i = np.arange(n)
    out: FloatArray = np.linalg.norm(z[np.minimum(i + lag, n - 1)] - z[np.maximum(i - lag, 0)], axis=1)
    return out


def _pauses(z: FloatArray, tau: float, is_moving: BoolArray, moving: IntArray) -> list[tuple[float, float]]:
    """The pauses for a candidate period ``tau``: stretches inside the motion (between its first and
    last moving sample) of at least PAUSE_LOOPS loops where the change over a quarter loop
    (:func:`_speed`), averaged over half a loop, stays under PAUSE_SPEED of its median over the moving
    samples. Over a quarter loop the motion changes by about its amplitude and the sensor noise of a
    held pose does not; the averaging keeps that noise from breaking a pause into pieces, and the length
    keeps a hold inside a loop from being a pause."""
    if moving.size < 2:
        return []
    reach = _speed(z, max(1, round(tau / 4)))
    ref = float(np.median(reach[is_moving]))
    if not ref > 0:
        return []
    n = reach.size
    w = max(3, round(tau / 2))
    c = np.concatenate([[0.0], np.cumsum(reach)])
    i = np.arange(n)
    lo, hi = np.clip(i - w // 2, 0, n), np.clip(i - w // 2 + w, 0, n)
    slow = (c[hi] - c[lo]) / np.maximum(hi - lo, 1) < PAUSE_SPEED * ref
    return [(a, b) for a, b in _runs(slow)
            if b - a >= PAUSE_LOOPS * tau and moving[0] < a and b < moving[-1]]


def _evaluate(h: FloatArray, g: FloatArray, dseed: FloatArray, thrs: list[float], z: FloatArray, tau: float,
              seeds: IntArray, opts: ExtractOptions, margin: int, t_max: int,
              breaks: list[tuple[float, float]], moving: BoolArray) -> _Candidate | None:
    followed = (follow_chain(dseed[i], int(s), thrs[i], tau, opts.search, opts.max_misses, margin, breaks, moving)
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
    cut = [(c, numbered_loops(c, med)) for c in good]
    most = max(len(lp) for _, lp in cut)
    if most < 2:
        return None
    m = max(8, round(med))
    zv = detrended(z, med)
    # score a few: the chains cutting nearly the most loops (a chain that slipped onto another
    # instant of the motion after a pause can cut one more), closest to the median period first; the
    # most consistent wins, and among those about as consistent, the one cutting the most loops
    pick = sorted((e for e in cut if len(e[1]) >= max(2, math.floor(0.75 * most))),
                  key=lambda e: (-len(e[1]), abs(e[0].period - med)))[:6]
    scored = [(linear_consistency(zv, [a for a, _ in lp], m)[0], len(lp), c, lp) for c, lp in pick]
    top_r = max(e[0] for e in scored)
    r_lin, _, best, numbered = max((e for e in scored if e[0] >= top_r - 0.02), key=lambda e: (e[1], e[0]))
    loops = [a for a, _ in numbered]
    # loops differ in timing inside too (stance and swing): judge them once time-aligned
    al = align(h, g, loops, med, opts.k)
    r_warp, errors = warped_consistency(zv, al, m)
    # A seed instant that the motion passes twice a loop (one channel, whose value and slope recur)
    # can cut some loops at the wrong pass: cuts moved to where the data best fits the average loop
    # (as the result's are, step 6) judge the period by the loops it really has.
    refined = _refined(z, best, al, med, m) if r_warp < REFINE_BELOW else None
    if refined is not None:
        numbered_r = numbered_loops(refined, med)
        if len(numbered_r) >= 2:
            al_r = align(h, g, [a for a, _ in numbered_r], med, opts.k)
            r_r, errors_r = warped_consistency(zv, al_r, m)
            if r_r > r_warp:
                best, numbered, al, r_warp, errors = refined, numbered_r, al_r, r_r, errors_r
                loops = [a for a, _ in numbered]
                r_lin = linear_consistency(zv, loops, m)[0]
    # the same without the drift removal: at a wrong sub-period the loops alternate, which shows here
    # (both, like R, the better of the linear and the warped loops: a warp can fail where a plain cut
    # fits, one channel whose anchors recur inside a loop)
    r_plain = max(warped_consistency(z, al, m)[0], linear_consistency(z, loops, m)[0])
    r = max(r_lin, r_warp)
    hit = best.hit_rate
    multiple, doubt = _alternation(z, al, [k for _, k in numbered], med, m, t_max)
    return _Candidate(tau=tau, chains=chains, best=best, loops=loops, consistency=r, agreement=agreement, period=med,
                      hit_rate=hit, alignment=al, errors=errors, plain=r_plain, multiple=multiple, doubt=doubt)


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
    factor: float = 1
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
    k = opts.k
    # Coarse takes (a phone at 20-50 Hz, a quick motion): the descriptor's radius of k samples must be a
    # small part of a loop. When the shortest repetition the values show is under UPSAMPLE_BELOW * k
    # samples, the matching runs on the take interpolated to about that many samples per loop (the loop
    # is still averaged from the input's samples).
    lags = acf_candidates(z, MIN_LOOP_SAMPLES, (n - 1) // 2, opts.max_candidates)
    up = _upsampling(lags, k)
    if up > 1:
        z = at_positions(z, np.arange((n - 1) * up + 1) / up)
        work = replace(work, dt=work.dt / up)
        factor = factor / up
        n = z.shape[0]
        lags = acf_candidates(z, MIN_LOOP_SAMPLES * up, (n - 1) // 2, opts.max_candidates)
    total_var = float(np.sum(z.var(axis=0)))

    h, g = descriptors(z, work.dt, k)
    margin = k + 2
    t_min = max(2 * k + 2, MIN_LOOP_SAMPLES * up,
                math.ceil(opts.min_period_s / work.dt) if opts.min_period_s else 0)
    t_max = (n - 1) // 2
    if opts.max_period_s:
        t_max = min(t_max, int(opts.max_period_s / work.dt))
    if t_max < t_min:
        raise NoPeriodFoundError(f"the take ({n * work.dt:.3g} s) is too short for two loops of at least"
                                 f" {t_min * work.dt:.3g} s")

    # The moving part of the take (a performer may stand still before and after looping, or between):
    # where the radius-k smoothed derivative is not small, and neither is the change over an eighth
    # of the shortest repetition (at a high rate, sensor noise in a held pose changes as much in k
    # samples as the motion does; over the longer reach it does not). Pauses are found per candidate.
    speed = np.linalg.norm(h[:, k * z.shape[1]:], axis=1)
    reach = _speed(z, max(k, round(min(lags) / 8)) if lags else k)
    reach_moving = reach > 0.1 * np.percentile(reach, 95)
    is_moving = (speed > 0.1 * np.percentile(speed, 95)) & reach_moving
    moving = np.flatnonzero(is_moving)
    extent = float(moving[-1] - moving[0]) if moving.size > 1 else float(n)
    joints = [(float(j) / factor, float(j) / factor) for j in work.starts[1:]]

    # seeds: interior instants where the curve moves (|h_i| at or above its 25th percentile there)
    hn = np.linalg.norm(h, axis=1)
    inner = np.arange(margin, n - margin)
    inner_moving = inner[is_moving[inner]] if is_moving[inner].any() else inner
    pool = inner_moving[hn[inner_moving] >= np.percentile(hn[inner_moving], 25.0)]
    if pool.size == 0:
        raise NoMotionError("the input barely moves")
    seeds = np.sort(rng.choice(pool, size=min(opts.seeds, pool.size), replace=False))

    # prior: autocorrelation of smoothed derivatives (offsets and slow trends do not count), and of the
    # values (the derivatives weigh harmonic h by h, so a loop whose higher harmonics dominate and drift
    # in phase with the tempo may show no derivative peak at the loop itself)
    feat = window_sums(np.diff(z, axis=0), k)[:, k * z.shape[1]:]
    cands = acf_candidates(feat, t_min, t_max, opts.max_candidates)
    for lag in lags:
        if t_min <= lag <= t_max and all(abs(lag - d) > 0.05 * d for d in cands):
            cands.append(lag)
    dseed = distance_rows(h, g, seeds)
    matched = seed_matches(dseed, seeds, k)
    thrs = [thr for _, thr in matched]

    def is_valid(c: _Candidate) -> bool:
        needed = _needed_r(opts, len(c.loops))
        return (c.consistency >= needed and c.hit_rate >= opts.min_hit_rate
                and c.coverage >= opts.min_coverage and c.agreement >= opts.min_agreement
                and (c.plain >= needed or len(c.loops) >= MIN_DRIFT_LOOPS))

    # A period must explain the loops it cuts (R), be found in most of them (hit rate) over most of
    # the motion (coverage), and most seeds must agree on it. Candidates are tried shortest first. One
    # whose loops alternate (loops j apart far more alike than neighbours) is 1/j of the loop: j times
    # it is tried next, whether or not the autocorrelation showed it (a dominant higher harmonic can
    # hide the fundamental's peak). One that repeats even with the drift left in and does not
    # alternate is the answer (longer candidates can only be its multiples), so the rest need not be
    # tried.
    evaluated: list[_Candidate] = []
    queue = sorted(cands)
    tried: list[float] = []
    longer: list[float] = []    # the loops that alternating candidates are parts of, still to be tried
    while queue:
        tau = queue.pop(0)
        longer = [t for t in longer if t != tau]
        if any(abs(tau - t) <= 0.05 * t for t in tried):
            continue
        tried.append(tau)
        pauses = _pauses(z, tau, is_moving, moving)
        c = _evaluate(h, g, dseed, thrs, z, tau, seeds, opts, margin, t_max, sorted(pauses + joints), is_moving)
        if c is None:
            continue
        paused = sum(max(0.0, min(b, moving[-1]) - max(a, moving[0])) for a, b in pauses) if moving.size else 0.0
        # the share of the moving take the loops span, the ends short of a loop (a partial loop, which
        # no cut can hold) counted in
        ends = 0.0
        if moving.size > 1:
            ends = (min(max(0.0, float(c.best.cuts[0] - moving[0])), c.period)
                    + min(max(0.0, float(moving[-1] - c.best.cuts[-1])), c.period))
        c.coverage = min(1.0, (float(c.best.steps()[0].sum()) + ends) / max(extent - paused, 1.0))
        evaluated.append(c)
        if not is_valid(c):
            continue
        if c.multiple:
            whole = c.multiple * c.period
            if whole <= t_max:
                queue = sorted([*queue, whole])
                longer.append(whole)
            continue
        # where the loops may alternate (a hint, or too few loops cut to tell), the longer loops they
        # might be parts of are tried too, and the loops that explain the motion best decide below
        for j in c.doubt:
            queue = sorted([*queue, j * c.period])
            longer.append(j * c.period)
        if c.plain >= _needed_r(opts, len(c.loops)) and not longer:
            break
    if not evaluated:
        raise NoPeriodFoundError("no period: the motion does not repeat (a cycle needs about two and a half"
                                 " loops or more of one repeated motion"
                                 + (f"; tried {len(cands)} candidate period(s))" if cands else ")"))
    valid = [c for c in evaluated if is_valid(c) and not c.multiple]
    if not valid:
        parts = [c for c in evaluated if is_valid(c)]
        if parts:
            p = min(parts, key=lambda c: c.period)
            raise NoPeriodFoundError(
                f"no consistent period: {p.period * work.dt:.3g} s repeats, but its loops alternate (loops"
                f" {p.multiple} apart are alike), so it is part of a longer loop of about"
                f" {p.multiple * p.period * work.dt:.3g} s, which does not repeat over enough loops")
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
        if best.plain < _needed_r(opts, len(best.loops)) and len(best.loops) < MIN_DRIFT_LOOPS and not why:
            why.append(f"its {len(best.loops)} loops are alike only with the drift removed (R = {best.plain:.2f}"
                       f" with it), which needs {MIN_DRIFT_LOOPS} loops or more")
        if not why:
            why.append(f"{len(best.loops)} loop(s) cut")
        raise NoPeriodFoundError(f"no consistent period: the best candidate ({best.period * work.dt:.3g} s) "
                                 + "; ".join(why))
    # The shortest valid candidate wins unless another explains the motion clearly better
    # (``_Candidate.unexplained`` under 1/1.5 of its own, less candidate_margin). A multiple of the
    # period repeats as well as the period, so it never does; a wrong sub-period was caught above or
    # is beaten here. Two loops warp onto each other almost perfectly, whatever they hold, so a
    # candidate with only two loops beats a shorter one only as the longer loop that one's loops may be
    # parts of (a clear F of alternation, or too few loops to test).
    def may_beat(o: _Candidate, c: _Candidate) -> bool:
        if o.unexplained * 1.5 + opts.candidate_margin >= c.unexplained:
            return False
        # three loops or more, or a period that is no multiple of the shorter one: no such trap
        ratio = o.period / c.period
        if len(o.loops) >= 3 or abs(ratio - round(ratio)) > 0.1 * ratio:
            return True
        # two loops at a multiple j: only where c could not be tested at j, or its F there is above
        # ALTERNATION_F (the difference too small to call it a part outright)
        return any(abs(o.period - j * c.period) <= 0.1 * o.period
                   for j, f in c.doubt.items() if not f <= ALTERNATION_F)

    ranked = sorted(valid, key=lambda c: c.period)
    cand = next((c for c in ranked if not any(may_beat(o, c) for o in valid if o is not c)),
                min(valid, key=lambda c: c.unexplained))

    return _finish(work, x_full, factor, z, h, g, cand, seeds, [mm for mm, _ in matched], opts, names, margin,
                   total_var, t_min, t_max, sd, active)


def _finish(work: Prepared, x: FloatArray, factor: float, z: FloatArray, h: FloatArray, g: FloatArray, cand: _Candidate,
            seeds: IntArray, matches: list[IntArray], opts: ExtractOptions, names: tuple[str, ...],
            margin: int, total_var: float, t_min: int, t_max: int, sd: FloatArray, active: BoolArray) -> Cycle:
    notes = list(work.notes)
    # Refine the cut points against the first average loop (a matched filter over a quarter loop each
    # side, instead of the seed's single instant), then cut, align and judge again.
    m_r = max(16, round(cand.period))
    refined = _refined(z, cand.best, cand.alignment, cand.period, m_r)
    loops0 = loops_of(refined, cand.period) if refined is not None else []
    if refined is not None and len(loops0) >= 2:
        cand.chains = [refined if ch is cand.best else ch for ch in cand.chains]
        cand.best = refined
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
    cuts_s = work.times(cand.best.cuts * factor)
    spans = work.times(np.array(loops) * factor)
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
    broken = (len(loops) < len(cand.loops) or bool(np.any(np.diff(cand.best.ks) != 1))
              or bool(cand.best.across.any()))
    use_median = opts.period_estimate == "median" or (
        opts.period_estimate == "auto" and len(loops) >= opts.median_from_loops and broken)
    if use_median:
        # The typical duration of the loops that make the cycle (turns and stumbles left out). Each loop's
        # duration is averaged over the seeds that cut it, each at its own instant, which evens out the
        # jitter of single cut points.
        pairs = []
        for ch in cand.chains:
            one = np.flatnonzero((np.diff(ch.ks) == 1) & ~ch.across[1:])
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
    cuts = chain.cuts
    lengths, counts = chain.steps()      # the stretches between cuts that cross no break
    span_len, span_loops = float(lengths.sum()), float(counts.sum())
    first, last = float(cuts[0]), float(cuts[-1])
    per = span_len / span_loops
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
        per = (span_len + (first - t_first) + (t_last - last)) / (span_loops + extra)
    return per * work.dt
