"""Stillness: per-sample detection (:func:`still_mask`) and its runs (:func:`still_segments`), the
mean accelerometer reading of every still period (:func:`still_poses`, the accelerometer fit's
input), and the explicit still-period gyro bias with its standard error (:func:`still_bias`,
:class:`StillBias`; what ``perfcap calibrate`` runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.calibration.frames import G0
from capture.errors import ConfigError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

_DEG = math.pi / 180.0


def _moving(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred moving mean and std (per column) over ``w`` samples, same length as ``x``."""
    n = x.shape[0]
    w = max(1, min(w, n))
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x * x, axis=0)])
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)
    hi = lo + w
    m = (c1[hi] - c1[lo]) / w
    v = np.maximum((c2[hi] - c2[lo]) / w - m * m, 0.0)
    return m, np.sqrt(v)


def still_mask(acc: ArrayLike, gyro: ArrayLike, rate_hz: float, *, window_s: float = 0.25,
               acc_std_max: float = 0.1, gyro_std_max: float = 1.0 * _DEG, gyro_max: float = 5.0 * _DEG,
               acc_norm_tol: float = 0.5, g: float = G0) -> np.ndarray:
    """Per-sample stillness: within a centred ``window_s`` window the accelerometer and gyro
    standard deviations (every axis) are below ``acc_std_max`` (m/s^2) and ``gyro_std_max``
    (rad/s), the mean rate is below ``gyro_max`` (a plausible bias bound) and the mean |a| is
    within ``acc_norm_tol`` of g.

    Raises:
        ValueError: arrays of different lengths or not (n, 3), or a non-positive rate.
    """
    a = np.asarray(acc, np.float64)
    w_ = np.asarray(gyro, np.float64)
    if a.shape != w_.shape or a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"acc and gyro must both be (n, 3), got {a.shape} and {w_.shape}")
    if not rate_hz > 0:
        raise ValueError("rate_hz must be positive")
    if a.shape[0] == 0:
        return np.zeros(0, bool)
    win = max(2, round(window_s * rate_hz))
    am, asd = _moving(a, win)
    gm, gsd = _moving(w_, win)
    still: np.ndarray = ((asd.max(axis=1) <= acc_std_max) & (gsd.max(axis=1) <= gyro_std_max)
                         & (np.linalg.norm(gm, axis=1) <= gyro_max)
                         & (np.abs(np.linalg.norm(am, axis=1) - g) <= acc_norm_tol))
    return still


def still_segments(mask: ArrayLike, min_len: int = 1) -> list[tuple[int, int]]:
    """Runs of True in ``mask`` as ``(start, stop)`` index pairs, at least ``min_len`` long."""
    m = np.asarray(mask, bool).astype(np.int8)
    d = np.diff(np.concatenate([[0], m, [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return [(int(s), int(e)) for s, e in zip(starts, stops, strict=True) if e - s >= min_len]


@dataclass(frozen=True)
class StillBias:
    """Gyro bias from a period known to be still.

    Attributes:
        bias: rad/s (3,).
        stderr: standard error per axis, rad/s (3,): the larger of the white-noise error and the
            batch-means error (10 consecutive blocks), so slow wander is not hidden.
        n: samples used.
        duration_s: length of the period (``nan`` without timestamps).
        gyro_std: per-axis sample standard deviation, rad/s.
        acc_std: per-axis accelerometer standard deviation, m/s^2 (``nan`` without acc).
    """

    bias: np.ndarray
    stderr: np.ndarray
    n: int
    duration_s: float
    gyro_std: np.ndarray
    acc_std: np.ndarray


def still_bias(gyro: ArrayLike, acc: ArrayLike | None = None, t_s: ArrayLike | None = None, *,
               min_samples: int = 20, gyro_std_max: float = 1.0 * _DEG, acc_std_max: float = 0.1,
               max_bias: float = 10.0 * _DEG, source: str | None = None) -> StillBias:
    """Explicit still-period calibration (``perfcap calibrate``): the mean gyro over samples the user
    says are still, with its standard error.

    Args:
        gyro: (n, 3) rad/s.
        acc: optional (n, 3) m/s^2, checked for stillness.
        t_s: optional timestamps, for the reported duration.
        min_samples: fewer samples is an error.
        gyro_std_max: per-axis gyro standard deviation above this means it moved.
        acc_std_max: per-axis accelerometer standard deviation above this means it moved.
        max_bias: a mean rate above this is not a bias.
        source: the stream, for error messages.

    Raises:
        ConfigError: too few samples, non-finite values, or the data was not still (the message
            says which test failed and by how much).
    """
    g = np.asarray(gyro, np.float64)
    if g.ndim != 2 or g.shape[1] != 3:
        raise ConfigError(f"still calibration: gyro must be (n, 3), got {g.shape}", source=source)
    if g.shape[0] < min_samples:
        raise ConfigError(f"still calibration needs at least {min_samples} samples, got {g.shape[0]}", source=source)
    if not np.all(np.isfinite(g)):
        raise ConfigError("still calibration: gyro has non-finite values", source=source)
    n = g.shape[0]
    mean = g.mean(axis=0)
    sd = g.std(axis=0, ddof=1)
    if float(sd.max()) > gyro_std_max:
        raise ConfigError(f"still calibration: the sensor moved (gyro std {np.degrees(sd.max()):.3f} deg/s > "
                          f"{np.degrees(gyro_std_max):.3f})", source=source)
    if float(np.linalg.norm(mean)) > max_bias:
        raise ConfigError(f"still calibration: mean rate {np.degrees(np.linalg.norm(mean)):.2f} deg/s is above the "
                          f"plausible bias bound {np.degrees(max_bias):.2f} deg/s: it was turning", source=source)
    asd = np.full(3, np.nan)
    if acc is not None:
        a = np.asarray(acc, np.float64)
        if a.shape != g.shape:
            raise ConfigError(f"still calibration: acc shape {a.shape} differs from gyro {g.shape}", source=source)
        asd = a.std(axis=0, ddof=1)
        if float(asd.max()) > acc_std_max:
            raise ConfigError(f"still calibration: the sensor moved (acc std {asd.max():.3f} m/s^2 > {acc_std_max})",
                              source=source)
    se = sd / math.sqrt(n)
    nb = 10
    if n >= 5 * nb:
        k = n // nb
        blocks = g[: k * nb].reshape(nb, k, 3).mean(axis=1)
        se = np.maximum(se, blocks.std(axis=0, ddof=1) / math.sqrt(nb))
    dur = float("nan")
    if t_s is not None:
        t = np.asarray(t_s, np.float64)
        if t.shape[0] == n and n > 1:
            dur = float(t[-1] - t[0])
    return StillBias(mean, se, n, dur, sd, asd)


def still_poses(t_s: ArrayLike, acc: ArrayLike, gyro: ArrayLike, *, min_still_s: float = 1.0,
                **still: Any) -> np.ndarray:
    """Mean accelerometer reading of every still period of at least ``min_still_s`` (k, 3)."""
    t = np.asarray(t_s, np.float64)
    a = np.asarray(acc, np.float64)
    if t.shape[0] < 2:
        return np.zeros((0, 3))
    rate = (t.shape[0] - 1) / float(t[-1] - t[0])
    mask = still_mask(a, gyro, rate, **still)
    segs = still_segments(mask, int(min_still_s * rate))
    return np.array([a[s:e].mean(axis=0) for s, e in segs]).reshape(-1, 3)
