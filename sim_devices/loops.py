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


#: the seeded families the cycle extraction sweeps run on (tests and ``benchmarks/bench_cycle_sweep.py``)
SWEEP_RATES_HZ = (50.0, 60.0, 100.0, 120.0, 200.0)
#: in ``random_harmonic_take`` every channel's fundamental is at least this share of its largest harmonic
MIN_FUNDAMENTAL = 0.25


@dataclass(frozen=True)
class SweepTake:
    """One take of a seeded family, with what it is (for messages)."""

    t: np.ndarray
    values: np.ndarray
    period_s: float             # the truth (the mean loop duration); NaN for takes with no period
    about: dict[str, float]


def random_harmonic_take(seed: int) -> SweepTake:
    """A jittered take whose loop shape has random harmonic content in which a higher harmonic may
    dominate: 1-12 channels, 3-8 whole loops of a nominal 0.4-2.5 s, each loop +-10 %, 1-5
    harmonics with amplitudes uniform in [0, 1] (the fundamental at least ``MIN_FUNDAMENTAL`` of each
    channel's largest, so the take's period is the loop's and not a part of it), value noise of
    standard deviation 0-0.1 (the largest harmonic's amplitude is 1), sampled at one of
    ``SWEEP_RATES_HZ`` with the stamps' usual jitter."""
    rng = np.random.default_rng(seed)
    channels = int(rng.integers(1, 13))
    n_loops = int(rng.integers(3, 9))
    harmonics = int(rng.integers(1, 6))
    period = float(rng.uniform(0.4, 2.5))
    rate = float(rng.choice(SWEEP_RATES_HZ))
    noise = float(rng.uniform(0.0, 0.1))
    base = jittered_loops(n_loops, period_s=period, jitter=0.1, rate_hz=rate, channels=channels,
                          harmonics=harmonics, noise=0.0, seed=seed)
    amp = rng.uniform(0.0, 1.0, (channels, harmonics))
    amp[:, 0] = np.maximum(amp[:, 0], MIN_FUNDAMENTAL * amp.max(axis=1))
    amp /= amp.max(axis=1, keepdims=True)
    shape = LoopTake(t=base.t, values=base.values, durations_s=base.durations_s, boundaries_s=base.boundaries_s,
                     start_phase=base.start_phase, amplitudes=amp,
                     phases=rng.uniform(0.0, 2 * np.pi, (channels, harmonics)))
    values = shape.template(shape.phase_at(base.t) + base.start_phase)
    values = values + rng.normal(0.0, noise, values.shape)
    about = {"channels": channels, "loops": n_loops, "harmonics": harmonics, "noise": round(noise, 3), "rate_hz": rate}
    return SweepTake(base.t, values, base.period_s, about)


def random_walk_take(seed: int) -> SweepTake:
    """A take with no period: 1-12 channels of 200-3,000 samples at 50-200 Hz of a Gaussian random
    walk, an integrated one (smooth, like a drifting position) or a walk with heavy-tailed steps
    (Student's t, 2 degrees of freedom: long still stretches and jumps), by ``seed % 3``."""
    rng = np.random.default_rng(seed)
    channels = int(rng.integers(1, 13))
    n = int(rng.integers(200, 3001))
    rate = float(rng.choice((50.0, 100.0, 120.0, 200.0)))
    kind = seed % 3
    x = np.cumsum(rng.normal(0.0, 1.0, (n, channels)), axis=0)
    if kind == 1:
        x = np.cumsum(x, axis=0)
    elif kind == 2:
        x = np.cumsum(rng.standard_t(2, (n, channels)), axis=0)
    return SweepTake(np.arange(n) / rate, x, float("nan"),
                     {"channels": channels, "samples": n, "rate_hz": rate, "kind": kind})


def paused_take(seed: int) -> SweepTake:
    """Loops, one long pause, loops again: 3-6 jittered loops on each side (one performance, 1-12
    channels, noise 0-0.05, 50-200 Hz) around either a stillness (the pose held, with sensor noise)
    or a gap in the stamps (the recording stopped), of 2-10 loops or 5-40 s, whichever is longer, by
    ``seed % 2``. ``about`` holds the pause's start and end times (s)."""
    rng = np.random.default_rng(seed)
    channels = int(rng.integers(1, 13))
    before, after = int(rng.integers(3, 7)), int(rng.integers(3, 7))
    period = float(rng.uniform(0.4, 2.0))
    rate = float(rng.choice(SWEEP_RATES_HZ))
    noise = float(rng.uniform(0.0, 0.05))
    take = jittered_loops(before + after, period_s=period, rate_hz=rate, channels=channels, noise=noise, seed=seed)
    split = float(take.boundaries_s[before])
    pause = max(float(rng.uniform(2.0, 10.0)) * period, float(rng.uniform(5.0, 40.0)))
    i = int(np.searchsorted(take.t, split))
    t = take.t.copy()
    t[i:] += pause
    values = take.values
    if seed % 2 == 0:   # the pose held: samples through the pause
        dt = 1.0 / rate
        held_t = split + dt * np.arange(1, int(pause / dt))
        held = values[i - 1] + rng.normal(0.0, max(noise, 1e-3), (held_t.size, channels))
        t = np.concatenate([t[:i], held_t, t[i:]])
        values = np.concatenate([values[:i], held, values[i:]])
    return SweepTake(t, values, take.period_s, {"channels": channels, "before": before, "after": after,
                                              "rate_hz": rate, "pause_from": split, "pause_to": split + pause,
                                              "held": float(seed % 2 == 0)})
