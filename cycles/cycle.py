"""``Cycle``: one closed motion loop extracted from a performance, with how it was found.

A cycle is sampled on a uniform grid from 0 to ``period_s`` inclusive; its first and last samples are
equal (the loop is closed). ``at(t)`` evaluates it anywhere, periodically, through a cubic spline with
periodic end conditions (C2 at the seam). Quaternion channels stay unit quaternions.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.interpolate import CubicSpline

if TYPE_CHECKING:
    from cycles._types import FloatArray


@dataclass(frozen=True, eq=False)
class Cycle:
    """One closed loop and the evidence for it.

    Attributes:
        period_s: the loop's duration (the refined period estimate).
        times_s: the sample times, ``linspace(0, period_s, M + 1)``.
        values: ``(M + 1, C)`` in the input's channels and units; ``values[0] == values[-1]``.
        channels: the channel names.
        loops: how many performed loops were averaged.
        cuts_s: every cut point found in the input, in the input's time base (seconds): the times at
            which the performance passed the cycle's start.
        loop_spans_s: ``(loops, 2)`` start and end time in the input of each loop that was averaged.
        confidence: 0..1, consistency times seed agreement.
        consistency: R = 1 - mean squared deviation of the aligned loops from the cycle / variance,
            on standardised channels.
        seed_agreement: share of the random seeds whose period agreed with the median.
        raw_period_s: the period of the thesis's eq. 5.3 (smallest feasible period, before refinement).
        closure_error: the gap ``c(0) - c(T)`` that stitching closed, as an RMS over channels in units
            of each channel's standard deviation.
        aligned: ``(loops, M + 1, C)`` the averaged input loops, time-aligned to the cycle, or None.
        quaternions: column index groups (w, x, y, z) that hold unit quaternions.
        notes: plain-language remarks (a gap that limited the input, loops left out and why).
    """

    period_s: float
    times_s: FloatArray
    values: FloatArray
    channels: tuple[str, ...]
    loops: int
    cuts_s: FloatArray
    loop_spans_s: FloatArray
    confidence: float
    consistency: float
    seed_agreement: float
    raw_period_s: float
    closure_error: float
    aligned: FloatArray | None = None
    quaternions: tuple[tuple[int, int, int, int], ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)
    elapsed_ms: float = 0.0

    @cached_property
    def _spline(self) -> CubicSpline:
        return CubicSpline(self.times_s, self.values, bc_type="periodic", axis=0)

    def at(self, t: float | FloatArray) -> FloatArray:
        """The cycle at time(s) ``t`` (seconds, any real value: it loops). Shape ``(C,)`` or ``(len(t), C)``."""
        tt = np.mod(np.asarray(t, np.float64), self.period_s)
        out = np.asarray(self._spline(tt))
        for q in self.quaternions:
            idx = list(q)
            part = out[..., idx]
            out[..., idx] = part / np.linalg.norm(part, axis=-1, keepdims=True)
        return out

    def resampled(self, samples: int) -> Cycle:
        """The same loop on ``samples + 1`` uniform samples (the spline, so smooth)."""
        if samples < 2:
            raise ValueError("a cycle needs at least 2 intervals")
        times = np.linspace(0.0, self.period_s, samples + 1)
        vals = self.at(times)
        vals[-1] = vals[0]
        return replace(self, times_s=times, values=vals, aligned=None)

    def time_scaled(self, period_s: float) -> Cycle:
        """The same loop played in ``period_s`` seconds."""
        if not period_s > 0:
            raise ValueError("period_s must be positive")
        f = period_s / self.period_s
        return replace(self, period_s=float(period_s), times_s=self.times_s * f)

    def shifted(self, dt_s: float) -> Cycle:
        """The loop started ``dt_s`` seconds later: the new cycle at t is this one at t + dt_s."""
        vals = self.at(self.times_s + dt_s)
        vals[-1] = vals[0]
        return replace(self, values=vals, aligned=None)

    def summary(self) -> dict[str, Any]:
        """The figures a report or ``--json`` shows (no per-sample arrays)."""
        return {
            "period_s": self.period_s,
            "raw_period_s": self.raw_period_s,
            "loops": self.loops,
            "confidence": self.confidence,
            "consistency": self.consistency,
            "seed_agreement": self.seed_agreement,
            "cuts_s": [float(c) for c in self.cuts_s],
            "loop_spans_s": [[float(a), float(b)] for a, b in self.loop_spans_s],
            "closure_error": self.closure_error,
            "samples": len(self.times_s) - 1,
            "channels": list(self.channels),
            "notes": list(self.notes),
            "elapsed_ms": self.elapsed_ms,
        }

    def write_csv(self, path: str) -> None:
        """The loop as CSV: a ``t`` column (seconds, 0..period inclusive) and one column per channel.

        Raises:
            OSError: the file cannot be written.
        """
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", *self.channels])
            for t, row in zip(self.times_s, self.values, strict=True):
                w.writerow([repr(float(t)), *(repr(float(v)) for v in row)])


def layer_onto(new: Cycle, master: Cycle, master_start_s: float) -> Cycle:
    """Fit a cycle performed while ``master`` was playing onto the master's clock.

    The performer followed the playback, which started (phase 0 of ``master``) at ``master_start_s`` in
    the new take's time base. The new cycle is time-scaled to the master period and shifted so that its
    time 0 is the master's phase 0: played together from the same instant, the layers stay in step.
    Ciccone 2019 (sections 5.2 and 5.4.2) performs layers over the playback of earlier ones and leaves
    the fine synchronisation to the MoCurve re-timing; this coarse alignment from the known playback
    phase is perfcap's (``docs/design/cycles.md``).

    Args:
        new: the cycle extracted from the take performed over the playback.
        master: the cycle that was playing.
        master_start_s: when the master's phase 0 played, in the new take's time base (seconds).
    """
    scaled = new.time_scaled(master.period_s)
    # The new cycle's time 0 is its first cut; where did the master's loop stand at that moment?
    first_cut = float(new.loop_spans_s[0, 0]) if len(new.loop_spans_s) else float(new.cuts_s[0])
    elapsed = first_cut - master_start_s
    phase = math.fmod(elapsed / master.period_s, 1.0)
    if phase < 0:
        phase += 1.0
    # At master phase phi, the new loop is (phi - phase) of a loop past its own start.
    return scaled.shifted(-phase * master.period_s)
