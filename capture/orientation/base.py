"""What every orientation filter backend shares: the per-sample ``FLAG_*`` bits and ``MODE_*``
steps, the settings table with its defaults (:data:`DEFAULTS`), the result of a batch
(:class:`OrientationResult`), orientation from gravity and the field (:func:`initial_orientation`,
:func:`gravity_from_quaternion`), and the :class:`Backend` base class with the prepared inputs and
output buffers (:class:`Steps`, :class:`StepOutputs`) that its per-sample loop works on."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from capture.calibration import G0, quat_heading, quat_yaw
from capture.quat import quat_conj, quat_mul

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

#: One vector (x, y, z) and one quaternion (w, x, y, z) as plain floats (the one-sample path).
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

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

#: What a backend does with a sample (``Steps.mode``): integrate it, repeat the previous
#: orientation (not integrated), or (re-)initialise from the accelerometer and magnetometer.
MODE_RUN, MODE_SKIP, MODE_INIT = 0, 1, 2

#: Every filter setting and its default (see :class:`~capture.orientation.OrientationFilter`).
DEFAULTS: dict[str, Any] = {
    "nominal_rate_hz": None,      # sets Fusion's sample_rate (startup ramp, rejection timeout); else estimated
    "gain": None,                 # fusion gain (0.5), madgwick beta (0.033 IMU / 0.041 MARG), mahony k_P (1.0)
    "acc_rejection_deg": 10.0,    # fusion
    "mag_rejection_deg": 10.0,    # fusion
    "rejection_timeout_s": 5.0,   # fusion
    "gyro_range_dps": 0.0,        # fusion over-range recovery (0 = off; with no magnetometer Fusion zeroes
                                  # heading in recovery)
    "gyro_offset": False,         # fusion: run imufusion.Bias (learns the gyro offset at rest, |w| < threshold)
    "offset_threshold_dps": 3.0,  # fusion Bias stationary threshold
    "offset_period_s": 3.0,       # fusion Bias stationary period
    "max_gap_s": 0.5,             # a time step longer than this is a gap (not integrated across) ...
    "gap_periods": 10.0,          # ... and so is one longer than this many nominal sample periods
    "init_grace_s": 1.0,          # fusion: no rejection for this long after an (re)initialisation ...
    "init_gain": 2.0,             # ... and at least this gain (a short version of Fusion's startup, which
                                  # ramps 10 -> 0.5 over 3 s)
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
    out = np.empty((*q.shape[:-1], 3))
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
    q: np.ndarray  # scipy ships no type hints: its rotations are Any
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


def reinitialised(q_prev: np.ndarray, acc: np.ndarray, mag: np.ndarray | None) -> np.ndarray:
    """The orientation a (re-)initialisation starts from: :func:`initial_orientation` from ``acc``
    (and ``mag``) keeping the heading of ``q_prev``, or ``q_prev`` again (a copy) when the
    accelerometer reading is not finite or zero."""
    heading = float(quat_heading(q_prev))
    if not np.isfinite(acc).all() or not acc.any():
        return q_prev.copy()
    return initial_orientation(acc, mag, heading)


class Steps(NamedTuple):
    """The samples of one batch, prepared for a backend's per-sample loop (a tuple: made once per
    batch, cheaply).

    Attributes:
        dt: (n,) time step of each sample, s (meaningful where ``mode`` is ``MODE_RUN``).
        gyro: (n, 3) rad/s.
        acc: (n, 3) m/s^2 (rows may be non-finite or zero: no valid accelerometer).
        mag: (n, 3) the magnetometer reading held at each sample (zeros where there is none).
        use_mag: (n,) whether ``mag`` is to be used at each sample.
        mode: (n,) ``MODE_*`` of each sample.
        q_before: the orientation (sensor -> ENU) before the first sample.
    """

    dt: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    use_mag: np.ndarray
    mode: np.ndarray
    q_before: np.ndarray


class StepOutputs(NamedTuple):
    """The buffers a backend's loop fills, one row per sample of :class:`Steps`.

    Attributes:
        q: (n, 4) sensor -> ENU quaternions, written.
        flags: (n,) ``FLAG_*`` bits, or-ed into (the caller's bits are kept).
        acc_error_deg: (n,) written (NaN where the library has no such figure).
        mag_error_deg: (n,) written (NaN where the library has no such figure).
    """

    q: np.ndarray
    flags: np.ndarray
    acc_error_deg: np.ndarray
    mag_error_deg: np.ndarray


class Backend(ABC):
    """State of one library filter; works in the library's native frame, reports ENU.

    Args:
        s: the filter settings (every key of :data:`DEFAULTS`, validated by the filter).
    """

    #: ``q_enu = to_enu * q_native``
    to_enu: ClassVar[np.ndarray] = np.array([1.0, 0.0, 0.0, 0.0])

    def __init__(self, s: dict[str, Any]) -> None:
        self.s = s
        self.from_enu = quat_conj(self.to_enu)

    @abstractmethod
    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        """Start again from the orientation ``q_enu`` (sensor -> ENU); ``mag_ref`` is the
        magnetometer reading taken with it, if any."""

    @abstractmethod
    def run(self, steps: Steps, out: StepOutputs) -> None:
        """Run the filter over every sample of ``steps``, filling ``out``."""

    def restart(self, steps: Steps, i: int, q_prev: np.ndarray) -> np.ndarray:
        """Sample ``i`` of a mode other than ``MODE_RUN``: the orientation it outputs, ``q_prev``
        (the previous sample's) again when it is skipped, else the filter (re-)initialised from its
        accelerometer and magnetometer readings, keeping ``q_prev``'s heading."""
        if steps.mode[i] == MODE_SKIP:
            return q_prev
        m = steps.mag[i] if steps.use_mag[i] else None
        q0 = reinitialised(q_prev, steps.acc[i], m)
        self.set_enu(q0, m)
        return q0
