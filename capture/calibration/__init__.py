"""IMU calibration: the per-device correction record, the fits that produce it, and gyro-bias
estimation from stillness.

What this module owns:

* :class:`ImuCalibration` - a frozen record of gyro bias, accelerometer offset and 3x3
  scale/misalignment, magnetometer hard iron and soft iron, mounting rotation (sensor -> segment)
  and yaw offset, with a versioned JSON form (validated on load) and a vectorised :meth:`apply`.
* Stillness detection (:func:`still_mask`, :func:`still_segments`) and the explicit still-period
  bias (:func:`still_bias`, with its standard error; what ``perfcap calibrate`` runs).
* Automatic gyro-bias estimation with a confidence value (:class:`GyroBiasEstimator` for
  streams, :func:`estimate_gyro_bias` for arrays).
* Accelerometer offset/scale fit from several still poses (:func:`fit_accelerometer`),
  magnetometer hard- and soft-iron ellipsoid fit from a rotation dance (:func:`fit_magnetometer`),
  mounting reset (:func:`mounting_from_gravity`) and yaw reset (:meth:`ImuCalibration.with_yaw_reset`).
* Small vectorised quaternion helpers (Hamilton, scalar first ``w, x, y, z``), shared with
  :mod:`capture.orientation`.

Units: rad/s, m/s^2; the magnetometer in whatever unit its stream declares (only its direction
matters to the filters). Frames: every vector is in the sensor frame unless said otherwise; the world
frame is ENU (see :mod:`capture.orientation`).

**What automatic bias estimation can and cannot tell apart.** A gyroscope reading ``w`` during an
apparently still period is ``bias + true rotation``. The estimator separates them with every cue
it has:

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
"""

from __future__ import annotations

import json
import logging
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.special import erf

from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate

log = logging.getLogger(__name__)

#: Standard gravity, m/s^2.
G0 = 9.80665
#: Version of the JSON calibration format written by :meth:`ImuCalibration.to_json`.
FORMAT_VERSION = 1
FORMAT_NAME = "perfcap.imu_calibration"

_DEG = math.pi / 180.0
Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]
_I3: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_Z3: Vec3 = (0.0, 0.0, 0.0)


# ------------------------------------------------------------------------------------------------
# Headings about world z (quaternion maths is capture.quat).

def quat_heading(q: ArrayLike) -> np.ndarray | float:
    """Heading of orientations ``q`` (sensor or body -> world, z up): the twist angle about world z,
    ``2 atan2(z, w)``, wrapped to [-pi, pi). Left-multiplying by a yaw of ``a`` adds exactly ``a``."""
    q = np.asarray(q, np.float64)
    h = np.mod(2.0 * np.arctan2(q[..., 3], q[..., 0]) + math.pi, 2 * math.pi) - math.pi
    return float(h) if h.ndim == 0 else h


def quat_yaw(angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about world z, as a quaternion."""
    return np.array([math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)])


# ------------------------------------------------------------------------------------------------
# The calibration record.

def _vec(name: str, v: Any, source: str | None) -> Vec3:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"calibration field {name!r} must be 3 numbers, got {v!r}", source=source) from exc
    if a.shape != (3,):
        raise ConfigError(f"calibration field {name!r} must be 3 numbers, got shape {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"calibration field {name!r} has a non-finite value: {a.tolist()}", source=source)
    return (float(a[0]), float(a[1]), float(a[2]))


def _mat(name: str, v: Any, source: str | None) -> Mat3:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"calibration field {name!r} must be a 3x3 matrix, got {v!r}", source=source) from exc
    if a.shape != (3, 3):
        raise ConfigError(f"calibration field {name!r} must be a 3x3 matrix, got shape {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"calibration field {name!r} has a non-finite value", source=source)
    det = float(np.linalg.det(a))
    if abs(det) < 1e-6 * max(1e-300, float(np.abs(a).max()) ** 3):
        raise ConfigError(f"calibration field {name!r} is singular (det={det:.3g})", source=source)
    return tuple(tuple(float(x) for x in row) for row in a)  # type: ignore[return-value]


@dataclass(frozen=True)
class ImuCalibration:
    """Corrections for one IMU (one device identity). The identity default changes nothing.

    Model (vectors are rows of (n, 3) arrays, in the sensor frame)::

        gyro_c = gyro - gyro_bias
        acc_c  = acc_matrix @ (acc - acc_offset)
        mag_c  = mag_soft_iron @ (mag - mag_hard_iron)

    and for the orientation outputs, with ``q`` the sensor -> world orientation::

        q_body = yaw(-yaw_offset_rad) * q * conj(mounting)

    Args:
        gyro_bias: rad/s, subtracted from the gyroscope.
        acc_offset: m/s^2, subtracted before ``acc_matrix``.
        acc_matrix: 3x3 scale and misalignment of the accelerometer.
        mag_hard_iron: magnetometer offset, in the mag stream's unit.
        mag_soft_iron: 3x3 soft-iron correction.
        mounting: unit quaternion ``w, x, y, z`` rotating sensor-frame vectors into the segment
            (body) frame.
        yaw_offset_rad: heading subtracted from the body orientation (yaw reset).
        device: the device identity this belongs to (informative).
        note: free text (how and when it was made).

    Raises:
        ConfigError: a field has the wrong shape, is not finite, a matrix is singular, or the
            mounting quaternion is not of unit norm (within 1e-3).
    """

    gyro_bias: Vec3 = _Z3
    acc_offset: Vec3 = _Z3
    acc_matrix: Mat3 = _I3
    mag_hard_iron: Vec3 = _Z3
    mag_soft_iron: Mat3 = _I3
    mounting: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    yaw_offset_rad: float = 0.0
    device: str = ""
    note: str = ""
    _cache: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        src = self.device or None
        set_ = object.__setattr__
        set_(self, "gyro_bias", _vec("gyro_bias", self.gyro_bias, src))
        set_(self, "acc_offset", _vec("acc_offset", self.acc_offset, src))
        set_(self, "acc_matrix", _mat("acc_matrix", self.acc_matrix, src))
        set_(self, "mag_hard_iron", _vec("mag_hard_iron", self.mag_hard_iron, src))
        set_(self, "mag_soft_iron", _mat("mag_soft_iron", self.mag_soft_iron, src))
        try:
            m = np.asarray(self.mounting, np.float64)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"calibration field 'mounting' must be 4 numbers, got {self.mounting!r}",
                              source=src) from exc
        if m.shape != (4,) or not np.all(np.isfinite(m)):
            raise ConfigError(f"calibration field 'mounting' must be 4 finite numbers (w, x, y, z), got {self.mounting!r}",
                              source=src)
        nm = float(np.linalg.norm(m))
        if abs(nm - 1.0) > 1e-3:
            raise ConfigError(f"calibration field 'mounting' must be a unit quaternion, its norm is {nm:.6f}", source=src)
        m = m / nm
        if m[0] < 0:
            m = -m
        set_(self, "mounting", tuple(float(x) for x in m))
        try:
            y = float(self.yaw_offset_rad)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"calibration field 'yaw_offset_rad' must be a number, got {self.yaw_offset_rad!r}",
                              source=src) from exc
        if not math.isfinite(y):
            raise ConfigError("calibration field 'yaw_offset_rad' is not finite", source=src)
        set_(self, "yaw_offset_rad", math.remainder(y, 2 * math.pi))
        if not isinstance(self.device, str) or not isinstance(self.note, str):
            raise ConfigError("calibration fields 'device' and 'note' must be strings", source=src)

    # -- derived --------------------------------------------------------------------------------
    @property
    def is_identity(self) -> bool:
        """True when :meth:`apply` and the body transform change nothing."""
        return self == ImuCalibration(device=self.device, note=self.note)

    @property
    def sensor_identity(self) -> bool:
        """True when :meth:`apply` changes nothing (mounting and yaw may still be set)."""
        return (self.gyro_bias == _Z3 and self.acc_offset == _Z3 and self.acc_matrix == _I3
                and self.mag_hard_iron == _Z3 and self.mag_soft_iron == _I3)

    @property
    def body_identity(self) -> bool:
        """True when the mounting is identity and the yaw offset is zero."""
        return self.mounting == (1.0, 0.0, 0.0, 0.0) and self.yaw_offset_rad == 0.0

    def _arrays(self) -> dict[str, Any]:
        c = self._cache
        if not c:
            c["gb"] = np.array(self.gyro_bias)
            c["ao"] = np.array(self.acc_offset)
            c["am"] = np.array(self.acc_matrix)
            c["mh"] = np.array(self.mag_hard_iron)
            c["ms"] = np.array(self.mag_soft_iron)
            c["mq"] = np.array(self.mounting)
            c["mqc"] = quat_conj(c["mq"])
            c["yq"] = quat_yaw(-self.yaw_offset_rad)
        return c

    # -- application ----------------------------------------------------------------------------
    def apply(self, acc: ArrayLike, gyro: ArrayLike, mag: ArrayLike | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Corrected ``(acc, gyro, mag)``; arrays of shape (3,) or (n, 3), returned as new float64
        arrays of the same shape (``mag`` stays ``None`` when not given).

        The 3x3 products are written out term by term (not BLAS), so a batch and the same samples
        one by one give bit-identical results.
        """
        c = self._arrays()
        a = np.asarray(acc, np.float64)
        g = np.asarray(gyro, np.float64) - c["gb"]
        a = _mat_apply(c["am"], a - c["ao"])
        m = None
        if mag is not None:
            m = _mat_apply(c["ms"], np.asarray(mag, np.float64) - c["mh"])
        return a, g, m

    def apply_one(self, acc: tuple[float, float, float], gyro: tuple[float, float, float]
                  ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """:meth:`apply` for one sample as plain floats (the same arithmetic, the same results)."""
        b = self.gyro_bias
        o = self.acc_offset
        m = self.acc_matrix
        x, y, z = acc[0] - o[0], acc[1] - o[1], acc[2] - o[2]
        a = (m[0][0] * x + m[0][1] * y + m[0][2] * z, m[1][0] * x + m[1][1] * y + m[1][2] * z,
             m[2][0] * x + m[2][1] * y + m[2][2] * z)
        return a, (gyro[0] - b[0], gyro[1] - b[1], gyro[2] - b[2])

    def apply_mag(self, mag: ArrayLike) -> np.ndarray:
        """Hard- and soft-iron corrected magnetometer readings, (3,) or (n, 3)."""
        c = self._arrays()
        return _mat_apply(c["ms"], np.asarray(mag, np.float64) - c["mh"])

    def body_orientation(self, q: ArrayLike) -> np.ndarray:
        """Body (segment) -> world orientation from sensor -> world quaternions (..., 4)."""
        c = self._arrays()
        q = np.asarray(q, np.float64)
        if self.body_identity:
            return q.copy()
        return quat_mul(c["yq"], quat_mul(q, c["mqc"]))

    def to_body(self, v: ArrayLike) -> np.ndarray:
        """Sensor-frame vectors (..., 3) expressed in the body (segment) frame."""
        v = np.asarray(v, np.float64)
        if self.mounting == (1.0, 0.0, 0.0, 0.0):
            return v.copy()
        return quat_rotate(self._arrays()["mq"], v)

    # -- resets ---------------------------------------------------------------------------------
    def with_yaw_reset(self, q_sensor_world: ArrayLike) -> ImuCalibration:
        """A copy whose yaw offset makes the current body heading zero.

        Args:
            q_sensor_world: the current sensor -> world orientation (4,).
        """
        c = self._arrays()
        q_body = quat_mul(np.asarray(q_sensor_world, np.float64), c["mqc"])
        return replace(self, yaw_offset_rad=float(quat_heading(q_body)))

    def with_mounting_reset(self, acc_still: ArrayLike, segment_down: ArrayLike = (0.0, 0.0, -1.0),
                            sensor_forward: ArrayLike | None = None,
                            segment_forward: ArrayLike = (1.0, 0.0, 0.0)) -> ImuCalibration:
        """A copy with the mounting from a still pose (see :func:`mounting_from_gravity`)."""
        m = mounting_from_gravity(acc_still, segment_down, sensor_forward, segment_forward)
        return replace(self, mounting=m)

    def with_gyro_bias(self, bias: ArrayLike) -> ImuCalibration:
        return replace(self, gyro_bias=_vec("gyro_bias", bias, self.device or None))

    # -- JSON -----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "device": self.device,
            "note": self.note,
            "gyro_bias_rad_s": list(self.gyro_bias),
            "acc_offset_m_s2": list(self.acc_offset),
            "acc_matrix": [list(r) for r in self.acc_matrix],
            "mag_hard_iron": list(self.mag_hard_iron),
            "mag_soft_iron": [list(r) for r in self.mag_soft_iron],
            "mounting_wxyz": list(self.mounting),
            "yaw_offset_rad": self.yaw_offset_rad,
        }

    def to_json(self) -> str:
        """The calibration as a JSON object with ``format`` and ``version`` fields."""
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    _KEYS: ClassVar[dict[str, str]] = {"gyro_bias_rad_s": "gyro_bias", "acc_offset_m_s2": "acc_offset", "acc_matrix": "acc_matrix",
             "mag_hard_iron": "mag_hard_iron", "mag_soft_iron": "mag_soft_iron", "mounting_wxyz": "mounting",
             "yaw_offset_rad": "yaw_offset_rad", "device": "device", "note": "note"}

    @classmethod
    def from_dict(cls, d: Any, source: str | None = None) -> ImuCalibration:
        """Validated calibration from a parsed JSON object.

        Raises:
            ConfigError: not an object, wrong ``format``, missing or unsupported ``version``, an
                unknown key, or a bad value (see the class).
        """
        if not isinstance(d, dict):
            raise ConfigError(f"calibration must be a JSON object, got {type(d).__name__}", source=source)
        fmt = d.get("format", FORMAT_NAME)
        if fmt != FORMAT_NAME:
            raise ConfigError(f"not an IMU calibration (format {fmt!r}, expected {FORMAT_NAME!r})", source=source)
        if "version" not in d:
            raise ConfigError("calibration has no 'version' field", source=source)
        v = d["version"]
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ConfigError(f"calibration 'version' must be a positive integer, got {v!r}", source=source)
        if v > FORMAT_VERSION:
            raise ConfigError(f"calibration version {v} was written by a newer perfcap (this one reads up to "
                              f"{FORMAT_VERSION})", source=source)
        unknown = sorted(set(d) - set(cls._KEYS) - {"format", "version"})
        if unknown:
            raise ConfigError(f"calibration has unknown field(s) {', '.join(unknown)}; known: "
                              f"{', '.join(sorted(cls._KEYS))}", source=source)
        kw = {cls._KEYS[k]: val for k, val in d.items() if k in cls._KEYS}
        try:
            return cls(**kw)
        except ConfigError as exc:
            raise ConfigError(str(exc), source=source or exc.source) from None

    @classmethod
    def from_json(cls, text: str | bytes, source: str | None = None) -> ImuCalibration:
        """Parse and validate :meth:`to_json` output.

        Raises:
            ConfigError: the text is not JSON, or the content is invalid (see :meth:`from_dict`).
        """
        try:
            d = json.loads(text)
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"calibration is not valid JSON: {exc}", source=source) from exc
        return cls.from_dict(d, source)


def _mat_apply(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``m @ v`` for vectors in the last axis, written term by term (deterministic rounding)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([m[0, 0] * x + m[0, 1] * y + m[0, 2] * z,
                     m[1, 0] * x + m[1, 1] * y + m[1, 2] * z,
                     m[2, 0] * x + m[2, 1] * y + m[2, 2] * z], axis=-1)


# ------------------------------------------------------------------------------------------------
# Mounting.

def mounting_from_gravity(acc_still: ArrayLike, segment_down: ArrayLike = (0.0, 0.0, -1.0),
                          sensor_forward: ArrayLike | None = None,
                          segment_forward: ArrayLike = (1.0, 0.0, 0.0)) -> tuple[float, float, float, float]:
    """Mounting rotation (sensor -> segment) from a still pose: the rotation that maps the measured
    gravity direction onto the segment's down axis.

    The accelerometer at rest reads the reaction to gravity (pointing up), so gravity in the sensor
    frame is ``-acc``. With only gravity the rotation about the down axis is free: the smallest
    rotation is returned, unless ``sensor_forward`` (a sensor axis that should point along
    ``segment_forward``) fixes it.

    Args:
        acc_still: mean accelerometer reading (3,) or samples (n, 3) of the still pose, any unit.
        segment_down: the segment axis that points down in that pose.
        sensor_forward: optional sensor-frame direction that should map onto ``segment_forward``.
        segment_forward: see ``sensor_forward``.

    Returns:
        The mounting quaternion ``(w, x, y, z)``.

    Raises:
        ConfigError: the accelerometer reading is zero or not finite, or the forward axis is
            parallel to gravity.
    """
    a = np.asarray(acc_still, np.float64)
    if a.ndim == 2:
        a = a.mean(axis=0)
    n = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
    if not (n > 0 and math.isfinite(n)):
        raise ConfigError(f"mounting reset needs a non-zero, finite accelerometer reading, got {a.tolist()}")
    down_s = -a / n
    down_b = np.asarray(segment_down, np.float64)
    down_b = down_b / np.linalg.norm(down_b)
    if sensor_forward is None:
        r, _ = Rotation.align_vectors(down_b[None, :], down_s[None, :])
    else:
        f = np.asarray(sensor_forward, np.float64)
        if np.linalg.norm(np.cross(f, down_s)) < 1e-3 * np.linalg.norm(f):
            raise ConfigError("mounting reset: the sensor forward axis is parallel to gravity")
        r, _ = Rotation.align_vectors(np.stack([down_b, np.asarray(segment_forward, np.float64)]),
                                      np.stack([down_s, f]), weights=[np.inf, 1.0])
    q = r.as_quat(scalar_first=True)
    if q[0] < 0:
        q = -q
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


# ------------------------------------------------------------------------------------------------
# Stillness.

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
    return ((asd.max(axis=1) <= acc_std_max) & (gsd.max(axis=1) <= gyro_std_max)
            & (np.linalg.norm(gm, axis=1) <= gyro_max)
            & (np.abs(np.linalg.norm(am, axis=1) - g) <= acc_norm_tol))


def still_segments(mask: ArrayLike, min_len: int = 1) -> list[tuple[int, int]]:
    """Runs of True in ``mask`` as ``(start, stop)`` index pairs, at least ``min_len`` long."""
    m = np.asarray(mask, bool).astype(np.int8)
    d = np.diff(np.concatenate([[0], m, [0]]))
    starts = np.flatnonzero(d == 1)
    stops = np.flatnonzero(d == -1)
    return [(int(s), int(e)) for s, e in zip(starts, stops) if e - s >= min_len]


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


# ------------------------------------------------------------------------------------------------
# Automatic bias estimation.

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
    period, giving one observation of the bias (see the module docstring for the model). The
    estimate combines the observations by weighted least squares with a zero-mean prior of
    standard deviation ``max_bias / 2``, rejects periods that disagree (Mahalanobis distance above
    ``reject_chi2``), and down-weights old periods (``drift_per_s``, temperature drift).

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
        T = np.concatenate(self._pend_t)
        X = np.vstack(self._pend)
        bid = np.floor((T - self._t_block0) / self.block_s).astype(np.int64)
        done = bid < bid_last
        if done.any():
            k = int(np.count_nonzero(done))
            self._blocks(T[:k], X[:k], bid[:k])
            self._pend_t = [T[k:]]
            self._pend = [X[k:]]
        else:
            self._pend_t = [T]
            self._pend = [X]
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
        N = nk.sum()
        nb = len(p.blocks)
        gm = (gk * nk[:, None]).sum(axis=0) / N
        # standard error of the mean rate: white noise, or the spread of block means if larger
        white = math.sqrt(float(((vk * (nk - 1)[:, None]).sum(axis=0) / max(N - nb, 1)).max()) / N)
        se_g = white
        if nb >= 4:
            se_g = max(se_g, float(gk.std(axis=0, ddof=1).max()) / math.sqrt(nb))
        se_g = max(se_g, 1e-6)
        u = ak.sum(axis=0)
        u /= np.linalg.norm(u)
        uu = np.outer(u, u)
        P = np.eye(3) - uu
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
                w_perp = k * (P @ w_t)
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
        sigma = se_g ** 2 * np.eye(3) + var_perp * P + var_par * uu
        return y, sigma

    @property
    def estimate(self) -> BiasEstimate:
        """The current estimate (the open still period, if long enough, included provisionally)."""
        if self._cached is not None:
            return self._cached
        periods = [p for p in self._periods]
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
        vs = [si @ y for si, y in zip(sis, ys)]
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
            T = np.concatenate(self._pend_t)
            if T.size:
                X = np.vstack(self._pend)
                assert self._t_block0 is not None
                bid = np.floor((T - self._t_block0) / self.block_s).astype(np.int64)
                self._blocks(T, X, bid)
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


# ------------------------------------------------------------------------------------------------
# Accelerometer fit.

@dataclass(frozen=True)
class AccelFit:
    """Accelerometer calibration from still poses: ``acc_c = matrix @ (acc - offset)``.

    Attributes:
        offset: m/s^2 (3,).
        matrix: 3x3 (upper triangular for the ``full`` model, diagonal for ``diagonal``).
        residual_rms: rms of ``|acc_c| - g`` over the poses, m/s^2.
        raw_rms: the same before calibration.
        poses: poses used; distinct: distinct orientations among them.
        model: ``full`` or ``diagonal``.
    """

    offset: np.ndarray
    matrix: np.ndarray
    residual_rms: float
    raw_rms: float
    poses: int
    distinct: int
    model: str


def _distinct_directions(u: np.ndarray, min_angle_deg: float) -> int:
    reps: list[np.ndarray] = []
    c = math.cos(math.radians(min_angle_deg))
    for v in u:
        if all(float(v @ r) < c for r in reps):
            reps.append(v)
    return len(reps)


def fit_accelerometer(poses: ArrayLike, *, g: float = G0, model: str = "auto", min_angle_deg: float = 20.0,
                      source: str | None = None) -> AccelFit:
    """Offset and scale/misalignment of an accelerometer from its mean readings in several still
    orientations (least squares on ``|matrix @ (a - offset)| = g`` with scipy).

    Args:
        poses: (k, 3) mean readings, m/s^2, one per still orientation (see :func:`still_poses`).
        g: the local gravity, m/s^2.
        model: ``diagonal`` (offset + 3 scales, 6 unknowns), ``full`` (offset + upper-triangular
            scale/misalignment, 9 unknowns) or ``auto`` (``full`` from 12 distinct orientations).
        min_angle_deg: poses closer than this count as the same orientation.
        source: the stream, for error messages.

    Raises:
        ConfigError: too few distinct orientations for the model, an axis never seen pointing both
            up and down, non-finite data, or an unknown model.
    """
    a = np.asarray(poses, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ConfigError(f"accelerometer fit: poses must be (k, 3), got {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError("accelerometer fit: poses contain non-finite values", source=source)
    if model not in ("auto", "full", "diagonal"):
        raise ConfigError(f"accelerometer fit: unknown model {model!r} (auto, full, diagonal)", source=source)
    norms = np.linalg.norm(a, axis=1)
    if np.any(norms <= 0):
        raise ConfigError("accelerometer fit: a pose reads zero", source=source)
    u = a / norms[:, None]
    distinct = _distinct_directions(u, min_angle_deg)
    if model == "auto":
        model = "full" if distinct >= 12 else "diagonal"
    need = 9 if model == "full" else 6
    if distinct < need:
        raise ConfigError(f"accelerometer fit ({model}) needs at least {need} distinct still orientations "
                          f"(>{min_angle_deg:.0f} deg apart), got {distinct} of {a.shape[0]} poses: turn the sensor "
                          f"to more faces and hold each still", source=source)
    missing = [f"{'+' if s > 0 else '-'}{'xyz'[i]}" for i in range(3) for s in (1, -1)
               if not np.any(s * u[:, i] >= 0.5)]
    if missing:
        raise ConfigError(f"accelerometer fit: orientations too similar: no pose with the {', '.join(missing)} "
                          f"axis pointing (within 60 deg) up; every axis must be seen both up and down", source=source)
    iu = np.triu_indices(3)
    diag_pos = [0, 3, 5]  # positions of the diagonal among the upper-triangular entries

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        off = p[:3]
        mat = np.zeros((3, 3))
        if model == "full":
            mat[iu] = p[3:9]
        else:
            mat[np.diag_indices(3)] = p[3:6]
        return off, mat

    def res(p: np.ndarray) -> np.ndarray:
        off, mat = unpack(p)
        return np.linalg.norm((a - off) @ mat.T, axis=1) - g

    p0 = np.zeros(9 if model == "full" else 6)
    if model == "full":
        p0[3:][diag_pos] = 1.0
    else:
        p0[3:6] = 1.0
    r = least_squares(res, p0, x_scale="jac")
    off, mat = unpack(r.x)
    rms = float(np.sqrt(np.mean(res(r.x) ** 2)))
    raw = float(np.sqrt(np.mean((norms - g) ** 2)))
    if rms > 0.05 * g:
        log.warning("accelerometer fit residual %.3f m/s^2 is large: were the poses still?", rms)
    return AccelFit(off, mat, rms, raw, int(a.shape[0]), distinct, model)


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


# ------------------------------------------------------------------------------------------------
# Magnetometer fit.

@dataclass(frozen=True)
class MagFit:
    """Magnetometer hard- and soft-iron calibration: ``mag_c = soft_iron @ (mag - hard_iron)``.

    Attributes:
        hard_iron: (3,) in the input unit.
        soft_iron: symmetric 3x3 (a multiple of identity for the ``sphere`` model); calibrated
            readings have magnitude ``field``.
        field: fitted field magnitude, input unit.
        model: ``ellipsoid`` (hard + soft iron) or ``sphere`` (hard iron only).
        coverage: fraction of 100 evenly spread directions with a sample within 25 deg (around the
            fitted centre), 0-1.
        planarity: smallest / largest eigenvalue of the centred readings' covariance (0 for a dance
            in one plane, about 1 for a full sphere).
        residual_rms: rms of ``|mag_c| / field - 1`` over the inliers.
        spread_before: std / mean of ``|mag|`` before (inliers).
        spread_after: std / mean of ``|mag_c|`` after (inliers).
        inliers: samples kept (outliers, i.e. magnetic disturbances, are trimmed at 4 robust sigmas).
    """

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field: float
    model: str
    coverage: float
    planarity: float
    residual_rms: float
    spread_before: float
    spread_after: float
    inliers: int


def _fib_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    phi = math.pi * (3 - math.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _coverage(d: np.ndarray, angle_deg: float = 25.0) -> float:
    grid = _fib_sphere(100)
    c = math.cos(math.radians(angle_deg))
    hit = np.zeros(len(grid), bool)
    for k in range(0, len(d), 4096):
        hit |= (grid @ d[k:k + 4096].T >= c).any(axis=1)
    return float(hit.mean())


def _sphere_fit(x: np.ndarray) -> np.ndarray:
    """Algebraic sphere fit: centre (3,)."""
    A = np.column_stack([2 * x, np.ones(len(x))])
    p, *_ = np.linalg.lstsq(A, (x * x).sum(axis=1), rcond=None)
    return p[:3]


def fit_magnetometer(mag: ArrayLike, *, model: str = "auto", min_coverage: float = 0.25,
                     min_planarity: float = 0.05, ellipsoid_coverage: float = 0.5, min_samples: int = 50,
                     source: str | None = None) -> MagFit:
    """Hard- and soft-iron fit from a rotation dance: an algebraic ellipsoid (or sphere) fit, refined
    by scipy least squares on the radial error, with outliers (magnetic disturbances) trimmed.

    A full ellipsoid (9 unknowns) is only determined when the readings cover the sphere; from a
    partial dance (a hand-held sensor turned mostly about one axis) it is ill-conditioned, so
    ``auto`` fits the ellipsoid when coverage >= ``ellipsoid_coverage`` and planarity >= 0.2 and
    only the hard iron (a sphere, 4 unknowns) otherwise.

    Args:
        mag: (n, 3) raw magnetometer readings (NaN rows are dropped).
        model: ``auto``, ``ellipsoid`` or ``sphere``.
        min_coverage: least direction coverage accepted (see :class:`MagFit`).
        min_planarity: least planarity accepted (a dance in one plane cannot fix the offset
            perpendicular to it).
        ellipsoid_coverage: coverage from which ``auto`` fits soft iron too.
        min_samples: fewest samples accepted.
        source: the stream, for error messages.

    Raises:
        ConfigError: too few samples, poor coverage or a planar dance (the message gives the
            figures and what to do), an ellipsoid asked for but not determined, or an unknown model.
    """
    if model not in ("auto", "ellipsoid", "sphere"):
        raise ConfigError(f"magnetometer fit: unknown model {model!r} (auto, ellipsoid, sphere)", source=source)
    m = np.asarray(mag, np.float64)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ConfigError(f"magnetometer fit: mag must be (n, 3), got {m.shape}", source=source)
    m = m[np.isfinite(m).all(axis=1)]
    if m.shape[0] < min_samples:
        raise ConfigError(f"magnetometer fit needs at least {min_samples} readings, got {m.shape[0]}", source=source)
    mc0 = m.mean(axis=0)
    scale = float(np.median(np.linalg.norm(m - mc0, axis=1))) or 1.0
    x = (m - mc0) / scale
    c = _sphere_fit(x)
    d = x - c
    cov = _coverage(d / np.linalg.norm(d, axis=1, keepdims=True))
    ev = np.linalg.eigvalsh(np.cov(d.T))
    planarity = float(ev[0] / ev[2]) if ev[2] > 0 else 0.0
    if cov < min_coverage:
        raise ConfigError(f"magnetometer fit: poor coverage: the readings span {cov:.2f} of all directions, need "
                          f"{min_coverage:.2f}; rotate the sensor slowly through every orientation (a figure-of-eight "
                          f"about all axes)", source=source)
    if planarity < min_planarity:
        raise ConfigError(f"magnetometer fit: the dance stayed in one plane (planarity {planarity:.3f}, need "
                          f"{min_planarity:.2f}), so the offset across that plane is unknown; tilt the sensor out of "
                          f"the plane too", source=source)
    if model == "auto":
        model = "ellipsoid" if cov >= ellipsoid_coverage and planarity >= 0.2 else "sphere"
    iu = np.triu_indices(3)
    if model == "ellipsoid":
        D = np.column_stack([x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, 2 * x[:, 0] * x[:, 1], 2 * x[:, 0] * x[:, 2],
                             2 * x[:, 1] * x[:, 2], 2 * x[:, 0], 2 * x[:, 1], 2 * x[:, 2]])
        v, *_ = np.linalg.lstsq(D, np.ones(len(x)), rcond=None)
        A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
        if not np.all(np.linalg.eigvalsh(A) > 0):
            raise ConfigError(f"magnetometer fit: the readings do not determine an ellipsoid (coverage {cov:.2f}); "
                              f"use model='sphere' (hard iron only) or rotate through more orientations", source=source)
        c = -np.linalg.solve(A, v[6:9])
        k = 1.0 + float(c @ A @ c)
        if k <= 0:
            raise ConfigError("magnetometer fit: degenerate ellipsoid", source=source)
        w, V = np.linalg.eigh(A / k)
        p = np.concatenate([c, (V @ np.diag(np.sqrt(w)) @ V.T)[iu]])
    else:
        p = np.concatenate([c, [1.0 / float(np.median(np.linalg.norm(d, axis=1)))]])

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if model == "sphere":
            return p[:3], p[3] * np.eye(3)
        S = np.zeros((3, 3))
        S[iu] = p[3:]
        return p[:3], S + S.T - np.diag(np.diag(S))

    def res(p: np.ndarray, xs: np.ndarray) -> np.ndarray:
        cc, S = unpack(p)
        return np.linalg.norm((xs - cc) @ S.T, axis=1) - 1.0

    inl = np.ones(len(x), bool)
    for _ in range(4):
        p = least_squares(res, p, args=(x[inl],), loss="soft_l1", f_scale=0.05).x
        e = res(p, x)
        med = float(np.median(e[inl]))
        mad = 1.4826 * float(np.median(np.abs(e[inl] - med))) + 1e-12
        new = np.abs(e - med) <= 4 * mad
        if np.array_equal(new, inl):
            break
        inl = new
    cc, S = unpack(p)
    det = float(np.linalg.det(S))
    if not det > 0 or not np.all(np.linalg.eigvalsh(S) > 0):
        raise ConfigError("magnetometer fit: the fitted soft-iron matrix is not positive definite", source=source)
    hard = mc0 + cc * scale
    # scaled so calibrated magnitudes equal the geometric-mean radius of the raw ellipsoid
    field_ = scale * det ** (-1.0 / 3.0)
    soft = S * (field_ / scale)
    mi = m[inl]
    before = np.linalg.norm(mi, axis=1)
    after = np.linalg.norm((mi - hard) @ soft.T, axis=1)
    return MagFit(hard, soft, field_, model, cov, planarity, float(np.sqrt(np.mean((after / field_ - 1.0) ** 2))),
                  float(before.std() / before.mean()), float(after.std() / after.mean()), int(inl.sum()))
