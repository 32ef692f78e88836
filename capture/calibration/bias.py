"""Automatic gyro-bias estimation from stillness, with a confidence value: the streaming
:class:`GyroBiasEstimator`, its result :class:`BiasEstimate`, and :func:`estimate_gyro_bias` for
a whole recording. What it can and cannot tell apart is in the estimator's docstring."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import erf

from capture.calibration.frames import G0

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class BiasEstimate:
    """Current automatic gyro-bias estimate.

    Attributes:
        bias: rad/s (3,), zeros while nothing was still.
        std: posterior standard deviation per axis, rad/s.
        confidence: 0-1, the probability (under the model) that every principal component of the
            error is within ``tolerance``; 0 with no still period.
        periods: still periods used.
        rejected: still periods rejected as inconsistent with the others (a real slow rotation).
        still_s: total still time used, seconds.
        cov: 3x3 posterior covariance, (rad/s)^2.
    """

    bias: np.ndarray
    std: np.ndarray
    confidence: float
    periods: int
    rejected: int
    still_s: float
    cov: np.ndarray


@dataclass
class _Period:
    t0: float
    t1: float
    blocks: list[tuple[float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]]
    obs: tuple[np.ndarray, np.ndarray] | None = None  # (y, Sigma), computed when closed


class GyroBiasEstimator:
    """Streaming automatic gyro-bias estimation from still periods, with a confidence value.

    Feed samples with :meth:`update` (arrays, any chunking; a Sample at a time works too) and read
    :attr:`estimate`. Samples are grouped into ``block_s`` blocks; a block is still when its
    accelerometer and gyro standard deviations, its mean rate (the plausible-bias bound
    ``max_bias``) and its |a| pass; a run of still blocks at least ``min_still_s`` long is one still
    period, giving one observation of the bias (see *the model* below). The estimate combines the
    observations by weighted least squares with a zero-mean prior of standard deviation
    ``max_bias / 2``, rejects periods that disagree (Mahalanobis distance above ``reject_chi2``),
    and down-weights old periods (``drift_per_s``, temperature drift).

    **The model: what automatic bias estimation can and cannot tell apart.** A gyroscope reading
    ``w`` during an apparently still period is ``bias + true rotation``. The estimator separates
    them with every cue it has:

    * *accelerometer and gyro variance, and |a| close to g* decide which periods count as still at all;
    * a *magnitude bound* (``max_bias``): a steady reading above it is motion, never bias;
    * the *accelerometer direction*: a real rotation about any axis perpendicular to gravity tilts the
      sensor, so the gravity direction drifts in the sensor frame at that rate; the estimator measures
      that drift over the period and removes it. The perpendicular part of a slow rotation is therefore
      observable, to the accelerometer's noise;
    * the *magnetometer heading* (when a magnetometer is given): a rotation about gravity turns the
      horizontal field in the sensor frame; its rate is measured and removed the same way;
    * *agreement between still periods*: the bias is constant in the sensor frame, a slow rotation is
      not. Periods in different orientations pin the bias down from their perpendicular parts alone,
      and a period whose reading disagrees with the others beyond its uncertainty is rejected (counted).

    What it cannot do: without a magnetometer, a *steady* rotation about gravity during the *only*
    still orientation seen (a turntable turning at 2 deg/s, say) is indistinguishable from bias along
    gravity. The estimator does not pretend: each still period is given an unknown steady rotation with
    prior standard deviation ``rotation_prior`` (0.3 deg/s), which is the uncertainty of the gravity
    component until a magnetometer, another orientation or many independent still periods reduce it;
    the confidence stays low (about 0.25 for one period) and the consumer decides. Many separate still
    periods in one orientation (a foot in stance) are assumed to rotate independently, so their
    average is trusted more; a turntable that turns identically in every one of them would still fool
    it.

    Args:
        block_s: block length, s.
        min_still_s: shortest still period used, s.
        acc_std_max: per-axis accelerometer std limit of a still block, m/s^2.
        gyro_std_max: per-axis gyro std limit of a still block, rad/s.
        max_bias: largest plausible bias, rad/s; a steadier faster rotation is motion.
        acc_norm_tol: allowed | |a| - g |, m/s^2.
        rotation_prior: standard deviation of the unknown steady rotation of a still period, rad/s.
        tolerance: error tolerance behind the confidence value, rad/s.
        drift_per_s: bias random walk, rad/s per second of age.
        max_periods: periods kept.
        reject_chi2: Mahalanobis distance squared above which a period is rejected (3 dof).
        g: gravity, m/s^2.

    Raises:
        ValueError: a non-positive duration or limit.
    """

    def __init__(self, *, block_s: float = 0.1, min_still_s: float = 0.4, acc_std_max: float = 0.1,
                 gyro_std_max: float = 1.0 * _DEG, max_bias: float = 5.0 * _DEG, acc_norm_tol: float = 0.5,
                 rotation_prior: float = 0.3 * _DEG, tolerance: float = 0.1 * _DEG,
                 drift_per_s: float = 0.001 * _DEG, max_periods: int = 64, reject_chi2: float = 11.34,
                 g: float = G0) -> None:
        for name, v in (("block_s", block_s), ("min_still_s", min_still_s), ("acc_std_max", acc_std_max),
                        ("gyro_std_max", gyro_std_max), ("max_bias", max_bias), ("rotation_prior", rotation_prior),
                        ("tolerance", tolerance), ("reject_chi2", reject_chi2)):
            if not v > 0:
                raise ValueError(f"{name} must be positive, got {v}")
        self.block_s = block_s
        self.min_still_s = min_still_s
        self.acc_std_max = acc_std_max
        self.gyro_std_max = gyro_std_max
        self.max_bias = max_bias
        self.acc_norm_tol = acc_norm_tol
        self.rotation_prior = rotation_prior
        self.tolerance = tolerance
        self.drift_per_s = drift_per_s
        self.reject_chi2 = reject_chi2
        self.g = g
        self._periods: deque[_Period] = deque(maxlen=max_periods)
        self._open: _Period | None = None
        self._t_block0: float | None = None
        self._pend_t: list[np.ndarray] = []
        self._pend: list[np.ndarray] = []
        self._t_last = -math.inf
        self._cached: BiasEstimate | None = None
        self.samples = 0
        self.blocks = 0
        self.still_blocks = 0

    # -- feeding --------------------------------------------------------------------------------
    def update(self, t_s: ArrayLike, gyro: ArrayLike, acc: ArrayLike, mag: ArrayLike | None = None) -> None:
        """Feed samples (cheap; the estimate is computed when :attr:`estimate` is read).

        Args:
            t_s: (n,) seconds, increasing (samples not after the previous one are dropped).
            gyro: (n, 3) rad/s, *without* the bias being estimated removed.
            acc: (n, 3) m/s^2.
            mag: optional (n, 3), any unit, NaN rows where there is no reading.

        Raises:
            ValueError: shapes disagree.
        """
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        g = np.asarray(gyro, np.float64).reshape(-1, 3)
        a = np.asarray(acc, np.float64).reshape(-1, 3)
        n = t.shape[0]
        if g.shape[0] != n or a.shape[0] != n:
            raise ValueError(f"t, gyro and acc lengths differ: {n}, {g.shape[0]}, {a.shape[0]}")
        m = np.full((n, 3), np.nan) if mag is None else np.asarray(mag, np.float64).reshape(-1, 3)
        if m.shape[0] != n:
            raise ValueError("mag length differs from t")
        ok = np.isfinite(t) & np.isfinite(g).all(axis=1) & np.isfinite(a).all(axis=1)
        if n:
            prev = np.maximum.accumulate(np.concatenate([[self._t_last], np.where(ok, t, -np.inf)]))[:-1]
            ok &= t > prev
        if not ok.all():
            t, g, a, m = t[ok], g[ok], a[ok], m[ok]
            n = t.shape[0]
        if n == 0:
            return
        self._t_last = float(t[-1])
        self.samples += n
        if self._t_block0 is None:
            self._t_block0 = float(t[0])
        self._pend_t.append(t)
        self._pend.append(np.hstack([g, a, m]))
        bid_last = math.floor((float(t[-1]) - self._t_block0) / self.block_s)
        t_all = np.concatenate(self._pend_t)
        x_all = np.vstack(self._pend)
        bid = np.floor((t_all - self._t_block0) / self.block_s).astype(np.int64)
        done = bid < bid_last
        if done.any():
            k = int(np.count_nonzero(done))
            self._blocks(t_all[:k], x_all[:k], bid[:k])
            self._pend_t = [t_all[k:]]
            self._pend = [x_all[k:]]
        else:
            self._pend_t = [t_all]
            self._pend = [x_all]
        self._cached = None

    def _blocks(self, t: np.ndarray, x: np.ndarray, bid: np.ndarray) -> None:
        starts = np.flatnonzero(np.r_[True, bid[1:] != bid[:-1]])
        cnt = np.diff(np.r_[starts, len(bid)])
        s1 = np.add.reduceat(x[:, :6], starts, axis=0)
        s2 = np.add.reduceat(x[:, :6] * x[:, :6], starts, axis=0)
        tm = np.add.reduceat(t, starts) / cnt
        mv = np.isfinite(x[:, 6:9]).all(axis=1)
        mn = np.add.reduceat(mv.astype(np.int64), starts)
        ms = np.add.reduceat(np.where(mv[:, None], x[:, 6:9], 0.0), starts, axis=0)
        mean = s1 / cnt[:, None]
        var = np.maximum(s2 / cnt[:, None] - mean * mean, 0.0) * (cnt / np.maximum(cnt - 1, 1))[:, None]
        sd = np.sqrt(var)
        anorm = np.linalg.norm(mean[:, 3:6], axis=1)
        still = ((cnt >= 3) & (sd[:, 3:6].max(axis=1) <= self.acc_std_max)
                 & (sd[:, 0:3].max(axis=1) <= self.gyro_std_max)
                 & (np.linalg.norm(mean[:, 0:3], axis=1) <= self.max_bias)
                 & (np.abs(anorm - self.g) <= self.acc_norm_tol))
        self.blocks += len(cnt)
        self.still_blocks += int(still.sum())
        for i in range(len(cnt)):
            if still[i]:
                if self._open is not None and float(tm[i]) - self._open.t1 > 2.5 * self.block_s:
                    self._close()  # a time gap ends a still period
                mag = ms[i] / mn[i] if mn[i] > 0 else None
                blk = (float(tm[i]), int(cnt[i]), mean[i, 0:3], var[i, 0:3], mean[i, 3:6], mag)
                if self._open is None:
                    self._open = _Period(float(tm[i]), float(tm[i]), [blk])
                else:
                    self._open.blocks.append(blk)
                    self._open.t1 = float(tm[i])
            else:
                self._close()

    def _close(self) -> None:
        p = self._open
        self._open = None
        if p is None:
            return
        if self._length(p) < self.min_still_s:
            return
        p.obs = self._observe(p)
        self._periods.append(p)

    def _length(self, p: _Period) -> float:
        return p.t1 - p.t0 + self.block_s

    # -- the model ------------------------------------------------------------------------------
    def _observe(self, p: _Period) -> tuple[np.ndarray, np.ndarray]:
        """One still period -> (bias observation y, covariance Sigma)."""
        tk = np.array([b[0] for b in p.blocks])
        nk = np.array([b[1] for b in p.blocks], np.float64)
        gk = np.array([b[2] for b in p.blocks])
        vk = np.array([b[3] for b in p.blocks])
        ak = np.array([b[4] for b in p.blocks])
        n_total = nk.sum()
        nb = len(p.blocks)
        gm = (gk * nk[:, None]).sum(axis=0) / n_total
        # standard error of the mean rate: white noise, or the spread of block means if larger
        white = math.sqrt(float(((vk * (nk - 1)[:, None]).sum(axis=0) / max(n_total - nb, 1)).max()) / n_total)
        se_g = white
        if nb >= 4:
            se_g = max(se_g, float(gk.std(axis=0, ddof=1).max()) / math.sqrt(nb))
        se_g = max(se_g, 1e-6)
        u = ak.sum(axis=0)
        u /= np.linalg.norm(u)
        uu = np.outer(u, u)
        p_perp = np.eye(3) - uu
        s2 = self.rotation_prior ** 2
        # rotation perpendicular to gravity: the gravity direction drifts at -w x u
        var_perp = s2
        w_perp = np.zeros(3)
        if nb >= 3:
            uk = ak / np.linalg.norm(ak, axis=1, keepdims=True)
            slope, se_slope = _slope(tk, uk)
            if se_slope is not None:
                w_t = -np.cross(u, slope)
                se_t2 = se_slope ** 2
                k = s2 / (s2 + se_t2)
                w_perp = k * (p_perp @ w_t)
                var_perp = k * se_t2
        # rotation about gravity: the horizontal field turns at -w_par in the sensor frame
        var_par = s2
        w_par = 0.0
        mags = [b[5] for b in p.blocks]
        if nb >= 3 and all(m is not None for m in mags):
            mk = np.array(mags)
            h = mk - np.outer(mk @ u, u)
            hn = np.linalg.norm(h, axis=1)
            if np.all(hn > 1e-9 * max(1.0, float(np.linalg.norm(mk, axis=1).max()))):
                h0 = h[0]
                ang = np.arctan2(np.cross(h0, h) @ u, h @ h0)
                ang = np.unwrap(ang)
                r, se_r = _slope(tk, ang[:, None])
                if se_r is not None:
                    se_m2 = se_r ** 2
                    k = s2 / (s2 + se_m2)
                    w_par = -k * float(r[0])
                    var_par = k * se_m2
        y = gm - w_perp - w_par * u
        sigma = se_g ** 2 * np.eye(3) + var_perp * p_perp + var_par * uu
        return y, sigma

    @property
    def estimate(self) -> BiasEstimate:
        """The current estimate (the open still period, if long enough, included provisionally)."""
        if self._cached is not None:
            return self._cached
        periods = list(self._periods)
        if self._open is not None and self._length(self._open) >= self.min_still_s:
            op = _Period(self._open.t0, self._open.t1, list(self._open.blocks))
            op.obs = self._observe(op)
            periods.append(op)
        self._cached = self._solve(periods)
        return self._cached

    def _solve(self, periods: list[_Period]) -> BiasEstimate:
        if not periods:
            z = np.zeros(3)
            prior = (self.max_bias / 2) ** 2 * np.eye(3)
            return BiasEstimate(z, np.sqrt(np.diag(prior)), 0.0, 0, 0, 0.0, prior)
        t_now = max(p.t1 for p in periods)
        ys, sis = [], []
        for p in periods:
            assert p.obs is not None
            y, s = p.obs
            age = t_now - p.t1
            ys.append(y)
            sis.append(np.linalg.inv(s + (self.drift_per_s * age) ** 2 * np.eye(3)))
        keep = list(range(len(periods)))
        prior_info = np.eye(3) / (self.max_bias / 2) ** 2
        vs = [si @ y for si, y in zip(sis, ys, strict=True)]
        while True:
            info = prior_info + sum(sis[i] for i in keep)
            vec = sum(vs[i] for i in keep)
            cov = np.linalg.inv(info)
            b = cov @ vec
            if len(keep) <= 1:
                break
            # leave-one-out: distance of each period from the estimate made without it
            worst, worst_d = -1, 0.0
            for i in keep:
                cov_o = np.linalg.inv(info - sis[i])
                r = ys[i] - cov_o @ (vec - vs[i])
                d = float(r @ np.linalg.solve(np.linalg.inv(sis[i]) + cov_o, r))
                if d > worst_d:
                    worst, worst_d = i, d
            if worst_d <= self.reject_chi2:
                break
            keep.remove(worst)
        ev = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
        conf = float(np.prod(erf(self.tolerance / (math.sqrt(2.0) * np.sqrt(ev) + 1e-300))))
        still = float(sum(self._length(periods[i]) for i in keep))
        return BiasEstimate(b, np.sqrt(np.diag(cov)), conf, len(keep), len(periods) - len(keep), still, cov)

    def still_periods(self) -> list[tuple[float, float]]:
        """Start and end times (s) of the still periods kept (closed ones, then the open one)."""
        out = [(p.t0 - self.block_s / 2, p.t1 + self.block_s / 2) for p in self._periods]
        if self._open is not None and self._length(self._open) >= self.min_still_s:
            out.append((self._open.t0 - self.block_s / 2, self._open.t1 + self.block_s / 2))
        return out

    def finish(self) -> BiasEstimate:
        """Close the open block and still period (end of data) and return the final estimate."""
        if self._pend_t:
            t_all = np.concatenate(self._pend_t)
            if t_all.size:
                x_all = np.vstack(self._pend)
                assert self._t_block0 is not None
                bid = np.floor((t_all - self._t_block0) / self.block_s).astype(np.int64)
                self._blocks(t_all, x_all, bid)
        self._pend_t, self._pend = [], []
        self._close()
        self._cached = None
        return self.estimate


def _slope(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Least-squares slope of columns of ``y`` against ``t`` and its (largest) standard error."""
    n = t.shape[0]
    tc = t - t.mean()
    sxx = float(tc @ tc)
    if n < 3 or sxx <= 0:
        return np.zeros(y.shape[1]), None
    yc = y - y.mean(axis=0)
    slope = tc @ yc / sxx
    res = yc - np.outer(tc, slope)
    s2 = (res * res).sum(axis=0) / (n - 2)
    return slope, math.sqrt(float(s2.max()) / sxx)


def estimate_gyro_bias(t_s: ArrayLike, gyro: ArrayLike, acc: ArrayLike, mag: ArrayLike | None = None,
                       **settings: Any) -> BiasEstimate:
    """Batch form of :class:`GyroBiasEstimator`: the estimate from a whole recording.

    Raises:
        ValueError: shapes disagree or a setting is invalid.
    """
    est = GyroBiasEstimator(**settings)
    est.update(t_s, gyro, acc, mag)
    return est.finish()
