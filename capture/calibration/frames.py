"""The world-frame conventions that calibration and orientation share: standard gravity :data:`G0`,
and headings about the z-up (ENU) world's vertical, :func:`quat_heading` and :func:`quat_yaw`
(Hamilton quaternions, scalar first ``w, x, y, z``); the rest of the quaternion maths is
:mod:`capture.quat`."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

#: Standard gravity, m/s^2.
G0 = 9.80665


def quat_heading(q: ArrayLike) -> np.ndarray | float:
    """Heading of orientations ``q`` (sensor or body -> world, z up): the twist angle about world z,
    ``2 atan2(z, w)``, wrapped to [-pi, pi). Left-multiplying by a yaw of ``a`` adds exactly ``a``."""
    q = np.asarray(q, np.float64)
    h = np.mod(2.0 * np.arctan2(q[..., 3], q[..., 0]) + math.pi, 2 * math.pi) - math.pi
    return float(h) if h.ndim == 0 else h


def quat_yaw(angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about world z, as a quaternion."""
    return np.array([math.cos(angle_rad / 2), 0.0, 0.0, math.sin(angle_rad / 2)])

