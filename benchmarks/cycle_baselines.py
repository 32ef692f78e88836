"""Peer period estimators for the cycle benchmark (a helper module of ``bench_cycles.py``, not a benchmark).

Two baselines that ``cycles.extract`` is measured against (issue 6):

* :func:`acf_period`: the FFT autocorrelation estimate, a frequency analysis of the kind Ciccone 2019
  (section 5.1) sets aside because performed loops vary in duration: channels standardised, power
  spectra summed, the first peak at or above 0.9 of the highest peak after the first zero crossing,
  refined by a parabola through the peak and its neighbours.
* :func:`mstump_period`: stumpy's multi-dimensional matrix profile (``stumpy.mstump``): the period is
  the typical spacing between every subsequence and its nearest neighbour in the all-dimension
  profile. stumpy is an optional dependency (``pip install perfcap[bench]``); without it the function
  returns NaN. Its first call in a process pays numba's JIT compilation (about 10 s on 2 cores), so
  time a warm-up call separately (see :func:`mstump_warmup`).

Both work on plain arrays ``t (n,)`` in seconds and ``values (n, C)`` and return a period in seconds, or NaN
when they find none. They never raise on data that merely has no period.
"""

from __future__ import annotations

import importlib.util
import math
from typing import Any

import numpy as np

#: relative spread of the time steps above which the take is resampled to its median step
UNIFORM_TOL = 1e-3
#: the ACF peak threshold: the first peak at or above this share of the highest one is the period
ACF_PEAK_SHARE = 0.9
#: default mstump window, seconds (half a typical human loop; the period is not known beforehand)
MSTUMP_WINDOW_S = 0.5
#: share of the subsequences whose nearest-neighbour spacing must agree for it to count as the period
MSTUMP_SHARE = 0.1
#: channels per FFT block (bounds the memory at thousands of channels)
_BLOCK = 512


def _as_arrays(t: Any, values: Any) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, np.float64).reshape(-1)
    x = np.asarray(values, np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] != t.size:
        raise ValueError(f"values must be (n, channels) with n = len(t) = {t.size}, not {x.shape}")
    return t, x


def uniform(t: Any, values: Any) -> tuple[float, np.ndarray]:
    """The take on a uniform grid: ``(dt, values)``.

    Sorts the samples and drops repeated stamps; if the steps are not uniform (relative spread above
    :data:`UNIFORM_TOL`) every channel is linearly resampled at the median step.

    Raises:
        ValueError: bad shapes or fewer than 4 distinct stamps.
    """
    t, x = _as_arrays(t, values)
    order = np.argsort(t, kind="stable")
    t, x = t[order], x[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, x = t[keep], x[keep]
    if t.size < 4:
        raise ValueError("need at least 4 distinct time stamps")
    d = np.diff(t)
    dt = float(np.median(d))
    if np.max(np.abs(d - dt)) <= UNIFORM_TOL * dt:
        return dt, x
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    grid = grid[grid <= t[-1]]
    out = np.empty((grid.size, x.shape[1]))
    for c in range(x.shape[1]):
        out[:, c] = np.interp(grid, t, x[:, c])
    return dt, out


def _standardised(x: np.ndarray) -> np.ndarray:
    """Channels as z-scores; channels that barely move (std < 1e-9 of the largest) are dropped."""
    sd = x.std(axis=0)
    if not np.any(sd > 0):
        return np.empty((x.shape[0], 0))
    keep = sd >= 1e-9 * sd.max()
    return (x[:, keep] - x[:, keep].mean(axis=0)) / sd[keep]


def summed_acf(x: np.ndarray) -> np.ndarray:
    """The normalised autocorrelation of the standardised channels of ``x`` (n, C), lags 0..n-1.

    The power spectra of the channels (zero-padded to at least 2n, so the correlation is linear, not
    circular) are summed, and the inverse transform is divided by its value at lag 0 (biased
    estimate: lag L sums n - L products).
    """
    n = x.shape[0]
    z = _standardised(x)
    if z.shape[1] == 0:
        return np.full(n, np.nan)
    nfft = 1 << math.ceil(math.log2(2 * n))
    power = np.zeros(nfft // 2 + 1)
    for b in range(0, z.shape[1], _BLOCK):
        f = np.fft.rfft(z[:, b:b + _BLOCK], n=nfft, axis=0)
        power += np.sum(f.real ** 2 + f.imag ** 2, axis=1)
    acf = np.fft.irfft(power, n=nfft)[:n]
    return acf / acf[0] if acf[0] > 0 else np.full(n, np.nan)


def acf_peak_lag(acf: np.ndarray, share: float = ACF_PEAK_SHARE) -> float:
    """The period in samples from a normalised autocorrelation, NaN if there is no peak.

    After the first zero crossing, take the local maxima; the first one at or above ``share`` of the
    highest is the period, refined by the vertex of the parabola through it and its two neighbours.
    """
    if acf.size < 4 or not np.all(np.isfinite(acf)):
        return float("nan")
    neg = np.flatnonzero(acf[1:] <= 0.0)
    if neg.size == 0:
        return float("nan")
    zc = int(neg[0]) + 1
    a = acf[zc:]
    if a.size < 3:
        return float("nan")
    mid = a[1:-1]
    peaks = np.flatnonzero((mid > a[:-2]) & (mid >= a[2:])) + 1
    if peaks.size == 0:
        return float("nan")
    top = float(a[peaks].max())
    if top <= 0.0:
        return float("nan")
    p = int(peaks[np.flatnonzero(a[peaks] >= share * top)[0]])
    y0, y1, y2 = float(a[p - 1]), float(a[p]), float(a[p + 1])
    den = y0 - 2.0 * y1 + y2
    off = 0.5 * (y0 - y2) / den if den < 0 else 0.0
    return zc + p + float(np.clip(off, -0.5, 0.5))


def acf_period(t: Any, values: Any) -> float:
    """FFT autocorrelation period estimate (the frequency-analysis peer), seconds; NaN if there is no peak.

    Args:
        t: sample times, seconds, ``(n,)``; irregular stamps are resampled at their median step.
        values: ``(n, C)`` or ``(n,)``, in any units.

    Returns:
        The period in seconds, or NaN when the autocorrelation has no usable peak (no zero crossing,
        no local maximum after it, or a constant input).

    Raises:
        ValueError: bad shapes or fewer than 4 distinct stamps.
    """
    dt, x = uniform(t, values)
    return acf_peak_lag(summed_acf(x)) * dt


def have_stumpy() -> bool:
    """Whether stumpy is importable (the ``bench`` extra)."""
    return importlib.util.find_spec("stumpy") is not None


def _mstump_profile(x: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    import stumpy  # lazy: optional, and importing it loads numba

    prof, nn = stumpy.mstump(np.ascontiguousarray(x.T), m)
    return np.asarray(prof[-1]), np.asarray(nn[-1])


def mstump_spacing(nn: np.ndarray, prof: np.ndarray | None = None, m: int = 0, share: float = MSTUMP_SHARE) -> float:
    """The period in samples from nearest-neighbour indices ``nn`` (one per subsequence), NaN if none.

    The spacing of subsequence i is ``|nn[i] - i|``. In a periodic take a subsequence's nearest
    neighbour is one loop away or a whole number of loops away (whichever loop was performed most
    alike), so the spacings cluster at 1, 2, 3... periods, about equally often with 4 loops (a plain
    median of the spacings is then a double period half of the time). So: the fundamental is the
    smallest spacing that at least ``share`` of the subsequences share within +-15%; every spacing
    within +-15% of a whole multiple of it is divided by that multiple, and the period is their mean
    (sub-sample resolution). Subsequences without a finite profile value (``prof``) or with a spacing
    below ``m`` (overlapping, same-loop matches) are ignored.
    """
    idx = np.arange(nn.size)
    ok = nn >= 0
    if prof is not None:
        ok &= np.isfinite(prof)
    s = np.sort(np.abs(nn[ok].astype(np.float64) - idx[ok]))
    s = s[s >= max(1, m)]
    if s.size == 0:
        return float("nan")
    need = max(3, math.ceil(share * s.size))
    count = np.searchsorted(s, 1.15 * s, side="right") - np.searchsorted(s, 0.85 * s, side="left")
    good = np.flatnonzero(count >= need)
    if good.size == 0:
        return float("nan")
    c = s[good[0]]
    f0 = float(np.median(s[(s >= 0.85 * c) & (s <= 1.15 * c)]))
    k = np.maximum(1.0, np.round(s / f0))
    fit = np.abs(s / k - f0) <= 0.15 * f0
    return float(np.mean(s[fit] / k[fit]))


def mstump_window(dt: float, n: int, window_s: float = MSTUMP_WINDOW_S) -> int:
    """The default mstump window: ``window_s`` in samples, at least 4 and at most a quarter of the take."""
    return int(max(4, min(round(window_s / dt), n // 4)))


def mstump_period(t: Any, values: Any, m: int | None = None) -> float:
    """Matrix-profile period estimate with ``stumpy.mstump``, seconds; NaN if stumpy is missing or no period.

    The take is put on a uniform grid (as :func:`acf_period`), then ``stumpy.mstump`` computes the
    multi-dimensional matrix profile with window ``m`` (default :data:`MSTUMP_WINDOW_S` = 0.5 s, see
    :func:`mstump_window`; a fixed window keeps this peer independent of the other estimates). The
    all-dimension profile (the last row of mstump's output, every channel counted) gives each
    subsequence's nearest neighbour; :func:`mstump_spacing` turns their spacings (whole multiples of
    the period) into a period.
    mstump's cost grows as channels x n^2 (1.4 s at 254 channels x 4 loops at 120 Hz on 2 cores), and
    the first call in a process adds about 10 s of numba JIT compilation.

    Args:
        t: sample times, seconds, ``(n,)``.
        values: ``(n, C)`` or ``(n,)``.
        m: subsequence length in samples (default 0.5 s).

    Returns:
        The period in seconds, or NaN.

    Raises:
        ValueError: bad shapes, fewer than 4 distinct stamps, or ``m`` < 3.
    """
    if not have_stumpy():
        return float("nan")
    dt, x = uniform(t, values)
    z = _standardised(x)
    n = z.shape[0]
    if m is None:
        m = mstump_window(dt, n)
    if m < 3:
        raise ValueError("m must be at least 3 samples")
    if z.shape[1] == 0 or n < 2 * m + 2:
        return float("nan")
    prof, nn = _mstump_profile(z, int(m))
    return mstump_spacing(nn, prof, int(m)) * dt


def mstump_warmup() -> None:
    """Compile stumpy's numba kernels (the first mstump call of a process); no-op without stumpy.

    It runs :func:`mstump_period` on a small 3-channel take, through the same code path as real calls.
    """
    if not have_stumpy():
        return
    t = np.arange(300) / 100.0
    x = np.stack([np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.sin(4 * np.pi * t) ** 2], axis=1)
    mstump_period(t, x)
