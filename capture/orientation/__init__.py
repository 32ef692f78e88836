"""Orientation fusion: one filter interface over x-io Fusion (``imufusion``) and the ``ahrs``
package, the unit/frame check at the stream boundary, and the bus processor that turns IMU streams
into orientation, gravity and linear-acceleration streams.

What this module owns:

* :class:`OrientationFilter` - ``fusion`` (imufusion ``Ahrs``, optionally with its ``Bias``
  gyro-offset learner, acceleration and magnetic rejection), ``madgwick``, ``mahony`` and ``ekf``
  (from ``ahrs``), streaming (state kept between calls) with a batch call on arrays,
  :meth:`OrientationFilter.update_many`.
* :func:`check_imu_stream` / :func:`check_mag_stream` - units and frames checked where streams
  enter; they return the conversion to SI or raise :class:`~capture.errors.ConfigError`.
* :class:`OrientationProcessor` - the bus subscriber publishing ``<dev>/orientation``,
  ``<dev>/gravity`` and ``<dev>/linear_acc``.

**Conventions (every filter's output is converted to these).**

* World frame **ENU**: x east, y north, z up. With a magnetometer, "north" is the horizontal
  component of the (calibrated) magnetic field. Without one, heading is relative: at start (and
  after a gap) the heading is zero, i.e. the sensor x axis projected on the horizontal plane points
  along world +x.
* Quaternions are Hamilton, scalar first ``(w, x, y, z)``, and rotate **sensor-frame vectors into
  the world frame** (``v_world = q v_sensor q*``).
* ``gravity`` is what the accelerometer reads from gravity alone, in the sensor frame (pointing
  *up*, magnitude 9.80665 m/s^2), computed from the output quaternion; ``linear_acc`` is the
  accelerometer minus ``gravity`` (m/s^2, sensor frame). This is Fusion's definition.
* Inside the filter everything is rad/s and m/s^2 (Fusion is fed deg/s and g, converted here).

How each library's convention is mapped (verified on ``fusion_sensor_data.csv``, see
``benchmarks/bench_fusion.py``): imufusion is run with ``CONVENTION_ENU``; ``ahrs`` Madgwick's
magnetic model puts north along x with z up (NWU), so its quaternion is rotated by +90 deg about z;
``ahrs`` Mahony's magnetic model puts north along y (ENU already); ``ahrs`` EKF is run with
``frame='NED'`` - whose gravity reference ``[0, 0, 1]`` is compared with the *accelerometer*, so its
world z is in fact up - and with the magnetic reference given explicitly in ENU.

**Pitfalls handled (measured; see the tests).**

* ``dt`` always comes from the timestamps (never a library default rate: ``ahrs`` defaults to
  100 Hz, which turns a 256 Hz recording's rotations into the wrong size, ``ahrs#9``/``#29``).
  Non-increasing times are not integrated (counted); a step longer than ``max_gap_s`` (0.5 s) or
  than ``gap_periods`` (10) nominal sample periods is a gap and is not integrated across: the filter
  is re-initialised from the accelerometer (and magnetometer), keeping the heading when there is no
  magnetometer (counted, flagged). Fusion then runs ``init_grace_s`` (1 s) without rejection and with
  a gain of at least ``init_gain`` (2), or one accelerometer reading taken in motion could leave it
  rejecting the accelerometer until its recovery timeout (measured on a reconnecting simulated
  WitMotion: 54 deg median roll/pitch error before, 2 deg after).
* ``imufusion`` 1.3.3 ignores the ``convention`` keyword of ``AhrsSettings(...)`` (it stays NWU);
  settings are assigned one by one and read back.
* ``ahrs`` Mahony winds its integral (bias) term up during a fast spin and keeps the wound-up
  bias afterwards (a steady heading drift of several deg/s, or worse). The wrapper freezes the
  integrator while the rate or |a| says the accelerometer is not measuring gravity, and clamps the
  bias magnitude (``mahony_bias_limit_dps``).
* ``ahrs`` Madgwick and Mahony return the previous quaternion unchanged when the gyro reads
  exactly zero (common with quantised gyros at rest), skipping the accelerometer correction too;
  the wrapper feeds a 1e-12 rad/s rate instead.
* ``ahrs`` EKF uses a magnetic reference for Munich unless given one; here it is set from the
  first magnetometer and accelerometer readings (or ``magnetic_dip_deg``). Its measurement model
  is chosen by its ``mag`` attribute, which the wrapper sets per sample.
* Mixed rates: a magnetometer slower than the IMU is held (zero-order hold of the latest reading)
  for at most ``mag_max_age_s``; older readings are not used (flagged ``FLAG_NO_MAG``). The
  ``ahrs`` filters, which have no magnetic rejection, ignore readings whose magnitude differs from
  the reference by more than ``mag_norm_tol``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from capture.bus import SAMPLES, Subscriber
from capture.calibration import (
    G0,
    GyroBiasEstimator,
    ImuCalibration,
    quat_heading,
    quat_yaw,
)
from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate
from capture.sample import Sample, SampleBatch, StreamInfo

log = logging.getLogger(__name__)

FILTERS = ("fusion", "madgwick", "mahony", "ekf")

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

#: Per-sample flags (bit mask, ``OrientationResult.flags``).
FLAG_INIT = 1 << 0          # (re-)initialised from the accelerometer/magnetometer on this sample
FLAG_ACC_IGNORED = 1 << 1   # Fusion ignored the accelerometer (rejection), or no valid accelerometer
FLAG_MAG_IGNORED = 1 << 2   # a magnetometer reading was available but rejected (Fusion, or the norm gate)
FLAG_ACC_RECOVERY = 1 << 3  # Fusion acceleration recovery active
FLAG_MAG_RECOVERY = 1 << 4  # Fusion magnetic recovery active
FLAG_OVERRANGE = 1 << 5     # Fusion angular-rate (over-range) recovery active
FLAG_NO_MAG = 1 << 6        # a magnetometer is in use but no reading younger than mag_max_age_s
FLAG_GAP = 1 << 7           # the time since the previous sample exceeded max_gap_s (not integrated)
FLAG_SKIPPED = 1 << 8       # not integrated: time not after the previous sample, or invalid gyro
FLAG_BIAS_FROZEN = 1 << 9   # Mahony: bias integrator frozen or clamped on this sample

_D2R = math.pi / 180.0
_R2D = 180.0 / math.pi
_TINY_RATE = 1e-12
_INV_G0 = 1.0 / G0
_ZERO3 = np.zeros(3)
_MODE_RUN, _MODE_SKIP, _MODE_INIT = 0, 1, 2
#: how long after a start without a magnetometer reading its first reading still re-initialises
_HEADING_WAIT_S = 1.0

#: Rotation from Madgwick's native NWU world to ENU (+90 deg about z).
_NWU_TO_ENU = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])

_DEFAULTS: dict[str, Any] = {
    "nominal_rate_hz": None,      # sets Fusion's sample_rate (startup ramp, rejection timeout); else estimated
    "gain": None,                 # fusion gain (0.5), madgwick beta (0.033 IMU / 0.041 MARG), mahony k_P (1.0)
    "acc_rejection_deg": 10.0,    # fusion
    "mag_rejection_deg": 10.0,    # fusion
    "rejection_timeout_s": 5.0,   # fusion
    "gyro_range_dps": 0.0,        # fusion over-range recovery (0 = off; with no magnetometer Fusion zeroes heading in recovery)
    "gyro_offset": False,         # fusion: run imufusion.Bias (learns the gyro offset at rest, |w| < threshold)
    "offset_threshold_dps": 3.0,  # fusion Bias stationary threshold
    "offset_period_s": 3.0,       # fusion Bias stationary period
    "max_gap_s": 0.5,             # a time step longer than this is a gap (not integrated across) ...
    "gap_periods": 10.0,          # ... and so is one longer than this many nominal sample periods
    "init_grace_s": 1.0,          # fusion: no rejection for this long after an (re)initialisation ...
    "init_gain": 2.0,             # ... and at least this gain (a short version of Fusion's startup, which ramps 10 -> 0.5 over 3 s)
    "mag_max_age_s": 0.25,
    "mag_norm_tol": 0.1,          # ahrs filters: ignore |m| off the reference by more than this fraction
    "acc_norm_tol": 0.1,          # ahrs filters: gyro-only update when | |a|/g - 1 | exceeds this (0: off)
    "magnetic_dip_deg": None,     # ekf magnetic reference; default from the first readings
    "mahony_ki": 0.3,
    "mahony_bias_limit_dps": 3.0,
    "mahony_freeze_dps": 100.0,   # freeze the Mahony integrator above this rate
    "mahony_freeze_acc": 0.1,     # ... or when | |a|/g - 1 | exceeds this
    "ekf_noises": (0.3 ** 2, 0.5 ** 2, 0.8 ** 2),
}


# ------------------------------------------------------------------------------------------------
# Stream boundary: units and frames.

_ACC_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "m s^-2": 1.0, "m/s/s": 1.0,
              "g": G0, "g0": G0, "gn": G0, "mg": G0 * 1e-3}
_GYRO_UNITS = {"rad/s": 1.0, "rad s^-1": 1.0, "deg/s": _D2R, "dps": _D2R, "°/s": _D2R, "degree/s": _D2R,
               "degrees/s": _D2R, "mrad/s": 1e-3}
_MAG_UNITS = {"t", "mt", "ut", "µt", "μt", "nt", "g", "gauss", "mg", "mgauss", "count", "counts", "lsb", "1", "a.u."}


@dataclass(frozen=True)
class ImuChannels:
    """Where the accelerometer and gyro are in an IMU stream's values and how to make them SI.

    Attributes:
        stream: the stream name.
        acc_idx: value columns of ax, ay, az.
        acc_scale: factor to m/s^2.
        gyro_idx: value columns of gx, gy, gz.
        gyro_scale: factor to rad/s.
    """

    stream: str
    acc_idx: tuple[int, int, int]
    acc_scale: float
    gyro_idx: tuple[int, int, int]
    gyro_scale: float

    @property
    def acc_sel(self) -> slice | list[int]:
        """Column selector of the accelerometer (a slice when the columns are consecutive)."""
        return _sel(self.acc_idx)

    @property
    def gyro_sel(self) -> slice | list[int]:
        return _sel(self.gyro_idx)


def _sel(idx: tuple[int, int, int]) -> slice | list[int]:
    return slice(idx[0], idx[0] + 3) if idx[1] == idx[0] + 1 and idx[2] == idx[0] + 2 else list(idx)


@dataclass(frozen=True)
class MagChannels:
    """Where the magnetometer is in a mag stream's values (its unit is kept; only direction matters)."""

    stream: str
    idx: tuple[int, int, int]
    unit: str


def _norm_unit(u: str) -> str:
    u = u.strip()
    return u if u in _ACC_UNITS or u in _GYRO_UNITS else u.replace(" ", "")


def _find(info: StreamInfo, names: tuple[str, str, str]) -> tuple[int, int, int]:
    lower = [c.lower() for c in info.channels]
    idx = []
    for nme in names:
        if nme not in lower:
            raise ConfigError(f"stream {info.name}: channel {nme!r} not found (channels: {', '.join(info.channels)})",
                              source=info.name)
        idx.append(lower.index(nme))
    return (idx[0], idx[1], idx[2])


def _check_frame(info: StreamInfo) -> None:
    f = (info.frame or "").lower()
    if "left-handed" in f or "left handed" in f:
        raise ConfigError(f"stream {info.name}: frame {info.frame!r} is left-handed; orientation needs a right-handed "
                          f"sensor frame (remap the axes in the device)", source=info.name)


def check_imu_stream(info: StreamInfo) -> ImuChannels:
    """Check an IMU stream at the boundary and return the conversion to rad/s and m/s^2.

    Accepted: kind ``imu``; channels ``ax ay az`` in m/s^2 or g (or mg), ``gx gy gz`` in rad/s or
    deg/s; a right-handed frame.

    Raises:
        ConfigError: wrong kind, a missing channel, a unit that is not accepted (the message names the
            stream, the channel and the unit found), axes of one sensor in different units, or a
            left-handed frame.
    """
    if info.kind != "imu":
        raise ConfigError(f"stream {info.name}: kind {info.kind!r} is not an IMU stream (kind 'imu')", source=info.name)
    _check_frame(info)
    ai = _find(info, ("ax", "ay", "az"))
    gi = _find(info, ("gx", "gy", "gz"))

    def scale(idx: tuple[int, int, int], table: dict[str, float], what: str) -> float:
        units = [_norm_unit(info.units[i]) for i in idx]
        for i, u in zip(idx, units):
            if u not in table and u.lower() not in table:
                raise ConfigError(f"stream {info.name}: channel {info.channels[i]} has unit {info.units[i]!r}, "
                                  f"not a {what} unit ({', '.join(sorted(table))})", source=info.name)
        sc = [table.get(u, table.get(u.lower(), 0.0)) for u in units]
        if len(set(sc)) != 1:
            raise ConfigError(f"stream {info.name}: {what} channels have different units "
                              f"{[info.units[i] for i in idx]}", source=info.name)
        return sc[0]

    return ImuChannels(info.name, ai, scale(ai, _ACC_UNITS, "acceleration"), gi, scale(gi, _GYRO_UNITS, "angular rate"))


def check_mag_stream(info: StreamInfo, imu: StreamInfo | None = None) -> MagChannels:
    """Check a magnetometer stream (and that it shares the IMU's sensor frame).

    Raises:
        ConfigError: wrong kind, a missing channel, an unknown unit or different units on the three
            axes (named), a left-handed frame, or a frame that differs from the IMU stream's.
    """
    if info.kind != "mag":
        raise ConfigError(f"stream {info.name}: kind {info.kind!r} is not a magnetometer stream (kind 'mag')",
                          source=info.name)
    _check_frame(info)
    idx = _find(info, ("mx", "my", "mz"))
    units = [info.units[i].strip() for i in idx]
    for i, u in zip(idx, units):
        if u.lower() not in _MAG_UNITS:
            raise ConfigError(f"stream {info.name}: channel {info.channels[i]} has unit {u!r}, not a magnetic-field "
                              f"unit ({', '.join(sorted(_MAG_UNITS))})", source=info.name)
    if len({u.lower() for u in units}) != 1:
        raise ConfigError(f"stream {info.name}: channels {[info.channels[i] for i in idx]} have different units {units}",
                          source=info.name)
    if imu is not None and info.frame and imu.frame and info.frame != imu.frame:
        raise ConfigError(f"stream {info.name}: frame {info.frame!r} differs from {imu.name}'s {imu.frame!r}; the "
                          f"magnetometer must be remapped to the IMU frame", source=info.name)
    return MagChannels(info.name, idx, units[0])


# ------------------------------------------------------------------------------------------------
# Results and helpers.

@dataclass(frozen=True)
class OrientationResult:
    """Output of :meth:`OrientationFilter.update_many` for n samples.

    Attributes:
        q: (n, 4) sensor -> world (ENU) quaternions, ``w x y z``.
        gravity: (n, 3) m/s^2, sensor frame (what gravity alone would make the accelerometer read).
        linear_acc: (n, 3) m/s^2, sensor frame (accelerometer minus gravity).
        flags: (n,) ``FLAG_*`` bit mask.
        acc_error_deg: (n,) Fusion's acceleration error (NaN for other filters).
        mag_error_deg: (n,) Fusion's magnetic error (NaN for other filters or without a reading).
    """

    q: np.ndarray
    gravity: np.ndarray
    linear_acc: np.ndarray
    flags: np.ndarray
    acc_error_deg: np.ndarray
    mag_error_deg: np.ndarray

    def __len__(self) -> int:
        return int(self.q.shape[0])


def gravity_from_quaternion(q: ArrayLike, g: float = G0) -> np.ndarray:
    """Gravity as the accelerometer reads it (up, magnitude ``g``) in the sensor frame, from
    sensor -> world (z up) quaternions (..., 4): the third row of the rotation matrix times g."""
    q = np.asarray(q, np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3,))
    out[..., 0] = 2.0 * (x * z - w * y) * g
    out[..., 1] = 2.0 * (y * z + w * x) * g
    out[..., 2] = (w * w - x * x - y * y + z * z) * g
    return out


def initial_orientation(acc: ArrayLike, mag: ArrayLike | None = None, heading_rad: float = 0.0) -> np.ndarray:
    """Orientation (sensor -> ENU) from one accelerometer reading and, if given, one magnetometer
    reading (north = horizontal field); without a magnetometer the tilt-only (smallest) rotation
    turned to ``heading_rad``.

    Raises:
        ValueError: the accelerometer reads zero or is not finite.
    """
    a = np.asarray(acc, np.float64)
    na = float(np.linalg.norm(a))
    if not (na > 0 and math.isfinite(na)):
        raise ValueError(f"cannot initialise orientation from accelerometer {a.tolist()}")
    up = np.array([[0.0, 0.0, 1.0]])
    if mag is not None:
        m = np.asarray(mag, np.float64)
        nm = float(np.linalg.norm(m))
        if nm > 0 and math.isfinite(nm) and np.linalg.norm(np.cross(a / na, m / nm)) > 0.05:
            r, _ = Rotation.align_vectors(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]), np.stack([a, m]),
                                          weights=[np.inf, 1.0])
            q = r.as_quat(scalar_first=True)
            return q if q[0] >= 0 else -q
    r, _ = Rotation.align_vectors(up, a[None, :])
    q = quat_mul(quat_yaw(heading_rad), r.as_quat(scalar_first=True))
    return q if q[0] >= 0 else -q


# ------------------------------------------------------------------------------------------------
# Backends: one per library, each with a per-sample loop over prepared arrays.

class _Backend:
    """State of one library filter; works in the library's native frame, reports ENU."""

    to_enu = np.array([1.0, 0.0, 0.0, 0.0])  # q_enu = to_enu * q_native

    def __init__(self, s: dict[str, Any]) -> None:
        self.s = s
        self.from_enu = quat_conj(self.to_enu)

    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        raise NotImplementedError

    def run(self, dt: np.ndarray, gyro: np.ndarray, acc: np.ndarray, mag: np.ndarray, use_mag: np.ndarray,
            mode: np.ndarray, flt: OrientationFilter, Q: np.ndarray, F: np.ndarray, AE: np.ndarray,
            ME: np.ndarray) -> None:
        raise NotImplementedError


class _FusionBackend(_Backend):
    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        import imufusion

        self._imf = imufusion
        self.ahrs = imufusion.Ahrs()
        self.rate = float(s["nominal_rate_hz"] or 100.0)
        self.grace_left = 0.0  # seconds of rejection-free updates left after an (re)initialisation
        self._apply_settings()
        self.offset: Any = None
        if s["gyro_offset"]:
            self.offset = imufusion.Bias()
            bs = imufusion.BiasSettings()
            bs.sample_rate = self.rate
            bs.stationary_threshold = float(s["offset_threshold_dps"])
            bs.stationary_period = float(s["offset_period_s"])
            self.offset.set_settings(bs)

    def _apply_settings(self, rejection: bool = True) -> None:
        imf = self._imf
        s = self.s
        st = imf.AhrsSettings()
        gain = 0.5 if s["gain"] is None else float(s["gain"])
        want = {"sample_rate": self.rate, "convention": imf.CONVENTION_ENU,
                "gain": gain if rejection else max(gain, float(s["init_gain"])),
                "gyroscope_range": float(s["gyro_range_dps"]),
                "acceleration_rejection": float(s["acc_rejection_deg"]) if rejection else 0.0,
                "magnetic_rejection": float(s["mag_rejection_deg"]) if rejection else 0.0,
                "rejection_timeout": float(s["rejection_timeout_s"])}
        # imufusion 1.3.3 ignores the ``convention`` constructor keyword: assign and read back each one
        for k, v in want.items():
            setattr(st, k, v)
            got = getattr(st, k)
            if (got != v) if isinstance(v, int) else not math.isclose(got, v, rel_tol=1e-6, abs_tol=1e-9):
                raise ConfigError(f"imufusion did not accept setting {k}={v} (reads back {got})")
        self.ahrs.set_settings(st)

    def set_rate(self, rate: float) -> None:
        if rate > 0 and not math.isclose(rate, self.rate, rel_tol=1e-3):
            self.rate = rate
            self._apply_settings(self.grace_left <= 0)

    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        self.ahrs.set_quaternion(np.asarray(q_enu, np.float64))
        self.ahrs.skip_startup()
        # One accelerometer reading taken in motion can be 10+ deg off; with rejection on, Fusion
        # would then ignore the accelerometer until its recovery timeout. Like Fusion's own startup,
        # run without rejection for a moment after every (re)initialisation.
        grace = float(self.s["init_grace_s"])
        if grace > 0:
            if self.grace_left <= 0:
                self._apply_settings(rejection=False)
            self.grace_left = grace

    def tick(self, dt: float) -> None:
        """Time passes after an update: end the post-initialisation grace when it is over."""
        self.grace_left -= dt
        if self.grace_left <= 0:
            self._apply_settings(rejection=True)

    def run(self, dt, gyro, acc, mag, use_mag, mode, flt, Q, F, AE, ME):  # type: ignore[override]
        ahrs = self.ahrs
        setp = ahrs.set_sample_period
        upd = ahrs.update
        upd_nm = ahrs.update_no_magnetometer
        getq = ahrs.get_quaternion
        gets = ahrs.get_internal_states
        getf = ahrs.get_flags
        off = self.offset.update if self.offset is not None else None
        gd = gyro * _R2D
        ag = acc * _INV_G0
        acc_ok = np.isfinite(ag).all(axis=1)
        ag[~acc_ok] = 0.0  # Fusion ignores a zero accelerometer: gyro-only update
        nan = math.nan
        n = dt.shape[0]
        # plain lists and row views made once: the per-sample loop then does no numpy indexing
        modes = mode.tolist()
        dts = dt.tolist()
        oks = acc_ok.tolist()
        ums = use_mag.tolist()
        g_rows = list(gd)
        a_rows = list(ag)
        m_rows = list(mag) if any(ums) else None
        qs: list[Any] = [None] * n
        ae = [nan] * n
        me = [nan] * n
        fs = [0] * n
        for i in range(n):
            md = modes[i]
            if md:
                if i:
                    flt._q = np.array(qs[i - 1], np.float64)
                if md == _MODE_SKIP:
                    qs[i] = flt._q
                    continue
                q0 = flt._init_q(i, acc, mag, use_mag)
                self.set_enu(q0, None)
                qs[i] = q0
                continue
            g = g_rows[i]
            if off is not None:
                g = off(g)
            setp(dts[i])
            if ums[i]:
                upd(g, a_rows[i], m_rows[i])  # type: ignore[index]
            else:
                upd_nm(g, a_rows[i])
            if self.grace_left > 0:
                self.tick(dts[i])
            qs[i] = getq()
            st = gets()
            fl = getf()
            f = 0
            if st.accelerometer_ignored or not oks[i]:
                f |= FLAG_ACC_IGNORED
            if ums[i]:
                me[i] = st.magnetic_error
                if st.magnetometer_ignored:
                    f |= FLAG_MAG_IGNORED
            ae[i] = st.acceleration_error
            if fl.acceleration_recovery:
                f |= FLAG_ACC_RECOVERY
            if fl.magnetic_recovery:
                f |= FLAG_MAG_RECOVERY
            if fl.overrange_recovery:
                f |= FLAG_OVERRANGE
            fs[i] = f
        Q[:] = qs
        AE[:] = ae
        ME[:] = me
        F |= np.array(fs, np.uint16)


class _AhrsBackend(_Backend):
    """Common loop of the ``ahrs`` filters (per-sample Python; ~3,000-9,000 samples/s)."""

    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])

    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        self.q = quat_mul(self.from_enu, q_enu)

    def step(self, q: np.ndarray, g: np.ndarray, a: np.ndarray | None, m: np.ndarray | None, dt: float) -> tuple[np.ndarray, int]:
        raise NotImplementedError

    def run(self, dt, gyro, acc, mag, use_mag, mode, flt, Q, F, AE, ME):  # type: ignore[override]
        to_enu = self.to_enu
        gz = ~gyro.any(axis=1)
        if gz.any():
            gyro = gyro.copy()
            gyro[gz, 0] = _TINY_RATE  # ahrs skips the whole update (acc too) on an exactly-zero rate
        acc_ok = np.isfinite(acc).all(axis=1) & (acc.any(axis=1))
        tol = float(self.s["acc_norm_tol"])
        if tol > 0:
            # no acceleration rejection in these filters: skip the accelerometer when |a| is not g
            acc_ok &= np.abs(np.linalg.norm(acc, axis=1) * (1.0 / G0) - 1.0) <= tol
        AE[:] = np.nan
        ME[:] = np.nan
        for i in range(dt.shape[0]):
            md = mode[i]
            if md:
                if i:
                    flt._q = Q[i - 1].copy()
                if md == _MODE_SKIP:
                    Q[i] = flt._q
                    continue
                q0 = flt._init_q(i, acc, mag, use_mag)
                self.set_enu(q0, mag[i] if use_mag[i] else None)
                Q[i] = q0
                continue
            q, f = self.step(self.q, gyro[i], acc[i] if acc_ok[i] else None, mag[i] if use_mag[i] else None,
                             float(dt[i]))
            nq = math.sqrt(float(q @ q))
            q = q / nq
            self.q = q
            Q[i] = quat_mul(to_enu, q)
            if not acc_ok[i]:
                f |= FLAG_ACC_IGNORED
            if f:
                F[i] |= f


class _MadgwickBackend(_AhrsBackend):
    to_enu = _NWU_TO_ENU

    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        from ahrs.filters import Madgwick

        g = s["gain"]
        self.gain_imu = 0.033 if g is None else float(g)
        self.gain_marg = 0.041 if g is None else float(g)
        self.f = Madgwick(gain_imu=self.gain_imu, gain_marg=self.gain_marg)

    def step(self, q, g, a, m, dt):  # type: ignore[override]
        f = self.f
        if a is None:
            a = np.zeros(3)  # Madgwick integrates the gyro alone when |a| = 0
        if m is not None:
            f.gain = self.gain_marg
            return np.asarray(f.updateMARG(q, g, a, m, dt=dt), np.float64), 0
        f.gain = self.gain_imu
        return np.asarray(f.updateIMU(q, g, a, dt=dt), np.float64), 0


class _MahonyBackend(_AhrsBackend):
    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        from ahrs.filters import Mahony

        kp = 1.0 if s["gain"] is None else float(s["gain"])
        self.f = Mahony(k_P=kp, k_I=float(s["mahony_ki"]), b0=np.zeros(3))
        self.limit = float(s["mahony_bias_limit_dps"]) * _D2R
        self.freeze_rate = float(s["mahony_freeze_dps"]) * _D2R
        self.freeze_acc = float(s["mahony_freeze_acc"])

    @property
    def bias(self) -> np.ndarray:
        return np.array(self.f.b, np.float64)

    def step(self, q, g, a, m, dt):  # type: ignore[override]
        f = self.f
        b_prev = f.b.copy()
        flag = 0
        if a is None:
            a = np.zeros(3)
        if m is not None:
            out = f.updateMARG(q, g, a, m, dt=dt)
        else:
            out = f.updateIMU(q, g, a, dt=dt)
        na = math.sqrt(float(a @ a))
        if (math.sqrt(float(g @ g)) > self.freeze_rate or abs(na / G0 - 1.0) > self.freeze_acc):
            f.b[:] = b_prev  # anti-windup: the accelerometer is not measuring gravity now
            flag = FLAG_BIAS_FROZEN
        nb = math.sqrt(float(f.b @ f.b))
        if nb > self.limit:
            f.b *= self.limit / nb
            flag = FLAG_BIAS_FROZEN
        return np.asarray(out, np.float64), flag


class _EkfBackend(_AhrsBackend):
    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        from ahrs.filters import EKF

        self._mag_marker = np.zeros(3)
        self.ref_set = s["magnetic_dip_deg"] is not None
        noises = [float(x) for x in s["ekf_noises"]]
        # frame='NED' makes the gravity reference [0, 0, 1], which the EKF compares with the
        # normalised accelerometer (pointing up at rest): its world z is up, i.e. our ENU. The
        # magnetic reference is given in ENU (never the library's Munich default).
        self.f = EKF(frame="NED", magnetic_ref=self._m_ref(60.0 if s["magnetic_dip_deg"] is None
                                                            else float(s["magnetic_dip_deg"])), noises=noises)

    @staticmethod
    def _m_ref(dip_deg: float) -> np.ndarray:
        d = math.radians(dip_deg)
        return np.array([0.0, math.cos(d), -math.sin(d)])  # ENU: north, pointing down by the dip

    def _set_ref(self, q_enu: np.ndarray, m: np.ndarray) -> None:
        mw = quat_rotate(q_enu, m)  # the reading in the world frame; north = its horizontal part
        dip = -math.degrees(math.atan2(float(mw[2]), math.hypot(float(mw[0]), float(mw[1]))))
        self.f.m_ref = self._m_ref(dip)
        self.ref_set = True
        log.debug("ekf magnetic reference set from the data: dip %.1f deg", dip)

    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        super().set_enu(q_enu, mag_ref)
        if not self.ref_set and mag_ref is not None:
            self._set_ref(q_enu, mag_ref)

    def step(self, q, g, a, m, dt):  # type: ignore[override]
        f = self.f
        if m is not None and not self.ref_set:
            self._set_ref(quat_mul(self.to_enu, q), m)
        if a is None:
            return np.asarray(f.f(q, g, dt), np.float64), 0  # its process model (update() would not integrate)
        f.mag = self._mag_marker if m is not None else None  # selects the 6- or 3-row measurement model
        return np.asarray(f.update(q, g, a, m, dt=dt), np.float64), 0


_BACKENDS: dict[str, type[_Backend]] = {"fusion": _FusionBackend, "madgwick": _MadgwickBackend,
                                        "mahony": _MahonyBackend, "ekf": _EkfBackend}


# ------------------------------------------------------------------------------------------------
# The filter.

class OrientationFilter:
    """One orientation filter over the libraries, in one convention (see the module docstring).

    Args:
        kind: ``fusion``, ``madgwick``, ``mahony`` or ``ekf``.
        **settings: see ``_DEFAULTS`` in this module: ``nominal_rate_hz``, ``gain``,
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
        unknown = sorted(set(settings) - set(_DEFAULTS))
        if unknown:
            raise ConfigError(f"unknown orientation setting(s) {', '.join(unknown)}; known: {', '.join(sorted(_DEFAULTS))}")
        s = dict(_DEFAULTS)
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
            self._mag_ref_norm = (self._mag_ref_norm * self._mag_ref_n + float(norm[learning].sum())) / (self._mag_ref_n + k)
            self._mag_ref_n += k
        ok = have & (np.abs(norm / self._mag_ref_norm - 1.0) <= self.settings["mag_norm_tol"])
        self.mag_gated += int(np.count_nonzero(have & ~ok))
        return ok

    def _init_q(self, i: int, acc: np.ndarray, mag: np.ndarray, use_mag: np.ndarray) -> np.ndarray:
        a = acc[i]
        heading = float(quat_heading(self._q))
        m = mag[i] if use_mag[i] else None
        if not np.isfinite(a).all() or not a.any():
            q = self._q.copy()
        else:
            q = initial_orientation(a, m, heading)
        self._q = q
        return q

    # -- the update --------------------------------------------------------------------------------
    def update_many(self, t_s: ArrayLike, gyro: ArrayLike, acc: ArrayLike, mag: ArrayLike | None = None) -> OrientationResult:
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
        Q = np.empty((n, 4))
        F = np.zeros(n, np.uint16)
        AE = np.empty(n)
        ME = np.empty(n)
        if n == 0:
            return OrientationResult(Q, np.empty((0, 3)), np.empty((0, 3)), F, AE, ME)
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
            mode[~g_ok | bad_time] = _MODE_SKIP
            mode[gap | first] = _MODE_INIT
            F[~g_ok | bad_time] |= FLAG_SKIPPED
            F[gap] |= FLAG_GAP
            F[gap | first] |= FLAG_INIT
            self.rejected += int(np.count_nonzero(~g_ok))
            self.non_increasing += int(np.count_nonzero(bad_time))
            self.gaps += int(np.count_nonzero(gap))
            t_end = float(run_max[-1]) if np.isfinite(run_max[-1]) else math.nan
        self.samples += n
        if not self._rate_known:
            run = np.flatnonzero(mode == _MODE_RUN)
            if run.size:
                self._set_rate_from(float(dt[run[0]]))
        if self._mag_seen:
            mag_arr, have = self._held_mag(t)
            use_mag = self._gate(t, mag_arr, have)
            F[~have] |= FLAG_NO_MAG
            F[have & ~use_mag] |= FLAG_MAG_IGNORED
            self.mag_stale += int(np.count_nonzero(~have))
            self.mag_used += int(np.count_nonzero(use_mag))
        else:
            mag_arr = np.zeros((n, 3))
            use_mag = np.zeros(n, bool)
        if not fast or self._await_heading:
            self._heading_from_mag(t, mode, use_mag, F)
        self._backend.run(dt, g, a, mag_arr, use_mag, mode, self, Q, F, AE, ME)
        self._q = Q[-1].copy()
        self.integrated += n if fast else int(np.count_nonzero(mode == _MODE_RUN))
        if math.isfinite(t_end):
            self._t_last = t_end
        grav = gravity_from_quaternion(Q)
        lin = a - grav
        return OrientationResult(Q, grav, lin, F, AE, ME)

    def _heading_from_mag(self, t: np.ndarray, mode: np.ndarray, use_mag: np.ndarray, F: np.ndarray) -> None:
        """A start (or restart after a gap) usually sees its IMU sample before the magnetometer
        reading of the same instant, so it starts with an arbitrary heading, which the filter would
        then take seconds to turn to north. Initialise again at the first usable reading instead."""
        start = 0
        inits = np.flatnonzero(mode == _MODE_INIT)
        if inits.size:
            k = int(inits[-1])
            self._init_t = float(t[k])
            self._await_heading = not bool(use_mag[k])
            start = k + 1
        if not self._await_heading:
            return
        hits = np.flatnonzero(use_mag[start:] & (mode[start:] == _MODE_RUN))
        if not hits.size:
            if math.isfinite(self._init_t) and float(t[-1]) - self._init_t > _HEADING_WAIT_S:
                self._await_heading = False
            return
        j = start + int(hits[0])
        self._await_heading = False
        if float(t[j]) - self._init_t <= _HEADING_WAIT_S:
            mode[j] = _MODE_INIT
            F[j] |= FLAG_INIT
            self._init_t = float(t[j])
            self.heading_inits += 1

    def _set_rate_from(self, dt: float) -> None:
        """Without ``nominal_rate_hz``, Fusion's sample_rate (its startup ramp and rejection timeout in
        samples) is taken from the first integrated time step: the same sample whatever the chunking."""
        self._rate_known = True
        if isinstance(self._backend, _FusionBackend) and dt > 0:
            self._backend.set_rate(min(10_000.0, max(1.0, 1.0 / dt)))

    def update_one(self, t_s: float, gyro: tuple[float, float, float], acc: tuple[float, float, float]
                   ) -> tuple[tuple[float, float, float, float], int]:
        """One sample, the fast way: the same result as :meth:`update_many` on that sample alone
        (bit for bit), without building arrays where the filter allows (Fusion, no magnetometer
        stream). Returns the quaternion (sensor -> ENU) and the flags.
        """
        be = self._backend
        if type(be) is not _FusionBackend or self._mag_seen or be.offset is not None:
            r = self.update_many([t_s], [gyro], [acc])
            return tuple(r.q[0].tolist()), int(r.flags[0])  # type: ignore[return-value]
        t_last = self._t_last
        gx, gy, gz = gyro
        if (t_last is None or not (math.isfinite(t_s) and math.isfinite(gx) and math.isfinite(gy) and math.isfinite(gz))
                or not (0.0 < t_s - t_last <= self._max_gap)):
            r = self.update_many([t_s], [gyro], [acc])
            return tuple(r.q[0].tolist()), int(r.flags[0])  # type: ignore[return-value]
        dt = t_s - t_last
        self.samples += 1
        if not self._rate_known:
            self._set_rate_from(dt)
        ax, ay, az = acc
        acc_ok = math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)
        ahrs = be.ahrs
        ahrs.set_sample_period(dt)
        ahrs.update_no_magnetometer(np.array((gx * _R2D, gy * _R2D, gz * _R2D)),
                                    np.array((ax * _INV_G0, ay * _INV_G0, az * _INV_G0)) if acc_ok else _ZERO3)
        if be.grace_left > 0:
            be.tick(dt)
        q = tuple(ahrs.get_quaternion().tolist())
        st = ahrs.get_internal_states()
        fl = ahrs.get_flags()
        f = 0
        if st.accelerometer_ignored or not acc_ok:
            f |= FLAG_ACC_IGNORED
        if fl.acceleration_recovery:
            f |= FLAG_ACC_RECOVERY
        if fl.overrange_recovery:
            f |= FLAG_OVERRANGE
        self._q = np.array(q)
        self._t_last = t_s
        self.integrated += 1
        return q, f  # type: ignore[return-value]

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
        return b.bias if isinstance(b, _MahonyBackend) else None

    def stats(self) -> dict[str, int]:
        """Counters: samples, integrated, gaps, non_increasing, rejected, mag_used, mag_stale, mag_gated."""
        return {"samples": self.samples, "integrated": self.integrated, "gaps": self.gaps,
                "non_increasing": self.non_increasing, "rejected": self.rejected, "mag_used": self.mag_used,
                "mag_stale": self.mag_stale, "mag_gated": self.mag_gated}


# ------------------------------------------------------------------------------------------------
# The bus processor.

@dataclass
class _Track:
    info: StreamInfo
    chans: ImuChannels
    flt: OrientationFilter
    cal: ImuCalibration
    out: tuple[StreamInfo, StreamInfo, StreamInfo]
    mag: MagChannels | None = None
    origin_ns: int | None = None
    seq: int = 0
    bias_est: GyroBiasEstimator | None = None
    auto_bias: np.ndarray | None = None
    auto_bias_checked_s: float = -math.inf
    fast: bool = False  # Samples take the scalar path (Fusion, no magnetometer, no auto bias)


def _prefix(name: str) -> str:
    return name.rsplit("/", 1)[0] if "/" in name else name


class OrientationProcessor(Subscriber):
    """Bus subscriber: orientation, gravity and linear acceleration for one or more IMU streams.

    For every IMU input ``<dev>/imu`` it publishes ``<dev>/orientation`` (kind ``orientation``,
    channels ``w x y z``: body -> world ENU), ``<dev>/gravity`` and ``<dev>/linear_acc`` (m/s^2, in
    the body frame: the sensor frame unless the calibration has a mounting rotation), each sample
    with the input's t_host/t_device/t_bus times and its own seq. A ``Sample`` in gives ``Sample``s
    out, a ``SampleBatch`` gives ``SampleBatch``es, with identical values either way. A mag stream
    among the inputs is paired with the IMU stream of the same device (``<dev>/...``) and held at
    its own rate. dt comes from ``t_bus_ns`` (the device clock mapped to host time).

    Args:
        inputs: the IMU streams (kind ``imu``) and optional magnetometer streams (kind ``mag``).
        filter: the filter kind (see :class:`OrientationFilter`).
        calibrations: per-device calibration, keyed by IMU stream name, device prefix (``<dev>``),
            device serial or device name (looked up in that order).
        auto_bias: also estimate the gyro bias from stillness (:class:`GyroBiasEstimator`) and
            subtract it once its confidence reaches ``auto_bias_confidence``.
        auto_bias_confidence: see ``auto_bias``.
        **settings: filter settings (see :class:`OrientationFilter`); ``nominal_rate_hz`` defaults to
            each stream's.

    Raises:
        ConfigError: an input fails the unit/frame check, a mag stream has no IMU stream of the same
            device, two inputs would publish the same output name, or a filter setting is invalid.
    """

    accepts = SAMPLES

    def __init__(self, inputs: list[StreamInfo], filter: str = DEFAULT_FILTER,
                 calibrations: Mapping[str, ImuCalibration] | None = None, *, auto_bias: bool = False,
                 auto_bias_confidence: float = 0.9, **settings: Any) -> None:
        self.filter_kind = filter
        self._publish: Callable[[Any], None] | None = None
        self._tracks: dict[str, _Track] = {}
        self._mag_to_track: dict[str, _Track] = {}
        self.auto_bias_confidence = auto_bias_confidence
        cals = dict(calibrations or {})
        imus = [i for i in inputs if i.kind != "mag"]
        mags = [i for i in inputs if i.kind == "mag"]
        if not imus:
            raise ConfigError("orientation processor needs at least one IMU stream (kind 'imu')")
        used: dict[str, str] = {}
        for info in imus:
            ch = check_imu_stream(info)
            pre = _prefix(info.name)
            st = dict(settings)
            if st.get("nominal_rate_hz") is None and info.nominal_rate_hz:
                st["nominal_rate_hz"] = float(info.nominal_rate_hz)
            flt = OrientationFilter(filter, **st)
            cal = self._find_cal(cals, info)
            frame_note = "sensor frame" if cal.mounting == (1.0, 0.0, 0.0, 0.0) else "body (segment) frame via the mounting"
            extra = {"source": info.name, "filter": filter}
            outs = (
                StreamInfo(f"{pre}/orientation", "orientation", ("w", "x", "y", "z"), ("1", "1", "1", "1"),
                           info.nominal_rate_hz, info.device,
                           "quaternion rotating body-frame vectors into the world frame ENU (x east, y north, z up); "
                           "Hamilton, scalar first", info.clock, None, dict(extra)),
                StreamInfo(f"{pre}/gravity", "gravity", ("x", "y", "z"), ("m/s^2",) * 3, info.nominal_rate_hz,
                           info.device, f"{frame_note} of {info.name}; the accelerometer reading due to gravity (up)",
                           info.clock, None, dict(extra)),
                StreamInfo(f"{pre}/linear_acc", "linear_acc", ("x", "y", "z"), ("m/s^2",) * 3, info.nominal_rate_hz,
                           info.device, f"{frame_note} of {info.name}; accelerometer minus gravity", info.clock, None,
                           dict(extra)),
            )
            for o in outs:
                if o.name in used or o.name in {i.name for i in inputs}:
                    raise ConfigError(f"orientation output {o.name} of {info.name} collides with "
                                      f"{used.get(o.name, 'an input stream')}", source=info.name)
                used[o.name] = info.name
            tr = _Track(info, ch, flt, cal, outs)
            if auto_bias:
                tr.bias_est = GyroBiasEstimator()
            self._tracks[info.name] = tr
        by_prefix = {_prefix(t.info.name): t for t in self._tracks.values()}
        for info in mags:
            mtr = by_prefix.get(_prefix(info.name))
            if mtr is None:
                raise ConfigError(f"magnetometer stream {info.name} has no IMU stream of the same device among the "
                                  f"inputs ({', '.join(self._tracks)})", source=info.name)
            if mtr.mag is not None:
                raise ConfigError(f"IMU stream {mtr.info.name} has two magnetometer streams ({mtr.mag.stream}, {info.name})",
                                  source=info.name)
            mtr.mag = check_mag_stream(info, mtr.info)
            self._mag_to_track[info.name] = mtr
        for tr in self._tracks.values():
            tr.fast = filter == "fusion" and tr.mag is None and tr.bias_est is None and not settings.get("gyro_offset")
        self.samples_in = 0
        self.samples_out = 0
        self.mag_in = 0
        self.ignored_items = 0
        self.items_in = 0

    @staticmethod
    def _find_cal(cals: dict[str, ImuCalibration], info: StreamInfo) -> ImuCalibration:
        for key in (info.name, _prefix(info.name), info.device.serial, info.device.name):
            if key and key in cals:
                return cals[key]
        return ImuCalibration()

    # -- wiring ----------------------------------------------------------------------------------
    def output_streams(self) -> list[StreamInfo]:
        """The streams this processor publishes (declare them before data flows)."""
        return [o for t in self._tracks.values() for o in t.out]

    def bind(self, publish: Callable[[Any], None]) -> None:
        """Set the publish callable (called once before data flows)."""
        self._publish = publish

    def set_calibration(self, stream: str, cal: ImuCalibration) -> None:
        """Replace the calibration of an IMU input (e.g. after a yaw or mounting reset).

        Raises:
            KeyError: ``stream`` is not an IMU input.
        """
        self._tracks[stream].cal = cal

    def filter_of(self, stream: str) -> OrientationFilter:
        """The filter of an IMU input (for its counters and state)."""
        return self._tracks[stream].flt

    # -- data ------------------------------------------------------------------------------------
    def on_item(self, item: Any) -> None:
        """Process one ``Sample`` or ``SampleBatch`` (items of other streams are counted and ignored).

        Raises:
            RuntimeError: :meth:`bind` was not called.
        """
        if self._publish is None:
            raise RuntimeError("OrientationProcessor.bind(publish) was not called")
        tr = self._tracks.get(item.stream)
        if tr is None:
            mt = self._mag_to_track.get(item.stream)
            if mt is None:
                self.ignored_items += 1  # not ours (including our own outputs)
                return
            self._on_mag(mt, item)
            return
        self.items_in += 1
        if type(item) is Sample:
            if tr.fast:
                self._run_one(tr, item)
            else:
                self._run(tr, np.asarray([item.values], np.float64), np.asarray([item.t_bus_ns], np.int64), item)
        else:
            self._run(tr, np.asarray(item.values, np.float64), np.asarray(item.t_bus_ns, np.int64), item)

    def _t_s(self, tr: _Track, t_ns: np.ndarray) -> np.ndarray:
        if tr.origin_ns is None:
            tr.origin_ns = int(t_ns[0])
        return (t_ns - tr.origin_ns) / 1e9

    def _on_mag(self, tr: _Track, item: Any) -> None:
        assert tr.mag is not None
        if type(item) is Sample:
            v = np.asarray([item.values], np.float64)
            t_ns = np.asarray([item.t_bus_ns], np.int64)
        else:
            v = np.asarray(item.values, np.float64)
            t_ns = np.asarray(item.t_bus_ns, np.int64)
        if v.shape[0] == 0:
            return
        m = v[:, list(tr.mag.idx)]
        m = tr.cal.apply_mag(m)
        self.mag_in += v.shape[0]
        tr.flt.add_mag(self._t_s(tr, t_ns), m)

    def _run_one(self, tr: _Track, item: Sample) -> None:
        """One Sample with Fusion: the arithmetic of :meth:`_run` on plain floats (same results)."""
        v = item.values
        ch = tr.chans
        i0, i1, i2 = ch.acc_idx
        sc = ch.acc_scale
        ax, ay, az = v[i0] * sc, v[i1] * sc, v[i2] * sc
        j0, j1, j2 = ch.gyro_idx
        sc = ch.gyro_scale
        gx, gy, gz = v[j0] * sc, v[j1] * sc, v[j2] * sc
        cal = tr.cal
        if not cal.sensor_identity:
            (ax, ay, az), (gx, gy, gz) = cal.apply_one((ax, ay, az), (gx, gy, gz))
        if tr.origin_ns is None:
            tr.origin_ns = item.t_bus_ns
        t = (item.t_bus_ns - tr.origin_ns) / 1e9
        q, _ = tr.flt.update_one(t, (gx, gy, gz), (ax, ay, az))
        w, x, y, z = q
        g0 = G0
        grav = (2.0 * (x * z - w * y) * g0, 2.0 * (y * z + w * x) * g0, (w * w - x * x - y * y + z * z) * g0)
        lin = (ax - grav[0], ay - grav[1], az - grav[2])
        if not cal.body_identity:
            q = tuple(cal.body_orientation(np.array([q]))[0].tolist())
            grav = tuple(cal.to_body(np.array([grav]))[0].tolist())
            lin = tuple(cal.to_body(np.array([lin]))[0].tolist())
        self.samples_in += 1
        self.samples_out += 1
        pub = self._publish
        assert pub is not None
        o_q, o_g, o_l = tr.out
        s0 = tr.seq
        tr.seq = s0 + 1
        th, td, tb = item.t_host_ns, item.t_device_ns, item.t_bus_ns
        pub(Sample(o_q.name, s0, th, td, tb, q))
        pub(Sample(o_g.name, s0, th, td, tb, grav))
        pub(Sample(o_l.name, s0, th, td, tb, lin))

    def _run(self, tr: _Track, v: np.ndarray, t_ns: np.ndarray, item: Any) -> None:
        n = v.shape[0]
        if n == 0:
            return
        ch = tr.chans
        acc = v[:, ch.acc_sel] * ch.acc_scale
        gyro = v[:, ch.gyro_sel] * ch.gyro_scale
        cal = tr.cal
        if not cal.sensor_identity:
            acc, gyro, _ = cal.apply(acc, gyro)
        t = self._t_s(tr, t_ns)
        if tr.bias_est is not None:
            self._auto_bias(tr, t, gyro, acc)
            if tr.auto_bias is not None:
                gyro = gyro - tr.auto_bias
        res = tr.flt.update_many(t, gyro, acc)
        if cal.body_identity:
            q, grav, lin = res.q, res.gravity, res.linear_acc
        else:
            q = cal.body_orientation(res.q)
            grav = cal.to_body(res.gravity)
            lin = cal.to_body(res.linear_acc)
        self.samples_in += n
        self.samples_out += n
        pub = self._publish
        assert pub is not None
        o_q, o_g, o_l = tr.out
        s0 = tr.seq
        tr.seq += n
        if type(item) is Sample:
            th, td, tb = item.t_host_ns, item.t_device_ns, item.t_bus_ns
            pub(Sample(o_q.name, s0, th, td, tb, tuple(q[0].tolist())))
            pub(Sample(o_g.name, s0, th, td, tb, tuple(grav[0].tolist())))
            pub(Sample(o_l.name, s0, th, td, tb, tuple(lin[0].tolist())))
        else:
            seq = np.arange(s0, s0 + n, dtype=np.int64)
            pub(SampleBatch(o_q.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, q))
            pub(SampleBatch(o_g.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, grav))
            pub(SampleBatch(o_l.name, seq, item.t_host_ns, item.t_device_ns, item.t_bus_ns, lin))

    def _auto_bias(self, tr: _Track, t: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
        est = tr.bias_est
        assert est is not None
        est.update(t, gyro, acc)
        if t[-1] - tr.auto_bias_checked_s >= 1.0:  # the estimate costs up to ~1 ms: once a second
            tr.auto_bias_checked_s = float(t[-1])
            e = est.estimate
            if e.confidence >= self.auto_bias_confidence:
                if tr.auto_bias is None:
                    log.info("%s: auto gyro bias %s deg/s (confidence %.2f, %d still periods)", tr.info.name,
                             np.round(np.degrees(e.bias), 3).tolist(), e.confidence, e.periods)
                tr.auto_bias = e.bias.copy()

    def auto_bias(self, stream: str) -> np.ndarray | None:
        """The automatic bias applied to an IMU input (rad/s), or ``None`` while not confident."""
        return self._tracks[stream].auto_bias

    def stats(self) -> dict[str, Any]:
        """Counters: items and samples in and out, mag readings, ignored items, and per input its
        filter's counters (gaps skipped, non-increasing, rejected inputs, mag use)."""
        per = {name: tr.flt.stats() for name, tr in self._tracks.items()}
        return {"items_in": self.items_in, "samples_in": self.samples_in, "samples_out": self.samples_out,
                "mag_in": self.mag_in, "ignored_items": self.ignored_items,
                "gaps_skipped": sum(p["gaps"] for p in per.values()),
                "rejected_inputs": sum(p["rejected"] + p["non_increasing"] for p in per.values()),
                "streams": per}

    @property
    def gaps_skipped(self) -> int:
        return sum(tr.flt.gaps for tr in self._tracks.values())

    @property
    def rejected_inputs(self) -> int:
        return sum(tr.flt.rejected + tr.flt.non_increasing for tr in self._tracks.values())
