"""The backends over the ``ahrs`` library's filters: the per-sample loop they share
(:class:`AhrsBackend`) and one class per filter, :class:`MadgwickBackend` (run in its native NWU
world and turned to ENU), :class:`MahonyBackend` (with an anti-windup for its integral term) and
:class:`EkfBackend` (with a magnetic reference taken from the data)."""

from __future__ import annotations

import logging
import math
from abc import abstractmethod
from typing import TYPE_CHECKING, Any

import numpy as np

from capture.calibration import G0
from capture.orientation.base import FLAG_ACC_IGNORED, FLAG_BIAS_FROZEN, Backend
from capture.quat import quat_mul, quat_rotate

if TYPE_CHECKING:
    from capture.orientation.base import StepOutputs, Steps

log = logging.getLogger(__name__)

_D2R = math.pi / 180.0
_TINY_RATE = 1e-12

#: Rotation from Madgwick's native NWU world to ENU (+90 deg about z).
_NWU_TO_ENU = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])


class AhrsBackend(Backend):
    """Common loop of the ``ahrs`` filters (per-sample Python; ~3,000-9,000 samples/s).

    ``ahrs`` Madgwick and Mahony return the previous quaternion unchanged when the gyro reads
    exactly zero (common with quantised gyros at rest), skipping the accelerometer correction too;
    the loop feeds a 1e-12 rad/s rate instead. These filters have no acceleration rejection: the
    accelerometer is left out of a sample whose | |a|/g - 1 | exceeds ``acc_norm_tol``.
    """

    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        self.q = np.array([1.0, 0.0, 0.0, 0.0])

    def set_enu(self, q_enu: np.ndarray, mag_ref: np.ndarray | None) -> None:
        self.q = quat_mul(self.from_enu, q_enu)

    @abstractmethod
    def step(self, q: np.ndarray, g: np.ndarray, a: np.ndarray | None, m: np.ndarray | None,
             dt: float) -> tuple[np.ndarray, int]:
        """One update of the library filter in its native frame.

        Args:
            q: the previous (native) quaternion.
            g: the rate, rad/s.
            a: the accelerometer, m/s^2, or ``None`` for a gyro-only update.
            m: the magnetometer reading, or ``None`` without one.
            dt: the time step, s.

        Returns:
            The new (not yet normalised) quaternion and the ``FLAG_*`` bits of the update.
        """

    def run(self, steps: Steps, out: StepOutputs) -> None:
        to_enu = self.to_enu
        dt, gyro, acc, mag, use_mag, mode, q_before = steps
        q_out, flags, acc_err, mag_err = out
        gz = ~gyro.any(axis=1)
        if gz.any():
            gyro = gyro.copy()
            gyro[gz, 0] = _TINY_RATE  # ahrs skips the whole update (acc too) on an exactly-zero rate
        acc_ok = np.isfinite(acc).all(axis=1) & (acc.any(axis=1))
        tol = float(self.s["acc_norm_tol"])
        if tol > 0:
            # no acceleration rejection in these filters: skip the accelerometer when |a| is not g
            acc_ok &= np.abs(np.linalg.norm(acc, axis=1) * (1.0 / G0) - 1.0) <= tol
        acc_err[:] = np.nan
        mag_err[:] = np.nan
        for i in range(dt.shape[0]):
            if mode[i]:
                q_out[i] = self.restart(steps, i, q_out[i - 1].copy() if i else q_before)
                continue
            q, f = self.step(self.q, gyro[i], acc[i] if acc_ok[i] else None, mag[i] if use_mag[i] else None,
                             float(dt[i]))
            nq = math.sqrt(float(q @ q))
            q = q / nq
            self.q = q
            q_out[i] = quat_mul(to_enu, q)
            if not acc_ok[i]:
                f |= FLAG_ACC_IGNORED
            if f:
                flags[i] |= f


class MadgwickBackend(AhrsBackend):
    """``ahrs`` Madgwick: its magnetic model puts north along x with z up (NWU), so its quaternion
    is rotated by +90 deg about z; ``gain`` is beta (0.033 IMU, 0.041 MARG by default)."""

    to_enu = _NWU_TO_ENU

    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        from ahrs.filters import Madgwick

        g = s["gain"]
        self.gain_imu = 0.033 if g is None else float(g)
        self.gain_marg = 0.041 if g is None else float(g)
        self.f = Madgwick(gain_imu=self.gain_imu, gain_marg=self.gain_marg)

    def step(self, q: np.ndarray, g: np.ndarray, a: np.ndarray | None, m: np.ndarray | None,
             dt: float) -> tuple[np.ndarray, int]:
        f = self.f
        if a is None:
            a = np.zeros(3)  # Madgwick integrates the gyro alone when |a| = 0
        if m is not None:
            f.gain = self.gain_marg
            return np.asarray(f.updateMARG(q, g, a, m, dt=dt), np.float64), 0
        f.gain = self.gain_imu
        return np.asarray(f.updateIMU(q, g, a, dt=dt), np.float64), 0


class MahonyBackend(AhrsBackend):
    """``ahrs`` Mahony (its magnetic model puts north along y: ENU already); ``gain`` is k_P.

    Mahony winds its integral (bias) term up during a fast spin and keeps the wound-up bias
    afterwards (a steady heading drift of several deg/s, or worse). The integrator is frozen while
    the rate (``mahony_freeze_dps``) or |a| (``mahony_freeze_acc``) says the accelerometer is not
    measuring gravity, and the bias magnitude is clamped (``mahony_bias_limit_dps``).
    """

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
        """The integral (bias) term, rad/s."""
        return np.array(self.f.b, np.float64)

    def step(self, q: np.ndarray, g: np.ndarray, a: np.ndarray | None, m: np.ndarray | None,
             dt: float) -> tuple[np.ndarray, int]:
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


class EkfBackend(AhrsBackend):
    """``ahrs`` EKF, run with ``frame='NED'`` - whose gravity reference ``[0, 0, 1]`` is compared
    with the *accelerometer*, so its world z is in fact up - and the magnetic reference in ENU.

    The EKF uses a magnetic reference for Munich unless given one; here it is set from the first
    magnetometer and accelerometer readings (or ``magnetic_dip_deg``). Its measurement model is
    chosen by its ``mag`` attribute, which is set per sample.
    """

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

    def step(self, q: np.ndarray, g: np.ndarray, a: np.ndarray | None, m: np.ndarray | None,
             dt: float) -> tuple[np.ndarray, int]:
        f = self.f
        if m is not None and not self.ref_set:
            self._set_ref(quat_mul(self.to_enu, q), m)
        if a is None:
            return np.asarray(f.f(q, g, dt), np.float64), 0  # its process model (update() would not integrate)
        f.mag = self._mag_marker if m is not None else None  # selects the 6- or 3-row measurement model
        return np.asarray(f.update(q, g, a, m, dt=dt), np.float64), 0
