"""IMU calibration: the per-device correction record, the fits that produce it, and gyro-bias
estimation from stillness. Units are rad/s and m/s^2, the magnetometer in whatever unit its stream
declares (only its direction matters to the filters); every vector is in the sensor frame unless
said otherwise, and the world frame is ENU (see :mod:`capture.orientation`).

* :mod:`~capture.calibration.record` - :class:`ImuCalibration` and its JSON form.
* :mod:`~capture.calibration.stillness` - still periods and the explicit still-period bias.
* :mod:`~capture.calibration.bias` - automatic gyro-bias estimation (:class:`GyroBiasEstimator`).
* :mod:`~capture.calibration.fits` - mounting, accelerometer and magnetometer fits.
* :mod:`~capture.calibration.frames` - :data:`G0` and headings about world z.
"""

from __future__ import annotations

from capture.calibration.bias import BiasEstimate, GyroBiasEstimator, estimate_gyro_bias
from capture.calibration.fits import AccelFit, MagFit, fit_accelerometer, fit_magnetometer, mounting_from_gravity
from capture.calibration.frames import G0, quat_heading, quat_yaw
from capture.calibration.record import FORMAT_NAME, FORMAT_VERSION, ImuCalibration, Mat3, Vec3
from capture.calibration.stillness import StillBias, still_bias, still_mask, still_poses, still_segments

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "G0",
    "AccelFit",
    "BiasEstimate",
    "GyroBiasEstimator",
    "ImuCalibration",
    "MagFit",
    "Mat3",
    "StillBias",
    "Vec3",
    "estimate_gyro_bias",
    "fit_accelerometer",
    "fit_magnetometer",
    "mounting_from_gravity",
    "quat_heading",
    "quat_yaw",
    "still_bias",
    "still_mask",
    "still_poses",
    "still_segments",
]
