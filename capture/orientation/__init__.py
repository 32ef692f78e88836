"""Orientation fusion: one filter interface over x-io Fusion (``imufusion``) and the ``ahrs``
package, the unit/frame check at the stream boundary, and the bus processor that turns IMU streams
into orientation, gravity and linear-acceleration streams.

* :mod:`~capture.orientation.filter` - :class:`OrientationFilter` (streaming, with a batch call on
  arrays) and the registry of filter kinds, :data:`FILTERS`.
* :mod:`~capture.orientation.fusion` - the ``fusion`` backend (imufusion ``Ahrs``, ``Bias``).
* :mod:`~capture.orientation.ahrs_filters` - the ``madgwick``, ``mahony`` and ``ekf`` backends.
* :mod:`~capture.orientation.base` - flags, settings, results and the backend base class.
* :mod:`~capture.orientation.streams` - :func:`check_imu_stream`, :func:`check_mag_stream`.
* :mod:`~capture.orientation.processor` - :class:`OrientationProcessor`, the bus subscriber.

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

The pitfalls each backend handles are in its class's docstring.
"""

from __future__ import annotations

from capture.orientation.base import (
    FLAG_ACC_IGNORED,
    FLAG_ACC_RECOVERY,
    FLAG_BIAS_FROZEN,
    FLAG_GAP,
    FLAG_INIT,
    FLAG_MAG_IGNORED,
    FLAG_MAG_RECOVERY,
    FLAG_NO_MAG,
    FLAG_OVERRANGE,
    FLAG_SKIPPED,
    OrientationResult,
    gravity_from_quaternion,
    initial_orientation,
)
from capture.orientation.filter import DEFAULT_FILTER, FILTERS, OrientationFilter
from capture.orientation.processor import OrientationProcessor
from capture.orientation.streams import ImuChannels, MagChannels, check_imu_stream, check_mag_stream

__all__ = [
    "DEFAULT_FILTER",
    "FILTERS",
    "FLAG_ACC_IGNORED",
    "FLAG_ACC_RECOVERY",
    "FLAG_BIAS_FROZEN",
    "FLAG_GAP",
    "FLAG_INIT",
    "FLAG_MAG_IGNORED",
    "FLAG_MAG_RECOVERY",
    "FLAG_NO_MAG",
    "FLAG_OVERRANGE",
    "FLAG_SKIPPED",
    "ImuChannels",
    "MagChannels",
    "OrientationFilter",
    "OrientationProcessor",
    "OrientationResult",
    "check_imu_stream",
    "check_mag_stream",
    "gravity_from_quaternion",
    "initial_orientation",
]
