"""A seeded performer who repeats one motion several times, imprecisely: the ground truth for cycle
extraction tests, benchmarks and the demo.

Each loop has its own duration (the performer's tempo wanders by up to ``jitter``), the phase runs
linearly inside a loop, the values carry noise and the sampling instants are off by a fraction of a
sample from the time stamps that are reported. The take covers exactly ``n_loops`` whole loops (from
a random point of the motion), so its true period, the mean loop duration, is well defined.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LoopTake:
    """A synthetic take and its truth."""

    t: np.ndarray                 # reported time stamps (s), (n,)
    values: np.ndarray            # (n, channels)
    durations_s: np.ndarray       # each loop's duration (s), (n_loops,)
    boundaries_s: np.ndarray      # loop starts and the end of the last one (s), (n_loops + 1,)
    start_phase: float            # the template phase at every loop boundary
    amplitudes: np.ndarray        # (channels, harmonics)
    phases: np.ndarray            # (channels, harmonics)

    @property
    def period_s(self) -> float:
        """The true period: the mean loop duration."""
        return float(np.mean(self.durations_s))

    def template(self, phase: np.ndarray) -> np.ndarray:
        """The noise-free motion at loop phase ``phase`` (1 = one loop), (len(phase), channels)."""
        ph = np.asarray(phase, np.float64)[:, None, None]
        h = np.arange(1, self.amplitudes.shape[1] + 1)[None, None, :]
        return np.asarray(np.sum(self.amplitudes[None] * np.sin(2 * np.pi * h * ph + self.phases[None]), axis=2))

    def phase_at(self, t: np.ndarray) -> np.ndarray:
        """The performer's loop phase at times ``t`` (s): loop index plus the fraction of that loop."""
        t = np.asarray(t, np.float64)
        k = np.clip(np.searchsorted(self.boundaries_s, t, side="right") - 1, 0, len(self.durations_s) - 1)
        return np.asarray(k + (t - self.boundaries_s[k]) / self.durations_s[k])


def harmonic_shape(channels: int, harmonics: int, rng: np.random.Generator,
                   per_channel_harmonic: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Amplitudes and phases of a random smooth loop shape.

    With ``per_channel_harmonic`` channel c moves only at harmonic ``c % harmonics + 1`` with amplitude
    1/(that harmonic), as in the spec's three-channel test; otherwise every channel mixes harmonics
    1..``harmonics`` with amplitudes falling as 1/h and random signs.
    """
    amp = np.zeros((channels, harmonics))
    if per_channel_harmonic:
        for c in range(channels):
            h = c % harmonics
            amp[c, h] = 1.0 / (h + 1)
    else:
        amp[:] = rng.uniform(0.3, 1.0, (channels, harmonics)) / np.arange(1, harmonics + 1)[None, :]
        amp[:, 0] = np.maximum(amp[:, 0], 0.5)
    return amp, rng.uniform(0, 2 * np.pi, (channels, harmonics))


def jittered_loops(n_loops: int = 4, *, period_s: float = 1.0, jitter: float = 0.1, rate_hz: float = 120.0,
                   channels: int = 3, harmonics: int = 3, noise: float = 0.02, time_jitter: float = 0.2,
                   per_channel_harmonic: bool = False, irregular_mean_s: float | None = None,
                   random_start: bool = True, seed: int = 0) -> LoopTake:
    """A take of ``n_loops`` whole loops.

    Args:
        n_loops: loops performed.
        period_s: nominal loop duration; each loop lasts ``period_s * U[1 - jitter, 1 + jitter]``.
        jitter: relative spread of the loop durations.
        rate_hz: sample rate of the reported time stamps.
        channels: number of channels.
        harmonics: harmonics of the loop phase in the shape.
        noise: standard deviation of the value noise (the shape's amplitudes are about 1).
        time_jitter: each sample is taken up to this many sample periods away from its reported stamp.
        per_channel_harmonic: see :func:`harmonic_shape`.
        irregular_mean_s: if given, the stamps are irregular (exponential gaps of this mean, reported
            exactly) instead of a uniform grid.
        random_start: start the loops at a random point of the shape rather than at phase 0.
        seed: the random seed; equal seeds give equal takes.
    """
    if n_loops < 1 or rate_hz <= 0 or period_s <= 0 or channels < 1 or harmonics < 1:
        raise ValueError("n_loops, rate_hz, period_s, channels and harmonics must be positive")
    rng = np.random.default_rng(seed)
    amp, ph = harmonic_shape(channels, harmonics, rng, per_channel_harmonic)
    durations = period_s * rng.uniform(1 - jitter, 1 + jitter, n_loops)
    bounds = np.concatenate([[0.0], np.cumsum(durations)])
    total = float(bounds[-1])
    if irregular_mean_s is not None:
        gaps = rng.exponential(irregular_mean_s, int(total / irregular_mean_s * 1.5) + 10)
        t = np.concatenate([[0.0], np.cumsum(gaps)])
        t = t[t <= total]
        t_true = t
    else:
        dt = 1.0 / rate_hz
        t = np.arange(0.0, total + 1e-12, dt)
        t_true = np.clip(t + rng.uniform(-time_jitter, time_jitter, t.size) * dt, 0.0, total)
    start = float(rng.uniform(0, 1)) if random_start else 0.0
    take = LoopTake(t=t, values=np.empty((0, channels)), durations_s=durations, boundaries_s=bounds,
                    start_phase=start, amplitudes=amp, phases=ph)
    vals = take.template(take.phase_at(t_true) + start) + rng.normal(0.0, noise, (t.size, channels))
    return LoopTake(t=t, values=vals, durations_s=durations, boundaries_s=bounds, start_phase=start,
                    amplitudes=amp, phases=ph)
