"""The orientation filter: :class:`OrientationFilter`, one streaming filter over every backend
(the registry :data:`FILTERS`, :data:`DEFAULT_FILTER`) in one convention, which validates the
settings, takes every time step from the timestamps, does not integrate across gaps or
non-increasing times, holds and gates a magnetometer running at its own rate, and has a batch call
on arrays (:meth:`~OrientationFilter.update_many`) and a one-sample path
(:meth:`~OrientationFilter.update_one`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.calibration import G0
from capture.errors import ConfigError
from capture.orientation.ahrs_filters import EkfBackend, MadgwickBackend, MahonyBackend
from capture.orientation.base import (
    DEFAULTS,
    FLAG_ACC_IGNORED,
    FLAG_ACC_RECOVERY,
    FLAG_GAP,
    FLAG_INIT,
    FLAG_MAG_IGNORED,
    FLAG_NO_MAG,
    FLAG_OVERRANGE,
    FLAG_SKIPPED,
    MODE_INIT,
    MODE_RUN,
    MODE_SKIP,
    Backend,
    OrientationResult,
    StepOutputs,
    Steps,
    gravity_from_quaternion,
)
from capture.orientation.fusion import FusionBackend

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from capture.orientation.base import Quat, Vec3

_BACKENDS: dict[str, type[Backend]] = {"fusion": FusionBackend, "madgwick": MadgwickBackend,
                                       "mahony": MahonyBackend, "ekf": EkfBackend}
#: The filter kinds, in the order the documentation and the benchmark list them.
FILTERS = tuple(_BACKENDS)

# The default filter, chosen by measurement (.venv/bin/python benchmarks/bench_fusion.py, 2 shared cores):
#   gaitmap foot IMUs vs optical mocap, median (p90) per-stride RMS error in deg, cross-validated
#   mounting, heading aligned per stride, left / right foot:
#     fusion 2.86 (3.44) / 4.29 (5.11)   madgwick 2.82 (3.40) / 4.22 (4.99)
#     mahony 2.98 (3.56) / 4.35 (5.21)   ekf      4.11 (5.22) / 5.17 (6.71)
#   fusion_sensor_data.csv, angle to fusion, median / p95 in deg before the magnetic disturbance
#   (MARG; IMU-only): madgwick 0.36 / 2.11 (0.19 / 1.63), mahony 0.91 / 6.49 (1.90 / 11.1),
#   ekf 0.88 / 3.08 (5.12 / 7.70): without acceleration rejection mahony and ekf lose heading in
#   fast motion; after it, fusion keeps the gyro heading through the disturbance, the others follow it.
#   throughput, per filter, one call over the file: fusion 200,000-370,000 samples/s; madgwick
#   ~6,000-10,000, mahony ~6,000-7,000, ekf ~3,500-3,900.
# Madgwick and Fusion are equally accurate on gait (0.04-0.07 deg apart); Fusion is 30-60x faster
# and the only one with acceleration/magnetic rejection and recovery: it is the default.
DEFAULT_FILTER = "fusion"

_R2D = 180.0 / math.pi
_INV_G0 = 1.0 / G0
_ZERO3 = np.zeros(3)

#: how long after a start without a magnetometer reading its first reading still re-initialises
_HEADING_WAIT_S = 1.0


class OrientationFilter:
    """One orientation filter over the libraries, in one convention (see :mod:`capture.orientation`).

    Pitfalls handled here (measured; see the tests):

    * ``dt`` always comes from the timestamps (never a library default rate: ``ahrs`` defaults to
      100 Hz, which turns a 256 Hz recording's rotations into the wrong size, ``ahrs#9``/``#29``).
      Non-increasing times are not integrated (counted); a step longer than ``max_gap_s`` (0.5 s) or
      than ``gap_periods`` (10) nominal sample periods is a gap and is not integrated across: the
      filter is re-initialised from the accelerometer (and magnetometer), keeping the heading when
      there is no magnetometer (counted, flagged). Fusion then runs a rejection-free grace (see
      :class:`~capture.orientation.fusion.FusionBackend`).
    * Mixed rates: a magnetometer slower than the IMU is held (zero-order hold of the latest reading)
      for at most ``mag_max_age_s``; older readings are not used (flagged ``FLAG_NO_MAG``). The
      ``ahrs`` filters, which have no magnetic rejection, ignore readings whose magnitude differs from
      the reference by more than ``mag_norm_tol``.

    Args:
        kind: ``fusion``, ``madgwick``, ``mahony`` or ``ekf``.
        **settings: see :data:`~capture.orientation.base.DEFAULTS`: ``nominal_rate_hz``, ``gain``,
            ``acc_rejection_deg``, ``mag_rejection_deg``, ``rejection_timeout_s``,
            ``gyro_range_dps``, ``gyro_offset``, ``offset_threshold_dps``, ``offset_period_s``,
            ``max_gap_s``, ``mag_max_age_s``, ``mag_norm_tol``, ``magnetic_dip_deg``,
            ``mahony_ki``, ``mahony_bias_limit_dps``, ``mahony_freeze_dps``, ``mahony_freeze_acc``,
            ``ekf_noises``.

    Raises:
        ConfigError: an unknown kind or setting, or a setting out of range.
    """

    def __init__(self, kind: str = DEFAULT_FILTER, **settings: Any) -> None:
        if kind not in _BACKENDS:
            raise ConfigError(f"unknown orientation filter {kind!r}; choose one of {', '.join(FILTERS)}")
        unknown = sorted(set(settings) - set(DEFAULTS))
        if unknown:
            raise ConfigError(f"unknown orientation setting(s) {', '.join(unknown)}; "
                              f"known: {', '.join(sorted(DEFAULTS))}")
        s = dict(DEFAULTS)
        s.update(settings)
        for k in ("max_gap_s", "mag_max_age_s", "mag_norm_tol", "mahony_bias_limit_dps", "mahony_freeze_dps"):
            if not (isinstance(s[k], (int, float)) and s[k] > 0):
                raise ConfigError(f"orientation setting {k} must be a positive number, got {s[k]!r}")
        if s["nominal_rate_hz"] is not None and not s["nominal_rate_hz"] > 0:
            raise ConfigError(f"orientation setting nominal_rate_hz must be positive, got {s['nominal_rate_hz']!r}")
        if s["gain"] is not None and not s["gain"] >= 0:
            raise ConfigError(f"orientation setting gain must be >= 0, got {s['gain']!r}")
        self.kind = kind
        self.settings = s
        self._backend = _BACKENDS[kind](s)
        self._rate_known = s["nominal_rate_hz"] is not None or kind != "fusion"
        if not (isinstance(s["gap_periods"], (int, float)) and s["gap_periods"] > 1):
            raise ConfigError(f"orientation setting gap_periods must be a number > 1, got {s['gap_periods']!r}")
        self._max_gap = float(s["max_gap_s"])
        if s["nominal_rate_hz"]:
            self._max_gap = min(self._max_gap, float(s["gap_periods"]) / float(s["nominal_rate_hz"]))
        self._q = np.array([1.0, 0.0, 0.0, 0.0])
        self._t_last: float | None = None
        self._mag_t = np.empty(0)
        self._mag_v = np.empty((0, 3))
        self._mag_seen = False
        # an initialisation made without a magnetometer reading (its heading is arbitrary) is
        # redone at the first usable reading within ``_HEADING_WAIT_S`` of it
        self._await_heading = True
        self._init_t = math.nan
        self.heading_inits = 0
        self._mag_ref_norm: float | None = None
        self._mag_ref_t0: float | None = None
        self._mag_ref_n = 0
        self.samples = 0
        self.integrated = 0
        self.gaps = 0
        self.non_increasing = 0
        self.rejected = 0
        self.mag_used = 0
        self.mag_stale = 0
        self.mag_gated = 0

    # -- inputs -------------------------------------------------------------------------------------
    def add_mag(self, t_s: ArrayLike, mag: ArrayLike) -> None:
        """Queue magnetometer readings taken at ``t_s`` (any rate); the next :meth:`update_many`
        holds the latest one not after each IMU sample, if younger than ``mag_max_age_s``."""
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        m = np.asarray(mag, np.float64).reshape(-1, 3)
        if t.shape[0] != m.shape[0]:
            raise ValueError(f"mag times ({t.shape[0]}) and readings ({m.shape[0]}) differ in number")
        ok = np.isfinite(t) & np.isfinite(m).all(axis=1) & m.any(axis=1)
        if not ok.all():
            t, m = t[ok], m[ok]
        if t.size == 0:
            return
        self._mag_seen = True
        tt = np.concatenate([self._mag_t, t])
        mm = np.vstack([self._mag_v, m])
        if tt.shape[0] > 1 and np.any(np.diff(tt) < 0):
            o = np.argsort(tt, kind="stable")
            tt, mm = tt[o], mm[o]
        self._mag_t, self._mag_v = tt, mm

    def _held_mag(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = t.shape[0]
        mag = np.zeros((n, 3))
        have = np.zeros(n, bool)
        if self._mag_t.size:
            j = np.searchsorted(self._mag_t, t, side="right") - 1
            ok = j >= 0
            jj = np.where(ok, j, 0)
            ok &= (t - self._mag_t[jj]) <= self.settings["mag_max_age_s"]
            mag[ok] = self._mag_v[jj[ok]]
            have = ok
            # keep the last reading not after the last IMU time, and everything newer
            keep_from = max(0, int(np.searchsorted(self._mag_t, t[-1], side="right")) - 1)
            self._mag_t = self._mag_t[keep_from:]
            self._mag_v = self._mag_v[keep_from:]
        return mag, have

    def _gate(self, t: np.ndarray, mag: np.ndarray, have: np.ndarray) -> np.ndarray:
        """ahrs filters: drop readings whose magnitude is off the reference (learned over the first 2 s)."""
        if self.kind == "fusion" or not have.any():
            return have
        norm = np.linalg.norm(mag, axis=1)
        idx = np.flatnonzero(have)
        if self._mag_ref_norm is None:
            self._mag_ref_norm = float(norm[idx[0]])
            self._mag_ref_t0 = float(t[idx[0]])
            self._mag_ref_n = 0
        assert self._mag_ref_t0 is not None
        learning = have & (t - self._mag_ref_t0 <= 2.0)
        if learning.any():
            k = int(learning.sum())
            self._mag_ref_norm = ((self._mag_ref_norm * self._mag_ref_n + float(norm[learning].sum()))
                                  / (self._mag_ref_n + k))
            self._mag_ref_n += k
        ok: np.ndarray = have & (np.abs(norm / self._mag_ref_norm - 1.0) <= self.settings["mag_norm_tol"])
        self.mag_gated += int(np.count_nonzero(have & ~ok))
        return ok

    # -- the update --------------------------------------------------------------------------------
    def update_many(self, t_s: ArrayLike, gyro: ArrayLike, acc: ArrayLike,
                    mag: ArrayLike | None = None) -> OrientationResult:
        """Run the filter over n samples (continuing from the previous call).

        Args:
            t_s: (n,) sample times, seconds (any origin, the same between calls); dt comes from these.
            gyro: (n, 3) rad/s, sensor frame.
            acc: (n, 3) m/s^2, sensor frame.
            mag: optional (n, 3) magnetometer readings taken with these samples (NaN rows: none; held
                from earlier readings). Readings at other times go through :meth:`add_mag`.

        Returns:
            The orientation, gravity, linear acceleration and flags of every sample (one output per
            input: a sample that is not integrated repeats the previous orientation and is flagged).

        Raises:
            ValueError: array shapes disagree.
        """
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        g = np.asarray(gyro, np.float64).reshape(-1, 3)
        a = np.asarray(acc, np.float64).reshape(-1, 3)
        n = t.shape[0]
        if g.shape[0] != n or a.shape[0] != n:
            raise ValueError(f"t, gyro and acc lengths differ: {n}, {g.shape[0]}, {a.shape[0]}")
        if mag is not None:
            m_in = np.asarray(mag, np.float64).reshape(-1, 3)
            if m_in.shape[0] != n:
                raise ValueError(f"mag length {m_in.shape[0]} differs from {n}")
            self.add_mag(t, m_in)
        out = StepOutputs(np.empty((n, 4)), np.zeros(n, np.uint16), np.empty(n), np.empty(n))
        flags = out.flags
        if n == 0:
            return OrientationResult(out.q, np.empty((0, 3)), np.empty((0, 3)), flags, out.acc_error_deg,
                                     out.mag_error_deg)
        # time steps, from the timestamps only
        max_gap = self._max_gap
        ok_all = bool(np.isfinite(t.sum() + g.sum()))
        t_last = self._t_last
        if ok_all and t_last is not None:
            dt = np.empty(n)
            dt[0] = t[0] - t_last
            np.subtract(t[1:], t[:-1], out=dt[1:])
            fast = bool(dt.min() > 0 and dt.max() <= max_gap)
        else:
            fast = False
        if fast:
            mode = np.zeros(n, np.int8)
            t_end = float(t[-1])
        else:
            mode = np.zeros(n, np.int8)
            g_ok = np.isfinite(g).all(axis=1) & np.isfinite(t)
            # previous *accepted* time of each sample: a rejected or non-increasing sample does not move it
            run_max = np.maximum.accumulate(np.concatenate([[-np.inf if t_last is None else t_last],
                                                            np.where(g_ok, t, -np.inf)]))
            prev = run_max[:-1]
            dt = t - prev
            bad_time = g_ok & (dt <= 0)
            gap = g_ok & (dt > max_gap) & np.isfinite(prev)
            first = g_ok & ~np.isfinite(prev)
            mode[~g_ok | bad_time] = MODE_SKIP
            mode[gap | first] = MODE_INIT
            flags[~g_ok | bad_time] |= FLAG_SKIPPED
            flags[gap] |= FLAG_GAP
            flags[gap | first] |= FLAG_INIT
            self.rejected += int(np.count_nonzero(~g_ok))
            self.non_increasing += int(np.count_nonzero(bad_time))
            self.gaps += int(np.count_nonzero(gap))
            t_end = float(run_max[-1]) if np.isfinite(run_max[-1]) else math.nan
        self.samples += n
        if not self._rate_known:
            run = np.flatnonzero(mode == MODE_RUN)
            if run.size:
                self._set_rate_from(float(dt[run[0]]))
        if self._mag_seen:
            mag_arr, have = self._held_mag(t)
            use_mag = self._gate(t, mag_arr, have)
            flags[~have] |= FLAG_NO_MAG
            flags[have & ~use_mag] |= FLAG_MAG_IGNORED
            self.mag_stale += int(np.count_nonzero(~have))
            self.mag_used += int(np.count_nonzero(use_mag))
        else:
            mag_arr = np.zeros((n, 3))
            use_mag = np.zeros(n, bool)
        if not fast or self._await_heading:
            self._heading_from_mag(t, mode, use_mag, flags)
        self._backend.run(Steps(dt, g, a, mag_arr, use_mag, mode, self._q), out)
        self._q = out.q[-1].copy()
        self.integrated += n if fast else int(np.count_nonzero(mode == MODE_RUN))
        if math.isfinite(t_end):
            self._t_last = t_end
        grav = gravity_from_quaternion(out.q)
        lin = a - grav
        return OrientationResult(out.q, grav, lin, flags, out.acc_error_deg, out.mag_error_deg)

    def _heading_from_mag(self, t: np.ndarray, mode: np.ndarray, use_mag: np.ndarray, flags: np.ndarray) -> None:
        """A start (or restart after a gap) usually sees its IMU sample before the magnetometer
        reading of the same instant, so it starts with an arbitrary heading, which the filter would
        then take seconds to turn to north. Initialise again at the first usable reading instead."""
        start = 0
        inits = np.flatnonzero(mode == MODE_INIT)
        if inits.size:
            k = int(inits[-1])
            self._init_t = float(t[k])
            self._await_heading = not bool(use_mag[k])
            start = k + 1
        if not self._await_heading:
            return
        hits = np.flatnonzero(use_mag[start:] & (mode[start:] == MODE_RUN))
        if not hits.size:
            if math.isfinite(self._init_t) and float(t[-1]) - self._init_t > _HEADING_WAIT_S:
                self._await_heading = False
            return
        j = start + int(hits[0])
        self._await_heading = False
        if float(t[j]) - self._init_t <= _HEADING_WAIT_S:
            mode[j] = MODE_INIT
            flags[j] |= FLAG_INIT
            self._init_t = float(t[j])
            self.heading_inits += 1

    def _set_rate_from(self, dt: float) -> None:
        """Without ``nominal_rate_hz``, Fusion's sample_rate (its startup ramp and rejection timeout in
        samples) is taken from the first integrated time step: the same sample whatever the chunking."""
        self._rate_known = True
        if isinstance(self._backend, FusionBackend) and dt > 0:
            self._backend.set_rate(min(10_000.0, max(1.0, 1.0 / dt)))

    def update_one(self, t_s: float, gyro: Vec3, acc: Vec3) -> tuple[Quat, int]:
        """One sample, the fast way: the same result as :meth:`update_many` on that sample alone
        (bit for bit), without building arrays where the filter allows (Fusion, no magnetometer
        stream). Returns the quaternion (sensor -> ENU) and the flags.
        """
        be = self._backend
        if type(be) is not FusionBackend or self._mag_seen or be.offset is not None:
            return self._update_one_many(t_s, gyro, acc)
        t_last = self._t_last
        gx, gy, gz = gyro
        if (t_last is None or not (math.isfinite(t_s) and math.isfinite(gx) and math.isfinite(gy) and math.isfinite(gz))
                or not (0.0 < t_s - t_last <= self._max_gap)):
            return self._update_one_many(t_s, gyro, acc)
        dt = t_s - t_last
        self.samples += 1
        if not self._rate_known:
            self._set_rate_from(dt)
        # the arithmetic of FusionBackend.run for this one sample, on plain floats (inline: a call
        # into the backend costs ~0.25 us, ~10% of the one-sample path)
        ax, ay, az = acc
        acc_ok = math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)
        ahrs = be.ahrs
        ahrs.set_sample_period(dt)
        ahrs.update_no_magnetometer(np.array((gx * _R2D, gy * _R2D, gz * _R2D)),
                                    np.array((ax * _INV_G0, ay * _INV_G0, az * _INV_G0)) if acc_ok else _ZERO3)
        if be.grace_left > 0:
            be.tick(dt)
        w, x, y, z = ahrs.get_quaternion().tolist()
        st = ahrs.get_internal_states()
        fl = ahrs.get_flags()
        f = 0
        if st.accelerometer_ignored or not acc_ok:
            f |= FLAG_ACC_IGNORED
        if fl.acceleration_recovery:
            f |= FLAG_ACC_RECOVERY
        if fl.overrange_recovery:
            f |= FLAG_OVERRANGE
        self._q = np.array((w, x, y, z))
        self._t_last = t_s
        self.integrated += 1
        return (w, x, y, z), f

    def _update_one_many(self, t_s: float, gyro: Vec3, acc: Vec3) -> tuple[Quat, int]:
        r = self.update_many([t_s], [gyro], [acc])
        w, x, y, z = r.q[0].tolist()
        return (w, x, y, z), int(r.flags[0])

    def update(self, t_s: float, gyro: ArrayLike, acc: ArrayLike, mag: ArrayLike | None = None) -> OrientationResult:
        """One sample (see :meth:`update_many`)."""
        return self.update_many([t_s], np.asarray(gyro, np.float64).reshape(1, 3),
                                np.asarray(acc, np.float64).reshape(1, 3),
                                None if mag is None else np.asarray(mag, np.float64).reshape(1, 3))

    @property
    def quaternion(self) -> np.ndarray:
        """The latest orientation (sensor -> ENU)."""
        return self._q.copy()

    @property
    def mahony_bias(self) -> np.ndarray | None:
        """The Mahony filter's integral (bias) term, rad/s; ``None`` for other kinds."""
        b = self._backend
        return b.bias if isinstance(b, MahonyBackend) else None

    def stats(self) -> dict[str, int]:
        """Counters: samples, integrated, gaps, non_increasing, rejected, mag_used, mag_stale, mag_gated."""
        return {"samples": self.samples, "integrated": self.integrated, "gaps": self.gaps,
                "non_increasing": self.non_increasing, "rejected": self.rejected, "mag_used": self.mag_used,
                "mag_stale": self.mag_stale, "mag_gated": self.mag_gated}
