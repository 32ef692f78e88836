"""The calibration record: :class:`ImuCalibration`, a frozen record of one IMU's gyro bias,
accelerometer offset and 3x3 scale/misalignment, magnetometer hard and soft iron, mounting rotation
(sensor -> segment) and yaw offset, with its vectorised :meth:`~ImuCalibration.apply`, its resets
and its versioned JSON form (:data:`FORMAT_NAME`, :data:`FORMAT_VERSION`), validated on load."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from capture.calibration.fits import mounting_from_gravity
from capture.calibration.frames import quat_heading, quat_yaw
from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

#: Version of the JSON calibration format written by :meth:`ImuCalibration.to_json`.
FORMAT_VERSION = 1
FORMAT_NAME = "perfcap.imu_calibration"
#: no bias, offset, hard iron or matrix entry of a real IMU comes near this (in any unit used)
MAX_ABS_VALUE = 1e6

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]
_I3: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
_Z3: Vec3 = (0.0, 0.0, 0.0)


def _vec(name: str, v: Any, source: str | None) -> Vec3:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:  # (an integer past float range)
        raise ConfigError(f"calibration field {name!r} must be 3 numbers, got {v!r}", source=source) from exc
    if a.shape != (3,):
        raise ConfigError(f"calibration field {name!r} must be 3 numbers, got shape {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"calibration field {name!r} has a non-finite value: {a.tolist()}", source=source)
    if np.abs(a).max() > MAX_ABS_VALUE:
        raise ConfigError(f"calibration field {name!r} has a value beyond {MAX_ABS_VALUE:g}: {a.tolist()}",
                          source=source)
    return (float(a[0]), float(a[1]), float(a[2]))


def _mat(name: str, v: Any, source: str | None) -> Mat3:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:  # (an integer past float range)
        raise ConfigError(f"calibration field {name!r} must be a 3x3 matrix, got {v!r}", source=source) from exc
    if a.shape != (3, 3):
        raise ConfigError(f"calibration field {name!r} must be a 3x3 matrix, got shape {a.shape}", source=source)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"calibration field {name!r} has a non-finite value", source=source)
    if np.abs(a).max() > MAX_ABS_VALUE:  # (and its cube below stays a float)
        raise ConfigError(f"calibration field {name!r} has a value beyond {MAX_ABS_VALUE:g}", source=source)
    det = float(np.linalg.det(a))
    if abs(det) < 1e-6 * max(1e-300, float(np.abs(a).max()) ** 3):
        raise ConfigError(f"calibration field {name!r} is singular (det={det:.3g})", source=source)
    return (_row(a[0]), _row(a[1]), _row(a[2]))


def _row(r: np.ndarray) -> Vec3:
    return (float(r[0]), float(r[1]), float(r[2]))


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
        except (TypeError, ValueError, OverflowError) as exc:
            raise ConfigError(f"calibration field 'mounting' must be 4 numbers, got {self.mounting!r}",
                              source=src) from exc
        if m.shape != (4,) or not np.all(np.isfinite(m)) or np.abs(m).max() > MAX_ABS_VALUE:
            raise ConfigError(f"calibration field 'mounting' must be 4 finite numbers (w, x, y, z), "
                              f"got {self.mounting!r}", source=src)
        nm = float(np.linalg.norm(m))
        if abs(nm - 1.0) > 1e-3:
            raise ConfigError(f"calibration field 'mounting' must be a unit quaternion, its norm is {nm:.6f}",
                              source=src)
        m = m / nm
        if m[0] < 0:
            m = -m
        set_(self, "mounting", tuple(float(x) for x in m))
        try:
            y = float(self.yaw_offset_rad)
        except (TypeError, ValueError, OverflowError) as exc:
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

    _KEYS: ClassVar[dict[str, str]] = {
        "gyro_bias_rad_s": "gyro_bias", "acc_offset_m_s2": "acc_offset", "acc_matrix": "acc_matrix",
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

